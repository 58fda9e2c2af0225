"""KITTI Depth, the 13 test drives: the first 300 ground-truth frames of each.

    python -m eval --config configs/eval/kitti_depth.py --checkpoint CKPT \\
        --data-root data/datasets
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("kitti_depth", split="test", sample_len=300)

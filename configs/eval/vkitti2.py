"""Virtual KITTI 2, the 5 test sequences: the first 300 frames of each.

    python -m eval --config configs/eval/vkitti2.py --checkpoint CKPT --data-root data/datasets
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("vkitti2", split="test", sample_len=300)

"""Dynamic Replica, test split: the first 150 frames of each sequence (shorter
sequences are skipped, as the official loader does).

    python -m eval --config configs/eval/dynamic_replica.py --checkpoint CKPT \\
        --data-root data/datasets
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("dynamic_replica", split="test", sample_len=150)

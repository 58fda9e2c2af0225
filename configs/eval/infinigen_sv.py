"""Infinigen SV, test split (scenes 001-030): the first 150 frames of each scene.

    python -m eval --config configs/eval/infinigen_sv.py --checkpoint CKPT \\
        --data-root data/datasets
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("infinigen_sv", split="test", sample_len=150)

"""Sintel stereo, final pass: every frame of every sequence (the official
loader ignores sample_len).

    python -m eval --config configs/eval/sintel_final.py --checkpoint CKPT \\
        --data-root data/datasets
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("sintel_final", split="test", sample_len=-1)

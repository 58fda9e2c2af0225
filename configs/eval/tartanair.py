"""TartanAir, the official loader's 17 test sequences: every frame. No official script
evaluates TartanAir (its loader is a training option), so there are no published numbers to
match; the protocol is otherwise the official one (20-frame windows, stride 10).

    python -m eval --config configs/eval/tartanair.py --checkpoint CKPT \\
        --data-root data/datasets
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("tartanair", split="test", sample_len=-1)

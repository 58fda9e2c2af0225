"""Spring (`test` = the sequences with ground truth): every frame. SAV's own Spring
protocol is not confirmed (its loader cannot read Spring's ground truth).

    python -m eval --config configs/eval/spring.py --checkpoint CKPT \\
        --data-root data/datasets
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("spring", split="test", sample_len=-1)

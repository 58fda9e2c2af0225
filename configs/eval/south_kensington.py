"""South Kensington SV (real stereo videos, no ground truth): the first 300 frames of each
sequence, qualitative only, as in the official evaluation script. The program writes the
predictions (`--config.save_predictions=true`) and the disparity strips; there are no
metrics to report.

    python -m eval --config configs/eval/south_kensington.py --checkpoint CKPT \\
        --data-root data/datasets --config.save_predictions=true
"""

from configs.eval.common import eval_config


def get_config():
  return eval_config("south_kensington", split="test", sample_len=300)

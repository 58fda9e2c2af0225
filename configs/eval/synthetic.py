"""The built-in synthetic stereo videos (exact dense ground truth); no download needed.

    python -m eval --config configs/eval/synthetic.py --checkpoint CKPT
    python -m eval --config configs/eval/synthetic.py --checkpoint CKPT \\
        --config.synthetic.num_sequences=2 --config.iters=4 --baseline sgbm
"""

import ml_collections

from configs.eval.common import eval_config


def get_config():
  c = eval_config("synthetic", split="test", sample_len=-1)
  c.synthetic = ml_collections.ConfigDict()
  # Number of clips (sequences) and their size.
  c.synthetic.num_sequences = 4
  c.synthetic.frames = 24
  c.synthetic.height = 128
  c.synthetic.width = 256
  # Moving objects per clip, and the smallest and largest disparity (px).
  c.synthetic.num_objects = 6
  c.synthetic.min_disparity = 2.0
  c.synthetic.max_disparity = 32.0
  # Std of Gaussian photometric noise per view and frame (grey levels; 0 = consistent views).
  c.synthetic.noise_std = 0.0
  # Generator seed (clips i = 0..num_sequences-1 of this seed); distinct from training's 0.
  c.synthetic.seed = 1000
  # Any other field of `sav_jax.data.SyntheticConfig` may be added to this block in a config
  # file of your own (e.g. max_speed, textures); a name it does not have is refused.
  c.baseline.max_disparity = 48
  return c

"""Small run on the built-in procedural stereo videos: no downloads, fits a laptop CPU.

Usage:
  python -m train --config configs/synthetic.py --workdir /tmp/sav_synth
  python -m train --config configs/synthetic.py --workdir /tmp/sav_synth \
      --config.train.num_steps=1000 --config.data.crop='(96, 160)'
"""

import ml_collections

from configs import sceneflow


def get_config() -> ml_collections.ConfigDict:
  c = sceneflow.base_config()
  # Short clips (T) keep a CPU step around a second or two.
  c.data.frames = 3
  # Small crop (H, W), multiples of 16.
  c.data.crop = (64, 128)
  # Proportions of the mixture are the weights themselves.
  c.data.mixing = "ratio"
  # One source: the procedural generator.
  c.data.sources.synthetic = ml_collections.ConfigDict(dict(dataset="synthetic", weight=1.0))
  # Generator: few objects, disparities that fit the small crop.
  c.data.synthetic = ml_collections.ConfigDict(dict(
      num_clips=100_000, seed=0, num_objects=3, min_disparity=1.0, max_disparity=24.0))
  # Reader threads (the generator renders in numpy).
  c.data.num_threads = 2
  # Elements prefetched by the reader threads.
  c.data.prefetch = 4
  # Remat costs compute and the small model fits in memory anyway.
  c.model.remat = False
  # Clips per step.
  c.train.batch_size = 2
  # Training steps.
  c.train.num_steps = 300
  # Refinement iterations at 1/4 (8 predictions in the loss).
  c.train.iters = 4
  # Log every this many steps.
  c.train.log_every = 10
  # A higher peak lr than the paper's: the run is short and starts from scratch.
  c.optimizer.lr = 4e-4
  # Warm up over the first 5% of the run.
  c.optimizer.pct_start = 0.05
  # Save every this many steps.
  c.checkpoint.every_steps = 100
  # Validate every this many steps.
  c.eval.every_steps = 100
  # Validate before training too (the starting EPE).
  c.eval.at_start = True
  # Held-out clips.
  c.eval.num_clips = 8
  # Validation batch.
  c.eval.batch_size = 4
  # Same iterations as training.
  c.eval.iters = 4
  return c

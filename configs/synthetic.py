"""Small run on the built-in procedural stereo videos: no downloads, fits a laptop CPU.

The full model runs, the VDA-S depth prior included (frozen, as in every config: here it
keeps its random initialisation, `random_depth_prior`), and everything else is trained; only
the clip size, the number of refinement iterations and the batch are small, so that the 200
steps take about five minutes on a 2-core CPU (1.3 s per step; `benchmarks/train_step.py
--frames 3 --height 32 --width 64 --iters 2 --batch 2 --no-remat`). On an accelerator, raise
them freely.

Usage:
  python -m train --config configs/synthetic.py --workdir /tmp/sav_synth
  python -m train --config configs/synthetic.py --workdir /tmp/sav_synth \
      --config.train.num_steps=1000 --config.data.crop='(64, 128)' --config.train.iters=4
"""

import ml_collections

from configs import sceneflow
from sav_jax.data.synthetic import SyntheticConfig


def get_config() -> ml_collections.ConfigDict:
  c = sceneflow.base_config()
  # The toy runs on the generator start from scratch, depth prior included.
  c.random_depth_prior = True
  # Short clips (T).
  c.data.frames = 3
  # Small crop (H, W), multiples of 16.
  c.data.crop = (32, 64)
  # Proportions of the mixture are the weights themselves.
  c.data.mixing = "ratio"
  # One source: the procedural generator.
  c.data.sources.synthetic = ml_collections.ConfigDict(dict(dataset="synthetic", weight=1.0))
  # Generator: few objects, disparities that fit the small crop.
  c.data.synthetic = sceneflow.dataclass_fields(
      SyntheticConfig, skip=("frames", "height", "width"), num_clips=100_000, seed=0,
      num_objects=3, min_disparity=1.0, max_disparity=12.0)
  # Reader threads (the generator renders in numpy).
  c.data.num_threads = 2
  # Elements prefetched by the reader threads.
  c.data.prefetch = 4
  # Remat costs compute and the small model fits in memory anyway.
  c.model.remat = False
  # Clips per step.
  c.train.batch_size = 2
  # Training steps.
  c.train.num_steps = 200
  # Refinement iterations at 1/4 (1/16 and 1/8 get 1 each: 4 predictions in the loss).
  c.train.iters = 2
  # Log every this many steps.
  c.train.log_every = 10
  # A higher peak lr than the paper's: the run is short and starts from scratch.
  c.optimizer.lr = 4e-4
  # Warm up over the first 5% of the run.
  c.optimizer.pct_start = 0.05
  # Save every this many steps.
  c.checkpoint.every_steps = 50
  # Validate every this many steps.
  c.eval.every_steps = 50
  # Validate before training too (the starting EPE).
  c.eval.at_start = True
  # Held-out clips.
  c.eval.num_clips = 8
  # Validation batch.
  c.eval.batch_size = 4
  # Same iterations as training.
  c.eval.iters = 2
  return c

"""The fields every evaluation config shares (the official SAV evaluation protocol).

Each `configs/eval/<dataset>.py` calls `eval_config(...)` with its dataset name, split
and number of evaluated frames per sequence (`datasets.md`, section 2); a dataset registered
with `register_dataset(..., eval_frames=L)` gets L when `sample_len` is not given.
"""

import ml_collections


def eval_config(dataset: str, split: str = "test", sample_len: int | None = None
                ) -> ml_collections.ConfigDict:
  """Evaluation config of one dataset.

  Args:
    dataset: registry name (`sav_jax.data.registry.DATASETS`) or "synthetic".
    split: dataset split.
    sample_len: frames evaluated per sequence, from the first one (<= 0: all frames); None:
      the dataset's own for its "test" split (`sav_jax.data.registry.EVAL_FRAMES`: the
      official ones, or `register_dataset(..., eval_frames=L)`'s), else all frames.

  Returns:
    The ConfigDict (override any field with `--config.<field>=<value>`).
  """
  if sample_len is None:
    from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
    sample_len = registry.EVAL_FRAMES.get(dataset, -1) if split == "test" else -1
  c = ml_collections.ConfigDict()
  # Dataset name, as the registry knows it.
  c.dataset = dataset
  # Split to evaluate.
  c.split = split
  # Only the first `sample_len` frames of each sequence are evaluated (<= 0: all).
  c.sample_len = sample_len
  # Refinement iterations at 1/4 resolution (the official evaluation uses 20).
  c.iters = 20
  # Sliding window length and stride of the official forward_batch_test (window <= 32, the
  # depth prior's temporal attention length).
  c.window = 20
  c.stride = 10
  # Compute dtype of the model: "float32" (official, mixed precision off) or "bfloat16".
  c.dtype = "float32"
  # Precision of float32 products and convolutions: "default" (XLA's choice: TF32 on recent
  # NVIDIA GPUs, about 1e-3 px from the official float32 output; full float32 on CPU) or
  # "highest" (full float32 everywhere, within ~1e-5 px of it; slower on GPUs).
  c.matmul_precision = "default"
  # Local devices that run consecutive windows at once, one window each (0: every device of
  # the default backend); the values are those of one device.
  c.devices = 1
  # Evaluate only the first N sequences (<= 0: all); for quick checks.
  c.max_sequences = -1
  # Write each sequence's predicted disparity as predictions/<sequence>.npy.
  c.save_predictions = False
  c.metrics = ml_collections.ConfigDict()
  # Also compute TCC (needs the depth-to-disparity scale).
  c.metrics.tcc = False
  # The official RAFT checkpoint (raft-things.pth): also compute the flow-based TCM, OPW
  # (and OPW_30/50/100) and RTC (and RTC_30), with TCC; needs the scale too. "" = off.
  c.metrics.raft = ""
  # RAFT iterations (the official evaluator: 20).
  c.metrics.raft_iters = 20
  c.baseline = ml_collections.ConfigDict()
  # StereoSGBM search range (px, rounded up to a multiple of 16) and block size.
  c.baseline.max_disparity = 256
  c.baseline.block_size = 5
  c.plots = ml_collections.ConfigDict()
  # Write per-sequence plots (per-frame EPE/TEPE curves, colourized disparity strips).
  c.plots.enabled = True
  # Frames shown in each disparity strip.
  c.plots.strip_frames = 6
  # Longest side of a strip tile (px); smaller frames are shown at their own size.
  c.plots.tile_size = 320
  return c

"""Sequences to evaluate: dataset readers from the registry, or the synthetic set.

Every sequence follows the `sav_jax.data.base.StereoSequence` interface: `name`,
`dataset`, `depth2disp_scale`, `sparse`, `len(seq)`, `seq[i]` and `seq.clip(start, n)`.
"""

from __future__ import annotations

import functools

import ml_collections
import numpy as np

from sav_jax._checks import is_int
from sav_jax.data import synthetic

SYNTHETIC = "synthetic"
# Dense datasets: valid = |d| < 512 and d != 0 (the official rule, recomputed from GT).
_MAX_DISPARITY = 512.0


class SyntheticSequence:
  """Clip `index` of the synthetic generator as a StereoSequence (rendered once, lazily).

  Args:
    cfg: generator config (its `frames` is the sequence length).
    index: clip index.
  """

  dataset = SYNTHETIC
  sparse = False

  def __init__(self, cfg: synthetic.SyntheticConfig, index: int):
    self.cfg = cfg
    self.index = index
    self.name = f"synthetic_{index:03d}"
    self.depth2disp_scale = float(cfg.fx * cfg.baseline)

  def __len__(self) -> int:
    return self.cfg.frames

  def __repr__(self) -> str:
    return f"SyntheticSequence({self.name}, frames={len(self)}, {self.cfg.width}x{self.cfg.height})"

  @functools.cached_property
  def _clip(self) -> dict:
    synthetic.check_host_memory(self.cfg)  # (beyond the host: one line, not the kernel's kill)
    c = synthetic.generate_clip(self.cfg, self.index)
    d = c["disparity"]
    valid = c["valid"] & (np.abs(d) < _MAX_DISPARITY) & (d != 0)
    return {"left": c["left"], "right": c["right"], "disparity": d, "valid": valid}

  def __getitem__(self, i: int) -> dict:
    return {k: v[i] for k, v in self._clip.items()}

  def clip(self, start: int, length: int, stride: int = 1) -> dict:
    idx = [start + k * stride for k in range(length)]
    if length < 1 or min(idx) < 0 or max(idx) >= len(self):
      raise IndexError(f"clip {start}+{length}x{stride} out of range for {len(self)} frames")
    return {k: v[idx] for k, v in self._clip.items()}


def synthetic_sequences(config: ml_collections.ConfigDict) -> list[SyntheticSequence]:
  """The synthetic evaluation set described by `config.synthetic`."""
  if "synthetic" not in config:
    raise ValueError("config.dataset='synthetic' needs a config.synthetic block (frames, "
                     "height, width, num_objects, min_disparity, max_disparity, seed, "
                     "num_sequences): see "
                     "configs/eval/synthetic.py")
  s = config.synthetic
  if not (is_int(s.num_sequences) and s.num_sequences >= 1):
    raise ValueError(f"config.synthetic.num_sequences must be an integer >= 1, got "
                     f"{s.num_sequences!r}")
  cfg = synthetic.config_from_block(s, "config.synthetic", own=("num_sequences",))
  return [SyntheticSequence(cfg, i) for i in range(s.num_sequences)]


def load_sequences(config: ml_collections.ConfigDict, data_root) -> list:
  """The sequences of `config.dataset` / `config.split`, cut to `config.sample_len` frames
  (`load_sequences_and_skipped`, less the names of the sequences skipped)."""
  return load_sequences_and_skipped(config, data_root)[0]


def load_sequences_and_skipped(config: ml_collections.ConfigDict, data_root
                               ) -> tuple[list, list[str]]:
  """The sequences of `config.dataset` / `config.split`, cut to `config.sample_len` frames,
  and the names of those skipped for being shorter (Dynamic Replica's, as the official
  evaluation skips them).

  Args:
    config: evaluation config (`dataset`, `split`, `sample_len`, `max_sequences`).
    data_root: dataset root (the common parent or the dataset's folder); unused for
      the synthetic set.

  Returns:
    `(sequences, skipped names)`: StereoSequence-like objects, and names.
  """
  skipped = []
  if config.dataset == SYNTHETIC:
    if config.split != "test":
      raise ValueError(f"the synthetic dataset has only the split 'test', got "
                       f"config.split={config.split!r}")
    seqs = synthetic_sequences(config)
    length = config.sample_len
    seqs = [s if length <= 0 or length >= len(s) else _Head(s, length) for s in seqs]
  else:
    from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
    if config.dataset not in registry.DATASETS:
      raise ValueError(f"unknown dataset {config.dataset!r}; known: "
                       f"{', '.join(registry.DATASETS + (SYNTHETIC,))}")
    whole = registry.get_sequences(config.dataset, data_root, config.split, max_frames=None)
    seqs = registry.eval_chunk(whole, int(config.sample_len),
                               drop_short=config.dataset in registry.DROP_SHORT)
    kept = {s.name for s in seqs}
    skipped = [str(s.name) for s in whole if s.name not in kept]
  if config.max_sequences > 0:
    seqs = seqs[:config.max_sequences]
  if not seqs and config.dataset != SYNTHETIC and config.sample_len > 0:
    if whole:
      raise ValueError(
          f"all {len(whole)} {config.dataset}/{config.split} sequences under {data_root} are "
          f"shorter than config.sample_len={config.sample_len} frames and were skipped, as the "
          "official evaluation does; set --config.sample_len to at most "
          f"{max(len(s) for s in whole)} (or 0 for whole sequences)")
  if not seqs:
    raise ValueError(f"no sequences found for {config.dataset}/{config.split} under {data_root}")
  return seqs, skipped


class _Head:
  """The first `n` frames of a sequence."""

  def __init__(self, seq, n: int):
    self._seq, self._n = seq, n
    self.name, self.dataset = seq.name, seq.dataset
    self.depth2disp_scale, self.sparse = seq.depth2disp_scale, seq.sparse
    self.has_gt = getattr(seq, "has_gt", True)

  def __len__(self) -> int:
    return self._n

  def __getitem__(self, i: int) -> dict:
    if not -self._n <= i < self._n:
      raise IndexError(i)
    return self._seq[i % self._n]

  def clip(self, start: int, length: int, stride: int = 1) -> dict:
    if start + (length - 1) * stride >= self._n:
      raise IndexError(f"clip beyond the first {self._n} frames")
    return self._seq.clip(start, length, stride)


def read_sequence(seq) -> dict:
  """All frames of `seq`: left/right `[T, H, W, 3]` uint8, disparity/valid `[T, H, W]` or None."""
  clip = seq.clip(0, len(seq))
  out = {"left": np.asarray(clip["left"]), "right": np.asarray(clip["right"]),
         "disparity": clip.get("disparity"), "valid": clip.get("valid")}
  if out["disparity"] is not None:
    out["disparity"] = np.asarray(out["disparity"], np.float32)
    out["valid"] = np.asarray(out["valid"], bool)
  return out

"""grain input pipelines: sources, mixtures, per-process shares, global device batches.

A training example is a dict of numpy arrays with static shapes:

  left, right: [T, H, W, 3] uint8 RGB
  disparity:   [T, H, W] float32, positive left-view disparity (px)
  valid:       [T, H, W] bool

The pipeline (per source, then mixed; the same on every process up to the slice):

  source (loading clips lazily)
    .shuffle(s).repeat()                    a new permutation every epoch (grain: seed s + epoch)
    .random_map(augment, seed=a)            augmentation seeded by (a, index)
  MapDataset.mix(sources, weights)          deterministic, even interleaving by weight
                                            (grain rounds the shares: the smallest to 100)
    [process_index::process_count]          each process reads and augments its share
    .to_iter_dataset(ReadOptions(threads))  prefetching threads
    .batch(per_process_batch, drop_remainder=True)  -> [B_local, T, H, W, ...]
    [.mp_prefetch(workers)]

with `s` and `a` hashes of (seed, source index, purpose) (`stream_seed`).

`GlobalBatchIterator` turns each local batch into global `jax.Array`s sharded on the
mesh's data axis (`jax.make_array_from_process_local_data`). Its `get_state()` /
`set_state()` (and `grain_iterator` for `grain.checkpoint.CheckpointSave`) make the
stream resumable exactly: a restored iterator yields the batches the uninterrupted
one would have.

Usage:

  src = synthetic_source(SyntheticConfig(frames=3, height=64, width=128), 10_000)
  ds = make_train_dataset([src], [1.0], batch_size=4, seed=0)
  it = GlobalBatchIterator(iter(ds), data_sharding)
  batch = next(it)          # {"left": jax.Array [B, T, H, W, 3], ...}
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import pathlib
import signal
import threading
import time
import warnings
from typing import Any, Callable, Mapping, Sequence

import grain
import jax
import numpy as np

from sav_jax._checks import caller_stacklevel, is_int, plural, require_int
from sav_jax.data import frame_io
from sav_jax.data.base import some_of
from sav_jax.data.synthetic import SyntheticConfig, SyntheticStereoVideo

log = logging.getLogger(__name__)

EXAMPLE_KEYS = ("left", "right", "disparity", "valid")


def as_example(clip: Mapping[str, Any]) -> dict[str, np.ndarray]:
  """Keeps the training keys with the pipeline's dtypes and checks their shapes.

  Args:
    clip: dict with `left`, `right` `[T, H, W, 3]`, `disparity` `[T, H, W]` (or
      `[T, H, W, 1]`) and `valid` `[T, H, W]` (bool or float; >= 0.5 is valid).

  Returns:
    A new dict with exactly `EXAMPLE_KEYS`.
  """
  left, right = np.asarray(clip["left"]), np.asarray(clip["right"])
  disp = np.asarray(clip["disparity"], np.float32)
  valid = np.asarray(clip["valid"])
  if disp.ndim == 4 and disp.shape[-1] == 1:
    disp = disp[..., 0]
  if valid.ndim == 4 and valid.shape[-1] == 1:
    valid = valid[..., 0]
  if valid.dtype != bool:
    valid = valid >= 0.5
  if left.shape != right.shape or left.ndim != 4 or left.shape[-1] != 3:
    raise ValueError(f"left/right must be [T, H, W, 3] of equal shape, got {left.shape} "
                     f"and {right.shape}")
  if disp.shape != left.shape[:3] or valid.shape != left.shape[:3]:
    raise ValueError(f"disparity {disp.shape} / valid {valid.shape} do not match the "
                     f"images {left.shape[:3]}")
  for name, view in (("left", left), ("right", right)):
    if view.dtype.kind == "f" and not np.isfinite(view).all():  # (NaN became 0, inf 255)
      raise ValueError(f"{name} frames hold NaN or infinite values: the pipeline expects "
                       "8-bit RGB, 0..255")
  if left.dtype.kind == "f" and left.size and 0 < float(left.max()) <= 1.0:
    warnings.warn(f"float frames with values up to {float(left.max()):g}: the pipeline expects "
                  "0..255 (multiply 0..1 images by 255)", stacklevel=caller_stacklevel())
  for name, view in (("left", left), ("right", right)):
    if view.dtype.kind in "iu" and view.dtype != np.uint8 and view.size and (
        int(view.max()) > 255 or int(view.min()) < 0):
      # (clipped to 0..255, a 16-bit frame was all but white)
      raise ValueError(f"{name} frames of dtype {view.dtype} with values in "
                       f"{int(view.min())}..{int(view.max())}: the pipeline expects 8-bit RGB, "
                       "0..255 (a 16-bit frame: x >> 8, as the dataset readers read one)")
  as_u8 = lambda a: a if a.dtype == np.uint8 else np.clip(np.rint(a), 0, 255).astype(np.uint8)
  return {"left": as_u8(left), "right": as_u8(right), "disparity": disp, "valid": valid}


def synthetic_source(cfg: SyntheticConfig, num_clips: int) -> grain.MapDataset:
  """`num_clips` procedural clips of `cfg` (deterministic per index)."""
  return grain.MapDataset.source(SyntheticStereoVideo(cfg, num_clips)).map(as_example)


class _LoadClip:
  """Registry item -> clip dict (picklable, for grain worker processes).

  An item is a `registry.TrainingClip(sequence, indices)` (or any `(sequence, indices)`
  pair whose sequence has `gather`), or an already loaded clip dict. The sequence's
  `sparse` flag is passed on so that augmentation treats sparse GT as the official
  sparse augmentor does.
  """

  def __call__(self, item) -> dict[str, np.ndarray]:
    if isinstance(item, Mapping):
      return dict(item)
    sequence, indices = item
    try:
      clip = sequence.gather(list(indices))
    except (ValueError, OSError) as e:  # the readers' errors name the file
      e.add_note(UNREADABLE_NOTE)  # kept through grain's threads and worker processes
      raise
    if clip.get("disparity") is None:
      raise ValueError(f"{clip_origin(sequence, indices)} has no ground truth: it cannot be "
                       "used for training")
    sparse = bool(getattr(sequence, "sparse", False))
    if not sparse:
      honour_dense_masks(clip)
    check_disparity_sign(clip, sequence, indices)
    clip["sparse"] = sparse
    clip[ORIGIN] = clip_origin(sequence, indices)
    return clip


def honour_dense_masks(clip: dict) -> None:
  """Sets a dense clip's disparity to 0 where its reader's valid mask says no but the
  official dense rule (`d != 0 and |d| < 512`, which the augmentation applies to the
  resized disparity instead of carrying the mask) would count it: a reader of your own
  that marks pixels invalid and leaves a value there (-1, a fill, garbage) trained on
  them. The built-in readers leave 0 or a value of 512 px or more there, so their clips,
  and the official resize of them, are unchanged."""
  for dkey, vkey in (("disparity", "valid"), ("right_disparity", "right_valid")):
    if clip.get(dkey) is None or clip.get(vkey) is None:
      continue
    disp, valid = np.asarray(clip[dkey]), frame_io.valid_mask(clip[vkey])  # (0.3 was valid)
    hidden = ~valid & frame_io.dense_valid(disp)
    if hidden.any():
      clip[dkey] = np.where(hidden, np.float32(0), disp).astype(disp.dtype)


def check_disparity_sign(clip: Mapping[str, Any], sequence, indices) -> None:
  """Raises ValueError, naming the clip and a ground-truth file, where most valid pixels of
  a frame of a loaded clip have a negative disparity: the loss compares the model's positive
  disparities of the left view (x_left - x_right) with it, and the dense augmentation counts
  any non-zero value below 512 px as valid, so a reader of your own that returns the
  official loaders' internal `-d` (or a right-view disparity) trained without a word on a
  target of the wrong sign."""
  disp = np.asarray(clip["disparity"])
  valid = clip.get("valid")
  valid = (disp != 0) if valid is None else np.asarray(valid, bool)
  negative = np.sum(valid & (disp < 0), axis=(-2, -1))
  positive = np.sum(valid & (disp > 0), axis=(-2, -1))
  bad = np.flatnonzero(negative > positive)
  if not bad.size:
    return
  t = int(bad[0])
  frame = list(indices)[t]
  files = getattr(sequence, "files", {}) or {}
  gt = files.get("left_gt", ())
  where = f" ({gt[frame]})" if frame < len(gt) else ""
  share = 100.0 * negative[t] / max(1, negative[t] + positive[t])
  raise ValueError(
      f"{clip_origin(sequence, indices)}: the ground truth of frame {frame}{where} is negative "
      f"at {share:.0f}% of its valid pixels (min {float(disp[t][valid[t]].min()):.3g} px): "
      "training needs the left view's disparity as a positive number of pixels (x_left - "
      "x_right; the official loaders store -d internally): negate it in your reader")


# The note (`BaseException.add_note`) on a reader's error for a clip's files: what
# `data.skip_unreadable` skips (not a config error such as a crop the frames cannot give).
UNREADABLE_NOTE = "a file of this clip does not read (data.skip_unreadable skips such clips)"


def is_unreadable(error: BaseException) -> bool:
  """Whether `error` is a clip's reader error (`UNREADABLE_NOTE`)."""
  return UNREADABLE_NOTE in getattr(error, "__notes__", ())


# The key of a loaded clip that says where it comes from (`clip_origin`): errors of its
# augmentation name it. `as_example` leaves it out of the batches.
ORIGIN = "origin"


def clip_origin(sequence, indices) -> str:
  """`dataset/sequence, frames [..] (first left image PATH)` for error messages."""
  indices = list(indices)
  where = f"{getattr(sequence, 'dataset', '?')}/{getattr(sequence, 'name', sequence)}"
  files = getattr(sequence, "files", None)
  try:
    first = f" (first left image {files['left'][indices[0]]})"
  except (TypeError, KeyError, IndexError):
    first = ""
  return f"{where}, frames {indices}{first}"


def registry_clips(dataset: str, root: str, frames: int, split: str = "train",
                   seed: int = 0, consecutive: bool = False) -> list:
  """The clips `registry_source` loads: `registry.TrainingClip(sequence, indices)` items
  (same arguments); raises ValueError, saying why, when there are none."""
  from sav_jax.data import registry  # pylint: disable=g-import-not-at-top
  items = (registry.get_consecutive_clips(dataset, root, frames, split) if consecutive else
           registry.get_training_clips(dataset, root, frames, split=split, seed=seed))
  if len(items) == 0:
    strided = not consecutive and dataset in registry.STRIDED
    raise ValueError(
        f"dataset {dataset!r} under {root!r} (split {split!r}) has no clips of {frames} "
        "frames: its sequences are too short for them" + (
            " (its training clips take every 1st to 5th frame, a stride drawn per clip from "
            "the seed: a clip spans up to 5x its frames)" if strided else "")
        + "; use fewer frames per clip")
  return items


def without_ground_truth(items) -> list:
  """The sequences of `registry_clips` items whose frames carry no ground truth (`has_gt`
  False: a "folder" sequence without `disparity/`, an images-only dataset), once each, in
  order."""
  seqs = []
  for sequence, _ in items:
    if not getattr(sequence, "has_gt", True) and all(s is not sequence for s in seqs):
      seqs.append(sequence)
  return seqs


def sequences_named(seqs) -> str:
  """`night (/data/val/night/left), ...`: sequences by name and the folder of their left
  frames, for messages (the first 5, the rest counted: `some_of`)."""
  def one(seq):
    try:
      return f"{seq.name} ({pathlib.Path(seq.files['left'][0]).parent})"
    except (AttributeError, TypeError, KeyError, IndexError):
      return str(getattr(seq, "name", seq))
  return some_of([one(s) for s in seqs], most=5)


def measured_items(items, dataset: str, split: str) -> list:
  """`items` without the clips of sequences that have no ground truth (validation: they
  have nothing to be scored against), with a warning naming those sequences; ValueError
  where no clip is left."""
  missing = without_ground_truth(items)
  if not missing:
    return list(items)
  kept = [item for item in items if all(item[0] is not s for s in missing)]
  what = f"{plural(len(missing), 'sequence')} of {dataset}/{split} without ground truth"
  if not kept:
    raise ValueError(f"no clip has ground truth to be scored against: {what}: "
                     f"{sequences_named(missing)}")
  log.warning("validation: left out the clips of %s (nothing to score them against): %s",
              what, sequences_named(missing))
  return kept


def clips_digest(items) -> str:
  """A digest of which clips `items` are, in order (sequence names and frame indices): a
  resumed run compares it with the saving run's to tell whether its data changed."""
  digest = hashlib.sha256()
  for sequence, indices in items:
    digest.update(f"{getattr(sequence, 'name', sequence)}|{list(indices)}\n".encode())
  return digest.hexdigest()[:16]


def registry_source(dataset: str, root: str, frames: int, split: str = "train",
                    seed: int = 0, consecutive: bool = False) -> grain.MapDataset:
  """Clips of a real dataset (`registry.get_training_clips`), loaded lazily, not augmented.

  Args:
    dataset: a registry name with training clips ("sceneflow", "dynamic_replica", ...).
    root: dataset root (`data/datasets` or the dataset's own folder).
    frames: clip length T.
    split: dataset split.
    seed: seed of the official per-start stride draws.
    consecutive: clips of consecutive frames instead (`registry.get_consecutive_clips`,
      any dataset with ground truth; for validation: the clips of sequences without ground
      truth are left out, with a warning, `measured_items`).
  """
  items = registry_clips(dataset, root, frames, split, seed, consecutive)
  if consecutive:  # validation: a sequence without ground truth has nothing to score
    items = measured_items(items, dataset, split)
  return clips_source(items)


def clips_source(items, skip_unreadable: int = 0) -> grain.MapDataset:
  """`registry_clips` items as a lazily loading `grain.MapDataset`.

  `skip_unreadable`: 0 (default) lets a clip that does not read (a corrupt or missing file:
  the reader's ValueError or OSError, naming the file) fail the stream; N > 0 replaces it
  by a readable clip drawn from the list at random (a hash of its index: not a neighbour,
  which would share its frames), with a warning naming it, trying up to N stand-ins (all of
  them unreadable is an error: a lost disk or mount is not skipped through). Deterministic:
  the same clip always stands in, so a resumed run sees the batches an uninterrupted one
  would."""
  if not (is_int(skip_unreadable) and skip_unreadable >= 0):
    raise ValueError(f"skip_unreadable must be an integer >= 0, got {skip_unreadable!r}")
  if skip_unreadable == 0:
    return grain.MapDataset.source(list(items)).map(_LoadClip())
  return grain.MapDataset.source(_SkippingClips(list(items), skip_unreadable))


class _SkippingClips:
  """`clips_source(items, skip_unreadable=N)`'s random-access source (picklable)."""

  def __init__(self, items: list, skip: int):
    self._items, self._skip, self._warned = items, skip, set()

  def __len__(self) -> int:
    return len(self._items)

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    load, n, first = _LoadClip(), len(self._items), None
    tries = min(self._skip, n - 1) + 1
    for k in range(tries):
      key = self.stand_in(index, k)
      item = self._items[key]
      try:
        return load(item)
      except (ValueError, OSError) as e:
        if not is_unreadable(e):
          raise
        first = first or e
        error = f"{type(e).__name__}: {e}"  # (readers name the file)
        if error not in self._warned:  # once per error and process: every epoch reads the
          self._warned.add(error)      # clip, and a bad frame is in ~2T overlapping clips
          log.warning("skipping an unreadable clip (data.skip_unreadable): %s: %s (other "
                      "clips with this error are skipped without a warning)", _where(item),
                      error)
    raise ValueError(f"clip {index} and {plural(tries - 1, 'stand-in')} drawn for it do not "
                     f"read (data.skip_unreadable={self._skip} skips no more: a lost disk or "
                     f"mount?); the first: {type(first).__name__}: {first}") from first

  def stand_in(self, index: int, k: int) -> int:
    """The clip read for `index` at try `k`: itself, then clips drawn at random (a hash of
    both), not its neighbours in the list, which overlap it (a SceneFlow frame is in about
    2T neighbouring clips): one bad file does not exhaust the tries."""
    if k == 0:
      return index
    other = int(np.random.default_rng([index, k]).integers(len(self._items) - 1))
    return other + (other >= index)  # any clip but itself

  def __getstate__(self):  # grain workers: without the warned set
    return {"_items": self._items, "_skip": self._skip}

  def __setstate__(self, state):
    self.__dict__.update(state, _warned=set())


def _where(item) -> str:
  """`clip_origin` of a registry item (a loaded clip dict: its origin, if it has one)."""
  if isinstance(item, Mapping):
    return str(item.get(ORIGIN, "a clip"))
  sequence, indices = item
  return clip_origin(sequence, indices)


@dataclasses.dataclass(frozen=True)
class Augment:
  """`sav_jax.data.augment.augment_clip` as a grain random map (picklable).

  Attributes:
    crop: `(H, W)` output size; checked after augmentation.
    overrides: other `AugmentConfig` fields, as `(name, value)` pairs (its defaults are
      the official training script's).
  """

  crop: tuple[int, int]
  overrides: tuple[tuple[str, Any], ...] = ()

  def augment_config(self):
    """The `AugmentConfig` applied (its checks raise ValueError naming the field)."""
    from sav_jax.data import augment  # pylint: disable=g-import-not-at-top
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in self.overrides}
    kwargs.setdefault("crop_size", tuple(self.crop))
    return augment.AugmentConfig(**kwargs)

  def __call__(self, clip, rng: np.random.Generator) -> dict[str, np.ndarray]:
    from sav_jax.data import augment  # pylint: disable=g-import-not-at-top
    if not clip.get("sparse", False):  # clips not loaded by `_LoadClip` (synthetic_source,
      clip = dict(clip)                # clip dicts): their masks were recomputed as all valid
      honour_dense_masks(clip)
    try:
      out = as_example(augment.augment_clip(clip, self.augment_config(), rng))
    except ValueError as e:  # which clip of which dataset (of a mixture)
      if not clip.get(ORIGIN):
        raise
      raise ValueError(f"{clip[ORIGIN]}: {e}") from e
    if out["left"].shape[1:3] != tuple(self.crop):
      raise ValueError(f"augmentation produced {out['left'].shape[1:3]}, expected the crop "
                       f"{tuple(self.crop)}")
    return out


def center_crop(clip: Mapping[str, np.ndarray], crop: tuple[int, int]) -> dict[str, np.ndarray]:
  """Central `crop = (H, W)` window of every frame (validation of real data)."""
  ex = as_example(clip)
  h, w = ex["left"].shape[1:3]
  ch, cw = crop
  if not (1 <= ch <= h and 1 <= cw <= w):
    raise ValueError(f"crop {crop} must be at least 1x1 and at most the frames {(h, w)}")
  y0, x0 = (h - ch) // 2, (w - cw) // 2
  return {k: v[:, y0:y0 + ch, x0:x0 + cw] for k, v in ex.items()}


def mixture_weights(lengths: Sequence[int], weights: Sequence[float], mode: str) -> list[float]:
  """Sampling proportions of the mixed sources.

  Args:
    lengths: number of clips of each source (all of them: the processes split the mix).
    weights: per-source weights.
    mode: `"ratio"`: the weights are the sampling proportions; `"concat"`: the weights
      are repeat counts of each dataset in a concatenation (the official
      `dataset + dataset`), so proportions are `weight * length`.

  Returns:
    Normalised proportions.
  """
  if len(lengths) != len(weights) or not lengths:
    raise ValueError(f"need one weight per source, got {len(weights)} for {len(lengths)}")
  if mode == "concat":
    raw = [float(w) * n for w, n in zip(weights, lengths)]
  elif mode == "ratio":
    raw = [float(w) for w in weights]
  else:
    raise ValueError(f"unknown mixing mode {mode!r}; expected 'ratio' or 'concat'")
  if not all(np.isfinite(raw)) or min(raw) <= 0:
    raise ValueError(f"mixture weights must be finite and > 0 (leave a source out instead of "
                     f"giving it 0), got {list(weights)}")
  return [r / sum(raw) for r in raw]


def make_train_dataset(sources: Sequence[grain.MapDataset], weights: Sequence[float], *,
                       batch_size: int, seed: int, mode: str = "ratio",
                       transforms: Sequence[Callable | None] | None = None,
                       process_index: int | None = None, process_count: int | None = None,
                       num_threads: int = 2, prefetch: int = 4,
                       worker_count: int = 0) -> grain.IterDataset:
  """Infinite, shuffled, mixed, per-process batched training stream.

  Args:
    sources: random-access datasets of clips (e.g. `synthetic_source`,
      `registry_source`), each over all clips (sharding happens here).
    weights: mixture weights (see `mixture_weights`).
    batch_size: clips per batch *of this process* (global batch / process count).
    seed: shuffling and augmentation seed (the same on every process: the processes
      split one global shuffled, augmented stream, element `k` going to process `k % P`).
    mode: `"ratio"` or `"concat"` weighting.
    transforms: per source, `None` or a random map `(clip, np.random.Generator) -> example`
      (e.g. `Augment`); without one, `as_example` is applied.
    process_index, process_count: this process's share (default: JAX's).
    num_threads: reader threads; prefetch: elements buffered per thread pool.
    worker_count: > 0 adds `mp_prefetch` with that many worker processes. They are
      started by Python's `spawn`, which imports the calling script again in each: a script
      (not a notebook) that builds the stream needs the `if __name__ == "__main__":` guard.

  Returns:
    A `grain.IterDataset` of dicts `left/right [B, T, H, W, 3] uint8`, `disparity
    [B, T, H, W] float32`, `valid [B, T, H, W] bool`.
  """
  transforms = list(transforms) if transforms is not None else [None] * len(sources)
  if len(transforms) != len(sources):
    raise ValueError(f"need one transform (or None) per source, got {len(transforms)} for "
                     f"{len(sources)} sources")
  if not (is_int(seed) and 0 <= seed < 2**32):
    raise ValueError(f"seed must be an integer in [0, 2**32), got {seed!r}")
  for name, value, least in (("batch_size", batch_size, 1), ("num_threads", num_threads, 0),
                             ("prefetch", prefetch, 0), ("worker_count", worker_count, 0)):
    require_int(value, name, least)  # (worker_count=-1 read as 0 without a word)
  props = mixture_weights([len(s) for s in sources], weights, mode)
  pi = jax.process_index() if process_index is None else process_index
  pc = jax.process_count() if process_count is None else process_count
  if not 0 <= pi < pc:
    raise ValueError(f"process_index {pi} not in [0, {pc})")
  streams = []
  for i, (src, tf) in enumerate(zip(sources, transforms)):
    ds = src.shuffle(seed=stream_seed(seed, i, "shuffle")).repeat()
    ds = (ds.random_map(tf, seed=stream_seed(seed, i, "augment")) if tf is not None
          else ds.map(as_example))
    streams.append(ds)
  ds = streams[0] if len(streams) == 1 else grain.MapDataset.mix(streams, props)
  # One global stream, the same on every process; each process takes every P-th element.
  # Shuffling and augmenting each process's slice instead gives every process the same
  # permutation and the same random draws, so a global batch would hold P neighbouring
  # clips (often overlapping frames of one sequence) cropped and jittered alike.
  ds = ds[pi::pc]
  read = grain.ReadOptions(num_threads=num_threads, prefetch_buffer_size=prefetch)
  it = ds.to_iter_dataset(read).batch(batch_size, drop_remainder=True, batch_fn=stack_examples)
  if worker_count > 0:
    from absl import flags  # pylint: disable=g-import-not-at-top
    if not flags.FLAGS.is_parsed():  # grain reads its absl flags (their defaults here) when it
      flags.FLAGS.mark_as_parsed()   # starts workers: a notebook or script parses none
    it = it.mp_prefetch(grain.MultiprocessingOptions(num_workers=worker_count),
                        worker_init_fn=_init_worker)
  return it


_STREAM_PURPOSES = ("shuffle", "augment")
# How `stream_seed` derives the sources' seeds (recorded with training checkpoints: a resume
# written with another derivation gets another shuffle, and is warned about).
SEEDING = 2


def stream_seed(seed: int, source: int, purpose: str) -> int:
  """The grain seed (in [0, 2**32)) of one source's shuffle or augmentation: a hash of
  (seed, source, purpose). grain's shuffle takes `seed + epoch` for each epoch, so seeds
  that differ by small offsets (`seed + i`) gave seed s + 1 the clip orders of seed s one
  epoch later: a seed sweep shared all but one epoch's order."""
  words = np.random.SeedSequence([seed, source, _STREAM_PURPOSES.index(purpose)])
  return int(words.generate_state(1, np.uint32)[0])


def _init_worker(worker_index: int, worker_count: int) -> None:
  """A grain worker process ignores SIGTERM and SIGINT: schedulers send SIGTERM, and a
  terminal's Ctrl-C SIGINT, to the whole process group, and the training process, which then
  finishes its step and saves a checkpoint, needs its workers until it is done (grain stops
  them itself: an event, then SIGKILL).

  So that a worker never outlives the training process (SIGKILLed, or taken by the
  out-of-memory killer: grain's own stop never comes, and the orphan would ignore `kill`),
  a thread ends the worker within a second of its parent's death."""
  del worker_index, worker_count
  signal.signal(signal.SIGTERM, signal.SIG_IGN)
  signal.signal(signal.SIGINT, signal.SIG_IGN)
  parent = os.getppid()

  def watch_parent():
    while os.getppid() == parent:  # (an orphan is adopted by init or a subreaper)
      time.sleep(0.5)
    os._exit(1)  # pylint: disable=protected-access

  threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()


def stack_examples(examples: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
  """Stacks examples into a batch; examples of different keys, shapes or dtypes (e.g.
  sources of another crop or frame count) are a ValueError that names the difference."""
  first = examples[0]
  for i, ex in enumerate(examples[1:], 1):
    if ex.keys() != first.keys():
      raise ValueError(f"examples of one batch have different keys: {sorted(first)} and "
                       f"{sorted(ex)}")
    for k in first:
      a, b = np.asarray(first[k]), np.asarray(ex[k])
      if a.shape != b.shape or a.dtype != b.dtype:
        raise ValueError(
            f"examples of one batch differ in {k!r}: {a.shape} {a.dtype} (example 0) and "
            f"{b.shape} {b.dtype} (example {i}); every source of a batch needs the same "
            "frame count and crop")
  return {k: np.stack([ex[k] for ex in examples]) for k in first}


def to_global(batch: Mapping[str, np.ndarray], sharding: jax.sharding.Sharding
              ) -> dict[str, jax.Array]:
  """Process-local `[B_local, ...]` numpy arrays -> global arrays `[B_local * P, ...]`.

  This is the pipeline's one intended host-to-device copy, so it is allowed even under
  `jax.transfer_guard("disallow")` (which counts multi-process placement as implicit).
  """
  with jax.transfer_guard_host_to_device("allow"):
    return {k: jax.make_array_from_process_local_data(sharding, np.asarray(v))
            for k, v in batch.items()}


class GlobalBatchIterator:
  """Iterator of global device batches over a grain iterator, with its state.

  Args:
    iterator: a `grain.DatasetIterator` of local numpy batches.
    sharding: sharding of the batch (leading axis on the mesh's data axis).
  """

  def __init__(self, iterator, sharding: jax.sharding.Sharding):
    self.grain_iterator = iterator
    self.sharding = sharding

  def __iter__(self):
    return self

  def __next__(self) -> dict[str, jax.Array]:
    return to_global(next(self.grain_iterator), self.sharding)

  def get_state(self):
    return self.grain_iterator.get_state()

  def set_state(self, state) -> None:
    self.grain_iterator.set_state(state)


def fixed_clips(ds: grain.MapDataset, num_clips: int,
                transform: Callable[[Mapping[str, Any]], dict] = as_example
                ) -> list[dict[str, np.ndarray]]:
  """The first `num_clips` clips of `ds` on the host (a held-out validation set)."""
  if not (is_int(num_clips) and num_clips >= 1):  # (numpy integers too)
    raise ValueError(f"num_clips must be an integer >= 1, got {num_clips!r}")
  if len(ds) < num_clips:
    raise ValueError(f"validation set has {len(ds)} clips, {num_clips} requested")
  return [transform(ds[i]) for i in range(num_clips)]


def eval_batches(clips: Sequence[Mapping[str, np.ndarray]], batch_size: int
                 ) -> list[tuple[dict[str, np.ndarray], int]]:
  """Stacks clips into batches of exactly `batch_size` (static shapes).

  The last batch is padded by repeating its last clip.

  Returns:
    `[(batch, num_real_clips)]` with `batch` arrays `[batch_size, ...]`.
  """
  if not (is_int(batch_size) and batch_size >= 1):  # (numpy integers too)
    raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
  if not clips:
    raise ValueError("no clips to batch")
  out = []
  for start in range(0, len(clips), batch_size):
    part = list(clips[start:start + batch_size])
    n = len(part)
    part += [part[-1]] * (batch_size - n)
    out.append((stack_examples([{k: c[k] for k in EXAMPLE_KEYS} for c in part]), n))
  return out

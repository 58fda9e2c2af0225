"""Dataset registry: sequences per dataset and split, and the official training clips.

  seqs = get_sequences("dynamic_replica", "data/datasets", "test")   # first 150 frames each
  clips = get_training_clips("sceneflow", "data/datasets", frames=5)
  seq, indices = clips[0]
  sample = seq.gather(indices)                                       # [5, H, W, ...]

`root` may be the common parent (`data/datasets`) or the dataset's own folder.
Evaluation splits are cut as the official evaluation does (`EVAL_FRAMES`): only the
first L frames of each sequence (L = N when N <= L), and Dynamic Replica sequences
shorter than L are skipped. Other splits return whole sequences.
"""

from __future__ import annotations

import functools
import inspect
import logging
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from sav_jax._checks import is_int
from sav_jax.data import (dynamic_replica, infinigen, kitti_depth, sceneflow, sintel,
                          south_kensington, spring, stereo_folder, tartanair, vkitti2)
from sav_jax.data.base import (StereoSequence, find_root, is_hidden, sceneflow_clips,
                               strided_clips)

log = logging.getLogger(__name__)

DEFAULT_ROOT = "data/datasets"

_LOADERS = {
    "sceneflow": sceneflow.load_sequences,
    "flyingthings3d": functools.partial(sceneflow.load_sequences, subsets=("FlyingThings3D",),
                                        dataset="flyingthings3d"),
    "monkaa": functools.partial(sceneflow.load_sequences, subsets=("Monkaa",), dataset="monkaa"),
    "driving": functools.partial(sceneflow.load_sequences, subsets=("Driving",),
                                 dataset="driving"),
    "sintel_clean": functools.partial(sintel.load_sequences, dstype="clean"),
    "sintel_final": functools.partial(sintel.load_sequences, dstype="final"),
    "dynamic_replica": dynamic_replica.load_sequences,
    "infinigen_sv": infinigen.load_sequences,
    "vkitti2": vkitti2.load_sequences,
    "kitti_depth": kitti_depth.load_sequences,
    "spring": spring.load_sequences,
    "south_kensington": south_kensington.load_sequences,
    "tartanair": tartanair.load_sequences,
    "folder": stereo_folder.load_sequences,  # your own videos (`stereo_folder`)
}
DATASETS = tuple(_LOADERS)
# The folders a datasets root holds each dataset in (`find_root`).
_FOLDERS = {
    "sceneflow": sceneflow.SUBSETS, "flyingthings3d": ("FlyingThings3D",), "monkaa": ("Monkaa",),
    "driving": ("Driving",), "sintel_clean": sintel.FOLDERS, "sintel_final": sintel.FOLDERS,
    "dynamic_replica": dynamic_replica.FOLDERS, "infinigen_sv": infinigen.FOLDERS,
    "vkitti2": vkitti2.FOLDERS, "kitti_depth": kitti_depth.FOLDERS, "spring": spring.FOLDERS,
    "south_kensington": south_kensington.FOLDERS, "tartanair": tartanair.FOLDERS,
    "folder": (),  # the root is the dataset's folder
}

SPLITS = {
    "sceneflow": sceneflow.SPLITS, "flyingthings3d": sceneflow.SPLITS,
    "monkaa": ("train",), "driving": ("train",),
    "sintel_clean": sintel.SPLITS, "sintel_final": sintel.SPLITS,
    "dynamic_replica": dynamic_replica.SPLITS, "infinigen_sv": infinigen.SPLITS,
    "vkitti2": vkitti2.SPLITS, "kitti_depth": kitti_depth.SPLITS,
    "spring": spring.SPLITS, "south_kensington": south_kensington.SPLITS,
    "tartanair": tartanair.SPLITS, "folder": stereo_folder.SPLITS,
}
# Official evaluation: frames 0..L-1 of each sequence of the "test" split
# (`sample_len` with `only_first_n_samples=1`). Sintel evaluates every frame; Spring's
# SAV protocol is unknown, and no official script evaluates TartanAir, so they are left whole.
EVAL_FRAMES = {"dynamic_replica": 150, "infinigen_sv": 150, "vkitti2": 300,
               "kitti_depth": 300, "south_kensington": 300}
# Datasets whose evaluation skips sequences shorter than its frames (`eval_chunk`'s
# drop_short): the official Dynamic Replica loader fails on them.
DROP_SHORT = ("dynamic_replica",)
# SceneFlow samples forward + time-reversed clips; these sample strided clips.
STRIDED = ("dynamic_replica", "infinigen_sv", "kitti_depth", "vkitti2", "tartanair", "folder")
_SCENEFLOW = ("sceneflow", "flyingthings3d", "monkaa", "driving")
OFFICIAL = "official"


class TrainingClip(NamedTuple):
  """One training sample: a sequence and the indices of its frames (in clip order)."""

  sequence: StereoSequence
  indices: list[int]


def _check_name(dataset: str) -> None:
  if dataset not in _LOADERS:
    raise ValueError(f"unknown dataset {dataset!r}; known datasets: {', '.join(DATASETS)}")


def eval_chunk(sequences: list[StereoSequence], length: int | None,
               drop_short: bool = False) -> list[StereoSequence]:
  """Cuts each sequence to its first evaluation chunk of `length` frames.

  Args:
    sequences: whole sequences.
    length: L; None or <= 0 keeps every frame; L >= N keeps the sequence whole.
    drop_short: skip sequences shorter than L (the official Dynamic Replica loader
      fails on them and skips them silently).
  """
  if length is not None and not is_int(length):
    raise TypeError(f"the evaluation chunk length must be an integer or None, got {length!r}")
  if length is None or length <= 0:
    return list(sequences)
  out, short = [], []
  for seq in sequences:
    if len(seq) < length and drop_short:
      short.append(seq.name)
      continue
    out.append(seq.head(min(length, len(seq))))
  if short:
    log.warning("skipped %d sequence(s) shorter than %d frames, as the official evaluation "
                "does: %s", len(short), length, ", ".join(map(str, short[:5]))
                + (" ..." if len(short) > 5 else ""))
  return out


def register_dataset(name: str, load_sequences, *, splits: tuple[str, ...],
                     folders: tuple[str, ...] = (), training: str | None = "strided",
                     eval_frames: int | None = None) -> None:
  """Adds a dataset reader of your own layout to the registry, for `get_sequences`, training
  sources (`config.data.sources.<x>.dataset`) and `python -m eval` (`eval_config(name)`);
  call it where those run (a training or evaluation config file is run in their process).

  Registering a name again with the same arguments does nothing (a config file loaded twice).

  Args:
    name: the registry name (not one of `DATASETS` already).
    load_sequences: `(folder, split, dataset=name) -> list[StereoSequence]`, called with the
      dataset's own folder, raising FileNotFoundError naming what is missing. With grain's
      worker processes (`data.worker_count` > 0) the sequences are pickled to them: define
      it and your sequence class in a module they can import (not in the config file, which
      is loaded under another name).
    splits: the splits it has ("train", "test", ...).
    folders: the dataset's folder names under a datasets root (`root/<folder>` is taken
      where it exists, else `root` itself; empty: the root is always the folder).
    training: how training clips are sampled: "strided" (the official Dynamic Replica
      clips), "sceneflow" (forward and time-reversed clips of consecutive frames) or None
      (evaluation only).
    eval_frames: evaluate the first L frames of each "test" sequence (None: whole ones).
  """
  global DATASETS, STRIDED, _SCENEFLOW  # pylint: disable=global-statement
  if not (isinstance(folders, (tuple, list))
          and all(isinstance(f, str) and f for f in folders)):  # a str: one per letter
    raise ValueError(f"register_dataset: folders must be a tuple of folder names, got "
                     f"{folders!r}" + (f" (one folder: folders=({folders!r},))"
                                       if isinstance(folders, str) else ""))
  entry = functools.partial(_registered, load_sequences, tuple(folders), name)
  same = _LOADERS.get(name)
  if (isinstance(same, functools.partial) and same.func is _registered
      and same.args == entry.args and SPLITS[name] == tuple(splits)
      and EVAL_FRAMES.get(name) == eval_frames
      and (name in STRIDED, name in _SCENEFLOW) == (training == "strided",
                                                    training == "sceneflow")):
    return  # registered again as it is (a config file loaded twice, a notebook cell re-run)
  if isinstance(same, functools.partial) and same.func is _registered:
    raise ValueError(f"register_dataset: {name!r} is already registered with other "
                     "arguments (load_sequences, splits, folders, training or eval_frames); "
                     "a registered name keeps its arguments: choose another name")
  if not (isinstance(name, str) and name.isidentifier()) or name in _LOADERS or \
      name == "synthetic":
    raise ValueError(f"register_dataset: name must be a new identifier (not one of "
                     f"{', '.join(DATASETS)} or 'synthetic'), got {name!r}")
  if not callable(load_sequences):
    raise ValueError(f"register_dataset: load_sequences must be a function, got "
                     f"{load_sequences!r}")
  _check_loader_signature(name, load_sequences)
  if not (isinstance(splits, (tuple, list)) and splits
          and all(isinstance(s, str) for s in splits)):
    raise ValueError(f"register_dataset: splits must be a non-empty tuple of names, got "
                     f"{splits!r}")
  if training not in ("strided", "sceneflow", None):
    raise ValueError(f"register_dataset: training must be 'strided', 'sceneflow' or None, got "
                     f"{training!r}")
  if eval_frames is not None and not (is_int(eval_frames) and eval_frames > 0):
    raise ValueError(f"register_dataset: eval_frames must be an integer > 0 or None, got "
                     f"{eval_frames!r}")
  _LOADERS[name] = entry
  _FOLDERS[name] = tuple(folders)
  SPLITS[name] = tuple(splits)
  if eval_frames is not None:
    EVAL_FRAMES[name] = int(eval_frames)
  if training == "strided":
    STRIDED += (name,)
  elif training == "sceneflow":
    _SCENEFLOW += (name,)
  DATASETS = tuple(_LOADERS)


def _check_loader_signature(name: str, load_sequences) -> None:
  """Raises ValueError unless `load_sequences(folder, split, dataset=name)` binds: a
  `(root, split)` reader failed only when its data was first read, with a TypeError from
  inside the registry."""
  try:
    signature = inspect.signature(load_sequences)
  except (TypeError, ValueError):  # (a callable without one: not checked)
    return
  try:
    signature.bind("folder", "split", dataset=name)
  except TypeError as e:
    raise ValueError(f"register_dataset: load_sequences must take (folder, split, "
                     f"dataset=name), as sav_jax.data.stereo_folder.load_sequences does; "
                     f"{getattr(load_sequences, '__name__', 'it')}{signature} does not "
                     f"({e})") from None


def _registered(load_sequences, folders: tuple[str, ...], name: str, root, split: str,
                **options) -> list[StereoSequence]:
  """A `register_dataset` reader, called with the dataset's own folder."""
  return load_sequences(find_root(root, *folders), split, dataset=name, **options)


def dataset_folders(dataset: str, root: str | Path) -> list[Path]:
  """The folders under `root` (the datasets folder, or the dataset's own) that hold
  `dataset`'s files, as far as they exist (for "folder", an existing root's split folders,
  those not made yet too: an output written into one would become a sequence of it)."""
  _check_name(dataset)
  base = Path(root).expanduser()
  if dataset == "folder":  # the root's split folders (the reader looks nowhere else)
    return [base / s for s in stereo_folder.SPLITS] if base.is_dir() else []
  if not _FOLDERS[dataset]:  # (the root is the dataset's folder)
    return [base] if base.is_dir() else []
  if base.name in _FOLDERS[dataset]:
    return [base] if base.is_dir() else []
  return [base / f for f in _FOLDERS[dataset] if (base / f).is_dir()]


def get_sequences(dataset: str, root: str | Path, split: str, *, max_frames=OFFICIAL,
                  **options) -> list[StereoSequence]:
  """The sequences of one dataset split.

  Args:
    dataset: one of `DATASETS`.
    root: the common dataset parent (`data/datasets`) or the dataset's folder.
    split: one of `SPLITS[dataset]` ("train", "test", and "val"/"valid" where the
      dataset has one).
    max_frames: "official" cuts the "test" split as the official evaluation does
      (`EVAL_FRAMES`) and leaves other splits whole; an int L cuts every sequence to
      its first L frames, of any split (None or <= 0: whole sequences). Either way a
      Dynamic Replica sequence shorter than L is skipped, with a warning, as the official
      evaluation skips it (`DROP_SHORT`).
    **options: passed to the dataset's `load_sequences` (e.g. `pass_name` for
      SceneFlow).

  Returns:
    list of `StereoSequence`, in the official order.
  """
  _check_name(dataset)
  if split not in SPLITS[dataset]:
    raise ValueError(f"{dataset} has no split {split!r}; its splits: {SPLITS[dataset]}")
  if not (max_frames is None or max_frames == OFFICIAL or (
      is_int(max_frames))):
    raise ValueError(f"max_frames must be {OFFICIAL!r}, an integer or None, got {max_frames!r}")
  try:
    seqs = _LOADERS[dataset](root, split, **options)
  except FileNotFoundError as e:  # where the root was taken for the dataset's own folder
    folders, base = _FOLDERS[dataset], Path(root).expanduser()
    if (not folders or not base.is_dir() or base.name in folders  # (its own folder, incomplete)
        or any((base / f).is_dir() or (base / f).is_symlink() for f in folders)
        or _names_a_path_inside(base, e)):
      raise
    names = " or ".join(f"{f}/" for f in folders)
    inside = next((a for a in base.resolve().parents if a.name in folders), None)
    if inside is not None:  # e.g. sintel_stereo/training: one folder too deep
      raise FileNotFoundError(
          f"{e} ({base} is inside the dataset's folder {inside}: pass that folder, or the "
          "datasets folder that holds it)") from None
    raise FileNotFoundError(
        f"{e} ({base} holds no {names} folder and is not one either: pass the datasets "
        f"folder that holds {folders[0]}/, or that folder itself)") from None
  if max_frames == OFFICIAL:
    length = EVAL_FRAMES.get(dataset) if split == "test" else None
  else:
    length = max_frames
  return eval_chunk(seqs, length, drop_short=dataset in DROP_SHORT)


def _names_a_path_inside(base: Path, error: Exception) -> bool:
  """Whether `error` names a path inside one of `base`'s folders: the reader took `base` as
  the dataset's folder (one renamed, e.g. `DR/` for `dynamic_replica_data/`, reads as well)
  and something in it is missing, so `base` is not to be called "not the dataset's folder"."""
  text = str(error)
  others = {f for folders in _FOLDERS.values() for f in folders}  # a datasets folder's, not in one
  try:
    return any(f"{d}{os.sep}" in text for d in base.iterdir()
               if d.is_dir() and not is_hidden(d) and d.name not in others)
  except OSError:  # an unreadable root: the hint stays
    return False


def get_consecutive_clips(dataset: str, root: str | Path, frames: int, split: str, *,
                          max_frames=OFFICIAL, **options) -> list[TrainingClip]:
  """Clips of `frames` consecutive frames of every sequence, without overlap: starts 0, T,
  2T, ... while the clip fits (the frame spacing of the evaluation, for validation during
  training: training clips skip 1-5 frames, which TEPE would measure instead).

  Args:
    dataset, root, split, max_frames, **options: as in `get_sequences` (any dataset).
    frames: clip length T >= 1.

  Returns:
    list of `TrainingClip(sequence, indices)`, in sequence order.
  """
  if not isinstance(frames, (int, np.integer)) or frames < 1:
    raise ValueError(f"frames must be an int >= 1, got {frames!r}")
  seqs = get_sequences(dataset, root, split, max_frames=max_frames, **options)
  return [TrainingClip(seq, list(range(start, start + frames)))
          for seq in seqs for start in range(0, len(seq) - frames + 1, frames)]


def get_training_clips(dataset: str, root: str | Path, frames: int, split: str = "train", *,
                       seed: int = 0, **options) -> list[TrainingClip]:
  """The official training samples of a dataset: frame-index lists of whole sequences.

  SceneFlow (and its subsets): for ref in 0..N-T-1, the clip [ref, ref+T) and the
  time-reversed clip N-1-ref, ..., N-ref-T. Dynamic Replica, Infinigen SV, KITTI Depth,
  VKITTI2 and TartanAir: starts 0, 3, 6, ...; each start draws a stride k in 1..5 (k = 1 for
  T = 1) once, from `np.random.default_rng(seed)` in sequence order, and the clip
  start, start+k, ..., start+(T-1)k is kept when start + k*T < N.

  Args:
    dataset: a dataset with official training clips (SceneFlow family, DR,
      Infinigen SV, KITTI Depth, VKITTI2, TartanAir).
    root: as in `get_sequences`.
    frames: clip length T >= 1.
    split: the split to sample (default "train").
    seed: seed of the stride draws (the result is a pure function of the files and it).
    **options: passed to `get_sequences`.

  Returns:
    list of `TrainingClip(sequence, indices)`.
  """
  _check_name(dataset)
  if dataset not in _SCENEFLOW + STRIDED:
    own = getattr(_LOADERS[dataset], "func", None) is _registered
    raise ValueError(f"{dataset} has no official training clips; datasets with them: "
                     f"{', '.join(_SCENEFLOW + STRIDED)}" + (
                         f" ({dataset!r} was registered with training=None, for evaluation "
                         "only: register it with training='strided' or 'sceneflow' to train "
                         "on it)" if own else ""))
  if not isinstance(frames, (int, np.integer)) or frames < 1:
    raise ValueError(f"frames must be an int >= 1, got {frames!r}")
  seqs = get_sequences(dataset, root, split, max_frames=None, **options)
  rng = np.random.default_rng(seed)
  clips = []
  for seq in seqs:
    if dataset in _SCENEFLOW:
      indices = sceneflow_clips(len(seq), frames)
    else:
      indices = strided_clips(len(seq), frames, rng)
    clips += [TrainingClip(seq, idx) for idx in indices]
  return clips

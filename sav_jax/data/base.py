"""Random-access stereo sequences: the interface every dataset reader returns.

A `StereoSequence` holds the per-frame file lists of one rectified stereo video and
decodes frames on demand, so building a dataset index costs only directory listings
(plus one camera file per sequence) and sequences pickle cheaply into grain workers.

  seq = registry.get_sequences("sintel_final", root, "test")[0]
  frame = seq[0]          # left/right [H, W, 3] uint8, disparity [H, W] f32, valid [H, W] bool
  clip = seq.clip(0, 5)   # the same keys stacked: [5, H, W, ...]
"""

from __future__ import annotations

import copy
import decimal
import logging
import os
import re
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from sav_jax._checks import is_int
from sav_jax.data import frame_io

log = logging.getLogger(__name__)


class StereoSequence:
  """One stereo video, frame by frame; the base class is the images-only reader.

  Attributes:
    name: sequence name (unique within its dataset and split).
    dataset: registry name of the dataset.
    depth2disp_scale: fx[px] * baseline[m] from the first frame's camera, or None.
    sparse: whether the GT is sparse (its valid mask is carried through augmentation
      rather than recomputed from the disparity).
    files: per-frame files by kind (`left`, `right`, `left_gt`, ...), equal lengths.
    with_right_disparity: also decode the right view's GT (`right_disparity`,
      `right_valid`) when the dataset has it; off by default because only the left
      GT enters the loss and the metrics.
  """

  def __init__(self, name: str, files: Mapping[str, Sequence], *, dataset: str = "images",
               depth2disp_scale: float | None = None, sparse: bool = False):
    self.name = name
    self.dataset = dataset
    self.depth2disp_scale = None if depth2disp_scale is None else float(depth2disp_scale)
    if self.depth2disp_scale is not None and not 0 < self.depth2disp_scale < np.inf:
      raise ValueError(f"{dataset}/{name}: depth2disp scale must be positive and finite, "
                       f"got {depth2disp_scale}")
    self.sparse = bool(sparse)
    self.with_right_disparity = False
    for key, value in files.items():  # a str is a sequence too: of one-letter "paths"
      if isinstance(value, (str, bytes, Path)):
        raise ValueError(f"{dataset}/{name}: files[{key!r}] must be a list of paths, one per "
                         f"frame, got the single path {str(value)!r}")
    self.files = {k: tuple(Path(p) for p in v) for k, v in files.items()}
    for key in ("left", "right"):
      if key not in self.files:
        raise ValueError(f"{dataset}/{name}: no '{key}' image list")
    lengths = {k: len(v) for k, v in self.files.items()}
    if len(set(lengths.values())) != 1 or lengths["left"] == 0:
      raise ValueError(f"{dataset}/{name}: per-frame file counts differ or are zero: {lengths}")

  def __len__(self) -> int:
    return len(self.files["left"])

  def __repr__(self) -> str:
    return (f"{type(self).__name__}(dataset={self.dataset!r}, name={self.name!r}, "
            f"frames={len(self)}, depth2disp_scale={self.depth2disp_scale}, "
            f"sparse={self.sparse})")

  @property
  def has_gt(self) -> bool:
    """Whether frames carry ground truth (False for images-only datasets)."""
    return "left_gt" in self.files

  @property
  def has_right_disparity(self) -> bool:
    """Whether the dataset ships GT for the right view too."""
    return "right_gt" in self.files

  def _index(self, index: int) -> int:
    n = len(self)
    if not is_int(index):  # (numpy's bool is no Integral either)
      raise TypeError(f"{self.dataset}/{self.name}: frame index must be an integer, got "
                      f"{index!r}")
    i = int(index)
    if i < 0:
      i += n
    if not 0 <= i < n:
      raise IndexError(f"frame {index} out of range for {self.dataset}/{self.name} ({n} frames)")
    return i

  def __getitem__(self, index: int) -> dict:
    """Decodes frame `index`.

    Returns:
      left, right: [H, W, 3] uint8 RGB; disparity: [H, W] float32 positive px of the
      left view (0 where unknown) or None; valid: [H, W] bool or None; plus
      right_disparity / right_valid when `with_right_disparity` and available.
    """
    i = self._index(index)
    left = frame_io.read_image(self.files["left"][i])
    right = frame_io.read_image(self.files["right"][i])
    if left.shape != right.shape:
      raise ValueError(f"left {self.files['left'][i]} is {left.shape[:2]} but right "
                       f"{self.files['right'][i]} is {right.shape[:2]}")
    frame = {"left": left, "right": right, "disparity": None, "valid": None}
    if self.has_gt:
      frame["disparity"], frame["valid"] = self._checked_gt(i, "left", left.shape[:2])
      if self.with_right_disparity and self.has_right_disparity:
        frame["right_disparity"], frame["right_valid"] = self._checked_gt(i, "right",
                                                                          left.shape[:2])
    return frame

  def _checked_gt(self, i: int, side: str, size: tuple[int, int]):
    path = self.files[side + "_gt"][i]
    reader = f"{type(self).__name__}._read_gt"
    gt = self._read_gt(i, side)
    # A reader of your own: what it returns is checked here, naming it and the file (a
    # bare array, a list or a mask of another size failed later, naming neither).
    if not (isinstance(gt, tuple) and len(gt) == 2):
      raise ValueError(f"{reader} returned {_what(gt)} for {path}; expected a pair "
                       "(disparity [H, W], valid [H, W])")
    disp, valid = (np.asarray(a) for a in gt)
    if disp.dtype.kind not in "iuf":
      raise ValueError(f"{reader}: the disparity of {path} is of dtype {disp.dtype}; "
                       "expected numbers (pixels)")
    if disp.shape != size:
      raise ValueError(f"ground truth {path} is {disp.shape} but the "
                       f"image {self.files[side][i]} is {size}")
    if valid.shape != size or valid.dtype.kind not in "biuf":
      raise ValueError(f"{reader}: the valid mask of {path} is {valid.shape} {valid.dtype}; "
                       f"expected {size} bool (or weights) as the image "
                       f"{self.files[side][i]}")
    return (np.ascontiguousarray(disp, np.float32),
            np.ascontiguousarray(frame_io.valid_mask(valid)))

  def _read_gt(self, i: int, side: str) -> tuple[np.ndarray, np.ndarray]:
    """(disparity, valid) of frame i for `side` ("left"/"right"); subclasses decode. `valid`
    is bool, or weights of which those above 0.5 count (the official metrics' rule)."""
    raise NotImplementedError(f"{type(self).__name__} has no ground truth")

  def gather(self, indices: Iterable[int]) -> dict:
    """Frames `indices` (any order, e.g. time-reversed) stacked along a new axis 0.

    Returns:
      The keys of `seq[i]` with arrays [T, ...] (None stays None).

    Raises:
      ValueError: no index, or frames of different sizes (naming the sequence, the
        first odd frame's file and both sizes).
    """
    indices = [self._index(i) for i in indices]
    frames = [self[i] for i in indices]
    if not frames:
      raise ValueError("gather needs at least one frame index")
    size = frames[0]["left"].shape[:2]
    for i, frame in zip(indices, frames):
      if frame["left"].shape[:2] != size:
        h, w = frame["left"].shape[:2]
        raise ValueError(
            f"{self.dataset}/{self.name}: frame {i} {self.files['left'][i]} is {h}x{w} but "
            f"frame {indices[0]} {self.files['left'][indices[0]]} is {size[0]}x{size[1]} "
            "(height x width); the frames of one sequence must share a size")
    return {k: None if frames[0][k] is None else np.stack([f[k] for f in frames])
            for k in frames[0]}

  def clip(self, start: int, length: int, stride: int = 1) -> dict:
    """Frames `start, start + stride, ...` (`length` of them; stride may be negative).

    Returns:
      See `gather`.
    """
    if length < 1 or stride == 0:
      raise ValueError(f"clip needs length >= 1 and stride != 0, got {length}, {stride}")
    indices = [start + k * stride for k in range(length)]
    if min(indices) < 0 or max(indices) >= len(self):
      raise IndexError(f"clip {indices[0]}..{indices[-1]} out of range for "
                       f"{self.dataset}/{self.name} ({len(self)} frames)")
    return self.gather(indices)

  def head(self, n: int) -> "StereoSequence":
    """A copy restricted to the first `n` frames (the evaluation chunk)."""
    if not 1 <= n <= len(self):
      raise ValueError(f"head({n}) needs 1 <= n <= {len(self)}")
    out = copy.copy(self)
    out.files = {k: v[:n] for k, v in self.files.items()}
    return out


class DepthSequence(StereoSequence):
  """Ground truth stored as depth; disparity = depth2disp_scale / Z (`frame_io`).

  Args:
    name, files, dataset, depth2disp_scale, sparse: as `StereoSequence`; `files`
      holds `left_gt` (and optionally `right_gt`) depth files.
    depth_reader: path -> [H, W] float32 metres (a module-level function, so the
      sequence pickles).
  """

  def __init__(self, name: str, files: Mapping[str, Sequence], *, dataset: str,
               depth2disp_scale: float, depth_reader: Callable[[Path], np.ndarray],
               sparse: bool = False):
    super().__init__(name, files, dataset=dataset, depth2disp_scale=depth2disp_scale,
                     sparse=sparse)
    if self.depth2disp_scale is None:  # (a value is checked by StereoSequence)
      raise ValueError(f"{dataset}/{name}: depth2disp scale must be positive and finite, "
                       f"got {depth2disp_scale}")
    self.depth_reader = depth_reader

  def clip_scale(self, start: int) -> float:
    """The depth-to-disparity scale of a clip that starts at frame `start`: the official
    loader converts a clip's depth with its first frame's camera. This reader has one
    camera per sequence (`depth2disp_scale`); readers with per-frame cameras override it."""
    del start
    return self.depth2disp_scale

  def gather(self, indices: Iterable[int]) -> dict:
    """As `StereoSequence.gather`, with every frame's depth converted by the scale of the
    first index's camera (`clip_scale`), as the official loader converts a clip;
    `seq[i]` and `seq.clip(0, n)` (evaluation: whole sequences) use frame 0's."""
    indices = list(indices)
    scale = self.clip_scale(self._index(indices[0])) if indices else self.depth2disp_scale
    if scale == self.depth2disp_scale:
      return super().gather(indices)
    clip = copy.copy(self)  # not an attribute set on self: grain threads share sequences
    clip.depth2disp_scale = scale
    return StereoSequence.gather(clip, indices)

  def _read_gt(self, i: int, side: str):
    path = self.files[side + "_gt"][i]
    depth = np.asarray(self.depth_reader(path))
    if depth.ndim != 2:  # e.g. a 0-d array: depth_to_disparity failed deep in numpy
      raise ValueError(f"depth {path} has shape {depth.shape}; expected [H, W]")
    return frame_io.depth_to_disparity(depth, self.depth2disp_scale)


# ----------------------------------------------------------------------------- helpers


def _what(value) -> str:
  """`value` in words for an error message: `an array of shape (48, 96) float32`, `a list`,
  `a tuple of 3`, `None`."""
  if value is None:
    return "None"
  if isinstance(value, np.ndarray):
    return f"an array of shape {value.shape} {value.dtype}"
  if isinstance(value, tuple):
    return f"a tuple of {len(value)}"
  return f"a {type(value).__name__}"


def camera_scale(fx: float, baseline: float, source) -> float:
  """The depth-to-disparity scale fx * baseline of camera data read from `source` (a file,
  or a file and where in it), refused naming it unless both are positive and finite: TCC
  and the depth metrics would be NaN, and disparities negative or 0."""
  if not (0 < fx < np.inf):
    raise ValueError(f"{source}: the focal length fx is {fx:g}; it must be positive and finite")
  if not (0 < baseline < np.inf):
    raise ValueError(f"{source}: the stereo baseline is {baseline:g}; it must be positive and "
                     "finite (a right camera left of the left one gives a negative one)")
  return float(fx) * float(baseline)


def find_root(root, *names: str) -> Path:
  """The dataset directory: `root/<name>` for the first existing name, else `root`.

  Lets callers pass either the common parent (`data/datasets`) or the dataset's own
  folder. Raises FileNotFoundError when `root` does not exist, NotADirectoryError when it
  is a file.
  """
  root = Path(root).expanduser()
  if root.exists() and not root.is_dir():
    raise NotADirectoryError(f"dataset root {root} is a file, not a folder")
  if not root.is_dir():
    raise FileNotFoundError(f"dataset root not found: {root}")
  refuse_broken_links([root / name for name in names])  # (not "the root holds no <name>/")
  for name in names:
    if (root / name).is_dir():
      return root / name
  return root


def require_dir(path: Path, what: str = "directory") -> Path:
  """Returns `path`; raises FileNotFoundError naming it when it is not a directory (and,
  where the folder is there one level deeper, the extra folder an archive unpacked into)."""
  if not Path(path).is_dir():
    if Path(path).exists():  # (a file: "not found" sent the user looking for a missing one)
      raise NotADirectoryError(f"{what} {path} is a file, not a folder")
    refuse_broken_links_to(path)
    raise FileNotFoundError(f"{what} not found: {path}{_nested_hint(Path(path))}")
  return Path(path)


def refuse_broken_links_to(path: Path) -> None:
  """Raises FileNotFoundError naming the link where `path`, missing, is missing because it or
  a folder above it is a link to nothing (storage not mounted); else does nothing."""
  part = Path(path)
  while not part.exists() and part != part.parent:
    refuse_broken_links([part])
    part = part.parent


def _nested_hint(path: Path, most: int = 1000) -> str:
  """`"; X/... exists one level deeper: ..."` where the missing part of `path` (all of it,
  below the deepest existing folder A) is there in a sub-folder X of A, else "" (also where
  a folder cannot be read: a hint never raises; at most `most` sub-folders are looked at)."""
  missing = []
  while not path.is_dir() and path != path.parent:
    missing.append(path.name)
    path = path.parent
  if not missing:
    return ""
  tail = Path(*reversed(missing))
  try:
    for i, sub in enumerate(sorted(path.iterdir())):
      if i >= most:
        break
      try:
        found = not is_hidden(sub) and (sub / tail).is_dir()
      except OSError:  # e.g. a lost+found folder only its owner can read
        found = False
      if found:
        return (f"; {sub / missing[-1]} exists one level deeper: is the dataset in an extra "
                f"folder (as some archives unpack)? Pass {sub} as its folder")
  except OSError:
    pass
  return ""


def natural_key(path: Path) -> tuple:
  """Sort key of a file name with its numbers compared by value: `f2` before `f10`, and
  decimal timestamps too (`1701.25` before `1701.5`); for zero-padded names the same order
  as plain sorting."""
  parts = re.split(r"(\d+(?:\.\d+)?)", Path(path).name)
  return tuple((0, decimal.Decimal(t), t) if i % 2 else (1, t, "")
               for i, t in enumerate(parts) if t)


def some_of(names: Sequence[str], most: int = 6) -> str:
  """`"a, b, c"`, or the first `most` names and `"... (N more)"`: a list for a log line."""
  names = [str(n) for n in names]
  shown = ", ".join(names[:most])
  return shown + (f", ... ({len(names) - most} more)" if len(names) > most else "")


def is_hidden(path: Path) -> bool:
  """Names starting with a dot (`.DS_Store`, macOS `._0001.png` copies, `.ipynb_checkpoints`),
  which a shell glob and the official loaders skip, and the `__MACOSX` folder of a zip made
  on macOS (its `._*` resource copies of the archive's files)."""
  name = Path(path).name
  return name.startswith(".") or name == "__MACOSX"


def list_files(directory: Path, *suffixes: str) -> list[Path]:
  """Files of `directory` with one of `suffixes` (e.g. ".png"), in natural name order
  (`natural_key`), hidden ones left out."""
  require_dir(directory)
  files = [p for p in Path(directory).iterdir() if p.suffix.lower() in suffixes and not is_hidden(p)]
  refuse_broken_links(files)  # left out, it would show only as a frame count that differs
  return sorted((p for p in files if p.is_file()), key=natural_key)


def list_dirs(directory: Path) -> list[Path]:
  """Sub-directories of `directory`, sorted by name, hidden ones left out."""
  require_dir(directory)
  entries = [p for p in Path(directory).iterdir() if not is_hidden(p)]
  refuse_broken_links(entries)  # left out, a sequence would vanish from an evaluation
  return sorted(p for p in entries if p.is_dir())


def refuse_broken_links(paths: Sequence[Path]) -> None:
  """Raises FileNotFoundError naming the first of `paths` that is a link to nothing."""
  broken = [p for p in paths if p.is_symlink() and not p.exists()]
  if broken:  # a missing target, or a loop of links
    raise FileNotFoundError(f"{broken[0]}: a symbolic link to a missing file or folder, or a "
                            f"loop of links ({os.readlink(broken[0])})")


def digits_key(path: Path) -> int | str:
  """The last integer in a file stem, the frame number: `rgb_00012`, `depth_00012`
  and `disp1_left_0012` all give 12 (the stem itself when it has no digits)."""
  groups = re.findall(r"\d+", Path(path).stem)
  return int(groups[-1]) if groups else Path(path).stem


def number_key(path: Path):
  """The frame number that matches files across folders: `digits_key`, but a decimal
  number whole (`1701234567.000000`: `digits_key` gives 0 for every such timestamp, so a
  right/ folder one frame ahead of left/ was paired with it)."""
  numbers = re.findall(r"\d+\.\d+|\d+", Path(path).stem)
  if numbers and "." in numbers[-1]:
    return decimal.Decimal(numbers[-1])
  return digits_key(path)


def check_matching(where: str, lists: Mapping[str, Sequence[Path]],
                   key: Callable[[Path], object] = lambda p: p.stem) -> None:
  """Raises ValueError unless all lists have the same length and frame keys.

  Args:
    where: sequence description for the message.
    lists: file lists by kind, matched by index (as the official loaders do).
    key: the frame key that must agree across kinds (default: the file stem).
  """
  counts = {k: len(v) for k, v in lists.items()}
  if len(set(counts.values())) != 1:
    raise ValueError(f"{where}: frame counts differ: {counts}" + _missing_frame(lists, key))
  names = list(lists)
  if counts[names[0]] == 0:
    raise FileNotFoundError(f"{where}: no frames found")
  for other in names[1:]:
    for a, b in zip(lists[names[0]], lists[other]):
      if key(a) != key(b):
        raise ValueError(f"{where}: stem mismatch between {a} and {b}")
  warn_if_gaps(where, lists[names[0]])


def warn_if_gaps(where: str, files: Sequence,
                 number: Callable[[Path], object] = digits_key) -> None:
  """Logs a warning where a sequence's frame numbers (`number` of each file, increasing) step
  by more than their smallest step: a frame missing from every folder (a partial download)
  would otherwise make its two neighbours look consecutive to the temporal metrics and the
  training clips. Names without increasing numbers (e.g. a camera index last) are passed.
  `files` may also be other items (frame records' numbers), shown as they are."""
  numbers = [number(p) for p in files]
  if len(numbers) < 3 or not all(isinstance(n, int) for n in numbers):
    return
  steps = [b - a for a, b in zip(numbers, numbers[1:])]
  usual = min(steps)
  if usual <= 0:
    return  # not frame numbers
  gaps = [i for i, step in enumerate(steps) if step != usual]
  if gaps:
    i = gaps[0]
    log.warning("%s: frame numbers are not evenly spaced: %d gap(s), the first after %s "
                "(next %s; usually +%d: a frame missing?); the frames are read as "
                "consecutive", where, len(gaps), getattr(files[i], "name", files[i]),
                getattr(files[i + 1], "name", files[i + 1]), usual)


def _missing_frame(lists: Mapping[str, Sequence[Path]], key: Callable[[Path], object]) -> str:
  """`"; e.g. 'right_gt' lacks frame 2 (left_gt has .../depth_00002.png)"`: the first frame
  key one list lacks that another has (the files are matched by key)."""
  keyed = {kind: {key(p): p for p in files} for kind, files in lists.items()}
  for kind, have in keyed.items():
    for other, theirs in keyed.items():
      missing = [k for k in theirs if k not in have]
      if other != kind and missing:
        return f"; e.g. {kind!r} lacks frame {missing[0]!r} ({other} has {theirs[missing[0]]})"
  return ""


def sceneflow_clips(n: int, frames: int) -> list[list[int]]:
  """SceneFlow training clips: for ref in 0..n-frames-1 (n - frames excluded) a forward
  clip `[ref, ref + frames)` and the time-reversed `n-1-ref, ..., n-ref-frames`."""
  clips = []
  for ref in range(n - frames):
    clips.append(list(range(ref, ref + frames)))
    clips.append([n - 1 - idx for idx in range(ref, ref + frames)])
  return clips


def strided_clips(n: int, frames: int, rng: np.random.Generator) -> list[list[int]]:
  """DR / Infinigen / KITTI / VKITTI2 training clips: starts 0, 3, 6, ...; each start
  draws a stride k in 1..5 (k = 1 when frames == 1), kept when start + k*frames < n."""
  clips = []
  for ref in range(0, n, 3):
    k = 1 if frames == 1 else int(rng.integers(1, 6))
    if ref + k * frames < n:
      clips.append(list(range(ref, ref + k * frames, k)))
  return clips

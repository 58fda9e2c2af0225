"""Your own stereo videos: one folder per sequence, ground truth optional (registry "folder").

Layout (root = the dataset's folder, given as `data.root` / `--data-root`):

  <split>/<sequence>/left/*.png|jpg       rectified left frames
  <split>/<sequence>/right/*.png|jpg      right frames
  <split>/<sequence>/disparity/*          optional: the left view's disparity (px), one file
                                          per frame: .png (16-bit, KITTI's d * 256, 0 = no
                                          ground truth), .pfm, .npy or .exr (0, non-finite
                                          and |d| >= 512 px: none)
  <split>/<sequence>/calib.txt|json       optional: fx and baseline (`sav-jax infer --calib`'s
                                          formats, checked against the frames' size as
                                          there), for depth and TCC

Splits are the folders `train`, `val` and `test` that exist. Frames of the three folders are
matched by the last number in their names (`left_0001.png`, `right_0001.png`, `0001.pfm`), so
each folder needs the same frame numbers; files are in natural name order (`2.png` before
`10.png`). A disparity folder
of 16-bit PNGs is sparse ground truth (KITTI's LiDAR convention: the sparse augmentation keeps
its valid mask); the float formats are dense. Training clips are sampled as the official
Dynamic Replica clips (starts 0, 3, 6, ..., a stride of 1-5 frames drawn per start);
evaluation takes whole sequences.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

from sav_jax import viz
from sav_jax.data import frame_io
from sav_jax.data.base import (StereoSequence, camera_scale, check_matching, is_hidden,
                               list_dirs, list_files, number_key, refuse_broken_links,
                               require_dir, some_of)

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DISPARITY_SUFFIXES = (".png", ".pfm", ".npy", ".exr")
CALIBRATION_FILES = ("calib.txt", "calib.json")


class FolderSequence(StereoSequence):
  """A sequence of `load_sequences`: disparity decoded by its file's suffix."""

  def _read_gt(self, i: int, side: str) -> tuple[np.ndarray, np.ndarray]:
    path = self.files[side + "_gt"][i]
    return read_disparity(path)


def read_disparity(path: Path) -> tuple[np.ndarray, np.ndarray]:
  """`(disparity [H, W] float32 px, valid [H, W] bool)` of one ground-truth file, by suffix:
  a 16-bit PNG as KITTI's (d * 256, 0 = none), PFM/NPY/EXR as float pixels (channel 0 of a
  multi-channel PFM; valid where finite, non-zero and below 512 px, the official rule)."""
  suffix = Path(path).suffix.lower()
  if suffix == ".png":
    return viz.read_png16(path)
  if suffix == ".pfm":
    disp = frame_io.read_pfm_disparity(path)
  elif suffix == ".npy":
    disp = frame_io.read_npy(path)
  elif suffix == ".exr":
    disp = frame_io.read_exr(path)
  else:
    raise ValueError(f"{path}: unknown disparity format {suffix!r}; expected one of "
                     f"{', '.join(DISPARITY_SUFFIXES)}")
  disp = np.asarray(disp)
  if disp.ndim != 2 or disp.dtype.kind not in "iuf" or disp.dtype == bool:
    raise ValueError(f"{path}: disparity of shape {disp.shape} and dtype {disp.dtype}; "
                     "expected one channel [H, W] of numbers (pixels)")
  disp = disp.astype(np.float32)
  valid = frame_io.dense_valid(disp)  # (False for NaN and inf too)
  _warn_if_out_of_range(path, disp, valid)
  _warn_if_negative(path, disp, valid)
  return np.where(valid, disp, 0.0).astype(np.float32), valid


_RANGE_WARNED: set[str] = set()
_NEGATIVE_WARNED: set[str] = set()


def _warn_if_negative(path: Path, disp: np.ndarray, valid: np.ndarray) -> None:
  """Warns (once per folder) where a file holds negative disparities: the official rule
  counts them as ground truth (the metrics take |d|), so a "no data" code such as -1 was
  scored silently as a disparity of 1 px."""
  folder = str(Path(path).parent)
  negative = int(np.count_nonzero(valid & (disp < 0)))
  if folder in _NEGATIVE_WARNED or not negative:
    return
  _NEGATIVE_WARNED.add(folder)
  share = 100 * negative / np.count_nonzero(valid)  # (a few pixels: 0.3%, not "0%")
  warnings.warn(f"{path}: {f'{share:.0f}' if share >= 1 else f'{share:.1g}'}% of its valid "
                f"disparities are negative (min {float(disp[valid].min()):g}), which the "
                "official rule counts as ground truth (the metrics take |d|): mark pixels "
                "without ground truth 0 or NaN, not with a negative code such as -1; "
                "disparities are x_left - x_right, positive (this is said once per folder)",
                stacklevel=2)


def _warn_if_out_of_range(path: Path, disp: np.ndarray, valid: np.ndarray) -> None:
  """Warns (once per folder) where most of a file's finite non-zero disparities are 512 px
  or more: the official rule leaves them out, so a folder of disparities in other units
  (KITTI's d * 256 saved as floats, 1/16 px, depth) trained and scored on its few small
  values only (a frame without any: a loss of 0, read as an EPE of 0)."""
  folder = str(Path(path).parent)
  if folder in _RANGE_WARNED:
    return
  given = np.isfinite(disp) & (disp != 0)
  large = int(np.count_nonzero(given & ~valid))
  if large * 2 <= int(np.count_nonzero(given)):
    return
  _RANGE_WARNED.add(folder)
  warnings.warn(f"{path}: {100 * large / np.count_nonzero(given):.0f}% of its non-zero "
                f"disparities are {frame_io.MAX_DISPARITY:g} px or more (max "
                f"{float(np.nanmax(np.where(given, np.abs(disp), 0))):g}), which the official "
                f"rule leaves out (valid: 0 < |d| < {frame_io.MAX_DISPARITY:g} px): is it in "
                "pixels (not d * 256, 1/16 px or depth)? Training and the metrics use the "
                "rest only (this is said once per folder)", stacklevel=2)


def load_sequences(root, split: str = "test", dataset: str = "folder") -> list[StereoSequence]:
  """The sequences of `root/<split>`, sorted by name.

  Args:
    root: the dataset's folder (it holds `train/`, `val/`, `test/`).
    split: "train", "val" or "test".
    dataset: registry name recorded on the sequences.

  Raises:
    FileNotFoundError: no such split folder, or no sequence in it (naming the folder).
    ValueError: frames that do not match across `left/`, `right/` and `disparity/`, mixed
      disparity formats, or a calibration file without fx and baseline (naming the file).
  """
  if split not in SPLITS:
    raise ValueError(f"folder dataset split must be one of {SPLITS}, got {split!r}")
  root = require_dir(Path(root).expanduser(), "dataset folder")
  split_dir = root / split
  if not split_dir.is_dir():
    found = [s for s in SPLITS if (root / s).is_dir()]
    raise FileNotFoundError(f"no {split}/ folder in {root} (it has {', '.join(found) or 'none'} "
                            f"of {', '.join(SPLITS)}): the layout is <split>/<sequence>/left, "
                            f"right[, disparity]{_root_hint(root, split)}")
  seqs = []
  for seq_dir in list_dirs(split_dir):
    where = f"{dataset} {split}/{seq_dir.name}"
    if not (seq_dir / "left").is_dir():
      raise FileNotFoundError(f"{seq_dir}: no left/ folder (a sequence folder holds left/, "
                              "right/ and optionally disparity/)")
    files = {"left": list_files(seq_dir / "left", *IMAGE_SUFFIXES),  # by number: 2 before 10
             "right": list_files(require_dir(seq_dir / "right", "right/ folder"),
                                 *IMAGE_SUFFIXES)}
    for side in ("left", "right"):
      if not files[side]:  # (a video file there was "frame counts differ: 'left' lacks frame 1")
        other = sorted(p.name for p in (seq_dir / side).iterdir() if not is_hidden(p))
        videos = any(Path(n).suffix.lower() in viz.VIDEO_SUFFIXES for n in other)
        hint = ("video files are not read, extract their frames" if videos else
                f"frames are read from {', '.join(IMAGE_SUFFIXES)} files")
        raise FileNotFoundError(f"{seq_dir / side}: no PNG or JPEG frames"
                                + (f" (it has {some_of(other)}: {hint})" if other else ""))
    sparse = False
    # a link to a missing disparity/ or calibration file: the sequence read without them
    refuse_broken_links([seq_dir / "disparity", *(seq_dir / n for n in CALIBRATION_FILES)])
    if (seq_dir / "disparity").is_dir():
      gt = list_files(seq_dir / "disparity", *DISPARITY_SUFFIXES)
      if not gt:  # (was "frame counts differ: 'left_gt' lacks frame 0", the folder unnamed)
        other = sorted(p.name for p in (seq_dir / "disparity").iterdir() if not is_hidden(p))
        raise FileNotFoundError(f"{seq_dir / 'disparity'}: no disparity files (expected "
                                f"{', '.join(DISPARITY_SUFFIXES)}"
                                + (f"; it has {some_of(other)})" if other else ")"))
      kinds = sorted({p.suffix.lower() for p in gt})
      if len(kinds) > 1:
        raise ValueError(f"{seq_dir / 'disparity'}: disparity files of several formats "
                         f"({', '.join(kinds)}); use one")
      files["left_gt"] = gt
      sparse = kinds == [".png"]
    for paths in files.values():
      _refuse_repeated_frames(paths)
    check_matching(where, files, number_key)
    seqs.append(FolderSequence(seq_dir.name, files, dataset=dataset, sparse=sparse,
                               depth2disp_scale=_scale(seq_dir, files["left"])))
  if not seqs:
    raise FileNotFoundError(f"no sequences in {split_dir} (expected <sequence>/left, right "
                            "folders)")
  return seqs


def _refuse_repeated_frames(paths: list[Path]) -> None:
  """Raises ValueError naming two files of one folder with the same frame number (`0001.png`
  beside `0001.jpg`, or `1.png`): each frame was read twice, as two consecutive frames,
  without a word. A number shared by every file (`clip_v2.png`) is no frame number: passed."""
  keys = [number_key(p) for p in paths]
  if len(set(keys)) == 1 and len({p.stem for p in paths}) == len(paths):
    return
  seen = {}
  for path, key in zip(paths, keys):
    if key in seen:
      raise ValueError(f"{path.parent}: {seen[key].name} and {path.name} are both frame "
                       f"{key} (frames are matched by the last number in their names); keep "
                       "one file per frame")
    seen[key] = path


def _root_hint(root: Path, split: str) -> str:
  """What a root without the split's folder is, where it looks like one level of the layout:
  a sequence (left/ in it), or a folder of sequences (a split's, or to be put in one)."""
  if (root / "left").is_dir():
    return (f"; {root} is a sequence: give the dataset's folder, {root.parent.parent}"
            if root.parent.name in SPLITS else
            f"; {root} is a sequence: put it in {root.parent}/{split}/ and give {root.parent}")
  if any((d / "left").is_dir() for d in list_dirs(root)):
    return (f"; {root} holds the sequences: give the folder above it, {root.parent}"
            if root.name in SPLITS else
            f"; {root} holds the sequences: put them in {root}/{split}/")
  return ""


def _scale(seq_dir: Path, left: list[Path]) -> float | None:
  """fx * baseline from the sequence's calibration file, or None without one; a file for
  another image size than the `left` frames' is refused, as `sav-jax infer --calib` refuses
  it (its width/height, or a principal point outside the frames). Both `calib.txt` and
  `calib.json` may be there only when they give the same scale."""
  scales = {path: _file_scale(path, left) for path in (seq_dir / n for n in CALIBRATION_FILES)
            if path.is_file()}
  if len(set(scales.values())) > 1:  # (one was read silently, the other left unread)
    given = ", ".join("none (doffs)" if v is None else f"{v:g}" for v in scales.values())
    raise ValueError(f"{seq_dir}: {' and '.join(p.name for p in scales)} give different "
                     f"depth-to-disparity scales (fx * baseline: {given}); keep one "
                     "calibration file")
  return next(iter(scales.values()), None)


def _file_scale(path: Path, left: list[Path]) -> float | None:
  """`_scale` of one calibration file."""
  from sav_jax.tools import UsageError  # pylint: disable=import-outside-toplevel
  from sav_jax.tools.infer import (CalibrationSpec,  # pylint: disable=import-outside-toplevel
                                   read_calibration)
  try:
    calib = read_calibration(path)
  except UsageError as e:  # a malformed line, no calibration in it: it names the file
    raise ValueError(str(e)) from None
  missing = [k for k in ("fx", "baseline") if k not in calib]
  if missing:
    raise ValueError(f"{path}: no {' and no '.join(missing)} (the depth-to-disparity scale "
                     "is fx * baseline)")
  if left and any(k in calib for k in ("width", "height", "cx", "cy")):
    height, width = frame_io.read_image(left[0]).shape[:2]
    try:  # (fx for frames of another size would scale every depth: TCC and the rest change)
      CalibrationSpec.from_mapping(calib).resolve(width, height)
    except UsageError as e:
      raise ValueError(f"{path}: {e} (the first frame: {left[0]})") from None
  if calib.get("doffs"):  # depth = fx B / (d + doffs): no single depth-to-disparity scale
    log.warning("%s: doffs %g px: depth is not fx * baseline / disparity, so the sequence "
                "gets no depth metrics (TCC); its disparity metrics are unaffected", path,
                calib["doffs"])
    return None
  return camera_scale(calib["fx"], calib["baseline"], path)

"""SceneFlow (FlyingThings3D, Monkaa, Driving): PFM disparity, the SAV training set.

Layout under the root (the folder holding the three subsets, or one subset's own
folder when a single subset is asked for):

  FlyingThings3D/<pass>/{TRAIN,TEST}/<A|B|C>/<seq>/{left,right}/*.png
  Monkaa/<pass>/<seq>/{left,right}/*.png
  Driving/<pass>/<focal>/<direction>/<speed>/{left,right}/*.png

with `<pass>` = `frames_finalpass` (SAV trains on the final pass only) and the GT in
the same tree with `<pass>` replaced by `disparity` (`*.pfm`, positive pixels). The
valid mask is the dense rule `0 < |d| < 512`. Splits: `train` (Things TRAIN + Monkaa +
Driving) and `test` (Things TEST, which SAV does not evaluate).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sav_jax.data import frame_io
from sav_jax.data.base import (StereoSequence, check_matching, find_root, list_dirs, list_files,
                               refuse_broken_links, require_dir)

SUBSETS = ("FlyingThings3D", "Monkaa", "Driving")
SPLITS = ("train", "test")
DEFAULT_PASS = "frames_finalpass"
# Directory depth of the sequence folders below <pass> (Things adds the split level).
_SEQ_DEPTH = {"FlyingThings3D": 2, "Monkaa": 1, "Driving": 3}


class SceneFlowSequence(StereoSequence):
  """A SceneFlow sequence; GT files are PFM disparities."""

  def _read_gt(self, i: int, side: str):
    disp = frame_io.read_pfm_disparity(self.files[side + "_gt"][i])
    valid = frame_io.dense_valid(disp)  # NaN/inf are invalid, and 0 as every reader has them
    return np.where(np.isfinite(disp), disp, np.float32(0)), valid


def _sequence(subset: str, seq_dir: Path, pass_dir: Path, dataset: str) -> SceneFlowSequence:
  """Reads one `<seq>/{left,right}` folder and its disparity twin."""
  gt_dir = pass_dir.parent / "disparity" / seq_dir.relative_to(pass_dir)
  name = f"{subset}/{seq_dir.relative_to(pass_dir).as_posix()}"
  left = list_files(seq_dir / "left", ".png")
  if not left and list_files(seq_dir / "left", ".webp"):
    raise FileNotFoundError(_webp(seq_dir / "left"))
  files = {"left": left,
           "right": list_files(seq_dir / "right", ".png"),
           "left_gt": list_files(require_dir(gt_dir / "left", "disparity folder"), ".pfm")}
  if (gt_dir / "right").is_dir():
    files["right_gt"] = list_files(gt_dir / "right", ".pfm")
  check_matching(f"SceneFlow {name}", files)
  return SceneFlowSequence(name, files, dataset=dataset)


def _webp(where: Path) -> str:
  """The message for frames from SceneFlow's WebP archives."""
  return (f"{where}: WebP frames (SceneFlow's lossy *_webp archives); the readers take the PNG "
          "archives' frames (frames_finalpass/, *.png), which SAV trains on")


def _subset_sequences(root: Path, subset: str, split: str, pass_name: str,
                      dataset: str) -> list[SceneFlowSequence]:
  sub_root = root if root.name == subset else root / subset
  if not (sub_root / pass_name).exists() and (sub_root / f"{pass_name}_webp").is_dir():
    raise FileNotFoundError(_webp(sub_root / f"{pass_name}_webp"))
  pass_dir = require_dir(sub_root / pass_name, f"{subset} {pass_name} folder")
  base = pass_dir / ("TEST" if split == "test" else "TRAIN") if subset == "FlyingThings3D" \
      else pass_dir
  # A sequence folder is any folder at the subset's depth that holds `left/`; list_dirs
  # refuses a link to a missing folder on the way (a glob left that sequence out silently).
  level = [require_dir(base)]
  for _ in range(_SEQ_DEPTH[subset]):
    level = [d for parent in level for d in list_dirs(parent)]
  refuse_broken_links([d / "left" for d in level])
  seq_dirs = sorted(d for d in level if (d / "left").is_dir())
  # A sequence with its right views but no left/ (a half-extracted archive) would be left out
  # silently by the official glob over left/; here it is named.
  no_left = sorted(str(d) for d in level if (d / "right").is_dir() and not (d / "left").is_dir())
  if no_left:
    raise FileNotFoundError(f"{subset} sequence folder(s) with right/ but no left/ (an "
                            f"incomplete extraction?): {', '.join(no_left)}")
  if not seq_dirs:
    raise FileNotFoundError(f"no {subset} sequences (<seq>/left/) under {base}")
  return [_sequence(subset, d, pass_dir, dataset) for d in seq_dirs]


def load_sequences(root, split: str, subsets: tuple[str, ...] = SUBSETS,
                   pass_name: str = DEFAULT_PASS, dataset: str = "sceneflow"):
  """SceneFlow sequences of `split` from the chosen subsets, in subset order.

  Args:
    root: folder holding the subsets (or the one subset's own folder).
    split: "train" or "test" (only FlyingThings3D has a test split).
    subsets: any of `SUBSETS`.
    pass_name: "frames_finalpass" (SAV) or "frames_cleanpass".
    dataset: registry name recorded on the sequences.

  Returns:
    list of `SceneFlowSequence`.
  """
  if split not in SPLITS:
    raise ValueError(f"SceneFlow split must be one of {SPLITS}, got {split!r}")
  if split == "test" and "FlyingThings3D" not in subsets:
    raise ValueError(f"{'/'.join(subsets)} has no test split (only FlyingThings3D does)")
  if split == "test":
    subsets = ("FlyingThings3D",)
  seqs = []
  for subset in subsets:
    sub_root = find_root(root, subset)
    seqs += _subset_sequences(sub_root, subset, split, pass_name, dataset)
  return seqs

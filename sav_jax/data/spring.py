"""Spring: HDF5 (`.dsp5`) disparity at twice the image resolution.

Layouts (root = the `Spring` folder or its parent); the first is what SAV's code
expects, the second is the one the Spring download unpacks to:

  train_frame_{left,right}/<seq>/frame_{left,right}/*.png
  train_disp1_left/<seq>/disp1_left/*.dsp5
  train_cam_data/<seq>/cam_data/intrinsics.txt        one `fx fy cx cy` row per frame

  train/<seq>/{frame_left,frame_right,disp1_left,cam_data}/...

A `.dsp5` holds dataset `disparity` at 2x resolution per axis with NaN where unknown;
the standard subsampling `[::2, ::2]` is applied and values are used as stored.
Valid = finite and the official dense rule `0 < |d| < 512` (SAV's code cannot read
`.dsp5`, so its Spring protocol is unknown; every other dense dataset gets this rule there,
and it keeps d = 0 (infinitely far) out of the depth metrics); invalid pixels get d = 0.
Scale: fx of the first intrinsics row times 0.065 m. Only the train half has GT: "test"
(SAV's name) and "train" both read it. Only the left GT is used.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from sav_jax.data import frame_io
from sav_jax.data.base import (StereoSequence, camera_scale, check_matching, digits_key, find_root,
                               list_dirs, list_files, refuse_broken_links)

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("Spring", "spring")

SPLITS = ("test", "train")
BASELINE_M = 0.065


class SpringSequence(StereoSequence):
  """A Spring sequence; GT is the left `.dsp5` disparity, subsampled to image size."""

  def _read_gt(self, i: int, side: str):
    disp = frame_io.read_dsp5(self.files[side + "_gt"][i])[::2, ::2]
    disp = np.where(np.isfinite(disp), disp, np.float32(0))
    return disp, frame_io.dense_valid(disp)


def read_fx(path: Path) -> float:
  """fx of the first row of a Spring `intrinsics.txt`."""
  text = frame_io.read_text(path, "Spring intrinsics")
  try:
    return float(np.loadtxt(io.StringIO(text), ndmin=2)[0, 0])
  except (ValueError, IndexError) as e:
    raise ValueError(f"malformed Spring intrinsics: {path}") from e


def _layout(root: Path):
  """Sequence names and a function seq -> its four folders."""
  refuse_broken_links([root / "train_frame_left", root / "train"])  # (not "no Spring data")
  if (root / "train_frame_left").is_dir() and (root / "train").is_dir():
    raise ValueError(f"Spring data under {root} in two layouts: train_frame_left/ (and its "
                     "train_* siblings) and train/<seq>/; keep one (the other's sequences "
                     "would be left out)")
  if (root / "train_frame_left").is_dir():
    names = [d.name for d in list_dirs(root / "train_frame_left")]
    def dirs(seq):
      return (root / "train_frame_left" / seq / "frame_left",
              root / "train_frame_right" / seq / "frame_right",
              root / "train_disp1_left" / seq / "disp1_left",
              root / "train_cam_data" / seq / "cam_data")
  elif (root / "train").is_dir():
    names = [d.name for d in list_dirs(root / "train")]
    def dirs(seq):
      base = root / "train" / seq
      return (base / "frame_left", base / "frame_right", base / "disp1_left",
              base / "cam_data")
  else:
    raise FileNotFoundError(f"no Spring data under {root}: neither train_frame_left/ "
                            "nor train/ exists")
  return names, dirs


def load_sequences(root, split: str, dataset: str = "spring"):
  """Spring sequences (the train half, which has GT), sorted by name.

  Args:
    root: the `Spring` folder or its parent.
    split: "test" or "train" (the same sequences).
    dataset: registry name recorded on the sequences.

  Returns:
    list of `SpringSequence` (dense; left GT only).
  """
  if split not in SPLITS:
    raise ValueError(f"Spring split must be one of {SPLITS}, got {split!r}")
  root = find_root(root, *FOLDERS)
  names, dirs = _layout(root)
  seqs = []
  for name in names:
    left, right, disp, cam = dirs(name)
    files = {"left": list_files(left, ".png"), "right": list_files(right, ".png"),
             "left_gt": list_files(disp, ".dsp5")}
    check_matching(f"Spring {name}", files, digits_key)
    scale = camera_scale(read_fx(cam / "intrinsics.txt"), BASELINE_M, cam / "intrinsics.txt")
    seqs.append(SpringSequence(name, files, dataset=dataset, depth2disp_scale=scale))
  if not seqs:
    raise FileNotFoundError(f"no Spring sequences under {root}")
  return seqs

"""MPI Sintel stereo (clean and final passes): sparse-masked PNG disparity.

Layout (root = the `sintel_stereo` folder or its parent):

  training/{clean,final}_{left,right}/<seq>/frame_XXXX.png
  training/disparities/<seq>/frame_XXXX.png     d = 4 R + G / 2**6 + B / 2**14
  training/occlusions/<seq>/frame_XXXX.png      valid = (occlusion == 0) & (d > 0)
  training/camdata_left/<seq>/frame_XXXX.cam    depth2disp scale = K[0, 0] * 0.1 m

Only the `training` half has GT. SAV evaluates every frame of every sequence (split
"test"); "train" reads the same sequences (for fine-tuning). Image, disparity,
occlusion and camera stems must match. There is no right-view GT.
"""

from __future__ import annotations

from sav_jax.data import frame_io
from sav_jax.data.base import (StereoSequence, camera_scale, check_matching, find_root, list_dirs,
                               list_files)

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("sintel_stereo",)

PASSES = ("clean", "final")
SPLITS = ("test", "train")
# Sintel's stereo rig: 10 cm baseline (dataset website; hard-coded in the official code).
BASELINE_M = 0.1


class SintelSequence(StereoSequence):
  """A Sintel sequence; GT is the disparity PNG plus the occlusion PNG."""

  def _read_gt(self, i: int, side: str):
    return frame_io.read_sintel_disparity(self.files["left_gt"][i], self.files["left_occ"][i])


def load_sequences(root, split: str, dstype: str = "final", dataset: str | None = None):
  """Sintel stereo sequences of one pass.

  Args:
    root: the `sintel_stereo` folder or its parent.
    split: "test" (what SAV evaluates) or "train"; both read `training/`.
    dstype: "clean" or "final".
    dataset: registry name recorded on the sequences (default `sintel_<dstype>`).

  Returns:
    list of `SintelSequence` (sparse, depth2disp scale from the first .cam file).
  """
  if split not in SPLITS:
    raise ValueError(f"Sintel split must be one of {SPLITS}, got {split!r}")
  if dstype not in PASSES:
    raise ValueError(f"Sintel pass must be one of {PASSES}, got {dstype!r}")
  dataset = dataset or f"sintel_{dstype}"
  train = find_root(root, *FOLDERS) / "training"
  seqs = []
  for seq_dir in list_dirs(train / f"{dstype}_left"):
    name = seq_dir.name
    files = {"left": list_files(seq_dir, ".png"),
             "right": list_files(train / f"{dstype}_right" / name, ".png"),
             "left_gt": list_files(train / "disparities" / name, ".png"),
             "left_occ": list_files(train / "occlusions" / name, ".png"),
             "camera": list_files(train / "camdata_left" / name, ".cam")}
    check_matching(f"Sintel {dstype}/{name}", files)
    k, _ = frame_io.read_sintel_cam(files["camera"][0])
    scale = camera_scale(k[0, 0], BASELINE_M, files["camera"][0])
    seqs.append(SintelSequence(name, files, dataset=dataset, depth2disp_scale=scale,
                               sparse=True))
  if not seqs:
    raise FileNotFoundError(f"no Sintel sequences in {train / (dstype + '_left')}")
  return seqs

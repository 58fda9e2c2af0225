"""Infinigen SV (InfinigenStereo): npy depth and Blender camera npz per frame.

Layout (root = the `InfinigenStereo` folder or its parent):

  <split>/<scene>/frames/Image/camera_{0,1}/Image_<rig>_<resample>_<frame>_<subcam>.png
  <split>/<scene>/frames/Depth/camera_{0,1}/Depth_<...>.npy      metres
  <split>/<scene>/frames/camview/camera_{0,1}/camview_<...>.npz  K (3x3 px), T (4x4 pose)

camera_0 is the left view. The three sorted lists are matched by index (stems must
agree after the type prefix; left and right files must have the same frame number,
Infinigen's suffix order being cam_rig, resample, frame, subcam). Depth is used as
stored (units not confirmed; depth below 1e-5, NaN or inf is invalid). Scale:
`K_left[0, 0] * ||t_left - t_right||` from frame 0's camview files (a training clip's
from its first frame's, as the official loader). Splits (download script): test = scene001-030,
train = scene031-216, val = scene217-226, as folders.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sav_jax.data import frame_io
from sav_jax.data.base import (DepthSequence, camera_scale, check_matching, find_root, list_dirs,
                               list_files, warn_if_gaps)

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("InfinigenStereo",)

SPLITS = ("train", "test", "val")
_CAMERAS = {"left": "camera_0", "right": "camera_1"}


def frame_key(path: Path) -> str:
  """`Image_0_0_0048_0` -> `0_0_0048_0`: the stem without its type prefix."""
  return path.stem.split("_", 1)[-1]


def view_key(path: Path) -> str:
  """The frame number of an Infinigen stem `<type>_<cam_rig>_<resample>_<frame>_<subcam>`
  (`Image_0_0_0048_1` -> `0048`), which left and right files of one frame share (the
  camera is `subcam`, or `cam_rig` in multi-rig renders); other names are compared whole."""
  parts = frame_key(path).split("_")
  return parts[2] if len(parts) == 4 else "_".join(parts)


def _frame_number(path: Path) -> int | str:
  """`view_key` as an integer where it is one (the frame number)."""
  key = view_key(path)
  return int(key) if key.isdigit() else key


def _camview(path: Path) -> tuple[np.ndarray, np.ndarray]:
  """K ([3, 3]) and T ([4, 4] or [3, 4] camera-to-world) of a camview archive."""
  cam = frame_io.read_npz(path)
  if "K" not in cam or "T" not in cam:
    raise ValueError(f"{path}: camview npz lacks K or T (has {sorted(cam)})")
  k, t = np.asarray(cam["K"], np.float64), np.asarray(cam["T"], np.float64)
  if k.shape != (3, 3) or t.shape not in ((4, 4), (3, 4)):
    raise ValueError(f"{path}: camview npz has K of shape {k.shape} and T of shape {t.shape} "
                     "(expected a 3x3 K and a 4x4 or 3x4 T)")
  return k, t


def depth2disp_scale(left_path: Path, right_path: Path) -> float:
  """K_left[0, 0] * ||T_left[:3, 3] - T_right[:3, 3]|| from two camview archives."""
  (k, t_left), (_, t_right) = _camview(left_path), _camview(right_path)
  return camera_scale(float(k[0, 0]), float(np.linalg.norm(t_left[:3, 3] - t_right[:3, 3])),
                      f"{left_path} and {right_path}")


class InfinigenSequence(DepthSequence):
  """A `DepthSequence` whose training clips take the scale of their first frame's camview
  archives, as the official loader does (the sequence's own, for evaluation, is frame 0's)."""

  def clip_scale(self, start: int) -> float:
    if start == 0:
      return self.depth2disp_scale
    return depth2disp_scale(self.files["left_cam"][start], self.files["right_cam"][start])


def _scene(scene: Path, dataset: str) -> DepthSequence:
  where = f"Infinigen {scene.parent.name}/{scene.name}"
  files, cams = {}, {}
  for side, cam in _CAMERAS.items():
    lists = {side: list_files(scene / "frames" / "Image" / cam, ".png"),
             side + "_gt": list_files(scene / "frames" / "Depth" / cam, ".npy"),
             side + "_cam": list_files(scene / "frames" / "camview" / cam, ".npz")}
    check_matching(f"{where} {cam}", lists, frame_key)
    files.update(lists)
    cams[side] = lists[side + "_cam"]
  check_matching(where, {"left": files["left"], "right": files["right"]}, view_key)
  warn_if_gaps(where, files["left"], _frame_number)
  scale = depth2disp_scale(cams["left"][0], cams["right"][0])
  return InfinigenSequence(scene.name, files, dataset=dataset, depth2disp_scale=scale,
                           depth_reader=frame_io.read_depth_npy)


def load_sequences(root, split: str, dataset: str = "infinigen_sv"):
  """Infinigen SV scenes of `split`, sorted by name.

  Args:
    root: the `InfinigenStereo` folder or its parent.
    split: "train", "test" or "val".
    dataset: registry name recorded on the sequences.

  Returns:
    list of `DepthSequence` (dense; left and right GT).
  """
  if split not in SPLITS:
    raise ValueError(f"Infinigen SV split must be one of {SPLITS}, got {split!r}")
  split_dir = find_root(root, *FOLDERS) / split
  seqs = [_scene(scene, dataset) for scene in list_dirs(split_dir)]
  if not seqs:
    raise FileNotFoundError(f"no Infinigen SV scenes in {split_dir}")
  return seqs

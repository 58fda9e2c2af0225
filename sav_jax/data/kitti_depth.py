"""KITTI Depth: sparse LiDAR depth PNGs on the raw KITTI drives (CODD splits).

Layout (root = the `kitti_depth` folder or its parent):

  gt_depth/<drive>_sync/proj_depth/groundtruth/image_0{2,3}/<id>.png   Z = v / 256 m
    (or gt_depth/{train,val}/<drive>_sync/..., as data_depth_annotated.zip unpacks)
  input/<date>/<drive>_sync/image_0{2,3}/data/<id>.png                 found by GT name
  input/<date>/calib_cam_to_cam.txt

image_02 is left. The GT is sparse (v = 0: no point; frames start at raw index 5);
valid = (d < 512) & (Z >= 1e-5). Scale: `P_rect_02[0, 0] * ||T_02 - T_03||`.
Splits (following CODD, as the official code): "test" = the 13 drives of `TEST`,
"val" = `VAL`, "train" = every other drive present in `gt_depth/`; a training drive
whose raw images (`input/<date>/<drive>_sync/`) are absent is skipped with a warning, as
the official loader does.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from sav_jax.data import frame_io
from sav_jax.data.base import (DepthSequence, camera_scale, check_matching, find_root,
                               list_dirs, list_files, refuse_broken_links_to, require_dir,
                               some_of)

log = logging.getLogger(__name__)

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("kitti_depth",)

SPLITS = ("train", "val", "test")
TEST = tuple(f"{d}_sync" for d in (
    "2011_09_26_drive_0002", "2011_09_26_drive_0005", "2011_09_26_drive_0013",
    "2011_09_26_drive_0020", "2011_09_26_drive_0023", "2011_09_26_drive_0036",
    "2011_09_26_drive_0079", "2011_09_26_drive_0095", "2011_09_26_drive_0113",
    "2011_09_28_drive_0037", "2011_09_29_drive_0026", "2011_09_30_drive_0016",
    "2011_10_03_drive_0047"))
VAL = ("2011_10_03_drive_0042_sync",)
# A raw KITTI drive's folder name, e.g. 2011_09_26_drive_0002_sync.
DRIVE_NAME = re.compile(r"\d{4}_\d{2}_\d{2}_drive_\d{4}_sync")
# The folders data_depth_annotated.zip unpacks the drives into (the KITTI depth benchmark's
# own train/val split, not CODD's): read as if merged.
ARCHIVE_SPLITS = ("train", "val")


def read_calib(path: Path) -> dict[str, np.ndarray]:
  """The numeric entries of a KITTI `calib_cam_to_cam.txt` (`key: v1 v2 ...`)."""
  calib = {}
  for line in frame_io.read_text(path, "KITTI calibration").splitlines():
    key, sep, value = line.partition(":")
    if not sep:
      continue
    try:
      calib[key.strip()] = np.array([float(x) for x in value.split()])
    except ValueError:
      continue  # e.g. `calib_time: 09-Jan-2012 13:57:47`
  return calib


def depth2disp_scale(calib_path: Path) -> float:
  """P_rect_02[0, 0] * ||T_02 - T_03|| (about 721 * 0.54)."""
  calib = read_calib(calib_path)
  missing = [k for k in ("P_rect_02", "T_02", "T_03") if k not in calib]
  if missing:
    raise ValueError(f"KITTI calibration {calib_path} lacks {missing}")
  sizes = {"P_rect_02": 12, "T_02": 3, "T_03": 3}
  wrong = [f"{k} has {calib[k].size} values, not {n}" for k, n in sizes.items()
           if calib[k].size != n]
  if wrong:
    raise ValueError(f"KITTI calibration {calib_path}: {'; '.join(wrong)}")
  return camera_scale(float(calib["P_rect_02"][0]),
                      float(np.linalg.norm(calib["T_02"] - calib["T_03"])), calib_path)


def _drive(root: Path, gt_drive: Path, dataset: str) -> DepthSequence:
  drive = gt_drive.name
  gt_dir = gt_drive / "proj_depth" / "groundtruth"
  image_dir = root / "input" / drive[:10] / drive
  files = {}
  for side, cam in (("left", "image_02"), ("right", "image_03")):
    gt = list_files(gt_dir / cam, ".png")
    files[side + "_gt"] = gt
    files[side] = [frame_io.require_file(image_dir / cam / "data" / p.name, "KITTI image")
                   for p in gt]
  check_matching(f"KITTI {drive}", {"left": files["left_gt"], "right": files["right_gt"]})
  scale = depth2disp_scale(root / "input" / drive[:10] / "calib_cam_to_cam.txt")
  return DepthSequence(drive, files, dataset=dataset, depth2disp_scale=scale,
                       depth_reader=frame_io.read_kitti_depth, sparse=True)


def split_drives(drives: list[str], split: str) -> list[str]:
  """The drives of `split` among `drives` (all present drives, sorted)."""
  if split == "test":
    return [d for d in drives if d in TEST]
  if split == "val":
    return [d for d in drives if d in VAL]
  return [d for d in drives if d not in TEST and d not in VAL]


def load_sequences(root, split: str, dataset: str = "kitti_depth"):
  """KITTI Depth drives of `split`, sorted by name.

  For "test" and "val" every listed drive must be present (FileNotFoundError
  otherwise), so evaluation numbers are never silently computed on a subset.

  Args:
    root: the `kitti_depth` folder or its parent.
    split: "train", "val" or "test".
    dataset: registry name recorded on the sequences.

  Returns:
    list of `DepthSequence` (sparse; left and right GT).
  """
  if split not in SPLITS:
    raise ValueError(f"KITTI Depth split must be one of {SPLITS}, got {split!r}")
  root = find_root(root, *FOLDERS)
  gt_root = require_dir(root / "gt_depth", "KITTI gt_depth folder")
  found = gt_drives(gt_root)
  drives = split_drives(sorted(found), split)
  expected = {"test": TEST, "val": VAL}.get(split, ())
  missing = sorted(set(expected) - set(drives))
  if missing:
    raise FileNotFoundError(f"KITTI Depth {split} drives missing from {gt_root}: {missing}")
  if split == "train":
    for d in drives:  # (a link to nothing is named, not taken for images not downloaded)
      refuse_broken_links_to(root / "input" / d[:10] / d)
    no_images = [d for d in drives if not (root / "input" / d[:10] / d).is_dir()]
    if no_images:  # one line for all of them
      log.warning("KITTI Depth: skipping %d training drive(s) without raw images under %s: "
                  "%s", len(no_images), root / "input", some_of(no_images))
      drives = [d for d in drives if d not in no_images]
      if not drives:
        raise FileNotFoundError(f"no KITTI Depth train drive has its raw images under "
                                f"{root / 'input'} (<date>/<drive>_sync/image_02/data/)")
  if not drives:
    raise FileNotFoundError(f"no KITTI Depth {split} drives in {gt_root}")
  return [_drive(root, found[d], dataset) for d in drives]


def gt_drives(gt_root: Path) -> dict[str, Path]:
  """The drive folders of `gt_root` (`gt_depth/`), by name: its `<date>_drive_<n>_sync`
  folders and those of its `train/` and `val/` folders (the archive's layout). Other
  folders are left out with a warning; a drive found twice is an error naming both."""
  found, other = {}, []
  for entry in list_dirs(gt_root):
    if entry.name in ARCHIVE_SPLITS:
      entries = list_dirs(entry)
    elif DRIVE_NAME.fullmatch(entry.name):
      entries = [entry]
    else:
      other.append(entry.name)
      continue
    for drive in entries:
      if not DRIVE_NAME.fullmatch(drive.name):
        other.append(f"{entry.name}/{drive.name}")
      elif drive.name in found:
        raise ValueError(f"KITTI Depth drive {drive.name} is in {gt_root} twice: "
                         f"{found[drive.name]} and {drive}; keep one")
      else:
        found[drive.name] = drive
  if other:
    log.warning("KITTI Depth: left out %d folder(s) of %s not named like a drive "
                "(<date>_drive_<n>_sync): %s", len(other), gt_root, some_of(other))
  return found

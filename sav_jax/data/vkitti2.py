"""Virtual KITTI 2: 16-bit centimetre depth PNGs, JPEG images, fixed 0.532725 m baseline.

Layout (root = the `vkitti2` folder or its parent):

  <SceneXX>/<variation>/frames/rgb/Camera_{0,1}/rgb_NNNNN.jpg
  <SceneXX>/<variation>/frames/depth/Camera_{0,1}/depth_NNNNN.png   Z = v / 100 m
  <SceneXX>/<variation>/intrinsic.txt   header, then `frame cameraID fx fy cx cy` rows

Camera_0 is left. Depth v = 0 is invalid; the sky saturates at 65535 (655.35 m, a
small valid disparity). Scale: fx of the first data row of `intrinsic.txt` times the
hard-coded 0.532725 m baseline. Splits as in the official code: "test" = the five
sequences of `TEST`, "train" = all 50 scene x variation pairs of `SCENES` and
`VARIATIONS` (including the test sequences, as the official list does).
"""

from __future__ import annotations

import logging
from pathlib import Path

from sav_jax.data import frame_io
from sav_jax.data.base import (DepthSequence, camera_scale, check_matching, digits_key, find_root,
                               list_files, refuse_broken_links_to, some_of)

log = logging.getLogger(__name__)

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("vkitti2",)

SPLITS = ("train", "test")
BASELINE_M = 0.532725
SCENES = ("Scene01", "Scene02", "Scene06", "Scene18", "Scene20")
VARIATIONS = ("15-deg-left", "15-deg-right", "30-deg-left", "30-deg-right", "clone", "fog",
              "morning", "overcast", "rain", "sunset")
TEST = ("Scene01_15-deg-left", "Scene02_30-deg-right", "Scene06_fog", "Scene18_morning",
        "Scene20_rain")


def read_fx(path: Path) -> float:
  """fx (K[0,0]) of the first data row of a VKITTI2 `intrinsic.txt`."""
  text = frame_io.read_text(path, "VKITTI2 intrinsics")
  lines = [ln.split() for ln in text.splitlines() if ln.strip()]
  try:
    return float(lines[1][2])  # line 0 is the header `frame cameraID K[0,0] ...`
  except (IndexError, ValueError) as e:
    raise ValueError(f"malformed VKITTI2 intrinsics (no fx in the first data row): {path}") from e


def _sequence(root: Path, name: str, dataset: str) -> DepthSequence:
  scene, variation = name.split("_", 1)
  seq_dir = root / scene / variation
  files = {}
  for side, cam in (("left", "Camera_0"), ("right", "Camera_1")):
    files[side] = list_files(seq_dir / "frames" / "rgb" / cam, ".jpg")
    files[side + "_gt"] = list_files(seq_dir / "frames" / "depth" / cam, ".png")
  check_matching(f"VKITTI2 {name}", files, digits_key)
  scale = camera_scale(read_fx(seq_dir / "intrinsic.txt"), BASELINE_M, seq_dir / "intrinsic.txt")
  return DepthSequence(name, files, dataset=dataset, depth2disp_scale=scale,
                       depth_reader=frame_io.read_vkitti2_depth)


def load_sequences(root, split: str, dataset: str = "vkitti2"):
  """VKITTI2 sequences of `split`, in the official order.

  Missing sequences are an error for "test" (the evaluation needs all five) and are
  skipped with a warning for "train" (as the official loader does).

  Args:
    root: the `vkitti2` folder or its parent.
    split: "train" or "test".
    dataset: registry name recorded on the sequences.

  Returns:
    list of `DepthSequence` (dense; left and right GT).
  """
  if split not in SPLITS:
    raise ValueError(f"VKITTI2 split must be one of {SPLITS}, got {split!r}")
  root = find_root(root, *FOLDERS)
  names = TEST if split == "test" else [f"{s}_{v}" for s in SCENES for v in VARIATIONS]
  seqs, missing = [], []
  for name in names:
    scene, variation = name.split("_", 1)
    refuse_broken_links_to(root / scene / variation)  # (not taken for a sequence not there)
    if split == "train" and not (root / scene / variation).is_dir():
      missing.append(f"{scene}/{variation}")
      continue
    seqs.append(_sequence(root, name, dataset))
  if not seqs:
    raise FileNotFoundError(f"no VKITTI2 {split} sequences under {root}")
  if missing:  # one line for all of them
    log.warning("VKITTI2: skipping %d missing training sequences under %s: %s", len(missing),
                root, some_of(missing))
  return seqs

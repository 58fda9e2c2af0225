"""South Kensington SV: real stereo videos without ground truth (qualitative only).

Layout (root = `SouthKensington/`, its `data/` folder, or their parent):

  data/<seq>/images/{left,right}/*.png
  data/<seq>/<anything>.txt     camera file: `Intrinsic: [[..] [..] [..]]`, then
                                `Frame <n>: Pose: <id>` blocks with 4x4 poses

Sequences without a `.txt` are skipped, as in the official loader (only the Indoor
videos ship `tracking_data.txt`); the camera file is `tracking_data.txt`, else the first
`.txt` by name that has an `Intrinsic:` entry (a `README.txt` beside it is not read as one). Frames have
`disparity = valid = None`. The depth2disp scale `K[0, 0] * 0.12 m` (hard-coded
baseline) only serves visualisation. Split: "test".
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from sav_jax.data import frame_io
from sav_jax.data.base import (StereoSequence, camera_scale, check_matching, digits_key, find_root,
                               is_hidden, list_dirs, list_files, refuse_broken_links)

log = logging.getLogger(__name__)

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("SouthKensington",)

SPLITS = ("test",)
BASELINE_M = 0.12
_FLOAT = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def read_intrinsics(path: Path) -> np.ndarray:
  """K [3, 3] from the `Intrinsic: [[...] [...] [...]]` entry of a camera txt."""
  text = frame_io.read_text(path, "South Kensington camera file")
  match = re.search(r"Intrinsic:\s*\[(.*?)\]\s*\]", text, re.S)
  values = re.findall(_FLOAT, match.group(1)) if match else []
  if len(values) != 9:
    raise ValueError(f"no 3x3 `Intrinsic: [[..] [..] [..]]` entry in {path}")
  return np.array([float(v) for v in values]).reshape(3, 3)


def load_sequences(root, split: str = "test", dataset: str = "south_kensington"):
  """South Kensington sequences that have a camera txt, sorted by name.

  Args:
    root: `SouthKensington/`, its `data/` folder, or their parent.
    split: "test".
    dataset: registry name recorded on the sequences.

  Returns:
    list of images-only `StereoSequence`.
  """
  if split not in SPLITS:
    raise ValueError(f"South Kensington split must be one of {SPLITS}, got {split!r}")
  root = find_root(root, *FOLDERS)
  if (root / "data").is_dir():
    root = root / "data"
  seqs = []
  for seq_dir in list_dirs(root):
    candidates = [p for p in seq_dir.glob("*.txt") if not is_hidden(p)]
    refuse_broken_links(candidates)  # a camera txt behind a dead link: the sequence vanished
    txts = sorted(p for p in candidates if p.is_file())
    if not txts:
      log.info("South Kensington: skipping %s (no camera txt)", seq_dir)
      continue
    files = {"left": list_files(seq_dir / "images" / "left", ".png"),
             "right": list_files(seq_dir / "images" / "right", ".png")}
    check_matching(f"South Kensington {seq_dir.name}", files, digits_key)
    camera, k = _camera_intrinsics(txts)
    scale = camera_scale(k[0, 0], BASELINE_M, camera)
    seqs.append(StereoSequence(seq_dir.name, files, dataset=dataset, depth2disp_scale=scale))
  if not seqs:
    raise FileNotFoundError(f"no South Kensington sequences with a camera txt under {root}")
  return seqs


def _camera_intrinsics(txts: list[Path]) -> tuple[Path, np.ndarray]:
  """`(camera file, K)`: `tracking_data.txt` among a sequence's `.txt` files (sorted by
  name), else the first whose `Intrinsic:` entry reads (other text files, also ones that are
  not UTF-8, are passed over); ValueError naming them all where none has one."""
  named = [p for p in txts if p.name == "tracking_data.txt"]
  if named:
    return named[0], read_intrinsics(named[0])
  for path in txts:
    try:
      return path, read_intrinsics(path)
    except ValueError:  # no entry, another text, or not UTF-8
      continue
  raise ValueError(f"no `Intrinsic: [[..] [..] [..]]` entry in any .txt of {txts[0].parent} "
                   f"(read: {', '.join(p.name for p in txts)})")

"""TartanAir: left-camera npy depth, a fixed pinhole (fx = 320 px) and a 0.25 m baseline.

Layout (root = the `TartanAir` folder or its parent), as the TartanAir (v1) download unpacks:

  <scene>/<Easy|Hard>/<Pxxx>/image_left/NNNNNN_left.png
  <scene>/<Easy|Hard>/<Pxxx>/image_right/NNNNNN_right.png
  <scene>/<Easy|Hard>/<Pxxx>/depth_left/NNNNNN_left_depth.npy    metres, float32

Every frame is 480x640 with `fx = fy = 320`, `cx = 320`, `cy = 240` and a 0.25 m baseline,
so disparity = 80 / Z (as the official loader and TartanAir's own documentation). Only the
left view has depth here (the official loader lists `depth_left` for both cameras; only the
left ground truth enters the loss and the metrics). The poses (`pose_left.txt`) are not
needed. Sequences are named `<scene>_<Easy|Hard>_<Pxxx>`; the "test" split is the official
loader's 17 (scene, difficulty, part) entries (`TEST`), "train" every other sequence. The
official scripts train and evaluate on neither; its loader is an option of the training
script (`--train_datasets tartanair`), whose clips this registry samples the same way.
"""

from __future__ import annotations

import logging
from pathlib import Path

from sav_jax.data import frame_io
from sav_jax.data.base import (DepthSequence, camera_scale, check_matching, digits_key, find_root,
                               list_dirs, list_files, refuse_broken_links, some_of)

log = logging.getLogger(__name__)

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("TartanAir", "tartanair")

SPLITS = ("train", "test")
FX_PX = 320.0
BASELINE_M = 0.25
DIFFICULTIES = ("Easy", "Hard")
TEST = (
    ("abandonedfactory", "Easy", "P002"), ("abandonedfactory", "Hard", "P002"),
    ("amusement", "Easy", "P007"), ("amusement", "Hard", "P007"),
    ("carwelding", "Hard", "P003"),
    ("endofworld", "Easy", "P006"), ("endofworld", "Hard", "P006"),
    ("gascola", "Easy", "P001"), ("gascola", "Hard", "P001"),
    ("hospital", "Hard", "P042"),
    ("office", "Easy", "P006"), ("office", "Hard", "P006"),
    ("office2", "Easy", "P004"), ("office2", "Hard", "P004"),
    ("oldtown", "Hard", "P006"),
    ("soulcity", "Easy", "P008"), ("soulcity", "Hard", "P008"),
)


def _sequence(seq_dir: Path, name: str, dataset: str) -> DepthSequence:
  files = {"left": list_files(seq_dir / "image_left", ".png"),
           "right": list_files(seq_dir / "image_right", ".png"),
           "left_gt": list_files(seq_dir / "depth_left", ".npy")}
  check_matching(f"TartanAir {name}", files, digits_key)
  return DepthSequence(name, files, dataset=dataset,
                       depth2disp_scale=camera_scale(FX_PX, BASELINE_M, "TartanAir"),
                       depth_reader=frame_io.read_depth_npy)


def _sequence_dirs(root: Path) -> list[tuple[tuple[str, str, str], Path]]:
  """((scene, difficulty, part), folder) of every sequence, in the official order: scenes
  by name, Easy before Hard, parts by name."""
  out = []
  for scene in list_dirs(root):
    refuse_broken_links([scene / d for d in DIFFICULTIES])  # (its sequences were left out)
    for difficulty in DIFFICULTIES:
      if (scene / difficulty).is_dir():
        out += [((scene.name, difficulty, part.name), part)
                for part in list_dirs(scene / difficulty)]
  return out


def load_sequences(root, split: str, dataset: str = "tartanair"):
  """TartanAir sequences of `split`.

  Test entries that are missing are named in a warning (TartanAir's official numbers are
  not published, so a partial download is still usable); no sequence at all is an error.

  Args:
    root: the `TartanAir` folder or its parent.
    split: "train" or "test".
    dataset: registry name recorded on the sequences.

  Returns:
    list of `DepthSequence` (dense; left GT only).
  """
  if split not in SPLITS:
    raise ValueError(f"TartanAir split must be one of {SPLITS}, got {split!r}")
  root = find_root(root, *FOLDERS)
  found = _sequence_dirs(root)
  test = set(TEST)
  chosen = [(key, d) for key, d in found if (key in test) == (split == "test")]
  if not chosen and found:  # the layout is right: none of its sequences is of this split
    raise FileNotFoundError(
        f"no TartanAir {split} sequences under {root}: its {len(found)} sequence(s) ("
        f"{some_of(['/'.join(k) for k, _ in found])}) are all "
        + ("outside the official loader's 17 test sequences (e.g. "
           f"{'/'.join(TEST[0])})" if split == "test" else
           "official test sequences (the train split is every other one)"))
  if not chosen:
    raise FileNotFoundError(
        f"no TartanAir {split} sequences under {root} (expected "
        "<scene>/<Easy|Hard>/<Pxxx>/image_left, image_right and depth_left folders)")
  if split == "test":
    missing = [key for key in TEST if key not in {k for k, _ in chosen}]
    if missing:
      log.warning("TartanAir: %d of the %d test sequences are missing under %s: %s",
                  len(missing), len(TEST), root, some_of(["/".join(k) for k in missing]))
  return [_sequence(d, "_".join(key), dataset) for key, d in chosen]

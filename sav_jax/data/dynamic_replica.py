"""Dynamic Replica: float16-in-PNG depth and PyTorch3D cameras from a gzip JSON index.

Layout (root = the `dynamic_replica_data` folder or its parent):

  <split>/frame_annotations_<split>.jgz   gzip JSON list of frame records
  <split>/<paths named by the records>    images, depth PNGs, masks

Each record has `sequence_name`, `camera_name` ("left"/"right"), `image.path`,
`image.size` [H, W], `depth.path` and `viewpoint` {R, T, focal_length,
principal_point, intrinsics_format}; paths are relative to `<root>/<split>/`. Frames
are grouped by sequence and camera in file order (not re-sorted).

Depth: the PNG's uint16 bits reinterpreted as float16. The depth2disp scale is
`fx_px(left) * (T_x(right) - T_x(left))` from frame 0 (a training clip's from its first
frame, as the official loader: `DepthSequence.gather`), with `fx_px = f_ndc * r` and
`r = W/2` (`ndc_norm_image_bounds`) or `min(H, W)/2` (`ndc_isotropic`): the official
PyTorch3D -> OpenCV conversion (`t_cv = (-T_x, -T_y, T_z)`) written out. Foreground
masks do not enter the metrics and are not read. Splits: train, valid, test.
"""

from __future__ import annotations

import gzip
import math
import zlib
from pathlib import Path

from sav_jax._checks import loads_json
from sav_jax.data import frame_io
from sav_jax.data.base import DepthSequence, camera_scale, find_root, warn_if_gaps

# The dataset's folder under a datasets root (the root may also be that folder itself).
FOLDERS = ("dynamic_replica_data",)

SPLITS = ("train", "valid", "test")


def _records(split_dir: Path, split: str) -> list[dict]:
  path = frame_io.require_file(split_dir / f"frame_annotations_{split}.jgz",
                               "Dynamic Replica annotation file")
  try:
    with gzip.open(path, "rt", encoding="utf8") as f:
      records = loads_json(f.read())
  except (OSError, EOFError, ValueError, zlib.error) as e:  # (zlib's: a damaged byte)
    raise ValueError(f"cannot read Dynamic Replica annotations {path}: {e}") from e
  if not isinstance(records, list):
    raise ValueError(f"{path}: expected a JSON list of frame records")
  return records


class DynamicReplicaSequence(DepthSequence):
  """A `DepthSequence` whose frames must have the size the annotation gives (`image.size`
  of frame 0, which the focal length in pixels, so the depth-to-disparity scale, is
  computed from): resized images under the original annotation file would give disparities
  off by the resize factor, silently."""

  def __init__(self, *args, annotated_size: tuple[int, int], annotation: Path,
               frame_scales: tuple[float, ...], **kwargs):
    super().__init__(*args, **kwargs)
    self.annotated_size, self.annotation = annotated_size, annotation
    self.frame_scales = tuple(frame_scales)

  def clip_scale(self, start: int) -> float:
    """fx * baseline of the clip's first frame's records (the official clip's camera)."""
    return self.frame_scales[start]

  def _checked_gt(self, i: int, side: str, size: tuple[int, int]):
    if tuple(size) != self.annotated_size:
      h, w = self.annotated_size
      raise ValueError(f"{self.files[side][i]} is {size[0]}x{size[1]} but {self.annotation} "
                       f"gives image.size {h}x{w} for {self.dataset}/{self.name} (height x "
                       "width); the depth-to-disparity scale comes from that size")
    return super()._checked_gt(i, side, size)


def focal_px(viewpoint: dict, size_hw) -> float:
  """Horizontal focal length in pixels of a PyTorch3D NDC viewpoint.

  Args:
    viewpoint: the record's `viewpoint` dict.
    size_hw: image size [H, W].
  """
  h, w = (_number(s, "image.size") for s in size_hw)
  fmt = str(viewpoint.get("intrinsics_format", "ndc_norm_image_bounds")).lower()
  if fmt == "ndc_norm_image_bounds":
    r = w / 2.0
  elif fmt == "ndc_isotropic":
    r = min(h, w) / 2.0
  else:
    raise ValueError(f"unknown Dynamic Replica intrinsics format {fmt!r} (known: "
                     "ndc_norm_image_bounds, ndc_isotropic)")
  return _number(viewpoint["focal_length"][0], "viewpoint.focal_length") * r


def depth2disp_scale(left: dict, right: dict, source="Dynamic Replica frame records") -> float:
  """fx_px(left) * (T_x(right) - T_x(left)) from two frame records; refused naming `source`
  unless both factors are positive and finite (`base.camera_scale`)."""
  try:
    fx = focal_px(left["viewpoint"], left["image"]["size"])
  except ValueError as e:
    raise ValueError(f"{source}: {e}") from e
  baseline = (_number(right["viewpoint"]["T"][0], "viewpoint.T")
              - _number(left["viewpoint"]["T"][0], "viewpoint.T"))
  return camera_scale(fx, baseline, source)


def _number(value, field: str) -> float:
  """`float(value)` for a record field; TypeError (a malformed record) naming the field."""
  if isinstance(value, bool) or not isinstance(value, (int, float)):
    raise TypeError(f"field {field} holds {str(value)[:40]!r}, not a number")
  try:
    number = float(value)
  except OverflowError:  # an integer beyond float's range
    number = math.inf
  if not math.isfinite(number):
    raise TypeError(f"field {field} holds {str(value)[:40]}, not a finite number")
  return number


def _frame_paths(split_dir: Path, rec: dict, where: str) -> tuple[Path, Path]:
  depth = rec.get("depth") or {}
  if not depth.get("path"):
    raise ValueError(f"{where}: frame {rec.get('frame_number')} has no depth annotation")
  image = frame_io.require_file(split_dir / rec["image"]["path"], "Dynamic Replica image")
  return image, frame_io.require_file(split_dir / depth["path"], "Dynamic Replica depth")


def load_sequences(root, split: str, dataset: str = "dynamic_replica"):
  """Dynamic Replica sequences of `split`, in annotation-file order.

  Args:
    root: the `dynamic_replica_data` folder or its parent.
    split: "train", "valid" or "test".
    dataset: registry name recorded on the sequences.

  Returns:
    list of `DepthSequence` (dense; left and right GT).
  """
  if split not in SPLITS:
    raise ValueError(f"Dynamic Replica split must be one of {SPLITS}, got {split!r}")
  split_dir = find_root(root, *FOLDERS) / split
  try:
    seqs = _sequences(split_dir, split, dataset)
  except (KeyError, IndexError, TypeError) as e:  # a record lacking a field, or of the wrong type
    raise ValueError(f"{split_dir / f'frame_annotations_{split}.jgz'}: malformed frame record "
                     f"({type(e).__name__}: {e})") from e
  if not seqs:
    raise FileNotFoundError(f"no Dynamic Replica sequences in {split_dir}")
  return seqs


def _sequences(split_dir: Path, split: str, dataset: str) -> list[DepthSequence]:
  groups: dict[str, dict[str, list[dict]]] = {}
  for rec in _records(split_dir, split):
    cams = groups.setdefault(rec["sequence_name"], {"left": [], "right": []})
    if rec.get("camera_name") not in cams:
      raise ValueError(f"{split_dir}: record with camera_name {rec.get('camera_name')!r}")
    cams[rec["camera_name"]].append(rec)
  seqs = []
  for name, cams in groups.items():
    where = f"Dynamic Replica {split}/{name}"
    if len(cams["left"]) != len(cams["right"]) or not cams["left"]:
      raise ValueError(f"{where}: {len(cams['left'])} left and {len(cams['right'])} "
                       "right frames")
    for i, (l, r) in enumerate(zip(cams["left"], cams["right"])):
      # Paired by position, as the official loader does; a record order that pairs
      # different frames would give wrong disparities silently.
      if "frame_number" in l and "frame_number" in r and l["frame_number"] != r["frame_number"]:
        raise ValueError(f"{where}: left and right records number {i} are frames "
                         f"{l['frame_number']} and {r['frame_number']} (left and right "
                         "records must come in the same frame order)")
    files = {}
    warn_if_gaps(where, [rec.get("frame_number") for rec in cams["left"]], lambda n: n)
    for side in ("left", "right"):
      paths = [_frame_paths(split_dir, rec, where) for rec in cams[side]]
      files[side] = [p[0] for p in paths]
      files[side + "_gt"] = [p[1] for p in paths]
    annotation = split_dir / f"frame_annotations_{split}.jgz"
    # Every frame's, for training clips (the official loader converts a clip with its first
    # frame's camera); frame 0's for the sequence (evaluation).
    scales = tuple(depth2disp_scale(l, r, f"{annotation} ({where}, frame {i})")
                   for i, (l, r) in enumerate(zip(cams["left"], cams["right"])))
    scale = scales[0]
    size = tuple(int(_number(v, "image.size")) for v in cams["left"][0]["image"]["size"])
    seqs.append(DynamicReplicaSequence(name, files, dataset=dataset, depth2disp_scale=scale,
                                       depth_reader=frame_io.read_float16_png,
                                       annotated_size=size, annotation=annotation,
                                       frame_scales=scales))
  return seqs

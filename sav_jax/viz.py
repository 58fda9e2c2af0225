"""Visualisation and disparity file formats: colour maps, videos, point clouds.

Images are RGB uint8 `[..., H, W, 3]` throughout; conversion to OpenCV's BGR
happens only inside the writers and readers that call OpenCV.

Colour: `colorize` maps disparity with a perceptual colour map (inferno, as the
official demo) over a range that is fixed for a whole video (`disparity_range`
over all frames), so a colour means the same disparity in every frame.

File formats (all round trips are tested value by value):
  * 16-bit PNG, KITTI convention: `uint16 = round(256 d)`, 0 = invalid (d <= 0 or
    not finite); values above 65535/256 px saturate and positive values below 1/512
    px are stored as 1 (1/256 px) so that they stay valid. Resolution 1/256 px.
  * PFM: `Pf` (one channel) or `PF` (three), little-endian (scale -1), rows stored
    bottom to top, as SceneFlow files.
  * OpenEXR: float32 channels (`Y` for one channel), ZIP compression.
  * PLY point clouds: `binary_little_endian 1.0`, vertices `x y z` float32 and
    `red green blue` uint8. Camera frame of the left camera (OpenCV axes: x right,
    y down, z forward), metres when the baseline is in metres.
"""

from __future__ import annotations

import io
import math
import numbers
import os
import pathlib
import uuid
import warnings

import cv2
import numpy as np

from sav_jax._checks import (OVERSHOOT_HIGH, OVERSHOOT_LOW, caller_stacklevel,  # (viz's API too)
                             check_utf8_path, looks_normalised, require_int, unit_range_advice,
                             widened)
from sav_jax._files import free_space_note

COLORMAPS = {"inferno": cv2.COLORMAP_INFERNO, "turbo": cv2.COLORMAP_TURBO,
             "magma": cv2.COLORMAP_MAGMA, "viridis": cv2.COLORMAP_VIRIDIS}
INVALID_COLOR = (255, 255, 255)
_PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def disparity_range(disp, valid=None, percentiles=(0.0, 100.0)) -> tuple[float, float]:
  """Colour range of a disparity map or a whole video.

  Args:
    disp: `[H, W]` or `[T, H, W]` disparity (px).
    valid: optional mask of the same shape (bool, or weights: > 0.5 is valid); only
      pixels with a finite disparity > 0 are used either way.
    percentiles: (low, high) percentiles of the used values, in 0..100; (0, 100) =
      min/max. Both at most 1 (e.g. (0.01, 0.99), fractions) gets a warning.

  Returns:
    `(vmin, vmax)` with `vmax > vmin` ((0, 1) when no pixel is usable).
  """
  d = np.asarray(disp, np.float32)
  use = np.isfinite(d) & (d > 0)
  if valid is not None:
    mask = np.asarray(valid)
    if mask.shape != d.shape:
      raise ValueError(f"valid has shape {mask.shape}; expected the disparity's {d.shape}")
    use &= mask > 0.5  # as colorize and the metrics: a fractional weight counts above 0.5
  try:
    lo_p, hi_p = (float(p) for p in percentiles)
  except (TypeError, ValueError):  # not two numbers: one, three, a string
    lo_p = hi_p = math.nan
  if not 0 <= lo_p <= hi_p <= 100:
    raise ValueError(f"percentiles must be (low, high) with 0 <= low <= high <= 100, got "
                     f"{percentiles!r}")
  if hi_p <= 1:  # (0.01, 0.99) meant the 1st and 99th percentiles: it is the 0.01th, 0.99th
    warnings.warn(f"disparity_range: percentiles ({lo_p:g}, {hi_p:g}) are both at most 1: "
                  f"percentiles are in 0..100, not fractions (the 1st and 99th are (1, 99))",
                  stacklevel=caller_stacklevel())
  vals = d[use]
  if vals.size == 0:
    return 0.0, 1.0
  lo, hi = (float(v) for v in np.percentile(vals, percentiles))
  if hi <= lo:
    hi = lo + 1.0
  return lo, hi


_COLORIZE_HINT = "a disparity or depth map? colour it with viz.colorize first"


def as_uint8_image(image, what: str = "image", *, is_map: bool = False) -> np.ndarray:
  """`image` as uint8: uint8 passes; other numbers must be finite and within 0..255 (they
  are rounded). A float image may overshoot 0..255 as far as `predict_video` lets its frames
  do without a warning (`_checks.OVERSHOOT_LOW` .. `OVERSHOOT_HIGH`, -64..320: a bicubic or
  Lanczos resize of sharp edges, unclipped noise): such values are clipped to 0..255. Raises
  ValueError naming `what` otherwise, with advice for what the values look like (16-bit,
  normalised); a float image no brighter than 1.0 gets a warning (0..1 images come out
  black: multiply them by 255). `is_map`: `image` is a one-channel map, so a float one is
  likely disparity or depth: it gets no overshoot allowance and the messages suggest
  `colorize`."""
  a = widened(np.asarray(image))  # bfloat16 (JAX's) as float32
  is_float = a.dtype.kind == "f"
  hint = f" ({_COLORIZE_HINT})" if is_map and is_float else ""
  if a.dtype == np.uint8:
    return a
  if a.dtype.kind not in "uif":
    raise ValueError(f"{what}: dtype {a.dtype}; expected uint8 or numbers in 0..255")
  if a.size == 0:
    return a.astype(np.uint8)
  if is_float and not np.isfinite(a).all():
    raise ValueError(f"{what}: NaN or inf values; expected 0..255{hint}")
  lo, hi = float(a.min()), float(a.max())
  # (not normalised frames, which predict_video refuses: clipped, they came out black)
  overshoot = (is_float and not is_map and OVERSHOOT_LOW <= lo and hi <= OVERSHOOT_HIGH
               and not looks_normalised(lo, hi))
  if (lo < 0 or hi > 255) and not overshoot:
    if hint:
      advice = _COLORIZE_HINT
    elif lo < 0:
      advice = ("RGB images are 0..255: negative values are no image's; normalised images "
                "need their mean and scale put back")
    else:
      advice = "16-bit images: divide by 257" if is_float else "16-bit images: >> 8"
      if is_map:  # an integer one-channel map: a 16-bit grey image or a stored disparity
        advice += f"; {_COLORIZE_HINT}"
    raise ValueError(f"{what}: values {lo:g}..{hi:g} outside 0..255 ({advice})")
  if is_float and 0 < hi <= 1.0:
    advice = (f"{_COLORIZE_HINT}; a 0..1 grey image: multiply it by 255" if hint
              else unit_range_advice(lo))
    warnings.warn(f"{what}: float values {lo:g}..{hi:g}: expected 0..255 ({advice})",
                  stacklevel=caller_stacklevel())
  if overshoot:
    a = np.clip(a, 0, 255)
  return np.rint(a).astype(np.uint8)


def as_real(value) -> float | None:
  """`value` as a float when it is one real number: a Python or NumPy number or a 0-d NumPy
  or JAX array (`K[0, 0]` of an intrinsics matrix, `jnp.float32(100)`); None for anything
  else (bools, strings, complex numbers, arrays of one or more dimensions). The scalar check
  of every number parameter here (intrinsics, colour range, frame rate)."""
  if isinstance(value, (bool, np.bool_, str, bytes)):
    return None
  if not isinstance(value, numbers.Real):
    dtype = getattr(value, "dtype", None)  # 0-d NumPy / JAX arrays (bfloat16 included)
    if dtype is None or np.ndim(value) != 0 or np.dtype(dtype).kind in "bcmMOSU":
      return None
  try:
    return float(value)
  except OverflowError:  # an int beyond float's range
    return math.inf if value > 0 else -math.inf
  except (TypeError, ValueError):
    return None


def _shown(value) -> str:
  """A number as printed (`0.0`, not `np.float64(0.0)` or `Array(0., dtype=float32)`); an
  array by its shape; anything else as its repr."""
  real = as_real(value)
  if real is not None:
    return str(real)
  if _is_array(value):
    return f"an array of shape {np.shape(value)}"
  return repr(value)


def _is_array(value) -> bool:
  """An array (or list) of one or more dimensions."""
  try:
    return not isinstance(value, (str, bytes)) and np.ndim(value) > 0
  except ValueError:  # ragged lists
    return True


def is_fps(fps) -> bool:
  """Whether `fps` is a frame rate OpenCV's MPEG-4 writer takes (0.01 to 65535; beyond, it
  fails to open, after the whole run)."""
  fps = as_real(fps)
  return fps is not None and math.isfinite(fps) and 0.01 <= fps <= 65535


def check_fps(fps, what: str = "fps") -> None:
  """Raises ValueError unless `fps` is a frame rate OpenCV's MPEG-4 writer takes (`is_fps`)."""
  if not is_fps(fps):
    raise ValueError(f"{what} must be a number from 0.01 to 65535, got {_shown(fps)}")


def check_intrinsics(what: str = "", **values) -> dict[str, float]:
  """The given values as floats; raises ValueError unless each is one real number (`as_real`:
  a Python or NumPy number or a 0-d NumPy / JAX array, not a bool, a string or an array of
  one or more dimensions), `fx`, `fy`, `baseline`, `max_depth` finite and positive and the
  others (`cx`, `cy`, `doffs`) finite; the message starts with `what`."""
  out = {}
  for name, value in values.items():
    positive = name in ("fx", "fy", "baseline", "max_depth")
    real = as_real(value)
    if real is None or not math.isfinite(real) or (positive and real <= 0):
      scalar = ": give one number (a scalar)" if real is None and _is_array(value) else ""
      raise ValueError(f"{what}{name} must be a finite{' positive' if positive else ''} number, "
                       f"got {_shown(value)}{scalar}")
    out[name] = real
  return out


def principal_point_inside(cx: float, cy: float, height: int, width: int) -> bool:
  """Whether the principal point (cx, cy) lies in a height x width frame. Pixel centres are
  at integers, so the frame spans [-0.5, width - 0.5] x [-0.5, height - 0.5] (the default
  centre, (width - 1) / 2, is its middle). `sav-jax infer` refuses a calibration outside it
  (intrinsics for another image size); `disparity_to_points` warns."""
  return -0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5


def _check_range(vmin, vmax) -> tuple[float, float]:
  lo, hi = as_real(vmin), as_real(vmax)
  if lo is None or hi is None:
    raise ValueError(f"colour range needs numbers (scalars) vmin < vmax, got vmin="
                     f"{_shown(vmin)}, vmax={_shown(vmax)}")
  vmin, vmax = lo, hi
  if not (math.isfinite(vmin) and math.isfinite(vmax) and vmax > vmin):
    raise ValueError(f"colour range needs finite vmin < vmax, got vmin={vmin}, vmax={vmax}")
  return vmin, vmax


def colorize(disp, vmin: float | None = None, vmax: float | None = None, *,
             cmap: str = "inferno", valid=None,
             invalid_color: tuple[int, int, int] = INVALID_COLOR) -> np.ndarray:
  """Colour-maps disparity (large disparity = near = bright).

  Args:
    disp: `[..., H, W]` disparity (px); a trailing channel axis of size 1 (`[..., H, W, 1]`
      with at least 3 axes, as image readers give one-channel maps) is dropped, so a video
      of 1-pixel-wide frames must come as `[T, H, 1, 1]`.
    vmin, vmax: colour range; a missing end comes from `disparity_range` over the
      whole array (so pass a video `[T, H, W]`, or a fixed range, for colours that
      are stable over time).
    cmap: one of `COLORMAPS`.
    valid: optional mask `[..., H, W]` or of `disp`'s shape (bool, or weights: > 0.5 is
      valid, as in the metrics); pixels outside it, and non-finite or non-positive
      disparities, get `invalid_color`.
    invalid_color: RGB colour of invalid pixels.

  Returns:
    `[..., H, W, 3]` uint8 RGB.
  """
  if cmap not in COLORMAPS:
    raise ValueError(f"unknown colour map {cmap!r}; choose one of {sorted(COLORMAPS)}")
  _check_colour(invalid_color)
  d, valid = _one_channel(disp, valid)
  if vmin is None or vmax is None:
    lo, hi = disparity_range(d, valid)
    filled = "vmin" if vmin is None else "vmax"
    vmin = lo if vmin is None else vmin
    vmax = hi if vmax is None else vmax
    try:
      vmin, vmax = _check_range(vmin, vmax)
    except ValueError as e:
      raise ValueError(f"{e} ({filled} taken from the data's range {lo:.4g}..{hi:.4g}, which "
                       f"lies beyond the given end; give both vmin and vmax)") from None
  else:
    vmin, vmax = _check_range(vmin, vmax)
  rgb = _mapped(d, vmin, vmax, cmap)
  bad = ~np.isfinite(d) | (d <= 0)
  if valid is not None:
    bad |= ~(np.asarray(valid) > 0.5)  # as the metrics: a fractional weight counts above 0.5
  rgb[bad] = invalid_color
  return rgb


def _check_colour(invalid_color) -> np.ndarray:
  """`invalid_color` as 3 integers in 0..255 (ValueError otherwise; a warning for a 0..1
  colour)."""
  colour = np.asarray(invalid_color)
  if (colour.shape != (3,) or colour.dtype.kind not in "uif" or not np.isfinite(colour).all()
      or colour.min() < 0 or colour.max() > 255 or (colour != np.round(colour)).any()):
    # (fractions were truncated: matplotlib's white (1.0, 1.0, 1.0) came out near black)
    raise ValueError(f"invalid_color must be 3 integers (R, G, B) in 0..255, got "
                     f"{invalid_color!r}")
  if colour.dtype.kind == "f" and 0 < colour.max() <= 1:
    warnings.warn(f"invalid_color {invalid_color!r} is nearly black in 0..255 (for a 0..1 "
                  "colour multiply it by 255)", stacklevel=caller_stacklevel())
  return colour.astype(np.uint8)


def _one_channel(disp, valid, what: str = "disparity") -> tuple[np.ndarray, np.ndarray | None]:
  """`disp` as float32 `[..., H, W]` (a trailing channel axis of 1 dropped where it has at
  least 3 axes) and `valid` of that shape (or of `disp`'s own), or None."""
  d = np.asarray(disp, np.float32)
  given = d.shape
  if d.ndim >= 3 and d.shape[-1] == 1:  # [..., H, W, 1]: one channel, not width-1 frames
    d = d[..., 0]
  if valid is not None:
    if np.shape(valid) == given != d.shape:
      valid = np.asarray(valid)[..., 0]
    if np.shape(valid) != d.shape:
      raise ValueError(f"valid mask shape {np.shape(valid)} differs from {what} {given}")
  return d, valid


def _mapped(d: np.ndarray, vmin: float, vmax: float, cmap: str) -> np.ndarray:
  """`[..., 3]` uint8 RGB of `cmap` over vmin..vmax (clipped; non-finite values at vmin)."""
  if d.size == 0:
    return np.zeros((*d.shape, 3), np.uint8)
  scale = 255.0 / (vmax - vmin)
  safe = np.where(np.isfinite(d), d, vmin)
  idx = np.clip((safe - float(vmin)) * scale, 0, 255).round().astype(np.uint8)
  flat = idx.reshape(-1, idx.shape[-1]) if idx.ndim >= 2 else idx.reshape(1, -1)
  rgb = cv2.applyColorMap(flat, COLORMAPS[cmap])[..., ::-1].reshape(*d.shape, 3)
  return np.ascontiguousarray(rgb)


# KITTI's disparity error colours (its development kit's log colour map): bins of the error
# in multiples of the outlier threshold (`colorize_error`), RGB; each bin is closed on the
# right, (lo, hi] (0 in the first). Blues up to 1 (a correct pixel), oranges to dark red above
# 1 (an outlier, D1's "bad" pixel).
KITTI_ERROR_BINS = (0.0, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0, 2.0, 4.0, 8.0, 16.0)
KITTI_ERROR_COLORS = ((49, 54, 149), (69, 117, 180), (116, 173, 209), (171, 217, 233),
                      (224, 243, 248), (254, 224, 144), (253, 174, 97), (244, 109, 67),
                      (215, 48, 39), (165, 0, 38))


def colorize_error(pred, gt, valid=None, *, abs_thresh: float = 3.0,
                   rel_thresh: float | None = 0.05,
                   invalid_color: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
  """Colours the disparity error |pred - gt| with KITTI's error colours.

  The error is measured in multiples of the outlier threshold: `min(e / abs_thresh,
  e / (rel_thresh |gt|))` (KITTI's D1: a pixel is an outlier where its error exceeds both
  3 px and 5% of the true disparity; `rel_thresh=None` for the absolute threshold alone,
  as the bad-N rates), then binned by `KITTI_ERROR_BINS` into `KITTI_ERROR_COLORS`, each bin
  closed on the right (`(1/16, 1/8]`, ...): blue up to the threshold, orange to dark red
  above it, so that an error of exactly the threshold is coloured correct, as D1 and the
  metrics' strict bad-N rates count it (KITTI's devkit takes its colour bins as `[lo, hi)`
  and colours that one error as an outlier though its own D1 counts it correct; the two
  differ at the bins' exact edges only). A perfect pixel (error 0) is valid and dark blue.

  Args:
    pred, gt: `[..., H, W]` (or `[..., H, W, 1]`) disparities (px) of one shape.
    valid: optional mask of that shape (bool, or weights: > 0.5 is valid); without it the
      pixels whose ground truth is not finite or is 0 (KITTI's "no ground truth") are
      invalid. Either way such pixels get `invalid_color` (black, as KITTI's maps), and a
      non-finite prediction where the ground truth is valid gets the last (worst) colour.
    abs_thresh: absolute threshold (px), > 0.
    rel_thresh: relative threshold (fraction of |gt|, > 0), or None.
    invalid_color: RGB colour of pixels without ground truth.

  Returns:
    `[..., H, W, 3]` uint8 RGB.
  """
  p, valid = _one_channel(pred, valid, "pred")
  g, _ = _one_channel(gt, None)
  if p.shape != g.shape:
    raise ValueError(f"colorize_error: pred of shape {np.shape(pred)} and gt of shape "
                     f"{np.shape(gt)} differ")
  ok_abs = as_real(abs_thresh)
  ok_rel = None if rel_thresh is None else as_real(rel_thresh)
  if ok_abs is None or not 0 < ok_abs < math.inf or (
      rel_thresh is not None and (ok_rel is None or not 0 < ok_rel < math.inf)):
    raise ValueError(f"colorize_error: abs_thresh must be a number > 0 and rel_thresh one > 0 "
                     f"or None, got abs_thresh={_shown(abs_thresh)}, "
                     f"rel_thresh={_shown(rel_thresh)}")
  colour = _check_colour(invalid_color)
  with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
    err = np.abs(p - g)
    norm = err / np.float32(ok_abs)
    if ok_rel is not None:
      norm = np.minimum(norm, err / (np.float32(ok_rel) * np.abs(g)))
    norm = np.where(err == 0, 0.0, norm)  # a perfect pixel, gt 0 too (0 / 0)
  norm = np.where(np.isfinite(norm), norm, np.inf)  # a NaN / inf prediction: the worst
  table = np.asarray(KITTI_ERROR_COLORS, np.uint8)
  # bins closed on the right, (lo, hi] (KITTI's devkit: [lo, hi)): an error of exactly the
  # threshold (1) is correct, as D1 and the bad-N rates count only errors above it
  bin_index = np.searchsorted(np.asarray(KITTI_ERROR_BINS, np.float32), norm, "left") - 1
  rgb = table[np.maximum(bin_index, 0)]
  bad = ~np.isfinite(g) | (g == 0) if valid is None else ~(np.asarray(valid) > 0.5) | \
      ~np.isfinite(g)
  rgb[bad] = colour
  return rgb


def nice_step(span: float, ticks: int) -> float:
  """A 1/2/5 x 10^k step giving at most about `ticks` intervals over `span` (> 0)."""
  if not span > 0:
    return 1.0
  raw = span / ticks
  base = 10.0 ** np.floor(np.log10(raw))
  return float(next(m * base for m in (1, 2, 5, 10) if m * base >= raw))


def colorbar(vmin: float, vmax: float, *, cmap: str = "inferno", length: int = 320,
             thickness: int = 16, ticks: int = 5, unit: str = "px") -> np.ndarray:
  """A horizontal colour bar of `colorize`'s colours over vmin..vmax, ticks labelled below.

  Put it under a frame coloured with the same range (`disparity_range`, or the range
  `sav-jax infer` prints and keeps in summary.json): `side_by_side` needs equal heights,
  so stack it with `np.concatenate([frame, bar], axis=0)` after `cv2.resize`-ing one of
  them to the other's width.

  Args:
    vmin, vmax: the colour range (finite, vmin < vmax).
    cmap: one of `COLORMAPS`.
    length: width of the bar (px), >= 32.
    thickness: height of the colour band (px), >= 1.
    ticks: about this many tick intervals (1/2/5 x 10^k steps), >= 1.
    unit: text after the last label ("" for none).

  Returns:
    `[thickness + 18, length, 3]` uint8 RGB: the band, then black tick labels on white.
  """
  if cmap not in COLORMAPS:
    raise ValueError(f"unknown colour map {cmap!r}; choose one of {sorted(COLORMAPS)}")
  vmin, vmax = _check_range(vmin, vmax)
  for name, value, least in (("length", length, 32), ("thickness", thickness, 1),
                             ("ticks", ticks, 1)):
    require_int(value, name, least, where="colorbar")
  values = vmin + (vmax - vmin) * np.arange(length, dtype=np.float64) / (length - 1)
  band = np.repeat(_mapped(values[None].astype(np.float32), vmin, vmax, cmap), thickness, 0)
  labels = np.full((18, length, 3), 255, np.uint8)
  step = nice_step(vmax - vmin, ticks)
  first = math.ceil(vmin / step - 1e-9) * step
  # (floor: with no step inside the range, int() made one mark beyond its end, an IndexError)
  marks = [first + k * step for k in range(math.floor((vmax - first) / step + 1e-9) + 1)]
  marks = marks or [vmin, vmax]  # (no 1/2/5 x 10^k value inside: 1..4 with ticks=1)
  columns = [int(round((v - vmin) / (vmax - vmin) * (length - 1))) for v in marks]
  labels[:3, columns] = 0  # the ticks
  for left, text in _tick_labels(marks, columns, length, unit):
    cv2.putText(labels, text, (left, 14), _FONT, _FONT_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
  return np.concatenate([band, labels], axis=0)


_FONT, _FONT_SCALE = cv2.FONT_HERSHEY_SIMPLEX, 0.35


def _tick_labels(marks, columns, length, unit) -> list[tuple[int, str]]:
  """`(left column, text)` of the tick labels that `colorbar` draws: each centred under its
  tick (kept inside the bar), the unit after the last one. Where labels would run into each
  other (a narrow bar, long numbers), some are left out, so that a pixel stays between the
  text boxes of those drawn (OpenCV's, which hold a pixel or two of margin: touching boxes
  read "0" and "1" as "01"): the last one always (it carries the unit), the others from the
  left."""
  placed = []
  for k, (v, x) in enumerate(zip(marks, columns)):
    text = f"{v:.6g}" + (f" {unit}" if unit and k == len(marks) - 1 else "")
    (width, _), _ = cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)
    placed.append((min(max(0, x - width // 2), length - width), width, text))
  last = placed[-1]
  kept, right = [], -1
  for left, width, text in placed[:-1]:
    if left > right and left + width < last[0]:
      kept.append((left, text))
      right = left + width
  return kept + [(last[0], last[2])]


def side_by_side(*images) -> np.ndarray:
  """Concatenates images (or videos) of equal height along the width.

  Args:
    *images: `[..., H, W_i, 3]` RGB, uint8 or numbers in 0..255 (`as_uint8_image`: a float
      image's resize overshoot is clipped, a float grey map gets no allowance). A grey map
      `[..., H, W]` (or `[..., H, W, 1]`) is repeated to grey RGB (colour a disparity or
      depth map with `colorize` first). With 3 or more axes a last axis of 2 or 4 is taken
      for channels (grey + alpha, RGBA) and refused: drop the alpha first (`image[..., :3]`).

  Returns:
    `[..., H, sum W_i, 3]` uint8.
  """
  parts = []
  for i, im in enumerate(images):
    what = f"side_by_side image {i}"
    a = np.asarray(im)
    if a.ndim >= 3 and a.shape[-1] in (1, 2, 4):
      if a.shape[-1] != 1:
        raise ValueError(f"{what} of shape {a.shape} has {a.shape[-1]} channels"
                         f"{' (RGBA?)' if a.shape[-1] == 4 else ''}: side_by_side takes RGB "
                         "[..., H, W, 3] or a grey map [..., H, W] or [..., H, W, 1] (drop "
                         "the alpha channel: image[..., :3])")
      a = a[..., 0]
    is_map = a.ndim == 2 or (a.ndim >= 2 and a.shape[-1] != 3)
    im = as_uint8_image(a, what, is_map=is_map)
    if is_map:
      im = np.repeat(im[..., None], 3, axis=-1)
    if parts and (im.ndim != parts[0].ndim or im.shape[:-2] != parts[0].shape[:-2]):
      raise ValueError(f"side_by_side: image {i} of shape {im.shape} does not match the first "
                       f"{parts[0].shape} (same frames and height needed)")
    parts.append(im)
  return np.concatenate(parts, axis=-2)


def _check_suffix(path, suffixes: tuple[str, ...], message: str) -> None:
  """Raises ValueError `"{path}: {message}"` unless `path` ends in one of `suffixes` (any
  case): the writers' check that a file's name says its format (PFM or EXR bytes went into
  x.png; OpenCV picks the format from the name)."""
  if pathlib.Path(path).suffix.lower() not in suffixes:
    raise ValueError(f"{path}: {message}")


# The largest frame side `write_video` writes (MPEG-4 part 2 codes sizes in 13 bits: FFmpeg's
# mp4v encoder refuses 8192 and more; even, as the codec needs).
MP4V_MAX_SIDE = 8190

# File names `write_video` accepts: containers that hold mp4v video.
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".avi", ".mkv")


def _opencv_fps_fits(fps: float) -> bool:
  """Whether OpenCV's FFmpeg writer can open an MPEG-4 video at `fps`: it takes the first
  power-of-ten denominator that puts the rate within 0.001 of `fps`, and MPEG-4's time base
  (that fraction's reduced numerator) must be at most 65535."""
  base, rate = 1, int(fps + 0.5)
  while abs(rate / base - fps) > 0.001:
    base *= 10
    rate = int(fps * base + 0.5)
  return rate // math.gcd(rate, base) <= 65535


def mp4v_fps(fps: float) -> float:
  """`fps` (a rate `is_fps` takes) as the nearest rate OpenCV's MPEG-4 writer opens: `fps`
  itself where it can; else rounded to 2, 1 or 0 decimals (119.8765 -> 119.88: the writer
  refused 1000/119877 as a time base, after a whole `sav-jax infer` run)."""
  fps = float(fps)
  for decimals in (None, 2, 1, 0):
    rate = fps if decimals is None else max(round(fps, decimals), 10.0 ** -decimals)
    if _opencv_fps_fits(rate):
      return rate
  return float(round(fps))


def write_video(path, frames, fps: float = 10.0) -> pathlib.Path:
  """Writes RGB frames as an MPEG-4 (mp4v) video with OpenCV (replacing a file at `path`
  once the video is complete: until then it is written under a temporary name beside it).

  Odd heights or widths are padded by one replicated row/column (the codec needs
  even sizes and would otherwise crop). Frames wider or taller than MPEG-4's limit
  (`MP4V_MAX_SIDE`: e.g. a side-by-side of 4096-wide frames) are scaled down to fit, keeping
  their aspect ratio, with a warning (OpenCV cannot open the writer for them).

  Args:
    path: output file (`.mp4`, or another of `VIDEO_SUFFIXES`; other names are refused).
    frames: `[T, H, W, 3]` uint8 RGB, a list of `[H, W, 3]` frames (all checked before the
      file is created), or an iterator of them (written as they come, so a long video need
      not be in memory; a bad frame stops the writing, removes the partial file and leaves
      a file at `path` as it was).
    fps: frame rate (0.01 to 65535; one MPEG-4 cannot time exactly is rounded to the
      nearest it can, `mp4v_fps`: 119.8765 -> 119.88).

  Returns:
    The path written.
  """
  path = pathlib.Path(path)
  check_utf8_path(path, "video")
  _check_suffix(path, VIDEO_SUFFIXES, "write_video writes mp4v video files; name one "
                f"{'/'.join(VIDEO_SUFFIXES)}")
  check_fps(fps, f"{path}: fps")
  if not path.parent.is_dir():  # OpenCV would only say it cannot open the writer
    raise FileNotFoundError(f"{path}: the folder {path.parent} does not exist")
  if path.is_dir() and not path.is_symlink():  # (the rename failed once every frame was
    # written, an iterator's frames consumed, naming the temporary file)
    raise IsADirectoryError(f"{path} is a folder; name the video file to write (e.g. "
                            f"{path / ('video' + path.suffix)})")
  if getattr(frames, "ndim", None) == 3 and frames.shape[-1] == 3:  # its rows taken for frames
    raise ValueError(f"{path}: frames must be [T, H, W, 3], got one image of shape "
                     f"{tuple(frames.shape)} (a video of one frame is image[None])")
  streamed = not isinstance(frames, (np.ndarray, list, tuple))
  warned: list[int] = []  # the 0..1 warning is given once per video, not once per frame
  if not streamed:  # all checked before the file is created
    checked = []
    for i, f in enumerate(frames):
      checked.append(_video_frame(path, i, f, checked[0].shape if checked else None, warned))
    frames = checked
  # Written under a temporary name beside `path` and renamed when complete: a bad frame of
  # an iterator, a full disk or Ctrl-C leave an existing file at `path` as it was (a link
  # at `path` is replaced, not written through).
  tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}.tmp{path.suffix}")
  writer, size = None, None
  try:
    for i, f in enumerate(frames):
      if streamed:
        f = _video_frame(path, i, f, size, warned)
      if writer is None:
        size = f.shape
        h, w = size[:2]
        scale = min(1.0, MP4V_MAX_SIDE / w, MP4V_MAX_SIDE / h)
        if scale < 1.0:
          h, w = max(1, int(h * scale)), max(1, int(w * scale))
          warnings.warn(f"{path}: frames of {size[0]}x{size[1]} are scaled to {h}x{w} (MPEG-4 "
                        f"video has at most {MP4V_MAX_SIDE} pixels a side)",
                        stacklevel=caller_stacklevel())
        he, we = h + h % 2, w + w % 2
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), mp4v_fps(fps),
                                 (we, he))
        if not writer.isOpened():
          writer = None
          raise OSError(f"{path}: OpenCV cannot open an mp4v video writer")
      if f.shape[:2] != (h, w):
        f = cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA)
      if (he, we) != (h, w):
        f = np.pad(f, ((0, he - h), (0, we - w), (0, 0)), mode="edge")
      # (RGB to BGR: cvtColor gives the same bytes as a reversed copy, faster)
      writer.write(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR))
    if writer is None:
      raise ValueError(f"{path}: no frames to write")
    writer.release()
    writer = None
    # OpenCV's writer reports no error: a disk that filled up left a file without its index
    # ("moov atom not found") under the final name, the run reported as a success.
    _check_written_video(path, tmp, i + 1)
    os.replace(tmp, path)
  finally:
    if writer is not None:
      writer.release()
    tmp.unlink(missing_ok=True)
  return path


def _check_written_video(path, tmp, frames: int) -> None:
  """An OSError unless the video just written to `tmp` opens with `frames` frames."""
  cap = cv2.VideoCapture(str(tmp))
  try:
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else None
  finally:
    cap.release()
  if count != frames:
    got = "does not open" if count is None else f"holds {count} frames"
    raise OSError(f"{path}: the video was not written completely: {frames} frames written, "
                  f"the file {got} (a full disk?){free_space_note(tmp.parent)}")


def _video_frame(path, i: int, frame, size, warned: list) -> np.ndarray:
  """Frame `i` as uint8 `[H, W, 3]`; a ValueError unless it is that (and `size`, if given).
  `as_uint8_image`'s warning is given for the first such frame only (noted in `warned`)."""
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    f = as_uint8_image(frame, f"{path} frame {i}")
  if caught and not warned:
    warned.append(i)
    warnings.warn(f"{caught[0].message} (said for the first such frame only)",
                  caught[0].category, stacklevel=caller_stacklevel())
  if f.ndim != 3 or f.shape[2] != 3 or min(f.shape[:2]) < 1 or (size and f.shape != size):
    raise ValueError(f"{path}: frame {i} has shape {f.shape}; expected RGB [H, W, 3] "
                     f"frames of one size{f' {size}' if size else ''}")
  return f


def depth_from_disparity(disp, fx: float, baseline: float, doffs: float = 0.0) -> np.ndarray:
  """Metric depth `Z = fx * baseline / (d + doffs)`; 0 where that denominator is not
  positive or `d` is not finite.

  Args:
    disp: `[..., H, W]` disparity (px).
    fx: focal length (px).
    baseline: stereo baseline (metres, or any unit: Z is in that unit).
    doffs: x-difference of the two cameras' principal points (px; Middlebury's `doffs`,
      `cx_right - cx_left`); 0 for cameras rectified to one principal point (KITTI).
      With doffs > 0 a disparity of 0 has a depth (fx * baseline / doffs): where 0 marks
      "no disparity" (a KITTI-style PNG, a sparse map), mask those pixels out yourself
      (`disparity_to_points(..., valid=disp > 0)`).

  Returns:
    `[..., H, W]` float32 depth; 0 where there is none (d + doffs <= 0 or not finite, or a
    depth beyond float32's range).

  Raises:
    ValueError: unless fx and baseline are finite and positive and doffs finite, each one
      number (a Python or NumPy number or a 0-d NumPy / JAX array: `K[0, 0]` will do).
  """
  k = check_intrinsics(fx=fx, baseline=baseline, doffs=doffs)
  fx, baseline, doffs = k["fx"], k["baseline"], k["doffs"]
  d = np.asarray(disp, np.float32) + np.float32(doffs)
  ok = np.isfinite(d) & (d > 0)
  z = np.zeros(d.shape, np.float32)
  with np.errstate(over="ignore"):
    z[ok] = np.float32(fx * baseline) / d[ok]
  z[np.isinf(z)] = 0  # a disparity so small that float32 depth overflows: no depth either
  return z


def disparity_to_points(disp, rgb, *, fx: float, fy: float, cx: float, cy: float,
                        baseline: float, doffs: float = 0.0, valid=None,
                        max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
  """Back-projects the left view's pixels with positive depth.

  Pixel (u, v) with depth Z (`depth_from_disparity`) maps to
  `((u - cx) Z / fx, (v - cy) Z / fy, Z)`: OpenCV's camera axes (x right, y down, z
  forward), in the baseline's unit.

  Args:
    disp: `[H, W]` disparity (px).
    rgb: `[H, W, 3]` colours of the left view: uint8 or numbers in 0..255 (`as_uint8_image`:
      a float frame's resize overshoot is clipped).
    fx, fy, cx, cy: intrinsics of the left camera (px); Python or NumPy numbers or 0-d
      arrays. A principal point outside the frame (`principal_point_inside`, which
      `sav-jax infer` enforces) gets a warning: intrinsics for another image size?
    baseline: stereo baseline.
    doffs: see `depth_from_disparity`.
    valid: optional extra `[H, W]` mask: bool, or weights (> 0.5 is valid, as in the
      metrics and `colorize`).
    max_depth: drop points farther than this (in the baseline's unit): disparities near
      0 (sky, far background) back-project to huge depths.

  Returns:
    `(xyz [N, 3] float32, colours [N, 3] uint8)`, rows in raster order.
  """
  d = np.asarray(disp, np.float32)
  rgb = as_uint8_image(rgb, "disparity_to_points rgb")
  if d.ndim != 2 or rgb.shape != (*d.shape, 3):
    raise ValueError(f"disparity_to_points: expected disp [H, W] and rgb [H, W, 3] of one "
                     f"frame, got {d.shape} and {rgb.shape}")
  if valid is not None and np.shape(valid) != d.shape:
    raise ValueError(f"disparity_to_points: valid mask shape {np.shape(valid)} differs from "
                     f"disp {d.shape}")
  far = {} if max_depth is None else {"max_depth": max_depth}
  k = check_intrinsics("disparity_to_points: ", fx=fx, fy=fy, baseline=baseline, cx=cx, cy=cy,
                       doffs=doffs, **far)
  fx, fy, cx, cy, baseline, doffs = (k[n] for n in ("fx", "fy", "cx", "cy", "baseline", "doffs"))
  max_depth = k.get("max_depth")
  if not principal_point_inside(cx, cy, *d.shape):
    warnings.warn(f"disparity_to_points: the principal point (cx {cx:g}, cy {cy:g}) is "
                  f"outside the {d.shape[0]}x{d.shape[1]} (height x width) map: intrinsics for "
                  "another image size? (scale fx, fy, cx, cy and doffs by the resize factor; "
                  "sav-jax infer refuses such a calibration)", stacklevel=caller_stacklevel())
  z = depth_from_disparity(d, fx, baseline, doffs)
  keep = z > 0
  if max_depth is not None:
    keep &= z <= max_depth
  if valid is not None:
    keep &= np.asarray(valid) > 0.5  # bool masks as they are (True > 0.5)
  v, u = np.nonzero(keep)
  zk = z[v, u]
  with np.errstate(over="ignore", invalid="ignore"):
    xyz = np.stack([(u - cx) * zk / fx, (v - cy) * zk / fy, zk], axis=-1).astype(np.float32)
  finite = np.isfinite(xyz).all(axis=1)  # x or y beyond float32 at depths near its limit
  return xyz[finite], rgb[v[finite], u[finite]]


def write_ply(path, xyz, colors, comments=()) -> int:
  """Writes a binary little-endian PLY point cloud.

  Args:
    path: output file.
    xyz: `[N, 3]` (or `[..., 3]`) float coordinates.
    colors: RGB of the same shape as `xyz`, uint8 or numbers in 0..255 (`as_uint8_image`).
    comments: lines for the header's `comment`s (the axes and unit, say), each printable
      ASCII on one line; viewers show or skip them, `read_ply` skips them.

  Returns:
    The number of points N.

  Raises:
    ValueError: `xyz` is not `[..., 3]` numbers or not finite in float32, `colors` has
      another shape or values outside 0..255 (beyond a float image's clipped overshoot,
      `as_uint8_image`), or a comment is not one line of printable ASCII (checked before the
      file is created).
  """
  comments = [comments] if isinstance(comments, str) else list(comments)
  for c in comments:
    if not isinstance(c, str) or not (c.isascii() and c.isprintable()):
      raise ValueError(f"write_ply: a comment must be one line of printable ASCII text, got "
                       f"{c!r}")
  xyz, colors = widened(np.asarray(xyz)), np.asarray(colors)
  if xyz.ndim < 1 or xyz.shape[-1] != 3 or xyz.dtype.kind not in "uif":
    raise ValueError(f"write_ply: xyz must be [N, 3] (or [..., 3]) numbers, got shape "
                     f"{xyz.shape} of dtype {xyz.dtype}")
  if colors.shape != xyz.shape:
    raise ValueError(f"write_ply: colors of shape {colors.shape} do not match xyz {xyz.shape}")
  colors = as_uint8_image(colors, "write_ply colors").reshape(-1, 3)
  with np.errstate(over="ignore"):
    xyz = xyz.astype(np.float32).reshape(-1, 3)
  bad = ~np.isfinite(xyz).all(axis=1)
  if bad.any():  # viewers reject or mis-scale such clouds (disparity_to_points drops them)
    raise ValueError(f"write_ply: {int(bad.sum())} of {len(xyz)} points are not finite in "
                     f"float32 (NaN, inf or beyond 3.4e38), the first at index "
                     f"{int(np.argmax(bad))}: drop them first")
  verts = np.empty(len(xyz), _PLY_DTYPE)
  for i, name in enumerate("xyz"):
    verts[name] = xyz[:, i]
  for i, name in enumerate(("red", "green", "blue")):
    verts[name] = colors[:, i]
  header = ("ply\nformat binary_little_endian 1.0\n"
            + "".join(f"comment {c}\n" for c in comments)
            + f"element vertex {len(verts)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            + "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
  with open(path, "wb") as fh:
    fh.write(header.encode("ascii"))
    fh.write(verts.tobytes())
  return len(verts)


def read_ply(path) -> tuple[np.ndarray, np.ndarray]:
  """Reads a PLY written by `write_ply`: `(xyz [N, 3] float32, rgb [N, 3] uint8)`.

  Raises FileNotFoundError when `path` is missing and ValueError naming it when it is not
  such a PLY file (other magic, format or vertex properties, or truncated).
  """
  with open(path, "rb") as fh:
    magic = fh.readline(64)  # not a whole binary file without newlines
    if magic.rstrip(b"\r\n") != b"ply":
      raise ValueError(f"{path}: not a PLY file (starts with {magic[:16]!r})")
    lines = ["ply"]
    while lines[-1] != "end_header":
      line = fh.readline()
      if not line:
        raise ValueError(f"{path}: truncated PLY header (no end_header)")
      try:
        lines.append(line.decode("ascii").strip())
      except UnicodeDecodeError:
        raise ValueError(f"{path}: PLY header line {len(lines) + 1} is not ASCII text "
                         f"({line[:16]!r})") from None
    if lines[1] != "format binary_little_endian 1.0":
      raise ValueError(f"{path}: unsupported PLY format {lines[1]!r}")
    elements = [i for i, l in enumerate(lines) if l.startswith("element")] + [len(lines)]
    first = lines[elements[0]].split() if len(elements) > 1 else []
    if len(first) != 3 or first[1] != "vertex" or not first[2].isdigit():
      raise ValueError(f"{path}: PLY header has no 'element vertex N' line first")
    count = int(first[2])
    props = [" ".join(l.split()) for l in lines[elements[0] + 1:elements[1]]
             if l.startswith("property")]
    want = ([f"property float {n}" for n in "xyz"]
            + [f"property uchar {n}" for n in ("red", "green", "blue")])
    if props != want:
      raise ValueError(f"{path}: PLY vertex properties {props} differ from write_ply's {want}")
    data = fh.read(count * _PLY_DTYPE.itemsize)
  if len(data) != count * _PLY_DTYPE.itemsize:
    raise ValueError(f"{path}: header says {count} vertices, file has "
                     f"{len(data) / _PLY_DTYPE.itemsize:g} ({len(data)} bytes of data)")
  verts = np.frombuffer(data, _PLY_DTYPE)
  xyz = np.stack([verts[n] for n in "xyz"], axis=-1).astype(np.float32)
  rgb = np.stack([verts[n] for n in ("red", "green", "blue")], axis=-1)
  return xyz, rgb


def _map_to_write(path, data, what: str, rgb: bool) -> np.ndarray:
  """`data` as float32, or a ValueError naming `path` unless it is `[H, W]` (or `[H, W, 3]`
  with `rgb`) with H, W >= 1."""
  a = np.asarray(data, np.float32)
  if not (a.ndim == 2 or (rgb and a.ndim == 3 and a.shape[2] == 3)) or 0 in a.shape:
    shapes = "[H, W] or [H, W, 3] arrays" if rgb else "[H, W] maps"
    raise ValueError(f"{path}: {what} stores {shapes} with H, W >= 1, got shape {a.shape}")
  return a


# The largest disparity a KITTI-style 16-bit PNG holds (px); larger ones are stored as it.
PNG16_MAX_DISPARITY = 65535 / 256.0


def write_png16(path, disp) -> int:
  """16-bit PNG disparity, KITTI convention (`round(256 d)` clipped to 1..65535, 0 = invalid).

  The format holds disparities up to `PNG16_MAX_DISPARITY` (255.996 px): larger ones are
  stored as that value, still valid; the return value counts them, so that callers can warn
  (use a float format, .npy / .pfm / .exr, for such maps). Non-positive and non-finite
  values are stored as 0 (invalid).

  `path` must end in `.png` (OpenCV picks the format from the name: another one would store
  the values lossily or scaled); a file there is replaced.

  Returns:
    The number of saturated pixels.
  """
  _check_suffix(path, (".png",), "a 16-bit PNG disparity file must be named *.png")
  d = _map_to_write(path, disp, "a 16-bit PNG disparity file", rgb=False)
  ok = np.isfinite(d) & (d > 0)
  v = np.zeros(d.shape, np.uint16)
  scaled = np.round(d[ok].astype(np.float64) * 256.0)
  v[ok] = np.clip(scaled, 1, 65535).astype(np.uint16)
  encoded, data = cv2.imencode(".png", v)
  if not encoded:
    raise OSError(f"{path}: OpenCV could not encode the PNG")
  with open(path, "wb") as fh:  # (any name: OpenCV's imwrite crashed on non-UTF-8 ones)
    fh.write(data.tobytes())
  return int(np.count_nonzero(scaled > 65535))


def read_png16(path) -> tuple[np.ndarray, np.ndarray]:
  """Reads a KITTI-style 16-bit PNG: `(disparity [H, W] float32, valid [H, W] bool)`.

  Raises FileNotFoundError / ValueError naming the file (`frame_io.read_png_uint16`).
  """
  from sav_jax.data import frame_io  # pylint: disable=import-outside-toplevel
  v = frame_io.read_png_uint16(path)
  return v.astype(np.float32) / 256.0, v > 0


def write_pfm(path, data) -> None:
  """PFM file (`Pf` for `[H, W]`, `PF` for `[H, W, 3]`), little-endian, bottom row first;
  a file at `path` is replaced. `path` must end in `.pfm`."""
  _check_suffix(path, (".pfm",), "write_pfm writes PFM files; name one .pfm")
  a = _map_to_write(path, data, "PFM", rgb=True)
  kind = "Pf" if a.ndim == 2 else "PF"
  with open(path, "wb") as fh:
    fh.write(f"{kind}\n{a.shape[1]} {a.shape[0]}\n-1.0\n".encode("ascii"))
    fh.write(np.ascontiguousarray(a[::-1]).astype("<f4").tobytes())


def read_pfm(path) -> np.ndarray:
  """Reads a PFM file (either endianness) into `[H, W]` or `[H, W, 3]` float32, top row first.

  The reader of `frame_io.read_pfm`: FileNotFoundError / ValueError naming the file when it
  is missing, not a PFM, has a malformed header or less data than the header declares.
  """
  from sav_jax.data import frame_io  # pylint: disable=import-outside-toplevel
  return frame_io.read_pfm(path)


def write_exr(path, data, channel: str = "Y") -> None:
  """OpenEXR file of float32 values (`[H, W]` -> one channel, `[H, W, 3]` -> R, G, B); a file
  at `path` is replaced."""
  import OpenEXR  # pylint: disable=import-outside-toplevel
  _check_suffix(path, (".exr",), "write_exr writes OpenEXR files; name one .exr")
  if not (isinstance(channel, str) and channel):
    raise ValueError(f"channel must be a non-empty channel name such as 'Y', got {channel!r}")
  a = _map_to_write(path, data, "EXR", rgb=True)
  if a.ndim == 2:
    channels = {channel: np.ascontiguousarray(a)}
  else:
    channels = {c: np.ascontiguousarray(a[..., i]) for i, c in enumerate("RGB")}
  header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
  encoded = io.BytesIO()
  with OpenEXR.File(header, channels) as f:
    f.write(encoded)
  with open(path, "wb") as fh:  # (any name: OpenEXR's own writer took UTF-8 names only)
    fh.write(encoded.getvalue())


def read_exr(path, channel: str | None = None) -> np.ndarray:
  """Reads an EXR channel (default: the only one, or R, G, B stacked) as float32.

  The reader of `frame_io.read_exr`: FileNotFoundError / ValueError naming the file when it
  is missing, not an EXR file, or has no such channel.
  """
  from sav_jax.data import frame_io  # pylint: disable=import-outside-toplevel
  return frame_io.read_exr(path, channel)

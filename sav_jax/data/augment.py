"""Training augmentation of stereo clips, following the official SAV augmentors.

Order and draws (`docs/datasets.md`, section 3; official `datasets/augmentor.py`):

1. Photometric (ColorJitter with a random order of brightness, contrast, saturation
   and hue, then gamma). With probability `asymmetric_prob` every image (each frame,
   each view) gets its own parameters; otherwise one parameter set is applied to all
   2T images as one stacked image (so the contrast mean is over the whole clip).
   Sparse datasets are always symmetric.
2. Eraser: per frame and view with probability `eraser_prob`, 1-2 rectangles (corner
   uniform in the image, sides in [50, 100)) filled with the mean colour of frame 0's
   left image; before resizing.
3. Scale `s = 2**U(scale_range)`, with probability `stretch_prob` independently
   stretched per axis by `2**U(+-max_stretch)`, both clamped to at least
   `max((ch+8)/H, (cw+8)/W)`. Images and dense disparity: cv2 bilinear resize,
   disparity times sx. Sparse GT: valid points scattered to rounded scaled
   coordinates (points landing on row or column 0 are dropped).
4. Crop, shared by all frames. Dense with y-jitter: `y0 ~ [2, H-ch-2)`,
   `x0 ~ [2, W-cw-2)`, the right view (and right GT) of each frame at
   `y0 + randint[-2, 2]`. Sparse (or y-jitter off): a plain crop.
5. Valid: dense datasets recompute `|d| < 512 and d != 0`; sparse ones carry theirs.

The photometric operations are written with numpy/OpenCV and reproduce what the official
torchvision ColorJitter does to PIL images: ImageEnhance's blends in float32, truncated to
uint8 after each operation, and the hue shift through PIL's 8-bit HSV conversion (hue in
1/255 turns, truncated), which OpenCV's HSV and greyscale do not match (up to 6 grey
levels apart). Tested against Pillow: identical on every 8-bit colour.
"""

from __future__ import annotations

import dataclasses
import math
import threading

import cv2
import numpy as np

from sav_jax._checks import is_int
from sav_jax.data import frame_io

# (disparity key, valid key, image key it belongs to).
_GT = (("disparity", "valid", "left"), ("right_disparity", "right_valid", "right"))


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
  """Ranges of the official training augmentation (defaults: the SAV training script).

  Attributes:
    crop_size: (height, width) of the output crop.
    scale_range: range of log2 of the isotropic scale.
    stretch_prob: probability of the per-axis stretch.
    max_stretch: per-axis stretch range, log2 (+-).
    spatial_prob: probability of resizing at all (official 1.0).
    photometric: switch for the colour jitter (step 1).
    brightness, contrast, saturation: ranges of the enhance factors.
    hue: range of the hue shift, in turns (+-0.5/3.14 officially), within [-0.5, 0.5].
    gamma, gain: ranges of the gamma adjustment (official: off, (1, 1)).
    asymmetric_prob: probability of independent jitter per image (dense only).
    eraser_prob: per frame and view probability of erasing rectangles (0: off).
    eraser_count: (min, max) rectangles, inclusive.
    eraser_size: [min, max) side of a rectangle, px.
    yjitter: vertical jitter of the right view's crop (dense only).
    yjitter_range: its amplitude, px (+-); the crop keeps max(2, it) px from the frame's
      top and bottom where the frame allows (officially 2 and 2).
    max_disparity: dense valid rule |d| < max_disparity.
  """

  crop_size: tuple[int, int] = (256, 512)
  scale_range: tuple[float, float] = (-0.2, 0.4)
  stretch_prob: float = 0.8
  max_stretch: float = 0.2
  spatial_prob: float = 1.0
  photometric: bool = True
  brightness: tuple[float, float] = (0.6, 1.4)
  contrast: tuple[float, float] = (0.6, 1.4)
  saturation: tuple[float, float] = (0.0, 1.4)
  hue: tuple[float, float] = (-0.5 / 3.14, 0.5 / 3.14)
  gamma: tuple[float, float] = (1.0, 1.0)
  gain: tuple[float, float] = (1.0, 1.0)
  asymmetric_prob: float = 0.2
  eraser_prob: float = 0.5
  eraser_count: tuple[int, int] = (1, 2)
  eraser_size: tuple[int, int] = (50, 100)
  yjitter: bool = True
  yjitter_range: int = 2
  max_disparity: float = 512.0

  def __post_init__(self):
    def pair(name):
      value = getattr(self, name)
      try:
        lo, hi = value
        ok = all(math.isfinite(v) for v in (lo, hi))
      except (TypeError, ValueError):
        ok = False
      if not ok:
        raise ValueError(f"AugmentConfig.{name} must be a pair of finite numbers, got {value!r}")
      return lo, hi

    def ints(value):
      try:
        return all(is_int(v) for v in value)
      except TypeError:
        return False

    for name in ("crop_size", "eraser_count", "eraser_size", "yjitter_range"):
      value = getattr(self, name)
      if not (is_int(value) if name == "yjitter_range" else ints(value)):
        raise ValueError(f"AugmentConfig.{name} must be "
                         f"{'an integer' if name == 'yjitter_range' else 'a pair of integers'}, "
                         f"got {value!r}")
    ch, cw = pair("crop_size")
    if ch < 1 or cw < 1:
      raise ValueError(f"AugmentConfig.crop_size must be positive, got {self.crop_size}")
    for name in ("scale_range", "brightness", "contrast", "saturation", "hue", "gamma", "gain",
                 "eraser_count", "eraser_size"):
      lo, hi = pair(name)
      if lo > hi:
        raise ValueError(f"AugmentConfig.{name} must be (min, max), got {(lo, hi)}")
    for name in ("brightness", "contrast", "saturation", "gain"):
      if getattr(self, name)[0] < 0:
        raise ValueError(f"AugmentConfig.{name} factors must be >= 0, got {getattr(self, name)}")
    if self.gamma[0] <= 0:
      raise ValueError(f"AugmentConfig.gamma must be > 0, got {self.gamma}")
    if not -0.5 <= self.hue[0] <= self.hue[1] <= 0.5:  # turns: +-0.5 is the whole circle
      raise ValueError(f"AugmentConfig.hue must lie in [-0.5, 0.5] (turns of the colour "
                       f"circle, as torchvision's ColorJitter), got {self.hue}")
    for name in ("stretch_prob", "spatial_prob", "asymmetric_prob", "eraser_prob"):
      if not 0 <= getattr(self, name) <= 1:
        raise ValueError(f"AugmentConfig.{name} is a probability in [0, 1], got "
                         f"{getattr(self, name)!r}")
    if not (self.yjitter_range >= 0 and self.max_stretch >= 0 and self.max_disparity > 0):
      raise ValueError("AugmentConfig.yjitter_range and max_stretch must be >= 0 and "
                       f"max_disparity > 0, got {self.yjitter_range!r}, {self.max_stretch!r}, "
                       f"{self.max_disparity!r}")
    if not -30 < self.scale_range[1] < 30:
      raise ValueError(f"AugmentConfig.scale_range is a range of log2 scales, got "
                       f"{self.scale_range}")
    if (self.eraser_size[0] >= self.eraser_size[1] or self.eraser_size[0] < 1
        or self.eraser_count[0] < 0):
      raise ValueError("AugmentConfig.eraser_size must be [min, max) with 1 <= min < max and "
                       f"eraser_count non-negative, got {self.eraser_size}, {self.eraser_count}")


class _Jitter:
  """One draw of the photometric parameters (torchvision ColorJitter + AdjustGamma)."""

  def __init__(self, cfg: AugmentConfig, rng: np.random.Generator):
    self.order = rng.permutation(4)
    self.brightness = rng.uniform(*cfg.brightness)
    self.contrast = rng.uniform(*cfg.contrast)
    self.saturation = rng.uniform(*cfg.saturation)
    self.hue = rng.uniform(*cfg.hue)
    self.gamma = rng.uniform(*cfg.gamma)
    self.gain = rng.uniform(*cfg.gain)

    # torchvision leaves out an operation whose range is its identity (e.g. hue=0); a
    # drawn factor of exactly 1 (or a hue shift under 1/255) still runs, lossy HSV included
    ranges = (cfg.brightness, cfg.contrast, cfg.saturation, cfg.hue)
    identity = ((1.0, 1.0),) * 3 + ((0.0, 0.0),)
    self.order = [op for op in self.order
                  if tuple(float(v) for v in ranges[op]) != identity[op]]

  def __call__(self, images: np.ndarray) -> np.ndarray:
    """Applies the draw to [N, H, W, 3] uint8 RGB as one image (stats over all N)."""
    n, h, w, _ = images.shape
    x = np.ascontiguousarray(images).reshape(n * h, w, 3)  # one 2-D image for OpenCV
    for op in self.order:
      if op == 0:  # brightness: blend with black
        x = _lut(x, _blend(0, self.brightness))
      elif op == 1:  # contrast: blend with the rounded mean grey level of the image
        mean = int(_grey(x).mean(dtype=np.float64) + 0.5)
        x = _lut(x, _blend(mean, self.contrast))
      elif op == 2:  # saturation: blend with the grey image
        x = _saturate(x, self.saturation)
      else:
        x = _shift_hue(x, int(self.hue * 255))  # int(): truncation, as np.int8(h*255)
    if self.gamma != 1.0 or self.gain != 1.0:
      x = _lut(x, 255.999 * self.gain * (np.arange(256) / 255.0) ** self.gamma)
    return x.reshape(n, h, w, 3)


def _lut(x: np.ndarray, table: np.ndarray) -> np.ndarray:
  """Per-value mapping of uint8 `x` through a 256-entry float table (PIL-style
  blend output: clipped to [0, 255], truncated)."""
  return cv2.LUT(x, np.clip(table, 0, 255).astype(np.uint8))


def _blend(level, factor: float) -> np.ndarray:
  """PIL's `Image.blend(degenerate, x, factor)` for a constant degenerate image `level`, as
  a table over x = 0..255: float32 `level + factor * (x - level)` (clipped by `_lut`)."""
  level = np.asarray(level, np.float32)  # one level, or a column of them
  return level + np.float32(factor) * (np.arange(256, dtype=np.float32) - level)


def _grey(x: np.ndarray) -> np.ndarray:
  """PIL's `convert("L")` of uint8 RGB `[..., 3]`: ITU-R 601 luma in 16-bit fixed point,
  rounded (OpenCV's 14-bit weights differ by a grey level on ~0.1% of colours)."""
  x = x.astype(np.int32)
  return ((x[..., 0] * 19595 + x[..., 1] * 38470 + x[..., 2] * 7471 + 0x8000) >> 16
          ).astype(np.uint8)


def _saturate(x: np.ndarray, factor: float) -> np.ndarray:
  """PIL's `ImageEnhance.Color`: `Image.blend(grey, x, factor)`, in float32, truncated to
  [0, 255]."""
  table = _blend(np.arange(256)[:, None], factor)  # [grey, value]
  table = np.clip(table, 0, 255).astype(np.uint8).reshape(-1)  # [grey * 256 + value]
  return table[(_grey(x).astype(np.uint16)[..., None] << 8) | x]


def _shift_hue(x: np.ndarray, shift: int) -> np.ndarray:
  """torchvision's `adjust_hue` of a PIL image: `x` ([H, W, 3] uint8 RGB) to PIL's 8-bit
  HSV, hue plus `shift` (mod 256), back to RGB; the round trip alone changes values."""
  hsv = _rgb_to_hsv_pil(x)
  hsv[..., 0] += np.uint8(shift % 256)  # uint8 arithmetic wraps, as the hue circle does
  return _hsv_to_rgb_pil(hsv)


def _pil_hue(rgb: np.ndarray) -> np.ndarray:
  """PIL's 8-bit hue of `[..., 3]` int RGB (its `rgb2hsv` in Convert.c: float32 ratios,
  the wrap in double precision, truncated); 0 for grey."""
  r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
  maxc, minc = rgb.max(-1), rgb.min(-1)
  span = np.where(maxc == minc, 1, maxc - minc).astype(np.float32)
  rc, gc, bc = ((maxc - c).astype(np.float32) / span for c in (r, g, b))
  h = np.where(r == maxc, (bc - gc).astype(np.float64),
               np.where(g == maxc, 2.0 + rc.astype(np.float64) - bc,
                        4.0 + gc.astype(np.float64) - rc)).astype(np.float32)
  h = np.fmod(h.astype(np.float64) / 6.0 + 1.0, 1.0).astype(np.float32)
  return np.where(maxc == minc, 0, np.clip((h.astype(np.float64) * 255.0).astype(np.int32),
                                           0, 255)).astype(np.uint8)


_HSV_LOCK = threading.Lock()
_HSV_TABLES = []


def _hsv_tables():
  """`_build_hsv_tables()`, built once per process: a lock makes grain's reader threads,
  which reach their first hue jitter together, wait for one build (each build peaks at
  ~300 MB; 8 threads built their own copies at once)."""
  with _HSV_LOCK:
    if not _HSV_TABLES:
      _HSV_TABLES.append(_build_hsv_tables())
    return _HSV_TABLES[0]


def _build_hsv_tables():
  """Lookup tables of PIL's HSV conversions, exact for every 8-bit colour (64 MB, built
  in ~2 s).

  `hue[(r << 16) | (g << 8) | b]`: hue depends only on the colour less its minimum
  (equalities between channels decide PIL's branch), which has a zero channel, so it is
  computed on 3 x 256 x 256 colours and spread. `sat[max - min, max]`. Back to RGB,
  `rgb[(h << 16) | (s << 8) | v]`: the hue's sixth orders v, `p = round(v (1 - s))`,
  `q = round(v (1 - s f))` and `t = round(v (1 - s (1 - f)))` (double, from float32 `s`
  and `f`, rounded half up); grey (s = 0) is (v, v, v).
  """
  a, b = (c.ravel() for c in np.meshgrid(np.arange(256), np.arange(256), indexing="ij"))
  zero = np.zeros_like(a)
  small = np.stack([_pil_hue(np.stack(c, -1)) for c in ((zero, a, b), (a, zero, b),
                                                        (a, b, zero))]).reshape(3, 256, 256)
  hue = np.empty((256, 256, 256), np.uint8)
  for r in range(256):
    rgb = np.stack(np.broadcast_arrays(np.int32(r), a.reshape(256, 256), b.reshape(256, 256)),
                   -1)
    d = rgb - rgb.min(-1, keepdims=True)
    hue[r] = np.where(d[..., 0] == 0, small[0][d[..., 1], d[..., 2]],
                      np.where(d[..., 1] == 0, small[1][d[..., 0], d[..., 2]],
                               small[2][d[..., 0], d[..., 1]]))
  span, maxc = np.meshgrid(np.arange(256), np.arange(256), indexing="ij")
  sat = (span.astype(np.float32) / np.maximum(maxc, 1).astype(np.float32)).astype(np.float64)
  sat = np.where(span <= maxc, np.clip((sat * 255.0).astype(np.int32), 0, 255), 0)
  h = np.arange(256, dtype=np.float64)
  sector = np.floor(h * 6.0 / 255.0)
  f = (h * 6.0 / 255.0 - sector).astype(np.float32)[:, None, None]
  fs = (np.arange(256) / 255.0).astype(np.float32)[None, :, None]
  v = np.arange(256, dtype=np.float64)[None, None, :]
  rounded = lambda k: np.floor(v * k.astype(np.float64) + 0.5).astype(np.uint8)
  p = np.broadcast_to(rounded(1.0 - fs.astype(np.float64)), (256, 256, 256))
  q = rounded(1.0 - (fs * f).astype(np.float64))
  t = rounded(1.0 - (fs * (np.float32(1.0) - f)).astype(np.float64))
  v = np.broadcast_to(v.astype(np.uint8), (256, 256, 256))
  # channel order by sector: (v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)
  orders = ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))
  rgb = np.empty((256, 256, 256, 3), np.uint8)
  for hh, i in enumerate(sector.astype(np.int64) % 6):
    rgb[hh] = np.stack([c[hh] for c in orders[i]], -1)
  rgb[:, 0] = v[0, 0][:, None]  # s = 0: grey
  return hue.reshape(-1), sat.astype(np.uint8), rgb.reshape(-1, 3)


def _code(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
  """The 24-bit index `(a << 16) | (b << 8) | c` of uint8 planes."""
  return (a.astype(np.int32) << 16) | (b.astype(np.int32) << 8) | c


def _rgb_to_hsv_pil(x: np.ndarray) -> np.ndarray:
  """PIL's RGB -> HSV (`Image.convert("HSV")`) of `[..., 3]` uint8 RGB, by table."""
  hue, sat, _ = _hsv_tables()
  r, g, b = x[..., 0], x[..., 1], x[..., 2]
  maxc, minc = np.maximum(np.maximum(r, g), b), np.minimum(np.minimum(r, g), b)
  return np.stack([hue[_code(r, g, b)], sat[maxc - minc, maxc], maxc], -1)


def _hsv_to_rgb_pil(hsv: np.ndarray) -> np.ndarray:
  """PIL's HSV -> RGB (`Image.convert("RGB")` of an HSV image) of `[..., 3]` uint8, by
  table."""
  return np.take(_hsv_tables()[2], _code(hsv[..., 0], hsv[..., 1], hsv[..., 2]), axis=0)


def _photometric(left, right, cfg: AugmentConfig, rng, sparse: bool):
  """Step 1 on [T, H, W, 3] uint8 views; returns new arrays."""
  if not sparse and rng.random() < cfg.asymmetric_prob:
    left, right = left.copy(), right.copy()
    for t in range(left.shape[0]):
      for view in (left, right):
        view[t] = _Jitter(cfg, rng)(view[t:t + 1])[0]
    return left, right
  out = _Jitter(cfg, rng)(np.concatenate([left, right]))
  return out[:len(left)], out[len(left):]


def _erase(left: np.ndarray, right: np.ndarray, cfg: AugmentConfig, rng) -> None:
  """Step 2, in place."""
  t, h, w = left.shape[:3]
  for i in range(t):
    for view in (left, right):
      if rng.random() < cfg.eraser_prob:
        # Recomputed per event (frame 0's left may itself have been erased already).
        fill = np.array(cv2.mean(left[0])[:3]).astype(np.uint8)
        for _ in range(int(rng.integers(cfg.eraser_count[0], cfg.eraser_count[1] + 1))):
          x0, y0 = int(rng.integers(0, w)), int(rng.integers(0, h))
          dx, dy = (int(rng.integers(*cfg.eraser_size)) for _ in range(2))
          view[i, y0:y0 + dy, x0:x0 + dx] = fill


def _scales(h: int, w: int, cfg: AugmentConfig, rng) -> tuple[float, float]:
  """Step 3's (sx, sy)."""
  min_scale = max((cfg.crop_size[0] + 8) / h, (cfg.crop_size[1] + 8) / w)
  sx = sy = 2.0 ** rng.uniform(*cfg.scale_range)
  if rng.random() < cfg.stretch_prob:
    sx *= 2.0 ** rng.uniform(-cfg.max_stretch, cfg.max_stretch)
    sy *= 2.0 ** rng.uniform(-cfg.max_stretch, cfg.max_stretch)
  return max(sx, min_scale), max(sy, min_scale)


def _resize(x: np.ndarray, sx: float, sy: float) -> np.ndarray:
  """cv2 bilinear resize of every frame of [T, H, W, ...]."""
  return np.stack([cv2.resize(f, None, fx=sx, fy=sy, interpolation=cv2.INTER_LINEAR)
                   for f in x])


def _resize_sparse(disp: np.ndarray, valid: np.ndarray, sx: float, sy: float, size):
  """Scatters valid points of one [H, W] map to rounded scaled coordinates."""
  h1, w1 = size
  ys, xs = np.nonzero(valid)
  xx = np.round(xs * sx).astype(np.int64)
  yy = np.round(ys * sy).astype(np.int64)
  keep = (xx > 0) & (xx < w1) & (yy > 0) & (yy < h1)
  target = (yy * w1 + xx)[keep]
  out_d = np.zeros(h1 * w1, np.float32)
  out_v = np.zeros(h1 * w1, bool)
  # Row-major point order: where points collide, the last one wins, as officially.
  out_d[target] = disp[ys[keep], xs[keep]] * np.float32(sx)
  out_v[target] = True
  return out_d.reshape(h1, w1), out_v.reshape(h1, w1)


def _spatial(out: dict, cfg: AugmentConfig, rng, sparse: bool) -> None:
  """Step 3 on `out` (in place of its entries)."""
  h, w = out["left"].shape[1:3]
  sx, sy = _scales(h, w, cfg, rng)
  if not rng.random() < cfg.spatial_prob:
    return
  out["left"], out["right"] = _resize(out["left"], sx, sy), _resize(out["right"], sx, sy)
  size = out["left"].shape[1:3]
  for dkey, vkey, _ in _GT:
    if out.get(dkey) is None:
      continue
    if sparse:
      maps = [_resize_sparse(d, v, sx, sy, size) for d, v in zip(out[dkey], out[vkey])]
      out[dkey] = np.stack([m[0] for m in maps])
      out[vkey] = np.stack([m[1] for m in maps])
    else:
      out[dkey] = _resize(out[dkey].astype(np.float32), sx, sy) * np.float32(sx)


def _crop(out: dict, cfg: AugmentConfig, rng, jitter: bool) -> None:
  """Step 4 on `out` (in place of its entries)."""
  ch, cw = cfg.crop_size
  t, h, w = out["left"].shape[:3]
  if h < ch or w < cw:
    raise ValueError(
        f"cannot crop {cfg.crop_size} from {(h, w)} frames: the crop is larger than the "
        f"frames, and the clip was not resized (spatial_prob={cfg.spatial_prob:g}: clips drawn "
        "without the spatial transform keep their size; the official training resizes every "
        "clip, spatial_prob=1)")
  r = cfg.yjitter_range if jitter else 0
  # The official y-jitter crop keeps a 2 px margin (its jitter is +-2): a larger jitter
  # keeps its own in y, so that the right view's rows are not clipped at the frame's edge.
  m, my = (2, max(2, r)) if jitter else (0, 0)
  # Frames within the margin of the crop (where the official randint fails): it shrinks.
  y0 = min(int(rng.integers(my, max(h - ch - my, my + 1))), h - ch)
  x0 = min(int(rng.integers(m, max(w - cw - m, m + 1))), w - cw)
  y1 = [min(max(y0 + int(rng.integers(-r, r + 1)), 0), h - ch) if jitter else y0
        for _ in range(t)]
  for dkey, vkey, view in _GT:
    keys = [k for k in (view, dkey, vkey) if out.get(k) is not None]
    for k in keys:
      rows = [y0] * t if view == "left" else y1
      out[k] = np.stack([out[k][i, y:y + ch, x0:x0 + cw] for i, y in enumerate(rows)])


def augment_clip(clip: dict, cfg: AugmentConfig, rng: np.random.Generator,
                 sparse: bool | None = None) -> dict:
  """Augments one stereo clip as the official training loader does.

  Args:
    clip: `left`, `right` [T, H, W, 3] uint8; `disparity` [T, H, W] float32 positive
      px (or None); `valid` [T, H, W] bool; optionally `right_disparity` /
      `right_valid`, and `sparse`. Other keys are passed through unchanged. A dense
      clip's `valid` is not read (step 5 recomputes it from the disparity, as the
      official augmentor does): a pixel it marks invalid needs a disparity of 0 (or of
      512 px or more) there, as `pipeline.honour_dense_masks` sets before training.
    cfg: augmentation ranges.
    rng: the only source of randomness (same seed, same output).
    sparse: sparse GT (KITTI, Sintel): symmetric colour, scatter resize, plain crop,
      valid carried. None reads `clip["sparse"]` (default False).

  Returns:
    The same keys with images [T, ch, cw, 3] uint8, disparity [T, ch, cw] float32
    (scaled by sx) and valid [T, ch, cw] bool.
  """
  sparse = bool(clip.get("sparse", False)) if sparse is None else bool(sparse)
  left, right = np.asarray(clip["left"]), np.asarray(clip["right"])
  if (left.ndim != 4 or left.shape[-1] != 3 or left.shape != right.shape
      or left.dtype != np.uint8 or 0 in left.shape):
    raise ValueError(f"left/right must be equal [T, H, W, 3] uint8 with T, H, W >= 1, got "
                     f"{left.shape} {left.dtype} and {right.shape} {right.dtype}")
  out = dict(clip)
  if cfg.photometric:  # returns new arrays
    left, right = _photometric(left, right, cfg, rng, sparse)
  else:  # the eraser writes in place: never into the caller's arrays
    left, right = left.copy(), right.copy()
  _erase(left, right, cfg, rng)
  out["left"], out["right"] = left, right
  for dkey, vkey, _ in _GT:
    if out.get(dkey) is not None:
      out[dkey] = np.asarray(out[dkey], np.float32)
      if out[dkey].shape != left.shape[:3]:
        raise ValueError(f"{dkey} is {out[dkey].shape}, images are {left.shape[:3]}")
      if sparse and out.get(vkey) is None:
        raise ValueError(f"sparse clips need `{vkey}` with `{dkey}`")
      if sparse:  # bool, or weights (`frame_io.valid_mask`: 0.3 was True)
        out[vkey] = frame_io.valid_mask(out[vkey])
        if out[vkey].shape != left.shape[:3]:
          raise ValueError(f"{vkey} is {out[vkey].shape}, images are {left.shape[:3]}")
      else:
        out[vkey] = None  # recomputed from the final disparity below
  _spatial(out, cfg, rng, sparse)
  _crop(out, cfg, rng, jitter=cfg.yjitter and not sparse)
  for dkey, vkey, _ in _GT:
    if out.get(dkey) is not None and not sparse:
      out[vkey] = frame_io.dense_valid(out[dkey], cfg.max_disparity)
  for k in ("left", "right") + tuple(k for g in _GT for k in g[:2]):
    if out.get(k) is not None:
      out[k] = np.ascontiguousarray(out[k])
  return out

"""Procedural stereo videos with exact ground truth (the project's built-in data).

A scene is a textured background plane (far, possibly slanted) and `num_objects`
textured planar shapes (rectangles, ellipses, star-shaped polygons), each moving
smoothly in 3D: image-plane translation, rotation about its normal, and geometric
depth change (approaching or receding changes size and disparity together).

Cameras: a rectified pinhole pair with focal `fx` (px), principal point at the image
centre and baseline `B` (m); the left camera is at the origin, the right one at
`(B, 0, 0)`. A point at depth Z has disparity `d = fx * B / Z` and is seen at
`x_r = x_l - d` on the same row.

Rendering is exact ray casting: for every pixel of each view and every layer, the
ray is intersected with the layer's plane (so slanted layers get their exact
per-pixel depth), the hit is tested against the shape, and a z-buffer keeps the
nearest surface. Colours come from a bilinear lookup into a smooth periodic texture
attached to the plane, so the left and right views sample the very same texture
function. Validity is exact too: a left pixel is invalid when its 3D point leaves
the right image (`x - d < 0` or `x - d > W - 1`) or when the segment from the right
camera to the point crosses a nearer surface (tested analytically per layer, not on
the right pixel grid).

Anti-aliasing: none beyond band-limited textures (one ray per pixel centre;
silhouettes are hard-edged). Consequently, warping the right view by the GT
disparity reproduces the left view up to bilinear-resampling and 8-bit rounding
error (about 0.4 grey levels mean, 1.7 at the 99th percentile with the default
`texture_min_cell=4`), except within the bilinear footprint of a depth discontinuity
in the right image; tests/data/test_synthetic.py asserts these bounds.

Usage:

  cfg = SyntheticConfig(frames=5, height=256, width=512)
  clip = generate_clip(cfg, index=0)          # dict of numpy arrays, see generate_clip
  source = SyntheticStereoVideo(cfg, 1000)    # grain random-access source
  ds = grain.MapDataset.source(source)
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import operator
from typing import NamedTuple

import cv2
import numpy as np

from sav_jax._checks import is_int

from sav_jax.data.raycast import Camera, Layer, plane_axes, render_view, unit, valid_mask
from sav_jax.data.textures import TEXTURE_KINDS, make_texture

SHAPES = ("rectangle", "ellipse", "polygon")


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
  """Configuration of the synthetic stereo-video generator.

  Attributes:
    frames: frames per clip, T.
    height: image height H (px).
    width: image width W (px).
    num_objects: moving objects in front of the background (0..254).
    min_disparity: smallest disparity anywhere in the scene (px, > 0).
    max_disparity: largest disparity anywhere in the scene (px, < width).
    background_fraction: the background's disparities lie in the lowest
      `background_fraction` of `[min_disparity, max_disparity]`; objects in the rest,
      so objects are always in front of the background.
    background_slant: 0..1, how much of its disparity band the background's slant
      may use (0 = fronto-parallel).
    background_speed: max drift of the background texture, px/frame at its centre.
    max_speed: max image-plane speed of object centres (px/frame).
    max_rotation: max rotation speed of objects about their normal (rad/frame).
    max_depth_change: max relative depth change per frame, |Z_t+1 / Z_t - 1| (< 0.5).
    max_tilt: max angle between an object's normal and the optical axis (rad, < 1.3).
    object_size: (min, max) object diameter at frame 0 as a fraction of min(H, W).
    shapes: object shapes to draw from (`SHAPES`).
    textures: texture patterns to draw from (`textures.TEXTURE_KINDS`).
    texture_min_cell: finest texture detail in texels (~px); power of two in 2..32.
      Smaller is sharper but makes bilinear resampling less exact.
    texture_contrast: scales the texture colour amplitudes (> 0).
    noise_std: std of Gaussian photometric noise (grey levels), independent per view
      and frame; 0 (default) keeps the views photometrically consistent.
    focal: focal length fx in px; None means `width`.
    baseline: stereo baseline in metres (> 0).
    seed: base seed; clip i uses the seed sequence (seed, i).
  """

  frames: int = 5
  height: int = 256
  width: int = 512
  num_objects: int = 6
  min_disparity: float = 2.0
  max_disparity: float = 64.0
  background_fraction: float = 0.25
  background_slant: float = 0.8
  background_speed: float = 1.0
  max_speed: float = 4.0
  max_rotation: float = 0.05
  max_depth_change: float = 0.03
  max_tilt: float = 0.6
  object_size: tuple[float, float] = (0.2, 0.5)
  shapes: tuple[str, ...] = SHAPES
  textures: tuple[str, ...] = TEXTURE_KINDS
  texture_min_cell: int = 4
  texture_contrast: float = 1.0
  noise_std: float = 0.0
  focal: float | None = None
  baseline: float = 0.1
  seed: int = 0

  def __post_init__(self):
    _normalise_scalars(self)
    _validate(self)

  @property
  def fx(self) -> float:
    """Focal length in pixels."""
    return float(self.width if self.focal is None else self.focal)


def _normalise_scalars(c: SyntheticConfig) -> None:
  """Numpy integers and floats become Python ones; a bool where a number is expected, a
  string, or a NaN/inf is a ValueError naming the field."""
  for f in dataclasses.fields(c):
    value = getattr(c, f.name)
    if f.type == "int":
      _check(is_int(value), f.name, "must be an int", value)
      object.__setattr__(c, f.name, int(value))
    elif f.type in ("float", "float | None") and not (value is None and "None" in f.type):
      _check(isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
             and math.isfinite(value), f.name, "must be a finite number", value)
      object.__setattr__(c, f.name, float(value))


def _check(ok: bool, field: str, message: str, value) -> None:
  if not ok:
    raise ValueError(f"SyntheticConfig.{field} {message}, got {value!r}")


def _validate(c: SyntheticConfig) -> None:
  """Raises ValueError naming the first inconsistent field."""
  _check(isinstance(c.frames, int) and c.frames >= 1, "frames", "must be an int >= 1", c.frames)
  _check(isinstance(c.height, int) and c.height >= 16, "height", "must be an int >= 16", c.height)
  _check(isinstance(c.width, int) and c.width >= 16, "width", "must be an int >= 16", c.width)
  _check(isinstance(c.num_objects, int) and 0 <= c.num_objects <= 254, "num_objects",
         "must be an int in [0, 254]", c.num_objects)
  _check(c.min_disparity > 0, "min_disparity", "must be > 0", c.min_disparity)
  _check(c.max_disparity >= c.min_disparity, "max_disparity", "must be >= min_disparity",
         (c.min_disparity, c.max_disparity))
  _check(c.max_disparity < c.width, "max_disparity", "must be < width", c.max_disparity)
  _check(0 < c.background_fraction <= 1, "background_fraction", "must be in (0, 1]",
         c.background_fraction)
  _check(0 <= c.background_slant <= 1, "background_slant", "must be in [0, 1]",
         c.background_slant)
  for name in ("background_speed", "max_speed", "max_rotation", "noise_std"):
    _check(getattr(c, name) >= 0, name, "must be >= 0", getattr(c, name))
  _check(0 <= c.max_depth_change < 0.5, "max_depth_change", "must be in [0, 0.5)",
         c.max_depth_change)
  _check(0 <= c.max_tilt < 1.3, "max_tilt", "must be in [0, 1.3) rad", c.max_tilt)
  lo_hi = tuple(c.object_size)
  _check(len(lo_hi) == 2 and 0 < lo_hi[0] <= lo_hi[1] <= 1, "object_size",
         "must be (min, max) with 0 < min <= max <= 1", c.object_size)
  _check(len(c.shapes) > 0 and set(c.shapes) <= set(SHAPES), "shapes",
         f"must be a non-empty subset of {SHAPES}", c.shapes)
  _check(len(c.textures) > 0 and set(c.textures) <= set(TEXTURE_KINDS), "textures",
         f"must be a non-empty subset of {TEXTURE_KINDS}", c.textures)
  cell = c.texture_min_cell
  _check(isinstance(cell, int) and 2 <= cell <= 32 and cell & (cell - 1) == 0,
         "texture_min_cell", "must be a power of two in [2, 32]", cell)
  _check(c.texture_contrast > 0, "texture_contrast", "must be > 0", c.texture_contrast)
  _check(c.focal is None or c.focal > 0, "focal", "must be None or > 0", c.focal)
  _check(c.baseline > 0, "baseline", "must be > 0", c.baseline)
  _check(isinstance(c.seed, int) and c.seed >= 0, "seed", "must be an int >= 0", c.seed)


def config_from_block(block, where: str, *, own=(), set_by=None, **fields) -> SyntheticConfig:
  """`SyntheticConfig` from a config file's block of generator fields (lists become tuples).

  A key that is no field (a typo would silently generate with the default) or a bad value
  is named as `{where}.{key}`.

  Args:
    block: mapping of field names to values (an `ml_collections.ConfigDict` block).
    where: the block's name in messages, e.g. `config.synthetic`.
    own: keys of the block that are the caller's, not the generator's (left out).
    set_by: fields the caller sets itself, each with the config field it comes from; the
      block may not give them.
    **fields: values of the fields the caller sets (override the block).
  """
  set_by = dict(set_by or {})
  names = {f.name for f in dataclasses.fields(SyntheticConfig)}
  for k in block:
    if k in set_by:
      raise ValueError(f"{where}.{k}: the clips' {k} is {set_by[k]}'s")
  unknown = sorted(set(block) - names - set(own))
  if unknown:
    allowed = sorted((names - set(set_by)) | set(own))
    raise ValueError(f"{where}.{unknown[0]} is not a field of the synthetic generator; its "
                     f"fields: {', '.join(allowed)}")
  kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in block.items() if k in names}
  try:
    return SyntheticConfig(**dict(kwargs, **fields))
  except ValueError as e:  # `SyntheticConfig.<field> ...`: name the block's field instead
    field = str(e).partition(" ")[0].removeprefix("SyntheticConfig.")
    if field in kwargs and field not in fields:
      raise ValueError(str(e).replace("SyntheticConfig.", f"{where}.", 1)) from None
    raise


class _Track(NamedTuple):
  """Static parameters of one object's motion (image-space centre, geometric depth)."""

  kind: str
  params: tuple
  radius_px: float  # circumradius in texels (= px at frame 0)
  extent: tuple  # (umin, umax, vmin, vmax) texel box of the shape
  normal: np.ndarray
  theta0: float
  omega: float
  u0: float
  v0: float
  vel: tuple[float, float]
  depth0: float
  rate: float  # Z_t = depth0 * (1 + rate) ** t
  texture: np.ndarray


def _texture(rng: np.random.Generator, cfg: SyntheticConfig, size: int) -> np.ndarray:
  """[S, S, 4] uint8 texture; RGBA because cv2.remap has a much faster 4-channel path."""
  tex = make_texture(rng, size, cfg.textures, cfg.texture_min_cell, cfg.texture_contrast)
  return cv2.cvtColor(tex, cv2.COLOR_RGB2RGBA)


def _tex_size(extent: float) -> int:
  """Texture side: a multiple of 64 (keeps every noise octave periodic)."""
  return 64 * max(1, math.ceil(extent / 64))


def _sample_shape(rng: np.random.Generator, kind: str, r: float) -> tuple:
  """Shape parameters (texels) with circumradius r."""
  if kind == "rectangle":
    beta = rng.uniform(0.2, 0.8) * (np.pi / 2)
    return (r * math.cos(beta), r * math.sin(beta))
  if kind == "ellipse":
    return (r, r * rng.uniform(0.35, 1.0))
  k = int(rng.integers(3, 9))
  # Jittered angles keep every sector below pi, so the polygon stays star-shaped
  # about its centre (what the sector-based inside test needs).
  angles = (np.arange(k) + rng.uniform(-0.2, 0.2, k)) * (2 * np.pi / k) + rng.uniform(-np.pi, np.pi)
  angles = np.sort((angles + np.pi) % (2 * np.pi) - np.pi)
  radii = r * rng.uniform(0.45, 1.0, k)
  radii[rng.integers(k)] = r
  return (angles, (radii * np.cos(angles)).astype(np.float32),
          (radii * np.sin(angles)).astype(np.float32))


def _shape_extent(kind: str, params: tuple) -> tuple:
  """(umin, umax, vmin, vmax) of a shape in its own texel coordinates."""
  if kind == "polygon":
    _, px, py = params
    return (float(px.min()), float(px.max()), float(py.min()), float(py.max()))
  a, b = params
  return (-a, a, -b, b)


def _depth_range(cfg: SyntheticConfig, radius_px: float, tilt: float, rate: float, lo: float):
  """Interval of frame-0 centre disparities keeping every frame's disparities in range.

  A disk of radius R (m) tilted by `tilt` spans depths Z_c +- R sin(tilt), so its
  disparities lie in d_c / (1 -+ rho) with rho = R sin(tilt) / Z_c, which grows as
  (1 + rate)**-t while R stays fixed. Returns (low, high) or None when infeasible.
  """
  g = (1.0 + rate) ** -np.arange(cfg.frames, dtype=np.float64)
  rho = radius_px * math.sin(tilt) / cfg.fx * g
  if np.any(rho * math.sqrt(2) >= 0.9):  # keep the bounding square in front of the camera
    return None
  low = float(np.max(lo * (1 + rho) / g))
  high = float(np.min(cfg.max_disparity * (1 - rho) / g))
  return (low, high) if low <= high else None


def _sample_track(rng: np.random.Generator, cfg: SyntheticConfig, lo: float) -> _Track:
  """Random shape, texture and smooth 3D motion of one object."""
  h, w = cfg.height, cfg.width
  kind = cfg.shapes[int(rng.integers(len(cfg.shapes)))]
  radius = rng.uniform(*cfg.object_size) * min(h, w) / 2
  params = _sample_shape(rng, kind, radius)
  tilt = rng.uniform(0.0, cfg.max_tilt)
  azimuth = rng.uniform(0.0, 2 * np.pi)
  speed, heading = rng.uniform(0.0, cfg.max_speed), rng.uniform(0.0, 2 * np.pi)
  rate = rng.uniform(-cfg.max_depth_change, cfg.max_depth_change)
  span = None
  for _ in range(8):  # shrink depth motion and tilt until the disparity bounds hold
    span = _depth_range(cfg, radius, tilt, rate, lo)
    if span is not None:
      break
    rate, tilt = rate * 0.5, tilt * 0.5
  if span is None:
    rate, tilt, span = 0.0, 0.0, (lo, cfg.max_disparity)
  d0 = rng.uniform(*span)
  normal = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth),
                     math.cos(tilt)])
  texture = _texture(rng, cfg, _tex_size(2 * radius + 4))
  return _Track(kind, params, radius, _shape_extent(kind, params), normal,
                rng.uniform(0, 2 * np.pi),
                rng.uniform(-cfg.max_rotation, cfg.max_rotation),
                rng.uniform(0.05, 0.95) * w, rng.uniform(0.05, 0.95) * h,
                (speed * math.cos(heading), speed * math.sin(heading)),
                cfg.fx * cfg.baseline / d0, rate, texture)


def _object_layer(tr: _Track, t: int, cam: Camera) -> Layer:
  """The object's plane at frame t."""
  z = tr.depth0 * (1.0 + tr.rate) ** t
  u, v = tr.u0 + tr.vel[0] * t, tr.v0 + tr.vel[1] * t
  center = np.array([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fx, z])
  scale = cam.fx / tr.depth0  # texels per metre: 1 texel = 1 px at frame 0
  e1, e2 = plane_axes(tr.normal, tr.theta0 + tr.omega * t)
  radius = tr.radius_px / scale
  sin_tilt = math.hypot(tr.normal[0], tr.normal[1])
  half = (tr.texture.shape[0] - 1) / 2
  return Layer(center, tr.normal, e1 * scale, e2 * scale, tr.kind, tr.params, tr.extent,
                z - radius * sin_tilt, tr.texture, (half, half))


def _background_layers(rng: np.random.Generator, cfg: SyntheticConfig, cam: Camera):
  """Background plane for every frame (static plane, drifting texture), and its max disparity.

  Its disparity is affine in the left image, d = d_c + gx (x - cx) + gy (y - cy), kept
  inside its band over the columns the right view can see, [0, W - 1 + max_disparity].
  """
  lo = cfg.min_disparity
  hi = lo + cfg.background_fraction * (cfg.max_disparity - lo)
  d_c = rng.uniform(lo, hi)
  margin = min(d_c - lo, hi - d_c) * rng.uniform(0.0, cfg.background_slant)
  ex = max(cam.cx, cfg.width - 1 + cfg.max_disparity - cam.cx)
  ey = max(cam.cy, cfg.height - 1 - cam.cy)
  ang = rng.uniform(0.0, 2 * np.pi)
  norm1 = abs(math.cos(ang)) + abs(math.sin(ang))
  gx, gy = margin * math.cos(ang) / (ex * norm1), margin * math.sin(ang) / (ey * norm1)
  # 1/Z affine in the image <=> the plane (gx f, gy f, d_c) . X = f B.
  normal = unit(np.array([gx * cam.fx, gy * cam.fx, d_c]))
  fb = cam.fx * cam.baseline
  center = np.array([0.0, 0.0, fb / d_c])
  scale = cam.fx / center[2]
  # A random in-plane rotation hides the texture grid's axis alignment.
  e1, e2 = plane_axes(normal, rng.uniform(0.0, 2 * np.pi))
  # One texture period spans at least the image (a power of two >= 64 keeps every
  # noise octave periodic), so no repetition shows within a disparity search range.
  size = max(64, 1 << (max(cfg.height, cfg.width) - 1).bit_length())
  texture = _texture(rng, cfg, size)
  speed, heading = rng.uniform(0.0, cfg.background_speed), rng.uniform(0.0, 2 * np.pi)
  start = rng.uniform(0.0, size, 2)
  layers = []
  for t in range(cfg.frames):
    origin = ((start[0] + t * speed * math.cos(heading)) % size,
              (start[1] + t * speed * math.sin(heading)) % size)
    layers.append(Layer(center, normal, e1 * scale, e2 * scale, "background", (), (),
                         fb / (d_c + margin), texture, origin))
  return layers, hi


# Host bytes per pixel of a synthetic video's arrays in `sav-jax demo` and `python -m eval`
# (the clip 17, predictions 8, the demo's comparison video 21) and per pixel of one frame (the
# generator's temporaries): a rough bound for `check_host_memory`.
_HOST_BYTES_PER_PIXEL, _HOST_BYTES_PER_FRAME_PIXEL = 48, 64


def check_host_memory(cfg: SyntheticConfig) -> None:
  """MemoryError ("out of host memory") for a synthetic video of `cfg` that cannot fit in the
  host's available memory: the generator filled it until the kernel killed the process
  (`--height 16000 --width 16000`), before the model's own memory check."""
  from sav_jax import inference  # pylint: disable=import-outside-toplevel  # (imports jax)
  import jax  # pylint: disable=import-outside-toplevel
  needed = cfg.height * cfg.width * (cfg.frames * _HOST_BYTES_PER_PIXEL
                                     + _HOST_BYTES_PER_FRAME_PIXEL)
  free = inference.available_memory_bytes(jax.devices("cpu")[0])
  if free is not None and needed > free:
    raise MemoryError(f"a synthetic video of {cfg.frames} frames of {cfg.height}x{cfg.width} "
                      f"needs about {needed / 2**30:.1f} GB, but only {free / 2**30:.1f} GB is "
                      "available")


def generate_clip(cfg: SyntheticConfig, index: int = 0) -> dict[str, np.ndarray]:
  """Renders clip `index` of the stream defined by `cfg` (a pure function of both).

  Args:
    cfg: generator configuration.
    index: clip number >= 0; the clip is seeded by the sequence (cfg.seed, index).

  Returns:
    A dict of numpy arrays:
      left, right: [T, H, W, 3] uint8 RGB.
      disparity: [T, H, W] float32, left view, positive px, dense (`fx*baseline/depth`).
      depth: [T, H, W] float32, left view, metres.
      valid: [T, H, W] bool, False where the left point is out of the right view or
        occluded in it.
      segmentation, segmentation_right: [T, H, W] uint8 layer ids (0 background,
        k = object k) of the left and right views.
      fx, baseline: float32 scalars (px, m).
  """
  index = operator.index(index)
  if index < 0:
    raise ValueError(f"clip index must be >= 0, got {index}")
  scene_seq, noise_seq = np.random.SeedSequence([cfg.seed, index]).spawn(2)
  rng = np.random.default_rng(scene_seq)
  t_, h, w = cfg.frames, cfg.height, cfg.width
  cam = Camera(cfg.fx, (w - 1) / 2, (h - 1) / 2, float(cfg.baseline))
  backgrounds, bg_max = _background_layers(rng, cfg, cam)
  tracks = [_sample_track(rng, cfg, bg_max) for _ in range(cfg.num_objects)]
  rx = ((np.arange(w, dtype=np.float64) - cam.cx) / cam.fx).astype(np.float32)[None, :]
  ry = ((np.arange(h, dtype=np.float64) - cam.cy) / cam.fx).astype(np.float32)[:, None]
  out = {
      "left": np.empty((t_, h, w, 3), np.uint8), "right": np.empty((t_, h, w, 3), np.uint8),
      "disparity": np.empty((t_, h, w), np.float32), "depth": np.empty((t_, h, w), np.float32),
      "valid": np.empty((t_, h, w), bool), "segmentation": np.empty((t_, h, w), np.uint8),
      "segmentation_right": np.empty((t_, h, w), np.uint8),
  }
  noise_rng = np.random.default_rng(noise_seq)
  for t in range(t_):
    layers = [backgrounds[t]] + [_object_layer(tr, t, cam) for tr in tracks]
    left, depth, seg = render_view(layers, 0.0, cam, rx, ry)
    right, _, seg_r = render_view(layers, cam.baseline, cam, rx, ry)
    out["valid"][t] = valid_mask(layers, depth, seg, cam, ry)
    out["depth"][t], out["segmentation"][t], out["segmentation_right"][t] = depth, seg, seg_r
    np.divide(np.float32(cam.fx * cam.baseline), depth, out=out["disparity"][t])
    for name, img in (("left", left), ("right", right)):
      if cfg.noise_std > 0:
        noisy = img[..., :3] + noise_rng.normal(0.5, cfg.noise_std, (h, w, 3)).astype(np.float32)
        out[name][t] = np.clip(noisy, 0.0, 255.0, out=noisy)  # +0.5 then truncation rounds
      else:
        cv2.cvtColor(img, cv2.COLOR_RGBA2RGB, dst=out[name][t])
  out["fx"] = np.array(cam.fx, np.float32)
  out["baseline"] = np.array(cam.baseline, np.float32)
  return out


class SyntheticStereoVideo:
  """Random-access source of synthetic stereo clips (grain `RandomAccessDataSource`).

  Clip i is `generate_clip(cfg, i)`: the same in any order, process or host.

  Args:
    cfg: generator configuration (defaults to `SyntheticConfig()`).
    num_clips: number of clips, `len(source)`.
  """

  def __init__(self, cfg: SyntheticConfig | None = None, num_clips: int = 1000):
    if not is_int(num_clips) or num_clips < 1:
      raise ValueError(f"num_clips must be an int >= 1, got {num_clips!r}")
    num_clips = int(num_clips)  # a numpy integer too
    self.cfg = SyntheticConfig() if cfg is None else cfg
    self.num_clips = num_clips

  def __len__(self) -> int:
    return self.num_clips

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    i = operator.index(index)
    if i < 0:
      i += self.num_clips
    if not 0 <= i < self.num_clips:
      raise IndexError(f"clip index {index} out of range for {self.num_clips} clips")
    return generate_clip(self.cfg, i)

  def __repr__(self) -> str:
    return f"SyntheticStereoVideo(num_clips={self.num_clips}, cfg={self.cfg!r})"

"""Torch-compatible resizing: bilinear (both align_corners modes) and bicubic.

Every resize here is separable and its weights are built in NumPy at trace time (shapes
are static), with torch's source coordinates and border handling
(`torch.nn.functional.interpolate`). Bilinear resizes are two-tap blends per axis:
`(1 - w) x[i0] + w x[i1]` with static indices (`bilinear_taps`), memory-bound and
exact in float32. Bicubic ones (only the ViT's position table) contract a dense
`[out, in]` matrix (`interp_matrix`) with `einsum`. A dense matrix would cost
`out x in` multiply-adds per output pixel: at 720x1280 the depth prior's bilinear
resizes alone took ~4 TMAC in float32 that way.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from sav_jax.ops.pool import accumulation_dtype, check_array

# Torch's bicubic kernel constant (upsample_bicubic2d).
_CUBIC_A = -0.75


def _source_coords(
    in_size: int, out_size: int, align_corners: bool, scale_factor: float | None
) -> np.ndarray:
  """Float source coordinate of every output pixel, as torch computes it."""
  dst = np.arange(out_size, dtype=np.float64)
  if align_corners:
    if out_size == 1:
      return np.zeros(1)
    return dst * ((in_size - 1) / (out_size - 1))
  # Torch uses 1/scale_factor when a scale factor is given, else in/out.
  ratio = 1.0 / scale_factor if scale_factor is not None else in_size / out_size
  return (dst + 0.5) * ratio - 0.5


def _cubic_weights(t: np.ndarray) -> np.ndarray:
  """Weights of the four taps (idx-1 .. idx+2) for fractional offset t."""
  a = _CUBIC_A

  def near(x):  # |x| <= 1
    return ((a + 2) * x - (a + 3)) * x * x + 1

  def far(x):  # 1 < |x| < 2
    return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

  return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], axis=-1)


@functools.lru_cache(maxsize=256)
def bilinear_taps(in_size: int, out_size: int, align_corners: bool = False,
                  scale_factor: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """The two taps of a 1-D torch linear interpolation: output `i` is
  `(1 - w[i]) * x[i0[i]] + w[i] * x[i1[i]]`.

  Returns:
    `(i0, i1, w)`: int32 indices and float64 weights, each `[out_size]`, read-only; where
    both taps clamp to the same input (the last one), `w` is 0.
  """
  src = _source_coords(in_size, out_size, align_corners, scale_factor)
  if not align_corners:
    src = np.maximum(src, 0.0)  # torch clamps negative coordinates (linear only)
  i0 = np.minimum(np.floor(src).astype(np.int64), in_size - 1)
  i1 = np.minimum(i0 + 1, in_size - 1)
  w1 = np.where(i1 == i0, 0.0, src - i0)
  out = (i0.astype(np.int32), i1.astype(np.int32), w1)
  for a in out:
    a.flags.writeable = False  # shared through the cache
  return out


def _blend_axis(x: jax.Array, axis: int, taps) -> jax.Array:
  """The two-tap blend of `bilinear_taps` along `axis` of floating `x` (identity: `x`)."""
  i0, i1, w1 = taps
  if len(i0) == x.shape[axis] and not w1.any() and np.array_equal(i0, np.arange(len(i0))):
    return x
  shape = [1] * x.ndim
  shape[axis] = len(w1)
  w = jnp.asarray(w1.reshape(shape), x.dtype)
  a = jnp.take(x, jnp.asarray(i0), axis=axis, mode="clip")
  b = jnp.take(x, jnp.asarray(i1), axis=axis, mode="clip")
  return (1.0 - w) * a + w * b


@functools.lru_cache(maxsize=256)
def interp_matrix(
    in_size: int,
    out_size: int,
    mode: str = "bilinear",
    align_corners: bool = False,
    scale_factor: float | None = None,
) -> np.ndarray:
  """Dense `[out_size, in_size]` matrix of a 1-D torch interpolation.

  Args:
    in_size: input length.
    out_size: output length.
    mode: "bilinear" or "bicubic".
    align_corners: torch's `align_corners` flag.
    scale_factor: the scale factor passed to torch (changes the source
      coordinates when it is not exactly `out_size / in_size`).

  Returns:
    float64 array `[out_size, in_size]`; row i holds the weights of output i.
  """
  mat = np.zeros((out_size, in_size), np.float64)
  rows = np.arange(out_size)
  if mode == "bilinear":
    i0, i1, w1 = bilinear_taps(in_size, out_size, align_corners, scale_factor)
    np.add.at(mat, (rows, i0), 1.0 - w1)
    np.add.at(mat, (rows, i1), w1)
  elif mode == "bicubic":
    src = _source_coords(in_size, out_size, align_corners, scale_factor)
    i0 = np.floor(src).astype(np.int64)
    weights = _cubic_weights(src - i0)
    for k in range(4):
      idx = np.clip(i0 - 1 + k, 0, in_size - 1)  # taps clamp at the border
      np.add.at(mat, (rows, idx), weights[:, k])
  else:
    raise ValueError(f"unknown interpolation mode {mode!r}; use 'bilinear' or 'bicubic'")
  return mat


def resize(
    x: jax.Array,
    size: tuple[int, int],
    mode: str = "bilinear",
    align_corners: bool = False,
    scale_factor: tuple[float, float] | None = None,
) -> jax.Array:
  """Resizes the two spatial axes of a channels-last array like torch.

  Args:
    x: `[..., height, width, channels]`.
    size: output `(height, width)`.
    mode: "bilinear" or "bicubic" (no antialiasing, as torch's default).
    align_corners: torch's `align_corners`.
    scale_factor: optional `(sy, sx)` passed to torch instead of a size; the
      output size must then be `floor(in * s)` and is given in `size`.

  Returns:
    `[..., size[0], size[1], channels]`, same dtype as `x`.
  """
  if hasattr(x, "ndim") and x.ndim < 3:
    raise ValueError(f"x must be [..., height, width, channels] (channels last, at least 3 "
                     f"dimensions), got shape {tuple(x.shape)}; a single-channel image is "
                     "x[..., None]")
  check_array("x", x, getattr(x, "ndim", 3), "[..., height, width, channels]")
  try:
    out_h, out_w = (int(v) for v in size)
  except (TypeError, ValueError):
    raise ValueError(f"size must be the output (height, width), got {size!r}") from None
  if (out_h, out_w) != tuple(size) or min(out_h, out_w) < 1:
    raise ValueError(f"size must be two positive integers (height, width), got {size!r}")
  in_h, in_w = x.shape[-3], x.shape[-2]
  sy, sx = _check_scale_factor(scale_factor, (in_h, in_w), (out_h, out_w))
  dt = accumulation_dtype(x.dtype)
  if mode == "bilinear":
    # Two taps per axis in float32 whatever the input dtype (bf16 inputs stay accurate;
    # float64 ones stay float64).
    y = _blend_axis(x.astype(dt), x.ndim - 3,
                    bilinear_taps(in_h, out_h, align_corners, sy))
    y = _blend_axis(y, x.ndim - 2, bilinear_taps(in_w, out_w, align_corners, sx))
    return _cast_like(y, x.dtype)
  my = interp_matrix(in_h, out_h, mode, align_corners, sy)
  mx = interp_matrix(in_w, out_w, mode, align_corners, sx)
  if (in_h, in_w) == (out_h, out_w) and np.array_equal(my, np.eye(in_h)) and np.array_equal(
      mx, np.eye(in_w)):
    return x
  my = jnp.asarray(my, dtype=dt)
  mx = jnp.asarray(mx, dtype=dt)
  y = jnp.einsum("oh,...hwc->...owc", my, x.astype(dt))
  y = jnp.einsum("pw,...owc->...opc", mx, y)
  return _cast_like(y, x.dtype)


def _check_scale_factor(scale_factor, in_size, out_size) -> tuple:
  """`scale_factor` as `(sy, sx)` (`(None, None)` for None); a ValueError unless it is two
  positive numbers whose output size, torch's `floor(in * s)`, is `out_size`."""
  if scale_factor is None:
    return None, None
  try:
    sy, sx = (float(s) for s in scale_factor)
  except (TypeError, ValueError):
    raise ValueError(f"scale_factor must be two numbers (sy, sx), got {scale_factor!r}") from None
  if not (0 < sy < float("inf") and 0 < sx < float("inf")):
    raise ValueError(f"scale_factor must be two positive numbers (sy, sx), got {scale_factor!r}")
  want = (math.floor(in_size[0] * sy), math.floor(in_size[1] * sx))
  if want != tuple(out_size):
    raise ValueError(f"size {tuple(out_size)} does not follow scale_factor {scale_factor!r} for "
                     f"a {in_size[0]}x{in_size[1]} input: torch's output size is floor(in * s) "
                     f"= {want}")
  return sy, sx


def _cast_like(y: jax.Array, dtype) -> jax.Array:
  """float32 (or float64) `y` in `dtype`: integers rounded to the nearest (halves up, as OpenCV's
  integer resizes do) and clipped to the type's range (a plain cast truncates: ~half of a
  uint8 image's values came out one lower)."""
  dtype = jax.dtypes.canonicalize_dtype(dtype)  # NumPy's int64 is JAX's int32 without x64
  if jnp.issubdtype(dtype, jnp.integer):
    info = jnp.iinfo(dtype)  # (float bounds: int ones beyond int32 overflowed JAX's argument)
    return jnp.clip(jnp.floor(y + 0.5), float(info.min), float(info.max)).astype(dtype)
  return y.astype(dtype)

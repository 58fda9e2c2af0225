"""Horizontal warping: torch `grid_sample` (bilinear, zeros, align_corners=True) along x.

The official correlation samples the right features at `(x - flow_x, y)` with the
vertical flow forced to zero, so the row coordinate is always an integer and the
bilinear sample degenerates to a two-tap linear interpolation along x. Taps outside
`[0, W-1]` contribute zero (grid_sample's zero padding).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sav_jax.ops.pool import accumulation_dtype, check_array
from sav_jax.ops.resize import _cast_like


def warp_x(features: jax.Array, disp: jax.Array) -> jax.Array:
  """Samples `features` at `x - disp` along the width axis.

  Args:
    features: `[N, H, W, C]`, the right-view features.
    disp: `[N, H, W]`, horizontal flow in pixels (positive moves the sample left).

  Returns:
    `[N, H, W, C]` in the dtype of `features`: `features[n, y, x - disp[n, y, x]]`,
    linearly interpolated, zero outside the image; computed in float32 (float64 for
    float64 inputs), rounded to the nearest for integer features (as `resize`).
  """
  check_array("features", features, 4, "[N, H, W, C]")
  check_array("disp", disp, 3, "[N, H, W]")
  if tuple(disp.shape) != tuple(features.shape[:3]):
    raise ValueError(f"disp {tuple(disp.shape)} must be features' [N, H, W] "
                     f"{tuple(features.shape[:3])}")
  width = features.shape[2]
  dt = accumulation_dtype(features.dtype, disp.dtype)
  xs = jnp.arange(width, dtype=dt)[None, None, :] - disp.astype(dt)
  x0 = jnp.floor(xs)
  w1 = (xs - x0)[..., None]
  x0 = x0.astype(jnp.int32)
  x1 = x0 + 1

  def tap(idx):
    inside = ((idx >= 0) & (idx <= width - 1))[..., None]
    vals = jnp.take_along_axis(features, jnp.clip(idx, 0, width - 1)[..., None], axis=2)
    return jnp.where(inside, vals.astype(dt), 0.0)

  out = (1.0 - w1) * tap(x0) + w1 * tap(x1)
  return _cast_like(out, features.dtype)

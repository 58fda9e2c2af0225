"""All-to-all-pair correlation (AAPC) of Stereo Any Video, without offset loops.

For every pixel and channel group, the official code correlates each of the `n`
positions of a local window in the left map with each of the `n` positions of
the same window in the (warped) right map: `n * n` dot products per group.
Windows are 1x9 (wide) or 3x3 (small); both maps are replicate-padded. Here the
`n` window views are static shifted slices, stacked once per view, and all
pairs come from one einsum.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sav_jax.ops.pool import pad_replicate
from sav_jax.ops.sample import warp_x

WIDE_WINDOW = (1, 9)
SMALL_WINDOW = (3, 3)


def window_views(x: jax.Array, window: tuple[int, int]) -> jax.Array:
  """Stacks the shifted views of a replicate-padded map.

  Args:
    x: `[N, H, W, C]`.
    window: `(wy, wx)`, odd sizes.

  Returns:
    `[N, H, W, wy*wx, C]`; view `a = dy*wx + dx` holds `x[y + dy - wy//2, x + dx - wx//2]`
    with coordinates clamped to the border.
  """
  wy, wx = window
  _, h, w, _ = x.shape
  xp = pad_replicate(x, (wy // 2, wy // 2), (wx // 2, wx // 2))
  views = [xp[:, dy:dy + h, dx:dx + w, :] for dy in range(wy) for dx in range(wx)]
  return jnp.stack(views, axis=3)


def window_correlation(
    left: jax.Array, right: jax.Array, window: tuple[int, int], groups: int = 4
) -> jax.Array:
  """All pairs of window positions, per channel group.

  Args:
    left: `[N, H, W, C]`.
    right: `[N, H, W, C]` (already warped).
    window: `(wy, wx)`.
    groups: channel groups; C must be divisible by it.

  Returns:
    `[N, H, W, groups * n * n]` with `n = wy*wx`; channel `g*n*n + a*n + b` is
    `sum_c left_view_a[c] * right_view_b[c]` over the channels of group g.
  """
  n_, h, w, c = left.shape
  if c % groups:
    raise ValueError(f"feature channels {c} are not divisible by {groups} groups")
  lv = window_views(left, window).reshape(n_, h, w, -1, groups, c // groups)
  rv = window_views(right, window).reshape(n_, h, w, -1, groups, c // groups)
  corr = jnp.einsum("nhwagc,nhwbgc->nhwgab", lv, rv, preferred_element_type=jnp.float32)
  return corr.reshape(n_, h, w, -1)


def aapc(
    fmap1: jax.Array, fmap2: jax.Array, disp: jax.Array, window: tuple[int, int], groups: int = 4
) -> jax.Array:
  """The official AAPC: warp the right map by the disparity, then window correlation.

  Args:
    fmap1: `[N, H, W, C]` left matching features.
    fmap2: `[N, H, W, C]` right matching features.
    disp: `[N, H, W]` current horizontal flow (the vertical component is always
      zero in the official code, so it is not an input here).
    window: `WIDE_WINDOW` or `SMALL_WINDOW`.
    groups: channel groups (4).

  Returns:
    `[N, H, W, groups * n * n]`, float32.
  """
  warped = warp_x(fmap2, disp)
  return window_correlation(fmap1, warped, window, groups)

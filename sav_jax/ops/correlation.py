"""All-to-all-pair correlation (AAPC) of Stereo Any Video, without offset loops.

For every pixel and channel group, the official code correlates each of the `n`
positions of a local window in the left map with each of the `n` positions of
the same window in the (warped) right map: `n * n` dot products per group.
Windows are 1x9 (wide) or 3x3 (small); both maps are replicate-padded.

Those `n * n` products only depend on the offset between the two positions. With
`L` and `R` the padded maps, the pair `(a, b)` at pixel `p` is
`L[p + a] . R[p + b] = E_{b - a}(p + a)`, where `E_d(q) = L[q] . R[q + d]`. So
only the `(2 wy - 1) * (2 wx - 1)` offset maps `E_d` are computed (17 for 1x9,
25 for 3x3, instead of 81 pairs), and the pairs are slices of them. Each `E_d`
row is a band of a small matrix product: the padded row is cut into blocks of
`block` positions, each block of `L` is multiplied with its block of `R` plus the
`2 wx - 2` positions after it, and the band diagonals are read out with a
pad-and-reshape skew. No map is ever stacked `n` times; the products run as
batched matrix multiplications.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sav_jax._checks import is_int
from sav_jax.ops.pool import accumulation_dtype, check_array, pad_replicate
from sav_jax.ops.sample import warp_x

WIDE_WINDOW = (1, 9)
SMALL_WINDOW = (3, 3)


def _band_products(left: jax.Array, right: jax.Array, bands: int, block: int) -> jax.Array:
  """`out[..., q, k] = left[..., q, :] . right[..., q + k, :]` for `k < bands`.

  Args:
    left: `[..., Q, C]` with `Q` a multiple of `block`.
    right: `[..., Q + block, C]` (positions past `Q + bands - 1` are never read).
    bands: number of diagonals, at most `block + 1`.
    block: positions per matrix product.

  Returns:
    `[..., Q, bands]` in `accumulation_dtype` (float32, float64 for float64 inputs).
  """
  *lead, q, c = left.shape
  nb = q // block
  lb = left.reshape(*lead, nb, block, c)
  main = right[..., :q, :].reshape(*lead, nb, block, c)
  nxt = right[..., block:q + block, :].reshape(*lead, nb, block, c)[..., :bands - 1, :]
  rb = jnp.concatenate([main, nxt], axis=-2)  # [..., nb, block + bands - 1, C]
  m = jnp.einsum("...qc,...rc->...qr", lb, rb, preferred_element_type=accumulation_dtype(left.dtype, right.dtype))
  # Skew: row q of m, columns q .. q + bands - 1. Flattened with one extra
  # column per row, element (q, q + k) sits at row q, column k.
  width = block + bands - 1
  m = m.reshape(*lead, nb, block * width)
  m = jnp.pad(m, [(0, 0)] * (m.ndim - 1) + [(0, block)])
  m = m.reshape(*lead, nb, block, width + 1)[..., :bands]
  return m.reshape(*lead, q, bands)


def window_correlation(
    left: jax.Array, right: jax.Array, window: tuple[int, int], groups: int = 4,
    block: int = 16,
) -> jax.Array:
  """All pairs of window positions, per channel group.

  Args:
    left: `[N, H, W, C]`.
    right: `[N, H, W, C]` (already warped).
    window: `(wy, wx)`, odd sizes.
    groups: channel groups; C must be divisible by it.
    block: width of the blocked matrix products (a speed/memory knob; the
      result does not depend on it). Raised to `2 wx - 2` when smaller.

  Returns:
    `[N, H, W, groups * n * n]` float32 (float64 for float64 inputs) with `n = wy*wx`; channel
    `g*n*n + a*n + b` is `sum_c left_view_a[c] * right_view_b[c]` over the
    channels of group g, where view `a = dy*wx + dx` holds the map at
    `(y + dy - wy//2, x + dx - wx//2)` with coordinates clamped to the border.
  """
  check_array("left", left, 4, "[N, H, W, C]")
  check_array("right", right, 4, "[N, H, W, C]")
  if tuple(left.shape) != tuple(right.shape):
    raise ValueError(f"left and right feature maps differ in shape: {tuple(left.shape)} vs "
                     f"{tuple(right.shape)}")
  if (not isinstance(window, (tuple, list)) or len(window) != 2
      or not all(is_int(k) and k >= 1 and k % 2 for k in window)):
    raise ValueError(f"window must be two odd sizes (wy, wx), e.g. (1, 9) or (3, 3), got "
                     f"{window!r}")
  n_, h, w, c = left.shape
  wy, wx = (int(k) for k in window)
  if not is_int(groups) or groups < 1 or c % groups:
    raise ValueError(f"groups must be a positive integer that divides the {c} feature "
                     f"channels, got {groups!r}")
  if not is_int(block) or block < 1:
    raise ValueError(f"block must be a positive integer, got {block!r}")
  ry, rx = wy // 2, wx // 2
  hp, wp = h + 2 * ry, w + 2 * rx
  dys, dxs = 2 * wy - 1, 2 * wx - 1
  block = max(block, dxs - 1)
  qw = -(-wp // block) * block  # padded width, a multiple of block

  def grouped(x, pad_y, pad_x):  # replicate pad, zero pad, -> [N, y, groups, x, C/groups]
    x = pad_replicate(x, (ry, ry), (rx, rx))
    x = jnp.pad(x, ((0, 0), pad_y, pad_x, (0, 0)))
    x = x.reshape(*x.shape[:3], groups, c // groups)
    return x.transpose(0, 1, 3, 2, 4)

  lg = grouped(left, (0, 0), (0, qw - wp))
  # R[q + d] for d = k - (wx - 1): shift by wx - 1 zeros on the left, and rows
  # by wy - 1 for the vertical offsets; zeros are only read for unused q.
  rg = grouped(right, (wy - 1, wy - 1), (wx - 1, qw + block - wp - (wx - 1)))
  offsets = [_band_products(lg, rg[:, k:k + hp], dxs, block) for k in range(dys)]
  e = jnp.stack(offsets, axis=-2)[:, :, :, :wp]  # [N, hp, groups, wp, dys, dxs]
  e = e.transpose(0, 1, 3, 2, 4, 5)  # [N, hp, wp, groups, dys, dxs]
  # Pair (a, b) at p: E_{b - a}(p + a), offset index b - a + (w - 1).
  pairs = [e[:, ay:ay + h, ax:ax + w, :, wy - 1 - ay:dys - ay, wx - 1 - ax:dxs - ax]
           .reshape(n_, h, w, groups, wy * wx) for ay in range(wy) for ax in range(wx)]
  return jnp.stack(pairs, axis=-2).reshape(n_, h, w, -1)


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
    `[N, H, W, groups * n * n]`, float32 (float64 for float64 inputs).
  """
  check_array("fmap1", fmap1, 4, "[N, H, W, C]")
  check_array("fmap2", fmap2, 4, "[N, H, W, C]")
  if tuple(fmap1.shape) != tuple(fmap2.shape):  # (warp_x named disp and features instead)
    raise ValueError(f"fmap1 and fmap2 differ in shape: {tuple(fmap1.shape)} vs "
                     f"{tuple(fmap2.shape)}")
  warped = warp_x(fmap2, disp)
  return window_correlation(fmap1, warped, window, groups)

"""Temporal convex upsampling (`convex_upsample_3D` of the official code)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sav_jax._checks import is_int
from sav_jax.ops.pool import accumulation_dtype, check_array


def neighbours_3d(x: jax.Array) -> jax.Array:
  """The 27 zero-padded 3x3x3 neighbours of every position (`unfoldNd`, padding 1).

  Args:
    x: `[B, T, H, W, C]`.

  Returns:
    `[B, T, H, W, 27, C]`; neighbour `k = dt*9 + dy*3 + dx` holds
    `x[t + dt - 1, y + dy - 1, x + dx - 1]`, zero outside the clip (time included).
  """
  _, t, h, w, _ = x.shape
  xp = jnp.pad(x, [(0, 0), (1, 1), (1, 1), (1, 1), (0, 0)])
  views = [
      xp[:, dt:dt + t, dy:dy + h, dx:dx + w, :]
      for dt in range(3) for dy in range(3) for dx in range(3)
  ]
  return jnp.stack(views, axis=4)


def _check_convex(flow, mask, rate, layout: str, taps: int) -> None:
  """A ValueError naming the argument whose shape does not fit the other's."""
  check_array("flow", flow, len(layout.split(",")), layout)
  check_array("mask", mask, flow.ndim, layout.replace("C]", f"{taps} * rate * rate]"))
  if not is_int(rate) or rate < 1:
    raise ValueError(f"rate must be a positive integer, got {rate!r}")
  want = (*flow.shape[:-1], taps * rate * rate)
  if tuple(mask.shape) != want:
    raise ValueError(f"mask {tuple(mask.shape)} does not fit flow {tuple(flow.shape)} at rate "
                     f"{rate}: expected {want} ({taps} * rate * rate logits per position)")


def convex_upsample_3d(flow: jax.Array, mask: jax.Array, rate: int = 4) -> jax.Array:
  """Upsamples a flow field by a convex combination of its 3x3x3 neighbours.

  Each output pixel is a softmax-weighted sum over the 27 (t, y, x) neighbours of
  its low-resolution cell in the previous, current and next frame; the flow is
  multiplied by `rate` first. Computed in float32 whatever the input dtype (float64 for
  float64 inputs).

  Args:
    flow: `[B, T, h, w, C]`.
    mask: `[B, T, h, w, 27 * rate * rate]` logits; channel `k*rate*rate + ry*rate + rx`.
    rate: upsampling factor.

  Returns:
    `[B, T, rate*h, rate*w, C]`, float32 (float64 for float64 inputs).
  """
  _check_convex(flow, mask, rate, "[B, T, h, w, C]", 27)
  b, t, h, w, c = flow.shape
  dt = accumulation_dtype(flow.dtype, mask.dtype)
  weights = mask.astype(dt).reshape(b, t, h, w, 27, rate, rate)
  # Softmax over the last axis: jaxlib 0.10 on CPU crashes (SIGSEGV) on the
  # gradient of a softmax over an inner axis of this shape.
  weights = jax.nn.softmax(jnp.moveaxis(weights, 4, -1), axis=-1)  # [B,T,h,w,ry,rx,27]
  nb = neighbours_3d(rate * flow.astype(dt))  # [B,T,h,w,27,C]
  # Tiny contraction: keep full float32 even where matmuls default to TF32/bf16.
  up = jnp.einsum(
      "bthwyxk,bthwkc->bthywxc", weights, nb, precision=jax.lax.Precision.HIGHEST)
  return up.reshape(b, t, h * rate, w * rate, c)


def neighbours_2d(x: jax.Array) -> jax.Array:
  """The 9 zero-padded 3x3 neighbours of every position (`F.unfold`, kernel 3, padding 1).

  Args:
    x: `[B, H, W, C]`.

  Returns:
    `[B, H, W, 9, C]`; neighbour `k = dy*3 + dx` holds `x[y + dy - 1, x + dx - 1]`,
    zero outside the image.
  """
  _, h, w, _ = x.shape
  xp = jnp.pad(x, [(0, 0), (1, 1), (1, 1), (0, 0)])
  return jnp.stack([xp[:, dy:dy + h, dx:dx + w, :] for dy in range(3) for dx in range(3)], axis=3)


def convex_upsample_2d(flow: jax.Array, mask: jax.Array, rate: int = 8) -> jax.Array:
  """RAFT's convex upsampling: each output pixel a softmax-weighted sum of 3x3 neighbours.

  The flow is multiplied by `rate` first; computed in float32 whatever the input dtype
  (float64 for float64 inputs).

  Args:
    flow: `[B, h, w, C]`.
    mask: `[B, h, w, 9 * rate * rate]` logits; channel `k*rate*rate + ry*rate + rx`.
    rate: upsampling factor.

  Returns:
    `[B, rate*h, rate*w, C]`, float32 (float64 for float64 inputs).
  """
  _check_convex(flow, mask, rate, "[B, h, w, C]", 9)
  b, h, w, c = flow.shape
  dt = accumulation_dtype(flow.dtype, mask.dtype)
  weights = mask.astype(dt).reshape(b, h, w, 9, rate, rate)
  weights = jax.nn.softmax(jnp.moveaxis(weights, 3, -1), axis=-1)  # [B,h,w,ry,rx,9]
  nb = neighbours_2d(rate * flow.astype(dt))  # [B,h,w,9,C]
  up = jnp.einsum("bhwyxk,bhwkc->bhywxc", weights, nb, precision=jax.lax.Precision.HIGHEST)
  return up.reshape(b, h * rate, w * rate, c)

"""Pooling and padding helpers with torch semantics (channels last)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sav_jax._checks import is_int


def accumulation_dtype(*dtypes) -> jnp.dtype:
  """The dtype the ops compute in for inputs of `dtypes`: float32 for integers, bfloat16,
  float16 and float32, float64 for float64 inputs (with `jax_enable_x64`; without it a NumPy
  float64 array is read as float32, as JAX reads it anyway)."""
  # (each canonicalised first: jnp.result_type of NumPy's float64 / int64 without x64 warned
  # "Explicitly requested dtype float64 ... is not available" at every op call)
  dtypes = [jax.dtypes.canonicalize_dtype(d) for d in dtypes]
  return jax.dtypes.canonicalize_dtype(jnp.promote_types(jnp.float32, jnp.result_type(*dtypes)))


def check_array(name: str, x, ndim: int, layout: str) -> None:
  """A ValueError naming `name`, its shape and the expected `layout` unless `x` is a
  numeric (float or integer) array of `ndim` dimensions (a TypeError for a non-array)."""
  if not hasattr(x, "shape") or not hasattr(x, "dtype"):
    raise TypeError(f"{name} must be an array {layout}, got a {type(x).__name__}")
  if not (jnp.issubdtype(x.dtype, jnp.floating) or jnp.issubdtype(x.dtype, jnp.integer)):
    raise ValueError(f"{name} must hold real numbers, got dtype {x.dtype}")
  if x.ndim != ndim:
    raise ValueError(f"{name} must be {layout} ({ndim} dimensions), got shape {tuple(x.shape)}")


def avg_pool(x: jax.Array, k: int) -> jax.Array:
  """`F.avg_pool2d(x, k, stride=k)`: non-overlapping mean, remainder dropped.

  Args:
    x: `[..., H, W, C]`.
    k: window and stride.

  Returns:
    `[..., H // k, W // k, C]`.
  """
  check_array("x", x, max(getattr(x, "ndim", 0), 3), "[..., H, W, C]")
  if not is_int(k) or k < 1:
    raise ValueError(f"avg_pool: the window k must be a positive integer, got {k!r}")
  h, w, c = x.shape[-3:]
  if h < k or w < k:  # torch: "Output size is too small"
    raise ValueError(f"avg_pool: a {h}x{w} map is smaller than the {k}x{k} window")
  ho, wo = h // k, w // k
  x = x[..., : ho * k, : wo * k, :]
  x = x.reshape(*x.shape[:-3], ho, k, wo, k, c)
  return x.mean(axis=(-4, -2))


def pad_replicate(x: jax.Array, pad_h: tuple[int, int], pad_w: tuple[int, int]) -> jax.Array:
  """Edge padding of the two spatial axes of `[..., H, W, C]`."""
  widths = [(0, 0)] * (x.ndim - 3) + [pad_h, pad_w, (0, 0)]
  return jnp.pad(x, widths, mode="edge")

"""Small building blocks shared by the modules: torch-style conv, norms, GELU."""

from __future__ import annotations

import functools
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


def conv(features: int, kernel: Sequence[int], stride: int | Sequence[int] = 1,
         padding: int | Sequence[int] = 0, use_bias: bool = True, dtype: Any = jnp.float32,
         name: str | None = None) -> nn.Conv:
  """A `nn.Conv` with torch's explicit symmetric zero padding.

  Args:
    features: output channels.
    kernel: kernel size per spatial axis (2 or 3 axes).
    stride: int or per-axis strides.
    padding: int or per-axis symmetric padding, as in torch.
    use_bias: whether the conv has a bias.
    dtype: compute dtype (parameters stay float32).
    name: module name (keep torch's attribute name).
  """
  nd = len(kernel)
  strides = (stride,) * nd if isinstance(stride, int) else tuple(stride)
  pads = (padding,) * nd if isinstance(padding, int) else tuple(padding)
  if nd == 3 and strides == (1, 1, 1):
    return Conv3D(features, tuple(kernel), pads, use_bias, dtype, name=name)
  return nn.Conv(features, tuple(kernel), strides=strides, padding=[(p, p) for p in pads],
                 use_bias=use_bias, dtype=dtype, param_dtype=jnp.float32, name=name)


class Conv3D(nn.Module):
  """Stride-1 3-D convolution over `[B, T, H, W, C]`, computed with 2-D convolutions.

  Same parameters as `nn.Conv` (`kernel` `[kt, kh, kw, C, O]`, `bias`), but XLA's
  2-D convolutions are 1.3-1.9x faster than its 3-D ones on CPU: a `(1, kh, kw)`
  kernel is one 2-D conv per frame, a `(kt, 1, 1)` kernel a 2-D conv over
  `(T, H*W)`, and a general kernel the sum of `kt` per-frame 2-D convs.
  """

  features: int
  kernel_size: tuple[int, int, int]
  padding: tuple[int, int, int]
  use_bias: bool = True
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, H, W, C]`. Returns `[B, T, H, W, features]` (zero padding)."""
    b, t, h, w, c = x.shape
    kt, kh, kw = self.kernel_size
    pt, ph, pw = self.padding
    kernel = self.param("kernel", nn.initializers.lecun_normal(), (kt, kh, kw, c, self.features),
                        jnp.float32).astype(self.dtype)
    x = x.astype(self.dtype)
    conv2d = functools.partial(jax.lax.conv_general_dilated, window_strides=(1, 1),
                               dimension_numbers=("NHWC", "HWIO", "NHWC"))
    if (kh, kw, ph, pw) == (1, 1, 0, 0):  # temporal kernel: a 2-D conv over (T, H*W)
      y = conv2d(x.reshape(b, t, h * w, c), kernel[:, 0], padding=[(pt, pt), (0, 0)])
    else:
      xp = jnp.pad(x, [(0, 0), (pt, pt), (0, 0), (0, 0), (0, 0)]) if pt else x
      y = 0
      for dt in range(kt):
        frames = xp[:, dt:dt + t].reshape(b * t, h, w, c)
        y = y + conv2d(frames, kernel[dt], padding=[(ph, ph), (pw, pw)])
    y = y.reshape(b, t, h, w, self.features)
    if self.use_bias:
      y = y + self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32).astype(self.dtype)
    return y


def instance_norm(x: jax.Array, eps: float = 1e-5) -> jax.Array:
  """`nn.InstanceNorm2d(affine=False)`: per-sample, per-channel over `[H, W]` of `[..., H, W, C]`."""
  xf = x.astype(jnp.float32)
  mean = xf.mean(axis=(-3, -2), keepdims=True)
  var = jnp.square(xf - mean).mean(axis=(-3, -2), keepdims=True)
  return ((xf - mean) * jax.lax.rsqrt(var + eps)).astype(x.dtype)


def layer_norm(eps: float = 1e-5, dtype: Any = jnp.float32, name: str | None = None) -> nn.LayerNorm:
  """`torch.nn.LayerNorm` (two-pass variance, float32 statistics)."""
  return nn.LayerNorm(epsilon=eps, use_fast_variance=False, dtype=dtype, param_dtype=jnp.float32,
                      name=name)


def dense(features: int, use_bias: bool = True, dtype: Any = jnp.float32,
          name: str | None = None) -> nn.Dense:
  return nn.Dense(features, use_bias=use_bias, dtype=dtype, param_dtype=jnp.float32, name=name)


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# torch.nn.GELU() is the exact (erf) GELU, not the tanh approximation.
gelu = functools.partial(jax.nn.gelu, approximate=False)


class CorrMLP(nn.Module):
  """Linear(324, 256) -> exact GELU -> Linear(256, 128), channels last, float32."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    return dense(128, name="fc2")(gelu(dense(256, name="fc1")(x)))


def normalize(images: jax.Array) -> jax.Array:
  """RGB 0..255 -> ImageNet-normalised float32 (x/255, then mean/std)."""
  mean = jnp.asarray(IMAGENET_MEAN, jnp.float32)
  std = jnp.asarray(IMAGENET_STD, jnp.float32)
  return (images.astype(jnp.float32) / 255.0 - mean) / std

"""The residual CNN encoders `fnet` and `cnet` (instance norm, 1/4 resolution)."""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from sav_jax.model.layers import conv, instance_norm


class ResidualBlock(nn.Module):
  """Two 3x3 convs with instance norm and a 1x1 conv + norm skip path.

  The official block always has the 1x1 `downsample` path, even when stride and
  width do not change.
  """

  planes: int
  stride: int = 1
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[N, H, W, C]`. Returns `[N, H/stride, W/stride, planes]`."""
    y = conv(self.planes, (3, 3), self.stride, 1, dtype=self.dtype, name="conv1")(x)
    y = nn.relu(instance_norm(y))
    y = conv(self.planes, (3, 3), 1, 1, dtype=self.dtype, name="conv2")(y)
    y = nn.relu(instance_norm(y))
    x = conv(self.planes, (1, 1), self.stride, 0, dtype=self.dtype, name="downsample_0")(x)
    return nn.relu(instance_norm(x) + y)


class BasicEncoder(nn.Module):
  """7x7/2 stem, residual stages 64 -> 96 (/2) -> 128, 1x1 projection."""

  output_dim: int = 96
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[N, H, W, 3]` normalised images. Returns `[N, H/4, W/4, output_dim]`."""
    x = conv(64, (7, 7), 2, 3, dtype=self.dtype, name="conv1")(x.astype(self.dtype))
    x = nn.relu(instance_norm(x))
    for i, (dim, stride) in enumerate([(64, 1), (96, 2), (128, 1)], start=1):
      x = ResidualBlock(dim, stride, self.dtype, name=f"layer{i}_0")(x)
      x = ResidualBlock(dim, 1, self.dtype, name=f"layer{i}_1")(x)
    return conv(self.output_dim, (1, 1), dtype=self.dtype, name="conv2")(x)

"""`depthnet`: the frozen Video Depth Anything prior and its trainable 4x4 conv."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from sav_jax.config import SAVConfig
from sav_jax.model.layers import conv
from sav_jax.model.vda import VideoDepthAnything
from sav_jax.ops.resize import resize

PATCH = 14  # DINOv2 patch size: VDA input sides must be multiples of it.


class DepthExtractor(nn.Module):
  """VDA features at 1/4 resolution.

  The frames are resized to the largest multiple of 14 below (bilinear,
  align_corners=False), run through VDA, resized back, and a trainable 4x4
  stride-4 conv brings them to 1/4. VDA is frozen: its output passes through
  `stop_gradient`, so no backward pass ever runs through the ViT.
  """

  cfg: SAVConfig = SAVConfig()

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, H, W, 3]` normalised. Returns `[B, T, H/4, W/4, 32]`."""
    _, _, h, w, _ = x.shape
    if h < PATCH or w < PATCH:
      raise ValueError(f"frames of {h}x{w} are too small for the depth prior (min 14x14)")
    xr = resize(x, ((h // PATCH) * PATCH, (w // PATCH) * PATCH), "bilinear", False)
    feats = VideoDepthAnything(**self.cfg.vda, dtype=self.cfg.compute_dtype,
                               name="depthanything")(xr)
    feats = jax.lax.stop_gradient(feats.astype(jnp.float32))
    feats = resize(feats, (h, w), "bilinear", False)
    return conv(self.cfg.depth_dim, (4, 4), 4, 0, dtype=self.cfg.compute_dtype, name="conv")(feats)

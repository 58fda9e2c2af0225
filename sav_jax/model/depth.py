"""`depthnet`: the frozen Video Depth Anything prior and its trainable 4x4 conv."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from sav_jax.config import SAVConfig
from sav_jax.model.layers import conv, in_frame_blocks
from sav_jax.model.dpt_temporal import resize_head_output
from sav_jax.model.vda import VideoDepthAnything
from sav_jax.ops.resize import resize

PATCH = 14  # DINOv2 patch size: VDA input sides must be multiples of it.


class DepthExtractor(nn.Module):
  """VDA features at 1/4 resolution.

  The frames are resized to the largest multiple of 14 below (bilinear,
  align_corners=False), run through VDA, resized back, and a trainable 4x4
  stride-4 conv brings them to 1/4. VDA is frozen as in the official model (its
  parameters `requires_grad=False`): its parameters pass through `stop_gradient` (their
  gradient is 0), while gradients with respect to the frames flow through it as in PyTorch,
  for pipelines that differentiate the disparity with respect to the images. A training
  step, which differentiates with respect to the trainable parameters only, runs no backward
  pass through the ViT (nothing trainable is behind it).

  `tokens` (per frame) and `from_tokens` (per clip: VDA's head is temporal) split
  the computation so that long-video inference can reuse the per-frame part.
  """

  cfg: SAVConfig = SAVConfig()

  def setup(self):
    self.depthanything = VideoDepthAnything(**self.cfg.vda, dtype=self.cfg.compute_dtype,
                                            attention_block_mb=self.cfg.frame_block_mb,
                                            attention=self.cfg.vit_attention)
    self.conv = conv(self.cfg.depth_dim, (4, 4), 4, 0, dtype=self.cfg.compute_dtype)

  def tokens(self, x: jax.Array) -> list[jax.Array]:
    """Args: x `[N, H, W, 3]` normalised frames. Returns VDA's four `[N, h*w, D]` token maps."""
    _, h, w, _ = x.shape
    if h < PATCH or w < PATCH:
      raise ValueError(f"frames of {h}x{w} are too small for the depth prior (min 14x14)")
    xr = resize(x, ((h // PATCH) * PATCH, (w // PATCH) * PATCH), "bilinear", False)
    return self._frozen(lambda mdl, xr: mdl.depthanything.tokens(xr))(self, xr)

  def _frozen(self, fn):
    """`fn(module, ...)` with the depth prior's parameters behind `stop_gradient`."""
    return nn.map_variables(fn, "params", trans_in_fn=_stop_prior_gradient,
                            init=self.is_initializing())

  def from_tokens(self, tokens: list[jax.Array], b: int, t: int, h: int, w: int) -> jax.Array:
    """Args: `tokens` of `b*t` frames (clip-major) of size `h x w`. Returns `[b, t, h/4, w/4, 32]`.

    The per-frame end (the head's resize to 14 x the patch grid, the resize to `h x w`
    and the 4x4 conv) runs in blocks of frames whose full-resolution float32 map fits
    `cfg.frame_block_mb` (`in_frame_blocks`; at 720x1280, 118 MB per frame).
    """
    grid = (h // PATCH, w // PATCH)
    feats = self._frozen(lambda mdl, tokens: mdl.depthanything.head_from_tokens(
        tokens, grid, b, t, resize_output=False))(self, tokens)
    feats = feats.reshape(b * t, *feats.shape[2:])

    def tail(mdl, x):
      x = resize_head_output(x, grid).astype(jnp.float32)
      return mdl.conv(resize(x, (h, w), "bilinear", False))

    out = in_frame_blocks(self, tail, feats, h * w * feats.shape[-1] * 4,
                          self.cfg.frame_block_mb)
    return out.reshape(b, t, *out.shape[-3:])

  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, H, W, 3]` normalised. Returns `[B, T, H/4, W/4, 32]`."""
    b, t, h, w, c = x.shape
    return self.from_tokens(self.tokens(x.reshape(b * t, h, w, c)), b, t, h, w)


def _stop_prior_gradient(variables):
  """The `depthanything` parameters of `variables` (a module's collections) behind
  `stop_gradient`; the rest as they are."""
  params = variables.get("params")
  if not params or "depthanything" not in params:
    return variables
  params = dict(params, depthanything=jax.tree_util.tree_map(jax.lax.stop_gradient,
                                                             params["depthanything"]))
  return dict(variables, params=params)

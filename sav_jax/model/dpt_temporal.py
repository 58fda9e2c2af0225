"""DPT head with temporal motion modules (Video Depth Anything), channels last.

Names follow the PyTorch `DPTHeadTemporal` (`projects.0`, `resize_layers.3`,
`scratch.refinenet1.resConfUnit2.conv1`, `motion_modules.0.temporal_transformer
.transformer_blocks.0.attention_blocks.1.to_q` ...) with list indices joined by
an underscore, so that checkpoint conversion is a mechanical rename.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from sav_jax.config import TEMPORAL_MAX_LEN  # the sinusoidal table's length (`max_len`)
from sav_jax.model.layers import conv, dense, gelu, layer_norm
from sav_jax.ops.resize import resize

# Motion-module settings fixed by DPTHeadTemporal (AnimateDiff-style modules).
MOTION_HEADS = 8
MOTION_ATTENTION_BLOCKS = 2
MOTION_TRANSFORMER_BLOCKS = 1
MOTION_GROUPS = 32
MOTION_GN_EPS = 1e-6
# The transformer blocks use torch's default nn.LayerNorm eps, unlike DINOv2 (1e-6).
MOTION_LN_EPS = 1e-5


@functools.lru_cache(maxsize=32)
def sinusoidal_table(length: int, dim: int) -> np.ndarray:
  """The `PositionalEncoding.pe` table of the motion modules, without its batch axis.

  `pe[t, 2i] = sin(t * f_i)`, `pe[t, 2i+1] = cos(t * f_i)` with
  `f_i = exp(2i * -ln(10000) / dim)`. Like torch, the exponent and the angle
  are rounded to float32 (the angle rounding alone moves the table by ~1e-6);
  exp/sin/cos are evaluated exactly and rounded once. Torch's own float32
  exp/sin are not correctly rounded, so the official buffers differ from this
  table by up to ~1e-6.

  Args:
    length: number of positions (frames).
    dim: channels (even).

  Returns:
    float32 `[length, dim]`.
  """
  if dim % 2:
    raise ValueError(f"sinusoidal table needs an even width, got {dim}")
  expo = np.arange(0, dim, 2).astype(np.float32) * np.float32(-math.log(10000.0) / dim)
  freq = np.exp(expo.astype(np.float64)).astype(np.float32)
  angle = (np.arange(length).astype(np.float32)[:, None] * freq[None]).astype(np.float64)
  table = np.zeros((length, dim), np.float32)
  table[:, 0::2] = np.sin(angle)
  table[:, 1::2] = np.cos(angle)
  table.flags.writeable = False  # shared through the cache
  return table


class TemporalAttention(nn.Module):
  """Self-attention across frames at every pixel, with an absolute sinusoidal pe."""

  heads: int = MOTION_HEADS
  max_len: int = TEMPORAL_MAX_LEN
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, S, C]` (S pixels). Returns `[B, T, S, C]`."""
    b, t, s, c = x.shape
    if t > self.max_len:
      raise ValueError(f"{t} frames exceed the temporal table length {self.max_len}")
    x = x + jnp.asarray(sinusoidal_table(self.max_len, c)[:t, None], x.dtype)
    head_dim = c // self.heads
    split = lambda y: y.reshape(b, t, s, self.heads, head_dim)  # noqa: E731
    q = split(dense(c, use_bias=False, dtype=self.dtype, name="to_q")(x))
    k = split(dense(c, use_bias=False, dtype=self.dtype, name="to_k")(x))
    v = split(dense(c, use_bias=False, dtype=self.dtype, name="to_v")(x))
    # logits accumulated and kept in float32 (bfloat16 logits would round before the softmax)
    logits = jnp.einsum("btshd,bushd->bshtu", q, k,
                        preferred_element_type=jnp.float32) * head_dim**-0.5
    probs = jax.nn.softmax(logits, axis=-1).astype(v.dtype)
    out = jnp.einsum("bshtu,bushd->btshd", probs, v).reshape(b, t, s, c)
    return dense(c, dtype=self.dtype, name="to_out_0")(out)


class GEGLU(nn.Module):
  """`proj` to 2x width, split into `[h, gate]`, return `h * gelu(gate)` (exact GELU)."""

  inner_dim: int
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    h, gate = jnp.split(dense(2 * self.inner_dim, dtype=self.dtype, name="proj")(x), 2, axis=-1)
    return h * gelu(gate)


class FeedForward(nn.Module):
  """`net.0` = GEGLU (4x), `net.1` = dropout (a no-op here), `net.2` = Linear."""

  mult: int = 4
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    dim = x.shape[-1]
    y = GEGLU(dim * self.mult, dtype=self.dtype, name="net_0")(x)
    return dense(dim, dtype=self.dtype, name="net_2")(y)


class TemporalTransformerBlock(nn.Module):
  """Two pre-norm temporal attentions then a GEGLU feed-forward, all residual."""

  heads: int = MOTION_HEADS
  max_len: int = TEMPORAL_MAX_LEN
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, S, C]`. Returns `[B, T, S, C]`."""
    for i in range(MOTION_ATTENTION_BLOCKS):
      y = layer_norm(MOTION_LN_EPS, dtype=self.dtype, name=f"norms_{i}")(x)
      x = x + TemporalAttention(self.heads, self.max_len, dtype=self.dtype,
                                name=f"attention_blocks_{i}")(y)
    y = layer_norm(MOTION_LN_EPS, dtype=self.dtype, name="ff_norm")(x)
    return x + FeedForward(dtype=self.dtype, name="ff")(y)


class TemporalTransformer3DModel(nn.Module):
  """GroupNorm (per frame) -> proj_in -> transformer blocks -> proj_out, plus the input."""

  heads: int = MOTION_HEADS
  max_len: int = TEMPORAL_MAX_LEN
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, H, W, C]`. Returns `[B, T, H, W, C]`."""
    b, t, h, w, c = x.shape
    y = nn.GroupNorm(MOTION_GROUPS, epsilon=MOTION_GN_EPS, use_fast_variance=False,
                     dtype=self.dtype, param_dtype=jnp.float32,
                     name="norm")(x.reshape(b * t, h, w, c))
    y = dense(c, dtype=self.dtype, name="proj_in")(y.reshape(b, t, h * w, c))
    for i in range(MOTION_TRANSFORMER_BLOCKS):
      y = TemporalTransformerBlock(self.heads, self.max_len, dtype=self.dtype,
                                   name=f"transformer_blocks_{i}")(y)
    y = dense(c, dtype=self.dtype, name="proj_out")(y)
    return y.reshape(b, t, h, w, c) + x


class TemporalModule(nn.Module):
  """Wrapper holding `temporal_transformer` (torch naming)."""

  max_len: int = TEMPORAL_MAX_LEN
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, H, W, C]`. Returns `[B, T, H, W, C]`."""
    return TemporalTransformer3DModel(max_len=self.max_len, dtype=self.dtype,
                                      name="temporal_transformer")(x)


class ResidualConvUnit(nn.Module):
  """`x + conv2(relu(conv1(relu(x))))` with 3x3 convs (no batch norm in VDA)."""

  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    c = x.shape[-1]
    y = conv(c, (3, 3), 1, 1, dtype=self.dtype, name="conv1")(jax.nn.relu(x))
    y = conv(c, (3, 3), 1, 1, dtype=self.dtype, name="conv2")(jax.nn.relu(y))
    return y + x


class FeatureFusionBlock(nn.Module):
  """RefineNet fusion: optional skip through resConfUnit1, resConfUnit2, resize, out_conv.

  The resize is bilinear with align_corners=True, to `size` or, without it,
  to twice the input size (torch ignores the scale factor's exact value when
  aligning corners, so only the output size matters).
  """

  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, skip: jax.Array | None = None,
               size: tuple[int, int] | None = None) -> jax.Array:
    """Args: x, skip `[N, H, W, C]`; size `(H', W')`. Returns `[N, H', W', C]`."""
    if skip is not None:
      # refinenet4 is never given a skip, so its resConfUnit1 holds no params.
      x = x + ResidualConvUnit(dtype=self.dtype, name="resConfUnit1")(skip)
    x = ResidualConvUnit(dtype=self.dtype, name="resConfUnit2")(x)
    if size is None:
      size = (2 * x.shape[-3], 2 * x.shape[-2])
    x = resize(x, size, mode="bilinear", align_corners=True)
    return conv(x.shape[-1], (1, 1), dtype=self.dtype, name="out_conv")(x)


class Scratch(nn.Module):
  """Container of the `scratch.*` layers; the head calls them one by one."""

  features: int = 64
  dtype: Any = jnp.float32

  def setup(self):
    f, dt = self.features, self.dtype
    self.layer1_rn = conv(f, (3, 3), 1, 1, use_bias=False, dtype=dt)
    self.layer2_rn = conv(f, (3, 3), 1, 1, use_bias=False, dtype=dt)
    self.layer3_rn = conv(f, (3, 3), 1, 1, use_bias=False, dtype=dt)
    self.layer4_rn = conv(f, (3, 3), 1, 1, use_bias=False, dtype=dt)
    self.refinenet1 = FeatureFusionBlock(dtype=dt)
    self.refinenet2 = FeatureFusionBlock(dtype=dt)
    self.refinenet3 = FeatureFusionBlock(dtype=dt)
    self.refinenet4 = FeatureFusionBlock(dtype=dt)
    # output_conv2 (the depth regressor) is never applied inside SAV: not built.
    self.output_conv1 = conv(f // 2, (3, 3), 1, 1, dtype=dt)


class DPTHeadTemporal(nn.Module):
  """DPT decoder with motion modules, stopped after `output_conv1` and its resize.

  Attributes:
    features: width of the fusion path.
    out_channels: widths of the four projected ViT layers.
    max_len: length of the motion modules' sinusoidal table (max frames).
    dtype: compute dtype (parameters stay float32).
  """

  features: int = 64
  out_channels: Sequence[int] = (48, 96, 192, 384)
  max_len: int = TEMPORAL_MAX_LEN
  dtype: Any = jnp.float32

  def setup(self):
    oc, dt = self.out_channels, self.dtype
    self.projects = [conv(c, (1, 1), dtype=dt) for c in oc]
    # torch ConvTranspose2d weights (in, out, kh, kw) map to HWOI kernels
    # with transpose_kernel=True (flip + in/out swap = torch's gradient-of-conv).
    self.resize_layers_0 = nn.ConvTranspose(oc[0], (4, 4), strides=(4, 4), padding="VALID",
                                            transpose_kernel=True, dtype=dt,
                                            param_dtype=jnp.float32)
    self.resize_layers_1 = nn.ConvTranspose(oc[1], (2, 2), strides=(2, 2), padding="VALID",
                                            transpose_kernel=True, dtype=dt,
                                            param_dtype=jnp.float32)
    # resize_layers.2 is an identity.
    self.resize_layers_3 = conv(oc[3], (3, 3), 2, 1, dtype=dt)
    self.scratch = Scratch(self.features, dtype=dt)
    self.motion_modules = [TemporalModule(self.max_len, dtype=dt) for _ in range(4)]

  def _temporal(self, i: int, x: jax.Array, frames: int) -> jax.Array:
    """Applies motion module i to `[B*T, H, W, C]` (b-major) frames."""
    n, h, w, c = x.shape
    y = self.motion_modules[i](x.reshape(n // frames, frames, h, w, c))
    return y.reshape(n, h, w, c)

  def __call__(self, tokens: Sequence[jax.Array], grid_hw: tuple[int, int],
               frames: int, resize_output: bool = True) -> jax.Array:
    """Decodes four ViT layers into the 32-channel feature map.

    Args:
      tokens: four patch-token arrays `[B*T, h*w, D]` (b-major, row-major patches).
      grid_hw: patch grid `(h, w)`.
      frames: T, to regroup the flat batch for the motion modules.
      resize_output: end with the resize to the input's size (`resize_head_output`);
        False returns `output_conv1`'s map at 8x the patch grid, for callers that
        resize it themselves in blocks of frames.

    Returns:
      `[B*T, 14h, 14w, features // 2]` (`[B*T, 8h, 8w, features // 2]` without the resize).
    """
    h, w = grid_hw
    resizers = (self.resize_layers_0, self.resize_layers_1, lambda y: y, self.resize_layers_3)
    layers = []
    for i, x in enumerate(tokens):
      x = x.reshape(x.shape[0], h, w, x.shape[-1])
      layers.append(resizers[i](self.projects[i](x)))
    layers[2] = self._temporal(0, layers[2], frames)
    layers[3] = self._temporal(1, layers[3], frames)
    sc = self.scratch
    rn = [sc.layer1_rn(layers[0]), sc.layer2_rn(layers[1]), sc.layer3_rn(layers[2]),
          sc.layer4_rn(layers[3])]
    path = sc.refinenet4(rn[3], size=rn[2].shape[1:3])
    path = self._temporal(2, path, frames)
    path = sc.refinenet3(path, rn[2], size=rn[1].shape[1:3])
    path = self._temporal(3, path, frames)
    path = sc.refinenet2(path, rn[1], size=rn[0].shape[1:3])
    path = sc.refinenet1(path, rn[0])
    out = sc.output_conv1(path)
    return resize_head_output(out, grid_hw) if resize_output else out


def resize_head_output(out: jax.Array, grid_hw: tuple[int, int]) -> jax.Array:
  """The head's last step: `output_conv1`'s map to the input's size (14 x the patch grid)."""
  h, w = grid_hw
  return resize(out, (14 * h, 14 * w), mode="bilinear", align_corners=True)

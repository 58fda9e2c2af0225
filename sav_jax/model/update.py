"""The temporal update block (`SequenceUpdateBlock3D` of the official code).

Shapes inside are `[B, T, h, w, C]`: 2-D convs run per frame (flax convs treat
the leading `B, T` as batch), 3-D convs over `(T, h, w)`.
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from sav_jax.config import FRAME_BLOCK_MB, GRU_CONV, resolve_gru_conv
from sav_jax.model.layers import (Conv2D, ConvParams, add_bias, conv, dense, dft_correlate_w,
                                  gelu, in_frame_blocks, layer_norm)


class BasicMotionEncoder(nn.Module):
  """Per-frame 2-D motion encoder: correlation and flow features + the flow.

  Stereo Any Video's flow has a y channel that is always zero (the official code zeroes
  it before every use), so its update block passes the x-flow alone: the 7x7 flow
  convolution then reads its kernel's x slice (the y slice only ever met zeros; the
  parameter keeps the official shape) and the output's last channel is that zero. RAFT
  passes both channels.
  """

  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, flow: jax.Array, corr: jax.Array) -> jax.Array:
    """Args: flow `[..., h, w, 2]`, or `[..., h, w, 1]` (x; y zero), corr `[..., h, w, C]`.
    Returns `[..., h, w, 128]` (126 features, then the flow's x and y)."""
    c = lambda f, k, p, n: conv(f, (k, k), 1, p, dtype=self.dtype, name=n)
    cor = nn.relu(c(256, 1, 0, "convc1")(corr))
    cor = nn.relu(c(192, 3, 1, "convc2")(cor))
    flow = flow.astype(self.dtype)
    flo = nn.relu(Conv2D(128, (7, 7), (3, 3), dtype=self.dtype, kernel_in=2, name="convf1")(flow))
    flo = nn.relu(c(64, 3, 1, "convf2")(flo))
    out = nn.relu(c(126, 3, 1, "conv")(jnp.concatenate([cor, flo], axis=-1)))
    if flow.shape[-1] == 1:
      flow = jnp.concatenate([flow, jnp.zeros_like(flow)], axis=-1)
    return jnp.concatenate([out, flow], axis=-1)


class TemporalAttention(nn.Module):
  """Self-attention over time at each pixel, q = k = v = the input (no qkv projection).

  The official module owns a `qkv` Linear that its forward never calls; the
  converter keeps that weight outside `params`.
  """

  dim: int = 256
  num_heads: int = 8
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, h, w, dim]`. Returns `[B, T, h, w, dim]`."""
    b, t, h, w, c = x.shape
    # One transpose to [B, h*w, heads, T, d] serves as q, k and v (the products' batch
    # axes lead), and one brings the output back.
    heads = x.reshape(b, t, h * w, self.num_heads, c // self.num_heads).transpose(0, 2, 3, 1, 4)
    scale = (c // self.num_heads) ** -0.5
    logits = jnp.einsum("bpntd,bpnsd->bpnts", heads, heads,
                        preferred_element_type=jnp.float32) * scale
    attn = jax.nn.softmax(logits, axis=-1).astype(self.dtype)
    out = jnp.einsum("bpnts,bpnsd->bpntd", attn, heads.astype(self.dtype))
    out = out.transpose(0, 3, 1, 2, 4).reshape(b, t, h, w, c)
    return dense(self.dim, dtype=self.dtype, name="proj")(out)


class TimeAttnBlock(nn.Module):
  """LayerNorm -> temporal attention -> `temporal_fc`, residual."""

  dim: int = 256
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, h, w, dim]`. Returns the same shape."""
    y = layer_norm(dtype=self.dtype, name="temporal_norm1")(x)
    y = TemporalAttention(self.dim, dtype=self.dtype, name="temporal_attn")(y)
    y = dense(self.dim, dtype=self.dtype, name="temporal_fc")(y)
    return x + y


def linear_attention(q: jax.Array, k: jax.Array, v: jax.Array, eps: float = 1e-6) -> jax.Array:
  """Linear attention ("Transformers are RNNs") as LoFTR implements it, head by head.

  The heads' `k^T v` products (`[D, Dv]` each) are computed together as one
  `[heads*D, heads*Dv]` product whose off-diagonal blocks (products across heads) are
  zeroed, and each head's normaliser rides along as `heads` more columns of the queries'
  product. That is 8x the multiply-adds of the per-head products (~0.13 M per position
  beside the layer's 0.65 M), but two plain matrix products instead of batched 32x32
  ones and the transposes they need: the space attention runs 12-15% faster on the CPU.
  Every head's sums hold the same terms as the per-head form.

  Args:
    q: `[N, L, heads, D]`.
    k: `[N, S, heads, D]`.
    v: `[N, S, heads, Dv]`.
    eps: denominator epsilon.

  Returns:
    `[N, L, heads, Dv]`.
  """
  n, length_q, heads, d = q.shape
  dv = v.shape[-1]
  length = v.shape[1]
  q = (jax.nn.elu(q) + 1).reshape(n, length_q, heads * d)
  k = (jax.nn.elu(k) + 1).reshape(n, length, heads * d)
  # The official code divides by the length and multiplies back (an fp16 overflow guard).
  v = (v / length).reshape(n, length, heads * dv)
  head_of_k = np.arange(heads * d) // d
  same_head = head_of_k[:, None] == np.arange(heads * dv)[None, :] // dv
  kv = jnp.where(same_head, jnp.einsum("nsc,nse->nce", k, v), 0)
  k_sum = jnp.where(head_of_k[:, None] == np.arange(heads), k.sum(axis=1)[:, :, None], 0)
  out = q @ jnp.concatenate([kv, k_sum], axis=-1)
  z = 1.0 / (out[..., heads * dv:] + eps)
  return out[..., :heads * dv].reshape(n, length_q, heads, dv) * z[..., None] * length


class LoFTREncoderLayer(nn.Module):
  """LoFTR encoder layer with linear attention (self-attention within a frame)."""

  d_model: int = 256
  nhead: int = 8
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[N, L, d_model]`. Returns the same shape."""
    n, length, c = x.shape
    # q, k and v as three products (LoFTR's form): one product with the kernels side by
    # side, its output sliced, was slower on the CPU, and the GPU comparison that had
    # adopted it was confounded (benchmarks/README.md, "Third lease").
    q, k, v = (dense(c, False, self.dtype, f"{p}_proj")(x).reshape(n, length, self.nhead, -1)
               for p in "qkv")
    msg = linear_attention(q, k, v).reshape(n, length, c)
    msg = dense(c, False, self.dtype, "merge")(msg)
    msg = layer_norm(dtype=self.dtype, name="norm1")(msg)
    msg = dense(2 * c, False, self.dtype, "mlp_0")(jnp.concatenate([x, msg], axis=-1))
    msg = dense(c, False, self.dtype, "mlp_2")(nn.relu(msg))
    msg = layer_norm(dtype=self.dtype, name="norm2")(msg)
    return x + msg


class SpaceAttnBlock(nn.Module):
  """Per-frame spatial linear attention over all `h*w` positions.

  Attributes:
    dim: channels.
    dtype: compute dtype.
    block_mb: frames run in blocks whose largest intermediate (the MLP's `2*dim`
      channels) fits this many MiB (`layers.in_frame_blocks`; same values).
  """

  dim: int = 256
  dtype: Any = jnp.float32
  block_mb: float = FRAME_BLOCK_MB

  def setup(self):
    self.encoder_layer = LoFTREncoderLayer(self.dim, dtype=self.dtype)

  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, h, w, dim]`. Returns the same shape."""
    b, t, h, w, c = x.shape
    frame_bytes = h * w * 2 * c * jnp.dtype(self.dtype).itemsize
    y = in_frame_blocks(self, lambda m, xb: m.encoder_layer(xb), x.reshape(b * t, h * w, c),
                        frame_bytes, self.block_mb)
    return y.reshape(b, t, h, w, c)


def conv_gru(h: jax.Array, x: jax.Array, convz, convr, convq) -> jax.Array:
  """One ConvGRU update of the state `h` from the input `x` (channels last)."""
  return gru_update(h, x, lambda hx: (convz(hx), convr(hx)), convq)


def gru_update(h: jax.Array, x: jax.Array, gates, convq) -> jax.Array:
  """`conv_gru` with the z and r logits from one call, `gates([h, x]) -> (z, r)`."""
  hx = jnp.concatenate([h, x], axis=-1)
  z_logits, r_logits = gates(hx)
  z, r = jax.nn.sigmoid(z_logits), jax.nn.sigmoid(r_logits)
  q = jnp.tanh(convq(jnp.concatenate([r * h, x], axis=-1)))
  return (1 - z) * h + z * q


class SKSepConvGRU3D(nn.Module):
  """Separable 3-D ConvGRU: a W pass (large-kernel z/r), then H, then T.

  Attributes:
    hidden_dim: state channels.
    dtype: compute dtype.
    wide_conv: how the W pass's 1x15 z/r convolutions run: "direct" (XLA's convolutions),
      "dft" (both as one `dft_correlate_w`: products per frequency bin; the same
      parameters and values to float32 rounding) or "auto" (`SAVConfig.gru_conv`,
      `config.resolve_gru_conv`).
    block_mb: with "dft", the memory budget (MiB) of its spectra (`dft_correlate_w`).
  """

  hidden_dim: int = 128
  dtype: Any = jnp.float32
  wide_conv: str = "direct"
  block_mb: float = FRAME_BLOCK_MB

  @nn.compact
  def __call__(self, h: jax.Array, x: jax.Array) -> jax.Array:
    """Args: h `[B, T, h, w, hidden]`, x `[B, T, h, w, 256]`. Returns the new h."""
    hd = self.hidden_dim
    c3 = lambda k, p, n: conv(hd, k, 1, p, dtype=self.dtype, name=n)

    # The z and r gates of the W pass: a 1x15 convolution (`conv{g}1_0`), GELU, a 1x5 one.
    second = lambda g: c3((1, 1, 5), (0, 0, 2), f"conv{g}1_2")  # noqa: E731

    def super_kernel(g):
      first, then = c3((1, 1, 15), (0, 0, 7), f"conv{g}1_0"), second(g)
      return lambda y: then(gelu(first(y)))

    wide_conv = resolve_gru_conv(self.wide_conv, self.dtype)
    if wide_conv == "dft":
      seconds = [second(g) for g in "zr"]

      def gates(hx):  # the z and r first convolutions share one DFT of [h, x]
        weights = [ConvParams(hd, (1, 1, 15), name=f"conv{g}1_0")(hx.shape[-1]) for g in "zr"]
        kernel = jnp.concatenate([k[0, 0] for k, _ in weights], axis=-1)
        bias = jnp.concatenate([b for _, b in weights])
        firsts = gelu(add_bias(dft_correlate_w(hx.astype(self.dtype), kernel, self.block_mb), bias))
        return tuple(second(part) for second, part in zip(seconds, jnp.split(firsts, 2, -1)))
    elif wide_conv == "direct":
      convz, convr = super_kernel("z"), super_kernel("r")
      gates = lambda hx: (convz(hx), convr(hx))  # noqa: E731
    else:
      raise ValueError(f"SKSepConvGRU3D.wide_conv={self.wide_conv!r}; expected one of {GRU_CONV}")
    h = gru_update(h, x, gates, c3((1, 1, 5), (0, 0, 2), "convq1"))
    k, p = (1, 5, 1), (0, 2, 0)
    h = conv_gru(h, x, c3(k, p, "convz2"), c3(k, p, "convr2"), c3(k, p, "convq2"))
    k, p = (5, 1, 1), (2, 0, 0)
    return conv_gru(h, x, c3(k, p, "convz3"), c3(k, p, "convr3"), c3(k, p, "convq3"))


class FlowHead3D(nn.Module):
  """3x3x3 conv (256) -> ReLU -> 3x3x3 conv (2): the disparity update."""

  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[B, T, h, w, C]`. Returns `[B, T, h, w, 2]`."""
    x = nn.relu(conv(256, (3, 3, 3), 1, 1, dtype=self.dtype, name="conv1")(x))
    return conv(2, (3, 3, 3), 1, 1, dtype=self.dtype, name="conv2")(x)


class SequenceUpdateBlock3D(nn.Module):
  """Motion encoder, time and space attention, 3-D GRU, flow and mask heads."""

  hidden_dim: int = 128
  mask_size: int = 4
  dtype: Any = jnp.float32
  block_mb: float = FRAME_BLOCK_MB
  gru_conv: str = "direct"  # `SKSepConvGRU3D.wide_conv` ("auto" resolved there)

  def setup(self):
    dt = self.dtype
    self.encoder = BasicMotionEncoder(dt)
    self.time_attn = TimeAttnBlock(256, dt)
    self.space_attn = SpaceAttnBlock(256, dt, self.block_mb)
    self.gru = SKSepConvGRU3D(self.hidden_dim, dt, self.gru_conv, self.block_mb)
    self.flow_head = FlowHead3D(dt)
    self.mask3d_0 = conv(256, (3, 3, 3), 1, 1, dtype=dt)
    self.mask3d_2 = conv(27 * self.mask_size ** 2, (1, 1, 1), 1, 0, dtype=dt)

  def __call__(self, net, inp, corr, flow, with_mask: bool = True):
    """One refinement update.

    Args:
      net: `[B, T, h, w, hidden]` GRU state.
      inp: `[B, T, h, w, 128]` context input.
      corr: `[B, T, h, w, 128]` correlation features (after `corr_mlp`).
      flow: `[B, T, h, w, 1]` current x-flow (the official block's input has a y channel,
        always zero: see `BasicMotionEncoder`).
      with_mask: compute the upsampling mask (else `mask` is None).

    Returns:
      `(net, mask, delta_flow)`: new state, upsampling-mask logits
      `[B, T, h, w, 27*mask_size**2]` (already x0.25, `mask_logits` of the new state), and
      `[B, T, h, w, 2]`.
    """
    dt = self.dtype
    if flow.shape[-1] != 1:
      raise ValueError(f"update block: flow must be the x-flow [..., 1], got shape {flow.shape}")
    motion = self.encoder(flow, corr.astype(dt))
    x = jnp.concatenate([inp.astype(dt), motion], axis=-1)
    x = self.time_attn(x)
    x = self.space_attn(x)
    net = self.gru(net.astype(dt), x)
    delta = self.flow_head(net).astype(jnp.float32)
    return net, self.mask_logits(net) if with_mask else None, delta

  def mask_logits(self, net):
    """The upsampling-mask head on a GRU state `[B, T, h, w, hidden]`: float32 logits
    `[B, T, h, w, 27*mask_size**2]`, already x0.25 (as the official code scales them)."""
    mask = self.mask3d_2(nn.relu(self.mask3d_0(net.astype(self.dtype))))
    return 0.25 * mask.astype(jnp.float32)

"""DINOv2 ViT backbone of Video Depth Anything (channels last, torch-exact numerics).

Submodule names follow the PyTorch `DinoVisionTransformer` (`patch_embed.proj`,
`blocks.<i>.attn.qkv`, `ls1.gamma` ...), with list indices joined by an
underscore (`blocks_3`), so that checkpoint conversion is a mechanical rename.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from sav_jax.config import FRAME_BLOCK_MB, resolve_vit_attention
from sav_jax.model.layers import dense, frames_per_block, gelu, layer_norm, param
from sav_jax.ops.resize import resize

# DINOv2 offsets the target grid by 0.1 before computing the pos-embed scale
# factor (facebookresearch/dino issue 8); VDA keeps that default.
INTERPOLATE_OFFSET = 0.1
# LayerNorm eps of every DINOv2 norm (norm1, norm2, final norm).
DINO_LN_EPS = 1e-6

# Per-variant ViT hyper-parameters and the blocks that feed the DPT head.
DINO_VARIANTS = {
    "vits": dict(embed_dim=384, depth=12, num_heads=6, layers=(2, 5, 8, 11)),
    "vitb": dict(embed_dim=768, depth=12, num_heads=12, layers=(2, 5, 8, 11)),
    "vitl": dict(embed_dim=1024, depth=24, num_heads=16, layers=(4, 11, 17, 23)),
}


def interpolate_pos_embed(pos_embed: jax.Array, grid_hw: tuple[int, int]) -> jax.Array:
  """Resizes the learned position table to a patch grid, as DINOv2 does.

  The patch part is resized bicubically (A=-0.75, antialias off,
  align_corners=False) with the *scale factor* `(n + 0.1) / sqrt(N)` rather
  than a target size, which shifts every source coordinate slightly
  (`(dst + 0.5) * sqrt(N) / (n + 0.1) - 0.5`). The table is returned untouched
  for the native square grid, exactly like the official early exit.

  Args:
    pos_embed: `[1, 1 + N, D]`, class-token row first, N a square number.
    grid_hw: patch grid `(h, w)` of the input.

  Returns:
    `[1, 1 + h * w, D]` float32, class-token row first, patches row-major.
  """
  h, w = grid_hw
  n = pos_embed.shape[1] - 1
  pos_embed = pos_embed.astype(jnp.float32)
  if h * w == n and h == w:
    return pos_embed
  side = int(math.sqrt(n))
  if side * side != n:
    raise ValueError(f"pos_embed has {n} patch rows, not a square grid")
  dim = pos_embed.shape[-1]
  grid = pos_embed[0, 1:].reshape(side, side, dim)
  scale = ((h + INTERPOLATE_OFFSET) / side, (w + INTERPOLATE_OFFSET) / side)
  out_hw = (math.floor(side * scale[0]), math.floor(side * scale[1]))
  if out_hw != (h, w):  # torch asserts the same
    raise ValueError(f"pos-embed resize gives {out_hw}, expected {(h, w)}")
  grid = resize(grid, out_hw, mode="bicubic", align_corners=False, scale_factor=scale)
  return jnp.concatenate([pos_embed[:, :1], grid.reshape(1, h * w, dim)], axis=1)


def attention_blocks(n: int, heads: int, length: int, budget_mb: float) -> tuple[int, int]:
  """Frames and query rows per block so that one block's float32 logits fit `budget_mb`.

  Returns `(n, length)` (a single block: the plain computation) when everything fits;
  else the largest divisor of `n` frames whose logits fit, with all query rows; else one
  frame and as many query rows as fit (at least one).
  """
  budget = budget_mb * 2**20
  per_frame = heads * length * length * 4
  if per_frame <= budget:
    return frames_per_block(n, per_frame, budget_mb), length
  return 1, max(1, int(budget // (heads * length * 4)))


def softmax_attention(q: jax.Array, k: jax.Array, v: jax.Array,
                      budget_mb: float = FRAME_BLOCK_MB) -> jax.Array:
  """`softmax(q k^T) v` per frame and head, in blocks that keep the logits under `budget_mb`.

  Every query row's softmax is independent of the others, so blocks of frames and of
  query rows (`jax.lax.map`) give the values of the single product while bounding its
  memory: at 720x1280 (4642 tokens) one frame's logits take 0.5 GB in float32, forty
  frames 21 GB.

  Args:
    q: `[N, L, heads, d]`, already scaled.
    k, v: `[N, L, heads, d]`.
    budget_mb: memory of one block's float32 logits, MiB.

  Returns:
    `[N, L, heads, d]` in `v`'s dtype; the softmax runs in float32.
  """
  n, length, heads, d = q.shape

  def plain(q, k, v):
    # Logits and softmax in float32 whatever the compute dtype: DINO logits get large
    # (bfloat16 logits would keep 8 bits of them).
    logits = jnp.einsum("nqhd,nkhd->nhqk", q, k, preferred_element_type=jnp.float32)
    probs = jax.nn.softmax(logits, axis=-1).astype(v.dtype)
    return jnp.einsum("nhqk,nkhd->nqhd", probs, v)

  frames, rows = attention_blocks(n, heads, length, budget_mb)
  if (frames, rows) == (n, length):
    return plain(q, k, v)
  if rows == length:
    split = lambda x: x.reshape(n // frames, frames, *x.shape[1:])  # noqa: E731
    out = jax.lax.map(lambda qkv: plain(*qkv), (split(q), split(k), split(v)))
    return out.reshape(n, length, heads, d)
  # One frame at a time, its query rows in blocks (padded queries are dropped again).
  nb = -(-length // rows)
  qp = jnp.pad(q, ((0, 0), (0, nb * rows - length), (0, 0), (0, 0)))

  def frame(args):
    qf, kf, vf = args  # [nb, rows, h, d], [L, h, d], [L, h, d]
    return jax.lax.map(lambda qr: plain(qr[None], kf[None], vf[None])[0], qf)

  out = jax.lax.map(frame, (qp.reshape(n, nb, rows, heads, d), k, v))  # [n, nb, rows, h, d]
  return out.reshape(n, nb * rows, heads, d)[:, :length]


def fused_attention(q: jax.Array, k: jax.Array, v: jax.Array,
                    implementation: str = "cudnn") -> jax.Array:
  """`softmax(q k^T) v` as one fused kernel (`jax.nn.dot_product_attention`).

  With "cudnn", cuDNN's flash attention: the logits are never stored, the softmax runs
  in float32 inside the kernel and the probabilities meet `v` in its dtype, as in
  `softmax_attention`. "xla" is JAX's reference path (it stores the logits), which
  checks the layout and scaling on any backend.

  Args:
    q: `[N, L, heads, d]`, already scaled.
    k, v: `[N, L, heads, d]`.
    implementation: "cudnn" (CUDA GPUs, bfloat16/float16) or "xla".

  Returns:
    `[N, L, heads, d]` in `v`'s dtype.
  """
  if implementation == "cudnn":
    backend = jax.default_backend()
    if backend != "gpu":
      raise ValueError(f"SAVConfig.vit_attention='cudnn' needs a CUDA GPU; JAX's backend is "
                       f"{backend!r} (use 'blocked', or the default 'auto', which picks it there)")
    if q.dtype not in (jnp.bfloat16, jnp.float16):
      raise ValueError(f"SAVConfig.vit_attention='cudnn' needs bfloat16 compute, got {q.dtype}")
  return jax.nn.dot_product_attention(q, k, v, scale=1.0, implementation=implementation)


class Attention(nn.Module):
  """Multi-head self-attention with a fused qkv projection (plain softmax path).

  Attributes:
    num_heads: heads.
    dtype: compute dtype (the softmax runs in float32).
    block_mb: memory budget of one block of logits (`softmax_attention`).
    implementation: "blocked" (`softmax_attention`, every backend), "cudnn"
      (`fused_attention`: CUDA GPUs, bfloat16) or "auto" (`config.resolve_vit_attention`).
  """

  num_heads: int
  dtype: Any = jnp.float32
  block_mb: float = FRAME_BLOCK_MB
  implementation: str = "blocked"

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[N, L, D]`. Returns `[N, L, D]`."""
    n, length, dim = x.shape
    head_dim = dim // self.num_heads
    qkv = dense(3 * dim, dtype=self.dtype, name="qkv")(x)
    # torch reshapes the fused output as (3, heads, head_dim).
    qkv = qkv.reshape(n, length, 3, self.num_heads, head_dim)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
    q = q * head_dim**-0.5
    if resolve_vit_attention(self.implementation, self.dtype) == "cudnn":
      out = fused_attention(q, k, v, "cudnn")
    else:
      out = softmax_attention(q, k, v, self.block_mb)
    out = out.reshape(n, length, dim)
    return dense(dim, dtype=self.dtype, name="proj")(out)


class Mlp(nn.Module):
  """fc1 -> exact GELU -> fc2."""

  hidden_dim: int
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[..., D]`. Returns `[..., D]`."""
    y = gelu(dense(self.hidden_dim, dtype=self.dtype, name="fc1")(x))
    return dense(x.shape[-1], dtype=self.dtype, name="fc2")(y)


class LayerScale(nn.Module):
  """Per-channel learned scale `gamma` (torch name kept)."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    gamma = param(self, "gamma", nn.initializers.ones, (x.shape[-1],))
    return x * gamma.astype(x.dtype)


class Block(nn.Module):
  """Pre-norm transformer block with LayerScale on both residual branches."""

  num_heads: int
  mlp_ratio: float = 4.0
  dtype: Any = jnp.float32
  attention_block_mb: float = FRAME_BLOCK_MB
  attention: str = "blocked"

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[N, L, D]`. Returns `[N, L, D]`."""
    dim = x.shape[-1]
    y = layer_norm(DINO_LN_EPS, dtype=self.dtype, name="norm1")(x)
    y = Attention(self.num_heads, self.dtype, self.attention_block_mb, self.attention,
                  name="attn")(y)
    x = x + LayerScale(name="ls1")(y)
    y = layer_norm(DINO_LN_EPS, dtype=self.dtype, name="norm2")(x)
    y = Mlp(int(dim * self.mlp_ratio), dtype=self.dtype, name="mlp")(y)
    return x + LayerScale(name="ls2")(y)


class PatchEmbed(nn.Module):
  """Non-overlapping `patch x patch` conv, flattened row-major to tokens."""

  embed_dim: int
  patch_size: int = 14
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[N, H, W, 3]`, H and W multiples of the patch. Returns `[N, h*w, D]`."""
    p = self.patch_size
    y = nn.Conv(self.embed_dim, (p, p), strides=(p, p), padding="VALID", dtype=self.dtype,
                param_dtype=jnp.float32, name="proj")(x)
    return y.reshape(y.shape[0], -1, self.embed_dim)


class DinoVisionTransformer(nn.Module):
  """DINOv2 ViT returning normalised intermediate layers.

  Attributes:
    embed_dim: token width D.
    depth: number of blocks.
    num_heads: attention heads.
    layers: indices of the blocks whose outputs are returned.
    patch_size: patch side in pixels.
    img_size: pretraining image side; fixes the learned pos-embed grid (518 -> 37x37).
    dtype: compute dtype (parameters stay float32).
    attention_block_mb: memory budget of one block of attention logits
      (`softmax_attention`); large inputs run the attention in blocks.
    attention: "blocked" (`softmax_attention`) or "cudnn" (`fused_attention`).
  """

  embed_dim: int = 384
  depth: int = 12
  num_heads: int = 6
  layers: Sequence[int] = (2, 5, 8, 11)
  patch_size: int = 14
  img_size: int = 518
  dtype: Any = jnp.float32
  attention_block_mb: float = FRAME_BLOCK_MB
  attention: str = "blocked"

  @nn.compact
  def __call__(self, x: jax.Array) -> tuple[list[tuple[jax.Array, jax.Array]], jax.Array]:
    """Runs `get_intermediate_layers(x, layers, return_class_token=True, norm=True)`.

    Args:
      x: `[N, H, W, 3]` normalised images, H and W multiples of the patch size.

    Returns:
      `(outputs, pos_embed)`: `outputs[i] = (patch [N, h*w, D], cls [N, D])` for
      block `layers[i]`, both after the final norm; `pos_embed` is the
      interpolated table `[1, 1 + h*w, D]` (float32) that was added.
    """
    n, height, width, _ = x.shape
    p = self.patch_size
    if height % p or width % p:
      raise ValueError(f"image {height}x{width} is not a multiple of the patch size {p}")
    grid = (height // p, width // p)
    num_pos = (self.img_size // p) ** 2 + 1
    cls_token = param(self, "cls_token", nn.initializers.zeros, (1, 1, self.embed_dim))
    pos_table = param(self, "pos_embed", nn.initializers.normal(0.02), (1, num_pos, self.embed_dim))
    tokens = PatchEmbed(self.embed_dim, p, dtype=self.dtype, name="patch_embed")(x)
    cls = jnp.broadcast_to(cls_token.astype(tokens.dtype), (n, 1, self.embed_dim))
    pos_embed = interpolate_pos_embed(pos_table, grid)
    tokens = jnp.concatenate([cls, tokens], axis=1) + pos_embed.astype(tokens.dtype)
    norm = layer_norm(DINO_LN_EPS, dtype=self.dtype, name="norm")
    outputs = []
    for i in range(self.depth):
      tokens = Block(self.num_heads, dtype=self.dtype, attention_block_mb=self.attention_block_mb,
                     attention=self.attention, name=f"blocks_{i}")(tokens)
      if i in self.layers:
        normed = norm(tokens)
        outputs.append((normed[:, 1:], normed[:, 0]))
    return outputs, pos_embed

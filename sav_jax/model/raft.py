"""RAFT optical flow (Teed & Deng, 2020): the flow model of the official evaluator.

The official evaluation computes TCM, OPW and RTC from RAFT flows (`raft-things`
checkpoint, 20 iterations, images padded to a multiple of 8 by edge replication, "sintel"
mode: the padding split between both sides, the full-resolution flow cropped back). This
is that model in Flax, with the official layout of the large model:

- `fnet`: residual encoder (instance norm) 7x7/2 stem, 64 -> 96 (/2) -> 128 (/2), 1x1 to 256.
- `cnet`: the same with batch norm (running statistics), 256 outputs split into the GRU
  state (`tanh`, 128) and its input (`relu`, 128).
- all-pairs correlation at 1/8, divided by sqrt(256), a 4-level pyramid (2x2 average
  pooling of the second image's axes), looked up in a 9x9 window (radius 4) around the
  current correspondence by bilinear sampling (`grid_sample`, zero padding,
  `align_corners=True`). The window is transposed as in the official code: channel
  `a*9 + b` of a level holds the sample at x offset `a - 4`, y offset `b - 4`.
- update block: motion encoder, separable ConvGRU (1x5 then 5x1), flow head, and the
  convex 8x upsampling mask (x0.25).

`raft_flow_fn(variables)` gives the `(img1, img2) -> flow` function that
`sav_jax.metrics.eval_batch` and `python -m eval` use; `sav_jax.convert.raft` reads the
official checkpoint.
"""

from __future__ import annotations

import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from sav_jax._checks import is_int
from sav_jax.model.layers import conv, instance_norm
from sav_jax.model.update import BasicMotionEncoder, conv_gru
from sav_jax.ops.pool import avg_pool, pad_replicate
from sav_jax.ops.upsample import convex_upsample_2d

HIDDEN = 128
CONTEXT = 128
LEVELS = 4
RADIUS = 4
# The coarsest level needs two rows and columns (its sampling divides by size - 1).
MIN_SIZE = 8 * 2 ** LEVELS


def _norm(kind: str, name: str):
  """`nn.InstanceNorm2d` (no parameters) or `nn.BatchNorm2d` in evaluation mode."""
  if kind == "instance":
    return instance_norm
  return nn.BatchNorm(use_running_average=True, epsilon=1e-5, name=name)


class RAFTResidualBlock(nn.Module):
  """Two 3x3 convs with norms; a strided block adds a 1x1 conv + norm on the skip path."""

  planes: int
  stride: int
  norm: str

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    y = conv(self.planes, (3, 3), self.stride, 1, name="conv1")(x)
    y = nn.relu(_norm(self.norm, "norm1")(y))
    y = nn.relu(_norm(self.norm, "norm2")(conv(self.planes, (3, 3), 1, 1, name="conv2")(y)))
    if self.stride != 1:  # the official norm3, registered again as downsample.1
      x = conv(self.planes, (1, 1), self.stride, 0, name="downsample_0")(x)
      x = _norm(self.norm, "downsample_1")(x)
    return nn.relu(x + y)


class RAFTEncoder(nn.Module):
  """RAFT's `BasicEncoder`: `[N, H, W, 3]` in [-1, 1] -> `[N, H/8, W/8, output_dim]`."""

  output_dim: int
  norm: str

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    x = nn.relu(_norm(self.norm, "norm1")(conv(64, (7, 7), 2, 3, name="conv1")(x)))
    for i, (dim, stride) in enumerate([(64, 1), (96, 2), (128, 2)], start=1):
      x = RAFTResidualBlock(dim, stride, self.norm, name=f"layer{i}_0")(x)
      x = RAFTResidualBlock(dim, 1, self.norm, name=f"layer{i}_1")(x)
    return conv(self.output_dim, (1, 1), name="conv2")(x)


class SepConvGRU(nn.Module):
  """ConvGRU with 1x5 convolutions, then again with 5x1 ones."""

  @nn.compact
  def __call__(self, h: jax.Array, x: jax.Array) -> jax.Array:
    for i, (k, p) in enumerate([((1, 5), (0, 2)), ((5, 1), (2, 0))], start=1):
      c = [conv(HIDDEN, k, 1, p, name=f"conv{g}{i}") for g in "zrq"]
      h = conv_gru(h, x, *c)
    return h


class FlowHead(nn.Module):
  """3x3 conv (256) -> ReLU -> 3x3 conv (2)."""

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    return conv(2, (3, 3), 1, 1, name="conv2")(nn.relu(conv(256, (3, 3), 1, 1, name="conv1")(x)))


class RAFTUpdateBlock(nn.Module):
  """Motion encoder, separable ConvGRU and flow head; `mask` is the upsampling head."""

  def setup(self):
    self.encoder = BasicMotionEncoder()
    self.gru = SepConvGRU()
    self.flow_head = FlowHead()
    self.mask_0 = conv(256, (3, 3), 1, 1)
    self.mask_2 = conv(9 * 64, (1, 1), 1, 0)

  def __call__(self, net, inp, corr, flow):
    """Returns `(net, delta_flow)`."""
    net = self.gru(net, jnp.concatenate([inp, self.encoder(flow, corr)], axis=-1))
    return net, self.flow_head(net)

  def mask(self, net):
    """Convex-upsampling logits `[..., 576]` (x0.25, as in the official code)."""
    return 0.25 * self.mask_2(nn.relu(self.mask_0(net)))


def correlation_pyramid(fmap1: jax.Array, fmap2: jax.Array, levels: int = LEVELS) -> list:
  """All-pairs correlation `[B, h, w, h_l, w_l]` per level (level l pooled 2^l times)."""
  d = fmap1.shape[-1]
  corr = jnp.einsum("bijd,bkld->bijkl", fmap1, fmap2) / jnp.sqrt(jnp.float32(d))
  pyramid = [corr]
  for _ in range(levels - 1):
    corr = avg_pool(corr[..., None], 2)[..., 0]
    pyramid.append(corr)
  return pyramid


def lookup(pyramid: list, coords: jax.Array, radius: int = RADIUS) -> jax.Array:
  """The correlation around `coords` at every level, `[B, h, w, levels * (2r+1)^2]`.

  Args:
    pyramid: from `correlation_pyramid`.
    coords: `[B, h, w, 2]` (x, y) positions in the second image at 1/8.
    radius: window radius r.

  The window's offsets are integers, so one pixel's samples share their bilinear weights:
  the `(2r+2)^2` corner values are gathered once and blended.
  """
  n = 2 * radius + 1
  span = jnp.arange(-radius, radius + 2)
  out = []
  for i, corr in enumerate(pyramid):
    b, h, w, hl, wl = corr.shape
    c = coords.astype(jnp.float32) / 2 ** i
    x0, y0 = jnp.floor(c[..., 0]), jnp.floor(c[..., 1])
    fx, fy = (c[..., 0] - x0)[..., None, None], (c[..., 1] - y0)[..., None, None]
    ys = y0.astype(jnp.int32)[..., None, None] + span[:, None]  # [b,h,w,n+1,1]
    xs = x0.astype(jnp.int32)[..., None, None] + span[None, :]  # [b,h,w,1,n+1]
    inside = (ys >= 0) & (ys < hl) & (xs >= 0) & (xs < wl)
    idx = jnp.clip(ys, 0, hl - 1) * wl + jnp.clip(xs, 0, wl - 1)
    vals = jnp.take_along_axis(corr.reshape(b, h, w, hl * wl),
                               idx.reshape(b, h, w, -1), axis=-1).reshape(idx.shape)
    p = jnp.where(inside, vals, 0.0)  # p[u, v]: row y0 - r + u, column x0 - r + v
    s = ((1 - fy) * (1 - fx) * p[..., :-1, :-1] + (1 - fy) * fx * p[..., :-1, 1:]
         + fy * (1 - fx) * p[..., 1:, :-1] + fy * fx * p[..., 1:, 1:])  # [..., y, x]
    out.append(jnp.swapaxes(s, -1, -2).reshape(b, h, w, n * n))  # channel = x * n + y
  return jnp.concatenate(out, axis=-1)


def coords_grid(b: int, h: int, w: int) -> jax.Array:
  """`[b, h, w, 2]` pixel positions (x, y)."""
  ys, xs = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32),
                        indexing="ij")
  return jnp.broadcast_to(jnp.stack([xs, ys], axis=-1), (b, h, w, 2))


class RAFT(nn.Module):
  """RAFT (large): `(image1, image2)` RGB 0..255 `[B, H, W, 3]`, H and W multiples of 8."""

  def setup(self):
    self.fnet = RAFTEncoder(256, "instance")
    self.cnet = RAFTEncoder(HIDDEN + CONTEXT, "batch")
    self.update_block = RAFTUpdateBlock()

  def __call__(self, image1: jax.Array, image2: jax.Array, iters: int = 20,
               flow_init: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """Returns `(flow at 1/8 [B, H/8, W/8, 2], flow [B, H, W, 2])`, (x, y) in pixels.

    Args:
      image1, image2: `[B, H, W, 3]` RGB 0..255; H and W multiples of 8 and at least 128
        (`pad_to_multiple_of_8` pads as the evaluator does).
      iters: refinement iterations (the evaluator: 20).
      flow_init: optional `[B, H/8, W/8, 2]` initial flow.
    """
    _check_images(image1, image2)
    b = image1.shape[0]
    norm = lambda im: 2 * (im.astype(jnp.float32) / 255.0) - 1.0  # noqa: E731
    fmaps = self.fnet(jnp.concatenate([norm(image1), norm(image2)], axis=0))
    pyramid = correlation_pyramid(fmaps[:b], fmaps[b:])
    ctx = self.cnet(norm(image1))
    net, inp = jnp.tanh(ctx[..., :HIDDEN]), nn.relu(ctx[..., HIDDEN:])
    coords0 = coords_grid(b, *fmaps.shape[1:3])
    coords1 = coords0 if flow_init is None else coords0 + flow_init

    def step(mdl, carry, inp, pyramid):
      net, coords1 = carry
      coords1 = jax.lax.stop_gradient(coords1)
      corr = lookup(pyramid, coords1)
      net, delta = mdl.update_block(net, inp, corr, coords1 - coords0)
      return (net, coords1 + delta), None

    scan = nn.scan(step, variable_broadcast=["params", "batch_stats"],
                   split_rngs={"params": False}, in_axes=(nn.broadcast, nn.broadcast),
                   length=iters)
    (net, coords1), _ = scan(self, (net, coords1), inp, pyramid)
    flow = coords1 - coords0
    return flow, convex_upsample_2d(flow, self.update_block.mask(net), 8)


def _check_images(image1, image2):
  if image1.ndim != 4 or image1.shape[-1] != 3 or image1.shape != image2.shape:
    raise ValueError(f"RAFT takes two images [B, H, W, 3] of one shape, got {image1.shape} "
                     f"and {image2.shape}")
  h, w = image1.shape[1:3]
  if h % 8 or w % 8:
    raise ValueError(f"RAFT needs H and W multiples of 8, got {h}x{w} "
                     "(pad with sav_jax.model.raft.pad_to_multiple_of_8)")
  if min(h, w) < MIN_SIZE:
    coarsest = 8 * 2 ** (LEVELS - 1)
    raise ValueError(f"RAFT needs images of at least {MIN_SIZE}x{MIN_SIZE} pixels after "
                     f"padding, got {h}x{w}: its coarsest correlation level (1/{coarsest}) "
                     "would have fewer than two rows or columns")


def padding_for(h: int, w: int) -> tuple[tuple[int, int], tuple[int, int]]:
  """The official `InputPadder` ("sintel" mode): `((top, bottom), (left, right))` to /8."""
  ph, pw = (-h) % 8, (-w) % 8
  return (ph // 2, ph - ph // 2), (pw // 2, pw - pw // 2)


def pad_to_multiple_of_8(image: jax.Array) -> jax.Array:
  """Edge-replicates `[..., H, W, C]` to multiples of 8, split as `padding_for`."""
  return pad_replicate(image, *padding_for(*image.shape[-3:-1]))


@functools.partial(jax.jit, static_argnames=("iters",))
def _padded_flow(variables, image1, image2, iters):
  h, w = image1.shape[1:3]
  (top, _), (left, _) = padding_for(h, w)
  _, flow = RAFT().apply(variables, pad_to_multiple_of_8(image1), pad_to_multiple_of_8(image2),
                         iters=iters)
  return flow[:, top:top + h, left:left + w]


def _check_iters(iters) -> int:
  """`iters` as an int; a ValueError unless it is an integer >= 1 (0 or fewer ran no
  update and gave a zero flow, which TCM/OPW/RTC would have scored without a word)."""
  if not is_int(iters) or iters < 1:
    raise ValueError(f"RAFT iters must be an integer >= 1, got {iters!r}")
  return int(iters)


def raft_flow(variables, image1, image2, iters: int = 20) -> jax.Array:
  """The evaluator's flow (`RAFTModel.forward_fullres`): pad to /8, RAFT, crop back.

  Args:
    variables: RAFT variables (`sav_jax.convert.raft.raft_variables_from_state_dict`).
    image1, image2: `[B, H, W, 3]` (or `[H, W, 3]`) RGB 0..255.
    iters: refinement iterations.

  Returns:
    `[B, H, W, 2]` (or `[H, W, 2]`) float32 flow (x, y) from image1 to image2.
  """
  iters = _check_iters(iters)
  single = np.ndim(image1) == 3
  if single:
    image1, image2 = image1[None], image2[None]
  image1, image2 = jnp.asarray(image1, jnp.float32), jnp.asarray(image2, jnp.float32)
  if image1.ndim != 4 or image1.shape[-1] != 3 or image1.shape != image2.shape:
    raise ValueError(f"raft_flow takes two images [B, H, W, 3] (or [H, W, 3]) of one shape, "
                     f"got {np.shape(image1)} and {np.shape(image2)}")
  padded = [n + p for n, p in zip(image1.shape[1:3], map(sum, padding_for(*image1.shape[1:3])))]
  if min(padded) < MIN_SIZE:
    raise ValueError(f"raft_flow: images of {image1.shape[1]}x{image1.shape[2]} are too small "
                     f"for RAFT (at least {MIN_SIZE}x{MIN_SIZE} after padding to /8)")
  flow = _padded_flow(variables, image1, image2, iters)
  return flow[0] if single else flow


def raft_flow_fn(variables, iters: int = 20):
  """`(img1 [3, H, W], img2 [3, H, W]) -> [2, H, W]` numpy flow: the `flow_fn` of
  `sav_jax.metrics.eval_batch` / `eval_sequence` (channels first, as the official
  evaluator's tensors)."""
  iters = _check_iters(iters)
  variables = jax.device_put(variables)

  def flow_fn(img1: Any, img2: Any) -> np.ndarray:
    for name, img in (("img1", img1), ("img2", img2)):
      if np.ndim(img) != 3 or np.shape(img)[0] != 3:
        raise ValueError(f"flow_fn: {name} must be [3, H, W] RGB 0..255, got {np.shape(img)}")
    flow = raft_flow(variables, np.moveaxis(np.asarray(img1, np.float32), 0, -1),
                     np.moveaxis(np.asarray(img2, np.float32), 0, -1), iters)
    return np.moveaxis(np.asarray(flow), -1, 0)

  return flow_fn

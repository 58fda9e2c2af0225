"""Small building blocks shared by the modules: torch-style conv, norms, GELU."""

from __future__ import annotations

import functools
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


def conv(features: int, kernel: Sequence[int], stride: int | Sequence[int] = 1,
         padding: int | Sequence[int] = 0, use_bias: bool = True, dtype: Any = jnp.float32,
         name: str | None = None) -> nn.Module:
  """A convolution with torch's explicit symmetric zero padding.

  Stride-1 convolutions are `Conv2D`/`Conv3D` (2-D convolutions with a hand-written
  backward pass, see `conv2d`); strided ones are `nn.Conv`. All have the parameters
  of `nn.Conv` (`kernel` `[*kernel, C, O]`, `bias`).

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
  if strides == (1,) * nd and nd in (2, 3):
    cls = Conv3D if nd == 3 else Conv2D
    return cls(features, tuple(kernel), pads, use_bias, dtype, name=name)
  return nn.Conv(features, tuple(kernel), strides=strides, padding=[(p, p) for p in pads],
                 use_bias=use_bias, dtype=dtype, param_dtype=jnp.float32, name=name)


_NHWC = ("NHWC", "HWIO", "NHWC")


def _conv2d(x: jax.Array, kernel: jax.Array, padding) -> jax.Array:
  return jax.lax.conv_general_dilated(x, kernel, (1, 1), padding, dimension_numbers=_NHWC)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _conv2d_canonical_vjp(x, kernel, padding):
  return _conv2d(x, kernel, padding)


def _conv2d_fwd(x, kernel, padding):
  return _conv2d(x, kernel, padding), (x, kernel)


def _conv2d_bwd(padding, res, g):
  x, kernel = res
  kh, kw = kernel.shape[:2]
  (pt, pb), (pl, pr) = padding
  # d/dx: the output gradient correlated with the flipped kernel, in/out swapped.
  flipped = jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2)
  dx = _conv2d(g, flipped, ((kh - 1 - pt, kh - 1 - pb), (kw - 1 - pl, kw - 1 - pr)))
  # d/dkernel: channels of x as the batch, the batch as input channels, the output
  # gradient as a kernel the size of the output: [C, kh, kw, O].
  dk = _conv2d(x.transpose(3, 1, 2, 0), g.transpose(1, 2, 0, 3), padding)
  return dx.astype(x.dtype), dk.transpose(1, 2, 0, 3).astype(kernel.dtype)


_conv2d_canonical_vjp.defvjp(_conv2d_fwd, _conv2d_bwd)


_CANONICAL_GRADIENT = {"enabled": True}


def set_canonical_conv_gradient(enabled: bool) -> None:
  """Switches `conv2d`'s hand-written CPU gradient on (default) or off.

  The hand-written gradient is a `jax.custom_vjp`, which supports reverse mode only:
  switch it off (before tracing) to use forward-mode autodiff (`jax.jvp`, `jax.jacfwd`)
  through the model on CPU, at the price of slow scanned gradients.
  """
  _CANONICAL_GRADIENT["enabled"] = bool(enabled)


def conv2d(x: jax.Array, kernel: jax.Array, padding) -> jax.Array:
  """Stride-1 2-D convolution `[N, H, W, C] * [kh, kw, C, O]` with explicit padding.

  On CPU its gradient is written as two convolutions of the forward's canonical form
  (NHWC x HWIO -> NHWC, with explicit transposes). XLA's own transposed convolutions
  are fast in straight-line code, but inside a `lax.scan` body (the refinement loop)
  XLA:CPU runs the kernel gradient on a slow generic path, ~20x slower (jaxlib 0.10).
  Other backends use the built-in gradient; `set_canonical_conv_gradient(False)` does
  too on CPU (needed for forward-mode autodiff).

  Args:
    x: `[N, H, W, C]`.
    kernel: `[kh, kw, C, O]`.
    padding: `((top, bottom), (left, right))` zero padding.
  """
  padding = tuple(tuple(int(p) for p in pair) for pair in padding)
  if _CANONICAL_GRADIENT["enabled"] and jax.default_backend() == "cpu":
    return _conv2d_canonical_vjp(x, kernel, padding)
  return _conv2d(x, kernel, padding)


class Conv2D(nn.Module):
  """Stride-1 2-D convolution over `[..., H, W, C]` (leading axes are batch); see `conv2d`."""

  features: int
  kernel_size: tuple[int, int]
  padding: tuple[int, int]
  use_bias: bool = True
  dtype: Any = jnp.float32
  # Input channels of the kernel when it has more than the input: the input is then its
  # first channels, the others being zero (their kernel slices are never read).
  kernel_in: int | None = None

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x `[..., H, W, C]`. Returns `[..., H', W', features]` (zero padding)."""
    *lead, h, w, c = x.shape
    k_in = c if self.kernel_in is None else self.kernel_in
    if k_in < c:
      raise ValueError(f"{self.name}: input has {c} channels, kernel_in is {k_in}")
    kernel = self.param("kernel", nn.initializers.lecun_normal(),
                        (*self.kernel_size, k_in, self.features), jnp.float32)
    kernel = kernel[..., :c, :].astype(self.dtype)
    (ph, pw) = self.padding
    y = conv2d(x.astype(self.dtype).reshape(-1, h, w, c), kernel, ((ph, ph), (pw, pw)))
    y = y.reshape(*lead, *y.shape[1:])
    if self.use_bias:
      y = y + self.param("bias", nn.initializers.zeros, (self.features,),
                         jnp.float32).astype(self.dtype)
    return y


class Conv3D(nn.Module):
  """Stride-1 3-D convolution over `[B, T, H, W, C]`, computed with 2-D convolutions (`conv2d`).

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
    if (kh, kw, ph, pw) == (1, 1, 0, 0):  # temporal kernel: a 2-D conv over (T, H*W)
      y = conv2d(x.reshape(b, t, h * w, c), kernel[:, 0], padding=[(pt, pt), (0, 0)])
    else:
      if kt != 2 * pt + 1:
        raise ValueError(f"Conv3D {self.name or ''}: a {kt}x{kh}x{kw} kernel needs temporal padding "
                         f"{(kt - 1) // 2} on each side (same length), got {pt}")
      y = _temporal_taps(x, kernel, pt, ((ph, ph), (pw, pw)))
    y = y.reshape(b, t, h, w, self.features)
    if self.use_bias:
      y = y + self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32).astype(self.dtype)
    return y


def _temporal_taps(x: jax.Array, kernel: jax.Array, pt: int, padding) -> jax.Array:
  """`sum_dt conv2d(x[t + dt - pt], kernel[dt])` with zero frames outside `[0, T)`.

  Never materialises the temporally padded input: every tap is a per-frame 2-D conv,
  and the frames a tap does not reach are left out rather than convolved as zeros.
  When the conv narrows the channels (`O < C`) one convolution with every tap's kernel
  side by side (`kt * O` outputs) convolves all frames once and each tap's outputs are
  shifted into place (no input copies; on an H200 the flow head's 256 -> 2 conv went
  from three convolutions to one, 5.9 -> 4.5 ms per 1/4 update at 720x1280);
  otherwise the tap convolves only the input frames it reaches (a slice of the input,
  fewer multiply-adds).

  Args:
    x: `[B, T, H, W, C]`.
    kernel: `[kt, kh, kw, C, O]`.
    pt: temporal zero padding on each side (`kt = 2 pt + 1`: the length is kept).
    padding: spatial padding `((top, bottom), (left, right))`.

  Returns:
    `[B, T, H', W', O]`.
  """
  b, t, h, w, c = x.shape
  kt, o = kernel.shape[0], kernel.shape[-1]
  frames = lambda a: a.reshape(-1, *a.shape[2:])  # noqa: E731
  unframe = lambda a, n: a.reshape(b, n, *a.shape[1:])  # noqa: E731
  # (tap, first and end output frame it reaches): output frame i reads input i + dt - pt.
  reach = [(dt, max(0, pt - dt), min(t, t + pt - dt)) for dt in range(kt)]
  taps = [(dt, lo, hi) for dt, lo, hi in reach if hi > lo]
  if o < c:  # every tap's kernel side by side: one convolution reads the input once
    every = unframe(conv2d(frames(x), jnp.concatenate([kernel[dt] for dt, _, _ in taps], -1),
                           padding), t)
  y = None
  for i, (dt, lo, hi) in enumerate(taps):
    off = dt - pt
    if o < c:
      part = every[:, lo + off:hi + off, ..., i * o:(i + 1) * o]
    else:
      part = unframe(conv2d(frames(x[:, lo + off:hi + off]), kernel[dt], padding), hi - lo)
    if (lo, hi) != (0, t):
      part = jnp.pad(part, [(0, 0), (lo, t - hi)] + [(0, 0)] * 3)
    y = part if y is None else y + part
  return frames(y)  # the centre tap (dt = pt) always reaches every frame


def frames_per_block(n: int, frame_bytes: float, budget_mb: float) -> int:
  """The largest divisor of `n` frames whose `frame_bytes` each fit `budget_mb` (at least 1)."""
  budget = budget_mb * 2**20
  return max(f for f in range(1, n + 1) if n % f == 0 and (f == 1 or f * frame_bytes <= budget))


def in_frame_blocks(module: nn.Module, fn, x: jax.Array, frame_bytes: float,
                    budget_mb: float) -> jax.Array:
  """`fn(module, x)` for a per-frame computation, run over blocks of frames.

  The frames (leading axis of `x`) are split into equal blocks whose `frame_bytes`
  (the largest intermediate of one frame) fit `budget_mb`; the blocks run one after
  the other (`nn.scan`, parameters shared), which bounds the memory of long or
  high-resolution inputs with the same values. When all frames fit, `fn` runs once
  on `x`, so small inputs compile to the plain program.

  Args:
    module: the module whose submodules `fn` calls (`fn(module, block)`).
    fn: maps `[f, ...]` frames to `[f, ...]` outputs; nothing may mix frames.
    x: `[N, ...]` frames.
    frame_bytes: memory of the largest intermediate per frame.
    budget_mb: memory budget of one block, MiB.
  """
  n = x.shape[0]
  frames = frames_per_block(n, frame_bytes, budget_mb)
  if frames == n:
    return fn(module, x)
  scan = nn.scan(lambda mdl, _, xb: (None, fn(mdl, xb)), variable_broadcast="params",
                 split_rngs={"params": False}, length=n // frames)
  _, out = scan(module, None, x.reshape(n // frames, frames, *x.shape[1:]))
  return out.reshape(n, *out.shape[2:])


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

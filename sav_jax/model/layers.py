"""Small building blocks shared by the modules: torch-style conv, norms, GELU."""

from __future__ import annotations

import functools
import inspect
import math
from typing import Any, Sequence

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


def conv(features: int, kernel: Sequence[int], stride: int | Sequence[int] = 1,
         padding: int | Sequence[int] = 0, use_bias: bool = True, dtype: Any = jnp.float32,
         name: str | None = None) -> nn.Module:
  """A convolution with torch's explicit symmetric zero padding.

  Stride-1 convolutions are `Conv2D`/`Conv3D` (2-D convolutions with a hand-written
  backward pass, see `conv2d`); strided 2-D ones are `StridedConv` (others `nn.Conv`). All
  have the parameters of `nn.Conv` (`kernel` `[*kernel, C, O]`, `bias`); all but `nn.Conv`
  add their bias with `add_bias` (its gradient summed in float32).

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
  if nd == 2:
    return StridedConv(features, tuple(kernel), strides, pads, use_bias, dtype, name=name)
  return nn.Conv(features, tuple(kernel), strides=strides, padding=[(p, p) for p in pads],
                 use_bias=use_bias, dtype=dtype, param_dtype=jnp.float32, name=name)


def param(module: nn.Module, name: str, init_fn, shape: Sequence[int],
          dtype: Any = jnp.float32) -> jax.Array:
  """`module.param(name, init_fn, shape, dtype)`: the same parameter, faster to trace.

  In `apply` Flax checks an existing parameter's shape against `jax.eval_shape` of its
  initialiser, a trace of its own on every call: the model's ~780 parameters took a
  quarter of its forward trace (~1.1 s of ~4.5 on the 2-core CPU). An existing parameter is
  checked against `shape` here (the same `ScopeParamShapeError` when it differs, the same
  error for a name used twice); a new one (`init`) is Flax's, made by `init_fn`.
  """
  shape = tuple(int(n) for n in shape)
  if not module.has_variable("params", name):
    return module.param(name, init_fn, shape, dtype)
  module.scope.reserve(name, "params")
  value = module.get_variable("params", name)
  if np.shape(value) != shape:
    raise flax.errors.ScopeParamShapeError(name, module.scope.path_text, np.shape(value), shape)
  return value


def add_bias(y: jax.Array, bias: jax.Array) -> jax.Array:
  """`y + bias` in `y`'s dtype for a float32 `bias` `[C]` over `y` `[..., C]`.

  The bias is broadcast to `y`'s shape before it is cast: the same values as
  `y + bias.astype(y.dtype)`, but the bias's gradient (the sum of `y`'s cotangent over
  every position) is summed in float32. Cast first, the broadcast's transpose sums a
  bfloat16 cotangent in bfloat16, which stalls once the sum is 2^8 times a term (XLA:CPU
  gave 1024 for 4096 ones): a bfloat16 training step got its biases' gradients wrong.
  """
  return y + jnp.broadcast_to(bias, y.shape).astype(y.dtype)


def with_bias(module: nn.Module, y: jax.Array) -> jax.Array:
  """`y` plus `module`'s float32 `bias` parameter `[module.features]` (zeros at init), added
  by `add_bias`, where `module.use_bias`; else `y`. The bias of every convolution and
  `Dense` here."""
  if not module.use_bias:
    return y
  return add_bias(y, param(module, "bias", nn.initializers.zeros, (module.features,)))


class StridedConv(nn.Module):
  """A strided 2-D convolution `[..., H, W, C] -> [..., H', W', features]` with torch's
  symmetric zero padding: `nn.Conv`'s parameters (`kernel` `[kh, kw, C, O]`, `bias`) and
  values, with the bias added by `add_bias` (its gradient summed in float32)."""

  features: int
  kernel_size: tuple[int, int]
  strides: tuple[int, int]
  padding: tuple[int, int]
  use_bias: bool = True
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    *lead, h, w, c = x.shape
    kernel = param(self, "kernel", nn.initializers.lecun_normal(),
                   (*self.kernel_size, c, self.features))
    y = jax.lax.conv_general_dilated(
        x.astype(self.dtype).reshape(-1, h, w, c), kernel.astype(self.dtype),
        tuple(self.strides), [(p, p) for p in self.padding], dimension_numbers=_NHWC)
    y = y.reshape(*lead, *y.shape[1:])
    return with_bias(self, y)


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
    kernel = param(self, "kernel", nn.initializers.lecun_normal(),
                   (*self.kernel_size, k_in, self.features))
    kernel = kernel[..., :c, :].astype(self.dtype)
    (ph, pw) = self.padding
    y = conv2d(x.astype(self.dtype).reshape(-1, h, w, c), kernel, ((ph, ph), (pw, pw)))
    y = y.reshape(*lead, *y.shape[1:])
    return with_bias(self, y)


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
    kernel = param(self, "kernel", nn.initializers.lecun_normal(),
                   (kt, kh, kw, c, self.features)).astype(self.dtype)
    x = x.astype(self.dtype)
    if (kh, kw, ph, pw) == (1, 1, 0, 0):  # temporal kernel: a 2-D conv over (T, H*W)
      y = conv2d(x.reshape(b, t, h * w, c), kernel[:, 0], padding=[(pt, pt), (0, 0)])
    else:
      if kt != 2 * pt + 1:
        raise ValueError(f"Conv3D {self.name or ''}: a {kt}x{kh}x{kw} kernel needs temporal padding "
                         f"{(kt - 1) // 2} on each side (same length), got {pt}")
      y = _temporal_taps(x, kernel, pt, ((ph, ph), (pw, pw)))
    y = y.reshape(b, t, h, w, self.features)
    return with_bias(self, y)


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


class ConvParams(nn.Module):
  """The parameters of a stride-1 `conv` (`Conv3D`'s names, shapes and initialisers: a
  `[*kernel_size, C, features]` kernel and a bias), without the convolution: for code that
  computes the convolution another way (`dft_correlate_w`) and keeps the checkpoint layout.
  Called with the input channels C; returns `(kernel, bias)` in float32."""

  features: int
  kernel_size: tuple[int, ...]

  @nn.compact
  def __call__(self, in_features: int) -> tuple[jax.Array, jax.Array]:
    kernel = param(self, "kernel", nn.initializers.lecun_normal(),
                   (*self.kernel_size, in_features, self.features))
    return kernel, param(self, "bias", nn.initializers.zeros, (self.features,))


# The most row blocks `dft_correlate_w` splits into (they are unrolled in the program).
DFT_MAX_BLOCKS = 16


@functools.lru_cache(maxsize=64)
def _dft_correlation_matrices(width: int, taps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """float32 `(analysis [W, 3F], kernel_bins [3F, k], synthesis [3F, W])` of `dft_correlate_w`.

  With n = W + k//2 (the shortest period with no wrap-around into the kept outputs) and
  F = n//2 + 1 bins, the input's bins X = Xr + i Xi and the taps' G = Gr + i Gi multiply as
  three real products per bin (Karatsuba): k1 = (Xr + Xi) Gr, k2 = Xr (Gi - Gr),
  k3 = Xi (Gr + Gi), Re = k1 - k3, Im = k1 + k2. `analysis` gives (Xr + Xi, Xr, Xi),
  `kernel_bins` (Gr, Gi - Gr, Gr + Gi) of a correlation's taps (offsets -k//2 .. k//2), and
  `synthesis` the inverse real DFT of the outputs 0 .. W-1 from (k1, k2, k3).
  """
  pad = taps // 2
  n = width + pad
  bins = n // 2 + 1
  angle = 2 * np.pi * np.outer(np.arange(width), np.arange(bins)) / n  # [W, F]
  cos, sin = np.cos(angle), np.sin(angle)
  analysis = np.concatenate([cos - sin, cos, -sin], axis=1)
  tap_angle = 2 * np.pi * np.outer(np.arange(bins), np.arange(taps) - pad) / n  # [F, k]
  tcos, tsin = np.cos(tap_angle), np.sin(tap_angle)
  kernel_bins = np.concatenate([tcos, tsin - tcos, tcos + tsin], axis=0)
  weight = np.full((bins, 1), 2.0 / n)  # the real DFT's conjugate bins folded in
  weight[0] = 1.0 / n
  if n % 2 == 0:
    weight[-1] = 1.0 / n
  synthesis = np.concatenate([weight * (cos - sin).T, -weight * sin.T, -weight * cos.T], axis=0)
  return tuple(a.astype(np.float32) for a in (analysis, kernel_bins, synthesis))


def dft_correlate_w(x: jax.Array, kernel: jax.Array, block_mb: float | None = None) -> jax.Array:
  """torch's stride-1 convolution with "same" zero padding along the width (the second
  last axis), computed through a real DFT along it: per frequency bin three real
  `[C] x [C, O]` products (Karatsuba) instead of one per tap and pixel.

  For the GRU's 1x15 gates at 1/4 of a 128x256 clip (W=64: a 71-point DFT, 36 bins) that is
  ~5x fewer multiply-adds than the direct convolution, and on XLA:CPU ~2x less time (~2.8x
  with the kernel's bins computed beforehand, as XLA does out of the refinement loop;
  `benchmarks/README.md`, "Fewer multiply-adds: DFT products"). Values agree with the direct
  convolution to float32 rounding (~1e-6 relative); computed in float32 at "highest" matmul
  precision whatever the input's dtype (the DFT's coefficients need it), returned in the
  input's dtype (float64 inputs too are computed in float32).

  Args:
    x: `[..., W, C]`.
    kernel: `[k, C, O]` taps along the width, k odd (padding k//2 on each side).
    block_mb: memory budget (MiB) of the rows' spectra and products (1.5x the input's size
      and more): the rows after the leading axis run in blocks that fit it, one after the
      other (at most `DFT_MAX_BLOCKS`, unrolled; the same values). None: all at once.

  Returns:
    `[..., W, O]`.
  """
  *lead, width, c = x.shape
  taps, kc, o = kernel.shape
  if taps % 2 == 0 or kc != c or width < 1:
    raise ValueError(f"dft_correlate_w: a kernel [k odd, {c}, O] for input channels {c} and a "
                     f"width >= 1, got kernel shape {kernel.shape} for input shape {x.shape}")
  analysis, kernel_bins, synthesis = _dft_correlation_matrices(width, taps)
  # float32 products on every backend (a GPU's default runs float32 products as TF32: 3x
  # the direct convolution's error there).
  dot = functools.partial(jnp.einsum, precision=jax.lax.Precision.HIGHEST)
  # per bin [O, C]: the layout XLA:CPU's batched product runs fastest with (~1.6x [C, O])
  bins = dot("gk,kp->gp", kernel_bins,
             kernel.astype(jnp.float32).transpose(0, 2, 1).reshape(taps, o * c))
  bins = bins.reshape(-1, o, c)

  def rows(m):  # [..., W, C] -> [..., W, O]
    flat = m.reshape(-1, width, c)
    spectrum = dot("mwc,wg->gmc", flat, analysis)
    y = dot("gmo,gw->mwo", dot("gmc,goc->gmo", spectrum, bins), synthesis)
    return y.reshape(*m.shape[:-1], o)

  # Blocks split the rows after the leading (batch) axis, so a batch sharded over devices
  # is never cut across them (blocks of all rows cost all-to-alls on 8 CPU devices).
  m = x.astype(jnp.float32).reshape(lead[0] if lead else 1, math.prod(lead[1:]), width, c)
  inner = m.shape[1]
  per_row = bins.shape[0] * (c + o) * 4
  fit = m.shape[0] * inner if block_mb is None else max(1, int(block_mb * 2**20 // per_row))
  count = min(-(-(m.shape[0] * inner) // fit), DFT_MAX_BLOCKS, inner)
  if count <= 1:
    y = rows(m)
  else:
    size = -(-inner // count)
    y = jnp.concatenate([rows(m[:, i:i + size]) for i in range(0, inner, size)], axis=1)
  return y.reshape(*lead, width, o).astype(x.dtype)


def frames_per_block(n: int, frame_bytes: float, budget_mb: float) -> int:
  """The largest divisor of `n` frames whose `frame_bytes` each fit `budget_mb` (at least 1)."""
  budget = budget_mb * 2**20
  return max(f for f in range(1, n + 1) if n % f == 0 and (f == 1 or f * frame_bytes <= budget))


# Flax's scan traces its body twice, the first time to check that the broadcast variables
# (the parameters) do not depend on the loop, unless told not to (`nn.scan`'s
# `check_constancy_invariants`; a Flax without the option traces twice).
_SCAN_CHECK_OPTION = "check_constancy_invariants" in inspect.signature(nn.scan).parameters


def scan_traced_once(module: nn.Module) -> dict:
  """`nn.scan` keyword arguments that trace its body once outside `init` (where the
  parameters exist already: the check has nothing to find), e.g. a window program's
  refinement steps (its trace a third shorter); `init`, which creates the parameters in the
  first trace, keeps both."""
  return {"check_constancy_invariants": module.is_initializing()} if _SCAN_CHECK_OPTION else {}


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
                 split_rngs={"params": False}, length=n // frames, **scan_traced_once(module))
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


class Dense(nn.Module):
  """`nn.Dense` (same parameters, initialisers and values) with the bias added by
  `add_bias`, so that its gradient is summed in float32 in bfloat16 compute."""

  features: int
  use_bias: bool = True
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    kernel = param(self, "kernel", nn.initializers.lecun_normal(), (x.shape[-1], self.features))
    y = jax.lax.dot_general(x.astype(self.dtype), kernel.astype(self.dtype),
                            (((x.ndim - 1,), (0,)), ((), ())))
    return with_bias(self, y)


def dense(features: int, use_bias: bool = True, dtype: Any = jnp.float32,
          name: str | None = None) -> Dense:
  return Dense(features, use_bias=use_bias, dtype=dtype, name=name)


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

"""Long-video inference: padding, the official sliding window and stitching.

    disp = predict_video(variables, left, right, cfg=cfg, iters=20)   # [T, H, W], every frame

Protocol (official `forward_batch_test`, `InputPadder(divis_by=32)` in "sintel" mode):
  * frames are replicate-padded to multiples of 32, the padding split between both
    sides (top/left get `floor(p/2)`), and unpadded after the model;
  * windows of `window=20` frames start every `stride=10` frames; each frame is
    taken from one window: the first window keeps its frames `[0, 15)`, a later
    full window `[5, 15)`, the window that reaches the end `[5, len)`;
  * the output is `abs()` of the final (test-mode) prediction.

What `predict_video` does differently from the official code (`forward_batch_test_official`
reproduces the official behaviour exactly, for parity):
  * Clips shorter than one window (N < 20): the official code keeps only the first
    N - 5 frames of its single window (nothing when N <= 5). We run the same single
    window and keep all N frames, so frames `[0, N-5)` are identical to the official
    output and the last 5 come from the same model run.
  * For N >= 20 the output is identical to the official one. The official code also
    runs trailing windows shorter than 10 frames and then discards them; we do not
    run them (their frames are already covered by the window that reaches the end).
  * Padding is computed once per video instead of once per window (same result: all
    windows have the same size).
  * General `window`/`stride` (stride <= window): the official code hard-codes 20/10;
    we keep the central `stride` frames of each full window, starting
    `(window - stride) // 2` frames in, which is the official rule for 20/10.

Reuse across windows: the per-frame part of the model (DINOv2 tokens of both views,
fnet, cnet) is computed once per frame, in chunks of `feature_chunk(window, stride)` =
gcd(window, stride) frames (10 for the official 20/10), and kept while
the windows that contain the frame run (`FrameFeatureCache`); only the temporal rest
(VDA's DPT head, the depth conv and the refinement) runs per window. With the official
20/10 windows this halves the per-frame work. The result is bit-identical to running
each window on its own with chunks of the same length (`run_window`'s default cache has
chunks of `STRIDE` = 10 frames; for other windows pass it
`FrameFeatureCache(feature_chunk(window, stride))`: other chunks batch the per-frame
convolutions differently, ~1e-5 px apart).

Several devices (`devices=`): consecutive windows run at once, one per device, with the
weights copied to each; a frame's per-frame features are computed on the device of the first
window that needs them and copied to the others. Same values as on one device.

Compilation: XLA executables per (config, iters, padded shape, matmul precision, device),
cached for the process: the per-frame part per chunk length (at most two for a video)
and the windowed part per window length (at most two for N >= 20 frames).

Memory: before compiling, `estimate_memory_bytes` (fitted to XLA's memory analysis)
is compared with the free device memory (host memory on CPU); after compiling, the
executable's own memory analysis is checked too. Sizes that cannot fit raise
`InsufficientMemoryError` (a MemoryError and a ValueError) with the estimate in GB
instead of crashing out of memory.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import os
import time
import warnings
import weakref
import zlib
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from sav_jax import _signals, runtime
from sav_jax._checks import caller_stacklevel, check_video_values  # noqa: F401  (public)
from sav_jax._checks import is_int as _is_int
from sav_jax._checks import require_int
from sav_jax.config import (DTYPES, TEMPORAL_MAX_LEN, SAVConfig, as_config,
                            resolve_vit_attention)
from sav_jax.model.dinov2 import DINO_VARIANTS, attention_blocks
from sav_jax.model.init import abstract_variables
from sav_jax.model.stereo_any_video import (channels_first_hint, check_iters, layout_hint,
                                            training_state_hint)

log = logging.getLogger(__name__)

PAD_MULTIPLE = 32
WINDOW = 20
STRIDE = 10
_CACHE_SIZE = 16  # executables per device
_COMPILED: "collections.OrderedDict[tuple, object]" = collections.OrderedDict()
# The jitted functions behind them, by (kind, cfg, iters, frame size): JAX keeps a jitted
# function's traces, so the executables of another device, placement or compiler options
# reuse the model's trace (~3-4 s on a 2-core CPU) instead of tracing it again.
_JITTED: "collections.OrderedDict[tuple, object]" = collections.OrderedDict()
_compile_seconds = 0.0  # `compile_seconds()`
_SKIP_COLLECTIONS = ("torch_unused",)
# Fitted to XLA's memory analysis of the compiled forward pass (temporaries, output and
# the two input windows; CPU, float32, default `frame_block_mb`, T=1..20, 32x32..736x1280,
# iters 4..20; benchmarks/README.md, "Memory at the paper's window"): a fixed 64 MiB,
# about 1 kB per input pixel plus 12 B per pixel and iteration, and 1.5x one block of the
# DINOv2 attention logits (float32; the blocks bound them, see `SAVConfig.frame_block_mb`).
# It errs high, by 19..60% on the shapes measured (`python benchmarks/memory_fit.py`;
# more on windows under 0.2 GB, where the fixed part dominates).
_BYTES_FIXED = 64 * 2**20
_BYTES_PER_PIXEL = 1000.0
_BYTES_PER_PIXEL_ITER = 12.0
_ATTN_BLOCK_FACTOR = 1.5
# The cheap pre-compile check refuses only sizes this far above the free memory (the
# estimate errs high); the compiled program's own analysis is then checked exactly.
_PRECHECK_MARGIN = 1.5
_BF16_FACTOR = 0.7


class InsufficientMemoryError(MemoryError, ValueError):
  """A window of this size would not fit in the available memory (message has the GB).

  Attributes:
    need: the message without its remedies (a command names its own flags instead).
    devices: where windows at once on this many CPU devices would not fit together (fewer
      devices is a remedy), else None.
  """

  def __init__(self, need: str, remedies: str | None = None, devices: int | None = None):
    self.need, self.devices = need, devices
    super().__init__(need if remedies is None else f"{need}; use {remedies}")


@dataclasses.dataclass(frozen=True)
class Window:
  """One model run of the sliding window.

  Attributes:
    start: first frame of the window in the video.
    length: number of frames run.
    keep_start, keep_stop: the window's frames `[keep_start, keep_stop)` (local
      indices) go to the output; empty for windows the official code discards.
  """

  start: int
  length: int
  keep_start: int
  keep_stop: int


def check_window(window: int, stride: int) -> None:
  """Raises ValueError unless window and stride are integers with 1 <= stride <= window and
  the window is at most `TEMPORAL_MAX_LEN` (32) frames, what the depth prior's temporal
  attention takes at once (a longer window failed in the model's trace, not naming it)."""
  if not (_is_int(window) and _is_int(stride) and 1 <= stride <= window):
    raise ValueError(f"need integers 1 <= stride <= window, got window={window!r}, "
                     f"stride={stride!r}")
  if window > TEMPORAL_MAX_LEN:
    raise ValueError(f"window={window!r} frames is more than the model runs at once: the depth "
                     f"prior's temporal attention takes at most {TEMPORAL_MAX_LEN} frames "
                     "(official windows: 20)")


def window_plan(num_frames: int, window: int = WINDOW, stride: int = STRIDE) -> list[Window]:
  """The windows `predict_video` runs; their kept frames tile `[0, num_frames)` in order.

  Args:
    num_frames: video length N >= 1.
    window: frames per window (at most 32, `check_window`).
    stride: distance between window starts (<= window).

  Returns:
    The windows in order. N < window gives one window keeping everything.
  """
  check_window(window, stride)
  if not (_is_int(num_frames) and num_frames >= 1):
    raise ValueError(f"need an integer number of frames >= 1, got {num_frames!r}")
  head = (window - stride) // 2
  plan, covered, start = [], 0, 0
  while covered < num_frames:
    length = min(window, num_frames - start)
    lo = head if plan else 0
    hi = head + stride if length == window else length
    plan.append(Window(start, length, lo, hi))
    covered, start = start + hi, start + stride
  return plan


def official_window_plan(num_frames: int, window: int = WINDOW,
                         stride: int = STRIDE) -> list[Window]:
  """Every window the official `forward_batch_test` runs, with what it keeps.

  First window: `[: -stride // 2]`; later windows with at least `stride` frames:
  `[stride // 2 : -stride // 2]` when full, `[stride // 2 :]` when shorter; shorter
  windows are run but dropped (empty keep range). Python slicing semantics.
  """
  check_window(window, stride)
  plan = []
  for start in range(0, num_frames, stride):
    length = min(window, num_frames - start)
    lo, hi = slice(None, -stride // 2).indices(length)[:2]
    if start > 0:
      if length < stride:
        lo = hi = 0
      else:
        stop = -stride // 2 if length >= window else None
        lo, hi = slice(stride // 2, stop).indices(length)[:2]
    plan.append(Window(start, length, lo, max(lo, hi)))
  return plan


def pad_amounts(height: int, width: int, multiple: int = PAD_MULTIPLE
                ) -> tuple[int, int, int, int]:
  """InputPadder 'sintel' padding `(top, bottom, left, right)` to multiples of `multiple`."""
  if not (_is_int(multiple) and multiple >= 1):
    raise ValueError(f"multiple must be an integer >= 1, got {multiple!r}")
  ph, pw = -height % multiple, -width % multiple
  return ph // 2, ph - ph // 2, pw // 2, pw - pw // 2


def _check_pads(pads) -> tuple[int, int, int, int]:
  try:
    pads = tuple(pads)
  except TypeError:
    pads = None
  if pads is None or len(pads) != 4 or not all(_is_int(p) and p >= 0 for p in pads):
    raise ValueError(f"pads must be 4 integers (top, bottom, left, right) >= 0, got {pads!r}")
  return tuple(int(p) for p in pads)


def _as_frames(frames):
  """`frames` as a JAX array (kept, traced ones too) or a NumPy array, `[..., H, W, C]`."""
  if not isinstance(frames, jax.Array):
    frames = np.asarray(frames)
  if frames.ndim < 3:
    raise ValueError(f"frames must be [..., H, W, C], got shape {tuple(frames.shape)}"
                     + layout_hint(frames.shape, batched=False))
  hint = channels_first_hint(frames.shape)
  if hint and frames.shape[-1] > 4:  # [..., 3, H, W]: it would pad the channel and height axes
    raise ValueError(f"frames must be [..., H, W, C], channels last; got shape "
                     f"{tuple(frames.shape)}{hint}")
  if frames.shape[-1] > 4:  # [T, H, W] (disparities, grey frames): it would pad T and H
    raise ValueError(f"frames must be [..., H, W, C] with 1 to 4 channels last; got shape "
                     f"{tuple(frames.shape)}, whose last axis of {frames.shape[-1]} is no "
                     "channel axis: for [..., H, W] arrays (disparities, grey frames) add one, "
                     "x[..., None], and take [..., 0] of the result")
  return frames


def pad_frames(frames, pads: tuple[int, int, int, int]):
  """Replicate-pads frames `[..., H, W, C]` spatially by `(top, bottom, left, right)`.

  Any leading axes (`[T, H, W, C]`, a batch `[B, T, H, W, C]`). A NumPy array (or list)
  gives a NumPy array; a JAX array, traced ones included (inside `jit`, `grad`, `vmap`),
  gives a JAX array, so padding is part of a differentiable pipeline (the gradient of a
  replicated edge pixel is the sum over its copies, as PyTorch's replicate padding).
  """
  pads = _check_pads(pads)
  frames = _as_frames(frames)
  top, bottom, left, right = pads
  width = ((0, 0),) * (frames.ndim - 3) + ((top, bottom), (left, right), (0, 0))
  if isinstance(frames, jax.Array):
    return jnp.pad(frames, width, mode="edge")
  return np.pad(frames, width, mode="edge")


def pad_to_multiple(frames, multiple: int = PAD_MULTIPLE):
  """`(padded, pads)`: frames `[..., H, W, C]` replicate-padded to multiples of `multiple`.

  The official evaluation's padding (`InputPadder(divis_by=32)`, "sintel" mode: split
  between both sides, top/left get the smaller half); the model needs multiples of 16.
  NumPy or JAX arrays as `pad_frames`; undo on the output with `unpad(disparities, pads)`.
  """
  frames = _as_frames(frames)
  pads = pad_amounts(*frames.shape[-3:-1], multiple)
  return pad_frames(frames, pads), pads


def unpad(x, pads: tuple[int, int, int, int]):
  """Removes `pad_frames` padding from `[..., Hp, Wp]` (disparities; NumPy or JAX, or a
  list, which gives a NumPy array as `pad_frames` does)."""
  top, bottom, left, right = _check_pads(pads)
  if not isinstance(x, jax.Array):
    x = np.asarray(x)
  if x.ndim < 2 or top + bottom > x.shape[-2] or left + right > x.shape[-1]:
    why = ("expected [..., Hp, Wp]" if x.ndim < 2 else
           f"they add up to {top + bottom} x {left + right}, more than its last two axes "
           f"{tuple(x.shape[-2:])}: [..., Hp, Wp] expected")
    raise ValueError(f"cannot remove pads {pads} from an array of shape {tuple(x.shape)}: "
                     f"{why} (for frames [..., Hp, Wp, C], unpad x[..., c])")
  if any(pads) and x.ndim >= 3 and x.shape[-1] <= 4 < x.shape[-2]:
    # frames [..., Hp, Wp, C]: their W and C axes were cropped (720x1280 frames lost 16
    # columns, not their 16 padded rows), silently where the pads fit
    raise ValueError(f"cannot remove pads {pads} from an array of shape {tuple(x.shape)}: "
                     f"[..., Hp, Wp] expected (disparities); for frames [..., Hp, Wp, C] "
                     f"(a last axis of {x.shape[-1]}), unpad x[..., c]")
  return x[..., top:x.shape[-2] - bottom, left:x.shape[-1] - right]


def resolve_config(cfg: SAVConfig | None = None, dtype: str | None = None) -> SAVConfig:
  """`cfg` (default `SAVConfig()`) with its compute dtype replaced by `dtype` if given."""
  cfg = as_config(cfg)
  if dtype is not None and not isinstance(dtype, str):
    try:  # jnp.bfloat16, np.float32, ...
      dtype = jnp.dtype(dtype).name
    except TypeError:
      raise ValueError(f"dtype must be 'float32' or 'bfloat16', got {dtype!r}") from None
  if dtype is not None and dtype not in DTYPES:  # not SAVConfig's message: the caller's dtype=
    raise ValueError(f"dtype must be 'float32' or 'bfloat16', got {dtype!r}")
  if dtype is not None and dtype != cfg.dtype:
    cfg = dataclasses.replace(cfg, dtype=dtype)
  return cfg


def estimate_memory_bytes(frames: int, height: int, width: int, iters: int = 20,
                          cfg: SAVConfig | None = None) -> int:
  """Peak extra memory of one forward pass on a padded window (a fitted estimate).

  Args:
    frames: window length T.
    height, width: padded frame size (multiples of 32).
    iters: refinement iterations.
    cfg: model config (bfloat16 compute lowers the estimate).

  Returns:
    Bytes: a fixed part, per-pixel activations, a per-pixel-and-iteration term and one
    block of the DINOv2 attention logits (`dinov2.attention_blocks` under
    `cfg.frame_block_mb`; none where the ViT attention resolves to cuDNN's fused kernel).
  """
  cfg = as_config(cfg)
  frames, height, width = _check_shape(frames, height, width)
  iters = check_iters(iters)
  pixels = frames * height * width
  heads = DINO_VARIANTS[cfg.vda_encoder]["num_heads"]
  tokens = (height // 14) * (width // 14) + 1  # patches and the class token
  block_frames, block_rows = attention_blocks(2 * frames, heads, tokens, cfg.frame_block_mb)
  attention = block_frames * heads * block_rows * tokens * 4
  if resolve_vit_attention(cfg.vit_attention, cfg.compute_dtype) == "cudnn":
    attention = 0  # the fused kernel stores no logits
  est = _BYTES_PER_PIXEL * pixels + _BYTES_PER_PIXEL_ITER * iters * pixels
  if cfg.dtype == "bfloat16":
    est *= _BF16_FACTOR
  return int(_BYTES_FIXED + est + _ATTN_BLOCK_FACTOR * attention)


def available_memory_bytes(device=None) -> int | None:
  """Free memory of `device` (default: the first device); None if unknown.

  For CPU, the host's available RAM, or less under a container's memory limit
  (`runtime.cgroup_free_bytes`). An accelerator whose runtime reports no memory
  statistics: None (its memory is not the host's).
  """
  device = jax.devices()[0] if device is None else device
  stats = None
  try:
    stats = device.memory_stats()
  except Exception:  # pylint: disable=broad-except  # not all backends implement it
    stats = None
  if stats and "bytes_limit" in stats:
    return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
  if device.platform != "cpu":
    return None
  limits = [runtime.cgroup_free_bytes(), _host_available_bytes()]
  limits = [x for x in limits if x is not None]
  return min(limits) if limits else None


def _host_available_bytes() -> int | None:
  try:
    with open("/proc/meminfo", encoding="ascii") as fh:
      for line in fh:
        if line.startswith("MemAvailable:"):
          return int(line.split()[1]) * 1024
  except OSError:
    pass
  try:
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
  except (ValueError, OSError, AttributeError):
    return None


def _raise_if_too_big(needed: float, shape: tuple[int, int, int], what: str,
                      margin: float = 1.0, device=None, iters: int | None = None) -> None:
  """`iters`: given where they take most of `needed` (the estimate's per-iteration part),
  so the message names them first among the remedies."""
  device = _default_device() if device is None else device
  free = available_memory_bytes(device)
  if free is not None and needed > margin * free:
    t, h, w = shape
    its = "" if iters is None else f" with iters={iters}"
    fewer = "" if iters is None else "fewer refinement iterations (iters), "
    raise InsufficientMemoryError(
        f"a {t}-frame window of {h}x{w} (padded){its} needs about {needed / 2**30:.1f} GB "
        f"({what}), but only {free / 2**30:.1f} GB is free on {device.platform}:{device.id}",
        f"{fewer}fewer frames per window (window/stride), smaller frames, bfloat16 "
        "(dtype='bfloat16') or a device with more memory")


def _model(cfg):
  # pylint: disable-next=import-outside-toplevel
  from sav_jax.model.stereo_any_video import StereoAnyVideo
  return StereoAnyVideo(cfg)


def _jitted(key, make):
  """`jax.jit(make())`, kept under `key` (the `_CACHE_SIZE` most recently used)."""
  if key in _JITTED:
    _JITTED.move_to_end(key)
  else:
    _JITTED[key] = jax.jit(make())
    while len(_JITTED) > _CACHE_SIZE:
      _JITTED.popitem(last=False)
  return _JITTED[key]


def _forward_fn(cfg: SAVConfig, iters: int):
  def make():
    model = _model(cfg)

    def forward(variables, left, right):
      out = model.apply(variables, left[None], right[None], iters=iters, final_only=True)
      return out.disparities[0, 0]

    return forward

  return _jitted(("forward", cfg, iters), make)


def model_variables(variables) -> dict:
  """The collections the forward pass needs (drops the `torch_unused` export-only one)."""
  return {k: v for k, v in variables.items() if k not in _SKIP_COLLECTIONS}


def _check_shape(frames, height, width) -> tuple[int, int, int]:
  """`(frames, height, width)` as Python ints; a ValueError naming the first that is not a
  positive integer (0 frames failed deep in the model, a float height inside JAX)."""
  for name, value in (("frames", frames), ("height", height), ("width", width)):
    require_int(value, name, 1)
  return int(frames), int(height), int(width)


def _cache_key(kind, variables, cfg, iters, shape):
  shape = _check_shape(*shape)
  leaves = jax.tree_util.tree_leaves(variables)
  sig = tuple((tuple(x.shape), str(x.dtype)) for x in leaves)
  options = tuple(sorted(runtime.inference_compiler_options(per_frame=kind == "frames").items()))
  return (kind, cfg, iters, shape, options, str(jax.config.jax_default_matmul_precision),
          str(jax.config.jax_default_device),
          bool(jax.config.values.get("jax_disable_most_optimizations")),
          jax.tree_util.tree_structure(variables), sig, _placement(leaves))


def _default_device():
  device = jax.config.jax_default_device
  if isinstance(device, str):  # a platform name
    return jax.devices(device)[0]
  return device or jax.devices()[0]


def _abstract(x):
  """Shape and dtype, and the placement unless it is just the default device: committed
  arrays there (orbax restores) would otherwise lower to another program than numpy or
  uncommitted ones, and miss the persistent compilation cache."""
  sharding = getattr(x, "sharding", None)
  if sharding is not None and sharding.device_set == {_default_device()}:
    sharding = None
  return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)


def _placement(leaves) -> frozenset:
  """The devices the arrays `leaves` are on, other than the default one (part of the key)."""
  default = _default_device()
  return frozenset(str(d) for x in leaves
                   for d in getattr(getattr(x, "sharding", None), "device_set", ())
                   if d != default)


def _compile(key, build, check_memory: bool):
  """The cached executable for `key`; on a miss, compiles `fn(*args)` from `build()`.

  `key` is `_cache_key(...)`; `build() -> (fn, args)` with abstract args (variables
  first) runs only on a miss. The compiled program's memory is checked before caching.
  """
  if key in _COMPILED:
    _COMPILED.move_to_end(key)
    return _COMPILED[key]
  kind, cfg, iters, shape = key[:4]
  cached = (" (or loading it from the compilation cache)"
            if jax.config.jax_compilation_cache_dir else "")
  what = {"frames": "per-frame features", "window": "refinement of a window"}.get(kind, kind)
  its = "" if kind == "frames" else f"iters={iters}, "  # the per-frame part runs no iterations
  log.info("compiling the model (%s) for %d frames padded to %dx%d (%s%s)%s", what, *shape, its,
           cfg.dtype, cached)
  global _compile_seconds
  start = time.perf_counter()
  fn, args = build()
  args = jax.tree_util.tree_map(_abstract, args)
  try:
    jitted = fn if hasattr(fn, "lower") else jax.jit(fn)  # (`_jitted`'s keep their traces)
    compiled = jitted.lower(*args).compile(compiler_options=dict(key[4]))
  finally:
    _compile_seconds += time.perf_counter() - start
  runtime.release_host_memory()  # the compiler's working memory, kept by the allocator
  if check_memory:
    input_bytes = sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(args[1:]))
    try:
      ma = compiled.memory_analysis()
      needed = ma.temp_size_in_bytes + ma.output_size_in_bytes + input_bytes
    except Exception:  # pylint: disable=broad-except  # analysis not offered by every backend
      ma = None
    if ma is not None:
      _raise_if_too_big(needed, shape, "from the compiled program", device=_device_of(args[0]))
  _COMPILED[key] = compiled
  # At most _CACHE_SIZE executables per placement (the last key field), the least recently
  # used go first: several devices each keep their own set of a video's executables.
  same = [k for k in _COMPILED if k[-1] == key[-1]]
  for k in same[:max(0, len(same) - _CACHE_SIZE)]:
    del _COMPILED[k]
  return compiled


def _device_of(tree):
  """The device the arrays of `tree` are on (the default device for host or abstract ones)."""
  for x in jax.tree_util.tree_leaves(tree):
    devices = getattr(getattr(x, "sharding", None), "device_set", None)
    if devices and len(devices) == 1:
      return next(iter(devices))
  return _default_device()


def _on_one_device(variables):
  """`variables`, copied to one device (the default one, else the first of theirs) when
  their arrays span several: the programs run on one device, and parameters replicated
  over a mesh (a training run's) failed there with JAX's sharding mismatch."""
  devices = {d for x in jax.tree_util.tree_leaves(variables)
             for d in getattr(getattr(x, "sharding", None), "device_set", ())}
  if len(devices) <= 1:
    return variables
  default = _default_device()
  return jax.device_put(variables, default if default in devices else
                        min(devices, key=lambda d: d.id))


def _precheck(frames, height, width, cfg, iters, check_memory, device=None) -> None:
  # Cheap check first, so that hopeless sizes fail before a long compile.
  if check_memory:
    # iters named where their part of the estimate exceeds the rest's per-pixel part
    many = iters is not None and _BYTES_PER_PIXEL_ITER * iters > _BYTES_PER_PIXEL
    _raise_if_too_big(estimate_memory_bytes(frames, height, width, iters, cfg),
                      (frames, height, width), "estimated", margin=_PRECHECK_MARGIN,
                      device=device, iters=iters if many else None)


def compiled_forward(variables, frames: int, height: int, width: int, *, cfg: SAVConfig,
                     iters: int, check_memory: bool = True):
  """The cached executable `(variables, left, right) -> raw disparity [T, Hp, Wp]`.

  The whole forward pass in one program (`predict_video` runs it in two parts, see
  `compiled_frame_features` and `compiled_window`).

  Args:
    variables: model variables (as passed to the executable, see `model_variables`).
    frames, height, width: padded window shape (height, width multiples of 16).
    cfg: model config.
    iters: refinement iterations (>= 2).
    check_memory: refuse (InsufficientMemoryError) shapes that cannot fit.

  Returns:
    A compiled function taking float32 `[T, Hp, Wp, 3]` left/right frames.
  """
  cfg, shape = resolve_config(cfg), (frames, height, width)
  key = _cache_key("forward", variables, cfg, iters, shape)
  if key not in _COMPILED:
    _precheck(*shape, cfg, iters, check_memory, _device_of(variables))
  spec = jax.ShapeDtypeStruct((frames, height, width, 3), jnp.float32)
  return _compile(key, lambda: (_forward_fn(cfg, iters), (variables, spec, spec)), check_memory)


def _frames_fn(cfg: SAVConfig):
  def make():
    model = _model(cfg)

    def frame_features(variables, left, right):
      return model.apply(variables, left[None], right[None], method=type(model).frame_features)

    return frame_features

  return _jitted(("frames", cfg), make)


def compiled_frame_features(variables, frames: int, height: int, width: int, *,
                            cfg: SAVConfig, check_memory: bool = True):
  """Cached executable `(variables, left, right) -> frame_features` of `[n, Hp, Wp, 3]` frames."""
  cfg, shape = resolve_config(cfg), (frames, height, width)
  key = _cache_key("frames", variables, cfg, 0, shape)
  spec = jax.ShapeDtypeStruct((frames, height, width, 3), jnp.float32)
  return _compile(key, lambda: (_frames_fn(cfg), (variables, spec, spec)), check_memory)


def compiled_window(variables, frames: int, height: int, width: int, *, cfg: SAVConfig,
                    iters: int, check_memory: bool = True):
  """Cached executable `(variables, frame_features) -> raw disparity [T, Hp, Wp]`."""
  cfg, shape = resolve_config(cfg), (frames, height, width)
  key = _cache_key("window", variables, cfg, iters, shape)

  def make():
    model = _model(cfg)

    def window(variables, feats):
      out = model.apply(variables, feats, (height, width), iters, True,
                        method=type(model).from_frame_features)
      return out.disparities[0, 0]

    return window

  def build():  # only on a cache miss: tracing the per-frame part for its shapes costs
    spec = jax.ShapeDtypeStruct((frames, height, width, 3), jnp.float32)
    feats = jax.eval_shape(_frames_fn(cfg), variables, spec, spec)
    return _jitted(("window", cfg, iters, height, width), make), (variables, feats)

  return _compile(key, build, check_memory)


def feature_chunk(window: int = WINDOW, stride: int = STRIDE) -> int:
  """The per-frame chunk length of windows of `window` frames `stride` apart:
  `gcd(window, stride)`, so every window starts and ends (except at the video's end) on a
  chunk boundary and no chunk is cut short where a later window needs the rest of it."""
  check_window(window, stride)
  return math.gcd(window, stride)


class FrameFeatureCache:
  """`frame_features` of single frames by frame index, for windows that overlap.

  The per-frame part of the model (DINOv2 tokens, fnet, cnet) is computed in chunks of
  `chunk` frames aligned to multiples of `chunk` from the start of the video, so a frame
  gets the same values whichever window asks for it first, provided the windows start
  and end on multiples of `chunk` (`feature_chunk(window, stride)`; the default suits
  the default windows).

  A cache belongs to one video, one frame size, one model config and one set of weights,
  and its windows move forward: `run_window` refuses another frame size or config, other
  weights (other parameter arrays than the first window's: pass the same `variables` to
  every window), a window starting before the previous one, and a window whose frames differ
  from those the cached features were computed from (a CRC-32 of each frame pair's float32
  values: another video started again at frame 0, or frames changed in place; a new video
  needs a new cache).
  """

  def __init__(self, chunk: int = STRIDE):
    if not (_is_int(chunk) and chunk >= 1):
      raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    self.chunk = int(chunk)
    self.frames: dict[int, dict] = {}
    self._use = None  # (frame size, pads, cfg) of the first window
    self._start = 0  # the latest window's start
    self._prints: dict[int, tuple[int, int]] = {}  # frame index -> CRC-32 of (left, right)
    self._weights = None  # weak references to the first window's parameter arrays

  def check_frames(self, left: np.ndarray, right: np.ndarray, start: int) -> None:
    """Raises ValueError if a frame of the window `left`/`right` from `start` differs from
    the one this cache computed features of; records the frames it has not seen."""
    # of the values the model sees (float32): the same frames as uint8 or float32 match
    crc = lambda frame: zlib.crc32(np.ascontiguousarray(frame, np.float32).data)  # noqa: E731
    for k in range(len(left)):
      i, seen = start + k, self._prints.get(start + k)
      if seen is None and i not in self.frames:
        self._prints[i] = (crc(left[k]), crc(right[k]))
      elif seen is not None and seen != (crc(left[k]), crc(right[k])):
        raise ValueError(
            f"frame {i} differs from the frame whose features this FrameFeatureCache holds: "
            "a cache serves one video (use a new cache for another video, or after changing "
            f"frames; start={start} must be the index of the window's first frame in the "
            "video)")

  def check_use(self, shape: tuple, pads: tuple, cfg: SAVConfig, start: int,
                variables=None) -> None:
    """Raises ValueError unless a window of frames `shape` [T, H, W, 3] padded by `pads`,
    for `cfg` and the weights `variables`, starting at frame `start`, can reuse this cache;
    then records it."""
    if variables is not None:
      leaves = jax.tree_util.tree_leaves(variables)
      if self._weights is None:
        self._weights = [_reference(x) for x in leaves]
      elif len(leaves) != len(self._weights) or not all(
          _refers_to(r, x) for r, x in zip(self._weights, leaves)):
        raise ValueError(
            "this FrameFeatureCache holds features computed with other weights (other "
            "parameter arrays than its first window's): pass the same variables to every "
            "window, or use a new cache for other weights")
    use = (tuple(shape[1:3]), tuple(pads), cfg)
    if self._use is not None and use != self._use:
      raise ValueError(
          f"this FrameFeatureCache holds features of {self._use[0][0]}x{self._use[0][1]} "
          f"frames padded by {self._use[1]} for {self._use[2]}, not {use[0][0]}x{use[0][1]} "
          f"frames padded by {use[1]} for {use[2]}: use a new cache for another video, size "
          "or config")
    if start < self._start:
      raise ValueError(
          f"window start {start} is before the previous window's ({self._start}): a "
          "FrameFeatureCache serves one video's windows in order (use a new cache for "
          "another video)")
    self._use, self._start = use, start

  def evict_before(self, index: int) -> None:
    """Forgets the frames before `index` (windows only move forward)."""
    for i in [i for i in self.frames if i < index]:
      del self.frames[i]
    for i in [i for i in self._prints if i < index]:
      del self._prints[i]

  def gather(self, start: int, stop: int, device=None):
    """The cached features of frames `[start, stop)` stacked on the T axis (copied to
    `device` first when given: frames computed on other devices)."""
    items = [self.frames[i] for i in range(start, stop)]
    if device is not None:
      items = jax.device_put(items, device)
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=1), *items)


def _reference(x):
  """A weak reference to array `x` (a Python number, which has none, is kept as is)."""
  try:
    return weakref.ref(x)
  except TypeError:
    return x


def _refers_to(ref, x) -> bool:
  if isinstance(ref, weakref.ref):
    return ref() is x
  return type(ref) is type(x) and ref == x


# Device arrays found finite: id -> weak reference (they are immutable, and an array that
# is gone frees its entry; jax arrays cannot be hashed). Host arrays, which can change in
# place, are scanned each time.
_FINITE_ARRAYS: dict[int, weakref.ref] = {}


def _known_finite(v) -> bool:
  ref = _FINITE_ARRAYS.get(id(v))
  return ref is not None and ref() is v


def _remember_finite(v) -> None:
  key = id(v)
  _FINITE_ARRAYS[key] = weakref.ref(v, lambda _, key=key: _FINITE_ARRAYS.pop(key, None))


def nonfinite_parameters(params) -> list[str]:
  """The names (`keystr`) of the parameters holding NaN or inf, scanned with NumPy: device
  arrays are fetched once (free on a CPU; remembered as finite afterwards, so a model run
  window by window, or video by video, pays this once), host arrays every time."""
  named = jax.tree_util.tree_leaves_with_path(params)
  fetch = [v for _, v in named if isinstance(v, jax.Array) and not _known_finite(v)]
  fetched = dict(zip(map(id, fetch), jax.device_get(fetch)))
  bad = []
  for k, v in named:
    on_device = isinstance(v, jax.Array)
    if on_device and id(v) not in fetched:
      continue  # found finite before
    if not np.isfinite(fetched[id(v)] if on_device else np.asarray(v)).all():
      bad.append(jax.tree_util.keystr(k))
    elif on_device:
      _remember_finite(v)
  return bad


def check_variables(variables, cfg: SAVConfig | None = None, source: str = "variables") -> None:
  """Raises ValueError unless `variables["params"]` has the model's tree and shapes, and
  every parameter is a floating-point array without NaN or inf (such a parameter, e.g. from
  a diverged training run, turns every prediction into NaN).

  Args:
    variables: `{"params": ...}` (other collections are ignored).
    cfg: the model config they are for (default `SAVConfig()`).
    source: what to call them in the message (a checkpoint path, ...).
  """
  from sav_jax.convert import CheckpointError  # pylint: disable=import-outside-toplevel
  cfg = resolve_config(cfg)
  got = variables.get("params") if isinstance(variables, Mapping) else None
  if got is None:
    found = sorted(variables)[:5] if isinstance(variables, Mapping) else type(variables).__name__
    bare = isinstance(variables, Mapping) and "fnet" in variables  # variables["params"]
    raise CheckpointError(f"{source}: expected Flax variables {{'params': ...}}, found "
                          f"{found}{training_state_hint(variables)}"
                          + (": the parameters alone? pass {'params': params}" if bare else ""))
  if isinstance(got, Mapping) and isinstance(got.get("params"), Mapping) and (
      "fnet" in got["params"]):
    raise CheckpointError(f"{source}: an extra 'params' layer ({{'params': {{'params': ...}}}}): "
                          "pass variables['params'] instead")
  want = {jax.tree_util.keystr(k): tuple(v.shape) for k, v in
          jax.tree_util.tree_leaves_with_path(abstract_variables(cfg)["params"])}
  have = {jax.tree_util.keystr(k): tuple(np.shape(v))
          for k, v in jax.tree_util.tree_leaves_with_path(got)}
  missing, extra = sorted(want.keys() - have.keys()), sorted(have.keys() - want.keys())
  wrong = sorted(k for k in want.keys() & have.keys() if want[k] != have[k])
  if missing or extra or wrong:
    from sav_jax.convert.params import encoder_of_width  # pylint: disable=import-outside-toplevel
    token = have.get("['depthnet']['depthanything']['pretrained']['cls_token']", ())
    held = encoder_of_width(token[-1:])
    if held is not None and held != cfg.vda_encoder:  # the whole depth prior is another size
      raise CheckpointError(
          f"{source}: the parameters hold a {held} depth prior (DINOv2 width {token[-1]}), "
          f"the config says vda_encoder={cfg.vda_encoder!r}: use "
          f"SAVConfig(vda_encoder={held!r}) (the model config stored with the weights, if any, "
          "says otherwise)")
    parts = [f"{len(missing)} missing, e.g. {', '.join(missing[:2])}" if missing else "",
             f"{len(extra)} unexpected, e.g. {', '.join(extra[:2])}" if extra else "",
             f"{len(wrong)} with other shapes, e.g. " + ", ".join(
                 f"{k} {have[k]} (expected {want[k]})" for k in wrong[:2]) if wrong else ""]
    raise CheckpointError(
        f"{source}: parameters do not match the Stereo Any Video model of this config "
        f"(vda_encoder={cfg.vda_encoder!r}): {'; '.join(p for p in parts if p)}")
  for path, leaf in jax.tree_util.tree_leaves_with_path(got):
    dtype = getattr(leaf, "dtype", None)
    dtype = np.asarray(leaf).dtype if dtype is None else dtype
    if not jnp.issubdtype(dtype, jnp.floating):
      raise CheckpointError(f"{source}: parameter {jax.tree_util.keystr(path)} has dtype "
                            f"{dtype}; expected floating-point arrays (float32, bfloat16, ...)")
  bad = nonfinite_parameters(got)
  if bad:
    raise CheckpointError(f"{source}: {len(bad)} parameter(s) hold NaN or inf values, e.g. "
                          f"{bad[0]}; they are not usable (a diverged training run?)")


def clear_cache() -> None:
  """Forgets every compiled executable (and the model's traces behind them)."""
  _COMPILED.clear()
  _JITTED.clear()


def compile_seconds() -> float:
  """Seconds this process has spent compiling (or loading from the persistent compilation
  cache) the executables of `predict_video` and friends; the difference of two readings
  separates compilation from running in a timing."""
  return _compile_seconds


def cache_size() -> int:
  """Number of compiled executables held."""
  return len(_COMPILED)


def _as_video(video, name: str) -> np.ndarray:
  """`video` as one array; a list of frames must hold frames of one shape (ValueError
  naming `name` and the first frame whose shape differs otherwise)."""
  _refuse_iterator(video, name)
  if _is_lazy_video(video):  # read whole (np.asarray made a 0-d array of one object of it)
    video = video[0:int(_video_shape(video, name)[0])]
  if isinstance(video, (list, tuple)):
    frames = [np.asarray(f) for f in video]
    for i, frame in enumerate(frames):
      if frame.shape != frames[0].shape:
        raise ValueError(f"{name}: frame {i} has shape {frame.shape} but frame 0 has "
                         f"{frames[0].shape}; all frames need one size [H, W, 3]")
    video = np.stack(frames) if frames else np.asarray(video)
  video = np.asarray(video)
  if video.dtype.kind == "V" and jnp.issubdtype(video.dtype, jnp.floating):
    video = video.astype(np.float32)  # bfloat16 / float8 frames (ml_dtypes: kind "V")
  return video


def _refuse_iterator(video, name: str) -> None:
  if isinstance(video, (str, bytes, os.PathLike)):
    raise ValueError(
        f"{name}: got a path ({os.fspath(video)!r}), not frames; read them first: "
        "left, right, names = sav_jax.tools.video_io.load_stereo(left_path, right_path) reads "
        "both views' frames of two folders or video files (and the left frames' names; "
        "video_io.FrameSource(path) reads one lazily)")
  if not hasattr(video, "shape") and not isinstance(video, (list, tuple)) and (
      hasattr(video, "__next__") or not hasattr(video, "__getitem__")):
    kind = type(video).__name__
    article = "an" if kind.startswith(tuple("aeiou")) else "a"
    raise ValueError(
        f"{name}: got {article} {kind}, which has neither a shape nor frames by index: "
        "pass an array [T, H, W, 3], a list of frames, or a lazy source with a shape and "
        "slicing (see iter_predict_video); an iterator or generator of frames can be "
        "collected with list(...) first")


def _video_shape(video, name: str = "video") -> tuple:
  """The `[T, H, W, C]` shape of an array, a lazy source or a list of frames (from its
  length and first frame: the list is not stacked)."""
  _refuse_iterator(video, name)
  if hasattr(video, "shape"):
    return tuple(video.shape)
  return (len(video), *np.shape(video[0])) if len(video) else (0,)


def _check_video_shapes(left_shape: tuple, right_shape: tuple) -> None:
  if left_shape != right_shape:
    raise ValueError(f"left and right videos differ in shape: {left_shape} vs {right_shape}")
  if len(left_shape) != 4 or left_shape[-1] != 3 or min(left_shape[:3]) < 1:
    raise ValueError(f"expected RGB videos [T, H, W, 3] (0..255), got shape {left_shape}"
                     + layout_hint(left_shape, batched=False))


def _as_video_pair(left, right, first: int = 0,
                   warned: set | None = None) -> tuple[np.ndarray, np.ndarray]:
  """`first`: the index of the first frame in the video, for messages. `warned`: the views
  already warned about (a lazy source's earlier windows), not warned about again; a view
  warned about now is added."""
  left, right = _as_video(left, "left"), _as_video(right, "right")
  _check_video_shapes(left.shape, right.shape)
  for name, video in (("left", left), ("right", right)):
    if (check_video_values(video, name, first, warn=warned is None or name not in warned)
        and warned is not None):
      warned.add(name)
  return left, right  # cast to float32 per window, so long uint8 videos stay small


def run_window(variables, left: np.ndarray, right: np.ndarray, *, cfg: SAVConfig, iters: int,
               pads: tuple[int, int, int, int] | None = None, check_memory: bool = True,
               cache: FrameFeatureCache | None = None, start: int = 0) -> np.ndarray:
  """Runs the model once on a window (pads, runs the cached executables).

  The per-frame features come from `cache` (computed there when missing); the
  temporal rest of the model runs on the whole window.

  Args:
    variables: model variables (numpy ones are copied to the device on every call:
      `jax.device_put(variables)` once for windows run one by one).
    left, right: `[T, H, W, 3]` frames, uint8 or float (0..255).
    cfg: model config.
    iters: refinement iterations.
    pads: padding `(top, bottom, left, right)`; default `pad_amounts(H, W)`.
    check_memory: see `compiled_forward`.
    cache: per-frame features shared by consecutive windows (default: a fresh one).
    start: index of the window's first frame in the video (the cache's key).

  Returns:
    `[T, Hp, Wp]` float32 raw test-mode output on the padded frames (signed, not unpadded).

  Raises:
    ValueError: for the inputs `predict_video` refuses, pads that are not 4 integers
      >= 0 giving a padded size of multiples of 16, and a `cache` of another frame size,
      padding or config, or of a later window (`FrameFeatureCache`).
    CheckpointError: variables that do not fit `cfg`'s model.
  """
  cfg = resolve_config(cfg)
  iters = check_iters(iters)
  left, right = _as_video_pair(left, right)
  if not (_is_int(start) and start >= 0):
    raise ValueError(f"start must be an integer >= 0, got {start!r}")
  check_variables(variables, cfg)
  if pads is None:
    pads = pad_amounts(*left.shape[1:3])
  elif not (len(tuple(pads)) == 4 and all(_is_int(p) and p >= 0 for p in pads)
            and (left.shape[1] + pads[0] + pads[1]) % 16 == 0
            and (left.shape[2] + pads[2] + pads[3]) % 16 == 0):
    raise ValueError(f"pads must be 4 integers (top, bottom, left, right) >= 0 that pad "
                     f"{left.shape[1]}x{left.shape[2]} frames to multiples of 16, got {pads!r}")
  pads = tuple(int(p) for p in pads)
  if cache is not None:  # (predict_video's own caches see one video: no frame check there)
    cache.check_use(left.shape, pads, cfg, start, variables)
    cache.check_frames(left, right, start)
  variables = _on_one_device(variables)  # (after the cache's check of the caller's arrays)
  # a writeable copy (a device array's numpy view is read-only)
  return np.array(_run_window(variables, left, right, cfg=cfg, iters=iters, pads=pads,
                              check_memory=check_memory, cache=cache, start=start))


def _run_window(variables, left, right, *, cfg, iters, pads, check_memory, cache, start,
                keep_from=None):
  """`run_window` on inputs already checked (by `predict_video`); `keep_from`: as
  `_dispatch_window`'s."""
  cache = FrameFeatureCache() if cache is None else cache
  variables = model_variables(variables)
  cache.evict_before(start)
  todo = _feature_todo(cache.frames, cache.chunk, start, left.shape[0])
  programs = _window_programs(variables, left.shape, pads, todo, cfg=cfg, iters=iters,
                              check_memory=check_memory)
  return np.asarray(jax.device_get(_dispatch_window(
      variables, left, right, todo, programs, pads=pads, cache=cache, start=start,
      keep_from=keep_from)))


def _feature_todo(have, chunk: int, start: int, n: int) -> list[tuple[int, int]]:
  """The chunks `(a, b)` (frames `start + a .. start + b - 1`, aligned to multiples of
  `chunk` and cut to the window) whose features a window of `n` frames from `start` computes:
  those with a frame not in `have`."""
  todo = []
  for lo in range(start // chunk * chunk, start + n, chunk):
    hi = lo + chunk
    if not all(i in have for i in range(max(lo, start), min(hi, start + n))):
      todo.append((max(lo, start) - start, min(hi, start + n) - start))
  return todo


def _window_programs(variables, shape, pads, todo, *, cfg, iters, check_memory):
  """The executables of one window (`{chunk length: frame features}`, window) on the device
  of `variables`, compiled before any of its work runs, so that no computation is counted
  as compilation."""
  n = shape[0]
  hp, wp = shape[1] + pads[0] + pads[1], shape[2] + pads[2] + pads[3]
  _precheck(n, hp, wp, cfg, iters, check_memory and
            _cache_key("window", variables, cfg, iters, (n, hp, wp)) not in _COMPILED,
            _device_of(variables))
  fns = {b - a: compiled_frame_features(variables, b - a, hp, wp, cfg=cfg,
                                        check_memory=check_memory) for a, b in todo}
  return fns, compiled_window(variables, n, hp, wp, cfg=cfg, iters=iters,
                              check_memory=check_memory)


def _dispatch_window(variables, left, right, todo, programs, *, pads, cache, start,
                     keep_from=None):
  """Starts a window's work (its missing per-frame features, then the window) on the
  device of `variables`, where the features of frames computed elsewhere are copied;
  returns the raw disparity `[T, Hp, Wp]` as a device array. `keep_from`: the first frame a
  later window needs; the cache forgets the frames before it once the window's features
  are gathered, so they are not held twice while the window runs."""
  fns, window = programs
  for a, b in todo:
    lp = pad_frames(np.asarray(left[a:b], np.float32), pads)
    rp = pad_frames(np.asarray(right[a:b], np.float32), pads)
    feats = fns[b - a](variables, lp, rp)
    for k in range(b - a):
      cache.frames[start + a + k] = jax.tree_util.tree_map(lambda x, k=k: x[:, k:k + 1], feats)
  feats = cache.gather(start, start + left.shape[0], _device_of(variables))
  if keep_from is not None:
    cache.evict_before(keep_from)
  return window(variables, feats)


# Swapped views: the model's disparities of a left view are positive (the match lies to the
# left in the right view); with the views swapped most come out negative, which the official
# `abs()` hides: the output then looks like a disparity map of the right view, with the left
# view's occlusions wrong. A window whose kept frames have more than `SWAPPED_SHARE` of their
# pixels below `-SWAPPED_PX` is warned about, once per call.
SWAPPED_PX = 1.0
SWAPPED_SHARE = 0.5


class SwappedViewsWarning(UserWarning):
  """Most disparities came out negative before `abs()`: left and right swapped?"""


def negative_share(raw: np.ndarray, px: float = SWAPPED_PX) -> float:
  """The share of `raw` disparities (before `abs()`) below `-px`."""
  raw = np.asarray(raw)
  return float(np.count_nonzero(raw < -px)) / max(raw.size, 1)


def _warn_if_swapped(raw: np.ndarray, first: int) -> bool:
  """Warns (`SwappedViewsWarning`) when frames `first ..` of `raw` look swapped; whether it
  did."""
  share = negative_share(raw)
  if share <= SWAPPED_SHARE:
    return False
  warnings.warn(
      f"frames {first}..{first + len(raw) - 1}: {share:.0%} of the disparities are below "
      f"-{SWAPPED_PX:g} px before the official abs() (the model's disparities of a left view "
      "are positive): are the left and right views swapped? (Or the weights not trained for "
      "this data.) The output is abs() of these values, which hides it",
      SwappedViewsWarning, stacklevel=caller_stacklevel())
  return True


def _run_plan(variables, left, right, plan, *, cfg, iters, check_memory, chunk, progress=False,
              raw_windows=None):
  """Runs the windows of `plan` and stitches `abs()` of their kept frames, `[N', H, W]`."""
  return np.concatenate([d for _, d in _iter_plan(
      variables, left, right, plan, cfg=cfg, iters=iters, check_memory=check_memory,
      chunk=chunk, progress=progress, raw_windows=raw_windows)], axis=0)


def _iter_plan(variables, left, right, plan, *, cfg, iters, check_memory, chunk, progress=False,
               raw_windows=None, check_frames=False, devices=None):
  """Yields `(first frame index, abs() of the window's kept frames [k, H, W])` per window.

  `left[sl]` / `right[sl]` are read per window (a lazy source decodes them then); with
  `check_frames` each window's frames are checked as `predict_video` checks arrays.
  `devices` (from `resolve_devices`) run consecutive windows at once, one each; None runs
  them where the variables are (the default device for host arrays).
  """
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  shape = _video_shape(left)  # (a list of frames beside a lazy source has none)
  pads = pad_amounts(*shape[1:3])
  variables = model_variables(variables)
  placed = ([jax.device_put(_on_one_device(variables))] if devices is None else
            [jax.device_put(variables, d) for d in devices[:len(plan)]])  # (those it uses)
  total = sum(w.keep_stop - w.keep_start for w in plan)

  def frames(win):
    sl = slice(win.start, win.start + win.length)
    lw, rw = left[sl], right[sl]
    if not check_frames:
      return lw, rw
    want = (win.length, *shape[1:])
    for name, source, got in (("left", left, lw), ("right", right, rw)):
      if isinstance(got, (list, tuple)):  # (np.shape of frames of two sizes: NumPy's error)
        odd = next((k for k, f in enumerate(got) if np.shape(f) != want[1:]), None)
        if odd is not None:
          raise ValueError(f"{name}: frame {win.start + odd} has shape "
                           f"{np.shape(got[odd])}, not {want[1:]} as the video's frames; all "
                           "frames need one size [H, W, 3]")
      if tuple(np.shape(got)) != want:
        raise ValueError(
            f"{name} video source {type(source).__name__} declares shape "
            f"{_video_shape(source)}, but its frames {win.start}..{win.start + win.length - 1} "
            f"came back with shape {tuple(np.shape(got))}, not {want}")
    return _as_video_pair(lw, rw, win.start, values_warned)

  warned, values_warned = False, set()  # a value warning once per view, not every window's

  def kept(win, raw):
    nonlocal warned
    if raw_windows is not None:
      raw_windows.append(raw)
    first = win.start + win.keep_start
    raw = np.asarray(unpad(raw, pads)[win.keep_start:win.keep_stop])
    warned = warned or _warn_if_swapped(raw, first)
    return first, np.abs(raw)

  with tqdm(total=total, unit="frame", desc="disparity",
            disable=not (progress and runtime.draws_progress())) as bar:
    cache = FrameFeatureCache(chunk)
    if len(placed) == 1:
      for i, win in enumerate(plan):
        _signals.raise_if_interrupted()  # a Ctrl-C that Python dropped (the CLI's commands)
        lw, rw = frames(win)
        keep_from = plan[i + 1].start if i + 1 < len(plan) else win.start + win.length
        yield kept(win, _run_window(placed[0], lw, rw, cfg=cfg, iters=iters, pads=pads,
                                    check_memory=check_memory, cache=cache, start=win.start,
                                    keep_from=keep_from))
        bar.update(win.keep_stop - win.keep_start)
      return
    if check_memory:
      _check_shared_host_memory(devices, plan, (shape[1] + pads[0] + pads[1],
                                                shape[2] + pads[2] + pads[3]), cfg, iters)
    for g in range(0, len(plan), len(placed)):
      _signals.raise_if_interrupted()
      group = plan[g:g + len(placed)]
      cache.evict_before(group[0].start)
      have, work = set(cache.frames), []
      for win, v in zip(group, placed):  # every executable first, then the work
        todo = _feature_todo(have, cache.chunk, win.start, win.length)
        have.update(win.start + i for a, b in todo for i in range(a, b))
        programs = _window_programs(v, (win.length, *shape[1:3]), pads, todo, cfg=cfg,
                                    iters=iters, check_memory=check_memory)
        work.append((win, v, todo, programs))
      raws = []  # dispatched in order, run at once on their devices
      for win, v, todo, programs in work:
        lw, rw = frames(win)
        raws.append(_dispatch_window(v, lw, rw, todo, programs, pads=pads, cache=cache,
                                     start=win.start))
      # the group's features are gathered: keep only what the next group needs
      following = plan[g + len(placed):]
      last = group[-1]
      cache.evict_before(following[0].start if following else last.start + last.length)
      for win, raw in zip(group, raws):
        yield kept(win, np.asarray(jax.device_get(raw)))
        bar.update(win.keep_stop - win.keep_start)


def _check_shared_host_memory(devices, plan, padded, cfg, iters) -> None:
  """InsufficientMemoryError where the windows run at once on CPU devices (one process's
  fake devices, `--xla_force_host_platform_device_count`) would not fit together: they
  share the host's memory, which each device's own check counts whole (8 windows that
  each fit passed, then ran out of it together)."""
  cpus = [d for d in devices if d.platform == "cpu"][:len(plan)]
  if len(cpus) < 2:
    return
  t, (h, w) = plan[0].length, padded
  needed = len(cpus) * estimate_memory_bytes(t, h, w, iters, cfg)
  free = available_memory_bytes(cpus[0])
  if free is not None and needed > _PRECHECK_MARGIN * free:
    raise InsufficientMemoryError(
        f"{len(cpus)} {t}-frame windows of {h}x{w} (padded) at once, one per CPU device, need "
        f"about {needed / 2**30:.1f} GB (estimated), but only {free / 2**30:.1f} GB is free "
        "on the host, whose memory CPU devices share (fewer devices run fewer windows at once)",
        "fewer devices (devices), fewer frames per window (window/stride), smaller frames or "
        "bfloat16 (dtype='bfloat16')", devices=len(cpus))


def resolve_devices(devices=None) -> list:
  """The devices `predict_video` runs windows on.

  Args:
    devices: None (the default device), a number n >= 1 (the first n local devices of the
      default backend), 0 or "all" (every local device of it), a `jax.Device`, or a
      sequence of them.

  Returns:
    A list of distinct devices.

  Raises:
    ValueError: a negative number or one above the local device count, an empty or
      repeated list, another process's device, or something else.
  """
  if devices is None:
    return [_default_device()]
  local = jax.local_devices(backend=_default_device().platform)
  if isinstance(devices, str):
    if devices != "all":
      raise ValueError(f"devices must be a number, 'all' or a list of jax devices, got "
                       f"{devices!r}")
    return list(local)
  if isinstance(devices, jax.Device):
    devices = [devices]  # (checked as a list: another process's device is refused too)
  if _is_int(devices):
    if devices == 0:
      return list(local)
    if devices < 0:
      raise ValueError(f"devices must be a number of local devices >= 0 (0: all), got {devices}")
    if not 1 <= devices <= len(local):
      raise ValueError(f"devices={devices}, but {len(local)} local {local[0].platform} "
                       f"device{'s are' if len(local) > 1 else ' is'} available")
    return list(local[:int(devices)])
  try:
    devices = list(devices)
  except TypeError:
    raise ValueError(f"devices must be a number, 'all' or a list of jax devices, got "
                     f"{devices!r}") from None
  bad = [d for d in devices if not isinstance(d, jax.Device)]
  if not devices or bad or len(set(devices)) != len(devices):
    raise ValueError(f"devices must be a non-empty list of distinct jax devices, got {devices!r}")
  remote = [d for d in devices if d.process_index != jax.process_index()]
  if remote:  # (jax.devices() with several processes: JAX's error placing the weights there)
    raise ValueError(f"devices must be this process's own devices (jax.local_devices()), but "
                     f"{remote[0]} is process {remote[0].process_index}'s")
  return devices


def predict_video(variables, left, right, *, cfg: SAVConfig | None = None, iters: int = 20,
                  window: int = WINDOW, stride: int = STRIDE, dtype: str | None = None,
                  progress: bool = False, check_memory: bool = True,
                  devices=None) -> np.ndarray:
  """Disparity of every frame of a stereo video of any length and size.

  Args:
    variables: model variables (`params_from_state_dict` or `restore_variables`).
    left, right: `[T, H, W, 3]` RGB frames (not BGR: frames from `cv2.imread` are
      `frame[..., ::-1]`), uint8, other integers or floats in 0..255, as arrays, lists of
      frames or lazy video sources (see `iter_predict_video`); checked first
      (`check_video_values`).
    cfg: model config (default `SAVConfig()`).
    iters: refinement iterations at 1/4 resolution (>= 2; the official evaluation uses 20).
    window, stride: sliding window (official: 20, 10; window <= 32, the depth prior's
      temporal attention length).
    dtype: compute dtype override ("float32" or "bfloat16").
    progress: show a tqdm progress bar (frames, frames per second) where standard error is
      a terminal or in a notebook (`runtime.draws_progress`; not in a log file).
    check_memory: refuse sizes that cannot fit (InsufficientMemoryError).
    devices: where the windows run: None where the variables are (the default device for
      numpy ones), or as `resolve_devices` takes them: a number n for the first n local
      devices, 0 or "all", or a list of devices. With n
      devices, n consecutive windows run at once, one per device; every frame's features
      are still computed once (on the device of the first window that needs them, and
      copied to the next), and the result is the same as on one device.

  Returns:
    `[T, H, W]` float32 disparity (px, >= 0: the official evaluation's `abs()`) of the left
    view, every frame.

  Warns:
    SwappedViewsWarning: once, at the first window where most disparities came out below
      -1 px before `abs()` (`negative_share`): left and right swapped, most likely.
  """
  _check_not_traced("predict_video", variables, left, right)
  chunks = iter_predict_video(variables, left, right, cfg=cfg, iters=iters, window=window,
                              stride=stride, dtype=dtype, progress=progress,
                              check_memory=check_memory, devices=devices)
  out = None  # filled window by window (a list of pieces and a concatenation held it twice)
  for t, d in chunks:
    if out is None:
      out = np.empty((_video_shape(left)[0], *d.shape[1:]), np.float32)
    out[t:t + len(d)] = d
  return out


def _check_not_traced(what: str, variables, *videos) -> None:
  """A TypeError if frames or weights are JAX tracers (`predict_video` under `jax.grad`,
  `jit` or `vmap` failed with JAX's TracerArrayConversionError from deep inside)."""
  leaves = [*jax.tree_util.tree_leaves(variables)]
  for v in videos:
    leaves.extend(v if isinstance(v, (list, tuple)) else [v])
  if any(isinstance(x, jax.core.Tracer) for x in leaves):
    raise TypeError(
        f"{what} runs the model window by window and returns NumPy arrays: it cannot be "
        "traced (jax.grad, jit, vmap). For a differentiable or jitted forward, call the model "
        "itself: padded, pads = sav_jax.inference.pad_to_multiple(frames) for both views, "
        "model.apply(variables, left, right, iters=..., final_only=True), then "
        "sav_jax.inference.unpad(out.disparities[-1], pads)")


def _is_lazy_video(x) -> bool:
  """A lazy video source: not an array or a list, with a shape and slicing (of any number of
  axes: a source of grey `[T, H, W]` frames is refused by its shape, not taken for a 0-d
  array of one object)."""
  return (not isinstance(x, (np.ndarray, jax.Array, list, tuple)) and hasattr(x, "shape")
          and hasattr(x, "__getitem__"))


def _is_uint8_frame_list(video) -> bool:
  """Whether `video` is a non-empty list (or tuple) of uint8 NumPy frames of one shape."""
  return (isinstance(video, (list, tuple)) and len(video) > 0
          and all(isinstance(f, np.ndarray) and f.dtype == np.uint8
                  and f.shape == video[0].shape for f in video))


def iter_predict_video(variables, left, right, *, cfg: SAVConfig | None = None,
                       iters: int = 20, window: int = WINDOW, stride: int = STRIDE,
                       dtype: str | None = None, progress: bool = False,
                       check_memory: bool = True, devices=None):
  """`predict_video` one window at a time, for videos that do not fit in memory.

  `left` and `right` are arrays as for `predict_video`, or lazy video sources: objects with
  a `shape` `(T, H, W, 3)` whose `source[a:b]` returns those frames as an array (e.g.
  `sav_jax.tools.video_io.FrameSource`, which decodes frames when asked). A list of uint8
  frames (beside uint8 frames) is read window by window as well, not stacked whole. Only one window
  of frames (and the per-frame features of its overlap) is held at a time; a lazy
  source's frames are checked as they are read (a warning about their values once per
  view, not at every window). The arguments are checked by the call;
  the windows run as the returned iterator is consumed. With several `devices`, a group of
  that many windows (and their frames) is held at a time.

  Returns:
    An iterator of `(t, disparities [k, H, W])`: frames `t .. t + k - 1`, in order, every
    frame once (the same values `predict_video` returns).
  """
  _check_not_traced("iter_predict_video", variables, left, right)
  cfg = resolve_config(cfg, dtype)
  iters = check_iters(iters)
  check_window(window, stride)  # before the videos and weights are read
  lazy = _is_lazy_video(left) or _is_lazy_video(right)
  # A list of uint8 frames beside uint8 frames (which need no value check) is read window by
  # window too: stacking it whole made a second copy of the video.
  lazy = lazy or (any(_is_uint8_frame_list(v) for v in (left, right))
                  and all(_is_uint8_frame_list(v) or (isinstance(v, np.ndarray)
                                                      and v.dtype == np.uint8)
                          for v in (left, right)))
  if lazy:  # the frames themselves are checked window by window, as they are read
    _check_video_shapes(_video_shape(left, "left"), _video_shape(right, "right"))
  else:
    left, right = _as_video_pair(left, right)
  check_variables(variables, cfg)
  devices = None if devices is None else resolve_devices(devices)
  plan = window_plan(int(_video_shape(left)[0]), window, stride)
  return _iter_plan(variables, left, right, plan, cfg=cfg, iters=iters,
                    check_memory=check_memory, chunk=feature_chunk(window, stride),
                    progress=progress,
                    check_frames=lazy, devices=devices)


def forward_batch_test_official(variables, left, right, *, cfg: SAVConfig | None = None,
                                iters: int = 20, window: int = WINDOW, stride: int = STRIDE,
                                return_windows: bool = False):
  """The official `forward_batch_test`, frame drops included (for parity checks).

  Args:
    variables, left, right, cfg, iters, window, stride: as `predict_video`. The official
      code runs 20/10; other values apply its slices with this `stride`
      (`official_window_plan`), which tile the video only where `window == 2 * stride`:
      otherwise consecutive windows keep overlapping frames (the output repeats them, e.g.
      56 frames for 40 with 20/8) or leave gaps.
    return_windows: also return every window's raw output.

  Returns:
    `[N', H, W]` float32 stitched `abs()` disparity, N' as the official code gives it
    (N - 5 for 5 < N < 20, empty for N <= 5); with `return_windows`, a tuple with the
    list of raw padded outputs `[L_i, Hp, Wp]` of every window run (dropped ones too).
  """
  _check_not_traced("forward_batch_test_official", variables, left, right)
  cfg = resolve_config(cfg)
  iters = check_iters(iters)
  check_window(window, stride)
  left, right = _as_video_pair(left, right)
  check_variables(variables, cfg)
  raws = [] if return_windows else None
  plan = official_window_plan(left.shape[0], window, stride)
  disp = _run_plan(variables, left, right, plan, cfg=cfg, iters=iters, check_memory=True,
                   chunk=feature_chunk(window, stride), raw_windows=raws)
  return (disp, raws) if return_windows else disp

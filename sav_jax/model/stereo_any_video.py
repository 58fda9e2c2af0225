"""The Stereo Any Video model: features, three-scale cascade, temporal updates."""

from __future__ import annotations

import functools
from typing import Mapping

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from sav_jax._checks import check_video_values, is_int
from sav_jax.config import SAVConfig, as_config
from sav_jax.model.depth import DepthExtractor
from sav_jax.model.encoder import BasicEncoder
from sav_jax.model.layers import CorrMLP, in_frame_blocks, normalize, scan_traced_once
from sav_jax.model.update import SequenceUpdateBlock3D
from sav_jax.ops.correlation import SMALL_WINDOW, WIDE_WINDOW, aapc
from sav_jax.ops.pool import avg_pool
from sav_jax.ops.resize import resize
from sav_jax.ops.upsample import convex_upsample_3d

# With `SAVConfig.remat`, the encoders' backward pass holds about this many maps the size of
# their largest intermediate (the 64-channel map at 1/2) per frame of a block: XLA's buffer
# assignment of the paper's training step (B=1 T=5 256x512) has ~4 GB of them live for
# the 15 frames of fnet (both views) and cnet at once.
ENCODER_BACKWARD_MAPS = 32


@flax.struct.dataclass
class SAVOutput:
  """Model output.

  Attributes:
    disparities: `[P, B, T, H, W]` float32, the x-flow of every refinement step
      upsampled to full resolution (P = iters//2 + iters//2 + iters: the 1/16,
      1/8 and 1/4 stages in order). Positive values are disparities (the left
      pixel x matches right pixel x - d). With `final_only=True`, P = 1.
  """

  disparities: jax.Array


def check_inputs(left, right, iters: int) -> int:
  """Raises a ValueError naming the problem with the inputs' shapes (their values are
  checked by `features`) or `iters`; returns `iters` as an int."""
  check_videos(left, right, values=False)
  return check_iters(iters)


def check_videos(left, right, values: bool = True) -> None:
  """Raises a ValueError naming the problem unless `left` and `right` are RGB videos
  `[B, T, H, W, 3]` of one shape, H and W multiples of 16, W >= 32.

  With `values`, frames that are not traced (a model call outside `jit`/`grad`, or arrays
  closed over there) are checked as `predict_video` checks them
  (`inference.check_video_values`: finite, 0..255, not normalised, a warning for 0..1
  frames), each view as one video of its B*T frames, then (unless that warned) clip by clip,
  so that one odd clip in a batch is found too."""
  for name, x in (("left", left), ("right", right)):
    if not hasattr(x, "shape") or not hasattr(x, "dtype"):
      raise ValueError(f"{name} must be an array [B, T, H, W, 3] (numpy or jax), got a "
                       f"{type(x).__name__}")
    if not (jnp.issubdtype(x.dtype, jnp.floating) or jnp.issubdtype(x.dtype, jnp.integer)):
      raise ValueError(f"{name} has dtype {x.dtype}; expected RGB values 0..255 as floats or "
                       "integers (uint8)")
  if left.shape != right.shape:
    raise ValueError(f"left and right videos differ in shape: {left.shape} vs {right.shape}")
  if left.ndim != 5 or left.shape[-1] != 3 or min(left.shape[:4]) < 1:
    raise ValueError(
        f"expected RGB videos [B, T, H, W, 3] with values 0..255 (B, T, H, W >= 1), got shape "
        f"{left.shape}{layout_hint(left.shape, batched=True)}")
  _check_size(left.shape[2:4])
  if not values:
    return
  for name, x in (("left", left), ("right", right)):
    if isinstance(x, jax.core.Tracer) or not getattr(x, "is_fully_addressable", True):
      continue  # traced, or other processes' shards (a multi-host array)
    x = np.asarray(x)
    if x.dtype.kind == "V":  # bfloat16 / float8 (ml_dtypes), not a NumPy float kind
      x = x.astype(np.float32)
    b, t = x.shape[:2]
    if check_video_values(x.reshape(b * t, *x.shape[2:]),
                          name if b == 1 else f"{name} (its {b} clips' frames in order, {t} each)"):
      continue
    # One clip of 0..1 or normalised frames among 0..255 ones does not move the batch's
    # range (nor its 99.9% quantile): each clip is looked at alone too, the first odd one named.
    for i in range(b if b > 1 else 0):
      if check_video_values(x[i], f"{name} clip {i} (of {b})"):
        break


def channels_first_hint(shape) -> str:
  """A hint for a video in PyTorch's channels-first layout (`[..., 3, H, W]`), else ""."""
  if len(shape) >= 3 and shape[-3] == 3 and shape[-1] != 3:
    return (" (channels first, as in PyTorch? the channel axis goes last: "
            "np.moveaxis(video, -3, -1))")
  return ""


def layout_hint(shape, batched: bool) -> str:
  """What a video of `shape` that is not `[B, T, H, W, 3]` (`batched`) or `[T, H, W, 3]`
  probably is, and the way to the expected layout; "" where nothing fits."""
  shape, want = tuple(shape), 5 if batched else 4
  hint = channels_first_hint(shape)
  if hint:
    return hint
  if len(shape) >= 3 and shape[-1] == 4:
    return " (RGBA? drop the alpha channel: video[..., :3])"
  if len(shape) >= 3 and shape[-1] == 1:
    return " (one channel? repeat it: np.repeat(video, 3, axis=-1))"
  if len(shape) == want - 1 and shape[-1] == 3:
    return (" (a batch of one video is video[None])" if batched else
            " (one frame? a video of one frame is frame[None])")
  if len(shape) == want - 1:
    return " (grey frames? give them 3 channels: np.repeat(video[..., None], 3, axis=-1))"
  if len(shape) == want + 1 and not batched and shape[-1] == 3:
    return " (one video per call: for a batch [B, T, H, W, 3], pass video[b])"
  return ""


def _check_size(size) -> tuple[int, int]:
  h, w = size
  if h % 16 or w % 16 or min(h, w) < 16:
    raise ValueError(
        f"height and width must be multiples of 16, got {h}x{w}; pad the frames as the "
        "official evaluation does with `padded, pads = sav_jax.inference.pad_to_multiple("
        "frames)` (NumPy or JAX, differentiable) and crop the output with "
        "`inference.unpad(disparities, pads)`, or use inference.predict_video, which pads "
        "for you")
  if w < 32:
    raise ValueError(
        f"width {w} is refused: at 1/16 the feature map is 1 pixel wide, where the official "
        "model's sampler divides by zero (its output is all NaN), so no result could be "
        "checked against it; use frames at least 32 wide (inference.pad_to_multiple and "
        "predict_video pad to multiples of 32)")
  return int(h), int(w)


def check_frame_features(frame_feats, size) -> tuple[int, int]:
  """Raises a ValueError naming the problem unless `frame_feats` are `frame_features` of
  frames of `size` (H, W); returns the size as ints."""
  try:
    h, w = (int(v) for v in size)
  except (TypeError, ValueError):
    raise ValueError(f"size must be the frames' (height, width), got {size!r}") from None
  if (h, w) != tuple(size):
    raise ValueError(f"size must be two integers (height, width), got {size!r}")
  _check_size((h, w))
  if not isinstance(frame_feats, Mapping) or not {"tokens", "fnet", "cnet"} <= set(frame_feats):
    found = sorted(frame_feats) if isinstance(frame_feats, Mapping) else type(frame_feats).__name__
    raise ValueError(f"frame_feats must be frame_features' dict (tokens, fnet, cnet), got {found}")
  fnet, cnet = (tuple(np.shape(frame_feats[k])) for k in ("fnet", "cnet"))
  tokens = [tuple(np.shape(x)) for x in frame_feats["tokens"]]
  want = (h // 4, w // 4)
  if (len(fnet) != 5 or len(cnet) != 5 or fnet[0] != 2 * cnet[0] or fnet[1] != cnet[1]
      or fnet[2:4] != want or cnet[2:4] != want
      or any(len(t) != 4 or t[:2] != fnet[:2] for t in tokens)):
    raise ValueError(
        f"frame features do not fit {h}x{w} frames: fnet {fnet} (expected [2B, T, {want[0]}, "
        f"{want[1]}, C]), cnet {cnet} (expected [B, T, {want[0]}, {want[1]}, C]), tokens "
        f"{tokens} (expected [2B, T, N, D] each)")
  return h, w


def check_final_only(final_only) -> bool:
  """`final_only` as a Python bool; a ValueError for a traced value (it sets the program's
  output shape) or a non-boolean."""
  if isinstance(final_only, jax.core.Tracer):
    raise ValueError(f"final_only must be a Python bool, got the traced {final_only!r}: under "
                     "jax.jit pass it as a static argument (static_argnames='final_only', or "
                     "close over it)")
  if not isinstance(final_only, (bool, np.bool_)):
    raise ValueError(f"final_only must be True or False, got {final_only!r}")
  return bool(final_only)


def check_iters(iters) -> int:
  """`iters` as a Python int; a ValueError unless it is an integer >= 2 (odd counts run as
  the official model runs them: `iters // 2` steps at 1/16 and at 1/8, `iters` at 1/4, the
  windows alternating from 1x9 at each scale; below 2 the official model has no 1/16 step).

  Any integer type is accepted (numpy's too, not bool), so `iters=np.int64(4)` and
  `iters=4` run, and cache, the same computation.
  """
  if isinstance(iters, jax.core.Tracer):
    raise ValueError(f"iters must be a Python integer, got the traced {iters!r}: under jax.jit "
                     "pass it as a static argument (static_argnames='iters', or close over it)")
  if not is_int(iters) or iters < 2:
    raise ValueError(
        f"iters must be an integer >= 2 (the 1/16 and 1/8 stages run iters//2 >= 1 steps "
        f"each), got {iters!r}")
  return int(iters)


def training_state_hint(variables) -> str:
  """`": a training state? pass {'params': state.params}"` for something that is no mapping
  of variables but has `params` (a `TrainState`), else ""."""
  if isinstance(variables, Mapping) or not hasattr(variables, "params"):
    return ""
  return ": a training state? pass {'params': state.params}"


def _check_collections(collections: set) -> None:
  """A ValueError when the Flax variables' collections are the parameter tree's top-level
  modules (`params` given instead of `{"params": params}`)."""
  if "params" not in collections and collections & {"depthnet", "fnet", "cnet", "update_block"}:
    raise ValueError("StereoAnyVideo.apply takes the Flax variables {'params': params}; it "
                     f"got the parameter tree itself (keys {sorted(collections)[:4]}...): "
                     "call model.apply({'params': params}, left, right, ...)")


class StereoAnyVideo(nn.Module):
  """Stereo Any Video (ICCV 2025). Attribute names follow the official modules."""

  cfg: SAVConfig = SAVConfig()

  @nn.nowrap
  def apply(self, variables, *args, **kwargs):
    """`nn.Module.apply`, with a clear error for `variables` that are not a mapping (a
    training state: Flax said only "argument of type 'TrainState' is not iterable")."""
    if not isinstance(variables, Mapping):
      raise TypeError(f"StereoAnyVideo.apply takes the Flax variables {{'params': params}} as "
                      f"its first argument; got a {type(variables).__name__}"
                      f"{training_state_hint(variables)}")
    _check_collections(set(variables))  # every method (features too), not only __call__
    return super().apply(variables, *args, **kwargs)

  def setup(self):
    # A dict (a FrozenDict once Flax has it) or None would fail deep inside, unnamed.
    as_config(self.cfg, "StereoAnyVideo(cfg)", allow_none=False)
    dt = self.cfg.compute_dtype
    self.cnet = BasicEncoder(self.cfg.fnet_dim, dt)
    self.fnet = BasicEncoder(self.cfg.fnet_dim, dt)
    self.depthnet = DepthExtractor(self.cfg)
    self.corr_mlp = CorrMLP()
    self.update_block = SequenceUpdateBlock3D(self.cfg.hidden_dim, self.cfg.upsample_rate, dt,
                                              self.cfg.frame_block_mb, self.cfg.gru_conv)

  def frame_features(self, left: jax.Array, right: jax.Array) -> dict:
    """The per-frame part of the features: nothing here mixes frames.

    Long-video inference computes it once per frame and reuses it in every window
    that contains the frame (`sav_jax.inference.predict_video`).

    Args:
      left: `[B, T, H, W, 3]` RGB 0..255.
      right: `[B, T, H, W, 3]`.

    Returns:
      dict with "tokens": VDA's four DINOv2 token maps `[2B, T, h*w, D]` (left clips
      then right clips; h x w the patch grid, no class token), "fnet":
      `[2B, T, H/4, W/4, fnet_dim]`, "cnet": `[B, T, H/4, W/4, fnet_dim]` (left view;
      `cfg.fnet_dim`, 96 in the official model), float32 apart from the tokens (compute
      dtype).
    """
    self._check_bound("frame_features")
    check_videos(left, right)
    b, t, h, w, _ = left.shape
    both = normalize(jnp.concatenate([left, right], axis=0)).reshape(2 * b * t, h, w, 3)
    tokens = [x.reshape(2 * b, t, *x.shape[1:]) for x in self.depthnet.tokens(both)]
    # The encoders' largest intermediate: the 64-channel map at 1/2 (float32 norms).
    frame_bytes = h * w * 64
    remat = lambda fn: fn  # noqa: E731
    if self.cfg.remat:
      # A backward pass recomputes the encoders block by block from the frames instead of
      # keeping their activations, so the blocks are sized for the backward's maps.
      remat, frame_bytes = nn.remat, frame_bytes * ENCODER_BACKWARD_MAPS
    fnet = in_frame_blocks(self, remat(lambda m, x: m.fnet(x).astype(jnp.float32)), both,
                           frame_bytes, self.cfg.frame_block_mb)
    cnet = in_frame_blocks(self, remat(lambda m, x: m.cnet(x).astype(jnp.float32)),
                           both[:b * t], frame_bytes, self.cfg.frame_block_mb)
    return {"tokens": tokens, "fnet": fnet.reshape(2 * b, t, *fnet.shape[1:]),
            "cnet": cnet.reshape(b, t, *cnet.shape[1:])}

  def window_features(self, frame_feats: dict, height: int, width: int):
    """The temporal part of the features (VDA's head) on top of `frame_features`.

    Args:
      frame_feats: `frame_features` of the clip (or its frames gathered from several
        calls along the T axis).
      height, width: frame size H, W.

    Returns:
      `(fmap1, fmap2, context)` as `features`.
    """
    b2, t = frame_feats["fnet"].shape[:2]
    b = b2 // 2
    tokens = [x.reshape(b2 * t, *x.shape[2:]) for x in frame_feats["tokens"]]
    depth = self.depthnet.from_tokens(tokens, b2, t, height, width).astype(jnp.float32)
    fnet = frame_feats["fnet"]
    # One concatenation per view (not both views then slices: no extra copy of the left).
    fmap1 = jnp.concatenate([depth[:b], fnet[:b]], axis=-1)
    fmap2 = jnp.concatenate([depth[b:], fnet[b:]], axis=-1)
    context = jnp.concatenate([depth[:b], frame_feats["cnet"]], axis=-1)
    return fmap1, fmap2, context

  def features(self, left: jax.Array, right: jax.Array):
    """Matching features of both views and the left context at 1/4.

    Args:
      left: `[B, T, H, W, 3]` RGB 0..255.
      right: `[B, T, H, W, 3]`.

    Returns:
      `(fmap1, fmap2, context)`, each `[B, T, H/4, W/4, 128]` float32:
      `[depth | fnet]` per view and `[depth | cnet]` of the left view (`cfg.depth_dim` +
      `cfg.fnet_dim` channels: 32 + 96 in the official model).
    """
    self._check_bound("features")
    return self.window_features(self.frame_features(left, right), *left.shape[2:4])

  def step(self, net, flow, inp, fmap1, fmap2, window, with_up: bool = True):
    """One refinement iteration at one scale.

    Args:
      net: `[B, T, h, w, 128]` GRU state.
      flow: `[B, T, h, w, 1]` x-flow (the y-flow never influences x in the
        official model: it is zeroed before every use).
      inp: `[B, T, h, w, 128]` context input.
      fmap1: `[B, T, h, w, 128]` left features.
      fmap2: `[B, T, h, w, 128]` right features.
      window: `WIDE_WINDOW` or `SMALL_WINDOW`, or a traced integer step index (even:
        1x9, odd: 3x3; both correlations are in the program, one runs).
      with_up: compute the mask head and the convex upsampling (skipped for
        iterations whose prediction nobody reads).

    Returns:
      `(net, flow, flow_up)` with `flow_up` `[B, T, 4h, 4w, 1]` (None without `with_up`).
    """
    b, t, h, w, c = fmap1.shape
    if self.cfg.detach_flow:  # the official flow.detach(): truncated backpropagation
      flow = jax.lax.stop_gradient(flow)
    args = (fmap1.reshape(b * t, h, w, c), fmap2.reshape(b * t, h, w, c),
            flow.reshape(b * t, h, w))
    if isinstance(window, tuple):
      corr = aapc(*args, window, self.cfg.corr_groups)
    else:
      wide, small = (functools.partial(aapc, window=win, groups=self.cfg.corr_groups)
                     for win in (WIDE_WINDOW, SMALL_WINDOW))
      corr = jax.lax.cond(window % 2 == 0, wide, small, *args)
    corr = self.corr_mlp(corr).reshape(b, t, h, w, -1)
    net, mask, delta = self.update_block(net, inp, corr, flow, with_mask=with_up)
    flow = flow + delta[..., :1]
    up = convex_upsample_3d(flow, mask, self.cfg.upsample_rate) if with_up else None
    return net, flow, up

  def refine(self, net, flow, inp, fmap1, fmap2, num_iters: int, all_ups: bool = True):
    """`num_iters` iterations at one scale, alternating 1x9 and 3x3 windows, in a `lax.scan`.

    The scan runs over single steps, each choosing its window's correlation with
    `lax.cond` on the step index, so the program holds the update block once per scale
    (a scan over (1x9, 3x3) pairs plus an unrolled last step for odd counts held it three
    times: on CPU the window program at T=5 128x256 iters=8 compiled in 17 s instead of
    29-34 s, with bit-identical outputs and the same speed). With `remat`, each step is
    rematerialized on its own, so a backward pass holds one step's activations at a time.

    With `all_ups=True` (training, every prediction) every step runs the mask head and
    the convex upsampling. With `all_ups=False` only the last iteration's upsampled flow
    is computed: no iteration runs them; they run once on the final state (the same
    values as the last iteration's own).

    Returns:
      `(flow_ups, last_flow)`: `[num_iters or 1, B, T, 4h, 4w, 1]` and `[B, T, h, w, 1]`.
    """
    remat = lambda fn: fn  # noqa: E731
    if self.cfg.remat:
      policy = self.cfg.remat_policy
      remat = lambda fn: nn.remat(  # noqa: E731
          fn, prevent_cse=False,
          policy=getattr(jax.checkpoint_policies, policy) if policy else None)

    def one(mdl, carry, inp, fmap1, fmap2):
      net, flow, i = carry
      net, new_flow, up = mdl.step(net, flow, inp, fmap1, fmap2, i, all_ups)
      return (net, new_flow, i + 1), (flow if up is None else (up, flow))

    scan = nn.scan(remat(one), variable_broadcast="params", split_rngs={"params": False},
                   in_axes=(nn.broadcast, nn.broadcast, nn.broadcast), length=num_iters,
                   **scan_traced_once(self))
    (net, flow, _), outs = scan(self, (net, flow, jnp.zeros((), jnp.int32)), inp, fmap1, fmap2)
    if all_ups:
      ups, flows_in = outs
    else:
      mask = self.update_block.mask_logits(net)
      ups, flows_in = convex_upsample_3d(flow, mask, self.cfg.upsample_rate)[None], outs
    self._sow_flows_in(fmap1, flows_in)
    return ups, flow

  def create_parameters(self, left: jax.Array, right: jax.Array) -> None:
    """Calls every submodule once: with `init` (`method=StereoAnyVideo.create_parameters`)
    it creates the very parameters of `init` with `__call__`, in about 2/3 of the time (no
    cascade of scans, each of whose steps `init` traces twice): `sav_jax.model.init`'s
    `abstract_variables` uses it. `left`/`right`: `[B, T, H, W, 3]` frames as for
    `__call__`."""
    self._check_bound("create_parameters")
    fmap1, fmap2, context = self.features(left, right)
    net, inp = jnp.tanh(context).astype(self.cfg.compute_dtype), nn.relu(context)
    flow = jnp.zeros((*fmap1.shape[:-1], 1), jnp.float32)
    self.step(net, flow, inp, fmap1, fmap2, WIDE_WINDOW, with_up=True)

  def _sow_flows_in(self, fmap1, flows_in):
    """The flow entering every iteration, for inspection (no-op unless mutable)."""
    self.sow("intermediates", f"flow_in_{fmap1.shape[2]}x{fmap1.shape[3]}", flows_in)

  def _check_bound(self, method: str) -> None:
    """A TypeError for a method called on the module itself, without variables (Flax said
    only "Can't check if running under init() on unbound modules")."""
    if self.scope is None:
      args = {"__call__": "left, right, iters=20",
              "from_frame_features": "frame_feats, size"}.get(method, "left, right")
      how = "" if method == "__call__" else f", method=sav_jax.StereoAnyVideo.{method}"
      name = "model" if method == "__call__" else f"model.{method}"
      raise TypeError(f"StereoAnyVideo is a Flax module without weights: call "
                      f"model.apply(variables, {args}{how}) with variables = "
                      "{'params': params} (sav_jax.convert.params_from_state_dict, or "
                      "sav_jax.model.init.init_variables for fresh ones), not "
                      f"{name}({args})")

  def _check_variables(self) -> None:
    """A ValueError when `apply` was given the parameter tree itself instead of the Flax
    variables `{"params": params}` (Flax would fail deep inside the depth prior, naming its
    first parameter)."""
    self._check_bound("__call__")
    if self.is_initializing():
      return
    _check_collections(set(self.variables))

  def __call__(self, left: jax.Array, right: jax.Array, iters: int = 20,
               final_only: bool = False) -> SAVOutput:
    """Disparity of the left video for every refinement step.

    Args:
      left: `[B, T, H, W, 3]` RGB in 0..255 (H, W multiples of 16).
      right: `[B, T, H, W, 3]`.
      iters: refinement steps at 1/4 (>= 2); 1/16 and 1/8 get `iters // 2` each.
      final_only: return only the last prediction (`P = 1`), as test mode does.

    Returns:
      `SAVOutput` with `disparities` `[P, B, T, H, W]`.
    """
    iters = check_inputs(left, right, iters)
    final_only = check_final_only(final_only)
    self._check_variables()
    return self.cascade(*self.features(left, right), left.shape[2:4], iters, final_only)

  def from_frame_features(self, frame_feats: dict, size: tuple[int, int], iters: int = 20,
                          final_only: bool = True) -> SAVOutput:
    """`__call__` from precomputed `frame_features` (frames of size `size` = (H, W)), but
    with `final_only=True` by default (the last prediction, `P = 1`, as long-video inference
    uses it; `__call__`'s default is every prediction)."""
    self._check_bound("from_frame_features")
    size = check_frame_features(frame_feats, size)
    iters = check_iters(iters)
    final_only = check_final_only(final_only)
    return self.cascade(*self.window_features(frame_feats, *size), size, iters, final_only)

  def cascade(self, fmap1, fmap2, context, size: tuple[int, int], iters: int,
              final_only: bool) -> SAVOutput:
    """The 1/16 -> 1/8 -> 1/4 refinement from `features`' output (frames of size `size`)."""
    h, w = size
    # The GRU state is carried in the compute dtype (the scan carry keeps one dtype).
    net, inp = jnp.tanh(context).astype(self.cfg.compute_dtype), nn.relu(context)
    scales = {k: tuple(avg_pool(a, k) for a in (net, inp, fmap1, fmap2)) for k in (4, 2)}
    scales[1] = (net, inp, fmap1, fmap2)
    preds = []
    flow = jnp.zeros((*scales[4][2].shape[:-1], 1), jnp.float32)
    for pool, up_factor in ((4, 4), (2, 2), (1, 1)):
      n = iters if pool == 1 else iters // 2
      s_net, s_inp, f1, f2 = scales[pool]
      if pool != 4:  # hand-over: rescale by the height ratio, align_corners=True
        hf = f1.shape[2]
        flow = (hf / prev_up.shape[2]) * resize(prev_up, (hf, f1.shape[3]), "bilinear", True)
      ups, flow = self.refine(s_net, flow, s_inp, f1, f2, n, all_ups=not final_only)
      prev_up = ups[-1]
      if final_only and pool != 1:
        continue
      if up_factor != 1:
        ups = up_factor * resize(ups, (h, w), "bilinear", True)
      preds.append(ups[..., 0])
    disp = jnp.concatenate(preds, axis=0)
    return SAVOutput(disparities=disp[-1:] if final_only else disp)

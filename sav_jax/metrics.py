"""Stereo-video metrics with the exact definitions of the official SAV evaluator.

Reimplements `evaluation/utils/eval_utils.py` (EPE/TEPE, TCC, TCM, OPW, RTC),
the evaluator's pre-processing and `aggregate_eval_results` of the official Stereo
Any Video code, in NumPy on host arrays. Sequences are `[T, H, W]` (a singleton
channel axis, `[T, 1, H, W]`, is accepted too). Per-pixel maps are computed in
float32 with the same elementwise operations as the float32 PyTorch reference (so
threshold decisions match bit for bit); reductions run in float64.

Notation: x = prediction, y = ground truth (GT), m = validity mask (float, may be
fractional), b = [m > mask_thr] (default 0.5), all `[T, H, W]`.

Evaluator pre-processing (`eval_sequence`): y <- |y|, x <- x * round(m).

EPE / TEPE (`eval_endpoint_error_sequence`), after an optional border crop:
  x <- x*b, y <- y*b, then NaN in y -> 0 (after masking, so a NaN GT under b=1
  becomes 0 and costs |x| there).
  EPE map   e_t = sqrt(m_t * (x_t - y_t)^2)             (m also weights the error)
  TEPE map  e_t = sqrt(m_t m_{t+1} (|x_t - x_{t+1}| - |y_t - y_{t+1}|)^2),
            t = 0..T-2 (absolute temporal differences, not signed ones).
  mean      = sum(e) / max(count_nonzero(e), 1e-5)
  bad_tau   = 100 * #(e > tau) / max(count_nonzero(e), 1e-5),  tau in 0.5,1,2,3
  The denominator counts non-zero errors: masked-out pixels and valid pixels
  with exactly zero error are both excluded. Comparisons are strict.
  delta^t_1px of the paper is `temp_epe_bad_1px`.

Depth metrics (`eval_batch`): Z = s / max(d, 1e-10) for x and y (s = depth to
disparity scale), then x <- Z_x*b, y <- Z_y*b, NaN(y) -> 0; dm_t = m_t m_{t+1}.
  TCC = mean_t relu(SSIM(|x_t - x_{t+1}| dm_t, |y_t - y_{t+1}| dm_t)), NaN(x) -> 0.
  TCM = (1/(T-1)) sum_{t: sum(M_t)>0} mean_{c=u,v} relu(SSIM_c(F^x_t M_t, F^y_t M_t)),
        F^x_t / F^y_t = optical flow between the depths of frames t, t+1 of x / y,
        both normalised to 0..255 by the min and max of the masked GT depth y_t
        (`tcm_flow_inputs`; RAFT in the official code: passed in as flows or
        a `flow_fn`, e.g. `sav_jax.model.raft.raft_flow_fn`),
        M_t = dm_t * [no channel of F^y_t > 250].
  SSIM: Gaussian window 11, sigma 1.5, "valid" filtering (an axis shorter than the
  window is not filtered), data_range 1, K = (0.01, 0.03), mean over the map.
  OPW / RTC use the optical flow F_t of the left video from frame t to t+1
  (RAFT, passed in the same way) and W_t = backward warp of x_{t+1}
  (`grid_sample`, bilinear, zero padding, align_corners=True) and
  V_t = [dm_t exp(-50 ||warp(I_{t+1}) - I_t||_2 / 255) [no F_t channel > 250]
         [W_t > 0] > 0.01].
  OPW   = (1/(T-1)) sum_{t: sum V_t > 0} sum(|W_t - x_t| V_t) / sum(V_t)
  OPW_K = same with V_t * [y_t <= K][y_{t+1} <= K], K = 30, 50, 100.
  RTC   = (1/(T-1)) sum_{t: sum V_t > 0} sum([max(x_t/W_t, W_t/x_t) < 1.01] V_t)
          / sum(V_t), where an infinite ratio counts as -1e10 and NaN as a miss;
  RTC_30 = same with the K = 30 depth mask.

Aggregation (`aggregate`): value = sum_s v_s T_s / sum_s T_s with T_s the number
of frames of sequence s (T_s, not T_s - 1, also for the temporal metrics).

Warnings of `eval_batch` / `eval_sequence` (the numbers stay the official rule's):
`NotMeasuredWarning` where the official rule scores what was not measured (the cases of
`not_measured_note`: no valid GT pixel, one frame, no pixel valid in two consecutive frames,
and, with the depth metrics, frame pairs without a pixel valid in both), and a `UserWarning` for a given input that no
metric used (e.g. a video without `scale` or without flows: OPW/RTC left out) and for a
float video that looks 0..1 or 16-bit rather than RGB 0..255 (OPW/RTC change).
"""

from __future__ import annotations

import numbers
import warnings
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from sav_jax._checks import (caller_stacklevel, float_frames_range, is_int, nonfinite_frames,
                             unit_range_advice, widened)

_F32 = np.float32
BAD_THRESHOLDS = (0.5, 1.0, 2.0, 3.0)
_BAD_NAMES = ("0.5", "1", "2", "3")
FlowFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


class NotMeasuredWarning(UserWarning):
  """`eval_batch` / `eval_sequence` returned official numbers that measure nothing: no valid
  ground-truth pixel (EPE, TEPE and their bad-pixel rates 0), or one frame (TEPE 0, no frame
  pair). A caller that reports such sequences itself (`python -m eval`: `gt_notes`) can
  silence this category: `warnings.simplefilter("ignore", NotMeasuredWarning)`."""


def _as_seq(name: str, a) -> np.ndarray:
  """`[T, H, W]` float32 view of `a` (`[T, 1, H, W]` is squeezed)."""
  try:  # (numpy's own message names no argument: a list of frames of two sizes, text)
    a = np.asarray(a, dtype=_F32)
  except (TypeError, ValueError) as e:
    raise ValueError(f"{name} must be a [T, H, W] array of numbers (frames of one size): {e}"
                     ) from None
  if a.ndim == 4 and a.shape[1] == 1:
    a = a[:, 0]
  if a.ndim != 3:
    raise ValueError(f"{name} must be [T, H, W] or [T, 1, H, W], got shape {a.shape}")
  if a.size == 0:
    raise ValueError(f"{name} is empty (shape {a.shape}): metrics need T >= 1 frames of at "
                     "least 1x1 pixels")
  return a


def _check_scale(scale) -> float:
  """`scale` (the depth-to-disparity scale) as a float; ValueError unless it is one finite
  positive real number (a string, bool, array, 0, NaN or inf is refused)."""
  a = widened(np.asarray(scale)) if not isinstance(scale, (str, bytes)) else None  # bfloat16
  if a is None or a.ndim != 0 or a.dtype.kind not in "uif" or not (np.isfinite(a) and a > 0):
    raise ValueError(f"scale (depth-to-disparity scale, fx * baseline) must be a finite positive "
                     f"number, got {scale!r}")
  return float(a)


def _check_depth_flows(depth_flows) -> None:
  """ValueError unless `depth_flows` is a pair `(pred_flows, gt_flows)`."""
  try:
    count = len(depth_flows)
  except TypeError:
    count = None
  if count != 2:
    got = f"{count} items" if count is not None else type(depth_flows).__name__
    raise ValueError(f"depth_flows must be a pair (pred_flows, gt_flows) of [T-1, 2, H, W] "
                     f"flows, got {got}")


def _as_mask(name: str, a) -> np.ndarray:
  """`_as_seq` of a validity mask, which must hold finite values in [0, 1] (bool, 0/1 or
  the official fractional weights)."""
  m = _as_seq(name, a)
  if m.size and not (np.isfinite(m).all() and m.min() >= 0 and m.max() <= 1):
    finite = m[np.isfinite(m)]
    lo, hi = (finite.min(), finite.max()) if finite.size else (_F32(np.nan), _F32(np.nan))
    # `:g` keeps 6 digits: 1.0000001 would read "got 0..1"; float32's shortest repr where so
    lo_s, hi_s = (f"{v:g}" if _F32(f"{v:g}") == v else str(v) for v in (lo, hi))
    raise ValueError(f"{name} must hold values in [0, 1] (a validity mask), got {lo_s}..{hi_s}"
                     f"{' with NaN/inf' if finite.size < m.size else ''}"
                     f"{'; a 0/255 image? divide it by 255' if hi == 255 else ''}")
  return m


def _check_same(names: Sequence[str], arrays: Sequence[np.ndarray]) -> None:
  """Raises ValueError if the arrays' shapes differ, naming both."""
  for name, a in zip(names[1:], arrays[1:]):
    if a.shape != arrays[0].shape:
      raise ValueError(
          f"shape mismatch: {names[0]} has shape {arrays[0].shape}, {name} has shape {a.shape}")


def check_mask_thr(mask_thr) -> None:
  """Raises ValueError unless `mask_thr` is a number in [0, 1) (outside it every pixel or none
  would count, a silently perfect or meaningless score)."""
  if isinstance(mask_thr, bool) or not isinstance(mask_thr, numbers.Real) or not (
      0 <= mask_thr < 1):
    raise ValueError(f"mask_thr must be a number in [0, 1) (mask values are in [0, 1]), got "
                     f"{mask_thr!r}")


def _mask_pair(x: np.ndarray, y: np.ndarray, mask: np.ndarray, mask_thr: float):
  """`x*b`, `y*b` with `b = mask > mask_thr`; NaN in y set to 0 afterwards."""
  check_mask_thr(mask_thr)
  keep = (mask > _F32(mask_thr)).astype(_F32)
  x = x * keep
  with np.errstate(invalid="ignore"):  # inf GT where masked out: NaN, then 0 as NaN GT is
    y = y * keep
  y[np.isnan(y)] = 0
  return x, y


def _rates(err: np.ndarray, prefix: str, clamp_thr: float) -> dict[str, float]:
  """Mean and strict bad-px rates (%) with the count_nonzero denominator."""
  denom = max(float(np.count_nonzero(err)), clamp_thr)
  out = {f"{prefix}_mean": float(np.sum(err, dtype=np.float64) / denom)}
  for name, tau in zip(_BAD_NAMES, BAD_THRESHOLDS):
    out[f"{prefix}_bad_{name}px"] = 100.0 * float(np.count_nonzero(err > _F32(tau))) / denom
  return out


def endpoint_error_maps(pred, gt, mask, crop: int = 0, mask_thr: float = 0.5):
  """Per-pixel EPE and TEPE maps of the official evaluator.

  Args:
    pred: `[T, H, W]` (or `[T, 1, H, W]`) predicted disparity.
    gt: same shape, GT disparity; NaNs allowed.
    mask: same shape, validity mask (binary or fractional).
    crop: border width removed from both spatial sides before anything else.
    mask_thr: pixels with `mask > mask_thr` are kept.

  Returns:
    `(epe [T, H', W'], tepe [T-1, H', W'])` float32, 0 where masked out.
  """
  x, y, m = _as_seq("pred", pred), _as_seq("gt", gt), _as_mask("mask", mask)
  _check_same(("pred", "gt", "mask"), (x, y, m))
  _check_finite("pred", x)  # a NaN pixel counted in the rates' denominator, never as bad
  if not (is_int(crop) and crop >= 0):
    raise ValueError(f"crop must be an integer >= 0 (border pixels), got {crop!r}")
  if crop > 0:
    if crop >= min(x.shape[1:]) - crop:  # the official check is `>`: it let an empty crop by
      raise ValueError(f"Incorrect crop size {crop} for spatial shape {x.shape[1:]} (nothing "
                       "would be left)")
    x, y, m = (a[:, crop:-crop, crop:-crop] for a in (x, y, m))
  x, y = _mask_pair(x, y, m, mask_thr)
  epe = np.sqrt(m * (x - y) ** 2)
  dmask = m[:-1] * m[1:]
  tdiff = np.abs(x[:-1] - x[1:]) - np.abs(y[:-1] - y[1:])
  tepe = np.sqrt(dmask * tdiff ** 2)
  return epe, tepe


def eval_endpoint_error_sequence(pred, gt, mask, crop: int = 0, mask_thr: float = 0.5,
                                 clamp_thr: float = 1e-5) -> dict[str, float]:
  """EPE and temporal EPE with bad-px rates (official `eval_endpoint_error_sequence`).

  Args:
    pred: `[T, H, W]` (or `[T, 1, H, W]`) predicted disparity.
    gt: same shape, GT disparity; NaNs allowed (set to 0 after masking).
    mask: same shape, validity mask; thresholded for x/y and used as a weight.
    crop: border width removed on each spatial side.
    mask_thr: mask threshold.
    clamp_thr: lower clamp of the non-zero-count denominator.

  Returns:
    `{epe_mean, epe_bad_{0.5,1,2,3}px, temp_epe_mean, temp_epe_bad_{0.5,1,2,3}px}`,
    bad rates in percent.
  """
  epe, tepe = endpoint_error_maps(pred, gt, mask, crop=crop, mask_thr=mask_thr)
  out = _rates(epe, "epe", clamp_thr)
  out.update(_rates(tepe, "temp_epe", clamp_thr))
  return out


def gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
  """Normalised 1-D Gaussian window `[size]`, built in float32 like the reference."""
  coords = np.arange(size, dtype=_F32) - _F32(size // 2)
  g = np.exp(-(coords ** 2) / _F32(2 * sigma ** 2))
  return (g / g.sum(dtype=_F32)).astype(_F32)


def _gaussian_filter(a: np.ndarray, win: np.ndarray) -> np.ndarray:
  """Separable "valid" Gaussian filter over the last two axes (H then W)."""
  n = win.shape[0]
  for axis in (-2, -1):
    if a.shape[axis] >= n:
      view = np.lib.stride_tricks.sliding_window_view(a, n, axis=axis)
      a = view @ win
  return a


def ssim(x, y, data_range: float = 1.0, win_size: int = 11, win_sigma: float = 1.5,
         k: tuple[float, float] = (0.01, 0.03), nonnegative: bool = True) -> np.ndarray:
  """SSIM of each image (the reference `ssim.py`, per channel, no reduction).

  Args:
    x: `[..., H, W]` images.
    y: same shape.
    data_range: value range used for the constants C1, C2.
    win_size: Gaussian window size (odd).
    win_sigma: Gaussian sigma.
    k: `(K1, K2)`.
    nonnegative: apply ReLU to each image's SSIM.

  Returns:
    `[...]` float64 mean SSIM map value of each image.
  """
  x = np.asarray(x, dtype=np.float64)
  y = np.asarray(y, dtype=np.float64)
  _check_same(("x", "y"), (x, y))
  if win_size % 2 != 1:
    raise ValueError(f"Window size should be odd, got {win_size}")
  win = gaussian_window(win_size, win_sigma).astype(np.float64)
  c1, c2 = (k[0] * data_range) ** 2, (k[1] * data_range) ** 2
  mu1, mu2 = _gaussian_filter(x, win), _gaussian_filter(y, win)
  s11 = _gaussian_filter(x * x, win) - mu1 ** 2
  s22 = _gaussian_filter(y * y, win) - mu2 ** 2
  s12 = _gaussian_filter(x * y, win) - mu1 * mu2
  cs_map = (2 * s12 + c2) / (s11 + s22 + c2)
  ssim_map = (2 * mu1 * mu2 + c1) / (mu1 ** 2 + mu2 ** 2 + c1) * cs_map
  val = ssim_map.reshape(*ssim_map.shape[:-2], -1).mean(-1)
  return np.maximum(val, 0.0) if nonnegative else val


def disparity_to_depth(disp, scale: float) -> np.ndarray:
  """`scale / max(disp, 1e-10)` in float32 (NaN stays NaN); `scale` finite and positive."""
  scale = _check_scale(scale)
  d = np.asarray(disp, dtype=_F32)
  return _F32(scale) / np.maximum(d, _F32(1e-10))


def eval_tcc_sequence(pred_depth, gt_depth, mask, mask_thr: float = 0.5) -> float:
  """TCC: mean SSIM of masked absolute temporal depth differences.

  Args:
    pred_depth: `[T, H, W]` (or `[T, 1, H, W]`) predicted depth, T >= 2.
    gt_depth: same shape, GT depth.
    mask: same shape, validity mask.
    mask_thr: mask threshold.

  Returns:
    `(1/(T-1)) sum_t relu(SSIM(|x_t-x_{t+1}| dm_t, |y_t-y_{t+1}| dm_t))`.
  """
  x, y, m = _as_seq("pred_depth", pred_depth), _as_seq("gt_depth", gt_depth), _as_mask("mask", mask)
  _check_same(("pred_depth", "gt_depth", "mask"), (x, y, m))
  _need_two_frames(x)
  x, y = _mask_pair(x, y, m, mask_thr)
  x[np.isnan(x)] = 0
  dmask = m[:-1] * m[1:]
  a = np.abs(x[:-1] - x[1:]) * dmask
  b = np.abs(y[:-1] - y[1:]) * dmask
  return float(ssim(a, b, data_range=1.0, nonnegative=True).sum() / (x.shape[0] - 1))


def _need_two_frames(x: np.ndarray) -> None:
  if x.shape[0] < 2:
    raise ValueError(f"temporal consistency metrics need T >= 2 frames, got shape {x.shape}")


def _as_flows(name: str, f, t: int, hw: tuple[int, int]) -> np.ndarray:
  """`[t, 2, H, W]` float32 flows (a `[t, 1, 2, H, W]` batch axis is squeezed)."""
  f = np.asarray(f, dtype=_F32)
  if f.ndim == 5 and f.shape[1] == 1:
    f = f[:, 0]
  if f.shape != (t, 2, *hw):
    raise ValueError(f"{name} must have shape {(t, 2, *hw)}, got shape {f.shape}")
  _check_finite(name, f)
  return f


def _check_finite(name: str, a: np.ndarray) -> None:
  """ValueError naming the frames of `a` with NaN/inf values: the official metrics would
  score them as perfect (no bad pixels, zero photometric error)."""
  bad = ~np.isfinite(a).reshape(len(a), -1).all(axis=1)
  if bad.any():
    raise ValueError(f"{name} has NaN or inf values in frame(s) "
                     f"{np.flatnonzero(bad)[:10].tolist()}; the metrics would count them as "
                     "perfect")


def _check_no_valid_inf(name: str, gt: np.ndarray, mask: np.ndarray, mask_name: str) -> None:
  """ValueError naming the frames where `gt` is +-inf at a valid pixel (`mask` > 0.5): the
  official metrics would be inf (EPE) and 100 % bad; NaN there counts as 0, officially."""
  bad = (np.isinf(gt) & valid_pixels(mask)).reshape(len(gt), -1).any(axis=1)
  if bad.any():
    raise ValueError(f"{name} is infinite at valid pixels of {mask_name} in frame(s) "
                     f"{np.flatnonzero(bad)[:10].tolist()} (every EPE would be inf); mark them "
                     f"invalid in {mask_name}")


def tcm_flow_inputs(pred_depth, gt_depth, mask, t: int, mask_thr: float = 0.5):
  """The four images the official TCM feeds to RAFT for the pair `(t, t+1)`.

  Depths are min-max normalised with the GT frame t range, scaled to 0..255 and
  repeated to 3 channels.

  Returns:
    `(pred_t, pred_t1, gt_t, gt_t1)`, each `[3, H, W]` float32; flows are taken
    from `pred_t -> pred_t1` and `gt_t -> gt_t1`.
  """
  x, y, _ = _tcm_depths(pred_depth, gt_depth, mask, mask_thr)
  if not is_int(t) or not 0 <= t < len(x) - 1:
    # (a negative t took NumPy's wrapped frames: t=-1 paired the last frame with the first)
    raise ValueError(f"t must be a frame index in [0, {len(x) - 2}] (the pair t, t+1 of "
                     f"{len(x)} frames), got {t!r}")
  return _tcm_images(x, y, t)


def _tcm_depths(pred_depth, gt_depth, mask, mask_thr: float):
  """`(x, y, m)`: the masked predicted and GT depths TCM normalises, and the raw mask."""
  x, y, m = _as_seq("pred_depth", pred_depth), _as_seq("gt_depth", gt_depth), _as_mask("mask", mask)
  _check_same(("pred_depth", "gt_depth", "mask"), (x, y, m))
  return (*_mask_pair(x, y, m, mask_thr), m)


def _tcm_images(x: np.ndarray, y: np.ndarray, t: int):
  """`tcm_flow_inputs` of masked depths (`_tcm_depths`)."""
  dmax, dmin = y[t].max(), y[t].min()
  with np.errstate(divide="ignore", invalid="ignore"):
    imgs = [(a - dmin) / (dmax - dmin) * _F32(255.0) for a in (x[t], x[t + 1], y[t], y[t + 1])]
  return tuple(np.repeat(a[None], 3, axis=0) for a in imgs)


def eval_tcm_sequence(pred_flows, gt_flows, mask) -> float:
  """TCM: SSIM between the optical flows of predicted and GT depth videos.

  Args:
    pred_flows: `[T-1, 2, H, W]` flow between normalised predicted depths t, t+1
      (see `tcm_flow_inputs`; RAFT in the official code).
    gt_flows: `[T-1, 2, H, W]` same for the GT depth.
    mask: `[T, H, W]` (or `[T, 1, H, W]`) validity mask (used raw, not thresholded).

  Returns:
    `(1/(T-1)) sum_{t: sum M_t > 0} mean_c relu(SSIM(F^x_t,c M_t, F^y_t,c M_t))`
    with `M_t = m_t m_{t+1} [no GT flow channel > 250]`.
  """
  m = _as_mask("mask", mask)
  _need_two_frames(m)
  n = m.shape[0] - 1
  fx = _as_flows("pred_flows", pred_flows, n, m.shape[1:])
  fy = _as_flows("gt_flows", gt_flows, n, m.shape[1:])
  dmask = m[:-1] * m[1:]
  total = 0.0
  for i in range(n):
    sel = dmask[i] * ~np.any(fy[i] > _F32(250), axis=0)
    if sel.sum(dtype=np.float64) > 0:
      total += float(ssim(fx[i] * sel, fy[i] * sel, data_range=1.0, nonnegative=True).mean())
  return total / n


def flow_warp(x, flow) -> np.ndarray:
  """Backward warp `x_t(p + flow_t(p))` like the official `flow_warp`.

  torch `grid_sample` (bilinear, zero padding, align_corners=True), emulated in
  float32 with the same normalise / unnormalise round trip.

  Args:
    x: `[N, H, W]` or `[N, C, H, W]`.
    flow: `[N, 2, H, W]` (x, y) displacement in pixels.

  Returns:
    Warped `x`, same shape, float32.
  """
  x = np.asarray(x, dtype=_F32)
  flow = np.asarray(flow, dtype=_F32)
  squeeze = x.ndim == 3
  xc = x[:, None] if squeeze else x
  n, _, h, w = xc.shape
  if flow.shape != (n, 2, h, w):
    raise ValueError(f"flow shape {flow.shape} does not match input shape {x.shape}")
  gy, gx = np.meshgrid(np.arange(h, dtype=_F32), np.arange(w, dtype=_F32), indexing="ij")
  coords = []
  for g, f, size in ((gx, flow[:, 0], w), (gy, flow[:, 1], h)):
    norm = _F32(2.0) * (g + f) / _F32(max(size - 1, 1)) - _F32(1.0)
    coords.append((norm + _F32(1.0)) * (_F32(size - 1) / _F32(2.0)))
  out = _bilinear_zero_pad(xc, coords[0], coords[1])
  return out[:, 0] if squeeze else out


def _bilinear_zero_pad(img: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
  """Bilinear sample `[N, C, H, W]` at pixel coords `[N, H, W]`; zeros outside."""
  n, c, h, w = img.shape
  x0, y0 = np.floor(px), np.floor(py)
  wx, wy = px - x0, py - y0
  ex, sy = _F32(1.0) - wx, _F32(1.0) - wy
  corners = ((y0, x0, sy * ex), (y0, x0 + 1, sy * wx), (y0 + 1, x0, wy * ex),
             (y0 + 1, x0 + 1, wy * wx))
  out = np.zeros_like(img)
  bidx = np.arange(n)[:, None, None]
  for yy, xx, wgt in corners:
    inside = (xx >= 0) & (xx <= w - 1) & (yy >= 0) & (yy <= h - 1)
    xi = np.where(inside, xx, 0).astype(np.int64)
    yi = np.where(inside, yy, 0).astype(np.int64)
    vals = img[bidx, :, yi, xi]  # [N, H, W, C]
    vals = np.where(inside[..., None], vals, _F32(0.0))
    out = out + np.moveaxis(vals, -1, 1) * wgt[:, None]
  return out


def _warp_pairs(left_video, pred_depth, gt_depth, mask, flows, mask_thr: float):
  """Checks the inputs of OPW/RTC; returns `(T - 1, pairs)`, where `pairs` yields, for each
  pair of frames t, t + 1: the masked depth x_t, the warped x_{t+1}, the validity V_t and the
  depth masks. One pair at a time: the whole video's intermediates took ~100 MB a frame at
  1280x720 (T=40: 4.1 GB above the inputs), the same values frame by frame."""
  x, y, m = _as_seq("pred_depth", pred_depth), _as_seq("gt_depth", gt_depth), _as_mask("mask", mask)
  _check_same(("pred_depth", "gt_depth", "mask"), (x, y, m))
  _need_two_frames(x)
  video = _as_left_video(left_video, "left_video")
  if video.shape[0] != x.shape[0] or video.shape[2:] != x.shape[1:]:
    raise ValueError(f"left_video shape {video.shape} does not match depth shape {x.shape}")
  f = _as_flows("flows", flows, x.shape[0] - 1, x.shape[1:])
  x, y = _mask_pair(x, y, m, mask_thr)

  def pairs():
    for t in range(x.shape[0] - 1):
      # The depth and the image share one warp (same coordinates; per channel the same values).
      both = flow_warp(np.concatenate([x[t + 1:t + 2, None], video[t + 1:t + 2]], 1),
                       f[t:t + 1])[0]
      warped, warped_img = both[0], both[1:]
      diff = warped_img / _F32(255.0) - video[t] / _F32(255.0)
      sq = diff ** 2
      photo = np.sqrt(sq[0] + sq[1] + sq[2])
      flow_ok = (~np.any(f[t] > _F32(250), axis=0)).astype(_F32)
      weight = m[t] * m[t + 1] * np.exp(_F32(-50.0) * photo) * flow_ok * (
          warped > 0).astype(_F32)
      depth_ok = {k: ~(y[t] > _F32(k)) & ~(y[t + 1] > _F32(k)) for k in (30, 50, 100)}
      yield x[t], warped, weight > _F32(1e-2), depth_ok

  return x.shape[0] - 1, pairs()


def _as_left_video(video, name: str = "video") -> np.ndarray:
  """`[T, 3, H, W]` left video from `[T, 3, H, W]` or a stereo `[T, 2, 3, H, W]`; a
  channels-last video (`[T, H, W, 3]`, the layout `predict_video` takes) is refused with the
  `np.moveaxis` that makes it channels first."""
  v = np.asarray(video, dtype=_F32)
  left = v[:, 0] if v.ndim == 5 else v
  if left.ndim != 4 or left.shape[1] != 3:
    hint = ""
    if left.ndim == 4 and left.shape[-1] == 3:
      hint = (f"; channels last (the layout predict_video takes)? pass "
              f"np.moveaxis({name}, -1, {v.ndim - 3})")
    raise ValueError(f"{name} must be [T, 3, H, W] or [T, 2, 3, H, W], got shape "
                     f"{v.shape}{hint}")
  return left


def _check_video_values(video, name: str) -> None:
  """Warns if `video` does not look like RGB 0..255 (float frames no brighter than ~1, as
  0..1 images, or values well outside 0..255): OPW/RTC's photometric weight
  exp(-50 ||warp(I_{t+1}) - I_t|| / 255) assumes 0..255 (0..1 frames keep nearly every
  pixel). As `sav_jax.inference.check_video_values` warns for the model's frames.

  Raises ValueError for NaN/inf values in the left view (the one OPW/RTC use), naming its
  frames: the photometric weight would be NaN there and OPW and RTC 0 without a word."""
  v = widened(np.asarray(video))  # bfloat16 (JAX's) as float32
  if v.dtype == np.uint8 or v.dtype.kind not in "uif" or v.size == 0:
    return
  if v.dtype.kind == "f" and v.ndim:
    bad = nonfinite_frames(v[:, 0] if v.ndim == 5 else v)
    if bad.size:
      raise ValueError(f"{name} has NaN or inf values in frame(s) {bad[:10].tolist()}; OPW "
                       "and RTC would be 0 (their photometric weight NaN)")
  lo, hi = float(v.min()), float(v.max())
  if not (np.isfinite(lo) and np.isfinite(hi)):
    return  # NaN/inf in the right view of a stereo video, which no metric reads
  looks, spread = float_frames_range(v, lo, hi)
  if v.dtype.kind == "f" and looks == "0..1":
    warnings.warn(f"{name}: float frames with values {lo:g}..{hi:g}{spread}: OPW and RTC expect "
                  f"RGB 0..255 ({unit_range_advice(lo)}); their photometric weight would "
                  "keep nearly every pixel", stacklevel=caller_stacklevel())
  elif looks in ("negative", "16-bit"):  # well outside (a resize's overshoot is not)
    fix = ("negative values are no image's: put back a normalisation's mean and scale"
           if looks == "negative" else "divide 16-bit frames by 257")
    warnings.warn(f"{name}: values {lo:g}..{hi:g}, outside 0..255, which OPW and RTC expect "
                  f"(RGB 0..255; {fix})", stacklevel=caller_stacklevel())


def _frame_ratio(num: np.ndarray, sel: np.ndarray) -> float:
  """One frame's term of `(1/n) sum_{t: sum sel_t > 0} sum(num_t * sel_t) / sum(sel_t)`."""
  cnt = np.count_nonzero(sel)
  return float(np.sum(num * sel, dtype=np.float64)) / cnt if cnt > 0 else 0.0


def eval_opw_sequence(left_video, pred_depth, gt_depth, mask, flows, mask_thr: float = 0.5):
  """OPW: flow-warping error of the predicted depth.

  Args:
    left_video: `[T, 3, H, W]` (or stereo `[T, 2, 3, H, W]`) RGB 0..255.
    pred_depth: `[T, H, W]` (or `[T, 1, H, W]`) predicted depth.
    gt_depth: same shape, GT depth (only for the <= 30/50/100 depth masks).
    mask: same shape, validity mask.
    flows: `[T-1, 2, H, W]` optical flow of the left video, frame t -> t+1.
    mask_thr: mask threshold.

  Returns:
    `(opw, opw_30, opw_50, opw_100)`.

  Warns (UserWarning): `left_video` does not look like RGB 0..255 (e.g. 0..1 floats).

  Raises (ValueError): NaN or inf values in the left view of `left_video`.
  """
  _check_video_values(left_video, "left_video")
  return _opw_rtc(left_video, pred_depth, gt_depth, mask, flows, mask_thr)[0]


def eval_rtc_sequence(left_video, pred_depth, gt_depth, mask, flows, mask_thr: float = 0.5,
                      tau: float = 1.01):
  """RTC: share of flow-consistent pixels whose depth ratio to the warp is < tau.

  Args:
    left_video: `[T, 3, H, W]` (or stereo `[T, 2, 3, H, W]`) RGB 0..255.
    pred_depth: `[T, H, W]` (or `[T, 1, H, W]`) predicted depth.
    gt_depth: same shape, GT depth (only for the <= 30 depth mask).
    mask: same shape, validity mask.
    flows: `[T-1, 2, H, W]` optical flow of the left video, frame t -> t+1.
    mask_thr: mask threshold.
    tau: ratio threshold (strict `<`).

  Returns:
    `(rtc, rtc_30)`.

  Warns (UserWarning): `left_video` does not look like RGB 0..255 (e.g. 0..1 floats).

  Raises (ValueError): NaN or inf values in the left view of `left_video`.
  """
  _check_video_values(left_video, "left_video")
  return _opw_rtc(left_video, pred_depth, gt_depth, mask, flows, mask_thr, tau)[1]


def _opw_rtc(left_video, pred_depth, gt_depth, mask, flows, mask_thr: float = 0.5,
             tau: float = 1.01):
  """`((opw, opw_30, opw_50, opw_100), (rtc, rtc_30))` from one pass of warps (each pair of
  frames is warped once for both metrics)."""
  n, pairs = _warp_pairs(left_video, pred_depth, gt_depth, mask, flows, mask_thr)
  opw, rtc = [0.0] * 4, [0.0] * 2
  for x, warped, valid, depth_ok in pairs:
    err = np.abs(warped - x)
    for j, sel in enumerate((valid, *(valid & depth_ok[k] for k in (30, 50, 100)))):
      opw[j] += _frame_ratio(err, sel)
    with np.errstate(divide="ignore", invalid="ignore"):
      r1 = x / warped
      r2 = warped / x
    r1[np.isinf(r1)] = _F32(-1e10)
    r2[np.isinf(r2)] = _F32(-1e10)
    good = (np.maximum(r1, r2) < _F32(tau)).astype(np.float64)
    rtc[0] += _frame_ratio(good, valid)
    rtc[1] += _frame_ratio(good, valid & depth_ok[30])
  return tuple(float(v / n) for v in opw), tuple(float(v / n) for v in rtc)


def _flow_from_fn(flow_fn: FlowFn, img1: np.ndarray, img2: np.ndarray, what: str) -> np.ndarray:
  """`flow_fn(img1, img2)` as a `[2, H, W]` float32 flow (a `[1, 2, H, W]` batch axis is
  dropped); ValueError naming `flow_fn` and `what` (the frames) for another shape (with the
  `np.moveaxis` of a channels-last `[H, W, 2]` one) or NaN/inf values."""
  f = np.asarray(flow_fn(img1, img2), _F32)
  hw = img1.shape[1:]
  if f.shape == (1, 2, *hw):
    f = f[0]
  if f.shape != (2, *hw):
    hint = ""
    if f.shape == (*hw, 2):
      hint = ("; channels last, as sav_jax.model.raft.raft_flow returns it? return "
              "np.moveaxis(flow, -1, 0) (sav_jax.model.raft.raft_flow_fn does)")
    raise ValueError(f"flow_fn must return a [2, H, W] flow, here {(2, *hw)}, for two [3, H, W] "
                     f"images; for {what} it returned shape {f.shape}{hint}")
  if not np.isfinite(f).all():
    raise ValueError(f"flow_fn returned NaN or inf values for {what}; the metrics would count "
                     "them as perfect")
  return f


def _video_flows(v: np.ndarray, flow_fn: FlowFn) -> np.ndarray:
  """`video_flows_from_fn` of a checked `[T, 3, H, W]` left video."""
  return np.stack([_flow_from_fn(flow_fn, v[i], v[i + 1], f"the left video frames {i}, {i + 1}")
                   for i in range(v.shape[0] - 1)])


def video_flows_from_fn(left_video, flow_fn: FlowFn) -> np.ndarray:
  """`[T-1, 2, H, W]` flows `flow_fn(I_t, I_{t+1})` of the left video (`compute_flow`).

  Raises:
    ValueError: `left_video` is not `[T, 3, H, W]` / `[T, 2, 3, H, W]` (channels last is
      named, with its `np.moveaxis`) or has one frame (T < 2), or `flow_fn` returned another
      shape than `[2, H, W]` or NaN/inf; NaN/inf values in the left view of `left_video`.

  Warns (UserWarning): `left_video` does not look like RGB 0..255 (e.g. 0..1 floats).
  """
  v = _as_left_video(left_video, "left_video")
  _need_two_frames(v)  # (one frame: numpy's "need at least one array to stack")
  _check_video_values(left_video, "left_video")
  return _video_flows(v, flow_fn)


def depth_flows_from_fn(pred_depth, gt_depth, mask, flow_fn: FlowFn, mask_thr: float = 0.5):
  """`(pred_flows, gt_flows)`, each `[T-1, 2, H, W]`, as the official TCM computes them.

  A pair of frames without a valid pixel in common, which TCM skips, gets zero flows
  without running `flow_fn` (the official code runs RAFT on its 0/0 inputs and drops the
  NaN flows).

  Raises:
    ValueError: a pair TCM uses whose GT frame t has one depth over the whole frame, so
      that the normalisation divides by zero (the official TCM would be NaN); `flow_fn`
      returned another shape than `[2, H, W]` (a channels-last one is named) or NaN/inf.
  """
  x, y, m = _tcm_depths(pred_depth, gt_depth, mask, mask_thr)
  _need_two_frames(x)
  fx, fy = [], []
  for i in range(x.shape[0] - 1):
    if not (m[i] * m[i + 1]).sum(dtype=np.float64) > 0:  # skipped by eval_tcm_sequence
      fx.append(np.zeros((2, *x.shape[1:]), _F32))
      fy.append(fx[-1])
      continue
    if y[i].max() == y[i].min():
      raise ValueError(f"TCM: the GT depth of frame {i} is {y[i].max()} at every pixel (masked "
                       "pixels count as 0), so its min-max normalisation divides by zero (the "
                       "official TCM would be NaN)")
    x0, x1, y0, y1 = _tcm_images(x, y, i)
    fx.append(_flow_from_fn(flow_fn, x0, x1, f"the predicted depth frames {i}, {i + 1}"))
    fy.append(_flow_from_fn(flow_fn, y0, y1, f"the GT depth frames {i}, {i + 1}"))
  return np.stack(fx), np.stack(fy)


def eval_batch(pred, gt, mask, *, scale: float | None = None, left_video=None,
               video_flows=None, depth_flows=None,
               flow_fn: FlowFn | None = None) -> tuple[dict[str, float], int]:
  """The official `eval_batch`: all metrics of one sequence, no pre-processing.

  Args:
    pred: `[T, H, W]` (or `[T, 1, H, W]`) predicted disparity.
    gt: same shape, GT disparity.
    mask: same shape, validity mask (`disparity_mask`).
    scale: depth-to-disparity scale (a finite positive number); None skips every depth
      metric.
    left_video: `[T, 3, H, W]` or `[T, 2, 3, H, W]` (channels first), RGB 0..255, needed
      for OPW/RTC.
    video_flows: `[T-1, 2, H, W]` left-video flows (else from `flow_fn`).
    depth_flows: `(pred_flows, gt_flows)` for TCM (else from `flow_fn`).
    flow_fn: optical flow `(img1 [3,H,W], img2 [3,H,W]) -> [2,H,W]` (RAFT:
      `sav_jax.model.raft.raft_flow_fn`).

  Returns:
    `({"disp_epe_mean", ..., "disp_TCC", "disp_TCM", "disp_OPW", "disp_OPW_{100,50,30}",
    "disp_RTC", "disp_RTC_30"}, T)`. TCM is left out without flows for it, OPW/RTC
    without a video or flows.

  Warns:
    UserWarning: an input given but unused, naming what is missing (`left_video`,
      `video_flows`, `depth_flows` or `flow_fn` without `scale`; `left_video` without
      `video_flows` / `flow_fn`; `video_flows` without `left_video`), or a `left_video`
      that does not look like RGB 0..255 (e.g. 0..1 floats).
    NotMeasuredWarning: no pixel of `mask` above 0.5 (every EPE/TEPE value 0), one frame
      (TEPE 0), or, with depth metrics, frame pairs without a pixel valid in both (scored
      TCC 1, TCM/OPW/RTC 0): the official rule's numbers, which measure nothing there, are
      returned (`not_measured_note`; where no pair is measured, the official evaluator stops
      with an error instead).
  """
  return _eval_batch(pred, gt, mask, scale, left_video, video_flows, depth_flows, flow_fn,
                     _BATCH_NAMES)


# The argument names of `eval_batch` / `eval_sequence`, for their warnings and errors.
_BATCH_NAMES = {"mask": "mask", "video": "left_video", "flows": "video_flows"}
_SEQUENCE_NAMES = {"mask": "valid", "video": "video", "flows": "flows"}


def _unused_inputs(scale, video, flows, depth_flows, flow_fn, names) -> str | None:
  """The warning for given inputs that no metric uses (and what is missing), or None."""
  given = [n for n, v in ((names["video"], video), (names["flows"], flows),
                          ("depth_flows", depth_flows), ("flow_fn", flow_fn)) if v is not None]
  if scale is None:
    if not given:
      return None
    return (f"{', '.join(given)} given but no scale: TCC, TCM, OPW and RTC (depth metrics) not "
            "computed, only EPE and TEPE; pass scale= (the depth-to-disparity scale, "
            "fx * baseline)")
  if video is not None and flows is None and flow_fn is None:
    return (f"{names['video']} given but no {names['flows']}/flow_fn: OPW and RTC not computed "
            f"(pass {names['flows']}= [T-1, 2, H, W] or flow_fn=)")
  if flows is not None and video is None:
    return (f"{names['flows']} given but no {names['video']}: OPW and RTC not computed (pass "
            f"{names['video']}= [T, 3, H, W], RGB 0..255)")
  return None


def valid_pixels(mask) -> np.ndarray:
  """The pixels the metrics count as valid: `mask > 0.5` (the official threshold), bool."""
  return np.asarray(mask) > _F32(0.5)


def any_valid(mask) -> bool:
  """Whether any pixel of `mask` is valid (`valid_pixels`)."""
  return bool(np.any(valid_pixels(mask)))


def not_measured_note(mask, metric_keys: Iterable[str] = (), mask_name: str = "valid"
                      ) -> str | None:
  """What the official scores of a sequence do not measure, or None: no valid pixel (every
  score), one frame or no pixel valid in two consecutive frames (TEPE and δt), or, where depth
  metrics are among `metric_keys` (`"disp_TCC"`, `"disp_TCM"`, `"disp_OPW"`), frame pairs
  without a pixel valid in both, which the official rule scores as measurements (TCC 1, TCM 0,
  OPW 0, RTC 0) in the sequence's mean over its pairs. Exact for binary masks: valid is
  `valid_pixels` (> 0.5); TCC weights fractional masks as they are, and the flow metrics'
  own selections (occlusion, large flows) may leave out more pixels than are named here.

  Args:
    mask: `[T, H, W]` (or `[T, 1, H, W]`) validity mask (valid: > 0.5).
    metric_keys: the metrics computed (a result dict's keys will do).
    mask_name: the mask's name in the text.
  """
  m = valid_pixels(mask)
  keys = set(metric_keys)
  depth = ", ".join(text for key, text in (
      ("disp_TCC", "TCC 1 (perfect)"), ("disp_TCM", "TCM 0 (worst)"),
      ("disp_OPW", "OPW 0 (perfect)"), ("disp_OPW", "RTC 0 (worst)")) if key in keys)
  # The official evaluator's TCM and OPW/RTC average over the pairs they measure: with none
  # it stops with an error (TypeError) rather than score the sequence.
  stops = ("; the official evaluator stops with an error on such a sequence (its TCM/OPW "
           "measure no pair)") if keys & {"disp_TCM", "disp_OPW"} else ""
  if not np.any(m):
    scores = ", ".join(["EPE, TEPE and their bad-pixel rates 0 (perfect)"] + [depth] * bool(depth))
    return (f"{mask_name} has no pixel > 0.5 (no valid ground truth): the official rule scores "
            f"{scores}, though nothing was measured{stops}")
  if m.shape[0] == 1:
    return ("one frame (T=1), no frame pair: the official rule scores TEPE and its bad-pixel "
            "rates (δt) 0, though nothing was measured")
  if no_valid_pair(m):
    return (f"{mask_name} has no pixel valid in two consecutive frames (TEPE's pairs): the "
            "official rule scores TEPE and its bad-pixel rates (δt) 0"
            + (f", and every pair {depth}" if depth else "")
            + f", though nothing was measured{stops}")
  m = m.reshape(m.shape[0], -1)
  empty = int(np.sum(~np.any(m[:-1] & m[1:], axis=1)))
  if empty and depth:
    return (f"{empty} of the {m.shape[0] - 1} frame pairs {'has' if empty == 1 else 'have'} no "
            "pixel valid in both frames: "
            f"the official rule scores each such pair {depth} in the sequence's mean over "
            "its pairs, though nothing was measured there")
  return None


def no_valid_pair(mask) -> bool:
  """Whether no pixel of `[T, H, W]` `mask` is valid (> 0.5) in two consecutive frames, so
  that TEPE (weighted by `mask_t * mask_{t+1}`) measures nothing (T >= 2)."""
  m = valid_pixels(mask)
  return m.shape[0] >= 2 and not np.any(m[:-1] & m[1:])


def _eval_batch(pred, gt, mask, scale, video, flows, depth_flows, flow_fn,
                names) -> tuple[dict[str, float], int]:
  """`eval_batch`; `names` (`_BATCH_NAMES` / `_SEQUENCE_NAMES`): the caller's argument names."""
  x, y, m = _as_seq("pred", pred), _as_seq("gt", gt), _as_mask(names["mask"], mask)
  _check_same(("pred", "gt", names["mask"]), (x, y, m))
  _check_finite("pred", x)  # GT may hold NaN (masked out), a prediction may not
  _check_no_valid_inf("gt", y, m, names["mask"])
  if scale is not None:
    scale = _check_scale(scale)
  if depth_flows is not None:
    _check_depth_flows(depth_flows)
  unused = _unused_inputs(scale, video, flows, depth_flows, flow_fn, names)
  warp = scale is not None and video is not None and (flows is not None or flow_fn is not None)
  if video is not None:  # its layout also where no metric uses it (flows or scale missing):
    left = _as_left_video(video, names["video"])  # it was refused only once they were added
  if warp:  # checked before any flow is computed
    _check_video_values(video, names["video"])
  res = {f"disp_{k}": v for k, v in eval_endpoint_error_sequence(x, y, m).items()}
  if scale is not None:
    zx, zy = disparity_to_depth(x, scale), disparity_to_depth(y, scale)
    res["disp_TCC"] = eval_tcc_sequence(zx, zy, m)
    if depth_flows is None and flow_fn is not None:
      depth_flows = depth_flows_from_fn(zx, zy, m, flow_fn)
    if depth_flows is not None:
      res["disp_TCM"] = eval_tcm_sequence(depth_flows[0], depth_flows[1], m)
    if warp:
      if flows is None:
        flows = _video_flows(left, flow_fn)
      opw, rtc = _opw_rtc(left, zx, zy, m, flows)
      res.update(zip(("disp_OPW", "disp_OPW_30", "disp_OPW_50", "disp_OPW_100"), opw))
      res.update(zip(("disp_RTC", "disp_RTC_30"), rtc))
  note = not_measured_note(m, res, names["mask"])
  if note:
    warnings.warn(f"{note}; the official rule's numbers are returned", NotMeasuredWarning,
                  stacklevel=caller_stacklevel())
  if unused:
    warnings.warn(unused, stacklevel=caller_stacklevel())
  return res, x.shape[0]


def eval_sequence(pred, gt, valid, flows=None, *, scale: float | None = None, video=None,
                  depth_flows=None, flow_fn: FlowFn | None = None) -> dict[str, float]:
  """The evaluator's per-sequence step: pre-processing, then `eval_batch`.

  GT becomes `|gt|` and the prediction is multiplied by `round(valid)`.

  Args:
    pred: `[T, H, W]` (or `[T, 1, H, W]`) predicted disparity.
    gt: same shape, GT disparity (any sign; NaNs allowed).
    valid: same shape, validity mask.
    flows: `[T-1, 2, H, W]` left-video flows for OPW/RTC (with `video` and `scale`).
    scale: depth-to-disparity scale (a finite positive number); None skips the depth
      metrics (TCC, TCM, OPW, RTC).
    video: `[T, 3, H, W]` left or `[T, 2, 3, H, W]` stereo video, channels first (for
      `predict_video`'s `[T, H, W, 3]` frames: `np.moveaxis(frames, -1, 1)`), RGB 0..255.
    depth_flows: `(pred_flows, gt_flows)` for TCM.
    flow_fn: optical flow function used for whatever flows are not given,
      `(img1 [3, H, W], img2 [3, H, W]) -> [2, H, W]` (`sav_jax.model.raft.raft_flow_fn`).

  Returns:
    The metric dict of `eval_batch` (its frame count is `len(pred)`).

  Warns:
    UserWarning: an input given but unused, naming what is missing (e.g. `video` or `flows`
      without `scale`: only EPE/TEPE; `video` without `flows` / `flow_fn`: no OPW/RTC), or
      a `video` that does not look like RGB 0..255 (e.g. 0..1 floats).
    NotMeasuredWarning: no pixel of `valid` above 0.5 (every EPE/TEPE value 0), one frame
      (TEPE 0), or, with depth metrics, frame pairs without a pixel valid in both (scored
      TCC 1, TCM/OPW/RTC 0): the official rule's numbers, which measure nothing there, are
      returned (`not_measured_note`; where no pair is measured, the official evaluator stops
      with an error instead).
  """
  x, y, m = _as_seq("pred", pred), _as_seq("gt", gt), _as_mask("valid", valid)
  _check_same(("pred", "gt", "valid"), (x, y, m))
  res, _ = _eval_batch(x * np.round(m), np.abs(y), m, scale, video, flows, depth_flows, flow_fn,
                       _SEQUENCE_NAMES)
  return res


def aggregate(results: Sequence[tuple[dict[str, float], int]]) -> dict[str, float]:
  """Frame-weighted mean over sequences (official `aggregate_eval_results`).

  Args:
    results: `(metrics, T)` per sequence, as returned by `eval_batch`.

  Returns:
    `{k: sum_s metrics_s[k] * T_s / sum_s T_s}`. A metric missing from some
    sequences is summed where present but still divided by the total frame count
    (as in the official code).
  """
  total = 0
  sums: dict[str, float] = {}
  for i, item in enumerate(results):
    if not (isinstance(item, (tuple, list)) and len(item) == 2 and isinstance(item[0], Mapping)
            and is_int(item[1]) and item[1] >= 1):
      raise ValueError(f"aggregate: item {i} must be a (metrics dict, frame count >= 1) pair, "
                       f"as eval_batch returns, got {type(item).__name__} {str(item)[:80]}")
    metrics, length = item
    total += int(length)
    for k, v in metrics.items():
      sums[k] = sums.get(k, 0.0) + float(np.asarray(v, np.float64).reshape(())) * length
  if total == 0:
    return {}
  return {k: v / total for k, v in sums.items()}

"""The official Stereo Any Video training loss and its logging metrics.

The official trainer (`train_stereoanyvideo.py: forward_batch` and
`train_utils/losses.py: sequence_loss`) computes, for every frame t of a clip,

  L_t = sum_n w_n * mean_{valid pixels of frame t} |pred_n - d_gt|,
  w_n = g ** (N - 1 - n),  g = gamma ** (15 / (N - 1))   (w = 1 when N == 1),
  valid = (valid_gt >= 0.5) & (|d_gt| < max_disparity)    (max_disparity = 700),

over the N = iters//2 + iters//2 + iters full-resolution predictions of the
1/16, 1/8 and 1/4 stages, and the loss is `(1/T) sum_t L_t`. There is no
temporal term. The mean of frame t is taken over the pixels of all clips that the
call sees: the official script runs one clip per GPU (`--batch_size 1`) and DDP
averages the per-GPU losses, so by default (`per_sample=True`) we compute the loss
of each clip on its own and average over clips; `per_sample=False` pools the valid
pixels of the whole batch per frame, as `sequence_loss` does for a batch on one GPU.

One deliberate difference: a frame with no valid pixel contributes 0 to the loss here,
where PyTorch's mean of an empty selection gives NaN.

Metrics (official `sequence_loss`, last prediction, per frame, then averaged over
frames and clips): `epe` is the mean |pred - gt| over valid pixels; `1px`, `3px`,
`5px` are the fractions of valid pixels with error *below* 1, 3, 5 px. They average
over the frames that have a valid pixel (officially NaN otherwise): a frame without one
(sparse ground truth outside the crop) would read as a perfect epe of 0 and the worst
accuracy, 0; `measured_frames` is the share of frames that have one (0 in a batch
without any valid pixel, whose metrics are then 0).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

MAX_DISPARITY = 700.0
LOSS_GAMMA = 0.9
# The metrics that are means over the frames with a valid pixel (`measured_frames` their
# share): means of them over several batches weight each by that share.
MEASURED_METRICS = ("epe", "1px", "3px", "5px")


def prediction_weights(num_predictions: int, gamma: float = LOSS_GAMMA) -> jax.Array:
  """Weights `w_n` of the N predictions, `[N]` float32 (the last one gets 1)."""
  if num_predictions < 1:
    raise ValueError(f"need at least one prediction, got {num_predictions}")
  if num_predictions == 1:
    return jnp.ones((1,), jnp.float32)
  adjusted = gamma ** (15.0 / (num_predictions - 1))
  exponents = jnp.arange(num_predictions - 1, -1, -1, dtype=jnp.float32)
  return jnp.asarray(adjusted, jnp.float32) ** exponents


def valid_mask(disparity: jax.Array, valid: jax.Array,
               max_disparity: float = MAX_DISPARITY) -> jax.Array:
  """Pixels used by the loss: `valid >= 0.5` and `|d| < max_disparity` (NaN excluded).

  Args:
    disparity: `[B, T, H, W]` ground-truth disparity (positive).
    valid: `[B, T, H, W]` bool or float validity.
    max_disparity: the official cut for very large disparities.

  Returns:
    `[B, T, H, W]` bool.
  """
  return (valid.astype(jnp.float32) >= 0.5) & (jnp.abs(disparity) < max_disparity)


def _frame_means(values: jax.Array, mask: jax.Array, per_sample: bool) -> jax.Array:
  """Masked means over pixels (and over clips unless `per_sample`).

  Args:
    values: `[..., B, T, H, W]`.
    mask: `[B, T, H, W]` bool.
    per_sample: average per clip (`[..., B, T]`) or pool the clips (`[..., T]`).

  Returns:
    The means; 0 where a frame has no valid pixel.
  """
  axes = (-2, -1) if per_sample else (-4, -2, -1)
  m = jnp.broadcast_to(mask, values.shape)
  total = jnp.sum(jnp.where(m, values, 0.0), axis=axes)
  count = jnp.sum(m, axis=axes, dtype=jnp.float32)
  return jnp.where(count > 0, total / jnp.maximum(count, 1.0), 0.0)


def _over_measured(frame_means: jax.Array, measured: jax.Array) -> jax.Array:
  """The mean of `frame_means` over the frames where `measured` (0 where none is)."""
  count = jnp.sum(measured, dtype=jnp.float32)
  return jnp.sum(jnp.where(measured, frame_means, 0.0)) / jnp.maximum(count, 1.0)


def sequence_loss(predictions: jax.Array, disparity: jax.Array, valid: jax.Array, *,
                  gamma: float = LOSS_GAMMA, max_disparity: float = MAX_DISPARITY,
                  per_sample: bool = True) -> tuple[jax.Array, dict[str, jax.Array]]:
  """Official SAV training loss and metrics.

  Args:
    predictions: `[N, B, T, H, W]` disparities of every refinement step (the
      model's `out.disparities`, positive = disparity).
    disparity: `[B, T, H, W]` positive ground-truth disparity.
    valid: `[B, T, H, W]` bool or float validity of the ground truth.
    gamma: base decay, adjusted to N as in the official code.
    max_disparity: pixels with `|d| >= max_disparity` are ignored.
    per_sample: normalise per clip, then average over clips (official DDP with one
      clip per GPU); else pool the batch's valid pixels per frame.

  Returns:
    `(loss, metrics)`: scalar float32 loss and a dict of scalars `epe`, `1px`, `3px`,
    `5px` (fractions; means over the frames with a valid pixel), `measured_frames` (the
    share of frames with one) and `valid_fraction`.
  """
  predictions = predictions.astype(jnp.float32)
  disparity = disparity.astype(jnp.float32)
  mask = valid_mask(disparity, valid, max_disparity)
  err = jnp.abs(predictions - disparity[None])                   # [N, B, T, H, W]
  per_frame = _frame_means(err, mask, per_sample)                 # [N, B, T] or [N, T]
  weights = prediction_weights(predictions.shape[0], gamma)
  weighted = jnp.einsum("n,n...->...", weights, per_frame)        # [B, T] or [T]
  loss = jnp.mean(weighted)
  last = err[-1]
  frame_valid = jnp.any(mask, axis=(-2, -1))                      # [B, T]
  measured = frame_valid if per_sample else jnp.any(frame_valid, axis=0)  # [B, T] or [T]
  metrics = {"epe": _over_measured(_frame_means(last, mask, per_sample), measured)}
  for tau in (1, 3, 5):
    below = (last < tau).astype(jnp.float32)
    metrics[f"{tau}px"] = _over_measured(_frame_means(below, mask, per_sample), measured)
  # (per clip, also when the batch is pooled: the share of the batch's frames)
  metrics["measured_frames"] = jnp.mean(frame_valid.astype(jnp.float32))
  metrics["valid_fraction"] = jnp.mean(mask.astype(jnp.float32))
  return loss, metrics

"""Periodic validation on a fixed held-out set with the official metrics (EPE, TEPE)."""

from __future__ import annotations

import logging
import warnings

import jax
import numpy as np
from jax.experimental import multihost_utils

from sav_jax import metrics as sav_metrics
from sav_jax._checks import plural
from sav_jax.data import pipeline
from train import input as input_lib
from train import state as state_lib
from train import step as step_lib

log = logging.getLogger(__name__)

# Official evaluator keys -> short names in the logs.
_NAMES = {"disp_epe_mean": "epe", "disp_temp_epe_mean": "tepe",
          "disp_epe_bad_1px": "bad_1px", "disp_epe_bad_3px": "bad_3px",
          "disp_temp_epe_bad_1px": "temp_bad_1px"}


class Evaluator:
  """Runs the model on the held-out clips and reports official metrics.

  Every process holds all clips (a small set) and feeds its slice of each batch; the
  predictions are gathered so that every process computes the same numbers.

  Args:
    config: training config (`eval.*`, `data.*`).
    model: `sav_jax.StereoAnyVideo`.
    params_sharding: sharding tree of the params.
    mesh: device mesh.
    clips: the held-out clips, if already read (`measured_clips(input_lib.eval_clips(config),
      ...)`, as `python -m train` reads them before the workdir is created).
  """

  def __init__(self, config, model, params_sharding, mesh, clips=None):
    ev = config.eval
    batch_size = ev.batch_size
    parts = state_lib.data_devices(mesh)  # (a mesh's other axes hold copies)
    if batch_size % parts:
      raise ValueError(f"eval.batch_size={batch_size} is not divisible by the {parts} devices "
                       f"of the mesh's {state_lib.DATA_AXIS!r} axis")
    self.clips = (measured_clips(input_lib.eval_clips(config), ev.dataset) if clips is None
                  else clips)
    self.batches = pipeline.eval_batches(self.clips, batch_size)
    self.predict = step_lib.make_eval_fn(model, ev.iters, params_sharding, mesh)
    self.sharding = state_lib.data_sharding(mesh)
    frames = sorted({len(c["left"]) for c in self.clips})
    # Clips of `frames` frames (data.frames, centre-cropped to data.crop): their EPE is not
    # `python -m eval`'s, which runs whole sequences at full size in 20-frame windows.
    self.described = (f"{plural(len(self.clips), 'clip')} of {ev.dataset} ("
                      f"{'/'.join(map(str, frames))} frames), {ev.iters} iterations")
    log.info("validation: %s", self.described)

  def _global(self, array: np.ndarray) -> jax.Array:
    """The whole batch (every process holds it) as a global array: each device gets its
    rows by its place in the sharding, whatever the processes' device order (a TPU pod's
    hosts hold non-contiguous device ids; taking rows by process index placed other clips
    than those scored against, silently)."""
    with jax.transfer_guard_host_to_device("allow"):  # the intended copy, as to_global's
      return jax.make_array_from_callback(array.shape, self.sharding, lambda i: array[i])

  def predictions(self, params) -> list[np.ndarray]:
    """Final disparities `[T, H, W]` of every held-out clip."""
    out = []
    for batch, n in self.batches:
      left, right = self._global(batch["left"]), self._global(batch["right"])
      pred = self.predict(params, left, right)
      if jax.process_count() > 1:
        with jax.transfer_guard("allow"):  # its copies are the point (implicit in it)
          pred = multihost_utils.process_allgather(pred, tiled=True)
      pred = np.asarray(jax.device_get(pred))
      out.extend(pred[:n])
    return out

  def __call__(self, params) -> dict[str, float]:
    """Frame-weighted means over the clips (official aggregation); NaN, with a warning,
    where a prediction holds NaN or inf (diverged weights: the run goes on, as with a
    finite loss)."""
    preds = self.predictions(params)
    diverged = [i for i, pred in enumerate(preds) if not np.all(np.isfinite(pred))]
    if diverged:
      if jax.process_index() == 0:
        log.warning("validation: the predictions of %d of the %d clips hold NaN or inf "
                    "(the weights diverged?): the scores are NaN", len(diverged), len(preds))
      return {short: float("nan") for short in _NAMES.values()}
    results = []
    with warnings.catch_warnings():  # said once, when the clips were chosen
      warnings.simplefilter("ignore", sav_metrics.NotMeasuredWarning)
      for pred, clip in zip(preds, self.clips):
        res = sav_metrics.eval_sequence(pred, clip["disparity"],
                                        clip["valid"].astype(np.float32))
        results.append((res, pred.shape[0]))
    agg = sav_metrics.aggregate(results)
    return {short: agg[key] for key, short in _NAMES.items() if key in agg}


def measured_clips(clips: list[dict], dataset: str) -> list[dict]:
  """The clips with a valid ground-truth pixel: one without (sparse ground truth outside the
  crop) would score a perfect 0 by the official rule, so it is left out, with a warning; the
  others' partial gaps (`metrics.not_measured_note`: TEPE 0 where no pixel is valid in two
  consecutive frames) are warned about. The same clips on every process; process 0 warns.
  ValueError where no clip is left."""
  empty = {i for i, c in enumerate(clips) if not sav_metrics.any_valid(c["valid"])}
  if len(empty) == len(clips):
    raise ValueError(f"config.eval.dataset={dataset!r}: none of the {len(clips)} validation clips "
                     "has a valid ground-truth pixel (sparse ground truth outside "
                     "config.data.crop?)")
  kept = [c for i, c in enumerate(clips) if i not in empty]
  if jax.process_index() == 0:
    if empty:
      log.warning("validation: %d of the %d clips of %s have no valid ground-truth pixel "
                  "(sparse ground truth outside the crop?) and are left out (the official rule "
                  "would score them a perfect 0)", len(empty), len(clips), dataset)
    notes = [n for n in map(sav_metrics.not_measured_note, (c["valid"] for c in kept)) if n]
    if notes:
      log.warning("validation: %d of the %d clips of %s are measured in part (their scores "
                  "count in the means), e.g.: %s", len(notes), len(kept), dataset, notes[0])
  return kept

"""The official evaluator's disparity metrics of one sequence, written out in numpy from their
definitions (a reference for the tests of eval's reports and training's validation)."""

import numpy as np


def epe_tepe_by_hand(pred, gt, valid, taus=(0.5, 1, 2, 3)) -> dict[str, float]:
  """EPE / TEPE and their bad-N rates of `[T, H, W]` arrays: pred x round(valid), |gt|, both
  zeroed where valid <= 0.5, then NaN in the ground truth 0 (at valid pixels too); errors
  |x - y| per pixel and ||x_t - x_t+1| - |y_t - y_t+1|| per pixel pair valid in both frames;
  each mean and rate (in %) over the non-zero errors. Keys
  `epe_mean`, `epe_bad_{tau}px`, `temp_epe_mean`, `temp_epe_bad_{tau}px` (tau as `%g`)."""
  keep = np.asarray(valid, np.float32) > 0.5
  x = np.where(keep, np.asarray(pred, np.float32), np.float32(0))
  y = np.where(keep, np.abs(np.asarray(gt, np.float32)), np.float32(0))
  y[np.isnan(y)] = 0
  both = keep[1:] & keep[:-1]
  errors = {"epe": np.abs(x - y),
            "temp_epe": np.where(both, np.abs(np.abs(x[1:] - x[:-1]) - np.abs(y[1:] - y[:-1])),
                                 0)}
  out = {}
  for prefix, e in errors.items():
    n = max(np.count_nonzero(e), 1e-5)
    out[f"{prefix}_mean"] = float(e.astype(np.float64).sum() / n)
    for tau in taus:
      out[f"{prefix}_bad_{tau:g}px"] = 100.0 * np.count_nonzero(e > tau) / n
  return out

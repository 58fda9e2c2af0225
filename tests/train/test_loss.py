"""The training loss and metrics against a loop-by-loop NumPy transcription of the official code."""

import numpy as np
import pytest

from train import loss as loss_lib


def _official_sequence_loss(preds, gt, valid, gamma=0.9, max_flow=700.0):
  """`train_utils/losses.py: sequence_loss` for one frame, with explicit loops.

  preds [N, B, H, W], gt [B, H, W], valid [B, H, W] -> (loss, metrics).
  """
  n = preds.shape[0]
  mask = []
  for b in range(gt.shape[0]):
    for y in range(gt.shape[1]):
      for x in range(gt.shape[2]):
        mag = np.sqrt(gt[b, y, x] ** 2)
        mask.append((b, y, x) if (valid[b, y, x] >= 0.5 and mag < max_flow) else None)
  mask = [m for m in mask if m is not None]
  loss = 0.0
  for i in range(n):
    w = 1.0 if n == 1 else (gamma ** (15 / (n - 1))) ** (n - i - 1)
    errs = [abs(preds[i][m] - gt[m]) for m in mask]
    loss += w * (sum(errs) / len(errs) if errs else 0.0)  # empty: 0 (PyTorch: NaN)
  epe = [abs(preds[-1][m] - gt[m]) for m in mask]
  metrics = {"epe": np.mean(epe) if epe else 0.0}
  for tau in (1, 3, 5):
    metrics[f"{tau}px"] = np.mean([e < tau for e in epe]) if epe else 0.0
  return loss, metrics


def _official_forward_batch(preds, gt, valid, per_sample):
  """`forward_batch`: per frame, loss / T summed; per_sample = one clip per GPU, DDP mean."""
  n, b, t = preds.shape[:3]
  groups = [[i] for i in range(b)] if per_sample else [list(range(b))]
  total, mets = 0.0, {"epe": 0.0, "1px": 0.0, "3px": 0.0, "5px": 0.0}
  for g in groups:
    for f in range(t):
      loss, m = _official_sequence_loss(preds[:, g, f], gt[g, f], valid[g, f])
      total += loss / t / len(groups)
      for k in mets:
        mets[k] += m[k] / t / len(groups)
  return total, mets


def _case(rng, n=6, b=2, t=3, h=5, w=7):
  gt = rng.uniform(0.5, 40.0, (b, t, h, w)).astype(np.float32)
  gt[0, 1, 2, 3] = 800.0          # above the 700 cut
  gt[1, 0, 0, :3] = np.nan        # NaN ground truth is never valid
  preds = (gt[None] + rng.normal(0, 3.0, (n, b, t, h, w))).astype(np.float32)
  preds = np.nan_to_num(preds, nan=1.0)
  valid = rng.uniform(0, 1, (b, t, h, w)).astype(np.float32)  # fractional: >= 0.5 counts
  return preds, gt, valid


@pytest.mark.parametrize("per_sample", [True, False])
@pytest.mark.parametrize("n", [1, 2, 20])
def test_loss_matches_loop_reference(per_sample, n):
  preds, gt, valid = _case(np.random.default_rng(n), n=n)
  loss, metrics = loss_lib.sequence_loss(preds, gt, valid, per_sample=per_sample)
  ref_loss, ref_metrics = _official_forward_batch(preds, gt, valid, per_sample)
  np.testing.assert_allclose(float(loss), ref_loss, rtol=1e-5)
  for k, v in ref_metrics.items():
    np.testing.assert_allclose(float(metrics[k]), v, rtol=1e-5, atol=1e-7, err_msg=k)


def test_prediction_weights_official_decay():
  w = np.asarray(loss_lib.prediction_weights(20))
  g = 0.9 ** (15 / 19)
  np.testing.assert_allclose(w, [g ** (19 - i) for i in range(20)], rtol=1e-6)
  assert w[-1] == 1.0 and np.all(np.diff(w) > 0)
  np.testing.assert_allclose(w[0], 0.9 ** 15, rtol=1e-6)  # the decay is fixed per cycle
  assert np.asarray(loss_lib.prediction_weights(1)).tolist() == [1.0]
  with pytest.raises(ValueError, match="need at least one prediction, got 0"):
    loss_lib.prediction_weights(0)


def test_frame_without_valid_pixels_contributes_zero_to_the_loss_and_not_to_the_metrics():
  preds, gt, valid = _case(np.random.default_rng(0))
  valid[:, 0] = 0.0
  loss, metrics = loss_lib.sequence_loss(preds, gt, valid)
  ref, ref_metrics = _official_forward_batch(preds, gt, valid, True)
  assert np.isfinite(float(loss))
  np.testing.assert_allclose(float(loss), ref, rtol=1e-5)
  # The metrics average the measured frames only: an unmeasured one is no perfect 0 EPE.
  measured = {k: v * 3 / 2 for k, v in ref_metrics.items()}  # 2 of the 3 frames measured
  for k, v in measured.items():
    np.testing.assert_allclose(float(metrics[k]), v, rtol=1e-5, err_msg=k)
  np.testing.assert_allclose(float(metrics["measured_frames"]), 2 / 3, rtol=1e-6)
  valid[1, 1:] = 0.0  # clip 1 has none left: 2 of the batch's 6 frames, pooled or not
  for per_sample in (True, False):
    _, m = loss_lib.sequence_loss(preds, gt, valid, per_sample=per_sample)
    np.testing.assert_allclose(float(m["measured_frames"]), 2 / 6, rtol=1e-6)
  for per_sample in (True, False):  # nothing valid at all: 0, and no NaN
    _, none = loss_lib.sequence_loss(preds, gt, np.zeros_like(valid), per_sample=per_sample)
    assert all(float(v) == 0.0 for v in none.values()), none


def test_large_and_invalid_disparities_are_ignored():
  gt = np.full((1, 1, 2, 2), 10.0, np.float32)
  gt[0, 0, 0, 0] = 700.0  # exactly at the cut: excluded (strict <)
  valid = np.ones_like(gt)
  valid[0, 0, 1, 1] = 0.4
  preds = np.full((1, 1, 1, 2, 2), 12.0, np.float32)
  preds[0, 0, 0, 0, 0] = 1e6
  preds[0, 0, 0, 1, 1] = 1e6
  loss, metrics = loss_lib.sequence_loss(preds, gt, valid)
  np.testing.assert_allclose(float(loss), 2.0, rtol=1e-6)
  np.testing.assert_allclose(float(metrics["3px"]), 1.0)
  np.testing.assert_allclose(float(metrics["1px"]), 0.0)


def test_valid_threshold_magnitude_cut_and_accuracy_bounds():
  # valid >= 0.5 counts (0.49 does not), the 700 cut is on |d| (a -750 is left out), and the
  # n-px accuracies count errors strictly below n (official `(epe < n)`).
  gt = np.array([[[[10.0, 10.0, 10.0], [-750.0, 10.0, 10.0]]]], np.float32)  # [1, 1, 2, 3]
  valid = np.array([[[[1.0, 0.5, 0.49], [1.0, 1.0, 1.0]]]], np.float32)
  preds = np.array([[[[[11.0, 13.0, 1e6], [1e6, 15.0, 10.0]]]]], np.float32)  # errors 1, 3, 5, 0
  loss, metrics = loss_lib.sequence_loss(preds, gt, valid)
  np.testing.assert_allclose(float(loss), (1 + 3 + 5 + 0) / 4, rtol=1e-6)
  np.testing.assert_allclose(float(metrics["epe"]), (1 + 3 + 5 + 0) / 4, rtol=1e-6)
  for tau, below in ((1, 1), (3, 2), (5, 3)):  # errors 0 | 0, 1 | 0, 1, 3
    np.testing.assert_allclose(float(metrics[f"{tau}px"]), below / 4, rtol=1e-6, err_msg=tau)
  np.testing.assert_allclose(float(metrics["valid_fraction"]), 4 / 6, rtol=1e-6)


def test_zero_and_negative_ground_truth_inside_the_cut_count():
  # The official mask is `valid >= 0.5` and `|d| < 700` alone: a disparity of 0 (a point at
  # infinity) or a negative one is scored like any other.
  gt = np.array([[[[0.0, -3.0, 4.0]]]], np.float32)  # [1, 1, 1, 3]
  preds = np.array([[[[[2.0, -3.5, 4.0]]]]], np.float32)  # errors 2, 0.5, 0
  loss, metrics = loss_lib.sequence_loss(preds, gt, np.ones_like(gt))
  np.testing.assert_allclose(float(loss), (2 + 0.5 + 0) / 3, rtol=1e-6)
  np.testing.assert_allclose(float(metrics["valid_fraction"]), 1.0)


def test_the_loss_cut_is_700_not_the_dense_valid_rules_512():
  # Official sequence_loss: max_flow = 700. A ground truth of 600 px (beyond the dense
  # datasets' 512 valid rule, which augmentation applies) still counts in the loss.
  gt = np.array([[[[600.0, 699.0, 10.0]]]], np.float32)  # [1, 1, 1, 3]
  preds = np.array([[[[[602.0, 695.0, 11.0]]]]], np.float32)  # errors 2, 4, 1
  loss, metrics = loss_lib.sequence_loss(preds, gt, np.ones_like(gt))
  assert loss_lib.MAX_DISPARITY == 700.0
  np.testing.assert_allclose(float(loss), (2 + 4 + 1) / 3, rtol=1e-6)
  np.testing.assert_allclose(float(metrics["valid_fraction"]), 1.0)


def test_pooled_frames_count_as_measured_when_any_clip_has_a_valid_pixel():
  # per_sample=False pools a frame's valid pixels over the batch (official sequence_loss on
  # one GPU): a frame where only clip 0 has ground truth is still one pooled, measured
  # frame, so the metrics are the official ones with no frame left out.
  preds, gt, valid = _case(np.random.default_rng(4))
  valid[1, 1:] = 0.0  # clip 1: frames 1 and 2 without ground truth
  loss, metrics = loss_lib.sequence_loss(preds, gt, valid, per_sample=False)
  ref_loss, ref_metrics = _official_forward_batch(preds, gt, valid, False)
  np.testing.assert_allclose(float(loss), ref_loss, rtol=1e-5)
  for k, v in ref_metrics.items():
    np.testing.assert_allclose(float(metrics[k]), v, rtol=1e-5, atol=1e-7, err_msg=k)

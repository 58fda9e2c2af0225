"""Tests of sav_jax.metrics against the official-evaluator golden values and closed forms.

Tolerance for the golden values: rtol 1e-6 (observed max relative deviation 3e-7,
on TCC; the reference runs in float32, the reductions here in float64).
"""

import json
import warnings

import numpy as np
import pytest

from sav_jax import metrics as M

RTOL = 1e-6
EPE_KEYS = ("mean", "bad_0.5px", "bad_1px", "bad_2px", "bad_3px")


@pytest.fixture(scope="module")
def golden(fixtures_dir):
  return dict(np.load(fixtures_dir / "metrics_golden.npz"))


@pytest.fixture(scope="module")
def golden_json(fixtures_dir):
  return json.loads((fixtures_dir / "metrics_golden.json").read_text())["golden_results"]


def _check(res, golden, prefix, keys):
  assert keys, prefix
  for k in keys:
    want = float(golden[f"{prefix}/{k}"][0])
    np.testing.assert_allclose(res[k], want, rtol=RTOL, atol=0, err_msg=f"{prefix}/{k}")


def _keys(golden, prefix):
  return [k[len(prefix) + 1:] for k in golden if k.startswith(prefix + "/")]


@pytest.mark.parametrize("prefix,mask_key,crop", [
    ("epe_binary_mask", "mask", 0),
    ("epe_binary_mask_crop4", "mask", 4),
    ("epe_fractional_mask", "frac_mask", 0),
])
def test_endpoint_error_golden(golden, prefix, mask_key, crop):
  res = M.eval_endpoint_error_sequence(golden["pred"], golden["gt"], golden[mask_key], crop=crop)
  keys = _keys(golden, prefix)
  assert len(keys) == 10
  assert set(keys) == set(res)
  _check(res, golden, prefix, keys)


def _seq_inputs(golden, s):
  names = ("pred", "gt", "mask") if s == 0 else ("seq1_pred", "seq1_gt", "seq1_mask")
  pairs = golden[f"seq{s}_flow_pairs"]
  flows = dict(left_video=golden[f"seq{s}_video"], video_flows=golden[f"seq{s}_flow_seq"],
               depth_flows=(pairs[0::2], pairs[1::2]))
  return [golden[n] for n in names], flows


@pytest.mark.parametrize("s", [0, 1])
def test_eval_batch_golden(golden, golden_json, s):
  (pred, gt, mask), flows = _seq_inputs(golden, s)
  scale = 100.0
  res, length = M.eval_batch(pred, gt, mask, scale=scale, **flows)
  assert length == golden_json[f"eval_batch_seq{s}"]["seq_len"] == pred.shape[0]
  keys = _keys(golden, f"eval_batch_seq{s}")
  assert len(keys) == 18 and set(keys) == set(res)
  _check(res, golden, f"eval_batch_seq{s}", keys)


@pytest.mark.parametrize("s", [0, 1])
def test_eval_sequence_matches_eval_batch(golden, s):
  (pred, gt, mask), flows = _seq_inputs(golden, s)
  res, _ = M.eval_batch(pred, gt, mask, scale=100.0, **flows)
  res2 = M.eval_sequence(pred, -gt, mask, flows["video_flows"], scale=100.0,
                         video=flows["left_video"], depth_flows=flows["depth_flows"])
  assert res2 == pytest.approx(res, rel=1e-12)


def test_aggregate_golden(golden, golden_json):
  outs = []
  for s in (0, 1):
    (pred, gt, mask), flows = _seq_inputs(golden, s)
    outs.append(M.eval_batch(pred, gt, mask, scale=100.0, **flows))
  want = golden_json["aggregate"]
  got = M.aggregate(outs)
  assert set(got) == set(want)
  for k, v in want.items():
    np.testing.assert_allclose(got[k], v, rtol=RTOL, err_msg=k)
  # The aggregation alone, from the recorded per-sequence values.
  recorded = [({k: golden[f"eval_batch_seq{s}/{k}"] for k in want},
               golden_json[f"eval_batch_seq{s}"]["seq_len"]) for s in (0, 1)]
  got = M.aggregate(recorded)
  for k, v in want.items():
    np.testing.assert_allclose(got[k], v, rtol=1e-6, err_msg=k)


def test_flow_fn_path_matches_given_flows(golden):
  (pred, gt, mask), flows = _seq_inputs(golden, 0)
  zero = lambda a, b: np.zeros((2, *a.shape[1:]), np.float32)
  t, h, w = pred.shape[0], pred.shape[2], pred.shape[3]
  z = np.zeros((t - 1, 2, h, w), np.float32)
  res, _ = M.eval_batch(pred, gt, mask, scale=100.0, left_video=flows["left_video"], flow_fn=zero)
  res2, _ = M.eval_batch(pred, gt, mask, scale=100.0, left_video=flows["left_video"],
                         video_flows=z, depth_flows=(z, z))
  assert res == res2


# --- closed-form cases -------------------------------------------------------------------


def _ones(t=3, h=16, w=20):
  return np.ones((t, h, w), np.float32)


def test_constant_error_gives_that_epe():
  gt = 5.0 * _ones()
  res = M.eval_endpoint_error_sequence(gt + 1.5, gt, _ones())
  assert res["epe_mean"] == pytest.approx(1.5)
  assert res["epe_bad_0.5px"] == 100.0 and res["epe_bad_1px"] == 100.0
  assert res["epe_bad_2px"] == 0.0 and res["epe_bad_3px"] == 0.0
  # Constant offset: temporal differences agree, so every TEPE error is 0.
  assert res["temp_epe_mean"] == 0.0 and res["temp_epe_bad_0.5px"] == 0.0


def test_static_scene_has_zero_tepe():
  rng = np.random.default_rng(0)
  frame = rng.uniform(1, 10, (16, 20)).astype(np.float32)
  pred = np.repeat(frame[None] + 0.7, 4, axis=0)
  gt = np.repeat(frame[None], 4, axis=0)
  res = M.eval_endpoint_error_sequence(pred, gt, _ones(4))
  assert res["temp_epe_mean"] == 0.0
  assert res["epe_mean"] == pytest.approx(0.7, rel=1e-6)


def test_thresholds_are_strict():
  gt = np.zeros((2, 4, 4), np.float32)
  for tau, key in ((0.5, "0.5"), (1.0, "1"), (2.0, "2"), (3.0, "3")):
    res = M.eval_endpoint_error_sequence(gt + tau, gt, np.ones_like(gt))
    assert res[f"epe_bad_{key}px"] == 0.0
    res = M.eval_endpoint_error_sequence(gt + np.nextafter(np.float32(tau), np.float32(9)), gt,
                                         np.ones_like(gt))
    assert res[f"epe_bad_{key}px"] == 100.0


def test_nonzero_count_denominator():
  gt = 3.0 * _ones(1, 4, 4)
  pred = gt.copy()
  pred[:, :2] += 2.0  # half the pixels off by 2, half exact
  res = M.eval_endpoint_error_sequence(pred, gt, np.ones_like(gt))
  assert res["epe_mean"] == pytest.approx(2.0)  # exact pixels are not counted
  assert res["epe_bad_1px"] == 100.0
  # All-zero error: denominator clamped, result 0 (not NaN).
  res = M.eval_endpoint_error_sequence(gt, gt, np.ones_like(gt))
  assert res["epe_mean"] == 0.0 and res["temp_epe_mean"] == 0.0


def test_nan_gt_zeroed_after_masking():
  gt = 2.0 * _ones(1, 2, 2)
  gt[0, 0, 0] = np.nan
  pred = 2.0 * _ones(1, 2, 2)
  pred[0, 0, 0] = 7.0
  res = M.eval_endpoint_error_sequence(pred, gt, np.ones_like(gt))
  assert res["epe_mean"] == pytest.approx(7.0)  # NaN gt -> 0, error |pred|
  mask = np.ones_like(gt)
  mask[0, 0, 0] = 0.0
  res = M.eval_endpoint_error_sequence(pred, gt, mask)
  assert res["epe_mean"] == 0.0


def test_the_by_hand_reference_zeroes_nan_ground_truth_as_the_official_rule():
  """tests/official_metrics.py (the reference of eval's and training's reports) takes NaN in
  the ground truth at a valid pixel as 0, an error of |pred| there (it gave NaN metrics)."""
  from tests.official_metrics import epe_tepe_by_hand  # pylint: disable=import-outside-toplevel
  rng = np.random.default_rng(5)
  gt = rng.uniform(1, 9, (3, 4, 5)).astype(np.float32)
  gt[0, 1, 1] = gt[2, 0, 3] = np.nan
  pred = rng.uniform(1, 9, gt.shape).astype(np.float32)
  valid = rng.random(gt.shape) < 0.8
  valid[0, 1, 1] = valid[2, 0, 3] = True
  ref = epe_tepe_by_hand(pred, gt, valid)
  res = M.eval_sequence(pred, gt, valid)
  assert {f"disp_{k}": v for k, v in ref.items()} == pytest.approx(res, rel=1e-6, abs=0)


def test_fractional_mask_weights_and_thresholds():
  gt = np.zeros((1, 1, 2), np.float32)
  pred = np.ones((1, 1, 2), np.float32)
  mask = np.array([[[0.64, 0.4]]], np.float32)
  res = M.eval_endpoint_error_sequence(pred, gt, mask)
  assert res["epe_mean"] == pytest.approx(0.8, rel=1e-6)  # sqrt(0.64 * 1); 0.4 dropped
  assert res["epe_bad_0.5px"] == 100.0 and res["epe_bad_1px"] == 0.0


def test_a_weight_of_exactly_the_threshold_is_masked_out():
  """b = [m > 0.5] is strict: a pixel weighted exactly 0.5 is dropped, however large its error
  (with >= it would count sqrt(0.5) * 99 = 70 px and the mean would be ~24 px)."""
  gt = np.zeros((1, 1, 3), np.float32)
  pred = np.array([[[1.0, 1.0, 99.0]]], np.float32)
  half = np.array([[[1.0, 1.0, 0.5]]], np.float32)
  res = M.eval_endpoint_error_sequence(pred, gt, half)
  assert res == M.eval_endpoint_error_sequence(pred, gt, np.array([[[1.0, 1.0, 0.0]]]))
  assert res["epe_mean"] == 1.0 and res["epe_bad_0.5px"] == 100.0 and res["epe_bad_3px"] == 0.0


def test_tepe_compares_absolute_temporal_differences():
  pred = np.array([1.0, 3.0], np.float32).reshape(2, 1, 1)
  gt = np.array([3.0, 1.0], np.float32).reshape(2, 1, 1)
  res = M.eval_endpoint_error_sequence(pred, gt, np.ones_like(pred))
  assert res["temp_epe_mean"] == 0.0  # signed differences would give 4
  assert res["epe_mean"] == pytest.approx(2.0)


def test_crop_and_channel_axis():
  rng = np.random.default_rng(1)
  pred, gt = rng.uniform(0, 5, (2, 3, 1, 20, 24)).astype(np.float32)
  mask = np.ones_like(pred)
  a = M.eval_endpoint_error_sequence(pred, gt, mask, crop=4)
  inner = (slice(None), 0, slice(4, -4), slice(4, -4))
  b = M.eval_endpoint_error_sequence(pred[inner], gt[inner], mask[inner])
  assert a == b
  for crop in (11, 10):  # 10: 20 rows minus 2 x 10 leaves nothing
    with pytest.raises(ValueError, match="crop"):
      M.eval_endpoint_error_sequence(pred, gt, mask, crop=crop)
  for crop in (-1, -2, 1.5):  # (-1: no crop at all, silently, if it were taken)
    with pytest.raises(ValueError, match="crop must be an integer >= 0"):
      M.eval_endpoint_error_sequence(pred, gt, mask, crop=crop)
  for thr in (float("nan"), 2.0, "0.5", True):
    with pytest.raises(ValueError, match=r"mask_thr must be a number in \[0, 1\)"):
      M.eval_endpoint_error_sequence(pred, gt, mask, mask_thr=thr)
  # The depth metrics too: with 2 every pixel was masked out and TCC scored a perfect 1.0.
  depth = np.abs(pred) + 1
  with pytest.raises(ValueError, match=r"mask_thr must be a number in \[0, 1\) .*got 2$"):
    M.eval_tcc_sequence(depth, depth + 1, mask, mask_thr=2)
  with pytest.raises(ValueError, match=r"mask_thr must be a number in \[0, 1\) .*got -1$"):
    M.tcm_flow_inputs(depth, depth + 1, mask, 0, mask_thr=-1)
  # The pair (t, t+1) of 3 frames: t in 0..1 (t=-1 paired the last frame with the first).
  assert len(M.tcm_flow_inputs(depth, depth + 1, mask, np.int64(1))) == 4
  for t in (-1, 2, 0.0, True):
    with pytest.raises(ValueError, match=rf"t must be a frame index in \[0, 1\] .*got {t!r}$"):
      M.tcm_flow_inputs(depth, depth + 1, mask, t)


def test_shape_mismatch_names_both_shapes():
  with pytest.raises(ValueError, match=r"\(3, 4, 5\).*\(3, 4, 6\)"):
    M.eval_endpoint_error_sequence(np.zeros((3, 4, 5)), np.zeros((3, 4, 6)), np.zeros((3, 4, 5)))
  with pytest.raises(ValueError, match=r"\[T, H, W\]"):
    M.eval_endpoint_error_sequence(np.zeros((3, 2, 4, 5)), np.zeros((3, 2, 4, 5)),
                                   np.zeros((3, 2, 4, 5)))


def test_ssim_and_tcc_identity():
  rng = np.random.default_rng(2)
  a = rng.uniform(0, 1, (3, 24, 30))
  np.testing.assert_allclose(M.ssim(a, a), 1.0, rtol=1e-12)
  depth = rng.uniform(5, 50, (4, 24, 30)).astype(np.float32)
  assert M.eval_tcc_sequence(depth, depth, np.ones_like(depth)) == pytest.approx(1.0, rel=1e-9)
  win = M.gaussian_window()
  assert win.shape == (11,) and win.sum() == pytest.approx(1.0, rel=1e-6)


def test_ssim_of_anticorrelated_images_is_clipped_at_zero():
  """SSIM's ReLU (`nonnegative`, on by default and in TCC): a checkerboard against its
  inverse has SSIM ~-0.996, scored 0; TCC of anticorrelated depth changes is 0, not < 0."""
  checker = (np.indices((16, 16)).sum(0) % 2).astype(np.float64)
  assert M.ssim(checker, 1 - checker) == 0.0
  # By hand: x in {0, 1}, y = 1 - x. A Gaussian window averages the checkerboard to 1/2
  # (its alternating sum is ~1e-4, squared ~1e-8), so mu_x = mu_y = 1/2, var = E[x^2] - 1/4
  # = 1/4 each, cov = E[xy] - 1/4 = -1/4: luminance term 1, contrast-structure term
  # (-1/2 + C2) / (1/2 + C2) with C2 = 0.03^2.
  c2 = 0.03 ** 2
  want = (-0.5 + c2) / (0.5 + c2)  # -0.99640647
  assert M.ssim(checker, 1 - checker, nonnegative=False) == pytest.approx(want, rel=1e-6)
  depth = np.full((2, 16, 16), 10.0, np.float32)
  pred, gt = depth.copy(), depth.copy()
  pred[1] += checker
  gt[1] += 1 - checker
  assert M.eval_tcc_sequence(pred, gt, np.ones_like(depth)) == 0.0


def test_flow_warp_shifts_with_zero_padding():
  img = np.arange(12, dtype=np.float32).reshape(1, 3, 4)
  flow = np.zeros((1, 2, 3, 4), np.float32)
  np.testing.assert_allclose(M.flow_warp(img, flow), img, atol=1e-5)
  flow[:, 0] = 1.0  # sample one pixel to the right
  want = np.concatenate([img[..., 1:], np.zeros((1, 3, 1), np.float32)], axis=-1)
  np.testing.assert_allclose(M.flow_warp(img, flow), want, atol=1e-5)
  flow[:, 0] = 0.5
  np.testing.assert_allclose(M.flow_warp(img, flow)[0, 0, :3], [0.5, 1.5, 2.5], atol=1e-5)


def test_opw_rtc_perfectly_consistent_video():
  rng = np.random.default_rng(3)
  t, h, w = 3, 16, 20
  depth = np.repeat(rng.uniform(5, 20, (1, h, w)).astype(np.float32), t, axis=0)
  video = np.repeat(rng.uniform(0, 255, (1, 3, h, w)).astype(np.float32), t, axis=0)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  mask = np.ones_like(depth)
  # Not exactly 0: grid_sample's normalise/unnormalise round trip is inexact in float32.
  np.testing.assert_allclose(M.eval_opw_sequence(video, depth, depth, mask, flows), 0.0, atol=1e-5)
  assert M.eval_rtc_sequence(video, depth, depth, mask, flows) == (1.0, 1.0)
  flows[:, 0, :5] = 300.0  # rejected flow (> 250) only drops pixels
  assert M.eval_rtc_sequence(video, depth, depth, mask, flows) == (1.0, 1.0)


def test_opw_depth_masks_keep_their_own_limits():
  """OPW_30/50/100 select GT depth <= 30/50/100 at t and t+1, in that order (and under their
  own keys in eval_batch): four GT depth bands (20, 40, 70, 200) with warping errors 0.05, 2,
  4, 8 give four different values; RTC_30 keeps only the 20 m band, the one consistent band."""
  t, h, w = 2, 4, 8
  gt = np.repeat(np.array([20.0, 40.0, 70.0, 200.0], np.float32), 2)[None, None]
  gt = np.broadcast_to(gt, (t, h, w)).copy()
  pred = np.full((t, h, w), 10.0, np.float32)
  pred[1] += np.repeat(np.array([1.0, 2.0, 4.0, 8.0], np.float32), 2)  # frame 1 = frame 0 + e
  pred[1, :, :2] = 10.05  # the 20 m band: ratio 1.005 < 1.01, consistent for RTC
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  mask = np.ones_like(gt)
  want = (np.mean([0.05, 2, 4, 8]), 0.05, np.mean([0.05, 2]), np.mean([0.05, 2, 4]))
  opw = M.eval_opw_sequence(video, pred, gt, mask, flows)
  np.testing.assert_allclose(opw, want, rtol=1e-5)
  assert M.eval_rtc_sequence(video, pred, gt, mask, flows) == (0.25, 1.0)
  res, _ = M.eval_batch(1 / pred, 1 / gt, mask, scale=1.0, left_video=video, video_flows=flows)
  got = [res[k] for k in ("disp_OPW", "disp_OPW_30", "disp_OPW_50", "disp_OPW_100")]
  np.testing.assert_allclose(got, want, rtol=1e-4)
  assert (res["disp_RTC"], res["disp_RTC_30"]) == (0.25, 1.0)


def test_pixels_warped_out_of_the_frame_do_not_count():
  """The [W_t > 0] term of V_t: a flow of +3 px samples zeros (zero padding) in the last 3
  columns; a black video keeps their photometric weight at 1, so without the term they would
  count |0 - 10| = 10 each (OPW 30/17). W = 17, H = 5: grid_sample's round trip is exact."""
  t, h, w = 2, 5, 17
  depth = np.full((t, h, w), 10.0, np.float32)
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  flows[:, 0] = 3.0
  mask = np.ones_like(depth)
  assert M.eval_opw_sequence(video, depth, depth, mask, flows) == (0.0, 0.0, 0.0, 0.0)
  assert M.eval_rtc_sequence(video, depth, depth, mask, flows) == (1.0, 1.0)


def test_tcm_skips_frames_without_valid_pixels():
  rng = np.random.default_rng(4)
  f = rng.normal(size=(2, 2, 16, 20)).astype(np.float32)
  mask = np.ones((3, 16, 20), np.float32)
  assert M.eval_tcm_sequence(f, f, mask) == pytest.approx(1.0, rel=1e-9)
  mask[2] = 0.0  # pair (1, 2) has no valid pixel: contributes 0, still divides by 2
  assert M.eval_tcm_sequence(f, f, mask) == pytest.approx(0.5, rel=1e-9)


def test_tcm_flows_from_a_flow_fn_skip_frames_without_valid_pixels():
  """The official TCM runs RAFT on a frame without valid GT (0/0 inputs) and drops the NaN
  flows with the pair; the flow_fn path skips the pair before, instead of failing on them."""
  rng = np.random.default_rng(5)
  depth = rng.uniform(1.0, 9.0, (3, 16, 20)).astype(np.float32)
  mask = np.ones_like(depth)
  calls = []

  def flow_fn(a, b):  # a stand-in that passes NaN through, as RAFT does
    calls.append(1)
    return np.stack([b[0] - a[0], a[1] * 0]) / 255.0

  mask[2] = 0.0
  fx, fy = M.depth_flows_from_fn(depth * 1.1, depth, mask, flow_fn)
  assert len(calls) == 2 and np.all(np.isfinite(fx)) and not fx[1].any() and not fy[1].any()
  # One pixel valid in both frames is a pair TCM measures: its flows are computed.
  one = np.zeros_like(mask)
  one[:, 3, 4] = 1.0
  calls.clear()
  M.depth_flows_from_fn(depth * 1.1, depth, one, flow_fn)
  assert len(calls) == 4
  # A flow_fn with a batch axis, [1, 2, H, W]: the axis is dropped, the values kept.
  batched = lambda a, b: np.full((1, 2, *a.shape[1:]), 1.5, np.float32)
  bx, by = M.depth_flows_from_fn(depth * 1.1, depth, one, batched)
  assert bx.shape == by.shape == (2, 2, 16, 20) and np.all(bx == 1.5) and np.all(by == 1.5)
  tcm = M.eval_tcm_sequence(fx, fy, mask)
  assert 0 < tcm < 0.5  # pair (0, 1) only, divided by 2
  with pytest.warns(M.NotMeasuredWarning, match="1 of the 2 frame pairs .* TCM 0 \\(worst\\)"):
    res, _ = M.eval_batch(depth, depth, mask, scale=1.0, flow_fn=flow_fn)
  assert 0 < res["disp_TCM"] <= 0.5
  mask[:] = 0.0
  assert M.eval_tcm_sequence(*M.depth_flows_from_fn(depth, depth, mask, flow_fn), mask) == 0.0
  mask[:] = 1.0
  depth[1] = 4.0  # one depth over the whole GT frame: 0/0 in a pair TCM uses
  with pytest.raises(ValueError, match="GT depth of frame 1 is 4.0 at every pixel"):
    M.depth_flows_from_fn(depth, depth, mask, flow_fn)


def test_infinite_ground_truth_at_valid_pixels_is_refused():
  pred, gt, valid, _, _ = _clip()
  gt = gt.copy()
  gt[1, 0, 0] = np.inf
  valid[1, 0, 0] = 0  # masked out: as NaN, it counts as 0
  masked = M.eval_sequence(pred, gt, valid)
  # the mean |pred - gt| over the other (valid) pixels, and the same scores as any finite GT
  # value there
  want = np.abs(pred.astype(np.float64) - gt)[valid > 0].mean()
  assert masked["disp_epe_mean"] == pytest.approx(want, rel=1e-6)
  finite_gt = gt.copy()
  finite_gt[1, 0, 0] = 7.0
  assert masked == pytest.approx(M.eval_sequence(pred, finite_gt, valid), rel=1e-12)
  valid[1, 0, 0] = 1
  with pytest.raises(ValueError, match=r"^gt is infinite at valid pixels of valid in frame\(s\) "
                                       r"\[1\] \(every EPE would be inf\); mark them invalid"):
    M.eval_sequence(pred, gt, valid)


def test_aggregate_is_frame_weighted():
  out = M.aggregate([({"a": 1.0, "b": 2.0}, 1), ({"a": 4.0}, 3)])
  assert out["a"] == pytest.approx(13.0 / 4.0)
  assert out["b"] == pytest.approx(0.5)  # missing metric still divides by all frames
  assert M.aggregate([]) == {}
  for bad in ([({"a": 1.0}, -3), ({"a": 1.0}, 3)], [({"a": 1.0}, 2.7)], [{"a": 1.0}],
              [({"a": 1.0}, True)], [({"a": 1.0}, 0)]):  # 0: a sequence without frames
    with pytest.raises(ValueError, match=r"item 0 must be a \(metrics dict, frame count >= 1\)"):
      M.aggregate(bad)


def test_non_finite_predictions_and_flows_are_refused():
  # The official formulas would score a NaN prediction as 0 % bad pixels and a NaN flow as
  # a perfect OPW; GT NaN stays allowed (it is masked out).
  rng = np.random.default_rng(0)
  gt = rng.uniform(1, 5, (3, 8, 10)).astype(np.float32)
  valid = np.ones_like(gt)
  pred = gt.copy()
  pred[1, 2, 3] = np.nan
  with pytest.raises(ValueError, match=r"pred has NaN or inf values in frame\(s\) \[1\]"):
    M.eval_sequence(pred, gt, valid)
  for fn in (M.eval_endpoint_error_sequence, M.endpoint_error_maps):  # the functions below it
    with pytest.raises(ValueError, match=r"pred has NaN or inf values in frame\(s\) \[1\]"):
      fn(pred, gt, valid)
  gt_nan = gt.copy()
  gt_nan[0, 0, 0] = np.nan
  # A NaN GT pixel counts as GT 0 (the official rule): with pred == gt elsewhere its error
  # |pred| is the only non-zero one, and the rates divide by the non-zero count (1).
  scores = M.eval_sequence(gt, gt_nan, valid)
  gt_zero = gt.copy()
  gt_zero[0, 0, 0] = 0.0
  assert scores == pytest.approx(M.eval_sequence(gt, gt_zero, valid), rel=1e-12)
  assert scores["disp_epe_mean"] == pytest.approx(float(gt[0, 0, 0]), rel=1e-6)
  assert scores["disp_epe_bad_3px"] == (100.0 if gt[0, 0, 0] > 3 else 0.0)
  flows = np.zeros((2, 2, 8, 10), np.float32)
  flows[0, 0, 0, 0] = np.inf
  video = rng.uniform(0, 255, (3, 3, 8, 10)).astype(np.float32)
  with pytest.raises(ValueError, match=r"flows has NaN or inf values in frame\(s\) \[0\]"):
    M.eval_batch(gt, gt, valid, scale=10.0, left_video=video, video_flows=flows)


def test_eval_sequence_preprocessing():
  rng = np.random.default_rng(5)
  gt = rng.uniform(1, 10, (3, 8, 10)).astype(np.float32)
  pred = gt + 0.25
  valid = np.ones_like(gt)
  valid[:, :2] = 0.3  # round() -> 0: prediction zeroed there, and mask <= 0.5
  res = M.eval_sequence(pred, -gt, valid)
  assert res["disp_epe_mean"] == pytest.approx(0.25, rel=1e-5)
  assert "disp_TCC" not in res  # no scale: depth metrics skipped
  res = M.eval_sequence(pred, gt, valid, scale=100.0)
  assert "disp_TCC" in res and "disp_OPW" not in res
  # round(valid), not valid, scales the prediction: a weight 0.64 keeps it whole, and the
  # error is sqrt(0.64 * (1 - 0)^2) = 0.8 (pred * 0.64 would give 0.64 * 0.8 = 0.512).
  one = np.ones((2, 1, 2), np.float32)
  res = M.eval_sequence(one, 0 * one, 0.64 * one)
  assert res["disp_epe_mean"] == pytest.approx(0.8, rel=1e-6)


def test_masks_outside_zero_one_are_refused():
  pred = gt = np.ones((2, 4, 4), np.float32)
  for mask, match in ((np.full((2, 4, 4), 255, np.uint8), r"255\.\.255; a 0/255 image\? divide"),
                      (np.full((2, 4, 4), np.nan), "with NaN/inf"),
                      (np.full((2, 4, 4), -1.0), r"\[0, 1\]"),
                      (np.full((2, 4, 4), 1.0000001, np.float32), r"got 1\.0000001\.\.1\.0000001")):
    with pytest.raises(ValueError, match=match):
      M.eval_endpoint_error_sequence(pred, gt, mask)
    with pytest.raises(ValueError, match="valid must hold values"):
      M.eval_sequence(pred, gt, mask)
  assert M.eval_endpoint_error_sequence(pred, gt, np.full((2, 4, 4), 0.7))  # fractional: fine


def test_unconvertible_inputs_are_named():
  g = np.ones((2, 4, 4), np.float32)
  ragged = [np.ones((4, 4)), np.ones((4, 5))]  # a list of frames of two sizes
  with pytest.raises(ValueError, match=r"^valid must be a \[T, H, W\] array of numbers"):
    M.eval_sequence(g, g, ragged)
  with pytest.raises(ValueError, match=r"^pred must be a \[T, H, W\] array of numbers"):
    M.eval_endpoint_error_sequence(ragged, g, g)


@pytest.mark.parametrize("scale", [0.0, -100.0, float("nan"), float("inf"), "100", True,
                                   np.array([100.0])])
def test_bad_scales_are_refused(scale):
  gt = np.ones((3, 12, 12), np.float32)
  with pytest.raises(ValueError, match=r"scale \(depth-to-disparity scale, fx \* baseline\) must "
                                       r"be a finite positive number, got "):
    M.eval_sequence(gt + 0.5, gt, np.ones_like(gt), scale=scale)  # 0 / NaN used to give TCC 1.0
  with pytest.raises(ValueError, match="scale"):
    M.disparity_to_depth(gt, scale)
  assert "disp_TCC" in M.eval_sequence(gt + 0.5, gt, np.ones_like(gt), scale=np.float32(100))


def test_empty_sequences_and_bad_depth_flow_pairs_are_refused():
  empty = np.zeros((0, 8, 8), np.float32)  # used to score a perfect 0 EPE
  with pytest.raises(ValueError, match=r"pred is empty \(shape \(0, 8, 8\)\): metrics need T >= 1"):
    M.eval_sequence(empty, empty, empty)
  with pytest.raises(ValueError, match=r"gt is empty \(shape \(2, 0, 8\)\)"):
    M.eval_endpoint_error_sequence(np.ones((2, 4, 8)), np.ones((2, 0, 8)), np.ones((2, 4, 8)))
  gt = np.ones((3, 12, 12), np.float32)
  flows = np.zeros((2, 2, 12, 12), np.float32)
  for bad, got in (((flows,), "got 1 items"), ((flows,) * 3, "got 3 items"), (5, "got int")):
    with pytest.raises(ValueError, match=rf"depth_flows must be a pair \(pred_flows, gt_flows\).*"
                                         rf"{got}"):
      M.eval_sequence(gt, gt, np.ones_like(gt), scale=100.0, depth_flows=bad)
  with pytest.raises(ValueError, match=r"gt_flows must have shape \(2, 2, 12, 12\)"):
    M.eval_sequence(gt, gt, np.ones_like(gt), scale=100.0, depth_flows=(flows, flows[:1]))
  res = M.eval_sequence(gt, gt, np.ones_like(gt), scale=100.0, depth_flows=(flows, flows))
  assert "disp_TCM" in res


def test_flows_of_a_one_frame_video_are_refused_by_name():
  """One frame has no pair: numpy's "need at least one array to stack" came out instead."""
  one, flow_fn = np.ones((1, 8, 8), np.float32), lambda a, b: np.zeros((2, 8, 8), np.float32)
  with pytest.raises(ValueError, match=r"need T >= 2 frames, got shape \(1, 3, 8, 8\)"):
    M.video_flows_from_fn(np.full((1, 3, 8, 8), 100, np.float32), flow_fn)
  with pytest.raises(ValueError, match=r"need T >= 2 frames, got shape \(1, 8, 8\)"):
    M.depth_flows_from_fn(one, one, one, flow_fn)


# --- the flow_fn path against the official argument order and TCM normalisation ------------


def _asym_flow(a, b):
  """Stand-in for RAFT: `[3, H, W]` x2 -> `[2, H, W]`, non-zero, depends on the content of
  both images and on their order (`f(a, b)` is neither `f(b, a)` nor `-f(b, a)`, which SSIM
  could not tell apart: SSIM(-p, -q) = SSIM(p, q))."""
  a = np.asarray(a, np.float64) / 255.0
  b = np.asarray(b, np.float64) / 255.0
  u = 2.0 * a[0] ** 2 - b[1] + 0.3
  v = 3.0 * (b[2] - a[2]) * (1 + a[1]) - 0.2
  return np.stack([u, v]).astype(np.float32)


def _tcm_inputs_official(pred_depth, gt_depth, mask, t, mask_thr=0.5):
  """My transcription of the images official `eval_TCM_sequence` hands to RAFT for the pair
  (t, t+1): x, y masked by [mask > thr], NaN in y -> 0, then ALL FOUR images min-max
  normalised with the range (max, min) of the masked GT frame t, times 255, 3 channels."""
  keep = (np.asarray(mask, np.float32) > np.float32(mask_thr)).astype(np.float32)
  x = np.asarray(pred_depth, np.float32) * keep
  y = np.asarray(gt_depth, np.float32) * keep
  y = np.where(np.isnan(y), np.float32(0), y)
  dmax, dmin = y[t].max(), y[t].min()
  return tuple(np.broadcast_to((a - dmin) / (dmax - dmin) * np.float32(255.0), (3, *a.shape))
               for a in (x[t], x[t + 1], y[t], y[t + 1]))


@pytest.fixture(scope="module")
def asym_case():
  """A small stereo clip (T=4, 16x20) with smooth content, so that OPW/RTC keep photometrically
  consistent pixels, a partial (and fractional) mask and a NaN GT pixel under it. The masked
  zeros are kept out of most frames: there they would make every image's min 0, and the GT
  frame t range hard to tell from an image's own range."""
  t, h, w = 4, 16, 20
  rng = np.random.default_rng(11)
  yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
  frames = [np.stack([128 + 25 * np.sin(0.25 * (xx - 1.2 * i) + 0.15 * yy + c)
                      for c in (0.0, 0.7, 1.9)]) for i in range(t)]
  left = np.stack(frames).astype(np.float32)
  video = np.stack([left, left[:, ::-1]], 1)  # [T, 2, 3, H, W]: flows must use the left view
  gt = (20 + 6 * np.sin(0.2 * xx[None] + 0.3 * yy[None] + 0.4 * np.arange(t)[:, None, None])
        + rng.uniform(0, 1, (t, h, w))).astype(np.float32)
  pred = (gt * rng.uniform(0.8, 1.2, gt.shape) + 0.5).astype(np.float32)
  mask = np.ones((t, h, w), np.float32)
  mask[3, :3, :4] = 0.0  # masked pixels become depth 0 in x_{t+1}, y_{t+1} of the last pair
  mask[1, 10:, 15:] = 0.7  # fractional: kept for the images, a weight for TCM
  mask[2, 0, 0] = 0.0
  gt[2, 0, 0] = np.nan  # under the mask: NaN -> 0 after masking (GT frame 2's min is 0)
  return dict(video=video, pred=pred, gt=gt, mask=mask, scale=50.0)


def _official_flows(c):
  """The flows as the official evaluator takes them, built here from the stand-in:
  `compute_flow(img[:, 0])` = f(I_t, I_{t+1}) of the left video, and TCM's
  f(x_t, x_{t+1}) / f(y_t, y_{t+1}) on the GT-frame-t-normalised depth images."""
  left = c["video"][:, 0]
  video_flows = np.stack([_asym_flow(left[i], left[i + 1]) for i in range(len(left) - 1)])
  zx = c["scale"] / np.maximum(c["pred"], 1e-10)
  zy = c["scale"] / np.maximum(c["gt"], 1e-10)
  fx, fy = [], []
  for i in range(len(left) - 1):
    x0, x1, y0, y1 = _tcm_inputs_official(zx, zy, c["mask"], i)
    fx.append(_asym_flow(x0, x1))
    fy.append(_asym_flow(y0, y1))
  return video_flows, (np.stack(fx), np.stack(fy)), (zx.astype(np.float32), zy.astype(np.float32))


def test_flow_fn_path_uses_the_official_order_and_tcm_normalisation(asym_case):
  """eval_batch with `flow_fn` equals eval_batch with the flows the official code would compute
  (RAFT(I_t, I_{t+1}); TCM images all normalised by GT frame t's range), and
  `tcm_flow_inputs` / `depth_flows_from_fn` give those images / flows. Catches reversed flow
  pairs (f(I_{t+1}, I_t)) and per-image normalisation."""
  c = asym_case
  video_flows, depth_flows, (zx, zy) = _official_flows(c)
  assert np.abs(video_flows).min() > 0 and np.abs(depth_flows[0]).max() < 250
  # tcm_flow_inputs against the transcription. float32 like the reference; the same formula
  # evaluated here agrees to the last bit (measured max relative difference 0); rtol 1e-6.
  for t in range(c["pred"].shape[0] - 1):
    got = M.tcm_flow_inputs(zx, zy, c["mask"], t)
    want = _tcm_inputs_official(zx, zy, c["mask"], t)
    for name, g, w in zip(("pred_t", "pred_t1", "gt_t", "gt_t1"), got, want):
      assert g.shape == (3, *zx.shape[1:]), name
      np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-4, err_msg=f"t={t} {name}")
  fx, fy = M.depth_flows_from_fn(zx, zy, c["mask"], _asym_flow)
  np.testing.assert_allclose(fx, depth_flows[0], rtol=1e-6, atol=1e-6)
  np.testing.assert_allclose(fy, depth_flows[1], rtol=1e-6, atol=1e-6)
  np.testing.assert_allclose(M.video_flows_from_fn(c["video"], _asym_flow), video_flows,
                             rtol=1e-6, atol=1e-6)
  # The whole eval: flow_fn path vs flows given. rtol 1e-6 (measured: identical).
  args = (c["pred"], c["gt"], c["mask"])
  got, _ = M.eval_batch(*args, scale=c["scale"], left_video=c["video"], flow_fn=_asym_flow)
  want, _ = M.eval_batch(*args, scale=c["scale"], left_video=c["video"],
                         video_flows=video_flows, depth_flows=depth_flows)
  assert set(got) == set(want) and {"disp_TCM", "disp_OPW", "disp_RTC"} <= set(got)
  assert got == pytest.approx(want, rel=1e-6, abs=1e-9)
  # The case can tell: reversed pairs and per-image normalisation change TCM, OPW and RTC
  # well beyond the tolerance (measured relative changes: reversed TCM +9%, OPW +1.4%,
  # RTC -4.6%; own-range TCM +15%).
  left = c["video"][:, 0]
  rev_video = np.stack([_asym_flow(left[i + 1], left[i]) for i in range(len(left) - 1)])
  rev_depth = [], []
  own_depth = [], []
  for i in range(len(left) - 1):
    x0, x1, y0, y1 = _tcm_inputs_official(zx, zy, c["mask"], i)
    rev_depth[0].append(_asym_flow(x1, x0))
    rev_depth[1].append(_asym_flow(y1, y0))
    own = [(a - a.min()) / (a.max() - a.min()) * 255 for a in (x0, x1, y0, y1)]
    own_depth[0].append(_asym_flow(own[0], own[1]))
    own_depth[1].append(_asym_flow(own[2], own[3]))
  rev, _ = M.eval_batch(*args, scale=c["scale"], left_video=c["video"], video_flows=rev_video,
                        depth_flows=tuple(map(np.stack, rev_depth)))
  own, _ = M.eval_batch(*args, scale=c["scale"], left_video=c["video"],
                        video_flows=video_flows, depth_flows=tuple(map(np.stack, own_depth)))
  for key in ("disp_TCM", "disp_OPW", "disp_RTC"):
    assert rev[key] != pytest.approx(want[key], rel=1e-3), key
  assert own["disp_TCM"] != pytest.approx(want["disp_TCM"], rel=1e-3)


# --- warnings and layout hints of the Python API ----------------------------------------


def _clip(t=3, h=32, w=64, seed=7):
  """A random sequence (pred, gt, valid), a float 0..255 left video `[T, 3, H, W]` and zero
  flows `[T-1, 2, H, W]`."""
  rng = np.random.default_rng(seed)
  gt = rng.uniform(5, 20, (t, h, w)).astype(np.float32)
  pred = gt + rng.normal(0, 1, gt.shape).astype(np.float32)
  video = rng.uniform(0, 255, (t, 3, h, w)).astype(np.float32)
  return pred, gt, np.ones_like(gt), video, np.zeros((t - 1, 2, h, w), np.float32)


def _no_warning(fn, *args, **kwargs):
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    return fn(*args, **kwargs)


def test_inputs_left_unused_are_named():
  """A given input that no metric uses (the metrics it was for were dropped silently) is
  named with what is missing; fully specified calls warn nothing."""
  pred, gt, valid, video, flows = _clip()
  epe_keys = set(_no_warning(M.eval_sequence, pred, gt, valid))
  with pytest.warns(UserWarning, match=r"^video, flows given but no scale: TCC, TCM, OPW and "
                                       r"RTC \(depth metrics\) not computed, only EPE and TEPE; "
                                       r"pass scale="):
    res = M.eval_sequence(pred, gt, valid, flows, video=video)
  assert set(res) == epe_keys  # the numbers are as before
  with pytest.warns(UserWarning, match=r"^flow_fn given but no scale"):
    M.eval_sequence(pred, gt, valid, flow_fn=lambda a, b: np.zeros((2, *a.shape[1:])))
  with pytest.warns(UserWarning, match=r"^video given but no flows/flow_fn: OPW and RTC not "
                                       r"computed \(pass flows= \[T-1, 2, H, W\] or flow_fn=\)"):
    res = M.eval_sequence(pred, gt, valid, scale=100.0, video=video)
  assert "disp_TCC" in res and "disp_OPW" not in res
  with pytest.warns(UserWarning, match=r"^flows given but no video: OPW and RTC not computed"):
    assert "disp_OPW" not in M.eval_sequence(pred, gt, valid, flows, scale=100.0)
  # eval_batch names its own arguments
  with pytest.warns(UserWarning, match=r"^left_video given but no video_flows/flow_fn"):
    M.eval_batch(pred, gt, valid, scale=100.0, left_video=video)
  with pytest.warns(UserWarning, match=r"^video_flows given but no left_video"):
    M.eval_batch(pred, gt, valid, scale=100.0, video_flows=flows)
  # fully specified (or nothing unused): no warning
  full = _no_warning(M.eval_sequence, pred, gt, valid, flows, scale=100.0, video=video,
                     depth_flows=(flows, flows))
  assert {"disp_TCC", "disp_TCM", "disp_OPW", "disp_RTC"} <= set(full)
  zero_flow = lambda a, b: np.zeros((2, *a.shape[1:]), np.float32)
  assert _no_warning(M.eval_sequence, pred, gt, valid, scale=100.0, video=video,
                     flow_fn=zero_flow) == full
  assert _no_warning(M.eval_sequence, pred, gt, valid, flows, scale=100.0, video=video,
                     flow_fn=zero_flow) == full  # as `python -m eval` calls it
  assert "disp_TCM" in _no_warning(M.eval_batch, pred, gt, valid, scale=100.0,
                                   flow_fn=zero_flow)[0]
  assert "disp_OPW" not in _no_warning(M.eval_sequence, pred, gt, valid, scale=100.0)


def test_scores_that_measure_nothing_warn_and_keep_the_official_numbers():
  """No valid GT pixel, or one frame: the official numbers, with a NotMeasuredWarning (a
  category of its own, which `python -m eval` can silence: it notes these itself)."""
  pred, gt, valid, video, flows = _clip()
  full = dict(scale=100.0, video=video, depth_flows=(flows, flows))
  with pytest.warns(M.NotMeasuredWarning,
                    match=r"^valid has no pixel > 0\.5 \(no valid ground truth\): the official "
                          r"rule scores EPE, TEPE and their bad-pixel rates 0 \(perfect\), TCC 1 "
                          r"\(perfect\), TCM 0 \(worst\), OPW 0 \(perfect\), RTC 0 \(worst\), "
                          r"though nothing was measured; the official evaluator stops with an "
                          r"error on such a sequence \(its TCM/OPW measure no pair\); the "
                          r"official rule's numbers are returned$") as record:
    res = M.eval_sequence(pred, gt, np.zeros_like(valid), flows, **full)
  assert len(record) == 1 and record[0].filename == __file__  # the caller's line
  assert res["disp_TCC"] == 1.0 and all(v == 0.0 for k, v in res.items() if k != "disp_TCC")
  with pytest.warns(M.NotMeasuredWarning, match=r"^mask has no pixel > 0\.5 .*rates 0 "
                                                r"\(perfect\), though nothing"):
    M.eval_batch(pred, gt, np.full_like(valid, 0.5))  # 0.5 is not above the threshold
  with pytest.warns(M.NotMeasuredWarning, match=r"^one frame \(T=1\), no frame pair: the "
                                                r"official rule scores TEPE and its bad-pixel "
                                                r"rates \(δt\) 0"):
    res = M.eval_sequence(pred[:1], gt[:1], valid[:1])
  assert res["disp_temp_epe_mean"] == 0.0 and res["disp_epe_mean"] > 0
  with warnings.catch_warnings():  # silenced by its category, nothing else given
    warnings.simplefilter("error")
    warnings.simplefilter("ignore", M.NotMeasuredWarning)
    M.eval_sequence(pred, gt, np.zeros_like(valid), flows, **full)
    M.eval_sequence(pred[:1], gt[:1], valid[:1])
  # Valid pixels in no two consecutive frames: TEPE measures nothing.
  alternate = valid.copy()
  alternate[1::2] = 0
  with pytest.warns(M.NotMeasuredWarning, match=r"^valid has no pixel valid in two consecutive "
                                                r"frames \(TEPE's pairs\): the official rule "
                                                r"scores TEPE and its bad-pixel rates \(δt\) 0"):
    res = M.eval_sequence(pred, gt, alternate)
  assert res["disp_temp_epe_mean"] == 0.0 and res["disp_epe_mean"] > 0
  with pytest.warns(M.NotMeasuredWarning, match=r"TEPE and its bad-pixel rates \(δt\) 0, and "
                                                r"every pair TCC 1 \(perfect\), TCM 0 \(worst\)"
                                                r".*the official evaluator stops with an error"):
    M.eval_sequence(pred, gt, alternate, flows, **full)
  _no_warning(M.eval_sequence, pred, gt, valid, flows, **full)
  # Frames without GT after frame 1: TEPE pools the valid pixels (measured), but the depth
  # metrics score each empty pair as if measured, in their mean over the T-1 pairs.
  valid[2:] = 0
  _no_warning(M.eval_sequence, pred, gt, valid)
  n = len(valid) - 1  # 2 pairs, 1 of them empty ("has")
  with pytest.warns(M.NotMeasuredWarning, match=rf"^{n - 1} of the {n} frame pairs has no pixel "
                                                r"valid in both frames: the official rule scores "
                                                r"each such pair TCC 1 \(perfect\), TCM 0 "
                                                r"\(worst\), OPW 0 \(perfect\), RTC 0 \(worst\) "
                                                r"in the sequence's mean over its pairs"):
    res = M.eval_sequence(pred, gt, valid, flows, **full)
  assert type(res["disp_OPW"]) is float and type(res["disp_RTC"]) is float  # not np.float64


def test_channels_last_videos_and_flows_are_refused_with_the_moveaxis():
  pred, gt, valid, video, flows = _clip()
  last = np.moveaxis(video, 1, -1)  # [T, H, W, 3], as predict_video takes frames
  with pytest.raises(ValueError, match=r"^video must be \[T, 3, H, W\] or \[T, 2, 3, H, W\], got "
                                       r"shape \(3, 32, 64, 3\); channels last \(the layout "
                                       r"predict_video takes\)\? pass np\.moveaxis\(video, -1, "
                                       r"1\)$"):
    M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=last)
  stereo = np.stack([last, last], 1)  # [T, 2, H, W, 3]
  with pytest.raises(ValueError, match=r"got shape \(3, 2, 32, 64, 3\); .*np\.moveaxis\(video, "
                                       r"-1, 2\)$"):
    M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=stereo)
  with pytest.raises(ValueError, match=r"^left_video must be .*np\.moveaxis\(left_video, -1, 1\)"):
    M.eval_batch(pred, gt, valid, scale=100.0, left_video=last, video_flows=flows)
  with pytest.raises(ValueError, match=r"^left_video must be .*np\.moveaxis\(left_video, -1, 1\)"):
    M.eval_opw_sequence(last, pred, gt, valid, flows)
  for unused in ({}, {"scale": 100.0}):  # no flows (nor scale): no metric uses it, refused too
    with pytest.raises(ValueError, match=r"^video must be .*np\.moveaxis\(video, -1, 1\)$"):
      M.eval_sequence(pred, gt, valid, video=last, **unused)
  with pytest.raises(ValueError, match=r"got shape \(3, 4, 32, 64\)$"):  # no channel axis: no hint
    M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=np.zeros((3, 4, 32, 64)))
  ok = M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=np.moveaxis(last, -1, 1))
  assert "disp_OPW" in ok  # the hint's fix works

  hw_2 = lambda a, b: np.zeros((*a.shape[1:], 2), np.float32)  # raft_flow's [H, W, 2]
  hint = (r"it returned shape \(32, 64, 2\); channels last, as sav_jax\.model\.raft\.raft_flow "
          r"returns it\? return np\.moveaxis\(flow, -1, 0\) \(sav_jax\.model\.raft\.raft_flow_fn "
          r"does\)$")
  with pytest.raises(ValueError, match=r"^flow_fn must return a \[2, H, W\] flow, here \(2, 32, "
                                       r"64\), for two \[3, H, W\] images; for the predicted "
                                       r"depth frames 0, 1 " + hint):
    M.eval_sequence(pred, gt, valid, scale=100.0, video=video, flow_fn=hw_2)
  with pytest.raises(ValueError, match=r"^flow_fn must .*for the left video frames 0, 1 " + hint):
    M.eval_sequence(pred, gt, valid, scale=100.0, video=video, flow_fn=hw_2,
                    depth_flows=(flows, flows))
  with pytest.raises(ValueError, match=r"^flow_fn must .*left video frames 0, 1 " + hint):
    M.video_flows_from_fn(video, hw_2)
  with pytest.raises(ValueError, match=r"^flow_fn must .* it returned shape \(2, 16, 64\)$"):
    M.video_flows_from_fn(video, lambda a, b: np.zeros((2, 16, 64)))
  nan = lambda a, b: np.full((2, *a.shape[1:]), np.nan, np.float32)
  with pytest.raises(ValueError, match=r"^flow_fn returned NaN or inf values for the left video "
                                       r"frames 0, 1"):
    M.video_flows_from_fn(video, nan)
  batched = lambda a, b: np.zeros((1, 2, *a.shape[1:]), np.float32)  # accepted, as before
  assert M.video_flows_from_fn(video, batched).shape == flows.shape


def test_non_finite_video_values_are_refused():
  """NaN/inf in the left video made OPW and RTC 0 (NaN photometric weights) without a word;
  the right view of a stereo video, which no metric reads, may hold them."""
  pred, gt, valid, video, flows = _clip()
  bad = video.copy()
  bad[1, 0, 4, 5] = np.nan
  msg = r"video has NaN or inf values in frame\(s\) \[1\]; OPW and RTC would be 0"
  with pytest.raises(ValueError, match=r"^" + msg):
    M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=bad)
  zero_flow = lambda a, b: np.zeros((2, *a.shape[1:]), np.float32)
  with pytest.raises(ValueError, match=r"^left_" + msg):
    M.eval_batch(pred, gt, valid, scale=100.0, left_video=np.where(bad == bad, bad, np.inf),
                 flow_fn=zero_flow)
  for fn in (M.eval_opw_sequence, M.eval_rtc_sequence):
    with pytest.raises(ValueError, match=r"^left_" + msg):
      fn(bad, pred, gt, valid, flows)
  with pytest.raises(ValueError, match=r"^left_" + msg):
    M.video_flows_from_fn(bad, zero_flow)
  stereo = np.stack([video, bad], axis=1)  # [T, 2, 3, H, W]: NaN in the right view only
  want = _no_warning(M.eval_sequence, pred, gt, valid, flows, scale=100.0, video=video)
  assert _no_warning(M.eval_sequence, pred, gt, valid, flows, scale=100.0,
                     video=stereo) == want


def test_bfloat16_videos_are_checked_as_floats():
  """A bfloat16 video (kind "V" to NumPy) skipped the 0..1 warning and the NaN check."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  pred, gt, valid, video, flows = _clip()
  with pytest.warns(UserWarning, match=r"^video: float frames with values .*: OPW and RTC "
                                       r"expect RGB 0\.\.255"):
    M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=jnp.asarray(video / 255,
                                                                             jnp.bfloat16))
  bad = video.copy()
  bad[2, 1, 0, 0] = np.inf
  with pytest.raises(ValueError, match=r"^video has NaN or inf values in frame\(s\) \[2\]"):
    M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=jnp.asarray(bad, jnp.bfloat16))


def test_a_bfloat16_scale_is_a_number():
  """A JAX bfloat16 scalar scale (NumPy kind "V") was refused as not "a finite positive
  number"."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  pred, gt, valid, _, _ = _clip()
  want = M.eval_sequence(pred, gt, valid, scale=96.0)
  assert M.eval_sequence(pred, gt, valid, scale=jnp.bfloat16(96)) == want
  assert M.eval_batch(pred, gt, valid, scale=jnp.asarray(96, jnp.bfloat16))[0] == want


def test_videos_that_are_not_rgb_0_255_warn():
  """A 0..1 float video changes OPW/RTC (its photometric weight keeps nearly every pixel)."""
  pred, gt, valid, video, flows = _clip()
  want = _no_warning(M.eval_sequence, pred, gt, valid, flows, scale=100.0, video=video)
  _no_warning(M.eval_sequence, pred, gt, valid, flows, scale=100.0,
              video=np.round(video).astype(np.uint8))
  unit = r"float frames with values [\d.e-]+\.\.0\.9\d+: OPW and RTC expect RGB 0\.\.255 " \
         r"\(multiply 0\.\.1 images by 255\)"
  with pytest.warns(UserWarning, match=r"^video: " + unit) as record:
    res = M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=video / 255)
  assert len(record) == 1 and record[0].filename == __file__
  assert res["disp_OPW"] != pytest.approx(want["disp_OPW"], rel=1e-3)  # why it warns
  zero_flow = lambda a, b: np.zeros((2, *a.shape[1:]), np.float32)
  with pytest.warns(UserWarning, match=r"^left_video: " + unit) as record:  # once, with flow_fn
    M.eval_batch(pred, gt, valid, scale=100.0, left_video=video / 255, flow_fn=zero_flow)
  assert len(record) == 1
  for fn in (M.eval_opw_sequence, M.eval_rtc_sequence):
    with pytest.warns(UserWarning, match=r"^left_video: " + unit):
      fn(video / 255, pred, gt, valid, flows)
  with pytest.warns(UserWarning, match=r"^left_video: " + unit):
    M.video_flows_from_fn(video / 255, zero_flow)
  with pytest.warns(UserWarning, match=r"^video: values [\d.]+\.\.6\d+(\.\d+)?, outside "
                                       r"0\.\.255, which OPW and RTC expect \(RGB 0\.\.255; "
                                       r"divide 16-bit"):
    M.eval_sequence(pred, gt, valid, flows, scale=100.0, video=video * 257)


def test_a_one_pixel_crop_removes_the_border():
  """crop=1 drops one row and column on each side (the official `[..., 1:-1, 1:-1]`): a
  border of 9 px errors around a 0.25 px interior leaves EPE 0.25 with no pixel bad at 0.5 px
  (uncropped, the 14 border pixels of each 4x5 frame would dominate: (14*9 + 6*0.25) / 20)."""
  gt = np.zeros((2, 4, 5), np.float32)
  pred = np.full_like(gt, 9.0)
  pred[:, 1:-1, 1:-1] = 0.25
  pred[1, 1:-1, 1:-1] = 0.75  # interior temporal change 0.5 px, border none
  res = M.eval_endpoint_error_sequence(pred, gt, np.ones_like(gt), crop=1)
  assert res["epe_mean"] == pytest.approx(0.5)  # (6 * 0.25 + 6 * 0.75) / 12
  assert res["epe_bad_0.5px"] == 50.0 and res["epe_bad_1px"] == 0.0
  assert res["temp_epe_mean"] == pytest.approx(0.5) and res["temp_epe_bad_0.5px"] == 0.0
  full = M.eval_endpoint_error_sequence(pred, gt, np.ones_like(gt))
  assert full["epe_mean"] == pytest.approx((28 * 9 + 6 * 0.25 + 6 * 0.75) / 40)


def _ssim_by_hand(x, y, size=11, sigma=1.5, k=(0.01, 0.03)):
  """SSIM of one [H, W] pair written out window by window: a 2-D Gaussian (outer product of
  the 1-D window) over every window position fully inside the image; an axis shorter than the
  window is not filtered (a 1-pixel window there), as the reference `gaussian_filter`."""
  g = np.exp(-((np.arange(size) - size // 2) ** 2) / (2 * sigma ** 2))
  g /= g.sum()
  gh = g if x.shape[0] >= size else np.ones(1)
  gw = g if x.shape[1] >= size else np.ones(1)
  w2 = np.outer(gh, gw)
  c1, c2 = k[0] ** 2, k[1] ** 2
  vals = []
  for i in range(x.shape[0] - len(gh) + 1):
    for j in range(x.shape[1] - len(gw) + 1):
      a, b = x[i:i + len(gh), j:j + len(gw)], y[i:i + len(gh), j:j + len(gw)]
      mx, my = (w2 * a).sum(), (w2 * b).sum()
      vx, vy = (w2 * a * a).sum() - mx ** 2, (w2 * b * b).sum() - my ** 2
      cxy = (w2 * a * b).sum() - mx * my
      vals.append((2 * mx * my + c1) / (mx ** 2 + my ** 2 + c1)
                  * (2 * cxy + c2) / (vx + vy + c2))
  return np.mean(vals)


@pytest.mark.parametrize("shape", [(11, 11), (11, 16), (16, 11), (7, 13), (12, 5)])
def test_ssim_matches_a_window_by_window_computation(shape):
  """SSIM of images whose sides are exactly the window size (11: one valid position, filtered)
  or shorter (not filtered along that axis), against the definition written out by hand."""
  rng = np.random.default_rng(sum(shape))
  x = rng.uniform(0, 1, shape)
  y = np.clip(x + rng.normal(0, 0.2, shape), 0, 1)
  want = _ssim_by_hand(x, y)
  assert want > 0.1  # (so that the ReLU does not hide a difference)
  # rel 1e-6: the window is built in float32, as the reference's (here in float64)
  assert M.ssim(x, y) == pytest.approx(want, rel=1e-6)


def test_tcc_of_nan_predicted_depth_counts_it_as_zero():
  """eval_tcc_sequence sets NaN predicted depth to 0 after masking, as the official TCC: a NaN
  at a masked-out pixel changes nothing (it is not NaN), one at a valid pixel scores as 0."""
  rng = np.random.default_rng(7)
  gt = rng.uniform(5, 20, (3, 16, 16)).astype(np.float32)
  pred = gt + rng.normal(0, 0.5, gt.shape).astype(np.float32)
  mask = np.ones_like(gt)
  mask[1, 3, 4] = 0
  want = M.eval_tcc_sequence(pred, gt, mask)
  assert 0 < want < 1
  nan_pred = pred.copy()
  nan_pred[1, 3, 4] = np.nan
  assert M.eval_tcc_sequence(nan_pred, gt, mask) == want
  nan_pred[2, 5, 6] = np.nan
  zero_pred = pred.copy()
  zero_pred[2, 5, 6] = 0
  assert M.eval_tcc_sequence(nan_pred, gt, mask) == M.eval_tcc_sequence(zero_pred, gt, mask)


def test_tcm_drops_pixels_where_the_gt_flow_exceeds_250():
  """M_t keeps pixels where no channel of the GT depth flow is > 250 (strictly; the predicted
  flow is not looked at): predicted flows that agree with the GT except at pixels of GT flow
  300 score a perfect 1; the same disagreement where only the predicted flow is 300, or where
  the GT flow is 250, counts (< 1)."""
  rng = np.random.default_rng(8)
  fy = rng.normal(0, 2, (1, 2, 16, 16)).astype(np.float32)
  fx = fy.copy()
  mask = np.ones((2, 16, 16), np.float32)
  fy[0, 1, 4:8, 4:8] = 300.0  # the GT flow's v channel only
  assert M.eval_tcm_sequence(fx, fy, mask) == pytest.approx(1.0, rel=1e-12)
  assert M.eval_tcm_sequence(fy, fx, mask) < 0.99  # the pixels count when only pred is 300
  fy[0, 1, 4:8, 4:8] = 250.0  # not above 250: kept, and the disagreement counts
  assert M.eval_tcm_sequence(fx, fy, mask) < 0.99


def test_tcm_clips_each_pairs_ssim_at_zero():
  """TCM applies SSIM's ReLU per flow channel, as the official `nonnegative_ssim=True`: flows
  that are a checkerboard and its inverse (SSIM ~-0.996 by hand, see the SSIM test above)
  score 0, not a negative TCM."""
  checker = (np.indices((16, 16)).sum(0) % 2).astype(np.float32)
  fx = np.stack([checker, checker])[None]
  mask = np.ones((2, 16, 16), np.float32)
  assert M.eval_tcm_sequence(fx, 1 - fx, mask) == 0.0
  assert M.eval_tcm_sequence(fx, fx, mask) == pytest.approx(1.0, rel=1e-12)


def test_opw_keeps_flows_up_to_250_px():
  """V_t drops pixels whose left-video flow is > 250 px only: a 30 px flow is kept. Frame 1's
  depth is 12 where frame 0's is 10 (a black video keeps the photometric weight 1), so the
  pixels that sample inside the frame (columns 0..9 of 40) give OPW |12 - 10| = 2, and RTC 0
  (ratio 1.2)."""
  t, h, w = 2, 3, 40
  depth = np.full((t, h, w), 10.0, np.float32)
  depth[1] = 12.0
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  flows[:, 0] = 30.0
  mask = np.ones_like(depth)
  np.testing.assert_allclose(M.eval_opw_sequence(video, depth, depth, mask, flows), 2.0,
                             rtol=1e-5)
  assert M.eval_rtc_sequence(video, depth, depth, mask, flows) == (0.0, 0.0)
  # The depth bands are <= K: a GT depth of exactly 30 is in OPW_30, one just above it is not.
  gt = np.full_like(depth, 30.0)
  np.testing.assert_allclose(M.eval_opw_sequence(video, depth, gt, mask, flows), 2.0, rtol=1e-5)
  gt[1] = np.nextafter(np.float32(30), np.float32(31))
  opw = M.eval_opw_sequence(video, depth, gt, mask, flows)
  assert opw[1] == 0.0 and opw[0] == opw[2] == opw[3] == pytest.approx(2.0, rel=1e-5)


def test_opw_weight_of_exactly_one_percent_is_dropped():
  """V_t = [weight > 0.01], strict: a pixel whose mask product m_t m_{t+1} is exactly 0.01
  (photometric weight 1 on a black video) is left out. With a +1 px flow, column 0 samples
  column 1 of frame 1 (depth 20 against 10: error 10) under the weight 1 * 0.01; the other
  pixels inside the frame have error |12 - 10| = 2, so OPW is 2 without column 0."""
  t, h, w = 2, 5, 17
  depth = np.full((t, h, w), 10.0, np.float32)
  depth[1] = 12.0
  depth[1, :, 1] = 20.0
  mask = np.ones_like(depth)
  mask[1, :, 0] = 0.01
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  flows[:, 0] = 1.0
  opw = M.eval_opw_sequence(video, depth, depth, mask, flows)
  np.testing.assert_allclose(opw, 2.0, rtol=1e-5)


def test_rtc_counts_an_overflowing_depth_ratio_as_consistent():
  """The official RTC sets an infinite ratio to -1e10 before max(x_t / W_t, W_t / x_t) < 1.01:
  where x_t / W_t overflows float32 (3e38 / 1e-3), the max is the other ratio, ~0, and the
  pixel counts as consistent (RTC 1, not 0), however inconsistent the depths are."""
  t, h, w = 2, 4, 6
  depth = np.full((t, h, w), 3e38, np.float32)
  depth[1] = 1e-3
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  mask = np.ones_like(depth)
  gt = np.full_like(depth, 10.0)
  with np.errstate(over="ignore"):  # (the overflow this test is about)
    assert M.eval_rtc_sequence(video, depth, gt, mask, flows) == (1.0, 1.0)
  depth[0] = 1e3  # a finite ratio of 1e6: inconsistent
  assert M.eval_rtc_sequence(video, depth, gt, mask, flows) == (0.0, 0.0)


def test_rtc_ratio_threshold_and_masked_out_depths():
  """RTC's ratio test is strict (< 1.01): depths 1.01 against 1 (float32, as the reference
  compares) are inconsistent, the float just below 1.01 consistent. A pixel of mask 0.4 at t
  (x_t masked to 0, but V_t weighs 0.4 > 0.01) has W_t / x_t = inf, set to -1e10, and
  x_t / W_t = 0: it counts as consistent, as in the official code. W = 17, H = 5 keeps
  grid_sample's round trip exact."""
  t, h, w = 2, 5, 17
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  mask = np.ones((t, h, w), np.float32)
  gt = np.full((t, h, w), 10.0, np.float32)
  depth = np.ones((t, h, w), np.float32)
  depth[0] = 1.01
  assert M.eval_rtc_sequence(video, depth, gt, mask, flows) == (0.0, 0.0)
  depth[0] = np.nextafter(np.float32(1.01), np.float32(0))
  assert M.eval_rtc_sequence(video, depth, gt, mask, flows) == (1.0, 1.0)
  depth[0] = 2.0  # ratio 2 everywhere ...
  mask[0, :, :5] = 0.4  # ... but the 5 columns masked out at t count as consistent
  assert M.eval_rtc_sequence(video, depth, gt, mask, flows) == (5 / 17, 5 / 17)


def test_two_frames_without_a_pixel_valid_in_both_are_noted():
  """no_valid_pair holds from T = 2 frames on: two frames whose valid pixels lie in different
  places leave TEPE's only pair empty, and the note says so (a note for T > 2 only left the
  two-frame case silent); one frame has no pair at all (its own note, T=1)."""
  mask = np.zeros((2, 2, 2), np.float32)
  mask[0, 0] = 1
  mask[1, 1] = 1
  assert M.no_valid_pair(mask) and not M.no_valid_pair(np.ones_like(mask))
  assert not M.no_valid_pair(mask[:1])
  assert M.not_measured_note(mask).startswith(
      "valid has no pixel valid in two consecutive frames (TEPE's pairs)")


def test_negative_infinite_ground_truth_is_refused_by_eval_batch_too():
  """eval_batch takes the GT as it is (no |gt|): -inf at a valid pixel would give an infinite
  EPE as +inf does, and is refused the same way."""
  gt = np.full((2, 3, 3), 4.0, np.float32)
  gt[1, 2, 2] = -np.inf
  with pytest.raises(ValueError, match=r"^gt is infinite at valid pixels of mask in frame\(s\) "
                                       r"\[1\]"):
    M.eval_batch(np.ones_like(gt), gt, np.ones_like(gt))


def test_tcc_weighs_depth_changes_by_the_fractional_mask():
  """eval_batch's TCC multiplies the depth changes by m_t m_{t+1} of the fractional mask as
  given (the official delta_mask), not a rounded one: against SSIM written out by hand."""
  rng = np.random.default_rng(9)
  disp = rng.uniform(2, 8, (2, 12, 12)).astype(np.float32)
  pred = disp + rng.normal(0, 0.3, disp.shape).astype(np.float32)
  mask = rng.uniform(0.6, 1.0, disp.shape).astype(np.float32)
  res, _ = M.eval_batch(pred, disp, mask, scale=20.0)
  zx, zy = np.float32(20.0) / pred, np.float32(20.0) / disp
  dm = (mask[0] * mask[1]).astype(np.float64)
  want = _ssim_by_hand(np.abs(zx[0] - zx[1]) * dm, np.abs(zy[0] - zy[1]) * dm)
  assert 0.1 < want < 0.99
  assert res["disp_TCC"] == pytest.approx(want, rel=1e-6)


def test_depth_of_a_disparity_at_or_below_zero_is_the_scale_over_1e_10():
  """Z = s / max(d, 1e-10): a disparity of 0, a negative one or one below 1e-10 takes the
  clamp 1e-10 (depth s * 1e10, which OPW / RTC then weigh at a valid pixel)."""
  z = M.disparity_to_depth(np.array([0.0, -2.0, 1e-12, 4.0], np.float32), 3.0)
  np.testing.assert_allclose(z, [3e10, 3e10, 3e10, 0.75], rtol=1e-6)


def test_opw_and_rtc_of_a_pair_with_one_valid_pixel_score_that_pixel():
  """A pair whose V_t keeps one pixel is measured there (a pair with none adds 0): zero flow
  and a black video (W_t = x_{t+1}, photometric weight 1), depth 10 then 10.05 at the only
  valid pixel: OPW 0.05 (GT depth 10, in every band), RTC 1 (ratio 1.005 < 1.01)."""
  t, h, w = 2, 5, 17
  depth = np.full((t, h, w), 10.0, np.float32)
  depth[1, 2, 3] = 10.05
  mask = np.zeros((t, h, w), np.float32)
  mask[:, 2, 3] = 1
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  gt = np.full_like(depth, 10.0)
  np.testing.assert_allclose(M.eval_opw_sequence(video, depth, gt, mask, flows), 0.05,
                             rtol=1e-4)
  assert M.eval_rtc_sequence(video, depth, gt, mask, flows) == (1.0, 1.0)


def test_tcm_weighs_flows_by_the_fractional_mask_as_given():
  """TCM's M_t is m_t m_{t+1} of the mask as given (0.6 * 0.6 = 0.36 here, below 0.5), not a
  thresholded one: agreeing flows score 1, and differing ones the per-channel SSIM of the
  flows times 0.36, written out by hand (SSIM's constants make the weight matter)."""
  rng = np.random.default_rng(10)
  fy = rng.normal(0, 0.5, (1, 2, 16, 16)).astype(np.float32)
  fx = (fy + rng.normal(0, 0.3, fy.shape)).astype(np.float32)
  mask = np.full((2, 16, 16), 0.6, np.float32)
  assert M.eval_tcm_sequence(fy, fy, mask) == pytest.approx(1.0, rel=1e-12)
  sel = np.float64(np.float32(0.6) * np.float32(0.6))
  want = np.mean([max(_ssim_by_hand(fx[0, c] * sel, fy[0, c] * sel), 0) for c in (0, 1)])
  assert 0.05 < want < 0.95
  assert want != pytest.approx(np.mean([_ssim_by_hand(fx[0, c], fy[0, c]) for c in (0, 1)]),
                               rel=1e-3)
  assert M.eval_tcm_sequence(fx, fy, mask) == pytest.approx(want, rel=1e-5)


def test_flows_below_minus_250_px_are_kept():
  """'No flow component > 250' is signed, as the official rule: a flow of -300 or -251 px (a
  large motion left or up) keeps its pixels in TCM's M_t and OPW's V_t; only components
  above +250 drop them."""
  rng = np.random.default_rng(11)
  fy = rng.normal(0, 2, (1, 2, 16, 16)).astype(np.float32)
  fx = fy.copy()
  fy[0, 1, 4:8, 4:8] = -300.0  # kept: the disagreement with fx counts
  want = np.mean([max(_ssim_by_hand(fx[0, c], fy[0, c]), 0) for c in (0, 1)])
  assert want < 0.99
  assert M.eval_tcm_sequence(fx, fy, np.ones((2, 16, 16), np.float32)) == pytest.approx(
      want, rel=1e-6)
  # OPW: a -251 px flow samples columns 0..5 of frame 1 from columns 251..256 of frame 0;
  # depth 10 then 12 on a black video: OPW |12 - 10| = 2 there (0 if they were dropped).
  # W = 257: grid_sample's round trip (a division by W - 1 = 256) is exact.
  t, h, w = 2, 2, 257
  depth = np.full((t, h, w), 10.0, np.float32)
  depth[1] = 12.0
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  flows[:, 0] = -251.0
  opw = M.eval_opw_sequence(video, depth, depth, np.ones_like(depth), flows)
  np.testing.assert_allclose(opw, 2.0, rtol=1e-5)


def test_a_mask_threshold_of_zero_keeps_every_positive_weight():
  """mask_thr is in [0, 1): 0 keeps every pixel of weight > 0, which then weighs the error
  (sqrt(0.25 * 2^2) = 1); the default 0.5 drops weights of 0.25 (all errors 0)."""
  gt = np.zeros((2, 4, 4), np.float32)
  mask = np.full_like(gt, 0.25)
  res = M.eval_endpoint_error_sequence(gt + 2, gt, mask, mask_thr=0)
  assert res["epe_mean"] == pytest.approx(1.0)
  assert res["epe_bad_0.5px"] == 100.0 and res["epe_bad_1px"] == 0.0
  assert M.eval_endpoint_error_sequence(gt + 2, gt, mask)["epe_mean"] == 0.0


def test_infinite_ground_truth_under_a_weight_of_one_half_is_masked_out_not_refused():
  """Valid is mask > 0.5: an inf GT under a weight of 0.5 or 0.3 is masked out (0, as NaN GT
  is), so eval_batch takes it and scores as for a finite GT value there."""
  rng = np.random.default_rng(12)
  gt = rng.uniform(2, 8, (2, 4, 4)).astype(np.float32)
  pred = gt + rng.normal(0, 1, gt.shape).astype(np.float32)
  mask = np.ones_like(gt)
  mask[1, 2, 2], mask[0, 1, 1] = 0.5, 0.3
  inf_gt = gt.copy()
  inf_gt[1, 2, 2], inf_gt[0, 1, 1] = np.inf, -np.inf
  assert M.eval_batch(pred, inf_gt, mask) == M.eval_batch(pred, gt, mask)


def test_opw_drops_pixels_where_any_flow_component_is_above_250():
  """V_t's [no F_t component > 250] is strict and per component: a flow of (250, 0) px keeps
  the pixels that sample inside the frame (columns 0..6 of 257; depth 10 then 12 on a black
  video: OPW 2), a flow of (251, 0) drops them all (one component above 250 is enough), so
  the pair adds 0. W = 257 keeps grid_sample's round trip exact."""
  t, h, w = 2, 2, 257
  depth = np.full((t, h, w), 10.0, np.float32)
  depth[1] = 12.0
  video = np.zeros((t, 3, h, w), np.uint8)
  flows = np.zeros((t - 1, 2, h, w), np.float32)
  mask = np.ones_like(depth)
  flows[:, 0] = 250.0
  np.testing.assert_allclose(M.eval_opw_sequence(video, depth, depth, mask, flows), 2.0,
                             rtol=1e-5)
  flows[:, 0] = 251.0
  assert M.eval_opw_sequence(video, depth, depth, mask, flows) == (0.0, 0.0, 0.0, 0.0)

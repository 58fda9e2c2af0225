"""Validation during training scores what the official evaluator scores."""

import types

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from sav_jax import metrics
from tests.official_metrics import epe_tepe_by_hand
from train import evaluation
from train import state as state_lib


class _SignFlippingModel:
  """Stands in for the model: predicts the clip's ground truth with the sign flipped on the
  left half of every frame (what a young model can do)."""

  def apply(self, variables, left, right, *, iters, final_only):
    del variables, right, iters
    assert final_only
    disparity = left[..., 0]  # the tests put the ground truth there
    sign = jnp.where(jnp.arange(disparity.shape[-1]) < disparity.shape[-1] // 2, -1.0, 1.0)
    return types.SimpleNamespace(disparities=(disparity * sign)[None])


def test_validation_scores_the_absolute_prediction_as_the_official_evaluator():
  rng = np.random.default_rng(0)
  clips = []
  for _ in range(3):
    gt = rng.uniform(1.0, 20.0, (3, 8, 16)).astype(np.float32)
    left = np.repeat(gt[..., None], 3, axis=-1)
    clips.append({"left": left, "right": left.copy(), "disparity": gt,
                  "valid": np.ones_like(gt, dtype=bool)})
  config = ml_collections.ConfigDict({"eval": {"batch_size": 2, "iters": 2,
                                               "dataset": "synthetic"}})
  mesh = state_lib.make_mesh(jax.devices()[:1])
  ev = evaluation.Evaluator(config, _SignFlippingModel(), state_lib.replicated(mesh), mesh,
                            clips=clips)
  # batches of eval.batch_size clips, the last one padded: (clips, real clips)
  assert [(b["left"].shape[0], n) for b, n in ev.batches] == [(2, 2), (2, 1)]
  preds = ev.predictions({})
  assert len(preds) == 3 and all(p.shape == (3, 8, 16) for p in preds)
  result = ev({})
  # `forward_batch_test` returns |prediction|: here exactly the ground truth.
  assert result["epe"] == 0.0 and result["tepe"] == 0.0
  signed = metrics.eval_sequence(-clips[0]["disparity"], clips[0]["disparity"],
                                 np.ones((3, 8, 16), np.float32))
  assert signed["disp_epe_mean"] > 1.0  # what scoring the signed prediction would give


def test_validation_runs_the_configured_number_of_iterations():
  seen = []

  class Recording(_SignFlippingModel):
    def apply(self, variables, left, right, *, iters, final_only):
      seen.append(iters)
      return super().apply(variables, left, right, iters=iters, final_only=final_only)

  gt = np.full((2, 8, 16), 3.0, np.float32)
  clips = [{"left": np.repeat(gt[..., None], 3, axis=-1), "right": np.zeros((2, 8, 16, 3)),
            "disparity": gt, "valid": np.ones_like(gt, dtype=bool)}]
  config = ml_collections.ConfigDict({"eval": {"batch_size": 1, "iters": 6,
                                               "dataset": "synthetic"}})
  mesh = state_lib.make_mesh(jax.devices()[:1])
  ev = evaluation.Evaluator(config, Recording(), state_lib.replicated(mesh), mesh, clips=clips)
  assert ev({})["epe"] == 0.0 and seen == [6]


class _DivergedModel:
  """Stands in for weights that diverged: NaN everywhere."""

  def apply(self, variables, left, right, *, iters, final_only):
    del variables, right, iters, final_only
    return types.SimpleNamespace(disparities=jnp.full(left.shape[:-1], jnp.nan)[None])


def test_clips_without_ground_truth_are_left_out_and_nan_predictions_score_nan(caplog):
  """A clip without a valid pixel (sparse GT outside the crop) scored a perfect 0 and pulled
  the means down; a diverged model's NaN stopped the run with a traceback, and its resume too
  (the catch-up validation of the saved step)."""
  rng = np.random.default_rng(1)
  clips = []
  for _ in range(3):
    gt = rng.uniform(1.0, 20.0, (3, 8, 16)).astype(np.float32)
    left = np.repeat(gt[..., None] + 1.0, 3, axis=-1)  # the stand-in predicts gt + 1: EPE 1
    clips.append({"left": left, "right": left.copy(), "disparity": gt,
                  "valid": np.ones_like(gt, dtype=bool)})
  clips[1]["valid"][:] = False
  clips[2]["valid"][1::2] = False  # no pixel valid in two consecutive frames: TEPE 0
  with caplog.at_level("WARNING"):
    kept = evaluation.measured_clips(clips, "kitti_depth")
  assert len(kept) == 2 and kept[1] is clips[2]
  assert ("1 of the 3 clips of kitti_depth have no valid ground-truth pixel (sparse ground "
          "truth outside the crop?) and are left out") in caplog.text
  assert "1 of the 2 clips of kitti_depth are measured in part" in caplog.text
  assert "no pixel valid in two consecutive frames" in caplog.text
  config = ml_collections.ConfigDict({"eval": {"batch_size": 1, "iters": 2,
                                               "dataset": "kitti_depth"}})
  mesh = state_lib.make_mesh(jax.devices()[:1])
  model = _SignFlippingModel()
  ev = evaluation.Evaluator(config, model, state_lib.replicated(mesh), mesh, clips=kept)
  assert ev.described.startswith("2 clips of kitti_depth")
  one = evaluation.Evaluator(config, model, state_lib.replicated(mesh), mesh, clips=kept[:1])
  assert one.described.startswith("1 clip of kitti_depth (3 frames)")
  assert ev({})["epe"] == pytest.approx(1.0)  # with the empty clip's 0 it was 2/3
  caplog.clear()
  diverged = evaluation.Evaluator(config, _DivergedModel(), state_lib.replicated(mesh), mesh,
                                  clips=kept)
  with caplog.at_level("WARNING"):
    scores = diverged({})
  assert scores and all(np.isnan(v) for v in scores.values())
  assert "the predictions of 2 of the 2 clips hold NaN or inf" in caplog.text
  for clip in clips:
    clip["valid"][:] = False
  with pytest.raises(ValueError, match=r"config.eval.dataset='kitti_depth': none of the 3 "
                                       r"validation clips has a valid ground-truth pixel"):
    evaluation.measured_clips(clips, "kitti_depth")


class _OffByModel(_SignFlippingModel):
  """Predicts the ground truth (from the left image) plus a fixed per-pixel offset, with the
  sign of the left half flipped (|prediction| is scored)."""

  def __init__(self, offset):
    self.offset = offset

  def apply(self, variables, left, right, *, iters, final_only):
    out = super().apply(variables, left + self.offset[..., None], right, iters=iters,
                        final_only=final_only)
    return out


def test_validation_scores_are_frame_weighted_means_of_each_named_metric(caplog):
  """Each logged score is the official metric its name says, averaged over the clips weighted by
  their frames (computed here by hand); a prediction holding inf scores NaN as NaN does."""
  rng = np.random.default_rng(2)
  clips, hand = [], []
  offset = rng.normal(0, 2.5, (8, 16)).astype(np.float32)  # errors across the bad-N thresholds
  for frames in (2, 5):
    gt = rng.uniform(1.0, 20.0, (frames, 8, 16)).astype(np.float32)
    valid = rng.random((frames, 8, 16)) > 0.25
    left = np.repeat(gt[..., None], 3, axis=-1)
    clips.append({"left": left, "right": left.copy(), "disparity": gt, "valid": valid})
    hand.append((epe_tepe_by_hand(np.abs(gt + offset), gt, valid, taus=(1, 3)), frames))
  config = ml_collections.ConfigDict({"eval": {"batch_size": 1, "iters": 2,
                                               "dataset": "synthetic"}})
  mesh = state_lib.make_mesh(jax.devices()[:1])
  ev = evaluation.Evaluator(config, _OffByModel(offset), state_lib.replicated(mesh), mesh,
                            clips=clips)
  assert ev.described == "2 clips of synthetic (2/5 frames), 2 iterations"
  scores = ev({})
  names = {"epe": "epe_mean", "tepe": "temp_epe_mean", "bad_1px": "epe_bad_1px",
           "bad_3px": "epe_bad_3px", "temp_bad_1px": "temp_epe_bad_1px"}
  assert set(scores) == set(names)
  for short, key in names.items():
    want = sum(h[key] * n for h, n in hand) / 7
    assert scores[short] == pytest.approx(want, rel=1e-5), short
  assert len({round(v, 6) for v in scores.values()}) == len(names)  # (distinct: no mix-up)

  class _InfModel(_SignFlippingModel):
    def apply(self, variables, left, right, *, iters, final_only):
      out = super().apply(variables, left, right, iters=iters, final_only=final_only)
      return types.SimpleNamespace(disparities=out.disparities.at[..., 0, 0].set(jnp.inf))

  diverged = evaluation.Evaluator(config, _InfModel(), state_lib.replicated(mesh), mesh,
                                  clips=clips)
  with caplog.at_level("WARNING"):
    scores = diverged({})
  assert set(scores) == set(names) and all(np.isnan(v) for v in scores.values())
  assert "the predictions of 2 of the 2 clips hold NaN or inf" in caplog.text
  with pytest.raises(ValueError, match="eval.batch_size=4 is not divisible by the 3 devices of "
                     "the mesh's 'data' axis"):
    evaluation.Evaluator(ml_collections.ConfigDict({"eval": {"batch_size": 4, "iters": 2,
                                                             "dataset": "synthetic"}}),
                         _InfModel(), None, jax.sharding.Mesh(np.array(jax.devices()[:1] * 3),
                                                              ("data",)), clips=clips)

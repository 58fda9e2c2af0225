"""Validation during training scores what the official evaluator scores."""

import types

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from sav_jax import metrics
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
  preds = ev.predictions({})
  assert len(preds) == 3 and all(p.shape == (3, 8, 16) for p in preds)
  result = ev({})
  # `forward_batch_test` returns |prediction|: here exactly the ground truth.
  assert result["epe"] == 0.0 and result["tepe"] == 0.0
  signed = metrics.eval_sequence(-clips[0]["disparity"], clips[0]["disparity"],
                                 np.ones((3, 8, 16), np.float32))
  assert signed["disp_epe_mean"] > 1.0  # what scoring the signed prediction would give

"""One train step of the real model on 8 fake CPU devices equals the step on 1 device.

The check runs in a subprocess (`python -m tests.train.test_sharding OUT`, started by
conftest.py with `XLA_FLAGS=--xla_force_host_platform_device_count=8`), because the
other tests have already initialised JAX with one device in this process. The child also
feeds a NaN batch to the 8-device step: the update must be skipped and counted.

Tolerances: loss and metrics rtol 1e-5 (the gradient all-reduce over 8 devices sums in a
different order than one device does: we see 7e-8 relative on the loss), the global
gradient norm rtol 1e-4 (a float32 sum of 9e6 squares; we see up to 1.5e-5). Parameters
after the update: allclose with rtol 1e-6 and atol 5e-7, i.e. 5e-3 of the step size
lr = 1e-4 (we see at most 1.5e-7). This needs AdamW's eps raised to 1e-3 in this test:
Adam's first update is lr * g / (|g| + eps), so with the default eps = 1e-8 a gradient
entry at rounding level (|g| ~ 1e-9) whose sign differs between the two reductions moves
by up to 2 lr (with eps = 1e-8 we saw 7e-5 of the entries do so).

The step runs the model on each device's own clips (`train.step.per_device_apply`); the
reference is the step traced for one device.

The initial parameters are the parity fixtures' deterministic official-layout weights
(converted, then placed on the 8-device mesh), which also spares a compilation of the
random initialiser.
"""

import json
import re
import sys

import numpy as np
import pytest

STEP_LR = 1e-4


@pytest.mark.train_job("sharding")
def test_eight_devices_match_one_device(jobs):
  result = json.loads(jobs.get("sharding").read_text())
  assert result["devices"] == 8 and result["mesh8"] == {"data": 8}
  np.testing.assert_allclose(result["loss8"], result["loss1"], rtol=1e-5)
  for k in ("epe", "1px", "3px"):
    np.testing.assert_allclose(result["metrics8"][k], result["metrics1"][k], rtol=1e-5, err_msg=k)
  # A float32 sum of 9e6 squares: its rounding depends on the summation order.
  np.testing.assert_allclose(result["metrics8"]["l2_grads"], result["metrics1"]["l2_grads"],
                             rtol=1e-4)
  assert result["param_max_scaled_diff"] <= 1.0  # allclose(rtol=1e-6, atol=5e-7)
  assert result["param_max_abs_diff"] <= 5e-3 * STEP_LR
  assert result["changed_fraction"] > 0.5  # the step did update the parameters
  assert result["frozen_unchanged"]


@pytest.mark.train_job("sharding")
def test_each_device_runs_the_model_on_its_own_clips(jobs):
  # The gradient's all-reduce and nothing else: traced on the global batch, the model's
  # concatenation of the views along the batch axis (and the slices back) moved frames and
  # feature maps between the devices in every step (3 all-to-alls, 26 collective permutes
  # here), and frame blocks (`model.frame_block_mb`) gathered every clip to every device.
  result = json.loads(jobs.get("sharding").read_text())
  assert set(result["step_collectives"]) == {"all-reduce"}, result["step_collectives"]
  assert result["eval_collectives"] == {}


@pytest.mark.train_job("sharding")
def test_microbatches_on_eight_devices_give_the_whole_batchs_step(jobs):
  result = json.loads(jobs.get("sharding").read_text())
  for k, (whole, parts) in result["toy_micro_metrics"].items():
    np.testing.assert_allclose(parts, whole, rtol=1e-5, err_msg=k)
  assert result["toy_micro_param_diff"] <= 1e-3 * result["toy_step_size"]


@pytest.mark.train_job("sharding")
def test_nan_batch_is_skipped_and_counted_on_eight_devices(jobs):
  result = json.loads(jobs.get("sharding").read_text())
  assert result["nan_loss_finite"] is False
  assert result["nan_num_skipped"] == 1 and result["nan_step"] == 2
  assert result["nan_params_unchanged"] and result["nan_opt_state_unchanged"]


@pytest.mark.train_job("sharding")
def test_dft_row_blocks_keep_a_sharded_batch_on_its_devices(jobs):
  result = json.loads(jobs.get("sharding").read_text())
  assert result["dft_block_collectives"] == 0  # (blocks of all rows: 30 all-to-alls and more)
  assert result["dft_block_max_diff"] <= 2e-6 * result["dft_block_scale"]  # float32 rounding


@pytest.mark.train_job("sharding")
def test_each_device_draws_its_own_random_numbers(jobs):
  # One key for the step: every device drew the same dropout mask for its own clips.
  result = json.loads(jobs.get("sharding").read_text())
  assert result["dropout_distinct_masks"] == 8
  assert result["dropout_keep_fraction"] == pytest.approx(0.5, abs=0.05)


@pytest.mark.train_job("sharding")
def test_a_mesh_with_a_second_axis_gives_the_one_device_step_and_predictions(jobs):
  # data=4 x model=2 (the model axis holds copies) and data=8 against one device, toy model:
  # the step (the gradient's transpose through shard_map on both axes), the validation's
  # predictions, and one compilation each for two steps and two predictions.
  result = json.loads(jobs.get("sharding").read_text())
  for name in ("8", "4x2"):
    toy = result["toy_meshes"][name]
    np.testing.assert_allclose(toy["loss"], result["toy_meshes"]["1"]["loss"], rtol=1e-6)
    np.testing.assert_allclose(toy["l2_grads"], result["toy_meshes"]["1"]["l2_grads"], rtol=1e-5)
    assert toy["param_diff"] <= 1e-3 * toy["step_size"], name
    assert toy["eval_diff"] <= 1e-5 * toy["eval_scale"], name
    assert toy["compilations"] == [1, 1], name


def _config():
  from configs import synthetic  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  c.data.frames, c.data.crop, c.train.iters, c.train.batch_size = 2, (32, 32), 2, 8
  c.data.synthetic.max_disparity, c.data.num_threads = 8.0, 1
  c.optimizer.lr, c.optimizer.schedule_steps, c.optimizer.div_factor = STEP_LR, 400, 1.0
  c.optimizer.eps = 1e-3
  return c


def _compare(p8, p1, before, frozen):
  import jax  # pylint: disable=g-import-not-at-top
  diffs = [np.abs(np.asarray(a) - np.asarray(b)).ravel()
           for a, b in zip(jax.tree.leaves(p8), jax.tree.leaves(p1))]
  d = np.concatenate(diffs)
  scale = np.concatenate([5e-7 + 1e-6 * np.abs(np.asarray(b)).ravel()
                          for b in jax.tree.leaves(p1)])
  moved = np.concatenate([(np.asarray(a) != np.asarray(b)).ravel()
                          for a, b in zip(jax.tree.leaves(p8), jax.tree.leaves(before))])
  frozen_same = all(np.array_equal(a, b) for a, b in zip(
      jax.tree.leaves(p8["depthnet"]["depthanything"]), jax.tree.leaves(frozen)))
  n_frozen = sum(np.size(x) for x in jax.tree.leaves(frozen))
  return {"param_max_abs_diff": float(d.max()),
          "param_max_scaled_diff": float(np.max(d / scale)),
          "changed_fraction": float(moved.sum() / (moved.size - n_frozen)),
          "frozen_unchanged": bool(frozen_same)}


def _initial_params(cfg):
  """Host params from the parity fixtures' official-layout weights (seed 0)."""
  import sav_jax  # pylint: disable=g-import-not-at-top
  from tests.conftest import FIXTURES, _load_make_weights  # pylint: disable=g-import-not-at-top
  sd = _load_make_weights().make_state_dict(str(FIXTURES / "sav_manifest.json"), 0)
  return sav_jax.convert.params_from_state_dict(sd, cfg)["params"]


def _toy_microbatches() -> dict:
  """A step of the toy model of test_state on the 8 devices: batch 16 as 2 parts of 8 clips
  (`train.microbatches`, each part sharded over the devices) against the whole batch."""
  import jax  # pylint: disable=g-import-not-at-top
  from tests.train import test_state as ts  # pylint: disable=g-import-not-at-top
  got = {}
  for k in (1, 2):
    c = ts._config()  # pylint: disable=protected-access
    c.train.batch_size, c.train.microbatches = 16, k
    _, mesh, _, state, _, step = ts._setup(c)  # pylint: disable=protected-access
    batch = ts._put(ts._batch(np.random.default_rng(0), c), mesh)  # pylint: disable=protected-access
    before = jax.device_get(state.params)  # (the step donates the state)
    got[k] = jax.device_get(step(state, batch))
  diff = max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
             for a, b in zip(jax.tree.leaves(got[1][0].params), jax.tree.leaves(got[2][0].params)))
  moved = max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
              for a, b in zip(jax.tree.leaves(got[1][0].params), jax.tree.leaves(before)))
  return {"toy_micro_param_diff": diff, "toy_step_size": moved,
          "toy_micro_metrics": {k: [float(got[1][1][k]), float(got[2][1][k])]
                                for k in ("loss", "epe", "l2_grads")}}


def _toy_meshes() -> dict:
  """Two steps and two validation predictions of the toy model of test_state (batch 8) on one
  device, on data=8 and on data=4 x model=2, from the same state."""
  import jax  # pylint: disable=g-import-not-at-top
  from jax.sharding import Mesh  # pylint: disable=g-import-not-at-top
  from tests.train import test_state as ts  # pylint: disable=g-import-not-at-top
  from train import optim, state as S, step as st  # pylint: disable=g-import-not-at-top
  c = ts._config()  # pylint: disable=protected-access
  c.train.batch_size = 8
  model = ts.ToyStereo()
  labels = optim.param_labels(S.abstract_params(model, c), c.optimizer.frozen)
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  batches = [ts._batch(np.random.default_rng(i), c) for i in (0, 1)]  # pylint: disable=protected-access
  meshes = {"1": S.make_mesh(jax.devices()[:1]), "8": S.make_mesh(),
            "4x2": Mesh(np.asarray(jax.devices()).reshape(4, 2), (S.DATA_AXIS, "model"))}
  host0, got = None, {}
  for name, mesh in meshes.items():
    state, sh = S.create_train_state(model, tx, c, mesh)
    host0 = jax.device_get(state) if host0 is None else host0
    step = st.jit_train_step(st.make_train_step(model, tx, c, labels, mesh), sh, mesh)
    predict = st.make_eval_fn(model, 2, sh.params, mesh)
    state, metrics = step(jax.device_put(host0, sh), ts._put(batches[0], mesh))  # pylint: disable=protected-access
    params, metrics = jax.device_get((state.params, metrics))
    state, _ = step(state, ts._put(batches[1], mesh))  # pylint: disable=protected-access
    b = ts._put(batches[0], mesh)  # pylint: disable=protected-access
    preds = [np.asarray(predict(state.params, b["left"], b["right"])) for _ in range(2)]
    got[name] = (params, metrics, preds[0],
                 [step._cache_size(), predict._cache_size()])  # pylint: disable=protected-access
  out = {}
  for name, (params, metrics, pred, compilations) in got.items():
    p1, _, pred1, _ = got["1"]
    out[name] = {
        "loss": float(metrics["loss"]), "l2_grads": float(metrics["l2_grads"]),
        "param_diff": max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
                          for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(p1))),
        "step_size": max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
                         for a, b in zip(jax.tree.leaves(p1), jax.tree.leaves(host0.params))),
        "eval_diff": float(np.abs(pred - pred1).max()), "eval_scale": float(np.abs(pred1).max()),
        "compilations": compilations}
  return {"toy_meshes": out}


def _dropout_on_eight_devices() -> dict:
  """`per_device_apply` of a model that only drops out (rate 1/2) a batch of 8 clips of ones on
  the 8 devices, with the one `dropout` key of a step: the masks of the clips, which the
  devices draw each for their own."""
  import flax.linen as nn  # pylint: disable=g-import-not-at-top
  import jax  # pylint: disable=g-import-not-at-top
  import jax.numpy as jnp  # pylint: disable=g-import-not-at-top
  from sav_jax.model.stereo_any_video import SAVOutput  # pylint: disable=g-import-not-at-top
  from train import state as S, step as st  # pylint: disable=g-import-not-at-top

  class Dropping(nn.Module):
    @nn.compact
    def __call__(self, left, right, iters=2, final_only=False):
      return SAVOutput(disparities=nn.Dropout(0.5, deterministic=False)(left[None, ..., 0]))

  mesh = S.make_mesh()
  ones = jax.device_put(jnp.ones((8, 2, 16, 16, 3)), S.data_sharding(mesh))
  apply = jax.jit(lambda x: st.per_device_apply(Dropping(), mesh)(
      {}, x, x, rngs={"dropout": jax.random.key(0)}).disparities)
  masks = np.asarray(apply(ones))[0] > 0
  return {"dropout_distinct_masks": len({m.tobytes() for m in masks}),
          "dropout_keep_fraction": float(masks.mean())}


def _dft_blocks_on_eight_devices() -> dict:
  """The GRU's DFT products (`layers.dft_correlate_w`) on a batch sharded over the 8 devices,
  in row blocks: blocks split the rows after the batch axis, so no device trades rows."""
  import jax  # pylint: disable=g-import-not-at-top
  import jax.numpy as jnp  # pylint: disable=g-import-not-at-top
  from jax.sharding import NamedSharding, PartitionSpec as P  # pylint: disable=g-import-not-at-top
  from sav_jax.model.layers import dft_correlate_w  # pylint: disable=g-import-not-at-top
  from train import state as S  # pylint: disable=g-import-not-at-top
  rng = np.random.default_rng(0)
  x = jax.device_put(jnp.asarray(rng.standard_normal((8, 4, 20, 6)), jnp.float32),
                     NamedSharding(S.make_mesh(), P("data")))
  kernel = jnp.asarray(rng.standard_normal((15, 6, 5)), jnp.float32)
  blocked = jax.jit(lambda a: dft_correlate_w(a, kernel, 1e-9))  # 4 blocks of 8 x 1 rows
  hlo = blocked.lower(x).compile().as_text()
  whole = jax.jit(lambda a: dft_correlate_w(a, kernel))(x)
  diff = float(jnp.abs(blocked(x) - whole).max())
  return {"dft_block_scale": float(jnp.abs(whole).max()),"dft_block_collectives": sum(hlo.count(op) for op in ("all-to-all(",
                                                                 "collective-permute(",
                                                                 "all-gather(")),
          "dft_block_max_diff": diff}


def _collectives(hlo: str) -> dict:
  """Collective operations of a compiled program's text, counted by kind."""
  found = re.findall(r"\b(all-gather|all-to-all|collective-permute|all-reduce|reduce-scatter)"
                     r"(?:-start)?\(", hlo)
  return {op: found.count(op) for op in sorted(set(found))}


def _child(out_path):
  """Runs in a fresh process with 8 CPU devices."""
  import jax  # pylint: disable=g-import-not-at-top
  import sav_jax  # pylint: disable=g-import-not-at-top
  from sav_jax.data import pipeline  # pylint: disable=g-import-not-at-top
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  from train import optim, state as S, step as st  # pylint: disable=g-import-not-at-top
  out = _toy_microbatches()
  out.update(_dft_blocks_on_eight_devices())
  out.update(_dropout_on_eight_devices())
  out.update(_toy_meshes())
  c = _config()
  model = sav_jax.StereoAnyVideo(S.model_config(c))
  params = S.abstract_params(model, c)
  labels = optim.param_labels(params, c.optimizer.frozen)
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  batch = next(iter(input_lib.train_dataset(c, process_index=0, process_count=1)))
  batch = dict(batch, left=batch["left"].astype(np.float32),
               right=batch["right"].astype(np.float32))
  mesh8, mesh1 = S.make_mesh(), S.make_mesh(jax.devices()[:1])
  placed = S.place_params(_initial_params(S.model_config(c)), params, mesh8)
  jax.config.update("jax_transfer_guard", "disallow")
  state8, sh8 = S.create_train_state(model, tx, c, mesh8, params=placed)
  host0 = jax.device_get(state8)
  step8 = st.jit_train_step(st.make_train_step(model, tx, c, labels, mesh8), sh8, mesh8)
  batch8 = pipeline.to_global(batch, S.data_sharding(mesh8))
  compiled8 = step8.lower(state8, batch8).compile()
  out["step_collectives"] = _collectives(compiled8.as_text())
  eval8 = st.make_eval_fn(model, 2, sh8.params, mesh8)
  out["eval_collectives"] = _collectives(eval8.lower(
      state8.params, batch8["left"], batch8["right"]).compile().as_text())
  new8, m8 = compiled8(state8, batch8)
  host8, m8 = jax.device_get((new8, m8))
  # The reference: the step traced for one device (the model's forward on the whole batch).
  sh1 = S.state_shardings(host0, mesh1)
  step1 = st.jit_train_step(st.make_train_step(model, tx, c, labels, mesh1), sh1, mesh1)
  new1, m1 = step1(jax.device_put(host0, sh1), pipeline.to_global(batch, S.data_sharding(mesh1)))
  host1, m1 = jax.device_get((new1, m1))
  out.update({"devices": jax.device_count(), "mesh8": dict(mesh8.shape), "loss8": float(m8["loss"]),
         "loss1": float(m1["loss"]), "metrics8": {k: float(v) for k, v in m8.items()},
         "metrics1": {k: float(v) for k, v in m1.items()}})
  out.update(_compare(host8.params, host1.params, host0.params,
                      host0.params["depthnet"]["depthanything"]))
  nan_batch = dict(batch, left=batch["left"].copy())
  nan_batch["left"][3, 1, 7, 9, 0] = np.nan
  after, mn = jax.device_get(compiled8(jax.device_put(host8, sh8), pipeline.to_global(
      nan_batch, S.data_sharding(mesh8))))
  same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a),
                                                               jax.tree.leaves(b)))
  out.update(nan_loss_finite=bool(np.isfinite(mn["loss"])), nan_num_skipped=int(after.num_skipped),
             nan_step=int(after.step), nan_params_unchanged=same(after.params, host8.params),
             nan_opt_state_unchanged=same(after.opt_state, host8.opt_state))
  with open(out_path, "w", encoding="utf-8") as f:
    json.dump(out, f, indent=1)


if __name__ == "__main__":
  _child(sys.argv[1])

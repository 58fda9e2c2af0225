"""In-process tests of the optimizer, state, step and checkpoints (toy model; fast).

The real model is only traced here (`jax.eval_shape`), never compiled: the tests that
compile it run in subprocesses (test_sharding, test_multihost, test_resume_and_learning).
"""

import functools
import io
import json
import logging
import os
import pathlib
import re
import shutil
import sys
import types

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import pytest

import sav_jax
from configs import synthetic
from sav_jax.data import pipeline
from sav_jax.data.synthetic import SyntheticConfig
from sav_jax.model.stereo_any_video import SAVOutput
from train import checkpoint as ckpt_lib
from train import loss as loss_lib
from train import optim, state as state_lib, step as step_lib

# Most programs here compile for a step or two: 231 CPU-seconds with `fast_compile`, 305
# without (2026-12-07).
pytestmark = pytest.mark.usefixtures("fast_compile")


def _config():
  c = synthetic.get_config()
  c.data.frames, c.data.crop, c.train.iters, c.train.batch_size = 2, (16, 16), 2, 2
  c.train.num_steps = 10
  return c


class ToyStereo(nn.Module):
  """Same interface and parameter layout idea as `StereoAnyVideo`, a few parameters."""

  @nn.compact
  def __call__(self, left, right, iters=2, final_only=False):
    x = jnp.concatenate([left, right], axis=-1) / 255.0
    prior = jax.lax.stop_gradient(_Frozen(name="depthnet")(x))
    d = nn.Dense(1, name="head")(jnp.concatenate([x, prior], -1))[..., 0] * 10.0
    preds = jnp.stack([d * (i + 1) / (2 * iters) for i in range(2 * iters)])
    return SAVOutput(disparities=preds[-1:] if final_only else preds)


class _Frozen(nn.Module):
  @nn.compact
  def __call__(self, x):
    return _VDA(name="depthanything")(x)


class _VDA(nn.Module):
  @nn.compact
  def __call__(self, x):
    return nn.Dense(3)(x)


def _batch(rng, c, nan=False):
  t, (h, w), b = c.data.frames, c.data.crop, c.train.batch_size
  left = rng.uniform(0, 255, (b, t, h, w, 3)).astype(np.float32)
  if nan:
    left[0, 0, 0, 0, 0] = np.nan
  return {"left": left, "right": rng.uniform(0, 255, (b, t, h, w, 3)).astype(np.float32),
          "disparity": rng.uniform(1, 8, (b, t, h, w)).astype(np.float32),
          "valid": np.ones((b, t, h, w), bool)}


def _setup(c):
  model = ToyStereo()
  mesh = state_lib.make_mesh()
  params = state_lib.abstract_params(model, c)
  labels = optim.param_labels(params, c.optimizer.frozen)
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  state, shardings = state_lib.create_train_state(model, tx, c, mesh)
  step = step_lib.jit_train_step(step_lib.make_train_step(model, tx, c, labels, mesh), shardings,
                                 mesh)
  return model, mesh, tx, state, shardings, step


def _put(batch, mesh):
  return {k: jax.device_put(v, state_lib.data_sharding(mesh)) for k, v in batch.items()}


def test_one_cycle_matches_pytorch_formula():
  max_lr, total, pct = 1e-4, 80_100, 0.01
  # the defaults: the official script's pct_start, PyTorch's div_factor and final_div_factor
  sched = optim.one_cycle_linear(max_lr, total)
  init, final = max_lr / 25, max_lr / 25 / 1e4
  end1, end2 = pct * total - 1, total - 1  # PyTorch OneCycleLR phase ends
  for s in [0, 1, 400, 800, 801, 5000, 40_000, 79_999, 80_000]:
    if s <= end1:
      ref = (max_lr - init) * (s / end1) + init
    else:
      ref = (final - max_lr) * ((s - end1) / (end2 - end1)) + max_lr
    np.testing.assert_allclose(float(sched(s)), ref, rtol=2e-5, err_msg=str(s))


def test_clipping_is_torchs_clip_grad_norm():
  # torch: g * min(1, max_norm / (norm + 1e-6)); optax's clip_by_global_norm divides by the
  # norm alone (a 1e-6 / norm relative difference in every clipped step).
  clip = optim.clip_grad_norm_like_torch(1.0)
  assert clip.init({"a": jnp.zeros(3)}) == optax.clip_by_global_norm(1.0).init({"a": jnp.zeros(3)})
  for norm in (0.5, 1.0, 1.0 + 1e-7, 3.0, 1e4):
    with jax.enable_x64(True):
      g = {"a": jnp.asarray([0.6, 0.0], jnp.float64) * norm,
           "b": jnp.asarray([[0.8]], jnp.float64) * norm}
      out, _ = clip.update(g, clip.init(g))
      coef = min(1.0, 1.0 / (norm + 1e-6))  # clip_grad_norm_'s clip_coef, clamped at 1
      for k in g:
        np.testing.assert_allclose(np.asarray(out[k]), np.asarray(g[k]) * coef, rtol=1e-12)
    if norm == 1.0:  # at max_norm exactly torch scales by 1 / (1 + 1e-6); optax does not
      assert float(coef) != 1.0


def test_a_clip_norm_of_0_turns_clipping_off():
  opt = synthetic.get_config().optimizer
  opt.clip_norm, opt.schedule, opt.lr, opt.weight_decay, opt.eps = 0.0, "constant", 1e-3, 0.0, 1e-8
  tx = optim.make_optimizer(opt, 10)
  grads = jnp.asarray([3.0, -4.0])  # norm 5: clipping at any norm < 5 would scale it
  updates, _ = tx.update(grads, tx.init(jnp.zeros(2)), jnp.zeros(2))
  # Adam's first step: -lr * g / (|g| + eps) (the bias-corrected moments are g and g**2), to
  # optax's float32 bias correction (~1e-5, as in test_optimizer_steps_match_torchs_...)
  np.testing.assert_allclose(np.asarray(updates), [-1e-3, 1e-3], rtol=3e-5)


def _torch_clip_adamw_one_cycle(params, grads, opt, total_steps):
  """The updates and the parameters after each step of the official update, in float64
  NumPy, transcribed from PyTorch's documented algorithms: `clip_grad_norm_(params,
  max_norm)`, then `AdamW.step()` (`lr` from the scheduler), then `OneCycleLR.step()`.

  Args:
    params: `[n]` initial trainable parameters.
    grads: `[steps, n]` their gradients at each step.
    opt: the optimizer config (`lr` is OneCycleLR's max_lr).
    total_steps: OneCycleLR's `total_steps`.

  Returns:
    `(updates, params)`: lists of `[n]` per step (the updates summed as they are made, not
    differences of parameters, which would lose digits: ~1e-8 steps of 1e3 values).
  """
  # OneCycleLR(anneal_strategy="linear", three_phase=False): phase 1 from initial_lr to
  # max_lr ends at step pct_start * total_steps - 1, phase 2 to min_lr at total_steps - 1;
  # lr = (end - start) * pct + start, pct the step's fraction of its phase.
  initial_lr = opt.lr / opt.div_factor
  min_lr = initial_lr / opt.final_div_factor
  end1, end2 = float(opt.pct_start * total_steps) - 1, total_steps - 1
  p = np.asarray(params, np.float64).copy()
  exp_avg, exp_avg_sq = np.zeros_like(p), np.zeros_like(p)
  updates, out = [], []
  for step, g in enumerate(np.asarray(grads, np.float64), start=1):
    last_epoch = step - 1  # the scheduler's count when this step runs
    if last_epoch <= end1:
      lr = (opt.lr - initial_lr) * (last_epoch / end1) + initial_lr
    else:
      lr = (min_lr - opt.lr) * ((last_epoch - end1) / (end2 - end1)) + opt.lr
    # clip_grad_norm_: clip_coef = max_norm / (total_norm + 1e-6), clamped to 1
    g = g * min(1.0, opt.clip_norm / (np.linalg.norm(g) + 1e-6))
    # AdamW: decoupled weight decay with the step's lr (p *= 1 - lr * weight_decay), then
    # the Adam update of the decayed p
    exp_avg = opt.b1 * exp_avg + (1 - opt.b1) * g
    exp_avg_sq = opt.b2 * exp_avg_sq + (1 - opt.b2) * g * g
    bias_correction1 = 1 - opt.b1**step
    bias_correction2 = 1 - opt.b2**step
    denom = np.sqrt(exp_avg_sq) / np.sqrt(bias_correction2) + opt.eps
    update = -lr * opt.weight_decay * p - (lr / bias_correction1) * exp_avg / denom
    p = p + update
    updates.append(update)
    out.append(p)
  return updates, out


def _optimizer_case():
  """A small parameter tree (a frozen depth-prior leaf among two trainable ones) and six
  steps of gradients of global norms 1e-9 (eps dominates Adam's denominator), 0.5, 3 and
  1e3 (clipped), 1 (clipped by 1 / (1 + 1e-6)) and 1e-3; head/bias[6] never gets a
  gradient (its update is the weight decay alone) and sits at 1e3 (weight decay visible)."""
  rng = np.random.default_rng(7)
  params = {"depthnet": {"depthanything": {"w": np.full(4, 2.0, np.float32)}},
            "fnet": {"kernel": rng.normal(size=(2, 3)).astype(np.float32)},
            "head": {"bias": np.array([0.5, -1.5, 3.0, -0.25, 1e3, -2e3, 1e3], np.float32)}}
  grads = []
  for norm in (1e-9, 0.5, 3.0, 1e3, 1.0, 1e-3):
    kernel, bias = rng.normal(size=(2, 3)), rng.normal(size=7)
    bias[6] = 0.0
    scale = norm / np.sqrt(np.sum(kernel**2) + np.sum(bias**2))
    grads.append({"depthnet": {"depthanything": {"w": np.full(4, 1e6, np.float32)}},
                  "fnet": {"kernel": (kernel * scale).astype(np.float32)},
                  "head": {"bias": (bias * scale).astype(np.float32)}})
  return params, grads


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_optimizer_steps_match_torchs_clip_then_adamw_with_one_cycle(dtype):
  from configs import sceneflow  # pylint: disable=g-import-not-at-top
  opt = sceneflow.get_config().optimizer
  # The official recipe, train_stereoanyvideo.py: AdamW(lr=1e-4, weight_decay=1e-5,
  # eps=1e-8) with PyTorch's default betas (0.9, 0.999); OneCycleLR(pct_start=0.01,
  # anneal_strategy="linear", total_steps=num_steps + 100) with PyTorch's default
  # div_factor=25 and final_div_factor=1e4; clip_grad_norm_(params, 1.0) every step.
  assert (opt.lr, opt.weight_decay, opt.eps, opt.b1, opt.b2) == (1e-4, 1e-5, 1e-8, 0.9, 0.999)
  assert (opt.schedule, opt.pct_start, opt.div_factor, opt.final_div_factor,
          opt.schedule_steps, opt.clip_norm) == ("one_cycle", 0.01, 25.0, 1e4, -1, 1.0)
  num_steps = 300  # total_steps 400: warm-up to step 3 (0.01 * 400 - 1), then annealing
  # float64: the algorithm, to the float32 lr of the schedule (~1e-7). float32 (training):
  # optax computes Adam's bias corrections 1 - b**t in float32, PyTorch (float32 too) in
  # double; 0.999 rounds to 0.99900001 and 0.999**t to ~6e-8, so 1 - 0.999**t (~1e-3 * t)
  # is 1-3e-5 off in the first steps and their updates ~1e-5 (up to ~2e-5): optax's
  # rounding, ~1e-7 in torch.
  rtol = {"float64": 1e-6, "float32": 3e-5}[dtype]
  params, grads = jax.tree.map(lambda x: x.astype(dtype), _optimizer_case())
  vector = optim.TrainableVector(optim.param_labels(params, opt.frozen))
  assert vector.size(params) == 13  # fnet/kernel, head/bias: the frozen leaf is left out
  with jax.enable_x64(dtype == "float64"):
    ref_updates, ref = _torch_clip_adamw_one_cycle(
        vector.gather(params), [np.asarray(vector.gather(g)) for g in grads], opt,
        num_steps + 100)
    tx = optim.make_optimizer(opt, num_steps)
    flat = vector.gather(params)
    assert flat.dtype == dtype
    state = tx.init(flat)
    update = jax.jit(tx.update)
    for step, g in enumerate(grads):
      updates, state = update(vector.gather(g), state, flat)
      flat = optax.apply_updates(flat, updates)
      # The update itself: the parameters (~1) move by ~1e-5 or less (float32 parameters
      # of 1e3 not at all), so comparing them alone would hide most of the step.
      np.testing.assert_allclose(np.asarray(updates), ref_updates[step], rtol=rtol, atol=0,
                                 err_msg=f"update of step {step}")
      np.testing.assert_allclose(np.asarray(flat), ref[step], rtol=rtol, atol=0,
                                 err_msg=f"parameters after step {step}")
    out = vector.scatter(params, flat)
  assert out["depthnet"]["depthanything"]["w"] is params["depthnet"]["depthanything"]["w"]


@pytest.mark.parametrize("name", ["sceneflow", "mixed", "synthetic"])
def test_augmentation_and_generator_fields_are_overridable(name):
  import dataclasses  # pylint: disable=import-outside-toplevel
  import importlib  # pylint: disable=import-outside-toplevel

  from sav_jax.data import pipeline  # pylint: disable=import-outside-toplevel
  from sav_jax.data.augment import AugmentConfig  # pylint: disable=import-outside-toplevel
  from train import input as input_lib  # pylint: disable=import-outside-toplevel
  c = importlib.import_module(f"configs.{name}").get_config()
  c.lock()  # as `python -m train` loads it: unknown fields are refused
  crop = tuple(c.data.crop)
  default = pipeline.Augment(crop, tuple(sorted(dict(c.data.augment).items()))).augment_config()
  assert default == AugmentConfig(crop_size=crop)  # the official defaults, unchanged
  assert set(c.data.augment) == {f.name for f in dataclasses.fields(AugmentConfig)} - {"crop_size"}
  c.data.augment.spatial_prob = 0.0
  c.data.augment.scale_range = (-0.1, 0.1)
  c.data.synthetic.focal = 300.0
  c.data.synthetic.max_speed = 1.5
  aug = pipeline.Augment(crop, tuple(sorted(dict(c.data.augment).items()))).augment_config()
  assert (aug.spatial_prob, aug.scale_range) == (0.0, (-0.1, 0.1))
  gen = input_lib.synthetic_config(c.data, c.data.synthetic, seed=3)
  assert (gen.focal, gen.max_speed, gen.seed, gen.frames) == (300.0, 1.5, 3, c.data.frames)


def test_log_and_save_periods_of_zero_mean_the_last_step_only():
  from train import loop  # pylint: disable=import-outside-toplevel

  class Writer:
    def __init__(self):
      self.steps = []

    def write(self, step, scalars, split="train"):
      self.steps.append(step)

  class Bar:
    shown = True  # a drawn progress bar: no log lines

    def update(self, *args, **kwargs):
      pass

  c = synthetic.get_config()
  c.train.log_every, c.train.num_steps = 0, 3
  writer = Writer()
  host = loop._HostMetrics(c, writer, Bar(), 0)  # pylint: disable=protected-access
  for step in (1, 2, 3):
    host(step, {"loss": 1.0, "epe": 1.0, "num_skipped": 0})
  assert writer.steps == [3]
  assert [loop._every(s, 0) for s in (1, 2)] == [False, False]  # pylint: disable=protected-access
  assert [loop._every(s, 2) for s in (1, 2)] == [False, True]  # pylint: disable=protected-access


def test_schedule_shorter_than_the_run_holds_its_final_lr():
  c = synthetic.get_config()
  c.optimizer.schedule, c.optimizer.schedule_steps = "one_cycle", 100
  sched = optim.make_schedule(c.optimizer, 200)
  final = c.optimizer.lr / c.optimizer.div_factor / c.optimizer.final_div_factor
  lrs = np.array([float(sched(s)) for s in (98, 99, 100, 150, 199)])
  assert lrs[0] > lrs[1] and np.all(lrs > 0), lrs
  np.testing.assert_allclose(lrs[1:], final, rtol=1e-5)


def test_a_constant_schedule_keeps_the_configured_rate():
  c = synthetic.get_config()
  c.optimizer.schedule, c.optimizer.lr = "constant", 3e-4
  sched = optim.make_schedule(c.optimizer, 200)
  np.testing.assert_allclose([float(sched(s)) for s in (0, 1, 100, 500)], 3e-4, rtol=1e-6)


def test_extending_a_one_cycle_run_names_the_learning_rate_jump():
  c = synthetic.get_config()
  c.optimizer.schedule, c.optimizer.schedule_steps = "one_cycle", 0
  c.optimizer.lr, c.optimizer.pct_start = 1e-4, 0.01
  saved = {**ckpt_lib.run_fields(c), "train.num_steps": 800}  # a finished run, extended
  with jax.transfer_guard("disallow"):  # as `python -m train` runs (it crashed there)
    note = optim.schedule_change_note(c.optimizer, 1000, 800, saved)
  before = float(optim.make_schedule(c.optimizer, 800)(800))
  after = float(optim.make_schedule(c.optimizer, 1000)(800))
  assert after > 2 * before
  assert note == (f"train.num_steps 800 -> 1000: the learning-rate schedule changes, the rate "
                  f"at step 800 goes from {before:.3g} to {after:.3g}; to keep the earlier "
                  "cycle (and then its final rate), pass --config.optimizer.schedule_steps=900")
  # the advice holds: that cycle is the saved run's
  c.optimizer.schedule_steps = 900
  assert float(optim.make_schedule(c.optimizer, 1000)(800)) == before
  saved_set = {**ckpt_lib.run_fields(c), "train.num_steps": 800}
  assert optim.schedule_change_note(c.optimizer, 1000, 800, saved_set) is None  # a set cycle
  c.optimizer.schedule_steps = 0
  assert optim.schedule_change_note(c.optimizer, 800, 800, saved) is None  # nothing changed
  assert optim.schedule_change_note(c.optimizer, 1000, 800, {}) is None  # older checkpoint
  assert optim.schedule_change_note(c.optimizer, 1000, 800, {"optimizer.lr": 1e-3}) is None
  # A saved schedule this version does not build: its rate is unknown, the note still comes.
  cosine = {**saved, "optimizer.schedule": "cosine"}
  assert "the rate at step 800 goes from nan to " in optim.schedule_change_note(
      c.optimizer, 1000, 800, cosine)
  # Rates that agree to 3 digits get the digits that tell them apart ("9.62e-05 to 9.62e-05").
  assert (optim._distinct(9.6201e-05, 9.6249e-05), optim._distinct(9.6249e-05, 9.6201e-05),  # pylint: disable=protected-access
          optim._distinct(0.5, 0.25)) == ("9.62e-05", "9.625e-05", "0.5")  # pylint: disable=protected-access
  # Another optimizer.lr too: "before" is the saved run's rate, not the new lr's.
  c.optimizer.lr = 1e-3
  note = optim.schedule_change_note(c.optimizer, 1000, 800, saved)
  after = float(optim.make_schedule(c.optimizer, 1000)(800))
  assert note == (f"train.num_steps 800 -> 1000, optimizer.lr 0.0001 -> 0.001: the learning-rate "
                  f"schedule changes, the rate at step 800 goes from {before:.3g} to "
                  f"{after:.3g}")
  # Skipped updates: the schedule counts updates (step - skipped), and so do the rates named
  # (they were the rates at step 800, which the run never used)
  note = optim.schedule_change_note(c.optimizer, 1000, 800, saved, updates=790)
  c.optimizer.lr = 1e-4
  before = float(optim.make_schedule(c.optimizer, 800)(790))
  c.optimizer.lr = 1e-3
  after = float(optim.make_schedule(c.optimizer, 1000)(790))
  assert note.endswith(f"the rate at step 800 (update 790: 10 skipped) goes from {before:.3g} "
                       f"to {after:.3g}"), note
  # Each schedule field changed alone is named, with its saved value (and no advice to keep
  # the cycle: that is for a changed train.num_steps alone).
  for field, value in (("schedule", "constant"), ("schedule_steps", 900), ("pct_start", 0.02),
                       ("div_factor", 10.0), ("final_div_factor", 1e3)):
    c = synthetic.get_config()
    c.optimizer.schedule, c.optimizer.schedule_steps, c.optimizer.pct_start = "one_cycle", 0, 0.01
    saved = {**ckpt_lib.run_fields(c), "train.num_steps": 1000}
    c.optimizer[field] = value
    note = optim.schedule_change_note(c.optimizer, 1000, 800, saved)
    assert note.startswith(f"optimizer.{field} {saved['optimizer.' + field]!r} -> {value!r}: the "
                           "learning-rate schedule changes"), (field, note)
    assert "to keep the earlier cycle" not in note, (field, note)


def _real_abstract_params():
  c = synthetic.get_config()
  return state_lib.abstract_params(sav_jax.StereoAnyVideo(state_lib.model_config(c)), c)


def test_trainable_vector_gathers_and_scatters_the_trainable_leaves_only():
  params = {"a": np.arange(6, dtype=np.float32).reshape(2, 3),
            "depthanything": {"w": np.full((4,), 7.0, np.float32)},
            "b": {"c": np.array([10.0, 11.0], np.float32)}}
  vector = optim.TrainableVector(optim.param_labels(params, "depthanything"))
  flat = vector.gather(params)  # jax.tree.leaves order: a, b/c (dict keys sorted)
  np.testing.assert_array_equal(flat, [0, 1, 2, 3, 4, 5, 10, 11])
  assert vector.size(params) == 8
  back = vector.scatter(params, -flat)
  np.testing.assert_array_equal(back["a"], -params["a"])
  np.testing.assert_array_equal(back["b"]["c"], [-10, -11])
  assert back["depthanything"]["w"] is params["depthanything"]["w"]  # frozen: untouched
  with pytest.raises(ValueError, match="a vector of 9 values for 8 trainable parameters"):
    vector.scatter(params, jnp.zeros(9))
  # the vector holds the common dtype; each leaf gets its own back
  mixed = {"a": np.ones(2, np.float16), "b": np.ones(1, np.float32)}
  vector = optim.TrainableVector(optim.param_labels(mixed, "depthanything"))
  assert vector.gather(mixed).dtype == np.float32
  assert vector.scatter(mixed, vector.gather(mixed))["a"].dtype == np.float16


def test_a_frozen_pattern_that_misses_the_depth_prior_is_refused():
  params = {"depthnet": {"depthanything": {"blocks_0": {"w": np.zeros(2)}, "head": {"w": np.zeros(2)}},
                         "conv": {"w": np.zeros(2)}}, "fnet": {"w": np.zeros(2)}}
  optim.check_depth_prior_frozen(optim.param_labels(params, "depthanything"), "depthanything")
  for pattern, n in (("", 2), ("blocks_", 1), ("^depthnet/depth_anything/", 2)):
    with pytest.raises(ValueError, match=rf"config\.optimizer\.frozen='{re.escape(pattern)}' "
                       rf"leaves {n} parameters of the frozen depth prior trainable "
                       r"\(e\.g\. depthnet/depthanything/"):
      optim.check_depth_prior_frozen(optim.param_labels(params, pattern), pattern)
  for pattern in (".", "^", "depthnet|fnet"):  # everything frozen: no update in the whole run
    with pytest.raises(ValueError, match=rf"config\.optimizer\.frozen='{re.escape(pattern)}' "
                       "freezes every parameter of the model"):
      optim.check_depth_prior_frozen(optim.param_labels(params, pattern), pattern)


def test_real_model_optimizer_state_has_no_frozen_entries():
  c = synthetic.get_config()
  params = _real_abstract_params()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  vector = optim.TrainableVector(optim.param_labels(params, c.optimizer.frozen))
  opt_shapes = jax.eval_shape(lambda p: tx.init(vector.gather(p)), params)
  n_frozen = sum(x.size for x in jax.tree.leaves(params["depthnet"]["depthanything"]))
  n_trainable = sum(x.size for x in jax.tree.leaves(params)) - n_frozen
  assert n_frozen > 2e7 and vector.size(params) == n_trainable
  moments = [x.shape for x in jax.tree.leaves(opt_shapes) if x.ndim > 0]
  assert moments == [(n_trainable,)] * 2  # Adam mu and nu, trainable only
  # the shapes traced once per model config, shared with init_variables and the converters
  from sav_jax.model.init import abstract_variables  # pylint: disable=g-import-not-at-top
  shared = abstract_variables(state_lib.model_config(c))["params"]
  assert all(a is b for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(shared)))


def test_step_updates_trainable_only_and_skips_nan_batches():
  c = _config()
  _, mesh, _, state, _, step = _setup(c)
  rng = np.random.default_rng(0)
  before = jax.device_get(state.params)
  state, m = step(state, _put(_batch(rng, c), mesh))
  after = jax.device_get(state.params)
  assert int(state.step) == 1 and int(state.num_skipped) == 0 and float(m["finite"]) == 1.0
  np.testing.assert_array_equal(after["depthnet"]["depthanything"]["Dense_0"]["kernel"],
                                before["depthnet"]["depthanything"]["Dense_0"]["kernel"])
  assert not np.allclose(after["head"]["kernel"], before["head"]["kernel"])
  opt_before = jax.device_get(state.opt_state)
  state, m = step(state, _put(_batch(rng, c, nan=True), mesh))
  assert not np.isfinite(float(m["loss"])) and float(m["finite"]) == 0.0
  assert int(state.step) == 2 and int(state.num_skipped) == 1 and int(m["num_skipped"]) == 1
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(state.params), after)
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(state.opt_state), opt_before)
  state, m = step(state, _put(_batch(rng, c), mesh))
  assert np.isfinite(float(m["loss"])) and int(state.num_skipped) == 1
  # The lr follows applied updates: 2 applied after 3 steps.
  sched = optim.make_schedule(c.optimizer, c.train.num_steps)
  np.testing.assert_allclose(float(m["lr"]), float(sched(1)), rtol=1e-6)


def test_the_step_trains_on_the_configured_loss_and_iterations():
  """`loss.gamma`, `loss.max_disparity`, `loss.per_sample` and `train.iters` reach the step:
  its loss is `sequence_loss` of the model's predictions (left, right) with those settings,
  which differs from the loss with any one of them left at its default."""
  c = _config()
  c.train.iters, c.loss.gamma, c.loss.max_disparity, c.loss.per_sample = 4, 0.5, 5.0, False
  c.optimizer.schedule, c.optimizer.lr = "constant", 0.1  # (an update that moves the norm)
  model, mesh, _, state, _, step = _setup(c)
  batch = _batch(np.random.default_rng(3), c)
  batch["valid"][0, :, :6] = False  # clips of other valid counts: pooled != per clip
  params = {"params": jax.device_get(state.params)}
  preds = {it: model.apply(params, batch["left"], batch["right"], iters=it).disparities
           for it in (2, 4)}
  kwargs = dict(gamma=0.5, max_disparity=5.0, per_sample=False)
  want = float(loss_lib.sequence_loss(preds[4], batch["disparity"], batch["valid"], **kwargs)[0])
  others = [loss_lib.sequence_loss(preds[2], batch["disparity"], batch["valid"], **kwargs)[0]]
  for field, default in (("gamma", 0.9), ("max_disparity", 700.0), ("per_sample", True)):
    others.append(loss_lib.sequence_loss(preds[4], batch["disparity"], batch["valid"],
                                         **dict(kwargs, **{field: default}))[0])
  assert all(abs(float(o) - want) > 1e-3 * want for o in others), (want, others)
  # the gradient norm is that of this loss's gradient in the trainable leaves (the head; the
  # depth prior is frozen), the parameter norm that of the updated trainable leaves
  head_grads = jax.grad(lambda head: loss_lib.sequence_loss(
      model.apply({"params": dict(params["params"], head=head)}, batch["left"], batch["right"],
                  iters=4).disparities, batch["disparity"], batch["valid"], **kwargs)[0])(
                      params["params"]["head"])
  new_state, m = step(state, _put(batch, mesh))
  np.testing.assert_allclose(float(m["loss"]), want, rtol=1e-5)
  np.testing.assert_allclose(float(m["l2_grads"]), np.sqrt(sum(
      np.sum(np.square(g)) for g in jax.tree.leaves(head_grads))), rtol=1e-4)
  np.testing.assert_allclose(float(m["l2_params"]), np.sqrt(sum(
      np.sum(np.square(p)) for p in jax.tree.leaves(jax.device_get(new_state.params["head"])))),
                             rtol=1e-5)


def test_an_update_that_overflows_is_skipped():
  """Finite loss and gradients, but an absurd learning rate makes the update non-finite: the
  step is skipped as for a NaN batch, not applied (the parameters would be inf/NaN)."""
  c = _config()
  c.optimizer.schedule, c.optimizer.lr = "constant", 1e38  # finite; the update norm is not
  _, mesh, _, state, _, step = _setup(c)
  before = jax.device_get(state.params)
  state, m = step(state, _put(_batch(np.random.default_rng(0), c), mesh))
  assert np.isfinite(float(m["loss"])) and np.isfinite(float(m["l2_grads"]))
  assert not np.isfinite(float(m["l2_updates"])) and float(m["finite"]) == 0.0
  assert int(state.num_skipped) == 1
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(state.params), before)


def test_checkpoint_roundtrip_with_data_iterator(tmp_path):
  c = _config()
  c.checkpoint.async_save = False
  model, mesh, tx, state, shardings, step = _setup(c)
  it = _toy_iterator(50, seed=3)
  state, _ = step(state, _put(_batch(np.random.default_rng(1), c), mesh))
  next(it)
  manager = ckpt_lib.make_manager(tmp_path, c)
  assert not ckpt_lib.save(manager, state, it, 1, params_finite=False)  # never saves NaNs
  assert ckpt_lib.save(manager, state, it, 1, force=True)
  manager.wait_until_finished()
  expected_next = next(it)
  fresh = _toy_iterator(50, seed=3)
  abstract = jax.eval_shape(state_lib.make_init_fn(model, tx, c))
  restored = ckpt_lib.restore(ckpt_lib.make_manager(tmp_path, c), abstract, shardings, fresh)
  assert int(restored.step) == 1 and restored.params["head"]["kernel"].sharding == \
      shardings.params["head"]["kernel"]
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(restored.params),
               jax.device_get(state.params))
  jax.tree.map(np.testing.assert_array_equal, next(fresh), expected_next)
  # A checkpoint of another optimizer config (no clipping: another state tree) is refused
  # with a message that says so, not orbax's tree diff.
  c.optimizer.clip_norm = 0.0
  tx2 = optim.make_optimizer(c.optimizer, c.train.num_steps)
  _, shardings2 = state_lib.create_train_state(model, tx2, c, mesh)
  abstract2 = jax.eval_shape(state_lib.make_init_fn(model, tx2, c))
  with pytest.raises(sav_jax.convert.CheckpointError, match="does not match this run's model or "
                     "optimizer config.*init_from") as e:
    ckpt_lib.restore(ckpt_lib.make_manager(tmp_path, c), abstract2, shardings2, fresh)
  # ... naming the arrays (orbax's "tree structures do not match:" named none)
  assert ("(4 arrays of the checkpoint are not in this run's state, e.g. opt_state/1/0/count, "
          "opt_state/1/0/mu, opt_state/1/0/nu; 4 arrays of this run's state are not in the "
          "checkpoint, e.g. opt_state/0/0/count") in str(e.value)


def test_only_the_last_k_checkpoints_are_kept(tmp_path):
  c = _config()
  c.checkpoint.async_save, c.checkpoint.keep = False, 2
  _, _, _, state, _, _ = _setup(c)
  it = _toy_iterator(50, seed=3)
  manager = ckpt_lib.make_manager(tmp_path, c)
  for step in (1, 2, 3):
    assert ckpt_lib.save(manager, state, it, step, force=True)
  manager.wait_until_finished()
  folder = tmp_path / "checkpoints"
  assert sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) == [2, 3]
  c.checkpoint.keep = 0  # 0: all of them
  manager = ckpt_lib.make_manager(tmp_path, c)
  for step in (4, 5, 6):
    assert ckpt_lib.save(manager, state, it, step, force=True)
  manager.wait_until_finished()
  assert sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) == [2, 3, 4, 5, 6]


def test_restore_without_a_step_resumes_from_the_latest_checkpoint(tmp_path):
  """`restore(step=None)` (what `initial_state` calls) takes the newest step, not an older
  one the folder also holds: a resume from an older one would redo steps, silently."""
  c = _config()
  c.checkpoint.async_save, c.checkpoint.keep = False, 0
  model, _, tx, state, shardings, _ = _setup(c)
  it = _toy_iterator(50, seed=3)
  manager = ckpt_lib.make_manager(tmp_path, c)
  for step in (2, 4, 5):  # the latest: 5; not the first, nor one before it
    next(it)
    extra = dict(run_config=c, data_clips={"s": [3, "d"]}, depth_prior="P") if step == 5 else {}
    assert ckpt_lib.save(manager, state.replace(step=jnp.asarray(step, jnp.int32)), it, step,
                         force=True, **extra)
  manager.wait_until_finished()
  # The config item holds what was given to `save`, and only that
  saved = ckpt_lib.saved_config(manager, 5)
  assert (saved["step"], saved["data_clips"], saved["depth_prior"]) == (5, {"s": [3, "d"]}, "P")
  assert saved["run"]["checkpoint.keep"] == 0 and saved["run"]["train.num_steps"] == 10
  assert set(ckpt_lib.saved_config(manager, 2)) == {"model", "step"}
  fresh = _toy_iterator(50, seed=3)
  abstract = jax.eval_shape(state_lib.make_init_fn(model, tx, c))
  restored = ckpt_lib.restore(ckpt_lib.make_manager(tmp_path, c), abstract, shardings, fresh)
  assert int(restored.step) == 5


def test_place_params_rejects_mismatches():
  c = _config()
  model = ToyStereo()
  abstract = state_lib.abstract_params(model, c)
  host = jax.tree.map(lambda a: np.zeros(a.shape, a.dtype), abstract)
  placed = state_lib.place_params(host, abstract, state_lib.make_mesh())
  assert placed["head"]["kernel"].shape == abstract["head"]["kernel"].shape
  host["head"]["kernel"] = np.zeros((1, 1), np.float32)
  with pytest.raises(ValueError, match="shape of head/kernel"):
    state_lib.place_params(host, abstract, state_lib.make_mesh())
  # float16 weights are placed as the model's float32; a transposed kernel (the same size)
  # and more than 20 problems are named, with how many
  half = {"a": np.ones((2, 3), np.float16), "b": np.ones(4, np.float32)}
  target = {"a": jax.ShapeDtypeStruct((2, 3), jnp.float32),
            "b": jax.ShapeDtypeStruct((4,), jnp.float32)}
  assert state_lib.place_params(half, target, state_lib.make_mesh())["a"].dtype == jnp.float32
  with pytest.raises(ValueError, match=r"^w do not match the model \(1 problems\): shape of a: "
                     r"\(3, 2\) != \(2, 3\)$"):
    state_lib.check_params(dict(half, a=np.ones((3, 2))), target, "w")
  many = {f"x{i:02d}": np.ones(1) for i in range(23)}
  with pytest.raises(ValueError, match=r"\(25 problems\): missing a; missing b; unexpected x00; "
                     r".*unexpected x17 \(and 5 more\)$") as e:
    state_lib.check_params(many, target, "w")
  assert "x18" not in str(e.value)
  labels = {"a": optim.TRAINABLE, "b": optim.FROZEN}
  assert state_lib.param_count(target, labels) == {"total": 10, optim.TRAINABLE: 6,
                                                   optim.FROZEN: 4}


def test_make_mesh_refuses_what_is_no_list_of_distinct_devices():
  one = jax.devices()[0]
  assert state_lib.make_mesh([one]).shape == {"data": 1}
  for bad in ([], [one, one], 2, "cpu", [one, "cpu:1"]):
    with pytest.raises(ValueError, match="make_mesh takes a non-empty list of distinct jax "
                                         "devices"):
      state_lib.make_mesh(bad)


def test_each_device_runs_the_forward_on_its_own_clips_with_its_own_key():
  # (traced on an abstract mesh of data 4 x model 2: this process has one device) The model
  # runs on each device's share of the batch (not on the global batch: clips moved between
  # devices in every step), the variables whole, the disparities [P, B, ...] split on B,
  # and each device's key folded with its index on `data` (one key: the same dropout mask).
  seen = []

  class Model:
    def apply(self, variables, left, right, *, iters, rngs=None):
      del iters
      seen.append((left.shape, right.shape, rngs is None))
      noise = 0.0 if rngs is None else jax.random.uniform(rngs["dropout"], left.shape)
      return SAVOutput(disparities=(left * variables["w"] + noise)[None])

  mesh = jax.sharding.AbstractMesh((4, 2), (state_lib.DATA_AXIS, "model"))
  apply = step_lib.per_device_apply(Model(), mesh)
  clips = jnp.ones((8, 3))

  def primitives(jaxpr):
    for eqn in jaxpr.eqns:
      yield eqn
      for value in eqn.params.values():
        for sub in value if isinstance(value, (tuple, list)) else (value,):
          sub = getattr(sub, "jaxpr", sub)  # (a ClosedJaxpr's)
          if hasattr(sub, "eqns"):
            yield from primitives(sub)

  for rngs in (True, False):
    seen.clear()
    jaxpr = jax.make_jaxpr(lambda w, l, r, k: apply(  # pylint: disable=cell-var-from-loop
        {"w": w}, l, r, iters=2, **({"rngs": {"dropout": k}} if rngs else {})).disparities)(
            jnp.ones(()), clips, clips, jax.random.key(0))
    assert seen == [((2, 3), (2, 3), not rngs)]  # 8 clips over data=4 (model: copies)
    assert jaxpr.out_avals[0].shape == (1, 8, 3)
    eqns = list(primitives(jaxpr.jaxpr))
    index = [e.params["axis_name"] for e in eqns if e.primitive.name == "axis_index"]
    folds = [e for e in eqns if e.primitive.name == "random_fold_in"]
    assert (index, len(folds)) == (([state_lib.DATA_AXIS], 1) if rngs else ([], 0))
  one = jax.sharding.AbstractMesh((1, 2), (state_lib.DATA_AXIS, "model"))
  model = Model()
  assert step_lib.per_device_apply(model, one) == model.apply  # (one device on data: as is)
  assert step_lib.per_device_apply(model, None) == model.apply
  with pytest.raises(ValueError, match="the mesh has no 'data' axis \\(its axes: 'batch'\\)"):
    step_lib.per_device_apply(model, jax.sharding.AbstractMesh((2,), ("batch",)))


def test_the_batch_is_split_over_the_data_axis_and_the_state_replicated():
  # (an abstract mesh of 4 devices: this process has one)
  mesh = jax.sharding.AbstractMesh((4,), (state_lib.DATA_AXIS,))
  assert state_lib.data_sharding(mesh).shard_shape((8, 2, 16, 16, 3)) == (2, 2, 16, 16, 3)
  assert state_lib.replicated(mesh).shard_shape((8, 3)) == (8, 3)


def test_resume_order_checkpoint_over_weights_over_scratch(tmp_path, caplog):
  from sav_jax.convert import save_variables  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.checkpoint.async_save = False
  model, mesh, tx = ToyStereo(), state_lib.make_mesh(), None
  params = state_lib.abstract_params(model, c)
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  it = _toy_iterator()
  manager = ckpt_lib.make_manager(tmp_path / "run", c)
  scratch, _, source = loop.initial_state(c, model, tx, mesh, manager, it)
  assert source == "scratch"
  weights = jax.tree.map(lambda a: np.full(a.shape, 0.5, a.dtype), params)
  save_variables(tmp_path / "w", {"params": weights}, {})
  c.init_from = str(tmp_path / "w")
  loaded, _, source = loop.initial_state(c, model, tx, mesh, manager, it)
  assert source == "weights" and int(loaded.step) == 0
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(loaded.params), weights)
  other = dict(weights, extra={"w": np.zeros(3, np.float32)})  # another model's weights
  save_variables(tmp_path / "w2", {"params": other}, {})
  c.init_from = str(tmp_path / "w2")
  with pytest.raises(ValueError, match=f"config.init_from={tmp_path / 'w2'}: its params do not "
                     r"match the model \(1 problems\): unexpected extra/w"):
    loop.initial_weights(c, params)  # (before the manager: `setup` calls it first)
  broken = jax.tree.map(np.copy, weights)  # NaN or integer arrays: every step was skipped
  broken["head"]["kernel"][0, 0] = np.nan
  broken["depthnet"]["depthanything"]["Dense_0"]["bias"] = np.zeros(3, np.int32)
  save_variables(tmp_path / "w3", {"params": broken}, {})
  c.init_from = str(tmp_path / "w3")
  with pytest.raises(ValueError, match=f"config.init_from={tmp_path / 'w3'}: its params cannot "
                     r"start a run \(2 problems\): key 'depthnet/depthanything/Dense_0/bias': "
                     r"dtype int32; .*key 'head/kernel': 1 of \d+ values are NaN or inf$"):
    loop.initial_weights(c, params)
  c.init_from = str(tmp_path / "w")
  ckpt_lib.save(manager, scratch.replace(step=jnp.asarray(7, jnp.int32)), it, 7, force=True,
                run_config=c)
  manager.wait_until_finished()
  assert ckpt_lib.changed_fields(manager, 7, c) == []
  c.optimizer.lr, c.train.num_steps, c.checkpoint.keep = 0.5, c.train.num_steps + 1, 9
  c.model.gru_conv = "direct"  # how the GRU computes, the same values
  c.model.remat_policy = "dots_saveable"  # and the other compute fields (but dtype)
  c.model.vit_attention, c.model.frame_block_mb = "blocked", 64.0
  c.train.microbatches = 2  # the same step in two parts
  assert ckpt_lib.changed_fields(manager, 7, c) == [  # keep: where and how, not what
      f"optimizer.lr: {_config().optimizer.lr!r} -> 0.5",
      f"train.num_steps: {_config().train.num_steps} -> {_config().train.num_steps + 1}"]
  with caplog.at_level(logging.WARNING):
    resumed, _, source = loop.initial_state(c, model, tx, mesh, manager, it)
  assert source == "checkpoint" and int(resumed.step) == 7  # the checkpoint wins
  assert "is not used" not in caplog.text  # the saving run's own init_from: no news
  # Another init_from than the saving run's is not read either: said (it was silent).
  c.init_from = str(tmp_path / "w2")
  with caplog.at_level(logging.WARNING):
    loop.initial_state(c, model, tx, mesh, manager, it)
  assert (f"config.init_from={tmp_path / 'w2'} is not used: this run resumes from checkpoint "
          "7 in ") in caplog.text


def test_depth_prior_weights_are_merged_into_the_initial_params(tmp_path):
  """`vda_weights` replace the frozen prior's subtree, from scratch and over `init_from`'s
  params (a run that dropped them would train with a random prior, silently)."""
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  model, mesh = ToyStereo(), state_lib.make_mesh()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  abstract = state_lib.abstract_params(model, c)
  vda = jax.tree.map(lambda a: np.full(a.shape, 0.25, a.dtype),
                     abstract["depthnet"]["depthanything"])
  host = jax.tree.map(lambda a: np.full(a.shape, 0.5, a.dtype), abstract)
  for name, weights in (("scratch", (None, vda)), ("init_from", (host, vda))):
    manager = ckpt_lib.make_manager(tmp_path / name, c)
    state, _, source = loop.initial_state(c, model, tx, mesh, manager, None, abstract, weights)
    manager.close()
    params = jax.device_get(state.params)
    assert source == "weights"
    jax.tree.map(np.testing.assert_array_equal, params["depthnet"]["depthanything"], vda)
    if name == "init_from":
      np.testing.assert_array_equal(params["head"]["kernel"], host["head"]["kernel"])


def test_a_smaller_keep_on_resume_never_deletes_the_earlier_policys_checkpoints(tmp_path):
  # A run saved with keep=0 (all), resumed without repeating it (the default keeps 3): orbax
  # deleted the older checkpoints at the first save, the finished run's last one included.
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.checkpoint.async_save, c.checkpoint.keep = False, 0
  model, mesh = ToyStereo(), state_lib.make_mesh()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  it = _toy_iterator()
  manager = ckpt_lib.make_manager(tmp_path, c)
  state, _, _ = loop.initial_state(c, model, tx, mesh, manager, it)
  for step in (1, 2, 3, 4):
    ckpt_lib.save(manager, state.replace(step=jnp.asarray(step, jnp.int32)), it, step,
                  force=True, run_config=c)
  manager.wait_until_finished()
  c.checkpoint.keep = 2
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"holds 4 checkpoints; this run's config.checkpoint.keep=2 would "
                     r"delete \[1, 2, 3\] \(saved with config.checkpoint.keep=0\) at its first "
                     r"save. Pass --config.checkpoint.keep=0 to keep them"):
    loop.initial_state(c, model, tx, mesh, ckpt_lib.make_manager(tmp_path, c), it)
  folder = tmp_path / "checkpoints"
  steps = lambda: sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit())  # noqa: E731
  assert steps() == [1, 2, 3, 4]
  c.checkpoint.keep = 4  # as many as the folder holds: the first save (step 5) pruned step 1
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"would delete \[1\] \(saved with "
                     r"config.checkpoint.keep=0\) at its first"):
    loop.initial_state(c, model, tx, mesh, ckpt_lib.make_manager(tmp_path, c), it)
  for keep in (0, 9, 5):  # the same policy, or one that deletes nothing: resumed
    c.checkpoint.keep = keep
    manager = ckpt_lib.make_manager(tmp_path, c)
    state, _, source = loop.initial_state(c, model, tx, mesh, manager, it)
    assert source == "checkpoint"
  ckpt_lib.save(manager, state.replace(step=jnp.asarray(5, jnp.int32)), it, 5, force=True,
                run_config=c)  # keep=5: the first save deletes nothing
  manager.wait_until_finished()
  assert steps() == [1, 2, 3, 4, 5]
  # A run saved before the keep policy was recorded (no run config in its checkpoints),
  # holding as many as this run keeps: it pruned so itself (the default keep), and resumes as
  # it did (it was refused)
  old = tmp_path / "old"
  c.checkpoint.keep = 0
  manager = ckpt_lib.make_manager(old, c)
  for step in (1, 2, 3, 4, 5):
    ckpt_lib.save(manager, state.replace(step=jnp.asarray(step, jnp.int32)), it, step,
                  force=True)
  manager.wait_until_finished()
  c.checkpoint.keep = 5
  ckpt_lib.check_keep(ckpt_lib.make_manager(old, c), c, {})
  c.checkpoint.keep = 4
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"holds 5 checkpoints; this run's "
                     r"config.checkpoint.keep=4 would delete \[1, 2\] \(saved before the keep "
                     r"policy was recorded\) at its first save. Pass --config.checkpoint.keep=0"):
    ckpt_lib.check_keep(ckpt_lib.make_manager(old, c), c, {})
  c.train.num_steps = 5  # a finished run, run again: it saves nothing, so deletes nothing
  ckpt_lib.check_keep(ckpt_lib.make_manager(old, c), c, {})
  # ... but once a later checkpoint records its keep, nothing says how the unrecorded ones
  # were kept (that run may have deleted nothing): they are not deleted
  c.checkpoint.keep, c.train.num_steps = 5, 10
  manager = ckpt_lib.make_manager(old, c)
  ckpt_lib.save(manager, state.replace(step=jnp.asarray(6, jnp.int32)), it, 6, force=True,
                run_config=c)
  manager.wait_until_finished()
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"would delete \[2\] \(saved before "
                     r"the keep policy was recorded\) at its first save"):
    ckpt_lib.check_keep(ckpt_lib.make_manager(old, c), c, ckpt_lib.saved_run(manager, 6))
  # Fewer checkpoints than keep, but more saves to come: orbax pruned the earlier policy's
  # checkpoints at a later save, without a word (the check looked at the first save only).
  for step in (1, 2, 3):
    shutil.rmtree(folder / str(step))
  c.checkpoint.keep, c.checkpoint.every_steps, c.train.num_steps = 3, 2, 11
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"holds 2 checkpoints; this run's "
                     r"config.checkpoint.keep=3 would delete \[4, 5\] \(step 4 saved with "
                     r"config.checkpoint.keep=0, step 5 with config.checkpoint.keep=5\) by the "
                     r"last of the 4 checkpoints it saves up to step 11. Pass "
                     r"--config.checkpoint.keep=0"):
    loop.initial_state(c, model, tx, mesh, ckpt_lib.make_manager(tmp_path, c), it)
  c.train.num_steps = 6  # one save: the folder then holds 3, all kept
  assert loop.initial_state(c, model, tx, mesh, ckpt_lib.make_manager(tmp_path, c), it)[2] == (
      "checkpoint")
  assert steps() == [4, 5]


@pytest.mark.parametrize("num_steps,every,start,saves", [
    (10, 3, 0, 4),  # 3, 6, 9 and the last, 10
    (9, 3, 0, 3),  # 3, 6, 9 (the last is one of them)
    (10, 3, 2, 4),  # 3, 6, 9, 10
    (10, 3, 3, 3),  # 6, 9, 10
    (10, 3, 9, 1),  # 10
    (10, 5, 4, 2),  # 5, 10
    (10, 5, 5, 1),  # 10
    (10, 3, 10, 0),  # a finished run saves nothing
    (10, 3, 12, 0),
    (10, 0, 2, 1),  # no period: the last step's only
])
def test_saves_after_counts_the_periodic_and_the_last_checkpoints(num_steps, every, start,
                                                                    saves):
  """How many checkpoints a resumed run saves decides which ones `check_keep` sees deleted
  (counted by hand: the multiples of every_steps in (start, num_steps], and num_steps)."""
  c = _config()
  c.train.num_steps, c.checkpoint.every_steps = num_steps, every
  assert ckpt_lib._saves_after(c, start) == saves  # pylint: disable=protected-access


class _Steps:
  """A stand-in for a checkpoint manager: only the steps it holds (their saved run configs
  come from a patched `saved_run`)."""

  def __init__(self, directory, steps):
    self.directory, self._steps = directory, steps

  def all_steps(self):
    return list(self._steps)


def test_check_keep_judges_each_checkpoint_by_the_keep_it_was_saved_with(tmp_path,
                                                                         monkeypatch):
  """Steps 1, 2, 3 and one more save at keep=3: orbax deletes step 1. Allowed where step 1
  was saved with a keep of 1..3; refused (naming its policy and the keep that keeps it) where
  it was saved with keep=0, a larger keep, or a run config without a readable keep."""
  runs = {2: {"checkpoint.keep": 3}, 3: {"checkpoint.keep": 3}}
  monkeypatch.setattr(ckpt_lib, "saved_run", lambda manager, step: runs[step])
  c = _config()
  c.checkpoint.keep, c.checkpoint.every_steps, c.train.num_steps = 3, 10, 10
  check = lambda: ckpt_lib.check_keep(_Steps(tmp_path, [1, 2, 3]), c, runs[3])  # noqa: E731
  for keep in (1, 3):  # its own policy deletes it as soon
    runs[1] = {"checkpoint.keep": keep}
    check()
  head = r"holds 3 checkpoints; this run's config.checkpoint.keep=3 would delete \[1\] "
  runs[1] = {"checkpoint.keep": 0}
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=head + r"\(saved with config.checkpoint.keep=0\) at its first save. "
                     r"Pass --config.checkpoint.keep=0 to keep them \(0 keeps all\), or move the "
                     r"ones you do not need out of that folder first \(or, to lower"):
    check()
  runs[1] = {"checkpoint.keep": 4}  # kept longer by its own run: suggest that keep
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=head + r"\(saved with config.checkpoint.keep=4\) at its first save. "
                     r"Pass --config.checkpoint.keep=4 \(the largest keep they were saved with"):
    check()
  runs[1] = {"train.num_steps": 10}  # a run config without the keep: unreadable, kept
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=head + r"\(saved with a config whose keep cannot be read\) at its "
                     r"first save. Pass --config.checkpoint.keep=0"):
    check()
  c.checkpoint.prune_earlier = True  # lowering the keep on purpose: allowed
  check()
  # Seven saves to come from step 3 (every step to 10): all three go by the last of them
  c.checkpoint.prune_earlier, c.checkpoint.every_steps = False, 1
  runs[1] = {"checkpoint.keep": 3}
  runs[3] = {"checkpoint.keep": 0}
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"would delete \[1, 2, 3\] \(steps 1, 2 saved with "
                     r"config.checkpoint.keep=3, step 3 with config.checkpoint.keep=0\) by the "
                     r"last of the 7 checkpoints it saves up to step 10") as e:
    check()
  assert "move the ones" not in str(e.value)  # (step 3, the one resumed from, among them)


def test_skip_unreadable_reaches_the_registry_sources(monkeypatch):
  from train import input as input_lib  # pylint: disable=g-import-not-at-top

  class Seq:
    name, dataset = "s", "sceneflow"

    def gather(self, indices):
      if indices[0] == 1:
        raise ValueError("/d/s/0001.png: cannot decode the image file")
      d = np.full((1, 2, 2), float(indices[0]), np.float32)
      return {"left": np.zeros((1, 2, 2, 3), np.uint8), "right": np.zeros((1, 2, 2, 3), np.uint8),
              "disparity": d, "valid": d > 0}

  monkeypatch.setattr(pipeline, "registry_clips", lambda *a, **k: [(Seq(), [i]) for i in range(3)])
  c = _config()
  spec = ml_collections.ConfigDict(dict(dataset="sceneflow", weight=1.0))
  src, _, _ = input_lib._source(c, spec, "train", 0)  # pylint: disable=protected-access
  with pytest.raises(ValueError, match="0001.png"):
    src[1]  # pylint: disable=pointless-statement
  c.data.skip_unreadable = 1
  src, _, _ = input_lib._source(c, spec, "train", 0)  # pylint: disable=protected-access
  assert src[1]["disparity"][0, 0, 0] in (0, 2)  # another clip stands in


def test_the_augmentation_fields_reach_the_registry_sources(monkeypatch):
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  monkeypatch.setattr(pipeline, "registry_clips",
                      lambda *a, **k: [(types.SimpleNamespace(name="s", gather=None), [0])])
  c = _config()
  c.data.augment.spatial_prob, c.data.augment.scale_range = 0.0, (-0.1, 0.1)
  spec = ml_collections.ConfigDict(dict(dataset="sceneflow", weight=1.0))
  _, augment, _ = input_lib._source(c, spec, "train", 0)  # pylint: disable=protected-access
  aug = augment.augment_config()
  assert (aug.crop_size, aug.spatial_prob, aug.scale_range) == ((16, 16), 0.0, (-0.1, 0.1))


def test_each_process_reads_its_share_of_the_batch(monkeypatch):
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.batch_size, c.data.synthetic.num_clips = 4, 8
  batch = next(iter(input_lib.train_dataset(c, process_index=1, process_count=2)))
  assert batch["left"].shape[:2] == (2, c.data.frames)  # 4 clips over 2 processes
  c.train.batch_size = 3
  with pytest.raises(ValueError, match=r"config.train.batch_size=3 is not divisible by 2 "
                                       r"processes"):
    input_lib.train_dataset(c, process_index=0, process_count=2)
  monkeypatch.setattr(jax, "process_count", lambda: 2)  # by default, the run's processes
  with pytest.raises(ValueError, match=r"config.train.batch_size=3 is not divisible by 2 "):
    input_lib.train_dataset(c)


def test_the_processes_batches_interleave_the_single_process_batch():
  """Process p of P reads elements p, p + P, ... of the one global stream: with a global
  batch of 4, process 0 holds the single process's clips 0 and 2, process 1 clips 1 and 3
  (every clip of the global batch once, none on two processes)."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.batch_size, c.data.synthetic.num_clips = 4, 8
  first = lambda p, n: next(iter(input_lib.train_dataset(c, process_index=p, process_count=n)))
  single = first(0, 1)
  for p in (0, 1):
    got = first(p, 2)
    for k in pipeline.EXAMPLE_KEYS:
      np.testing.assert_array_equal(got[k], single[k][p::2], err_msg=f"process {p}: {k}")


def test_config_seed_orders_the_clips_and_the_generator_seed_makes_them():
  """config.seed shuffles the training stream (the same synthetic clips in another order);
  config.data.synthetic.seed generates the clips (other clips, config.seed unchanged)."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.batch_size, c.data.synthetic.num_clips = 4, 4  # one batch: one epoch
  epoch = lambda: list(next(iter(input_lib.train_dataset(c, process_index=0,
                                                         process_count=1)))["disparity"])
  base = epoch()
  where = lambda clip: [j for j, b in enumerate(base) if np.array_equal(clip, b)]
  c.seed = 1
  order = [where(clip) for clip in epoch()]
  assert sorted(order) == [[0], [1], [2], [3]] and order != [[0], [1], [2], [3]]
  c.seed, c.data.synthetic.seed = 0, 1
  assert all(where(clip) == [] for clip in epoch())


def test_the_training_stream_gets_the_config_fields(monkeypatch):
  """train_dataset hands the stream the run's seed, mixing mode, per-process batch, process
  share, reader settings, and each source's weight, sources in the order of their names."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  got = {}

  def stream(sources, weights, **kwargs):
    got.update(kwargs, weights=list(weights), clips=[len(s) for s in sources])
    return "stream"

  monkeypatch.setattr(pipeline, "make_train_dataset", stream)
  c = _config()
  c.data.sources = ml_collections.ConfigDict({"b": dict(dataset="synthetic", weight=3.0),
                                              "a": dict(dataset="synthetic", weight=0.5)})
  c.seed, c.data.mixing, c.train.batch_size, c.data.synthetic.num_clips = 17, "concat", 6, 9
  c.data.num_threads, c.data.prefetch, c.data.worker_count = 3, 5, 2
  assert input_lib.train_dataset(c, process_index=2, process_count=3) == "stream"
  transforms = got.pop("transforms")
  assert got == dict(weights=[0.5, 3.0], clips=[9, 9], batch_size=2, seed=17, mode="concat",
                     process_index=2, process_count=3, num_threads=3, prefetch=5,
                     worker_count=2)
  assert list(transforms) == [None, None]  # generated clips are used as they are


def test_the_training_clips_have_the_configs_frames_and_crop_and_a_digest_of_them(
    monkeypatch):
  """Generated clips of config.data.frames frames at config.data.crop = (H, W); the record
  of the clips (what a resume compares) changes with the generator's settings; a registry
  source draws its clips with config.seed."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  c = _config()
  c.data.frames, c.data.crop, c.data.synthetic.num_clips = 3, (16, 32), 4
  records = []

  def batch():
    records.append({})
    return next(iter(input_lib.train_dataset(c, process_index=0, process_count=1,
                                             clips=records[-1])))

  assert batch()["left"].shape == (2, 3, 16, 32, 3)
  batch()
  c.data.synthetic.max_disparity += 1.0
  batch()
  assert records[0] == records[1] and records[2] != records[0]
  assert input_lib.changed_clips(records[0], records[2]) == ["synthetic: other clips (4)"]
  seeds = []

  def clips(*args, seed=None, **kwargs):
    seeds.append(seed)
    return [(types.SimpleNamespace(name="s", gather=None), [0])]

  monkeypatch.setattr(pipeline, "registry_clips", clips)
  c.seed = 11
  input_lib._source(c, ml_collections.ConfigDict(dict(dataset="sceneflow", weight=1.0)),  # pylint: disable=protected-access
                    "train", 0)
  assert seeds == [11]


def test_data_errors_name_the_config_fields_once_and_keep_their_type():
  """A data error is prefixed with the config fields behind it, unless it names a field
  itself; a missing file stays a FileNotFoundError (what the trainer tells apart)."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  naming = input_lib._naming  # pylint: disable=protected-access
  with pytest.raises(FileNotFoundError, match=r"^config\.data\.root='d': /d/x\.png: missing$"):
    with naming("config.data.root='d'"):
      raise FileNotFoundError("/d/x.png: missing")
  with pytest.raises(ValueError, match=r"^config\.data\.crop=\(8, 8\) is odd$"):
    with naming("config.data.root='d'"):
      raise ValueError("config.data.crop=(8, 8) is odd")


def test_a_workdir_inside_a_dataset_the_run_reads_is_refused(tmp_path):
  # A run in the folder dataset's train/ split wrote checkpoints/ there, which the reader then
  # took for a sequence without left/: the same command could not resume.
  from train import loop  # pylint: disable=g-import-not-at-top
  data = tmp_path / "my_videos"
  for split in ("train", "val"):
    (data / split / "seq" / "left").mkdir(parents=True)
  c = synthetic.get_config()
  c.data.sources = ml_collections.ConfigDict(
      {"mine": dict(dataset="folder", weight=1.0, root=str(data))})
  for inside in (data / "train", data / "train" / "runs" / "a"):
    with pytest.raises(ValueError, match=rf"--workdir {inside} is inside {data / 'train'}, a "
                       r"folder of the dataset 'folder' \(config\.data\.sources\.mine\): a "
                       r"run writes checkpoints/.* choose a folder outside it"):
      loop.validate_config(c, inside)
    assert not (inside / "checkpoints").exists()
  held_out = tmp_path / "held_out"
  (held_out / "val" / "seq" / "left").mkdir(parents=True)
  c.eval.dataset, c.eval.split, c.eval.root = "folder", "val", str(held_out)
  with pytest.raises(ValueError, match=r"inside .*held_out/val, a folder of the dataset "
                     r"'folder' \(config\.eval\.dataset \(config\.eval\.root\)\)"):
    loop.validate_config(c, held_out / "val" / "run")
  loop.validate_config(c, data / "runs" / "a")  # beside the splits: the reader looks not there
  loop.validate_config(c, tmp_path / "run")
  c.eval.every_steps = 0  # no validation: its data is not read
  loop.validate_config(c, held_out / "val" / "run")


def test_a_training_source_may_have_its_own_data_root(monkeypatch):
  """Your own videos (the "folder" dataset) beside the SceneFlow family under data.root."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  roots = []

  def clips(dataset, root, *args, **kwargs):
    roots.append((dataset, root))
    return [(types.SimpleNamespace(name="s", gather=None), [0])]

  monkeypatch.setattr(pipeline, "registry_clips", clips)
  c = _config()
  c.data.root = "data/datasets"
  for spec in (ml_collections.ConfigDict(dict(dataset="folder", weight=1.0, root="my_videos")),
               ml_collections.ConfigDict(dict(dataset="sceneflow", weight=1.0))):
    input_lib._source(c, spec, "train", 0)  # pylint: disable=protected-access
  assert roots == [("folder", "my_videos"), ("sceneflow", "data/datasets")]
  # the held-out set too: eval.root, else data.root
  held_out = []

  def source(dataset, root, *args, **kwargs):
    held_out.append((dataset, root))
    raise ValueError("no clips")

  monkeypatch.setattr(pipeline, "registry_source", source)
  c.eval.dataset, c.eval.split = "folder", "val"
  for root, field in (("my_videos", "eval.root"), ("", "data.root")):
    c.eval.root = root
    with pytest.raises(ValueError, match=rf"config\.{field}='{root or 'data/datasets'}'"):
      input_lib.eval_clips(c)
  assert held_out == [("folder", "my_videos"), ("folder", "data/datasets")]
  assert ckpt_lib._operational("data.sources.mine.root")  # pylint: disable=protected-access
  assert not ckpt_lib._operational("data.sources.mine.weight")  # pylint: disable=protected-access


def _own_videos(root, sequences):
  """`<root>/<split>/<name>/{left,right[,disparity]}` of the "folder" dataset: 16x16 frames,
  `(split, name, frames, with ground truth)` each."""
  import cv2  # pylint: disable=import-outside-toplevel
  from sav_jax import viz  # pylint: disable=import-outside-toplevel
  for split, name, frames, gt in sequences:
    for side in ("left", "right") + (("disparity",) if gt else ()):
      (root / split / name / side).mkdir(parents=True)
    for i in range(frames):
      for side in ("left", "right"):
        assert cv2.imwrite(str(root / split / name / side / f"{i:04d}.png"),
                           np.full((16, 16, 3), 10 * i, np.uint8))
      if gt:
        viz.write_png16(root / split / name / "disparity" / f"{i:04d}.png",
                        np.full((16, 16), 2.0 + i, np.float32))


def test_sequences_without_ground_truth_are_refused_for_training_left_out_of_validation(
    tmp_path, caplog):
  """A "folder" sequence without disparity/ in the training split stopped the run at the
  step whose batch first drew one of its clips (its repr for a name), and in the validation
  split it stopped the start as "cannot be used for training": the held-out clips without
  ground truth are left out with a warning, as those without a valid pixel are."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  _own_videos(tmp_path, [("train", "walk", 12, True), ("train", "night", 12, False),
                         ("val", "park", 4, True), ("val", "dusk", 4, False)])
  c = _config()
  c.data.sources = ml_collections.ConfigDict(
      {"mine": dict(dataset="folder", weight=1.0, root=str(tmp_path))})
  c.data.frames, c.seed = 2, 0
  with pytest.raises(ValueError, match=r"config\.data\.sources\.mine\.dataset='folder', "
                     r"config\.data\.sources\.mine\.root=.*: 1 sequence of folder/train "
                     r"without ground truth .*: night \(.*train/night/left\); every training "
                     r"clip needs it"):
    input_lib.train_dataset(c, process_index=0, process_count=1)
  c.eval.dataset, c.eval.split, c.eval.root, c.eval.num_clips = "folder", "val", str(tmp_path), 4
  with caplog.at_level(logging.WARNING, "sav_jax.data.pipeline"):
    held_out = input_lib.eval_clips(c)
  assert [x["disparity"][:, 0, 0].tolist() for x in held_out] == [[2.0, 3.0], [4.0, 5.0]]
  assert re.search(r"left out the clips of 1 sequence of folder/val without ground truth "
                   r".*: dusk \(.*val/dusk/left\)", caplog.text)
  shutil.rmtree(tmp_path / "val" / "park")
  with pytest.raises(ValueError, match=r"config\.eval\.dataset='folder', .*: no clip has ground "
                                       r"truth to be scored against: 1 sequence of folder/val"):
    input_lib.eval_clips(c)


def test_a_resume_whose_training_clips_changed_is_warned_about(tmp_path, caplog):
  """Data added to a dataset between a stop and its resume: the saved position in the data
  was applied to another shuffle, silently (some clips twice, some never)."""
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.checkpoint.async_save = False
  model, mesh = ToyStereo(), state_lib.make_mesh()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  clips = {}
  it = iter(input_lib.train_dataset(c, process_index=0, process_count=1, clips=clips))
  assert list(clips) == list(c.data.sources) and all(v["clips"] > 0 for v in clips.values())
  manager = ckpt_lib.make_manager(tmp_path, c)
  state, _, _ = loop.initial_state(c, model, tx, mesh, manager, it, data_clips=clips)
  ckpt_lib.save(manager, state.replace(step=jnp.asarray(3, jnp.int32)), it, 3, force=True,
                run_config=c, data_clips=clips)
  manager.wait_until_finished()
  assert ckpt_lib.saved_clips(manager, 3) == clips
  with caplog.at_level(logging.WARNING):
    loop.initial_state(c, model, tx, mesh, manager, it, data_clips=clips)
  assert "training clips changed" not in caplog.text
  name = next(iter(clips))
  more = {name: dict(clips[name], clips=clips[name]["clips"] + 10, digest="0" * 16)}
  with caplog.at_level(logging.WARNING):
    loop.initial_state(c, model, tx, mesh, manager, it, data_clips=more)
  assert (f"the training clips changed since checkpoint 3 ({name}: {clips[name]['clips']} -> "
          f"{clips[name]['clips'] + 10} clips): the restored position") in caplog.text
  assert "config field" not in caplog.text  # (the config as saved)
  for gammas, says in (([0.8], "1 config field changed since checkpoint 3: loss.gamma: 0.9 -> "
                                "0.8\n"),
                       ([0.8, 1e-4], "2 config fields changed since checkpoint 3: loss.gamma: "
                                     "0.9 -> 0.8; optimizer.weight_decay: 1e-05 -> 0.0001\n")):
    changed = c.copy_and_resolve_references()
    changed.loss.gamma = gammas[0]
    if len(gammas) > 1:
      changed.optimizer.weight_decay = gammas[1]
    caplog.clear()
    with caplog.at_level(logging.WARNING):
      loop.initial_state(changed, model, tx, mesh, manager, it, data_clips=clips)
    assert f"resuming with {says}" in caplog.text + "\n", caplog.text
  other = {name: dict(clips[name], digest="1" * 16), "b": clips[name]}
  assert input_lib.changed_clips(clips, other) == [
      "b: added", f"{name}: other clips ({clips[name]['clips']})"]
  assert input_lib.changed_clips({}, more) == []  # a checkpoint without the record
  assert clips[name]["seeding"] == pipeline.SEEDING
  before = {name: {k: v for k, v in clips[name].items() if k != "seeding"}}  # older sav-jax
  assert input_lib.changed_clips(before, clips) == [
      f"{name}: the clip order and augmentation are drawn with other seeds (the checkpoint is "
      "of sav-jax before 2026-12-05)"]
  # the digest tells which clips, in order
  seq = types.SimpleNamespace(name="s")
  assert pipeline.clips_digest([(seq, [0, 1])]) == pipeline.clips_digest([(seq, (0, 1))])
  assert pipeline.clips_digest([(seq, [0, 1])]) != pipeline.clips_digest([(seq, [1, 2])])


def test_vda_weights_load_into_the_real_model(tmp_path, vda_state_dict, monkeypatch):
  from sav_jax.convert import CheckpointError, save_state_dict  # pylint: disable=g-import-not-at-top
  from sav_jax.convert import vda as vda_lib  # pylint: disable=g-import-not-at-top
  # (the prior's shapes are the run's model's: no trace of the prior alone, ~1.8 s)
  monkeypatch.setattr(vda_lib, "_abstract_params", lambda model: pytest.fail("traced the prior"))
  save_state_dict(vda_state_dict, tmp_path / "vda.npz")
  vda = ckpt_lib.load_vda_params(tmp_path / "vda.npz")
  abstract = _real_abstract_params()["depthnet"]["depthanything"]
  assert jax.tree.structure(vda) == jax.tree.structure(abstract)
  jax.tree.map(lambda a, b: np.testing.assert_equal(np.shape(a), b.shape), vda, abstract)
  from train import loop  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  c.vda_weights = str(tmp_path / "vda.npz")
  host, got = loop.initial_weights(c, _real_abstract_params())  # checked against its subtree
  assert host is None and jax.tree.structure(got) == jax.tree.structure(abstract)
  # Converted for the run's depth prior: VDA-S weights are not a ViT-L prior.
  with pytest.raises(CheckpointError) as e:
    ckpt_lib.load_vda_params(tmp_path / "vda.npz", sav_jax.SAVConfig(vda_encoder="vitl"))
  assert "\n" not in str(e.value) and str(e.value).endswith(  # one line: the first problem
      "(first: the depth prior's weights are vits (DINOv2 width 384); the model is configured "
      "for vitl (SAVConfig.vda_encoder))"), e.value
  assert str(e.value).startswith(f"config.vda_weights={tmp_path / 'vda.npz'}: "), e.value
  assert re.search(r"key 'pretrained\.cls_token': shape \(1, 1, 384\) does not match Video "
                   r"Depth Anything \(expects \(1, 1, 1024\)\)",  # the whole report (-v 1)
                   str(e.value.__cause__).replace("\n", " ")), e.value.__cause__


def test_init_from_a_folder_of_another_depth_prior_names_both(monkeypatch):
  """A folder's params (a `sav-jax convert` output, a run) of a ViT-S prior for a ViT-B model:
  a 5,000-character list of 335 shape problems that never said ViT-S vs ViT-B."""
  from train import loop  # pylint: disable=g-import-not-at-top
  token = {"depthnet": {"depthanything": {"pretrained": {"cls_token": np.zeros((1, 1, 384))}}}}
  monkeypatch.setattr(ckpt_lib, "load_model_params", lambda *a, **k: token)
  c = synthetic.get_config()
  c.init_from, c.model.vda_encoder = "runs/sceneflow", "vitb"
  with pytest.raises(ValueError, match=r"^config\.init_from=runs/sceneflow: its depth prior is "
                     r"vits \(DINOv2 width 384\); this run's model is configured for vitb: pass "
                     r"--config\.model\.vda_encoder=vits$"):
    loop.initial_weights(c, {})
  c.model.vda_encoder = "vits"  # the same prior: on to the shape check, which names the rest
  with pytest.raises(ValueError, match=r"its params do not match the model \(2 problems\): "
                                       r"missing x; unexpected depthnet"):
    loop.initial_weights(c, {"x": jax.ShapeDtypeStruct((1,), jnp.float32)})


def test_init_files_of_the_wrong_kind_name_the_file_and_the_field(tmp_path, vda_state_dict,
                                                                   sav_state_dict):
  from sav_jax.convert import CheckpointError, save_state_dict  # pylint: disable=g-import-not-at-top
  save_state_dict(vda_state_dict, tmp_path / "vda.npz")
  save_state_dict(sav_state_dict, tmp_path / "sav.npz")
  with pytest.raises(CheckpointError) as e:
    ckpt_lib.load_vda_params(tmp_path / "sav.npz")
  assert "config.vda_weights=" in str(e.value) and "sav.npz is a Stereo Any Video" in str(e.value)
  assert "give it as config.init_from" in str(e.value) and len(str(e.value)) < 400
  with pytest.raises(CheckpointError, match=r"vda\.npz is a Video Depth Anything .*vda_weights"):
    ckpt_lib.load_model_params(tmp_path / "vda.npz", sav_jax.SAVConfig())
  broken = dict(sav_state_dict)
  del broken["fnet.conv1.weight"]
  save_state_dict(broken, tmp_path / "broken.npz")
  with pytest.raises(CheckpointError, match=r"(?s)config.init_from=.*broken.npz: .*fnet.conv1.weight"):
    ckpt_lib.load_model_params(tmp_path / "broken.npz", sav_jax.SAVConfig())
  del broken["fnet.conv1.bias"]  # train's one line: the count and the first, as infer's
  save_state_dict(broken, tmp_path / "broken.npz", overwrite=True)
  with pytest.raises(CheckpointError) as e:
    ckpt_lib.load_model_params(tmp_path / "broken.npz", sav_jax.SAVConfig())
  assert "\n" not in str(e.value) and "2 problem(s)" in str(e.value), str(e.value)
  assert "(first: missing key 'fnet.conv1.bias')" in str(e.value), str(e.value)
  (tmp_path / "notes").write_text("not weights")  # a file that is no checkpoint: the field too
  with pytest.raises(CheckpointError, match=rf"^config.init_from: {tmp_path / 'notes'}: unknown "
                                            "checkpoint suffix"):
    ckpt_lib.load_model_params(tmp_path / "notes", sav_jax.SAVConfig())


def test_paths_with_the_home_folder_as_tilde_are_expanded(tmp_path, monkeypatch,
                                                          vda_state_dict, sav_state_dict):
  """The shell leaves `~` after `--workdir=` and `--config.init_from=`: the run made a folder
  named `~` in the current one, and the weights' files were not found."""
  from train import loop  # pylint: disable=g-import-not-at-top
  from sav_jax.convert import CheckpointError, save_state_dict  # pylint: disable=g-import-not-at-top
  monkeypatch.setenv("HOME", str(tmp_path / "home"))
  monkeypatch.chdir(tmp_path)
  save_state_dict(vda_state_dict, tmp_path / "home" / "vda.npz")
  save_state_dict(sav_state_dict, tmp_path / "home" / "sav.npz")
  # read from the home folder: the other kind's error, not "no such file"
  with pytest.raises(CheckpointError, match=r"sav\.npz is a Stereo Any Video"):
    ckpt_lib.load_vda_params("~/sav.npz")
  with pytest.raises(CheckpointError, match=r"vda\.npz is a Video Depth Anything"):
    ckpt_lib.load_model_params("~/vda.npz", sav_jax.SAVConfig())
  from sav_jax.convert import orbax_io  # pylint: disable=import-outside-toplevel
  step = tmp_path / "home" / "run" / "checkpoints" / "3"
  (step / "state").mkdir(parents=True)
  (step / orbax_io._METADATA_FILE).write_text("{}")  # pylint: disable=protected-access
  c = synthetic.get_config()
  c.init_from = "~/sav.npz"
  c.train.num_steps = 2  # the home folder's run is at step 3: refused, naming it
  with pytest.raises(ValueError, match=rf"resume from \({step}\)"):
    loop.setup(c, "~/run")
  c.vda_weights = "~/none.npz"  # a new run's files, looked for in the home folder: only this
  with pytest.raises(FileNotFoundError, match="config.vda_weights=~/none.npz: no such file"):
    loop.setup(c, "~/new")
  assert sorted(p.name for p in tmp_path.iterdir()) == ["home"]  # no folder named "~"


def test_a_bad_generator_config_used_only_for_validation_says_so():
  from train import loop  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  c.data.sources = {"sf": {"dataset": "sceneflow", "weight": 1.0}}  # trains on a dataset
  c.data.crop, c.data.synthetic.max_disparity = (32, 64), 64.0
  c.eval.every_steps, c.eval.dataset = 5, "synthetic"  # validates on generated clips
  with pytest.raises(ValueError, match=r"config\.data\.synthetic\.max_disparity must be < "
                                       r"width.* \(for the validation clips: config\.eval\.dataset="
                                       r"'synthetic' generates them at config\.data\.crop=\(32, 64\)"):
    loop._check_blocks(c)  # pylint: disable=protected-access


def test_resumed_run_logs_each_step_once(tmp_path):
  from train.logging_utils import MetricWriter  # pylint: disable=g-import-not-at-top
  first = MetricWriter(tmp_path)
  for step in (10, 20, 30):  # a run checkpointed at step 20, killed after logging step 30
    first.write(step, {"loss": 1.0})
  first.close()
  with open(tmp_path / "metrics.jsonl", "a", encoding="utf-8") as f:
    f.write('{"step": 40, "spl')  # cut by the kill
  resumed = MetricWriter(tmp_path, start_step=20)
  resumed.write(30, {"loss": 0.5})
  resumed.close()
  steps = [json.loads(l)["step"] for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  assert steps == [10, 20, 30]
  records = [json.loads(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  assert records[-1]["loss"] == 0.5
  aside = (tmp_path / "metrics.superseded.jsonl").read_text().splitlines()
  assert json.loads(aside[0])["loss"] == 1.0 and aside[1] == '{"step": 40, "spl'
  fresh = tmp_path / "fresh"  # killed before its first checkpoint: restarts at step 0
  first = MetricWriter(fresh)
  first.write(0, {"epe": 2.0}, split="val")  # eval.at_start
  first.write(1, {"loss": 1.0})
  first.close()
  again = MetricWriter(fresh, start_step=0)
  again.write(0, {"epe": 2.0}, split="val")
  again.close()
  records = [json.loads(l) for l in (fresh / "metrics.jsonl").read_text().splitlines()]
  assert [(r["step"], r["split"]) for r in records] == [(0, "val")]
  assert len((fresh / "metrics.superseded.jsonl").read_text().splitlines()) == 2
  # TensorBoard shows the same: each run's events from its start, none lost (the runs
  # above started within a second: tensorboardX's file names alone were the same).
  assert _tensorboard_view(tmp_path / "tb") == {"train/loss": [(10, 1.0), (20, 1.0), (30, 0.5)]}
  assert _tensorboard_view(fresh / "tb") == {"val/epe": [(0, 2.0)]}


def test_metric_records_are_strict_json_and_the_superseded_ones_accumulate(tmp_path):
  """NaN and inf as strings (JSON has no such numbers); lines that are no record, or a record
  cut before its newline (the next record would be written onto it), are moved aside too."""
  from train.logging_utils import MetricWriter  # pylint: disable=g-import-not-at-top
  first = MetricWriter(tmp_path)
  first.write(1, {"loss": float("nan"), "epe": float("inf")})
  first.write(2, {"loss": 1.0})
  first.close()
  with open(tmp_path / "metrics.jsonl", "a", encoding="utf-8") as f:
    f.write('[1, 2]\n3\n{"step": 1, "split": "train"}')
  for loss in (0.5, 0.25):  # two runs resumed from step 1, each after logging step 2
    resumed = MetricWriter(tmp_path, start_step=1)
    assert resumed.logged(1, "train") and not resumed.logged(2, "train")
    assert not resumed.logged(1, "val")
    resumed.write(2, {"loss": loss})
    assert resumed.logged(2, "train")
    resumed.close()
  strict = lambda line: json.loads(line, parse_constant=pytest.fail)  # pylint: disable=unnecessary-lambda-assignment
  records = [strict(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  assert [(r["step"], r["loss"]) for r in records] == [(1, "nan"), (2, 0.25)]
  assert records[0]["epe"] == "inf"
  aside = (tmp_path / "metrics.superseded.jsonl").read_text().splitlines()
  assert aside[1:4] == ["[1, 2]", "3", '{"step": 1, "split": "train"}'] and len(aside) == 5
  assert [strict(aside[i])["loss"] for i in (0, 4)] == [1.0, 0.5]
  assert not MetricWriter(tmp_path / "other", enabled=False).logged(0, "val")
  assert not (tmp_path / "other").exists()


def test_metric_records_take_the_steps_numpy_and_jax_scalars(tmp_path, caplog):
  """The loop's values are NumPy and JAX scalars: JSON numbers in the record, the same at
  `<split>/<name>` in TensorBoard; a NaN is said by the loop, not by tensorboardX too."""
  from train.logging_utils import MetricWriter  # pylint: disable=g-import-not-at-top
  workdir = tmp_path / "runs" / "a"  # (created with its parents)
  writer = MetricWriter(workdir)
  with caplog.at_level(logging.WARNING):
    writer.write(np.int64(3), {"loss": np.float32(0.5), "epe": jnp.asarray(2.0)}, split="val")
    writer.write(jnp.asarray(4), {"loss": np.float32("nan")}, split="val")
  assert not [r for r in caplog.records if r.name.startswith("tensorboardX")]
  # each record is on disk once written (a killed run keeps it), before the writer is closed
  records = [json.loads(l) for l in (workdir / "metrics.jsonl").read_text().splitlines()]
  assert [(r["step"], r["split"], r["loss"]) for r in records] == [(3, "val", 0.5),
                                                                   (4, "val", "nan")]
  assert records[0]["epe"] == 2.0
  view = _tensorboard_view(workdir / "tb")
  assert view["val/epe"] == [(3, 2.0)] and view["val/loss"][0] == (3, 0.5)
  writer.close()
  resumed = MetricWriter(workdir, start_step=4)  # the log says which split each step has
  assert resumed.logged(3, "val") and resumed.logged(4, "val")
  assert not resumed.logged(3, "train") and not resumed.logged(4, "train")
  resumed.close()
  assert not (workdir / "metrics.superseded.jsonl").exists()  # (nothing after step 4)


def _tensorboard_view(folder) -> dict[str, list[tuple[int, float]]]:
  """The scalars TensorBoard shows for the event files in `folder`: read in the order of their
  names, a file's START session log at step s drops the earlier files' events at steps >= s
  (`purge_step`)."""
  import struct  # pylint: disable=g-import-not-at-top
  from tensorboardX.proto import event_pb2  # pylint: disable=g-import-not-at-top
  scalars = {}
  for path in sorted(folder.glob("events.out.tfevents.*")):
    data, i = path.read_bytes(), 0
    while i < len(data):  # TFRecord: length (8 bytes), its CRC (4), the event, its CRC (4)
      (n,) = struct.unpack("<Q", data[i:i + 8])
      event = event_pb2.Event.FromString(data[i + 12:i + 12 + n])
      i += 16 + n
      if event.session_log.status == event_pb2.SessionLog.START:
        scalars = {tag: [(s, v) for s, v in values if s < event.step]
                   for tag, values in scalars.items()}
      for value in event.summary.value:
        scalars.setdefault(value.tag, []).append((event.step, value.simple_value))
  return {tag: values for tag, values in scalars.items() if values}


def test_scratch_runs_start_from_the_official_initialisation(tmp_path):
  from sav_jax.model.init import init_variables  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  c.seed = 3
  model, mesh = sav_jax.StereoAnyVideo(state_lib.model_config(c)), state_lib.make_mesh()
  params = _real_abstract_params()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  manager = ckpt_lib.make_manager(tmp_path / "run", c)
  state, _, source = loop.initial_state(c, model, tx, mesh, manager, None, params)
  assert source == "scratch"
  want = init_variables(state_lib.model_config(c), seed=3)["params"]
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(state.params), want)


def test_train_command_reports_a_missing_init_file_in_one_line(tmp_path):
  import subprocess  # pylint: disable=g-import-not-at-top
  from tests.train.conftest import ROOT, child_env  # pylint: disable=g-import-not-at-top
  proc = subprocess.run(
      [sys.executable, "-m", "train", "--config", str(ROOT / "configs/synthetic.py"),
       "--workdir", str(tmp_path / "w"), f"--config.init_from={tmp_path / 'missing.pth'}",
       "--config.train.progress_bar=False"],
      cwd=ROOT, env=child_env(tmp_path / "cache"), capture_output=True, text=True, timeout=300,
      check=False)
  assert proc.returncode == 2, proc.stderr[-2000:]
  assert f"train: error: config.init_from={tmp_path / 'missing.pth'}: no such" in proc.stderr
  assert "Traceback" not in proc.stderr and not (tmp_path / "w").exists()


class _BigToy(ToyStereo):
  """`ToyStereo` with one parameter large enough that orbax writes it to a chunk file
  (smaller arrays are stored inline in the checkpoint's index)."""

  big: int = 2000

  @nn.compact
  def __call__(self, left, right, iters=2, final_only=False):
    self.param("big", nn.initializers.normal(), (self.big,))
    return ToyStereo.__call__(self, left, right, iters, final_only)


def _toy_run(workdir, frozen=None, run_config=False):
  """A toy training run's config, model, optimizer and mesh, and its checkpoint at step 1 in
  `workdir` (with `optimizer.frozen=frozen` if given; with the run config if `run_config`)."""
  c = _config()
  c.checkpoint.async_save = False
  if frozen is not None:
    c.optimizer.frozen = frozen
  model, mesh = _BigToy(), state_lib.make_mesh()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  state, _ = state_lib.create_train_state(model, tx, c, mesh)
  manager = ckpt_lib.make_manager(workdir, c)
  assert ckpt_lib.save(manager, state, _toy_iterator(), 1, force=True,
                       run_config=c if run_config else None)
  manager.wait_until_finished()
  manager.close()
  return c, model, tx, mesh


def _toy_iterator(num_clips: int = 10, seed: int = 0):
  """A training stream of `num_clips` tiny synthetic clips (T=2, 16x16), batch 2."""
  src = pipeline.synthetic_source(SyntheticConfig(frames=2, height=16, width=16,
                                                  max_disparity=8.0), num_clips)
  return iter(pipeline.make_train_dataset([src], [1.0], batch_size=2, seed=seed, num_threads=1))


def _toy_restore(workdir, c, model, tx, mesh):
  abstract = jax.eval_shape(state_lib.make_init_fn(model, tx, c))
  manager = ckpt_lib.make_manager(workdir, c)
  try:
    return ckpt_lib.restore(manager, abstract, state_lib.state_shardings(abstract, mesh),
                            _toy_iterator())
  finally:
    manager.close()


@pytest.fixture(scope="module")
def toy_run(module_tmp_path):
  """`(workdir, config, model, tx, mesh)` of a toy run with a checkpoint at step 1; tests
  that damage it work on a copy."""
  workdir = module_tmp_path / "toy_run"
  return (workdir, *_toy_run(workdir))


def test_training_checkpoint_params_restore_without_orbax_warnings(toy_run, caplog):
  workdir = toy_run[0]
  with caplog.at_level("WARNING"):
    variables, config = sav_jax.convert.restore_variables(workdir)
  assert set(variables) == {"params"} and config["step"] == 1
  assert not [r for r in caplog.records if "could not be restored" in r.getMessage()]


def _corrupt_copy(workdir, tmp_path, how):
  import shutil  # pylint: disable=g-import-not-at-top
  copy = tmp_path / "run"
  shutil.copytree(workdir, copy)
  chunks = list((copy / "checkpoints" / "1" / "state").glob("ocdbt.process_*/d/*"))
  assert chunks
  for chunk in chunks:
    if how == "truncated":
      chunk.write_bytes(chunk.read_bytes()[:10])
    else:
      chunk.unlink()
  return copy


def test_a_pipe_in_a_training_checkpoint_is_refused_before_the_restore(toy_run, tmp_path):
  """A named pipe in the step folder (even one orbax would not read) is refused, as for
  `restore_variables`: a pipe orbax reads makes a resume wait forever, Ctrl-C held back."""
  _, c, model, tx, mesh = toy_run
  copy = tmp_path / "run"
  shutil.copytree(toy_run[0], copy)
  pipe = copy / "checkpoints" / "1" / "state" / "stray"
  os.mkfifo(pipe)
  with pytest.raises(sav_jax.convert.CheckpointError, match=f"{pipe} is not a regular file"):
    _toy_restore(copy, c, model, tx, mesh)


def test_changed_fields_names_fields_new_or_gone_since_the_checkpoint():
  """A field the saved run config lacks (added to the config since) or holds alone (gone
  since) is a change too, shown as '(absent)'; operational ones (checkpoint.*) are not."""
  c = _config()
  saved = dict(ckpt_lib.run_fields(c))
  del saved["train.num_steps"]  # c has it (10)
  del saved["checkpoint.keep"]  # operational: not named
  saved["train.gone"] = 1
  saved["eval.every_steps"] = -7  # where and how it runs: not named
  saved["init_from"] = "/elsewhere"
  assert ckpt_lib.changed_fields(None, 1, c, saved=saved) == [
      "train.gone: 1 -> '(absent)'", "train.num_steps: '(absent)' -> 10"]
  # A checkpoint saved before the run config was: nothing to compare (not every field "new")
  assert ckpt_lib.changed_fields(None, 1, c, saved={}) == []


def test_a_saved_run_config_without_all_three_weights_fields_leaves_the_prior_unknown():
  """`saved_depth_prior` derives the prior from the saved run config only where it holds all
  of vda_weights, init_from and random_depth_prior; with some missing it is unknown."""
  unknown = "unknown (saved before depth_prior was recorded)"
  assert ckpt_lib.saved_depth_prior({"run": {"init_from": "w.pth"}}) == unknown
  assert ckpt_lib.saved_depth_prior({"run": {"vda_weights": "v.pth",
                                             "random_depth_prior": False}}) == unknown


def test_a_checkpoint_without_data_positions_passes_the_data_state_check(tmp_path):
  """No `data/process_*` files (a copy cut short): `check_data_state` has no counts to
  compare and lets `restore` name the missing folder, instead of failing itself."""
  c = _config()
  (tmp_path / "1").mkdir()
  manager = _Steps(tmp_path, [1])
  ckpt_lib.check_data_state(manager, 1, c, saved={"data.worker_count": c.data.worker_count})
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"data.worker_count=5, this run"):
    ckpt_lib.check_data_state(manager, 1, c, saved={"data.worker_count": 5})


@pytest.mark.parametrize("how", ["truncated", "deleted"])
def test_corrupt_training_checkpoint_is_named_as_such(toy_run, tmp_path, how, monkeypatch):
  import gc  # pylint: disable=g-import-not-at-top
  _, c, model, tx, mesh = toy_run
  copy = _corrupt_copy(toy_run[0], tmp_path, how)
  sav_jax.convert.orbax_io.quiet_failed_reads()  # also once the test has put its hook back
  unraisable = []
  monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
  step = copy / "checkpoints" / "1"
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=f"{step}: the checkpoint is corrupt or incomplete") as e:
    sav_jax.convert.restore_variables(copy)  # infer, convert, eval, init_from
  assert "TensorStore" not in str(e.value) and len(str(e.value)) < 600
  with pytest.raises(sav_jax.convert.CheckpointError) as e:  # resuming the run
    _toy_restore(copy, c, model, tx, mesh)
  assert f"{step}: the checkpoint is corrupt or incomplete" in str(e.value)
  assert "does not match" not in str(e.value) and "Move this step folder" in str(e.value)
  gc.collect()  # orbax's other pending reads: no "Exception ignored in <coroutine ...>"
  assert not [u for u in unraisable if "reading array" in str(u.exc_value)]


def test_training_checkpoint_without_an_item_is_named_incomplete(toy_run, tmp_path):
  import shutil  # pylint: disable=g-import-not-at-top
  _, c, model, tx, mesh = toy_run
  copy = tmp_path / "run"
  shutil.copytree(toy_run[0], copy)
  step = copy / "checkpoints" / "1"
  shutil.rmtree(step / "data")  # the grain iterator's state
  with pytest.raises(sav_jax.convert.CheckpointError) as e:
    _toy_restore(copy, c, model, tx, mesh)
  assert str(e.value).startswith(f"{step}: the checkpoint is incomplete: it has no data folder "
                                 "(the data iterator)")
  assert "does not match" not in str(e.value) and "Move this step folder" in str(e.value)
  shutil.copytree(toy_run[0] / "checkpoints" / "1" / "data", step / "data")
  (step / "state" / "_METADATA").unlink()  # the list of the state's arrays: resuming said "does
  with pytest.raises(sav_jax.convert.CheckpointError) as e:  # not match this run's model"
    _toy_restore(copy, c, model, tx, mesh)
  assert str(e.value).startswith(f"{step}: the checkpoint is incomplete: it has no "
                                 "state/_METADATA")
  assert "does not match" not in str(e.value) and "Move this step folder" in str(e.value)
  with pytest.raises(sav_jax.convert.CheckpointError,  # (infer, convert: a FileNotFoundError)
                     match=f"{step / 'state'}: the checkpoint is corrupt or incomplete .*no "
                     "_METADATA"):
    sav_jax.convert.restore_variables(copy)
  shutil.copy(toy_run[0] / "checkpoints" / "1" / "state" / "_METADATA", step / "state")
  (step / "data" / "process_0-of-1.json").unlink()  # the folder, without this process's file
  with pytest.raises(sav_jax.convert.CheckpointError) as e:
    _toy_restore(copy, c, model, tx, mesh)
  assert str(e.value).startswith(f"{step}: the checkpoint is incomplete: it has no "
                                 "data/process_0-of-1.json (this process's position in the data)")
  assert "does not match" not in str(e.value)


def test_a_refused_resume_names_the_config_fields_it_changes(tmp_path):
  from train import loop  # pylint: disable=g-import-not-at-top
  c, model, _, mesh = _toy_run(tmp_path, run_config=True)
  c2 = _config()
  c2.optimizer.clip_norm = 0.0  # no clipping stage: another optimizer state tree
  tx2 = optim.make_optimizer(c2.optimizer, c2.train.num_steps)
  manager = ckpt_lib.make_manager(tmp_path, c2)
  try:
    with pytest.raises(sav_jax.convert.CheckpointError,
                       match=r"does not match this run's model or optimizer config .*The config "
                       rf"fields this run changes since that checkpoint: optimizer.clip_norm: "
                       rf"{c.optimizer.clip_norm!r} -> 0.0$"):
      loop.initial_state(c2, model, tx2, mesh, manager, _toy_iterator())
  finally:
    manager.close()


def _check_data_state(workdir, config):
  manager = ckpt_lib.make_manager(workdir, config)
  try:
    ckpt_lib.check_data_state(manager, 1, config)
  finally:
    manager.close()


def test_resume_needs_the_saving_runs_process_and_worker_counts(toy_run, tmp_path):
  # grain's iterator state is per process and its form depends on data.worker_count: other
  # counts failed as "does not match this run's model or optimizer config" (KeyError
  # 'exhausted') or with an IndexError traceback.
  import shutil  # pylint: disable=g-import-not-at-top
  workdir, c = toy_run[:2]
  _check_data_state(workdir, c)  # its own settings
  workers = ml_collections.ConfigDict(c.to_dict())
  workers.data.worker_count = 2
  # a checkpoint without the run config: told from the saved state's form
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"checkpoints/1: its data iterator was saved with "
                     r"data.worker_count=0, this run has 2: resume with the saving run's"):
    _check_data_state(workdir, workers)
  saved = tmp_path / "with_config"
  _toy_run(saved, run_config=True)
  _check_data_state(saved, c)
  with pytest.raises(sav_jax.convert.CheckpointError, match="data.worker_count=0, this run has 2"):
    _check_data_state(saved, workers)
  copy = tmp_path / "two_processes"
  shutil.copytree(workdir, copy)
  data = copy / "checkpoints" / "1" / "data"
  (data / "process_0-of-1.json").rename(data / "process_0-of-2.json")
  shutil.copy(data / "process_0-of-2.json", data / "process_1-of-2.json")
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"saved by 2 process\(es\), this run has 1: resume with that many"):
    _check_data_state(copy, c)


def test_resume_with_another_frozen_pattern_is_refused(toy_run, tmp_path):
  workdir, c, model, _, mesh = toy_run
  c2 = _config()
  c2.optimizer.frozen = ""  # Adam moments for the prior too: longer moment vectors
  tx2 = optim.make_optimizer(c2.optimizer, c2.train.num_steps)
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"does not match this run's model or optimizer config \(opt_state/1/0/"
                     r"mu has shape \(2010,\) in the checkpoint, \(2031,\) in this run; AdamW's "
                     r"moment vectors hold one value per trainable parameter: e.g. "
                     r"optimizer.frozen differs\)"):
    _toy_restore(workdir, c2, model, tx2, mesh)
  # The other way round: the checkpoint's moments cover the prior, this run's do not.
  c3, _, _, _ = _toy_run(tmp_path / "unfrozen", frozen="")
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"opt_state/1/0/mu has shape \(2031,\) in the checkpoint, \(2010,\)"):
    _toy_restore(tmp_path / "unfrozen", c, model, tx, mesh)
  hook = sys.unraisablehook
  restored = _toy_restore(tmp_path / "unfrozen", c3, model, tx2, mesh)  # its own config
  assert sys.unraisablehook is hook  # a good checkpoint leaves no global hook behind
  abstract3 = jax.eval_shape(state_lib.make_init_fn(model, tx2, c3))
  assert jax.tree.map(jnp.shape, restored.opt_state) == jax.tree.map(jnp.shape,
                                                                     abstract3.opt_state)


def test_checkpoint_of_the_per_parameter_optimizer_layout_is_named(tmp_path):
  """Checkpoints written before the optimizer worked on one vector held the moments per leaf
  (`optax.multi_transform`): resuming names that, and init_from still reads the weights."""
  import optax  # pylint: disable=g-import-not-at-top
  c = _config()
  c.checkpoint.async_save = False
  model, mesh = _BigToy(), state_lib.make_mesh()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  state, _ = state_lib.create_train_state(model, tx, c, mesh)
  labels = optim.param_labels(state.params, c.optimizer.frozen)
  old_tx = optax.multi_transform({optim.TRAINABLE: tx, optim.FROZEN: optax.set_to_zero()},
                                 labels)
  old = state.replace(opt_state=old_tx.init(state.params))
  manager = ckpt_lib.make_manager(tmp_path, c)
  assert ckpt_lib.save(manager, old, _toy_iterator(), 1, force=True)
  manager.wait_until_finished()
  manager.close()
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"checkpoints/1: cannot resume from this checkpoint: its optimizer "
                     r"state has the per-parameter layout of sav-jax before 2026-12-02 .*Start a "
                     r"new WORKDIR with --config.init_from=<that workdir> to keep its weights"):
    _toy_restore(tmp_path, c, model, tx, mesh)
  variables, _ = sav_jax.convert.restore_variables(tmp_path)  # what init_from reads
  jax.tree.map(np.testing.assert_array_equal, variables["params"],
               jax.device_get(state.params))


def test_resume_with_another_parameter_shape_names_the_array(toy_run):
  workdir, c, _, tx, mesh = toy_run
  # The parameter is named, not the optimizer's moment vectors that change with it.
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"does not match this run's model or optimizer config \(params/big has "
                     r"shape \(2000,\) in the checkpoint, \(1000,\) in this run; e.g. another "
                     r"model config\)"):
    _toy_restore(workdir, c, _BigToy(big=1000), tx, mesh)


def test_checkpoint_folder_keeps_the_users_own_folders(tmp_path):
  c = _config()
  ckpts = tmp_path / "checkpoints"
  (ckpts / "notes.orbax-checkpoint-tmp-5").mkdir(parents=True)
  (ckpts / "notes.orbax-checkpoint-tmp-5" / "n.txt").write_text("keep me")
  (ckpts / "7.orbax-checkpoint-tmp-1234").mkdir()  # a save cut by a kill
  ckpt_lib.make_manager(tmp_path, c).close()
  assert sorted(p.name for p in ckpts.iterdir()) == ["notes.orbax-checkpoint-tmp-5"]
  (ckpts / "0").mkdir()
  (ckpts / "0" / "mine.txt").write_text("keep me")
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"\['0'\] are named like checkpoints but are not"):
    ckpt_lib.make_manager(tmp_path, c)
  assert (ckpts / "0" / "mine.txt").read_text() == "keep me"
  shutil.rmtree(ckpts / "0")
  # An old checkpoint whose deletion (keep) a kill cut short: orbax deletes it in place, so
  # its metadata can go first. Named as such (it was "not ones written by python -m train").
  (ckpts / "3" / "state" / "ocdbt.process_0").mkdir(parents=True)
  (ckpts / "3" / "commit_success.txt").write_text("")
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"\['3'\] hold only parts of a checkpoint .*checkpoint.keep.*Delete "
                     "them, or move them out of this folder, to resume"):
    ckpt_lib.make_manager(tmp_path, c)
  assert (ckpts / "3" / "state" / "ocdbt.process_0").is_dir()  # left alone


def test_only_a_steps_own_unfinished_save_is_removed_at_start(tmp_path):
  """The start removes `<step>.orbax-checkpoint-tmp[-N]` folders only: not a user's folders
  whose names merely contain that (a prefix, a suffix), not a link of that name (nor what it
  points to); and a step-named link is not taken for a partly deleted checkpoint."""
  c = _config()
  ckpts = tmp_path / "checkpoints"
  ckpts.mkdir()
  mine = ["run7.orbax-checkpoint-tmp-1", "7.orbax-checkpoint-tmp-1.bak", "a7.orbax-checkpoint-tmp"]
  for name in mine:
    (ckpts / name).mkdir()
    (ckpts / name / "n.txt").write_text("keep me")
  (tmp_path / "elsewhere").mkdir()
  (tmp_path / "elsewhere" / "n.txt").write_text("keep me")
  (ckpts / "8.orbax-checkpoint-tmp-2").symlink_to(tmp_path / "elsewhere")
  (ckpts / "9.orbax-checkpoint-tmp").mkdir()  # a save cut by a kill: removed
  (ckpts / "5.orbax-checkpoint-tmp-3").write_text("keep me")  # a file, not a save: kept
  mine.append("5.orbax-checkpoint-tmp-3")
  ckpt_lib.make_manager(tmp_path, c).close()
  assert sorted(p.name for p in ckpts.iterdir()) == sorted(mine + ["8.orbax-checkpoint-tmp-2"])
  for name in mine[:-1]:
    assert (ckpts / name / "n.txt").read_text() == "keep me"
  assert (ckpts / "8.orbax-checkpoint-tmp-2").is_symlink()
  assert (tmp_path / "elsewhere" / "n.txt").read_text() == "keep me"
  # A step-named link to a folder of checkpoint-like entries is not called the remains of a
  # deletion ("Delete them"): it is named as a folder that is not a checkpoint (move it)
  (tmp_path / "partial" / "state").mkdir(parents=True)
  (ckpts / "3").symlink_to(tmp_path / "partial")
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"\['3'\] are named like checkpoints but are not ones written"):
    ckpt_lib.make_manager(tmp_path, c)
  assert (tmp_path / "partial" / "state").is_dir()


@pytest.mark.parametrize("field,value,match", [
    ("train.batch_size", 0, r"config\.train\.batch_size=0: expected an integer >= 1"),
    ("train.batch_size", 3, r"config\.train\.batch_size=3 is not divisible by the 2 devices"),
    ("eval.batch_size", 3, r"config\.eval\.batch_size=3 is not divisible by the 2 devices"),
    ("train.num_steps", 0, r"config\.train\.num_steps=0"),
    ("train.num_steps", 10**400,  # (--config.train.num_steps=1e400: an OverflowError)
     r"config\.train\.num_steps=1000\.\.\. \(401 digits\): expected an integer >= 1"),
    ("train.iters", 1, r"config\.train\.iters=1: expected an integer >= 2"),
    ("data.crop", (32,), r"config\.data\.crop=\(32,\): expected \(height, width\)"),
    ("data.crop", (32, 40), r"config\.data\.crop=\(32, 40\).*multiples of 16"),
    ("optimizer.lr", -1.0, r"config\.optimizer\.lr=-1\.0: expected a number > 0"),
    ("optimizer.schedule", "cosine", r"config\.optimizer\.schedule='cosine'"),
    ("optimizer.frozen", "(", r"config\.optimizer\.frozen='\(': expected a regular expression "
     r"matching the depth prior's parameter paths"),
    ("optimizer.weight_decay", -1e-5, r"config\.optimizer\.weight_decay=-1e-05: expected a "
     r"number >= 0"),
    ("optimizer.b2", 1.0, r"config\.optimizer\.b2=1\.0: expected a number in \[0, 1\)"),
    ("optimizer.clip_norm", -1.0, r"config\.optimizer\.clip_norm=-1\.0: expected a number >= 0"),
    ("loss.gamma", 0.0, r"config\.loss\.gamma=0\.0: expected a number > 0"),
    ("loss.max_disparity", 0.0, r"config\.loss\.max_disparity=0\.0: expected a number > 0"),
    ("eval.iters", 1, r"config\.eval\.iters=1: expected an integer >= 2"),
    ("model.dtype", "float16", r"config\.model\.dtype='float16'; expected 'float32' or"),
    ("model.remat_policy", "bogus", r"config\.model\.remat_policy='bogus'"),
    ("matmul_precision", "tf32", r"config\.matmul_precision='tf32': expected 'default', "),
    ("compile_cache", None, r"config\.compile_cache=None: expected a folder, 'default' or ''"),
    ("data.mixing", "mix", r"config\.data\.mixing='mix': expected 'concat' or 'ratio'"),
    ("data.prefetch", -1, r"config\.data\.prefetch=-1: expected an integer >= 0"),
    ("data.frames", 33, r"config\.data\.frames=33: expected an integer in \[1, 32\] \(the "
     r"depth prior's temporal attention takes at most 32 frames\)"),
    ("data.skip_unreadable", True, r"config\.data\.skip_unreadable=True: expected an integer "
     r">= 0 \(0: an unreadable clip stops the run\)"),
    ("seed", 2**32, r"config\.seed=4294967296: expected an integer in \[0, 2\*\*32\)"),
    ("data.synthetic.num_clips", 0, r"config\.data\.synthetic\.num_clips=0: expected an "),
    ("data.synthetic.max_disparity", -1.0,
     r"config\.data\.synthetic\.max_disparity must be >= min_disparity"),
    ("data.sources.synthetic.weight", 0.0,
     r"config\.data\.sources\.synthetic\.weight=0\.0: expected a number > 0"),
    ("data.sources.synthetic.root", 3, r"config\.data\.sources\.synthetic\.root=3: expected a "
     r"folder"),
    ("data.sources.synthetic.weigth", 1.0, r"config\.data\.sources\.synthetic has the unknown "
     r"field\(s\) weigth; a source has dataset, weight and root"),
    ("optimizer.pct_start", 0.001, r"config\.optimizer\.pct_start=0\.001 with a one-cycle "
     r"length of config\.train\.num_steps \+ 100 = 300 steps: degenerate .* = -0\.7"),
    ("eval.synthetic_seed", synthetic.get_config().data.synthetic.seed,
     r"config\.eval\.synthetic_seed=\d+ equals config\.data\.synthetic\.seed: validation "
     r"would score clips the run trains on"),
    ("train.microbatches", 2, r"config\.train\.microbatches=2: parts of 1 clips .* not "
     r"divisible by the 2 devices"),
    ("eval.split", "valid", r"config\.eval\.split='valid': the synthetic held-out set has only "
     r"the split 'test'"),
])
def test_config_values_a_run_cannot_use_are_named(tmp_path, field, value, match, monkeypatch):
  from train import loop  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  *sections, name = field.split(".")
  node = c
  for section in sections:
    node = node[section]
  node[name] = value
  with pytest.raises(ValueError, match=match):
    loop.validate_config(c, tmp_path / "w", num_devices=2)
  loop.validate_config(synthetic.get_config(), tmp_path / "w", num_devices=2)
  assert not (tmp_path / "w").exists()
  with pytest.raises(ValueError, match="--workdir is empty"):  # an unset $WORKDIR
    loop.validate_config(synthetic.get_config(), "")
  # A checkpoint given as --workdir (meant as init_from): a run trained nested inside it, and
  # the path its last line named loaded the checkpoint's weights, not the run's
  from sav_jax.convert import orbax_io  # pylint: disable=import-outside-toplevel
  for name, items, kind in (("converted", orbax_io._ITEMS, "a `sav-jax convert` checkpoint"),  # pylint: disable=protected-access
                            ("step", ("state",), "a training run's checkpoint step")):
    for item in items:
      (tmp_path / name / item).mkdir(parents=True)
    (tmp_path / name / orbax_io._METADATA_FILE).write_text("{}")  # pylint: disable=protected-access
    with pytest.raises(ValueError, match=rf"--workdir {tmp_path / name} is {kind}, not a run's "
                       rf"folder: to start from its weights, pass --config.init_from="):
      loop.validate_config(synthetic.get_config(), tmp_path / name)
  # A run's checkpoints folder: a new run nested in it, and its last line named that folder,
  # whose weights are the old run's.
  run = tmp_path / "run"
  (run / "checkpoints").mkdir(parents=True)
  (tmp_path / "step").rename(run / "checkpoints" / "2")
  with pytest.raises(ValueError, match=rf"--workdir {run / 'checkpoints'} is a run's checkpoints "
                     rf"folder: to resume that run, pass its folder, --workdir {run}; "):
    loop.validate_config(synthetic.get_config(), run / "checkpoints")
  loop.validate_config(synthetic.get_config(), run)  # the run's own folder resumes
  monkeypatch.chdir(run / "checkpoints")  # "--workdir ." named "." as the run's folder too
  with pytest.raises(ValueError, match=rf"--workdir \. is a run's checkpoints folder: to resume "
                     rf"that run, pass its folder, --workdir {run}; "):
    loop.validate_config(synthetic.get_config(), ".")


@pytest.mark.parametrize("field,accepted,refused", [
    # (the values at each bound the expected text states, and those just beyond it; a float
    # where an integer is expected, a bool where an integer is, and inf and NaN, are refused)
    ("seed", [0, 2**32 - 1], [-1, 0.5]),
    ("data.frames", [1, 32], [0, 2.0]),
    ("data.num_threads", [0], [-1]),
    ("data.prefetch", [0], [-1]),
    ("data.worker_count", [0], [-1]),
    ("data.skip_unreadable", [0, 3], [-1]),
    ("data.synthetic.num_clips", [1], [0]),
    ("data.crop", [(16, 32)], [(0, 32), (32, 0), (32, 16), (32.0, 64.0)]),
    ("train.batch_size", [1], [0, 2.0]),
    ("train.num_steps", [1], [0, True, 6.0]),
    ("train.iters", [2], [True, 2.0]),
    ("train.max_skipped_steps", [0], [-1]),
    ("optimizer.lr", [1e-9], [0.0, float("inf"), float("nan")]),
    ("optimizer.weight_decay", [0.0, 0], [float("inf")]),
    ("optimizer.eps", [1e-12], [0.0]),
    ("optimizer.b1", [0.0, 0.999], [1.0, -0.1]),
    ("optimizer.b2", [0.0], [-0.1]),
    ("optimizer.clip_norm", [0.0], [float("nan")]),
    ("optimizer.pct_start", [0.5], [0.0, 1.0]),
    ("optimizer.div_factor", [1e-3], [0.0]),
    ("optimizer.final_div_factor", [1e-3], [0.0]),
    ("optimizer.schedule_steps", [-1, 0], [None, 5.0]),
    ("optimizer.frozen", ["depthanything"], [re.compile("depthanything")]),
    ("loss.gamma", [1e-3], [float("nan")]),
    ("checkpoint.every_steps", [0, -1], [None, 10.0]),
    ("checkpoint.keep", [0], [-1]),
    ("eval.batch_size", [1], [0]),
    ("eval.num_clips", [1], [0]),
    ("eval.root", [""], [None]),
    ("data.root", ["", "data"], [None]),
])
def test_config_values_at_the_bounds_pass_and_those_beyond_are_named(tmp_path, field, accepted,
                                                                       refused):
  from train import loop  # pylint: disable=g-import-not-at-top
  # (not type-safe: a config file may give any value, which ConfigDict's fields would refuse)
  c = ml_collections.ConfigDict(synthetic.get_config().to_dict(), type_safe=False)
  c.eval.batch_size = 1
  *sections, name = field.split(".")
  node = functools.reduce(lambda n, k: n[k], sections, c)
  for value in accepted:
    node[name] = value
    loop.validate_config(c, tmp_path / "w")
  for value in refused:
    node[name] = value
    with pytest.raises(ValueError, match=rf"^config\.{re.escape(field)}={re.escape(repr(value))}: "
                       "expected "):
      loop.validate_config(c, tmp_path / "w")


def test_an_empty_workdir_is_refused_by_setup(tmp_path, monkeypatch):
  # setup made Path("") of it first, which is ".": the run trained in the current folder.
  from train import loop  # pylint: disable=g-import-not-at-top
  monkeypatch.chdir(tmp_path)
  with pytest.raises(ValueError, match="--workdir is empty"):
    loop.setup(synthetic.get_config(), "")
  with pytest.raises(ValueError, match="--workdir is empty"):
    loop.run(synthetic.get_config(), "")
  assert not any(tmp_path.iterdir())


def test_one_run_at_a_time_in_a_workdir(tmp_path):
  # A second run in the same workdir deleted the first one's save in progress, replaced its
  # log and crashed it with an orbax traceback.
  from train import loop  # pylint: disable=g-import-not-at-top
  workdir = tmp_path / "w"
  first = loop.lock_workdir(workdir)
  assert (workdir / loop.LOCK).read_text().endswith(f" {os.getpid()}")
  with pytest.raises(FileExistsError, match=rf"--workdir {workdir} is in use by another "
                     rf"training run \(\S+ {os.getpid()}\): wait for it to end"):
    loop.lock_workdir(workdir)
  first.release()
  assert not (workdir / loop.LOCK).exists()
  loop.lock_workdir(workdir).release()  # free again
  (workdir / loop.LOCK).write_text("host 1")  # a killed run's file, held by no process
  loop.lock_workdir(workdir).release()
  assert not any(workdir.iterdir())


def test_config_blocks_a_run_cannot_use_are_named(tmp_path, caplog):
  """The augmentation (for real data only: it runs per clip inside the grain reader, where
  its error would come after the workdir is created), the sources, and a config file
  written without the base fields."""
  import ml_collections  # pylint: disable=g-import-not-at-top
  from configs import mixed, sceneflow  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  for module in (sceneflow, synthetic, mixed):
    assert loop.missing_fields(module.get_config(), sceneflow.base_config()) == []
  c = sceneflow.get_config()
  c.data.augment.scale_range = (1.0, 0.0)
  with pytest.raises(ValueError, match=r"config\.data\.augment\.scale_range must be \(min, "):
    loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.augment.scale_range = (1.0, 0.0)  # checked though the generator's clips skip it
  with pytest.raises(ValueError, match=r"config\.data\.augment\.scale_range must be \(min, "):
    loop.validate_config(c, tmp_path / "w")
  c.data.augment.scale_range, c.data.augment.eraser_prob = (0.0, 0.1), 1.0
  with caplog.at_level(logging.WARNING):  # it was silently without effect
    loop.validate_config(c, tmp_path / "w")
  assert ("config.data.augment.scale_range, config.data.augment.eraser_prob changed, but no "
          "training source is augmented") in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    loop.validate_config(synthetic.get_config(), tmp_path / "w")
  assert "no training source is augmented" not in caplog.text
  c = synthetic.get_config()
  c.data.sources.extra = ml_collections.ConfigDict(dict(weight=1.0))  # no dataset: a traceback
  with pytest.raises(ValueError, match=r"config\.data\.sources\.extra\.dataset=None: expected "
                     "'synthetic' or a dataset name"):
    loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.synthetic.max_disparty = 4.0  # a typo in a config file trained with the default
  with pytest.raises(ValueError, match=r"config\.data\.synthetic\.max_disparty is not a field of "
                     r"the synthetic generator; its fields: .*max_disparity.*num_clips"):
    loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.crop = (32, 16)  # the model refuses width 16 (no official reference)
  with pytest.raises(ValueError, match=r"config\.data\.crop=\(32, 16\): expected .* the width "
                     "at least 32"):
    loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.sources = ml_collections.ConfigDict(
      {"mine": dict(dataset="folder", weight=1.0, root=str(tmp_path / "data"))})
  c.data.augment.crop_size = (48, 96)  # AugmentConfig's: each clip was refused when read
  with pytest.raises(ValueError, match=r"config\.data\.augment\.crop_size=\(48, 96\): the "
                     r"crop is config\.data\.crop's \(\(32, 64\)\); leave it out"):
    loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.synthetic.max_disparity = -4.0  # named by the config field, not the dataclass's
  with pytest.raises(ValueError, match=r"config\.data\.synthetic\.max_disparity "):
    loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.synthetic.height = 64
  with pytest.raises(ValueError, match=r"config\.data\.synthetic\.height: the clips' height is "
                     r"config\.data\.crop's"):
    loop.validate_config(c, tmp_path / "w")
  c.data.sources = ml_collections.ConfigDict()
  with pytest.raises(ValueError, match=r"config\.data\.sources is empty"):
    loop.validate_config(c, tmp_path / "w")
  c = ml_collections.ConfigDict(dict(seed=0, model=dict(dtype="float32")))
  with pytest.raises(ValueError, match=r"the config lacks \d+ fields \(checkpoint, compile_cache"
                     r".*model\.frame_block_mb.*base_config\(\)"):
    loop.check_fields(c)
  from configs.eval import folder  # pylint: disable=g-import-not-at-top
  with pytest.raises(ValueError, match=r"the config lacks 12 fields \(.*\); it is an evaluation "
                     r"config \(python -m eval\): build"):
    loop.check_fields(folder.get_config())
  c = synthetic.get_config()
  c.eval.roots, c.train.num_step = "my_videos", 3  # misspelt in a config file: never read
  with pytest.raises(ValueError, match=r"the config has no such field eval\.roots, "
                     r"train\.num_step \(misspelt"):
    loop.check_fields(c)
  c = synthetic.get_config()
  c.model.depth_dim = 16  # a SAVConfig field the base leaves out: the model's own check
  loop.check_fields(c)
  assert not (tmp_path / "w").exists()


def test_check_fields_leaves_blocks_with_their_own_checks_to_them():
  # The generator's fields the base leaves out (its clip shape: config.data's, refused by its
  # own check naming config.data.crop) and a block replaced by a value (config.data.augment's
  # check names it) are not "no such field" here, nor a TypeError from looking into None.
  from train import loop  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  c.data.synthetic.height = 64
  c.data.augment = None
  loop.check_fields(c)
  c = synthetic.get_config()  # eight unknown fields are all named: no "..."
  for i in range(8):
    c.train[f"x{i}"] = i
  with pytest.raises(ValueError, match=r"no such field train\.x0, .*train\.x7 \(misspelt"):
    loop.check_fields(c)
  c.train.x8 = 8
  with pytest.raises(ValueError, match=r"no such field train\.x0, .*train\.x7, \.\.\. \("):
    loop.check_fields(c)

def test_checks_of_what_a_run_does_not_use_are_left_out(tmp_path, caplog):
  """The generator's block, its seed against validation's and the validation split are
  checked where a source or the validation generates clips; augmentation changes are said to
  be without effect where no source is augmented only."""
  from configs import sceneflow  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  c.eval.every_steps = 0  # no validation: its seed, split and fields are not used
  c.eval.synthetic_seed, c.eval.split, c.eval.iters = c.data.synthetic.seed, "valid", 1
  c.eval.batch_size = 3
  loop.validate_config(c, tmp_path / "w", num_devices=2)
  c.data.synthetic.max_disparity = -4.0  # but the training source's generator is
  with pytest.raises(ValueError, match=r"^config\.data\.synthetic\.max_disparity "):
    loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.sources = ml_collections.ConfigDict({"sf": dict(dataset="sceneflow", weight=1.0)})
  c.eval.synthetic_seed = c.data.synthetic.seed  # no training clip is generated: no overlap
  c.data.augment.eraser_prob = 1.0
  with caplog.at_level(logging.WARNING):
    loop.validate_config(c, tmp_path / "w")
  assert "no training source is augmented" not in caplog.text
  c.eval.every_steps, c.data.synthetic.max_disparity = 0, -4.0  # no clip is generated
  loop.validate_config(c, tmp_path / "w")
  c = synthetic.get_config()
  c.data.sources.extra = "sceneflow"  # not a block: named (it was an AttributeError)
  with pytest.raises(ValueError, match=r"^config\.data\.sources\.extra\.weight=None: "):
    loop.validate_config(c, tmp_path / "w")
  del c.data.sources["extra"]
  c.data.sources.other = ml_collections.ConfigDict(dict(dataset="sceneflow", weight=1.0, root=3))
  with pytest.raises(ValueError, match=r"^config\.data\.sources\.other\.root=3: "):  # (TypeError)
    loop.validate_config(c, tmp_path / "w")
  del c.data.sources["other"]
  c.data.sources.other = ml_collections.ConfigDict(dict(dataset="synthetic", weight=2))
  loop.validate_config(c, tmp_path / "w")  # an integer weight
  c.data.sources.other.weight = True
  with pytest.raises(ValueError, match=r"^config\.data\.sources\.other\.weight=True: "):
    loop.validate_config(c, tmp_path / "w")  # (a bool is no weight)
  del c.data.sources["other"]
  del c.data.synthetic["seed"]
  assert loop.missing_fields(c, sceneflow.base_config()) == ["data.synthetic.seed"]


def test_run_traces_under_the_configured_matmul_precision(monkeypatch):
  from train import loop  # pylint: disable=g-import-not-at-top
  seen = []
  monkeypatch.setattr(loop, "_run", lambda *a: seen.append(jax.config.jax_default_matmul_precision))
  c = synthetic.get_config()
  c.matmul_precision = "highest"
  loop.run(c, "unused", parts={})
  assert seen == ["highest"] and jax.config.jax_default_matmul_precision is None


def test_compile_cache_setting(tmp_path, restore_cache_config, monkeypatch, caplog):
  """"default" keeps the folder the user gave JAX (here: the test session's), else takes
  sav-jax's default folder; a folder is created and used; "" turns any cache off; a folder that
  cannot be one is named (the default folder falls back to no cache, with a warning)."""
  from train import loop  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  session = jax.config.jax_compilation_cache_dir
  assert session and c.compile_cache == "default"
  assert loop.setup_compile_cache(c) == pathlib.Path(session)
  c.compile_cache = ""  # off: the folder JAX was given (the variable's) is not used either
  assert loop.setup_compile_cache(c) is None
  assert not jax.config.jax_compilation_cache_dir
  c.compile_cache = str(tmp_path / "xla")
  assert loop.setup_compile_cache(c) == tmp_path / "xla" and (tmp_path / "xla").is_dir()
  assert jax.config.jax_compilation_cache_dir == str(tmp_path / "xla")
  (tmp_path / "notes.txt").write_text("keep me")
  c.compile_cache = str(tmp_path / "notes.txt")
  with pytest.raises(ValueError, match=r"config\.compile_cache='.*notes\.txt': compilation "
                     "cache .* exists and is not a folder"):
    loop.setup_compile_cache(c)
  assert (tmp_path / "notes.txt").read_text() == "keep me"
  jax.config.update("jax_compilation_cache_dir", None)  # no folder given to JAX
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home_cache"))
  c.compile_cache = "default"
  assert loop.setup_compile_cache(c) == tmp_path / "home_cache" / "sav-jax" / "xla"
  jax.config.update("jax_compilation_cache_dir", None)
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "notes.txt"))  # cannot hold a folder
  with caplog.at_level("WARNING", logger="train.loop"):
    assert loop.setup_compile_cache(c) is None
  assert "no compilation cache: cannot create the compilation cache folder" in caplog.text


def test_a_workdir_that_is_a_file_is_refused(tmp_path):
  from train import loop  # pylint: disable=g-import-not-at-top
  (tmp_path / "notes.txt").write_text("keep me")
  for workdir in (tmp_path / "notes.txt", tmp_path / "notes.txt" / "run"):
    with pytest.raises(NotADirectoryError, match=f"{tmp_path / 'notes.txt'} exists and is not"):
      loop.validate_config(synthetic.get_config(), workdir)
  assert (tmp_path / "notes.txt").read_text() == "keep me"
  (tmp_path / "run").mkdir()
  (tmp_path / "run" / "checkpoints").write_text("keep me")  # where the run saves
  with pytest.raises(NotADirectoryError, match=f"{tmp_path / 'run' / 'checkpoints'} exists and "
                     "is not"):
    loop.validate_config(synthetic.get_config(), tmp_path / "run")


def test_train_command_reports_bad_input_in_one_line_before_creating_the_workdir(tmp_path):
  """A config value, no depth-prior weights or an unknown validation dataset (before any
  tracing), unreadable init weights (after tracing the model's shapes, before the workdir is
  created), an override of a field that does not exist or of the wrong type, and a config
  file that is missing or does not parse (while absl parses the flags)."""
  import subprocess  # pylint: disable=g-import-not-at-top
  from sav_jax.convert import save_variables  # pylint: disable=g-import-not-at-top
  from tests.train.conftest import ROOT, child_env  # pylint: disable=g-import-not-at-top
  weights = tmp_path / "weights"
  save_variables(weights, {"params": {"w": np.random.default_rng(0).normal(size=4000)}}, {})
  for chunk in weights.glob("variables/ocdbt.process_*/d/*"):
    chunk.write_bytes(chunk.read_bytes()[:10])
  config = str(ROOT / "configs/synthetic.py")
  broken = tmp_path / "broken.py"
  broken.write_text("def get_config(:\n")
  (tmp_path / "raises.py").write_text("raise RuntimeError('boom')\n")
  (tmp_path / "no_get.py").write_text("x = 1\n")
  (tmp_path / "returns_5.py").write_text("def get_config():\n  return 5\n")
  (tmp_path / "frame.png").write_bytes(b"\x89PNG\x00\x00")
  for flags, message in [
      ([str(tmp_path / "raises.py")], f"the config file {tmp_path / 'raises.py'} cannot be used: "
       "loading it raised RuntimeError: boom"),
      ([str(tmp_path / "no_get.py")], f"the config file {tmp_path / 'no_get.py'} cannot be "
       "used: loading it raised AttributeError: "),
      # (an override is given, so ml_collections meets the int first; it was reported as
      # "no such config field Attribute <class 'int'>.train")
      ([str(tmp_path / "returns_5.py")], f"the config file {tmp_path / 'returns_5.py'} cannot "
       "be used: its get_config() returned int, not a ConfigDict"),
      ([str(tmp_path / "returns_5.py"), "--config.train.steps=3"], "the config file "
       f"{tmp_path / 'returns_5.py'} cannot be used: its get_config() returned int, not a "
       "ConfigDict"),
      ([config, "--config.train.iters.deeper=1"], "no such config field train.iters.deeper: "
       "config.train.iters is int, not a config block (overrides: --config.train.iters.deeper"),
      ([str(tmp_path / "frame.png")], f"the config file {tmp_path / 'frame.png'} does not "
       "parse: source code string cannot contain null bytes"),
      ([config, "--config.train.iters=1"], "config.train.iters=1: expected an integer >= 2"),
      # the model's compute fields are the config's (vit_attention was "no such config field")
      ([config, "--config.model.vit_attention=flash"], "config.model.vit_attention='flash'; "
       "expected one of ('auto', 'blocked', 'cudnn')"),
      # a repeated override: the last wins (a tuple's values were joined: (32, 32, 48, 56))
      ([config, "--config.data.crop=(32, 32)", "--config.data.crop", "(48, 56)"],
       "config.data.crop=(48, 56): expected (height, width): two positive multiples of 16"),
      ([config, f"--config.init_from={weights}"], f"config.init_from: {weights}: the "
       "checkpoint is corrupt or incomplete"),
      ([config, "--config.train.batchsize=1"], "no such config field 'batchsize'; Did you mean "
       '"batch_size" instead of "batchsize"? (overrides: --config.train.batchsize, '),
      ([config, "--config.data.sources.vkitti2.weight=1"], "no such config field 'vkitti2' "
       "(overrides: --config.data.sources.vkitti2.weight, --config.train.progress_bar); the "
       "fields are those of the --config file's get_config(); training sources are added or "
       "removed in a config file of your own (see configs/mixed.py)"),
      # an evaluation config given by mistake, with an override into a block it lacks (as
      # every command here has): it was "no such config field 'train'", a misspelt override
      ([str(ROOT / "configs/eval/folder.py")],
       f"the config file {ROOT / 'configs/eval/folder.py'} lacks 12 of a training config's "
       "fields (checkpoint, compile_cache, data, eval, init_from, loss, model, optimizer, ...); "
       "it is an evaluation config (python -m eval): build its get_config() on "
       "configs.sceneflow.base_config()"),
      ([str(tmp_path / "nope.py")], "cannot load the --config file: "
       f"[Errno 2] No such file or directory: '{tmp_path / 'nope.py'}'"),
      ([str(broken)], f"the config file {broken} does not parse: line 1: "),
      ([str(ROOT / "configs/sceneflow.py")], "config.vda_weights and config.init_from are "
       "both empty: the frozen depth prior would stay random"),
      ([config, "--config.train.batch_size=abc"], "flag --config.train.batch_size=abc: "
       "invalid literal for int()"),
      # a whole number in scientific notation is an integer (int() refused "2e2"); the
      # message shows it read as 200
      ([config, "--config.train.num_steps", "2e2", "--config.optimizer.pct_start=0.001",
        "--config.optimizer.lr=1e-4"], "config.optimizer.pct_start=0.001 with a one-cycle "
       "length of config.train.num_steps + 100 = 300 steps"),
      ([config, "--config.eval.every_steps=1", "--config.eval.dataset=foo"],
       "config.eval.dataset='foo', config.eval.split='test', config.data.root='data/datasets', "
       "config.data.crop=(32, 64): unknown dataset 'foo'; known datasets: sceneflow"),
      ([config, "--coordinator_address=localhost:1", "--num_processes=2", "--process_id=5"],
       "--coordinator_address needs --num_processes >= 1 and 0 <= --process_id < "
       "--num_processes, got --num_processes=2 --process_id=5"),
      ([config, "--num_processes=-3"], "--num_processes and --process_id need "
       "--coordinator_address"),
      ([config, "--distributed=auto"], "--distributed=auto found no cluster to join (a TPU pod, "
       "a SLURM job, ...): "),  # (JAX's traceback; its reason follows)
      ([config, "--config.eval.every_steps=1", "--config.eval.synthetic_seed=-1"],
       "config.eval.dataset='synthetic' (config.eval.synthetic_seed=-1, config.data.synthetic): "
       "SyntheticConfig.seed must be")]:
    proc = subprocess.run(
        [sys.executable, "-m", "train", "--config", *flags, "--workdir", str(tmp_path / "w"),
         "--config.train.progress_bar=False"],
        cwd=ROOT, env=child_env(tmp_path / "cache"), capture_output=True, text=True,
        timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert f"train: error: {message}" in proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr
    assert not (tmp_path / "w").exists()
  # a workdir that cannot be created (sysfs refuses even root): a traceback before
  proc = subprocess.run(
      [sys.executable, "-m", "train", "--config", config, "--workdir", "/sys/sav_jax_test/w",
       "--config.train.progress_bar=False"], cwd=ROOT, env=child_env(tmp_path / "cache"),
      capture_output=True, text=True, timeout=300, check=False)
  assert proc.returncode == 2 and "train: error: " in proc.stderr, proc.stderr[-2000:]
  assert "/sys/sav_jax_test" in proc.stderr and "Traceback" not in proc.stderr
  # -v 1: the traceback too, and the same exit status
  proc = subprocess.run(
      [sys.executable, "-m", "train", "--config", config, "--workdir", "/sys/sav_jax_test/w",
       "--config.train.progress_bar=False", "-v", "1"], cwd=ROOT,
      env=child_env(tmp_path / "cache"), capture_output=True, text=True, timeout=300, check=False)
  assert proc.returncode == 2 and "Traceback" in proc.stderr, proc.stderr[-2000:]
  assert proc.stderr.rstrip().splitlines()[-1].startswith("train: error: "), proc.stderr[-2000:]
  proc = subprocess.run([sys.executable, "-m", "train", "--help"], cwd=ROOT,
                        env=child_env(tmp_path / "cache"), capture_output=True, text=True,
                        timeout=300, check=False)
  assert proc.returncode == 0 and "--workdir: Run directory" in proc.stdout  # absl's status: 1
  # From another folder (an installed package's user), --config configs/... names the
  # package's file: the override is checked against it (was "No such file or directory")
  proc = subprocess.run(
      [sys.executable, "-m", "train", "--config=configs/synthetic.py", "--workdir",
       str(tmp_path / "w"), "--config.train.batch_size=abc"], cwd=tmp_path,
      env=child_env(tmp_path / "cache"), capture_output=True, text=True, timeout=300,
      check=False)
  assert proc.returncode == 2, proc.stderr[-2000:]
  assert "train: error: flag --config.train.batch_size=abc: invalid literal" in proc.stderr


def test_train_command_interrupted_while_reading_its_flags_is_one_line(tmp_path):
  # Ctrl-C in the first half second (the flags, the config file) gave a traceback
  import subprocess  # pylint: disable=g-import-not-at-top
  from tests.train.conftest import ROOT  # pylint: disable=g-import-not-at-top
  code = ("import runpy\nfrom absl import app\n"
          "def run(*args, **kwargs):\n  raise KeyboardInterrupt\n"
          "app.run = run\nrunpy.run_module('train', run_name='__main__', alter_sys=True)\n")
  proc = subprocess.run([sys.executable, "-c", code, "--config", "x", "--workdir", "w"],
                        cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)},
                        capture_output=True, text=True, timeout=120, check=False)
  assert (proc.returncode, proc.stderr) == (130, "train: interrupted (Ctrl-C)\n"), proc.stderr


def test_a_workdir_that_is_a_link_to_a_missing_folder_is_named(tmp_path):
  # the run failed with "[Errno 17] File exists: 'w'"
  from train import loop  # pylint: disable=g-import-not-at-top
  (tmp_path / "w").symlink_to(tmp_path / "gone" / "w")
  for workdir in (tmp_path / "w", tmp_path / "w" / "run"):
    with pytest.raises(ValueError, match=rf"^--workdir {workdir}: {tmp_path / 'w'} is a "
                                         "symbolic link to a missing folder"):
      loop.validate_config(synthetic.get_config(), workdir)


def test_train_command_stops_on_a_ctrl_c_python_dropped_before_the_run(tmp_path):
  # Ctrl-C ~1 s after the start landed in JAX's GC callback while JAX was being imported:
  # dropped before the training loop remembered interrupts, the run went on and exited 0
  import subprocess  # pylint: disable=g-import-not-at-top
  from tests.train.conftest import ROOT  # pylint: disable=g-import-not-at-top
  code = ("import runpy, signal\nfrom train import loop\n"
          "def setup(config, workdir):\n"
          "  try:  # what Python does with a KeyboardInterrupt raised in a GC callback\n"
          "    signal.getsignal(signal.SIGINT)(signal.SIGINT, None)\n"
          "  except KeyboardInterrupt:\n    pass\n"
          "loop.setup = setup\nloop.run = lambda *args: print('RAN')\n"
          "runpy.run_module('train', run_name='__main__', alter_sys=True)\n")
  proc = subprocess.run([sys.executable, "-c", code, "--config",
                         str(ROOT / "configs" / "synthetic.py"), "--workdir", "w"],
                        cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)},
                        capture_output=True, text=True, timeout=120, check=False)
  assert proc.returncode == 130 and "RAN" not in proc.stdout, proc.stderr[-2000:]
  assert proc.stderr.endswith("train: interrupted (Ctrl-C); no checkpoint was saved: the same "
                              "command starts the run anew\n"), proc.stderr[-2000:]


@pytest.mark.parametrize("argv, want", [
    # the last of a repeated override wins, in either spelling
    (["train", "--config.data.crop=(32, 32)", "--config.data.crop", "(48, 64)", "--workdir", "w"],
     ["train", "--config.data.crop", "(48, 64)", "--workdir", "w"]),
    (["--config.a=1", "--config.b=2", "--config.a=3"], ["--config.b=2", "--config.a=3"]),
    (["--config.a", "-1", "--config.a", "2"], ["--config.a", "2"]),  # a negative value
    # after `--` nothing is an override; a field without a value, or before a flag, is kept
    (["--config.a=1", "--", "--config.a=2"], ["--config.a=1", "--", "--config.a=2"]),
    (["--config.a", "--config.b=1", "--config.a"], ["--config.a", "--config.b=1", "--config.a"]),
])
def test_train_command_keeps_the_last_of_each_config_override(argv, want):
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top
  assert train_main.last_overrides(argv) == want


@pytest.mark.parametrize("value, want", [
    ("1e5", "100000"), ("1.2e5", "120000"), ("1E+3", "1000"), ("-2e2", "-200"),
    ("1.e3", "1000"), ("2.5e1", "25"), ("1e100", "1" + "0" * 100),
    # not a whole number, or not a number in scientific notation: kept
    ("1e-4", "1e-4"), ("1.25e1", "1.25e1"), ("1e1000", "1e1000"), ("1e3x", "1e3x"),
    ("100", "100"), ("abc", "abc")])
def test_train_command_reads_whole_numbers_in_scientific_notation(value, want):
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top
  assert train_main.integral_numbers(["train", f"--config.train.num_steps={value}"]) == [
      "train", f"--config.train.num_steps={want}"]
  assert train_main.integral_numbers(["--config.train.num_steps", value, "--workdir", "1e3"]) == [
      "--config.train.num_steps", want, "--workdir", "1e3"]
  # only an override's own value: not an argument after `--config.a=1` or another flag
  assert train_main.integral_numbers(["--config.a=1", value]) == ["--config.a=1", value]


@pytest.mark.parametrize("argv, want", [
    (["train", "--config", "a.py", "--config=b.py"], "a.py"),
    (["train", "-config", "a.py"], "a.py"),
    (["train", "--config=runs/a=1/c.py:x", "--config", "b.py"], "runs/a=1/c.py:x"),
    (["train", "-config=c.py"], "c.py"),
    (["train", "--config.train.iters=3", "--config"], "(--config)"), ([], "(--config)")])
def test_train_command_names_the_config_file_in_its_messages(argv, want):
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top
  assert train_main._config_arg(argv) == want  # pylint: disable=protected-access


@pytest.mark.parametrize("argv, status, says", [
    # absl's help flags exit with status 1: the command's is 0, as for any help
    (["--help"], 0, ""), (["--helpfull"], 0, ""),
    # a flag error names the flag and where the flags are listed
    (["--config", "configs/synthetic.py", "--workdir", "w", "--num_processes=x"], 2,
     "train: error: flag --num_processes=x: "),
    # a file argument after `:` (configs/eval/synthetic.py:x): the file named is the file
    (["--config={tmp}/broken.py:x", "--workdir", "w"], 2,
     "train: error: the config file {tmp}/broken.py does not parse: line 1: "),
    # the config file's own KeyError, one without a key too: not "no such config field"
    (["--config", "{tmp}/bare_key_error.py", "--workdir", "w"], 2,
     "train: error: the config file {tmp}/bare_key_error.py cannot be used: loading it raised "
     "KeyError: "),
    # without an override, ml_collections leaves a missing file to the config's first use
    (["--config", "{tmp}/nope.py", "--workdir", "w"], 2, "train: error: cannot load the "
     "--config file: [Errno 2] No such file or directory: '{tmp}/nope.py'"),
    # and a get_config() that returns no config or one whose keys() raises (with an override,
    # met while parsing)
    (["--config", "{tmp}/returns_5.py", "--workdir", "w"], 2, "train: error: the config file "
     "{tmp}/returns_5.py cannot be used: its get_config() returned int, not a ConfigDict\n"),
    (["--config", "{tmp}/bad_keys.py", "--workdir", "w"], 2, "train: error: the config file "
     "{tmp}/bad_keys.py cannot be used: loading it raised RuntimeError: boom"),
    # a true/false field's value after a space: absl read the field alone (true) and left the
    # value to main, which dropped it
    (["--config", "configs/synthetic.py", "--workdir", "w", "--config.random_depth_prior",
      "false"], 2, "train: error: unexpected argument 'false'; a true/false field takes its "
     "value after '=': --config.random_depth_prior=false"),
])
def test_train_command_flag_errors_and_help_in_process(tmp_path, capsys, monkeypatch, argv,
                                                       status, says):
  """`parse_flags` and `load_config` as `python -m train` runs them (absl's app defines the
  help flags)."""
  from absl import app, flags  # pylint: disable=g-import-not-at-top
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top
  (tmp_path / "broken.py").write_text("def get_config(:\n")
  (tmp_path / "bare_key_error.py").write_text("def get_config():\n  raise KeyError\n")
  (tmp_path / "returns_5.py").write_text("def get_config():\n  return 5\n")
  (tmp_path / "bad_keys.py").write_text("class C:\n  def keys(self):\n    raise RuntimeError("
                                      "'boom')\n\n\ndef get_config():\n  return C()\n")
  app.define_help_flags()
  monkeypatch.setattr(sys, "argv", ["train", *(a.format(tmp=tmp_path) for a in argv)])
  try:
    with pytest.raises(SystemExit) as info:
      train_main.parse_flags(sys.argv)
      train_main.load_config()
  finally:
    flags.FLAGS.unparse_flags()
  err = capsys.readouterr().err
  assert info.value.code == status, err
  assert err.startswith(says.format(tmp=tmp_path)) and err.count("\n") == (status != 0), err
  if argv[-1].startswith("--num_processes"):
    assert err.endswith(" (--helpfull lists the flags)\n")


def test_train_command_names_the_training_fields_a_config_lacks(tmp_path, capsys):
  """`_not_a_training_config`: a config without one of `sceneflow.base_config()`'s fields is
  named with it; a training config, or a file that cannot be loaded, is left to the caller."""
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top
  (tmp_path / "no_train.py").write_text("from configs import sceneflow\n\n\ndef get_config():\n"
                                       "  c = sceneflow.base_config()\n  del c['train']\n"
                                       "  return c\n")
  (tmp_path / "raises.py").write_text("def get_config():\n  return {}['x']\n")
  for kept in (synthetic.__file__, str(tmp_path / "raises.py")):
    assert train_main._not_a_training_config(["train", "--config", kept]) is None  # pylint: disable=protected-access
  with pytest.raises(SystemExit) as info:
    train_main._not_a_training_config(["train", "--config", str(tmp_path / "no_train.py")])  # pylint: disable=protected-access
  assert info.value.code == 2
  assert capsys.readouterr().err.startswith(
      f"train: error: the config file {tmp_path / 'no_train.py'} lacks 1 of a training config's "
      "fields (train): build its get_config() on configs.sceneflow.base_config()")


def test_train_command_finds_the_packages_config_files_from_any_folder(monkeypatch, tmp_path,
                                                                       capsys):
  import configs  # pylint: disable=g-import-not-at-top
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top
  package = pathlib.Path(configs.__file__).parent
  monkeypatch.chdir(tmp_path)  # a folder without configs/
  (tmp_path / "mine.py").write_text("")
  argv = ["train", "--config", "configs/synthetic.py", "-config", "configs/mixed.py",
          "-config=configs/eval/folder.py:x", "--config", "mine.py", "--config=configs/nope.py",
          "--config.data.crop=(32, 64)", "--config"]
  assert train_main.located_config(argv) == [
      "train", "--config", str(package / "synthetic.py"), "-config", str(package / "mixed.py"),
      f"-config={package / 'eval' / 'folder.py'}:x", "--config", "mine.py",
      "--config=configs/nope.py", "--config.data.crop=(32, 64)", "--config"]
  # a `configs` of the folder's own, first on the module path: one line
  monkeypatch.setitem(sys.modules, "configs", types.ModuleType("configs"))
  with pytest.raises(SystemExit) as info:
    train_main.located_config(["train", "--config", "configs/synthetic.py"])
  assert info.value.code == 2
  assert capsys.readouterr().err.startswith(
      "train: error: `configs` is another package, not sav-jax's configs package: ")


def test_train_command_reports_where_a_run_resumes_and_an_unloadable_config(
    toy_run, tmp_path, monkeypatch, capsys):
  from sav_jax.convert import orbax_io  # pylint: disable=g-import-not-at-top
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top

  def resume_point(workdir):
    monkeypatch.setattr(train_main, "_WORKDIR", types.SimpleNamespace(value=str(workdir)))
    return train_main._resume_point()  # pylint: disable=protected-access

  assert resume_point(toy_run[0]) == (f"the last checkpoint is {toy_run[0] / 'checkpoints' / '1'}"
                                      ": the same command resumes from it")
  anew = "no checkpoint was saved: the same command starts the run anew"
  assert resume_point(tmp_path / "new") == anew

  def unreadable(path):
    raise PermissionError(13, "Permission denied", str(path))

  monkeypatch.setattr(orbax_io, "find_training_checkpoint", unreadable)
  assert resume_point(toy_run[0]) == anew
  # ml_collections' report of a --config file it cannot load: its last line names the file
  for report in ("Could not load:\n\n  b.py: not found  \n",
                 "Could not load:\n  b.py: not found\n  \n"):  # (a blank last line)
    with pytest.raises(SystemExit) as info:
      train_main._config_file_error(OSError(report))  # pylint: disable=protected-access
    assert info.value.code == 2
    assert capsys.readouterr().err == ("train: error: cannot load the --config file: b.py: not "
                                       "found\n")


def _train_main_with_flags(monkeypatch, coordinator=None, num_processes=None, process_id=None,
                           distributed="off", **more):
  """`train.__main__` with its config loading stubbed and its flags' values set as given
  (`more`: other flags by their module names, `_WORKDIR=...`); absl does not parse them."""
  from train import __main__ as train_main  # pylint: disable=g-import-not-at-top
  monkeypatch.setattr(train_main, "load_config", lambda: None)
  for name, value in (("_COORD", coordinator), ("_NUM_PROC", num_processes),
                      ("_PROC_ID", process_id), ("_DISTRIBUTED", distributed), *more.items()):
    monkeypatch.setattr(train_main, name, types.SimpleNamespace(value=value))
  return train_main


@pytest.mark.parametrize("coordinator, n, i, says", [
    ("h:1", 1, 0, None), ("h:1", 3, 2, None),  # valid: joins the coordinator
    ("h:1", 2, 2, "got --num_processes=2 --process_id=2"),
    ("h:1", 0, 0, "got --num_processes=0 --process_id=0"),
    ("h:1", 2, -1, "got --num_processes=2 --process_id=-1"),
    ("h:1", None, 0, "got --num_processes=None --process_id=0"),
    ("h:1", 2, None, "got --num_processes=2 --process_id=None"),
    (None, None, 4, "need --coordinator_address"), (None, 2, None, "need --coordinator_address"),
    ("h", 2, 1, "--coordinator_address='h': expected host:port"),  # (JAX: an IndexError)
    ("h:", 2, 1, "expected host:port"), (":1", 2, 1, "expected host:port")])
def test_train_command_checks_its_multi_process_flags(monkeypatch, capsys, coordinator, n, i,
                                                      says):
  class Joined(Exception):
    pass

  def initialize(*args):
    raise Joined(args)

  monkeypatch.setattr(jax.distributed, "initialize", initialize)
  train_main = _train_main_with_flags(monkeypatch, coordinator, n, i)
  with pytest.raises(SystemExit if says else Joined) as info:
    train_main.main(["train"])
  if says is None:
    assert info.value.args == (("h:1", n, i),)
  else:
    assert info.value.code == 2 and says in capsys.readouterr().err


@pytest.mark.parametrize("error", [ValueError, RuntimeError])
def test_train_command_says_distributed_auto_found_no_cluster(monkeypatch, capsys, error):
  """JAX's `initialize()` without a cluster raises either (a traceback, status 1, before)."""
  def initialize():
    raise error("no cluster")

  monkeypatch.setattr(jax.distributed, "initialize", initialize)
  train_main = _train_main_with_flags(monkeypatch, distributed="auto")
  with pytest.raises(SystemExit) as info:
    train_main.main(["train"])
  assert info.value.code == 2
  assert capsys.readouterr().err.startswith("train: error: --distributed=auto found no cluster "
                                            "to join (a TPU pod, a SLURM job, ...): no cluster; ")


# XLA's error (its buffer tables cut short) and train's one line about it, status 1.
_DEVICE_OUT_OF_MEMORY = (
    lambda loop: jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to "
                                            "allocate 30.5GiB.\nBufferAssignment OOM Debugging."),
    1, "out of memory on the device: RESOURCE_EXHAUSTED: Out of memory while trying to allocate "
    "30.5GiB.; use --config.train.microbatches=K (the same batch as K parts), "
    "--config.model.remat=true, --config.model.dtype=bfloat16, a smaller "
    "--config.train.batch_size or --config.data.crop, or fewer --config.train.iters; no "
    "checkpoint was saved: the same command starts the run anew")


@pytest.mark.parametrize("where, error, status, says", [
    # bad input found by the setup: status 2, one line (-v 1 for the traceback)
    ("setup", lambda loop: ValueError("config.x: bad"), 2,
     "config.x: bad (-v 1 for the traceback)"),
    ("setup", lambda loop: PermissionError(13, "Permission denied", "w"), 2,
     "[Errno 13] Permission denied: 'w' (-v 1 for the traceback)"),
    # a batch the pipeline cannot make: one line, status 2 as bad input
    ("run", lambda loop: loop.DataError("the training batch of step 7 could not be made: x"), 2,
     "the training batch of step 7 could not be made: x"),
    # too many skipped updates: status 1, one line naming where the same command resumes
    ("run", lambda loop: loop.Diverged("step 8: 6 updates skipped"), 1, "step 8: 6 updates "
     "skipped; no checkpoint was saved: the same command starts the run anew"),
    # the device out of memory, placing the initial state or running a step: status 1
    ("setup", *_DEVICE_OUT_OF_MEMORY), ("run", *_DEVICE_OUT_OF_MEMORY)])
@pytest.mark.parametrize("verbosity", [0, 1])
def test_train_command_ends_a_failed_run_with_one_line_and_its_status(
    monkeypatch, capsys, tmp_path, where, error, status, says, verbosity):
  """README: bad input exits with status 2, a training batch that cannot be made too, a run
  that diverged or ran out of device memory with status 1; each with one line on stderr
  (with absl's `-v 1`: after the error's traceback), and the JAX settings of a training run
  made first (host-to-device copies are errors, JAX's INFO lines quiet)."""
  from train import loop  # pylint: disable=g-import-not-at-top

  def fail(*args, **kwargs):
    raise error(loop)

  monkeypatch.setattr(loop, "setup", fail if where == "setup" else lambda *a, **k: {})
  monkeypatch.setattr(loop, "run", fail)
  train_main = _train_main_with_flags(monkeypatch, _WORKDIR=str(tmp_path / "w"))
  monkeypatch.setattr(train_main, "flags", types.SimpleNamespace(
      FLAGS=types.SimpleNamespace(verbosity=verbosity)))  # (absl's flags are not parsed here)
  updates = []
  monkeypatch.setattr(jax.config, "update", lambda *args: updates.append(args))
  loggers = [logging.getLogger(name) for name in ("", "absl", "jax")]
  levels = [logger.level for logger in loggers]
  try:
    with pytest.raises(SystemExit) as info:
      train_main.main(["train"])
    set_levels = [logger.level for logger in loggers]
  finally:
    for logger, level in zip(loggers, levels):
      logger.setLevel(level)
  assert info.value.code == status
  err = capsys.readouterr().err
  if verbosity:  # the traceback of the error raised, then its line (without the -v 1 hint)
    traceback, line = err.rsplit("\n", 2)[:2]
    assert traceback.startswith("Traceback (most recent call last):\n"), err
    raised = error(loop)
    assert f"{type(raised).__name__}: {str(raised).splitlines()[0]}" in traceback, err
    assert line == f"train: error: {says.replace(' (-v 1 for the traceback)', '')}"
  else:
    assert err == f"train: error: {says}\n"
  assert updates == [("jax_transfer_guard_host_to_device", "disallow")]
  if jax.config.jax_logging_level in (None, "", "NOTSET"):  # (no JAX_LOGGING_LEVEL given)
    assert set_levels == [logging.INFO, logging.WARNING, logging.WARNING]


def test_logged_means_leave_out_skipped_steps(caplog, monkeypatch):
  from train import loop  # pylint: disable=import-outside-toplevel

  class Writer:
    def __init__(self):
      self.records = []

    def write(self, step, scalars, split="train"):
      self.records.append((step, scalars))

  class Bar:
    shown = True  # a drawn progress bar: no log lines

    def update(self, *args, **kwargs):
      pass

  c = synthetic.get_config()
  c.train.log_every, c.train.num_steps, c.train.max_skipped_steps = 3, 6, 5
  writer = Writer()
  host = loop._HostMetrics(c, writer, Bar(), 0)  # pylint: disable=protected-access
  nan = float("nan")
  steps = [(1.0, 2.0, 1.0, 0), (nan, nan, 0.0, 1), (3.0, 4.0, 1.0, 1),  # one skipped step
           (nan, nan, 0.0, 2), (nan, nan, 0.0, 3), (nan, nan, 0.0, 4)]  # only skipped steps
  with caplog.at_level(logging.WARNING):
    for step, (loss, epe, finite, skipped) in enumerate(steps, 1):
      host(step, {"loss": loss, "epe": epe, "finite": finite, "lr": 0.1 * step,
                  "num_skipped": skipped})
  # a warning where the counter grew, none where it stayed
  assert re.findall(r"step (\d+): non-finite", caplog.text) == ["2", "4", "5", "6"]
  caplog.clear()
  (s1, first), (s2, second) = writer.records
  assert (s1, s2) == (3, 6)
  assert first["loss"] == 2.0 and first["epe"] == 3.0  # the finite steps' means
  np.testing.assert_allclose(first["finite"], 2 / 3)  # over all steps
  np.testing.assert_allclose(first["lr"], 0.3)  # the last step's rate (a mean was never used)
  assert first["num_skipped"] == 1.0 and first["window_steps"] == 3
  assert np.isnan(second["loss"]) and np.isnan(second["epe"]) and second["finite"] == 0.0
  assert second["num_skipped"] == 4.0
  # The warning names what was not finite (an absurd learning rate overflows the update's
  # norm alone: it said "non-finite loss or gradient").
  inf = float("inf")
  with caplog.at_level(logging.WARNING):
    host(7, {"loss": 1.0, "epe": 1.0, "finite": 0.0, "lr": 1e30, "num_skipped": 5,
             "l2_grads": 2.0, "l2_updates": inf})
  assert ("step 7: non-finite update norm (finite loss and gradients: is the learning rate "
          "too large?), update skipped (5 so far)") in caplog.text
  with caplog.at_level(logging.WARNING):  # the gradient too: not the learning rate's
    loop._HostMetrics(c, writer, Bar(), 0)(  # pylint: disable=protected-access
        1, {"loss": 1.0, "epe": 1.0, "finite": 0.0, "lr": 0.1, "num_skipped": 1,
            "l2_grads": inf, "l2_updates": inf})
  assert "step 1: non-finite gradient norm and update norm, update skipped (1 so far)" in (
      caplog.text)
  # More than max_skipped_steps: a Diverged error naming the limit (a FloatingPointError
  # "6 skipped updates > train.max_skipped_steps" before, printed with its traceback)
  with pytest.raises(loop.Diverged, match=r"^step 8: 6 updates skipped for a non-finite loss "
                     r"or gradient, more than config.train.max_skipped_steps=5: the run "
                     r"diverged \(a lower --config.optimizer.lr\?"):
    host(8, {"loss": nan, "epe": nan, "finite": 0.0, "lr": 0.8, "num_skipped": 6})
  # Resumed from step 2 (a SIGTERM save off the logging period): the record at step 3 is the
  # mean of one step, and says so.
  resumed = loop._HostMetrics(c, writer, Bar(), 0)  # pylint: disable=protected-access
  resumed(3, {"loss": 5.0, "epe": 1.0, "finite": 1.0, "lr": 0.3, "num_skipped": 0})
  assert writer.records[-1][0] == 3 and writer.records[-1][1]["window_steps"] == 1
  # A step without measured frames (no valid pixel in its batch) adds nothing to the EPE mean.
  measured = loop._HostMetrics(c, writer, Bar(), 0)  # pylint: disable=protected-access
  for step, (epe, share) in enumerate([(2.0, 1.0), (0.0, 0.0), (5.0, 0.5)], 1):
    measured(step, {"loss": 1.0, "epe": epe, "finite": 1.0, "lr": 0.1, "num_skipped": 0,
                    "measured_frames": share})
  record = writer.records[-1][1]
  assert record["epe"] == pytest.approx((2.0 + 2.5) / 1.5) and record["loss"] == 1.0
  assert record["measured_frames"] == pytest.approx(0.5)
  # The next window's frames only; a skipped step's are not measured.
  for step, (epe, share, skipped) in enumerate([(4.0, 1.0, 0), (nan, 1.0, 1), (2.0, 0.5, 1)], 4):
    measured(step, {"loss": 1.0, "epe": epe, "finite": float(not np.isnan(epe)), "lr": 0.1,
                    "num_skipped": skipped, "measured_frames": share})
  assert writer.records[-1][0] == 6
  assert writer.records[-1][1]["epe"] == pytest.approx((4.0 + 1.0) / 1.5)
  # Records at the periods, at a stop (`last_step`) and at train.num_steps off the periods;
  # without a "finite" metric, a NaN loss marks a skipped step.
  c2 = synthetic.get_config()
  c2.train.log_every, c2.train.num_steps = 4, 6
  ends = loop._HostMetrics(c2, writer, Bar(), 0)  # pylint: disable=protected-access
  del writer.records[:]
  for step, loss in enumerate([1.0, nan, 3.0, 5.0, 7.0, 9.0], 1):
    ends(step, {"loss": loss, "epe": 1.0, "lr": 0.1, "num_skipped": int(step > 1)},
         last_step=step == 5)
  assert [(s, r["loss"], r["window_steps"]) for s, r in writer.records] == [
      (4, 3.0, 4.0), (5, 7.0, 1.0), (6, 9.0, 1.0)]
  caplog.clear()
  with caplog.at_level(logging.INFO):
    host(3, {"loss": 5.0, "epe": 1.5, "1px": 0.25, "finite": 1.0, "lr": 0.3, "num_skipped": 0})
  assert "step 3:" not in caplog.text  # the bar shows it
  # Without the progress bar (off, or a log file), each record is a line of the log too,
  # with the time left to the last step; the first record's rate leaves out the first step,
  # whose time holds the compile (100 s here, then 2 s a step).
  Bar.shown = False
  clock = iter([0.0, 100.0, 104.0, 104.0, 106.0, 106.0, 0.0, 30.0, 30.0, 30.0])
  monkeypatch.setattr(loop.time, "perf_counter", lambda: next(clock))
  quiet = loop._HostMetrics(c, writer, Bar(), 0)  # pylint: disable=protected-access
  metrics = {"loss": 5.0, "epe": 1.5, "1px": 0.25, "finite": 1.0, "lr": 0.3, "num_skipped": 0}
  with caplog.at_level(logging.INFO):
    for step in (1, 2, 3):
      quiet(step, metrics)
  assert "step 3: loss 5, epe 1.5, 1px 0.25, lr 0.3 (0.5 steps/s, 6 s to step 6)" in (
      caplog.text), caplog.text
  caplog.clear()
  with caplog.at_level(logging.INFO):  # the last step: no time left to say
    quiet(6, {"loss": 5.0, "epe": 1.5, "finite": 1.0, "lr": 0.3, "num_skipped": 0})
  assert "step 6: loss 5, epe 1.5, lr 0.3 (0.5 steps/s)" in caplog.text, caplog.text
  c.train.log_every = 1  # a record of the first step alone: no rate to say yet
  caplog.clear()
  with caplog.at_level(logging.INFO):
    loop._HostMetrics(c, writer, Bar(), 0)(1, metrics)  # pylint: disable=protected-access
  assert "step 1: loss 5, epe 1.5, 1px 0.25, lr 0.3 (the first step, with the compile: 30 s)" in (
      caplog.text), caplog.text
  assert [loop._duration(t) for t in (40.4, 59.4, 59.6, 60, 720, 3900)] == [  # pylint: disable=protected-access
      "40 s", "59 s", "1 min", "1 min", "12 min", "1 h 05 min"]


def test_the_progress_bar_is_drawn_on_terminals_only_and_the_schedule_is_described(monkeypatch):
  """A bar in a log file (nohup, a batch job) was carriage-return updates and no step lines."""
  from train import logging_utils  # pylint: disable=g-import-not-at-top

  class Terminal(io.StringIO):
    def isatty(self):
      return True

  monkeypatch.delitem(sys.modules, "ipykernel", raising=False)  # (not in a notebook)
  for stream, enabled, shown in ((Terminal(), True, True), (io.StringIO(), True, False),
                                 (Terminal(), False, False)):
    bar = logging_utils.Progress(0, 10, enabled=enabled, stream=stream)
    assert bar.shown == shown
    bar.update(1, loss=1.0, epe=0.123456)
    bar.close()
    assert ("1/10" in stream.getvalue()) == shown
    assert ("loss=1, epe=0.1235" in stream.getvalue()) == shown  # 4 significant digits
  resumed = Terminal()  # a run resumed at step 5: its bar goes on from there
  bar = logging_utils.Progress(5, 10, stream=resumed)
  bar.update(1)
  bar.close()
  assert "6/10" in resumed.getvalue()
  for index, shown in ((1, False), (0, True)):  # on standard error, by process 0 only
    monkeypatch.setattr(sys, "stderr", Terminal())
    monkeypatch.setattr(jax, "process_index", lambda i=index: i)
    bar = logging_utils.Progress(0, 10)
    bar.update(3)
    bar.close()
    assert ("3/10" in sys.stderr.getvalue()) == shown
  monkeypatch.setitem(sys.modules, "ipykernel", types.ModuleType("ipykernel"))  # a notebook:
  assert logging_utils.Progress(0, 10, stream=io.StringIO()).shown  # no TTY, but tqdm draws
  c = synthetic.get_config()
  c.optimizer.lr, c.optimizer.pct_start, c.optimizer.div_factor = 1e-4, 0.01, 25.0
  c.optimizer.final_div_factor, c.optimizer.schedule_steps = 1e4, 0
  assert optim.schedule_summary(c.optimizer, 120_000) == (
      "one-cycle (linear), from 4e-06 up to 0.0001 at update 1200, down to 4e-10 at update "
      "120099 of a 120100-update cycle (this run's last update is 119999, at 8.45e-08)")
  # 8.45e-08: 4e-10 + (1e-4 - 4e-10) * (120099 - 119999) / (120099 - 1200), the rate the
  # last step's log line shows (the rate after it, 8.37e-08, was shown before)
  c.optimizer.schedule_steps = 1000
  assert optim.schedule_summary(c.optimizer, 5000).endswith(
      "update 999 of a 1000-update cycle, then held (this run: 5000 updates)")
  # A run one update short of the cycle ends at update 998, above the final rate:
  # 4e-10 + (1e-4 - 4e-10) * (999 - 998) / (999 - 9) = 1.01e-07.
  assert optim.schedule_summary(c.optimizer, 999).endswith(
      "update 999 of a 1000-update cycle (this run's last update is 998, at 1.01e-07)")
  assert optim.schedule_summary(c.optimizer, 1000).endswith(
      "update 999 of a 1000-update cycle, then held (this run: 1000 updates)")
  c.optimizer.schedule = "constant"
  assert optim.schedule_summary(c.optimizer, 5000) == "constant 0.0001"
  c.optimizer.lr = 1.25e-4
  assert optim.schedule_summary(c.optimizer, 5000) == "constant 0.000125"


def _loop_parts(c, workdir, step_hook=None, evaluator=None):
  """`loop.run`'s parts for the toy model; `step_hook(k)` runs after its k-th step."""
  _, mesh, _, state, _, step = _setup(c)
  calls = [0]

  def train_step(state, batch):
    out = step(state, batch)
    calls[0] += 1
    if step_hook is not None:
      step_hook(calls[0])
    return out

  it = _toy_iterator()
  return dict(grain_it=it, manager=ckpt_lib.make_manager(workdir, c), state=state,
              train_step=train_step, evaluator=evaluator,
              model=type("M", (), {"cfg": sav_jax.SAVConfig()})(),
              batches=pipeline.GlobalBatchIterator(it, state_lib.data_sharding(mesh)))


def _steps_logged(workdir):
  return [json.loads(l)["step"] for l in (workdir / "metrics.jsonl").read_text().splitlines()]


def test_sigterm_saves_the_current_step_and_stops(tmp_path):
  import os  # pylint: disable=g-import-not-at-top
  import signal  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 6, 1, False
  c.checkpoint.every_steps, c.eval.every_steps = 100, 0

  def preempt(k):
    if k == 2:
      os.kill(os.getpid(), signal.SIGTERM)  # a scheduler's notice, during step 2

  handler = signal.getsignal(signal.SIGTERM)
  parts = _loop_parts(c, tmp_path, preempt)
  manager, handlers = parts["manager"], []
  close = manager.close  # the last save is finished under the run's handler (a second
  manager.close = lambda: (handlers.append(signal.getsignal(signal.SIGTERM)), close())[1]
  with pytest.raises(loop.Preempted, match=r"stopped at step 2 of 6 \(SIGTERM\)"):
    loop.run(c, tmp_path, parts)  # notice then must not kill the process mid-write)
  assert len(handlers) == 1 and handlers[0] is not handler
  assert signal.getsignal(signal.SIGTERM) is handler  # restored
  assert sav_jax.convert.find_training_checkpoint(tmp_path) == tmp_path / "checkpoints" / "2"
  assert _steps_logged(tmp_path) == [1, 2]
  # The same command resumes from it and finishes.
  state = loop.run(c, tmp_path, _resumed_parts(c, tmp_path))
  assert int(state.step) == 6 and _steps_logged(tmp_path) == [1, 2, 3, 4, 5, 6]
  # Off the logging period, the window up to the stop is logged at the stop, so that every
  # step is in one record (the resumed run starts after it): 1-2, 3 | 4, 5-6.
  c.train.log_every = 2
  again = tmp_path / "again"
  with pytest.raises(loop.Preempted, match=r"stopped at step 3 of 6 \(SIGTERM\)"):
    loop.run(c, again, _loop_parts(c, again, lambda k: k == 3 and preempt(2)))
  loop.run(c, again, _resumed_parts(c, again))
  records = [json.loads(l) for l in (again / "metrics.jsonl").read_text().splitlines()]
  assert [(r["step"], r["window_steps"]) for r in records] == [(2, 2), (3, 1), (4, 1), (6, 2)]


def test_a_finished_run_run_again_says_it_is_complete(tmp_path, caplog):
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 2, 1, False
  c.checkpoint.every_steps, c.eval.every_steps = 100, 0
  loop.run(c, tmp_path, _loop_parts(c, tmp_path))
  assert "is complete" not in caplog.text
  with caplog.at_level(logging.WARNING):
    state = loop.run(c, tmp_path, _resumed_parts(c, tmp_path))
  assert int(state.step) == 2 and _steps_logged(tmp_path) == [1, 2]
  assert (f"the run in {tmp_path} is complete: its checkpoint is of step 2, "
          "config.train.num_steps=2; nothing to train") in caplog.text


def test_ctrl_c_during_a_checkpoint_save_lets_the_save_finish(tmp_path, monkeypatch):
  # A KeyboardInterrupt inside orbax's synchronous part of a save dropped the checkpoint:
  # Ctrl-C is held back while the save starts, and raised once it has (the first one asks
  # for a checkpoint after the next step; the second, during that save, stops at once).
  import os  # pylint: disable=g-import-not-at-top
  import signal  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 6, 1, False
  c.checkpoint.every_steps, c.eval.every_steps = 2, 0
  real_save, saved = ckpt_lib.save, []

  def interrupted_save(manager, state, it, step, **kw):
    os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while orbax starts the save
    saved.append(real_save(manager, state, it, step, **kw))
    return saved[-1]

  monkeypatch.setattr(ckpt_lib, "save", interrupted_save)
  # Python's own Ctrl-C handler (pytest-xdist's workers ignore SIGINT, which is kept too).
  handler = signal.signal(signal.SIGINT, signal.default_int_handler)
  try:
    with pytest.raises(KeyboardInterrupt):
      loop.run(c, tmp_path, _loop_parts(c, tmp_path))
    assert saved == [True, True] and signal.getsignal(signal.SIGINT) is signal.default_int_handler
  finally:
    signal.signal(signal.SIGINT, handler)
  assert sav_jax.convert.find_training_checkpoint(tmp_path) == tmp_path / "checkpoints" / "3"
  with loop.interrupt_after():  # nothing held back: the block runs, nothing raised
    pass


def test_the_first_ctrl_c_saves_the_step_and_stops_as_sigterm_does(tmp_path):
  """Ctrl-C stopped a run where it landed: up to `checkpoint.every_steps` - 1 steps were lost
  (2,999 with sceneflow.py), where SIGTERM saved the current step."""
  import os  # pylint: disable=g-import-not-at-top
  import signal  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 6, 1, False
  c.checkpoint.every_steps, c.eval.every_steps = 100, 0

  def ctrl_c(k):
    if k == 2:
      os.kill(os.getpid(), signal.SIGINT)

  handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # (xdist ignores it)
  try:
    with pytest.raises(loop.Preempted, match=r"stopped at step 2 of 6 \(Ctrl-C\)") as info:
      loop.run(c, tmp_path, _loop_parts(c, tmp_path, ctrl_c))
    assert info.value.reason == loop.CTRL_C  # (exit status 130, SIGTERM's 143)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back
    assert sav_jax.convert.find_training_checkpoint(tmp_path) == tmp_path / "checkpoints" / "2"
    state = loop.run(c, tmp_path, _resumed_parts(c, tmp_path))  # the same command resumes
    assert int(state.step) == 6 and _steps_logged(tmp_path) == [1, 2, 3, 4, 5, 6]
  finally:
    signal.signal(signal.SIGINT, handler)
  def early(k):  # before any step finished (the first compile): at once, no checkpoint
    if k == 1:
      os.kill(os.getpid(), signal.SIGINT)

  handler = signal.signal(signal.SIGINT, signal.default_int_handler)
  try:
    with pytest.raises(KeyboardInterrupt):
      loop.run(c, tmp_path / "early", _loop_parts(c, tmp_path / "early", early))
  finally:
    signal.signal(signal.SIGINT, handler)
  assert sav_jax.convert.find_training_checkpoint(tmp_path / "early") is None
  handler = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job: left as it is
  try:
    with loop.Preemption(None):
      assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
  finally:
    signal.signal(signal.SIGINT, handler)


def test_which_notice_stops_the_run_after_its_step_and_which_at_once(caplog):
  """`Preemption`'s handlers, called as the signals would call them: a Ctrl-C before the
  first step, a second one, or one after a SIGTERM goes to the previous handler at once; the
  others are the reason `Preemption(step)` returns, each warned about once."""
  import signal  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  # pylint: disable=protected-access
  at_once = []
  ctrl_c = loop.Preemption(None)  # (one process: no manager is asked)
  ctrl_c._previous_int = lambda signum, frame: at_once.append("ctrl_c")
  ctrl_c._on_interrupt(signal.SIGINT, None)  # in the first compile: at once
  assert at_once == ["ctrl_c"] and ctrl_c(1) is None
  with caplog.at_level(logging.WARNING):
    ctrl_c._on_interrupt(signal.SIGINT, None)
  assert at_once == ["ctrl_c"] and ctrl_c(2) == loop.CTRL_C
  ctrl_c._on_interrupt(signal.SIGINT, None)  # the second
  assert at_once == ["ctrl_c", "ctrl_c"]
  ctrl_c._on_signal(signal.SIGTERM, None)  # the scheduler's notice: its reason (status 143)
  assert ctrl_c(3) == "SIGTERM"
  term = loop.Preemption(None)
  term._previous_int = lambda signum, frame: at_once.append("term")
  with caplog.at_level(logging.WARNING):
    term._on_signal(signal.SIGTERM, None)
    term._on_signal(signal.SIGTERM, None)
  assert term(1) == "SIGTERM" and at_once == ["ctrl_c", "ctrl_c"]
  term._on_interrupt(signal.SIGINT, None)  # a Ctrl-C after a SIGTERM
  assert at_once[-1] == "term" and term(2) == "SIGTERM"
  assert caplog.text.count("saving a checkpoint after this step") == 2  # one each
  # The context installs both handlers, and puts the previous ones back.
  term_before = signal.getsignal(signal.SIGTERM)
  int_before = signal.signal(signal.SIGINT, signal.default_int_handler)  # (xdist ignores it)
  try:
    with loop.Preemption(None) as preemption:
      assert signal.getsignal(signal.SIGTERM) == preemption._on_signal
      assert signal.getsignal(signal.SIGINT) == preemption._on_interrupt
    assert signal.getsignal(signal.SIGTERM) == term_before
    assert signal.getsignal(signal.SIGINT) == signal.default_int_handler
  finally:
    signal.signal(signal.SIGINT, int_before)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # (the drop)
def test_a_ctrl_c_that_python_drops_still_stops_the_run(tmp_path):
  # A Ctrl-C that landed in JAX's garbage-collection callback ("Exception ignored in:
  # <function _xla_gc_callback>") was dropped by Python: an 8-device run went on to its last
  # step and exited 0. The loop remembers it and stops before the next step.
  import signal  # pylint: disable=g-import-not-at-top
  from tests.conftest import drop_ctrl_c_in_gc  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 4, 1, False
  c.checkpoint.every_steps, c.eval.every_steps = 100, 0

  steps = []

  def dropped_ctrl_c(step):
    steps.append(step)
    if step == 1:
      drop_ctrl_c_in_gc()  # the first asks for a save after the step (nothing to drop)
      drop_ctrl_c_in_gc()  # the second stops at once: its KeyboardInterrupt is dropped

  handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # (xdist ignores it)
  try:
    with pytest.raises(KeyboardInterrupt):
      loop.run(c, tmp_path, _loop_parts(c, tmp_path, step_hook=dropped_ctrl_c))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back
  finally:
    signal.signal(signal.SIGINT, handler)
  assert steps == [1]  # stopped before step 2 (it ran all 4)
  # Where SIGINT is ignored (a job started in the background), a save holds nothing back
  # and says nothing (it logged "Ctrl-C: the checkpoint save it met is started; stopping").
  handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
  try:
    with loop.interrupt_after():
      assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
  finally:
    signal.signal(signal.SIGINT, handler)


def test_sigterm_on_a_validation_step_still_validates(tmp_path):
  import os  # pylint: disable=g-import-not-at-top
  import signal  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 4, 1, False
  c.checkpoint.every_steps, c.eval.every_steps, c.eval.at_start = 100, 2, False
  validated = []

  def evaluator(params):
    validated.append(len(validated))
    return {"epe": 1.0}

  for notice_at, steps in ((2, [2]), (4, [2, 4])):  # a periodic validation step; the last
    workdir = tmp_path / str(notice_at)
    parts = _loop_parts(c, workdir, lambda k, n=notice_at: k == n and os.kill(
        os.getpid(), signal.SIGTERM), evaluator=evaluator)
    validated.clear()
    if notice_at < c.train.num_steps:
      with pytest.raises(loop.Preempted, match=f"stopped at step {notice_at} of 4"):
        loop.run(c, workdir, parts)
    else:  # a notice during the last step: the run is complete, nothing to resume
      assert int(loop.run(c, workdir, parts).step) == 4
    records = [json.loads(l) for l in (workdir / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if r["split"] == "val"] == steps, notice_at
    assert sav_jax.convert.find_training_checkpoint(workdir).name == str(notice_at)


def test_the_last_step_is_validated_and_saved_off_the_periods(tmp_path):
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 3, 2, False
  c.checkpoint.every_steps, c.checkpoint.async_save, c.checkpoint.keep = 2, False, 0
  c.eval.every_steps, c.eval.at_start = 2, True
  parts = _loop_parts(c, tmp_path, evaluator=lambda params: {"epe": 1.0})
  assert int(loop.run(c, tmp_path, parts).step) == 3
  records = [json.loads(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  assert [(r["step"], r["split"]) for r in records] == [
      (0, "val"), (2, "train"), (2, "val"), (3, "train"), (3, "val")]
  assert sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir()) == [2, 3]


def test_a_validation_lost_with_the_process_is_run_on_resume(tmp_path):
  # The checkpoint of a validation step is saved before the validation runs: a run killed
  # while validating (SIGKILL, out of memory) resumes after that step, and the validation
  # was never logged. The resumed run validates the restored step first; the last step's
  # too, where a rerun of the finished run has nothing else to do.
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.log_every, c.train.progress_bar = 4, 1, False
  c.checkpoint.every_steps, c.checkpoint.async_save = 2, False
  c.eval.every_steps, c.eval.at_start = 2, False
  validated = []

  def killed(params):
    raise KeyboardInterrupt  # (what a kill looks like to the log: nothing written)

  def evaluator(params):
    validated.append(True)
    return {"epe": float(len(validated))}

  def val_steps():
    return [json.loads(l)["step"] for l in (tmp_path / "metrics.jsonl").read_text().splitlines()
            if json.loads(l)["split"] == "val"]

  with pytest.raises(KeyboardInterrupt):
    loop.run(c, tmp_path, _loop_parts(c, tmp_path, evaluator=killed))
  assert sav_jax.convert.find_training_checkpoint(tmp_path).name == "2" and val_steps() == []
  parts = _resumed_parts(c, tmp_path)
  parts["evaluator"] = evaluator
  assert int(loop.run(c, tmp_path, parts).step) == 4
  assert val_steps() == [2, 4] and _steps_logged(tmp_path) == [1, 2, 2, 3, 4, 4]
  # Nothing is validated twice: a rerun of the finished run does nothing ...
  parts = _resumed_parts(c, tmp_path)
  parts["evaluator"] = evaluator
  validated.clear()
  loop.run(c, tmp_path, parts)
  assert validated == [] and val_steps() == [2, 4]
  # ... but runs the last validation if the log lacks it.
  lines = (tmp_path / "metrics.jsonl").read_text().splitlines(keepends=True)
  (tmp_path / "metrics.jsonl").write_text("".join(lines[:-1]))
  parts = _resumed_parts(c, tmp_path)
  parts["evaluator"] = evaluator
  loop.run(c, tmp_path, parts)
  assert validated == [True] and val_steps() == [2, 4]


def _resumed_parts(c, workdir):
  from train import loop  # pylint: disable=g-import-not-at-top
  parts = _loop_parts(c, workdir)
  model, mesh, tx = ToyStereo(), state_lib.make_mesh(), optim.make_optimizer(c.optimizer,
                                                                            c.train.num_steps)
  parts["state"], _, source = loop.initial_state(c, model, tx, mesh, parts["manager"],
                                                 parts["grain_it"])
  assert source == "checkpoint"
  return parts


def test_an_error_after_a_save_still_finishes_that_save(tmp_path):
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.num_steps, c.train.progress_bar = 6, False
  c.checkpoint.every_steps, c.checkpoint.async_save = 2, True
  c.eval.every_steps, c.eval.at_start = 2, False

  def evaluator(params):  # validation runs right after the checkpoint of its step
    raise RuntimeError("validation out of memory")

  parts = _loop_parts(c, tmp_path, evaluator=evaluator)
  manager, closed = parts["manager"], []
  close = manager.close  # (it waits for the saves in flight)
  manager.close = lambda: (closed.append(True), close())[1]
  with pytest.raises(RuntimeError, match="validation out of memory"):
    loop.run(c, tmp_path, parts)
  assert closed == [True]  # before the error left `run`
  assert sav_jax.convert.find_training_checkpoint(tmp_path) == tmp_path / "checkpoints" / "2"


def test_resume_checks_num_steps_and_never_needs_the_init_files(toy_run, tmp_path, monkeypatch):
  import shutil  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  workdir = tmp_path / "run"
  shutil.copytree(toy_run[0], workdir)
  (workdir / "checkpoints" / "1").rename(workdir / "checkpoints" / "5")
  c = _config()
  c.train.num_steps = 3
  with pytest.raises(ValueError, match=r"config.train.num_steps=3 is below the step of the "
                     r"checkpoint .*checkpoints/5\): pass a train.num_steps of at least 5"):
    loop.setup(c, workdir)
  c.train.num_steps = 4  # one short of the checkpoint: refused too
  with pytest.raises(ValueError, match=r"config.train.num_steps=4 is below the step of the "):
    loop.setup(c, workdir)

  class Reached(Exception):
    pass

  def past_the_checks():
    raise Reached

  # The files a run started from may be gone when it resumes (moved, a scratch disk
  # cleaned, another node): the checkpoint in the workdir is all a resume reads.
  monkeypatch.setattr(loop.state_lib, "make_mesh", past_the_checks)
  c.train.num_steps, c.init_from, c.vda_weights = 10, str(tmp_path / "moved.pth"), ""
  with pytest.raises(Reached):
    loop.setup(c, workdir)
  c.init_from, c.vda_weights = "", str(tmp_path / "moved_vda.pth")
  with pytest.raises(Reached):
    loop.setup(c, workdir)
  with pytest.raises(FileNotFoundError, match="config.vda_weights=.*moved_vda.pth: no such"):
    loop.setup(c, tmp_path / "fresh")  # not resuming: read, so checked


def test_microbatches_give_the_whole_batchs_step():
  """`train.microbatches`: the batch as equal parts run one after the other, one update with
  the mean gradient: the same step as the whole batch at once (float32 summation order)."""
  rng = np.random.default_rng(0)
  c = _config()
  c.train.batch_size = 4
  batch = _batch(rng, c)
  got = {}
  for k in (1, 2, 4):
    c.train.microbatches = k
    _, mesh, _, state, _, step = _setup(c)
    before = jax.device_get(state.params)
    got[k] = jax.device_get(step(state, _put(batch, mesh)))
  for k in (2, 4):
    for key in ("loss", "epe", "1px", "l2_grads", "valid_fraction"):
      np.testing.assert_allclose(got[k][1][key], got[1][1][key], rtol=1e-5, err_msg=key)
    for a, b, p0 in zip(jax.tree.leaves(got[k][0].params), jax.tree.leaves(got[1][0].params),
                        jax.tree.leaves(before)):
      np.testing.assert_allclose(a, b, atol=1e-3 * max(float(np.abs(b - p0).max()), 1e-12))
  assert not np.allclose(got[1][0].params["head"]["kernel"], before["head"]["kernel"])
  # Sparse ground truth: part 1 of 2 (clips 1 and 3) without a valid pixel, a frame of
  # clip 2 with a few only: the accuracy metrics are the whole batch's means over its
  # measured frames, not the mean of the parts' (which halved them). Then a quarter of
  # part 1's frames measured (clip 3's second): each part's means weigh by its measured
  # share (1 and 1/4), not equally.
  batch["valid"][1::2] = False
  batch["valid"][2, 0] = False
  batch["valid"][2, 0, :2] = True
  for part_1_measured in (False, True):
    batch["valid"][3, 1] = part_1_measured
    sparse = {}
    for k in (1, 2):
      c.train.microbatches = k
      _, mesh, _, state, _, step = _setup(c)
      sparse[k] = jax.device_get(step(state, _put(batch, mesh)))[1]
    for key in ("loss", "epe", "1px", "3px", "5px", "measured_frames", "valid_fraction"):
      np.testing.assert_allclose(sparse[2][key], sparse[1][key], rtol=1e-5,
                                 err_msg=f"{key} (part 1 measured: {part_1_measured})")
  for k, per_sample, match in ((3, True, "microbatches=3 does not divide config.train.batch_size=4"),
                               (0, True, "microbatches=0: expected an integer >= 1"),
                               (2, False, "needs config.loss.per_sample=True"),
                               (True, True, "microbatches=True: expected an integer >= 1")):
    c.train.microbatches, c.loss.per_sample = k, per_sample
    with pytest.raises(ValueError, match=match):
      step_lib.check_microbatches(c)


def test_validation_clips_that_cannot_be_used_name_the_config_fields(monkeypatch):
  """Reading and cropping the held-out clips came after the block naming the fields: a crop
  larger than the frames, or a split without ground truth, named no config field."""
  import grain  # pylint: disable=g-import-not-at-top
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  c = synthetic.get_config()
  c.eval.dataset, c.eval.split, c.data.root, c.data.crop = "sintel_final", "test", "d", (32, 64)
  clip = {"left": np.zeros((c.data.frames, 24, 40, 3), np.uint8),
          "right": np.zeros((c.data.frames, 24, 40, 3), np.uint8),
          "disparity": np.zeros((c.data.frames, 24, 40), np.float32),
          "valid": np.ones((c.data.frames, 24, 40), bool)}
  monkeypatch.setattr(pipeline, "registry_source",
                      lambda *a, **k: grain.MapDataset.source([clip] * 3))
  with pytest.raises(ValueError, match=r"config\.eval\.dataset='sintel_final', config\.eval\.split="
                     r"'test', config\.data\.root='d', config\.data\.crop=\(32, 64\): crop "):
    input_lib.eval_clips(c)
  c.data.crop = (16, 32)
  assert [x["left"].shape[1:3] for x in input_lib.eval_clips(c)] == [(16, 32)] * 3


def test_held_out_clips_are_spread_over_the_split_and_not_trained_on(monkeypatch):
  import grain  # pylint: disable=g-import-not-at-top
  from train import input as input_lib  # pylint: disable=g-import-not-at-top
  c = _config()
  c.train.batch_size, c.data.synthetic.num_clips, c.eval.num_clips = 4, 4, 4
  batch = next(iter(input_lib.train_dataset(c, process_index=0, process_count=1)))
  held_out = input_lib.eval_clips(c)  # generated from config.eval.synthetic_seed
  assert len(held_out) == 4
  for clip in batch["disparity"]:
    assert not any(np.array_equal(clip, h["disparity"]) for h in held_out)
  # A dataset's split: clips from all over it (every 5th of 10 windows), consecutive frames.
  c.eval.dataset, c.eval.split, c.eval.num_clips = "sintel_final", "test", 2
  calls = []

  def source(*args, **kwargs):
    calls.append(kwargs)
    return grain.MapDataset.source([{"left": np.full((2, 16, 16, 3), i, np.uint8),
                                     "right": np.zeros((2, 16, 16, 3), np.uint8),
                                     "disparity": np.ones((2, 16, 16), np.float32),
                                     "valid": np.ones((2, 16, 16), bool)} for i in range(10)])

  monkeypatch.setattr(pipeline, "registry_source", source)
  assert [int(x["left"][0, 0, 0, 0]) for x in input_lib.eval_clips(c)] == [0, 5]
  assert calls[0]["consecutive"] is True
  c.eval.num_clips = 3  # every 10 // 3 = 3rd window, the first 3 of them
  assert [int(x["left"][0, 0, 0, 0]) for x in input_lib.eval_clips(c)] == [0, 3, 6]


@pytest.mark.parametrize("during", ["setup", "run"])
def test_ctrl_c_ends_the_train_command_with_one_line(toy_run, tmp_path, during):
  # Ctrl-C printed a ~40-line KeyboardInterrupt traceback of wherever it landed; now one line
  # that says where the run resumes from, status 130 (128 + SIGINT).
  import subprocess  # pylint: disable=g-import-not-at-top
  from tests.train.conftest import ROOT, child_env  # pylint: disable=g-import-not-at-top
  code = ("import runpy, sys\nfrom train import loop\n"
          "def interrupt(*a, **k):\n  raise KeyboardInterrupt\n"
          f"loop.setup = {'interrupt' if during == 'setup' else 'lambda *a, **k: {}'}\n"
          "loop.run = interrupt\n"
          "sys.argv = ['train', '--config', 'configs/synthetic.py', '--workdir', sys.argv[1]]\n"
          "runpy.run_module('train', run_name='__main__')\n")
  for workdir, says in ((toy_run[0], f"the last checkpoint is {toy_run[0] / 'checkpoints' / '1'}:"
                         " the same command resumes from it"),
                        (tmp_path / "new", "no checkpoint was saved: the same command starts "
                         "the run anew")):
    proc = subprocess.run([sys.executable, "-c", code, str(workdir)], cwd=ROOT,
                          env=child_env(tmp_path / "cache"), capture_output=True, text=True,
                          timeout=300, check=False)
    assert proc.returncode == 130, proc.stderr[-2000:]
    assert proc.stderr.strip() == f"train: interrupted (Ctrl-C); {says}", proc.stderr[-2000:]
  if during == "run":  # the first Ctrl-C: a checkpoint of the step, then 130 (SIGTERM's 143)
    for reason, status in (("loop.CTRL_C", 130), ("'SIGTERM'", 143)):
      stopped = code.replace("def interrupt(*a, **k):\n  raise KeyboardInterrupt\n",
                             "def interrupt(*a, **k):\n  raise loop.Preempted('stopped at step "
                             f"3 of 9 (x), with a checkpoint', {reason})\n")
      proc = subprocess.run([sys.executable, "-c", stopped, str(tmp_path / "new")], cwd=ROOT,
                            env=child_env(tmp_path / "cache"), capture_output=True, text=True,
                            timeout=300, check=False)
      assert proc.returncode == status, proc.stderr[-2000:]
      assert proc.stderr.strip() == "train: stopped at step 3 of 9 (x), with a checkpoint"


def test_a_failed_checkpoint_write_is_one_line_naming_step_folder_and_cause(tmp_path):
  # A full disk during an async save surfaced as orbax's chained traceback at the next save,
  # then thousands of lines of its pending writes failing as Python shut down.
  class Manager:
    directory = tmp_path / "checkpoints"

    def __init__(self, error):
      self.error = error

    def wait_until_finished(self):
      raise self.error

  orbax_text = ('RESOURCE_EXHAUSTED: Error writing "params.x/0" in OCDBT database at local file '
                f'"{tmp_path}/checkpoints/2.orbax-checkpoint-tmp/state.orbax-checkpoint-tmp/": '
                "Failed to write 9244672 bytes to file 9: No space left on device "
                "[os_error_code='28']")
  with pytest.raises(ckpt_lib.CheckpointSaveError) as info:
    ckpt_lib.wait_until_saved(Manager(ValueError(orbax_text)))
  assert str(info.value).startswith(f"saving checkpoint 2 in {tmp_path / 'checkpoints'} failed: "
                                    "no space left on device. The checkpoints saved before are "
                                    "intact")
  assert isinstance(info.value.__cause__, ValueError)
  with pytest.raises(ckpt_lib.CheckpointSaveError,
                     match=r"saving a checkpoint in .* failed: OSError: \[Errno 5\] I/O error"):
    ckpt_lib.wait_until_saved(Manager(OSError(5, "I/O error")))
  proc = _train_failing_with(
      "checkpoint.CheckpointSaveError('saving checkpoint 2 in W failed: no space')", tmp_path)
  assert proc.returncode == 1, proc.stderr[-2000:]
  assert proc.stderr.strip() == "train: error: saving checkpoint 2 in W failed: no space"


def _train_failing_with(error: str, tmp_path, where: str = "run"):
  """`python -m train` (synthetic config, workdir `tmp_path/w`) whose `loop.run` (or
  `loop.setup`: `where`) raises `error` (Python source; `jax` and `train.checkpoint` as
  `checkpoint` are imported)."""
  import subprocess  # pylint: disable=g-import-not-at-top
  from tests.train.conftest import ROOT, child_env  # pylint: disable=g-import-not-at-top
  code = ("import runpy, sys, jax\nfrom train import checkpoint, loop\n"
          f"def fail(*a, **k):\n  raise {error}\n"
          f"loop.setup = lambda *a, **k: {{}}\nloop.{where} = fail\n"
          "sys.argv = ['train', '--config', 'configs/synthetic.py', '--workdir', sys.argv[1]]\n"
          "runpy.run_module('train', run_name='__main__')\n")
  return subprocess.run([sys.executable, "-c", code, str(tmp_path / "w")], cwd=ROOT,
                        env=child_env(tmp_path / "cache"), capture_output=True, text=True,
                        timeout=300, check=False)


def test_a_device_out_of_memory_is_one_line_with_what_to_change(tmp_path):
  # A step too big for the device ended the run with XLA's traceback and its buffer tables
  # (hundreds of lines on a GPU), naming none of the settings that make a step smaller.
  for where in ("setup", "run"):  # (setup places the initial state on the devices)
    proc = _train_failing_with(
        "jax.errors.JaxRuntimeError('RESOURCE_EXHAUSTED: Out of memory while trying to allocate "
        "30.5GiB.\\nBufferAssignment OOM Debugging.\\n  parameter allocation: 1GiB')", tmp_path,
        where)
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert proc.stderr.strip() == (
        "train: error: out of memory on the device: RESOURCE_EXHAUSTED: Out of memory while "
        "trying to allocate 30.5GiB.; use --config.train.microbatches=K (the same batch as K "
        "parts), --config.model.remat=true, --config.model.dtype=bfloat16, a smaller "
        "--config.train.batch_size or --config.data.crop, or fewer --config.train.iters; no "
        "checkpoint was saved: the same command starts the run anew"), (where, proc.stderr[-2000:])


def test_a_batch_the_pipeline_cannot_make_is_one_error_naming_the_step():
  """A file that does not read or a crop the frames cannot give, met at step 7, ended the
  run with grain's traceback (status 1), naming no step and no checkpoint."""
  from train import loop  # pylint: disable=import-outside-toplevel

  class Failing:
    def __next__(self):
      raise ValueError("cannot crop (48, 96) from (40, 72) frames")

  class Manager:
    def __init__(self, latest):
      self.latest = latest

    def latest_step(self):
      return self.latest

  with pytest.raises(loop.DataError, match=r"^the training batch of step 7 could not be made: "
                     r"ValueError: cannot crop \(48, 96\) from \(40, 72\) frames \(the "
                     r"checkpoint of step 5 is kept: fix the data or the config and run the "
                     r"same command to resume\)$"):
    loop._next_batch(Failing(), 7, Manager(5))  # pylint: disable=protected-access
  with pytest.raises(loop.DataError, match=r"\(no checkpoint yet\)$"):
    loop._next_batch(Failing(), 1, Manager(None))  # pylint: disable=protected-access

  class Broken:  # any error, e.g. a reader's KeyError for a field a record lacks
    def __next__(self):
      raise KeyError("disparity")

  with pytest.raises(loop.DataError, match=r"^the training batch of step 2 could not be made: "
                     r"KeyError: 'disparity' \(no checkpoint yet\)$"):
    loop._next_batch(Broken(), 2, Manager(None))  # pylint: disable=protected-access
  assert loop._next_batch(iter([{"x": 1}]), 1, Manager(None)) == {"x": 1}  # pylint: disable=protected-access

  class Unreadable:  # a reader's error (its note): the option that trains through it is named
    def __next__(self):
      e = ValueError("/d/0011.png: cannot decode the image file")
      e.add_note(pipeline.UNREADABLE_NOTE)
      raise e

  with pytest.raises(loop.DataError, match=r"0011.png: cannot decode the image file \(the "
                     r"checkpoint of step 5 is kept: .* to resume; --config.data."
                     r"skip_unreadable=N trains on another, readable clip in place of an "
                     r"unreadable one\)$"):
    loop._next_batch(Unreadable(), 7, Manager(5))  # pylint: disable=protected-access
  with pytest.raises(loop.DataError, match=r"to resume\)$"):  # already on: no hint
    loop._next_batch(Unreadable(), 7, Manager(5), 3)  # pylint: disable=protected-access


def test_the_depth_prior_of_checkpoints_saved_before_it_was_recorded():
  """A checkpoint without `depth_prior` (older code): its saved training config tells where
  the prior came from; without that either it is unknown, never called random (resuming such
  a run needs neither weights field, so the current config cannot tell)."""
  import sav_jax  # pylint: disable=g-import-not-at-top
  run = {"vda_weights": "vda.pth", "init_from": "", "random_depth_prior": False}
  assert ckpt_lib.saved_depth_prior({"run": run}) == "Video Depth Anything weights vda.pth"
  toy = {"run": {**run, "vda_weights": "", "random_depth_prior": True}}
  assert ckpt_lib.saved_depth_prior(toy).startswith("random (config.random_depth_prior=true")
  for old in ({}, {"run": {}}, None, {"depth_prior": 3}):
    origin = ckpt_lib.saved_depth_prior(old)
    assert origin.startswith("unknown") and sav_jax.convert.random_prior_note(
        {"depth_prior": origin}, "w") is None
  # A run from such weights: an official file (nothing saved) or an old toy run.
  c = synthetic.get_config()
  c.random_depth_prior, c.init_from = False, "sav.pth"
  assert ckpt_lib.depth_prior_origin(c, {}) == "the weights of sav.pth"
  c.init_from = "runs/toy"
  assert ckpt_lib.depth_prior_origin(c, toy) == (
      "random (config.random_depth_prior=true: a toy run) (via config.init_from=runs/toy)")


def test_the_catch_up_validation_check_places_its_flag_under_the_transfer_guard(monkeypatch):
  """On several processes `broadcast_one_to_all` puts the flag on a device: an implicit
  host-to-device copy, which `python -m train`'s transfer guard refused (a resumed
  multi-host run at a validation step crashed)."""
  from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top

  def broadcast(x):  # what it does with several processes: a device copy of `x`
    return np.asarray(jax.device_get(jnp.asarray(x) | False))

  monkeypatch.setattr(multihost_utils, "broadcast_one_to_all", broadcast)
  c = synthetic.get_config()
  c.eval.every_steps, c.train.num_steps = 5, 23
  logged = types.SimpleNamespace(logged=lambda step, split: (step, split) == (5, "val"))
  before = jax.config.jax_transfer_guard_host_to_device
  jax.config.update("jax_transfer_guard_host_to_device", "disallow")
  try:
    with pytest.raises(Exception, match="Disallowed host-to-device transfer"):
      broadcast(np.asarray(True))  # the guard is on
    assert loop._validation_missing(c, logged, 10) is True  # pylint: disable=protected-access
    assert loop._validation_missing(c, logged, 5) is False  # pylint: disable=protected-access
    assert loop._validation_missing(c, logged, 7) is False  # pylint: disable=protected-access
    assert loop._validation_missing(c, logged, 23) is True  # the last step  # pylint: disable=protected-access
    assert loop._validation_missing(c, logged, 0) is False  # (at_start's)  # pylint: disable=protected-access
  finally:
    jax.config.update("jax_transfer_guard_host_to_device", before)


@pytest.mark.parametrize("damage", ["truncated", "deleted"])
def test_a_resume_names_an_unreadable_config_item(toy_run, tmp_path, damage):
  """The config saved with a checkpoint, cut short: the resume went on without a word,
  skipping every check of the fields changed since (keep, worker count, the warnings)."""
  import shutil  # pylint: disable=g-import-not-at-top
  from train import loop  # pylint: disable=g-import-not-at-top
  _, c, model, tx, mesh = toy_run
  copy = tmp_path / "run"
  shutil.copytree(toy_run[0], copy)
  step = copy / "checkpoints" / "1"
  if damage == "truncated":
    (step / "config" / "metadata").write_text("{\"model\": {", encoding="utf-8")
  else:
    (step / "config" / "metadata").unlink()
  manager = ckpt_lib.make_manager(copy, c)
  try:
    with pytest.raises(sav_jax.convert.CheckpointError,
                       match=f"{step}: the checkpoint is corrupt or incomplete.*Move this step "
                       "folder") as e:
      loop.initial_state(c, model, tx, mesh, manager, _toy_iterator())
  finally:
    manager.close()
  assert len(str(e.value)) < 800
  shutil.rmtree(step / "config")  # no config item at all: a checkpoint from before it was saved
  manager = ckpt_lib.make_manager(copy, c)
  try:
    assert loop.initial_state(c, model, tx, mesh, manager, _toy_iterator())[2] == "checkpoint"
  finally:
    manager.close()


@pytest.mark.parametrize("content", ["{\"next_index\": 3", "", "[1, 2]", "{}"])
def test_unreadable_data_position_is_named_as_such(toy_run, tmp_path, content):
  """A data position cut short, or one grain cannot set (edited, another grain version), is
  named as such, not as a model or optimizer config mismatch."""
  import shutil  # pylint: disable=g-import-not-at-top
  _, c, model, tx, mesh = toy_run
  copy = tmp_path / "run"
  shutil.copytree(toy_run[0], copy)
  position = copy / "checkpoints" / "1" / "data" / "process_0-of-1.json"
  position.write_text(content, encoding="utf-8")
  with pytest.raises(sav_jax.convert.CheckpointError) as e:
    _toy_restore(copy, c, model, tx, mesh)
  message = str(e.value)
  assert "does not match" not in message and "Move this step folder" in message
  if content.startswith("{\"next") or not content:  # not JSON: a file cut short
    assert "the checkpoint is corrupt or incomplete" in message
  else:
    assert message.startswith(f"{position}: this process's position in the data cannot be "
                              "restored")


def test_a_workdir_whose_name_is_not_utf8_is_refused_before_the_run(tmp_path):
  """Latin-1 bytes (a zip made on Windows): the run trained, then its first checkpoint save
  failed inside orbax's TensorStore ("Unable to cast Python instance of type <class 'str'>"),
  the training's steps lost."""
  from train import loop  # pylint: disable=g-import-not-at-top
  odd = tmp_path / os.fsdecode(b"caf\xe9")
  for workdir in (odd, odd / "run"):
    with pytest.raises(ValueError, match=r"caf\\udce9.*': the --workdir folder's name is not "
                                         "UTF-8 text"):
      loop.validate_config(synthetic.get_config(), workdir)
  assert not odd.exists()


def test_a_keep_recorded_by_a_run_that_pruned_nothing_never_deletes_keep_all_checkpoints(
    tmp_path, caplog):
  """Each checkpoint is kept as the run that saved it asked. A run saved with keep=0 (all),
  resumed with keep=5 for fewer saves than would prune (allowed: nothing is deleted), records
  keep=5 in its own checkpoints; a later resume with that keep was allowed too (the latest
  checkpoint's keep), and orbax deleted the keep=0 run's checkpoints at its saves."""
  from train import loop  # pylint: disable=g-import-not-at-top
  c = _config()
  c.checkpoint.async_save, c.checkpoint.keep, c.checkpoint.every_steps = False, 0, 1
  model, mesh = ToyStereo(), state_lib.make_mesh()
  tx = optim.make_optimizer(c.optimizer, c.train.num_steps)
  it = _toy_iterator()
  folder = tmp_path / "checkpoints"
  steps = lambda: sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit())  # noqa: E731

  def run(keep, num_steps):  # a run (or resume) of `keep`, saving each step to `num_steps`
    c.checkpoint.keep, c.train.num_steps = keep, num_steps
    manager = ckpt_lib.make_manager(tmp_path, c)
    state, _, _ = loop.initial_state(c, model, tx, mesh, manager, it)
    for step in range(int(state.step) + 1, num_steps + 1):
      ckpt_lib.save(manager, state.replace(step=jnp.asarray(step, jnp.int32)), it, step,
                    force=True, run_config=c)
    manager.wait_until_finished()
    manager.close()

  run(0, 1)  # the user's run: keep every checkpoint
  with pytest.raises(sav_jax.convert.CheckpointError,  # (one checkpoint, the latest: named)
                     match=r"holds 1 checkpoint; this run's config.checkpoint.keep=3 would "
                     r"delete \[1\] \(saved with config.checkpoint.keep=0\) by the last of "
                     r"the 3 checkpoints it saves up to step 4\. Pass "
                     r"--config.checkpoint.keep=0 to keep them"):
    run(3, 4)  # resumed without it, at the default keep
  run(0, 2)
  assert steps() == [1, 2]
  run(5, 4)  # resumed with keep=5, two saves: the folder holds 4, nothing is deleted
  assert steps() == [1, 2, 3, 4]
  with pytest.raises(sav_jax.convert.CheckpointError,
                     match=r"holds 4 checkpoints; this run's config.checkpoint.keep=5 would "
                     r"delete \[1, 2\] \(saved with config.checkpoint.keep=0\) by the last of "
                     r"the 3 checkpoints it saves up to step 7\. Pass "
                     r"--config.checkpoint.keep=0 to keep them"):
    run(5, 7)  # the same keep=5 again, with saves that prune: steps 1 and 2 would go
  assert steps() == [1, 2, 3, 4]
  run(5, 5)  # one save: the folder then holds 5, all kept
  assert steps() == [1, 2, 3, 4, 5]
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"would delete \[1\] \(saved with "
                     r"config.checkpoint.keep=0\) by the last of the 4 checkpoints"):
    run(8, 9)  # a larger keep than the latest checkpoint's does not delete them either
  # Checkpoints of a pruning policy go as that policy (or a larger keep) has them go: a
  # resume with keep=5 after the keep=0 ones were moved out deletes step 3 (saved with 5).
  for step in (1, 2):
    shutil.move(folder / str(step), tmp_path / str(step))
  run(5, 8)
  assert steps() == [4, 5, 6, 7, 8]
  run(0, 9)  # keep=0 resumes whatever the folder holds
  assert steps() == [4, 5, 6, 7, 8, 9]
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"would delete \[4, 5, 6, 7\] \(saved "
                     r"with config.checkpoint.keep=5\) at its first save. Pass "
                     r"--config.checkpoint.keep=5 \(the largest keep they were saved with: each "
                     r"is then deleted only as its own keep deletes it\), or 0 to keep them all, "
                     r"or move"):
    run(3, 10)  # a smaller keep than theirs
  assert steps() == [4, 5, 6, 7, 8, 9]
  run(5, 10)  # theirs: steps 4, 5 go (not "kept"), as keep=5 has them go; step 9 (keep=0) stays
  assert steps() == [6, 7, 8, 9, 10]
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"would delete \[6, 7, 8, 9\] \(steps "
                     r"6, 7, 8 saved with config.checkpoint.keep=5, step 9 with "
                     r"config.checkpoint.keep=0\) by the last of the 4 checkpoints it saves up "
                     r"to step 14. Pass --config.checkpoint.keep=0"):
    run(5, 14)
  assert steps() == [6, 7, 8, 9, 10]
  # A checkpoint whose config (its keep) cannot be read is kept, and named
  (folder / "6" / "config" / "metadata").write_text("{\"model\": {", encoding="utf-8")
  with pytest.raises(sav_jax.convert.CheckpointError, match=r"would delete \[6\] \(saved with a "
                     r"config whose keep cannot be read\) at its first save. Pass "
                     r"--config.checkpoint.keep=0"):
    run(5, 11)
  assert steps() == [6, 7, 8, 9, 10]
  # Lowering the keep on purpose: the checkpoint resumed from is among those a smaller keep
  # deletes, so no move helps; checkpoint.prune_earlier lets it, naming what goes
  c.checkpoint.prune_earlier = True
  with caplog.at_level(logging.WARNING, logger="train.checkpoint"):
    run(2, 12)
  assert steps() == [11, 12]
  assert re.search(r"prune_earlier: this run's config.checkpoint.keep=2 will delete "
                   r"\[6, 7, 8, 9, 10\] \(.*step 9 .*keep=0.*\) by the last of the 2 "
                   r"checkpoints it saves up to step 12", caplog.text), caplog.text


def test_one_cycle_refuses_a_warm_up_ending_at_step_0_or_at_the_cycles_end():
  # PyTorch's linear OneCycleLR divides by the warm-up's length (pct_start * total - 1): at
  # 0 its first rate is 0 / 0 (here NaN); a warm-up ending at total - 1 leaves no decay.
  with pytest.raises(ValueError, match="degenerate one-cycle schedule"):
    optim.one_cycle_linear(1e-4, 100, 0.01)  # 0.01 * 100 - 1 = 0
  with pytest.raises(ValueError, match="degenerate one-cycle schedule"):
    optim.one_cycle_linear(1e-4, 100, 1.0)  # ends at 99 = total - 1
  assert np.isfinite(float(optim.one_cycle_linear(1e-4, 201, 0.01)(0)))  # ends at 1.01

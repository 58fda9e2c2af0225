"""The training program, in big_vision's order.

  1. (multi-host) `jax.distributed.initialize` -- done by `train.__main__`,
  2. mesh over all devices with a `data` axis,
  3. input pipeline (each process reads its shard, batches become global arrays),
  4. parameter and optimizer shapes with `jax.eval_shape`,
  5. shardings (state replicated, batch on `data`),
  6. state created directly sharded with `jax.jit(init, out_shardings=...)`,
  7. the jitted update with `donate_argnums=(0,)`,
  8. resume: checkpoint in the workdir > converted init weights > scratch,
  9. the loop: log, validate, checkpoint; `wait_until_finished()` at exit.
"""

from __future__ import annotations

import logging
import pathlib

import flax
import jax
import numpy as np

import sav_jax
from sav_jax.data import pipeline
from train import checkpoint as ckpt_lib
from train import evaluation, input as input_lib, optim, state as state_lib, step as step_lib
from train.logging_utils import MetricWriter, Progress

log = logging.getLogger(__name__)


def _merge_vda(params, vda):
  flat = flax.traverse_util.flatten_dict(params)
  flat.update({ckpt_lib.VDA_PATH + k: v for k, v in flax.traverse_util.flatten_dict(vda).items()})
  return flax.traverse_util.unflatten_dict(flat)


def initial_state(config, model, tx, mesh, manager, data_iterator):
  """Resume order: latest checkpoint > `init_from`/`vda_weights` > random init.

  Returns:
    `(state, shardings, source)` with source "checkpoint", "weights" or "scratch".
  """
  init = state_lib.make_init_fn(model, tx, config)
  abstract = jax.eval_shape(init)
  shardings = state_lib.state_shardings(abstract, mesh)
  if manager.latest_step() is not None:
    log.info("resuming from checkpoint %d", manager.latest_step())
    return ckpt_lib.restore(manager, abstract, shardings, data_iterator), shardings, "checkpoint"
  cfg = state_lib.model_config(config)
  vda = ckpt_lib.load_vda_params(config.vda_weights) if config.vda_weights else None
  if config.init_from:
    host = ckpt_lib.load_model_params(config.init_from, cfg)
    host = _merge_vda(host, vda) if vda is not None else host
    params = state_lib.place_params(host, abstract.params, mesh)
    state, _ = state_lib.create_train_state(model, tx, config, mesh, params=params)
    return state, shardings, "weights"
  state, _ = state_lib.create_train_state(model, tx, config, mesh)
  if vda is not None:
    vda_abstract = abstract.params
    for k in ckpt_lib.VDA_PATH:
      vda_abstract = vda_abstract[k]
    placed = state_lib.place_params(vda, vda_abstract, mesh)
    state = state.replace(params=_merge_vda(state.params, placed))
    return state, shardings, "weights"
  return state, shardings, "scratch"


class _Window:
  """Host-side running mean of the train metrics between two log steps."""

  def __init__(self):
    self.sums, self.n = {}, 0

  def add(self, metrics):
    for k, v in metrics.items():
      self.sums[k] = self.sums.get(k, 0.0) + float(v)
    self.n += 1

  def pop(self, last):
    out = {k: v / max(self.n, 1) for k, v in self.sums.items()}
    out["num_skipped"] = float(last["num_skipped"])  # a counter, not a mean
    self.sums, self.n = {}, 0
    return out


def run(config, workdir) -> state_lib.TrainState:
  """Trains `config` in `workdir` (created if needed) and returns the final state."""
  workdir = pathlib.Path(workdir)
  is_main = jax.process_index() == 0
  mesh = state_lib.make_mesh()
  if config.train.batch_size % mesh.size:
    raise ValueError(f"train.batch_size={config.train.batch_size} is not divisible by the "
                     f"{mesh.size} devices")
  log.info("mesh %s over %d devices, %d processes", dict(mesh.shape), mesh.size,
           jax.process_count())
  grain_it = iter(input_lib.train_dataset(config))
  batches = pipeline.GlobalBatchIterator(grain_it, state_lib.data_sharding(mesh))

  model = sav_jax.StereoAnyVideo(state_lib.model_config(config))
  abstract_params = state_lib.abstract_params(model, config)
  labels = optim.param_labels(abstract_params, config.optimizer.frozen)
  log.info("parameters: %s", state_lib.param_count(abstract_params, labels))
  tx = optim.make_optimizer(config.optimizer, config.train.num_steps, abstract_params)
  manager = ckpt_lib.make_manager(workdir, config)
  state, shardings, source = initial_state(config, model, tx, mesh, manager, grain_it)
  train_step = step_lib.jit_train_step(step_lib.make_train_step(model, tx, config, labels),
                                       shardings, mesh)
  evaluator = evaluation.Evaluator(config, model, shardings.params, mesh) \
      if config.eval.every_steps > 0 else None

  start = int(jax.device_get(state.step))
  total = config.train.num_steps
  log.info("start at step %d of %d (state from %s)", start, total, source)
  writer = MetricWriter(workdir, enabled=is_main)
  progress = Progress(start, total, enabled=config.train.progress_bar)
  window, pending, last = _Window(), None, None
  skipped_seen = int(jax.device_get(state.num_skipped))
  if evaluator is not None and start == 0 and config.eval.at_start:
    writer.write(0, evaluator(state.params), split="val")

  def flush(entry):
    nonlocal skipped_seen, last
    step, metrics = entry
    last = jax.device_get(metrics)
    window.add(last)
    progress.update(1, loss=last["loss"], epe=last["epe"])
    if int(last["num_skipped"]) > skipped_seen:
      skipped_seen = int(last["num_skipped"])
      log.warning("step %d: non-finite loss or gradient, update skipped (%d so far)", step,
                  skipped_seen)
      if skipped_seen > config.train.max_skipped_steps:
        raise FloatingPointError(f"{skipped_seen} skipped updates > train.max_skipped_steps")
    if step % config.train.log_every == 0 or step == total:
      writer.write(step, window.pop(last))

  for step in range(start + 1, total + 1):
    with jax.profiler.StepTraceAnnotation("train", step_num=step):
      state, metrics = train_step(state, next(batches))
    if pending is not None:
      flush(pending)  # one step late, so host work overlaps the device
    pending = (step, metrics)
    save_now = step % config.checkpoint.every_steps == 0 or step == total
    eval_now = evaluator is not None and (step % config.eval.every_steps == 0 or step == total)
    if save_now or eval_now:
      flush(pending)
      pending = None
    if save_now:
      finite = bool(np.isfinite(last["l2_params"]))
      ckpt_lib.save(manager, state, grain_it, step, params_finite=finite, force=True)
    if eval_now:
      writer.write(step, evaluator(state.params), split="val")
  if pending is not None:
    flush(pending)
  manager.wait_until_finished()
  manager.close()
  progress.close()
  writer.close()
  return state

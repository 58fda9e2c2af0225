"""Checkpoints of a run (orbax `CheckpointManager`) and initial weights.

A checkpoint `workdir/checkpoints/<step>/` holds three items:
  state:  `{"params", "opt_state", "step", "rng", "num_skipped"}` (`StandardSave`),
  data:   the grain iterator state of every process (`grain.checkpoint.CheckpointSave`,
          one JSON file per process),
  config: `{"model": SAVConfig dict, "step": step}` (`JsonSave`), so that
          `sav-jax infer`/`convert`, `python -m eval` and `init_from` can use the step
          folder (or the workdir: its latest step) as model weights.
Orbax writes into a temporary directory and renames it when complete, so a run killed
mid-save leaves no checkpoint under a final name; such leftovers are cleaned up at start.

Resume order (`initial_state` in `train.loop`): the latest checkpoint in the workdir,
else converted init weights (`init_from`: `.pth/.pt/.npz/.safetensors` in the official
layout, an orbax directory from `sav_jax.convert.save_variables`, or another run's
workdir / checkpoint step folder; `vda_weights`: a
Video Depth Anything file for the frozen prior), else random initialisation.
"""

from __future__ import annotations

import logging
import pathlib

import grain
import jax
import numpy as np
import orbax.checkpoint as ocp

import sav_jax
from train.state import TrainState

log = logging.getLogger(__name__)

VDA_PATH = ("depthnet", "depthanything")


def make_manager(workdir, config) -> ocp.CheckpointManager:
  """A manager keeping the last `checkpoint.keep` checkpoints (0 = all)."""
  ck = config.checkpoint
  options = ocp.CheckpointManagerOptions(
      max_to_keep=ck.keep if ck.keep > 0 else None, create=True,
      enable_async_checkpointing=ck.async_save, cleanup_tmp_directories=True)
  return ocp.CheckpointManager(pathlib.Path(workdir).absolute() / "checkpoints",
                               item_names=("state", "data", "config"), options=options)


def _state_dict(state: TrainState) -> dict:
  return {"step": state.step, "params": state.params, "opt_state": state.opt_state,
          "rng": state.rng, "num_skipped": state.num_skipped}


def save(manager: ocp.CheckpointManager, state: TrainState, data_iterator, step: int,
         params_finite: bool = True, force: bool = False,
         model_config: sav_jax.SAVConfig | None = None) -> bool:
  """Saves state, data-iterator state and the model config at `step`.

  Args:
    manager: checkpoint manager of the run.
    state: the train state after `step` steps.
    data_iterator: the grain iterator positioned after those `step` batches.
    step: checkpoint number.
    params_finite: the caller's knowledge that the params are finite (the train step
      only applies finite updates and reports `l2_params`); False refuses to save.
    force: save even if `step` is not on the manager's save interval.
    model_config: the model's config (default: `SAVConfig()`), for readers of the weights.

  Returns:
    Whether a save was started.
  """
  if not params_finite:
    log.error("step %d: non-finite parameters; NOT saving a checkpoint", step)
    return False
  config = {"model": (model_config or sav_jax.SAVConfig()).to_dict(), "step": int(step)}
  args = ocp.args.Composite(state=ocp.args.StandardSave(_state_dict(state)),
                            data=grain.checkpoint.CheckpointSave(data_iterator),
                            config=ocp.args.JsonSave(config))
  return manager.save(step, args=args, force=force)


def restore(manager: ocp.CheckpointManager, abstract_state: TrainState, shardings: TrainState,
            data_iterator, step: int | None = None) -> TrainState:
  """Restores the state (with its shardings) and the data iterator in place.

  Args:
    manager: checkpoint manager of the run.
    abstract_state: `jax.eval_shape` of the state (structure, shapes, dtypes).
    shardings: the state's shardings.
    data_iterator: grain iterator whose state is overwritten.
    step: checkpoint step (default: latest).
  """
  step = manager.latest_step() if step is None else step
  target = jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                        _state_dict(abstract_state), _state_dict(shardings))
  args = ocp.args.Composite(state=ocp.args.StandardRestore(target),
                            data=grain.checkpoint.CheckpointRestore(data_iterator))
  try:
    restored = manager.restore(step, args=args)["state"]
  except (ValueError, KeyError, TypeError) as e:  # orbax: tree structures or shapes differ
    first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    raise sav_jax.convert.CheckpointError(
        f"{manager.directory / str(step)}: cannot resume from this checkpoint: it does not match "
        f"this run's model or optimizer config ({type(e).__name__}: {first[:300]}). Resume "
        "with the config it was written with, or start a new WORKDIR with "
        "--config.init_from=<that workdir> to keep only its weights") from e
  return TrainState(**restored)


def load_model_params(path, cfg: sav_jax.SAVConfig, abstract_params) -> dict:
  """Host params (the `params` collection only) from full-model weights.

  Args:
    path: official `.pth/.pt/.npz/.safetensors` weights, an orbax directory written by
      `sav_jax.convert.save_variables`, or another run's checkpoint (its step folder, or its
      workdir for the latest step; only the params are read).
    cfg: the model config.
    abstract_params: `jax.eval_shape` of the params; on several hosts an orbax directory
      (then holding exactly `{"params": ...}`) is restored into it on each process's
      first local device.

  Returns:
    Nested dict of numpy arrays; `torch_unused` and other collections are dropped.
  """
  path = pathlib.Path(path)
  if path.is_dir() and jax.process_count() == 1:  # any collections (e.g. torch_unused)
    variables, _ = sav_jax.convert.restore_variables(path)
    variables = jax.device_get(variables)
  elif path.is_dir():  # the default target would name another host's device
    local = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    target = {"params": jax.tree.map(
        lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=local), abstract_params)}
    variables, _ = sav_jax.convert.restore_variables(path, target)
    variables = jax.device_get(variables)
  else:
    variables = _convert(path, "sav", "init_from",
                         lambda sd: sav_jax.convert.params_from_state_dict(sd, cfg))
  log.info("initial weights from %s", path)
  return dict(variables["params"])


def load_vda_params(path) -> dict:
  """Host params of the frozen prior (to go under `params/depthnet/depthanything`)."""
  params, unused = _convert(path, "vda", "vda_weights", sav_jax.convert.vda_params_from_state_dict)
  log.info("frozen depth prior from %s (%d unused keys)", path, len(unused))
  return jax.tree.map(np.asarray, params)


_FIELDS = {"sav": "init_from", "vda": "vda_weights"}


def _convert(path, want: str, field: str, fn):
  """`fn(state dict)` of the file at `path`, which must be of kind `want` ("sav"/"vda");
  errors name the file, the config field and, for the other kind, the field it is for."""
  sd = sav_jax.convert.load_state_dict_of_kind(
      path, want, {k: f"give it as config.{f}" for k, f in _FIELDS.items()},
      label=f"config.{field}={path}")
  try:
    return fn(sd)
  except ValueError as e:
    raise sav_jax.convert.CheckpointError(f"config.{field}={path}: {e}") from e

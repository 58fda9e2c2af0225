"""The training program, in big_vision's order.

  1. (multi-host) `jax.distributed.initialize` -- done by `train.__main__`,
  2. mesh over all devices with a `data` axis,
  3. input pipeline (each process reads its shard, batches become global arrays),
  4. parameter and optimizer shapes with `jax.eval_shape`,
  5. shardings (state replicated, batch on `data`),
  6. state created directly sharded with `jax.jit(init, out_shardings=...)`,
  7. the jitted update with `donate_argnums=(0,)`,
  8. resume: checkpoint in the workdir > converted init weights > scratch,
  9. the loop: log, validate, checkpoint; on SIGTERM (or a multi-host preemption notice)
     a checkpoint of the current step, then stop; `wait_until_finished()` at any exit.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import pathlib
import re
import signal
import threading
import time

import flax
import jax
from jax.experimental import multihost_utils
import ml_collections
import numpy as np

import sav_jax
from sav_jax import _signals, runtime
from sav_jax._checks import check_utf8_path, plural, within_int64
from sav_jax._locks import FolderBusyError, FolderLock
from sav_jax.convert import keys as keys_lib, params as convert_params
from sav_jax.data import pipeline
from sav_jax.model.dpt_temporal import TEMPORAL_MAX_LEN
from sav_jax.model.init import init_variables
from sav_jax.model.stereo_any_video import check_iters
from train import checkpoint as ckpt_lib
from train import evaluation, input as input_lib, loss as loss_lib, optim
from train import state as state_lib, step as step_lib
from train.logging_utils import MetricWriter, Progress

log = logging.getLogger(__name__)


def _vda_part(params):
  """The frozen depth prior's subtree of a model's params (or of their abstract shapes)."""
  for k in ckpt_lib.VDA_PATH:
    params = params[k]
  return params


def _merge_vda(params, vda):
  flat = flax.traverse_util.flatten_dict(params)
  flat.update({ckpt_lib.VDA_PATH + k: v for k, v in flax.traverse_util.flatten_dict(vda).items()})
  return flax.traverse_util.unflatten_dict(flat)


def initial_weights(config, abstract_params, saved: dict | None = None):
  """`(params, vda params)` on the host from `init_from` and `vda_weights` (None where unset);
  `saved`: a dict to fill with the config saved beside `init_from`'s weights.

  Raises:
    CheckpointError or FileNotFoundError: naming the field and the file.
    ValueError: naming the field and the file, when its params do not fit the model.
  """
  cfg = state_lib.model_config(config)
  # Conversion is host work that may touch the default device (e.g. eager shape probes).
  with jax.transfer_guard("allow"):
    vda = ckpt_lib.load_vda_params(config.vda_weights, cfg) if config.vda_weights else None
    host = (ckpt_lib.load_model_params(config.init_from, cfg, saved)
            if config.init_from else None)
  # Checked here, before the workdir is created.
  if host is not None:
    token = flax.traverse_util.flatten_dict(host).get(ckpt_lib.VDA_PATH + ("pretrained",
                                                                          "cls_token"))
    found = convert_params.encoder_of_width(np.shape(token)[-1:])
    if found is not None and found != cfg.vda_encoder:  # else hundreds of shape problems
      raise ValueError(f"config.init_from={config.init_from}: its depth prior is {found} "
                       f"(DINOv2 width {np.shape(token)[-1]}); this run's model is configured "
                       f"for {cfg.vda_encoder}: pass --config.model.vda_encoder={found}")
    state_lib.check_params(host, abstract_params, f"config.init_from={config.init_from}: its "
                           "params")
    # An orbax folder's arrays are not checked on the way as an official file's are: a NaN
    # made every step a skipped one, an integer array was cast to float without a word.
    bad = [problem for key, x in flax.traverse_util.flatten_dict(host, sep="/").items()
           if (problem := keys_lib.value_problem(key, x))]
    if bad:
      raise ValueError(f"config.init_from={config.init_from}: its params cannot start a run "
                       f"({len(bad)} problems): {'; '.join(bad[:10])}"
                       + (f" (and {len(bad) - 10} more)" if len(bad) > 10 else ""))
  if vda is not None:
    state_lib.check_params(vda, _vda_part(abstract_params),
                           f"config.vda_weights={config.vda_weights}: its params")
  return host, vda


def initial_state(config, model, tx, mesh, manager, data_iterator, abstract_params=None,
                  weights=None, data_clips=None, resumed: dict | None = None):
  """Resume order: latest checkpoint > `init_from`/`vda_weights` > the official init.

  From scratch, a `StereoAnyVideo` starts from `init_variables(cfg, config.seed)` (PyTorch's
  default initialisation, as the official run; identical on every host); other models (tests'
  stand-ins) from their Flax initialisers.

  Args:
    config, model, tx, mesh: the run's config, model, optimizer and mesh.
    manager: its checkpoint manager.
    data_iterator: grain iterator, restored in place from a checkpoint.
    abstract_params: `state.abstract_params(model, config)` if already computed.
    weights: `initial_weights(config, ...)` if already loaded (not used on resume).
    data_clips: this run's training clips (`input.train_dataset`'s `clips`): a resume whose
      clips differ from the checkpoint's is warned about.
    resumed: a dict to fill with the config saved with the checkpoint a resume restores
      (`ckpt_lib.saved_config`: read once).

  Returns:
    `(state, shardings, source)` with source "checkpoint", "weights" or "scratch".
  """
  if abstract_params is None:
    abstract_params = state_lib.abstract_params(model, config)
  abstract = state_lib.abstract_state(model, tx, config, abstract_params)
  shardings = state_lib.state_shardings(abstract, mesh)
  if manager.latest_step() is not None:
    step = manager.latest_step()
    log.info("resuming from checkpoint %d", step)
    stored = ckpt_lib.saved_config(manager, step)  # read once ({} for older checkpoints)
    if resumed is not None:
      resumed.update(stored)
    saved = ckpt_lib.saved_entry(stored, "run")
    ckpt_lib.check_data_state(manager, step, config, saved)
    ckpt_lib.check_keep(manager, config, saved)
    changed = ckpt_lib.changed_fields(manager, step, config, saved)
    for field in ("init_from", "vda_weights"):  # never read on resume: say so if new
      if config[field] and saved and config[field] != saved.get(field):
        log.warning("config.%s=%s is not used: this run resumes from checkpoint %d in %s "
                    "(a workdir's own checkpoints come first); to start from %s, use a new "
                    "--workdir", field, config[field], step, manager.directory, config[field])
    try:
      state = ckpt_lib.restore(manager, abstract, shardings, data_iterator)
    except sav_jax.convert.CheckpointError as e:
      if not changed or "does not match this run's" not in str(e):
        raise
      raise sav_jax.convert.CheckpointError(
          f"{e}. The config fields this run changes since that checkpoint: "
          f"{'; '.join(changed)}") from None
    clips = input_lib.changed_clips(ckpt_lib.saved_entry(stored, "data_clips"),
                                    data_clips or {})
    if data_clips is not None and clips:
      log.warning("the training clips changed since checkpoint %d (%s): the restored position "
                  "in the data applies to another list of clips, so the rest of this epoch is "
                  "not what the interrupted run would have read (some clips come twice, some "
                  "not at all)", step, "; ".join(clips))
    if changed:  # allowed (e.g. to extend a run), but never unnoticed
      log.warning("resuming with %s changed since checkpoint %d: %s",
                  plural(len(changed), "config field"), step, "; ".join(changed))
      with jax.transfer_guard("allow"):  # one scalar, to the host
        updates = step - int(jax.device_get(state.num_skipped))
      note = optim.schedule_change_note(config.optimizer, config.train.num_steps, step,
                                        saved, updates)
      if note:
        log.warning("%s", note)
    return state, shardings, "checkpoint"
  cfg = state_lib.model_config(config)
  host, vda = weights if weights is not None else initial_weights(config, abstract.params)
  source = "weights"
  if host is None and isinstance(model, sav_jax.StereoAnyVideo):
    # The official initialisation (PyTorch's defaults), the same on every host.
    host, source = init_variables(cfg, config.seed)["params"], "scratch"
  if host is not None:
    host = _merge_vda(host, vda) if vda is not None else host
    params = state_lib.place_params(host, abstract.params, mesh)
    state, _ = state_lib.create_train_state(model, tx, config, mesh, params, shardings)
    return state, shardings, source if vda is None else "weights"
  state, _ = state_lib.create_train_state(model, tx, config, mesh, shardings=shardings)
  if vda is not None:
    placed = state_lib.place_params(vda, _vda_part(abstract.params), mesh)
    state = state.replace(params=_merge_vda(state.params, placed))
    return state, shardings, "weights"
  return state, shardings, "scratch"


class _HostMetrics:
  """Fetches step metrics (one step late), updates the bar, warns on skips, logs means."""

  def __init__(self, config, writer: MetricWriter, progress: Progress, skipped: int):
    self.config, self.writer, self.progress = config, writer, progress
    self.skipped = skipped
    self.sums, self.n, self.n_finite, self.last, self.measured = {}, 0, 0, None, 0.0
    self.window_start = time.perf_counter()
    self.first_done = None  # when the first step's metrics came: its time holds the compile

  def __call__(self, step: int, metrics, last_step: bool = False) -> None:
    """Takes `step`'s metrics; writes the window's means at the end of a logging period, at
    `train.num_steps`, and at `last_step` (a run that stops there with a checkpoint: its
    steps since the last record would never be logged, as the resumed run starts after it)."""
    last = self.last = jax.device_get(metrics)
    first_window = self.first_done is None or self.first_done >= self.window_start
    if self.first_done is None:
      self.first_done = time.perf_counter()
    # A skipped step's loss, EPE and norms are NaN or inf: the window's means are over its
    # finite steps only (a window of skipped steps only logs NaN), its rate and the
    # counter over all of them.
    finite = bool(last["finite"]) if "finite" in last else bool(np.isfinite(last["loss"]))
    # The accuracy metrics are means over a step's measured frames: weighted by their share,
    # so that a step without any (sparse ground truth outside the crops) adds nothing.
    weight = float(last.get("measured_frames", 1.0))
    for k, v in last.items():
      if finite or k in _OVER_ALL_STEPS:
        w = weight if k in _OVER_MEASURED else 1.0
        self.sums[k] = self.sums.get(k, 0.0) + w * float(v)
    self.n += 1
    self.n_finite += finite
    self.measured += weight if finite else 0.0
    self.progress.update(1, loss=last["loss"], epe=last["epe"])
    if int(last["num_skipped"]) > self.skipped:
      self.skipped = int(last["num_skipped"])
      bad = [name for k, name in (("loss", "loss"), ("l2_grads", "gradient norm"),
                                  ("l2_updates", "update norm"))
             if k in last and not np.isfinite(last[k])]
      if bad == ["update norm"]:  # finite loss and gradients: the step itself overflowed
        bad = ["update norm (finite loss and gradients: is the learning rate too large?)"]
      log.warning("step %d: non-finite %s, update skipped (%d so far)", step,
                  " and ".join(bad) or "loss or gradient", self.skipped)
      if self.skipped > self.config.train.max_skipped_steps:
        raise Diverged(
            f"step {step}: {self.skipped} updates skipped for a non-finite loss or gradient, "
            f"more than config.train.max_skipped_steps={self.config.train.max_skipped_steps}: "
            "the run diverged (a lower --config.optimizer.lr? the checkpoints saved since the "
            "skips began hold the weights that diverged)")
    if (_every(step, self.config.train.log_every) or step == self.config.train.num_steps
        or last_step):
      means = {k: (v / self.n if k in _OVER_ALL_STEPS else
                   v / self.measured if k in _OVER_MEASURED and self.measured > 0 else
                   v / max(self.n_finite, 1))
               for k, v in self.sums.items()}
      means.update({k: float("nan") for k in last if k not in means})  # no finite step
      means["num_skipped"] = float(last["num_skipped"])  # a counter, not a mean
      # The steps the means are over: log_every, but fewer in the window that ends at a
      # stop off the logging period (a SIGTERM save) and in the first one after it.
      means["window_steps"] = float(self.n)
      if "lr" in last:
        means["lr"] = float(last["lr"])  # the rate of its last step (a mean was never used)
      self.writer.write(step, means)
      if not self.progress.shown and jax.process_index() == 0:  # else the bar's
        # (the first record's rate leaves out the first step, whose time holds the compile)
        start, n = (self.first_done, self.n - 1) if first_window else (self.window_start, self.n)
        rate = n / max(time.perf_counter() - start, 1e-9)
        shown = ", ".join(f"{k} {means[k]:.4g}" for k in ("loss", "epe", "1px", "lr")
                          if k in means)
        left = max(int(self.config.train.num_steps) - step, 0)
        if n == 0:  # only the first step: no rate yet
          took = _duration(self.first_done - self.window_start)
          log.info("step %d: %s (the first step, with the compile: %s)", step, shown, took)
        else:
          log.info("step %d: %s (%.3g steps/s%s)", step, shown, rate,
                   f", {_duration(left / rate)} to step {self.config.train.num_steps}"
                   if left else "")
      self.sums, self.n, self.n_finite, self.measured = {}, 0, 0, 0.0
      self.window_start = time.perf_counter()


def _duration(seconds: float) -> str:
  """`1 h 05 min`, `12 min`, `40 s`: an estimated time left."""
  seconds = int(round(seconds))
  if seconds < 60:
    return f"{seconds} s"
  hours, minutes = divmod(seconds // 60, 60)
  return f"{hours} h {minutes:02d} min" if hours else f"{minutes} min"


# Step metrics averaged over every step of a logging window (the others: over its finite steps).
_OVER_ALL_STEPS = ("finite", "num_skipped")
# Step metrics averaged over a window's measured frames (`train.loss.sequence_loss`).
_OVER_MEASURED = loss_lib.MEASURED_METRICS


def _every(step: int, period: int) -> bool:
  """Whether `step` is on a period of `period` steps (never for period <= 0)."""
  return period > 0 and step % period == 0


def _is_int(x) -> bool:
  """A Python int (not a bool) within 64 bits (`within_int64`)."""
  return isinstance(x, int) and not isinstance(x, bool) and within_int64(x)


def _is_iters(x) -> bool:
  """An `iters` the model takes (`check_iters`), given as a Python int."""
  try:
    check_iters(x)
  except ValueError:
    return False
  return _is_int(x)


def _is_real(x) -> bool:
  return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _is_crop(x) -> bool:
  return (isinstance(x, (tuple, list)) and len(x) == 2
          and all(_is_int(v) and v > 0 and v % 16 == 0 for v in x) and x[1] >= 32)


def _is_regex(x) -> bool:
  try:
    re.compile(x)
  except (re.error, TypeError):
    return False
  return isinstance(x, str)


# (field, test, what it must be): the values a run cannot use, found before anything is
# created in the workdir or compiled (later they fail deep inside grain, optax or a trace).
_CHECKS = (
    ("seed", lambda x: _is_int(x) and 0 <= x < 2**32, "an integer in [0, 2**32)"),
    ("compile_cache", lambda x: isinstance(x, str), "a folder, 'default' or '' (off)"),
    ("matmul_precision", lambda x: x in runtime.MATMUL_PRECISIONS,
     ", ".join(map(repr, runtime.MATMUL_PRECISIONS[:-1]))
     + f" or {runtime.MATMUL_PRECISIONS[-1]!r}"),
    ("data.frames", lambda x: _is_int(x) and 1 <= x <= TEMPORAL_MAX_LEN,
     f"an integer in [1, {TEMPORAL_MAX_LEN}] (the depth prior's temporal attention takes at "
     f"most {TEMPORAL_MAX_LEN} frames)"),
    ("data.root", lambda x: isinstance(x, str), "a folder"),
    ("data.mixing", lambda x: x in ("concat", "ratio"), "'concat' or 'ratio'"),
    ("data.num_threads", lambda x: _is_int(x) and x >= 0, "an integer >= 0"),
    ("data.prefetch", lambda x: _is_int(x) and x >= 0, "an integer >= 0"),
    ("data.worker_count", lambda x: _is_int(x) and x >= 0, "an integer >= 0 (0: threads only)"),
    ("data.skip_unreadable", lambda x: _is_int(x) and x >= 0,
     "an integer >= 0 (0: an unreadable clip stops the run)"),
    ("data.synthetic.num_clips", lambda x: _is_int(x) and x >= 1, "an integer >= 1"),
    ("data.crop", _is_crop, "(height, width): two positive multiples of 16 (the model's "
     "coarsest scale is 1/16), the width at least 32 (a 1-pixel-wide 1/16 map has no "
     "official reference)"),
    ("train.batch_size", lambda x: _is_int(x) and x >= 1, "an integer >= 1"),
    ("train.num_steps", lambda x: _is_int(x) and x >= 1, "an integer >= 1"),
    ("train.iters", _is_iters,
     "an integer >= 2 (the 1/16 and 1/8 stages run iters//2 >= 1 steps each)"),
    ("train.max_skipped_steps", lambda x: _is_int(x) and x >= 0, "an integer >= 0"),
    ("optimizer.lr", lambda x: _is_real(x) and x > 0, "a number > 0"),
    ("optimizer.weight_decay", lambda x: _is_real(x) and x >= 0, "a number >= 0"),
    ("optimizer.eps", lambda x: _is_real(x) and x > 0, "a number > 0"),
    ("optimizer.b1", lambda x: _is_real(x) and 0 <= x < 1, "a number in [0, 1)"),
    ("optimizer.b2", lambda x: _is_real(x) and 0 <= x < 1, "a number in [0, 1)"),
    ("optimizer.clip_norm", lambda x: _is_real(x) and x >= 0, "a number >= 0 (0 disables)"),
    ("optimizer.schedule", lambda x: x in ("one_cycle", "constant"), "'one_cycle' or 'constant'"),
    ("optimizer.pct_start", lambda x: _is_real(x) and 0 < x < 1, "a number in (0, 1)"),
    ("optimizer.div_factor", lambda x: _is_real(x) and x > 0, "a number > 0"),
    ("optimizer.final_div_factor", lambda x: _is_real(x) and x > 0, "a number > 0"),
    ("optimizer.schedule_steps", _is_int, "an integer (<= 0: train.num_steps + 100)"),
    ("optimizer.frozen", _is_regex,
     "a regular expression matching the depth prior's parameter paths ('depthanything')"),
    ("loss.gamma", lambda x: _is_real(x) and x > 0, "a number > 0"),
    ("loss.max_disparity", lambda x: _is_real(x) and x > 0, "a number > 0"),
    ("checkpoint.every_steps", _is_int, "an integer (<= 0: at the end only)"),
    ("checkpoint.keep", lambda x: _is_int(x) and x >= 0, "an integer >= 0 (0 keeps all)"),
)
_EVAL_CHECKS = (
    ("eval.iters", _is_iters, "an integer >= 2"),
    ("eval.batch_size", lambda x: _is_int(x) and x >= 1, "an integer >= 1"),
    ("eval.num_clips", lambda x: _is_int(x) and x >= 1, "an integer >= 1"),
    ("eval.root", lambda x: isinstance(x, str), "a folder, or '' for config.data.root"),
)


# Blocks whose fields the user names.
_FREE_BLOCKS = ("data.sources",)


# Blocks whose unknown fields their own checks name (the augmentation's, the generator's,
# the model's: SAVConfig.from_dict, which takes the architecture fields the base leaves out,
# `depth_dim`, `hidden_dim`, ...).
_CHECKED_BLOCKS = ("data.augment", "data.synthetic", "model")


def missing_fields(config, base, prefix: str = "", skip: tuple[str, ...] = ()) -> list[str]:
  """The fields of `base` (`configs.sceneflow.base_config()`) that `config` lacks (with the
  two swapped: the fields `config` has that the base lacks), not looking into `skip`."""
  missing = []
  for key, value in base.items():
    path = prefix + key
    if key not in config:
      missing.append(path)
    elif (isinstance(value, ml_collections.ConfigDict) and path not in _FREE_BLOCKS + skip
          and isinstance(config[key], ml_collections.ConfigDict)):
      missing += missing_fields(config[key], value, path + ".", skip)
  return missing


def check_fields(config) -> None:
  """Raises a ValueError naming the fields a training config lacks (a config file written
  from scratch instead of on `configs.sceneflow.base_config()`), before any is read."""
  from configs import lacking_fields, sceneflow  # pylint: disable=import-outside-toplevel
  missing = missing_fields(config, sceneflow.base_config())
  if missing:
    raise ValueError(f"the config {lacking_fields(config, missing)}")
  unknown = missing_fields(sceneflow.base_config(), config, skip=_CHECKED_BLOCKS)
  if unknown:  # (a misspelt field in a config file: nothing would read it)
    raise ValueError(f"the config has no such field {', '.join(unknown[:8])}"
                     f"{', ...' if len(unknown) > 8 else ''} (misspelt? it would not be read): "
                     "the fields are those of configs.sceneflow.base_config()")


def _given_workdir(workdir) -> pathlib.Path:
  """`workdir` as a Path, `~` expanded (the shell leaves it after `--workdir=`: the run made
  a folder named `~` in the current one); "" (an unset, quoted $WORKDIR) is refused:
  Path("") is the current folder, where the run would write."""
  if not str(workdir):
    raise ValueError("--workdir is empty; give the run's folder")
  return pathlib.Path(workdir).expanduser()


def _refuse_workdir_in_data(config, workdir: pathlib.Path) -> None:
  """Raises ValueError where `workdir` is inside the folder of a dataset the run reads (a
  training source's, or the validation's): the run writes `checkpoints/`, `tb/` and
  `metrics.jsonl` there, which its reader may take for data (a run in the `train/` split of
  the "folder" dataset made `checkpoints/` a sequence without `left/`, so that the same
  command could not resume); `python -m eval` refuses its `--out` there alike."""
  from sav_jax.data import registry  # pylint: disable=g-import-not-at-top
  where = workdir.expanduser().resolve()
  used = [(f"config.data.sources.{name}", spec.get("dataset"), input_lib.source_root(config, spec))
          for name, spec in sorted(config.data.sources.items())]
  if config.eval.every_steps > 0:
    root, field = ((config.eval.root, "config.eval.root") if config.eval.get("root") else
                   (config.data.root, "config.data.root"))
    used.append((f"config.eval.dataset ({field})", config.eval.dataset, root))
  for field, dataset, root in used:
    if dataset not in registry.DATASETS:  # synthetic (or an unknown name: said later)
      continue
    for folder in registry.dataset_folders(dataset, root):
      if where.is_relative_to(folder.resolve()):
        raise ValueError(f"--workdir {workdir} is inside {folder}, a folder of the dataset "
                         f"{dataset!r} ({field}): a run writes checkpoints/, tb/ and "
                         "metrics.jsonl there, "
                         "which the dataset's reader would take for data; keep runs out of the "
                         "dataset: choose a folder outside it")


def validate_config(config, workdir, num_devices: int | None = None) -> None:
  """Checks the values of a training config and the workdir before a run creates anything.

  Args:
    config: the training config.
    workdir: the run directory (need not exist).
    num_devices: devices of the mesh, which the batch sizes must be multiples of.

  Raises:
    ValueError: naming `config.<field>`, its value and what it must be; or `workdir`, whose
      path is not UTF-8 text (orbax cannot write checkpoints there).
    NotADirectoryError: `workdir` (or a folder above it, or its `checkpoints`) is a file.
  """
  workdir = _given_workdir(workdir)
  # (orbax's TensorStore takes no other bytes: the first checkpoint save failed, after training)
  check_utf8_path(workdir.absolute(), "--workdir folder")
  for existing in (workdir, *workdir.absolute().parents):  # up to the first that exists
    if existing.exists():
      break
    if existing.is_symlink():  # (mkdir failed: "File exists")
      raise ValueError(f"--workdir {workdir}: {existing} is a symbolic link to a missing "
                       f"folder ({os.readlink(existing)}), or a loop of links")
  for path in (existing, workdir / "checkpoints"):
    if path.exists() and not path.is_dir():
      raise NotADirectoryError(f"--workdir {workdir}: {path} exists and is not a directory")
  from sav_jax.convert import orbax_io  # pylint: disable=g-import-not-at-top
  for is_kind, kind in ((orbax_io.is_variables_checkpoint, "a `sav-jax convert` checkpoint"),
                        (orbax_io.is_training_step, "a training run's checkpoint step")):
    if workdir.is_dir() and is_kind(workdir):  # (a run there nests in it; its path loads these)
      raise ValueError(f"--workdir {workdir} is {kind}, not a run's folder: to start from its "
                       f"weights, pass --config.init_from={workdir} and a new --workdir")
  if (workdir.is_dir() and not (workdir / "checkpoints").exists()
      and any(orbax_io.is_training_step(p) for p in workdir.iterdir() if p.is_dir())):
    # (a new run nested in it, and its last line named this folder: the old run's weights)
    run = workdir.absolute().parent
    raise ValueError(f"--workdir {workdir} is a run's checkpoints folder: to resume that run, "
                     f"pass its folder, --workdir {run}; to start from its weights, "
                     f"--config.init_from={run} and a new --workdir")
  writable = workdir / "checkpoints" if (workdir / "checkpoints").exists() else existing
  if not os.access(writable, os.W_OK | os.X_OK):
    raise PermissionError(f"--workdir {workdir}: no permission to write in {writable}")
  evaluating = config.eval.every_steps > 0
  for field, ok, want in _CHECKS + (_EVAL_CHECKS if evaluating else ()):
    value = _value(config, field)
    if not ok(value):
      shown = repr(value)
      if isinstance(value, int) and len(shown) > 20:  # (1e400: 401 digits)
        shown = f"{shown[:4]}... ({len(shown.lstrip('-'))} digits)"
      raise ValueError(f"config.{field}={shown}: expected {want}")
  _check_blocks(config)
  # (after the checks of the sources and roots it reads: a source that is no block, or a
  # root that is no text, failed in it with an AttributeError or TypeError traceback)
  _refuse_workdir_in_data(config, workdir)
  for field in ("train.batch_size", "eval.batch_size")[:2 if evaluating else 1]:
    if num_devices and _value(config, field) % num_devices:
      raise ValueError(f"config.{field}={_value(config, field)} is not divisible by the "
                       f"{num_devices} devices")
  synthetic_sources = [n for n, spec in config.data.sources.items()
                       if isinstance(spec, ml_collections.ConfigDict)
                       and spec.get("dataset") == "synthetic"]
  if (evaluating and config.eval.dataset == "synthetic" and synthetic_sources
      and config.eval.synthetic_seed == config.data.synthetic.seed):
    raise ValueError(f"config.eval.synthetic_seed={config.eval.synthetic_seed} equals "
                     "config.data.synthetic.seed: validation would score clips the run trains "
                     f"on (source {synthetic_sources[0]}); choose another seed")
  if evaluating and config.eval.dataset == "synthetic" and config.eval.split != "test":
    raise ValueError(f"config.eval.split={config.eval.split!r}: the synthetic held-out set has "
                     "only the split 'test' (its clips come from config.eval.synthetic_seed)")
  microbatches = step_lib.check_microbatches(config)
  if num_devices and (config.train.batch_size // microbatches) % num_devices:
    raise ValueError(f"config.train.microbatches={microbatches}: parts of "
                     f"{config.train.batch_size // microbatches} clips (config.train.batch_size="
                     f"{config.train.batch_size}) are not divisible by the {num_devices} devices")


def _check_blocks(config) -> None:
  """The checks of the model, the sources, the generator, the augmentation and the
  schedule, with their errors naming the config's fields."""
  try:
    state_lib.model_config(config)
  except ValueError as e:  # SAVConfig names the field as `SAVConfig.<name>`
    raise ValueError(str(e).replace("SAVConfig.", "config.model.")) from e
  if not config.data.sources:
    raise ValueError("config.data.sources is empty: name at least one training source, e.g. "
                     "--config.data.sources.NAME=... in the config file (configs/sceneflow.py)")
  for name, spec in config.data.sources.items():
    weight = spec.get("weight") if isinstance(spec, ml_collections.ConfigDict) else None
    if not (_is_real(weight) and weight > 0):
      raise ValueError(f"config.data.sources.{name}.weight={weight!r}: expected a number > 0 "
                       "(leave the source out instead of giving it 0)")
    if not isinstance(spec.get("dataset"), str):  # (a name that is no dataset: named later)
      raise ValueError(f"config.data.sources.{name}.dataset={spec.get('dataset')!r}: expected "
                       "'synthetic' or a dataset name (sav_jax.data.registry.DATASETS)")
    if not isinstance(spec.get("root", ""), str):
      raise ValueError(f"config.data.sources.{name}.root={spec.get('root')!r}: expected a "
                       "folder (the source's own data root; default config.data.root)")
    unknown = sorted(set(spec) - {"dataset", "weight", "root"})
    if unknown:
      raise ValueError(f"config.data.sources.{name} has the unknown field(s) "
                       f"{', '.join(unknown)}; a source has dataset, weight and root")
  datasets = {spec.get("dataset") for spec in config.data.sources.values()}
  if "synthetic" in datasets or (config.eval.every_steps > 0
                                 and config.eval.dataset == "synthetic"):
    try:
      input_lib.synthetic_config(config.data, config.data.synthetic, config.data.synthetic.seed)
    except ValueError as e:  # SyntheticConfig names the field as `SyntheticConfig.<name>`
      where = "" if "synthetic" in datasets else (
          f" (for the validation clips: config.eval.dataset='synthetic' generates them at "
          f"config.data.crop={tuple(config.data.crop)}; or validate on a dataset's split, "
          "--config.eval.dataset=NAME --config.eval.split=SPLIT, or not at all, "
          "--config.eval.every_steps=0)")
      raise ValueError(str(e).replace("SyntheticConfig.", "config.data.synthetic.")
                       + where) from e
  # Real data is augmented (in the grain reader, per clip); synthetic clips are not. The
  # block is checked either way, and changes to it that no source uses are named.
  try:
    augment = pipeline.Augment(tuple(config.data.crop), input_lib.augment_overrides(config))
    applied = augment.augment_config()
  except ValueError as e:  # AugmentConfig names the field as `AugmentConfig.<name>`
    raise ValueError(str(e).replace("AugmentConfig.", "config.data.augment.")) from e
  except TypeError as e:  # a field AugmentConfig does not have
    raise ValueError(f"config.data.augment: {e}") from e
  if "crop_size" in config.data.augment:  # (another crop failed at the first clip read)
    raise ValueError(f"config.data.augment.crop_size={config.data.augment.crop_size}: the "
                     f"crop is config.data.crop's ({tuple(config.data.crop)}); leave it out")
  if not datasets - {"synthetic"}:
    default = dataclasses.replace(type(applied)(), crop_size=applied.crop_size)
    changed = [f.name for f in dataclasses.fields(applied)
               if getattr(applied, f.name) != getattr(default, f.name)]
    if changed:
      log.warning("config.data.augment.%s changed, but no training source is augmented: "
                  "synthetic clips are used as generated (augmentation applies to dataset "
                  "sources)", ", config.data.augment.".join(changed))
  opt = config.optimizer
  try:
    optim.make_schedule(opt, config.train.num_steps)
  except ValueError as e:
    cycle = (f"config.optimizer.schedule_steps={opt.schedule_steps}" if opt.schedule_steps > 0
             else f"config.train.num_steps + 100 = {config.train.num_steps + 100} steps")
    raise ValueError(f"config.optimizer.pct_start={opt.pct_start} with a one-cycle length of "
                     f"{cycle}: {e}") from e


def _value(config, field: str):
  for key in field.split("."):
    config = config[key]
  return config


def setup_compile_cache(config) -> pathlib.Path | None:
  """Turns on JAX's persistent compilation cache as `config.compile_cache` says.

  "default": the folder the user configured for JAX (`JAX_COMPILATION_CACHE_DIR`), else
  `sav_jax.runtime.default_cache_dir()`; "": off (a cache `JAX_COMPILATION_CACHE_DIR` sets too); any
  other value: that folder, created if missing. A resumed run then loads the train and
  validation steps its first run compiled. Returns the folder in use, or None (also when
  the default folder cannot be created: the run goes on without the cache, with a warning).

  Raises:
    ValueError: naming `config.compile_cache`, when the folder it names cannot be used.
  """
  value = config.compile_cache
  if not value:
    runtime.disable_compilation_cache()
    return None
  try:
    return runtime.enable_compilation_cache(None if value == "default" else value)
  except ValueError as e:
    if value == "default":
      log.warning("no compilation cache: %s", e)
      return None
    raise ValueError(f"config.compile_cache={value!r}: {e}") from e


def setup(config, workdir):
  """Steps 2-8 of the module docstring (every check of the config, the workdir and the
  weights happens here, before the first step). Returns a dict of the run's parts for `run`."""
  workdir = _given_workdir(workdir)  # (before Path(): Path("") is ".")
  check_fields(config)
  resume_from = sav_jax.convert.find_training_checkpoint(workdir / "checkpoints")
  if resume_from is not None and int(resume_from.name) > config.train.num_steps:
    raise ValueError(
        f"config.train.num_steps={config.train.num_steps} is below the step of the checkpoint "
        f"this run would resume from ({resume_from}): pass a train.num_steps of at least "
        f"{int(resume_from.name)}, or another --workdir")
  for field in ("init_from", "vda_weights"):  # before anything is created in the workdir
    # (a resumed run never reads them: the files may have moved since its first start)
    if (resume_from is None and config[field]
        and not pathlib.Path(config[field]).expanduser().exists()):
      raise FileNotFoundError(f"config.{field}={config[field]}: no such file or directory")
  if not (config.init_from or config.vda_weights or config.random_depth_prior) and (
      resume_from is None):
    raise ValueError(
        "config.vda_weights and config.init_from are both empty: the frozen depth prior would "
        "stay random for the whole run (the official model always loads Video Depth "
        "Anything). Pass --config.vda_weights=video_depth_anything_vits.pth (or init_from), "
        "or --config.random_depth_prior=true for a toy run")
  mesh = state_lib.make_mesh()
  validate_config(config, workdir, mesh.size)
  log.info("compilation cache: %s", setup_compile_cache(config) or "off")
  log.info("mesh %s over %s, %s", dict(mesh.shape), plural(mesh.size, "device"),
           plural(jax.process_count(), "process", "processes"))
  data_clips = {}
  grain_it = iter(input_lib.train_dataset(config, clips=data_clips))
  # The validation clips, read before the model is traced: data that cannot be used fails
  # within seconds, and before the workdir is created.
  evaluating = config.eval.every_steps > 0
  eval_clips = (evaluation.measured_clips(input_lib.eval_clips(config), config.eval.dataset)
                if evaluating else None)
  model = sav_jax.StereoAnyVideo(state_lib.model_config(config))
  abstract_params = state_lib.abstract_params(model, config)
  labels = optim.param_labels(abstract_params, config.optimizer.frozen)
  optim.check_depth_prior_frozen(labels, config.optimizer.frozen)
  log.info("parameters: %s", state_lib.param_count(abstract_params, labels))
  tx = optim.make_optimizer(config.optimizer, config.train.num_steps)
  log.info("learning rate: %s", optim.schedule_summary(config.optimizer, config.train.num_steps))
  weights, saved = None, {}
  if (config.init_from or config.vda_weights) and resume_from is None:
    # Not resuming: weights that cannot be read fail before the workdir is created.
    weights = initial_weights(config, abstract_params, saved)
    if config.init_from and not config.vda_weights:
      note = sav_jax.convert.random_prior_note(saved, f"config.init_from={config.init_from}")
      if note:
        log.warning("%s; this run keeps it (pass --config.vda_weights to replace it)", note)
  depth_prior = ckpt_lib.depth_prior_origin(config, saved)
  lock = lock_workdir(workdir)
  try:
    manager = ckpt_lib.make_manager(workdir, config)
    resumed = {}
    state, shardings, source = initial_state(config, model, tx, mesh, manager, grain_it,
                                             abstract_params, weights, data_clips, resumed)
    if source == "checkpoint":  # the prior the resumed weights hold, as their first run said
      depth_prior = ckpt_lib.saved_depth_prior(resumed)
    train_step = step_lib.jit_train_step(step_lib.make_train_step(model, tx, config, labels, mesh),
                                         shardings, mesh)
    evaluator = (evaluation.Evaluator(config, model, shardings.params, mesh, eval_clips)
                 if evaluating else None)
  except BaseException:
    lock.release()
    raise
  log.info("start at step %d of %d (state from %s)", int(jax.device_get(state.step)),
           config.train.num_steps, source)
  return dict(grain_it=grain_it, manager=manager, state=state, train_step=train_step, model=model,
              evaluator=evaluator, lock=lock, data_clips=data_clips, depth_prior=depth_prior,
              batches=pipeline.GlobalBatchIterator(grain_it, state_lib.data_sharding(mesh)))


LOCK = ".train.lock"


class _NoLock:
  def release(self) -> None:
    pass


def lock_workdir(workdir: pathlib.Path):
  """Process 0's lock on `workdir` (`WORKDIR/.train.lock`, `sav_jax._locks`), held until
  `run` ends: a second run in the same workdir (a requeued job while the first still runs,
  the command started twice) deleted the first one's save in progress, replaced its log and
  crashed it with an orbax traceback. The other processes of a run share process 0's.

  Raises:
    FileExistsError: another run holds the lock.
  """
  if jax.process_index() != 0:
    return _NoLock()
  workdir.mkdir(parents=True, exist_ok=True)
  try:
    return FolderLock(workdir, LOCK)
  except FolderBusyError as e:
    raise FileExistsError(f"--workdir {workdir} is in use by another training run ({e.holder}): "
                          "wait for it to end, or choose another --workdir") from None


def run(config, workdir, parts: dict | None = None) -> state_lib.TrainState:
  """Trains `config` in `workdir` (created if needed) and returns the final state.

  `parts`: what `setup(config, workdir)` returned, if the caller ran it (else run here).
  The train and validation steps are traced under `config.matmul_precision`.
  """
  with jax.default_matmul_precision(config.matmul_precision):
    return _run(config, workdir, parts)


def _run(config, workdir, parts: dict | None) -> state_lib.TrainState:
  parts = setup(config, workdir) if parts is None else parts
  try:
    return _train(config, pathlib.Path(workdir), parts)
  finally:  # the workdir's lock, however the run ends (exit, preemption, error, Ctrl-C)
    parts.get("lock", _NoLock()).release()


def _train(config, workdir: pathlib.Path, parts: dict) -> state_lib.TrainState:
  state, manager, evaluator = parts["state"], parts["manager"], parts["evaluator"]
  start, total = int(jax.device_get(state.step)), config.train.num_steps
  if start >= total:
    log.warning("the run in %s is complete: its checkpoint is of step %d, "
                "config.train.num_steps=%d; nothing to train (a larger "
                "--config.train.num_steps extends it)", workdir, start, total)
  writer = MetricWriter(workdir, enabled=jax.process_index() == 0, start_step=start)
  progress = Progress(start, total, enabled=config.train.progress_bar)
  host = _HostMetrics(config, writer, progress, int(jax.device_get(state.num_skipped)))
  stop = None
  # Whatever ends the loop (the last step, a preemption, an error, Ctrl-C), a checkpoint
  # already started is finished before the process goes: orbax writes it in a background
  # thread, and a save cut short is deleted at the next start. The SIGTERM handler stays
  # until then (a second notice while the last save is written must not kill it).
  with Preemption(manager) as preemption, _signals.remembered_interrupts():
    try:
      if evaluator is not None and start == 0 and config.eval.at_start:
        _validate(evaluator, state.params, writer, 0)
      elif evaluator is not None and _validation_missing(config, writer, start):
        log.info("validating step %d first: a validation step whose validation is not in the "
                 "log (the run that saved it ended before validating, or validated at other "
                 "steps)", start)
        _validate(evaluator, state.params, writer, start)
      pending = None
      for step in range(start + 1, total + 1):
        _signals.raise_if_interrupted()  # a Ctrl-C that Python dropped (see the function)
        with jax.profiler.StepTraceAnnotation("train", step_num=step):
          state, metrics = parts["train_step"](state, _next_batch(
              parts["batches"], step, manager, config.data.skip_unreadable))
        _signals.raise_if_interrupted()  # a second Ctrl-C (dropped) during the step: no save
        if step == start + 1:  # the step was compiled by this call: free the compiler's memory
          runtime.release_host_memory()
        if pending is not None:
          host(*pending)  # one step late, so that host work overlaps the device
        pending = (step, metrics)
        stop = preemption(step)
        save_now = _every(step, config.checkpoint.every_steps) or step == total or bool(stop)
        eval_now = evaluator is not None and (_every(step, config.eval.every_steps)
                                              or step == total)
        if save_now or eval_now:
          host(*pending, last_step=bool(stop))
          pending = None
        if save_now:
          with interrupt_after():  # a Ctrl-C inside orbax's start of a save would drop it
            ckpt_lib.save(manager, state, parts["grain_it"], step, force=True,
                          params_finite=bool(np.isfinite(host.last["l2_params"])),
                          model_config=parts["model"].cfg, run_config=config,
                          data_clips=parts.get("data_clips"),
                          depth_prior=parts.get("depth_prior"))
          if stop:  # written before anything else: the scheduler's grace period is short
            ckpt_lib.wait_until_saved(manager)
        if eval_now:  # (after a notice too: a resumed run starts after this step)
          _validate(evaluator, state.params, writer, step)
        if stop:
          break
      if pending is not None:
        host(*pending)
    finally:
      ckpt_lib.wait_until_saved(manager)
      latest = manager.latest_step()  # the last step's, unless its save was refused (NaN)
      manager.close()
      progress.close()
      writer.close()
  if stop and step < total:
    raise Preempted(f"stopped at step {step} of {total} ({stop}), with a checkpoint of that "
                    "step: run the same command again to resume", stop)
  if start < total and jax.process_index() == 0:
    log.info("done: step %d of %d; the latest checkpoint: %s (the weights for sav-jax infer, "
             "python -m eval and config.init_from: %s)", total, total,
             workdir / "checkpoints" / str(latest), workdir)
  return state


def _validate(evaluator, params, writer: MetricWriter, step: int) -> None:
  """Validates `params` at `step`: the scores to the metric log, and a line to the log."""
  scores = evaluator(params)
  writer.write(step, scores, split="val")
  if jax.process_index() == 0:
    log.info("step %d validation (%s): %s", step,
             getattr(evaluator, "described", "held-out clips"),
             ", ".join(f"{k} {float(v):.4g}" for k, v in scores.items()))


def _validation_missing(config, writer: MetricWriter, start: int) -> bool:
  """Whether the restored step `start` is a validation step (a period of
  `config.eval.every_steps`, or the last) whose validation the log lacks: the run that saved
  its checkpoint was killed while validating (the checkpoint is written first). The same
  answer on every process (process 0 holds the log; validation is collective)."""
  due = start > 0 and (_every(start, config.eval.every_steps) or start == config.train.num_steps)
  if not due:
    return False
  missing = np.asarray(not writer.logged(start, "val"))
  with jax.transfer_guard("allow"):  # several processes: it places `missing` on a device
    return bool(multihost_utils.broadcast_one_to_all(missing))


class Diverged(FloatingPointError):
  """More updates skipped for non-finite values than `train.max_skipped_steps` allows."""


class Preempted(RuntimeError):
  """The run stopped early on a preemption notice or a Ctrl-C (`reason`: "SIGTERM",
  `CTRL_C`, "preemption notice"), after saving a checkpoint of its step."""

  def __init__(self, message: str, reason: str = "SIGTERM"):
    super().__init__(message)
    self.reason = reason


CTRL_C = "Ctrl-C"


class DataError(RuntimeError):
  """A training batch could not be made (a file that does not read, a crop the frames
  cannot give): the run stops, its checkpoints kept."""


def _next_batch(batches, step: int, manager, skip_unreadable: int = 0):
  """The batch of `step`; a failure of the input pipeline (grain re-raises it from its
  threads or workers) becomes one `DataError` naming the step and where to resume from (and,
  for a file that does not read, `data.skip_unreadable` where it is off)."""
  try:
    return next(batches)
  except Exception as e:  # pylint: disable=broad-except  # any reader or augmentation error
    latest = manager.latest_step()
    resume = (f"the checkpoint of step {latest} is kept: fix the data or the config and run "
              "the same command to resume" if latest is not None else "no checkpoint yet")
    if skip_unreadable == 0 and pipeline.is_unreadable(e):
      resume += ("; --config.data.skip_unreadable=N trains on another, readable clip in place "
                 "of an unreadable one")
    raise DataError(f"the training batch of step {step} could not be made: "
                    f"{type(e).__name__}: {e} ({resume})") from e


def interrupt_after():
  """`sav_jax._signals.interrupt_after` for a checkpoint save: a Ctrl-C inside orbax's start
  of a save would drop it."""
  return _signals.interrupt_after("Ctrl-C: the checkpoint save it met is started; stopping")


class Preemption:
  """Whether the run must stop at a step, with a checkpoint: a context manager, called with
  each step after it ran.

  One process: SIGTERM (the notice that SLURM, Kubernetes, cloud spot/preemptible VMs and
  `kill` send before they kill a job) is caught while the context is open, and the step
  running at that moment is the last. Several processes (`jax.distributed`): JAX's
  preemption service catches the signal on any host and every process stops at the same
  step (`CheckpointManager.reached_preemption`: the checkpoint is a collective write).
  """

  def __init__(self, manager):
    self.manager = manager
    self.reason = None
    self.stepped = False  # whether a step of this process finished (see `_on_interrupt`)
    self._previous = self._previous_int = None

  def __enter__(self) -> "Preemption":
    if (jax.process_count() == 1
        and threading.current_thread() is threading.main_thread()):  # Python's rule
      self._previous = signal.signal(signal.SIGTERM, self._on_signal)
      if callable(signal.getsignal(signal.SIGINT)):  # not ignored (a background job)
        self._previous_int = signal.signal(signal.SIGINT, self._on_interrupt)
    return self

  def __exit__(self, *exc) -> None:
    if self._previous is not None:
      signal.signal(signal.SIGTERM, self._previous)
      self._previous = None
    if self._previous_int is not None:
      signal.signal(signal.SIGINT, self._previous_int)
      self._previous_int = None

  def _on_interrupt(self, signum, frame) -> None:
    """The first Ctrl-C stops the run as SIGTERM does (after this step, with a checkpoint of
    it); another one, one after a SIGTERM, or one before this process finished a step (in
    the start's validation or the first compile: minutes for a checkpoint of nothing new),
    stops it at once (KeyboardInterrupt)."""
    if self.reason is not None or not self.stepped:
      self._previous_int(signum, frame)
      return
    log.warning("Ctrl-C: saving a checkpoint after this step, then stopping (Ctrl-C again "
                "stops at once, without it)")
    self.reason = CTRL_C

  def _on_signal(self, signum, frame) -> None:
    del frame
    if self.reason is None:
      log.warning("%s: saving a checkpoint after this step, then stopping",
                  signal.Signals(signum).name)
    self.reason = signal.Signals(signum).name

  def __call__(self, step: int) -> str | None:
    """The reason to stop after `step` (None: go on)."""
    self.stepped = True
    if self.reason is None and jax.process_count() > 1 and self.manager.reached_preemption(step):
      self.reason = "preemption notice"
    return self.reason

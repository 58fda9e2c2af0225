"""Checkpoints of a run (orbax `CheckpointManager`) and initial weights.

A checkpoint `workdir/checkpoints/<step>/` holds three items:
  state:  `{"params", "opt_state", "step", "rng", "num_skipped"}` (`StandardSave`),
  data:   the grain iterator state of every process (`grain.checkpoint.CheckpointSave`,
          one JSON file per process),
  config: `{"model": SAVConfig dict, "step": step, "run": the training config,
          "data_clips": the training clips' counts and digests, "depth_prior": where the
          frozen depth prior's weights came from (`depth_prior_origin`)}` (`JsonSave`),
          so that `sav-jax infer`/`convert`, `python -m eval` and `init_from` can use the
          step folder (or the workdir: its latest step) as model weights, and a resumed run
          can name the fields changed since (`changed_fields`); the run config's
          `checkpoint.keep` is the keep policy the checkpoint was saved under, which a later
          run's pruning keeps to (`check_keep`).
Orbax writes into a temporary directory and renames it when complete, so a run killed
mid-save leaves no checkpoint under a final name; such leftovers (`<step>.orbax-checkpoint-tmp*`,
nothing else) are deleted at start.

Resume order (`initial_state` in `train.loop`): the latest checkpoint in the workdir,
else converted init weights (`init_from`: `.pth/.pt/.npz/.safetensors` in the official
layout, an orbax directory from `sav_jax.convert.save_variables`, or another run's
workdir / checkpoint step folder; `vda_weights`: a
Video Depth Anything file for the frozen prior), else random initialisation.
"""

from __future__ import annotations

import contextlib
import json
import logging
import pathlib
import re
import shutil
import traceback

import grain
import jax
import numpy as np
import orbax.checkpoint as ocp

import sav_jax
from sav_jax._checks import is_int, loads_json, plural
from sav_jax.convert import orbax_io
from sav_jax.model.init import MACHINE_FIELDS, abstract_variables
from sav_jax.model.vda import VideoDepthAnything
from train import optim
from train.state import TrainState

log = logging.getLogger(__name__)

VDA_PATH = ("depthnet", "depthanything")


# An unfinished save of a step (orbax's temporary name for it).
_UNFINISHED = re.compile(r"\d+\.orbax-checkpoint-tmp(-\d+)?")


def make_manager(workdir, config) -> ocp.CheckpointManager:
  """A manager keeping the last `checkpoint.keep` checkpoints (0 = all).

  Raises:
    CheckpointError: `workdir/checkpoints` holds a folder named like a step that is not a
      checkpoint (orbax would take it for one: resume from it, or delete it as an old one).
  """
  ck = config.checkpoint
  directory = pathlib.Path(workdir).absolute() / "checkpoints"
  steps = [p for p in directory.iterdir() if p.name.isdigit()] if directory.is_dir() else []
  foreign = sorted(p.name for p in steps if not orbax_io.is_training_step(p))
  remains = [name for name in foreign if _checkpoint_remains(directory / name)]
  if remains:  # (a kill while orbax deleted an old checkpoint: it is not renamed first)
    raise sav_jax.convert.CheckpointError(
        f"{directory}: {remains[:5]} hold only parts of a checkpoint (no _CHECKPOINT_METADATA "
        "or no state/): what a deletion of an old checkpoint (checkpoint.keep) leaves when a "
        "kill cuts it short. Delete them, or move them out of this folder, to resume (nothing "
        "was changed)")
  if foreign:
    raise sav_jax.convert.CheckpointError(
        f"{directory}: {foreign[:5]} are named like checkpoints but are not ones written by "
        "python -m train (no _CHECKPOINT_METADATA and state/); this folder is for the run's "
        "checkpoints only: move them elsewhere")
  if jax.process_index() == 0 and directory.is_dir():
    # Orbax's own clean-up (`cleanup_tmp_directories`) deletes any folder whose name holds
    # its temporary suffix, e.g. a user's `notes.orbax-checkpoint-tmp-5`: only steps' here.
    for path in directory.iterdir():
      if _UNFINISHED.fullmatch(path.name) and path.is_dir() and not path.is_symlink():
        log.info("removing %s, an unfinished save", path)
        shutil.rmtree(path)
  options = ocp.CheckpointManagerOptions(
      max_to_keep=ck.keep if ck.keep > 0 else None, create=True,
      enable_async_checkpointing=ck.async_save, cleanup_tmp_directories=False)
  return ocp.CheckpointManager(directory, item_names=("state", "data", "config"),
                               options=options)


# What a step folder of a training checkpoint holds (`save`'s items and orbax's files).
_STEP_ENTRIES = frozenset({"_CHECKPOINT_METADATA", "commit_success.txt", "state", "data",
                           "config"})


def _checkpoint_remains(path: pathlib.Path) -> bool:
  """Whether the step-named folder `path`, not a checkpoint, holds nothing but a checkpoint's
  own entries (some of them): an old checkpoint partly deleted, not a folder of the user's."""
  if not path.is_dir() or path.is_symlink():
    return False
  names = {p.name for p in path.iterdir()}
  return bool(names) and names <= _STEP_ENTRIES


def _state_dict(state: TrainState) -> dict:
  return {"step": state.step, "params": state.params, "opt_state": state.opt_state,
          "rng": state.rng, "num_skipped": state.num_skipped}


# Fields that say where and how a run executes, not what it computes: changing them on
# resume is expected (prefixes).
# (`data.worker_count` is not one: grain's iterator state, and what each batch holds, differ
# with it; `check_data_state` refuses a change.)
# The model's are its `MACHINE_FIELDS` (remat, the ViT attention's and the GRU's
# implementations, the frame block budget: the same values, e.g. a GPU run resumed on a CPU,
# where cuDNN's attention does not run), and `train.microbatches` (the same step in K parts,
# for a device's memory).
_OPERATIONAL = ("checkpoint.", "eval.", "compile_cache", "init_from", "vda_weights",
                "random_depth_prior", "data.root", "data.num_threads", "data.prefetch",
                "data.skip_unreadable", "train.progress_bar", "train.log_every",
                "train.max_skipped_steps", "train.microbatches",
                *(f"model.{f}" for f in MACHINE_FIELDS))


def run_fields(config) -> dict:
  """A training config as `{"a.b.c": JSON value}` (tuples become lists)."""
  flat = {}

  def walk(block, prefix):
    for key, value in block.items():
      if hasattr(value, "items"):
        walk(value, f"{prefix}{key}.")
      else:
        flat[prefix + key] = json.loads(json.dumps(value, default=repr))

  walk(config, "")
  return flat


def saved_config(manager: ocp.CheckpointManager, step: int) -> dict:
  """The JSON config `save` wrote with checkpoint `step` (`model`, `step`, `run`,
  `data_clips`), {} where there is none; read once by a resume, its entries taken with
  `saved_entry`.

  Raises:
    CheckpointError: the checkpoint has a config item that cannot be read (a file cut short):
      a resume would skip every check of what changed since, without a word.
  """
  directory = pathlib.Path(manager.directory) / str(step)
  if not (directory / "config").is_dir():  # written before the config was saved with it
    return {}
  try:
    saved = manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
    saved = saved["config"]
  except Exception as e:  # pylint: disable=broad-except  # orbax's, from the JSON or the file
    corrupt = orbax_io.corrupt_checkpoint_error(directory, e)
    if corrupt is None:
      first = str(e).strip().splitlines()[0] if str(e).strip() else ""
      corrupt = sav_jax.convert.CheckpointError(
          f"{directory}: the checkpoint is corrupt or incomplete: its config item cannot be "
          f"read ({type(e).__name__}: {first[:300]})")
    raise sav_jax.convert.CheckpointError(
        f"{corrupt}. Move this step folder out of {directory.parent} to resume from the "
        "checkpoint before it, or start a new WORKDIR") from e
  return saved if isinstance(saved, dict) else {}


def saved_entry(saved: dict, key: str) -> dict:
  """Entry `key` of a `saved_config`, {} where it is missing or not a mapping."""
  entry = saved.get(key)
  return entry if isinstance(entry, dict) else {}


def saved_run(manager: ocp.CheckpointManager, step: int) -> dict:
  """The run config saved with checkpoint `step` (`run_fields`), {} where there is none."""
  return saved_entry(saved_config(manager, step), "run")


def saved_clips(manager: ocp.CheckpointManager, step: int) -> dict:
  """The training clips' record saved with checkpoint `step` (`train.input.train_dataset`'s
  `clips`), {} for checkpoints saved without one."""
  return saved_entry(saved_config(manager, step), "data_clips")


def changed_fields(manager: ocp.CheckpointManager, step: int, config,
                   saved: dict | None = None) -> list[str]:
  """`field: saved -> now` for every field of `config` that a resumed run changes, but
  those that only say where and how it runs (`_OPERATIONAL`); [] for checkpoints written
  before the config was saved with them. `saved`: `saved_run(manager, step)` if the caller
  has read it already."""
  saved = saved_run(manager, step) if saved is None else saved
  if not saved:
    return []
  now = run_fields(config)
  return [f"{k}: {saved.get(k, '(absent)')!r} -> {now.get(k, '(absent)')!r}"
          for k in sorted(set(saved) | set(now))
          if saved.get(k) != now.get(k) and not _operational(k)]


def _operational(field: str) -> bool:
  """`_OPERATIONAL`, and a training source's own data root (`data.sources.<x>.root`)."""
  return field.startswith(_OPERATIONAL) or bool(re.fullmatch(r"data\.sources\.\w+\.root", field))


def depth_prior_origin(config, saved: dict | None = None) -> str:
  """Where a run's frozen depth prior comes from, saved with its checkpoints (and carried by
  `sav-jax convert` and by a later run's `init_from`), so that weights whose prior is random
  (a toy run's) are named as such wherever they are used.

  Args:
    config: the training config.
    saved: the config saved with `config.init_from`'s weights (`load_model_params`), if any.
  """
  return _origin(config.vda_weights, config.init_from, config.random_depth_prior, saved)


_UNKNOWN_PRIOR = "unknown (saved before depth_prior was recorded)"


def _origin(vda_weights: str, init_from: str, random_prior: bool, saved: dict | None) -> str:
  if vda_weights:
    return f"Video Depth Anything weights {vda_weights}"
  if init_from:
    inherited = saved_depth_prior(saved) if saved else _UNKNOWN_PRIOR
    if inherited == _UNKNOWN_PRIOR:  # an official file, or weights saved without the entry
      return f"the weights of {init_from}"
    return f"{inherited} (via config.init_from={init_from})"
  if random_prior:
    return f"{sav_jax.convert.RANDOM_PRIOR} (config.random_depth_prior=true: a toy run)"
  return f"{sav_jax.convert.RANDOM_PRIOR} (no config.vda_weights or config.init_from)"


def saved_depth_prior(saved: dict) -> str:
  """The `depth_prior` a checkpoint's saved config records; for a checkpoint saved before
  the entry existed, what its saved training config says (one `init_from` level), else
  "unknown (...)" (never "random": resuming such a run needs neither weights field)."""
  origin = saved.get("depth_prior") if isinstance(saved, dict) else None
  if isinstance(origin, str) and origin:
    return origin
  run = saved.get("run") if isinstance(saved, dict) else None
  if isinstance(run, dict) and {"vda_weights", "init_from", "random_depth_prior"} <= set(run):
    return _origin(run["vda_weights"] or "", run["init_from"] or "",
                   bool(run["random_depth_prior"]), None)
  return _UNKNOWN_PRIOR


def save(manager: ocp.CheckpointManager, state: TrainState, data_iterator, step: int,
         params_finite: bool = True, force: bool = False,
         model_config: sav_jax.SAVConfig | None = None, run_config=None,
         data_clips: dict | None = None, depth_prior: str | None = None) -> bool:
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
    run_config: the training config, saved for `changed_fields` and `check_keep` (its
      `checkpoint.keep`: this checkpoint's keep policy) (None: not saved).
    data_clips: each training source's clip count and digest (`train.input.train_dataset`'s
      `clips`), saved for a resumed run to compare (None: not saved).
    depth_prior: `depth_prior_origin` (None: not saved).

  Returns:
    Whether a save was started.
  """
  if not params_finite:
    log.error("step %d: non-finite parameters; NOT saving a checkpoint", step)
    return False
  config = {"model": (model_config or sav_jax.SAVConfig()).to_dict(), "step": int(step)}
  if run_config is not None:
    config["run"] = run_fields(run_config)
  if data_clips is not None:
    config["data_clips"] = data_clips
  if depth_prior is not None:
    config["depth_prior"] = depth_prior
  args = ocp.args.Composite(state=ocp.args.StandardSave(_state_dict(state)),
                            data=grain.checkpoint.CheckpointSave(data_iterator),
                            config=ocp.args.JsonSave(config))
  with _naming_save_errors(manager):
    return manager.save(step, args=args, force=force)


class CheckpointSaveError(RuntimeError):
  """Writing a checkpoint failed (a full disk, a quota, a storage error): the run cannot go on
  without losing its progress. The checkpoints written before are intact, and the unfinished
  save is removed at the next start."""


_TMP_STEP = re.compile(r"/(\d+)\.orbax-checkpoint-tmp")


@contextlib.contextmanager
def _naming_save_errors(manager: ocp.CheckpointManager):
  """Turns orbax's error from a checkpoint write (raised from its background thread, at the
  next save or wait, as a long chain through its futures) into a CheckpointSaveError that
  names the step, the folder and the cause in one line."""
  try:
    yield
  except Exception as e:  # pylint: disable=broad-except  # orbax wraps the cause variously
    text = str(e)
    step = _TMP_STEP.search(text)
    what = f"checkpoint {step.group(1)}" if step else "a checkpoint"
    if "No space left on device" in text or "os_error_code='28'" in text:
      cause = "no space left on device"
    elif "Disk quota exceeded" in text or "os_error_code='122'" in text:
      cause = "disk quota exceeded"
    else:
      first = text.strip().splitlines()[0] if text.strip() else type(e).__name__
      cause = f"{type(e).__name__}: {first[:400]}"
    raise CheckpointSaveError(
        f"saving {what} in {manager.directory} failed: {cause}. The checkpoints saved before "
        "are intact (the unfinished one is removed at the next start): free space or give "
        "another --workdir, then run the same command again to resume") from e


def wait_until_saved(manager: ocp.CheckpointManager) -> None:
  """`manager.wait_until_finished()`, a failed write raised as a CheckpointSaveError."""
  with _naming_save_errors(manager):
    manager.wait_until_finished()


def check_keep(manager: ocp.CheckpointManager, config, saved: dict) -> None:
  """Raises CheckpointError where this run's `checkpoint.keep` would delete a checkpoint that
  the keep policy it was saved with keeps: orbax prunes every step of the folder beyond the
  last `keep` at each save, so a run resumed without its `--config.checkpoint.keep=0` (the
  default is 3) deleted the older checkpoints, a finished run's included, without a word (at
  its first save, or at a later one where the folder held fewer than `keep`).

  Each checkpoint records the keep of the run that saved it (`checkpoint.keep` of its saved
  run config), and each one this run would delete is judged by its own: one saved with
  `keep=0` is never deleted, one saved with `keep=K` only by a run whose keep is K or larger
  (it then goes no sooner than its own policy had it go). The latest checkpoint's keep alone
  did not tell: a run resumed with a keep under which its saves deleted nothing (the folder
  held fewer) records that keep in its own checkpoints, and a later resume with it deleted
  the earlier run's `keep=0` checkpoints. A checkpoint saved before the run config was
  recorded goes only where the folder holds exactly `keep` checkpoints, all of them from
  before the record (the latest's `saved` has no keep): such a run pruned so itself, at this
  keep. `checkpoint.prune_earlier` (a user lowering the keep on purpose: the checkpoints this
  run resumes from are among those a smaller keep deletes, so moving them out first cannot
  help) lets this run's keep delete them, with a warning that names them.

  Args:
    manager: the run's checkpoint manager.
    config: this run's training config.
    saved: `saved_run` of the latest checkpoint (read by the caller already).
  """
  keep = int(config.checkpoint.keep)
  steps = sorted(manager.all_steps())
  saves = _saves_after(config, steps[-1]) if steps else 0
  if keep <= 0 or saves == 0 or len(steps) + saves <= keep:  # orbax keeps `keep` per save
    return
  doomed = steps[:len(steps) + saves - keep]
  policies = {step: _saved_keep(saved if step == steps[-1] else None, manager, step)
              for step in doomed}
  unrecorded_ok = _saved_keep(saved) is None and len(steps) == keep

  def deletable(policy) -> bool:
    if policy is None:  # saved before the keep was recorded
      return unrecorded_ok
    return isinstance(policy, int) and 0 < policy <= keep  # (a string: unreadable)

  if all(deletable(p) for p in policies.values()):
    return
  when = ("at its first save" if saves == 1 else
          f"by the last of the {saves} checkpoints it saves up to step {config.train.num_steps}")
  if config.checkpoint.get("prune_earlier", False):  # the user lowers the keep on purpose
    log.warning("config.checkpoint.prune_earlier: this run's config.checkpoint.keep=%d will "
                "delete %s (%s) %s", keep, doomed, _policies_text(policies), when)
    return
  protective = [p for p in policies.values() if not (isinstance(p, int) and p > 0)]
  suggest = 0 if protective else max(policies.values())  # every one then goes as it would
  # (a keep they were saved with deletes them too, as that keep does: not "to keep them")
  fix = ("to keep them (0 keeps all)" if suggest == 0 else
         "(the largest keep they were saved with: each is then deleted only as its own keep "
         "deletes it), or 0 to keep them all")
  # (moving them out helps unless the checkpoint this run resumes from is among them)
  move = ("" if steps[-1] in doomed else
          ", or move the ones you do not need out of that folder first")
  raise sav_jax.convert.CheckpointError(
      f"{manager.directory} holds {plural(len(steps), 'checkpoint')}; this run's "
      f"config.checkpoint.keep={keep} would delete {doomed} ({_policies_text(policies)}) "
      f"{when}. Pass --config.checkpoint.keep={suggest} {fix}{move} (or, to lower the keep "
      "on purpose, --config.checkpoint.prune_earlier=true lets this keep delete them)")


_UNREADABLE = "with a config whose keep cannot be read"


def _saved_keep(run: dict | None, manager: ocp.CheckpointManager | None = None,
                step: int | None = None) -> int | str | None:
  """The `checkpoint.keep` a checkpoint was saved with, from its saved run config `run`
  (None: read checkpoint `step`'s): None where it was saved before the run config was
  recorded, `_UNREADABLE` where its config cannot be read or holds no valid keep (such a
  checkpoint is never deleted by a keep other than 0)."""
  if run is None:
    try:
      run = saved_run(manager, step)
    except sav_jax.convert.CheckpointError:  # cut short: named, and kept
      return _UNREADABLE
  if "checkpoint.keep" not in run:
    return None if not run else _UNREADABLE
  policy = run["checkpoint.keep"]
  return policy if is_int(policy) and policy >= 0 else _UNREADABLE


def _policies_text(policies: dict) -> str:
  """`{step: _saved_keep}` as "saved with config.checkpoint.keep=0" where all agree, else
  "steps 1, 2 saved with config.checkpoint.keep=0, step 3 with ..."."""
  def what(policy):
    if policy is None:
      return "before the keep policy was recorded"
    return policy if policy == _UNREADABLE else f"with config.checkpoint.keep={policy}"

  groups = {}
  for step, policy in policies.items():
    groups.setdefault(what(policy), []).append(step)
  if len(groups) == 1:
    return f"saved {next(iter(groups))}"
  parts = [f"step{'s' if len(s) > 1 else ''} {', '.join(map(str, s))} "
           f"{'saved ' if i == 0 else ''}{w}" for i, (w, s) in enumerate(groups.items())]
  return ", ".join(parts)


def _saves_after(config, start: int) -> int:
  """How many checkpoints a run resumed at step `start` saves: those of the period
  `checkpoint.every_steps` and the last step's (a SIGTERM or Ctrl-C adds one)."""
  total, every = int(config.train.num_steps), int(config.checkpoint.every_steps)
  if total <= start:
    return 0
  periodic = total // every - start // every if every > 0 else 0
  return periodic + int(every <= 0 or total % every != 0)


def check_data_state(manager: ocp.CheckpointManager, step: int, config,
                     saved: dict | None = None) -> None:
  """Raises CheckpointError unless this run can restore the data-iterator state of
  checkpoint `step`: grain saves one position per process (`process_<i>-of-<P>.json`),
  whose form depends on `data.worker_count`, so both must be those of the saving run.
  `saved`: `saved_run(manager, step)` if the caller has read it already."""
  directory = pathlib.Path(manager.directory) / str(step)
  files = sorted((directory / "data").glob("process_*-of-*.json"))
  counts = {int(m.group(1)) for f in files
            if (m := re.fullmatch(r"process_\d+-of-(\d+)\.json", f.name))}
  hint = ("; or start a new WORKDIR with --config.init_from=<this workdir> to keep only its "
          "weights")
  if counts and counts != {jax.process_count()}:
    raise sav_jax.convert.CheckpointError(
        f"{directory}: its data iterator was saved by {sorted(counts)[0]} process(es), this "
        f"run has {jax.process_count()}: resume with that many (each process's position in "
        f"the data is its own){hint}")
  now = config.data.worker_count
  saved = (saved_run(manager, step) if saved is None else saved).get("data.worker_count")
  if saved is None and files:  # from before the run config was saved: the state's form
    try:
      state = loads_json(files[0].read_text(encoding="utf-8"))
    except (OSError, ValueError):
      state = None
    threads_only = isinstance(state, dict) and "next_index" in state
    if isinstance(state, dict) and threads_only != (now == 0):
      saved = 0 if threads_only else "a number > 0"
  if saved is not None and saved != now:
    raise sav_jax.convert.CheckpointError(
        f"{directory}: its data iterator was saved with data.worker_count={saved}, this run "
        f"has {now}: resume with the saving run's data.worker_count (grain's iterator state "
        f"and the clips of each batch differ with the worker count){hint}")


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
  directory = pathlib.Path(manager.directory) / str(step)
  target = jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                        _state_dict(abstract_state), _state_dict(shardings))
  args = ocp.args.Composite(state=ocp.args.StandardRestore(target),
                            data=grain.checkpoint.CheckpointRestore(data_iterator))

  hint = (f". Move this step folder out of {directory.parent} to resume from the checkpoint "
          "before it, or start a new WORKDIR")
  position = (directory / "data" /
              f"process_{jax.process_index()}-of-{jax.process_count()}.json")

  def mismatch(e):
    first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    detail = f"{type(e).__name__}: {first[:300]}"
    if _raised_in_grain(e):  # the position file parsed, but grain could not set it
      return sav_jax.convert.CheckpointError(
          f"{position}: this process's position in the data cannot be restored ({detail}): "
          f"not a position grain {grain.__version__} writes for this data pipeline (edited by "
          f"hand, or written by another grain version?){hint}")
    return _mismatch(directory, detail)

  missing = [item for item in ("state", "data") if not (directory / item).is_dir()]
  if missing:  # e.g. a copy interrupted, or a folder edited by hand
    raise sav_jax.convert.CheckpointError(
        f"{directory}: the checkpoint is incomplete: it has no {' and no '.join(missing)} "
        f"folder (the {'training state' if 'state' in missing else 'data iterator'}){hint}")
  if not (directory / "state" / "_METADATA").is_file():  # (orbax's error: a tree mismatch)
    raise sav_jax.convert.CheckpointError(
        f"{directory}: the checkpoint is incomplete: it has no state/_METADATA (the list of the "
        f"training state's arrays){hint}")
  if not position.is_file():
    raise sav_jax.convert.CheckpointError(
        f"{directory}: the checkpoint is incomplete: it has no {position.relative_to(directory)} "
        f"(this process's position in the data){hint}")
  orbax_io.check_regular_files(directory)
  saved = _saved_shapes(directory / "state")
  _check_saved_shapes(directory, saved, target)
  restored = orbax_io.checked_restore(
      lambda: manager.restore(step, args=args)["state"], directory, mismatch,
      corrupt_hint=hint)
  _check_restored_tree(directory, restored, target, saved)
  return TrainState(**restored)


def _raised_in_grain(e: BaseException) -> bool:
  """Whether `e` was raised inside grain's code (restoring the data iterator's position)."""
  return any(frame.f_globals.get("__name__", "").startswith("grain.")
             for frame, _ in traceback.walk_tb(e.__traceback__))


def _mismatch(directory, detail: str) -> sav_jax.convert.CheckpointError:
  return sav_jax.convert.CheckpointError(
      f"{directory}: cannot resume from this checkpoint: it does not match this run's model or "
      f"optimizer config ({detail}). Resume with the config it was written with, or start a new "
      "WORKDIR with --config.init_from=<that workdir> to keep only its weights")


def _saved_shapes(state_dir: pathlib.Path) -> dict[str, tuple] | None:
  """`{path name: shape}` of the arrays in a checkpoint's state item (None if unreadable:
  the restore then names the problem)."""
  handler = ocp.PyTreeCheckpointHandler()
  try:
    tree = handler.metadata(state_dir).tree
    return {optim.path_name(p): tuple(x.shape)
            for p, x in jax.tree_util.tree_leaves_with_path(tree) if hasattr(x, "shape")}
  except (ValueError, KeyError, TypeError, AttributeError, OSError):
    return None
  finally:
    handler.close()


def _check_saved_shapes(directory, saved: dict | None, target: dict) -> None:
  """Raises the resume-mismatch error, naming the array, when one of `target`'s arrays has
  another shape in the checkpoint (orbax's own error would not say why)."""
  if saved is None:
    return
  if any(name.startswith("opt_state/inner_states/") for name in saved):
    raise sav_jax.convert.CheckpointError(
        f"{directory}: cannot resume from this checkpoint: its optimizer state has the "
        "per-parameter layout of sav-jax before 2026-12-02 (AdamW's moments are one vector of "
        "the trainable parameters now). Start a new WORKDIR with --config.init_from=<that "
        "workdir> to keep its weights (the optimizer state then starts anew)")
  wanted = {optim.path_name(p): tuple(x.shape)
            for p, x in jax.tree_util.tree_leaves_with_path(target)}
  # The parameters first: another model also changes the optimizer's moment vectors.
  for name in sorted(wanted, key=lambda n: not n.startswith("params/")):
    if name in saved and saved[name] != wanted[name]:
      why = ("AdamW's moment vectors hold one value per trainable parameter: e.g. "
             "optimizer.frozen differs" if name.startswith("opt_state/") else
             "e.g. another model config")
      raise _mismatch(directory, f"{name} has shape {saved[name]} in the checkpoint, "
                      f"{wanted[name]} in this run; {why}")
  # Arrays of other names (orbax: "tree structures do not match:", naming none of them).
  extra, lacking = sorted(saved.keys() - wanted.keys()), sorted(wanted.keys() - saved.keys())
  if extra or lacking:
    parts = [f"{len(extra)} arrays of the checkpoint are not in this run's state, e.g. "
             f"{', '.join(extra[:3])}" if extra else "",
             f"{len(lacking)} arrays of this run's state are not in the checkpoint, e.g. "
             f"{', '.join(lacking[:3])}" if lacking else ""]
    raise _mismatch(directory, "; ".join(p for p in parts if p))


def _check_restored_tree(directory, restored: dict, target: dict, saved: dict | None) -> None:
  """Raises the resume-mismatch error unless the checkpoint held exactly `target`'s arrays.

  Orbax restores a checkpoint of another state tree without complaint when only leaves
  differ (e.g. another optimizer config): leaves the checkpoint lacks come back as None
  (and the first update fails inside optax), leaves the target lacks are dropped.
  `saved`: `_saved_shapes` of the checkpoint.
  """
  problem = None
  if jax.tree.structure(restored) != jax.tree.structure(target):
    missing = [jax.tree_util.keystr(p) for p, x in jax.tree_util.tree_leaves_with_path(
        restored, is_leaf=lambda x: x is None) if x is None]
    problem = (f"the checkpoint lacks {len(missing)} arrays of this run's state, e.g. "
               f"{missing[0]}" if missing else "the state trees differ")
  else:
    n_target = len(jax.tree.leaves(target))
    if saved is not None and len(saved) != n_target:
      problem = (f"the checkpoint holds {len(saved)} arrays, this run's state {n_target}; e.g. "
                 "another optimizer config")
  if problem is not None:
    raise _mismatch(directory, problem)


def load_model_params(path, cfg: sav_jax.SAVConfig, saved: dict | None = None) -> dict:
  """Host params (the `params` collection only) from full-model weights.

  Args:
    path: official `.pth/.pt/.npz/.safetensors` weights, an orbax directory written by
      `sav_jax.convert.save_variables`, or another run's checkpoint (its step folder, or its
      workdir for the latest step; only the params are read).
    cfg: the model config.
    saved: a dict to fill with the config saved beside a directory's weights (e.g. its
      `depth_prior`).

  Returns:
    Nested dict of numpy arrays; `torch_unused` and other collections are dropped.
  """
  path = pathlib.Path(path).expanduser()  # (`~` the shell left after --config.init_from=)
  if path.is_dir():
    try:  # any collections (e.g. torch_unused), on this process's first device
      variables, stored = sav_jax.convert.restore_variables(path)
    except sav_jax.convert.CheckpointError as e:  # it names the folder; say which field
      raise sav_jax.convert.CheckpointError(f"config.init_from: {e}") from e
    variables = jax.device_get(variables)
    if saved is not None and isinstance(stored, dict):
      saved.update(stored)
  else:
    variables = _convert(path, "sav", "init_from",
                         lambda sd: sav_jax.convert.params_from_state_dict(sd, cfg))
  log.info("initial weights from %s", path)
  return dict(variables["params"])


def load_vda_params(path, cfg: sav_jax.SAVConfig | None = None) -> dict:
  """Host params of the frozen prior (to go under `params/depthnet/depthanything`), for the
  depth prior of `cfg.vda_encoder` (default: the paper's model)."""
  path = pathlib.Path(path).expanduser()  # (`~` the shell left after --config.vda_weights=)
  if path.is_dir():
    raise sav_jax.convert.CheckpointError(
        f"config.vda_weights={path} is a folder: it takes a Video Depth Anything weights file "
        "(.pth/.safetensors/.npz); a whole model's folder (a `sav-jax convert` output, a "
        "training run) goes in config.init_from")
  cfg = cfg or sav_jax.SAVConfig()

  def convert(sd):  # the prior's shapes from the run's model's (traced already)
    return sav_jax.convert.vda_params_from_state_dict(
        sd, VideoDepthAnything(**cfg.vda),
        abstract_variables(cfg)["params"]["depthnet"]["depthanything"])

  params, unused = _convert(path, "vda", "vda_weights", convert)
  log.info("frozen depth prior from %s (%d unused keys)", path, len(unused))
  return jax.tree.map(np.asarray, params)


_FIELDS = {"sav": "init_from", "vda": "vda_weights"}


def _convert(path, want: str, field: str, fn):
  """`fn(state dict)` of the file at `path`, which must be of kind `want` ("sav"/"vda");
  errors name the file, the config field and, for the other kind, the field it is for."""
  try:
    sd = sav_jax.convert.load_state_dict_of_kind(
        path, want, {k: f"give it as config.{f}" for k, f in _FIELDS.items()},
        label=f"config.{field}={path}")
  except ValueError as e:  # e.g. a file that is no checkpoint: it names the file
    if f"config.{field}" in str(e).split(":")[0]:  # it names the field already
      raise
    raise sav_jax.convert.CheckpointError(f"config.{field}: {e}") from e
  try:
    return fn(sd)
  except ValueError as e:  # one line, as `sav-jax infer` gives it (-v 1: the whole list)
    raise sav_jax.convert.CheckpointError(
        f"config.{field}={path}: {sav_jax.convert.keys.one_line(e)}") from e

"""Saving and restoring Flax variables plus a JSON config with orbax-checkpoint.

A checkpoint is a directory written by `orbax.checkpoint.Checkpointer` with a
`CompositeCheckpointHandler` and two items: `variables` (the Flax variables pytree, via
`StandardSave`) and `config` (a JSON-able dict, via `JsonSave`). Orbax writes into a
temporary directory and renames it when complete, so a killed save leaves no half-written
checkpoint under the final name.

`restore_variables` also reads the model out of a training run's checkpoint
(`WORKDIR/checkpoints/<step>/` with the items `state` and, since 2026-11-30, `config`,
written by `python -m train`): only `state["params"]` is read, not the optimizer state.
"""

import contextlib
import gc
import json
import logging
import os
import pathlib
import re
import shutil
import stat
import sys
import threading
import time
import traceback
from collections.abc import Mapping

import jax
import numpy as np

from sav_jax import _signals
from sav_jax._checks import check_utf8_path
from sav_jax.convert.pickle_reader import CheckpointError

__all__ = ["save_variables", "restore_variables", "is_variables_checkpoint",
           "find_training_checkpoint", "is_orbax_checkpoint", "checked_restore",
           "check_target",
           "corrupt_checkpoint_error", "quiet_failed_reads"]

log = logging.getLogger(__name__)

_ITEMS = ("variables", "config")
_METADATA_FILE = "_CHECKPOINT_METADATA"


def _ocp():
  # Imported on first use: orbax (and tensorstore) add ~30 MB and a second to
  # `import sav_jax`, which inference without checkpoints does not need.
  import orbax.checkpoint  # pylint: disable=import-outside-toplevel
  return orbax.checkpoint


def _check_utf8(directory: pathlib.Path) -> None:
  """A ValueError naming `directory` unless its path is UTF-8 text: orbax's TensorStore takes
  no other bytes (a name from a zip made on Windows failed deep inside it with a traceback,
  "Unable to cast Python instance of type <class 'str'>")."""
  check_utf8_path(directory, "orbax checkpoint folder")


def _checkpointer():
  ocp = _ocp()
  handler = ocp.CompositeCheckpointHandler(variables=ocp.StandardCheckpointHandler(),
                                          config=ocp.JsonCheckpointHandler())
  return ocp.Checkpointer(handler)


def is_variables_checkpoint(directory) -> bool:
  """Whether `directory` looks like a finished checkpoint written by `save_variables`."""
  directory = pathlib.Path(directory)
  return (directory.is_dir() and (directory / _METADATA_FILE).is_file()
          and all((directory / item).is_dir() for item in _ITEMS))


def is_training_step(directory: pathlib.Path) -> bool:
  """Whether `directory` is a step folder written by `python -m train`."""
  return (directory / _METADATA_FILE).is_file() and (directory / "state").is_dir()


def find_training_checkpoint(path) -> pathlib.Path | None:
  """The step folder of a `python -m train` checkpoint at `path`, or None.

  Args:
    path: a step folder (`WORKDIR/checkpoints/<step>`), the `checkpoints` folder or the
      run's `WORKDIR` (then the latest finished step).
  """
  path = pathlib.Path(path).absolute()
  if is_training_step(path):
    return path
  for root in (path, path / "checkpoints"):
    if root.is_dir():  # unfinished saves have temporary, non-numeric names
      steps = [(int(d.name), d) for d in root.iterdir()
               if d.name.isdigit() and is_training_step(d)]
      if steps:
        return max(steps)[1]
  return None


def is_orbax_checkpoint(path) -> bool:
  """A `save_variables` directory or a training checkpoint (`find_training_checkpoint`)."""
  return is_variables_checkpoint(path) or find_training_checkpoint(path) is not None


def save_variables(directory, variables, config_dict: dict, overwrite: bool = False
                   ) -> pathlib.Path:
  """Saves Flax variables and a config dict atomically.

  Args:
    directory: checkpoint directory to create (missing parent folders are created).
    variables: nested dicts of arrays (jax or numpy), e.g. `{"params": {...}}`. Zero-size
      arrays are not supported by orbax.
    config_dict: JSON-serialisable dict (tuples come back as lists).
    overwrite: replace an existing checkpoint written by this function. A directory that is
      not such a checkpoint is never deleted; an empty one is written into without it.

  Returns:
    The absolute checkpoint path.

  Raises:
    FileExistsError: `directory` exists, and is not an empty folder, and `overwrite` is False.
    CheckpointError: `directory` exists but is not a checkpoint (with `overwrite`), the
      config is not JSON-serialisable, `variables` has no `"params"` mapping or holds
      zero-size arrays.
  """
  directory = pathlib.Path(directory).absolute()
  if directory.is_symlink():
    if not directory.exists():
      raise CheckpointError(f"{directory} is a broken symbolic link (to {os.readlink(directory)})")
    # replace what the link points to, and keep the link (the swap below renames folders)
    directory = directory.resolve()
  _check_utf8(directory)
  if directory.exists():
    if not overwrite and not (directory.is_dir() and not any(directory.iterdir())):
      raise FileExistsError(f"{directory} exists; pass overwrite=True to replace it")
    if not directory.is_dir():
      raise CheckpointError(f"{directory} is a file, not a checkpoint folder; it is not "
                            "replaced")
    if not is_variables_checkpoint(directory) and any(directory.iterdir()):
      raise CheckpointError(f"{directory}: refusing to overwrite a non-empty directory that "
                            "is not a sav-jax variables checkpoint")
  if not (isinstance(variables, Mapping) and isinstance(variables.get("params"), Mapping)):
    found = sorted(variables)[:5] if isinstance(variables, Mapping) else type(variables).__name__
    raise CheckpointError(f"{directory}: expected Flax variables {{'params': ...}}, found "
                          f"{found} (pass the whole variables, not variables['params'])")
  _check_config(config_dict, directory)
  empty = [jax.tree_util.keystr(p) for p, x in jax.tree_util.tree_leaves_with_path(variables)
           if np.size(x) == 0]
  if empty:
    raise CheckpointError(f"{directory}: orbax cannot save zero-size arrays: {empty[:5]}")
  ocp = _ocp()
  args = ocp.args.Composite(variables=ocp.args.StandardSave(variables),
                            config=ocp.args.JsonSave(config_dict))
  if not directory.exists():
    try:  # (as file outputs: `sav-jax convert x.pth ckpt/sav` with no ckpt/ yet)
      directory.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
      raise CheckpointError(f"{directory}: cannot create its folder {directory.parent} "
                            f"({e.strerror or e})") from e
    _save_or_clean_up(directory, args, directory)
  else:  # write the new one beside the old one, then swap: a kill never leaves neither
    new = directory.with_name(f"{directory.name}.new-{os.getpid()}")
    old = directory.with_name(f"{directory.name}.old-{os.getpid()}")
    _save_or_clean_up(new, args, directory)
    own = {p.name for p in new.iterdir()}
    for extra in [p for p in directory.iterdir() if p.name not in own]:
      extra.rename(new / extra.name)  # a user's file in the folder is kept, not deleted
    directory.rename(old)
    new.rename(directory)
    shutil.rmtree(old)
  log.info("saved variables and config to %s", directory)
  return directory


def _save_or_clean_up(target: pathlib.Path, args, directory: pathlib.Path) -> None:
  """Orbax's save of `args` to `target`; a failed or interrupted one leaves nothing behind.

  Orbax writes into `<target>.orbax-checkpoint-tmp...` and renames it when done: an
  exception or Ctrl-C on the way left that folder beside the user's destination. It is
  removed (with `target`, which is this call's own) and the error re-raised; an OSError
  is reported as a CheckpointError naming `directory`, not orbax's temporary path.
  """
  def ours():
    prefix = f"{target.name}.orbax-checkpoint-tmp"
    return {p for p in target.parent.iterdir() if p.name.startswith(prefix)}

  before, threads = ours(), set(threading.enumerate())
  try:
    with _checkpointer() as ckptr:
      ckptr.save(target, args=args, force=target != directory)
  except BaseException as e:
    # Orbax's writer threads may still be filling the folder: let them end (<= 60 s, they
    # fail noisily if it vanishes under them), then remove it until it is gone (<= 5 s).
    deadline = time.monotonic() + 60
    for thread in set(threading.enumerate()) - threads:
      try:
        thread.join(max(0.0, deadline - time.monotonic()))
      except RuntimeError:  # listed while it was starting: not joinable yet
        pass
    leftovers = ours() - before | ({target} if target != directory else set())
    deadline = time.monotonic() + 5
    while leftovers and time.monotonic() < deadline:
      for leftover in leftovers:
        shutil.rmtree(leftover, ignore_errors=True)
      leftovers = {p for p in leftovers if os.path.lexists(p)}
      time.sleep(0.02 if leftovers else 0)
    if isinstance(e, OSError):
      reason = e.strerror or str(e)
      raise CheckpointError(f"{directory}: could not write the checkpoint ({reason})") from e
    raise


def _check_config(config_dict, directory):
  if not isinstance(config_dict, dict):
    raise CheckpointError(f"{directory}: config must be a dict, got {type(config_dict).__name__}")
  try:
    json.dumps(config_dict)
  except (TypeError, ValueError) as e:
    raise CheckpointError(f"{directory}: config is not JSON-serialisable ({e})") from e


# How the `depth_prior` entry a training run saves with its weights begins when the frozen
# depth prior is random (`train.checkpoint.depth_prior_origin`).
RANDOM_PRIOR = "random"


def random_prior_note(saved: dict, what: str) -> str | None:
  """A warning for weights whose saved config (`saved`) says their depth prior is random,
  naming `what` (the weights); None otherwise."""
  origin = saved.get("depth_prior") if isinstance(saved, dict) else None
  if not (isinstance(origin, str) and origin.startswith(RANDOM_PRIOR)):
    return None
  return (f"{what}: its frozen depth prior is {origin}, not Video Depth Anything's weights, so "
          "its disparities mean little; train with --config.vda_weights="
          "video_depth_anything_vits.pth for a real one")


def untrained_note(saved: dict, what: str) -> str | None:
  """A warning for weights whose saved config (`saved`) says that only their depth prior is
  trained (`sav-jax convert --vda` wrote them: `"kind": "vda"`), naming `what`; None
  otherwise."""
  if not (isinstance(saved, dict) and saved.get("kind") == "vda"):
    return None
  return (f"{what}: only its depth prior is trained (the output of `sav-jax convert --vda`, "
          "whose stereo network is freshly initialised), so its disparities mean nothing; it "
          "is an initialisation for training (--config.init_from)")


def restore_variables(directory, target=None):
  """Restores what `save_variables` wrote.

  Args:
    directory: checkpoint directory, or a training run's checkpoint (see
      `find_training_checkpoint`), whose `params` are returned as `{"params": ...}` with
      the config saved beside them (`{}` for checkpoints from before configs were saved).
    target: optional abstract pytree (e.g. `jax.eval_shape(model.init, ...)`, leaves
      `jax.ShapeDtypeStruct`, with or without shardings) or concrete arrays to restore into
      (`{"params": ...}` for a training checkpoint); one that misses arrays of the
      checkpoint, has others or other shapes is refused, naming them, before anything is
      read (`check_target`). Without it, the structure, shapes and dtypes come from the
      saved metadata and arrays are placed on this process's first device (so a checkpoint
      written on another device or topology, or read by each of several processes,
      restores too).

  Returns:
    `(variables, config_dict)`.

  Raises:
    CheckpointError: `directory` is not a checkpoint written by `save_variables`, or the
      target does not match it.
  """
  directory = pathlib.Path(directory).absolute()
  _check_utf8(directory)
  if not is_variables_checkpoint(directory):
    step = find_training_checkpoint(directory)
    if step is None:
      raise CheckpointError(_not_a_checkpoint_message(directory))
    if step != directory:  # (a step folder given by name is what was asked for)
      _warn_of_newer_unfinished(step)
    check_regular_files(step)
    return _restore_training_params(step, target)
  check_regular_files(directory)
  with _checkpointer() as ckptr:
    stored = _target_from_metadata(ckptr, directory, "variables")
    if target is None:
      target = stored
    else:
      check_target(directory, target, stored)
    ocp = _ocp()
    args = ocp.args.Composite(variables=ocp.args.StandardRestore(target),
                              config=ocp.args.JsonRestore())
    restored = _restore(ckptr, directory, args, "cannot restore variables")
  return restored["variables"], restored["config"]


def _restore(ckptr, directory, args, what: str):
  """`ckptr.restore(directory, args=args)` through `checked_restore`, a mismatch with `args`
  reported as "{directory}: {what} (...)"."""
  return checked_restore(
      lambda: ckptr.restore(directory, args=args), directory,
      lambda e: CheckpointError(f"{directory}: {what} ({type(e).__name__}: {e})"))


def checked_restore(restore, directory, mismatch, corrupt_hint: str = ""):
  """`restore()` of the checkpoint at `directory`, with orbax's failures as CheckpointErrors.

  Args:
    restore: the orbax call.
    directory: the checkpoint, named in the messages.
    mismatch: `error -> exception` for a ValueError/KeyError/TypeError/IndexError that is not a
      failed read (the checkpoint does not fit the target); raised from the error.
    corrupt_hint: appended to the corrupt-checkpoint message (`corrupt_checkpoint_error`).

  The `quiet_failed_reads` filter is in place during the call and kept only if it fails
  (`_quiet_reads_kept_on_failure`); other exceptions propagate unchanged.
  """
  try:
    # A Ctrl-C is held until the restore is done: met inside it, orbax reported the reads it
    # cancelled as a corrupt checkpoint, or its reader threads lost the interrupt.
    with _quiet_reads_kept_on_failure(), _signals.interrupt_after():
      restored = restore()
  except Exception as e:  # pylint: disable=broad-except  # orbax: a bare Exception if unreadable
    memory = next((x for x in _causes(e) if isinstance(x, MemoryError)), None)
    if memory is not None and memory is not e:
      raise MemoryError(f"{directory}: out of host memory reading the checkpoint") from e
    corrupt = corrupt_checkpoint_error(directory, e)
    if corrupt is None:
      if not isinstance(e, (ValueError, KeyError, TypeError, IndexError)):
        raise
      raise mismatch(e) from e
  else:
    return restored
  # Finalise the restore's other pending reads now, under the filter installed above: outside
  # the except block, which holds them.
  gc.collect()
  raise CheckpointError(f"{corrupt}{corrupt_hint}") if corrupt_hint else corrupt


# Tensorstore's errors start with an absl status code, e.g. 'OUT_OF_RANGE: Error reading
# "params.w/0" in OCDBT database at local file ...'.
_TENSORSTORE_ERROR = re.compile(r"^[A-Z_]+: Error (reading|opening|decoding|writing)")
# Orbax wraps a failed array read in a bare Exception: 'Encountered error while reading array
# index: (slice(0, 4, 1),). See full TensorStore details: <a long spec>'.
_ORBAX_READ_ERROR = "Encountered error while reading array"


def _causes(error: BaseException) -> list[BaseException]:
  """`error` and up to 7 of its causes or contexts."""
  chain, e = [], error
  while e is not None and len(chain) < 8:
    chain.append(e)
    e = e.__cause__ or e.__context__
  return chain


def corrupt_checkpoint_error(directory, error: BaseException) -> CheckpointError | None:
  """A `CheckpointError` saying that the checkpoint at `directory` is corrupt or incomplete
  when `error` (or its cause) is a failed tensorstore read (e.g. truncated or deleted chunk
  files under `ocdbt.process_*/d/`) or a JSON file that does not parse, else None.

  Args:
    directory: the checkpoint, named in the message.
    error: what orbax raised.

  Returns:
    The error to raise (from `error`), or None for any other kind of error.
  """
  chain = _causes(error)
  if any(isinstance(e, MemoryError) for e in chain):  # not a damaged file: the caller's
    return None
  lines = [str(e).strip().splitlines()[0] if str(e).strip() else "" for e in chain]
  if not any(l.startswith(_ORBAX_READ_ERROR) or _TENSORSTORE_ERROR.match(l) for l in lines):
    json_errors = [e for e in chain if isinstance(e, (json.JSONDecodeError, RecursionError))]
    if not json_errors:
      return None
    what = ("nested too deeply" if isinstance(json_errors[0], RecursionError)
            else f"cannot be parsed: {json_errors[0]}")
    lines = [f"a JSON file {what}"]
  # The most specific line: tensorstore's own (the file and what is wrong), else orbax's
  # without the store's multi-line spec.
  detail = next((l.split(" [tensorstore_spec=")[0] for l in lines if _TENSORSTORE_ERROR.match(l)),
                lines[0].split(" See full TensorStore details")[0])
  if log.isEnabledFor(logging.DEBUG):  # formatted now: a record must not keep the traceback
    log.debug("%s: %s", directory, "".join(traceback.format_exception(error)))
  return CheckpointError(f"{directory}: the checkpoint is corrupt or incomplete (a file of it "
                         f"is truncated or missing): {detail[:300]}")


@contextlib.contextmanager
def _quiet_reads_kept_on_failure():
  """`quiet_failed_reads` for the block: removed when it succeeds (a good checkpoint leaves no
  global hook behind), kept when it raises (the reads a failure leaves pending report at any
  later time)."""
  previous = sys.unraisablehook
  quiet_failed_reads()
  yield
  sys.unraisablehook = previous


def quiet_failed_reads() -> None:
  """Makes `sys.unraisablehook` drop the reports of a restore that failed on unreadable data.

  Orbax turns even the `GeneratorExit` of a pending read coroutine into an `Exception`, so
  each one prints "Exception ignored in: <coroutine ...>" and a TensorStore spec of some 50
  lines when it is garbage-collected, e.g. at exit after the one-line error; and reads that
  complete after orbax closed its event loop print "RuntimeError: Event loop is closed" from
  tensorstore's threads, at any later time. Installed around every restore, and kept (for the
  rest of the process) only when the restore failed: exactly these two reports are dropped,
  every other unraisable exception goes to the previous hook.
  """
  if getattr(sys.unraisablehook, "_sav_jax_quiet_reads", False):
    return
  previous = sys.unraisablehook

  def hook(unraisable):
    if not _is_failed_read_noise(unraisable):
      previous(unraisable)

  hook._sav_jax_quiet_reads = True  # pylint: disable=protected-access
  sys.unraisablehook = hook


def _is_failed_read_noise(unraisable) -> bool:
  exc = unraisable.exc_value
  if type(exc) is Exception and str(exc).startswith(_ORBAX_READ_ERROR):  # pylint: disable=C0123
    return True
  # From tensorstore's threads or a pending read's coroutine, once orbax closed its loop.
  return isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed"


def _warn_of_newer_unfinished(step: pathlib.Path) -> None:
  """Warns where `step`'s folder holds step folders of later steps that are not finished
  checkpoints (a copy of the run cut short): `find_training_checkpoint` passes over them, so
  the weights read are not the run's latest (a resume refuses such folders)."""
  newer = sorted((int(d.name) for d in step.parent.iterdir()
                  if d.name.isdigit() and int(d.name) > int(step.name) and d.is_dir()
                  and not is_training_step(d)))
  if newer:
    log.warning("%s: %s named like later checkpoints but %s no %s and state/ (unfinished, or "
                "a copy cut short): reading the latest finished one, step %s", step.parent,
                newer[:5], "has" if len(newer) == 1 else "have", _METADATA_FILE, step.name)


def _not_a_checkpoint_message(directory):
  if not directory.exists():
    return f"{directory}: checkpoint directory not found"
  if not directory.is_dir():
    return f"{directory}: not a directory (expected an orbax checkpoint directory)"
  found = sorted(os.listdir(directory))[:8]
  for run in (directory, directory.parent):  # a run's WORKDIR, or its checkpoints/ folder
    if (run / "checkpoints").is_dir() and (run / "metrics.jsonl").is_file() and \
        run / "checkpoints" in (directory, directory / "checkpoints"):
      return (f"{directory}: a training run without a finished checkpoint yet ("
              f"{run / 'checkpoints'} holds none; the first is saved at step "
              "config.checkpoint.every_steps at the latest)")
  return (f"{directory}: not a sav-jax checkpoint (expected {_METADATA_FILE} and the items "
          f"{list(_ITEMS)}, or a training run's WORKDIR/checkpoints/<step>; found {found})")


def _restore_training_params(step: pathlib.Path, target=None):
  """`({"params": ...}, config)` from a training checkpoint's step folder."""
  ocp = _ocp()
  has_config = (step / "config").is_dir()
  handlers = {"state": ocp.PyTreeCheckpointHandler()}
  if has_config:
    handlers["config"] = ocp.JsonCheckpointHandler()
  with ocp.Checkpointer(ocp.CompositeCheckpointHandler(**handlers)) as ckptr:
    # The tree from the `state` item's own metadata: the composite's would also look at the
    # `data` item (the grain iterator, which has no handler here) and warn about it.
    stored = _target_from_metadata(handlers["state"], step / "state", None, "params")
    if target is None:
      params = stored
    else:
      if not (isinstance(target, Mapping) and "params" in target):
        found = sorted(target)[:5] if isinstance(target, Mapping) else type(target).__name__
        raise CheckpointError(f"{step}: the target must be Flax variables {{'params': ...}}, "
                              f"found {found}")
      params = target["params"]
      check_target(step, {"params": params}, {"params": stored})
    args = {"state": ocp.args.PyTreeRestore(
        {"params": params}, restore_args={"params": ocp.checkpoint_utils.construct_restore_args(
            params)}, partial_restore=True)}  # the optimizer state is not read
    if has_config:
      args["config"] = ocp.args.JsonRestore()
    restored = _restore(ckptr, step, ocp.args.Composite(**args),
                        "cannot restore the parameters of this training checkpoint")
  if not has_config:
    log.warning("%s: no model config saved with this checkpoint; assuming the default model", step)
  return {"params": restored["state"]["params"]}, restored["config"] if has_config else {}


# Bounds on what a checkpoint's metadata may declare before anything is read: the largest
# array of the largest model (ViT-L prior) is 36 MiB and all of its weights 1.46 GiB, so a
# declared 24000 x 24000 array (a few hundred kB of compressible chunks) used 4.7 GB of host
# memory before the shape check against the model could refuse it.
MAX_LEAF_BYTES = 256 * 2**20
MAX_TOTAL_BYTES = 4 * 2**30


def check_declared_sizes(directory, tree) -> None:
  """Raises CheckpointError where the abstract arrays `tree` (from a checkpoint's metadata)
  declare an array beyond `MAX_LEAF_BYTES` or more than `MAX_TOTAL_BYTES` in all: no model
  has such arrays, and reading them first would take that much host memory."""
  total = 0
  for path, x in jax.tree_util.tree_leaves_with_path(tree):
    if not hasattr(x, "shape"):
      continue
    size = int(np.prod(x.shape, dtype=object)) * np.dtype(x.dtype).itemsize
    total += size
    if size > MAX_LEAF_BYTES:
      raise CheckpointError(
          f"{directory}: the checkpoint declares {jax.tree_util.keystr(path)} of shape "
          f"{tuple(x.shape)} ({size / 2**30:.3g} GiB), larger than any array of the model "
          f"({MAX_LEAF_BYTES // 2**20} MiB at most): not a checkpoint of this model, or a "
          "damaged one (nothing was read)")
  if total > MAX_TOTAL_BYTES:
    raise CheckpointError(
        f"{directory}: the checkpoint declares {total / 2**30:.3g} GiB of arrays, more than any "
        f"model's weights ({MAX_TOTAL_BYTES // 2**30} GiB at most): not a checkpoint of this "
        "model, or a damaged one (nothing was read)")


def check_regular_files(directory) -> None:
  """Raises CheckpointError where a file of the checkpoint folder (links followed) is not a
  regular file or folder: a named pipe made a restore wait forever, holding Ctrl-C back."""
  for root, dirs, files in os.walk(directory):
    for name in files + dirs:
      path = pathlib.Path(root) / name
      try:
        mode = path.stat().st_mode
      except OSError:
        continue  # a broken link: the restore names the missing file
      if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise CheckpointError(f"{directory}: {path} is not a regular file (a pipe, socket or "
                              "device): the checkpoint is damaged or not a checkpoint")


def check_target(directory, target, stored) -> None:
  """Raises CheckpointError unless `target` has the arrays of `stored` (the checkpoint's
  abstract arrays), by name and shape: orbax checks shapes only for targets with shardings
  (it restored the others, NumPy arrays or `jax.eval_shape`'s ShapeDtypeStructs, at the
  stored shapes without a word), and a training checkpoint's partial restore (which skips
  the optimizer state) returned a target's subset of the parameters, or leaves of it that
  the checkpoint does not hold, as they were."""
  def arrays(tree):
    return {jax.tree_util.keystr(p): tuple(x.shape) if hasattr(x, "shape") else None
            for p, x in jax.tree_util.tree_leaves_with_path(tree)}
  have, want = arrays(stored), arrays(target)
  missing, extra = sorted(have.keys() - want.keys()), sorted(want.keys() - have.keys())
  wrong = [f"{k} {want[k]} (stored {have[k]})" for k in want
           if k in have and want[k] is not None and want[k] != have[k]]
  parts = [f"{len(missing)} missing from the target, e.g. {', '.join(missing[:3])}"
           if missing else "",
           f"{len(extra)} not in the checkpoint, e.g. {', '.join(extra[:3])}" if extra else "",
           f"{len(wrong)} array(s) of other shapes, e.g. {', '.join(wrong[:3])}" if wrong else ""]
  if missing or extra or wrong:
    raise CheckpointError(f"{directory}: the target does not match the checkpoint: "
                          + "; ".join(p for p in parts if p))


def _target_from_metadata(reader, directory, item, key=None):
  """Abstract arrays on this process's first device, from the saved tree metadata of `item` (its
  `key` subtree when given); with `item=None`, `reader` is the item's own handler and
  `directory` the item's folder."""
  listing = (directory if item is None else directory / item) / "_METADATA"
  if not listing.is_file():  # (orbax: a bare FileNotFoundError, or a tree of None)
    raise CheckpointError(f"{directory}: the checkpoint is corrupt or incomplete (a file of it "
                          f"is truncated or missing): it has no {listing.relative_to(directory)} "
                          "(the list of its arrays)")
  try:
    with _quiet_reads_kept_on_failure():  # (its reads fail as a restore's do)
      if item is None:
        tree = reader.metadata(directory).tree
      else:
        tree = reader.metadata(directory).item_metadata[item].tree
      tree = tree if key is None else tree[key]
  except (KeyError, AttributeError, TypeError, ValueError) as e:
    corrupt = corrupt_checkpoint_error(directory, e)
    if corrupt is not None:
      raise corrupt from e
    raise CheckpointError(f"{directory}: unreadable checkpoint metadata ({e})") from e
  # This process's first device (`jax.devices()[0]` is process 0's on several hosts).
  sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])

  def leaf(meta):
    if hasattr(meta, "shape") and hasattr(meta, "dtype"):
      return jax.ShapeDtypeStruct(tuple(meta.shape), meta.dtype, sharding=sharding)
    return meta

  target = jax.tree.map(leaf, tree)
  check_declared_sizes(directory, target)
  return target

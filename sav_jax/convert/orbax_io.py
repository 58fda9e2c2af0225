"""Saving and restoring Flax variables plus a JSON config with orbax-checkpoint.

A checkpoint is a directory written by `orbax.checkpoint.Checkpointer` with a
`CompositeCheckpointHandler` and two items: `variables` (the Flax variables pytree, via
`StandardSave`) and `config` (a JSON-able dict, via `JsonSave`). Orbax writes into a
temporary directory and renames it when complete, so a killed save leaves no half-written
checkpoint under the final name.
"""

import json
import logging
import os
import pathlib

import jax
import numpy as np

from sav_jax.convert.pickle_reader import CheckpointError

__all__ = ["save_variables", "restore_variables", "is_variables_checkpoint"]

log = logging.getLogger(__name__)

_ITEMS = ("variables", "config")
_METADATA_FILE = "_CHECKPOINT_METADATA"


def _ocp():
  # Imported on first use: orbax (and tensorstore) add ~30 MB and a second to
  # `import sav_jax`, which inference without checkpoints does not need.
  import orbax.checkpoint  # pylint: disable=import-outside-toplevel
  return orbax.checkpoint


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


def save_variables(directory, variables, config_dict: dict, overwrite: bool = False
                   ) -> pathlib.Path:
  """Saves Flax variables and a config dict atomically.

  Args:
    directory: checkpoint directory to create.
    variables: nested dicts of arrays (jax or numpy), e.g. `{"params": {...}}`. Zero-size
      arrays are not supported by orbax.
    config_dict: JSON-serialisable dict (tuples come back as lists).
    overwrite: replace an existing checkpoint written by this function. A directory that is
      not such a checkpoint is never deleted.

  Returns:
    The absolute checkpoint path.

  Raises:
    FileExistsError: `directory` exists and `overwrite` is False.
    CheckpointError: `directory` exists but is not a checkpoint (with `overwrite`), the
      config is not JSON-serialisable, or `variables` holds zero-size arrays.
  """
  directory = pathlib.Path(directory).absolute()
  if directory.exists():
    if not overwrite:
      raise FileExistsError(f"{directory} exists; pass overwrite=True to replace it")
    if not is_variables_checkpoint(directory) and any(directory.iterdir()):
      raise CheckpointError(f"{directory}: refusing to overwrite a non-empty directory that "
                            "is not a sav-jax variables checkpoint")
  _check_config(config_dict, directory)
  empty = [jax.tree_util.keystr(p) for p, x in jax.tree_util.tree_leaves_with_path(variables)
           if np.size(x) == 0]
  if empty:
    raise CheckpointError(f"{directory}: orbax cannot save zero-size arrays: {empty[:5]}")
  ocp = _ocp()
  args = ocp.args.Composite(variables=ocp.args.StandardSave(variables),
                            config=ocp.args.JsonSave(config_dict))
  with _checkpointer() as ckptr:
    ckptr.save(directory, args=args, force=overwrite and directory.exists())
  log.info("saved variables and config to %s", directory)
  return directory


def _check_config(config_dict, directory):
  if not isinstance(config_dict, dict):
    raise CheckpointError(f"{directory}: config must be a dict, got {type(config_dict).__name__}")
  try:
    json.dumps(config_dict)
  except (TypeError, ValueError) as e:
    raise CheckpointError(f"{directory}: config is not JSON-serialisable ({e})") from e


def restore_variables(directory, target=None):
  """Restores what `save_variables` wrote.

  Args:
    directory: checkpoint directory.
    target: optional abstract pytree (e.g. `jax.eval_shape(model.init, ...)`, leaves
      `jax.ShapeDtypeStruct`, with or without shardings) or concrete arrays to restore into.
      Without it, the structure, shapes and dtypes come from the saved metadata and arrays
      are placed on the default device (so a checkpoint written on another device or
      topology restores too).

  Returns:
    `(variables, config_dict)`.

  Raises:
    CheckpointError: `directory` is not a checkpoint written by `save_variables`, or the
      target does not match it.
  """
  directory = pathlib.Path(directory).absolute()
  if not is_variables_checkpoint(directory):
    raise CheckpointError(_not_a_checkpoint_message(directory))
  with _checkpointer() as ckptr:
    if target is None:
      target = _target_from_metadata(ckptr, directory)
    ocp = _ocp()
    args = ocp.args.Composite(variables=ocp.args.StandardRestore(target),
                              config=ocp.args.JsonRestore())
    try:
      restored = ckptr.restore(directory, args=args)
    except (ValueError, KeyError, TypeError) as e:
      raise CheckpointError(f"{directory}: cannot restore variables ({type(e).__name__}: {e})"
                           ) from e
  return restored["variables"], restored["config"]


def _not_a_checkpoint_message(directory):
  if not directory.exists():
    return f"{directory}: checkpoint directory not found"
  if not directory.is_dir():
    return f"{directory}: not a directory (expected an orbax checkpoint directory)"
  found = sorted(os.listdir(directory))[:8]
  return (f"{directory}: not a sav-jax variables checkpoint (expected {_METADATA_FILE} and "
          f"the items {list(_ITEMS)}; found {found})")


def _target_from_metadata(ckptr, directory):
  """Abstract arrays on the default device, from the saved tree metadata."""
  try:
    tree = ckptr.metadata(directory).item_metadata["variables"].tree
  except (KeyError, AttributeError, TypeError, ValueError) as e:
    raise CheckpointError(f"{directory}: unreadable checkpoint metadata ({e})") from e
  sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])

  def leaf(meta):
    if hasattr(meta, "shape") and hasattr(meta, "dtype"):
      return jax.ShapeDtypeStruct(tuple(meta.shape), meta.dtype, sharding=sharding)
    return meta

  return jax.tree.map(leaf, tree)

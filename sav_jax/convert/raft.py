"""The official RAFT checkpoint (`raft-things.pth`) -> Flax variables of `sav_jax.model.raft.RAFT`.

Key mapping as for the stereo model (`a.b.0.c.weight` -> `a/b_0/c/kernel`, conv kernels
OIHW -> HWIO, norm `weight` -> `scale`); the context encoder's BatchNorm running statistics
(`running_mean`, `running_var`) go to the `batch_stats` collection (`mean`, `var`) and its
`num_batches_tracked` counters are dropped (evaluation mode never reads them). A strided
residual block registers its skip-path BatchNorm twice (`norm3` and `downsample.1`, as
`torch.save` writes it): where a file holds both they must be equal, and either one alone
is taken for that BatchNorm.
"""

from __future__ import annotations

import functools
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from sav_jax.convert.keys import KeyProblems, path_to_torch
from sav_jax.convert.torch_io import load_state_dict_of_kind, unwrap_state_dict

@functools.cache
def abstract_raft_variables() -> dict:
  """Shapes of RAFT's variables (`{"params", "batch_stats"}`), traced once."""
  from sav_jax.model.raft import MIN_SIZE, RAFT  # pylint: disable=import-outside-toplevel
  image = jnp.zeros((1, MIN_SIZE, MIN_SIZE, 3), jnp.float32)
  return jax.eval_shape(lambda: RAFT().init(jax.random.key(0), image, image, iters=1))


def _torch_name(collection: str, path: tuple[str, ...]) -> str:
  if collection == "batch_stats":
    path = (*path[:-1], {"mean": "running_mean", "var": "running_var"}[path[-1]])
  return path_to_torch(path)


def raft_variables_from_state_dict(state_dict: Mapping[str, np.ndarray]) -> dict:
  """Official RAFT state dict (large model, as `raft-things.pth`) -> Flax variables.

  Args:
    state_dict: `{torch_name: array}` (a leading `module.` and the wrappers of
      `unwrap_state_dict` are accepted; torch and JAX tensors too); read files with
      `sav_jax.convert.load_state_dict` or use `load_raft`.

  Returns:
    `{"params": ..., "batch_stats": ...}` for `sav_jax.model.raft.RAFT`.

  Raises:
    ValueError: listing every missing, unexpected and mis-shaped key, every tensor that is
      not floating point or holds NaN/inf, and every `norm3` that differs from its
      `downsample.1`, at once.
  """
  sd = dict(unwrap_state_dict(state_dict, "state_dict"))
  target = {(col, path): leaf for col, tree in abstract_raft_variables().items()
            for path, leaf in traverse_util.flatten_dict(tree).items()}
  by_torch = {_torch_name(col, path): (col, path) for col, path in target}
  for key in [k for k in sd if ".norm3." in k]:  # the twin of a lone norm3 (equal values)
    twin = key.replace(".norm3.", ".downsample.1.")
    if twin in by_torch:  # (a norm3 of no model BatchNorm is unexpected, its twin no key)
      sd.setdefault(twin, sd[key])
  problems = KeyProblems()
  flat: dict[str, dict] = {"params": {}, "batch_stats": {}}
  for key, value in sd.items():
    if key.endswith(".num_batches_tracked"):
      continue
    if ".norm3." in key:
      twin = key.replace(".norm3.", ".downsample.1.")
      if twin not in by_torch:
        problems.add_unexpected(key)
      elif not np.array_equal(np.asarray(sd[twin]), np.asarray(value)):
        problems.add(f"key {key!r} differs from {twin!r} (one BatchNorm in RAFT, "
                     "stored under both names)")
      continue
    col, path = by_torch.get(key, (None, None))
    arr = problems.convert(key, value, path, path and target[col, path].shape, "RAFT")
    if arr is not None:
      flat[col][path] = arr
  problems.add_absent(by_torch, sd)
  problems.raise_if_any("state dict does not match RAFT (the large model of raft-things.pth)",
                        len(sd))
  return {col: traverse_util.unflatten_dict(tree) for col, tree in flat.items()}


def load_raft(path) -> dict:
  """Reads an official RAFT checkpoint file (`.pth`, `.npz`, `.safetensors`; no pickled code
  is run) and returns its Flax variables; a file of another model is refused by name."""
  sd = load_state_dict_of_kind(path, "raft", {
      "sav": "pass the RAFT optical-flow checkpoint (raft-things.pth) here",
      "vda": "pass the RAFT optical-flow checkpoint (raft-things.pth) here"})
  return raft_variables_from_state_dict(sd)

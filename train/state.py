"""Training state, mesh and shardings; the state is created directly sharded.

Follows big_vision's order: shapes with `jax.eval_shape`, shardings from those shapes
(parameters and optimizer state replicated, the batch sharded on the `data` axis), then
`jax.jit(init, out_shardings=...)` so nothing is materialised unsharded.
"""

from __future__ import annotations

from typing import Any

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

import sav_jax
from sav_jax.model.init import abstract_variables
from train import optim

DATA_AXIS = "data"


@flax.struct.dataclass
class TrainState:
  """Everything a checkpoint holds besides the data iterator.

  Attributes:
    step: int32 scalar, number of batches consumed (skipped ones included).
    params: model parameters (`{"params": ...}` contents, frozen VDA included).
    opt_state: optax state of the `optim.TrainableVector` of `params` (AdamW's moments
      are two vectors of the trainable size; nothing for the frozen depth prior).
    rng: uint32 `[2]` raw key data; step randomness is `fold_in(rng, step)`.
    num_skipped: int32 scalar, updates skipped because the loss or a norm was
      not finite.
  """

  step: jax.Array
  params: Any
  opt_state: Any
  rng: jax.Array
  num_skipped: jax.Array


def make_mesh(devices=None) -> Mesh:
  """A 1-D mesh with axis `data` over `devices` (default: all devices of all processes).

  Raises:
    ValueError: `devices` is not a non-empty sequence of distinct `jax.Device`s (a number,
      an empty list and a device twice gave JAX's errors, or none until later).
  """
  if devices is None:
    return Mesh(np.asarray(jax.devices()), (DATA_AXIS,))
  try:
    listed = list(devices)
  except TypeError:
    listed = None
  if (not listed or not all(isinstance(d, jax.Device) for d in listed)
      or len(set(listed)) != len(listed)):
    raise ValueError(f"make_mesh takes a non-empty list of distinct jax devices (e.g. "
                     f"jax.devices()[:4]), got {devices!r}")
  return Mesh(np.asarray(listed), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, P())


def data_devices(mesh: Mesh) -> int:
  """The number of parts the batch is split into: the size of the mesh's `data` axis (a
  mesh of yours with other axes holds copies of each part along them).

  Raises:
    ValueError: the mesh has no `data` axis.
  """
  if DATA_AXIS not in mesh.axis_names:
    raise ValueError(f"the mesh has no {DATA_AXIS!r} axis (its axes: "
                     f"{', '.join(map(repr, mesh.axis_names)) or 'none'}): the batch is split "
                     f"over an axis named {DATA_AXIS!r}")
  return dict(mesh.shape)[DATA_AXIS]


def data_sharding(mesh: Mesh) -> NamedSharding:
  """Leading (batch) axis split over `data`, the rest replicated (ValueError naming the
  mesh's axes when it has no `data` axis)."""
  data_devices(mesh)
  return NamedSharding(mesh, P(DATA_AXIS))


def model_config(config) -> sav_jax.SAVConfig:
  """`SAVConfig` from the `model` block of a config."""
  return sav_jax.SAVConfig.from_dict(dict(config.model))


def _dummy_video(config) -> jax.ShapeDtypeStruct:
  # Parameter shapes do not depend on the video size; lazy_init never computes on it.
  return jax.ShapeDtypeStruct((1, config.data.frames, *config.data.crop, 3), jnp.float32)


def make_init_fn(model, tx: optax.GradientTransformation, config):
  """`init(params_or_none) -> TrainState`, jit-able.

  With `params=None` the model is initialised from `config.seed` (random weights);
  otherwise the given params are used and only the optimizer state is created.
  """
  video = _dummy_video(config)

  def init(params=None) -> TrainState:
    # RngBitGenerator keys compile much faster than threefry for ~500 initialisers.
    init_rng = jax.random.key(config.seed, impl="rbg")
    train_rng = jax.random.fold_in(jax.random.key(config.seed), 1)
    if params is None:
      variables = model.lazy_init(init_rng, video, video, iters=2)
      params = variables["params"]
    vector = optim.TrainableVector(optim.param_labels(params, config.optimizer.frozen))
    return TrainState(step=jnp.zeros((), jnp.int32), params=params,
                      opt_state=tx.init(vector.gather(params)),
                      rng=jax.random.key_data(train_rng), num_skipped=jnp.zeros((), jnp.int32))

  return init


def abstract_params(model, config):
  """`jax.ShapeDtypeStruct` tree of the model's params (traced, nothing computed).

  For a `sav_jax.StereoAnyVideo` this is `sav_jax.model.init.abstract_variables`, traced
  once per model config and shared with `init_variables` and the weight converters (the
  shapes do not depend on the clip size): a run from scratch or from official weights
  then traces the model's initialisation once instead of twice (4-7 s on CPU).
  """
  if isinstance(model, sav_jax.StereoAnyVideo):
    return abstract_variables(model.cfg)["params"]
  video = _dummy_video(config)
  return jax.eval_shape(
      lambda: model.lazy_init(jax.random.key(0), video, video, iters=2))["params"]


def state_shardings(abstract, mesh: Mesh):
  """Every leaf of the state replicated over the mesh (pure data parallelism)."""
  return jax.tree.map(lambda _: replicated(mesh), abstract)


def abstract_state(model, tx, config, params=None):
  """`jax.eval_shape` of the state; given abstract `params`, the model is not retraced."""
  init = make_init_fn(model, tx, config)
  return jax.eval_shape(init) if params is None else jax.eval_shape(init, params)


def create_train_state(model, tx, config, mesh: Mesh, params=None, shardings=None):
  """Creates the state directly with its shardings.

  Args:
    model: `sav_jax.StereoAnyVideo`.
    tx: optimizer from `train.optim.make_optimizer`.
    config: full training config.
    mesh: device mesh.
    params: optional initial params (arrays already placed with `place_params`).
    shardings: the state's shardings if known (saves tracing the model once more).

  Returns:
    `(state, shardings)`; `shardings` is a `TrainState` of `NamedSharding`s.
  """
  init = make_init_fn(model, tx, config)
  if shardings is None:
    shardings = state_shardings(abstract_state(model, tx, config, params), mesh)
  if params is None:
    return jax.jit(init, out_shardings=shardings)(), shardings
  return jax.jit(init, out_shardings=shardings, donate_argnums=(0,))(params), shardings


def check_params(host_params, abstract, what: str = "initial params") -> None:
  """Raises a ValueError naming (the first 20 of) every missing, unexpected or mis-shaped
  leaf of `host_params` against `abstract` (shapes only), with how many there are."""
  flat_target = flax.traverse_util.flatten_dict(abstract, sep="/")
  flat_src = flax.traverse_util.flatten_dict(host_params, sep="/")
  problems = [f"missing {k}" for k in flat_target if k not in flat_src]
  problems += [f"unexpected {k}" for k in flat_src if k not in flat_target]
  problems += [f"shape of {k}: {np.shape(flat_src[k])} != {flat_target[k].shape}"
               for k in flat_target if k in flat_src
               and tuple(np.shape(flat_src[k])) != tuple(flat_target[k].shape)]
  if problems:
    more = f" (and {len(problems) - 20} more)" if len(problems) > 20 else ""
    raise ValueError(f"{what} do not match the model ({len(problems)} problems): "
                     + "; ".join(problems[:20]) + more)


def place_params(host_params, abstract, mesh: Mesh):
  """Host (numpy) params -> replicated global arrays, checked against `abstract`.

  Works on several hosts: every process passes the same values and each fills only
  its addressable devices (`jax.make_array_from_callback`).

  Raises:
    ValueError: naming every missing, unexpected or mis-shaped leaf.
  """
  check_params(host_params, abstract)
  flat_target = flax.traverse_util.flatten_dict(abstract, sep="/")
  flat_src = flax.traverse_util.flatten_dict(host_params, sep="/")
  sharding = replicated(mesh)
  out = {}
  # An intended host-to-device copy (make_array_from_callback counts as implicit).
  with jax.transfer_guard_host_to_device("allow"):
    for key, target in flat_target.items():
      arr = np.asarray(flat_src[key], dtype=target.dtype)
      out[key] = jax.make_array_from_callback(arr.shape, sharding, lambda idx, a=arr: a[idx])
  return flax.traverse_util.unflatten_dict(out, sep="/")


def param_count(params, labels=None) -> dict[str, int]:
  """Number of parameters, in total and per optimizer label."""
  counts = {"total": sum(int(np.prod(x.shape)) for x in jax.tree.leaves(params))}
  if labels is not None:
    for lab in (optim.TRAINABLE, optim.FROZEN):
      counts[lab] = sum(int(np.prod(x.shape)) for x, l in zip(jax.tree.leaves(params),
                                                               jax.tree.leaves(labels)) if l == lab)
  return counts

"""Fast, official-style parameter initialisation (host NumPy, no XLA compile).

`model.init` works too, but compiling the initialisers of ~500 tensors takes tens
of seconds on CPU. `init_variables` builds the same tree from `jax.eval_shape`
and fills it on the host with PyTorch's default initialisation, as the official
model is initialised before training:

- Conv / Linear `kernel`: U(-1/sqrt(fan_in), 1/sqrt(fan_in)) (torch's
  `kaiming_uniform_(a=sqrt(5))`), `bias` with the same bound;
- `fnet` / `cnet` conv kernels: `kaiming_normal_(mode="fan_out", relu)`, zero-free
  bias as torch default;
- `update_block.time_attn.temporal_fc`: zeros (the official code zero-inits it);
- norm `scale` 1, norm `bias` 0; LayerScale `gamma` 1; position embeddings N(0, 0.02);
- the depth prior as its own constructors initialise it (`_init_depth_prior`): DINOv2's
  Linear layers N(0, 0.02) with zero biases and its class token N(0, 1e-6) (`init_weights`),
  the motion modules' `proj_out` zeroed (each starts as an identity residual); its
  convolutions and DPT head keep the PyTorch defaults above. The depth prior draws from a
  stream of its own (`default_rng([seed, 1])`): the other parameters are the values
  PyTorch's defaults give all of them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from sav_jax._checks import is_int
from sav_jax.config import SAVConfig, as_config

_NORM_NAMES = ("norm", "ln")


# SAVConfig fields that set how the model computes, not its parameters (every parameter
# is float32 whatever `dtype` says).
COMPUTE_FIELDS = ("dtype", "remat", "remat_policy", "frame_block_mb", "vit_attention",
                  "gru_conv")
# Those of them that choose how the machine runs it, not the values (the dtype does): a
# checkpoint's are its saving machine's (`sav-jax infer` takes this one's defaults), and a
# resumed training run may change them unannounced.
MACHINE_FIELDS = tuple(f for f in COMPUTE_FIELDS if f != "dtype")


# Optimizer labels: the depth prior is frozen, as the official trainer's
# `requires_grad_(False)` on every parameter whose name contains `depthanything`.
FROZEN = "frozen"
TRAINABLE = "trainable"
DEPTH_PRIOR_PATTERN = "depthanything"


def path_name(path) -> str:
  """`depthnet/depthanything/.../kernel` or `opt_state/1/0/mu` for a pytree key path (dict
  keys, sequence indices and attribute names joined by `/`)."""
  return "/".join(str(getattr(k, "key", getattr(k, "idx", getattr(k, "name", k)))) for k in path)


def param_labels(params, frozen_pattern: str = DEPTH_PRIOR_PATTERN):
  """`"frozen"` for leaves whose `/`-joined path matches `frozen_pattern`, else `"trainable"`.

  Args:
    params: parameter pytree (nested dicts).
    frozen_pattern: regular expression searched in paths like
      `depthnet/depthanything/pretrained/blocks_0/attn/qkv/kernel`; empty = nothing frozen.

  Returns:
    A pytree of labels with the structure of `params`.
  """
  import re  # pylint: disable=g-import-not-at-top
  regex = re.compile(frozen_pattern) if frozen_pattern else None

  def label(path, _):
    return FROZEN if regex is not None and regex.search(path_name(path)) else TRAINABLE

  return jax.tree_util.tree_map_with_path(label, params)


def freeze_depth_prior(tx, params, frozen_pattern: str = DEPTH_PRIOR_PATTERN):
  """`tx` (an optax transformation) on the trainable parameters only, for your own loop.

  The official trainer freezes the Video Depth Anything prior (`requires_grad_(False)`):
  no update, no optimizer state, no weight decay. The model stops its gradient, but a
  plain `optax.adamw(...)` over all parameters would still decay its weights and hold
  moments for its ~29 M values; this gives those leaves zero updates and no state.

  Args:
    tx: the optimizer, e.g. `optax.adamw(1e-4, weight_decay=1e-5)`.
    params: the parameter tree the optimizer will see (`variables["params"]`), or one of
      the same structure (shapes only are fine).
    frozen_pattern: as `param_labels`.

  Returns:
    An `optax.multi_transform` to `init(params)` and `update(grads, state, params)`.

  Raises:
    ValueError: `params` is the Flax variables dict (`{"params": ...}`) rather than the
      parameter tree: optax would fail only at `init`, on a tree-structure mismatch.
  """
  if isinstance(params, Mapping) and "params" in params:
    raise ValueError("freeze_depth_prior takes the parameter tree the optimizer sees, "
                     "variables['params']; it got the Flax variables (collections "
                     f"{sorted(params)}): pass variables['params']")
  import optax  # pylint: disable=g-import-not-at-top
  return optax.multi_transform({TRAINABLE: tx, FROZEN: optax.set_to_zero()},
                               param_labels(params, frozen_pattern))


def abstract_variables(cfg: SAVConfig):
  """Shapes of the model's variables (nothing allocated).

  Traced once per architecture (`StereoAnyVideo.create_parameters`; ~4 s as a process's
  first trace on the 2-core CPU): configs that differ only in `COMPUTE_FIELDS` (a bfloat16
  or rematerialised model of the same weights) share it.
  Each call returns dicts of its own (the leaves are shared), so a caller may edit the tree.
  """
  cfg, defaults = as_config(cfg), SAVConfig()
  return _copy_dicts(_abstract_variables(
      dataclasses.replace(cfg, **{f: getattr(defaults, f) for f in COMPUTE_FIELDS})))


def _copy_dicts(tree):
  """`tree`'s nested dicts copied (in their order), its leaves as they are: the cached trace
  stays as traced whatever a caller does to the copy (`init_variables`, the converters and
  the checkpoint checks read it)."""
  return {k: _copy_dicts(v) for k, v in tree.items()} if isinstance(tree, Mapping) else tree


@functools.lru_cache(maxsize=8)
def _abstract_variables(cfg: SAVConfig):
  from sav_jax.model.stereo_any_video import StereoAnyVideo  # pylint: disable=import-outside-toplevel
  model = StereoAnyVideo(cfg)
  dummy = jax.ShapeDtypeStruct((1, 2, 64, 64, 3), jnp.float32)
  return jax.eval_shape(lambda l, r: model.init(jax.random.PRNGKey(0), l, r,
                                                method=StereoAnyVideo.create_parameters),
                        dummy, dummy)


def _is_norm(path: tuple[str, ...]) -> bool:
  return any(n in path[-2].lower() for n in _NORM_NAMES)


def _init_depth_prior(path: tuple[str, ...], shape: tuple[int, ...], rng: np.random.Generator):
  """The official constructors' own initialisation of the depth prior (used where no VDA
  weights are loaded): DINOv2's `init_weights` (Linear layers N(0, 0.02) with zero biases,
  the class token N(0, 1e-6)) and the motion modules' zeroed `proj_out` (each starts as an
  identity residual); None for the PyTorch defaults (convolutions, the head)."""
  leaf = path[-1]
  if "motion_modules" in path[3] and path[-2] == "proj_out":
    return np.zeros(shape, np.float32)
  if path[2] != "pretrained" or _is_norm(path):
    return None
  if leaf == "cls_token":
    return (1e-6 * rng.standard_normal(shape)).astype(np.float32)
  if path[-3:-1] == ("patch_embed", "proj"):  # a convolution
    return None
  if leaf == "kernel" and len(shape) == 2:  # trunc_normal_(std=0.02): +-2 is 100 std away
    return (0.02 * rng.standard_normal(shape)).astype(np.float32)
  if leaf == "bias":
    return np.zeros(shape, np.float32)
  return None


def _init_leaf(path: tuple[str, ...], shape: tuple[int, ...], rng: np.random.Generator):
  leaf = path[-1]
  if path[:3] == ("update_block", "time_attn", "temporal_fc"):
    return np.zeros(shape, np.float32)
  if leaf == "scale" or leaf == "gamma":
    return np.ones(shape, np.float32)
  if leaf == "bias" and _is_norm(path):
    return np.zeros(shape, np.float32)
  if leaf in ("kernel", "bias"):
    kernel_shape = shape if leaf == "kernel" else None
    if kernel_shape is None:  # a bias: bound from the sibling kernel's fan-in
      return None
    fan_in = int(np.prod(shape[:-1]))
    if path[0] in ("fnet", "cnet") and len(shape) == 4:
      fan_out = shape[-1] * int(np.prod(shape[:-2]))
      return rng.normal(0.0, math.sqrt(2.0 / fan_out), shape).astype(np.float32)
    bound = 1.0 / math.sqrt(fan_in)
    return rng.uniform(-bound, bound, shape).astype(np.float32)
  return (0.02 * rng.standard_normal(shape)).astype(np.float32)


def init_variables(cfg: SAVConfig | None = None, seed: int = 0) -> dict:
  """`{"params": ...}` for `StereoAnyVideo(cfg)`, initialised as the official model.

  Args:
    cfg: model config (default: the paper's model).
    seed: NumPy seed; the same seed gives the same parameters on every host.

  Returns:
    Flax variables with float32 NumPy leaves (put them on devices as needed).
  """
  cfg = as_config(cfg)
  if not (is_int(seed) and seed >= 0):  # numpy's own error named no argument
    raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
  flat = traverse_util.flatten_dict(abstract_variables(cfg)["params"])
  rng = np.random.default_rng(seed)
  # The depth prior's own initialisation draws from a stream of its own, so that the other
  # parameters get the same values as with PyTorch's defaults throughout.
  prior_rng = np.random.default_rng([seed, 1])
  out = {}
  for path in sorted(flat):
    value = _init_leaf(path, tuple(flat[path].shape), rng)
    if value is None:  # bias of a conv/linear: torch uses the kernel's fan-in bound
      kernel = flat.get((*path[:-1], "kernel"))
      fan_in = int(np.prod(kernel.shape[:-1])) if kernel is not None else flat[path].shape[0]
      bound = 1.0 / math.sqrt(fan_in)
      value = rng.uniform(-bound, bound, flat[path].shape).astype(np.float32)
    if path[:2] == ("depthnet", "depthanything") and len(path) > 3:
      prior = _init_depth_prior(path, tuple(flat[path].shape), prior_rng)
      value = value if prior is None else prior
    out[path] = value
  return {"params": traverse_util.unflatten_dict(out)}

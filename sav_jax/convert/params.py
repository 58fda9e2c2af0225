"""Official Stereo Any Video state dicts <-> Flax variables (strict, both ways).

Key mapping: a torch key `a.b.3.c.weight` becomes the Flax path `a/b_3/c/kernel`
(a list index is joined to the name before it). Leaves: conv/linear `weight` ->
`kernel` (OIHW -> HWIO, OIDHW -> DHWIO, (out, in) -> (in, out)), norm `weight` ->
`scale`, `bias` -> `bias`. The Video Depth Anything part (`depthnet.depthanything.*`)
is mapped by `sav_jax.convert.vda`.

Parameters that the official forward never uses (listed by the fixture
manifest) are not model parameters here; they are kept verbatim in the
`"torch_unused"` collection so that exporting gives back the exact file.
"""

from __future__ import annotations

from typing import Mapping

import jax
import numpy as np
from flax import traverse_util

from sav_jax.config import VDA_VARIANTS, SAVConfig, as_config
from sav_jax.convert.keys import KeyProblems, flax_to_torch_array, path_to_torch
from sav_jax.convert.torch_io import unwrap_state_dict
from sav_jax.model.init import abstract_variables
from sav_jax.convert.vda import convert_vda_state_dict, vda_state_dict_from_params
from sav_jax.model.dinov2 import DINO_VARIANTS
from sav_jax.model.vda import VideoDepthAnything

VDA_PREFIX = "depthnet.depthanything."
UNUSED_COLLECTION = "torch_unused"
# Non-VDA parameters without effect on the forward pass.
SAV_UNUSED_KEYS = ("update_block.time_attn.temporal_attn.qkv.weight",)




def vda_encoder_of(state_dict: Mapping, prefix: str = VDA_PREFIX) -> str | None:
  """The `SAVConfig.vda_encoder` whose depth prior the weights hold ("vits", "vitb", "vitl"),
  from the width of the DINOv2 class token `{prefix}pretrained.cls_token` (`prefix=""` for a
  Video Depth Anything checkpoint); None when the file does not say or names no supported one."""
  return encoder_of_width(np.shape(state_dict.get(prefix + "pretrained.cls_token", ()))[-1:])


def encoder_of_width(width: tuple) -> str | None:
  """The `vda_encoder` whose DINOv2 class token has the width `(C,)` (a shape's last axis),
  else None."""
  return next((name for name in VDA_VARIANTS if width == (DINO_VARIANTS[name]["embed_dim"],)),
              None)


def params_from_state_dict(state_dict: Mapping[str, np.ndarray], cfg: SAVConfig | None = None) -> dict:
  """Official Stereo Any Video state dict -> Flax variables.

  Args:
    state_dict: `{torch_name: array}` with the official key names, as numpy arrays or
      tensors that convert to them (torch's, JAX's); a leading `module.` and the wrappers
      of `unwrap_state_dict` (`{"model": ...}`, `{"state_dict": ...}`) are accepted, so
      `torch.load(path)`'s result can be passed as it is. Use
      `sav_jax.convert.load_state_dict` to read files without torch.
    cfg: model config (default: the paper's model).

  Returns:
    `{"params": ..., "torch_unused": {torch_name: array}}`.

  Raises:
    ValueError: listing every missing, unexpected and mis-shaped key, and every tensor that
      is not floating point or holds NaN/inf, at once; a `CheckpointError` (a ValueError)
      when `state_dict` is not a state dict at all.
  """
  cfg = as_config(cfg)
  sd = unwrap_state_dict(state_dict, "state_dict")
  abstract = abstract_variables(cfg)["params"]
  target = traverse_util.flatten_dict(abstract)
  problems = KeyProblems()
  flat: dict[tuple[str, ...], np.ndarray] = {}
  width = target[("update_block", "time_attn", "temporal_attn", "proj", "kernel")].shape[0]
  unused = problems.unused({k: sd[k] for k in SAV_UNUSED_KEYS if k in sd},
                           {SAV_UNUSED_KEYS[0]: (3 * width, width)}, "Stereo Any Video")
  vda_sd = {k[len(VDA_PREFIX):]: v for k, v in sd.items() if k.startswith(VDA_PREFIX)}
  vda_params, vda_unused = convert_vda_state_dict(vda_sd, VideoDepthAnything(**cfg.vda),
                                                  problems.scoped(VDA_PREFIX),
                                                  abstract["depthnet"]["depthanything"])
  flat.update({("depthnet", "depthanything", *p): v
               for p, v in traverse_util.flatten_dict(vda_params).items()})
  unused.update({VDA_PREFIX + k: v for k, v in vda_unused.items()})
  # Exact official names only: `x.kernel` or `a.b_0.c` are not aliases of `x.weight`, `a.b.0.c`.
  by_torch = {path_to_torch(path): path for path in target
              if path[:2] != ("depthnet", "depthanything")}
  for key, value in sd.items():
    if key.startswith(VDA_PREFIX) or key in SAV_UNUSED_KEYS:
      continue
    path = by_torch.get(key)
    arr = problems.convert(key, value, path, path and target[path].shape)
    if arr is not None:
      flat[path] = arr
  problems.add_absent([*SAV_UNUSED_KEYS, *by_torch], sd)
  problems.raise_if_any(f"state dict does not match Stereo Any Video ({cfg.vda_encoder})",
                        len(sd))
  return {"params": traverse_util.unflatten_dict(flat), UNUSED_COLLECTION: unused}


def state_dict_from_params(variables: Mapping, cfg: SAVConfig | None = None
                           ) -> dict[str, np.ndarray]:
  """Flax variables -> official state dict (inverse of `params_from_state_dict`).

  Unused-in-forward keys come from the `"torch_unused"` collection when present
  (exact round trip), else are filled with zeros of the official shape (trained params
  have none), so the file always has every official key.

  Args:
    variables: `{"params": ...}` (plus `"torch_unused"`).
    cfg: the model config they are for (default: the paper's model with the depth prior
      the parameters hold, ViT-S, ViT-B or ViT-L; ViT-S where the tree has no
      class token to tell).

  Raises:
    CheckpointError: the variables are not the model's (missing, unexpected or mis-shaped
      parameters, non-float dtypes, NaN or inf values: `inference.check_variables`), so a
      broken tree never becomes a file that only fails when it is read back.
  """
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  if cfg is None:
    try:
      width = np.shape(variables["params"]["depthnet"]["depthanything"]["pretrained"][
          "cls_token"])[-1:]
    except (KeyError, TypeError, IndexError):
      width = ()
    cfg = SAVConfig(vda_encoder=encoder_of_width(width) or "vits")
    source = ("state_dict_from_params (cfg=None: the paper's architecture with the depth "
              "prior the parameters hold; pass the model's SAVConfig for another)")
  else:
    source = "state_dict_from_params"
  inference.check_variables(variables, cfg, source)
  params = traverse_util.flatten_dict(jax.device_get(variables["params"]))
  unused = dict(variables.get(UNUSED_COLLECTION, {}))
  sd: dict[str, np.ndarray] = {}
  vda = {p[2:]: v for p, v in params.items() if p[:2] == ("depthnet", "depthanything")}
  vda_unused = {k[len(VDA_PREFIX):]: v for k, v in unused.items() if k.startswith(VDA_PREFIX)}
  for k, v in vda_state_dict_from_params(traverse_util.unflatten_dict(vda), vda_unused).items():
    sd[VDA_PREFIX + k] = v
  for path, value in params.items():
    if path[:2] == ("depthnet", "depthanything"):
      continue
    sd[path_to_torch(path)] = flax_to_torch_array(np.asarray(value), path[-1])
  for k in SAV_UNUSED_KEYS:
    sd[k] = np.asarray(unused[k]) if k in unused else np.zeros((768, 256), np.float32)
  return sd


def export_state_dict(variables: Mapping, path, overwrite: bool = False,
                      cfg: SAVConfig | None = None):
  """Writes Flax variables as an official-format state dict file.

  Args:
    variables: `{"params": ...}` (plus `"torch_unused"` for an exact export).
    path: `.safetensors` or `.npz` (`.pth` when torch is installed).
    overwrite: replace an existing file.
    cfg: as `state_dict_from_params`.

  Returns:
    The written path. The official code loads it with `load_state_dict(strict=True)`.

  Raises:
    CheckpointError: variables that are not the model's, before anything is written.
  """
  from sav_jax.convert.torch_io import save_state_dict  # pylint: disable=import-outside-toplevel
  return save_state_dict(state_dict_from_params(variables, cfg), path, overwrite=overwrite)

"""Video Depth Anything checkpoints: PyTorch key layout <-> Flax params of `VideoDepthAnything`.

The Flax module mirrors the torch attribute names, so the mapping is
mechanical: dots become `/`, a list index is joined to its list with `_`
(`blocks.3` -> `blocks_3`, `to_out.0` -> `to_out_0`), and leaves are renamed
and re-laid out:

  Conv2d weight          (O, I, kh, kw) -> kernel (kh, kw, I, O)
  ConvTranspose2d weight (I, O, kh, kw) -> kernel (kh, kw, O, I)  (transpose_kernel=True)
  Linear weight          (out, in)      -> kernel (in, out)       (fused qkv stays fused)
  LayerNorm/GroupNorm weight            -> scale
  bias, cls_token, pos_embed, gamma     -> unchanged

Both 4-D cases are the same permutation `(2, 3, 1, 0)`. The sinusoidal
`pos_encoder.pe` buffers are not parameters: they are recomputed and checked.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from flax.traverse_util import flatten_dict, unflatten_dict

from sav_jax.convert.keys import KeyProblems, flax_to_torch_array, path_to_torch
from sav_jax.convert.torch_io import unwrap_state_dict
from sav_jax.model.dinov2 import DINO_VARIANTS
from sav_jax.model.dpt_temporal import MOTION_ATTENTION_BLOCKS, TEMPORAL_MAX_LEN, sinusoidal_table
from sav_jax.model.vda import VideoDepthAnything

# Keys of the public checkpoint that SAV never uses (no Flax param exists for them).
VDA_UNUSED_KEYS = (
    "pretrained.mask_token",  # only used with token masks
    "head.scratch.refinenet4.resConfUnit1.conv1.weight",  # refinenet4 never gets a skip input
    "head.scratch.refinenet4.resConfUnit1.conv1.bias",
    "head.scratch.refinenet4.resConfUnit1.conv2.weight",
    "head.scratch.refinenet4.resConfUnit1.conv2.bias",
    "head.scratch.output_conv2.0.weight",  # the depth regressor, commented out in SAV's copy
    "head.scratch.output_conv2.0.bias",
    "head.scratch.output_conv2.2.weight",
    "head.scratch.output_conv2.2.bias",
)
# Suffix of the motion modules' sinusoidal buffers.
PE_SUFFIX = ".pos_encoder.pe"
# Torch builds the table with float32 exp/sin that are not correctly rounded, so
# the stored buffers differ from `sinusoidal_table` by up to ~1e-6 (9.5e-7 on the
# fixtures); any other table (other width, length or formula) differs by O(0.1).
PE_ATOL = 1e-5
# A checkpoint saved in float16 or bfloat16 holds the table rounded to that type: within
# half a step of values in [-1, 1], 2**-9 for bfloat16 (read back as float32 whose low 16
# bits are zero), 2**-12 for float16.
PE_ATOL_HALF = 2.0 ** -9 + PE_ATOL


def _pe_atol(a: np.ndarray) -> float:
  """`PE_ATOL`, or `PE_ATOL_HALF` for a float16 buffer, or a float32 one holding float16 or
  bfloat16 values (a half-precision release loaded into a float32 model and saved again,
  `model.half().float()`)."""
  if a.dtype == np.float16:
    return PE_ATOL_HALF
  if a.dtype != np.float32 or a.size == 0:
    return PE_ATOL
  a = np.ascontiguousarray(a)
  bfloat16 = not np.any(a.view(np.uint32) & 0xFFFF)
  with np.errstate(over="ignore"):
    float16 = bool(np.array_equal(a.astype(np.float16).astype(np.float32), a))
  return PE_ATOL_HALF if bfloat16 or float16 else PE_ATOL


def _abstract_params(model: VideoDepthAnything) -> dict:
  """Param shapes of `model` (tracing takes seconds, so cached per configuration)."""
  return _abstract_params_cached(model.encoder, model.features, tuple(model.out_channels))


@functools.lru_cache(maxsize=8)
def _abstract_params_cached(encoder: str, features: int, out_channels: tuple) -> dict:
  model = VideoDepthAnything(encoder, features, out_channels)
  x = jnp.zeros((1, 1, 14, 14, 3), jnp.float32)
  return jax.eval_shape(model.init, jax.random.PRNGKey(0), x)["params"]


def vda_unused_shapes(model: VideoDepthAnything | None = None) -> dict[str, tuple[int, ...]]:
  """Shapes of the `VDA_UNUSED_KEYS` entries for a model configuration (its DINOv2 width
  from `DINO_VARIANTS`: no trace)."""
  model = model or VideoDepthAnything()
  return _unused_shapes(DINO_VARIANTS[model.encoder]["embed_dim"], model.features)


def _unused_shapes(embed: int, f: int) -> dict[str, tuple[int, ...]]:
  shapes = {"pretrained.mask_token": (1, embed)}
  for conv in ("conv1", "conv2"):
    shapes[f"head.scratch.refinenet4.resConfUnit1.{conv}.weight"] = (f, f, 3, 3)
    shapes[f"head.scratch.refinenet4.resConfUnit1.{conv}.bias"] = (f,)
  shapes["head.scratch.output_conv2.0.weight"] = (32, f // 2, 3, 3)
  shapes["head.scratch.output_conv2.0.bias"] = (32,)
  shapes["head.scratch.output_conv2.2.weight"] = (1, 32, 1, 1)
  shapes["head.scratch.output_conv2.2.bias"] = (1,)
  return shapes


def vda_pe_buffers(model: VideoDepthAnything | None = None) -> dict[str, np.ndarray]:
  """The `pos_encoder.pe` buffers `{torch_key: [1, max_len, C]}` the official module holds."""
  model = model or VideoDepthAnything()
  return _pe_buffers((model.out_channels[2], model.out_channels[3], model.features,
                      model.features))


def _pe_buffers(widths) -> dict[str, np.ndarray]:
  """The buffers of the four motion modules of these channel widths."""
  out = {}
  for i, c in enumerate(widths):
    for j in range(MOTION_ATTENTION_BLOCKS):
      key = (f"head.motion_modules.{i}.temporal_transformer.transformer_blocks.0."
             f"attention_blocks.{j}{PE_SUFFIX}")
      out[key] = sinusoidal_table(TEMPORAL_MAX_LEN, c)[None].copy()
  return out


def _check_pe(sd: dict[str, np.ndarray], expected: dict[str, np.ndarray],
              problems: KeyProblems) -> None:
  for key, table in expected.items():
    if key not in sd:
      problems.add_missing(key)
      continue
    a = np.asarray(sd[key])
    name = repr(problems.prefix + key)
    if a.shape != table.shape:
      problems.add(f"key {name}: shape {a.shape} does not match Video Depth Anything (expects "
                   f"{table.shape}, a sinusoidal buffer)")
    elif not np.allclose(a, table, rtol=0.0, atol=_pe_atol(a)):
      err = float(np.max(np.abs(a.astype(np.float64) - table)))
      problems.add(f"key {name} is not the sinusoidal table (max abs diff {err:.3g} > "
                   f"{_pe_atol(a):.3g})")


def vda_params_from_state_dict(sd: dict[str, np.ndarray],
                               model: VideoDepthAnything | None = None,
                               abstract: dict | None = None
                               ) -> tuple[dict, dict[str, np.ndarray]]:
  """Converts a flat VDA state dict (public `video_depth_anything_vits.pth` layout).

  Strict: every missing, unexpected or mis-shaped key, every tensor that is not floating
  point or holds NaN/inf, and any `pos_encoder.pe`
  buffer that is not the sinusoidal table, is collected and reported in one
  `ValueError`.

  Args:
    sd: `{torch_key: array}` without prefix (strip `depthnet.depthanything.` first); the
      wrappers of `unwrap_state_dict` and torch or JAX tensors are accepted.
    model: the target configuration (default: ViT-S, features 64).
    abstract: `model`'s parameter shapes, where the caller has them: the depth prior's
      subtree of the whole model's (`sav_jax.model.init.abstract_variables(cfg)["params"]
      ["depthnet"]["depthanything"]`, traced once per process); else traced here (~1.8 s
      on a 2-core CPU).

  Returns:
    `(params, unused)`: the `params` collection of `VideoDepthAnything` (float32
    numpy leaves) and `{key: array}` for exactly the `VDA_UNUSED_KEYS`.
  """
  sd = unwrap_state_dict(sd, "state_dict")
  problems = KeyProblems()
  params, unused = convert_vda_state_dict(sd, model or VideoDepthAnything(), problems, abstract)
  problems.raise_if_any("state dict does not match Video Depth Anything", len(sd))
  return params, unused


def convert_vda_state_dict(sd: dict[str, np.ndarray], model: VideoDepthAnything,
                           problems: KeyProblems, abstract: dict | None = None
                           ) -> tuple[dict, dict[str, np.ndarray]]:
  """`vda_params_from_state_dict`, collecting its problems in `problems` (whose `prefix`
  names the keys as the caller's file does) instead of raising."""
  abstract = _abstract_params(model) if abstract is None else abstract
  target = flatten_dict(abstract)
  by_torch = {path_to_torch(path): path for path in target}
  unused_shapes = vda_unused_shapes(model)
  pe = vda_pe_buffers(model)
  flat, unused = {}, {}
  for key, value in sd.items():
    if key in pe:
      continue
    if key in unused_shapes:
      unused.update(problems.unused({key: value}, unused_shapes, "Video Depth Anything"))
      continue
    path = by_torch.get(key)
    arr = problems.convert(key, value, path, path and target[path].shape,
                           "Video Depth Anything")
    if arr is not None:
      flat[path] = arr
  problems.add_absent([*by_torch, *unused_shapes], sd)
  _check_pe(sd, pe, problems)
  _note_other_encoder(sd, model, problems)
  return unflatten_dict(flat), unused


def _note_other_encoder(sd, model: VideoDepthAnything, problems: KeyProblems) -> None:
  """Says which DINOv2 variant the weights are when it is not the model's (a ViT-L depth
  prior for a ViT-S model gives hundreds of shape problems that do not say so)."""
  width = np.shape(sd.get("pretrained.cls_token", ()))[-1:]
  found = [name for name, v in DINO_VARIANTS.items() if (v["embed_dim"],) == width]
  if found and found[0] != model.encoder:
    problems.notes.append(
        f"the depth prior's weights are {found[0]} (DINOv2 width {width[0]}); the model is "
        f"configured for {model.encoder} (SAVConfig.vda_encoder)")


def vda_state_dict_from_params(params: dict, unused: dict[str, np.ndarray] | None = None,
                               model: VideoDepthAnything | None = None) -> dict[str, np.ndarray]:
  """Inverse of `vda_params_from_state_dict`: Flax params -> flat torch-layout state dict.

  Args:
    params: the `params` collection of `VideoDepthAnything`.
    unused: the `VDA_UNUSED_KEYS` arrays to carry over; keys not given (all, when None)
      are written as zeros of the official shape, so the file stays complete.
    model: the configuration, for the sinusoidal buffers (default: read from `params`, the
      width of each motion module).

  Returns:
    `{torch_key: np.ndarray}` including the recomputed `pos_encoder.pe` buffers.
  """
  sd = {}
  for path, value in flatten_dict(params).items():
    sd[path_to_torch(path)] = flax_to_torch_array(np.asarray(value), path[-1])
  unused = unused or {}
  shapes = _unused_shapes(np.shape(params["pretrained"]["cls_token"])[-1],
                          np.shape(params["head"]["scratch"]["refinenet4"]["out_conv"]["bias"])[0])
  sd.update({k: np.asarray(unused[k]) if k in unused else np.zeros(shape, np.float32)
             for k, shape in shapes.items()})
  if model is None:
    head = params["head"]
    sd.update(_pe_buffers([np.shape(head[f"motion_modules_{i}"]["temporal_transformer"]["norm"]
                                    ["scale"])[0] for i in range(4)]))
  else:
    sd.update(vda_pe_buffers(model))
  return sd

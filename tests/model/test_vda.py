"""Video Depth Anything: parity with the official oracle, and the checkpoint converter.

Feature tolerance (fixture README): `|a - b| <= 1e-4 * max|b| + 1e-5`, under
`jax.default_matmul_precision("highest")`. Measured on CPU: ~1e-6 relative at
every stage (pos-embed, DINOv2 blocks 2/5/8/11 patch and class tokens, head).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sav_jax.convert.vda import (PE_ATOL, VDA_UNUSED_KEYS, vda_params_from_state_dict,
                                 vda_state_dict_from_params)
from sav_jax.model.dpt_temporal import DPTHeadTemporal, sinusoidal_table
from sav_jax.model.vda import VideoDepthAnything

# Values against the oracle's, not XLA's optimised code (tests/conftest.py): 26 CPU-seconds
# with `fast_compile`, 49 without (2026-12-07).
pytestmark = pytest.mark.usefixtures("fast_compile")

SAV_PREFIX = "depthnet.depthanything."
BLOCKS = (2, 5, 8, 11)
PE_KEY = ("head.motion_modules.2.temporal_transformer.transformer_blocks.0."
          "attention_blocks.1.pos_encoder.pe")


def assert_features_close(got, want, name):
  got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
  assert got.shape == want.shape, f"{name}: shape {got.shape} != {want.shape}"
  err = np.abs(got - want).max()
  bound = 1e-4 * np.abs(want).max() + 1e-5
  assert err <= bound, f"{name}: max abs err {err:.3g} > {bound:.3g}"


@pytest.fixture(scope="module")
def converted(vda_state_dict):
  return vda_params_from_state_dict(vda_state_dict)


@pytest.fixture(scope="module")
def vda_input(golden_small):
  """Golden clip (batch 0) plus its time-reversed copy (batch 1): batches must not mix."""
  x = golden_small["vda_resized_left"].transpose(0, 1, 3, 4, 2)  # B,T,3,H,W -> B,T,H,W,3
  return jnp.asarray(np.concatenate([x, x[:, ::-1]], axis=0))


@pytest.fixture(scope="module")
def outputs(converted, vda_input):
  params, _ = converted
  model = VideoDepthAnything()
  fn = jax.jit(functools.partial(model.apply, method=VideoDepthAnything.intermediates))
  with jax.default_matmul_precision("highest"):
    return jax.device_get(fn({"params": params}, vda_input))


def test_pos_embed(outputs, golden_small):
  assert_features_close(outputs["pos_embed"], golden_small["dino_pos_embed"], "pos_embed")


@pytest.mark.parametrize("i,block", list(enumerate(BLOCKS)))
def test_dino_intermediate_layers(outputs, golden_small, i, block):
  t = golden_small["dino_block2_patch_left"].shape[0]  # batch 0 = the first T rows (b-major)
  assert_features_close(outputs["patch"][i][:t], golden_small[f"dino_block{block}_patch_left"],
                        f"block{block} patch")
  assert_features_close(outputs["cls"][i][:t], golden_small[f"dino_block{block}_cls_left"],
                        f"block{block} cls")


def test_head_frame0(outputs, golden_small):
  want = golden_small["vda_head_left_f0"][0].transpose(1, 2, 0)
  head = outputs["head"]
  assert head.shape == (2, 3, 56, 126, 32)
  assert_features_close(head[0, 0], want, "head frame 0")


def test_time_reversed_batch_is_consistent(outputs):
  # The ViT is per frame: batch 1 holds the same frames in reverse order.
  np.testing.assert_allclose(outputs["patch"][3][3:], outputs["patch"][3][2::-1], atol=1e-5)
  # The head mixes frames, so a different order gives different features.
  assert np.abs(outputs["head"][1, ::-1] - outputs["head"][0]).max() > 1e-3


def test_bfloat16_call(converted, vda_input, golden_small):
  params, _ = converted
  model = VideoDepthAnything(dtype=jnp.bfloat16)
  out = jax.jit(model.apply)({"params": params}, vda_input[:1])
  assert out.shape == (1, 3, 56, 126, 32) and out.dtype == jnp.bfloat16
  got = np.asarray(out[0, 0], np.float64).ravel()
  want = golden_small["vda_head_left_f0"][0].transpose(1, 2, 0).astype(np.float64).ravel()
  cos = got @ want / (np.linalg.norm(got) * np.linalg.norm(want))
  assert cos > 0.99, cos


def test_input_checks(converted):
  params, _ = converted
  model = VideoDepthAnything()
  with pytest.raises(ValueError, match="multiples of 14"):
    model.apply({"params": params}, jnp.zeros((1, 2, 28, 30, 3)))
  with pytest.raises(ValueError, match="at most 32 frames"):
    jax.eval_shape(model.apply, {"params": params}, jnp.zeros((1, 33, 14, 14, 3)))


def test_conv_transpose_layout(converted, vda_state_dict):
  """resize_layers.0 against torch's ConvTranspose2d(k=4, s=4) definition, written in numpy."""
  params, _ = converted
  x = np.random.default_rng(0).normal(size=(1, 2, 3, 48)).astype(np.float32)
  w = vda_state_dict["head.resize_layers.0.weight"]  # (in, out, kh, kw)
  b = vda_state_dict["head.resize_layers.0.bias"]
  want = np.einsum("nijc,coab->niajbo", x, w).reshape(1, 8, 12, 48) + b
  with jax.default_matmul_precision("highest"):
    got = DPTHeadTemporal().apply({"params": params["head"]}, jnp.asarray(x),
                                  method=lambda m, y: m.resize_layers_0(y))
  np.testing.assert_allclose(np.asarray(got), want, atol=1e-5)


def test_sinusoidal_table_matches_buffers(vda_state_dict):
  got = sinusoidal_table(32, 64)
  np.testing.assert_allclose(got, vda_state_dict[PE_KEY][0], rtol=0, atol=1e-6)


def test_sinusoidal_buffer_tolerance_is_wider_only_for_half_precision_values():
  from sav_jax.convert.vda import PE_ATOL_HALF, _pe_atol  # pylint: disable=import-outside-toplevel
  # 1 + 2**-7 and 2**-30 are bfloat16 values (2**-30 is 0 in float16), 1 + 2**-10 a float16
  # one; 1 + 2**-15 is neither (float32 bit 8 set: low 8 bits zero, low 16 bits not).
  for a, atol in ((np.float16([0.5]), PE_ATOL_HALF),
                  (np.float32([1 + 2**-7, 2**-30]), PE_ATOL_HALF),
                  (np.float32([1 + 2**-10]), PE_ATOL_HALF), (np.float32([1 + 2**-15]), PE_ATOL),
                  (np.float64([1 + 2**-7]), PE_ATOL)):
    assert _pe_atol(a) == atol, a


def test_unused_keys_returned(converted, vda_state_dict):
  _, unused = converted
  assert sorted(unused) == sorted(VDA_UNUSED_KEYS)
  for k, v in unused.items():
    np.testing.assert_array_equal(v, vda_state_dict[k])


def test_round_trip_is_exact(converted, vda_state_dict):
  params, unused = converted
  back = vda_state_dict_from_params(params, unused)
  assert sorted(back) == sorted(vda_state_dict)
  for k, v in vda_state_dict.items():
    assert back[k].shape == v.shape and back[k].dtype == v.dtype, k
    if k.endswith(".pos_encoder.pe"):
      # Recomputed: torch's float32 exp/sin are not correctly rounded (<= 1e-6 off).
      np.testing.assert_allclose(back[k], v, rtol=0, atol=1e-6, err_msg=k)
    else:
      np.testing.assert_array_equal(back[k], v, err_msg=k)


def test_wrapped_checkpoint_with_jax_tensors_gives_same_params(converted, vda_state_dict):
  params, unused = vda_params_from_state_dict(
      {"state_dict": {"module." + k: jnp.asarray(v) for k, v in vda_state_dict.items()}})
  jax.tree.map(np.testing.assert_array_equal, params, converted[0])
  assert sorted(unused) == sorted(converted[1])


def test_sav_prefixed_subset_gives_same_params(converted, sav_state_dict):
  sub = {k[len(SAV_PREFIX):]: v for k, v in sav_state_dict.items() if k.startswith(SAV_PREFIX)}
  params, unused = vda_params_from_state_dict(sub)
  ref_params, ref_unused = converted
  jax.tree.map(np.testing.assert_array_equal, params, ref_params)
  jax.tree.map(np.testing.assert_array_equal, unused, ref_unused)


@pytest.mark.parametrize("edit,message", [
    ("missing", "missing key 'pretrained.blocks.3.attn.qkv.weight'"),
    ("extra", "unexpected key 'head.scratch.refinenet5.out_conv.weight'"),
    ("shape", "key 'head.projects.0.weight': shape (48, 384, 1, 2) does not match Video Depth "
              "Anything (expects (48, 384, 1, 1))"),
    ("pe", f"key '{PE_KEY}' is not the sinusoidal table"),
    ("pe_missing", f"missing key '{PE_KEY}'"),
    ("pe_shape", f"key '{PE_KEY}': shape (1, 16, "),
    ("unused", "missing key 'pretrained.mask_token'"),
])
def test_converter_is_strict(vda_state_dict, edit, message):
  sd = dict(vda_state_dict)
  if edit == "missing":
    del sd["pretrained.blocks.3.attn.qkv.weight"]
  elif edit == "extra":
    sd["head.scratch.refinenet5.out_conv.weight"] = np.zeros((64, 64, 1, 1), np.float32)
  elif edit == "shape":
    sd["head.projects.0.weight"] = np.zeros((48, 384, 1, 2), np.float32)
  elif edit == "pe":
    sd[PE_KEY] = sd[PE_KEY] + 10 * PE_ATOL
  elif edit == "pe_shape":  # a table of another length
    sd[PE_KEY] = sd[PE_KEY][:, :16]
  elif edit == "pe_missing":  # recomputed, but the official strict load_state_dict needs it
    del sd[PE_KEY]
  else:
    del sd["pretrained.mask_token"]
  with pytest.raises(ValueError, match="1 problem") as info:
    vda_params_from_state_dict(sd)
  assert message in str(info.value)


def test_converter_lists_all_problems(vda_state_dict):
  sd = dict(vda_state_dict)
  del sd["pretrained.norm.bias"]
  sd["pretrained.extra"] = np.zeros(3, np.float32)
  sd["head.scratch.layer1_rn.weight"] = np.zeros((64, 48, 1, 1), np.float32)
  with pytest.raises(ValueError) as info:
    vda_params_from_state_dict(sd)
  msg = str(info.value)
  assert "3 problem" in msg
  for part in ("missing key 'pretrained.norm.bias'", "unexpected key 'pretrained.extra'",
               "key 'head.scratch.layer1_rn.weight': shape (64, 48, 1, 1)"):
    assert part in msg


def test_export_writes_buffers_of_the_params_widths():
  # A head narrower than VDA-S's: the sinusoidal buffers follow the params' widths.
  from sav_jax.convert.vda import _abstract_params  # pylint: disable=import-outside-toplevel
  model = VideoDepthAnything(features=32, out_channels=(24, 48, 96, 192))
  params = jax.tree.map(lambda a: np.full(a.shape, 0.5, np.float32), _abstract_params(model))
  sd = vda_state_dict_from_params(params)
  assert sd[PE_KEY].shape == (1, sd[PE_KEY].shape[1], 32)
  back, _ = vda_params_from_state_dict(sd, model)
  jax.tree.map(np.testing.assert_array_equal, back, params)

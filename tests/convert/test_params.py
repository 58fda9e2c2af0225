"""Official state dict <-> Flax variables, `sav-jax convert`, and export."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sav_jax
from sav_jax import cli, convert
from sav_jax.convert.params import UNUSED_COLLECTION

SD_KEYS_WITH_PE = ".pos_encoder.pe"

pytestmark = pytest.mark.usefixtures("fast_compile")


@pytest.fixture(scope="module")
def variables(sav_state_dict):
  return convert.params_from_state_dict(sav_state_dict)


def _assert_same_state_dicts(a, b):
  assert sorted(a) == sorted(b)
  for k in a:
    if k.endswith(SD_KEYS_WITH_PE):  # recomputed sinusoidal tables (torch's float32 rounding)
      np.testing.assert_allclose(a[k], b[k], atol=1e-6, rtol=0, err_msg=k)
    else:
      np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_round_trip_is_exact(sav_state_dict, variables):
  _assert_same_state_dicts(convert.state_dict_from_params(variables), sav_state_dict)


def test_module_prefix_accepted(sav_state_dict, variables):
  wrapped = {"module." + k: v for k, v in sav_state_dict.items()}
  got = convert.params_from_state_dict(wrapped)
  jax.tree_util.tree_map(np.testing.assert_array_equal, got["params"], variables["params"])


def test_loaded_checkpoint_objects_accepted_as_they_are(sav_state_dict, variables):
  # What torch.load gives for a training checkpoint: the state dict under "model", with
  # tensors that are not numpy arrays (JAX arrays here, torch's alike: both have __array__).
  checkpoint = {"model": {"module." + k: jnp.asarray(v) for k, v in sav_state_dict.items()},
                "optimizer": {"state": {}}, "total_steps": 7}
  got = convert.params_from_state_dict(checkpoint)
  jax.tree_util.tree_map(np.testing.assert_array_equal, got["params"], variables["params"])
  with pytest.raises(convert.CheckpointError, match="state_dict: no state dict found; the "
                     "checkpoint is a list"):
    convert.params_from_state_dict([1, 2])
  with pytest.raises(convert.CheckpointError, match=r"not a state dict of tensors: 1 of 2 "
                     r"entries are not \(str, tensor\) pairs, e.g. 'step': int"):
    convert.params_from_state_dict({"fnet.conv1.weight": np.zeros(3, np.float32), "step": 7})

  class BFloat16Tensor:  # as torch's: an array-like that numpy cannot take
    shape, dtype = (2,), "torch.bfloat16"

    def __array__(self, *args, **kwargs):
      raise TypeError("Got unsupported ScalarType BFloat16")

  with pytest.raises(convert.CheckpointError, match=r"'fnet.conv1.weight' \(BFloat16Tensor of "
                     r"dtype torch.bfloat16\) does not convert to a numpy array: .*\.float\(\)"):
    convert.params_from_state_dict({"fnet.conv1.weight": BFloat16Tensor()})


class _TorchLikeTensor:
  """Stands in for a torch.Tensor (torch is not a test dependency): numpy refuses it as it is,
  as it refuses a tensor that requires grad or is bfloat16; detach/cpu/float/numpy as torch's."""
  __module__ = "torch"

  def __init__(self, value, dtype, requires_grad=False):
    self.value, self.dtype, self.requires_grad = value, dtype, requires_grad
    self.shape = value.shape

  def __array__(self, *args, **kwargs):
    raise RuntimeError("Can't call numpy() on Tensor that requires grad" if self.requires_grad
                       else "Got unsupported ScalarType BFloat16")

  def detach(self):
    return _TorchLikeTensor(self.value, self.dtype)

  def cpu(self):
    return self

  def float(self):
    return _TorchLikeTensor(self.value.astype(np.float32), "torch.float32")

  def numpy(self):
    if self.dtype == "torch.bfloat16":
      raise TypeError("Got unsupported ScalarType BFloat16")
    if self.requires_grad:
      raise RuntimeError("Can't call numpy() on Tensor that requires grad")
    return self.value


def _torch_tensors(sd, dtype):
  """The state dict as torch.load gives it: real torch tensors where torch is installed."""
  try:
    import torch  # pylint: disable=import-outside-toplevel
  except ImportError:
    return {k: _TorchLikeTensor(_to_bfloat16(v), "torch.bfloat16", requires_grad=True)
            if dtype == "bfloat16" and v.dtype == np.float32
            else _TorchLikeTensor(v, f"torch.{v.dtype}", requires_grad=True)
            for k, v in sd.items()}
  out = {k: torch.from_numpy(np.array(v)) for k, v in sd.items()}
  return {k: (t.to(getattr(torch, dtype)) if t.dtype == torch.float32 else t).requires_grad_(
      t.is_floating_point()) for k, t in out.items()}


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_torch_tensors_accepted_as_torch_load_gives_them(sav_state_dict, variables, dtype):
  # Parameters that require grad (a model's state_dict(keep_vars=True)) and bfloat16 ones
  # convert without a manual .detach().float(); bfloat16 values are exact in float32.
  got = convert.params_from_state_dict({"model": _torch_tensors(sav_state_dict, dtype)})
  if dtype == "float32":
    jax.tree_util.tree_map(np.testing.assert_array_equal, got["params"], variables["params"])
  else:
    want = convert.params_from_state_dict({k: _to_bfloat16(v) if v.dtype == np.float32 else v
                                           for k, v in sav_state_dict.items()})
    jax.tree_util.tree_map(np.testing.assert_array_equal, got["params"], want["params"])


def test_torch_tensors_keep_their_dtype_unless_numpy_has_none():
  # Only bfloat16 (and float8), which NumPy has no type for, are widened to float32: a
  # BatchNorm's int64 counter and a float16 weight stay as they are (as in a file read).
  half = np.array([0.5, -2.0], np.float16)
  count = np.array(12, np.int64)
  sd = convert.unwrap_state_dict({
      "w": _TorchLikeTensor(half, "torch.float16", requires_grad=True),
      "n": _TorchLikeTensor(count, "torch.int64"),
      "b": _TorchLikeTensor(_to_bfloat16(np.array([1.5, 3.0], np.float32)), "torch.bfloat16")})
  assert sd["w"].dtype == np.float16 and sd["n"].dtype == np.int64 and sd["n"] == 12
  assert sd["b"].dtype == np.float32
  np.testing.assert_array_equal(sd["w"], half)
  np.testing.assert_array_equal(sd["b"], [1.5, 3.0])


def test_strict_errors_list_every_problem(sav_state_dict):
  sd = dict(sav_state_dict)
  del sd["fnet.conv1.weight"]
  del sd["depthnet.depthanything.pretrained.blocks.0.attn.qkv.bias"]
  sd["update_block.bogus.weight"] = np.zeros(3, np.float32)
  sd["corr_mlp.fc1.weight"] = np.zeros((256, 300), np.float32)
  with pytest.raises(ValueError) as e:
    convert.params_from_state_dict(sd)
  msg = str(e.value)
  for needle in ("fnet.conv1.weight", "pretrained.blocks.0.attn.qkv.bias",
                 "update_block.bogus.weight", "corr_mlp.fc1.weight", "(256, 300)"):
    assert needle in msg, (needle, msg)


def test_only_official_names_are_accepted(sav_state_dict):
  sd = dict(sav_state_dict)
  sd["fnet.conv1.kernel"] = sd.pop("fnet.conv1.weight")  # a Flax leaf name is not an alias
  sd["cnet.layer1_0.conv1.weight"] = sd["cnet.layer1.0.conv1.weight"]  # nor a Flax path
  norm = "update_block.time_attn.temporal_norm1.weight"
  sd[norm] = sd[norm][None]  # one extra dimension: a shape error, not missing + unexpected
  with pytest.raises(ValueError) as e:
    convert.params_from_state_dict(sd)
  msg = str(e.value)
  for needle in ("unexpected key 'fnet.conv1.kernel'", "missing key 'fnet.conv1.weight'",
                 "unexpected key 'cnet.layer1_0.conv1.weight'", f"key '{norm}': shape (1, "):
    assert needle in msg, (needle, msg)
  assert f"missing key '{norm}'" not in msg and f"unexpected key '{norm}'" not in msg
  assert msg.count("problem") == 1 and "4 problem(s)" in msg, msg


def test_long_reports_are_bounded_and_name_full_keys(sav_state_dict):
  sd = {k: v for k, v in sav_state_dict.items() if not k.startswith("update_block.")}
  vda = "depthnet.depthanything.pretrained.norm.bias"
  del sd[vda]
  sd["extra.weight"] = np.zeros(3, np.float32)
  n_update = sum(k.startswith("update_block.") for k in sav_state_dict)
  with pytest.raises(ValueError) as e:
    convert.params_from_state_dict(sd)
  lines = str(e.value).splitlines()
  assert lines[0] == (f"state dict does not match Stereo Any Video (vits): {n_update + 2} "
                      f"problem(s) (1 unexpected key, {n_update + 1} missing keys):"), lines[0]
  assert "  unexpected key 'extra.weight'" in lines
  assert f"  missing key '{vda}'" in lines  # the depth prior's keys by their name in the file
  # Listed first: the depth prior's missing key, then 9 of update_block's.
  assert lines[-1] == (f"  ... and {n_update - 9} more missing keys (by module: "
                       f"update_block {n_update - 9})"), lines[-1]
  assert len(lines) == 1 + 1 + 10 + 1, lines  # header, unexpected, 10 missing, the rest counted


def test_report_counts_the_rest_by_the_modules_concerned():
  from sav_jax.convert.keys import KeyProblems  # pylint: disable=import-outside-toplevel
  problems = KeyProblems(limit=2)
  problems.add_absent([f"update_block.gru.conv{i}.weight" for i in range(5)], {})
  with pytest.raises(ValueError) as e:  # an empty state dict: no note on its keys
    problems.raise_if_any("no match", keys_given=0)
  assert str(e.value).splitlines() == [
      "no match: 5 problem(s):", "  missing key 'update_block.gru.conv0.weight'",
      "  missing key 'update_block.gru.conv1.weight'",
      "  ... and 3 more missing keys (by module: update_block.gru 3)"]
  problems.add_unexpected("fnet.extra.weight")
  problems.add_missing("depthnet.depthanything.pretrained.norm.bias")
  with pytest.raises(ValueError) as e:
    problems.raise_if_any("no match", keys_given=3)
  assert str(e.value).splitlines()[0] == ("no match: 7 problem(s) (1 unexpected key, "
                                          "6 missing keys):")
  assert str(e.value).splitlines()[-1] == ("  ... and 4 more missing keys (by module: "
                                           "update_block.gru 3, depthnet.depthanything 1)")
  KeyProblems().raise_if_any("nothing to report", keys_given=0)  # no problems: no error
  problems = KeyProblems(limit=0)  # the modules with most keys first, not the first seen
  for key in ("fnet.conv1.weight", "cnet.conv1.weight", "cnet.conv2.weight"):
    problems.add_missing(key)
  with pytest.raises(ValueError) as e:
    problems.raise_if_any("no match", keys_given=0)
  assert str(e.value).splitlines()[-1] == ("  ... and 3 more missing keys (by module: cnet 2, "
                                           "fnet 1)")
  nested = KeyProblems("depthnet.").scoped("depthanything.")  # a scope adds to the prefix
  nested.add_missing("head.bias")
  assert nested.missing == ["missing key 'depthnet.depthanything.head.bias'"]


def test_torch_names_and_flax_paths():
  from sav_jax.convert import keys  # pylint: disable=import-outside-toplevel
  for key, ndim, path in (
      ("fnet.layer1.0.conv1.weight", 4, ("fnet", "layer1_0", "conv1", "kernel")),
      ("update_block.mask.2.weight", 2, ("update_block", "mask_2", "kernel")),
      ("fnet.norm1.weight", 1, ("fnet", "norm1", "scale")),
      ("blocks.11.norm1.bias", 1, ("blocks_11", "norm1", "bias")),
      ("pretrained.cls_token", 3, ("pretrained", "cls_token")),
      ("0.weight", 2, ("0", "kernel")),  # an nn.Sequential's own state dict
      ("head.conv_1x1.weight", 4, ("head", "conv_1x1", "kernel"))):  # "_1" is no list index
    assert keys.torch_to_path(key, ndim) == path, key
    assert keys.path_to_torch(path) == key, path
  # (O, I, kh, kw) -> (kh, kw, I, O): each element where numpy's indexing puts it.
  w = np.arange(2 * 3 * 4 * 5, dtype=np.float32).reshape(2, 3, 4, 5)
  k = keys.torch_to_flax_array(w)
  assert k.shape == (4, 5, 3, 2) and k[3, 1, 2, 0] == w[0, 2, 3, 1]
  np.testing.assert_array_equal(keys.flax_to_torch_array(k), w)
  assert keys.flax_to_torch_array(np.ascontiguousarray(k)).flags.c_contiguous
  lin = np.arange(6, dtype=np.float32).reshape(2, 3)
  assert keys.torch_to_flax_array(lin)[2, 1] == lin[1, 2]
  c1 = np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4)  # Conv1d (O, I, k) -> (k, I, O)
  assert keys.torch_to_flax_array(c1)[3, 1, 0] == c1[0, 1, 3]
  np.testing.assert_array_equal(keys.flax_to_torch_array(keys.torch_to_flax_array(c1)), c1)
  for leaf in ("scale", "kernel"):  # a 1-D tensor keeps its layout whatever its leaf
    np.testing.assert_array_equal(keys.torch_to_flax_array(lin[0], leaf), lin[0])
  for x in (lin, c1, w):  # only a kernel is re-laid out: `pos_embed`, `cls_token` are not
    np.testing.assert_array_equal(keys.torch_to_flax_array(x, "pos_embed"), x)
    np.testing.assert_array_equal(keys.flax_to_torch_array(x, "pos_embed"), x)


def test_shape_problems_give_torchs_layout():
  # A Conv2d weight (O, I, kh, kw) for the Flax kernel (kh, kw, I, O) = (3, 3, 4, 2): the
  # report shows the tensor as it is in the file and the shape torch would have, (2, 4, 3, 3).
  from sav_jax.convert import keys  # pylint: disable=import-outside-toplevel
  arr, problem = keys.converted("c.weight", np.zeros((2, 3, 1, 1), np.float32), "kernel",
                                (3, 3, 4, 2))
  assert arr is None and problem == ("key 'c.weight': shape (2, 3, 1, 1) does not match the "
                                     "model (expects (2, 4, 3, 3))")


@pytest.mark.parametrize("dtype", ["float16", "bfloat16", "float64"])
def test_tensors_kept_for_export_are_float32_as_params_are(dtype):
  from sav_jax.convert import keys  # pylint: disable=import-outside-toplevel
  a = keys.unused_array(np.array([[0.5, -2.0]], jnp.dtype(dtype)))
  assert a.dtype == np.float32
  np.testing.assert_array_equal(a, [[0.5, -2.0]])
  assert keys.unused_array(np.arange(3, dtype=np.int64)).dtype == np.int64  # refused later


def test_float64_values_beyond_float32_are_refused_not_made_inf():
  # The finiteness check looked at the float64 tensor; its float32 conversion held inf.
  from sav_jax.convert import keys  # pylint: disable=import-outside-toplevel
  w = np.array([[0.5, -1e300, 3.0], [2.0, 1e-300, -0.25]])  # Linear (out, in), float64
  arr, problem = keys.converted("fc.weight", w, "kernel", (3, 2))
  assert arr is None and problem == ("key 'fc.weight': 1 of 6 values are NaN or inf once "
                                     "converted to float32 (values beyond its range)")
  w[0, 1] = -1e30
  arr, problem = keys.converted("fc.weight", w, "kernel", (3, 2))
  assert problem is None and arr.dtype == np.float32
  np.testing.assert_array_equal(arr, [[0.5, 2.0], [np.float32(-1e30), 0.0], [3.0, -0.25]])


def test_a_state_dict_of_another_model_is_named_so():
  with pytest.raises(ValueError) as e:
    convert.params_from_state_dict({"encoder.conv.weight": np.zeros((2, 3), np.float32),
                                    "head.bias": np.zeros(2, np.float32)})
  assert e.value.args[0].splitlines()[1] == (
      "  none of the state dict's 2 keys is one of the model's: is it a checkpoint of another "
      "model?"), e.value
  assert len(str(e.value).splitlines()) < 20


def test_depth_prior_is_converted_for_the_configured_encoder():
  # The ViT-L depth prior's keys have ViT-L shapes: only the missing keys are reported.
  cfg = sav_jax.SAVConfig(vda_encoder="vitl")
  sd = {"depthnet.depthanything.pretrained.cls_token": np.zeros((1, 1, 1024), np.float32),
        "depthnet.depthanything.head.projects.3.weight": np.zeros((1024, 1024, 1, 1),
                                                                  np.float32)}
  with pytest.raises(ValueError) as e:
    convert.params_from_state_dict(sd, cfg)
  msg = str(e.value)
  assert "(vitl)" in msg and "missing key" in msg
  assert "wrong shape" not in msg and "cls_token'" not in msg, msg


def test_the_depth_prior_size_is_read_from_the_file(tmp_path, capsys):
  vitl = {"depthnet.depthanything.pretrained.cls_token": np.zeros((1, 1, 1024), np.float32),
          "cnet.conv1.weight": np.zeros((64, 3, 7, 7), np.float32)}
  assert convert.params.vda_encoder_of(vitl) == "vitl"
  assert convert.params.vda_encoder_of({"pretrained.cls_token": np.zeros((1, 1, 384))}, "") == "vits"
  assert convert.params.vda_encoder_of({"pretrained.cls_token": np.zeros((1, 1, 768))}, "") == "vitb"
  assert convert.params.vda_encoder_of({"pretrained.cls_token": np.zeros((1, 1, 1536))}, "") is None
  assert convert.params.vda_encoder_of({}) is None
  # `sav-jax convert` and `sav-jax infer` build the model the file's depth prior needs: the
  # report is against the ViT-L model (its other keys missing), not 500 ViT-S shape errors.
  np.savez(tmp_path / "vitl.npz", **vitl)
  assert cli.main(["convert", str(tmp_path / "vitl.npz"), str(tmp_path / "out")]) == 2
  err = capsys.readouterr().err
  assert "does not match Stereo Any Video (vitl)" in err and "wrong shape" not in err, err
  import cv2  # pylint: disable=import-outside-toplevel
  for view in ("left", "right"):
    (tmp_path / view).mkdir()
    cv2.imwrite(str(tmp_path / view / "0000.png"), np.zeros((32, 32, 3), np.uint8))
  assert cli.main(["infer", "--left", str(tmp_path / "left"), "--right", str(tmp_path / "right"),
                   "--checkpoint", str(tmp_path / "vitl.npz"), "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert "does not match Stereo Any Video (vitl)" in err, err


def test_the_vitb_depth_prior_is_supported():
  # Video-Depth-Anything-Base (video_depth_anything_vitb.pth): its width picks the config,
  # whose model takes its shapes; `sav-jax convert --vda` builds the model around it.
  from sav_jax.model.vda import VideoDepthAnything  # pylint: disable=import-outside-toplevel
  from sav_jax.tools.convert import init_with_vda  # pylint: disable=import-outside-toplevel
  cfg = sav_jax.SAVConfig(vda_encoder="vitb")
  model = VideoDepthAnything(**cfg.vda)
  shapes = jax.eval_shape(model.init, jax.random.PRNGKey(0),
                          jnp.zeros((1, 1, 14, 14, 3), jnp.float32))["params"]
  vda = jax.tree_util.tree_map(lambda s: np.zeros(s.shape, np.float32), shapes)
  sd = convert.vda_state_dict_from_params(vda)
  assert sd["pretrained.cls_token"].shape == (1, 1, 768)
  assert sd["head.projects.3.weight"].shape == (768, 768, 1, 1)
  # the official head's unused regressor: Conv2d(features // 2 = 64, 32, 3)
  assert sd["head.scratch.output_conv2.0.weight"].shape == (32, 64, 3, 3)
  assert convert.params.vda_encoder_of(sd, "") == "vitb"
  variables = init_with_vda(sd, cfg, seed=0)
  assert variables["params"]["depthnet"]["depthanything"]["pretrained"]["cls_token"].shape == (
      1, 1, 768)
  clip = jax.ShapeDtypeStruct((1, 2, 32, 32, 3), jnp.float32)
  out = jax.eval_shape(lambda v, l, r: sav_jax.StereoAnyVideo(cfg).apply(v, l, r, iters=2),
                       {"params": variables["params"]}, clip, clip)
  assert out.disparities.shape == (4, 1, 2, 32, 32)
  # ... and the vits model is told what the file is, and how to configure for it.
  with pytest.raises(ValueError, match=r"the depth prior's weights are vitb \(DINOv2 width 768\); "
                                       r"the model is configured for vits"):
    convert.vda_params_from_state_dict(sd)


def test_non_float_and_non_finite_tensors_are_refused(sav_state_dict):
  sd = dict(sav_state_dict)
  w = sd["cnet.conv1.weight"].copy()
  w.flat[[0, 5]] = [np.nan, np.inf]
  sd["cnet.conv1.weight"] = w
  sd["fnet.conv1.bias"] = sd["fnet.conv1.bias"].astype(np.int32)
  sd["corr_mlp.fc1.weight"] = sd["corr_mlp.fc1.weight"].astype(np.complex64)
  vda = "depthnet.depthanything.pretrained.blocks.0.attn.qkv.bias"
  sd[vda] = np.full_like(sd[vda], np.nan)
  big = sd["fnet.conv1.weight"].astype(np.float64)  # finite, but not in float32
  big.flat[3] = 1e300
  sd["fnet.conv1.weight"] = big
  with pytest.raises(ValueError) as e:
    convert.params_from_state_dict(sd)
  msg = str(e.value)
  for needle in (f"key 'cnet.conv1.weight': 2 of {w.size} values are NaN or inf",
                 "key 'fnet.conv1.bias': dtype int32", "key 'corr_mlp.fc1.weight': dtype complex64",
                 f"key 'fnet.conv1.weight': 1 of {big.size} values are NaN or inf once converted "
                 "to float32", "blocks.0.attn.qkv.bias", "5 problem(s)"):
    assert needle in msg, (needle, msg)
  sd = dict(sav_state_dict)
  sd["cnet.conv1.weight"] = sd["cnet.conv1.weight"].astype(np.float16)  # floats of any width
  assert convert.params_from_state_dict(sd)["params"]["cnet"]["conv1"]["kernel"].dtype == np.float32


def _to_bfloat16(a):
  """float32 rounded to bfloat16 (nearest even) and widened back, as a bf16 file reads."""
  bits = np.asarray(a, np.float32).view(np.uint32).astype(np.uint64)
  bits = (bits + 0x7FFF + ((bits >> 16) & 1)) & 0xFFFF0000
  return bits.astype(np.uint32).view(np.float32)


def test_half_precision_checkpoints_convert(sav_state_dict):
  # A float16 or bfloat16 file holds the motion modules' sinusoidal tables rounded to
  # that type (up to 2.4e-4 / 2.0e-3 from the float32 table, against 1e-5 allowed before),
  # also saved again as float32 (the fp16 release loaded into a float32 model and saved).
  import ml_dtypes  # pylint: disable=import-outside-toplevel  # (JAX's)
  for cast in (lambda a: a.astype(np.float16), _to_bfloat16,
               lambda a: a.astype(np.float16).astype(np.float32),
               # in memory, as JAX or ml_dtypes give them (the tables were refused)
               lambda a: a.astype(ml_dtypes.bfloat16), lambda a: jnp.asarray(a, jnp.bfloat16)):
    sd = {k: cast(v) if v.dtype == np.float32 else v for k, v in sav_state_dict.items()}
    variables = convert.params_from_state_dict(sd)
    params = variables["params"]
    np.testing.assert_allclose(params["cnet"]["conv1"]["kernel"].transpose(3, 2, 0, 1),
                               sav_state_dict["cnet.conv1.weight"], rtol=1e-2, atol=1e-3)
    # exactly the file's half-precision values, widened (float32 holds every one of them)
    np.testing.assert_array_equal(
        params["cnet"]["conv1"]["kernel"].transpose(3, 2, 0, 1),
        np.asarray(cast(sav_state_dict["cnet.conv1.weight"])).astype(np.float32))
    # the tensors kept for export are float32 too: an export is float32 throughout
    unused = variables[convert.params.UNUSED_COLLECTION]
    assert len(unused) >= 2 and {v.dtype for v in unused.values()} == {np.dtype(np.float32)}
  # a float32 table off by 1e-3 is still another table
  key = next(k for k in sav_state_dict if k.endswith(".pos_encoder.pe"))
  sd = dict(sav_state_dict)
  sd[key] = sd[key] + np.float32(1e-3)
  with pytest.raises(ValueError, match="is not the sinusoidal table"):
    convert.params_from_state_dict(sd)
  # also when its low 8 bits are zero (bfloat16's are its low 16)
  sd[key] = (sd[key].view(np.uint32) & np.uint32(0xFFFFFF00)).view(np.float32)
  with pytest.raises(ValueError, match="is not the sinusoidal table"):
    convert.params_from_state_dict(sd)


def test_tensors_kept_for_export_are_checked_as_parameters_are(sav_state_dict):
  # unused by the forward, kept for an exact export: a bad one converted, and the export
  # then failed the official load_state_dict(strict=True)
  qkv = "update_block.time_attn.temporal_attn.qkv.weight"
  conv = "depthnet.depthanything.head.scratch.output_conv2.0.weight"
  for key, bad, problem in (
      (qkv, np.zeros((7, 7), np.float32), f"key '{qkv}': shape (7, 7) does not match Stereo "
       "Any Video (expects (768, 256))"),
      (qkv, np.zeros((768, 256), np.int64), f"key '{qkv}': dtype int64; expected a "
       "floating-point tensor"),
      (conv, np.full_like(sav_state_dict[conv], np.nan), f"key '{conv}': "
       f"{sav_state_dict[conv].size} of {sav_state_dict[conv].size} values are NaN or inf"),
      (qkv, None, f"missing key '{qkv}'"), (conv, None, f"missing key '{conv}'")):  # required
    sd = {k: v for k, v in sav_state_dict.items() if k != key}
    with pytest.raises(ValueError) as e:
      convert.params_from_state_dict(sd if bad is None else {**sd, key: bad})
    assert problem in str(e.value) and "1 problem(s)" in str(e.value), str(e.value)


def test_export_of_trained_params_is_complete(sav_state_dict, variables):
  exported = convert.state_dict_from_params({"params": variables["params"]})  # no torch_unused
  assert sorted(exported) == sorted(sav_state_dict)
  back = convert.params_from_state_dict(exported)
  jax.tree_util.tree_map(np.testing.assert_array_equal, back["params"], variables["params"])
  assert not np.any(exported["depthnet.depthanything.head.scratch.output_conv2.0.weight"])


def test_export_refuses_variables_that_are_not_the_models(tmp_path, variables):
  # A broken tree was written as it was: the file failed only when read back, and with
  # overwrite=True it replaced a good file.
  good = tmp_path / "good.npz"
  convert.export_state_dict(variables, good)
  before = good.read_bytes()
  params = jax.tree_util.tree_map(np.asarray, variables["params"])
  missing = {"params": {k: v for k, v in params.items() if k != "corr_mlp"}}
  nan = {"params": {**params, "cnet": {**params["cnet"], "conv1": {
      **params["cnet"]["conv1"], "bias": np.full_like(params["cnet"]["conv1"]["bias"], np.nan)}}}}
  wrong = {"params": {**params, "corr_mlp": {**params["corr_mlp"], "fc1": {
      **params["corr_mlp"]["fc1"], "kernel": np.zeros((3, 3), np.float32)}}}}
  extra = {"params": {**params, "fnet_extra": {"kernel": np.zeros(2, np.float32)}}}
  for bad, match in ((missing, r"4 missing, e\.g\. \['corr_mlp'\]"),
                     (nan, r"hold NaN or inf values, e\.g\. \['cnet'\]\['conv1'\]\['bias'\]"),
                     (wrong, r": 1 with other shapes, e\.g\. \['corr_mlp'\]\['fc1'\]\['kernel'\] "
                      r"\(3, 3\) \(expected \(324, 256\)\)$"),
                     (extra, r": 1 unexpected, e\.g\. \['fnet_extra'\]\['kernel'\]$"),
                     (params, r"expected Flax variables \{'params': \.\.\.\}, found "
                      r"\['cnet', .*: the parameters alone\? pass \{'params': params\}$")):
    with pytest.raises(convert.CheckpointError, match=match):
      convert.export_state_dict(bad, good, overwrite=True)
  assert good.read_bytes() == before
  vitl = convert.state_dict_from_params  # the depth prior's width picks the config
  with pytest.raises(convert.CheckpointError, match="vda_encoder='vitl'"):
    vitl(variables, sav_jax.SAVConfig(vda_encoder="vitl"))


def test_export_of_another_architecture_uses_its_stored_config(tmp_path, capsys):
  # A model trained with other sizes (--config.model.depth_dim=16 ...): `sav-jax convert`
  # checks it against the config its checkpoint stores, not the paper's architecture.
  from sav_jax.model.init import init_variables  # pylint: disable=import-outside-toplevel
  cfg = sav_jax.SAVConfig(depth_dim=16, fnet_dim=112)
  other = init_variables(cfg, seed=2)
  with pytest.raises(convert.CheckpointError, match=r"cfg=None: the paper's architecture .*pass "
                                                    r"the model's SAVConfig"):
    convert.state_dict_from_params(other)
  sd = convert.state_dict_from_params(other, cfg)
  convert.save_variables(tmp_path / "ckpt", other, {"model": cfg.to_dict()})
  assert cli.main(["convert", str(tmp_path / "ckpt"), str(tmp_path / "out.npz")]) == 0
  back = convert.load_state_dict(tmp_path / "out.npz")
  assert sorted(back) == sorted(sd)
  for k in sd:
    np.testing.assert_array_equal(back[k], sd[k], err_msg=k)


def test_export_of_unusable_parameters_names_the_checkpoint(tmp_path, variables, capsys):
  params = jax.tree_util.tree_map(np.asarray, variables["params"])
  bias = np.full_like(params["cnet"]["conv1"]["bias"], np.nan)
  nan = {"params": {**params, "cnet": {**params["cnet"], "conv1": {
      **params["cnet"]["conv1"], "bias": bias}}}}
  convert.save_variables(tmp_path / "diverged", nan, {"model": sav_jax.SAVConfig().to_dict()})
  assert cli.main(["convert", str(tmp_path / "diverged"), str(tmp_path / "out.npz")]) == 2
  err = capsys.readouterr().err
  assert f"{tmp_path / 'diverged'}: state_dict_from_params: 1 parameter(s) hold NaN" in err
  assert not (tmp_path / "out.npz").exists()


def test_unused_parameters_are_kept_outside_params(variables):
  unused = variables[UNUSED_COLLECTION]
  assert "update_block.time_attn.temporal_attn.qkv.weight" in unused
  assert "depthnet.depthanything.head.scratch.output_conv2.0.weight" in unused
  assert "qkv" not in variables["params"]["update_block"]["time_attn"]["temporal_attn"]


def test_cli_convert_then_model_matches(tmp_path, sav_state_dict, variables, capsys):
  src = tmp_path / "sav.safetensors"
  convert.save_state_dict(sav_state_dict, src)
  dst = tmp_path / "ckpt"
  assert cli.main(["convert", str(src), str(dst)]) == 0
  out = capsys.readouterr().out
  assert "trainable" in out and "frozen" in out
  restored, config = convert.restore_variables(dst)
  assert config["model"] == sav_jax.SAVConfig().to_dict()
  # The same tree, dtypes and values as converting in memory, so the same forward (the
  # model takes the restored variables: traced, not compiled).
  assert (jax.tree_util.tree_structure(restored["params"])
          == jax.tree_util.tree_structure(variables["params"]))
  for got, want in zip(jax.tree_util.tree_leaves(restored["params"]),
                       jax.tree_util.tree_leaves(variables["params"])):
    assert np.asarray(got).dtype == np.asarray(want).dtype
    np.testing.assert_array_equal(got, want)
  clip = jax.ShapeDtypeStruct((1, 2, 32, 32, 3), jnp.float32)
  out = jax.eval_shape(lambda v, l, r: sav_jax.StereoAnyVideo().apply(v, l, r, iters=2),
                       {"params": restored["params"]}, clip, clip)
  assert out.disparities.shape == (4, 1, 2, 32, 32)
  # Exporting the orbax checkpoint gives back the official file.
  exported = tmp_path / "back.npz"
  assert cli.main(["convert", str(dst), str(exported)]) == 0
  _assert_same_state_dicts(convert.load_state_dict(exported), sav_state_dict)
  # Never overwrite silently.
  assert cli.main(["convert", str(src), str(dst)]) == 2
  assert "exists" in capsys.readouterr().err
  # An orbax checkpoint is exported to a file, not copied to another folder; --vda takes a file.
  for flags, message in (([str(dst), str(tmp_path / "copy")], "is already an orbax variables "
                          "checkpoint: name a .safetensors/.npz/.pth"),
                         (["--vda", str(dst), str(tmp_path / "v.npz")], "--vda takes a Video "
                          "Depth Anything file, not a folder")):
    assert cli.main(["convert", *flags]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
  assert not (tmp_path / "copy").exists() and not (tmp_path / "v.npz").exists()


def test_cli_convert_vda_only(tmp_path, vda_state_dict, capsys, caplog):
  src = tmp_path / "video_depth_anything_vits.npz"
  convert.save_state_dict(vda_state_dict, src)
  assert cli.main(["convert", str(src), str(tmp_path / "a")]) == 2  # needs --vda
  assert ("is a Video Depth Anything (depth prior only) checkpoint, not a Stereo Any Video one; "
          "add --vda") in capsys.readouterr().err
  sav = tmp_path / "sav.npz"
  np.savez(sav, **{"fnet.conv1.weight": np.zeros((3, 3), np.float32)})
  assert cli.main(["convert", "--vda", str(sav), str(tmp_path / "c")]) == 2
  assert "sav.npz is a Stereo Any Video checkpoint, not a Video Depth" in capsys.readouterr().err
  assert not (tmp_path / "a").exists() and not (tmp_path / "c").exists()
  assert cli.main(["convert", "--vda", str(src), str(tmp_path / "b"), "--seed", "-1"]) == 2
  assert "--seed must be >= 0, got -1" in capsys.readouterr().err
  assert cli.main(["convert", "--vda", str(src), str(tmp_path / "b")]) == 0
  restored, _ = convert.restore_variables(tmp_path / "b")
  vda, _ = convert.vda_params_from_state_dict(vda_state_dict)
  jax.tree_util.tree_map(np.testing.assert_array_equal,
                         restored["params"]["depthnet"]["depthanything"], vda)
  assert "fnet" in restored["params"]
  # Only the depth prior is trained: the tools that run the weights say so.
  from sav_jax.tools.infer import load_checkpoint  # pylint: disable=import-outside-toplevel
  with caplog.at_level(logging.WARNING):
    load_checkpoint(tmp_path / "b")
  assert "b: only its depth prior is trained (the output of `sav-jax convert --vda`" in \
      caplog.text, caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):  # a file cannot record it: said when it is written
    assert cli.main(["convert", "--vda", str(src), str(tmp_path / "init.safetensors")]) == 0
  assert "init.safetensors holds a freshly initialised stereo network (seed 0)" in caplog.text
  caplog.clear()
  with caplog.at_level(logging.WARNING):  # exporting the orbax one to a file says so too
    assert cli.main(["convert", str(tmp_path / "b"), str(tmp_path / "b.npz")]) == 0
  assert (f"{tmp_path / 'b'}: only its depth prior is trained (the output of `sav-jax convert "
          f"--vda`") in caplog.text and f"({tmp_path / 'b.npz'} will not record it)" in \
      caplog.text, caplog.text


def test_cli_convert_vda_initialises_the_model_of_the_files_prior_with_the_seed(
    tmp_path, capsys, monkeypatch):
  # `sav-jax convert --vda video_depth_anything_vitb.pth` builds the ViT-B model, seeded with
  # --seed (the initialisation itself stands in here: it is what the other tests run).
  from sav_jax.model import init  # pylint: disable=import-outside-toplevel
  calls = []

  def fake_init(cfg, seed):
    calls.append((cfg.vda_encoder, seed))
    raise ValueError("stopped before the initialisation")

  monkeypatch.setattr(init, "init_variables", fake_init)
  src = tmp_path / "video_depth_anything_vitb.npz"
  np.savez(src, **{"pretrained.cls_token": np.zeros((1, 1, 768), np.float32),
                   "head.scratch.output_conv1.bias": np.zeros(32, np.float32)})
  assert cli.main(["convert", "--vda", "--seed", "7", str(src), str(tmp_path / "out")]) == 2
  assert "stopped before the initialisation" in capsys.readouterr().err
  assert calls == [("vitb", 7)]
  assert not (tmp_path / "out").exists()


def test_cli_convert_file_to_file_and_destination_checks(tmp_path, sav_state_dict, capsys):
  src = tmp_path / "sav.npz"
  np.savez(src, **sav_state_dict)
  dst = tmp_path / "sav.safetensors"
  assert cli.main(["convert", str(src), str(dst)]) == 0  # checked, then the official names
  assert dst.is_file()
  _assert_same_state_dicts(convert.load_state_dict(dst), sav_state_dict)
  dst.write_bytes(b"stale")  # an existing file is replaced with --overwrite only
  assert cli.main(["convert", str(src), str(dst)]) == 2
  assert "exists; pass --overwrite" in capsys.readouterr().err and dst.read_bytes() == b"stale"
  assert cli.main(["convert", str(src), str(dst), "--overwrite"]) == 0
  _assert_same_state_dicts(convert.load_state_dict(dst), sav_state_dict)
  (tmp_path / "notes.txt").write_text("mine")
  (tmp_path / "folder.npz").mkdir()
  (tmp_path / "folder").mkdir()
  (tmp_path / "folder" / "a.txt").write_text("mine")
  for dst, message in ((src, "SRC and DST are the same path"),
                       (tmp_path / "folder" / ".." / src.name, "SRC and DST are the same path"),
                       (tmp_path / "folder.npz", "is not a file; it is not replaced"),
                       (tmp_path / "notes.txt", "is not a `sav-jax convert` variables folder"),
                       (tmp_path / "folder", "is not a `sav-jax convert` variables folder"),
                       (tmp_path / "sav.ckpt", "cannot write a .ckpt file"),
                       # a typo for .npz made an orbax folder named weights.npy
                       (tmp_path / "weights.npy", "cannot write a .npy file"),
                       # a traceback after the whole conversion before
                       (tmp_path / "notes.txt" / "odir", "notes.txt is a file, not a folder"),
                       (tmp_path / "notes.txt" / "a" / "x.npz",
                        "notes.txt is a file, not a folder")):
    assert cli.main(["convert", str(src), str(dst), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
  assert (tmp_path / "notes.txt").read_text() == "mine"
  assert (tmp_path / "folder" / "a.txt").read_text() == "mine"
  assert not (tmp_path / "sav.ckpt").exists() and not (tmp_path / "weights.npy").exists()
  # A link to an empty folder is not an empty folder made for the checkpoint: replaced with
  # --overwrite only. A dangling link is not nothing, and not written through: named as what it
  # is (it was "exists; pass --overwrite", then with it "exists and is not a file").
  (tmp_path / "empty_target").mkdir()
  (tmp_path / "link").symlink_to(tmp_path / "empty_target")
  (tmp_path / "dangling.npz").symlink_to(tmp_path / "nowhere.npz")
  assert cli.main(["convert", str(src), str(tmp_path / "link")]) == 2
  assert "exists; pass --overwrite" in capsys.readouterr().err
  for dst, overwrite in (("dangling.npz", []), ("dangling.npz", ["--overwrite"])):
    assert cli.main(["convert", str(src), str(tmp_path / dst), *overwrite]) == 2
    assert (f"dangling.npz is a symbolic link to a missing path ({tmp_path / 'nowhere.npz'})"
            in capsys.readouterr().err)
  assert not any((tmp_path / "empty_target").iterdir()) and (tmp_path / "dangling.npz").is_symlink()
  assert not (tmp_path / "nowhere.npz").exists()
  (tmp_path / "empty").mkdir()  # an empty folder made for the checkpoint: nothing to replace
  assert cli.main(["convert", str(src), str(tmp_path / "empty")]) == 0
  assert convert.is_variables_checkpoint(tmp_path / "empty")
  assert cli.main(["convert", str(tmp_path / "folder"), str(tmp_path / "x.npz")]) == 2
  err = capsys.readouterr().err
  assert "folder" in err and "not a regular file" not in err and err.count("\n") == 1, err
  bad = dict(sav_state_dict, **{"fnet.conv1.weight": np.zeros((2, 2), np.float32)})
  np.savez(tmp_path / "bad.npz", **bad)
  assert cli.main(["convert", str(tmp_path / "bad.npz"), str(tmp_path / "y.npz")]) == 2
  err = capsys.readouterr().err  # the report says which file its keys are of
  assert f"{tmp_path / 'bad.npz'}: state dict does not match" in err and "fnet.conv1" in err, err
  try:
    import torch  # pylint: disable=import-outside-toplevel,unused-import
  except ImportError:  # refused before the conversion
    assert cli.main(["convert", str(src), str(tmp_path / "w.bin")]) == 2
    assert "writing .bin needs torch" in capsys.readouterr().err


def test_cli_convert_rejects_garbage(tmp_path, capsys):
  bad = tmp_path / "random.pth"
  bad.write_bytes(np.random.default_rng(0).bytes(1000))
  assert cli.main(["convert", str(bad), str(tmp_path / "out")]) == 2
  assert "random.pth" in capsys.readouterr().err
  assert not (tmp_path / "out").exists()


def test_cli_convert_with_paths_that_are_not_utf8(tmp_path, sav_state_dict, capsys, caplog):
  """Latin-1 bytes in a folder's name (a zip made on Windows): files are read and written;
  an orbax DST is refused before the conversion's work (orbax's TensorStore failed after it,
  with a traceback: "Unable to cast Python instance of type <class 'str'>")."""
  import os  # pylint: disable=import-outside-toplevel
  # (pytest-xdist cannot send a report whose captured log holds the path's surrogates)
  caplog.set_level(logging.WARNING, logger="sav_jax.convert.torch_io")
  odd = tmp_path / os.fsdecode(b"caf\xe9")
  odd.mkdir()
  np.savez(odd / "sav.npz", **sav_state_dict)
  assert cli.main(["convert", str(odd / "sav.npz"), str(odd / "sav.safetensors")]) == 0
  _assert_same_state_dicts(convert.load_state_dict(odd / "sav.safetensors"), sav_state_dict)
  assert "caf\\udce9/sav.safetensors (official" in capsys.readouterr().out
  assert cli.main(["convert", str(odd / "sav.npz"), str(odd / "ckpt")]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and ("caf\\udce9/ckpt': the orbax checkpoint folder DST's name is "
                                   "not UTF-8 text") in err, err
  assert sorted(p.name for p in odd.iterdir()) == ["sav.npz", "sav.safetensors"]


def test_a_whole_state_dict_converts_without_a_trace_of_the_depth_prior_alone(
    sav_state_dict, variables, monkeypatch):
  """The whole model's shapes (`abstract_variables`, traced once) hold the depth prior's: a
  conversion does not trace the prior on its own as well (~1.8 s on the 2-core CPU), nor
  does `sav-jax convert --vda`'s model around a depth prior's file."""
  from sav_jax.convert import vda  # pylint: disable=import-outside-toplevel
  from sav_jax.tools.convert import init_with_vda  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(vda, "_abstract_params", lambda model: pytest.fail("traced the prior"))
  got = convert.params_from_state_dict(sav_state_dict)
  jax.tree_util.tree_map(np.testing.assert_array_equal, got["params"], variables["params"])
  prefix = convert.params.VDA_PREFIX
  whole = init_with_vda({k[len(prefix):]: v for k, v in sav_state_dict.items()
                         if k.startswith(prefix)}, sav_jax.SAVConfig(), seed=0)
  jax.tree_util.tree_map(np.testing.assert_array_equal,
                         whole["params"]["depthnet"]["depthanything"],
                         variables["params"]["depthnet"]["depthanything"])

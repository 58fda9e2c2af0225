"""Model structure, input validation, gradients and shape generality."""

import dataclasses
import warnings

import flax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sav_jax
from sav_jax.model import init as init_lib
from sav_jax.model.init import abstract_variables, init_variables

SHAPE = (1, 2, 32, 48, 3)  # B, T, H, W, C: smallest shape with a 2x3 grid at 1/16

pytestmark = pytest.mark.usefixtures("fast_compile")


@pytest.fixture(scope="module")
def model():
  return sav_jax.StereoAnyVideo()


@pytest.fixture(scope="module")
def variables():
  return jax.tree_util.tree_map(jnp.asarray, init_variables(seed=1))


@pytest.fixture(scope="module")
def clip():
  rng = np.random.default_rng(3)
  left = rng.uniform(0, 255, SHAPE).astype(np.float32)
  right = np.roll(left, -3, axis=3)
  return jnp.asarray(left), jnp.asarray(right)


def test_parameter_tree_matches_the_official_manifest(fixtures_dir):
  import json
  manifest = json.loads((fixtures_dir / "sav_manifest.json").read_text())
  used = sum(int(np.prod(e["shape"])) for e in manifest["keys"]
             if e["kind"] == "parameter" and e["used_in_forward"])
  shapes = abstract_variables(sav_jax.SAVConfig())["params"]
  assert sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(shapes)) == used
  assert set(shapes) == {"cnet", "fnet", "depthnet", "corr_mlp", "update_block"}


def test_compute_settings_share_the_parameter_shapes():
  """`abstract_variables` traces once for configs that differ only in how the model
  computes; a real trace of such a model gives that very tree (shapes and float32)."""
  base = sav_jax.SAVConfig()
  other = sav_jax.SAVConfig(dtype="bfloat16", remat=True, remat_policy="dots_saveable",
                            frame_block_mb=1.0, vit_attention="blocked", gru_conv="direct")
  assert set(init_lib.COMPUTE_FIELDS) == {f.name for f in dataclasses.fields(base)
                                          if getattr(base, f.name) != getattr(other, f.name)}
  assert all(a is b for a, b in zip(jax.tree.leaves(abstract_variables(other)),
                                    jax.tree.leaves(abstract_variables(base))))  # one trace
  # each call's dicts are its own: editing one (a trimmed restore target) changes no other
  mine = abstract_variables(base)
  mine["params"].pop("corr_mlp")
  mine["params"]["fnet"].clear()
  assert set(abstract_variables(base)["params"]) == {"cnet", "fnet", "depthnet", "corr_mlp",
                                                     "update_block"}
  assert abstract_variables(other)["params"]["fnet"]
  assert "corr_mlp" in init_variables(base)["params"]
  dummy = jax.ShapeDtypeStruct((1, 2, 64, 64, 3), jnp.float32)
  traced = jax.eval_shape(lambda l, r: sav_jax.StereoAnyVideo(other).init(
      jax.random.PRNGKey(0), l, r, iters=2), dummy, dummy)
  assert jax.tree.structure(traced) == jax.tree.structure(abstract_variables(base))
  for got, want in zip(jax.tree.leaves(traced), jax.tree.leaves(abstract_variables(base))):
    assert (got.shape, got.dtype) == (want.shape, want.dtype) and got.dtype == jnp.float32


@pytest.mark.parametrize("left_shape,right_shape,iters,match", [
    ((1, 2, 32, 48, 3), (1, 2, 32, 48, 3), 1, "an integer >= 2"),
    ((1, 2, 32, 48, 3), (1, 2, 32, 48, 3), 0, "an integer >= 2"),
    ((1, 2, 32, 48, 3), (1, 2, 32, 48, 3), True, "an integer >= 2"),
    ((1, 2, 32, 48, 3), (1, 2, 32, 48, 3), 2.0, "an integer >= 2"),
    ((1, 2, 32, 48, 1), (1, 2, 32, 48, 1), 2, r"RGB.*\(one channel\? repeat it: np\.repeat"),
    ((2, 32, 48, 3), (2, 32, 48, 3), 2, r"RGB.*\(a batch of one video is video\[None\]\)"),
    ((1, 2, 32, 48, 4), (1, 2, 32, 48, 4), 2, r"RGB.*\(RGBA\? drop the alpha channel"),
    ((1, 2, 32, 48, 3), (1, 3, 32, 48, 3), 2, "differ in shape"),
    ((1, 2, 40, 48, 3), (1, 2, 40, 48, 3), 2, "multiples of 16"),
    ((1, 0, 32, 48, 3), (1, 0, 32, 48, 3), 2, r"B, T, H, W >= 1"),
    ((0, 2, 32, 48, 3), (0, 2, 32, 48, 3), 2, r"B, T, H, W >= 1"),
])
def test_bad_inputs_raise_clear_errors(model, left_shape, right_shape, iters, match):
  left, right = jnp.zeros(left_shape), jnp.zeros(right_shape)
  with pytest.raises(ValueError, match=match):
    jax.eval_shape(lambda l, r: model.init(jax.random.PRNGKey(0), l, r, iters=iters), left, right)


def test_frame_feature_entry_points_check_sizes(model):
  # from_frame_features ran 20x40 frames (the 1/8 -> 1/4 hand-over scale then 5/8), and a
  # wrong size failed deep inside a concatenation or a reshape.
  params = abstract_variables(sav_jax.SAVConfig())
  frames = jax.ShapeDtypeStruct((1, 2, 32, 48, 3), jnp.float32)
  method = sav_jax.StereoAnyVideo.frame_features
  feats = jax.eval_shape(lambda v, l, r: model.apply(v, l, r, method=method), params, frames,
                         frames)
  run = lambda size, f=feats: jax.eval_shape(  # noqa: E731
      lambda v, f: model.apply(v, f, size, 2, method=sav_jax.StereoAnyVideo.from_frame_features),
      params, f)
  assert run((32, 48)).disparities.shape == (1, 1, 2, 32, 48)
  for size, match in (((20, 40), "multiples of 16"),
                      ((48, 32), r"do not fit 48x32 frames: fnet \(2, 2, 8, 12, 96\)"),
                      ((32, 64), "do not fit 32x64 frames"), ((32,), "height, width"),
                      ((32.5, 48), "two integers")):
    with pytest.raises(ValueError, match=match):
      run(size)
  with pytest.raises(ValueError, match=r"frame_features' dict \(tokens, fnet, cnet\)"):
    run((32, 48), {"fnet": feats["fnet"]})
  cnet = jax.ShapeDtypeStruct((2, *feats["cnet"].shape[1:]), jnp.float32)  # another batch's
  with pytest.raises(ValueError, match=r"do not fit 32x48 frames: .* cnet \(2, 2, 8, 12, 96\)"):
    run((32, 48), {**feats, "cnet": cnet})
  # iters and final_only are checked as __call__ checks them (iters=1 has no 1/16 step)
  call = lambda **kw: jax.eval_shape(  # noqa: E731
      lambda v, f: model.apply(v, f, (32, 48), method=sav_jax.StereoAnyVideo.from_frame_features,
                               **kw), params, feats)
  assert call(iters=2, final_only=False).disparities.shape == (4, 1, 2, 32, 48)
  with pytest.raises(ValueError, match=r"iters must be an integer >= 2 .* got 1"):
    call(iters=1)
  with pytest.raises(ValueError, match=r"iters must be an integer >= 2 .* got 2.5"):
    call(iters=2.5)
  with pytest.raises(ValueError, match="final_only must be True or False, got 'no'"):
    call(iters=2, final_only="no")
  odd = jax.ShapeDtypeStruct((1, 2, 20, 40, 3), jnp.float32)
  with pytest.raises(ValueError, match="multiples of 16, got 20x40"):
    jax.eval_shape(lambda v, l, r: model.apply(v, l, r, method=method), params, odd, odd)
  # Width 16: a 1-pixel-wide map at 1/16, where the official sampler gives NaN everywhere
  # (sav-jax returned numbers no reference checks); height 16 has the official guard.
  narrow = jax.ShapeDtypeStruct((1, 2, 32, 16, 3), jnp.float32)
  with pytest.raises(ValueError, match=r"width 16 is refused: at 1/16 the feature map is 1 "
                     r"pixel wide, where the official model's sampler divides by zero"):
    jax.eval_shape(lambda v, l, r: model.apply(v, l, r, iters=2), params, narrow, narrow)
  low = jax.ShapeDtypeStruct((1, 2, 16, 32, 3), jnp.float32)
  out = jax.eval_shape(lambda v, l, r: model.apply(v, l, r, iters=2), params, low, low)
  assert out.disparities.shape == (4, 1, 2, 16, 32)


@pytest.mark.parametrize("dtype", [jnp.bool_, jnp.complex64])
def test_frames_of_a_non_numeric_dtype_are_refused(model, dtype):
  left = jnp.zeros((1, 2, 32, 48, 3), dtype)
  with pytest.raises(ValueError, match=f"left has dtype {jnp.dtype(dtype).name}; expected RGB"):
    jax.eval_shape(lambda l, r: model.init(jax.random.PRNGKey(0), l, r, iters=2), left, left)


def test_frames_given_as_lists_are_refused(model):
  frames = np.zeros((1, 2, 32, 48, 3)).tolist()
  with pytest.raises(ValueError, match="left must be an array .* got a list"):
    model.init(jax.random.PRNGKey(0), frames, frames, iters=2)


def test_concrete_frames_are_checked_for_values_as_predict_video_checks_them(model, variables):
  """A model call outside jit/grad sees the frames' values: NaN frames (a NaN output
  everywhere) and normalised ones are refused, 0..1 frames warned about (once per view, not
  again by the feature stage), naming the view and the frame (counted over the batch's clips)
  and the caller's line; bfloat16 frames are checked as floats; traced frames cannot be."""
  frames = np.full((2, *SHAPE[1:]), 100.0, np.float32)
  nan = frames.copy()
  nan[1, 0, 3, 5, 0] = np.nan
  with (pytest.warns(UserWarning, match=r"left \(its 2 clips' frames in order, 2 each\): float "
                     r"frames with values 0\.392157\.\.0\.392157: .*multiply 0\.\.1 images by "
                     "255") as record,
        pytest.raises(ValueError, match=r"right \(its 2 clips' frames in order, 2 each\): "
                      r"non-finite values \(NaN/inf\) in frame\(s\) \[2\]")):
    model.apply(variables, frames / 255, nan, iters=2)
  assert len(record) == 1 and record[0].filename == __file__  # not Flax's or the package's
  with pytest.raises(ValueError, match=r"^right: non-finite values \(NaN/inf\) in frame\(s\) "
                     r"\[0\]"):
    model.apply(variables, jnp.asarray(frames[:1], jnp.bfloat16),
                jnp.asarray(nan[1:], jnp.bfloat16), iters=2)
  with pytest.raises(ValueError, match=r"left: float frames with values -1\.7\.\.1\.3 look "
                     "normalised"):
    normalised = np.broadcast_to(np.float32([1.3, -1.7, -1.7]), SHAPE)  # (x / 255 - mean) / std
    model.apply(variables, normalised, frames[:1], iters=2)
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    out = jax.eval_shape(lambda l, r: model.apply(variables, l, r, iters=2, final_only=True),
                         frames / 255, frames / 255)
  assert out.disparities.shape == (1, 2, *SHAPE[1:4])


def test_one_odd_clip_in_a_batch_is_found(model, variables):
  """One clip of 0..1 or normalised frames beside 0..255 clips left the batch's range (and
  its 99.9% quantile) as 0..255 frames': it passed a model call without a word. Each clip
  is looked at alone too; the first odd one is named, once per view."""
  rng = np.random.default_rng(4)
  frames = rng.uniform(0, 255, (3, *SHAPE[1:])).astype(np.float32)
  unit = frames.copy()
  unit[1] /= 255
  nan = frames.copy()
  nan[2, 1, 0, 0, 0] = np.nan
  with (pytest.warns(UserWarning, match=r"^left clip 1 \(of 3\): float frames with values "
                     r"[\d.e-]+\.\.0\.99\d*: .*multiply 0\.\.1 images by 255") as record,
        pytest.raises(ValueError, match=r"right \(its 3 clips' frames in order, 2 each\): "
                      r"non-finite values \(NaN/inf\) in frame\(s\) \[5\]")):
    model.apply(variables, unit, nan, iters=2)
  assert len(record) == 1 and record[0].filename == __file__
  normalised = frames.copy()
  normalised[2] = (normalised[2] / 255 - 0.45) / 0.225
  with pytest.raises(ValueError, match=r"^left clip 2 \(of 3\): float frames with values "
                     r"-[\d.]+\.\.[\d.]+ look normalised"):
    model.apply(variables, normalised, frames, iters=2)


def test_numpy_integer_iters_accepted(model):
  """`iters=np.int64(2)` (e.g. from a config array) runs like `iters=2`."""
  left = jnp.zeros((1, 2, 32, 48, 3))
  shapes = jax.eval_shape(
      lambda l, r: model.init_with_output(jax.random.PRNGKey(0), l, r, iters=np.int64(2))[0],
      left, left)
  assert shapes.disparities.shape == (4, 1, 2, 32, 48)  # 1 at 1/16, 1 at 1/8, 2 at 1/4


def test_odd_iters_run_as_the_official_cascade(model):
  """iters=3: 1 + 1 + 3 predictions, as the official model gives; 1 has no 1/16 step."""
  left = jnp.zeros((1, 2, 32, 48, 3))
  shapes = jax.eval_shape(
      lambda l, r: model.init_with_output(jax.random.PRNGKey(0), l, r, iters=3)[0], left, left)
  assert shapes.disparities.shape == (5, 1, 2, 32, 48)
  with pytest.raises(ValueError, match=r"iters must be an integer >= 2 .* got 1"):
    jax.eval_shape(lambda l, r: model.init(jax.random.PRNGKey(0), l, r, iters=1), left, left)
  with pytest.raises(ValueError, match=r"iters must be a Python integer, got the traced .*"
                                       r"static_argnames='iters'"):  # jax.jit(model.apply)
    jax.eval_shape(lambda l, r, i: model.init(jax.random.PRNGKey(0), l, r, iters=i), left,
                   left, 4)


def test_bad_config_raises():
  with pytest.raises(ValueError, match="vda_encoder"):
    sav_jax.SAVConfig(vda_encoder="vitx")
  with pytest.raises(ValueError, match="dtype"):
    sav_jax.SAVConfig(dtype="float16")


@pytest.mark.parametrize("fields,match", [
    ({"hidden_dim": "abc"}, r"SAVConfig\.hidden_dim='abc' \(builtins\.str\); expected int"),
    ({"corr_groups": True}, r"SAVConfig\.corr_groups=True \(builtins\.bool\); expected int"),
    ({"hidden_dim": 0}, r"SAVConfig\.hidden_dim must be >= 1"),
    ({"frame_block_mb": "1"}, r"SAVConfig\.frame_block_mb='1' \(builtins\.str\); expected float"),
    ({"remat": 1}, r"SAVConfig\.remat=1 \(builtins\.int\); expected bool"),
    ({"frame_block_mb": True}, r"SAVConfig\.frame_block_mb=True \(builtins\.bool\); expected float"),
    ({"dtype": None}, r"SAVConfig\.dtype=None \(builtins\.NoneType\); expected str"),
    ({"remat_policy": "bogus"}, r"remat_policy='bogus'; expected None or one of .*dots_saveable"),
    # the policy itself (as jax.checkpoint takes it): its name is what the field holds
    ({"remat": True, "remat_policy": jax.checkpoint_policies.dots_saveable},
     r"remat_policy=.*; expected Optional\[str\] \(the name .*'dots_saveable', not the policy\)"),
    # a factory of policies (called with names), not a policy: refused even with remat=True
    ({"remat": True, "remat_policy": "save_only_these_names"},
     r"remat_policy='save_only_these_names'; expected None or one of"),
    ({"remat_policy": "dots_saveable"}, r"remat_policy='dots_saveable' has no effect with remat=False"),
    ({"hidden_dim": 64}, r"SAVConfig\.hidden_dim=64: the model supports only 128"),
    ({"context_dim": 160, "fnet_dim": 128}, r"context_dim=160: the model supports only 128"),
    ({"upsample_rate": 2}, r"upsample_rate=2: the model supports only 4"),
    ({"corr_groups": 5}, r"corr_groups=5 must divide the 128 feature channels"),
    ({"hiden_dim": 128}, r"unknown SAVConfig fields \['hiden_dim'\]; known: \['context_dim'"),
    ({"depth_dim": 16}, r"depth_dim \+ fnet_dim must equal context_dim \(16 \+ 96 != 128\)"),
    ({"frame_block_mb": float("inf")}, r"frame_block_mb must be a finite number > 0"),
    ({"frame_block_mb": 0}, r"frame_block_mb must be a finite number > 0, got 0\.0"),
])
def test_config_fields_of_the_wrong_type_or_value_are_named(fields, match):
  """A config read from a checkpoint's JSON fails here, not deep inside JAX at trace time."""
  with pytest.raises(ValueError, match=match):
    sav_jax.SAVConfig.from_dict(fields)


def test_config_accepts_ints_for_floats_and_named_remat_policies():
  cfg = sav_jax.SAVConfig(frame_block_mb=512, remat=True, remat_policy="dots_saveable")
  assert cfg.frame_block_mb == 512 and cfg.remat_policy == "dots_saveable"
  assert sav_jax.SAVConfig.from_dict(cfg.to_dict()) == cfg
  # one group is a divisor of the 128 correlation channels too (the int fields' floor is 1)
  assert sav_jax.SAVConfig(corr_groups=1).corr_groups == 1
  with pytest.raises(ValueError, match="SAVConfig mapping"):
    sav_jax.SAVConfig.from_dict(["hidden_dim"])
  # numpy scalars (e.g. from a config array) are taken as the Python values they stand for
  npcfg = sav_jax.SAVConfig(hidden_dim=np.int64(128), remat=np.True_,
                            frame_block_mb=np.float32(512))
  assert npcfg == sav_jax.SAVConfig(remat=True, frame_block_mb=512.0)
  assert type(npcfg.hidden_dim) is int and type(npcfg.remat) is bool
  with pytest.raises(ValueError, match=r"remat=np.int64\(1\) \(numpy\.int64\); expected bool"):
    sav_jax.SAVConfig(remat=np.int64(1))
  # any mapping: a ConfigDict (training configs) or a FrozenDict
  import flax  # pylint: disable=import-outside-toplevel
  import ml_collections  # pylint: disable=import-outside-toplevel
  for mapping in (ml_collections.ConfigDict({"remat": True}), flax.core.FrozenDict(remat=True)):
    assert sav_jax.SAVConfig.from_dict(mapping) == sav_jax.SAVConfig(remat=True)


def test_config_defaults_and_derived_settings():
  """The documented defaults, and the depth prior's and compute dtype's settings derived
  from the fields (Video Depth Anything's `model_configs`: vitl's DPT head has 256 features
  and out_channels 256, 512, 1024, 1024)."""
  cfg = sav_jax.SAVConfig()
  assert (cfg.frame_block_mb, cfg.detach_flow, cfg.compute_dtype) == (1024.0, True, jnp.float32)
  assert (cfg.vda_encoder, cfg.dtype, cfg.remat, cfg.remat_policy, cfg.vit_attention,
          cfg.gru_conv) == ("vits", "float32", False, None, "auto", "auto")
  # design.md: features [VDA 32 | fnet 96] = 128 channels, correlated in 4 groups; a 128-channel
  # GRU; convex upsampling from 1/4 resolution
  assert (cfg.depth_dim, cfg.fnet_dim, cfg.context_dim, cfg.corr_groups, cfg.hidden_dim,
          cfg.upsample_rate) == (32, 96, 128, 4, 128, 4)
  assert cfg.vda == dict(encoder="vits", features=64, out_channels=(48, 96, 192, 384))
  assert sav_jax.SAVConfig(vda_encoder="vitb").vda == dict(
      encoder="vitb", features=128, out_channels=(96, 192, 384, 768))
  assert sav_jax.SAVConfig(dtype="bfloat16").compute_dtype == jnp.bfloat16
  assert sav_jax.SAVConfig(dtype=np.dtype(np.float32)).dtype == "float32"  # a dtype object
  assert sav_jax.SAVConfig(vda_encoder="vitl").vda == dict(
      encoder="vitl", features=256, out_channels=(256, 512, 1024, 1024))


def test_a_dict_for_the_config_is_named_everywhere():
  # A dict where a SAVConfig belongs failed deep inside (dataclasses.replace, a FrozenDict
  # without compute_dtype); every entry point now names it.
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  fields = {"vda_encoder": "vits"}
  x = jax.ShapeDtypeStruct((1, 2, 32, 32, 3), jnp.float32)
  for call in (lambda: init_variables(fields), lambda: init_variables("vitl"),
               lambda: abstract_variables(fields),
               lambda: sav_jax.convert.params_from_state_dict({}, fields),
               lambda: inference.estimate_memory_bytes(2, 32, 32, cfg=fields),
               lambda: jax.eval_shape(lambda l, r: sav_jax.StereoAnyVideo(fields).init(
                   jax.random.PRNGKey(0), l, r, iters=2), x, x),
               lambda: jax.eval_shape(lambda l, r: sav_jax.StereoAnyVideo(None).init(
                   jax.random.PRNGKey(0), l, r, iters=2), x, x)):
    with pytest.raises(TypeError, match=r"must be a sav_jax\.SAVConfig \(SAVConfig\.from_dict"):
      call()


def test_fresh_depth_prior_is_initialised_as_the_official_constructors_do(variables):
  # DINOv2's init_weights (Linear N(0, 0.02), zero biases, class token N(0, 1e-6)), the
  # motion modules' zeroed proj_out (identity residuals), PyTorch defaults elsewhere.
  vda = variables["params"]["depthnet"]["depthanything"]
  block = vda["pretrained"]["blocks_0"]
  assert 0.018 < float(jnp.std(block["attn"]["qkv"]["kernel"])) < 0.022
  assert not jnp.any(block["attn"]["qkv"]["bias"]) and not jnp.any(block["mlp"]["fc2"]["bias"])
  assert float(jnp.abs(vda["pretrained"]["cls_token"]).max()) < 1e-5
  for i in range(4):
    out = vda["head"][f"motion_modules_{i}"]["temporal_transformer"]["proj_out"]
    assert not jnp.any(out["kernel"]) and not jnp.any(out["bias"])
  patch = vda["pretrained"]["patch_embed"]["proj"]  # a convolution: bound 1/sqrt(fan_in)
  bound = 1 / np.sqrt(14 * 14 * 3)
  assert float(jnp.abs(patch["bias"]).max()) <= bound and float(jnp.std(patch["bias"])) > 0.5 * bound / np.sqrt(3)


def test_fresh_depth_prior_head_and_embeddings_are_initialised_as_officially(variables):
  # Outside DINOv2 (the DPT head, its motion modules) PyTorch's defaults hold: Linear weight
  # and bias U(+-1/sqrt(fan_in)), not DINOv2's N(0, 0.02) and zero biases; the position
  # embedding is N(0, 0.02), LayerScale's gamma 1.
  vda = variables["params"]["depthnet"]["depthanything"]
  attn = vda["head"]["motion_modules_0"]["temporal_transformer"]["transformer_blocks_0"][
      "attention_blocks_0"]
  for name in ("to_q", "to_out_0"):
    w = np.asarray(attn[name]["kernel"])
    bound = 1 / np.sqrt(w.shape[0])
    assert np.abs(w).max() <= bound and abs(w.std() / (bound / np.sqrt(3)) - 1) < 0.05, name
  b = np.asarray(attn["to_out_0"]["bias"])
  assert 0.5 / np.sqrt(len(b)) < np.abs(b).max() <= 1 / np.sqrt(len(b))
  pos = np.asarray(vda["pretrained"]["pos_embed"])
  assert 0.019 < pos.std() < 0.021 and abs(pos.mean()) < 0.002, (pos.std(), pos.mean())
  assert np.all(np.asarray(vda["pretrained"]["blocks_0"]["ls1"]["gamma"]) == 1)


def test_fresh_weights_outside_the_depth_prior_follow_the_official_initialisation(variables):
  # The official model: fnet/cnet (BasicEncoder) conv weights kaiming_normal_(fan_out, relu),
  # i.e. N(0, 2 / fan_out) with fan_out = out * kh * kw; temporal_fc zeroed (update.py); norms
  # 1 and 0; every other Conv/Linear PyTorch's default: weight and bias U(+-1/sqrt(fan_in)),
  # fan_in = in * kh * kw (of the weight, for the bias too), whose std is bound / sqrt(3).
  # Bounds are exact; the spreads of tensors of >= 500 values are checked within 12 %
  # (sampling error of a std from 500 draws: ~3 %).
  flat = {k: np.asarray(v) for k, v in
          flax.traverse_util.flatten_dict(variables["params"]).items()
          if k[:2] != ("depthnet", "depthanything")}
  seen = {"kaiming": 0, "default": 0, "bias": 0, "zero": 0, "norm": 0}
  for path, w in flat.items():
    name = "/".join(path)
    if path[:3] == ("update_block", "time_attn", "temporal_fc"):
      assert not w.any(), name
      seen["zero"] += 1
    elif any(n in path[-2].lower() for n in ("norm", "ln")):
      assert np.all(w == (1.0 if path[-1] == "scale" else 0.0)), name
      seen["norm"] += 1
    elif path[-1] == "kernel":
      fan_in = int(np.prod(w.shape[:-1]))  # HWIO / (in, out)
      if path[0] in ("fnet", "cnet"):
        fan_out = w.shape[-1] * int(np.prod(w.shape[:-2]))
        if w.size >= 500:
          assert abs(w.std() / np.sqrt(2.0 / fan_out) - 1) < 0.12, (name, w.std())
          assert abs(w.mean()) < 0.2 * w.std(), name
        seen["kaiming"] += 1
      else:
        bound = 1 / np.sqrt(fan_in)
        assert np.abs(w).max() <= bound, name
        if w.size >= 500:
          assert abs(w.std() / (bound / np.sqrt(3)) - 1) < 0.12, (name, w.std(), bound)
        seen["default"] += 1
    elif path[-1] == "bias":
      kernel = flat[(*path[:-1], "kernel")]
      bound = 1 / np.sqrt(int(np.prod(kernel.shape[:-1])))
      assert np.abs(w).max() <= bound, name
      if w.size >= 64:
        assert np.abs(w).max() > 0.5 * bound, name  # drawn, not zero
      seen["bias"] += 1
  assert seen["kaiming"] >= 20 and seen["default"] >= 20 and seen["zero"] == 2, seen
  assert seen["norm"] >= 2 and seen["bias"] >= 40, seen


def test_the_depth_priors_own_draws_leave_the_other_parameters_as_pytorchs_defaults(
    monkeypatch):
  """The depth prior's own initialisation draws from a stream of its own: every other
  parameter keeps the value that PyTorch's defaults alone (no depth-prior rule) give it, for
  seed 0 (the default, a valid seed) as for any; the parameters are drawn in the order of
  their names. (A small tree of the model's names, the prior sorted between the others.)"""
  conv = {"kernel": jax.ShapeDtypeStruct((3, 3, 3, 4), jnp.float32),
          "bias": jax.ShapeDtypeStruct((4,), jnp.float32)}
  qkv = {"kernel": jax.ShapeDtypeStruct((8, 24), jnp.float32),
         "bias": jax.ShapeDtypeStruct((24,), jnp.float32)}
  tree = {"cnet": {"conv1": conv}, "fnet": {"conv1": conv}, "update_block": {"gru": conv},
          "depthnet": {"depthanything": {"pretrained": {"blocks_0": {"attn": {"qkv": qkv}}}}}}
  monkeypatch.setattr(init_lib, "abstract_variables", lambda cfg: {"params": tree})
  fresh = flax.traverse_util.flatten_dict(init_variables(seed=0)["params"])
  # drawn in the order of the names, not of the tree's dicts
  monkeypatch.setattr(init_lib, "abstract_variables",
                      lambda cfg: {"params": dict(reversed(tree.items()))})
  again = flax.traverse_util.flatten_dict(init_variables(seed=0)["params"])
  assert all(np.array_equal(v, again[k]) for k, v in fresh.items())
  monkeypatch.setattr(init_lib, "_init_depth_prior", lambda path, shape, rng: None)
  plain = flax.traverse_util.flatten_dict(init_variables(seed=0)["params"])
  assert fresh.keys() == plain.keys() and len(fresh) == 8
  for k, v in fresh.items():
    if k[0] != "depthnet":
      np.testing.assert_array_equal(v, plain[k], err_msg="/".join(k))
    else:  # the prior's rule did apply: zero bias, N(0, 0.02) kernel from its own stream
      assert not np.array_equal(v, plain[k]) and (k[-1] == "kernel" or not v.any())
  want = 0.02 * np.random.default_rng([0, 1]).standard_normal((8, 24))
  np.testing.assert_allclose(fresh[("depthnet", "depthanything", "pretrained", "blocks_0",
                                    "attn", "qkv", "kernel")], want, rtol=1e-6)


def _grads_of_every_prediction(cfg, variables, clip):
  """d/d(variables, left) of a loss over every prediction (as training's, each prediction's
  error weighted differently), under jit, on the host."""
  m = sav_jax.StereoAnyVideo(cfg)

  def loss(v, left, right):
    d = m.apply(v, left, right, iters=2).disparities
    w = jnp.linspace(0.5, 1.0, d.shape[0]).reshape(-1, *[1] * (d.ndim - 1))
    return (w * jnp.abs(d.astype(jnp.float32) - 3)).mean()

  return jax.device_get(jax.jit(jax.grad(loss, argnums=(0, 1)))(variables, *clip))


def test_rematerialised_gradients_equal_the_plain_ones_and_the_depth_prior_is_frozen(
    variables, clip):
  """remat (training's setting: single refinement steps and the encoders' frame blocks
  recomputed in the backward pass; one frame per block at this budget, see
  test_training_rematerializes_single_steps_and_encoder_blocks) changes what the backward
  pass keeps, not the gradient: float32 gradients of a loss over every prediction, with
  respect to the weights and the frames, equal those without remat."""
  g_remat, g_left = _grads_of_every_prediction(
      sav_jax.SAVConfig(remat=True, frame_block_mb=4), variables, clip)
  g_plain, g_left_plain = _grads_of_every_prediction(sav_jax.SAVConfig(), variables, clip)
  np.testing.assert_allclose(g_left, g_left_plain, rtol=0,
                             atol=1e-5 * np.abs(g_left_plain).max())
  assert np.abs(g_left).sum() > 0
  flat_remat = flax.traverse_util.flatten_dict(g_remat["params"], sep="/")
  flat_plain = flax.traverse_util.flatten_dict(g_plain["params"], sep="/")
  assert flat_remat.keys() == flat_plain.keys()
  # Each leaf to 1e-5 of its own largest value; leaves whose true gradient is 0 (a bias
  # before an instance norm) hold only rounding noise, bounded by the whole gradient's scale.
  scale = max(np.abs(x).max() for x in flat_plain.values())
  off = {path: float(np.abs(flat_remat[path] - plain).max() / max(np.abs(plain).max(), 1e-30))
         for path, plain in flat_plain.items()
         if np.abs(flat_remat[path] - plain).max() > max(1e-5 * np.abs(plain).max(), 1e-7 * scale)}
  assert not off, off
  vda = jax.tree_util.tree_leaves(g_remat["params"]["depthnet"]["depthanything"])
  assert all(np.abs(x).max() == 0 for x in vda)
  for name in ("fnet", "cnet", "update_block", "corr_mlp"):
    assert any(np.abs(x).max() > 0 for x in jax.tree_util.tree_leaves(g_remat["params"][name]))
  assert np.abs(g_remat["params"]["depthnet"]["conv"]["kernel"]).max() > 0


def test_bfloat16_gradients_are_finite_and_the_depth_prior_is_frozen(variables, clip):
  """The bfloat16 mode with remat: finite gradients, the frozen prior's zero."""
  g_vars, g_left = _grads_of_every_prediction(sav_jax.SAVConfig(remat=True, dtype="bfloat16"),
                                              variables, clip)
  assert all(np.isfinite(x).all() for x in jax.tree_util.tree_leaves(g_vars))
  assert np.isfinite(g_left).all() and np.abs(g_left).sum() > 0
  vda = jax.tree_util.tree_leaves(g_vars["params"]["depthnet"]["depthanything"])
  assert all(np.abs(x).max() == 0 for x in vda)
  assert any(np.abs(x).max() > 0 for x in jax.tree_util.tree_leaves(g_vars["params"]["update_block"]))


def test_gradients_reach_the_frames_through_the_frozen_depth_prior(variables):
  """As in PyTorch, where the prior's parameters have requires_grad=False but nothing detaches
  its output: the depth features depend on the frames in the gradient too (a stop_gradient
  on the prior's output made that part of d disparity / d frames 0), while the prior's
  parameters get none."""
  from sav_jax.model.depth import DepthExtractor  # pylint: disable=import-outside-toplevel
  depth = DepthExtractor(sav_jax.SAVConfig())
  dv = {"params": variables["params"]["depthnet"]}
  x = jnp.asarray(np.random.default_rng(4).normal(size=(1, 2, 28, 56, 3)), jnp.float32)

  @jax.jit
  def grads(dv, x):
    return jax.grad(lambda dv, x: depth.apply(dv, x).sum(), argnums=(0, 1))(dv, x)

  g_vars, g_x = grads(dv, x)
  assert np.abs(np.asarray(g_x)).mean() > 0 and np.isfinite(np.asarray(g_x)).all()
  assert all(np.abs(np.asarray(v)).max() == 0
             for v in jax.tree_util.tree_leaves(g_vars["params"]["depthanything"]))
  assert np.abs(np.asarray(g_vars["params"]["conv"]["kernel"])).max() > 0


def _primitive_counts(jaxpr, counts=None) -> dict:
  """How often each primitive occurs in `jaxpr` and in every jaxpr nested in it."""
  counts = {} if counts is None else counts
  for eqn in jaxpr.eqns:
    counts[eqn.primitive.name] = counts.get(eqn.primitive.name, 0) + 1
    for value in eqn.params.values():
      for sub in value if isinstance(value, (tuple, list)) else (value,):
        sub = getattr(sub, "jaxpr", sub)  # a ClosedJaxpr's jaxpr
        if hasattr(sub, "eqns"):
          _primitive_counts(sub, counts)
  return counts


def test_each_refinement_step_is_traced_once_outside_init(model, monkeypatch):
  """Flax's scan traced its body twice (first to check that the parameters do not depend on
  the loop): every scale's step is now traced once in `apply` (a third less trace of a
  window's program); `init`, which creates the parameters in that first trace, keeps it."""
  from sav_jax.model.layers import CorrMLP  # pylint: disable=import-outside-toplevel
  params = abstract_variables(model.cfg)  # (its own trace calls every module once)
  calls, real = [], CorrMLP.__call__
  monkeypatch.setattr(CorrMLP, "__call__", lambda self, x: calls.append(1) or real(self, x))
  clip = jax.ShapeDtypeStruct(SHAPE, jnp.float32)
  jax.eval_shape(lambda v, l, r: model.apply(v, l, r, iters=2), params, clip, clip)
  assert len(calls) == 3  # one step per scale (1/16, 1/8, 1/4)
  calls.clear()
  init = jax.eval_shape(lambda l, r: model.init(jax.random.PRNGKey(0), l, r, iters=2), clip,
                        clip)
  assert len(calls) == 6 and "corr_mlp" in init["params"]


def test_inference_runs_every_update_inside_the_refinement_loops(model, variables, clip):
  """final_only: each scale's iterations are one scan over single steps (the window's
  correlation chosen by lax.cond) and nothing of the update block is unrolled beside it
  (the mask head runs once per scale, on the final state): the GRU's six gates
  (`logistic`) appear once in each of the three scans and nowhere else. A scan over
  (1x9, 3x3) pairs plus an unrolled last pair made the program ~2x slower to compile."""
  jaxpr = jax.make_jaxpr(lambda v, l, r: model.apply(v, l, r, iters=4, final_only=True))(
      variables, *clip).jaxpr
  assert "logistic" not in {e.primitive.name for e in jaxpr.eqns}
  scans = [e for e in jaxpr.eqns if e.primitive.name == "scan"]
  assert len(scans) == 3
  assert [_primitive_counts(e.params["jaxpr"].jaxpr).get("logistic") for e in scans] == [6] * 3
  assert [e.params["length"] for e in scans] == [2, 2, 4]  # iters//2, iters//2, iters
  # No scan upsamples: each keeps only maps of its own scale (h = H/16, H/8, H/4), not the
  # every-iteration full-resolution predictions of training.
  heights = [max(v.aval.shape[-3] for v in e.outvars if v.aval.ndim >= 5) for e in scans]
  assert heights == [SHAPE[2] // 16, SHAPE[2] // 8, SHAPE[2] // 4]


def test_training_rematerializes_single_steps_and_encoder_blocks(variables, clip):
  """remat (training, every prediction): each scale's refinement is one scan over single
  steps, each step under its own checkpoint (a backward pass holds one step's activations),
  with the update block once per scale and nothing of it unrolled; the fnet and cnet
  encoders run under checkpoints over blocks of frames sized for their backward pass:
  here one frame per block (32 x 96 KiB of maps per frame against a 4 MiB budget)."""

  def structure(cfg):
    m = sav_jax.StereoAnyVideo(cfg)
    jaxpr = jax.make_jaxpr(lambda v, l, r: m.apply(v, l, r, iters=6).disparities)(
        variables, *clip).jaxpr
    scans = [e for e in jaxpr.eqns if e.primitive.name == "scan"]
    bodies = [e.params["jaxpr"].jaxpr for e in scans]
    checkpoints = [sum(q.primitive.name == "remat2" for q in b.eqns) for b in bodies]
    gates = [_primitive_counts(b).get("logistic", 0) for b in bodies]
    return ([e.params["length"] for e in scans], checkpoints, gates,
            _primitive_counts(jaxpr)["logistic"])

  lengths, checkpoints, gates, all_gates = structure(
      sav_jax.SAVConfig(remat=True, frame_block_mb=4))
  assert lengths == [2 * SHAPE[1], SHAPE[1], 3, 3, 6]  # fnet (both views), cnet, 3 scales
  assert checkpoints == [1] * 5
  assert gates == [0, 0, 6, 6, 6] and all_gates == 18
  # Without remat the encoders' maps fit the same budget whole: no blocks, no checkpoints.
  lengths, checkpoints, gates, all_gates = structure(sav_jax.SAVConfig(frame_block_mb=4))
  assert lengths == [3, 3, 6] and checkpoints == [0] * 3 and gates == [6] * 3


def test_remat_policy_reaches_the_refinement_steps(variables, clip):
  """`remat_policy` names the checkpoint policy of every refinement step (the three scales'
  scans), not only the config's field."""
  m = sav_jax.StereoAnyVideo(sav_jax.SAVConfig(remat=True, remat_policy="dots_saveable"))
  jaxpr = jax.make_jaxpr(lambda v, l, r: m.apply(v, l, r, iters=2).disparities)(
      variables, *clip).jaxpr
  bodies = [e.params["jaxpr"].jaxpr for e in jaxpr.eqns if e.primitive.name == "scan"]
  policies = [q.params["policy"] for b in bodies for q in b.eqns if q.primitive.name == "remat2"]
  assert policies == [jax.checkpoint_policies.dots_saveable] * 3


def test_batch_elements_are_independent(model, variables, clip):
  """Changing one clip of a batch leaves the other's result unchanged (one compile)."""
  left, right = clip
  other_l, other_r = left[:, ::-1], right[:, ::-1]
  fn = jax.jit(lambda v, l, r: model.apply(v, l, r, iters=2, final_only=True).disparities)
  mixed = fn(variables, jnp.concatenate([left, other_l]), jnp.concatenate([right, other_r]))
  same = fn(variables, jnp.concatenate([left, left]), jnp.concatenate([right, right]))
  assert mixed.shape == (1, 2, *SHAPE[1:4])
  np.testing.assert_allclose(mixed[:, 0], same[:, 0], atol=1e-5)
  np.testing.assert_allclose(same[:, 0], same[:, 1], atol=1e-5)
  assert float(jnp.abs(mixed[:, 1] - same[:, 1]).max()) > 1e-3


def test_final_only_equals_the_last_of_all_predictions(model, variables, clip):
  """iters=6: 3 + 3 + 6 steps, so the final-only path covers odd stages and a scanned prefix."""

  @jax.jit
  def both(v, l, r):
    full, full_inter = model.apply(v, l, r, iters=6, mutable=["intermediates"])
    last, last_inter = model.apply(v, l, r, iters=6, final_only=True, mutable=["intermediates"])
    return full.disparities, last.disparities, full_inter, last_inter

  full, last, full_inter, last_inter = both(variables, *clip)
  assert full.shape == (12, *SHAPE[:4]) and last.shape == (1, *SHAPE[:4])
  np.testing.assert_allclose(last[0], full[-1], atol=1e-5)
  # the flow entering every iteration (intermediates) is the same in both modes
  flows, last_flows = (inter["intermediates"] for inter in (full_inter, last_inter))
  assert flows.keys() == last_flows.keys() == {"flow_in_2x3", "flow_in_4x6", "flow_in_8x12"}
  for name, (want,) in flows.items():
    assert want.shape[0] == (6 if name == "flow_in_8x12" else 3)
    np.testing.assert_allclose(last_flows[name][0], want, atol=1e-5, err_msg=name)


def test_detach_flow_false_differentiates_through_every_refinement_step(variables, monkeypatch):
  """The official model detaches the flow entering each refinement step (RAFT's truncated
  backpropagation), so with the default the gradient of the final disparity leaves out the
  paths through the earlier steps' flows; `detach_flow=False` gives the true derivative:
  the same as the model with that stop_gradient removed by hand, and not the truncated one.
  The values are the same either way (to float32 rounding). The refinement cascade alone (the stop_gradient's
  only place), differentiated with respect to the right view's features: the encoders in
  front of it are the same program either way, and compiling their backward three times
  took 2/3 of this test's 150 s."""
  rng = np.random.default_rng(0)
  size = SHAPE[2:4]
  fmap1, fmap2, context = (jnp.asarray(rng.normal(size=(*SHAPE[:2], 8, 12, 128)), jnp.float32)
                           for _ in range(3))
  weights = jnp.asarray(rng.normal(size=SHAPE[:-1]), jnp.float32)

  def run(cfg):
    m = sav_jax.StereoAnyVideo(cfg)
    f = lambda f2: (weights * m.apply(variables, fmap1, f2, context, size, 2,  # noqa: E731
                                      True, method="cascade").disparities[0]).sum()
    value, grad = jax.jit(jax.value_and_grad(f))(fmap2)
    return float(value), np.asarray(grad)

  value, truncated = run(sav_jax.SAVConfig())
  value_full, full = run(sav_jax.SAVConfig(detach_flow=False))
  assert value_full == pytest.approx(value, rel=1e-6)  # two programs: float32 rounding
  # The hand-made reference: every jax.lax.stop_gradient the identity.
  monkeypatch.setattr(jax.lax, "stop_gradient", lambda x: x)
  _, reference = run(sav_jax.SAVConfig())
  scale = np.abs(reference).max()
  np.testing.assert_allclose(full, reference, rtol=0, atol=1e-5 * scale)
  assert np.linalg.norm(full - truncated) > 0.05 * np.linalg.norm(full)


def test_final_only_must_be_a_static_bool(model):
  # A traced final_only (it sets the output's shape) raised JAX's TracerBoolConversionError
  # from inside the cascade; like iters, it is named with the way out.
  left = jnp.zeros(SHAPE)
  init = lambda l, r, fo: model.init(jax.random.PRNGKey(0), l, r, iters=2,  # noqa: E731
                                     final_only=fo)
  with pytest.raises(ValueError, match="final_only must be a Python bool, got the traced .*"
                     "static_argnames='final_only'"):
    jax.eval_shape(init, left, left, True)
  with pytest.raises(ValueError, match="final_only must be True or False, got 'yes'"):
    jax.eval_shape(lambda l, r: init(l, r, "yes"), left, left)


def test_apply_with_the_parameter_tree_itself_is_named(model, variables):
  # model.apply(params, ...) (not {"params": params}) failed deep inside the depth prior with
  # Flax's ScopeCollectionNotFound about "cls_token".
  x = jnp.zeros(SHAPE)
  with pytest.raises(ValueError, match=r"takes the Flax variables \{'params': params\}; it got "
                     r"the parameter tree itself \(keys \['cnet', 'corr_mlp', 'depthnet'"):
    jax.eval_shape(lambda p: model.apply(p, x, x, iters=2), variables["params"])
  for method in (sav_jax.StereoAnyVideo.features, "frame_features"):  # README's other entries
    with pytest.raises(ValueError, match=r"got the parameter tree itself"):
      jax.eval_shape(lambda p: model.apply(p, x, x, method=method), variables["params"])
  out = jax.eval_shape(lambda v: model.apply(v, x, x, iters=2, final_only=True), variables)
  assert out.disparities.shape == (1, *SHAPE[:4])


def test_calling_the_module_without_variables_says_to_use_apply(model):
  """`model(left, right)` (a notebook's first try) failed with Flax's "Can't check if running
  under init() on unbound modules"; each entry point now names the `apply` call to make."""
  x = np.zeros(SHAPE, np.float32)
  with pytest.raises(TypeError, match=r"without weights: call model\.apply\(variables, left, "
                     r"right, iters=20\) with variables = \{'params': params\}.*not "
                     r"model\(left, right, iters=20\)"):
    model(x, x, iters=2)
  for method in ("features", "frame_features"):
    with pytest.raises(TypeError, match=rf"model\.apply\(variables, left, right, "
                       rf"method=sav_jax\.StereoAnyVideo\.{method}\)"):
      getattr(model, method)(x, x)
  with pytest.raises(TypeError, match=r"method=sav_jax\.StereoAnyVideo\.from_frame_features"):
    model.from_frame_features({}, SHAPE[2:4])


def test_freeze_depth_prior_leaves_the_prior_out_of_a_users_optimizer(variables):
  """A plain AdamW over all parameters decays the frozen prior's weights (its gradient is
  zero, its weight decay is not) and holds moments for it; `freeze_depth_prior` gives those
  leaves zero updates and no state, as the official `requires_grad_(False)`."""
  import optax  # pylint: disable=g-import-not-at-top
  params = variables["params"]
  # host gradients and jitted updates: eager jnp over the 300+ leaves' shapes took 22 s
  grads = jax.tree.map(lambda x: np.ones(x.shape, x.dtype), params)
  grads["depthnet"]["depthanything"] = jax.tree.map(lambda x: np.zeros(x.shape, x.dtype),
                                                    params["depthnet"]["depthanything"])
  adamw = optax.adamw(1e-3, weight_decay=0.1)
  n_prior = sum(x.size for x in jax.tree.leaves(params["depthnet"]["depthanything"]))
  n_all = sum(x.size for x in jax.tree.leaves(params))
  assert n_prior > 20e6 and n_all - n_prior > 9e6

  plain = jax.jit(lambda g, p: adamw.update(g, adamw.init(p), p)[0])(grads, params)
  assert max(np.abs(x).max() for x in jax.tree.leaves(plain["depthnet"]["depthanything"])) > 0

  tx = init_lib.freeze_depth_prior(adamw, params)
  state = tx.init(params)
  n_state = sum(x.size for x in jax.tree.leaves(state) if x.ndim)
  assert n_state == 2 * (n_all - n_prior)  # the two moments of the trainable leaves only
  updates = jax.jit(tx.update)(grads, state, params)[0]
  assert all(np.abs(x).max() == 0 for x in jax.tree.leaves(updates["depthnet"]["depthanything"]))
  for name in ("fnet", "update_block"):
    assert all(np.abs(x).min() > 0 for x in jax.tree.leaves(updates[name]))
  np.testing.assert_array_equal(updates["depthnet"]["conv"]["kernel"],
                                plain["depthnet"]["conv"]["kernel"])


def test_freeze_depth_prior_names_the_variables_dict_passed_for_the_params():
  """`freeze_depth_prior(tx, variables)` (the README says `variables["params"]`) would build
  labels that `tx.init(variables["params"])` fails on with optax's tree-structure error."""
  import optax  # pylint: disable=g-import-not-at-top
  params = {"depthnet": {"depthanything": {"w": np.ones(2, np.float32)}},
            "fnet": {"w": np.ones(2, np.float32)}}
  with pytest.raises(ValueError, match=r"got the Flax variables \(collections \['params'\]\): "
                     r"pass variables\['params'\]"):
    init_lib.freeze_depth_prior(optax.sgd(1.0), {"params": params})
  tx = init_lib.freeze_depth_prior(optax.sgd(1.0), params)
  updates = tx.update(params, tx.init(params), params)[0]
  np.testing.assert_array_equal(updates["depthnet"]["depthanything"]["w"], 0)
  np.testing.assert_array_equal(updates["fnet"]["w"], -1)

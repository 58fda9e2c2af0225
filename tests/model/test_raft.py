"""RAFT (the official evaluator's optical flow) against the official RAFT code.

The oracle (`tests/fixtures/raft/raft_oracle.npz`, from `make_raft_oracle.py`) holds the
official model's outputs for make_weights.py's seed-0 weights on a 130x150 pair (padded to
136x152 as the evaluator pads): the encoders, the correlation lookup at random positions,
the convex upsampling, and the flow after 1, 3 and 20 iterations (the tests run 1 and 20).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sav_jax import convert
from sav_jax.convert.raft import load_raft, raft_variables_from_state_dict
from sav_jax.convert.torch_io import CheckpointError
from sav_jax.model import raft
from sav_jax.ops.upsample import convex_upsample_2d

# Values against the oracle's, not XLA's optimised code (tests/conftest.py): 21 CPU-seconds
# with `fast_compile`, 34 without (2026-12-07).
pytestmark = pytest.mark.usefixtures("fast_compile")

# Max abs difference allowed against the official float32 outputs (the values reach 6.6
# for the features, 30 for the correlation, 43 px for the 20-iteration flow; measured
# differences: 1.5e-5, 4.0e-5 and 3.2e-5).
FEATURE_ATOL = 1e-4
FLOW_ATOL = 2e-4


def hwc(a):
  """Official `[C, H, W]` -> `[1, H, W, C]`."""
  return np.moveaxis(a, 0, -1)[None]


@pytest.fixture(scope="module")
def variables(raft_state_dict):
  return raft_variables_from_state_dict(raft_state_dict)


@pytest.fixture(scope="module")
def padded(raft_oracle):
  """The evaluator's padded, normalised pair `[2, 136, 152, 3]` in [-1, 1]."""
  pair = np.concatenate([hwc(raft_oracle["image1"]), hwc(raft_oracle["image2"])])
  return 2 * (raft.pad_to_multiple_of_8(jnp.asarray(pair)) / 255.0) - 1.0


def test_encoders_match_official(variables, padded, raft_oracle):
  model = raft.RAFT()
  fmaps = model.apply(variables, padded, method=lambda m, x: m.fnet(x))
  ctx = model.apply(variables, padded[:1], method=lambda m, x: m.cnet(x))
  for got, key in ((fmaps[0], "fmap1"), (fmaps[1], "fmap2"), (ctx[0], "cnet")):
    np.testing.assert_allclose(got, hwc(raft_oracle[key])[0], atol=FEATURE_ATOL, rtol=0,
                               err_msg=key)


def test_correlation_lookup_matches_official(raft_oracle):
  """All-pairs pyramid and the (transposed) 9x9 bilinear window at fractional positions,
  some outside the image (zero padding)."""
  f1, f2 = jnp.asarray(hwc(raft_oracle["fmap1"])), jnp.asarray(hwc(raft_oracle["fmap2"]))
  coords = jnp.asarray(hwc(raft_oracle["lookup_coords"]))
  got = jax.jit(lambda a, b, c: raft.lookup(raft.correlation_pyramid(a, b), c))(f1, f2, coords)
  assert got.shape == (1, 17, 19, 324)
  np.testing.assert_allclose(got[0], hwc(raft_oracle["lookup"])[0], atol=FEATURE_ATOL, rtol=0)


def test_convex_upsampling_matches_official(raft_oracle):
  got = convex_upsample_2d(jnp.asarray(hwc(raft_oracle["up_flow_in"])),
                           jnp.asarray(hwc(raft_oracle["up_mask_in"])), 8)
  assert got.shape == (1, 136, 152, 2)
  np.testing.assert_allclose(got[0], hwc(raft_oracle["up_flow"])[0], atol=1e-5, rtol=0)


def test_flow_matches_official(variables, raft_oracle):
  """`raft_flow` is the evaluator's call: padding, RAFT, cropping back to 130x150 (one
  iteration here; the evaluator's 20 below). The oracle's 3-iteration flow is not run: each
  iteration count is a program of its own to compile."""
  flow = raft.raft_flow(variables, hwc(raft_oracle["image1"])[0],
                        hwc(raft_oracle["image2"])[0], iters=1)
  assert flow.shape == (130, 150, 2)
  np.testing.assert_allclose(flow, hwc(raft_oracle["flow_it1"])[0], atol=FLOW_ATOL, rtol=0)


def test_flow_fn_is_the_evaluators_flow(variables, raft_oracle):
  """`raft_flow_fn` at the evaluator's 20 iterations, channels first as `metrics` calls it."""
  flow = raft.raft_flow_fn(variables)(raft_oracle["image1"], raft_oracle["image2"])
  assert flow.shape == (2, 130, 150) and flow.dtype == np.float32
  np.testing.assert_allclose(flow, raft_oracle["flow_it20"], atol=FLOW_ATOL, rtol=0)
  assert np.abs(raft_oracle["flow_it20"]).max() > 10  # a flow that moved, not a near-zero one


@pytest.mark.parametrize("h,w", [(130, 150), (128, 128), (436, 1024), (375, 1242), (1, 9)])
def test_padding_is_the_input_padders(h, w):
  pad_h = (((h // 8) + 1) * 8 - h) % 8  # the official InputPadder, "sintel" mode
  pad_w = (((w // 8) + 1) * 8 - w) % 8
  assert raft.padding_for(h, w) == ((pad_h // 2, pad_h - pad_h // 2),
                                    (pad_w // 2, pad_w - pad_w // 2))
  x = np.arange(h * w, dtype=np.float32).reshape(h, w, 1)
  padded = np.asarray(raft.pad_to_multiple_of_8(x))
  (top, bottom), (left, right) = raft.padding_for(h, w)
  assert padded.shape == (h + top + bottom, w + left + right, 1)
  np.testing.assert_array_equal(padded[top:top + h, left:left + w], x)
  np.testing.assert_array_equal(padded[0, left:left + w], x[0])  # edge rows replicated
  np.testing.assert_array_equal(padded[-1, left:left + w], x[-1])


def test_bad_images_are_refused(variables):
  small = np.zeros((100, 200, 3), np.float32)
  with pytest.raises(ValueError, match=r"100x200 are too small for RAFT \(at least 128x128"):
    raft.raft_flow(variables, small, small)
  with pytest.raises(ValueError, match="of one shape"):
    raft.raft_flow(variables, np.zeros((128, 128, 3)), np.zeros((136, 128, 3)))
  with pytest.raises(ValueError, match="multiples of 8"):
    raft.RAFT().apply(variables, jnp.zeros((1, 130, 136, 3)), jnp.zeros((1, 130, 136, 3)))
  with pytest.raises(ValueError, match=r"img1 must be \[3, H, W\]"):
    raft.raft_flow_fn(variables)(np.zeros((128, 128, 3)), np.zeros((128, 128, 3)))


@pytest.mark.parametrize("iters", [0, -1, 2.5, True])
def test_iterations_that_run_no_update_are_refused(variables, iters):
  image = np.zeros((128, 128, 3), np.float32)  # refused before anything is traced
  with pytest.raises(ValueError, match=r"RAFT iters must be an integer >= 1"):
    raft.raft_flow(variables, image, image, iters)
  with pytest.raises(ValueError, match=r"RAFT iters must be an integer >= 1"):
    raft.raft_flow_fn(variables, iters)


def test_checkpoint_is_recognised_and_read_from_a_file(tmp_path, raft_state_dict, variables,
                                                       sav_state_dict):
  assert convert.checkpoint_kind(raft_state_dict) == "raft"
  assert convert.checkpoint_kind(sav_state_dict) == "sav"
  path = convert.save_state_dict({"module." + k: v for k, v in raft_state_dict.items()},
                                 tmp_path / "raft-things.npz")
  got = load_raft(path)
  jax.tree_util.tree_map(np.testing.assert_array_equal, got, variables)
  assert set(got) == {"params", "batch_stats"}
  sav = convert.save_state_dict(sav_state_dict, tmp_path / "sav.safetensors")
  with pytest.raises(CheckpointError, match="is a Stereo Any Video checkpoint, not a RAFT"):
    load_raft(sav)
  with pytest.raises(CheckpointError, match="is a RAFT .optical flow. checkpoint, not a Stereo"):
    convert.load_state_dict_of_kind(path, "sav")


def test_raft_small_and_a_raft_missing_keys_are_named(tmp_path, raft_state_dict, capsys):
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  # raft-small.pth (from the same models.zip): a plain ConvGRU, no mask; not supported.
  small = {k: np.zeros(s, np.float32) for k, s in (
      ("fnet.conv1.weight", (32, 3, 7, 7)), ("cnet.conv1.weight", (32, 3, 7, 7)),
      ("update_block.encoder.convc1.weight", (96, 196, 1, 1)),
      ("update_block.gru.convz.weight", (96, 242, 3, 3)))}
  assert convert.checkpoint_kind(small) == "raft_small"
  path = convert.save_state_dict(small, tmp_path / "raft-small.safetensors")
  with pytest.raises(CheckpointError, match=r"is a RAFT-small .optical flow. checkpoint, not a "
                                            r"RAFT .* only the large RAFT is supported: "
                                            r"raft-things.pth"):
    load_raft(path)
  # raft-things.pth less its mask head is still RAFT: the strict report names the keys.
  sd = {k: v for k, v in raft_state_dict.items() if not k.startswith("update_block.mask.")}
  assert convert.checkpoint_kind(sd) == "raft"
  with pytest.raises(ValueError, match="missing key 'update_block.mask.0.weight'"):
    load_raft(convert.save_state_dict(sd, tmp_path / "no_mask.npz"))
  # `sav-jax convert` of a RAFT file says where the file goes instead.
  path = convert.save_state_dict(raft_state_dict, tmp_path / "raft-things.safetensors")
  assert cli.main(["convert", str(path), str(tmp_path / "out")]) == 2
  err = capsys.readouterr().err
  assert "is a RAFT (optical flow) checkpoint, not a Stereo Any Video one; RAFT, the " \
         "evaluation's optical-flow model, needs no conversion: give the file to python -m " \
         "eval as --config.metrics.raft=raft-things.pth" in err, err
  assert not (tmp_path / "out").exists()


def test_either_name_of_the_twice_registered_batchnorm_is_enough(raft_state_dict, variables):
  for kept in ("norm3", "downsample.1"):
    dropped = "downsample.1" if kept == "norm3" else "norm3"
    sd = {k: v for k, v in raft_state_dict.items() if f".{dropped}." not in k}
    assert len(sd) < len(raft_state_dict)
    got = raft_variables_from_state_dict(sd)
    jax.tree_util.tree_map(np.testing.assert_array_equal, got, variables)


def test_state_dict_problems_are_listed(raft_state_dict):
  sd = dict(raft_state_dict)
  del sd["update_block.gru.convz1.weight"]
  sd["fnet.conv1.weight"] = sd["fnet.conv1.weight"][:, :, :5, :5]
  sd["cnet.norm1.running_var"] = np.full(64, np.nan, np.float32)
  sd["cnet.layer2.0.norm3.bias"] = sd["cnet.layer2.0.norm3.bias"] + 1
  sd["update_block.extra.weight"] = np.zeros((2, 2), np.float32)
  # A norm3 of a block without a skip path: unexpected, and its twin, which the file does
  # not hold, is not named (it was, as an unexpected key too).
  sd["fnet.layer1.0.norm3.bias"] = np.zeros(64, np.float32)
  with pytest.raises(ValueError) as err:
    raft_variables_from_state_dict(sd)
  msg = str(err.value)
  assert msg.startswith("state dict does not match RAFT (the large model of raft-things.pth): "
                        "6 problem(s)"), msg
  for part in ("missing key 'update_block.gru.convz1.weight'",
               "key 'fnet.conv1.weight': shape (64, 3, 5, 5) does not match RAFT (expects "
               "(64, 3, 7, 7))",
               "key 'cnet.norm1.running_var': 64 of 64 values are NaN or inf",
               "key 'cnet.layer2.0.norm3.bias' differs from 'cnet.layer2.0.downsample.1.bias'",
               "unexpected key 'update_block.extra.weight'",
               "unexpected key 'fnet.layer1.0.norm3.bias'"):
    assert part in msg, (part, msg)
  assert "fnet.layer1.0.downsample" not in msg, msg
  with pytest.raises(ValueError, match=r"none of the state dict's 2 keys is one of the model's"):
    raft_variables_from_state_dict({"encoder.weight": np.zeros((2, 2), np.float32),
                                    "head.layer1.0.norm3.bias": np.zeros(2, np.float32)})

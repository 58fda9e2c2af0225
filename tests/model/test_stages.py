"""Stage-by-stage parity with the official implementation (golden_small fixture).

Each stage gets the fixture's own inputs, so an error is pinned to one stage.
Run under `jax.default_matmul_precision("highest")` (no TF32/bf16 matmuls).
Tolerances follow the fixture README: features `|a-b| <= 1e-4*max|b| + 1e-5`,
correlations `atol = 1e-3`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sav_jax.model.encoder import BasicEncoder
from sav_jax.model.layers import CorrMLP, conv, normalize
from sav_jax.model.update import BasicMotionEncoder, SequenceUpdateBlock3D
from sav_jax.ops.correlation import SMALL_WINDOW, WIDE_WINDOW, aapc
from sav_jax.ops.pool import avg_pool
from sav_jax.ops.resize import resize
from sav_jax.ops.upsample import convex_upsample_3d
from tests.parity import feature_close, nchw_to_nhwc, subtree

# Values against the oracle's, not XLA's optimised code (tests/conftest.py): 24 CPU-seconds
# with `fast_compile`, 33 without (2026-12-07).
pytestmark = pytest.mark.usefixtures("fast_compile")


@pytest.fixture(autouse=True)
def _highest():
  with jax.default_matmul_precision("highest"):
    yield


def test_normalisation(golden_small):
  x = nchw_to_nhwc(golden_small["input_left"])
  feature_close(normalize(jnp.asarray(x)), nchw_to_nhwc(golden_small["norm_left"]))


def test_vda_input_resize(golden_small):
  x = nchw_to_nhwc(golden_small["norm_left"])
  out = resize(jnp.asarray(x), (56, 126), "bilinear", align_corners=False)
  feature_close(out, nchw_to_nhwc(golden_small["vda_resized_left"]))


def test_vda_output_resize_and_depth_conv(golden_small, sav_state_dict):
  x = nchw_to_nhwc(golden_small["vda_head_left_f0"])
  up = resize(jnp.asarray(x), (64, 128), "bilinear", align_corners=False)
  feature_close(up, nchw_to_nhwc(golden_small["vda_head_resized_left_f0"]))
  layer = conv(32, (4, 4), 4, 0)
  out = layer.apply({"params": subtree(sav_state_dict, "depthnet.conv.")}, up)
  feature_close(out[0], nchw_to_nhwc(golden_small["depthnet_left"][0, 0]))


@pytest.mark.parametrize("name,view", [("cnet", "left"), ("fnet", "left"), ("fnet", "right")])
def test_encoders(golden_small, sav_state_dict, name, view):
  x = jnp.asarray(normalize(nchw_to_nhwc(golden_small[f"input_{view}"][0, :1])))
  out = BasicEncoder(96).apply({"params": subtree(sav_state_dict, f"{name}.")}, x)
  feature_close(out, nchw_to_nhwc(golden_small[f"{name}_{view}_f0"]))


def test_pooled_features(golden_small):
  f1 = np.concatenate([nchw_to_nhwc(golden_small["depthnet_left"][0])], -1)
  # Only depth channels are known for every frame; check pooling on them.
  feature_close(avg_pool(jnp.asarray(f1), 2)[..., :32], nchw_to_nhwc(golden_small["fmap1_s8"])[..., :32])
  feature_close(avg_pool(jnp.asarray(f1), 4)[..., :32], nchw_to_nhwc(golden_small["fmap1_s16"])[..., :32])


def _fmaps_s4_f0(g):
  f1 = np.concatenate([nchw_to_nhwc(g["depthnet_left"][:, 0]), nchw_to_nhwc(g["fnet_left_f0"])], -1)
  f2 = np.concatenate([nchw_to_nhwc(g["depthnet_right"][:, 0]), nchw_to_nhwc(g["fnet_right_f0"])], -1)
  return f1, f2


@pytest.mark.parametrize("scale", ["s4", "s8", "s16"])
@pytest.mark.parametrize("size", ["large", "small"])
def test_correlation(golden_small, scale, size):
  g = golden_small
  if scale == "s4":
    f1, f2 = _fmaps_s4_f0(g)
    flow, ref = g["corr_flow_s4_f0"], g[f"corr_s4_{size}_f0"]
  else:
    f1, f2 = nchw_to_nhwc(g[f"fmap1_{scale}"]), nchw_to_nhwc(g[f"fmap2_{scale}"])
    suffix = "_f0" if scale == "s8" else ""
    flow, ref = g[f"corr_flow_{scale}{suffix}"], g[f"corr_{scale}_{size}{suffix}"]
    f1, f2 = f1[: flow.shape[0]], f2[: flow.shape[0]]
  window = WIDE_WINDOW if size == "large" else SMALL_WINDOW
  # The y channel of the flow is deliberately non-zero in the fixture: it must not matter.
  out = aapc(jnp.asarray(f1), jnp.asarray(f2), jnp.asarray(flow[:, 0]), window)
  np.testing.assert_allclose(out, nchw_to_nhwc(ref), atol=1e-3, rtol=0)


def test_corr_mlp(golden_small, sav_state_dict):
  x = nchw_to_nhwc(golden_small["corr_s8_large_f0"])
  out = CorrMLP().apply({"params": subtree(sav_state_dict, "corr_mlp.")}, jnp.asarray(x))
  feature_close(out, nchw_to_nhwc(golden_small["corr_mlp_out_s8_large_f0"]))
  out = CorrMLP().apply({"params": subtree(sav_state_dict, "corr_mlp.")},
                        jnp.asarray(golden_small["ub_corr_mlp_in"]))
  feature_close(out, golden_small["ub_corr_mlp_out"])


def _bt(x, t=3):
  """`(B*T), C, h, w` -> `[B, T, h, w, C]`."""
  x = nchw_to_nhwc(x)
  return jnp.asarray(x.reshape(-1, t, *x.shape[1:]))


@pytest.mark.parametrize("gru_conv", ["direct", "dft"])
def test_update_block(golden_small, sav_state_dict, gru_conv):
  """Both forms of the GRU's 1x15 convolutions (XLA's; DFT products, CPU's default)."""
  g = golden_small
  params = subtree(sav_state_dict, "update_block.")
  del params["time_attn"]["temporal_attn"]["qkv"]  # never used by the official forward
  flow = _bt(g["ub_in_flow"])
  assert np.all(np.asarray(flow[..., 1]) == 0)
  net, mask, delta = SequenceUpdateBlock3D(gru_conv=gru_conv).apply(
      {"params": params}, _bt(g["ub_in_net"]), _bt(g["ub_in_inp"]), _bt(g["ub_in_corr"]),
      flow[..., :1])
  feature_close(net, _bt(g["ub_out_net"]))
  feature_close(mask, _bt(g["ub_out_mask"]))
  feature_close(delta, _bt(g["ub_out_delta_flow"]))


def test_motion_encoder_x_flow_equals_two_channel_flow_with_zero_y(golden_small, sav_state_dict):
  """The update block passes the x-flow alone: the encoder reads its 7x7 kernel's x slice
  and appends the zero y channel, which must equal the official two-channel form (RAFT's
  path, with both channels) on a y that is zero; a y that is not zero must matter there."""
  params = subtree(sav_state_dict, "update_block.")["encoder"]
  assert params["convf1"]["kernel"].shape == (7, 7, 2, 128)
  flow, corr = _bt(jnp.asarray(golden_small["ub_in_flow"])), _bt(golden_small["ub_in_corr"])
  enc = BasicMotionEncoder()
  x_only = enc.apply({"params": params}, flow[..., :1], corr)
  both = enc.apply({"params": params}, flow, corr)
  np.testing.assert_allclose(np.asarray(x_only), np.asarray(both), rtol=0, atol=1e-6)
  y_flow = flow.at[..., 1].set(1.0)
  assert not np.allclose(np.asarray(enc.apply({"params": params}, y_flow, corr)), np.asarray(both))


def test_update_block_refuses_a_two_channel_flow(golden_small, sav_state_dict):
  params = subtree(sav_state_dict, "update_block.")
  del params["time_attn"]["temporal_attn"]["qkv"]
  g = golden_small
  with pytest.raises(ValueError, match=r"x-flow \[\.\.\., 1\].*\(1, 3, 4, 8, 2\)"):
    SequenceUpdateBlock3D().apply({"params": params}, _bt(g["ub_in_net"]), _bt(g["ub_in_inp"]),
                                  _bt(g["ub_in_corr"]), _bt(g["ub_in_flow"]))


def test_conv_with_a_wider_kernel_reads_its_first_input_channels():
  from sav_jax.model.layers import Conv2D  # pylint: disable=import-outside-toplevel
  x = jnp.asarray(np.random.default_rng(0).standard_normal((1, 6, 6, 1)), jnp.float32)
  conv2 = Conv2D(4, (3, 3), (1, 1), kernel_in=2)
  variables = conv2.init(jax.random.PRNGKey(0), x)
  assert variables["params"]["kernel"].shape == (3, 3, 2, 4)
  padded = jnp.concatenate([x, jnp.zeros_like(x)], axis=-1)
  np.testing.assert_allclose(np.asarray(conv2.apply(variables, x)),
                             np.asarray(Conv2D(4, (3, 3), (1, 1)).apply(variables, padded)),
                             rtol=0, atol=1e-6)
  with pytest.raises(ValueError, match="input has 3 channels, kernel_in is 2"):
    conv2.apply(variables, jnp.zeros((1, 6, 6, 3)))


def test_convex_upsample(golden_small):
  g = golden_small
  out = convex_upsample_3d(_bt(g["cu_in_flow"]), _bt(g["ub_out_mask"]))
  feature_close(out, _bt(g["cu_out"]))

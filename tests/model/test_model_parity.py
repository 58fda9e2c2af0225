"""End-to-end parity with the official forward pass (golden_small fixture).

Weights: make_weights.py seed 0, converted by `params_from_state_dict`. Input: the
fixture's 1x3x64x128 stereo clip, iters=4 (8 predictions). Tolerances (stated per
check): features `|a-b| <= 1e-4*max|b| + 1e-5`; disparities of every prediction
`atol = 1e-4 px` (the fixture README's target; the issue's hard limit is 1e-3 px).
The forward of `run` compiles with XLA's default options, the bfloat16 and
frame-block variants with most of them off (`fast_compile_test`: half the compile time).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sav_jax
from tests.conftest import XLA_DEFAULT_EMITTERS
from tests.parity import feature_close, nchw_to_nhwc

DISP_ATOL = 1e-4  # px


@pytest.fixture(scope="module")
def variables(sav_state_dict):
  return sav_jax.convert.params_from_state_dict(sav_state_dict, sav_jax.SAVConfig())


@pytest.fixture(scope="module")
def run(variables, golden_small):
  """Runs the model once (all predictions + the per-iteration flows)."""
  model = sav_jax.StereoAnyVideo(sav_jax.SAVConfig())
  left = jnp.asarray(nchw_to_nhwc(golden_small["input_left"]))
  right = jnp.asarray(nchw_to_nhwc(golden_small["input_right"]))

  @jax.jit
  def fwd(v, left, right):
    out, inter = model.apply(v, left, right, iters=4, mutable=["intermediates"])
    feats = model.apply(v, left, right, method=sav_jax.StereoAnyVideo.features)
    final = model.apply(v, left, right, iters=4, final_only=True)
    return out.disparities, inter["intermediates"], feats, final.disparities

  with jax.default_matmul_precision("highest"):
    # XLA's default compile, emitters included (the suite's XLA_FLAGS change them)
    compiled = fwd.lower(variables, left, right).compile(compiler_options=XLA_DEFAULT_EMITTERS)
    return jax.device_get(compiled(variables, left, right))


def test_depth_features(run, golden_small):
  _, _, (fmap1, fmap2, _), _ = run
  feature_close(fmap1[..., :32], nchw_to_nhwc(golden_small["depthnet_left"]))
  feature_close(fmap2[..., :32], nchw_to_nhwc(golden_small["depthnet_right"]))
  feature_close(fmap1[0, 0, ..., 32:], nchw_to_nhwc(golden_small["fnet_left_f0"])[0])


def test_every_prediction(run, golden_small):
  disp = run[0]
  ref = golden_small["predictions"][:, :, :, 0]  # [D, T, B, H, W]
  ref = np.transpose(ref, (0, 2, 1, 3, 4))  # -> [D, B, T, H, W]
  assert disp.shape == ref.shape
  errs = np.abs(disp - ref).reshape(len(ref), -1).max(axis=1)
  assert np.all(errs <= DISP_ATOL), f"per-prediction max abs error (px): {errs}"


def test_test_mode_output(run, golden_small):
  final = run[3]
  ref = np.transpose(golden_small["test_mode_output"][:, :, 0], (1, 0, 2, 3))[None]
  np.testing.assert_allclose(final, ref, atol=DISP_ATOL, rtol=0)


@pytest.mark.parametrize("scale,hw", [("s16", "4x8"), ("s8", "8x16"), ("s4", "16x32")])
def test_every_iteration_flow(run, golden_small, scale, hw):
  """The x-flow entering every refinement iteration, at every scale (hand-overs included)."""
  (flows,) = run[1][f"flow_in_{hw}"]  # [n, B, T, h, w, 1]
  ref = golden_small[f"iter_flow_{scale}"][:, :, 0]  # [n, (B*T), h, w], x channel
  np.testing.assert_allclose(flows[..., 0].reshape(ref.shape), ref, atol=DISP_ATOL, rtol=0)


BF16_EPE = 0.05  # px: issue 7's bound for the bfloat16 mode against float32


@pytest.mark.usefixtures("fast_compile_test")  # the module's `run` is the default compile
def test_bfloat16_mode_stays_close_to_float32(variables, golden_small):
  """bfloat16 compute (float32 params, softmaxes, correlation, upsampling, accumulator).

  Compared with the official float32 test-mode output on the fixture input: the mean
  absolute difference (EPE between the two) must stay within BF16_EPE.
  """
  model = sav_jax.StereoAnyVideo(sav_jax.SAVConfig(dtype="bfloat16"))
  left = jnp.asarray(nchw_to_nhwc(golden_small["input_left"]))
  right = jnp.asarray(nchw_to_nhwc(golden_small["input_right"]))
  fwd = jax.jit(lambda v, l, r: model.apply(v, l, r, iters=4, final_only=True).disparities)
  got = np.asarray(fwd(variables, left, right))
  ref = np.transpose(golden_small["test_mode_output"][:, :, 0], (1, 0, 2, 3))[None]
  assert got.dtype == np.float32 and got.shape == ref.shape
  epe = float(np.mean(np.abs(got - ref)))
  print(f"bfloat16 vs float32 EPE {epe:.4f} px, max {np.max(np.abs(got - ref)):.3f} px, "
        f"disparity range {ref.min():.2f}..{ref.max():.2f} px")
  assert epe <= BF16_EPE, epe
  assert epe > 0  # it did compute in bfloat16


@pytest.mark.usefixtures("fast_compile_test")  # the module's `run` is the default compile
def test_frame_blocks_reproduce_the_official_output(variables, golden_small):
  """A tiny `frame_block_mb` runs every per-frame stage one frame at a time (encoders,
  the depth head's full-resolution end, the space attention) and the ViT attention in
  blocks of query rows: the values stay those of the official forward."""
  cfg = sav_jax.SAVConfig(frame_block_mb=1e-3)
  model = sav_jax.StereoAnyVideo(cfg)
  left = jnp.asarray(nchw_to_nhwc(golden_small["input_left"]))
  right = jnp.asarray(nchw_to_nhwc(golden_small["input_right"]))
  fwd = jax.jit(lambda v, l, r: model.apply(v, l, r, iters=4, final_only=True).disparities)
  # Blocked: the frames run in loops (one more scan per blocked stage).
  scans = lambda m: str(jax.make_jaxpr(  # noqa: E731
      lambda v, l, r: m.apply(v, l, r, iters=4, final_only=True).disparities)(
          variables, left, right)).count("scan[")
  assert scans(model) > scans(sav_jax.StereoAnyVideo(sav_jax.SAVConfig()))
  with jax.default_matmul_precision("highest"):
    got = np.asarray(fwd(variables, left, right))
  ref = np.transpose(golden_small["test_mode_output"][:, :, 0], (1, 0, 2, 3))[None]
  np.testing.assert_allclose(got, ref, atol=DISP_ATOL, rtol=0)

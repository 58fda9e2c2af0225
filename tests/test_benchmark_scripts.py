"""The profiling helpers behind the figures in benchmarks/README.md."""

import pathlib
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import op_profile  # noqa: E402  pylint: disable=wrong-import-position,import-error


def test_multiply_adds_of_a_convolution_and_a_product_from_the_optimized_hlo():
  def fn(x, k, w):
    y = jax.lax.conv_general_dilated(x, k, (1, 1), ((1, 1), (1, 1)),
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return jnp.tanh(y).reshape(-1, 8) @ w

  x, k, w = jnp.ones((2, 6, 10, 4)), jnp.ones((3, 3, 4, 8)), jnp.ones((8, 5))
  ops = op_profile.parse_hlo(jax.jit(fn).lower(x, k, w).compile().as_text())
  conv_macs = 2 * 6 * 10 * 8 * (3 * 3 * 4)  # every output element: 3x3 taps x 4 channels
  dot_macs = (2 * 6 * 10) * 5 * 8
  # Whatever XLA fuses, the products it runs carry these multiply-adds, and no operation
  # is charged more than both together.
  macs = {op["macs"] for op in ops.values() if op["macs"]}
  assert conv_macs in macs and dot_macs in macs
  assert max(macs) <= conv_macs + dot_macs


def test_module_path_from_the_operation_metadata():
  op = {"op_name": "jit(<lambda>)/StereoAnyVideo/StereoAnyVideo.cascade/StereoAnyVideo.refine/"
                   "while/body/closed_call/StereoAnyVideo.pair/StereoAnyVideo.step/update_block/"
                   "gru/convz1_0/conv_general_dilated"}
  assert op_profile.module_of(op, 2) == "update_block/gru"
  assert op_profile.module_of(op, 8) == "update_block/gru/convz1_0"
  assert op_profile.module_of({"op_name": ""}, 2) == "(no metadata)"

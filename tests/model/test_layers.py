"""`conv2d`/`Conv2D`/`Conv3D`: the hand-written gradient equals XLA's, in and out of a scan;
`dft_correlate_w` equals the direct convolution; bfloat16 biases get float32-summed gradients."""

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sav_jax.model import layers
from sav_jax.model.layers import (Conv2D, Conv3D, ConvParams, conv2d, dft_correlate_w,
                                  set_canonical_conv_gradient)

# Checks of values against XLA's own ops: no need for XLA's optimisations (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("fast_compile")


def _reference(x, kernel, padding):
  return jax.lax.conv_general_dilated(x, kernel, (1, 1), padding,
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


@pytest.mark.parametrize("kernel_hw,padding", [
    ((3, 3), ((1, 1), (1, 1))), ((1, 15), ((0, 0), (7, 7))), ((5, 1), ((2, 2), (0, 0))),
    ((4, 4), ((0, 0), (0, 0))), ((3, 3), ((0, 1), (2, 0)))])
def test_conv2d_value_and_gradient_match_xla(kernel_hw, padding):
  rng = np.random.default_rng(0)
  x = jnp.asarray(rng.standard_normal((3, 8, 20, 5)), jnp.float32)
  kernel = jnp.asarray(rng.standard_normal((*kernel_hw, 5, 7)), jnp.float32)
  want, vjp_want = jax.vjp(lambda a, b: _reference(a, b, padding), x, kernel)
  got, vjp_got = jax.vjp(lambda a, b: conv2d(a, b, padding), x, kernel)
  np.testing.assert_array_equal(got, want)
  g = jnp.asarray(rng.standard_normal(want.shape), jnp.float32)
  for a, b in zip(vjp_got(g), vjp_want(g)):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(b))))


def test_gradient_inside_a_scan_matches_the_unrolled_loop():
  rng = np.random.default_rng(1)
  x = jnp.asarray(rng.standard_normal((2, 6, 10, 8)), jnp.float32)
  kernel = jnp.asarray(0.2 * rng.standard_normal((3, 3, 8, 8)), jnp.float32)
  pad = ((1, 1), (1, 1))

  def scanned(k, x):
    y, _ = jax.lax.scan(lambda c, _: (jnp.tanh(conv2d(c, k, pad)), None), x, length=3)
    return jnp.sum(y ** 2)

  def unrolled(k, x):
    for _ in range(3):
      x = jnp.tanh(_reference(x, k, pad))
    return jnp.sum(x ** 2)

  got = jax.jit(jax.grad(scanned, argnums=(0, 1)))(kernel, x)
  want = jax.jit(jax.grad(unrolled, argnums=(0, 1)))(kernel, x)
  for a, b in zip(got, want):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * float(jnp.max(jnp.abs(b))))


# (kernel, padding, output channels, frames): widening (7 > 5 channels: the taps read
# input slices) and narrowing (3 < 5: the taps' outputs are shifted), one frame too. With
# one or two frames the edge taps reach no frame or a single one (the narrowing path then
# drops taps from its side-by-side kernel: the flow head's 256 -> 2 conv on short clips).
@pytest.mark.parametrize("kernel,padding,out,frames", [
    ((3, 3, 3), (1, 1, 1), 7, 4), ((3, 3, 3), (1, 1, 1), 3, 4), ((5, 3, 1), (2, 1, 0), 3, 3),
    ((3, 3, 3), (1, 1, 1), 7, 1), ((5, 1, 1), (2, 0, 0), 7, 4), ((1, 1, 15), (0, 0, 7), 7, 4),
    ((3, 3, 3), (1, 1, 1), 3, 1), ((3, 3, 3), (1, 1, 1), 7, 2), ((3, 3, 3), (1, 1, 1), 3, 2),
    ((5, 3, 1), (2, 1, 0), 3, 2)])
def test_conv3d_equals_xla_3d_convolution(kernel, padding, out, frames):
  rng = np.random.default_rng(2)
  x = jnp.asarray(rng.standard_normal((2, frames, 6, 9, 5)), jnp.float32)
  layer = Conv3D(out, kernel, padding)
  variables = layer.init(jax.random.key(0), x)
  variables = jax.tree.map(lambda v: v + 0.1, variables)  # a non-zero bias too

  def want_fn(v, x):
    return jax.lax.conv_general_dilated(
        x, v["params"]["kernel"], (1, 1, 1), [(p, p) for p in padding],
        dimension_numbers=("NDHWC", "DHWIO", "NDHWC")) + v["params"]["bias"]

  np.testing.assert_allclose(layer.apply(variables, x), want_fn(variables, x), rtol=1e-5,
                             atol=1e-5)
  loss = lambda f: lambda v, x: jnp.sum(jnp.tanh(f(v, x)))  # noqa: E731
  got = jax.grad(loss(layer.apply), argnums=(0, 1))(variables, x)
  want = jax.grad(loss(want_fn), argnums=(0, 1))(variables, x)
  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)


def test_conv3d_rejects_a_temporal_padding_that_changes_the_length():
  with pytest.raises(ValueError, match="temporal padding 1"):
    Conv3D(4, (3, 3, 3), (0, 1, 1)).init(jax.random.key(0), jnp.ones((1, 4, 5, 5, 2)))


def test_conv2d_module_keeps_leading_axes_and_nn_conv_parameters():
  x = jnp.ones((2, 3, 8, 8, 4))
  layer = Conv2D(6, (3, 3), (1, 1))
  variables = layer.init(jax.random.key(0), x)
  assert variables["params"]["kernel"].shape == (3, 3, 4, 6)
  assert variables["params"]["bias"].shape == (6,)
  assert layer.apply(variables, x).shape == (2, 3, 8, 8, 6)
  # Values: every [b, t] frame on its own, as nn.Conv computes it with the same parameters
  # (distinct frames and a non-zero bias, so frames mixed or misplaced would show).
  x = jnp.asarray(np.random.default_rng(5).standard_normal((2, 3, 8, 8, 4)), jnp.float32)
  variables = jax.tree.map(lambda v: v + 0.1, variables)
  got = np.asarray(layer.apply(variables, x))
  ref = nn.Conv(6, (3, 3), padding=((1, 1), (1, 1)), precision="highest")
  for b in range(2):
    for t in range(3):
      np.testing.assert_allclose(got[b, t], ref.apply(variables, x[b, t]), rtol=0, atol=1e-5,
                                 err_msg=str((b, t)))


def test_existing_parameters_are_checked_without_tracing_their_initialiser():
  """`layers.param`: init makes the parameter with its initialiser; apply checks the shape
  without calling it (Flax's check traced it on every call: a quarter of the model's
  forward trace), with Flax's errors for a wrong shape and for a name used twice."""
  calls = []

  def counted(key, shape, dtype):
    calls.append(shape)
    return jnp.full(shape, 2.0, dtype)

  class Layer(nn.Module):
    twice: bool = False

    @nn.compact
    def __call__(self, x):
      w = layers.param(self, "w", counted, (x.shape[-1], 3))
      if self.twice:
        w = w + layers.param(self, "w", counted, (x.shape[-1], 3))
      return x @ w

  x = jnp.ones((2, 4))
  variables = Layer().init(jax.random.key(0), x)
  assert calls == [(4, 3)] and variables["params"]["w"].shape == (4, 3)
  np.testing.assert_array_equal(variables["params"]["w"], 2.0)
  calls.clear()
  y = jax.jit(Layer().apply)({"params": {"w": jnp.ones((4, 3))}}, x)
  np.testing.assert_array_equal(y, 4.0)  # the given values, not the initialiser's
  assert not calls
  with pytest.raises(flax.errors.ScopeParamShapeError,
                     match=r'parameter "w" in "/", the given initializer is expected to '
                     r'generate shape \(5, 3\), but the existing parameter .* shape \(4, 3\)'):
    Layer().apply(variables, jnp.ones((2, 5)))
  with pytest.raises(ValueError, match='Duplicate use of scope name: "w"'):
    Layer(twice=True).apply(variables, x)
  with pytest.raises(ValueError, match='Duplicate use of scope name: "w"'):
    Layer(twice=True).init(jax.random.key(0), x)


def test_forward_mode_autodiff_with_the_canonical_gradient_switched_off():
  rng = np.random.default_rng(3)
  x = jnp.asarray(rng.standard_normal((1, 5, 6, 3)), jnp.float32)
  kernel = jnp.asarray(rng.standard_normal((3, 3, 3, 4)), jnp.float32)
  pad = ((1, 1), (1, 1))
  fn = lambda a: conv2d(a, kernel, pad)  # noqa: E731
  if jax.default_backend() == "cpu":
    with pytest.raises(TypeError, match="custom_vjp"):
      jax.jvp(fn, (x,), (x,))
  set_canonical_conv_gradient(False)
  try:
    _, tangent = jax.jvp(fn, (x,), (x,))
  finally:
    set_canonical_conv_gradient(True)
  np.testing.assert_allclose(tangent, _reference(x, kernel, pad), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("width,taps", [(64, 15), (16, 15), (9, 15), (20, 5), (7, 1), (1, 3)])
def test_dft_correlation_equals_the_direct_convolution_and_its_gradient(width, taps):
  """Every width against the taps (n = W + k//2 odd and even, a kernel wider than the
  input): the same values and gradients as torch's 'same' convolution, to float32 rounding."""
  rng = np.random.default_rng(width * 100 + taps)
  x = jnp.asarray(rng.standard_normal((2, 3, width, 6)), jnp.float32)
  kernel = jnp.asarray(rng.standard_normal((taps, 6, 5)), jnp.float32)
  pad = ((0, 0), (taps // 2, taps // 2))
  want, vjp_want = jax.vjp(lambda a, b: _reference(a, b[None], pad), x, kernel)
  got, vjp_got = jax.vjp(dft_correlate_w, x, kernel)
  assert got.shape == want.shape == (2, 3, width, 5)
  scale = float(jnp.abs(want).max())
  np.testing.assert_allclose(got, want, rtol=0, atol=2e-6 * scale)
  g = jnp.asarray(rng.standard_normal(want.shape), jnp.float32)
  for a, b in zip(vjp_got(g), vjp_want(g)):
    np.testing.assert_allclose(a, b, rtol=0, atol=2e-6 * float(jnp.abs(b).max()))


def test_dft_correlation_in_blocks_of_rows_under_a_memory_budget():
  rng = np.random.default_rng(2)
  x = jnp.asarray(rng.standard_normal((2, 3, 20, 6)), jnp.float32)
  kernel = jnp.asarray(rng.standard_normal((15, 6, 5)), jnp.float32)
  whole = dft_correlate_w(x, kernel)
  row = (3 * 14) * (6 + 5) * 4 / 2**20  # one row's spectrum and products (n = 27: 14 bins)
  products = lambda f: str(jax.make_jaxpr(f)(x)).count("dot_general")  # noqa: E731
  assert products(lambda a: dft_correlate_w(a, kernel, 1.0)) == 4  # bins + 3 for all 6 rows
  # blocks of the rows after the leading (batch) axis: of 3, 1 or 2 each (x 2 in the batch)
  for budget, blocks in ((2.5 * row, 3), (4 * row, 2), (1e-9, 3)):
    blocked = lambda a, b=budget: dft_correlate_w(a, kernel, b)  # noqa: E731
    assert products(blocked) == 1 + 3 * blocks, budget
    np.testing.assert_allclose(jax.jit(blocked)(x), whole, rtol=0, atol=1e-5)
  # 7 rows, 3 fit: blocks of 3, 3 and 1
  seven = x.reshape(6, 20, 6)[jnp.array([[0, 1, 2, 3, 4, 5, 0]])]
  blocked = lambda a: dft_correlate_w(a, kernel, 3 * row)  # noqa: E731
  assert str(jax.make_jaxpr(blocked)(seven)).count("dot_general") == 1 + 3 * 3
  np.testing.assert_allclose(blocked(seven), dft_correlate_w(seven, kernel), rtol=0, atol=1e-5)
  assert dft_correlate_w(x[:0], kernel, 1e-9).shape == (0, 3, 20, 5)  # no rows: no blocks
  # at most DFT_MAX_BLOCKS blocks (they are unrolled), however small the budget
  many = jnp.zeros((1, layers.DFT_MAX_BLOCKS * 2, 20, 6))
  assert str(jax.make_jaxpr(lambda a: dft_correlate_w(a, kernel, 1e-9))(many)).count(
      "dot_general") == 1 + 3 * layers.DFT_MAX_BLOCKS


def test_dft_correlation_keeps_the_dtype_and_names_a_wrong_kernel():
  rng = np.random.default_rng(1)
  x = jnp.asarray(rng.standard_normal((4, 12, 3)), jnp.bfloat16)
  kernel = jnp.asarray(rng.standard_normal((5, 3, 2)), jnp.float32)
  got = dft_correlate_w(x, kernel)
  assert got.dtype == jnp.bfloat16 and got.shape == (4, 12, 2)
  assert "precision=(Precision.HIGHEST" in str(jax.make_jaxpr(dft_correlate_w)(x, kernel))
  want = _reference(x.astype(jnp.float32)[None], kernel[None], ((0, 0), (2, 2)))[0]
  np.testing.assert_allclose(np.asarray(got, np.float32), want, rtol=1e-2, atol=1e-2)
  for bad in ((4, 3, 2), (5, 4, 2)):  # even taps (no centre), channels not the input's
    with pytest.raises(ValueError, match=r"dft_correlate_w: a kernel \[k odd, 3, O\] for "
                       r"input channels 3 and a width >= 1, got kernel shape"):
      dft_correlate_w(x, jnp.zeros(bad))
  with pytest.raises(ValueError, match=r"got kernel shape \(1, 3, 2\) for input shape "
                     r"\(4, 0, 3\)"):
    dft_correlate_w(x[:, :0], jnp.zeros((1, 3, 2)))  # no width (was a ZeroDivisionError)


def test_conv_params_are_conv3d_parameters():
  """Same names, shapes and initial values as the `Conv3D` it stands for (the GRU's DFT path
  reads the checkpoint's convolution weights through it)."""
  x = jnp.zeros((1, 2, 3, 8, 6))
  conv_vars = Conv3D(4, (1, 1, 5), (0, 0, 2)).init(jax.random.key(3), x)
  params_vars = ConvParams(4, (1, 1, 5)).init(jax.random.key(3), 6)
  assert jax.tree.map(jnp.shape, params_vars) == jax.tree.map(jnp.shape, conv_vars)
  for a, b in zip(jax.tree.leaves(params_vars), jax.tree.leaves(conv_vars)):
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("make,shape", [
    (lambda: layers.conv(8, (3, 3), 1, 1, dtype=jnp.bfloat16), (4, 32, 64, 6)),
    (lambda: layers.conv(8, (3, 3, 3), 1, 1, dtype=jnp.bfloat16), (1, 4, 32, 64, 6)),
    (lambda: layers.conv(8, (5, 1, 1), 1, (2, 0, 0), dtype=jnp.bfloat16), (1, 4, 32, 64, 6)),
    (lambda: layers.conv(8, (4, 4), 4, 0, dtype=jnp.bfloat16), (4, 128, 256, 3)),
    (lambda: layers.dense(8, dtype=jnp.bfloat16), (4, 32, 64, 6))])
def test_bfloat16_bias_gradient_is_summed_in_float32(make, shape):
  """In bfloat16 compute a bias's gradient is the sum of the output's cotangent over its
  8192 positions. Summed in bfloat16 (the bias cast before its broadcast, as flax's Dense
  and Conv do), XLA:CPU stalled at 1024 where the sum is ~10240 (8192 cotangents of ~1.25:
  a term below half a bfloat16 step of its partial sum is lost). It must be the float32
  sum of the bfloat16 cotangents: within 1e-4 relative of their float64 sum (float32
  summation of 8192 positive terms is ~1e-6 off)."""
  rng = np.random.default_rng(0)
  module = make()
  x = jnp.asarray(rng.standard_normal(shape), jnp.float32)
  variables = module.init(jax.random.key(0), x)
  y = module.apply(variables, x)
  assert y.dtype == jnp.bfloat16 and np.prod(y.shape[:-1]) == 8192
  cot = jnp.asarray(1 + rng.uniform(0, 0.5, y.shape), jnp.bfloat16)  # exact bfloat16 values
  loss = lambda v: jnp.sum(module.apply(v, x).astype(jnp.float32) * cot)  # noqa: E731
  got = jax.grad(loss)(variables)["params"]["bias"]
  want = np.asarray(cot, np.float64).reshape(-1, y.shape[-1]).sum(axis=0)
  assert got.dtype == jnp.float32
  np.testing.assert_allclose(got, want, rtol=1e-4)

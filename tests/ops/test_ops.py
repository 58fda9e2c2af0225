"""Closed-form and loop-reference checks of the torch-compatible primitives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sav_jax.ops.correlation import SMALL_WINDOW, WIDE_WINDOW, aapc, window_correlation
from sav_jax.ops.pool import avg_pool
from sav_jax.ops.resize import interp_matrix, resize
from sav_jax.ops.sample import warp_x
from sav_jax.ops.upsample import convex_upsample_3d, neighbours_3d

RNG = np.random.default_rng(0)

# Checks of values against references: no need for XLA's optimisations (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("fast_compile")


# ---------------------------------------------------------------- resize
def test_bilinear_align_corners_true_keeps_corners_and_ramps():
  x = np.arange(5, dtype=np.float32)[None, :, None, None] * np.ones((1, 5, 7, 1), np.float32)
  out = np.asarray(resize(jnp.asarray(x), (9, 7), "bilinear", align_corners=True))
  np.testing.assert_allclose(out[0, :, 0, 0], np.linspace(0, 4, 9), atol=1e-6)


def test_bilinear_align_corners_false_matches_torch_formula():
  # torch: src = (dst + 0.5) * in/out - 0.5, clamped at 0; 4 -> 8 gives these weights.
  m = interp_matrix(4, 8, "bilinear", False)
  src = np.clip((np.arange(8) + 0.5) * 0.5 - 0.5, 0, None)
  np.testing.assert_allclose(m @ np.arange(4.0), np.minimum(src, 3), atol=1e-12)
  # Downsampling 8 -> 4 averages neighbour pairs (no antialiasing, like torch's default).
  np.testing.assert_allclose(interp_matrix(8, 4, "bilinear", False) @ np.arange(8.0),
                             [0.5, 2.5, 4.5, 6.5])


def test_resize_identity_and_rows_sum_to_one():
  x = jnp.asarray(RNG.normal(size=(2, 6, 10, 3)), jnp.float32)
  np.testing.assert_array_equal(resize(x, (6, 10)), x)
  for mode in ("bilinear", "bicubic"):
    for ac in (True, False):
      m = interp_matrix(7, 13, mode, ac)
      np.testing.assert_allclose(m.sum(1), 1.0, atol=1e-12)


@pytest.mark.parametrize("shape,size,align_corners", [
    ((2, 7, 13, 3), (5, 29), False), ((2, 7, 13, 3), (16, 6), True), ((1, 9, 4, 2), (9, 11), True),
    ((3, 1, 6, 2), (4, 6), False)])
def test_bilinear_two_taps_equal_the_dense_interpolation(shape, size, align_corners):
  """The two-tap blend gives the dense matrix product's values and gradients."""
  x = jnp.asarray(RNG.normal(size=shape), jnp.float32)
  my = jnp.asarray(interp_matrix(shape[1], size[0], "bilinear", align_corners), jnp.float32)
  mx = jnp.asarray(interp_matrix(shape[2], size[1], "bilinear", align_corners), jnp.float32)
  dense = lambda x: jnp.einsum("oh,pw,nhwc->nopc", my, mx, x)  # noqa: E731
  fast = lambda x: resize(x, size, "bilinear", align_corners)  # noqa: E731
  np.testing.assert_allclose(fast(x), dense(x), rtol=1e-6, atol=1e-6)
  cot = jnp.asarray(RNG.normal(size=(shape[0], *size, shape[3])), jnp.float32)
  grad = lambda f: jax.grad(lambda x: jnp.sum(f(x) * cot))(x)  # noqa: E731
  np.testing.assert_allclose(grad(fast), grad(dense), rtol=1e-5, atol=1e-5)
  assert resize(x.astype(jnp.bfloat16), size, "bilinear", align_corners).dtype == jnp.bfloat16


def test_bilinear_resize_matches_opencv():
  """align_corners=False is OpenCV's INTER_LINEAR (float input), up and down."""
  import cv2  # pylint: disable=import-outside-toplevel
  img = RNG.uniform(0, 1, (11, 17, 3)).astype(np.float32)
  for out_h, out_w in ((23, 40), (6, 9)):
    want = cv2.resize(img, (out_w, out_h), interpolation=cv2.INTER_LINEAR)
    got = np.asarray(resize(jnp.asarray(img)[None], (out_h, out_w), "bilinear", False))[0]
    np.testing.assert_allclose(got, want, atol=2e-5)
  # Integer images are rounded to the nearest value (a cast truncated: about half of the
  # values came out one lower than torch's), and stay in the type's range.
  img8 = RNG.integers(0, 256, (11, 17, 3), dtype=np.uint8)
  for mode in ("bilinear", "bicubic"):
    exact = np.asarray(resize(jnp.asarray(img8, jnp.float32)[None], (23, 40), mode, False))[0]
    got = np.asarray(resize(jnp.asarray(img8)[None], (23, 40), mode, False))[0]
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, np.clip(np.floor(exact + 0.5), 0, 255))
  # halves round up, as OpenCV's uint8 resize does (a 2x downsample averages pairs)
  row = jnp.asarray([[0, 1, 0, 3, 10, 11]], jnp.uint8)[None, :, :, None]
  np.testing.assert_array_equal(resize(row, (1, 3), "bilinear", False)[0, 0, :, 0], [1, 2, 11])


def test_bicubic_scale_factor_source_coordinates():
  """torch maps dst -> (dst + 0.5) / scale - 0.5 with the *given* scale factor."""
  n_in, n_out = 37, 4
  scale = (n_out + 0.1) / n_in
  m_scale = interp_matrix(n_in, n_out, "bicubic", False, scale)
  m_size = interp_matrix(n_in, n_out, "bicubic", False)
  assert not np.allclose(m_scale, m_size)  # the +0.1 offset changes the weights
  # Keys' cubic convolution kernel with A = -0.75, evaluated independently per tap.
  a = -0.75

  def kernel(d):
    d = abs(d)
    if d <= 1:
      return (a + 2) * d**3 - (a + 3) * d**2 + 1
    return a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a if d < 2 else 0.0

  src = (np.arange(n_out) + 0.5) / scale - 0.5
  for row, s in enumerate(src):
    expect = np.zeros(n_in)
    for tap in range(int(np.floor(s)) - 1, int(np.floor(s)) + 3):
      expect[min(max(tap, 0), n_in - 1)] += kernel(s - tap)  # taps clamp at the border
    np.testing.assert_allclose(m_scale[row], expect, atol=1e-12)


# ---------------------------------------------------------------- warp
def test_warp_integer_and_fractional_shifts_with_zero_padding():
  w = 8
  f = np.arange(1, w + 1, dtype=np.float32)[None, None, :, None] * np.ones((1, 2, w, 3), np.float32)
  out = np.asarray(warp_x(jnp.asarray(f), jnp.full((1, 2, w), 2.0)))
  expect = np.concatenate([[0, 0], np.arange(1, w - 1)]).astype(np.float32)  # f[x-2], 0 outside
  np.testing.assert_allclose(out[0, 0, :, 0], expect)
  out = np.asarray(warp_x(jnp.asarray(f), jnp.full((1, 2, w), 0.25)))
  # x - 0.25: 0.75 * f[x] + 0.25 * f[x-1]; at x = 0 the left tap is outside -> 0.
  expect = 0.75 * np.arange(1, w + 1) + 0.25 * np.arange(0, w)
  np.testing.assert_allclose(out[0, 1, :, 2], expect, atol=1e-6)


# ---------------------------------------------------------------- pooling
def test_avg_pool_drops_remainder_like_torch():
  x = RNG.normal(size=(1, 9, 10, 2)).astype(np.float32)
  out = np.asarray(avg_pool(jnp.asarray(x), 4))
  assert out.shape == (1, 2, 2, 2)
  np.testing.assert_allclose(out[0, 1, 0], x[0, 4:8, 0:4].mean(axis=(0, 1)), atol=1e-6)
  with pytest.raises(ValueError, match="a 3x10 map is smaller than the 4x4 window"):
    avg_pool(jnp.asarray(x[:, :3]), 4)  # torch refuses it too; an empty map before


# ---------------------------------------------------------------- correlation
def _corr_loops(left, right, window, groups=4):
  n, h, w, c = left.shape
  wy, wx = window
  cg = c // groups
  pad = lambda a: np.pad(a, [(0, 0), (wy // 2,) * 2, (wx // 2,) * 2, (0, 0)], mode="edge")
  lp, rp = pad(left), pad(right)
  offsets = [(dy, dx) for dy in range(wy) for dx in range(wx)]
  out = np.zeros((n, h, w, groups * len(offsets) ** 2), np.float64)
  for g in range(groups):
    sl = slice(g * cg, (g + 1) * cg)
    for a, (ay, ax) in enumerate(offsets):
      for b, (by, bx) in enumerate(offsets):
        ch = g * len(offsets) ** 2 + a * len(offsets) + b
        out[..., ch] = (lp[:, ay:ay + h, ax:ax + w, sl] * rp[:, by:by + h, bx:bx + w, sl]).sum(-1)
  return out


@pytest.mark.parametrize("window", [WIDE_WINDOW, SMALL_WINDOW, (5, 3), (3, 1)])
@pytest.mark.parametrize("block,width", [(16, 11), (4, 11), (16, 37), (40, 23)])
def test_window_correlation_matches_loops(window, block, width):
  # Widths below, between and above multiples of the block; blocks narrower than
  # the band (raised internally) and wider than the padded row.
  left = RNG.normal(size=(2, 5, width, 16)).astype(np.float32)
  right = RNG.normal(size=(2, 5, width, 16)).astype(np.float32)
  out = window_correlation(jnp.asarray(left), jnp.asarray(right), window, block=block)
  np.testing.assert_allclose(out, _corr_loops(left, right, window), atol=1e-4)


@pytest.mark.parametrize("window", [WIDE_WINDOW, SMALL_WINDOW])
def test_window_correlation_gradients_match_stacked_views(window):
  # Reference: every window view stacked, all pairs from one einsum (the direct form).
  def stacked(left, right):
    wy, wx = window
    h, w = left.shape[1:3]
    pad = lambda a: jnp.pad(a, [(0, 0), (wy // 2,) * 2, (wx // 2,) * 2, (0, 0)], mode="edge")
    views = lambda a: jnp.stack([pad(a)[:, y:y + h, x:x + w] for y in range(wy)
                                 for x in range(wx)], axis=3).reshape(*a.shape[:3], wy * wx, 4, -1)
    return jnp.einsum("nhwagc,nhwbgc->nhwgab", views(left), views(right)).reshape(*left.shape[:3], -1)

  left = jnp.asarray(RNG.normal(size=(1, 4, 13, 8)), jnp.float32)
  right = jnp.asarray(RNG.normal(size=(1, 4, 13, 8)), jnp.float32)
  weights = jnp.asarray(RNG.normal(size=(1, 4, 13, 4 * (window[0] * window[1]) ** 2)), jnp.float32)
  loss = lambda f: lambda a, b: jnp.sum(weights * f(a, b))
  got = jax.grad(loss(lambda a, b: window_correlation(a, b, window)), argnums=(0, 1))(left, right)
  want = jax.grad(loss(stacked), argnums=(0, 1))(left, right)
  for g, w_ in zip(got, want):
    np.testing.assert_allclose(g, w_, atol=1e-4)


def test_aapc_with_zero_flow_is_plain_window_correlation():
  f1 = RNG.normal(size=(1, 4, 9, 8)).astype(np.float32)
  f2 = RNG.normal(size=(1, 4, 9, 8)).astype(np.float32)
  out = aapc(jnp.asarray(f1), jnp.asarray(f2), jnp.zeros((1, 4, 9)), SMALL_WINDOW)
  np.testing.assert_allclose(out, _corr_loops(f1, f2, SMALL_WINDOW), atol=1e-4)


def test_correlation_rejects_indivisible_channels():
  with pytest.raises(ValueError, match="divisible"):
    window_correlation(jnp.zeros((1, 2, 2, 6)), jnp.zeros((1, 2, 2, 6)), SMALL_WINDOW)


# ---------------------------------------------------------------- convex upsampling
def test_neighbours_3d_zero_pads_time_and_space():
  x = jnp.asarray(RNG.normal(size=(1, 2, 3, 4, 1)), jnp.float32)
  nb = np.asarray(neighbours_3d(x))
  assert nb.shape == (1, 2, 3, 4, 27, 1)
  np.testing.assert_array_equal(nb[..., 13, :], x)  # centre
  assert np.all(nb[:, 0, :, :, 0:9] == 0)  # previous frame of frame 0 is outside
  np.testing.assert_array_equal(nb[0, 1, 1, 1, 0], x[0, 0, 0, 0])  # (t-1, y-1, x-1)


def _convex_loops(flow, mask, rate):
  b, t, h, w, c = flow.shape
  wts = mask.reshape(b, t, h, w, 27, rate, rate).astype(np.float64)
  wts = np.exp(wts - wts.max(4, keepdims=True))
  wts /= wts.sum(4, keepdims=True)
  fp = np.pad(rate * flow, [(0, 0), (1, 1), (1, 1), (1, 1), (0, 0)])
  out = np.zeros((b, t, h * rate, w * rate, c))
  for ti in range(t):
    for y in range(h):
      for x in range(w):
        for ry in range(rate):
          for rx in range(rate):
            acc = 0.0
            for k in range(27):
              dt, dy, dx = k // 9, (k // 3) % 3, k % 3
              acc = acc + wts[:, ti, y, x, k, ry, rx, None] * fp[:, ti + dt, y + dy, x + dx]
            out[:, ti, y * rate + ry, x * rate + rx] = acc
  return out


def test_convex_upsample_matches_loops():
  flow = RNG.normal(size=(1, 3, 2, 3, 2)).astype(np.float32)
  mask = RNG.normal(size=(1, 3, 2, 3, 27 * 4)).astype(np.float32)
  out = convex_upsample_3d(jnp.asarray(flow), jnp.asarray(mask), rate=2)
  np.testing.assert_allclose(out, _convex_loops(flow, mask, 2), atol=1e-5)


def test_convex_upsample_of_bfloat16_inputs_computes_in_float32():
  """bfloat16 flow and mask (the model's compute dtype): the softmax and the combination
  run in float32 on the values given, not in bfloat16 (8 bits: ~1e-2 off)."""
  flow = jnp.asarray(RNG.normal(size=(1, 3, 2, 3, 1)) * 8, jnp.bfloat16)
  mask = jnp.asarray(RNG.normal(size=(1, 3, 2, 3, 27 * 4)) * 4, jnp.bfloat16)
  out = convex_upsample_3d(flow, mask, rate=2)
  assert out.dtype == jnp.float32
  want = _convex_loops(*(np.asarray(a, np.float32) for a in (flow, mask)), 2)
  np.testing.assert_allclose(out, want, rtol=1e-5, atol=1e-5)


def test_convex_upsample_of_constant_flow_in_the_interior():
  """Away from the zero padding, a convex combination of a constant is the constant x rate."""
  flow = np.full((1, 3, 4, 4, 1), 1.5, np.float32)
  mask = RNG.normal(size=(1, 3, 4, 4, 27 * 16)).astype(np.float32)
  out = np.asarray(convex_upsample_3d(jnp.asarray(flow), jnp.asarray(mask)))
  np.testing.assert_allclose(out[0, 1, 4:12, 4:12], 6.0, atol=1e-5)

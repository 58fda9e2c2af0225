"""Closed-form and loop-reference checks of the torch-compatible primitives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sav_jax.ops.correlation import SMALL_WINDOW, WIDE_WINDOW, aapc, window_correlation
from sav_jax.ops.pool import avg_pool
from sav_jax.ops.resize import interp_matrix, resize
from sav_jax.ops.sample import warp_x
from sav_jax.ops.upsample import convex_upsample_2d, convex_upsample_3d, neighbours_3d

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


def test_warp_of_integer_features_rounds_to_the_nearest():
  """An integer image warped by half a pixel was truncated (a plain cast): 10.5 came out 10."""
  f = jnp.asarray(np.array([10, 11, 20, 250], np.uint8)[None, None, :, None])
  out = warp_x(f, jnp.full((1, 1, 4), 0.5))  # 0.5 * (f[x] + f[x - 1]), 0 left of the image
  assert out.dtype == jnp.uint8
  np.testing.assert_array_equal(np.asarray(out)[0, 0, :, 0], [5, 11, 16, 135])


# ---------------------------------------------------------------- pooling
def test_avg_pool_drops_remainder_like_torch():
  x = RNG.normal(size=(1, 9, 10, 2)).astype(np.float32)
  out = np.asarray(avg_pool(jnp.asarray(x), 4))
  assert out.shape == (1, 2, 2, 2)
  np.testing.assert_allclose(out[0, 1, 0], x[0, 4:8, 0:4].mean(axis=(0, 1)), atol=1e-6)
  # every window: the 4x4 blocks of the 8x8 corner (the last row and 2 columns dropped)
  want = x[:, :8, :8].astype(np.float64).reshape(1, 2, 4, 2, 4, 2).mean(axis=(2, 4))
  np.testing.assert_allclose(out, want, rtol=0, atol=1e-6)
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
  with pytest.raises(ValueError, match="divides the 6 feature channels, got 4"):
    window_correlation(jnp.zeros((1, 2, 2, 6)), jnp.zeros((1, 2, 2, 6)), SMALL_WINDOW)
  # block=0 with a one-column window divided by zero; a fractional one failed in jnp.pad
  for block in (0, 2.5):
    with pytest.raises(ValueError, match=rf"block must be a positive integer, got {block}"):
      window_correlation(jnp.zeros((1, 2, 2, 8)), jnp.zeros((1, 2, 2, 8)), (3, 1), block=block)


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


# ---------------------------------------------------------------- torch semantics, in NumPy
# Independent references written from the documented definitions of torch's
# F.interpolate (bilinear, bicubic), grid_sample and F.unfold, per output element.
def _linear_taps(n_in, n_out, align_corners, scale=None):
  """torch's linear interpolation along one axis: per output index, its `(input, weight)`
  taps. Source index: `i * (in - 1) / (out - 1)` (0 for one output) with align_corners,
  else `(i + 0.5) / scale - 0.5` (scale: the given factor, else out / in) clamped at 0; the
  second tap is the next input, or the same one at the last input."""
  taps = []
  for i in range(n_out):
    if align_corners:
      src = i * (n_in - 1) / (n_out - 1) if n_out > 1 else 0.0
    else:
      src = max((i + 0.5) * (1.0 / scale if scale else n_in / n_out) - 0.5, 0.0)
    i0 = int(np.floor(src))
    lam = src - i0
    taps.append([(i0, 1.0 - lam), (i0 + 1 if i0 < n_in - 1 else i0, lam)])
  return taps


def _keys_cubic(d, a=-0.75):
  d = abs(d)
  if d <= 1:
    return (a + 2) * d**3 - (a + 3) * d**2 + 1
  return a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a if d < 2 else 0.0


def _cubic_taps(n_in, n_out, align_corners, scale=None):
  """torch's bicubic taps along one axis: four inputs around the (unclamped) source index,
  Keys' kernel with A = -0.75, each index clamped to the border."""
  taps = []
  for i in range(n_out):
    if align_corners:
      src = i * (n_in - 1) / (n_out - 1) if n_out > 1 else 0.0
    else:
      src = (i + 0.5) * (1.0 / scale if scale else n_in / n_out) - 0.5
    f = int(np.floor(src))
    taps.append([(min(max(f - 1 + k, 0), n_in - 1), _keys_cubic(src - (f - 1 + k)))
                 for k in range(4)])
  return taps


def _interpolate_ref(x, size, mode, align_corners, scale=(None, None)):
  """`F.interpolate` of channels-last `x` [N, H, W, C] in float64, output by output."""
  taps = _linear_taps if mode == "bilinear" else _cubic_taps
  ty = taps(x.shape[1], size[0], align_corners, scale[0])
  tx = taps(x.shape[2], size[1], align_corners, scale[1])
  out = np.zeros((x.shape[0], *size, x.shape[3]))
  for i, j in np.ndindex(*size):
    for a, wa in ty[i]:
      for b, wb in tx[j]:
        out[:, i, j] += wa * wb * x[:, a, b].astype(np.float64)
  return out


@pytest.mark.parametrize("mode,shape,size,align_corners,scale", [
    ("bilinear", (1, 5, 7, 2), (1, 1), True, None),  # one output: the first input
    ("bilinear", (1, 5, 7, 2), (1, 3), False, None),
    ("bilinear", (2, 5, 7, 2), (3, 11), False, (0.6, 1.7)),  # the scale factors, per axis
    ("bilinear", (1, 3, 4, 2), (3, 4), False, (1.2, 1.1)),  # same size, shifted by the factor
    ("bilinear", (1, 4, 6, 1), (9, 2), True, None),
    ("bicubic", (1, 4, 5, 2), (9, 11), False, None),  # border taps clamp (upsampling)
    ("bicubic", (1, 4, 5, 2), (7, 13), True, None),
    ("bicubic", (1, 6, 5, 1), (1, 1), True, None),
    ("bicubic", (1, 9, 6, 2), (4, 8), False, (0.47, 1.4)),
    ("bicubic", (1, 3, 4, 1), (3, 4), False, (1.2, 1.1)),
])
def test_resize_matches_torch_interpolate_definition(mode, shape, size, align_corners, scale):
  x = RNG.normal(size=shape).astype(np.float32)
  got = resize(jnp.asarray(x), size, mode, align_corners, scale)
  assert got.shape == (shape[0], *size, shape[3])
  want = _interpolate_ref(x, size, mode, align_corners, scale or (None, None))
  np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5, atol=1e-5)


def test_integer_resize_clips_the_bicubic_overshoot():
  """Bicubic weights go negative: a sharp 0/255 edge overshoots below 0 and above 255; uint8
  outputs are the rounded values clipped to 0..255, not wrapped around."""
  edge = np.zeros((1, 4, 8, 1), np.uint8)
  edge[:, :, 4:] = 255
  want = _interpolate_ref(edge, (4, 19), "bicubic", False)
  assert want.min() < -0.5 and want.max() > 255.5  # (the overshoot is there to clip)
  got = np.asarray(resize(jnp.asarray(edge), (4, 19), "bicubic", False))
  assert got.dtype == np.uint8
  np.testing.assert_array_equal(got, np.clip(np.floor(want + 0.5), 0, 255))


@pytest.mark.filterwarnings("ignore:Explicitly requested dtype")  # (JAX's, for int64)
def test_integer_resize_of_numpy_int64_and_uint32_images():
  """NumPy's default integers (int64) and uint32 failed with an OverflowError from JAX: the
  clip's bounds (iinfo of the type) did not fit its int32 arguments."""
  x = np.array([0, 100, 101, 200]).reshape(1, 4, 1)  # int64
  for dtype in (np.int64, np.uint32):
    got = np.asarray(resize(x.astype(dtype), (1, 7), align_corners=True))
    np.testing.assert_array_equal(got.ravel(), [0, 50, 100, 101, 101, 151, 200])


def _grid_sample_x(features, disp):
  """grid_sample (bilinear, zero padding, align_corners=True) at `(x - disp, y)`: two taps,
  each outside `[0, W - 1]` contributing zero."""
  n, h, w, _ = features.shape
  out = np.zeros(features.shape, np.float64)
  for b, y, x in np.ndindex(n, h, w):
    sx = x - float(disp[b, y, x])
    x0 = int(np.floor(sx))
    for xi, wt in ((x0, 1.0 - (sx - x0)), (x0 + 1, sx - x0)):
      if 0 <= xi < w:
        out[b, y, x] += wt * features[b, y, xi]
  return out


def test_warp_matches_grid_sample_for_any_disparity():
  """Fractional disparities of both signs, far outside the row too: samples past either
  edge fade to zero, those exactly at the last column read it."""
  w = 7
  f = RNG.normal(size=(2, 3, w, 4)).astype(np.float32)
  disp = RNG.uniform(-w - 2, w + 2, (2, 3, w)).astype(np.float32)
  disp[0, 0] = np.arange(w) - (w - 1)  # every sample at x = W - 1 exactly
  disp[0, 1] = -0.5  # half a pixel right: the last column half outside
  disp[0, 2] = np.arange(w) - (w - 0.25)  # a quarter pixel past the last column
  got = warp_x(jnp.asarray(f), jnp.asarray(disp))
  np.testing.assert_allclose(np.asarray(got), _grid_sample_x(f, disp), atol=1e-6)
  np.testing.assert_allclose(np.asarray(got)[0, 0], np.broadcast_to(f[0, 0, -1], (w, 4)))
  assert warp_x(jnp.asarray(f, jnp.bfloat16), jnp.asarray(disp)).dtype == jnp.bfloat16


def test_aapc_correlates_the_left_map_with_the_warped_right_map():
  f1 = RNG.normal(size=(1, 4, 11, 8)).astype(np.float32)
  f2 = RNG.normal(size=(1, 4, 11, 8)).astype(np.float32)
  disp = RNG.uniform(-3, 6, (1, 4, 11)).astype(np.float32)
  warped = _grid_sample_x(f2, disp)
  # the official windows: 1x9 (wide) and 3x3 (small)
  for window, official in ((WIDE_WINDOW, (1, 9)), (SMALL_WINDOW, (3, 3))):
    out = aapc(jnp.asarray(f1), jnp.asarray(f2), jnp.asarray(disp), window)
    np.testing.assert_allclose(out, _corr_loops(f1, warped, official), atol=1e-4)


def test_avg_pool_refuses_a_map_narrower_than_the_window():
  x = jnp.zeros((1, 9, 3, 2))
  with pytest.raises(ValueError, match="a 9x3 map is smaller than the 4x4 window"):
    avg_pool(x, 4)
  assert avg_pool(jnp.zeros((1, 4, 4, 2)), 4).shape == (1, 1, 1, 2)  # the window itself: fine
  # k = 0 divided by zero, a float k failed in a reshape
  for k in (0, 2.0):
    with pytest.raises(ValueError, match=rf"the window k must be a positive integer, got {k}"):
      avg_pool(x, k)


def _convex_2d_loops(flow, mask, rate):
  """RAFT's upsample_flow: the mask viewed as [9, rate, rate] per pixel, softmax over the 9
  taps, times F.unfold(rate * flow, 3, padding=1) (zero padding, tap k = dy * 3 + dx)."""
  b, h, w, c = flow.shape
  wts = mask.reshape(b, h, w, 9, rate, rate).astype(np.float64)
  wts = np.exp(wts - wts.max(3, keepdims=True))
  wts /= wts.sum(3, keepdims=True)
  fp = np.pad(rate * flow.astype(np.float64), [(0, 0), (1, 1), (1, 1), (0, 0)])
  out = np.zeros((b, h * rate, w * rate, c))
  for y, x, ry, rx in np.ndindex(h, w, rate, rate):
    for k in range(9):
      out[:, y * rate + ry, x * rate + rx] += (wts[:, y, x, k, ry, rx, None]
                                               * fp[:, y + k // 3, x + k % 3])
  return out


@pytest.mark.parametrize("rate", [8, 2])
def test_convex_upsample_2d_matches_raft(rate):
  flow = RNG.normal(size=(1, 3, 4, 2)).astype(np.float32)
  mask = (RNG.normal(size=(1, 3, 4, 9 * rate * rate)) * 3).astype(np.float32)
  if rate == 8:  # RAFT's rate is the default
    out = convex_upsample_2d(jnp.asarray(flow), jnp.asarray(mask))
  else:
    out = convex_upsample_2d(jnp.asarray(flow), jnp.asarray(mask), rate=rate)
  assert out.shape == (1, 3 * rate, 4 * rate, 2) and out.dtype == jnp.float32
  np.testing.assert_allclose(out, _convex_2d_loops(flow, mask, rate), rtol=1e-5, atol=1e-5)


def test_convex_upsampling_asks_for_full_float32_products():
  """The convex combinations ask for HIGHEST precision whatever the default matmul
  precision (on GPUs, TF32 or bfloat16 products would round the flow to ~1e-3 relative)."""
  flow2, mask2 = jnp.zeros((1, 2, 2, 2)), jnp.zeros((1, 2, 2, 9 * 4))
  flow3, mask3 = jnp.zeros((1, 2, 2, 2, 2)), jnp.zeros((1, 2, 2, 2, 27 * 4))
  with jax.default_matmul_precision("bfloat16"):
    for fn, args in ((convex_upsample_2d, (flow2, mask2)), (convex_upsample_3d, (flow3, mask3))):
      text = jax.jit(lambda f, m, fn=fn: fn(f, m, rate=2)).lower(*args).as_text()
      assert "HIGHEST" in text, fn.__name__


# ---------------------------------------------------------------- float64 gradients
def _central_difference_error(fn, x, rng):
  """Largest relative difference between `jax.grad` of `sum(fn(x) * weights)` along random
  directions and its central finite difference, in float64."""
  w = jnp.asarray(rng.normal(size=jax.eval_shape(fn, x).shape))
  loss = jax.jit(lambda z: jnp.sum(fn(z) * w))  # (jitted: eager ops compiled one by one)
  grad, eps, worst = jax.jit(jax.grad(loss))(x), 1e-6, 0.0
  for _ in range(3):
    d = jnp.asarray(rng.normal(size=x.shape))
    fd = (loss(x + eps * d) - loss(x - eps * d)) / (2 * eps)
    worst = max(worst, abs(float(fd - jnp.sum(grad * d))) / abs(float(fd)))
  return worst


def test_float64_inputs_are_computed_in_float64_and_match_finite_differences():
  """With jax_enable_x64, float64 inputs stay float64 through every op (they were cast to
  float32 inside, so a float64 gradient check disagreed with the op's own gradient by
  5e-2 to 1 relative): warping, correlation, resizing and convex upsampling."""
  rng = np.random.default_rng(5)
  with jax.enable_x64(True):
    f64 = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float64)
    feats, left, right = f64(1, 3, 11, 8), f64(1, 3, 7, 8), f64(1, 3, 7, 8)
    disp = jnp.asarray(rng.uniform(-3, 14, (1, 3, 11)) + 0.3)
    small_disp = jnp.asarray(rng.uniform(0.1, 3, (1, 3, 7)) + 0.37)
    flow, mask = f64(1, 3, 2, 3, 1), f64(1, 3, 2, 3, 27 * 4)
    flow2, mask2 = f64(1, 2, 3, 1), f64(1, 2, 3, 9 * 4)
    cases = {
        "warp (features)": (lambda z: warp_x(z, disp), feats),
        "warp (disparity)": (lambda z: warp_x(feats, z), disp),
        "correlation 1x9": (lambda z: window_correlation(z, right, WIDE_WINDOW), left),
        "aapc 3x3 (disparity)": (lambda z: aapc(left, right, z, SMALL_WINDOW), small_disp),
        "bilinear": (lambda z: resize(z, (9, 13), "bilinear", False), feats[..., :2]),
        "bilinear, align_corners": (lambda z: resize(z, (9, 13), "bilinear", True), feats),
        "bicubic": (lambda z: resize(z, (9, 13), "bicubic"), feats[..., :2]),
        "convex 3d (flow)": (lambda z: convex_upsample_3d(z, mask, 2), flow),
        "convex 3d (mask)": (lambda z: convex_upsample_3d(flow, z, 2), mask),
        "convex 2d (mask)": (lambda z: convex_upsample_2d(flow2, z, 2), mask2),
    }
    for name, (fn, x) in cases.items():
      assert fn(x).dtype == jnp.float64, name
      assert _central_difference_error(fn, x, rng) < 1e-6, name
  # float32 and bfloat16 inputs are still computed in float32
  assert window_correlation(*(jnp.zeros((1, 2, 4, 8), jnp.bfloat16),) * 2,
                            SMALL_WINDOW).dtype == jnp.float32
  assert convex_upsample_3d(jnp.zeros((1, 1, 1, 1, 1), jnp.bfloat16),
                            jnp.zeros((1, 1, 1, 1, 27 * 4), jnp.bfloat16), 2).dtype == jnp.float32


def test_numpy_float64_and_int64_inputs_give_no_jax_dtype_warning():
  """Every op warned "Explicitly requested dtype float64 requested in dtype is not available"
  for NumPy's default float64 / int64 arrays without x64: its own dtype computation asked."""
  import warnings  # pylint: disable=import-outside-toplevel
  f = RNG.normal(size=(1, 2, 5, 4))  # float64
  with jax.enable_x64(False), warnings.catch_warnings():
    warnings.simplefilter("error")
    assert warp_x(f, np.zeros((1, 2, 5), np.int64)).dtype == jnp.float32
    assert resize(f, (3, 3)).dtype == jnp.float32
    assert convex_upsample_2d(f[..., :1], np.zeros((1, 2, 5, 9 * 4)), 2).dtype == jnp.float32


def test_misshapen_op_arguments_are_named():
  """Misshapen arguments got deep errors ("indices and arr must have the same number of
  dimensions", "cannot reshape array") or, for right maps of another width and even windows,
  a silently wrong correlation; each is now a ValueError naming the argument and its shape."""
  f = jnp.ones((1, 4, 8, 8))
  cases = [
      (lambda: warp_x(f, jnp.ones((1, 4, 8, 1))), r"disp must be \[N, H, W\].*\(1, 4, 8, 1\)"),
      (lambda: warp_x(f, jnp.ones((1, 4, 5))), r"disp \(1, 4, 5\) must be features' .*\(1, 4, 8\)"),
      (lambda: aapc(f, f, jnp.ones((1, 4, 8, 1)), SMALL_WINDOW), r"disp must be \[N, H, W\]"),
      (lambda: aapc(f, jnp.ones((1, 4, 9, 8)), jnp.ones((1, 4, 8)), SMALL_WINDOW),
       r"fmap1 and fmap2 differ in shape: \(1, 4, 8, 8\) vs \(1, 4, 9, 8\)"),
      (lambda: window_correlation(f, jnp.ones((1, 4, 9, 8)), SMALL_WINDOW),
       r"left and right .* differ in shape: \(1, 4, 8, 8\) vs \(1, 4, 9, 8\)"),
      (lambda: window_correlation(f, f, (2, 2)), r"window must be two odd sizes .*\(2, 2\)"),
      (lambda: window_correlation(f[0], f[0], SMALL_WINDOW), r"left must be \[N, H, W, C\].*\(4, 8, 8\)"),
      (lambda: window_correlation(f.astype(bool), f.astype(bool), SMALL_WINDOW), "left .*dtype bool"),
      (lambda: resize(f, 16), r"size must be the output \(height, width\), got 16"),
      (lambda: resize(jnp.ones((4, 4)), (8, 8)), r"x must be \[\.\.\., height, width, channels\].*\(4, 4\)"),
      (lambda: convex_upsample_3d(jnp.ones((1, 2, 3, 4, 1)), jnp.ones((1, 2, 3, 4, 16)), 4),
       r"mask \(1, 2, 3, 4, 16\) does not fit flow \(1, 2, 3, 4, 1\) at rate 4: expected "
       r"\(1, 2, 3, 4, 432\)"),
      (lambda: convex_upsample_3d(jnp.ones((2, 3, 4, 1)), jnp.ones((2, 3, 4, 432)), 4),
       r"flow must be \[B, T, h, w, C\].*\(2, 3, 4, 1\)"),
      (lambda: convex_upsample_2d(jnp.ones((1, 3, 4, 1)), jnp.ones((1, 3, 4, 27 * 4)), 2),
       r"expected \(1, 3, 4, 36\)"),
  ]
  for fn, match in cases:
    with pytest.raises(ValueError, match=match):
      fn()
  with pytest.raises(TypeError, match="disp must be an array"):
    warp_x(f, 2.0)


def test_resize_scale_factor_must_give_the_size():
  """A size that is not torch's floor(in * scale_factor) has no torch counterpart: the
  source coordinates (from the scale) and the output grid disagree. It was accepted silently."""
  x = jnp.asarray(RNG.normal(size=(4, 4, 1)), jnp.float32)
  with pytest.raises(ValueError, match=r"size \(10, 10\) does not follow scale_factor \(2, 2\) "
                     r"for a 4x4 input: .* = \(8, 8\)"):
    resize(x, (10, 10), "bicubic", scale_factor=(2, 2))
  with pytest.raises(ValueError, match="scale_factor must be two positive numbers"):
    resize(x, (8, 8), "bilinear", scale_factor=(2, -2))
  assert resize(x, (9, 9), "bicubic", scale_factor=(2.3, 2.3)).shape == (9, 9, 1)

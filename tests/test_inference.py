"""Long-video inference: parity with the official forward_batch_test, stitching, memory.

Real-model tests use the golden_batch_test fixture (21 frames of 28x30, iters=2, weights
seed 0): its windows have 20, 11 and 1 frames (padded to 32x32), so every real-model
check here reuses those three compiled shapes. Stitching for other lengths (N=7, N=23
and a sweep) runs with a stand-in for the model that labels each output frame with the
window and position it came from.
"""

import collections
import math
import os
import pathlib
import re
import subprocess
import sys
import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sav_jax
from sav_jax import inference, runtime
from sav_jax.model.init import init_variables
from tests.conftest import XLA_OLDER_EMITTERS, drop_ctrl_c_in_gc

ATOL = 1e-4  # px, the fixture README's criterion for final disparities
ITERS = 2


pytestmark = pytest.mark.usefixtures("fast_compile")


@pytest.fixture(scope="module")
def variables(sav_state_dict):
  return sav_jax.convert.params_from_state_dict(sav_state_dict, sav_jax.SAVConfig())


@pytest.fixture(scope="module")
def golden(fixtures_dir):
  g = dict(np.load(fixtures_dir / "golden_batch_test.npz"))
  video = np.transpose(g["stereo_video"], (0, 1, 3, 4, 2))  # [T, 2, H, W, 3]
  g["left"], g["right"] = video[:, 0], video[:, 1]
  return g


_COMPILE_SECONDS = {}  # inference.compile_seconds() around the module's first runs


@pytest.fixture(scope="module")
def official(variables, golden):
  _COMPILE_SECONDS["before_official"] = inference.compile_seconds()
  with jax.default_matmul_precision("highest"):
    out = inference.forward_batch_test_official(variables, golden["left"], golden["right"],
                                                iters=ITERS, return_windows=True)
  _COMPILE_SECONDS["after_official"] = inference.compile_seconds()
  return out


@pytest.fixture(scope="module")
def predicted(variables, golden):
  """predict_video on the 21 golden frames, with the cache size before and after."""
  before, seconds = inference.cache_size(), inference.compile_seconds()
  disp = _predict(variables, golden["left"], golden["right"])
  _COMPILE_SECONDS["predicted"] = inference.compile_seconds() - seconds
  return disp, before, inference.cache_size()


def _predict(variables, left, right, **kw):
  with jax.default_matmul_precision("highest"):
    return inference.predict_video(variables, left, right, iters=ITERS, **kw)


@pytest.mark.parametrize("i", [0, 1, 2])
def test_window_raw_outputs_match_official(official, golden, i):
  ref = golden[f"window{i}_forward_out"][:, 0, 0]  # [n, 32, 32] padded, before abs
  raw = official[1][i]
  assert raw.shape == ref.shape
  err = np.abs(raw - ref).max()
  assert err <= ATOL, f"window {i}: max abs error {err:.2e} px"


def test_official_stitching_matches_golden(official, golden):
  ref = golden["disparity"][:, 0]
  assert official[0].shape == ref.shape == (21, 28, 30)
  np.testing.assert_allclose(official[0], ref, atol=ATOL, rtol=0)


def test_predict_video_equals_official_for_long_clips(predicted, golden, official):
  disp, before, after = predicted
  assert after == before  # the official run compiled these padded shapes: nothing new
  assert _COMPILE_SECONDS["predicted"] == 0  # ... so no compile time was counted
  assert _COMPILE_SECONDS["after_official"] > _COMPILE_SECONDS["before_official"]
  assert disp.shape == (21, 28, 30) and disp.dtype == np.float32
  np.testing.assert_array_equal(disp, official[0])
  np.testing.assert_allclose(disp, golden["disparity"][:, 0], atol=ATOL, rtol=0)


def test_stitching_equals_windows_run_by_hand(variables, golden, predicted):
  """Frames 0..14 from window [0, 20), frames 15..20 from window [10, 21) ([5:] of it)."""
  pads = inference.pad_amounts(28, 30)
  assert pads == (2, 2, 1, 1)
  with jax.default_matmul_precision("highest"):
    w0 = inference.run_window(variables, golden["left"][:20], golden["right"][:20],
                              cfg=sav_jax.SAVConfig(), iters=ITERS)
    w1 = inference.run_window(variables, golden["left"][10:], golden["right"][10:],
                              cfg=sav_jax.SAVConfig(), iters=ITERS)
  by_hand = np.concatenate([np.abs(w0[:15, 2:-2, 1:-1]), np.abs(w1[5:, 2:-2, 1:-1])])
  np.testing.assert_array_equal(predicted[0], by_hand)
  # The official model's own window outputs, stitched by hand, agree too.
  ref = np.concatenate([golden["window0_forward_out"][:15, 0, 0],
                        golden["window1_forward_out"][5:, 0, 0]])
  np.testing.assert_allclose(by_hand, np.abs(ref[:, 2:-2, 1:-1]), atol=ATOL, rtol=0)


@pytest.mark.parametrize("start", [10, 20])
def test_short_clips_keep_every_frame(variables, golden, official, start):
  """N=11 and N=1 (< one window): all frames; the official keeps N-5 (none for N=1)."""
  left, right = golden["left"][start:], golden["right"][start:]
  disp = _predict(variables, left.astype(np.uint8), right.astype(np.uint8))  # integer-valued
  n = 21 - start
  assert disp.shape == (n, 28, 30)
  raw = official[1][start // 10]  # the golden run of exactly these frames
  np.testing.assert_array_equal(disp, np.abs(raw[:, 2:-2, 1:-1]))
  with jax.default_matmul_precision("highest"):
    off = inference.forward_batch_test_official(variables, left, right, iters=ITERS)
  assert len(off) == max(n - 5, 0)
  np.testing.assert_array_equal(disp[:len(off)], off)


class _LabelModel:
  """Stand-in for the compiled model: raw output value = 1000 * (start + 1) + local index."""

  def __init__(self):
    self.calls, self.pads = [], set()

  def __call__(self, variables, left, right, *, cfg, iters, pads=None, check_memory=True,
               cache=None, start=0, keep_from=None):
    start = int(left[0, 0, 0, 0])  # frames carry their global index
    self.calls.append((start, len(left)))
    self.pads.add(tuple(pads))
    h, w = left.shape[1:3]
    top, bottom, lft, rgt = pads
    value = 1000.0 * (start + 1) + np.arange(len(left), dtype=np.float32)
    return -np.broadcast_to(value[:, None, None], (len(left), h + top + bottom,
                                                   w + lft + rgt)).copy()


class _Frames:  # frames by index only: iter() of it is a plain "iterator"

  def __init__(self, frames):
    self.frames = frames

  def __getitem__(self, i):
    return self.frames[i]


def _labelled_video(n):
  return np.broadcast_to(np.arange(n, dtype=np.float32)[:, None, None, None], (n, 5, 7, 3))


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
@pytest.mark.parametrize("n", [7, 23])
def test_every_frame_returned(monkeypatch, n):
  fake = _LabelModel()
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", fake)
  video = _labelled_video(n)
  disp = inference.predict_video({}, video, video)
  assert disp.shape == (n, 5, 7)
  assert fake.pads == {(13, 14, 12, 13)}  # 5x7 to 32x32: 27 rows, 25 columns split
  start, local = disp[:, 0, 0] // 1000 - 1, disp[:, 0, 0] % 1000
  np.testing.assert_array_equal(start + local, np.arange(n))  # frame t came from frame t
  if n == 7:
    assert fake.calls == [(0, 7)]
  else:  # official windows: [0, 20) keeps 0..14, [10, 23) keeps 15..22; [20, 23) not run
    assert fake.calls == [(0, 20), (10, 13)]
    np.testing.assert_array_equal(start, [0] * 15 + [10] * 8)
  off = inference.forward_batch_test_official({}, video, video)
  assert len(off) == (2 if n == 7 else 23)  # the official drops frames for N < 20
  np.testing.assert_array_equal(off, disp[:len(off)])


def test_predict_video_under_a_jax_transformation_says_what_to_call_instead():
  # jax.grad of predict_video failed with JAX's TracerArrayConversionError from deep inside.
  video = jnp.zeros((2, 32, 32, 3))
  message = r"predict_video runs the model window by window .* cannot be traced \(jax\.grad"
  for transform in (jax.grad, jax.jit, jax.vmap):
    with pytest.raises(TypeError, match=message):
      transform(lambda x: inference.predict_video({}, x, video).sum())(
          video[None] if transform is jax.vmap else video)
  with pytest.raises(TypeError, match=message.replace("predict_video", "iter_predict_video")):
    jax.jit(lambda x: list(inference.iter_predict_video({}, x, video)))(video)
  with pytest.raises(TypeError, match=r"forward_batch_test_official runs .*unpad"):
    jax.jit(lambda v: inference.forward_batch_test_official(v, video, video))({"w": jnp.ones(2)})


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # (the drop)
def test_a_ctrl_c_that_python_dropped_stops_the_windows(monkeypatch):
  # Python drops a KeyboardInterrupt raised in a garbage-collection callback (JAX has one):
  # under the commands' `remembered_interrupts`, the next window raises it again.
  import signal  # pylint: disable=import-outside-toplevel
  from sav_jax import _signals  # pylint: disable=import-outside-toplevel
  ran = []

  def stand_in(variables, left, right, *, pads, **kw):
    ran.append(len(left))
    if len(ran) == 1:
      drop_ctrl_c_in_gc()
    return np.full((len(left), 32, 32), 5.0, np.float32)

  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", stand_in)
  video = np.zeros((35, 32, 32, 3), np.uint8)  # three windows
  handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # (xdist ignores it)
  try:
    with _signals.remembered_interrupts(), pytest.raises(KeyboardInterrupt):
      inference.predict_video({}, video, video)
    assert ran == [20]  # the second window did not run
    ran.clear()
    assert inference.predict_video({}, video, video).shape == (35, 32, 32)  # outside: no trace
  finally:
    signal.signal(signal.SIGINT, handler)


def test_swapped_views_are_warned_about_once(monkeypatch):
  # The model's disparities of a left view are positive; with the views swapped they come
  # out negative and the official abs() hid it: a plausible-looking map of the wrong view.
  share = {"negative": 1.0}

  def stand_in(variables, left, right, *, pads, **kw):
    t, h, w = len(left), left.shape[1] + pads[0] + pads[1], left.shape[2] + pads[2] + pads[3]
    out = np.full((t, h, w), 5.0, np.float32)
    out.reshape(t, -1)[:, :int(round(share["negative"] * h * w))] *= -1
    return out

  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", stand_in)
  video = np.zeros((35, 32, 32, 3), np.uint8)
  for negative, warned in ((1.0, True), (0.0, False), (0.5, False), (0.55, True)):
    share["negative"] = negative
    with warnings.catch_warnings(record=True) as seen:
      warnings.simplefilter("always")
      disp = inference.predict_video({}, video, video)  # three windows
    assert (disp == 5).all()  # abs() as before
    swapped = [w for w in seen if issubclass(w.category, inference.SwappedViewsWarning)]
    assert len(swapped) == int(warned), (negative, [str(w.message) for w in seen])
    if warned:
      assert str(swapped[0].message).startswith(
          f"frames 0..14: {negative:.0%} of the disparities are below -1 px before the official "
          "abs()")
      assert swapped[0].filename == __file__  # the caller's line
  assert inference.negative_share(np.array([-2.0, -1.0, -0.5, 0.0, 3.0])) == 0.2  # below -1
  assert inference.negative_share(np.zeros((0, 4))) == 0.0


def test_bfloat16_frames_are_read_as_float32(monkeypatch):
  # ml_dtypes' bfloat16 has NumPy kind "V": it was refused as "dtype bfloat16; expected uint8
  # or float", though model.apply takes it.
  seen = []

  def record(variables, left, right, **kw):
    seen.append((left.dtype, np.asarray(left, np.float32)))
    return np.zeros((left.shape[0], 32, 32), np.float32)  # padded to multiples of 32

  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", record)
  video = np.random.default_rng(0).integers(0, 256, (3, 16, 16, 3)).astype(np.float32)
  out = inference.predict_video({}, video.astype(jnp.bfloat16), video.astype(jnp.bfloat16))
  assert out.shape == (3, 16, 16) and seen[0][0] == np.float32
  np.testing.assert_array_equal(seen[0][1], video)  # integers 0..255 are exact in bfloat16


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
@pytest.mark.parametrize("window,stride", [(20, 10), (8, 4), (6, 3), (5, 5)])
def test_stitching_sweep(monkeypatch, window, stride):
  monkeypatch.setattr(inference, "_run_window", _LabelModel())
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  for n in range(1, 3 * window + 4):
    video = _labelled_video(n)
    disp = inference.predict_video({}, video, video, window=window, stride=stride)
    label = disp[:, 0, 0]
    np.testing.assert_array_equal(label // 1000 - 1 + label % 1000, np.arange(n))
    if n >= window and window == 2 * stride:  # identical to the official code
      off = inference.forward_batch_test_official({}, video, video, window=window,
                                                  stride=stride)
      np.testing.assert_array_equal(off, disp)


class _CountingPrograms:
  """Stand-ins for the compiled programs: the per-frame one records which frames it
  computes and tags each frame's feature with its chunk length; the window records the
  tags it sees (frame -> set of chunk lengths)."""

  def __init__(self):
    self.computed = collections.Counter()
    self.right_minus_left = set()
    self.seen = collections.defaultdict(set)
    self.chunk_lengths = set()

  def frames(self, variables, n, hp, wp, *, cfg, check_memory=True):
    self.chunk_lengths.add(n)

    def run(v, left, right):
      assert left.dtype == right.dtype == np.float32  # as the compiled program takes them
      self.computed.update(int(i) for i in left[:, 0, 0, 0])
      self.right_minus_left.update((right - left)[:, 0, 0, 0].tolist())
      return {"f": np.stack([left[:, 0, 0, 0], np.full(n, n, np.float32)], -1)[None]}

    return run

  def window(self, variables, n, hp, wp, *, cfg, iters, check_memory=True):
    def run(v, feats):
      first = int(feats["f"][0, 0, 0])
      assert feats["f"][0, :, 0].tolist() == list(range(first, first + n))  # its frames, in order
      for i, length in np.asarray(feats["f"][0]):
        self.seen[int(i)].add(int(length))
      return np.broadcast_to(np.arange(first, first + n, dtype=np.float32)[:, None, None],
                             (n, hp, wp))  # each frame's index as its disparity

    return run


def _features_computed_once(monkeypatch, n: int, run) -> "_CountingPrograms":
  """`run(video)` on a labelled video of `n` frames with counting stand-ins for the compiled
  programs; asserts every frame's features were computed once, in one chunk."""
  fake = _CountingPrograms()
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "compiled_frame_features", fake.frames)
  monkeypatch.setattr(inference, "compiled_window", fake.window)
  run(_labelled_video(n))
  assert fake.computed == collections.Counter(range(n))
  assert all(len(lengths) == 1 for lengths in fake.seen.values()) and len(fake.seen) == n
  return fake


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
@pytest.mark.parametrize("window,stride,n", [(20, 10, 45), (20, 7, 45), (8, 3, 20), (9, 6, 31)])
def test_each_frame_features_computed_once_in_one_chunk(monkeypatch, window, stride, n):
  # A stride that does not divide the window used to cut chunks at window ends, so the next
  # window recomputed them (24 of 45 frames twice at 20/7) from chunks of other lengths.
  fake = _features_computed_once(
      monkeypatch, n, lambda video: inference.predict_video(
          {}, video, video, window=window, stride=stride, iters=2, check_memory=False))
  chunk = inference.feature_chunk(window, stride)
  assert chunk == math.gcd(window, stride)
  with pytest.raises(ValueError, match="need integers 1 <= stride <= window"):
    inference.feature_chunk(window, 0)
  assert fake.chunk_lengths <= {chunk, n % chunk or chunk}


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
@pytest.mark.parametrize("window,stride,n", [(20, 7, 45), (8, 3, 20)])
def test_official_windows_compute_each_frame_features_once(monkeypatch, window, stride, n):
  # The README: chunks of gcd(window, stride) frames, so no frame is computed twice even
  # where the stride does not divide the window; forward_batch_test_official runs windows so.
  _features_computed_once(monkeypatch, n, lambda video: inference.forward_batch_test_official(
      {}, video, video, window=window, stride=stride, iters=2))


class _ShortSource:
  """A lazy video source that declares more frames (or another size) than it gives."""

  def __init__(self, video, shape):
    self.video, self.shape = video, shape

  def __getitem__(self, sl):
    return self.video[sl]


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
def test_lazy_source_frames_must_match_its_shape(monkeypatch):
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", _LabelModel())
  video = _labelled_video(22)
  for shape, match in (((25, 5, 7, 3), r"declares shape \(25, 5, 7, 3\), but its frames "
                                       r"10..24 came back with shape \(12, 5, 7, 3\)"),
                       ((22, 4, 7, 3), r"declares shape \(22, 4, 7, 3\), but its frames 0..19 came back with shape \(20, 5, 7, 3\)")):
    source = _ShortSource(video, shape)
    with pytest.raises(ValueError, match="left video source _ShortSource " + match):
      inference.predict_video({}, source, _ShortSource(video, shape))
  # A source of grey [T, H, W] frames was taken for a 0-d array of one object: "got shape ()"
  grey = _ShortSource(video[..., 0], video.shape[:3])
  with pytest.raises(ValueError, match=r"got shape \(22, 5, 7\) \(grey frames\? give them 3"):
    inference.predict_video({}, grey, grey)


def test_a_lazy_source_of_0_1_frames_is_warned_about_once_per_view(monkeypatch):
  """A lazy source's frames are checked window by window; 0..1 frames were warned about at
  every window (two warnings per window: 200 for 1000 frames), now once per view."""
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window",
                      lambda v, left, right, *, pads, **k: np.zeros(
                          (len(left), 8 + pads[0] + pads[1], 8 + pads[2] + pads[3]), np.float32))
  unit = np.random.default_rng(0).uniform(0, 1, (45, 8, 8, 3)).astype(np.float32)
  with warnings.catch_warnings(record=True) as record:
    warnings.simplefilter("default")
    out = inference.predict_video({}, _ShortSource(unit, unit.shape),
                                  _ShortSource(unit, unit.shape))
  assert out.shape == (45, 8, 8)
  assert [str(w.message).split(":")[0] for w in record] == ["left", "right"]
  assert all(w.filename == __file__ for w in record)
  nan = unit.copy()
  nan[33, 1, 1, 1] = np.nan  # the errors are not silenced: frame 33 (in the last windows)
  with (pytest.warns(UserWarning, match="multiply 0..1 images by 255"),
        pytest.raises(ValueError, match=r"^right: non-finite values \(NaN/inf\) in frame\(s\) "
                      r"\[33\]")):
    inference.predict_video({}, _ShortSource(unit, unit.shape), _ShortSource(nan, nan.shape))


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
def test_run_window_cache_belongs_to_one_video(monkeypatch):
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  calls = []

  def stand_in(variables, left, right, **kw):
    calls.append(kw["start"])
    out = np.zeros((len(left), 16, 16), np.float32)
    out.flags.writeable = False  # as a device array's numpy view
    return out

  monkeypatch.setattr(inference, "_run_window", stand_in)
  video = _labelled_video(20)
  cache = inference.FrameFeatureCache()
  run = lambda v, **kw: inference.run_window({}, v, v, cfg=sav_jax.SAVConfig(), iters=2,
                                             cache=cache, **kw)
  out = run(video, start=0)
  out[out < 0] = 0  # the result is the caller's to change
  run(video[10:], start=10)
  with pytest.raises(ValueError, match="window start 0 is before the previous window's"):
    run(video, start=0)
  # Frames other than those the cached features are of (another video from the same
  # start, frames changed in place) were served the cached features: a stale result.
  other = video.copy()
  other[12, 0, 0, 0] += 1
  with pytest.raises(ValueError, match="frame 12 differs from the frame whose features this "
                     "FrameFeatureCache holds"):
    run(other[10:], start=10)
  run(video[10:], start=10)  # the same frames again: served
  # ... the right view too: a changed right frame beside the same left one is not served
  with pytest.raises(ValueError, match="frame 12 differs from the frame whose features"):
    inference.run_window({}, video[10:], other[10:], cfg=sav_jax.SAVConfig(), iters=2,
                         cache=cache, start=10)
  # another height, width or padding (to 16x16), another config
  for frames, pads in ((np.zeros((4, 9, 7, 3), np.uint8), None),
                       (np.zeros((4, 5, 9, 3), np.uint8), None), (video[10:], (0, 11, 0, 9))):
    with pytest.raises(ValueError, match="holds features of 5x7 frames padded by"):
      run(frames, start=20, pads=pads)
  for cfg in (sav_jax.SAVConfig(dtype="bfloat16"), sav_jax.SAVConfig(vda_encoder="vitb")):
    with pytest.raises(ValueError, match="use a new cache"):
      inference.run_window({}, video, video, cfg=cfg, iters=2, cache=cache, start=20)
  assert calls == [0, 10, 10]
  # Other weights were served the first ones' features silently (two checkpoints compared on
  # one video); the same frames as uint8 instead of float32 were "frame 0 differs".
  weights = {"params": {"w": np.ones(3, np.float32)}}
  cache = inference.FrameFeatureCache()
  run = lambda v, w, **kw: inference.run_window(w, v, v, cfg=sav_jax.SAVConfig(), iters=2,
                                                cache=cache, **kw)
  run(video, weights, start=0)
  run(video[10:].astype(np.uint8), dict(weights), start=10)  # the same arrays, same values
  for other in ({"params": {"w": np.ones(3, np.float32)}},
                {"params": {"w": weights["params"]["w"], "z": np.ones(3, np.float32)}}):  # + one
    with pytest.raises(ValueError, match="holds features computed with other weights"):
      run(video[10:], other, start=10)
  assert calls[-2:] == [0, 10]


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
def test_iterators_and_lists_beside_lazy_sources(monkeypatch):
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", _LabelModel())
  video = _labelled_video(12)
  with pytest.raises(ValueError, match="left: got a generator, which has neither a shape nor "
                     r"frames by index: .* list\(\.\.\.\) first"):
    inference.predict_video({}, (f for f in video), video)
  with pytest.raises(ValueError, match="right: got a list_iterator"):
    inference.predict_video({}, video, iter(list(video)))
  with pytest.raises(ValueError, match="right: got an iterator"):  # (iter of a __getitem__)
    inference.predict_video({}, video, iter(_Frames(video)))
  lazy = _ShortSource(video, video.shape)  # "differ in shape: (12, 5, 7, 3) vs ()"
  for left, right in ((lazy, list(video)), (list(video), lazy)):
    out = inference.predict_video({}, left, right, window=8, stride=4)
    label = out[:, 0, 0]
    np.testing.assert_array_equal(label // 1000 - 1 + label % 1000, np.arange(12))


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
def test_forward_batch_test_official_takes_lazy_sources(monkeypatch):
  """Its docstring takes frames as predict_video does; a lazy source with a shape and slicing
  (no len) failed with "got shape ()", though its shape is (23, 5, 7, 3)."""
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", _LabelModel())
  video = _labelled_video(23)
  lazy = _ShortSource(video, video.shape)
  np.testing.assert_array_equal(inference.forward_batch_test_official({}, lazy, lazy),
                                inference.forward_batch_test_official({}, video, video))


def test_a_frame_of_another_size_in_a_window_of_a_list_is_named(monkeypatch):
  """A list beside a lazy source (or a source whose slices are lists) is read window by
  window; a frame of another size in it failed with NumPy's "inhomogeneous shape"."""
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", _LabelModel())
  video = np.zeros((25, 5, 7, 3), np.uint8)
  frames = list(video)
  frames[15] = np.zeros((5, 8, 3), np.uint8)
  for left, right in ((frames, _ShortSource(video, video.shape)),
                      (_ShortSource(frames, video.shape), video)):
    with pytest.raises(ValueError, match=r"^left: frame 15 has shape \(5, 8, 3\), not "
                       r"\(5, 7, 3\)"):
      inference.predict_video({}, left, right)


@pytest.mark.filterwarnings("ignore:.*float frames with values")
def test_a_window_run_without_its_start_is_told_to_give_it(monkeypatch):
  """The second window run by hand without `start` (default 0) was told only that frame 0
  differs and to use a new cache for another video."""
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", lambda v, left, right, **kw: np.zeros(
      (len(left), 16, 16), np.float32))
  video, cache = _labelled_video(20), inference.FrameFeatureCache()
  run = lambda v, **kw: inference.run_window({}, v, v, cfg=sav_jax.SAVConfig(), iters=2,
                                             cache=cache, **kw)
  run(video[:10])
  with pytest.raises(ValueError, match=r"frame 0 differs .* start=0 must be the index of the "
                     "window's first frame in the video"):
    run(video[10:])
  run(video[10:], start=10)


@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
def test_predict_video_fills_one_output_array(monkeypatch):
  """The windows' pieces went to a list, then np.concatenate: the output held twice."""
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", _LabelModel())
  concatenated = []
  real = np.concatenate
  monkeypatch.setattr(np, "concatenate", lambda *a, **k: concatenated.append(1) or real(*a, **k))
  video = _labelled_video(23).astype(np.uint8)
  out = inference.predict_video({}, video, video)
  assert out.shape == (23, 5, 7) and out.dtype == np.float32 and not concatenated
  label = out[:, 0, 0]
  np.testing.assert_array_equal(label // 1000 - 1 + label % 1000, np.arange(23))


def test_dtype_override_takes_dtype_objects():
  assert inference.resolve_config(None, jnp.bfloat16).dtype == "bfloat16"
  assert inference.resolve_config(None, np.float32).dtype == "float32"
  with pytest.raises(ValueError, match="dtype must be 'float32' or 'bfloat16'"):
    inference.resolve_config(None, object())
  # The caller's dtype= is named (it named SAVConfig.dtype, a config the caller never set).
  for dtype in (np.float16, "float16"):
    with pytest.raises(ValueError, match=r"^dtype must be 'float32' or 'bfloat16', got 'float16'$"):
      inference.resolve_config(None, dtype)


def test_padding_matches_input_padder():
  assert inference.pad_amounts(436, 1024) == (6, 6, 0, 0)
  assert inference.pad_amounts(375, 1242) == (4, 5, 3, 3)
  x = np.arange(2 * 3 * 5 * 1, dtype=np.float32).reshape(2, 3, 5, 1)
  pads = (1, 2, 3, 0)
  p = inference.pad_frames(x, pads)
  assert p.shape == (2, 6, 8, 1)
  np.testing.assert_array_equal(p[:, 0, 3:], x[:, 0])  # replicate
  np.testing.assert_array_equal(inference.unpad(p[..., 0], pads), x[..., 0])
  # A list, which pad_frames takes, is taken here too (it failed with "'list' object has
  # no attribute 'ndim'").
  np.testing.assert_array_equal(inference.unpad(p[..., 0].tolist(), pads), x[..., 0])


def test_padding_in_jax_pipelines():
  """pad_to_multiple on batches, NumPy and JAX alike, inside jit and grad: the JAX result
  equals the NumPy one, and the gradient of a replicated edge pixel sums its copies."""
  rng = np.random.default_rng(0)
  x = rng.uniform(0, 255, (2, 3, 20, 27, 3)).astype(np.float32)  # [B, T, H, W, 3]
  p_np, pads = inference.pad_to_multiple(x, 16)
  assert pads == (6, 6, 2, 3) and p_np.shape == (2, 3, 32, 32, 3)
  assert isinstance(p_np, np.ndarray)
  p_jax, pads_jax = jax.jit(lambda v: inference.pad_to_multiple(v, 16)[0])(x), pads
  assert isinstance(p_jax, jax.Array)
  np.testing.assert_array_equal(np.asarray(p_jax), p_np)
  back = inference.unpad(jnp.moveaxis(p_jax, -1, 0), pads_jax)  # [3, B, T, H, W]
  np.testing.assert_array_equal(np.asarray(jnp.moveaxis(back, 0, -1)), x)

  def loss(v):
    padded, pd = inference.pad_to_multiple(v, 16)
    return jnp.sum(padded[..., 0] * 1.0)

  g = np.asarray(jax.grad(loss)(jnp.asarray(x)))
  # A corner pixel is copied into a (6+1) x (2+1) block; an interior pixel once.
  assert g[0, 0, 0, 0, 0] == 7 * 3 and g[0, 0, -1, -1, 0] == 7 * 4
  assert g[0, 0, 5, 5, 0] == 1 and g[0, 0, 0, 5, 0] == 7 and np.all(g[..., 1:] == 0)
  assert g.sum() == 2 * 3 * 32 * 32


def test_padding_bad_input_is_named():
  with pytest.raises(ValueError, match=r"pads must be 4 integers .* got \(1, 2, 3\)"):
    inference.pad_frames(np.zeros((2, 4, 4, 3)), (1, 2, 3))
  for pads in ((1, 2, 3, 4, 5), (1, 2, -3, 0), (1, 2, 0.5, 0)):
    with pytest.raises(ValueError, match="pads must be 4 integers"):
      inference.pad_frames(np.zeros((2, 4, 4, 3)), pads)
  with pytest.raises(ValueError, match=r"frames must be \[\.\.\., H, W, C\], got shape \(4, 4\)"):
    inference.pad_to_multiple(np.zeros((4, 4)))
  for multiple in (0, 32.0):
    with pytest.raises(ValueError, match=f"multiple must be an integer >= 1, got {multiple}"):
      inference.pad_to_multiple(np.zeros((1, 4, 4, 3)), multiple)
  # A [T, H, W] array (ground-truth disparities) was read as [H, W, C]: T and H padded.
  for width in (70, 5):  # (5: the first width that is no channel axis)
    with pytest.raises(ValueError, match=rf"got shape \(2, 50, {width}\), whose last axis of "
                                         rf"{width} is no channel axis: .* x\[\.\.\., None\]"):
      inference.pad_to_multiple(np.zeros((2, 50, width)))
  padded, pads = inference.pad_to_multiple(np.zeros((2, 50, 70))[..., None])
  assert padded.shape == (2, 64, 96, 1) and pads == (7, 7, 13, 13)
  with pytest.raises(ValueError, match=r"cannot remove pads \(4, 4, 0, 0\) from an array of "
                     r"shape \(2, 6, 8\): they add up to 8 x 0, more than its last two axes "
                     r"\(6, 8\)"):
    inference.unpad(np.zeros((2, 6, 8)), (4, 4, 0, 0))
  with pytest.raises(ValueError, match=r"they add up to 0 x 9, more than"):
    inference.unpad(np.zeros((2, 6, 8)), (0, 0, 4, 5))  # each fits, together they do not
  with pytest.raises(ValueError, match=r"shape \(8,\): expected \[\.\.\., Hp, Wp\]"):
    inference.unpad(np.zeros(8), (0, 0, 0, 0))
  # Padded frames of 720x1280 ([..., Hp, Wp, C]) lost 16 columns, not their 16 padded rows.
  padded, pads = inference.pad_to_multiple(np.zeros((1, 720, 1280, 3), np.uint8))
  with pytest.raises(ValueError, match=r"\(1, 736, 1280, 3\): \[\.\.\., Hp, Wp\] expected "
                     r"\(disparities\); for frames .* unpad x\[\.\.\., c\]"):
    inference.unpad(padded, pads)
  assert inference.unpad(padded[..., 0], pads).shape == (1, 720, 1280)
  # ... four channels too (RGBA frames, which pad_frames takes), where the pads fit its W, C
  rgba = inference.pad_frames(np.zeros((1, 30, 6, 4), np.uint8), (1, 1, 1, 1))
  with pytest.raises(ValueError, match=r"\(1, 32, 8, 4\): \[\.\.\., Hp, Wp\] expected"):
    inference.unpad(rgba, (1, 1, 1, 1))


def test_bad_inputs():
  with pytest.raises(ValueError, match="differ in shape"):
    inference.predict_video({}, np.zeros((2, 8, 8, 3)), np.zeros((3, 8, 8, 3)))
  # Other layouts a user's frames come in are named with the way to [T, H, W, 3].
  for shape, hint in (((2, 8, 8), r"grey frames\? give them 3 channels: np\.repeat\(video\[\.\.\., None\]"),
                      ((2, 8, 8, 1), r"one channel\? repeat it"),
                      ((2, 8, 8, 4), r"RGBA\? drop the alpha channel: video\[\.\.\., :3\]"),
                      ((8, 8, 3), r"one frame\? a video of one frame is frame\[None\]")):
    with pytest.raises(ValueError, match=r"\[T, H, W, 3\] \(0\.\.255\), got shape .*" + hint):
      inference.predict_video({}, np.zeros(shape), np.zeros(shape))
  for shape in ((0, 8, 8, 3), (2, 0, 8, 3), (2, 8, 0, 3)):  # no frames, no rows, no columns
    with pytest.raises(ValueError, match=r"\[T, H, W, 3\] \(0\.\.255\), got shape \("):
      inference.predict_video({}, np.zeros(shape), np.zeros(shape))
  with pytest.raises(ValueError, match=r"left: got a path \('left\.mp4'\), not frames; read them "
                     r"first: left, right, names = sav_jax\.tools\.video_io\.load_stereo\("
                     r"left_path, right_path\) reads"):  # (three values: `l, r = ` failed)
    inference.predict_video({}, "left.mp4", "right.mp4")
  with pytest.raises(ValueError, match=r"right: got a path \('right\.mp4'\), not frames"):
    inference.predict_video({}, np.zeros((2, 8, 8, 3)), pathlib.Path("right.mp4"))
  with pytest.raises(ValueError, match=r"frames must be \[\.\.\., H, W, C\], channels last; got "
                     r"shape \(2, 3, 30, 50\) \(channels first"):
    inference.pad_to_multiple(np.zeros((2, 3, 30, 50)))  # it padded the channel axis
  with pytest.raises(ValueError, match=r"for a batch \[B, T, H, W, 3\], pass video\[b\]"):
    inference.predict_video({}, np.zeros((1, 2, 8, 8, 3)), np.zeros((1, 2, 8, 8, 3)))
  # PyTorch's channels-first layout gets the way out, at both entries.
  hint = r"channels first, as in PyTorch\? the channel axis goes last: np.moveaxis\(video, -3, -1\)"
  for shape in ((2, 3, 8, 10), (1, 2, 3, 8, 10)):
    with pytest.raises(ValueError, match=hint):
      inference.predict_video({}, np.zeros(shape), np.zeros(shape))
  with pytest.raises(ValueError, match=hint):
    sav_jax.StereoAnyVideo(sav_jax.SAVConfig()).init(
        jax.random.PRNGKey(0), np.zeros((1, 2, 3, 8, 10)), np.zeros((1, 2, 3, 8, 10)), iters=2)
  with pytest.raises(ValueError, match="stride"):
    inference.window_plan(10, window=4, stride=5)
  # (stride 0 would never move the windows on: window_plan would loop forever; a float
  # window would fail later, slicing the video)
  for window, stride in ((4, 0), (20.0, 10)):
    with pytest.raises(ValueError, match=r"need integers 1 <= stride <= window"):
      inference.check_window(window, stride)
  # The depth prior's temporal attention takes 32 frames: a longer window is named up front
  # (it failed in the window program's trace with "VDA processes at most 32 frames").
  assert inference.window_plan(40, window=32, stride=16)[0].length == 32
  for plan in (inference.window_plan, inference.official_window_plan):
    with pytest.raises(ValueError, match=r"window=33 frames is more than the model runs at once"
                       r": the depth prior's temporal attention takes at most 32 frames"):
      plan(40, window=33, stride=10)
  with pytest.raises(ValueError, match="window=40 frames"):
    inference.predict_video({}, np.zeros((3, 8, 8, 3)), np.zeros((3, 8, 8, 3)), window=40)
  for n in (0, 25.5):
    with pytest.raises(ValueError, match="need an integer number of frames >= 1"):
      inference.window_plan(n)
  assert inference.window_plan(30, window=np.int64(20), stride=np.int64(10)) == \
      inference.window_plan(30, window=20, stride=10)
  frames = [np.zeros((8, 8, 3), np.uint8)] * 3
  odd = frames[:1] + [np.zeros((8, 10, 3), np.uint8)] + frames[:1]
  for left, right, side in ((odd, frames, "left"), (frames, tuple(odd), "right")):
    with pytest.raises(ValueError, match=rf"{side}: frame 1 has shape \(8, 10, 3\) but frame 0 "
                                         r"has \(8, 8, 3\); all frames need one size"):
      inference.predict_video({}, left, right)


def test_numpy_integer_window_and_stride(variables, golden, predicted):
  disp = _predict(variables, golden["left"], golden["right"], window=np.int64(20),
                  stride=np.int64(10))
  np.testing.assert_array_equal(disp, predicted[0])


def test_run_window_checks_its_inputs_before_compiling(variables):
  before = inference.cache_size()
  video = np.full((2, 32, 32, 3), 100, np.uint8)
  cfg = sav_jax.SAVConfig()
  run = lambda l, r, **kw: inference.run_window(variables, l, r, **{"cfg": cfg, "iters": ITERS,
                                                                     **kw})
  cases = [((video, video[:, :, :24]), {}, "differ in shape"),
           ((video, np.concatenate([video, video])), {}, "differ in shape"),
           ((video[..., 0], video[..., 0]), {}, r"\[T, H, W, 3\]"),
           ((video, np.full(video.shape, np.nan, np.float32)), {}, "right: non-finite"),
           ((video[:0], video[:0]), {}, r"\[T, H, W, 3\]"),
           ((video, video), {"iters": 1}, "iters must be an integer >= 2"),
           ((video, video), {"pads": (1, 1, 0, 0)}, "pads must be 4 integers"),
           ((video, video), {"pads": (0, 0, -1, 1)}, "pads must be 4 integers"),
           # 40x32: a multiple of 8, not of 16 (the model's 1/16 stage)
           ((video, video), {"pads": (4, 4, 0, 0)}, "pads must be 4 integers"),
           ((video, video), {"pads": (0, 0, 4, 4)}, "pads must be 4 integers"),
           ((video, video), {"start": -1}, "start must be an integer >= 0")]
  for args, kw, match in cases:
    with pytest.raises(ValueError, match=match):
      run(*args, **kw)
  # variables that do not fit the model (a deep Flax scope error before)
  with pytest.raises(sav_jax.convert.CheckpointError, match="expected Flax variables"):
    inference.run_window(variables["params"], video, video, cfg=cfg, iters=ITERS)
  assert inference.cache_size() == before  # nothing compiled


def test_bad_values_iters_and_variables_fail_before_compiling(variables):
  before = inference.cache_size()
  video = np.full((3, 32, 32, 3), 100, np.uint8)
  nan = video.astype(np.float32)
  nan[2, 5, 5, 0] = np.nan
  with pytest.raises(ValueError, match=r"right: non-finite values \(NaN/inf\) in frame\(s\) \[2\]"):
    inference.predict_video(variables, video, nan, iters=ITERS)
  with pytest.raises(ValueError, match=r"non-finite values \(NaN/inf\) in frame\(s\) \[22\]"):
    inference.check_video_values(nan, "left", first=20)  # a lazy source's window at frame 20
  deep = video.astype(np.uint16) * 257  # 16-bit frames
  with pytest.raises(ValueError, match=r"left: uint16 values 25700\.\.25700 are outside 0\.\.255 "
                     r"in frame\(s\) \[0, 1, 2\]"):
    inference.predict_video(variables, deep, deep, iters=ITERS)
  one = video.astype(np.int32)
  one[1, 0, 0, 2] = 300  # one frame of a window starting at frame 20
  with pytest.raises(ValueError, match=r"right: int32 values 100\.\.300 are outside 0\.\.255 in "
                     r"frame\(s\) \[21\]"):
    inference.check_video_values(one, "right", first=20)
  one[1, 0, 0, 2] = -10  # negative values: no 16-bit hint (it said "frames >> 8")
  with pytest.raises(ValueError, match=r"int32 values -10\.\.100 are outside 0\.\.255 in frame\(s\) "
                     r"\[21\] \(RGB frames are 0\.\.255: negative values are no image's"):
    inference.check_video_values(one, "right", first=20)
  with pytest.raises(ValueError, match="dtype bool"):
    inference.check_video_values(video > 0, "left")
  with pytest.warns(UserWarning, match="multiply 0..1 images by 255") as record:
    inference.check_video_values(video / 255.0, "left")
  with (pytest.warns(UserWarning, match="multiply 0..1 images by 255") as record,
        pytest.raises(sav_jax.convert.CheckpointError)):  # the values are checked first
    inference.predict_video({"params": {}}, video / 255.0, video / 255.0, iters=ITERS)
  assert {w.filename for w in record} == {__file__}  # the caller's line (was inference.py's)
  with pytest.warns(UserWarning, match="25700..25700, outside 0..255.*divide 16-bit frames by 257"):
    inference.check_video_values(deep.astype(np.float32), "left")
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    inference.check_video_values(np.float32([[[[-0.4, 255.6, 9]]]]), "left")  # overshoot
    # A bicubic resize of sharp 0..255 edges overshoots to about -38..293, and unclipped
    # noise further than 0..255 too: 0..255 frames still (they got "divide 16-bit frames by
    # 257" or "put the mean and scale back").
    edges = np.zeros((1, 8, 16, 3), np.float32)
    edges[:, :, 8:] = 255.0
    sharp = np.asarray(jax.image.resize(edges, (1, 8, 64, 3), "lanczos5"))
    assert sharp.min() < -20 and sharp.max() > 275, (sharp.min(), sharp.max())
    inference.check_video_values(sharp, "left")
    inference.check_video_values(np.float32([[[[-63.0, 319.0, 9]]]]), "left")
  for values, advice in (([-65.0, 200.0], "negative values are no image's"),
                         ([0.0, 1023.0], "divide 16-bit frames by 257")):  # 10-bit as float
    with pytest.warns(UserWarning, match=advice):
      inference.check_video_values(np.float32(values).reshape(1, 1, 2, 1), "left")
  # 0..1 frames behind a resize's overshoot or a few bright pixels are still found.
  unit = np.random.default_rng(0).uniform(0, 1, (2, 16, 16, 3)).astype(np.float32)
  with pytest.warns(UserWarning, match=r"values -0\.0\d+\.\.1\.0\d+: .*multiply 0\.\.1"):
    inference.check_video_values(unit * 1.04 - 0.01, "left")
  hot = unit.copy()
  hot[0, 0, 0, 0] = 200.0  # one value in 1536
  with pytest.warns(UserWarning, match=r"values 0\.\d+\.\.200, 99\.9% of them at most 0\.99\d*: "
                     r".*multiply 0\.\.1 images by 255"):
    inference.check_video_values(hot, "left")
  # A 0..255 video whose red channel is dark (a blue night scene) is not taken for 0..1
  # frames: the sample keeps every channel (a flat stride of 9 read the red one only).
  night = np.random.default_rng(1).uniform(0, 219, (5, 256, 512, 3)).astype(np.float32)
  night[..., 0] = np.random.default_rng(2).integers(0, 2, night.shape[:3])
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    inference.check_video_values(night, "left")
    inference.check_video_values(night[..., ::-1], "left")  # a strided view
  # Normalised frames (mean and scale taken off) are refused; an offset gets that hint.
  with pytest.raises(ValueError, match=r"left: float frames with values -1\.9\d+\.\.2\.\d+ look "
                     r"normalised \(.*\(frames \* std \+ mean\) \* 255\)"):
    inference.check_video_values((unit - 0.45) / 0.225, "left")
  with pytest.warns(UserWarning, match=r"values -124\.\.131, outside 0\.\.255.*normalised frames"):
    inference.check_video_values(np.float32([[[[-124, 131, 9]]]]), "left")  # a mean taken off
  with pytest.raises(ValueError, match="iters must be an integer >= 2"):
    inference.predict_video(variables, video, video, iters=1)
  iters = inference.check_iters(np.int64(4))
  assert iters == 4 and type(iters) is int
  with pytest.raises(ValueError, match=r"expected Flax variables \{'params': \.\.\.\}"):
    inference.predict_video(variables["params"], video, video, iters=ITERS)
  # A training state, and one 'params' layer too many, are named with the way out.
  state = types.SimpleNamespace(params=variables["params"], step=0)
  with pytest.raises(ValueError, match=r"found SimpleNamespace: a training state\? pass "
                                       r"\{'params': state.params\}"):
    inference.predict_video(state, video, video, iters=ITERS)
  with pytest.raises(TypeError, match=r"StereoAnyVideo.apply takes the Flax variables "
                                      r"\{'params': params\} as its first argument; got a "
                                      r"SimpleNamespace: a training state\? pass"):
    sav_jax.StereoAnyVideo().apply(state, video[None], video[None], iters=ITERS)
  with pytest.raises(ValueError, match=r"an extra 'params' layer .*: pass variables\['params'\]"):
    inference.predict_video({"params": variables}, video, video, iters=ITERS)
  with pytest.raises(ValueError, match="seed must be an integer >= 0, got -1"):
    init_variables(sav_jax.SAVConfig(), -1)
  assert sav_jax.SAVConfig(dtype=jnp.bfloat16).dtype == "bfloat16"  # as predict_video(dtype=)
  with pytest.raises(ValueError, match="SAVConfig.dtype"):
    sav_jax.SAVConfig(dtype=object())
  with pytest.raises(ValueError, match=r"variables: the parameters hold a vits depth prior \(DINOv2 "
                     r"width 384\), the config says vda_encoder='vitl': use "
                     r"SAVConfig\(vda_encoder='vits'\)"):
    inference.predict_video(variables, video, video, iters=ITERS,
                            cfg=sav_jax.SAVConfig(vda_encoder="vitl"))
  with pytest.raises(TypeError, match="SAVConfig.from_dict"):
    inference.predict_video(variables, video, video, iters=ITERS, cfg={"dtype": "float32"})
  assert inference.cache_size() == before  # nothing compiled


def test_non_float_parameters_are_refused_before_compiling(variables):
  before = inference.cache_size()
  leaves, treedef = jax.tree_util.tree_flatten_with_path(variables)
  in_params = [i for i, (p, _) in enumerate(leaves) if p[0].key == "params"]
  k = min(in_params, key=lambda i: np.size(leaves[i][1]))  # a small parameter
  path = jax.tree_util.keystr(leaves[k][0][1:])  # the path inside "params"
  video = np.zeros((2, 32, 32, 3), np.uint8)

  def refused(bad, message, place=lambda x: x):
    """Parameter k replaced by `bad` (every leaf put by `place`): refused, named."""
    broken = jax.tree_util.tree_unflatten(
        treedef, [place(bad) if i == k else place(leaf) for i, (_, leaf) in enumerate(leaves)])
    with pytest.raises(ValueError, match=message):
      inference.check_variables(broken, source="source.npz")
    with pytest.raises(ValueError, match=re.escape(path)):
      inference.predict_video(broken, video, video, iters=ITERS)

  shape = np.shape(leaves[k][1])
  for bad in (np.full(shape, "0.5"), np.zeros(shape, object), np.zeros(shape, np.int32)):
    refused(bad, rf"source\.npz: parameter {re.escape(path)} has dtype {bad.dtype}; expected "
                 r"floating-point arrays")
  inference.check_variables(jax.tree_util.tree_map(lambda x: x.astype(jax.numpy.bfloat16),
                                                   variables))
  # NaN or inf weights (a diverged run) would give all-NaN disparities: refused, named, on
  # the host and on the device (fetched once, then remembered as finite).
  for value, place in ((np.inf, np.asarray), (np.nan, jax.device_put)):
    refused(np.full(shape, value, np.float32), rf"source\.npz: 1 parameter\(s\) hold NaN or inf "
                                               rf"values, e\.g\. {re.escape(path)}", place)
  assert inference.cache_size() == before  # nothing compiled


def test_memory_error_before_compiling(variables, monkeypatch):
  monkeypatch.setattr(inference, "available_memory_bytes", lambda device=None: 2**30)
  before = inference.cache_size()
  video = np.zeros((20, 720, 1280, 3), np.uint8)
  with pytest.raises(inference.InsufficientMemoryError, match=r"needs about \d+\.\d GB") as e:
    inference.predict_video(variables, video, video)
  assert isinstance(e.value, MemoryError) and isinstance(e.value, ValueError)
  assert "736x1280" in str(e.value) and "iters" not in str(e.value)
  small = video[:2, :64, :64]
  with pytest.raises(inference.InsufficientMemoryError,  # iters take it: they are named
                     match=r"2-frame window of 64x64 \(padded\) with iters=10000000 needs "
                     r"about .*use fewer refinement iterations \(iters\), fewer frames"):
    inference.predict_video(variables, small, small, iters=10**7)
  assert inference.cache_size() == before


def test_memory_error_from_compiled_program(variables, golden, monkeypatch):
  """When the estimate passes, XLA's memory analysis of the executable is checked."""
  monkeypatch.setattr(inference, "estimate_memory_bytes", lambda *a, **k: 0)
  monkeypatch.setattr(inference, "available_memory_bytes", lambda device=None: 1024)
  before = inference.cache_size()
  with pytest.raises(inference.InsufficientMemoryError, match="from the compiled program"):
    inference.predict_video(variables, golden["left"][:2], golden["right"][:2], iters=ITERS)
  assert inference.cache_size() == before  # nothing cached for a program that cannot run


def test_memory_precheck_margin_and_message(monkeypatch):
  """Before compiling, an estimate (which errs high) is refused only above 1.5x the free
  memory; the message gives both in GB. Free memory that is unknown refuses nothing."""
  need, free = {}, {"bytes": 2 * 2**30}
  monkeypatch.setattr(inference, "estimate_memory_bytes", lambda *a: need["bytes"])
  monkeypatch.setattr(inference, "available_memory_bytes", lambda device=None: free["bytes"])

  def precheck():
    inference._precheck(20, 64, 96, sav_jax.SAVConfig(), 20, True)  # pylint: disable=protected-access

  need["bytes"] = 3 * 2**30  # 1.5x 2 GB
  precheck()
  need["bytes"] = 3.5 * 2**30
  with pytest.raises(inference.InsufficientMemoryError,
                     match=r"^a 20-frame window of 64x96 \(padded\) needs about 3\.5 GB "
                     r"\(estimated\), but only 2\.0 GB is free on \w+:0; use fewer frames"):
    precheck()
  free["bytes"] = None
  precheck()


def test_memory_estimate_grows_with_size():
  small = inference.estimate_memory_bytes(20, 32, 32, 20)
  big = inference.estimate_memory_bytes(20, 736, 1280, 20)
  assert 0 < small < big
  assert 20 * 736 * 1280 * 1000 < big < 20 * 736 * 1280 * 10000
  bf16 = inference.estimate_memory_bytes(20, 736, 1280, 20, sav_jax.SAVConfig(dtype="bfloat16"))
  assert bf16 < big


def test_memory_estimate_by_its_formula():
  """64 MiB, 1000 B per input pixel and 12 B per pixel and iteration (x0.7 in bfloat16), and
  1.5x one block of the DINOv2 logits: both views' frames x 6 heads (vits) x tokens^2 x 4 B,
  with 19 tokens for 32x128 frames (2 x 9 patches of 14 px and the class token)."""
  pixels, logit_bytes = 3 * 32 * 128, 6 * 19 * 19 * 4  # 3 frames; one frame's logits
  per_pixel = 1000 * pixels + 12 * 4 * pixels  # iters=4
  for cfg, activations, block_frames in (
      (sav_jax.SAVConfig(), per_pixel, 6),  # all 2 x 3 frames in one block
      (sav_jax.SAVConfig(dtype="bfloat16", vit_attention="blocked"), 0.7 * per_pixel, 6),
      (sav_jax.SAVConfig(frame_block_mb=2 * logit_bytes / 2**20), per_pixel, 2)):
    want = int(64 * 2**20 + activations + 1.5 * block_frames * logit_bytes)
    assert inference.estimate_memory_bytes(3, 32, 128, 4, cfg) == want


def test_memory_estimate_follows_the_attention_blocks():
  """Unblocked, DINOv2's logits of the paper's window (40 frames x 6 x 4642^2) are ~20 GB;
  the default blocks bound them to about 1 GB."""
  blocked = inference.estimate_memory_bytes(20, 736, 1280, 20)
  unblocked = inference.estimate_memory_bytes(20, 736, 1280, 20,
                                              sav_jax.SAVConfig(frame_block_mb=1e6))
  assert 15 * 2**30 < unblocked - blocked < 40 * 2**30


def test_memory_estimate_counts_no_logits_for_the_fused_attention(monkeypatch):
  cfg = sav_jax.SAVConfig(dtype="bfloat16", frame_block_mb=1e6)
  blocked = inference.estimate_memory_bytes(20, 736, 1280, 20, cfg)
  fused = inference.estimate_memory_bytes(20, 736, 1280, 20,
                                          sav_jax.SAVConfig(dtype="bfloat16", vit_attention="cudnn"))
  assert 15 * 2**30 < blocked - fused < 40 * 2**30
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # "auto" picks the fused kernel
  assert inference.estimate_memory_bytes(20, 736, 1280, 20, cfg) == fused


def test_per_frame_features_are_computed_once_per_frame(variables, golden, monkeypatch):
  """21 frames in windows [0, 20) and [10, 21): 21 frames of per-frame work, not 31."""
  counted, events = [], []
  real_frames, real_window = inference.compiled_frame_features, inference.compiled_window

  def logged(kind, fn):
    def run(*args):
      events.append(f"run {kind}")
      return fn(*args)
    return run

  def counting(variables, frames, *args, **kwargs):
    counted.append(frames)
    events.append("compile frames")
    return logged("frames", real_frames(variables, frames, *args, **kwargs))

  def window(*args, **kwargs):
    events.append("compile window")
    return logged("window", real_window(*args, **kwargs))

  monkeypatch.setattr(inference, "compiled_frame_features", counting)
  monkeypatch.setattr(inference, "compiled_window", window)
  disp = _predict(variables, golden["left"], golden["right"])
  assert counted == [10, 10, 1]  # chunks [0, 10), [10, 20), [20, 21)
  # Each window gets its executables before running anything (so that no computation runs
  # during a compile and is counted as compilation by `compile_seconds`).
  assert events == ["compile frames"] * 2 + ["compile window"] + ["run frames"] * 2 + [
      "run window", "compile frames", "compile window", "run frames", "run window"]
  assert disp.shape == (21, 28, 30)
  # On CPU the per-frame programs keep XLA's newer fusion emitters (8x faster to compile
  # there); the window's are compiled with the older, leaner ones (the default). Which
  # options those are is tests/test_runtime.py's check (without the suite's XLA_FLAGS).
  options = {k[0]: dict(k[4]) for k in inference._COMPILED}  # pylint: disable=protected-access
  assert options["frames"] == runtime.inference_compiler_options(per_frame=True)
  assert options["window"] == runtime.inference_compiler_options()
  # the same options where this jaxlib has only the newer emitters (jaxlib 0.11+)
  assert (options["window"] != options["frames"]) is XLA_OLDER_EMITTERS


def test_same_program_for_committed_and_numpy_variables():
  """Weights restored by orbax are committed device arrays, a .pth's are numpy: both must
  lower to the same program (one persistent-cache entry)."""
  fn = lambda v, x: v["w"] * x  # noqa: E731
  spec = jax.ShapeDtypeStruct((3,), np.float32)
  texts = []
  for i, w in enumerate((np.ones(3, np.float32),
                         jax.device_put(np.ones(3, np.float32), jax.devices()[0]))):
    key = inference._cache_key(f"test-{i}", {"w": w}, sav_jax.SAVConfig(), 2, (1, 1, 3))  # pylint: disable=protected-access
    compiled = inference._compile(key, lambda w=w: (fn, ({"w": w}, spec)), False)  # pylint: disable=protected-access
    inference._COMPILED.pop(key)  # pylint: disable=protected-access
    texts.append(compiled.as_text())
  assert texts[0] == texts[1]


def test_variables_on_another_device_run_there():
  """Weights placed on a device other than the default one: compiled for that device
  (the shapes-only lowering keeps a placement that is not the default)."""
  code = """if True:
    import jax, numpy as np, sav_jax
    from sav_jax import inference
    fn = lambda v, x: v["w"] * x
    spec = jax.ShapeDtypeStruct((3,), np.float32)
    w = jax.device_put(np.full(3, 2.0, np.float32), jax.devices()[1])
    key = inference._cache_key("t", {"w": w}, sav_jax.SAVConfig(), 2, (1, 1, 3))
    assert key != inference._cache_key("t", {"w": np.ones(3, np.float32)}, sav_jax.SAVConfig(),
                                       2, (1, 1, 3))
    compiled = inference._compile(key, lambda: (fn, ({"w": w}, spec)), False)
    x = jax.device_put(np.ones(3, np.float32), jax.devices()[1])
    print(np.asarray(compiled({"w": w}, x)).tolist())
  """
  env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
         "JAX_PLATFORMS": "cpu"}
  out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=120, check=False)
  assert out.returncode == 0, out.stderr[-2000:]
  assert out.stdout.strip() == "[2.0, 2.0, 2.0]"


def test_cache_key_follows_the_default_device():
  cfg = sav_jax.SAVConfig()
  plain = inference._cache_key("window", {}, cfg, 2, (1, 32, 32))  # pylint: disable=protected-access
  with jax.default_device(jax.devices()[0]):
    pinned = inference._cache_key("window", {}, cfg, 2, (1, 32, 32))  # pylint: disable=protected-access
  assert plain != pinned and plain[:5] == pinned[:5]


def test_window_shapes_that_are_not_positive_integers_are_named(variables):
  # 0 frames failed with "max() arg is an empty sequence" in the model, a float height with
  # JAX's "Error interpreting argument".
  cfg = sav_jax.SAVConfig()
  for shape, name in (((0, 32, 64), "frames"), ((2, 32.0, 64), "height"),
                      ((2, 32, True), "width")):
    for fn in (inference.compiled_forward, inference.compiled_frame_features,
               inference.compiled_window):
      kw = {} if fn is inference.compiled_frame_features else {"iters": 2}
      with pytest.raises(ValueError, match=f"{name} must be an integer >= 1, got "):
        fn(variables, *shape, cfg=cfg, **kw)
    with pytest.raises(ValueError, match=f"{name} must be an integer >= 1"):
      inference.estimate_memory_bytes(*shape)
  for iters in (None, -5, 2.5):  # a TypeError deep in the formula, or a number silently
    with pytest.raises(ValueError, match="iters"):
      inference.estimate_memory_bytes(2, 32, 64, iters)


def test_compiled_programs_take_the_default_config(variables):
  # cfg=None raised "'NoneType' object has no attribute 'dtype'" inside _compile.
  assert (inference.compiled_frame_features(variables, 1, 32, 32, cfg=None) is
          inference.compiled_frame_features(variables, 1, 32, 32, cfg=sav_jax.SAVConfig()))


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
@pytest.mark.parametrize("devices", [None, 2])
def test_window_features_are_not_held_twice_while_a_window_runs(monkeypatch, devices):
  """When a window's program runs, the cache holds only frames a later window needs: the
  window's own features are in the gathered array (they were held twice, ~1.25 GB of
  features per 10 frames at 720x1280)."""
  fake, caches, held = _CountingPrograms(), [], []

  class Recorded(inference.FrameFeatureCache):
    def __init__(self, *a, **kw):
      super().__init__(*a, **kw)
      caches.append(self)

  def window(variables, n, hp, wp, **kw):
    run = fake.window(variables, n, hp, wp, **kw)

    def recorded(v, feats):
      held.append(sorted(caches[-1].frames))
      return run(v, feats)

    return recorded

  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "compiled_frame_features", fake.frames)
  monkeypatch.setattr(inference, "compiled_window", window)
  monkeypatch.setattr(inference, "FrameFeatureCache", Recorded)
  if devices:
    monkeypatch.setattr(inference, "resolve_devices", lambda d: [None] * d)
    monkeypatch.setattr(jax, "device_put", lambda x, *a, **kw: x)
  video = _labelled_video(45)  # windows start at 0, 10, 20, 30 (15 frames)
  out = inference.predict_video({}, video, video, iters=2, check_memory=False,
                                devices=devices)
  assert out.shape == (45, 5, 7) and fake.computed == collections.Counter(range(45))
  np.testing.assert_array_equal(out, np.broadcast_to(np.arange(45.0)[:, None, None], out.shape))
  if devices is None:  # each window runs after the previous one's frames are forgotten
    assert held == [list(range(10, 20)), list(range(20, 30)), list(range(30, 40)), []]
  else:  # two windows dispatched at once (the stand-ins run at dispatch), then forgotten
    assert held[1] == list(range(30)) and held[2] == list(range(20, 40))
  assert not caches[-1].frames


def test_feature_chunks_are_aligned_to_the_video():
  """Chunks start at multiples of `chunk` from frame 0, wherever a window starts, cut to the
  window; a chunk runs unless all of its frames in the window are cached."""
  todo = inference._feature_todo  # pylint: disable=protected-access
  assert todo(set(), 10, 5, 20) == [(0, 5), (5, 15), (15, 20)]  # frames 5..9, 10..19, 20..24
  assert todo(set(range(5, 22)), 10, 5, 20) == [(15, 20)]  # 22..24 of chunk 20..29 missing
  with pytest.raises(ValueError, match="chunk must be a positive integer, got 0"):
    inference.FrameFeatureCache(chunk=0)


@pytest.mark.filterwarnings("ignore:.*float frames with values")
@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
def test_run_window_fills_a_chunk_that_an_earlier_window_cut_short(monkeypatch):
  """Windows [0, 15) and [10, 25) by hand with the default cache (chunks of 10): the first
  computes [10, 15) of chunk [10, 20); the second needs frames 15..19 of that chunk too."""
  fake = _CountingPrograms()
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "compiled_frame_features", fake.frames)
  monkeypatch.setattr(inference, "compiled_window", fake.window)
  video, cache = _labelled_video(25).astype(np.uint8), inference.FrameFeatureCache()
  right = video + 100
  for start, stop in ((0, 15), (10, 25)):
    out = inference.run_window({}, video[start:stop], right[start:stop], cfg=sav_jax.SAVConfig(),
                               iters=2, check_memory=False, cache=cache, start=start)
    assert out.shape == (15, 32, 32)  # 5x7 padded to 32x32
  assert sorted(fake.seen) == list(range(25))  # every frame's own features reached a window
  assert set(fake.computed) == set(range(25)) and fake.right_minus_left == {100}
  assert sorted(cache.frames) == list(range(10, 25))  # frames before the last window forgotten
  # The last window again, its first frame changed: refused (the cache, which forgot the
  # frames before 10, still holds frame 10's features and what they were computed from).
  other = video[10:25].copy()
  other[0] += 1
  with pytest.raises(ValueError, match="frame 10 differs from the frame whose features"):
    inference.run_window({}, other, other, cfg=sav_jax.SAVConfig(), iters=2, check_memory=False,
                         cache=cache, start=10)


@pytest.mark.filterwarnings("ignore::sav_jax.inference.SwappedViewsWarning")  # labels < 0
def test_a_list_of_uint8_frames_is_not_copied_whole(monkeypatch):
  """A list of uint8 frames (`[cv2.imread(p)[..., ::-1] for p in paths]`) was stacked into
  one array before the first window: a second copy of the whole video. Such lists are read
  window by window, as lazy sources are (uint8 values need no check); the output is the
  same, and lists of other frames are still checked whole before anything runs."""
  monkeypatch.setattr(inference, "check_variables", lambda *a: None)
  monkeypatch.setattr(inference, "_run_window", _LabelModel())
  stacked = []
  real_stack = np.stack
  monkeypatch.setattr(np, "stack", lambda arrays, *a, **k: (
      stacked.append(len(arrays)) if isinstance(arrays, (list, tuple)) else None)
      or real_stack(arrays, *a, **k))
  video = _labelled_video(23).astype(np.uint8)
  frames = list(video)
  out = inference.predict_video({}, frames, list(video))
  assert max(stacked) <= 20, stacked  # a window's frames at most, never all 23
  label = out[:, 0, 0]
  np.testing.assert_array_equal(label // 1000 - 1 + label % 1000, np.arange(23))
  np.testing.assert_array_equal(out, inference.predict_video({}, video, video))
  # beside an array, and window by window from iter_predict_video
  stacked.clear()
  got = dict(inference.iter_predict_video({}, frames, video, window=8, stride=4))
  assert max(stacked) <= 8, stacked
  assert sorted(got) == [0, 6, 10, 14, 18]
  np.testing.assert_array_equal(np.concatenate([got[t] for t in sorted(got)]),
                                inference.predict_video({}, video, video, window=8, stride=4))
  # lists of other frames: checked (and stacked) whole, before any window runs
  floats = [f.astype(np.float32) for f in video]
  floats[17] = floats[17] * np.nan
  with pytest.raises(ValueError, match=r"left: non-finite values \(NaN/inf\) in frame\(s\) \[17\]"):
    inference.predict_video({}, floats, video)
  with pytest.raises(ValueError, match="left: frame 3 has shape"):
    inference.predict_video({}, frames[:3] + [video[3, :4]] + frames[4:], video)
  with pytest.raises(ValueError, match="differ in shape"):
    inference.predict_video({}, frames[:22], video)

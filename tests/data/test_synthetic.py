"""Physics checks of the synthetic stereo-video generator (sav_jax.data.synthetic).

Everything here is checked against the camera model, not by eye: the right view
warped by the ground-truth disparity must reproduce the left view on valid pixels,
disparity must equal fx*B/Z, motion must respect the configured bounds, and the
valid mask must flag exactly the out-of-view and occluded points.
"""

import hashlib
import pickle
import subprocess
import sys

import numpy as np
import pytest

from sav_jax.data import synthetic, textures
from sav_jax.data.synthetic import SyntheticConfig, SyntheticStereoVideo, generate_clip

SMALL = SyntheticConfig(frames=4, height=96, width=192, num_objects=5, max_disparity=32.0,
                        seed=1)
TILTED = SyntheticConfig(frames=3, height=128, width=256, num_objects=8, max_tilt=1.0,
                         max_rotation=0.2, seed=2)
STATIC = dict(max_speed=0.0, max_rotation=0.0, max_depth_change=0.0, background_speed=0.0)

# Warp-check bounds (grey levels, on valid pixels away from depth discontinuities).
# Measured with texture_min_cell=4: mean ~0.37, p99 ~1.7.
WARP_MEAN_MAX = 0.6
WARP_P99_MAX = 3.0


@pytest.fixture(scope="module")
def small_clips():
  return [generate_clip(SMALL, i) for i in range(6)]


@pytest.fixture(scope="module")
def default_clip():
  return generate_clip(SyntheticConfig(), 0)


def _right_coords(disp):
  """Exact right-image x of every left pixel, its left bilinear tap and the weight."""
  h, w = disp.shape
  xr = np.arange(w, dtype=np.float32)[None, :] - disp
  x0 = np.clip(np.floor(xr).astype(np.int64), 0, w - 1)
  x1 = np.clip(x0 + 1, 0, w - 1)
  rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
  return xr, x0, x1, rows


def _warp_errors(clip, t, disp_offset=0.0):
  """|left - bilinear(right at x - d)| on valid pixels whose bilinear taps in the right
  image lie on the same surface (a 1-px band at depth edges is excluded).

  Returns:
    (errors [N*3], number of valid pixels, number of those excluded).
  """
  disp = clip["disparity"][t] + np.float32(disp_offset)
  xr, x0, x1, rows = _right_coords(disp)
  right = clip["right"][t].astype(np.float32)
  a = (xr - x0)[..., None]
  warped = right[rows, x0] * (1 - a) + right[rows, x1] * a
  seg, seg_r = clip["segmentation"][t], clip["segmentation_right"][t]
  valid = clip["valid"][t]
  interior = valid & (seg_r[rows, x0] == seg) & (seg_r[rows, x1] == seg)
  err = np.abs(warped - clip["left"][t].astype(np.float32))[interior]
  return err.ravel(), int(valid.sum()), int((valid & ~interior).sum())


def _all_warp_errors(clips, disp_offset=0.0):
  errs, n_valid, n_excl = [], 0, 0
  for clip in clips:
    for t in range(clip["disparity"].shape[0]):
      e, v, x = _warp_errors(clip, t, disp_offset)
      errs.append(e)
      n_valid += v
      n_excl += x
  return np.concatenate(errs), n_valid, n_excl


def test_warp_right_by_gt_disparity_reproduces_left(small_clips, default_clip):
  clips = small_clips + [default_clip, generate_clip(TILTED, 0)]
  err, n_valid, n_excl = _all_warp_errors(clips)
  assert err.mean() < WARP_MEAN_MAX, err.mean()
  assert np.percentile(err, 99) < WARP_P99_MAX, np.percentile(err, 99)
  # Only a thin band at depth discontinuities is excluded.
  assert n_excl < 0.02 * n_valid, n_excl / n_valid
  # Negative control: a 1.5 px disparity error must be clearly visible.
  bad, _, _ = _all_warp_errors(clips[:2], disp_offset=1.5)
  assert bad.mean() > 3 * WARP_MEAN_MAX, bad.mean()


def test_disparity_equals_fx_baseline_over_depth(small_clips, default_clip):
  for clip, cfg in [(c, SMALL) for c in small_clips] + [(default_clip, SyntheticConfig())]:
    fb = float(clip["fx"]) * float(clip["baseline"])
    assert float(clip["fx"]) == cfg.fx and float(clip["baseline"]) == np.float32(cfg.baseline)
    expect = fb / clip["depth"].astype(np.float64)
    np.testing.assert_allclose(clip["disparity"], expect, rtol=1e-6)
    # Dense GT stays inside the configured disparity range everywhere.
    assert clip["disparity"].min() >= cfg.min_disparity * (1 - 1e-5)
    assert clip["disparity"].max() <= cfg.max_disparity * (1 + 1e-5)


def test_shapes_dtypes_ranges(small_clips):
  t, h, w = SMALL.frames, SMALL.height, SMALL.width
  clip = small_clips[0]
  expected = {
      "left": ((t, h, w, 3), np.uint8), "right": ((t, h, w, 3), np.uint8),
      "disparity": ((t, h, w), np.float32), "depth": ((t, h, w), np.float32),
      "valid": ((t, h, w), np.bool_), "segmentation": ((t, h, w), np.uint8),
      "segmentation_right": ((t, h, w), np.uint8), "fx": ((), np.float32),
      "baseline": ((), np.float32),
  }
  assert set(clip) == set(expected)
  for key, (shape, dtype) in expected.items():
    assert clip[key].shape == shape and clip[key].dtype == dtype, key
  assert np.all(np.isfinite(clip["depth"])) and clip["depth"].min() > 0
  assert clip["segmentation"].max() <= SMALL.num_objects
  assert 0.5 < clip["valid"].mean() < 1.0
  # Textured, not flat: every frame has real contrast.
  assert all(clip["left"][i].std() > 10 for i in range(t))


def test_static_scene_when_all_motion_is_off():
  clip = generate_clip(SyntheticConfig(frames=3, height=64, width=128, max_disparity=16.0,
                                       **STATIC), 0)
  for key in ("left", "right", "disparity", "valid", "segmentation"):
    for t in range(1, 3):
      np.testing.assert_array_equal(clip[key][t], clip[key][0], err_msg=key)


def test_background_plane_is_static(small_clips):
  for clip in small_clips:
    seg, disp = clip["segmentation"], clip["disparity"]
    for t in range(SMALL.frames - 1):
      both = (seg[t] == 0) & (seg[t + 1] == 0)
      np.testing.assert_array_equal(disp[t][both], disp[t + 1][both])


def test_depth_change_per_frame_is_bounded_and_nonzero():
  cfg = SyntheticConfig(frames=5, height=96, width=192, num_objects=6, max_disparity=32.0,
                        max_tilt=0.0, max_depth_change=0.05, seed=4)
  bound = cfg.max_depth_change / (1 - cfg.max_depth_change)
  changes = []
  for i in range(3):
    clip = generate_clip(cfg, i)
    for k in range(1, cfg.num_objects + 1):
      per_frame = []
      for t in range(cfg.frames):
        d = clip["disparity"][t][clip["segmentation"][t] == k]
        if d.size:  # fronto-parallel object: one disparity per frame
          assert np.ptp(d) <= 1e-5 * d.max()
        per_frame.append(d[0] if d.size else np.nan)
      ratio = np.array(per_frame[1:]) / np.array(per_frame[:-1])
      ratio = ratio[np.isfinite(ratio)]
      assert np.all(np.abs(ratio - 1) <= bound + 1e-5), ratio
      changes.extend(np.abs(ratio - 1))
  assert max(changes) > 0.2 * cfg.max_depth_change  # objects really approach/recede


def test_objects_move_with_bounded_speed():
  cfg = SyntheticConfig(frames=5, height=96, width=192, num_objects=1, max_disparity=32.0,
                        shapes=("ellipse",), max_tilt=0.0, max_speed=3.0, seed=5)
  steps = []
  for i in range(8):
    seg = generate_clip(cfg, i)["segmentation"] == 1
    for t in range(cfg.frames - 1):
      a, b = seg[t], seg[t + 1]
      touches = [m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any() for m in (a, b)]
      if a.sum() < 50 or b.sum() < 50 or any(touches):
        continue  # a cropped ellipse's centroid is not its centre
      ca = np.array(np.nonzero(a)).mean(1)
      cb = np.array(np.nonzero(b)).mean(1)
      steps.append(np.hypot(*(cb - ca)))
  steps = np.array(steps)
  assert steps.size >= 10
  # The projected centre moves at most max_speed px/frame (rasterised centroid: +0.3).
  assert steps.max() <= cfg.max_speed + 0.3, steps.max()
  assert np.median(steps) > 0.1 * cfg.max_speed, steps


def test_valid_mask_matches_the_right_view(small_clips, default_clip):
  """Independent check of the analytic occlusion test against the rendered right view.

  Where both bilinear taps of x_r = x - d in the right image show the same layer L,
  the left point must be valid exactly when L is its own layer. The only allowed
  disagreements are sub-pixel slivers (a surface thinner than one pixel sitting
  between the two right pixel centres), hence the 1e-4 budget.
  """
  n_checked = n_wrong = n_occ = n_valid = 0
  for clip, cfg in [(c, SMALL) for c in small_clips] + [(default_clip, SyntheticConfig())]:
    for t in range(cfg.frames):
      xr, x0, x1, rows = _right_coords(clip["disparity"][t])
      in_view = (xr >= 0) & (xr <= cfg.width - 1)
      seg, valid, seg_r = clip["segmentation"][t], clip["valid"][t], clip["segmentation_right"][t]
      tap0, tap1 = seg_r[rows, x0], seg_r[rows, x1]
      checked = in_view & (tap0 == tap1)
      n_checked += checked.sum()
      n_wrong += (checked & ((tap0 == seg) != valid)).sum()
      occ = in_view & ~valid
      n_occ += occ.sum()
      n_valid += valid.sum()
  assert n_wrong <= 1e-4 * n_checked, (n_wrong, n_checked)
  assert n_occ > 0.01 * n_valid  # objects in front of the background cast occlusions


def test_left_border_out_of_view_is_invalid(small_clips):
  for clip in small_clips:
    xr, _, _, _ = _right_coords(clip["disparity"][0])
    out = xr < 0
    assert out[:, 0].all()  # d >= min_disparity > 0
    assert not clip["valid"][0][out].any()
    assert out.sum() >= SMALL.height * int(SMALL.min_disparity)


def test_determinism_by_seed_and_index():
  cfg = SyntheticConfig(frames=2, height=48, width=96, max_disparity=16.0, seed=7)
  a, b = generate_clip(cfg, 3), generate_clip(cfg, 3)
  for key in a:
    assert a[key].tobytes() == b[key].tobytes(), key
  other_index = generate_clip(cfg, 4)
  other_seed = generate_clip(SyntheticConfig(**{**cfg.__dict__, "seed": 8}), 3)
  assert a["left"].tobytes() != other_index["left"].tobytes()
  assert a["left"].tobytes() != other_seed["left"].tobytes()
  with pytest.raises(ValueError, match="index"):
    generate_clip(cfg, -1)


def _digest(clip):
  h = hashlib.sha256()
  for key in sorted(clip):
    h.update(key.encode() + clip[key].tobytes())
  return h.hexdigest()


def test_source_is_random_access_and_process_independent():
  cfg = SyntheticConfig(frames=2, height=48, width=96, max_disparity=16.0, seed=3)
  src = SyntheticStereoVideo(cfg, num_clips=4)
  assert len(src) == 4
  forward = [_digest(src[i]) for i in range(4)]
  backward = [_digest(src[i]) for i in reversed(range(4))][::-1]
  assert forward == backward and len(set(forward)) == 4
  assert _digest(src[-1]) == forward[3] == _digest(generate_clip(cfg, 3))
  assert _digest(pickle.loads(pickle.dumps(src))[2]) == forward[2]
  with pytest.raises(IndexError):
    src[4]
  code = ("import hashlib; from sav_jax.data.synthetic import *\n"
          f"c = generate_clip({cfg!r}, 2)\n"
          "h = hashlib.sha256()\n"
          "[h.update(k.encode() + c[k].tobytes()) for k in sorted(c)]\n"
          "print(h.hexdigest())")
  res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
  assert res.stdout.strip() == forward[2]


def test_grain_map_dataset():
  import grain  # pylint: disable=import-outside-toplevel
  cfg = SyntheticConfig(frames=2, height=48, width=96, max_disparity=16.0)
  src = SyntheticStereoVideo(cfg, num_clips=3)
  ds = grain.MapDataset.source(src)
  assert len(ds) == 3
  assert _digest(ds[1]) == _digest(generate_clip(cfg, 1))
  batch = ds.batch(2)[0]
  assert batch["left"].shape == (2, 2, 48, 96, 3)
  assert batch["valid"].dtype == np.bool_


def test_photometric_noise_is_optional_and_geometry_free():
  base = dict(frames=2, height=48, width=96, max_disparity=16.0)
  clean = generate_clip(SyntheticConfig(**base), 0)
  noisy = generate_clip(SyntheticConfig(**base, noise_std=3.0), 0)
  for key in ("disparity", "valid", "segmentation"):
    np.testing.assert_array_equal(clean[key], noisy[key])
  diff = noisy["left"].astype(np.float32) - clean["left"]
  assert 2.0 < diff.std() < 4.0



def test_faint_noise_rounds_to_the_noiseless_frames():
  # +0.5 before the truncation to uint8: noise far below a grey level changes nothing.
  base = dict(frames=1, height=16, width=32, num_objects=1, max_disparity=8.0, seed=4)
  clean = generate_clip(SyntheticConfig(**base), 0)
  faint = generate_clip(SyntheticConfig(**base, noise_std=1e-3), 0)
  for key in ("left", "right"):
    np.testing.assert_array_equal(faint[key], clean[key])


def test_background_disparity_stays_in_its_band_where_the_right_view_sees_it():
  """Left-image columns 0 .. W - 1 + max_disparity (what the right view shows): the
  background's disparity stays in its band, below every object's (so it never occludes)."""
  from sav_jax.data import raycast  # pylint: disable=import-outside-toplevel
  cfg = SyntheticConfig(frames=1, height=32, width=64, max_disparity=40.0, background_slant=1.0)
  cam = raycast.Camera(cfg.fx, (cfg.width - 1) / 2, (cfg.height - 1) / 2, cfg.baseline)
  xs = np.arange(cfg.width + int(cfg.max_disparity), dtype=np.float64)
  rx = ((xs - cam.cx) / cam.fx).astype(np.float32)[None, :]
  ry = ((np.arange(cfg.height) - cam.cy) / cam.fx).astype(np.float32)[:, None]
  for seed in range(20):
    layers, hi = synthetic._background_layers(np.random.default_rng(seed), cfg, cam)  # pylint: disable=protected-access
    depth = raycast.cast(layers[0], 0.0, rx, ry)[0]
    disp = cam.fx * cam.baseline / depth
    assert cfg.min_disparity - 1e-3 <= disp.min() and disp.max() <= hi + 1e-3, seed


def test_every_configured_shape_and_texture_kind_is_drawn(monkeypatch):
  kinds = []
  real = textures._pattern  # pylint: disable=protected-access
  monkeypatch.setattr(textures, "_pattern", lambda rng, kind, *a: kinds.append(kind) or real(
      rng, kind, *a))
  cfg = SyntheticConfig(frames=1, height=32, width=64, max_disparity=16.0, max_rotation=0.2)
  rng = np.random.default_rng(0)
  tracks = [synthetic._sample_track(rng, cfg, 4.0) for _ in range(24)]  # pylint: disable=protected-access
  assert {t.kind for t in tracks} == set(synthetic.SHAPES)
  assert set(kinds) == set(textures.TEXTURE_KINDS)
  # each object turns about its normal by its own omega per frame
  cam = synthetic.Camera(cfg.fx, 31.5, 15.5, cfg.baseline)
  for tr in tracks[:4]:
    e0, e1 = (synthetic._object_layer(tr, t, cam).e1 for t in (0, 1))  # pylint: disable=protected-access
    cos = float(e0 @ e1) / float(np.linalg.norm(e0) * np.linalg.norm(e1))
    assert np.arccos(np.clip(cos, -1, 1)) == pytest.approx(abs(tr.omega), abs=1e-6)
    assert abs(tr.omega) > 1e-4


def test_objects_are_nearer_than_the_background_band_and_rendered_whole(monkeypatch):
  """Tilted objects keep every pixel's disparity above the background's band (the valid mask
  assumes the background never occludes), and the pixel boxes that limit the ray casting hold
  each layer's whole image: casting every pixel gives the same clip."""
  from sav_jax.data import raycast  # pylint: disable=import-outside-toplevel
  cfg = SyntheticConfig(frames=1, height=32, width=32, focal=32.0, num_objects=8,
                        max_disparity=24.0, max_tilt=1.2, object_size=(0.6, 1.0), seed=5)
  band = cfg.min_disparity + cfg.background_fraction * (cfg.max_disparity - cfg.min_disparity)
  clips = [generate_clip(cfg, i) for i in (1, 6)]  # large tilted objects near the band
  for clip in clips:
    on_objects = clip["segmentation"] > 0
    assert on_objects.any() and clip["disparity"][on_objects].min() >= band * (1 - 1e-5)
  monkeypatch.setattr(raycast, "bbox", lambda layer, ox, cam, h, w: (0, h, 0, w))
  for i, clip in zip((1, 6), clips):
    whole = generate_clip(cfg, i)
    for key in clip:
      np.testing.assert_array_equal(whole[key], clip[key], err_msg=key)

def test_textures_tile_seamlessly():
  rng = np.random.default_rng(0)
  for kind in textures.TEXTURE_KINDS:
    tex = textures.make_texture(rng, 128, (kind,)).astype(np.float32)
    inner = np.abs(np.diff(tex, axis=1)).mean()
    seam = np.abs(tex[:, 0] - tex[:, -1]).mean()
    assert seam < 2 * inner + 0.5, (kind, seam, inner)
    inner_y = np.abs(np.diff(tex, axis=0)).mean()
    assert np.abs(tex[0] - tex[-1]).mean() < 2 * inner_y + 0.5, kind


@pytest.mark.parametrize("field, kwargs", [
    ("frames", dict(frames=0)),
    ("height", dict(height=8)),
    ("width", dict(width=4)),
    ("num_objects", dict(num_objects=-1)),
    ("min_disparity", dict(min_disparity=0.0)),
    ("max_disparity", dict(min_disparity=10.0, max_disparity=5.0)),
    ("max_disparity", dict(max_disparity=600.0)),
    ("max_speed", dict(max_speed=-1.0)),
    ("max_depth_change", dict(max_depth_change=0.7)),
    ("max_tilt", dict(max_tilt=1.5)),
    ("object_size", dict(object_size=(0.5, 0.2))),
    ("shapes", dict(shapes=("hexagon",))),
    ("textures", dict(textures=())),
    ("texture_min_cell", dict(texture_min_cell=3)),
    ("noise_std", dict(noise_std=-1.0)),
    ("baseline", dict(baseline=0.0)),
    ("seed", dict(seed=-2)),
    ("max_disparity", dict(max_disparity=512.0)),
    ("texture_min_cell", dict(texture_min_cell=64)),
    ("max_speed", dict(max_speed=True)),
    ("background_fraction", dict(background_fraction=0.0)),
    ("frames", dict(frames=True)),
    ("max_speed", dict(max_speed=float("inf"))),
    ("noise_std", dict(noise_std=float("nan"))),
    ("max_disparity", dict(max_disparity="64")),
    ("focal", dict(focal=float("inf"))),
])
def test_bad_config_names_the_field(field, kwargs):
  with pytest.raises(ValueError, match=rf"SyntheticConfig\.{field}\b"):
    SyntheticConfig(**kwargs)


def test_config_takes_numpy_scalars_as_python_values():
  cfg = SyntheticConfig(frames=np.int64(2), height=np.int32(32), width=64,
                        max_disparity=np.float32(6.0), seed=np.uint8(3))
  assert cfg == SyntheticConfig(frames=2, height=32, width=64, max_disparity=6.0, seed=3)
  assert type(cfg.frames) is int and type(cfg.max_disparity) is float


def test_source_rejects_bad_length():
  with pytest.raises(ValueError, match="num_clips"):
    SyntheticStereoVideo(SyntheticConfig(), num_clips=0)
  numpy_count = SyntheticStereoVideo(SyntheticConfig(), num_clips=np.int64(5))  # as elsewhere
  assert len(numpy_count) == 5 and type(numpy_count.num_clips) is int


def test_config_from_block_names_the_config_fields():
  """A config file's generator block: a typo is refused (it would generate with the
  default), bad values are named by the block's field, the caller's fields are its own."""
  block = {"frames": 3, "height": 32, "width": 48, "max_disparity": 6.0,
           "num_sequences": 2, "object_size": [0.2, 0.4]}
  cfg = synthetic.config_from_block(block, "config.synthetic", own=("num_sequences",))
  assert (cfg.frames, cfg.height, cfg.max_disparity, cfg.object_size) == (3, 32, 6.0, (0.2, 0.4))
  with pytest.raises(ValueError, match=r"config\.synthetic\.max_disparty is not a field of the "
                     r"synthetic generator; its fields: .*max_disparity.*num_sequences"):
    synthetic.config_from_block({"max_disparty": 4.0}, "config.synthetic",
                                own=("num_sequences",))
  with pytest.raises(ValueError, match=r"config\.synthetic\.min_disparity must be > 0, got 0"):
    synthetic.config_from_block(dict(block, min_disparity=0), "config.synthetic",
                                own=("num_sequences",))
  fixed = {"frames": "config.data.frames"}
  with pytest.raises(ValueError, match=r"config\.d\.frames: the clips' frames is "
                     r"config\.data\.frames's"):
    synthetic.config_from_block({"frames": 2}, "config.d", set_by=fixed, frames=3)
  # a bad value the caller set itself keeps the dataclass's name (the block did not give it)
  with pytest.raises(ValueError, match=r"^SyntheticConfig\.seed "):
    synthetic.config_from_block({"seed": 1}, "config.d", seed=-1)
  assert synthetic.config_from_block({"seed": 1}, "config.d", seed=5).seed == 5

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
  # independent per pixel and channel: the channels' noise is uncorrelated (|r| ~ 0.01)
  corr = np.corrcoef(diff.reshape(-1, 3).T)
  assert np.abs(corr[np.triu_indices(3, 1)]).max() < 0.1, corr


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
  # the documented band: the lowest background_fraction of [min_disparity, max_disparity]
  band = cfg.min_disparity + cfg.background_fraction * (cfg.max_disparity - cfg.min_disparity)
  for seed in range(20):
    layers, hi = synthetic._background_layers(np.random.default_rng(seed), cfg, cam)  # pylint: disable=protected-access
    assert hi == pytest.approx(band)  # objects are drawn above `hi`
    depth = raycast.cast(layers[0], 0.0, rx, ry)[0]
    disp = cam.fx * cam.baseline / depth
    assert cfg.min_disparity - 1e-3 <= disp.min() and disp.max() <= band + 1e-3, seed


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
  turns = []
  for tr in tracks:
    e0, e1 = (synthetic._object_layer(tr, t, cam).e1 for t in (0, 1))  # pylint: disable=protected-access
    cos = float(e0 @ e1) / float(np.linalg.norm(e0) * np.linalg.norm(e1))
    turns.append(np.arccos(np.clip(cos, -1, 1)))
    assert turns[-1] == pytest.approx(abs(tr.omega), abs=1e-6)
    assert abs(tr.omega) > 1e-4
  # at most max_rotation rad a frame, and the range is used
  assert cfg.max_rotation / 2 < max(turns) <= cfg.max_rotation + 1e-6, max(turns)


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


def _shape_area(kind, params):
  """Area (texels^2) of a shape from its parameters, by elementary geometry."""
  if kind == "rectangle":
    return 4 * params[0] * params[1]
  if kind == "ellipse":
    return np.pi * params[0] * params[1]
  _, px, py = params  # shoelace formula over the (angularly ordered) vertices
  px, py = px.astype(np.float64), py.astype(np.float64)
  return 0.5 * abs(np.dot(px, np.roll(py, -1)) - np.dot(py, np.roll(px, -1)))


@pytest.mark.parametrize("kind", synthetic.SHAPES)
def test_object_image_size_follows_its_depth(kind):
  """A fronto-parallel object shows its shape at 1 texel = 1 px at frame 0, and its image
  scales as Z_0 / Z_t when it approaches or recedes (size and disparity change together)."""
  from sav_jax.data import raycast  # pylint: disable=import-outside-toplevel
  cfg = SyntheticConfig(frames=1, height=128, width=128, num_objects=1, max_disparity=32.0,
                        max_tilt=0.0, shapes=(kind,), object_size=(0.5, 0.6), seed=3)
  cam = raycast.Camera(cfg.fx, 63.5, 63.5, cfg.baseline)
  rng = np.random.default_rng(11)
  bg = synthetic._background_layers(rng, cfg, cam)[0][0]  # pylint: disable=protected-access
  tr = synthetic._sample_track(rng, cfg, 10.0)  # pylint: disable=protected-access
  # centred, not moving in the image, receding by 6% a frame
  tr = tr._replace(u0=cam.cx, v0=cam.cy, vel=(0.0, 0.0), rate=0.06)
  rx = ((np.arange(128) - cam.cx) / cam.fx).astype(np.float32)[None, :]
  ry = ((np.arange(128) - cam.cy) / cam.fx).astype(np.float32)[:, None]
  area0 = _shape_area(kind, tr.params)
  for t in (0, 4):
    layer = synthetic._object_layer(tr, t, cam)  # pylint: disable=protected-access
    _, depth, seg = raycast.render_view([bg, layer], 0.0, cam, rx, ry)
    z = tr.depth0 * 1.06 ** t
    expect = area0 * (tr.depth0 / z) ** 2
    # pixel counting of a shape a few dozen px across: within 3% of the area
    assert abs((seg == 1).sum() - expect) < 0.03 * expect, (t, (seg == 1).sum(), expect)
    np.testing.assert_allclose(depth[seg == 1], z, rtol=1e-5)


def test_cast_hits_the_plane_at_the_solved_intersection():
  """Ray/plane intersection against a 3x3 linear solve: O + Z (rx, ry, 1) = C + s u1 + r u2
  (u1, u2 the unit in-plane axes); the texel offsets are s |e1| and r |e2|. A plane behind
  the camera is not hit."""
  from sav_jax.data import raycast  # pylint: disable=import-outside-toplevel
  normal = raycast.unit(np.array([0.3, -0.2, 1.0]))
  e1, e2 = raycast.plane_axes(normal, 0.7)
  center = np.array([0.2, -0.1, 3.0])
  layer = raycast.Layer(center, normal, 40.0 * e1, 40.0 * e2, "rectangle", (1e3, 1e3), (),
                        0.0, np.zeros((64, 64, 4), np.uint8), (0.0, 0.0))
  rx = np.array([[-0.4, 0.0, 0.25]], np.float32)
  ry = np.array([[-0.3], [0.1]], np.float32)
  for ox in (0.0, 0.1):
    depth, tu, tv, hit = raycast.cast(layer, ox, rx, ry)
    assert hit.all()
    for i in range(2):
      for j in range(3):
        a = np.stack([[rx[0, j], ry[i, 0], 1.0], -e1, -e2], axis=1)
        z, s, r = np.linalg.solve(a, center - np.array([ox, 0.0, 0.0]))
        assert depth[i, j] == pytest.approx(z, rel=1e-5)
        assert tu[i, j] == pytest.approx(40.0 * s, abs=1e-3)
        assert tv[i, j] == pytest.approx(40.0 * r, abs=1e-3)
  for z in (-3.0, -0.1):  # far behind, and just behind: n.(C - O) < 0, depth about -0.02
    behind = layer._replace(center=np.array([0.2, -0.1, z]))
    assert not raycast.cast(behind, 0.0, rx, ry)[3].any()


def test_background_drift_is_bounded_by_background_speed():
  """A fronto-parallel background (1 texel = 1 px everywhere) drifts by at most
  background_speed px/frame: the translation between consecutive left frames, found by
  phase correlation refined by ECC alignment (accurate to ~0.01 px here)."""
  import cv2  # pylint: disable=import-outside-toplevel
  cfg = SyntheticConfig(frames=2, height=64, width=128, num_objects=0, max_disparity=16.0,
                        background_slant=0.0, background_speed=3.0, seed=9)
  window = cv2.createHanningWindow((cfg.width, cfg.height), cv2.CV_32F)
  stop = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
  shifts = []
  for i in range(12):
    left = generate_clip(cfg, i)["left"].astype(np.float32).mean(-1)
    (dx, dy), _ = cv2.phaseCorrelate(left[0], left[1], window)
    warp = np.array([[1, 0, dx], [0, 1, dy]], np.float32)
    _, warp = cv2.findTransformECC(left[0], left[1], warp, cv2.MOTION_TRANSLATION, stop, None, 1)
    shifts.append(np.hypot(*warp[:, 2]))
  shifts = np.array(shifts)
  assert shifts.max() <= cfg.background_speed + 0.05, shifts
  assert np.median(shifts) > 0.2 * cfg.background_speed, shifts  # it really drifts


def test_without_objects_validity_is_exactly_the_right_image_bounds():
  """Nothing occludes a lone background: a left pixel is valid iff 0 <= x - d <= W - 1.
  Sub-pixel disparities (the background band is [0.25, 1]) put the last column's x - d in
  (W - 2, W - 1], which must still count as in view."""
  cfg = SyntheticConfig(frames=2, height=32, width=64, num_objects=0, min_disparity=0.25,
                        max_disparity=4.0, background_fraction=0.2, seed=2)
  for i in range(3):
    clip = generate_clip(cfg, i)
    xr = np.arange(cfg.width, dtype=np.float64) - clip["disparity"].astype(np.float64)
    expect = (xr >= 0) & (xr <= cfg.width - 1)
    np.testing.assert_array_equal(clip["valid"], expect)
    assert (xr[..., -1] > cfg.width - 2).any()  # the case above really occurs


def test_an_object_is_drawn_where_its_centre_projects(monkeypatch):
  """Principal point at the image centre ((W-1)/2, (H-1)/2, pixel centres at integers) and
  image-plane motion as configured: a fronto-parallel ellipse whose centre projects to
  (u0 + vx t, v0 + vy t), while it approaches, is rasterised around that point in the left
  view and around (u - d, v) in the right one."""
  real = synthetic._sample_track  # pylint: disable=protected-access
  u0, v0, vel = 50.3, 27.6, (1.5, -0.8)
  monkeypatch.setattr(synthetic, "_sample_track", lambda rng, cfg, lo: real(rng, cfg, lo)._replace(
      u0=u0, v0=v0, vel=vel, rate=-0.05))
  cfg = SyntheticConfig(frames=3, height=64, width=128, num_objects=1, max_disparity=16.0,
                        max_tilt=0.0, shapes=("ellipse",), object_size=(0.4, 0.5), seed=1)
  for i in range(3):
    clip = generate_clip(cfg, i)
    for t in range(cfg.frames):
      u, v = u0 + vel[0] * t, v0 + vel[1] * t
      d = float(clip["disparity"][t][clip["segmentation"][t] == 1].mean())
      for seg, x in ((clip["segmentation"][t], u), (clip["segmentation_right"][t], u - d)):
        ys, xs = np.nonzero(seg == 1)
        # centroid of a rasterised ellipse >= 14 px across: within 0.15 px of its centre
        assert abs(xs.mean() - x) < 0.15 and abs(ys.mean() - v) < 0.15, (i, t, xs.mean(), ys.mean())


def test_valid_mask_sees_a_nearly_coplanar_occluder():
  """An occluder only 0.5% nearer than the surface behind it still hides a sliver of it from
  the right camera (closed-form for fronto-parallel rectangles: left pixel x of the far one
  is hidden where x - d_far falls inside the near one's right image)."""
  from sav_jax.data import raycast  # pylint: disable=import-outside-toplevel
  h, w, fx, base = 48, 160, 160.0, 0.16  # fB = 25.6
  cam = raycast.Camera(fx, (w - 1) / 2, (h - 1) / 2, base)
  tex = np.full((8, 8, 4), 128, np.uint8)

  def rect(k, u, v, z, a, b):  # 1 texel = 1 px: a, b are the half-sizes in px
    s = fx / z
    center = np.array([(u - cam.cx) * z / fx, (v - cam.cy) * z / fx, z])
    return raycast.Layer(center, np.array([0.0, 0.0, 1.0]), np.array([s, 0.0, 0.0]),
                         np.array([0.0, s, 0.0]), "rectangle", (a, b), (-a, a, -b, b), z, tex,
                         (0.0, 0.0))

  bg = rect(0, cam.cx, cam.cy, 20.0, 0, 0)._replace(kind="background", params=(), extent=())
  z_far, z_near = 0.4, 0.398  # d = 64 and 64.32 px
  far = rect(1, 100.0, 24.0, z_far, 30.0, 20.0)
  near = rect(2, 110.1, 24.0, z_near, 10.0, 10.0)  # left edge at x = 100.1
  layers = [bg, far, near]
  ry = ((np.arange(h) - cam.cy) / fx).astype(np.float32)[:, None]
  rx = ((np.arange(w) - cam.cx) / fx).astype(np.float32)[None, :]
  _, depth, seg = raycast.render_view(layers, 0.0, cam, rx, ry)
  valid = raycast.valid_mask(layers, depth, seg, cam, ry)
  d_far, d_near = fx * base / z_far, fx * base / z_near
  x = np.arange(w)[None, :] - d_far
  y = np.arange(h)[:, None]
  hidden = (np.abs(x - (110.1 - d_near)) <= 10.0) & (np.abs(y - 24.0) <= 10.0) & (seg == 1)
  assert hidden.sum() >= 15  # one column of the far rectangle, rows 14..34
  assert not valid[hidden].any()
  assert valid[(seg == 1) & ~hidden].all()


def test_valid_mask_agrees_with_unculled_ray_casting(monkeypatch):
  """The valid mask skips layers by pixel box and depth bound (zmin); casting the right
  camera's ray through x - d into every layer, without any culling, must give the same mask.
  Large, strongly tilted objects make the depth bound matter (a tilted layer's near part is
  well in front of its centre)."""
  from sav_jax.data import raycast  # pylint: disable=import-outside-toplevel
  scenes = []
  real = synthetic.valid_mask
  monkeypatch.setattr(synthetic, "valid_mask", lambda layers, *a: scenes.append(layers) or real(
      layers, *a))
  n_occluded = 0
  for seed in range(3):
    cfg = SyntheticConfig(frames=2, height=64, width=128, num_objects=10, max_tilt=1.2,
                          object_size=(0.4, 0.9), max_disparity=40.0, seed=seed)
    for i in range(2):
      scenes.clear()
      clip = generate_clip(cfg, i)
      h, w, fx, cx, cy = cfg.height, cfg.width, cfg.fx, (cfg.width - 1) / 2, (cfg.height - 1) / 2
      for t, layers in enumerate(scenes):
        depth, seg = clip["depth"][t], clip["segmentation"][t]
        xr = np.arange(w)[None, :] - clip["disparity"][t]
        rx = ((xr - cx) / fx).astype(np.float32)
        ry = np.broadcast_to(((np.arange(h) - cy) / fx).astype(np.float32)[:, None], (h, w))
        occluded = np.zeros((h, w), bool)
        for layer in layers[1:]:  # a plane never occludes itself: no need to skip seg == j
          z, _, _, hit = raycast.cast(layer, cfg.baseline, rx, ry)
          occluded |= hit & (z < depth * np.float32(1 - 1e-5))
        expect = (xr >= 0) & (xr <= w - 1) & ~occluded
        n_occluded += (occluded & (xr >= 0)).sum()
        np.testing.assert_array_equal(clip["valid"][t], expect, err_msg=f"{seed} {i} {t}")
  assert n_occluded > 1000


def _shape_outline(kind, params):
  """Points (texels) whose convex hull holds the shape: depth is affine on a plane, so its
  extremes over the shape are among them."""
  if kind == "rectangle":
    a, b = params
    return np.array([[-a, -b], [-a, b], [a, -b], [a, b]])
  if kind == "ellipse":
    phi = np.linspace(0, 2 * np.pi, 721)
    return np.stack([params[0] * np.cos(phi), params[1] * np.sin(phi)], 1)
  return np.stack([params[1], params[2]], 1).astype(np.float64)


def test_tilted_objects_changing_depth_keep_every_point_in_the_disparity_range():
  """Every point of every object, in every frame, has its disparity inside [top of the
  background band, max_disparity] (computed from the 3D plane points, visible or not), also
  for large, strongly tilted objects whose depth changes fast."""
  cfg = SyntheticConfig(frames=6, height=64, width=64, num_objects=1, max_disparity=24.0,
                        max_tilt=1.2, max_depth_change=0.2, object_size=(0.5, 1.0), seed=6)
  band = cfg.min_disparity + cfg.background_fraction * (cfg.max_disparity - cfg.min_disparity)
  cam = synthetic.Camera(cfg.fx, 31.5, 31.5, cfg.baseline)
  rng = np.random.default_rng(0)
  top = []
  for _ in range(60):
    tr = synthetic._sample_track(rng, cfg, band)  # pylint: disable=protected-access
    outline = _shape_outline(tr.kind, tr.params)
    for t in range(cfg.frames):
      layer = synthetic._object_layer(tr, t, cam)  # pylint: disable=protected-access
      # texel offsets -> metres: e1, e2 are orthogonal with length texels/metre
      pts = layer.center + outline @ np.stack([layer.e1, layer.e2]) / (layer.e1 @ layer.e1)
      disp = cfg.fx * cfg.baseline / pts[:, 2]
      assert band * (1 - 1e-6) <= disp.min() and disp.max() <= cfg.max_disparity * (1 + 1e-6)
      top.append(disp.max())
  assert max(top) > 0.97 * cfg.max_disparity  # the bound is approached, so it is tested


def test_equal_disparity_bounds_make_every_surface_fronto_parallel_at_that_disparity():
  # min_disparity == max_disparity leaves no room for tilt or depth motion: every pixel of
  # every frame has exactly that disparity (objects fall back to still, untilted planes).
  cfg = SyntheticConfig(frames=3, height=32, width=64, num_objects=4, min_disparity=8.0,
                        max_disparity=8.0, max_tilt=1.0, max_depth_change=0.2, seed=3)
  disp = generate_clip(cfg, 0)["disparity"]
  np.testing.assert_allclose(disp, 8.0, rtol=1e-5)


def test_value_noise_is_normalised():
  # zero mean and a standard deviation of about 1 (exactly 1 on the node grid; the bicubic
  # interpolation to full size lowers it slightly)
  for seed in range(3):
    noise = textures.value_noise(np.random.default_rng(seed), 128, 4)
    assert abs(noise.mean()) < 0.05 and 0.8 < noise.std() < 1.05, (noise.mean(), noise.std())
  # a larger falloff is smoother: less of the variance in neighbour differences
  rough = [np.var(np.diff(textures.value_noise(np.random.default_rng(0), 128, 4,
                                               falloff=f), axis=1)) for f in (0.0, 1.0)]
  assert rough[1] < 0.5 * rough[0], rough
  with pytest.raises(ValueError, match="size 10 is not a multiple of min_cell 4"):
    textures.value_noise(np.random.default_rng(0), 10, 4)


@pytest.mark.parametrize("size", [12, 48, 128])
def test_value_noise_of_a_multiple_of_min_cell_has_that_size_and_tiles(size):
  """Sizes that are no power of two, and below max_cell (64), keep the octaves up to the
  largest power-of-two cell dividing S (4 for 12, 16 for 48): 12 gave 16x16 noise, 48 gave
  64x64 (and 10 no error). The wrap-around step is no larger than the steps inside."""
  noise = textures.value_noise(np.random.default_rng(0), size, 4)
  assert noise.shape == (size, size)
  for a in (noise, noise.T):
    assert np.abs(a[:, 0] - a[:, -1]).mean() < 2 * np.abs(np.diff(a, axis=1)).mean()


def test_plane_waves_tile_with_an_integer_wave_vector():
  """A period of S/4 along x (angle 0) is the wave vector (4, 0): the phase grows by
  2 pi 4 / S a texel along x and not at all along y; along y (angle pi/2) the reverse."""
  size = 64
  for angle, (kx, ky) in ((0.0, (4, 0)), (np.pi / 2, (0, 4))):
    px, py = textures._plane_wave(  # pylint: disable=protected-access
        np.random.default_rng(0), size, size / 4, size / 4, angle)
    assert px.shape == (1, size) and py.shape == (size, 1)
    np.testing.assert_allclose(px[0] - px[0, 0], kx * 2 * np.pi / size * np.arange(size),
                               atol=1e-5)
    np.testing.assert_allclose(py[:, 0], ky * 2 * np.pi / size * np.arange(size), atol=1e-5)
  # the "gradient" pattern is such a wave of one period across the tile: all of its power at
  # wave vectors of components in {-1, 0, 1}
  k = np.abs(np.fft.fftfreq(size) * size)
  one = np.maximum(k[:, None], k[None, :]) == 1
  for seed in range(3):
    grad = textures._pattern(  # pylint: disable=protected-access
        np.random.default_rng(seed), "gradient", size, 4)
    power = np.abs(np.fft.fft2(grad)) ** 2
    assert power[one].sum() > 0.999 * power.sum(), seed


def test_soft_sign_is_the_cubic_smoothstep_of_the_clipped_gain():
  # x (1.5 - 0.5 x^2) of clip(2 x, -1, 1): 0.5 -> 0.6875, saturating at +-1 from |x| = 0.5
  x = np.array([-2.0, -0.5, -0.25, 0.0, 0.25, 0.5, 2.0], np.float32)
  np.testing.assert_allclose(textures._soft_sign(x, 2.0),  # pylint: disable=protected-access
                             [-1, -1, -0.6875, 0, 0.6875, 1, 1])


def test_texture_contrast_scales_the_colour_amplitudes():
  # The same draws at half the contrast: texel = base + contrast * amplitude, so
  # 2 * half - full is the constant base colour (up to 8-bit rounding) where nothing saturates.
  for kind in textures.TEXTURE_KINDS:
    full, half = (textures.make_texture(np.random.default_rng(1), 128, (kind,), contrast=c)
                  .astype(np.float64) for c in (1.0, 0.5))
    bases = []
    for ch in range(3):
      unsaturated = (full[..., ch] > 0) & (full[..., ch] < 255)
      base = (2 * half[..., ch] - full[..., ch])[unsaturated]
      assert unsaturated.mean() > 0.9 and np.ptp(base) <= 3.0, (kind, ch, np.ptp(base))
      bases.append(np.median(base))
    assert full.std((0, 1)).min() > 5, kind  # not a trivially flat texture
    assert np.ptp(bases) > 3.0, (kind, bases)  # a base colour, not a grey


@pytest.mark.parametrize("min_cell", [4, 8])
def test_textures_have_no_detail_finer_than_min_cell(min_cell):
  """Band limit: wavelengths shorter than min_cell texels carry under 0.1% of a texture's
  (grey) variance (measured <= 0.04%; noise octaves at min_cell / 2 would give >= 0.1%)."""
  for kind in textures.TEXTURE_KINDS:
    for seed in range(2):
      tex = textures.make_texture(np.random.default_rng(seed), 128, (kind,), min_cell)
      grey = tex.astype(np.float64).mean(-1)
      power = np.abs(np.fft.fft2(grey - grey.mean())) ** 2
      f = np.fft.fftfreq(128)
      fine = np.hypot(f[:, None], f[None, :]) > 1 / min_cell
      assert power[fine].sum() < 1e-3 * power.sum(), (kind, seed, power[fine].sum() / power.sum())


def test_projected_object_centres_move_at_most_max_speed():
  """The image-plane speed bound, on the projection of each object's 3D centre (exact, where
  the rasterised-centroid test above needs a 0.3 px allowance): every step <= max_speed px,
  and the bound is approached."""
  cfg = SyntheticConfig(frames=3, height=64, width=64, num_objects=1, max_disparity=16.0,
                        max_speed=3.0, seed=2)
  cam = synthetic.Camera(cfg.fx, 31.5, 31.5, cfg.baseline)
  rng = np.random.default_rng(0)
  steps = []
  for _ in range(40):
    tr = synthetic._sample_track(rng, cfg, 5.0)  # pylint: disable=protected-access
    c = np.array([synthetic._object_layer(tr, t, cam).center for t in range(cfg.frames)])  # pylint: disable=protected-access
    uv = cfg.fx * c[:, :2] / c[:, 2:] + np.array([cam.cx, cam.cy])
    steps.extend(np.hypot(*np.diff(uv, axis=0).T))
  assert max(steps) <= cfg.max_speed * (1 + 1e-9), max(steps)
  assert max(steps) > 0.9 * cfg.max_speed, max(steps)


def test_an_object_texture_does_not_repeat_across_the_object():
  # One texture period spans the whole shape, so an object shows no repeated pattern (which
  # would make its matching ambiguous).
  cfg = SyntheticConfig(frames=1, height=256, width=256, num_objects=1, object_size=(0.5, 1.0))
  rng = np.random.default_rng(0)
  for _ in range(6):
    tr = synthetic._sample_track(rng, cfg, 20.0)  # pylint: disable=protected-access
    span = np.ptp(_shape_outline(tr.kind, tr.params), axis=0).max()  # texels
    assert tr.texture.shape[0] >= span, (tr.texture.shape, span)

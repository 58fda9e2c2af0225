"""Training augmentation (sav_jax.data.augment): geometry, photometry, masks, determinism."""

import dataclasses

import numpy as np
import pytest

from sav_jax.data import augment
from sav_jax.data.augment import AugmentConfig, _Jitter, _resize_sparse, _scales, augment_clip

T, H, W = 3, 48, 96
# Spatial identity: s = 1 exactly (crop + 8 = image size), so only the crop moves pixels.
IDENTITY = AugmentConfig(crop_size=(H - 8, W - 8), scale_range=(0.0, 0.0), stretch_prob=0.0,
                         photometric=False, eraser_prob=0.0, yjitter=False)


def _uniform_clip(colours_left, colours_right):
  """Clip whose every image is one flat colour ([T, 3] uint8 lists)."""
  left = np.broadcast_to(np.asarray(colours_left, np.uint8)[:, None, None], (T, H, W, 3))
  right = np.broadcast_to(np.asarray(colours_right, np.uint8)[:, None, None], (T, H, W, 3))
  return {"left": left.copy(), "right": right.copy()}


def _texture(x, y, phase):
  """Smooth RGB function (periods >= 40 px keep bilinear resampling error small)."""
  return np.stack([128 + 60 * np.sin(2 * np.pi * x / 41 + phase + c) * np.cos(2 * np.pi * y / 53
                                                                              + c)
                   for c in range(3)], axis=-1)


def _planar_clip(rng):
  """Left/right views of slanted planes d = a + b x + c y (left pixel coordinates):
  left(x, y) = f(x, y), right(x_r, y) = f(x, y) with x_r = x - d(x, y)."""
  ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
  clip = {"left": [], "right": [], "disparity": [], "valid": []}
  for t in range(T):
    a, b, c = 8.0 + 2 * t, 0.05, 0.1
    d = a + b * xs + c * ys
    x_of_right = (xs + a + c * ys) / (1 - b)  # the left x seen at right column xs
    clip["left"].append(np.round(_texture(xs, ys, t)).astype(np.uint8))
    clip["right"].append(np.round(_texture(x_of_right, ys, t)).astype(np.uint8))
    clip["disparity"].append(d.astype(np.float32))
    clip["valid"].append(np.zeros((H, W), bool))  # dense: must be recomputed, not carried
  return {k: np.stack(v) for k, v in clip.items()}


def test_shapes_dtypes_and_determinism():
  rng = np.random.default_rng(0)
  clip = _planar_clip(rng)
  clip["depth2disp_scale"] = 7.5
  cfg = AugmentConfig(crop_size=(24, 40), eraser_prob=1.0)
  before = {k: np.copy(v) for k, v in clip.items()}
  a = augment_clip(clip, cfg, np.random.default_rng(5))
  for k, v in before.items():
    np.testing.assert_array_equal(clip[k], v)  # the input is never written
  b = augment_clip(clip, cfg, np.random.default_rng(5))
  c = augment_clip(clip, cfg, np.random.default_rng(6))
  assert a["left"].shape == a["right"].shape == (T, 24, 40, 3) and a["left"].dtype == np.uint8
  assert a["disparity"].shape == a["valid"].shape == (T, 24, 40)
  assert a["disparity"].dtype == np.float32 and a["valid"].dtype == bool
  assert a["depth2disp_scale"] == 7.5  # passed through
  for k in ("left", "right", "disparity", "valid"):
    np.testing.assert_array_equal(a[k], b[k])
    assert a[k].flags.c_contiguous
  assert not np.array_equal(a["left"], c["left"])


def _warp_errors(out, scale=1.0):
  """|left - right sampled at x - scale * d| on interior pixels of every frame."""
  errs = []
  _, h, w = out["disparity"].shape
  for t in range(T):
    d = out["disparity"][t] * scale
    xr = np.arange(w)[None, :] - d
    x0 = np.floor(xr).astype(int)
    inside = (x0 >= 0) & (x0 + 1 <= w - 1)
    inside[:2], inside[-2:] = False, False  # cv2 resize clamps the source at borders
    assert inside.sum() > 300
    rows = np.broadcast_to(np.arange(h)[:, None], d.shape)
    x0c = np.clip(x0, 0, w - 2)
    a = (xr - x0c)[..., None]
    right = out["right"][t].astype(np.float64)
    warped = right[rows, x0c] * (1 - a) + right[rows, x0c + 1] * a
    errs.append(np.abs(warped - out["left"][t])[inside])
  return np.concatenate(errs)


@pytest.mark.parametrize("seed", range(4))
def test_left_right_consistency_after_crop_and_scale(seed):
  clip = _planar_clip(np.random.default_rng(seed))
  cfg = AugmentConfig(crop_size=(24, 48), scale_range=(0.2, 0.4), photometric=False,
                      eraser_prob=0.0, yjitter=False)  # stretch on: sx != sy
  out = augment_clip(clip, cfg, np.random.default_rng(seed))
  err = _warp_errors(out)
  assert err.mean() < 0.8 and err.max() < 4.0, (err.mean(), err.max())
  # The check is sensitive: a disparity 10 % off (e.g. scaled by sy, or not at all)
  # misaligns the views by about a pixel.
  assert _warp_errors(out, 0.9).mean() > 3 * err.mean() + 1.0
  np.testing.assert_array_equal(out["valid"], (out["disparity"] != 0)
                                & (np.abs(out["disparity"]) < 512))
  assert out["valid"].all()


def test_dense_valid_is_recomputed_from_the_final_disparity():
  clip = _planar_clip(np.random.default_rng(1))
  clip["disparity"][:, :10] = 0.0
  clip["disparity"][:, 20:30, 40:60] = 600.0
  clip["valid"][:] = True
  out = augment_clip(clip, IDENTITY, np.random.default_rng(2))
  d = out["disparity"]
  np.testing.assert_array_equal(out["valid"], (d != 0) & (np.abs(d) < 512))
  assert (~out["valid"]).sum() > 0 and out["valid"].sum() > 0


def test_a_dense_clips_valid_mask_is_not_read():
  # augment_clip's docstring: a dense clip's valid mask is recomputed, not carried (the
  # official rule); pixels it marks invalid need a disparity of 0 (pipeline.honour_dense_masks)
  clip = _planar_clip(np.random.default_rng(1))
  clip["valid"][:] = False
  out = augment_clip(clip, IDENTITY, np.random.default_rng(2))
  np.testing.assert_array_equal(out["valid"], out["disparity"] != 0)
  assert out["valid"].all()


def test_sparse_resize_scatters_rounded_points():
  disp = np.zeros((4, 6), np.float32)
  valid = np.zeros((4, 6), bool)
  for (y, x, v) in ((1, 2, 3.0), (2, 4, 5.0), (3, 0, 7.0), (0, 3, 9.0), (1, 3, 11.0)):
    disp[y, x], valid[y, x] = v, True
  d, m = _resize_sparse(disp, valid, 1.5, 2.0, (8, 9))
  # (1,2) -> (2, 3); (2,4) -> (4, 6); (3,0) -> x = 0 dropped; (0,3) -> y = 0 dropped;
  # (1,3) -> (2, round(4.5) = 4).
  assert sorted(zip(*np.nonzero(m))) == [(2, 3), (2, 4), (4, 6)]
  assert d[2, 3] == 4.5 and d[4, 6] == 7.5 and d[2, 4] == 16.5
  assert d[~m].max() == 0
  # rounded, not floored: x = y = 1 at sx = sy = 1.7 lands on (2, 2), not (1, 1) (floor kept
  # the point on row and column 1; the same point at 1.4 stays on (1, 1))
  one = np.zeros((4, 6), bool)
  one[1, 1] = True
  for s, at in ((1.7, (2, 2)), (1.4, (1, 1))):
    d, m = _resize_sparse(np.where(one, 2.0, 0).astype(np.float32), one, s, s, (7, 10))
    assert list(zip(*np.nonzero(m))) == [at] and d[at] == np.float32(2.0 * s)


def test_sparse_clip_carries_its_mask():
  rng = np.random.default_rng(3)
  clip = _planar_clip(rng)
  mask = rng.random((T, H, W)) < 0.1
  clip["disparity"] = np.where(mask, clip["disparity"], 0).astype(np.float32)
  clip["valid"] = mask
  clip["sparse"] = True
  cfg = AugmentConfig(crop_size=(24, 48))
  out = augment_clip(clip, cfg, np.random.default_rng(4))
  assert out["valid"].dtype == bool and out["valid"].shape == (T, 24, 48)
  assert out["valid"].any() and (out["disparity"][out["valid"]] > 0).all()
  assert (out["disparity"][~out["valid"]] == 0).all()
  assert out["valid"].sum() <= mask.sum()
  with pytest.raises(ValueError, match="sparse clips need `valid`"):
    augment_clip({**clip, "valid": None}, cfg, np.random.default_rng(4))


def test_yjitter_moves_only_the_right_view_by_at_most_two_rows():
  rows = np.broadcast_to(np.arange(H, dtype=np.uint8)[:, None, None], (T, H, W, 3))
  clip = {"left": rows.copy(), "right": rows.copy(), "disparity": np.ones((T, H, W), np.float32),
          "right_disparity": np.ones((T, H, W), np.float32) * rows[..., 0]}
  for yjitter in (False, True):
    cfg = dataclasses.replace(IDENTITY, yjitter=yjitter)
    shifts = set()
    for seed in range(6):
      out = augment_clip(clip, cfg, np.random.default_rng(seed))
      delta = out["right"][..., 0].astype(int) - out["left"][..., 0]
      for t in range(T):
        assert len(np.unique(delta[t])) == 1  # a pure row offset, same x0
        shifts.add(int(delta[t, 0, 0]))
        np.testing.assert_array_equal(out["right_disparity"][t], out["right"][t, ..., 0])
    if yjitter:
      assert shifts <= set(range(-2, 3)) and len(shifts) > 1
    else:
      assert shifts == {0}


def test_a_larger_yjitter_keeps_its_own_margin_so_the_right_rows_are_not_clipped():
  # +-6 px on 60-row frames cropped to 32: the left crop starts 6..22, so every right offset
  # in -6..6 fits (a 2 px margin clipped them at the edges: too few +-6 offsets, too many 0s)
  h = 60
  rows = np.broadcast_to(np.arange(h, dtype=np.uint8)[:, None, None], (1, h, 80, 3))
  clip = {"left": rows.copy(), "right": rows.copy(), "disparity": np.ones((1, h, 80), np.float32)}
  cfg = dataclasses.replace(IDENTITY, crop_size=(32, 64), spatial_prob=0.0, yjitter=True,
                            yjitter_range=6)
  starts, offsets = [], []
  for seed in range(200):
    out = augment_clip(clip, cfg, np.random.default_rng(seed))
    starts.append(int(out["left"][0, 0, 0, 0]))
    offsets.append(int(out["right"][0, 0, 0, 0]) - starts[-1])
  assert 6 <= min(starts) and max(starts) <= h - 32 - 6
  counts = np.bincount(np.asarray(offsets) + 6, minlength=13)
  assert len(counts) == 13 and counts.min() >= 5, counts  # uniform: ~15 each
  # the official +-2 keeps the official 2 px margin (the same draws as before)
  cfg2 = dataclasses.replace(cfg, yjitter_range=2)
  assert min(int(augment_clip(clip, cfg2, np.random.default_rng(s))["left"][0, 0, 0, 0])
             for s in range(200)) == 2


def test_sparse_weights_as_valid_mask_are_thresholded_as_in_the_metrics():
  clip = _planar_clip(np.random.default_rng(0))
  clip.update(sparse=True, disparity=np.full((T, H, W), 5.0, np.float32))
  cfg = dataclasses.replace(IDENTITY, spatial_prob=0.0)
  for weight, any_valid in ((0.3, False), (0.7, True)):  # 0.3 was valid (bool(0.3))
    out = augment_clip({**clip, "valid": np.full((T, H, W), weight)}, cfg,
                       np.random.default_rng(0))
    assert out["valid"].dtype == bool
    assert out["valid"].all() if any_valid else not out["valid"].any()


def test_photometric_symmetric_vs_asymmetric_brightness():
  only_brightness = dict(photometric=True, contrast=(1, 1), saturation=(1, 1), hue=(0, 0))
  colours_l = [[200, 100, 50], [90, 180, 30], [10, 60, 250]]
  colours_r = [[150, 150, 150], [240, 20, 120], [70, 70, 200]]
  clip = _uniform_clip(colours_l, colours_r)
  src = np.array(colours_l + colours_r, np.float64)
  for asym, expect_shared in ((0.0, True), (1.0, False)):
    cfg = dataclasses.replace(IDENTITY, asymmetric_prob=asym, **only_brightness)
    out = augment_clip(clip, cfg, np.random.default_rng(11))
    got = np.concatenate([out["left"][:, 0, 0], out["right"][:, 0, 0]]).astype(np.float64)
    assert (out["left"] == out["left"][:, :1, :1]).all()  # still flat
    # One shared factor f reproduces every image as trunc(f * colour) (in float32, as PIL);
    # got[0, 0] pins f down to +-0.005.
    f = got[0, 0] / src[0, 0]
    src32 = src.astype(np.float32)
    shared = any(np.array_equal(np.floor(np.clip(np.float32(f2) * src32, 0, 255)), got)
                 for f2 in np.linspace(f - 0.01, f + 0.01, 401))
    assert shared == expect_shared


def test_photometric_saturation_zero_gives_grey_and_gamma_lut():
  clip = _uniform_clip([[200, 100, 50]] * T, [[10, 60, 250]] * T)
  cfg = dataclasses.replace(IDENTITY, photometric=True, brightness=(1, 1), contrast=(1, 1),
                            saturation=(0, 0), hue=(0, 0), asymmetric_prob=0.0)
  out = augment_clip(clip, cfg, np.random.default_rng(0))
  for view in (out["left"], out["right"]):
    assert (view == view[..., :1]).all()  # R = G = B
  assert abs(int(out["left"][0, 0, 0, 0]) - round(0.299 * 200 + 0.587 * 100 + 0.114 * 50)) <= 1
  cfg = dataclasses.replace(IDENTITY, photometric=True, brightness=(1, 1), contrast=(1, 1),
                            saturation=(1, 1), hue=(0, 0), gamma=(2.0, 2.0))
  out = augment_clip(clip, cfg, np.random.default_rng(0))
  expect = [int(255.999 * (v / 255) ** 2) for v in (200, 100, 50)]
  np.testing.assert_array_equal(out["left"][0, 0, 0], expect)


def test_hue_shift_keeps_grey_and_rotates_colour():
  clip = _uniform_clip([[128, 128, 128]] * T, [[220, 30, 30]] * T)
  cfg = dataclasses.replace(IDENTITY, photometric=True, brightness=(1, 1), contrast=(1, 1),
                            saturation=(1, 1), hue=(1 / 3, 1 / 3), asymmetric_prob=0.0)
  out = augment_clip(clip, cfg, np.random.default_rng(0))
  assert (out["left"] == 128).all()
  r, g, b = (int(v) for v in out["right"][0, 0, 0])
  assert g > 150 and r < 60 and b < 60  # red turned a third of a turn: green


def _torchvision_jitter(image, jitter):
  """What the official augmentor's torchvision ColorJitter does to a PIL image with the
  draw of `jitter` (`F.adjust_*` for PIL images are ImageEnhance and PIL's 8-bit HSV)."""
  from PIL import Image, ImageEnhance  # pylint: disable=import-outside-toplevel
  img = Image.fromarray(image)
  for op in jitter.order:
    if op == 0:
      img = ImageEnhance.Brightness(img).enhance(jitter.brightness)
    elif op == 1:
      img = ImageEnhance.Contrast(img).enhance(jitter.contrast)
    elif op == 2:
      img = ImageEnhance.Color(img).enhance(jitter.saturation)
    else:
      h, s, v = img.convert("HSV").split()
      h = np.array(h, np.uint8)
      with np.errstate(over="ignore"):
        h += np.array(jitter.hue * 255).astype(np.int8).astype(np.uint8)
      img = Image.merge("HSV", (Image.fromarray(h, "L"), s, v)).convert("RGB")
  return np.array(img)


def test_colour_jitter_equals_torchvision_on_pil_images():
  # OpenCV's HSV and greyscale, used before, were up to 6 grey levels from PIL's.
  cfg = AugmentConfig(saturation=(0.0, 1.4))  # the official training script's ranges
  colours = np.stack(np.meshgrid(np.arange(0, 256, 3), np.arange(0, 256, 5),
                                 np.arange(0, 256, 7), indexing="ij"), -1)
  image = colours.reshape(-1, 86 * 4, 3).astype(np.uint8)  # 86 * 52 * 37 colours
  rng = np.random.default_rng(0)
  for _ in range(12):
    jitter = augment._Jitter(cfg, rng)  # pylint: disable=protected-access
    np.testing.assert_array_equal(jitter(image[None])[0], _torchvision_jitter(image, jitter))


def test_eraser_fills_with_frame0_left_mean():
  clip = _uniform_clip([[200, 10, 10], [0, 200, 0], [0, 0, 200]],
                       [[5, 5, 5], [6, 6, 6], [7, 7, 7]])
  cfg = dataclasses.replace(IDENTITY, eraser_prob=1.0, eraser_count=(1, 1))
  out = augment_clip(clip, cfg, np.random.default_rng(3))
  erased = 0
  for view, colours in ((out["left"], clip["left"]), (out["right"], clip["right"])):
    for t in range(T):
      px = view[t].reshape(-1, 3)
      is_fill = (px == (200, 10, 10)).all(axis=1)
      assert (is_fill | (px == colours[t, 0, 0]).all(axis=1)).all()
      erased += int(is_fill.sum() > 0 and not np.array_equal(colours[t, 0, 0], (200, 10, 10)))
  assert erased >= 3


def test_bad_inputs():
  clip = _planar_clip(np.random.default_rng(0))
  with pytest.raises(ValueError, match="uint8"):
    augment_clip({**clip, "right": clip["right"][:, :-1]}, IDENTITY, np.random.default_rng(0))
  with pytest.raises(ValueError, match="disparity is"):
    augment_clip({**clip, "disparity": clip["disparity"][:, 1:]}, IDENTITY,
                 np.random.default_rng(0))
  with pytest.raises(ValueError, match=r"cannot crop .* the crop is larger than the frames, and "
                     r"the clip was not resized \(spatial_prob=0: "):
    augment_clip(clip, dataclasses.replace(IDENTITY, crop_size=(H + 1, W), spatial_prob=0.0),
                 np.random.default_rng(0))
  with pytest.raises(ValueError, match="scale_range"):
    AugmentConfig(scale_range=(0.4, -0.2))
  for kw, match in ((dict(stretch_prob=1.5), "stretch_prob is a probability"),
                    (dict(eraser_prob=-0.1), "eraser_prob is a probability"),
                    (dict(scale_range=(float("nan"),) * 2), "scale_range must be a pair of finite"),
                    (dict(crop_size=256), "crop_size must be a pair"),
                    (dict(crop_size=(1, 2, 3)), "crop_size must be a pair"),
                    (dict(brightness=(-1.0, 1.0)), "brightness factors must be >= 0"),
                    (dict(gamma=(0.0, 1.0)), "gamma must be > 0"),
                    (dict(eraser_size=(-5, 10)), "eraser_size must be"),
                    (dict(yjitter_range=-3), "yjitter_range"),
                    (dict(scale_range=(0.0, 100.0)), "log2 scales"),
                    (dict(crop_size=(24.0, 48.0)), r"crop_size must be a pair of integers"),
                    (dict(eraser_size=(10.5, 20)), r"eraser_size must be a pair of integers"),
                    (dict(eraser_count=(1, 1.5)), r"eraser_count must be a pair of integers"),
                    (dict(yjitter_range=1.5), r"yjitter_range must be an integer"),
                    (dict(hue=(-0.7, 0.7)), r"hue must lie in \[-0.5, 0.5\]")):
    with pytest.raises(ValueError, match=match):
      AugmentConfig(**kw)
  with pytest.raises(ValueError,
                     match=r"\[T, H, W, 3\] uint8 with T, H, W >= 1, got \(2, 3, 4, 1\)"):
    gray = np.zeros((2, 3, 4, 1), np.uint8)
    augment_clip({**clip, "left": gray, "right": gray}, IDENTITY, np.random.default_rng(0))
  empty = np.zeros((2, 0, 4, 3), np.uint8)  # was "cannot convert float NaN to integer"
  with pytest.raises(ValueError, match=r"with T, H, W >= 1, got \(2, 0, 4, 3\) uint8"):
    augment_clip({"left": empty, "right": empty}, IDENTITY, np.random.default_rng(0))


def test_defaults_are_the_official_training_values():
  """docs/datasets.md section 3 (and the < 512 dense valid rule of section 0), literally:
  ColorJitter brightness and contrast 0.4, saturation [0, 1.4], hue 0.5/3.14, gamma off;
  asymmetric p = 0.2; eraser p = 0.5, 1-2 rectangles, sides [50, 100); s = 2^U(-0.2, 0.4),
  stretch p = 0.8 by 2^U(-0.2, 0.2); always resized; 256x512 crop, y-jitter +-2."""
  cfg = AugmentConfig()
  assert dataclasses.asdict(cfg) == dict(
      crop_size=(256, 512), scale_range=(-0.2, 0.4), stretch_prob=0.8, max_stretch=0.2,
      spatial_prob=1.0, photometric=True, brightness=(1 - 0.4, 1 + 0.4),
      contrast=(1 - 0.4, 1 + 0.4), saturation=(0.0, 1.4), hue=(-0.5 / 3.14, 0.5 / 3.14),
      gamma=(1.0, 1.0), gain=(1.0, 1.0), asymmetric_prob=0.2, eraser_prob=0.5,
      eraser_count=(1, 2), eraser_size=(50, 100), yjitter=True, yjitter_range=2,
      max_disparity=512.0)


@pytest.mark.parametrize("h, w", [(300, 600), (400, 560), (200, 300)])
def test_scale_is_clamped_to_the_crop_plus_eight_pixels(h, w):
  """Both scales are at least max((256 + 8) / H, (512 + 8) / W), as officially: a clip
  drawn at s = 1/2 (or stretched below the bound) still covers the crop with 8 px to spare."""
  bound = max((256 + 8) / h, (512 + 8) / w)
  assert bound > max(256 / h, 512 / w) + 0.01  # the + 8 matters on these sizes
  for stretch in (0.0, 1.0):
    cfg = AugmentConfig(scale_range=(-1.0, -1.0), stretch_prob=stretch)
    for seed in range(4):
      sx, sy = _scales(h, w, cfg, np.random.default_rng(seed))
      assert sx == sy == bound, (sx, sy, bound)


def test_stretch_is_drawn_per_axis():
  """With the stretch, sx = s * 2^U(+-0.2) and sy = s * 2^U(+-0.2) are independent draws
  (one factor for both would never change the aspect ratio); without it sx == sy."""
  ratios = []
  for seed in range(20):
    cfg = AugmentConfig(scale_range=(0.0, 0.0), stretch_prob=1.0)
    sx, sy = _scales(2000, 4000, cfg, np.random.default_rng(seed))
    assert 2 ** -0.2 <= sx <= 2 ** 0.2 and 2 ** -0.2 <= sy <= 2 ** 0.2
    ratios.append(np.log2(sx / sy))
  assert np.ptp(ratios) > 0.2  # one shared factor: all 0
  cfg = AugmentConfig(scale_range=(0.1, 0.3), stretch_prob=0.0)
  sx, sy = _scales(2000, 4000, cfg, np.random.default_rng(0))
  assert sx == sy != 1


def test_sparse_clips_get_symmetric_colour_and_no_yjitter():
  """The official sparse augmentor (KITTI) has no asymmetric jitter and a plain crop: equal
  left and right views stay equal, whatever `asymmetric_prob` and `yjitter` say (dense clips,
  the control, come out different)."""
  clip = _planar_clip(np.random.default_rng(0))
  clip["right"] = clip["left"].copy()
  clip["valid"] = np.random.default_rng(1).random((T, H, W)) < 0.3
  cfg = AugmentConfig(crop_size=(24, 48), asymmetric_prob=1.0, eraser_prob=0.0, yjitter=True)
  for seed in range(4):
    out = augment_clip(clip, cfg, np.random.default_rng(seed), sparse=True)
    np.testing.assert_array_equal(out["left"], out["right"])
    dense = augment_clip(clip, cfg, np.random.default_rng(seed), sparse=False)
    assert not np.array_equal(dense["left"], dense["right"])
  # the y-jitter alone (no colour jitter): sparse rows stay aligned, dense ones move
  cfg = dataclasses.replace(cfg, photometric=False)
  moved = 0
  for seed in range(4):
    out = augment_clip(clip, cfg, np.random.default_rng(seed), sparse=True)
    np.testing.assert_array_equal(out["left"], out["right"])
    dense = augment_clip(clip, cfg, np.random.default_rng(seed), sparse=False)
    moved += not np.array_equal(dense["left"], dense["right"])
  assert moved > 0


def test_colour_jitter_order_is_drawn_per_jitter():
  """torchvision's ColorJitter applies brightness, contrast, saturation and hue in a random
  order (randperm(4)) per draw: every order occurs, and the order changes the image."""
  rng = np.random.default_rng(0)
  orders = {tuple(int(op) for op in _Jitter(AugmentConfig(), rng).order) for _ in range(400)}
  assert len(orders) == 24
  # fixed factors: the order is all that differs between seeds
  fixed = dataclasses.replace(IDENTITY, crop_size=(H, W), spatial_prob=0.0, photometric=True,
                              brightness=(1.3, 1.3), contrast=(0.6, 0.6), saturation=(0.4, 0.4),
                              hue=(0.2, 0.2), asymmetric_prob=0.0)
  clip = _planar_clip(np.random.default_rng(0))
  outs = {augment_clip(clip, fixed, np.random.default_rng(seed))["left"].tobytes()
          for seed in range(12)}
  assert len(outs) > 3


@pytest.mark.parametrize("margin", [0, 1, 3])
def test_crop_within_two_pixels_of_the_frame_keeps_its_size(margin):
  # The y-jitter crop keeps a 2 px margin where the frame allows it; closer, the margin
  # shrinks and the crop still has the asked size, left and right alike.
  clip = _planar_clip(np.random.default_rng(0))
  cfg = dataclasses.replace(IDENTITY, crop_size=(H - margin, W - margin), spatial_prob=0.0,
                            yjitter=True)
  for seed in range(4):
    out = augment_clip(clip, cfg, np.random.default_rng(seed))
    for k in ("left", "right", "disparity", "valid"):
      assert out[k].shape[1:3] == (H - margin, W - margin), (k, out[k].shape)


def test_hsv_tables_are_built_once_by_concurrent_threads(monkeypatch):
  # grain's reader threads reach their first hue jitter together; each build peaks at
  # ~300 MB, so they must wait for one build rather than make their own.
  import threading
  import time
  builds = []

  def slow_build():
    builds.append(1)
    time.sleep(0.2)
    return ("tables",)

  monkeypatch.setattr(augment, "_HSV_TABLES", [])
  monkeypatch.setattr(augment, "_build_hsv_tables", slow_build)
  got = []
  threads = [threading.Thread(target=lambda: got.append(augment._hsv_tables())) for _ in range(4)]
  for t in threads:
    t.start()
  for t in threads:
    t.join()
  assert len(builds) == 1 and got == [("tables",)] * 4


def _coded_clip(t, h, w):
  """Dense clip whose disparity is 1000 * (row + 1) + column + 1, so that every output pixel
  names the source pixel it was cropped from (valid under the tests' max_disparity=1e9);
  flat black images."""
  ys, xs = np.mgrid[0:h, 0:w]
  disp = np.broadcast_to((1000.0 * (ys + 1) + xs + 1).astype(np.float32), (t, h, w))
  image = np.zeros((t, h, w, 3), np.uint8)
  return {"left": image, "right": image.copy(), "disparity": disp.copy(),
          "right_disparity": disp.copy()}


def test_dense_crop_corner_is_drawn_as_the_official_randint_2_to_size_minus_crop_minus_2():
  # Official y-jitter crop: y0 = randint(2, H - ch - 2), x0 = randint(2, W - cw - 2) (numpy's
  # randint excludes the high end). On 48x96 frames cropped to 40x88 both are in {2, 3, 4, 5}.
  clip = _coded_clip(2, H, W)
  cfg = dataclasses.replace(IDENTITY, spatial_prob=0.0, yjitter=True, max_disparity=1e9)
  corners = set()
  for seed in range(120):
    d = augment_clip(clip, cfg, np.random.default_rng(seed))["disparity"][0, 0, 0]
    corners.add((int(d) // 1000 - 1, int(d) % 1000 - 1))
  assert {y for y, _ in corners} == {2, 3, 4, 5}
  assert {x for _, x in corners} == {2, 3, 4, 5}
  # a y-jitter under 2 px keeps the 2 px margin (AugmentConfig.yjitter_range: max(2, it))
  cfg1 = dataclasses.replace(cfg, yjitter_range=1)
  assert {int(augment_clip(clip, cfg1, np.random.default_rng(s))["disparity"][0, 0, 0]) // 1000 - 1
          for s in range(120)} == {2, 3, 4, 5}
  # without the y-jitter (and for sparse clips): the plain randint(0, H - ch), randint(0, W - cw)
  sparse_clip = {**clip, "right_disparity": None, "valid": np.ones((2, H, W), bool)}
  for plain, c in ((dataclasses.replace(cfg, yjitter=False), clip), (cfg, sparse_clip)):
    corners = set()
    for seed in range(150):
      out = augment_clip(c, plain, np.random.default_rng(seed), sparse=c is sparse_clip)
      d = int(out["disparity"][0, 0, 0])
      corners.add((d // 1000 - 1, d % 1000 - 1))
    assert {y for y, _ in corners} == set(range(8)) == {x for _, x in corners}, sorted(corners)


def test_yjitter_offset_is_drawn_per_frame():
  # Officially `y1 = y0 + randint(-2, 3)` inside the frame loop: the frames of one clip get
  # their own offsets (one offset for the whole clip would be a different augmentation).
  clip = _coded_clip(8, H, W)
  cfg = dataclasses.replace(IDENTITY, spatial_prob=0.0, yjitter=True, max_disparity=1e9)
  for seed in range(3):
    out = augment_clip(clip, cfg, np.random.default_rng(seed))
    offsets = (out["right_disparity"][:, 0, 0] - out["disparity"][:, 0, 0]) / 1000
    assert set(offsets.tolist()) <= {-2, -1, 0, 1, 2}
    assert len(set(offsets.tolist())) > 1, offsets


def test_eraser_rectangles_corner_anywhere_in_the_frame_sides_50_to_99():
  # Officially: x0 = randint(0, W), y0 = randint(0, H), dx, dy = randint(50, 100) each, the
  # rectangle [y0:y0+dy, x0:x0+dx] (clipped by the frame). A flat right view shows the fill
  # (frame 0 left's mean colour) as one rectangle whose top-left corner is (y0, x0).
  h, w = 120, 200  # wider than high: swapped x/y ranges show
  cfg = dataclasses.replace(IDENTITY, eraser_prob=1.0, eraser_count=(1, 1))
  corners, sides = [], []
  for seed in range(150):
    left = np.full((1, h, w, 3), (200, 10, 10), np.uint8)
    right = np.full((1, h, w, 3), 5, np.uint8)
    augment._erase(left, right, cfg,  # pylint: disable=protected-access
                   np.random.default_rng(seed))
    ys, xs = np.nonzero((right[0] == (200, 10, 10)).all(-1))
    assert ys.size > 0  # p = 1: every right view is erased, inside the frame
    y0, x0, y1, x1 = ys.min(), xs.min(), ys.max() + 1, xs.max() + 1
    assert ys.size == (y1 - y0) * (x1 - x0)  # one filled rectangle
    corners.append((y0, x0))
    sides += [s for s, end, size in ((y1 - y0, y1, h), (x1 - x0, x1, w)) if end < size]
  # x0 reaches past the frame's height (x drawn over the width), and both reach the far edges
  # (uniform over the whole image, not only where a 50 px side fits)
  assert max(x for _, x in corners) >= w - 20 and max(y for y, _ in corners) >= h - 20
  assert min(sides) >= 50 and max(sides) == 99, (min(sides), max(sides))


def test_gain_alone_scales_through_the_gamma_lut():
  # torchvision adjust_gamma on PIL: int(255.999 * gain * (v / 255) ** gamma), also for gamma 1
  clip = _uniform_clip([[200, 100, 50]] * T, [[10, 60, 250]] * T)
  cfg = dataclasses.replace(IDENTITY, photometric=True, brightness=(1, 1), contrast=(1, 1),
                            saturation=(1, 1), hue=(0, 0), gain=(0.5, 0.5))
  out = augment_clip(clip, cfg, np.random.default_rng(0))
  np.testing.assert_array_equal(out["left"][0, 0, 0], [100, 50, 25])  # int(255.999*.5*v/255)
  np.testing.assert_array_equal(out["right"][0, 0, 0], [5, 30, 125])


def test_sparse_points_on_the_far_edges_are_dropped_and_collisions_keep_the_last():
  # Official resize_sparse_flow_map keeps 0 < x < W1 and 0 < y < H1 (rounded, scaled) and
  # writes the points in row-major order (the last write to a pixel stays).
  disp = np.zeros((4, 6), np.float32)
  valid = np.zeros((4, 6), bool)
  for (y, x, v) in ((1, 5, 3.0), (3, 2, 5.0), (1, 1, 7.0), (2, 4, 8.0), (2, 5, 9.0)):
    disp[y, x], valid[y, x] = v, True
  # sx = sy = 2 into (6, 10): (1,5) -> x = 10 = W1 dropped; (3,2) -> y = 6 = H1 dropped;
  # (1,1) -> (2, 2); (2,4) -> (4, 8); (2,5) -> x = 10 dropped. sx = sy = 0.5 into (2, 3):
  # (1,5), (1,1) -> y = 0 dropped; (3,2) -> y = 2 = H1 dropped; (2,4) -> (1, 2) and
  # (2,5) -> (1, round(2.5) = 2), the same pixel: the later point's 9 * 0.5 stays.
  d, m = _resize_sparse(disp, valid, 2.0, 2.0, (6, 10))
  assert list(zip(*np.nonzero(m))) == [(2, 2), (4, 8)] and (d[2, 2], d[4, 8]) == (14.0, 16.0)
  d, m = _resize_sparse(disp, valid, 0.5, 0.5, (2, 3))
  assert list(zip(*np.nonzero(m))) == [(1, 2)] and d[1, 2] == 4.5  # 9 * 0.5, not 8 * 0.5


def test_asymmetric_jitter_works_on_each_image_own_pixels():
  # With p = 1 every image gets its own draw of its own pixels: identity ranges (every
  # ColorJitter operation left out) give the input back, views and frames in place.
  clip = _uniform_clip([[200, 100, 50], [90, 180, 30], [10, 60, 250]],
                       [[150, 150, 150], [240, 20, 120], [70, 70, 200]])
  cfg = dataclasses.replace(IDENTITY, photometric=True, brightness=(1, 1), contrast=(1, 1),
                            saturation=(1, 1), hue=(0, 0), asymmetric_prob=1.0)
  out = augment_clip(clip, cfg, np.random.default_rng(0))
  np.testing.assert_array_equal(out["left"], clip["left"][:, 4:-4, 4:-4])
  np.testing.assert_array_equal(out["right"], clip["right"][:, 4:-4, 4:-4])


def test_eraser_fill_is_the_truncated_mean_colour():
  # Official: `seq[i][cam][...] = np.mean(seq[0][0].reshape(-1, 3), axis=0)`, a float mean
  # written into uint8 (truncated): half 0, half 255 is 127.5 -> 127; 1/3 of 200 -> 66.
  left = np.zeros((1, 60, 90, 3), np.uint8)
  left[0, :30] = (255, 255, 0)
  left[0, :20, :, 2] = 200
  before = left.copy()
  cfg = dataclasses.replace(IDENTITY, eraser_prob=1.0, eraser_count=(1, 1))
  # frame 0's left is the first image erased: its fill is the mean of the unerased image
  augment._erase(left, np.zeros_like(left), cfg,  # pylint: disable=protected-access
                 np.random.default_rng(0))
  filled = left[0][(left[0] != before[0]).any(-1)]
  assert len(filled) > 0 and (filled == (127, 127, 66)).all(), np.unique(filled, axis=0)


def test_stretch_factors_span_both_directions_on_each_axis():
  # sx = s * 2^U(-0.2, 0.2) and sy = s * 2^U(-0.2, 0.2): each axis both shrinks and grows.
  cfg = AugmentConfig(scale_range=(0.0, 0.0), stretch_prob=1.0)
  logs = np.log2([_scales(2000, 4000, cfg, np.random.default_rng(seed)) for seed in range(40)])
  assert (np.abs(logs) <= 0.2).all()
  assert (logs.min(0) < -0.1).all() and (logs.max(0) > 0.1).all(), logs


def test_dense_valid_rule_keeps_negative_and_drops_zero_and_the_cut():
  # Official (video_datasets.py, dense): valid = |d| < 512 and d != 0 on the final disparity;
  # the sign does not matter, and `max_disparity` moves the cut.
  clip = _planar_clip(np.random.default_rng(0))
  clip["disparity"][:, :, :] = np.array([-5.0, 0.0, 511.5, 512.0, -600.0, 30.0] * (W // 6),
                                        np.float32)
  out = augment_clip(clip, IDENTITY, np.random.default_rng(0))
  kinds = {float(d): bool(v) for d, v in zip(out["disparity"][0, 0], out["valid"][0, 0])}
  assert kinds == {-5.0: True, 0.0: False, 511.5: True, 512.0: False, -600.0: False,
                   30.0: True}
  out = augment_clip(clip, dataclasses.replace(IDENTITY, max_disparity=30.0),
                     np.random.default_rng(0))
  kinds = {float(d): bool(v) for d, v in zip(out["disparity"][0, 0], out["valid"][0, 0])}
  assert kinds == {-5.0: True, 0.0: False, 511.5: False, 512.0: False, -600.0: False,
                   30.0: False}


def test_sparse_weight_of_exactly_one_half_is_invalid():
  # AugmentConfig/augment_clip: weights count where > 0.5, as the metrics' `m > 0.5`
  clip = _planar_clip(np.random.default_rng(0))
  clip.update(sparse=True, disparity=np.full((T, H, W), 5.0, np.float32),
              valid=np.full((T, H, W), 0.5))
  out = augment_clip(clip, dataclasses.replace(IDENTITY, spatial_prob=0.0),
                     np.random.default_rng(0))
  assert not out["valid"].any()


def test_each_jitter_factor_is_drawn_over_its_own_whole_range():
  # torchvision ColorJitter draws every factor uniformly in its own [min, max] (brightness
  # 0.4 is [0.6, 1.4], not [1, 1.4]); distinct ranges show a factor drawn from another's.
  ranges = dict(brightness=(0.6, 1.4), contrast=(0.2, 0.3), saturation=(0.0, 1.4),
                hue=(-0.5 / 3.14, 0.5 / 3.14), gamma=(0.5, 0.7), gain=(1.1, 1.3))
  cfg = AugmentConfig(**ranges)
  rng = np.random.default_rng(0)
  draws = [_Jitter(cfg, rng) for _ in range(200)]
  for name, (lo, hi) in ranges.items():
    values = np.array([getattr(j, name) for j in draws])
    span = hi - lo
    assert lo <= values.min() < lo + 0.1 * span and hi - 0.1 * span < values.max() <= hi, name


def test_sparse_mask_is_carried_through_the_resize_not_read_off_the_disparity():
  # Official resize_sparse_flow_map scatters the valid flags themselves: a valid point keeps
  # its flag whatever its value (here 0 px everywhere), only its place changes.
  clip = _planar_clip(np.random.default_rng(0))
  clip.update(sparse=True, disparity=np.zeros((T, H, W), np.float32),
              valid=np.ones((T, H, W), bool))
  cfg = dataclasses.replace(IDENTITY, crop_size=(24, 48), scale_range=(-0.3, -0.3))
  out = augment_clip(clip, cfg, np.random.default_rng(0))  # s = 0.81 > (24 + 8) / 48
  assert (out["disparity"] == 0).all() and out["valid"].mean() > 0.9


def test_right_ground_truth_is_resized_and_cropped_as_the_left():
  # Officially every GT map of a frame goes through the same resize (times sx) and crop:
  # with equal left and right GT and no y-jitter they stay equal.
  clip = _planar_clip(np.random.default_rng(0))
  clip["right_disparity"] = clip["disparity"].copy()
  cfg = AugmentConfig(crop_size=(24, 48), scale_range=(0.2, 0.4), photometric=False,
                      eraser_prob=0.0, yjitter=False)
  for seed in range(3):
    out = augment_clip(clip, cfg, np.random.default_rng(seed))
    np.testing.assert_array_equal(out["right_disparity"], out["disparity"])
    np.testing.assert_array_equal(out["right_valid"], out["valid"])


def _same_noise_clip(seed):
  """Every frame and both views the same random image; disparity = its red channel."""
  img = np.random.default_rng(seed).integers(1, 256, (H, W, 3), dtype=np.uint8)
  left = np.broadcast_to(img, (T, H, W, 3)).copy()
  return {"left": left, "right": left.copy(), "disparity": left[..., 0].astype(np.float32)}


@pytest.mark.parametrize("seed", range(3))
def test_one_crop_window_is_shared_by_every_frame(seed):
  # Step 4: the crop (y0, x0) is drawn once and shared by all frames (no y-jitter here).
  out = augment_clip(_same_noise_clip(seed), IDENTITY, np.random.default_rng(seed))
  for k in ("left", "right", "disparity"):
    for t in range(1, T):
      np.testing.assert_array_equal(out[k][t], out[k][0], err_msg=f"{k} frame {t}")


def test_dense_disparity_is_resized_bilinearly_as_the_images_and_times_sx():
  # Step 3: images and dense disparity both get cv2's bilinear resize, disparity times sx;
  # with s = 2 exactly (no stretch), a disparity equal to the red channel stays 2x it
  # (up to the uint8 rounding of the image); nearest-neighbour would be far off on noise.
  cfg = dataclasses.replace(IDENTITY, scale_range=(1.0, 1.0))
  out = augment_clip(_same_noise_clip(0), cfg, np.random.default_rng(0))
  assert out["left"].shape[1:3] == (H - 8, W - 8)
  err = np.abs(out["disparity"] / 2 - out["left"][..., 0])
  assert err.max() <= 1.0, err.max()


def test_asymmetric_jitter_draws_for_every_frame_and_view_and_symmetric_shares_one():
  # Step 1: with asymmetric_prob = 1 each of the 2T images gets its own parameters (two
  # identical inputs come out different); otherwise one set for all (they stay identical).
  clip = _same_noise_clip(1)
  for asym in (0.0, 1.0):
    cfg = dataclasses.replace(IDENTITY, photometric=True, asymmetric_prob=asym)
    out = augment_clip(clip, cfg, np.random.default_rng(3))
    images = np.concatenate([out["left"], out["right"]])
    for i in range(2 * T):
      for j in range(i):
        assert np.array_equal(images[i], images[j]) == (asym == 0.0), (asym, i, j)


def test_symmetric_contrast_blends_with_the_mean_grey_of_the_whole_clip():
  # Step 1: symmetric jitter treats the 2T images as one stacked image, so the contrast
  # mean is over the whole clip: a flat image is pulled towards the clip's grey (blending
  # with its own mean would leave a flat image unchanged).
  colours_l = [[250, 250, 250], [200, 200, 200], [150, 150, 150]]
  colours_r = [[10, 10, 10], [60, 60, 60], [110, 110, 110]]  # clip mean grey 130
  cfg = dataclasses.replace(IDENTITY, photometric=True, asymmetric_prob=0.0, contrast=(0.5, 0.5),
                            brightness=(1, 1), saturation=(1, 1), hue=(0, 0))
  out = augment_clip(_uniform_clip(colours_l, colours_r), cfg, np.random.default_rng(0))
  got = np.concatenate([out["left"][:, 0, 0, 0], out["right"][:, 0, 0, 0]]).astype(int)
  src = np.array([c[0] for c in colours_l + colours_r])
  np.testing.assert_allclose(got, 130 + 0.5 * (src - 130), atol=1)

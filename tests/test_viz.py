"""Colour maps, videos, point clouds and disparity file formats (round trips)."""

import math
import os
import re
import struct
import threading
import warnings

import cv2
import numpy as np
import pytest

from sav_jax import metrics, viz
from sav_jax._checks import OVERSHOOT_HIGH, OVERSHOOT_LOW


@pytest.fixture()
def disp():
  rng = np.random.default_rng(0)
  d = rng.uniform(0.5, 200.0, (13, 17)).astype(np.float32)
  d[0, 0], d[3, 4], d[5, 6] = 0.0, -2.0, np.nan
  return d


def test_png16_round_trip(tmp_path, disp):
  viz.write_png16(tmp_path / "d.png", disp)
  raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
  assert raw.dtype == np.uint16
  back, valid = viz.read_png16(tmp_path / "d.png")
  ok = np.isfinite(disp) & (disp > 0)
  np.testing.assert_array_equal(valid, ok)
  np.testing.assert_array_equal(back[ok], np.round(disp[ok].astype(np.float64) * 256) / 256)
  assert np.all(back[~ok] == 0)
  assert np.abs(back[ok] - disp[ok]).max() <= 1 / 512 + 1e-6
  assert viz.write_png16(tmp_path / "d.png", disp) == 0  # nothing saturated
  big = np.array([[300.0, viz.PNG16_MAX_DISPARITY], [256.0, 1.0]])
  assert viz.write_png16(tmp_path / "big.png", big) == 2  # 300 and 256 saturate, still valid
  back, valid = viz.read_png16(tmp_path / "big.png")
  np.testing.assert_array_equal(back, [[65535 / 256] * 2, [65535 / 256, 1.0]])
  assert valid.all()


def test_png16_keeps_tiny_positive_disparities_valid(tmp_path):
  """round(256 d) of a positive d below 1/512 px is 0, the invalid code: such values are
  stored as 1 (1/256 px) and read back valid; 0 and negative values stay invalid."""
  viz.write_png16(tmp_path / "t.png", np.array([[1e-3, 1 / 1024, 0.0, -1e-3]], np.float32))
  raw = cv2.imread(str(tmp_path / "t.png"), cv2.IMREAD_UNCHANGED)
  np.testing.assert_array_equal(raw, [[1, 1, 0, 0]])
  back, valid = viz.read_png16(tmp_path / "t.png")
  np.testing.assert_array_equal(back, [[1 / 256, 1 / 256, 0, 0]])
  np.testing.assert_array_equal(valid, [[True, True, False, False]])


@pytest.mark.parametrize("shape", [(13, 17), (6, 5, 3)])
def test_pfm_round_trip(tmp_path, shape):
  a = np.random.default_rng(1).normal(size=shape).astype(np.float32)
  viz.write_pfm(tmp_path / "a.pfm", a)
  np.testing.assert_array_equal(viz.read_pfm(tmp_path / "a.pfm"), a)
  with open(tmp_path / "a.pfm", "rb") as fh:
    assert fh.readline().strip() == (b"Pf" if len(shape) == 2 else b"PF")
    assert fh.readline().split() == [str(shape[1]).encode(), str(shape[0]).encode()]
    assert float(fh.readline()) < 0  # little-endian
    first_row_stored = np.frombuffer(fh.read(4 * shape[1] * (shape[2] if len(shape) == 3 else 1)),
                                     "<f4")
  np.testing.assert_array_equal(first_row_stored, a[-1].ravel())  # bottom row first


def test_pfm_big_endian(tmp_path):
  a = np.arange(6, dtype=np.float32).reshape(2, 3)
  with open(tmp_path / "b.pfm", "wb") as fh:
    fh.write(b"Pf\n3 2\n1.0\n" + a[::-1].astype(">f4").tobytes())
  np.testing.assert_array_equal(viz.read_pfm(tmp_path / "b.pfm"), a)


@pytest.mark.parametrize("shape", [(13, 17), (6, 5, 3)])
def test_exr_round_trip(tmp_path, shape):
  a = np.random.default_rng(2).normal(size=shape).astype(np.float32)
  viz.write_exr(tmp_path / "a.exr", a)
  np.testing.assert_array_equal(viz.read_exr(tmp_path / "a.exr"), a)


def test_depth_and_points(tmp_path):
  d = np.array([[10.0, 0.0, 5.0], [-1.0, 20.0, np.inf]], np.float32)
  z = viz.depth_from_disparity(d, fx=100.0, baseline=0.5)
  np.testing.assert_allclose(z, [[5.0, 0.0, 10.0], [0.0, 2.5, 0.0]])
  rgb = np.arange(18, dtype=np.uint8).reshape(2, 3, 3)
  xyz, col = viz.disparity_to_points(d, rgb, fx=100.0, fy=50.0, cx=1.0, cy=0.5, baseline=0.5)
  assert len(xyz) == 3  # d <= 0 and inf dropped
  np.testing.assert_allclose(xyz[0], [(0 - 1.0) * 5 / 100, (0 - 0.5) * 5 / 50, 5.0], rtol=1e-6)
  np.testing.assert_allclose(xyz[2], [0.0, (1 - 0.5) * 2.5 / 50, 2.5], rtol=1e-6)
  np.testing.assert_array_equal(col, rgb[[0, 0, 1], [0, 2, 1]])
  # Middlebury's doffs: Z = fx B / (d + doffs); d + doffs <= 0 is invalid
  np.testing.assert_allclose(viz.depth_from_disparity(d, 100.0, 0.5, doffs=-5.0),
                             [[10.0, 0.0, 0.0], [0.0, 50 / 15, 0.0]], rtol=1e-6)
  calib = dict(fx=100.0, fy=50.0, cx=1.0, cy=0.5, baseline=0.5)
  xyz, _ = viz.disparity_to_points(d, rgb, **calib, doffs=-5.0)
  np.testing.assert_allclose(xyz[:, 2], [10.0, 50 / 15], rtol=1e-6)
  # weights count above 0.5 (as in colorize and the metrics); NaN weights are invalid
  weights = np.array([[0.3, 1.0, 0.6], [1.0, np.nan, 1.0]])
  xyz, col = viz.disparity_to_points(d, rgb, **calib, valid=weights)
  np.testing.assert_array_equal(col, rgb[[0], [2]])
  xyz, _ = viz.disparity_to_points(d, rgb, **calib, valid=weights > 0.1)  # bool as given
  np.testing.assert_allclose(xyz[:, 2], [5.0, 10.0])
  # max_depth drops the far points (depths 5, 10, 2.5 here)
  xyz, col = viz.disparity_to_points(d, rgb, **calib, max_depth=5.0)
  np.testing.assert_allclose(xyz[:, 2], [5.0, 2.5])
  for bad in (0.0, -1.0, np.inf, np.nan):
    with pytest.raises(ValueError, match="max_depth must be a finite positive number"):
      viz.disparity_to_points(d, rgb, **calib, max_depth=bad)
  # Disparities so small that float32 depth (or x, y) overflows: no depth, no point.
  tiny = np.array([[1e-40, 1e-36, 10.0]], np.float32)
  with np.errstate(all="raise"):  # and no overflow warning on the way
    z = viz.depth_from_disparity(tiny, fx=100.0, baseline=0.5)
    assert z[0, 0] == 0 and np.isfinite(z).all() and z[0, 1] > 1e37
    xyz, _ = viz.disparity_to_points(tiny, rgb[:1], **calib)
    assert len(xyz) == 2 and np.isfinite(xyz).all()
    with pytest.warns(UserWarning, match="principal point"):  # (far outside the frame)
      xyz, _ = viz.disparity_to_points(tiny, rgb[:1], **dict(calib, cx=-1000.0))  # x = 10 z: inf
  np.testing.assert_allclose(xyz, [[(2 + 1000.0) * 5 / 100, (0 - 0.5) * 5 / 50, 5.0]], rtol=1e-6)


def test_ply_header_count_and_values(tmp_path):
  rng = np.random.default_rng(3)
  xyz = rng.normal(size=(57, 3)).astype(np.float32)
  rgb = rng.integers(0, 256, (57, 3), dtype=np.uint8)
  assert viz.write_ply(tmp_path / "p.ply", xyz, rgb) == 57
  data = (tmp_path / "p.ply").read_bytes()
  header, body = data.split(b"end_header\n", 1)
  lines = header.decode().splitlines()
  assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 57"]
  assert lines[3:] == ["property float x", "property float y", "property float z",
                       "property uchar red", "property uchar green", "property uchar blue"]
  assert len(body) == 57 * 15
  back_xyz, back_rgb = viz.read_ply(tmp_path / "p.ply")
  np.testing.assert_array_equal(back_xyz, xyz)
  np.testing.assert_array_equal(back_rgb, rgb)
  # comments (the axes and unit) go after the format line; read_ply skips them
  assert viz.write_ply(tmp_path / "c.ply", xyz, rgb, ["axes: x right", "unit: m"]) == 57
  header = (tmp_path / "c.ply").read_bytes().split(b"end_header\n", 1)[0].decode()
  assert header.splitlines()[:5] == ["ply", "format binary_little_endian 1.0",
                                     "comment axes: x right", "comment unit: m",
                                     "element vertex 57"]
  np.testing.assert_array_equal(viz.read_ply(tmp_path / "c.ply")[0], xyz)
  for bad in ("two\nlines", "caf\u00e9"):  # would break the header / is not ASCII
    with pytest.raises(ValueError, match="comment must be one line of printable ASCII"):
      viz.write_ply(tmp_path / "bad.ply", xyz, rgb, [bad])
  assert not (tmp_path / "bad.ply").exists()


def _raises_within(seconds, exc, match, fn, *args):
  """`fn(*args)` raises `exc` matching `match`, in a thread (an endless loop fails, not hangs)."""
  caught = []

  def target():
    try:
      fn(*args)
    except Exception as e:  # pylint: disable=broad-except
      caught.append(e)

  thread = threading.Thread(target=target, daemon=True)
  thread.start()
  thread.join(seconds)
  assert not thread.is_alive(), f"{fn.__name__}{args} still running after {seconds} s"
  assert caught, f"{fn.__name__}{args} raised nothing"
  assert isinstance(caught[0], exc), repr(caught[0])
  assert re.search(match, str(caught[0])), str(caught[0])


@pytest.mark.parametrize("content, match", [
    (b"Pf\n", "malformed PFM header"),  # used to loop forever
    (b"Pf\nabc def\n-1\n" + bytes(8), "malformed PFM header"),
    (b"Pf\n2\n-1\n" + bytes(8), "malformed PFM header"),
    (b"Pf\n2 1\n", "malformed PFM header"),
    (b"Pf\n-2 2\n-1\n" + bytes(16), "malformed PFM header"),
    (b"Pf\n2 2\n-1\n" + bytes(8), r"truncated PFM file \(8 bytes of data, 16 expected\)"),
    (b"P6\n2 2\n255\n" + bytes(12), "not a PFM file"),
    (b"Pf\n" + b"9" * 5000 + b" 2\n-1\n" + bytes(8), "malformed PFM header")],  # int(): no file
    ids=["truncated_header", "letters", "one_dim", "no_scale", "negative", "short", "not_pfm",
         "5000_digits"])
def test_bad_pfm_names_the_file(tmp_path, content, match):
  path = tmp_path / "bad.pfm"
  path.write_bytes(content)
  _raises_within(10, ValueError, f"{match}.*bad.pfm", viz.read_pfm, path)


def test_missing_and_corrupt_disparity_files_name_the_file(tmp_path):
  junk = tmp_path / "junk.bin"
  junk.write_bytes(bytes(range(256)) * 4)
  for reader in (viz.read_pfm, viz.read_exr, viz.read_png16):
    with pytest.raises(FileNotFoundError, match="missing.bin"):
      reader(tmp_path / "missing.bin")
    with pytest.raises(ValueError, match="junk.bin"):
      reader(junk)
  with pytest.raises(FileNotFoundError, match="missing.ply"):
    viz.read_ply(tmp_path / "missing.ply")
  from sav_jax.tools import video_io  # pylint: disable=import-outside-toplevel
  np.save(tmp_path / "objects.npy", np.array([{}], dtype=object), allow_pickle=True)
  with pytest.raises(ValueError, match="objects.npy"):  # never unpickled
    video_io.read_map(tmp_path / "objects.npy")
  with pytest.raises(ValueError, match="junk.bin: not a PLY file"):
    viz.read_ply(junk)
  cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((2, 3, 3), np.uint8))
  with pytest.raises(ValueError, match=r"1-channel 16-bit PNG, got uint8 .*rgb.png"):
    viz.read_png16(tmp_path / "rgb.png")
  viz.write_exr(tmp_path / "y.exr", np.ones((2, 3), np.float32))
  with pytest.raises(ValueError, match="y.exr has no channel 'Z'"):
    viz.read_exr(tmp_path / "y.exr", "Z")
  good = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
  props = (b"property float x\nproperty float y\nproperty float z\n"
           b"property uchar red\nproperty uchar green\nproperty uchar blue\n")
  for name, content, match in (
      ("latin.ply", good + b"comment caf\xe9\n" + props + b"end_header\n" + bytes(15), "ASCII"),
      ("nohdr.ply", good + props, "no end_header"),
      ("novert.ply", b"ply\nformat binary_little_endian 1.0\nend_header\n", "element vertex"),
      ("magic.ply", b"plyx\n" + good[4:] + props + b"end_header\n" + bytes(15), "not a PLY file"),
      ("faces.ply", good.replace(b"vertex", b"face") + props + b"end_header\n" + bytes(15),
       "element vertex"),
      ("normals.ply", good + props + b"property float nx\nend_header\n" + bytes(19),
       "vertex properties"),
      ("short.ply", good + props + b"end_header\n" + bytes(14), "header says 1 vertices")):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ValueError, match=f"{name}.*{match}"):
      viz.read_ply(tmp_path / name)


def test_write_ply_refuses_bad_shapes_and_colours(tmp_path):
  path = tmp_path / "p.ply"
  xyz, rgb = np.zeros((4, 5, 3), np.float32), np.full((4, 5, 3), 7.0)
  assert viz.write_ply(path, xyz, rgb) == 20  # [..., 3] is flattened; floats 0..255 rounded
  np.testing.assert_array_equal(viz.read_ply(path)[1], 7)
  path.unlink()
  for bad_xyz, bad_rgb, match in (
      (np.zeros((3, 2)), np.zeros((3, 2)), r"xyz must be \[N, 3\].*shape \(3, 2\)"),
      (np.array([["a", "b", "c"]]), np.zeros((1, 3)), "dtype <U1"),
      (np.zeros((2, 3)), np.zeros((3, 3)), r"colors of shape \(3, 3\) do not match xyz \(2, 3\)"),
      (np.zeros((2, 3)), np.zeros((3, 2)), r"colors of shape \(3, 2\) do not match xyz \(2, 3\)"),
      (np.zeros((1, 3)), np.full((1, 3), 400.0), r"values 400\.\.400 outside 0\.\.255"),
      (np.zeros((1, 3)), np.full((1, 3), -1), r"values -1\.\.-1 outside 0\.\.255"),
      (np.array([[0, 0, 1], [np.nan, 0, 1], [1e39, 0, 1]]), np.zeros((3, 3)),
       r"2 of 3 points are not finite in float32 .*, the first at index 1")):
    with pytest.raises(ValueError, match=match):
      viz.write_ply(path, bad_xyz, bad_rgb)
  assert not path.exists()  # refused before the file is created


def test_colorize_fixed_range_is_temporally_stable():
  video = np.stack([np.full((4, 6), 10.0), np.full((4, 6), 20.0)]).astype(np.float32)
  video[1, 0, 0] = 10.0
  rgb = viz.colorize(video)  # one range for the whole video
  assert rgb.shape == (2, 4, 6, 3) and rgb.dtype == np.uint8
  np.testing.assert_array_equal(rgb[0, 0, 0], rgb[1, 0, 0])  # same value -> same colour
  assert not np.array_equal(rgb[0, 1, 1], rgb[1, 1, 1])
  fixed = viz.colorize(video[1], vmin=10.0, vmax=20.0)
  np.testing.assert_array_equal(fixed, rgb[1])
  assert viz.disparity_range(video) == (10.0, 20.0)
  bad = viz.colorize(np.array([[0.0, np.nan, 5.0]]), 0.0, 10.0)
  np.testing.assert_array_equal(bad[0, :2], [viz.INVALID_COLOR] * 2)
  with pytest.raises(ValueError, match="colour map"):
    viz.colorize(video, cmap="nope")


def test_colorize_is_rgb_with_white_invalid_pixels_by_default():
  """The colour map comes out RGB (OpenCV's is BGR): inferno runs from (0, 0, 4) at vmin to
  (252, 255, 164) at vmax; invalid pixels are white by default."""
  rgb = viz.colorize(np.array([[1.0, 2.0, 0.0]], np.float32), 1.0, 2.0)
  assert [tuple(c) for c in rgb[0]] == [(0, 0, 4), (252, 255, 164), (255, 255, 255)]
  assert viz.INVALID_COLOR == (255, 255, 255)


def test_disparity_range_ignores_non_positive_disparities():
  """Only d > 0 sets the colour range: 0 (no disparity) and negative values do not."""
  assert viz.disparity_range(np.array([[0.0, -1.0, 5.0, 10.0]], np.float32)) == (5.0, 10.0)


def test_side_by_side_and_video(tmp_path):
  left = np.zeros((3, 9, 7, 3), np.uint8)
  colour = viz.colorize(np.ones((3, 9, 7), np.float32) * np.arange(3)[:, None, None] + 1)
  frames = viz.side_by_side(left, colour)
  assert frames.shape == (3, 9, 14, 3)
  viz.write_video(tmp_path / "v.mp4", frames, fps=5)
  cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
  count = 0
  while True:
    ok, frame = cap.read()
    if not ok:
      break
    assert frame.shape == (10, 14, 3)  # odd height padded to even
    count += 1
  assert count == 3
  # Wider than MPEG-4 allows (a side-by-side of 4096-wide frames, 8200 here): scaled to fit
  # (OpenCV could not open the writer: an OSError after a whole `sav-jax infer` run).
  wide = np.zeros((2, 20, 8200, 3), np.uint8)
  wide[:, :, 4100:] = 255
  with pytest.warns(UserWarning, match=r"frames of 20x8200 are scaled to 19x8190"):
    viz.write_video(tmp_path / "wide.mp4", iter(wide), fps=5)
  cap = cv2.VideoCapture(str(tmp_path / "wide.mp4"))
  ok, frame = cap.read()
  assert ok and frame.shape == (20, 8190, 3)
  assert frame[5, :4000].max() < 40 and frame[5, 4200:8000].min() > 215  # the content, scaled
  # one image [H, W, 3]: its rows were taken for frames ("frame 0 has shape (14, 3)")
  with pytest.raises(ValueError, match=r"one image of shape \(9, 14, 3\) \(a video of one "):
    viz.write_video(tmp_path / "one.mp4", frames[0])


def test_a_failed_video_leaves_the_file_it_would_replace(tmp_path):
  # An iterator's bad frame truncated the existing file, then deleted it: neither was left.
  keep = tmp_path / "keep.mp4"
  keep.write_text("precious")
  frames = iter([np.zeros((8, 8, 3), np.uint8), np.zeros((5, 5, 3), np.uint8)])
  with pytest.raises(ValueError, match="frame 1 has shape"):
    viz.write_video(keep, frames)
  assert keep.read_text() == "precious" and sorted(tmp_path.iterdir()) == [keep]
  viz.write_video(keep, np.zeros((2, 8, 8, 3), np.uint8))  # a complete one replaces it
  assert cv2.VideoCapture(str(keep)).read()[0] and sorted(tmp_path.iterdir()) == [keep]
  # Float 0..1 frames: one warning per video, not one per frame (a 300-frame run's flood).
  with pytest.warns(UserWarning) as record:
    viz.write_video(tmp_path / "w.mp4", iter(np.full((6, 8, 8, 3), 0.5, np.float32)))
  assert len(record) == 1 and "multiply 0..1 images by 255" in str(record[0].message)
  assert record[0].filename == __file__


def test_bad_images_and_parameters_are_refused_before_writing(tmp_path):
  # Floats in 0..255 are rounded (a resize's overshoot clipped); beyond, NaN, or a wrong layout
  # is an error.
  np.testing.assert_array_equal(viz.side_by_side(np.full((2, 2, 3), 9.6, np.float32)), 10)
  for bad, match in ((np.full((2, 2, 3), 400.0), r"values 400\.\.400 outside 0\.\.255"),
                     (np.full((2, 2, 3), np.nan), "NaN or inf"),
                     (np.full((2, 2, 3), 1000, np.uint16), "16-bit")):
    with pytest.raises(ValueError, match=match):
      viz.side_by_side(bad)
  with pytest.warns(UserWarning, match="multiply 0..1 images by 255") as record:
    viz.side_by_side(np.full((2, 2, 3), 0.8, np.float32))
  assert {w.filename for w in record} == {__file__}
  with pytest.raises(ValueError, match="does not match the first"):
    viz.side_by_side(np.zeros((4, 5, 3), np.uint8), np.zeros((3, 5, 3), np.uint8))
  video = tmp_path / "v.mp4"
  with pytest.raises(ValueError, match=r"frame 0 has shape \(8, 8\); expected RGB"):
    viz.write_video(video, np.zeros((2, 8, 8), np.uint8))
  with pytest.raises(FileNotFoundError, match=r"v.mp4: the folder .*missing does not exist"):
    viz.write_video(tmp_path / "missing" / "v.mp4", np.zeros((2, 8, 8, 3), np.uint8))
  for fps in (0, 100000, 0.001):  # outside what the MPEG-4 writer opens with
    with pytest.raises(ValueError, match=r"fps must be a number from 0\.01 to 65535"):
      viz.write_video(video, np.zeros((2, 8, 8, 3), np.uint8), fps=fps)
  assert not video.exists()
  for lo, hi in ((3.0, 1.0), (float("nan"), 1.0)):
    with pytest.raises(ValueError, match="finite vmin < vmax"):
      viz.colorize(np.ones((2, 2)), lo, hi)
  ramp = np.arange(1, 7, dtype=np.float32).reshape(2, 3)
  assert viz.disparity_range(ramp, np.array([[0.2, 0.9, 1], [0, 0, 0.6]])) == (2.0, 6.0)
  with pytest.raises(ValueError, match=r"valid has shape \(3, 2\); expected the disparity's"):
    viz.disparity_range(ramp, np.ones((3, 2), bool))
  for bad in ((100, 0), (50,), "ab", (1, 2, 3), (0, "x")):  # (tracebacks from unpacking)
    with pytest.raises(ValueError, match="percentiles must be"):
      viz.disparity_range(ramp, percentiles=bad)
  for name, kw, match in (("x.png", {}, "write_exr writes OpenEXR files"),
                          ("x.exr", {"channel": ""}, "channel must be a non-empty"),
                          ("x.exr", {"channel": 5}, "channel must be a non-empty")):
    with pytest.raises(ValueError, match=match):  # (EXR bytes written into x.png before)
      viz.write_exr(tmp_path / name, ramp, **kw)
  assert not (tmp_path / "x.png").exists() and not (tmp_path / "x.exr").exists()
  with pytest.raises(ValueError, match="fps must be a number from 0.01 to 65535, got '10'"):
    viz.check_fps("10")
  with pytest.raises(ValueError, match="fx must be a finite positive number, got '10'"):
    viz.check_intrinsics(fx="10")
  assert viz.colorize(np.zeros((0, 4, 4)), 0.0, 1.0).shape == (0, 4, 4, 3)
  disp, rgb = np.full((4, 5), 2.0, np.float32), np.zeros((4, 5, 3), np.uint8)
  calib = dict(fx=10.0, fy=10.0, cx=2.0, cy=2.0, baseline=0.1)
  assert len(viz.disparity_to_points(disp, rgb, **calib)[0]) == 20
  with pytest.raises(ValueError, match=r"disp \[H, W\] and rgb \[H, W, 3\]"):
    viz.disparity_to_points(disp[None], rgb, **calib)
  with pytest.raises(ValueError, match=r"disp \[H, W\] and rgb \[H, W, 3\]"):
    viz.disparity_to_points(disp, rgb.transpose(2, 0, 1), **calib)
  with pytest.raises(ValueError, match="fy must be a finite positive number"):
    viz.disparity_to_points(disp, rgb, **{**calib, "fy": 0.0})
  for fx in (0.0, float("nan")):
    with pytest.raises(ValueError, match="fx must be a finite positive number"):
      viz.depth_from_disparity(disp, fx, 0.1)
  for writer, what, suffix in ((viz.write_png16, "16-bit PNG", ".png"),
                               (viz.write_pfm, "PFM", ".pfm"), (viz.write_exr, "EXR", ".exr")):
    for shape in ((0, 4), (4, 5, 2)):
      path = tmp_path / f"empty_{len(shape)}{suffix}"
      with pytest.raises(ValueError, match=f"{path.name}: .*{what}.*got shape"):
        writer(path, np.ones(shape, np.float32))
      assert not path.exists()
  # A name of another format would store the values lossily or scaled: refused, and a file
  # of that name is left as it was.
  for name in ("d.jpg", "d.pfm", "d"):
    (tmp_path / name).write_bytes(b"mine")
    with pytest.raises(ValueError, match=f"{name}: a 16-bit PNG disparity file must be named"):
      viz.write_png16(tmp_path / name, disp)
    assert (tmp_path / name).read_bytes() == b"mine"
  for name in ("photo.png", "clip.jpg", "clip"):
    (tmp_path / name).write_bytes(b"mine")
    with pytest.raises(ValueError, match=f"{name}: write_video writes mp4v video files"):
      viz.write_video(tmp_path / name, np.zeros((2, 8, 8, 3), np.uint8))
    assert (tmp_path / name).read_bytes() == b"mine"


def test_colorize_fractional_valid_follows_the_metrics_threshold():
  rgb = viz.colorize(np.ones((1, 3), np.float32), 0.0, 2.0, valid=np.array([[0.3, 0.6, 1.0]]))
  assert tuple(rgb[0, 0]) == viz.INVALID_COLOR and tuple(rgb[0, 1]) != viz.INVALID_COLOR


def test_colorize_names_the_end_taken_from_the_data():
  with pytest.raises(ValueError, match=r"vmin=3.0, vmax=2.0 \(vmin taken from the data's range "
                                       r"3..5, which lies beyond the given end; give both"):
    viz.colorize(np.array([[3.0, 4.0, 5.0]]), vmax=2.0)


def test_colorize_takes_its_range_from_the_valid_pixels_only():
  # 100 px outside the mask sets no end: the range is 1..5, so 5 px is the brightest colour
  # (not level round(4 / 99 * 255) = 10 of a 1..100 range)
  lut = _lut()
  d = np.array([[1.0, 5.0, 100.0]], np.float32)
  rgb = viz.colorize(d, valid=np.array([[True, True, False]]))
  assert [tuple(c) for c in rgb[0]] == [tuple(lut[0]), tuple(lut[255]), viz.INVALID_COLOR]
  np.testing.assert_array_equal(viz.colorize(d, vmin=0.0, valid=d < 50)[0, 1], lut[255])


@pytest.mark.parametrize("vmin, vmax", [(-math.inf, 1.0), (0.0, math.inf), (math.nan, 1.0),
                                        (0.0, math.nan)])
def test_colour_range_ends_must_be_finite(vmin, vmax):
  # an infinite end gives 255 / inf = 0 levels per px: every pixel one colour
  with pytest.raises(ValueError, match="colour range needs finite vmin < vmax"):
    viz.colorize(np.array([[1.0, 2.0]]), vmin, vmax)
  with pytest.raises(ValueError, match="colour range needs finite vmin < vmax"):
    viz.colorbar(vmin, vmax)


def test_as_real_keeps_the_sign_of_integers_beyond_float():
  assert viz.as_real(10**400) == math.inf and viz.as_real(-10**400) == -math.inf
  with pytest.raises(ValueError, match="cx must be a finite number, got -inf"):
    viz.check_intrinsics(cx=-10**400)


def test_colorize_checks_the_invalid_colour():
  disp = np.array([[0.0, 1.0]], np.float32)
  assert tuple(viz.colorize(disp, 0.5, 2.0, invalid_color=(1, 2, 3))[0, 0]) == (1, 2, 3)
  assert tuple(viz.colorize(disp, 0.5, 2.0, invalid_color=(255.0, 0, 0))[0, 0]) == (255, 0, 0)
  # 0..1 colours (matplotlib's) were truncated: (0.5, 0.5, 0.5) to black; (1.0, 1.0, 1.0) is
  # a valid near-black, with a warning
  with pytest.warns(UserWarning, match=r"invalid_color \(1\.0, 1\.0, 1\.0\) is nearly black"):
    viz.colorize(disp, 0.5, 2.0, invalid_color=(1.0, 1.0, 1.0))
  for bad in ((300, 0, 0), (0, 0), (-1, 0, 0), "red", (np.nan, 0, 0), (0.5, 0.5, 0.5)):
    with pytest.raises(ValueError, match=r"invalid_color must be 3 integers \(R, G, B\)"):
      viz.colorize(disp, 0.5, 2.0, invalid_color=bad)


def test_intrinsics_and_ranges_take_0d_arrays_and_refuse_the_rest():
  # fx = K[0, 0] of an intrinsics matrix, or a JAX scalar, was refused: "fx must be a finite
  # positive number, got Array(100., dtype=float32)".
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  d = np.array([[1.0, 2.0], [4.0, 0.0]], np.float32)
  rgb = np.zeros((2, 2, 3), np.uint8)
  k = np.array([[100.0, 0, 0.5], [0, 50.0, 0.5], [0, 0, 1]])
  want = viz.depth_from_disparity(d, 100.0, 0.1)
  for fx in (jnp.float32(100.0), jnp.asarray(100.0), k[0, 0], np.array(100.0), np.float32(100),
             np.array(100, np.int64)):
    np.testing.assert_array_equal(viz.depth_from_disparity(d, fx=fx, baseline=0.1), want)
    np.testing.assert_array_equal(
        viz.depth_from_disparity(d, fx, np.array(0.1), doffs=jnp.zeros(())), want)
  calib = dict(fx=100.0, fy=50.0, cx=0.5, cy=0.5, baseline=0.1)
  xyz, col = viz.disparity_to_points(d, rgb, **calib, max_depth=5.0)
  xyz0, col0 = viz.disparity_to_points(d, rgb, fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2],
                                       baseline=jnp.float32(0.1), doffs=np.array(0.0),
                                       max_depth=jnp.asarray(5.0))
  assert type(xyz0) is np.ndarray and xyz0.dtype == np.float32  # (not a JAX array)
  np.testing.assert_allclose(xyz0, xyz, rtol=1e-6)
  np.testing.assert_array_equal(col0, col)
  assert viz.check_intrinsics(fx=np.array(2.0), doffs=jnp.float32(-1.5)) == {"fx": 2.0,
                                                                               "doffs": -1.5}
  # Still refused: bools, strings, NaN, non-positive, and arrays of one or more dimensions.
  for fx, got in ((True, "True"), ("10", "'10'"), (np.array(np.nan), "nan"),
                  (jnp.float32(np.nan), "nan"), (np.array(-1.0), "-1.0"), (jnp.float32(0), "0.0"),
                  (np.bool_(True), r"(np\.)?True"), (np.array(True), r"array\(True\)"),
                  (jnp.asarray(True), r"Array\(True"), (1 + 2j, r"\(1\+2j\)")):
    with pytest.raises(ValueError, match=f"fx must be a finite positive number, got {got}"):
      viz.depth_from_disparity(d, fx=fx, baseline=0.1)
  for fx, shape in ((np.array([100.0]), "(1,)"), (jnp.ones((2, 2)), "(2, 2)"),
                    ([100.0], "(1,)"), (k, "(3, 3)")):
    with pytest.raises(ValueError, match=re.escape(
        f"fx must be a finite positive number, got an array of shape {shape}: give one number "
        "(a scalar)")):
      viz.depth_from_disparity(d, fx=fx, baseline=0.1)
  with pytest.raises(ValueError, match=r"disparity_to_points: cx must be a finite number, got an "
                                       r"array of shape \(3,\)"):
    viz.disparity_to_points(d, rgb, **{**calib, "cx": k[:, 2]})
  # The other scalars: the frame rate and the colour range.
  assert viz.is_fps(np.array(10.0)) and viz.is_fps(jnp.float32(25)) and not viz.is_fps(True)
  with pytest.raises(ValueError, match="fps must be a number from 0.01 to 65535, got an array"):
    viz.check_fps(np.array([10.0]))
  np.testing.assert_array_equal(viz.colorize(d, jnp.float32(0.5), np.array(4.0)),
                                viz.colorize(d, 0.5, 4.0))
  for lo in (np.array([0.5]), "0.5", True):
    with pytest.raises(ValueError, match="colour range needs numbers"):
      viz.colorize(d, lo, 4.0)


def test_colorize_drops_a_trailing_channel_of_one():
  # [T, H, W, 1] came out [T, H, W, 1, 3].
  video = np.arange(1, 25, dtype=np.float32).reshape(2, 3, 4)
  valid = video % 5 != 0
  want = viz.colorize(video, valid=valid)
  for shown in (viz.colorize(video[..., None], valid=valid),
                viz.colorize(video[..., None], valid=valid[..., None]),
                viz.colorize(video[..., None], 1.0, 24.0, valid=valid)):
    assert shown.shape == (2, 3, 4, 3)
    np.testing.assert_array_equal(shown, want)
  assert viz.colorize(video[0, ..., None], 1.0, 24.0).shape == (3, 4, 3)  # [H, W, 1]
  assert viz.colorize(video[0, :, :1], 1.0, 24.0).shape == (3, 1, 3)  # [H, 1]: a 1-wide map
  with pytest.raises(ValueError, match=r"valid mask shape \(3, 4\) differs from disparity "
                                       r"\(2, 3, 4, 1\)"):
    viz.colorize(video[..., None], valid=valid[0])


def test_side_by_side_names_an_image_with_other_channels():
  rgb = np.zeros((4, 5, 3), np.uint8)
  # an RGBA first image was blamed on the second: "image 1 of shape (4, 5, 3) does not match
  # the first (4, 5, 4, 3)"
  for first, second, bad, channels in ((np.zeros((4, 5, 4), np.uint8), rgb, 0, 4),
                                       (rgb, np.zeros((4, 5, 2), np.uint8), 1, 2),
                                       (np.zeros((2, 4, 5, 4)), np.zeros((2, 4, 5, 3)), 0, 4)):
    with pytest.raises(ValueError, match=re.escape(
        f"side_by_side image {bad} of shape {np.shape((first, second)[bad])} has {channels} "
        "channels") + r".*RGB \[\.\.\., H, W, 3\] or a grey map"):
      viz.side_by_side(first, second)
  # [H, W, 1] is a grey map, as [H, W]
  grey = np.full((4, 5, 1), 7, np.uint8)
  out = viz.side_by_side(grey, rgb)
  assert out.shape == (4, 10, 3)
  np.testing.assert_array_equal(out[:, :5], 7)
  np.testing.assert_array_equal(viz.side_by_side(grey[None], rgb[None]), out[None])
  np.testing.assert_array_equal(viz.side_by_side(rgb, grey[..., 0]), viz.side_by_side(rgb, grey))


def test_side_by_side_points_a_float_map_to_colorize():
  rgb = np.zeros((4, 5, 3), np.uint8)
  disp = np.linspace(0.0, 0.9, 20, dtype=np.float32).reshape(4, 5)
  with pytest.warns(UserWarning, match=r"side_by_side image 1: .*viz\.colorize") as record:
    viz.side_by_side(rgb, disp)
  assert {w.filename for w in record} == {__file__}
  with pytest.warns(UserWarning, match="viz.colorize"):  # [H, W, 1] and a video of maps too
    viz.side_by_side(rgb[None], disp[None, ..., None])
  for bad, match in ((disp * 500, r"values 0\.\.450 outside 0\.\.255 \(a disparity or depth "
                                  r"map\? colour it with viz\.colorize first\)"),
                     (np.where(disp > 0.5, np.nan, disp), "NaN or inf.*viz.colorize")):
    with pytest.raises(ValueError, match=match):
      viz.side_by_side(rgb, bad)
  # RGB images keep their advice
  with pytest.raises(ValueError, match=r"outside 0\.\.255 \(16-bit images: >> 8\)"):
    viz.side_by_side(np.full((4, 5, 3), 300, np.uint16))
  with pytest.raises(ValueError, match=r"outside 0\.\.255 \(16-bit images: divide by 257\)"):
    viz.side_by_side(np.full((4, 5, 3), 1000.0))


def test_disparity_range_warns_about_fractions():
  ramp = np.arange(1, 101, dtype=np.float32).reshape(10, 10)
  with pytest.warns(UserWarning, match=r"percentiles \(0\.01, 0\.99\) are both at most 1: "
                                       r"percentiles are in 0\.\.100") as record:
    lo, hi = viz.disparity_range(ramp, percentiles=(0.01, 0.99))
  assert record[0].filename == __file__ and hi < 3  # (as asked: the 0.99th percentile)
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    assert viz.disparity_range(ramp, percentiles=(1, 99)) == pytest.approx((1.99, 99.01))
    viz.disparity_range(ramp, percentiles=(0.5, 99.5))
    viz.disparity_range(ramp)


def test_write_pfm_checks_the_suffix(tmp_path):
  ramp = np.arange(1, 7, dtype=np.float32).reshape(2, 3)
  for name in ("e.png", "e.exr", "e"):  # (PFM bytes went into e.png)
    (tmp_path / name).write_bytes(b"mine")
    with pytest.raises(ValueError, match=f"{name}: write_pfm writes PFM files; name one .pfm"):
      viz.write_pfm(tmp_path / name, ramp)
    assert (tmp_path / name).read_bytes() == b"mine"
  viz.write_pfm(tmp_path / "E.PFM", ramp)
  np.testing.assert_array_equal(viz.read_pfm(tmp_path / "E.PFM"), ramp)


def test_disparity_to_points_warns_as_the_cli_refuses_a_principal_point_outside():
  from sav_jax.tools import UsageError  # pylint: disable=import-outside-toplevel
  from sav_jax.tools.infer import CalibrationSpec  # pylint: disable=import-outside-toplevel
  disp, rgb = np.full((32, 64), 2.0, np.float32), np.zeros((32, 64, 3), np.uint8)
  for cx, cy in ((3200.0, 1600.0), (64.0, 10.0), (-0.6, 10.0), (10.0, 31.6), (63.5, 31.5),
                 (-0.5, -0.5), (31.5, 15.5), (70.0, 15.5)):
    outside = not viz.principal_point_inside(cx, cy, 32, 64)
    try:
      CalibrationSpec(fx=40.0, baseline=0.1, cx=cx, cy=cy).resolve(64, 32)
      refused = False
    except UsageError:
      refused = True
    assert refused == outside, (cx, cy)  # one rule with `sav-jax infer`
    with warnings.catch_warnings(record=True) as caught:
      warnings.simplefilter("always")
      xyz, _ = viz.disparity_to_points(disp, rgb, fx=40.0, fy=40.0, cx=cx, cy=cy, baseline=0.1)
    assert len(xyz) == 32 * 64  # a warning, not an error (cropped images may have one outside)
    assert [str(w.message) for w in caught] == ([
        f"disparity_to_points: the principal point (cx {cx:g}, cy {cy:g}) is outside the 32x64 "
        "(height x width) map: intrinsics for another image size? (scale fx, fy, cx, cy and "
        "doffs by the resize factor; sav-jax infer refuses such a calibration)"]
        if outside else []), (cx, cy)
    assert all(w.filename == __file__ for w in caught)
  assert viz.principal_point_inside(3200, 1600, 32, 64) is False


def test_bfloat16_images_and_points_are_taken_as_float16_ones_are(tmp_path):
  """bfloat16 (JAX's compute dtype) was refused: "dtype bfloat16; expected uint8 or numbers"
  (its NumPy kind is 'V'), in side_by_side, disparity_to_points' rgb and write_ply."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  rgb = np.arange(2 * 4 * 3, dtype=np.float32).reshape(2, 4, 3) * 8
  for dtype in (jnp.bfloat16, np.float16):
    assert np.array_equal(viz.side_by_side(jnp.asarray(rgb, dtype)), rgb.astype(np.uint8))
    xyz, col = viz.disparity_to_points(np.full((2, 4), 2.0), jnp.asarray(rgb, dtype), fx=10.0,
                                       fy=10.0, cx=1.5, cy=0.5, baseline=0.2)
    assert np.array_equal(col, rgb.reshape(-1, 3).astype(np.uint8))
    assert viz.write_ply(tmp_path / "p.ply", jnp.asarray(xyz, dtype), jnp.asarray(col, dtype)) == 8
    back, colours = viz.read_ply(tmp_path / "p.ply")
    assert np.array_equal(back, xyz.astype(jnp.bfloat16 if dtype is jnp.bfloat16 else dtype)
                          .astype(np.float32)) and np.array_equal(colours, col)


def test_colorize_error_uses_kittis_bins_and_keeps_perfect_pixels():
  """Error maps: colorize's "d <= 0 is invalid" painted every perfect pixel (error 0) white;
  colorize_error bins the error in multiples of KITTI's outlier threshold."""
  gt = np.array([[100.0, 100.0, 100.0, 100.0, 10.0, 10.0, 0.0, 40.0]], np.float32)
  pred = gt + np.array([[0.0, 2.9, 3.1, 5.1, 3.1, 1e3, 7.0, np.nan]], np.float32)
  rgb = viz.colorize_error(pred, gt)
  colours = [tuple(c) for c in viz.KITTI_ERROR_COLORS]
  # 0 -> bin 0; 2.9 px -> 2.9/3 = 0.97 (bin 4, correct); 3.1 px at gt 100: min(1.03, 0.62)
  # -> bin 4 (within 5%); 5.1 px at gt 100: min(1.7, 1.02) -> bin 5; 3.1 px at gt 10:
  # min(1.03, 6.2) -> bin 5; 1000 px -> bin 9; gt 0: no ground truth (black); NaN: worst
  assert [tuple(c) for c in rgb[0]] == [colours[0], colours[4], colours[4], colours[5],
                                        colours[5], colours[9], (0, 0, 0), colours[9]]
  absolute = viz.colorize_error(pred, gt, rel_thresh=None)  # the bad-3 map: 3.1 px is bad
  assert tuple(absolute[0, 2]) == colours[5] and tuple(absolute[0, 3]) == colours[5]  # 1.7
  valid = np.ones_like(gt)
  valid[0, 0] = 0
  masked = viz.colorize_error(pred[..., None], gt[..., None], valid, invalid_color=(9, 9, 9))
  assert masked.shape == (1, 8, 3) and tuple(masked[0, 0]) == (9, 9, 9)
  assert tuple(masked[0, 6]) == colours[6]  # gt 0 inside the given mask: 7 px / 3 = 2.3
  both_zero = viz.colorize_error(np.zeros((1, 2)), np.zeros((1, 2)), np.ones((1, 2)))
  assert (both_zero == colours[0]).all()  # 0 / 0 in the relative term: perfect, not the worst
  video = viz.colorize_error(np.zeros((3, 2, 5)), np.ones((3, 2, 5)))  # [T, H, W]
  assert video.shape == (3, 2, 5, 3) and (video == colours[3]).all()  # 1 px: 1/3 of 3 px
  for p_shape, g_shape in (((2, 5), (2, 4)), ((1, 4), (4, 1))):  # (the second broadcasts)
    with pytest.raises(ValueError, match=re.escape(f"pred of shape {p_shape} and gt of shape "
                                                   f"{g_shape}")):
      viz.colorize_error(np.zeros(p_shape), np.zeros(g_shape))
  for kw in ({"abs_thresh": 0}, {"rel_thresh": -1.0}, {"abs_thresh": "3"}):
    with pytest.raises(ValueError, match="abs_thresh must be a number > 0"):
      viz.colorize_error(pred, gt, **kw)
  with pytest.raises(ValueError, match="invalid_color must be 3 integers"):
    viz.colorize_error(pred, gt, invalid_color=(0, 0))


def test_colorbar_matches_colorize_and_labels_its_ticks():
  bar = viz.colorbar(2.0, 12.0, length=101, thickness=5, cmap="turbo")
  assert bar.shape == (5 + 18, 101, 3) and bar.dtype == np.uint8
  expected = viz.colorize(np.linspace(2.0, 12.0, 101, dtype=np.float32)[None], 2.0, 12.0,
                          cmap="turbo")[0]
  assert np.array_equal(bar[0], expected) and np.array_equal(bar[4], expected)
  ticks = np.nonzero((bar[5] == 0).all(axis=-1))[0]  # ticks at 2, 4, .., 12: every 20 px
  assert list(ticks) == [0, 20, 40, 60, 80, 100]
  labels = bar[8:]
  assert (labels < 128).any() and (labels == 255).any()  # black text on white
  # every tick's number is drawn under it (text ink near each tick column), and the unit after
  # the last one only
  plain = viz.colorbar(2.0, 12.0, length=101, thickness=5, cmap="turbo", unit="")
  ink = np.nonzero((plain[5 + 5:] < 128).any(axis=(0, 2)))[0]
  for x in ticks:
    assert np.any(np.abs(ink - x) <= 6), (x, ink)
  differs = np.nonzero((plain != bar).any(axis=(0, 2)))[0]
  assert differs.size and differs.min() > 64, differs  # "12 px" in place of "12" (to the left)
  negative = viz.colorbar(-1.0, 1.0, length=64)  # ranges through 0 are coloured, not "invalid"
  assert len({tuple(c) for c in negative[0]}) > 32
  with pytest.raises(ValueError, match="finite vmin < vmax"):
    viz.colorbar(3.0, 3.0)
  with pytest.raises(ValueError, match="length must be an integer >= 32"):
    viz.colorbar(0.0, 1.0, length=8)
  with pytest.raises(ValueError, match="unknown colour map"):
    viz.colorbar(0.0, 1.0, cmap="jet")


def _lut(cmap=cv2.COLORMAP_INFERNO):
  """OpenCV's colour map as an RGB table of 256 entries (index = colour level)."""
  return cv2.applyColorMap(np.arange(256, dtype=np.uint8)[None], cmap)[0, :, ::-1]


def test_disparity_range_edge_cases():
  # inf and NaN are not disparities; a weight of exactly 0.5 is not valid (> 0.5 is)
  d = np.array([[2.0, np.inf, 6.0, np.nan, 9.0]], np.float32)
  assert viz.disparity_range(d) == (2.0, 9.0)
  assert viz.disparity_range(d, valid=np.array([[1.0, 1.0, 1.0, 1.0, 0.5]])) == (2.0, 6.0)
  # nothing usable: (0, 1); one value (or equal percentiles): a range of 1 px above it
  assert viz.disparity_range(np.array([[0.0, -3.0, np.nan]])) == (0.0, 1.0)
  assert viz.disparity_range(np.full((2, 3), 5.0)) == (5.0, 6.0)
  ramp = np.arange(1, 102, dtype=np.float32)  # 1..101: the p-th percentile is 1 + p
  assert viz.disparity_range(ramp, percentiles=(50, 50)) == (51.0, 52.0)
  assert viz.disparity_range(ramp, percentiles=(10, 90)) == (11.0, 91.0)
  with pytest.warns(UserWarning, match="both at most 1"):
    viz.disparity_range(ramp, percentiles=(0, 1))
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    assert viz.disparity_range(ramp, percentiles=(0, 1.5)) == (1.0, 2.5)


def test_as_uint8_image_bounds_and_the_0_to_1_warning():
  assert viz.as_uint8_image(np.zeros((0, 2, 3), np.float32)).shape == (0, 2, 3)
  assert viz.as_uint8_image(np.zeros((0, 2, 3), np.float32)).dtype == np.uint8
  np.testing.assert_array_equal(viz.as_uint8_image(np.array([254.6, 255.0, 0.4])), [255, 255, 0])
  for bad in (256, -1, 65535):  # integers: no overshoot allowance
    with pytest.raises(ValueError, match="outside 0..255"):
      viz.as_uint8_image(np.array([0, bad]))
  for bad in (320.5, -64.5):  # floats beyond a resize's overshoot
    with pytest.raises(ValueError, match="outside 0..255"):
      viz.as_uint8_image(np.array([0.0, bad]))
  with pytest.warns(UserWarning, match="multiply 0..1 images by 255"):
    viz.as_uint8_image(np.array([0.0, 1.0], np.float32))
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # black, integer 0..1, or brighter than 1: no warning
    for fine in (np.zeros(3, np.float32), np.array([0, 1], np.uint16), np.array([0.0, 2.0])):
      viz.as_uint8_image(fine)


def test_float_images_may_overshoot_as_predict_video_frames_may():
  # a bicubic resize of 0..255 frames overshoots (255.3, -2.4): predict_video takes such
  # frames without a word, so the image helpers clip them instead of refusing them with
  # advice for 16-bit images
  frame = np.array([[[255.3, 128.0, -2.4], [0.0, 255.0, 12.6]]], np.float32)
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    np.testing.assert_array_equal(viz.as_uint8_image(frame), [[[255, 128, 0], [0, 255, 13]]])
    xyz, rgb = viz.disparity_to_points(np.ones((1, 2), np.float32), frame, fx=10.0, fy=10.0,
                                       cx=0.5, cy=0.0, baseline=1.0)
  assert len(xyz) == 2 and rgb.tolist() == [[255, 128, 0], [0, 255, 13]]
  edges = np.array([0.0, 255.0, OVERSHOOT_LOW, OVERSHOOT_HIGH])
  np.testing.assert_array_equal(viz.as_uint8_image(edges), [0, 255, 0, 255])
  # beyond the overshoot, the advice fits what the values look like
  with pytest.raises(ValueError,
                     match=r"0\.\.40000 outside 0\.\.255 \(16-bit images: divide by 257\)"):
    viz.as_uint8_image(np.array([0.0, 40000.0]))
  with pytest.raises(ValueError, match=r"-120\.\.100 outside 0\.\.255 \(.*normalised"):
    viz.as_uint8_image(np.array([-120.0, 100.0]))
  with pytest.raises(ValueError, match=r"-1\.\.3 outside 0\.\.255 \(.*normalised"):
    viz.as_uint8_image(np.array([-1, 3], np.int16))
  # a normalised float frame (mean and scale taken off) is within the overshoot allowance,
  # but predict_video refuses it: clipped, it came out black without a word
  with pytest.raises(ValueError, match=r"-2\.1\.\.2\.6 outside 0\.\.255 \(.*normalised"):
    viz.as_uint8_image(np.array([-2.1, 0.3, 2.6], np.float32))
  # an integer map beyond 0..255 may be a 16-bit grey image or a stored disparity (a KITTI
  # PNG's 256 d): both pieces of advice, not ">> 8" alone
  with pytest.raises(ValueError, match=r"\(16-bit images: >> 8; a disparity or depth map\? "
                                       r"colour it with viz\.colorize first\)"):
    viz.side_by_side(np.zeros((2, 3, 3), np.uint8), np.full((2, 3), 5120, np.uint16))
  # a float map is likely disparity: no allowance, the colorize advice
  with pytest.raises(ValueError, match=r"255\.3 outside 0\.\.255 \(a disparity or depth map"):
    viz.as_uint8_image(np.array([[0.0, 255.3]]), is_map=True)


def test_fps_and_principal_point_bounds():
  assert viz.is_fps(0.01) and viz.is_fps(65535) and viz.is_fps(25)
  assert not any(viz.is_fps(f) for f in (0.0099, 65535.5, 0, -5, math.inf, math.nan, True, "5"))
  # pixel centres at integers: a 4x6 (height x width) frame spans [-0.5, 5.5] x [-0.5, 3.5]
  inside = [(-0.5, -0.5), (5.5, 3.5), (2.5, 1.5), (-0.5, 3.5), (5.5, -0.5)]
  outside = [(-0.51, 1.0), (5.51, 1.0), (2.0, -0.51), (2.0, 3.51), (6.0, 1.0), (2.0, 4.0)]
  assert all(viz.principal_point_inside(cx, cy, 4, 6) for cx, cy in inside)
  assert not any(viz.principal_point_inside(cx, cy, 4, 6) for cx, cy in outside)


def test_colorize_maps_the_range_linearly_and_clips_outside_it():
  lut = _lut()
  # range 2..12: level round((d - 2) * 25.5); below vmin the first colour, above the last
  d = np.array([[2.0, 7.0, 12.0, 4.0, 1.0, 50.0]], np.float32)
  levels = [0, 128, 255, 51, 0, 255]  # (127.5 rounds to even)
  np.testing.assert_array_equal(viz.colorize(d, 2.0, 12.0)[0], lut[levels])
  np.testing.assert_array_equal(viz.colorize(d, 2.0, 12.0, cmap="turbo")[0],
                                _lut(cv2.COLORMAP_TURBO)[levels])
  # one end given: the other from the data (here 1..50)
  np.testing.assert_array_equal(viz.colorize(d, vmin=0.0)[0, 5], lut[255])
  np.testing.assert_array_equal(viz.colorize(d, vmin=0.0)[0, 4], lut[round(255 / 50)])
  np.testing.assert_array_equal(viz.colorize(d, vmax=99.0)[0, 4], lut[0])
  # a weight of exactly 0.5 is invalid (> 0.5 is valid), as in the metrics
  rgb = viz.colorize(np.ones((1, 2)), 0.0, 2.0, valid=np.array([[0.5, 0.51]]))
  assert tuple(rgb[0, 0]) == viz.INVALID_COLOR and tuple(rgb[0, 1]) == tuple(lut[128])
  for shape in ((0, 4), (3, 0), (2, 0, 3)):  # empty maps, of no rows or no columns
    assert viz.colorize(np.zeros(shape, np.float32), 0.0, 1.0).shape == (*shape, 3)


def test_colorize_error_masks_and_thresholds():
  colours = [tuple(c) for c in viz.KITTI_ERROR_COLORS]
  gt = np.array([[np.nan, 10.0, 10.0, 0.0, 0.0, 1e-38]], np.float32)
  pred = np.array([[5.0, 10.0, 40.0, 0.0, 7.0, 1e3]], np.float32)
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # 0 / 0, x / 0, overflow, NaN: no RuntimeWarning
    rgb = viz.colorize_error(pred, gt)
    masked = viz.colorize_error(pred, gt, valid=np.array([[1.0, 0.5, 0.51, 1.0, 1.0, 1.0]]))
  # no ground truth (NaN or 0) is black without a mask; a NaN one stays black within a mask
  # (30 px at gt 10: min(30 / 3, 30 / 0.5) = 10 -> bin 8, 8..16; 7 px at gt 0: 7 / 3 ->
  # bin 6; 1000 px at gt 1e-38: 1000 / 3 -> bin 9)
  assert [tuple(c) for c in rgb[0]] == [(0, 0, 0), colours[0], colours[8], (0, 0, 0),
                                        (0, 0, 0), colours[9]]
  assert [tuple(c) for c in masked[0]] == [(0, 0, 0), (0, 0, 0), colours[8], colours[0],
                                           colours[6], colours[9]]
  # thresholds: any number > 0 (below 1 too), not 0, not inf
  off, hundred = np.array([[101.0]]), np.array([[100.0]])  # an error of 1 px
  half = viz.colorize_error(off, hundred, abs_thresh=0.5, rel_thresh=None)  # 1 / 0.5 = 2: (1, 2]
  assert tuple(half[0, 0]) == colours[5]
  rel = viz.colorize_error(off, hundred, abs_thresh=100.0, rel_thresh=0.5)  # 1 / 50: bin 0
  assert tuple(rel[0, 0]) == colours[0]
  # an error of exactly a bin's upper edge is in that bin (not KITTI's devkit's): 3 px is
  # correct, as bad_3px (strict, e > 3) and D1 count it, and 1.5 px is in (1/4, 1/2]
  gt = np.full((1, 4), 50.0, np.float32)
  pred = gt + np.array([[3.0, 1.5, 3.0001, 0.0]], np.float32)
  edges = viz.colorize_error(pred, gt, rel_thresh=None)
  assert [tuple(c) for c in edges[0]] == [colours[4], colours[3], colours[5], colours[0]]
  bad = metrics.eval_endpoint_error_sequence(pred[None], gt[None], np.ones((1, 1, 4)))
  assert bad["epe_bad_3px"] == 100 / 3  # the 3.0001 px pixel only (the 0 error is not counted)
  for kw in ({"abs_thresh": math.inf}, {"rel_thresh": 0.0}, {"rel_thresh": math.inf},
             {"abs_thresh": -0.5}):
    with pytest.raises(ValueError, match="abs_thresh must be a number > 0"):
      viz.colorize_error(off, hundred, **kw)


def test_nice_step_is_1_2_5_times_a_power_of_10():
  # the smallest 1/2/5 x 10^k step >= span / ticks
  for span, ticks, step in ((10, 5, 2), (1, 5, 0.2), (7, 5, 2), (30, 5, 10), (3, 5, 1),
                            (0.3, 5, 0.1), (1000, 4, 500), (12, 10, 2), (4.5, 1, 5),
                            (10, 10, 1), (50, 5, 10)):
    assert viz.nice_step(span, ticks) == pytest.approx(step), (span, ticks)
  assert viz.nice_step(0.0, 5) == 1.0 and viz.nice_step(-2.0, 5) == 1.0


def _tick_columns(bar):
  return list(np.nonzero((bar[-18] == 0).all(axis=-1))[0])


def test_colorbar_ticks_off_the_step_and_at_the_last_pixel():
  # 4.5..13.7: step 2, ticks at 6, 8, 10, 12 -> column round((v - 4.5) / 9.2 * 91)
  bar = viz.colorbar(4.5, 13.7, length=92)
  assert _tick_columns(bar) == [round((v - 4.5) / 9.2 * 91) for v in (6, 8, 10, 12)]
  # float steps: 0.07 / 0.01 is 7.000000000000001 and 0.3 / 0.1 is 2.9999999999999996; the
  # ticks at both ends are kept all the same
  assert _tick_columns(viz.colorbar(0.07, 0.11, length=41)) == [0, 10, 20, 30, 40]
  assert _tick_columns(viz.colorbar(0.0, 0.3, length=61)) == [0, 20, 40, 60]
  # `ticks` sets the step: 10 / 10 -> 1 px, 10 / 2 -> 5 px
  assert _tick_columns(viz.colorbar(0.0, 10.0, length=101, ticks=10)) == list(range(0, 101, 10))
  assert _tick_columns(viz.colorbar(0.0, 10.0, length=101, ticks=2)) == [0, 50, 100]
  # no step inside the range (1..4 with one interval: a step of 5): the ends are labelled
  # (it raised IndexError, a mark at 5 beyond the bar); one inside: that one alone
  assert _tick_columns(viz.colorbar(1.0, 4.0, length=61, ticks=1)) == [0, 60]
  assert _tick_columns(viz.colorbar(3.0, 4.9, length=39, ticks=1)) == [round(1 / 1.9 * 38)]
  # the smallest sizes accepted
  assert viz.colorbar(0.0, 1.0, length=32, thickness=1, ticks=1).shape == (1 + 18, 32, 3)
  for kw in ({"thickness": 0}, {"ticks": 0}, {"length": 31}):
    with pytest.raises(ValueError, match="must be an integer >="):
      viz.colorbar(0.0, 1.0, **kw)


def test_colorbar_leaves_out_labels_that_would_run_into_each_other():
  # 0..1000 on 64 px: six ticks 200 apart (12-13 px) under labels "200" of 19 px: they ran
  # into one smear. The ticks stay; the labels drawn do not overlap, the last has its unit.
  bar = viz.colorbar(0.0, 1000.0, length=64)
  assert _tick_columns(bar) == [0, 13, 25, 38, 50, 63]
  kept = viz._tick_labels([0, 200, 400, 600, 800, 1000], [0, 13, 25, 38, 50, 63], 64, "px")
  assert [t for _, t in kept] == ["0", "1000 px"], kept
  ink = np.flatnonzero((bar[-18 + 4:] < 128).any(axis=(0, 2)))
  assert ink.min() <= 2 and ink.max() >= 60 and not ink[(ink > 8) & (ink < 64 - 38)].size
  # a wide bar keeps every label (as before): 2..12 on 320 px
  wide = viz._tick_labels([2, 4, 6, 8, 10, 12], [0, 64, 128, 191, 255, 319], 320, "px")
  assert [t for _, t in wide] == ["2", "4", "6", "8", "10", "12 px"]
  # ten ticks 10 px apart: "8" and "9" ran into "10 px"; each label box clear of the next
  placed = viz._tick_labels(list(range(11)), list(range(0, 101, 10)), 101, "px")
  texts = [t for _, t in placed]
  assert texts[-1] == "10 px" and "9" not in texts and texts[:6] == list("023456")  # "01"
  ends = [left + cv2.getTextSize(t, viz._FONT, viz._FONT_SCALE, 1)[0][0] for left, t in placed]
  assert all(end < nxt for end, (nxt, _) in zip(ends, placed[1:])), placed


def test_side_by_side_repeats_grey_maps_of_any_width():
  rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 1, 3, 3)  # [T=2, H=1, W=3, 3]
  for width in (1, 2, 4):  # (2 and 4 are channel counts only with 3 or more axes)
    grey = np.arange(width, dtype=np.uint8)[None] * 10  # [H=1, W]
    out = viz.side_by_side(rgb[0], grey)
    assert out.shape == (1, 3 + width, 3)
    np.testing.assert_array_equal(out[:, :3], rgb[0])
    np.testing.assert_array_equal(out[0, 3:], np.repeat(grey[0][:, None], 3, axis=1))
  video = viz.side_by_side(rgb, np.full((2, 1, 5), 7, np.uint8), rgb)  # a grey video [T, H, W]
  assert video.shape == (2, 1, 11, 3) and (video[:, :, 3:8] == 7).all()
  np.testing.assert_array_equal(video[:, :, 8:], rgb)


def _read_video(path):
  cap = cv2.VideoCapture(str(path))
  frames = []
  while True:
    ok, frame = cap.read()
    if not ok:
      break
    frames.append(frame[..., ::-1])  # (OpenCV reads BGR)
  fps = cap.get(cv2.CAP_PROP_FPS)
  cap.release()
  return np.stack(frames), fps


def test_write_video_keeps_colours_order_rate_and_pads_with_the_edge(tmp_path):
  # 3 frames of 9x7 (odd: padded to 10x8 with the last row / column repeated): pure red,
  # green, blue, each with a white last row and column; float frames in 0..255 too
  frames = np.zeros((3, 9, 7, 3), np.float32)
  for t in range(3):
    frames[t, :, :, t] = 255.0
  frames[:, -1], frames[:, :, -1] = 255.0, 255.0
  path = tmp_path / "v.mp4"
  assert viz.write_video(str(path), list(frames), fps=7.5) == path  # (a str path too)
  back, fps = _read_video(path)
  assert back.shape == (3, 10, 8, 3) and fps == pytest.approx(7.5)
  for t in range(3):  # (mp4v is lossy: compare with a margin)
    centre = back[t, 3:6, 2:4].reshape(-1, 3).astype(int).mean(axis=0)
    assert centre[t] > 200 and np.delete(centre, t).max() < 60, (t, centre)
    assert back[t, -2:, :6].min() > 180 and back[t, :7, -2:].min() > 180  # edge, not black
  # a 1x1 frame is a frame (padded to 2x2); a frame with no pixels is not
  viz.write_video(tmp_path / "one.mp4", np.full((2, 1, 1, 3), 200, np.uint8))
  back, _ = _read_video(tmp_path / "one.mp4")
  assert back.shape == (2, 2, 2, 3) and abs(int(back.mean()) - 200) < 20
  with pytest.raises(ValueError, match="frame 0 has shape"):
    viz.write_video(tmp_path / "none.mp4", np.zeros((1, 4, 0, 3), np.uint8))


def test_write_video_takes_rates_mpeg4_cannot_time_exactly(tmp_path):
  # 119.8765 frames/s (a variable-rate video's average, or --fps): OpenCV's writer refused the
  # time base 1000/119877 (above MPEG-4's 65535), after a whole sav-jax infer run
  for fps, written in ((119.8765, 119.88), (65.6789, 65.68), (29.876543, 29.877)):
    viz.write_video(tmp_path / "v.mp4", np.zeros((2, 4, 4, 3), np.uint8), fps=fps)
    back, got = _read_video(tmp_path / "v.mp4")
    assert len(back) == 2 and got == pytest.approx(written, abs=1e-6), (fps, got)
  assert viz.mp4v_fps(25.0) == 25.0 and viz.mp4v_fps(65534.5) == 65534.0


def test_write_video_scales_tall_frames_to_fit(tmp_path):
  # 8200x1: scaled by 8190 / 8200 to 8190 rows and (at least) 1 column, padded to 2
  tall = np.zeros((1, 8200, 1, 3), np.uint8)
  tall[:, 4100:] = 255
  with pytest.warns(UserWarning, match=r"frames of 8200x1 are scaled to 8190x1"):
    viz.write_video(tmp_path / "tall.mp4", tall, fps=5)
  back, _ = _read_video(tmp_path / "tall.mp4")
  assert back.shape == (1, 8190, 2, 3)
  assert back[0, :4000].max() < 40 and back[0, 4200:8000].min() > 215  # the content, scaled
  with pytest.warns(UserWarning, match=r"frames of 1x8200 are scaled to 1x8190"):
    viz.write_video(tmp_path / "wide.mp4", tall.transpose(0, 2, 1, 3), fps=5)
  assert _read_video(tmp_path / "wide.mp4")[0].shape == (1, 2, 8190, 3)


def test_write_video_refuses_names_it_cannot_write(tmp_path):
  frames = np.zeros((1, 4, 4, 3), np.uint8)
  with pytest.raises(ValueError, match="write_video writes mp4v video files"):
    viz.write_video(tmp_path / "v.png", frames)
  with pytest.raises(ValueError, match="name is not UTF-8 text"):  # (OpenCV crashed on it)
    viz.write_video(tmp_path / "caf\udce9.mp4", frames)
  assert list(tmp_path.iterdir()) == []
  # A folder of the video's name: refused before any frame is taken (the rename failed once
  # the whole video was written, an iterator's frames consumed, naming the temporary file).
  (tmp_path / "out.mp4").mkdir()
  taken = []
  def stream():
    for f in frames:
      taken.append(f)
      yield f
  with pytest.raises(IsADirectoryError, match=r"out\.mp4 is a folder; name the video file"):
    viz.write_video(tmp_path / "out.mp4", stream())
  assert taken == [] and sorted(p.name for p in tmp_path.iterdir()) == ["out.mp4"]


def test_points_and_ply_bytes_by_hand(tmp_path):
  # Z = fx B / d, X = (u - cx) Z / fx, Y = (v - cy) Z / fy, rows in raster order
  d = np.array([[4.0, 8.0], [2.0, 16.0]], np.float32)
  rgb = np.array([[[10, 20, 30], [40, 50, 60]], [[70, 80, 90], [100, 110, 120]]], np.float32)
  fx, fy, cx, cy, b = 80.0, 40.0, 0.5, 0.25, 0.1
  xyz, col = viz.disparity_to_points(d, rgb, fx=fx, fy=fy, cx=cx, cy=cy, baseline=b,
                                     valid=np.array([[1.0, 0.5], [0.51, 1.0]]))
  want = [[(u - cx) * (fx * b / d[v, u]) / fx, (v - cy) * (fx * b / d[v, u]) / fy,
           fx * b / d[v, u]] for v, u in ((0, 0), (1, 0), (1, 1))]  # (0, 1): weight 0.5
  np.testing.assert_allclose(xyz, want, rtol=1e-6)
  assert xyz.dtype == np.float32 and col.dtype == np.uint8
  np.testing.assert_array_equal(col, [[10, 20, 30], [70, 80, 90], [100, 110, 120]])
  # The PLY's bytes as any reader sees them: an ASCII header, then 15-byte little-endian
  # records x, y, z (float32) and red, green, blue (uint8); one comment line per string
  assert viz.write_ply(tmp_path / "p.ply", xyz, col, comments="unit: m") == 3
  header, body = (tmp_path / "p.ply").read_bytes().split(b"end_header\n", 1)
  assert header.decode("ascii").splitlines()[2:4] == ["comment unit: m", "element vertex 3"]
  rec = np.frombuffer(body, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"),
                                      ("g", "u1"), ("b", "u1")]))
  np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], -1), xyz)
  np.testing.assert_array_equal(np.stack([rec["r"], rec["g"], rec["b"]], -1), col)
  # one point of shape [3] is a cloud of one; disparities <= 0 give no depth, no warning
  assert viz.write_ply(tmp_path / "one.ply", xyz[0], col[0]) == 1
  np.testing.assert_array_equal(viz.read_ply(tmp_path / "one.ply")[0], xyz[:1])
  with np.errstate(all="raise"):
    z = viz.depth_from_disparity(np.array([[0.0, -1.0, 5.0]], np.float32), fx=10.0, baseline=2.0)
  np.testing.assert_array_equal(z, [[0.0, 0.0, 4.0]])


def test_formats_and_frames_refused_with_their_reason(tmp_path):
  for bad in (np.array([True, False]), np.array([1 + 2j])):
    with pytest.raises(ValueError, match="expected uint8 or numbers in 0..255"):
      viz.as_uint8_image(bad)
  with pytest.raises(ValueError, match="NaN or inf"):
    viz.as_uint8_image(np.array([1.0, np.nan]))
  with pytest.raises(ValueError, match="no frames to write"):
    viz.write_video(tmp_path / "e.mp4", [])
  with pytest.raises(ValueError, match="no frames to write"):
    viz.write_video(tmp_path / "e.mp4", iter([]))
  assert list(tmp_path.iterdir()) == []
  with pytest.raises(ValueError, match="valid mask shape"):  # (not broadcast over the rows)
    viz.disparity_to_points(np.ones((2, 3)), np.zeros((2, 3, 3), np.uint8), fx=1.0, fy=1.0,
                            cx=1.0, cy=0.5, baseline=1.0, valid=np.ones((1, 3)))
  with pytest.raises(ValueError, match="16-bit PNG disparity file stores"):
    viz.write_png16(tmp_path / "rgb.png", np.ones((2, 3, 3)))
  # inf is not a disparity: stored as 0 (invalid), not as the largest one
  assert viz.write_png16(tmp_path / "inf.png", np.array([[np.inf, -np.inf, 2.0]])) == 0
  np.testing.assert_array_equal(viz.read_png16(tmp_path / "inf.png")[1], [[False, False, True]])
  # a big-endian PLY of write_ply's vertices is refused, not read as little-endian values
  viz.write_ply(tmp_path / "big.ply", np.ones((1, 3)), np.full((1, 3), 9, np.uint8))
  header, body = (tmp_path / "big.ply").read_bytes().split(b"end_header\n")
  (tmp_path / "big.ply").write_bytes(header.replace(b"little", b"big") + b"end_header\n" + body)
  with pytest.raises(ValueError, match="unsupported PLY format 'format binary_big_endian 1.0'"):
    viz.read_ply(tmp_path / "big.ply")


def test_colorbar_unit_follows_the_last_label_only():
  with_unit, without = (viz.colorbar(2.0, 12.0, length=201, unit=u) for u in ("px", ""))
  differ = np.nonzero((with_unit != without).any(axis=(0, 2)))[0]
  assert len(differ) and differ.min() > 160  # right of the 10 tick (column 160): "12 px"
  assert differ.max() >= 195  # the label ends at the bar's right edge
  # and is drawn whole: it starts its own width left of the edge (centred on the tick at
  # column 200 it would run past the edge, cut)
  width = cv2.getTextSize("12 px", cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)[0][0]
  assert differ.min() <= 201 - width + 2, (differ.min(), width)
  # so is the first, "2" under column 0: it starts at the left edge (its ink reaches past
  # half its width), not centred on the edge, half outside the bar
  width = cv2.getTextSize("2", cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)[0][0]
  ink = np.nonzero((without[-15:, :20] < 128).any(axis=(0, 2)))[0]  # (below the ticks)
  assert ink.max() > width // 2, (ink, width)


def test_map_writers_and_readers_take_names_that_are_not_utf8(tmp_path):
  """Latin-1 bytes (a zip made on Windows): write_exr refused them and read_exr called a good
  file "not an OpenEXR file" (OpenEXR's own open takes UTF-8 names only); the other formats
  are written by Python already. A video is refused with the path named."""
  odd = tmp_path / os.fsdecode(b"caf\xe9")
  odd.mkdir()
  d = np.arange(12, dtype=np.float32).reshape(3, 4) + 1
  for name, write, read in (("d.exr", viz.write_exr, viz.read_exr),
                            ("d.pfm", viz.write_pfm, viz.read_pfm),
                            ("d.png", viz.write_png16, lambda p: viz.read_png16(p)[0])):
    write(odd / name, d)
    write(tmp_path / name, d)
    assert (odd / name).read_bytes() == (tmp_path / name).read_bytes(), name
    np.testing.assert_array_equal(read(odd / name), d)
  xyz = np.ones((2, 3), np.float32)
  assert viz.write_ply(odd / "p.ply", xyz, np.zeros((2, 3), np.uint8)) == 2
  np.testing.assert_array_equal(viz.read_ply(odd / "p.ply")[0], xyz)
  with pytest.raises(ValueError, match=r"caf\\udce9/v.mp4': the video's name is not UTF-8"):
    viz.write_video(odd / "v.mp4", np.zeros((1, 2, 4, 3), np.uint8))
  assert sorted(p.name for p in odd.iterdir()) == ["d.exr", "d.pfm", "d.png", "p.ply"]


def test_read_ply_refuses_vertex_layouts_other_than_write_ply_s(tmp_path):
  # Six properties, as write_ply's, in another order or of another type: the same 15 bytes
  # a vertex would be read as the wrong fields (colours as coordinates, BGR as RGB), so
  # read_ply refuses such a header rather than count its properties only
  body = np.zeros(2, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"),
                               ("g", "u1"), ("b", "u1")])).tobytes()
  for props in (["float x", "float y", "float z", "uchar blue", "uchar green", "uchar red"],
                ["float y", "float x", "float z", "uchar red", "uchar green", "uchar blue"],
                ["float x", "float y", "float z", "char red", "uchar green", "uchar blue"]):
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 2\n"
              + "".join(f"property {p}\n" for p in props) + "end_header\n")
    (tmp_path / "o.ply").write_bytes(header.encode("ascii") + body)
    with pytest.raises(ValueError, match="PLY vertex properties .* differ from write_ply's"):
      viz.read_ply(tmp_path / "o.ply")


def test_read_ply_reads_the_vertices_of_other_writers_headers(tmp_path):
  # The PLY format as defined, not write_ply's bytes only: CRLF line ends, tokens separated by
  # any whitespace, and a face element after the vertices (a mesh) whose properties are not
  # the vertices' (x y z little-endian float32, then red green blue uint8: 15 bytes a vertex)
  header = ("ply\r\nformat binary_little_endian 1.0\r\ncomment from a mesh tool\r\n"
            "element vertex 2\r\nproperty  float x\r\nproperty float  y\r\n"
            "property\tfloat z\r\nproperty uchar red\r\nproperty uchar green\r\n"
            "property uchar blue\r\nelement face 1\r\n"
            "property list uchar int vertex_indices\r\nend_header\r\n")
  body = (struct.pack("<3f3B", 1.5, -2.0, 3.25, 10, 20, 30)
          + struct.pack("<3f3B", 0.0, 1e-3, -7.0, 255, 0, 128) + struct.pack("<B3i", 3, 0, 1, 1))
  (tmp_path / "mesh.ply").write_bytes(header.encode("ascii") + body)
  xyz, rgb = viz.read_ply(tmp_path / "mesh.ply")
  np.testing.assert_array_equal(xyz, np.array([[1.5, -2.0, 3.25], [0.0, 1e-3, -7.0]],
                                              np.float32))
  np.testing.assert_array_equal(rgb, [[10, 20, 30], [255, 0, 128]])


def test_write_exr_names_a_one_channel_map_s_channel(tmp_path):
  # `channel` names the one channel of an [H, W] map (a depth map as "Z"): stored under that
  # name, not the default "Y"
  a = np.array([[1.5, -2.0, 3.25]], np.float32)
  viz.write_exr(tmp_path / "z.exr", a, channel="Z")
  np.testing.assert_array_equal(viz.read_exr(tmp_path / "z.exr", "Z"), a)
  with pytest.raises(ValueError, match=r"has no channel 'Y' \(has \['Z'\]\)"):
    viz.read_exr(tmp_path / "z.exr", "Y")


def test_colorize_error_relative_threshold_takes_the_magnitude_of_negative_gt():
  # The relative threshold is 5% of |gt|: a negative ground truth (datasets that store the
  # right view's disparity, or signed flow) gets the same colour as its positive mirror.
  # 4 px off gt -10: min(4 / 3, 4 / (0.05 * 10)) = min(1.33, 8) = 1.33 -> bin (1, 2], the
  # first outlier colour; a signed gt made 4 / -0.5 = -8, coloured as a perfect pixel
  colours = [tuple(c) for c in viz.KITTI_ERROR_COLORS]
  pred = np.array([[-14.0, 14.0]], np.float32)
  gt = np.array([[-10.0, 10.0]], np.float32)
  assert [tuple(c) for c in viz.colorize_error(pred, gt)[0]] == [colours[5], colours[5]]


def test_colorize_level_is_255_steps_over_the_range():
  # range 2..12 has 255 steps of 10 / 255 px: 9.5 px is round(7.5 * 25.5) = round(191.25) =
  # level 191 (a 256-step scale would give round(192.0) = 192)
  lut = _lut()
  d = np.array([[9.5, 3.0]], np.float32)  # 3.0: round(25.5) = 26 (half to even)
  np.testing.assert_array_equal(viz.colorize(d, 2.0, 12.0)[0], lut[[191, 26]])


def test_error_colours_and_bins_are_kittis_devkit_table():
  # KITTI stereo devkit (io_disp.h, errorImage): rows (lo, hi, R, G, B) of the error in
  # multiples of the 3 px / 5% threshold, copied from there, not from viz
  devkit = ((0, 0.0625, 49, 54, 149), (0.0625, 0.125, 69, 117, 180),
            (0.125, 0.25, 116, 173, 209), (0.25, 0.5, 171, 217, 233), (0.5, 1, 224, 243, 248),
            (1, 2, 254, 224, 144), (2, 4, 253, 174, 97), (4, 8, 244, 109, 67),
            (8, 16, 215, 48, 39), (16, 1e9, 165, 0, 38))
  assert viz.KITTI_ERROR_BINS == tuple(float(r[0]) for r in devkit)
  assert viz.KITTI_ERROR_COLORS == tuple(r[2:] for r in devkit)
  # and colorize_error uses them: 3 px per unit (rel_thresh=None) -> 20 px is 6.7 (bin 7),
  # 30 px is 10 (bin 8), 60 px is 20 (bin 9, the last, dark red)
  gt = np.full((1, 3), 100.0, np.float32)
  rgb = viz.colorize_error(gt + np.array([[20.0, 30.0, 60.0]], np.float32), gt, rel_thresh=None)
  assert [tuple(c) for c in rgb[0]] == [devkit[k][2:] for k in (7, 8, 9)]


def test_a_baseline_of_zero_or_below_is_refused():
  """Z = fx * baseline / d: a baseline <= 0 gives no positive depth anywhere (an empty point
  cloud without a word), so it is refused by name, as fx and fy are."""
  d = np.full((2, 3), 4.0, np.float32)
  rgb = np.zeros((2, 3, 3), np.uint8)
  for b in (0.0, -0.1):
    with pytest.raises(ValueError, match=rf"^baseline must be a finite positive number, got {b}"):
      viz.depth_from_disparity(d, fx=100.0, baseline=b)
    with pytest.raises(ValueError, match=r"^disparity_to_points: baseline must be a finite "
                                         rf"positive number, got {b}"):
      viz.disparity_to_points(d, rgb, fx=100.0, fy=100.0, cx=1.0, cy=0.5, baseline=b)

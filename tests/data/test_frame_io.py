"""File decoders of sav_jax.data.frame_io, checked value by value against the formats.

Every fixture file is written with the library its users' files come from (OpenCV for
PNG/JPEG, OpenEXR, h5py, numpy) or byte by byte from the format's specification
(PFM, Sintel .cam), never with the reader under test.
"""

import struct
import sys
import warnings

import cv2
import numpy as np
import pytest

from sav_jax.data import frame_io

RNG = np.random.default_rng(0)


def _pfm_bytes(arr, little_endian, kind):
  """PFM by the spec: header lines, then float32 rows from the bottom row up."""
  h, w = arr.shape[:2]
  scale = b"-1.000000" if little_endian else b"2.5"  # only the sign matters
  rows = b"".join(struct.pack(("<" if little_endian else ">") + "f" * arr[y].size,
                              *arr[y].ravel()) for y in reversed(range(h)))
  return kind + b"\n" + b"%d %d\n" % (w, h) + scale + b"\n" + rows


@pytest.mark.parametrize("little_endian", [True, False])
def test_pfm_one_channel_both_endiannesses_and_row_order(tmp_path, little_endian):
  arr = RNG.normal(size=(5, 7)).astype(np.float32) * 100
  arr[0, 0] = 0.0  # marks the top-left corner
  path = tmp_path / "d.pfm"
  path.write_bytes(_pfm_bytes(arr, little_endian, b"Pf"))
  out = frame_io.read_pfm(path)
  assert out.dtype == np.float32 and out.shape == (5, 7)
  np.testing.assert_array_equal(out, arr)  # top row first, native byte order
  np.testing.assert_array_equal(frame_io.read_pfm_disparity(path), arr)


@pytest.mark.parametrize("little_endian", [True, False])
def test_pfm_three_channels(tmp_path, little_endian):
  arr = RNG.normal(size=(4, 6, 3)).astype(np.float32)
  path = tmp_path / "f.pfm"
  path.write_bytes(_pfm_bytes(arr, little_endian, b"PF"))
  np.testing.assert_array_equal(frame_io.read_pfm(path), arr)
  np.testing.assert_array_equal(frame_io.read_pfm_disparity(path), arr[..., 0])


@pytest.mark.parametrize("little_endian", [True, False])
def test_write_pfm_matches_the_spec(tmp_path, little_endian):
  arr = RNG.normal(size=(3, 4)).astype(np.float32)
  frame_io.write_pfm(tmp_path / "a.pfm", arr, little_endian=little_endian)
  data = (tmp_path / "a.pfm").read_bytes()
  header, payload = data.split(b"\n", 3)[:3], data.split(b"\n", 3)[3]
  assert header[:2] == [b"Pf", b"4 3"]
  assert (float(header[2]) < 0) == little_endian
  assert payload == _pfm_bytes(arr, little_endian, b"Pf").split(b"\n", 3)[3]


def test_pfm_errors(tmp_path):
  with pytest.raises(FileNotFoundError, match="missing.pfm"):
    frame_io.read_pfm(tmp_path / "missing.pfm")
  (tmp_path / "bad.pfm").write_bytes(b"P6\n4 3\n255\n" + bytes(36))
  with pytest.raises(ValueError, match="not a PFM"):
    frame_io.read_pfm(tmp_path / "bad.pfm")
  (tmp_path / "hdr.pfm").write_bytes(b"Pf\nfour 3\n-1\n" + bytes(48))
  with pytest.raises(ValueError, match="malformed PFM header"):
    frame_io.read_pfm(tmp_path / "hdr.pfm")
  (tmp_path / "short.pfm").write_bytes(b"Pf\n4 3\n-1\n" + bytes(40))
  with pytest.raises(ValueError, match="truncated.*short.pfm"):
    frame_io.read_pfm(tmp_path / "short.pfm")
  # A NaN scale (it would pick the byte order), an empty image, a header smaller than the data
  for name, header in (("nan", b"Pf\n4 3\nnan\n"), ("empty", b"Pf\n0 0\n-1\n")):
    (tmp_path / f"{name}.pfm").write_bytes(header + bytes(48))
    with pytest.raises(ValueError, match=f"malformed PFM header.*{name}.pfm"):
      frame_io.read_pfm(tmp_path / f"{name}.pfm")
  (tmp_path / "long.pfm").write_bytes(b"Pf\n2 3\n-1\n" + bytes(48))
  with pytest.raises(ValueError, match=r"more data than its header's 2x3 float32 values "
                     r"\(48 bytes, 24 expected\): .*long.pfm"):
    frame_io.read_pfm(tmp_path / "long.pfm")
  # Blank lines inside the header, and width, height and scale on one line, are read.
  values = np.arange(6, dtype="<f4")
  for header in (b"Pf\n\n3 2\n\n-1.0\n", b"Pf\n3 2 -1.0\n"):
    (tmp_path / "ok.pfm").write_bytes(header + values.tobytes())
    np.testing.assert_array_equal(frame_io.read_pfm(tmp_path / "ok.pfm"),
                                  values.reshape(2, 3)[::-1])


def test_npy_and_npz_hold_real_numbers(tmp_path):
  np.save(tmp_path / "s.npy", np.array([["a"] * 3] * 2))
  np.save(tmp_path / "c.npy", np.ones((2, 3), np.complex64))  # numpy would drop the imaginary
  for name in ("s", "c"):
    with pytest.raises(ValueError, match=fr"{name}\.npy: holds .* values, not real numbers"):
      frame_io.read_npy(tmp_path / f"{name}.npy")
  np.savez(tmp_path / "cam.npz", K=np.array([["x"] * 3] * 3), T=np.eye(4))
  with pytest.raises(ValueError, match=r"cam\.npz, array 'K': holds <U1 values"):
    frame_io.read_npz(tmp_path / "cam.npz")
  np.save(tmp_path / "ok.npy", np.arange(6, dtype=np.uint16).reshape(2, 3))
  assert frame_io.read_npy(tmp_path / "ok.npy").dtype == np.uint16


def test_read_image_colour_grey_alpha_and_16_bit(tmp_path):
  rgb = RNG.integers(0, 256, (6, 9, 3), dtype=np.uint8)
  cv2.imwrite(str(tmp_path / "c.png"), rgb[..., ::-1])  # OpenCV writes BGR
  np.testing.assert_array_equal(frame_io.read_image(tmp_path / "c.png"), rgb)
  grey = rgb[..., 0]
  cv2.imwrite(str(tmp_path / "g.png"), grey)
  np.testing.assert_array_equal(frame_io.read_image(tmp_path / "g.png"),
                                np.repeat(grey[..., None], 3, axis=2))
  bgra = np.concatenate([rgb[..., ::-1], np.full((6, 9, 1), 7, np.uint8)], axis=2)
  cv2.imwrite(str(tmp_path / "a.png"), bgra)
  np.testing.assert_array_equal(frame_io.read_image(tmp_path / "a.png"), rgb)
  cv2.imwrite(str(tmp_path / "w.png"), rgb[..., ::-1].astype(np.uint16) * 257)
  np.testing.assert_array_equal(frame_io.read_image(tmp_path / "w.png"), rgb)


def test_read_image_warns_on_8bit_content_in_16bit_files(tmp_path):
  # 0..255 values in a 16-bit file read as black (high byte): said, once per folder.
  for folder in ("a", "b"):
    (tmp_path / folder).mkdir()
    for i in range(2):
      cv2.imwrite(str(tmp_path / folder / f"{i}.png"), np.full((4, 5), 200, np.uint16))
  with pytest.warns(UserWarning, match=r"a/0\.png is a 16-bit image whose values all fit in "
                    r"0\.\.255 \(max 200\)"):
    assert frame_io.read_image(tmp_path / "a" / "0.png").max() == 0
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    frame_io.read_image(tmp_path / "a" / "1.png")
    frame_io.read_image(tmp_path / "b" / "0.png")
    cv2.imwrite(str(tmp_path / "full.png"), np.full((4, 5), 40000, np.uint16))
    assert frame_io.read_image(tmp_path / "full.png").max() == 40000 >> 8
  assert [str(w.message).split(" is ")[0] for w in caught] == [str(tmp_path / "b" / "0.png")]


def test_read_image_jpeg_and_errors(tmp_path):
  rgb = np.zeros((16, 16, 3), np.uint8)
  rgb[..., 0], rgb[..., 2] = 200, 40
  cv2.imwrite(str(tmp_path / "j.jpg"), rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
  out = frame_io.read_image(tmp_path / "j.jpg")
  assert out.shape == (16, 16, 3) and np.abs(out.astype(int) - rgb).max() <= 3
  with pytest.raises(FileNotFoundError, match="nope.png"):
    frame_io.read_image(tmp_path / "nope.png")
  (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
  with pytest.raises(ValueError, match="corrupt.png"):
    frame_io.read_image(tmp_path / "corrupt.png")


@pytest.mark.parametrize("progressive", [False, True])
def test_read_image_refuses_a_jpeg_cut_short(tmp_path, progressive):
  """`cv2.imread` decodes a truncated JPEG without an error (grey rows, a warning on stderr);
  the reader refuses it by its missing end marker, even when an embedded thumbnail's end
  marker comes earlier in the file, and takes bytes after a complete file's end, markers
  among them (a "motion photo": a video appended to the JPEG)."""
  rgb = RNG.integers(0, 256, (64, 96, 3), dtype=np.uint8)
  flags = [cv2.IMWRITE_JPEG_QUALITY, 95, cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)]
  data = cv2.imencode(".jpg", rgb[..., ::-1], flags)[1].tobytes()
  thumb = cv2.imencode(".jpg", rgb[::8, ::8, ::-1])[1].tobytes()
  app1 = b"Exif\x00\x00" + thumb  # an APP1 segment holding a whole JPEG, as EXIF does
  with_thumb = data[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + data[2:]
  for name, blob in (("plain", data), ("thumb", with_thumb)):
    (tmp_path / f"{name}.jpg").write_bytes(blob)
    whole = frame_io.read_image(tmp_path / f"{name}.jpg")
    np.testing.assert_array_equal(
        whole, cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1])
    for tail in (b"\x00" * 16, b"ftypmp42\xff\xda\x00\x08" + bytes(range(256)) * 8):
      (tmp_path / f"{name}_tail.jpg").write_bytes(blob + tail)
      np.testing.assert_array_equal(frame_io.read_image(tmp_path / f"{name}_tail.jpg"), whole)
    (tmp_path / f"{name}_cut.jpg").write_bytes(blob[:len(blob) * 2 // 3])
    assert cv2.imread(str(tmp_path / f"{name}_cut.jpg")) is not None  # what the check is for
    with pytest.raises(ValueError, match=f"{name}_cut.jpg: truncated JPEG"):
      frame_io.read_image(tmp_path / f"{name}_cut.jpg")
    for cut in (3, 5, len(blob) - 1):  # in the first segment's length, in its data, the end
      assert frame_io.is_truncated_jpeg(blob[:cut]), cut
  (tmp_path / "empty.jpg").write_bytes(b"")
  with pytest.raises(ValueError, match="empty.jpg: cannot decode"):
    frame_io.read_image(tmp_path / "empty.jpg")


def test_sintel_disparity_png_and_occlusion_mask(tmp_path):
  r, g, b = (RNG.integers(0, 256, (4, 5), dtype=np.uint8) for _ in range(3))
  r[0, 0] = g[0, 0] = b[0, 0] = 0  # d = 0: invalid even where not occluded
  cv2.imwrite(str(tmp_path / "d.png"), np.stack([b, g, r], axis=-1))
  occ = np.where(RNG.random((4, 5)) < 0.3, 255, 0).astype(np.uint8)
  occ[0, 0] = 0
  cv2.imwrite(str(tmp_path / "o.png"), occ)
  disp, valid = frame_io.read_sintel_disparity(tmp_path / "d.png", tmp_path / "o.png")
  for y in range(4):
    for x in range(5):
      expect = 4.0 * r[y, x] + g[y, x] / 64.0 + b[y, x] / 16384.0
      assert disp[y, x] == np.float32(expect)
      assert valid[y, x] == (occ[y, x] == 0 and expect > 0)
  assert disp.dtype == np.float32 and not valid[0, 0]
  cv2.imwrite(str(tmp_path / "small.png"), occ[:3])
  with pytest.raises(ValueError, match="small.png"):
    frame_io.read_sintel_disparity(tmp_path / "d.png", tmp_path / "small.png")


def test_sintel_cam(tmp_path):
  k = np.array([[1120.0, 0, 511.5], [0, 1120.0, 217.5], [0, 0, 1]])
  rt = RNG.normal(size=(3, 4))
  raw = struct.pack("<f", 202021.25) + struct.pack("<9d", *k.ravel()) + struct.pack("<12d",
                                                                                     *rt.ravel())
  (tmp_path / "f.cam").write_bytes(raw)
  k2, rt2 = frame_io.read_sintel_cam(tmp_path / "f.cam")
  np.testing.assert_array_equal(k2, k)
  np.testing.assert_array_equal(rt2, rt)
  (tmp_path / "tag.cam").write_bytes(struct.pack("<f", 1.0) + raw[4:])
  with pytest.raises(ValueError, match="wrong tag.*tag.cam"):
    frame_io.read_sintel_cam(tmp_path / "tag.cam")
  (tmp_path / "short.cam").write_bytes(raw[:50])
  with pytest.raises(ValueError, match="truncated"):
    frame_io.read_sintel_cam(tmp_path / "short.cam")


def test_16_bit_png_depth_scales(tmp_path):
  v = np.array([[0, 1, 256, 2560], [100, 65535, 12345, 7]], np.uint16)
  cv2.imwrite(str(tmp_path / "d.png"), v)
  kitti = frame_io.read_kitti_depth(tmp_path / "d.png")
  vk = frame_io.read_vkitti2_depth(tmp_path / "d.png")
  for (y, x), raw in np.ndenumerate(v):
    assert kitti[y, x] == (-1.0 if raw == 0 else np.float32(raw) / np.float32(256))
    assert vk[y, x] == (-1.0 if raw == 0 else np.float32(raw) / np.float32(100))
  assert vk[1, 1] == np.float32(655.35)
  cv2.imwrite(str(tmp_path / "eight.png"), v.astype(np.uint8))
  with pytest.raises(ValueError, match="16-bit.*eight.png"):
    frame_io.read_kitti_depth(tmp_path / "eight.png")


def test_float16_png_depth(tmp_path):
  depth = np.array([[0.0, 1e-6, 0.5, 1.25], [3.75, 100.0, 65504.0, np.inf]], np.float16)
  cv2.imwrite(str(tmp_path / "d.png"), depth.view(np.uint16))
  out = frame_io.read_float16_png(tmp_path / "d.png")
  assert out.dtype == np.float32
  np.testing.assert_array_equal(out, depth.astype(np.float32))


def test_exr(tmp_path):
  import OpenEXR as openexr  # pylint: disable=import-outside-toplevel
  z = RNG.random((5, 6)).astype(np.float32)
  rgb = RNG.random((5, 6, 3)).astype(np.float32)
  header = {"compression": openexr.ZIP_COMPRESSION, "type": openexr.scanlineimage}
  openexr.File(header, {"Z": z}).write(str(tmp_path / "z.exr"))
  # OpenEXR's binding ignores strides: hand it contiguous channel planes.
  planes = {c: np.ascontiguousarray(rgb[..., i]) for i, c in enumerate("RGB")}
  openexr.File(header, {**planes, "Z": z}).write(str(tmp_path / "rgbz.exr"))
  np.testing.assert_array_equal(frame_io.read_exr(tmp_path / "z.exr"), z)
  np.testing.assert_array_equal(frame_io.read_exr(tmp_path / "rgbz.exr"), rgb)
  np.testing.assert_array_equal(frame_io.read_exr(tmp_path / "rgbz.exr", "Z"), z)
  with pytest.raises(ValueError, match="no channel 'Q'"):
    frame_io.read_exr(tmp_path / "rgbz.exr", "Q")
  (tmp_path / "bad.exr").write_bytes(b"not an exr")
  with pytest.raises(ValueError, match="bad.exr"):
    frame_io.read_exr(tmp_path / "bad.exr")
  (tmp_path / "cut.exr").write_bytes((tmp_path / "z.exr").read_bytes()[:-100])  # pixels cut
  with pytest.raises(ValueError, match="cannot read EXR file .*cut.exr: not an OpenEXR file, "
                     "or one cut short or corrupt"):
    frame_io.read_exr(tmp_path / "cut.exr")


def test_npz_that_inflates_far_is_refused_before_it_is_read(tmp_path):
  """A 4 MB camera .npz inflated to a 4 GB array (the converter's .npz reader had a bound:
  the same one now)."""
  np.savez_compressed(tmp_path / "cam.npz", K=np.eye(3), Z=np.zeros(5_000_000))  # 40 MB, ~40 kB
  with pytest.raises(ValueError, match=r"cannot read npz file .*cam\.npz: ValueError: .*cam\.npz: "
                     r"zip record 'Z\.npy' inflates \d+ bytes to 40000128 \(\d+x, more than "
                     r"100x\): not a dataset's arrays \(camera and depth arrays shrink little: "
                     r"a damaged"):
    frame_io.read_npz(tmp_path / "cam.npz")
  np.savez_compressed(tmp_path / "ok.npz", K=np.eye(3), Z=np.zeros(100_000))  # 800 kB: fine
  assert sorted(frame_io.read_npz(tmp_path / "ok.npz")) == ["K", "Z"]


def test_an_npy_too_large_for_memory_names_the_file(tmp_path, monkeypatch):
  np.save(tmp_path / "d.npy", np.zeros(3, np.float32))

  def out_of_memory(*args, **kwargs):
    raise MemoryError("Unable to allocate 74.5 GiB")

  monkeypatch.setattr(np, "load", out_of_memory)
  with pytest.raises(MemoryError, match=r"d\.npy: out of host memory reading the npy file"):
    frame_io.read_npy(tmp_path / "d.npy")


def test_an_npz_under_an_npy_name_and_the_reverse_are_named(tmp_path):
  """np.load opens either format whatever the file's name (np.savez to an open file named
  .npy keeps that name): an archive as depth or disparity, or one array as an Infinigen camera,
  went through as an AttributeError or TypeError naming no file."""
  with open(tmp_path / "d.npy", "wb") as f:
    np.savez(f, depth=np.ones((2, 3), np.float32))
  with pytest.raises(ValueError, match=r"d\.npy: an \.npz archive \(of depth\) under an \.npy "
                     r"name; expected one array as np\.save writes it"):
    frame_io.read_npy(tmp_path / "d.npy")
  with pytest.raises(ValueError, match=r"d\.npy: an \.npz archive"):
    frame_io.read_depth_npy(tmp_path / "d.npy")
  with open(tmp_path / "cam.npz", "wb") as f:
    np.save(f, np.eye(3))
  with pytest.raises(ValueError, match=r"cam\.npz: a single \.npy array of shape \(3, 3\) under "
                     r"an \.npz name"):
    frame_io.read_npz(tmp_path / "cam.npz")


def test_npy_and_npz(tmp_path):
  arr = RNG.random((3, 4)).astype(np.float32)
  np.save(tmp_path / "d.npy", arr)
  np.testing.assert_array_equal(frame_io.read_npy(tmp_path / "d.npy"), arr)
  np.savez(tmp_path / "c.npz", K=np.eye(3), T=np.eye(4))
  assert sorted(frame_io.read_npz(tmp_path / "c.npz")) == ["K", "T"]
  (tmp_path / "bad.npy").write_bytes(b"\x93NUMPY garbage")
  with pytest.raises(ValueError, match="bad.npy"):
    frame_io.read_npy(tmp_path / "bad.npy")
  # Damaged archives (a partial download, a flipped byte) are named whatever numpy, zipfile
  # or zlib raise for them (BadZipFile, zlib.error, TokenError went through unnamed).
  np.savez_compressed(tmp_path / "z.npz", K=RNG.random((3, 3)), T=RNG.random((4, 4)))
  data = (tmp_path / "z.npz").read_bytes()
  for i in range(0, len(data), 3):
    cut, flipped = data[:i], data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:]
    for damaged, may_pass in ((cut, False), (flipped, True)):
      (tmp_path / "damaged.npz").write_bytes(damaged)
      try:
        frame_io.read_npz(tmp_path / "damaged.npz")  # a byte zip does not check may pass
      except ValueError as e:
        assert "damaged.npz" in str(e)
      else:  # a cut loses the central directory at the end: never readable
        assert may_pass, f"an archive cut at byte {i} of {len(data)} was read"
  header = (tmp_path / "d.npy").read_bytes()
  for i in range(8, 64):
    (tmp_path / "damaged.npy").write_bytes(header[:i] + b"(" + header[i + 1:])
    try:
      frame_io.read_npy(tmp_path / "damaged.npy")
    except ValueError as e:
      assert "damaged.npy" in str(e)
    else:  # a "(" anywhere else breaks the header's dict literal
      assert header[i:i + 1] == b"(", f"a header with '(' at byte {i} was read"


def test_hdf5_dsp5(tmp_path, monkeypatch):
  import h5py  # pylint: disable=import-outside-toplevel
  disp = RNG.random((4, 6)).astype(np.float32)
  disp[1, 2] = np.nan
  with h5py.File(tmp_path / "d.dsp5", "w") as f:
    f.create_dataset("disparity", data=disp)
  np.testing.assert_array_equal(frame_io.read_dsp5(tmp_path / "d.dsp5"), disp)
  with pytest.raises(ValueError, match="no dataset 'depth'"):
    frame_io.read_hdf5(tmp_path / "d.dsp5", "depth")
  (tmp_path / "bad.dsp5").write_bytes(b"garbage")
  with pytest.raises(ValueError, match="bad.dsp5"):
    frame_io.read_dsp5(tmp_path / "bad.dsp5")
  with h5py.File(tmp_path / "group.dsp5", "w") as f:
    f.create_group("disparity")  # a group of that name is not the dataset
  with pytest.raises(ValueError, match="group.dsp5 has no dataset 'disparity'"):
    frame_io.read_dsp5(tmp_path / "group.dsp5")
  with h5py.File(tmp_path / "rgb.dsp5", "w") as f:
    f.create_dataset("disparity", data=np.stack([disp] * 3, axis=-1))
  with pytest.raises(ValueError, match=r"rgb.dsp5: dataset 'disparity' has shape \(4, 6, 3\)"):
    frame_io.read_dsp5(tmp_path / "rgb.dsp5")
  monkeypatch.setitem(sys.modules, "h5py", None)  # import now fails as if absent
  with pytest.raises(ImportError, match="needs h5py"):
    frame_io.read_dsp5(tmp_path / "d.dsp5")


def test_depth_to_disparity_rules():
  s = 100.0
  depth = np.array([-1.0, 0.0, 9e-6, 1e-5, 0.5, 0.2, 2.0, np.inf, np.nan], np.float32)
  disp, valid = frame_io.depth_to_disparity(depth, s)
  expect = [0, 0, 0, s / np.float32(1e-5), 200, 500, 50, 0, 0]
  np.testing.assert_allclose(disp, expect, rtol=1e-6)
  # Z < 1e-5 -> d = 0 invalid; d >= 512 invalid; infinite or NaN depth -> d = 0 invalid.
  np.testing.assert_array_equal(valid, [0, 0, 0, 0, 1, 1, 1, 0, 0])
  assert disp.dtype == np.float32 and valid.dtype == bool
  for bad in (0.0, -1.0, np.nan, np.inf):
    with pytest.raises(ValueError, match="scale .* must be a finite positive number"):
      frame_io.depth_to_disparity(depth, bad)


def test_image_header_beyond_opencvs_pixel_limit_is_named(tmp_path):
  import struct  # pylint: disable=g-import-not-at-top
  import zlib  # pylint: disable=g-import-not-at-top
  ihdr = b"IHDR" + struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0)
  idat, iend = b"IDAT" + zlib.compress(b""), b"IEND"
  png = b"\x89PNG\r\n\x1a\n" + b"".join(
      struct.pack(">I", len(c) - 4) + c + struct.pack(">I", zlib.crc32(c))
      for c in (ihdr, idat, iend))
  (tmp_path / "huge.png").write_bytes(png)  # 65 bytes declaring 3.6e9 pixels
  with pytest.raises(ValueError, match="huge.png: cannot decode the image file"):
    frame_io.decode_image_file(tmp_path / "huge.png")


def test_pfm_data_one_value_short_or_over_is_refused_stray_bytes_pass(tmp_path):
  # Exactly W x H float32 values follow the header: one value missing is a truncated file
  # (numpy's own "buffer is smaller" error named no file), one value more a header declaring
  # fewer pixels than were written (the rows would be cut wrongly); 1-3 stray bytes after
  # the values (a trailing newline) are no pixel and are read past.
  values = np.arange(1, 7, dtype="<f4")  # 2 rows of 3, stored bottom row first
  header = b"Pf\n3 2\n-1.0\n"
  for name, data in (("short", values.tobytes()[:-4]), ("byte", values.tobytes()[:-1])):
    (tmp_path / f"{name}.pfm").write_bytes(header + data)
    with pytest.raises(ValueError, match=fr"truncated PFM file \({len(data)} bytes of data, 24 "
                       fr"expected\): .*{name}\.pfm"):
      frame_io.read_pfm(tmp_path / f"{name}.pfm")
  (tmp_path / "over.pfm").write_bytes(header + values.tobytes() + struct.pack("<f", 7.0))
  with pytest.raises(ValueError, match=r"more data than its header's 3x2 float32 values "
                     r"\(28 bytes, 24 expected\)"):
    frame_io.read_pfm(tmp_path / "over.pfm")
  for stray in (b"\n", b"\n\n\n"):
    (tmp_path / "stray.pfm").write_bytes(header + values.tobytes() + stray)
    np.testing.assert_array_equal(frame_io.read_pfm(tmp_path / "stray.pfm"),
                                  [[4, 5, 6], [1, 2, 3]])


def test_pfm_zero_scale_and_other_magic_numbers_are_refused(tmp_path):
  # The scale's sign is the byte order: 0 (or -0) gives none, and the official reader would
  # take it as big-endian silently. PGM/PPM (P5, P6) and case variants are not PFM.
  values = np.arange(6, dtype="<f4").tobytes()
  for scale in (b"0", b"-0.0", b"0.0"):
    (tmp_path / "zero.pfm").write_bytes(b"Pf\n3 2\n" + scale + b"\n" + values)
    with pytest.raises(ValueError, match=r"malformed PFM header .*zero\.pfm"):
      frame_io.read_pfm(tmp_path / "zero.pfm")
  for magic in (b"P5", b"P6", b"pf", b"pF", b"PF4"):
    (tmp_path / "magic.pfm").write_bytes(magic + b"\n3 2\n-1.0\n" + values)
    with pytest.raises(ValueError, match=r"not a PFM file .*magic\.pfm"):
      frame_io.read_pfm(tmp_path / "magic.pfm")


def test_sintel_occlusion_any_non_zero_value_is_occluded(tmp_path):
  # The official mask is `occlusion == 0`: a value of 1 (not only 255) is occluded, so a
  # threshold at mid-grey would count faintly marked pixels as valid ground truth.
  d = np.full((1, 6, 3), (0, 0, 3), np.uint8)  # BGR: R = 3, d = 12 px everywhere
  cv2.imwrite(str(tmp_path / "d.png"), d)
  cv2.imwrite(str(tmp_path / "o.png"), np.array([[0, 1, 2, 127, 128, 255]], np.uint8))
  disp, valid = frame_io.read_sintel_disparity(tmp_path / "d.png", tmp_path / "o.png")
  np.testing.assert_array_equal(disp, np.full((1, 6), 12.0, np.float32))
  np.testing.assert_array_equal(valid, [[True, False, False, False, False, False]])


def test_sintel_cam_one_value_short_is_truncated(tmp_path):
  # 4 + 21 * 8 bytes: a file missing its last float64 (t_z) is named as truncated, not
  # left to numpy's "buffer is smaller than requested size" naming no file.
  raw = struct.pack("<f", 202021.25) + struct.pack("<21d", *range(21))
  (tmp_path / "f.cam").write_bytes(raw)
  k, rt = frame_io.read_sintel_cam(tmp_path / "f.cam")
  assert k[0, 0] == 0 and k[2, 2] == 8 and rt[0, 0] == 9 and rt[2, 3] == 20
  for cut in (8, 1):
    (tmp_path / "short.cam").write_bytes(raw[:-cut])
    with pytest.raises(ValueError, match=r"truncated Sintel \.cam file .*short\.cam"):
      frame_io.read_sintel_cam(tmp_path / "short.cam")


def test_16_bit_depth_png_of_several_channels_is_refused(tmp_path):
  # A 16-bit colour PNG (a depth visualisation saved in its place) has 3 channels: refused
  # naming the file, not returned as [H, W, 3] "depth" that fails later without it.
  cv2.imwrite(str(tmp_path / "rgb.png"), np.full((2, 3, 3), 1000, np.uint16))
  for read in (frame_io.read_kitti_depth, frame_io.read_vkitti2_depth,
               frame_io.read_float16_png):
    with pytest.raises(ValueError, match=r"expected a 1-channel 16-bit PNG, got uint16 with "
                       r"shape \(2, 3, 3\) in .*rgb\.png"):
      read(tmp_path / "rgb.png")


def test_dense_valid_rule_at_its_edges():
  # The official dense rule `d != 0 and |d| < 512`: a negative disparity counts (|d|), 512
  # itself does not, nor 0, NaN or inf.
  d = np.array([-3.0, 0.0, -0.0, 3.0, 511.5, 512.0, -511.5, -512.0, 600.0, np.nan, np.inf,
                -np.inf], np.float32)
  np.testing.assert_array_equal(frame_io.dense_valid(d),
                                [1, 0, 0, 1, 1, 0, 1, 0, 0, 0, 0, 0])
  np.testing.assert_array_equal(frame_io.dense_valid(d, max_disparity=4.0),
                                [1, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0])


def test_depth_to_disparity_of_exactly_512_px_is_invalid():
  # d < 512, strict (the official `disp < 512`): scale 1024 over depth 2 m gives 512 px.
  disp, valid = frame_io.depth_to_disparity(np.array([[2.0, 4.0, 2.0 + 2**-20]], np.float32),
                                            1024.0)
  np.testing.assert_array_equal(disp[0, :2], [512.0, 256.0])
  np.testing.assert_array_equal(valid, [[False, True, True]])


def test_sintel_disparity_png_of_16_bits_is_refused(tmp_path):
  # The encoding is of 8-bit channels (4 R + G / 64 + B / 16384): 16-bit channels would give
  # disparities 256 times too large, read as if valid.
  cv2.imwrite(str(tmp_path / "d.png"), np.full((2, 3, 3), 3, np.uint16))
  cv2.imwrite(str(tmp_path / "o.png"), np.zeros((2, 3), np.uint8))
  with pytest.raises(ValueError, match=r"expected an 8-bit RGB Sintel disparity PNG, got "
                     r"uint16 .*d\.png"):
    frame_io.read_sintel_disparity(tmp_path / "d.png", tmp_path / "o.png")


def test_16_bit_image_warning_edge_is_255(tmp_path):
  # A 16-bit frame whose maximum is 255 reads as black (255 >> 8 = 0): warned; one reaching
  # 256 keeps a non-zero high byte somewhere and is not.
  for folder, top, warned in (("at", 255, True), ("over", 256, False)):
    (tmp_path / folder).mkdir()
    img = np.zeros((2, 3), np.uint16)
    img[1, 2] = top
    cv2.imwrite(str(tmp_path / folder / "0.png"), img)
    with warnings.catch_warnings(record=True) as caught:
      warnings.simplefilter("always")
      out = frame_io.read_image(tmp_path / folder / "0.png")
    assert len(caught) == int(warned), folder
    assert out[1, 2].tolist() == [top >> 8] * 3


def test_write_pfm_takes_one_channel_arrays_as_pf(tmp_path):
  # [H, W, 1] (a disparity with its channel axis kept) is the one-channel `Pf` of [H, W].
  arr = np.arange(6, dtype=np.float32).reshape(2, 3, 1)
  frame_io.write_pfm(tmp_path / "a.pfm", arr)
  assert (tmp_path / "a.pfm").read_bytes() == _pfm_bytes(arr[..., 0], True, b"Pf").replace(
      b"-1.000000", b"-1.0")

"""Decoders for the image, disparity, depth and camera files of the stereo datasets.

Every reader takes a path, returns numpy arrays and raises a clear error naming the
file: FileNotFoundError when it does not exist, ValueError when it cannot be decoded
or its content contradicts the format. Nothing here writes into a dataset directory
(`write_pfm` is for tests and exports).

Conventions (`docs/datasets.md`, section 0):
  * images are uint8 RGB `[H, W, 3]`; alpha is dropped and grey is repeated to 3
    channels, as the official PIL-based loader does;
  * disparities are positive pixels of the left view (the official "flow" `(-d, 0)`
    sign is not reproduced: users get +d);
  * depth is metres; readers mark "no depth" with -1 where the format has a code for
    it, and `depth_to_disparity` turns every depth below 1e-5 into d = 0 (invalid).
"""

from __future__ import annotations

import contextlib
import math
import os
import tokenize
import warnings
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np

PathLike = str | os.PathLike
# Sintel .cam and Middlebury .flo magic number.
SINTEL_TAG = np.float32(202021.25)
DEPTH_EPS = 1e-5
# Dense valid rule cap (official: |d| < 512).
MAX_DISPARITY = 512.0


def dense_valid(disp: np.ndarray, max_disparity: float = MAX_DISPARITY) -> np.ndarray:
  """The official valid rule of dense ground truth: `d != 0 and |d| < max_disparity`."""
  return (disp != 0) & (np.abs(disp) < max_disparity)


def valid_mask(valid) -> np.ndarray:
  """A ground-truth mask as bool: bool as it is; weights count above 0.5, the official
  metrics' rule (a cast to bool took any weight above 0, 0.3 too)."""
  valid = np.asarray(valid)
  return valid if valid.dtype == bool else valid > 0.5


def require_file(path: PathLike, what: str = "file") -> Path:
  """Returns `path` as a Path; raises FileNotFoundError naming it when missing."""
  path = Path(path)
  if not path.is_file():
    raise FileNotFoundError(f"{what} not found: {path}")
  return path


def read_text(path: PathLike, what: str = "file") -> str:
  """The text of a camera/calibration file (UTF-8, as the datasets ship them, without the
  byte-order mark Windows editors put first, which would glue itself to the first key); a
  missing file or one that is not UTF-8 text (UTF-16, binary) is an error naming it."""
  path = require_file(path, what)
  try:
    return path.read_text(encoding="utf-8-sig")
  except UnicodeDecodeError as e:
    raise ValueError(f"{what} {path} is not UTF-8 text ({e.reason} at byte {e.start})") from e


def is_truncated_jpeg(data: bytes) -> bool:
  """Whether `data` is a JPEG stream cut before its end-of-image marker.

  `cv2.imread` decodes such a file without an error (it warns "Premature end of JPEG file"
  on stderr and fills the missing rows with grey), so a partly downloaded frame would pass
  as a real one (`cv2.imdecode` of OpenCV 4.x returns None for it; this check does not
  depend on that). The markers are followed from the start: segments are skipped by their
  length (an EXIF thumbnail's own end marker inside APP1 is not seen), and in the
  compressed data a 0xFF byte is followed by 0x00 (a stuffed byte) or a restart marker
  unless a marker starts there. Bytes after the end marker (e.g. the video of a "motion
  photo") are not looked at. Data that does not start like a JPEG is not one: False.
  """
  if data[:3] != b"\xff\xd8\xff":
    return False
  pos, n = 2, len(data)
  while True:
    pos = data.find(b"\xff", pos)
    if pos < 0 or pos + 1 >= n:
      return True
    marker = data[pos + 1]
    if marker == 0xD9:  # end of image
      return False
    if marker in (0x00, 0x01, 0xFF) or 0xD0 <= marker <= 0xD7:  # no length follows
      pos += 1 if marker == 0xFF else 2
      continue
    if pos + 4 > n:
      return True
    pos += 2 + int.from_bytes(data[pos + 2:pos + 4], "big")


def decode_image_file(path: PathLike, what: str = "image") -> np.ndarray:
  """Decodes an image file as OpenCV does (`IMREAD_UNCHANGED`: BGR, grey or BGRA; 8 or 16
  bit), refusing what `cv2.imread` would pass silently.

  Raises:
    FileNotFoundError: no such file (named).
    ValueError: the file cannot be decoded, or is a JPEG cut short (named).
  """
  path = require_file(path, what)
  data = path.read_bytes()
  if is_truncated_jpeg(data):
    raise ValueError(f"{path}: truncated JPEG (its data ends before the end-of-image "
                     "marker: a partial download or copy?)")
  # cv2.imdecode returns None (no exception) for unreadable or truncated PNG files.
  try:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
  except cv2.error as e:  # e.g. a header declaring more than OpenCV's 2^30 pixels
    raise ValueError(f"{path}: cannot decode the {what} file ({str(e).strip()})") from e
  if img is None:
    raise ValueError(f"{path}: cannot decode the {what} file")
  return img


def read_image(path: PathLike) -> np.ndarray:
  """Reads an 8-bit PNG/JPEG image as RGB.

  16-bit images are reduced to their high byte (no dataset here ships them; the
  official `astype(uint8)` would wrap instead). A 16-bit image whose values all fit in
  0..255 (8-bit content in a 16-bit file) then turns black: that is warned, once per folder.

  Args:
    path: image file.

  Returns:
    [H, W, 3] uint8 RGB.
  """
  img = decode_image_file(path)
  if img.dtype == np.uint16:
    _warn_low_range_16bit(path, img)
    img = (img >> 8).astype(np.uint8)
  elif img.dtype != np.uint8:
    raise ValueError(f"unsupported image dtype {img.dtype} in {path}")
  if img.ndim == 2:
    img = img[..., None]
  if img.shape[2] == 1:
    return np.repeat(img, 3, axis=2)
  if img.shape[2] == 4:
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
  return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


_LOW_RANGE_WARNED: set[str] = set()


def _warn_low_range_16bit(path: PathLike, img: np.ndarray) -> None:
  """Warns (once per folder) that a 16-bit frame holding only 0..255 reads as black."""
  folder = str(Path(path).parent)
  if folder in _LOW_RANGE_WARNED:
    return
  top = int(img.max())
  if top > 255:
    return
  _LOW_RANGE_WARNED.add(folder)
  warnings.warn(f"{path} is a 16-bit image whose values all fit in 0..255 (max "
                f"{top}): 16-bit frames are read by their high byte, so it reads as "
                "black; save 8-bit content as 8-bit images (this is said once per folder)",
                stacklevel=3)


def read_png_uint16(path: PathLike) -> np.ndarray:
  """Reads a single-channel 16-bit PNG as its raw values.

  Returns:
    [H, W] uint16.
  """
  img = decode_image_file(path)
  if img.dtype != np.uint16 or img.ndim != 2:
    raise ValueError(f"expected a 1-channel 16-bit PNG, got {img.dtype} with shape "
                     f"{img.shape} in {path}")
  return img


def read_pfm(path: PathLike) -> np.ndarray:
  """Reads a PFM file (Portable Float Map).

  Header: `PF` (3 channels) or `Pf` (1 channel), then `W H`, then the scale whose
  sign gives the byte order (negative: little-endian). Rows are stored bottom to
  top, so they are flipped here.

  Returns:
    float32 [H, W] (`Pf`) or [H, W, 3] (`PF`), top row first.
  """
  path = require_file(path, "PFM file")
  with open(path, "rb") as f:
    kind = f.readline().rstrip()
    if kind not in (b"PF", b"Pf"):
      raise ValueError(f"not a PFM file (header {kind[:16]!r}): {path}")
    tokens = []  # width, height and scale; blank lines between them are tolerated
    for _ in range(8):
      line = f.readline()
      tokens += line.split()
      if not line or len(tokens) >= 3:
        break
    try:
      scale = float(tokens[2]) if len(tokens) == 3 else 0.0
    except ValueError:
      scale = 0.0
    if (len(tokens) != 3 or not all(t.isdigit() and len(t) <= 12 for t in tokens[:2])
        or not np.isfinite(scale) or scale == 0.0 or int(tokens[0]) * int(tokens[1]) == 0):
      raise ValueError(f"malformed PFM header (expected a non-zero 'width height' and a finite "
                       f"non-zero scale, got {b' '.join(tokens)[:40]!r}): {path}")
    data = f.read()
  width, height = int(tokens[0]), int(tokens[1])
  channels = 3 if kind == b"PF" else 1
  count = width * height * channels
  if len(data) < 4 * count:
    raise ValueError(f"truncated PFM file ({len(data)} bytes of data, {4 * count} "
                     f"expected): {path}")
  if len(data) >= 4 * count + 4:  # a header smaller than the image (a few stray bytes pass)
    raise ValueError(f"PFM file holds more data than its header's {width}x{height}"
                     f"{'x3' if channels == 3 else ''} float32 values ({len(data)} bytes, "
                     f"{4 * count} expected): {path}")
  dtype = np.dtype("<f4" if scale < 0 else ">f4")
  arr = np.frombuffer(data, dtype, count).reshape((height, width, channels))
  arr = np.flipud(arr).astype(np.float32)  # native byte order, top row first
  return arr[..., 0] if channels == 1 else arr


def write_pfm(path: PathLike, array: np.ndarray, little_endian: bool = True) -> None:
  """Writes a float array as PFM (rows bottom to top, scale magnitude 1).

  Args:
    path: output file.
    array: [H, W] or [H, W, 3] float.
    little_endian: byte order of the payload (scale -1 if True, +1 otherwise).
  """
  arr = np.asarray(array, np.float32)
  if arr.ndim == 3 and arr.shape[2] == 1:
    arr = arr[..., 0]
  if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)):
    raise ValueError(f"PFM holds [H, W] or [H, W, 3] arrays, got shape {arr.shape}")
  kind = b"PF" if arr.ndim == 3 else b"Pf"
  header = b"%s\n%d %d\n%s\n" % (kind, arr.shape[1], arr.shape[0],
                                 b"-1.0" if little_endian else b"1.0")
  payload = np.flipud(arr).astype("<f4" if little_endian else ">f4").tobytes()
  with open(path, "wb") as f:
    f.write(header + payload)


def read_pfm_disparity(path: PathLike) -> np.ndarray:
  """SceneFlow disparity: a PFM of positive pixels; channel 0 of a 3-channel file.

  Returns:
    [H, W] float32.
  """
  arr = read_pfm(path)
  return np.ascontiguousarray(arr[..., 0] if arr.ndim == 3 else arr)


def read_sintel_disparity(disp_path: PathLike, occ_path: PathLike):
  """Sintel stereo disparity PNG and its occlusion mask.

  `d = 4 R + G / 2**6 + B / 2**14` (computed in float64); valid where the occlusion
  PNG is 0 and d > 0 (no 512 cap; `outofframe` is not used).

  Args:
    disp_path: 8-bit RGB disparity PNG.
    occ_path: 8-bit occlusion PNG (non-zero = occluded).

  Returns:
    (disparity [H, W] float32, valid [H, W] bool).
  """
  rgb = decode_image_file(disp_path)
  if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] < 3:
    raise ValueError(f"expected an 8-bit RGB Sintel disparity PNG, got {rgb.dtype} "
                     f"{rgb.shape}: {disp_path}")
  b, g, r = (rgb[..., c].astype(np.float64) for c in range(3))  # OpenCV order is BGR
  disp = r * 4 + g / 2**6 + b / 2**14
  occ = decode_image_file(occ_path)
  if occ.ndim == 3:
    occ = occ[..., 0]
  if occ.shape != disp.shape:
    raise ValueError(f"occlusion mask {occ_path} is {occ.shape}, disparity {disp_path} "
                     f"is {disp.shape}")
  return disp.astype(np.float32), (occ == 0) & (disp > 0)


def read_sintel_cam(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
  """Sintel `.cam`: float32 tag 202021.25, 9 float64 (K), 12 float64 ([R|t]).

  Returns:
    (K [3, 3] float64, RT [3, 4] float64).
  """
  path = require_file(path, "Sintel camera file")
  raw = path.read_bytes()
  if len(raw) < 4 + 21 * 8:
    raise ValueError(f"truncated Sintel .cam file ({len(raw)} bytes): {path}")
  tag = np.frombuffer(raw, "<f4", 1)[0]
  if tag != SINTEL_TAG:
    raise ValueError(f"wrong tag {tag} in Sintel .cam file (expected {SINTEL_TAG}): {path}")
  vals = np.frombuffer(raw, "<f8", 21, offset=4)
  return vals[:9].reshape(3, 3).copy(), vals[9:].reshape(3, 4).copy()


def read_kitti_depth(path: PathLike) -> np.ndarray:
  """KITTI depth PNG: uint16, Z = v / 256 m, v = 0 (no LiDAR point) -> -1.

  Returns:
    [H, W] float32 metres.
  """
  v = read_png_uint16(path)
  return np.where(v == 0, np.float32(-1), v.astype(np.float32) / 256.0)


def read_vkitti2_depth(path: PathLike) -> np.ndarray:
  """Virtual KITTI 2 depth PNG: uint16 centimetres, Z = v / 100 m, v = 0 -> -1.

  Returns:
    [H, W] float32 metres (the sky saturates at 655.35).
  """
  v = read_png_uint16(path)
  return np.where(v == 0, np.float32(-1), v.astype(np.float32) / 100.0)


def read_float16_png(path: PathLike) -> np.ndarray:
  """Dynamic Replica depth: a 16-bit PNG whose raw bits are IEEE float16.

  Returns:
    [H, W] float32 metres.
  """
  return read_png_uint16(path).view(np.float16).astype(np.float32)


def read_npy(path: PathLike) -> np.ndarray:
  """`np.load` without pickles (Infinigen depth, TartanAir depth)."""
  path = require_file(path, "npy file")
  with _numpy_read_errors(path, "npy"):  # (MemoryError: a header declaring a huge shape)
    arr = np.load(path, allow_pickle=False)
  if not isinstance(arr, np.ndarray):  # np.load opens an .npz archive whatever its name
    names = ", ".join(arr.files)
    arr.close()
    raise ValueError(f"{path}: an .npz archive (of {names or 'no arrays'}) under an .npy name; "
                     "expected one array as np.save writes it")
  return _real_numbers(arr, path)


def read_depth_npy(path: PathLike) -> np.ndarray:
  """A float depth map `.npy` (Infinigen, TartanAir: float32 metres). Other dtypes are refused,
  naming the file: a bool array (a mask saved in its place) read as depth 1 everywhere, and
  integers (millimetres?) as tiny disparities, both counted as valid ground truth."""
  arr = read_npy(path)
  if arr.dtype.kind != "f":
    mask = " (a mask saved as depth?)" if arr.dtype == bool else ""
    raise ValueError(f"{path}: depth of dtype {arr.dtype}{mask}; expected float depth (the "
                     "dataset's float32 metres)")
  return arr


def _real_numbers(arr: np.ndarray, path, key: str | None = None) -> np.ndarray:
  """`arr` if it holds real numbers (bool, integer or float), else an error naming the file
  (strings or complex values would fail later in numpy with no file named, or lose data)."""
  if arr.dtype.kind not in "biuf":
    where = f"{path}" if key is None else f"{path}, array {key!r}"
    raise ValueError(f"{where}: holds {arr.dtype} values, not real numbers")
  return arr


def read_npz(path: PathLike) -> dict[str, np.ndarray]:
  """All arrays of an `.npz` archive (Infinigen camview: `K`, `T`)."""
  path = require_file(path, "npz file")
  with _numpy_read_errors(path, "npz"):
    loaded = np.load(path, allow_pickle=False)
  if not isinstance(loaded, np.lib.npyio.NpzFile):  # np.load reads an .npy whatever its name
    raise ValueError(f"{path}: a single .npy array of shape {loaded.shape} under an .npz name; "
                     "expected an .npz archive of named arrays (np.savez)")
  with _numpy_read_errors(path, "npz"), loaded as z:  # (its arrays are read here)
    # a few MB inflating to GB (a camera file is ~1 kB): the converter's bound on .npz
    from sav_jax.convert.pickle_reader import check_inflation  # pylint: disable=import-outside-toplevel
    check_inflation(z.zip, path, "a dataset's arrays", "camera and depth arrays shrink "
                    "little: a damaged file?", ValueError)
    arrays = {k: z[k] for k in z.files}
  return {k: _real_numbers(v, path, k) for k, v in arrays.items()}


# What numpy's readers raise for a damaged `.npy`/`.npz` (a partial download, a flipped
# byte): its own ValueErrors, zipfile's and zlib's, a header that does not tokenize or parse.
_CORRUPT_ARCHIVE = (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error,
                    NotImplementedError, tokenize.TokenError, SyntaxError)


@contextlib.contextmanager
def _numpy_read_errors(path, kind: str):
  """numpy's errors reading the `kind` ("npy", "npz") file `path` as one naming it: a damaged
  file (`_CORRUPT_ARCHIVE`) as a ValueError, a size beyond this host as a MemoryError."""
  try:
    yield
  except _CORRUPT_ARCHIVE as e:
    raise ValueError(f"cannot read {kind} file {path}: {type(e).__name__}: {e}") from e
  except MemoryError as e:
    raise MemoryError(f"{path}: out of host memory reading the {kind} file") from e


def read_exr(path: PathLike, channel: str | None = None) -> np.ndarray:
  """Reads an OpenEXR image (no SAV loader uses EXR; offered for custom data).

  Args:
    path: `.exr` file.
    channel: channel name to return; None returns the only channel, or R, G, B
      stacked when the file has them.

  Returns:
    float32 [H, W], or [H, W, 3] for RGB.
  """
  import OpenEXR  # pylint: disable=import-outside-toplevel

  path = require_file(path, "EXR file")
  try:  # (opened by Python: OpenEXR's own open took UTF-8 names only, "not an OpenEXR file")
    with open(path, "rb") as fh, OpenEXR.File(fh, separate_channels=True) as f:
      chans = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
  except (RuntimeError, ValueError) as e:  # cut short: "Invalid part index '0': file has 0 parts"
    raise ValueError(f"cannot read EXR file {path}: not an OpenEXR file, or one cut short or "
                     f"corrupt (OpenEXR: {e})") from e
  if channel is not None:
    if channel not in chans:
      raise ValueError(f"EXR file {path} has no channel {channel!r} (has {sorted(chans)})")
    return chans[channel].astype(np.float32)
  if len(chans) == 1:
    return next(iter(chans.values())).astype(np.float32)
  if {"R", "G", "B"} <= set(chans):
    return np.stack([chans[c] for c in "RGB"], axis=-1).astype(np.float32)
  raise ValueError(f"EXR file {path} has channels {sorted(chans)}: pass `channel`")


def read_hdf5(path: PathLike, key: str) -> np.ndarray:
  """Reads dataset `key` of an HDF5 file (h5py is imported only here).

  Raises:
    ImportError: h5py is not installed (the `spring` and `test` extras have it).
  """
  try:
    import h5py  # pylint: disable=import-outside-toplevel
  except ImportError as e:
    raise ImportError("reading HDF5 / Spring .dsp5 files needs h5py: "
                      "pip install h5py (or the sav-jax[spring] extra)") from e
  path = require_file(path, "HDF5 file")
  try:
    with h5py.File(path, "r") as f:
      if not isinstance(f.get(key), h5py.Dataset):
        raise ValueError(f"HDF5 file {path} has no dataset {key!r} (has {sorted(f.keys())})")
      arr = np.asarray(f[key])
  except OSError as e:
    raise ValueError(f"cannot read HDF5 file {path}: {e}") from e
  return _real_numbers(arr, path, key)


def read_dsp5(path: PathLike) -> np.ndarray:
  """Spring `.dsp5`: HDF5 dataset `disparity` at 2x resolution, NaN where unknown.

  Returns:
    [2H, 2W] float32 as stored (subsampling is the Spring reader's job).
  """
  disp = read_hdf5(path, "disparity")
  if disp.ndim != 2:
    raise ValueError(f"Spring disparity {path}: dataset 'disparity' has shape {disp.shape}, "
                     "not [2H, 2W]")
  return disp.astype(np.float32)


def depth_to_disparity(depth: np.ndarray, scale: float,
                       eps: float = DEPTH_EPS) -> tuple[np.ndarray, np.ndarray]:
  """d = scale / Z, with d = 0 where Z < eps (incl. the -1 "no depth" code) or NaN.

  Valid is `0 < d < 512`: the official reader's `(d < 512) & (Z >= eps)` combined
  with the dense `d != 0` rule, so infinite depth (d = 0) is invalid too.

  Args:
    depth: [H, W] metres.
    scale: fx[px] * baseline[m] (the "depth2disp scale").
    eps: smallest valid depth.

  Returns:
    (disparity [H, W] float32, valid [H, W] bool).

  Raises:
    ValueError: unless scale is finite and positive.
  """
  if not (math.isfinite(scale) and scale > 0):
    raise ValueError(f"depth_to_disparity: scale (fx * baseline) must be a finite positive "
                     f"number, got {scale}")
  depth = np.asarray(depth, np.float32)
  bad = ~(depth >= eps)  # also catches NaN
  with np.errstate(divide="ignore"):
    disp = np.float32(scale) / np.where(bad, np.float32(1), depth)
  disp[bad] = 0
  return disp, (disp > 0) & (disp < MAX_DISPARITY)

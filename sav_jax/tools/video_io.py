"""Reading stereo inputs (frame folders, video files) and writing disparity files.

Inputs are checked completely before anything is computed or written: equal frame
counts and sizes for both views, no empty folders, every frame decodable. Grayscale
frames are repeated to RGB and 16-bit frames are scaled to 8 bits (`round(v / 257)`),
each with a logged note; an alpha channel is dropped. Float images are refused.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import operator
import os
import pathlib
import threading

import cv2
import numpy as np

from sav_jax import viz
from sav_jax._checks import require_int
from sav_jax.data.base import number_key

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
DISPARITY_FORMATS = ("png16", "npy", "pfm", "exr")
_FORMAT_SUFFIX = {"png16": ".png", "npy": ".npy", "pfm": ".pfm", "exr": ".exr"}
DISPARITY_SUFFIXES = tuple(_FORMAT_SUFFIX.values())


def list_frames(folder) -> list[pathlib.Path]:
  """Image files of a frame folder in natural name order (`frame_2` before `frame_10`;
  for zero-padded names the official demo's sorted order); hidden files (`._0001.png`
  copies of macOS archives) are left out. A symbolic link to a missing file is an error that
  names it (left out, the video would lose a frame without a word)."""
  from sav_jax.data import base  # pylint: disable=import-outside-toplevel
  folder = pathlib.Path(folder)
  if not folder.is_dir():
    raise FileNotFoundError(f"{folder}: not a folder")
  files = base.list_files(folder, *IMAGE_EXTENSIONS)
  if not files:
    videos = base.list_files(folder, *VIDEO_EXTENSIONS)
    if videos:
      raise ValueError(f"{folder}: holds video files ({videos[0].name}...), not frames: pass "
                       "one video file")
    entries = sorted(p for p in folder.iterdir() if not base.is_hidden(p))
    subfolders = [p.name for p in entries if p.is_dir()]
    others = [p.name for p in entries if not p.is_dir()]
    held = ("" if not entries else "; it holds " + ", ".join(
        [f"{len(subfolders)} folder(s) ({', '.join(subfolders[:3])}: give the one with the "
         "frames)"] * bool(subfolders)
        + [f"{len(others)} other file(s) ({', '.join(others[:3])})"] * bool(others)))
    raise ValueError(f"{folder}: no frames (no {'/'.join(IMAGE_EXTENSIONS)} images)" + (
        held or ": empty folder"))
  return files


_NOTES_LOCK = threading.Lock()  # (frames are decoded in threads: `parallel.ordered_map`)


def _note_once(notes: set[str], note: str) -> None:
  """Adds `note` unless a note of its kind (the same words up to ", e.g.") is there."""
  kind = note.split(", e.g. ")[0]
  with _NOTES_LOCK:
    if not any(n.split(", e.g. ")[0] == kind for n in notes):
      notes.add(note)


def to_rgb8(img: np.ndarray, source: str, notes: set[str]) -> np.ndarray:
  """Converts a decoded OpenCV image (BGR, grey or BGRA; 8 or 16 bit) to RGB uint8.

  Args:
    img: `[H, W]`, `[H, W, 1]`, `[H, W, 3]` or `[H, W, 4]` array as `cv2.imread` returns it.
    source: name for messages.
    notes: receives one sentence per kind of conversion made, naming the first file (so the
      view) it was made for (logged once by the caller).

  Returns:
    `[H, W, 3]` uint8 RGB.
  """
  if img.ndim == 3 and img.shape[2] == 4:  # before any conversion: a quarter less memory
    _note_once(notes, f"alpha channel dropped, e.g. {source}")
    img = img[..., :3]
  if img.dtype == np.uint16:
    _note_once(notes, f"16-bit frames converted to 8 bits (round(v / 257)), e.g. {source}")
    top = int(img.max())
    if top < 256:  # 8-bit values in a 16-bit file: 0..1 after the conversion
      _note_once(notes, "some 16-bit frames hold only values 0..255 (8-bit data saved as "
                 f"16-bit?), e.g. {source}: they come out black; save them as 8-bit frames")
    elif top < 4096:  # 10- or 12-bit sensor data: 0..16 after the conversion
      _note_once(notes, "some 16-bit frames use only values below 4096 (10- or 12-bit data?), "
                 f"e.g. {source}: they come out nearly black; scale them to the 16-bit range "
                 "or save 8-bit frames")
    # round(v / 257) in 16-bit integers (a float32 copy took twice the frame's memory):
    # v / 257 is never halfway between integers, so it rounds up where v % 257 > 128.
    img = (img // 257 + (img % 257 > 128)).astype(np.uint8)
  elif img.dtype != np.uint8:
    raise ValueError(f"{source}: unsupported pixel type {img.dtype} (expected 8- or 16-bit "
                     "integer images)")
  if img.ndim == 3 and img.shape[2] == 1:
    img = img[..., 0]
  if img.ndim == 2:
    _note_once(notes, "grayscale frames converted to RGB (grey repeated in 3 channels), e.g. "
               f"{source}")
    return np.repeat(img[..., None], 3, axis=2)
  if img.ndim != 3 or img.shape[2] != 3:
    raise ValueError(f"{source}: unsupported image shape {img.shape}")
  if img.dtype == np.uint8 and img.flags.c_contiguous:  # (the same bytes, ~3x faster)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
  return np.ascontiguousarray(img[..., ::-1])


def read_frame(path, notes: set[str]) -> np.ndarray:
  """Decodes one image file to `[H, W, 3]` uint8 RGB (see `to_rgb8`)."""
  from sav_jax.data import frame_io  # pylint: disable=import-outside-toplevel
  try:
    img = frame_io.decode_image_file(path)
  except ValueError as e:
    raise ValueError(f"unreadable frame: {e}") from None
  return to_rgb8(img, str(path), notes)


def read_video_file(path, max_frames: int | None = None) -> np.ndarray:
  """Decodes a video file to `[T, H, W, 3]` uint8 RGB (the first `max_frames` frames).

  Raises:
    FileNotFoundError: no such file.
    ValueError: not a video file name, unreadable, no frames, or frames that differ in
      size (named, with both sizes).
  """
  require_int(max_frames, "max_frames", 1, where="read_video_file", none_ok=True)
  path = pathlib.Path(path)
  _check_video_path(path)
  return np.stack(list(_checked_frames(path, None, max_frames, set())))


def _size(shape) -> str:
  """`HxW` (height x width) of an `[H, W, ...]` shape, for messages."""
  return f"{shape[0]}x{shape[1]}"


def _frame_files(path: pathlib.Path) -> list[pathlib.Path] | None:
  """Every frame file of a folder (callers take the first --max-frames), or None for a
  video file."""
  if path.is_dir():
    return list_frames(path)
  _check_video_path(path)
  return None


def _first(listing, max_frames: int | None):
  """The first `max_frames` of a folder's `listing` (None, a video file's, stays None)."""
  return None if listing is None else listing[:max_frames]


def _read_noted(path) -> tuple[np.ndarray, set[str]]:
  """`read_frame` with notes of its own: `(frame, notes)`."""
  notes: set[str] = set()
  return read_frame(path, notes), notes


def _checked_frames(path: pathlib.Path, files, max_frames: int | None, notes: set[str]):
  """Yields the frames of a folder (`files`) or of a video file (`files` None) as `[H, W, 3]`
  uint8 RGB; a ValueError naming the frame if one cannot be decoded or differs in size from
  the first, or if a video has none."""
  from sav_jax.tools import parallel  # pylint: disable=import-outside-toplevel
  # (a folder's frames decoded by a few threads, in order: the first bad one is still named;
  # each frame's notes kept apart and added in the frames' order, so that a note names the
  # first file of its kind, as one thread does, not the one decoded first)
  frames = (parallel.ordered_map(_read_noted, files) if files is not None
            else _decode(path, max_frames, notes))
  label = (lambda i: files[i].name) if files is not None else (lambda i: f"frame {i}")
  first = None
  # (an error here stops the decoding threads now)
  with contextlib.closing(frames) if files is not None else contextlib.nullcontext():
    for i, frame in enumerate(frames):
      if files is not None:
        frame, its_notes = frame
        for note in sorted(its_notes):
          _note_once(notes, note)
      first = frame.shape if first is None else first
      if frame.shape != first:
        raise ValueError(f"{path}: frames differ in size: {label(i)} is {_size(frame.shape)} "
                         f"but the first frame {label(0)} is {_size(first)} (height x width)")
      yield frame
  if first is None:
    raise ValueError(f"{path}: the video has no decodable frames")


def _frame_names(files, count: int) -> list[str]:
  """Output names: the files' stems, or `frame_000000`... for a video or clashing stems
  (`0001.png` beside `0001.jpg`: logged, naming the first pair)."""
  by_position = [f"frame_{i:06d}" for i in range(count)]
  if files is None:
    return by_position
  seen = {}
  for f in files:
    if f.stem in seen:
      log.warning("note: %s and %s in %s share a name before the suffix: the outputs are "
                  "named by position, frame_000000 to frame_%06d (frame i of the folder's "
                  "order)", seen[f.stem].name, f.name, f.parent, count - 1)
      return by_position
    seen[f.stem] = f
  return list(seen)


def _read_source(path, max_frames: int | None, notes: set[str]):
  """`(frames [T, H, W, 3] uint8, names, listing)` of a frame folder or a video file
  (`listing`: all of the folder's frame files, also those beyond `max_frames`; None for a
  video file)."""
  path = pathlib.Path(path)
  listing = _frame_files(path)
  files = _first(listing, max_frames)
  frames = np.stack(list(_checked_frames(path, files, max_frames, notes)))
  return frames, _frame_names(files, len(frames)), listing


class FrameSource:
  """The frames of a folder or a video file, decoded when asked: `source[a:b]` gives
  `[b - a, H, W, 3]` uint8 RGB (a lazy video source of `inference.iter_predict_video`).

  Opening it decodes every frame once to check it (readable, one size, 8 or 16 bit) and
  keeps none, so that a bad frame is found before anything is computed or written. A video
  file is then read forward once more, keeping the last `keep` decoded frames: reads that
  go back at most that far re-decode nothing (set it to the reader's reach: for
  `iter_predict_video` on N devices, window + (N - 1) * stride frames and one more); a
  read further back decodes the video again from its start.
  """

  def __init__(self, path, max_frames: int | None = None, notes: set[str] | None = None,
               keep: int = 64):
    # (max_frames=-1 dropped the last frame, a keep of None failed at the first read)
    require_int(max_frames, "max_frames", 1, where="FrameSource", none_ok=True)
    require_int(keep, "keep", 0, where="FrameSource")
    self.path = pathlib.Path(path)
    self.keep = keep
    self.notes = set() if notes is None else notes
    self._listing = _frame_files(self.path)  # (all: the pairing check looks beyond the cut)
    self._files = _first(self._listing, max_frames)
    count = 0
    for frame in _checked_frames(self.path, self._files, max_frames, self.notes):
      count, (h, w) = count + 1, frame.shape[:2]
    self.names = _frame_names(self._files, count)
    self.shape = (count, h, w, 3)
    self.fps = None if self._files is not None else video_fps(self.path)
    self._reader, self._next, self._buffer = None, 0, {}
    self._ahead = {}  # frame index: a decoding begun ahead of its read (folders)
    self._lock = threading.Lock()  # (reads from several threads: one at a time)

  def __len__(self) -> int:
    return self.shape[0]

  def __getitem__(self, index) -> np.ndarray:
    if not isinstance(index, slice):
      return _one_frame(self, index)
    start, stop, step = index.indices(len(self))
    if step != 1:
      raise ValueError("FrameSource slices take step 1")
    with self._lock:  # (the kept frames are shared: reads from threads raised KeyError)
      if self._files is not None:
        frames = self._folder_frames(start, stop)
      else:
        frames = [self._video_frame(i) for i in range(start, stop)]
    return np.stack(frames) if frames else np.zeros((0, *self.shape[1:]), np.uint8)

  def _folder_frames(self, start: int, stop: int) -> list[np.ndarray]:
    """Frames start..stop-1 of a folder: those not kept from the last reads decoded by a
    few threads (or taken from the ones decoded ahead); the last `keep` are kept for the
    next read (windows overlap), and the next `stop - start` are decoded ahead in the
    background (while the model runs on these: a decoding error is raised when the frame
    is read)."""
    from sav_jax.tools import parallel  # pylint: disable=import-outside-toplevel
    if all(i in self._buffer for i in range(start, stop)):
      # (frames of the last reads, e.g. `infer`'s calibrated frames of a window's chunk: kept
      # as they are, with the frames decoded ahead; dropping those beyond `stop` had them
      # decoded again for the next window)
      return [self._buffer[i] for i in range(start, stop)]
    got = {}
    for i in range(start, stop):
      if i not in self._buffer and i in self._ahead:
        got[i] = self._ahead.pop(i).result()
    missing = [i for i in range(start, stop) if i not in self._buffer and i not in got]
    got.update(zip(missing, parallel.ordered_map(
        lambda i: read_frame(self._files[i], self.notes), missing)))
    frames = [self._buffer[i] if i in self._buffer else got[i] for i in range(start, stop)]
    if stop > start:
      self._buffer.update(got)
      for old in [k for k in self._buffer if k <= stop - 1 - max(1, self.keep) or k >= stop]:
        del self._buffer[old]
      ahead = range(stop, min(len(self), stop + (stop - start)))
      for old in [k for k in self._ahead if k not in ahead]:
        self._ahead.pop(old).cancel()
      pool = parallel.prefetch_pool()
      if pool is not None:
        for i in ahead:
          if i not in self._ahead:
            self._ahead[i] = pool.submit(read_frame, self._files[i], self.notes)
    return frames

  def close(self) -> None:
    """Stops the decoding of frames ahead of their reads (waiting for those begun) and
    drops the frames kept; a later read decodes its frames again."""
    with self._lock:
      ahead, self._ahead, self._buffer = self._ahead, {}, {}
    for future in ahead.values():
      future.cancel()
    concurrent.futures.wait(list(ahead.values()))

  def _video_frame(self, i: int) -> np.ndarray:
    if i in self._buffer:
      return self._buffer[i]
    if self._reader is None or i < self._next:  # (re)start from the first frame
      self._reader, self._next, self._buffer = _decode(self.path, None, self.notes), 0, {}
    while self._next <= i:
      frame = next(self._reader, None)
      if frame is None:
        raise ValueError(f"{self.path}: frame {self._next} cannot be decoded any more")
      self._buffer[self._next] = frame
      self._next += 1
    # Keep the last `keep` frames: the next window starts inside them.
    for old in [k for k in self._buffer if k <= i - max(1, self.keep)]:
      del self._buffer[old]
    return self._buffer[i]


def _one_frame(source, index) -> np.ndarray:
  """`source[index]` for an integer `index` of a sliceable source: from the end where negative,
  an IndexError outside `[-len, len)` (a negative one wrapped around: frame 2 of 3 for -4)."""
  n = len(source)
  i = operator.index(index)
  if not -n <= i < n:
    raise IndexError(f"frame index {index} is out of range for {n} frames")
  i %= n
  return source[i:i + 1][0]


def resize_frames(frames, height: int, width: int) -> np.ndarray:
  """`[N, H, W(, C)]` frames (or disparity maps) bilinearly resized to `height x width`, as
  float32, with torch's `align_corners=True` coordinates: the official `demo.py`'s
  `F.interpolate(..., mode="bilinear", align_corners=True)`. The same size: a float32 copy."""
  from sav_jax.ops.resize import bilinear_taps  # pylint: disable=import-outside-toplevel
  x = np.asarray(frames, np.float32)
  for axis, size in ((1, int(height)), (2, int(width))):
    if x.shape[axis] == size:
      continue
    i0, i1, w1 = bilinear_taps(x.shape[axis], size, True)
    shape = [1] * x.ndim
    shape[axis] = size
    w = w1.reshape(shape).astype(np.float32)
    x = (1 - w) * np.take(x, i0, axis=axis) + w * np.take(x, i1, axis=axis)
  return np.array(x, np.float32)  # (a copy when nothing was resized)


def align_corners_scale(size: int, resized: int) -> float:
  """Input pixels per resized pixel along an axis of `size` resized to `resized` with
  `align_corners=True` (resized position x maps to x * (size - 1) / (resized - 1)): the
  factor that takes a disparity measured on the resized frames to the input's pixels. (The
  plain ratio size / resized is off by up to a few percent for small sizes.)"""
  return (size - 1) / (resized - 1) if resized > 1 and size > 1 else size / resized


def disparities_to_input_size(disparities, height: int, width: int) -> np.ndarray:
  """`[N, h, w]` disparities computed on frames resized to `h x w` (`resize_frames`), back
  at the input's `height x width`, in its pixels: resized the same way and scaled by
  `align_corners_scale(width, w)`."""
  d = np.asarray(disparities, np.float32)
  scale = np.float32(align_corners_scale(int(width), d.shape[2]))
  return resize_frames(d, height, width) * scale


class ResizedSource:
  """A lazy video source (or an array) whose frames come resized to `height x width` as
  float32 (`resize_frames`) when read: `sav-jax infer --resize`."""

  def __init__(self, source, height: int, width: int):
    self.source = source
    self.shape = (len(source), int(height), int(width), 3)

  def __len__(self) -> int:
    return self.shape[0]

  def __getitem__(self, index) -> np.ndarray:
    if not isinstance(index, slice):
      return _one_frame(self, index)
    return resize_frames(self.source[index], *self.shape[1:3])


def _check_video_path(path: pathlib.Path) -> None:
  if not path.exists():
    raise FileNotFoundError(f"{path}: no such file or folder")
  if path.suffix.lower() not in VIDEO_EXTENSIONS:
    raise ValueError(f"{path}: expected a frame folder or a video file "
                     f"({'/'.join(VIDEO_EXTENSIONS)})")
  viz.check_utf8_path(path, "video file")  # OpenCV's reader crashed on other bytes


def video_fps(path) -> float | None:
  """The frame rate a video file declares, or None where it declares none a video can be
  written at (`viz.is_fps`)."""
  viz.check_utf8_path(path, "video file")  # (a segmentation fault in OpenCV otherwise)
  cap = cv2.VideoCapture(str(path))
  try:
    fps = float(cap.get(cv2.CAP_PROP_FPS)) if cap.isOpened() else 0.0
  finally:
    cap.release()
  return fps if viz.is_fps(fps) else None


# How the note on a video that decodes to fewer frames than it declares names the cause.
TRUNCATED = "truncated or corrupt?"


def _decode(path, max_frames: int | None, notes: set[str]):
  """Yields the frames of a video file as `[H, W, 3]` uint8 RGB."""
  cap = cv2.VideoCapture(str(path))
  if not cap.isOpened():
    raise ValueError(f"{path}: unreadable video (OpenCV cannot open it)")
  try:
    count = 0
    while max_frames is None or count < max_frames:
      ok, img = cap.read()
      if not ok:
        declared = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if declared > count:
          notes.add(f"{path}: {count} frames decoded where the file declares {declared} "
                    f"({TRUNCATED}, or a variable frame rate, whose count is an estimate)")
        break
      count += 1
      yield to_rgb8(img, str(path), notes)
  finally:
    cap.release()


def open_stereo(left, right, max_frames: int | None = None):
  """`load_stereo` without loading: `(FrameSource, FrameSource, names)`, checked alike."""
  if max_frames is not None and max_frames < 1:
    raise ValueError(f"--max-frames must be >= 1, got {max_frames}")
  notes = _same_source_note(left, right)
  lv, rv = FrameSource(left, max_frames, notes), FrameSource(right, max_frames, notes)
  _check_pair(lv, rv, notes, (lv._listing, rv._listing), (left, right))  # pylint: disable=W0212
  return lv, rv, lv.names


def _same_source_note(left, right) -> set[str]:
  """A note when --left and --right name the same folder or file (a slip: the model sees
  two identical views and returns a disparity of about 0 everywhere)."""
  if os.path.realpath(left) != os.path.realpath(right):
    return set()
  return {f"--left and --right are the same source ({os.path.realpath(left)}): identical "
          "views give a disparity of about 0 everywhere"}


def _check_pair(lv, rv, notes: set[str], files=(None, None), sources=("left", "right")
                ) -> None:
  """Raises ValueError unless the two videos match in length and size; logs the notes
  (`files`: the two folders' whole listings, None for a video file; `sources`: their paths)."""
  if len(lv) != len(rv):
    short = [n for n in sorted(notes) if TRUNCATED in n]
    raise ValueError(f"different frame counts: left has {len(lv)} ({sources[0]}), right has "
                     f"{len(rv)} ({sources[1]})" + _unpaired_frame(*files)
                     + "".join(f"; {n}" for n in short))
  if lv.shape != rv.shape:
    turned = lv.shape[1:3] == rv.shape[2:0:-1]
    raise ValueError(f"different frame sizes: left is {_size(lv.shape[1:])} ({sources[0]}), "
                     f"right is {_size(rv.shape[1:])} ({sources[1]}) (height x width)"
                     + ("; one is turned: rotation metadata in one video file? OpenCV applies "
                        "it" if turned else ""))
  fps = (getattr(lv, "fps", None), getattr(rv, "fps", None))
  if None not in fps and abs(fps[0] - fps[1]) > 0.01 * max(fps):
    notes.add(f"the left video runs at {fps[0]:g} frames/s, the right at {fps[1]:g}: frames "
              "are paired by their index, so the views drift apart in time if they are one "
              "recording")
  shifted = _shifted_pairing(*files, pairs=len(lv))
  if shifted:
    notes.add(shifted)
  for note in sorted(notes):
    log.warning("note: %s", note)


def _unpaired_frame(left_files, right_files) -> str:
  """`"; e.g. frame 12 is in the left folder (left_0012.png), not in the right"`: the first
  frame number that one folder's listing has and the other's lacks ("" for video files, or
  names without numbers)."""
  if left_files is None or right_files is None:
    return ""
  numbered = [{_frame_number(p): p for p in files} for files in (left_files, right_files)]
  if None in numbered[0] or None in numbered[1]:
    return ""
  for (have, lack), (side, other) in (((0, 1), ("left", "right")), ((1, 0), ("right", "left"))):
    missing = sorted(set(numbered[have]) - set(numbered[lack]))
    if missing:
      return (f"; e.g. frame {missing[0]} is in the {side} folder "
              f"({pathlib.Path(numbered[have][missing[0]]).name}), not in the {other}")
  return ""


def _frame_number(path):
  """The last number in a frame file's stem (`left_0012` -> 12, a decimal timestamp
  `1701234567.000000` whole: `number_key`), or None."""
  number = number_key(pathlib.Path(path))
  return None if isinstance(number, str) else number


def _shifted_pairing(left_files, right_files, pairs: int | None = None) -> str | None:
  """A note when two frame folders number their frames alike but pair different numbers:
  the same numbers at different places (left 0000, 0001, ... beside right 0001, 0002, ...:
  one frame missing or extra at the start), or, where the folders share numbers, different
  numbers at one place (each camera dropped another frame: left 0002 beside right 0003).
  Frames are paired by their order, so such pairs are from two moments. Folders numbered
  differently (`im0` / `im1`) or alike at the same places get none.

  Args:
    left_files, right_files: each folder's whole listing (before --max-frames: a cut that
      hides the shift still pairs the frames wrongly).
    pairs: how many frames are paired (--max-frames); places beyond are not.
  """
  if not left_files or not right_files:
    return None
  if [pathlib.Path(f).stem for f in left_files] == [pathlib.Path(f).stem for f in right_files]:
    return None  # the same names at the same places (KITTI's 000000_10 ... in both)
  left_numbers = [_frame_number(f) for f in left_files]
  right_numbers = [_frame_number(f) for f in right_files]
  if (None in left_numbers or None in right_numbers  # unnumbered, or numbers that repeat
      or len(set(left_numbers)) < len(left_numbers)
      or len(set(right_numbers)) < len(right_numbers)):
    return None
  pairs = min(len(left_files), len(right_files), pairs or len(left_files))
  name = lambda f: pathlib.Path(f).name
  right_place = {n: i for i, n in enumerate(right_numbers)}
  for i, n in enumerate(left_numbers[:pairs]):
    j = right_place.get(n)
    if j is not None and j != i:
      return (f"the frame folders number their frames alike but not at the same places: "
              f"left {name(left_files[i])} is frame {i} of its folder, right "
              f"{name(right_files[j])} frame {j} of its; frames are paired by their order, so "
              f"left {name(left_files[i])} is paired with right {name(right_files[i])} (a "
              "frame missing or extra in one folder?)")
  if not set(left_numbers) & set(right_numbers):
    return None  # numbered apart (two cameras' own counters)
  differ = [i for i in range(pairs) if left_numbers[i] != right_numbers[i]]
  if differ:
    i = differ[0]
    return (f"the frame folders number their frames alike, but {len(differ)} of the "
            f"{pairs} pairs join different numbers, the first left {name(left_files[i])} "
            f"with right {name(right_files[i])} (frame {i} of each folder): frames are paired "
            "by their order (a frame missing in each folder?)")
  return None


def load_stereo(left, right, max_frames: int | None = None):
  """Reads and checks a stereo pair of frame folders or video files.

  Args:
    left, right: frame folders (sorted image files) or video files.
    max_frames: read at most this many frames of each.

  Returns:
    `(left [T, H, W, 3] uint8, right [T, H, W, 3] uint8, names)`: names are the left
    file stems (or `frame_000000`...) used for the output files.

  Raises:
    FileNotFoundError / ValueError with a one-line explanation.
  """
  if max_frames is not None and max_frames < 1:
    raise ValueError(f"--max-frames must be >= 1, got {max_frames}")
  notes = _same_source_note(left, right)
  lv, names, left_listing = _read_source(left, max_frames, notes)
  rv, _, right_listing = _read_source(right, max_frames, notes)
  _check_pair(lv, rv, notes, (left_listing, right_listing), (left, right))
  return lv, rv, names


def disparity_path(folder, name: str, fmt: str) -> pathlib.Path:
  """File of frame `name` in `folder` for a disparity format."""
  if fmt not in _FORMAT_SUFFIX:
    raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(DISPARITY_FORMATS)}")
  return pathlib.Path(folder) / f"{name}{_FORMAT_SUFFIX[fmt]}"


def write_map(path, data: np.ndarray, fmt: str) -> int:
  """Writes one `[H, W]` float map (disparity or depth) in `fmt`.

  Returns the number of values the format could not hold and stored as its largest
  (png16: disparities above 255.996 px; 0 for the float formats)."""
  if fmt == "png16":
    return viz.write_png16(path, data)
  if fmt == "npy":
    np.save(path, np.asarray(data, np.float32))
  elif fmt == "pfm":
    viz.write_pfm(path, data)
  elif fmt == "exr":
    viz.write_exr(path, data)
  else:
    raise ValueError(f"unknown format {fmt!r}")
  return 0


def read_map(path) -> np.ndarray:
  """Reads a map written by `write_map` (format from the suffix), `[H, W]` float32."""
  suffix = pathlib.Path(path).suffix.lower()
  if suffix == ".png":
    return viz.read_png16(path)[0]
  if suffix == ".npy":
    from sav_jax.data import frame_io  # pylint: disable=import-outside-toplevel
    return frame_io.read_npy(path).astype(np.float32)
  if suffix == ".pfm":
    return viz.read_pfm(path)
  if suffix == ".exr":
    return viz.read_exr(path)
  raise ValueError(f"{path}: unknown disparity file type")

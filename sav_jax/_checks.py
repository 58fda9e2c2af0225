"""Argument checks (and the counts in their messages) shared by the library's modules."""

from __future__ import annotations

import decimal
import json
import numbers
import os
import re
import sys
import warnings

import numpy as np


def plural(n: int, one: str, many: str | None = None) -> str:
  """`"1 sequence"`, `"2 sequences"`, `"2 processes"` (`many` where "s" is not the plural)."""
  return f"{n} {one if n == 1 else many or one + 's'}"


def widened(a: np.ndarray) -> np.ndarray:
  """ml_dtypes' bfloat16 and float8 arrays (JAX's, NumPy's) as float32, exactly; NumPy's
  own types as they are."""
  return a.astype(np.float32) if a.dtype.name.startswith(("bfloat16", "float8")) else a


def check_utf8_path(path, what: str = "file") -> None:
  """Raises ValueError unless `path` is UTF-8 text: a name of other bytes (Latin-1 from a
  zip made on Windows, kept by Python as surrogates) crashed OpenCV's video writer and reader
  with a segmentation fault, and orbax and JAX's cache fail on it with a traceback."""
  try:
    str(path).encode("utf-8")
  except UnicodeEncodeError as e:
    raise ValueError(
        f"{ascii(str(path))}: the {what}'s name is not UTF-8 text (bytes of another encoding "
        f"at character {e.start}, e.g. Latin-1 from a zip made on Windows); rename it to "
        "UTF-8 (convmv -f latin1 -t utf8 does so)") from None


def loads_json(text: str):
  """`json.loads`, its RecursionError (a document nested thousands deep) a ValueError, as its
  other failures are, so that the callers' one-line errors cover it."""
  try:
    return json.loads(text)
  except RecursionError:
    raise ValueError("the JSON is nested too deeply") from None


def is_int(x) -> bool:
  """A Python or numpy integer, not a bool (which would pass as 0 or 1)."""
  return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def require_int(value, name: str, least: int, *, where: str = "",
                none_ok: bool = False) -> None:
  """ValueError unless `value` is an integer (`is_int`) >= `least`, or None where `none_ok`:
  `[where: ]name must be an integer >= least[ or None], got value`."""
  if (none_ok and value is None) or (is_int(value) and value >= least):
    return
  raise ValueError(f"{where + ': ' if where else ''}{name} must be an integer >= {least}"
                   f"{' or None' if none_ok else ''}, got {value!r}")


def within_int64(n: int) -> bool:
  """Whether the integer `n` lies within +-(2**63 - 1): the config values the commands take
  (`1e400` passed the integer checks and ended in an OverflowError where it met a float)."""
  return abs(n) < 2**63


_SCIENTIFIC = re.compile(r"[+-]?\d+(\.\d*)?[eE]\+?\d{1,3}")


def scientific_integer(text: str) -> int | None:
  """The integer a whole number in scientific notation spells (`"1e3"` -> 1000, `"1.2e5"`),
  else None (a negative exponent, a fraction such as `"1.25e1"`, any other text): what the
  commands' integer config overrides accept beside plain digits."""
  if not _SCIENTIFIC.fullmatch(text.strip()):
    return None
  number = decimal.Decimal(text.strip())
  return int(number) if number == number.to_integral_value() else None


def sav_jax_configs(command: str):
  """sav-jax's `configs` package (the config files of `python -m train` and `python -m eval`),
  imported. ValueError where another package or module of that name comes first on the module
  path, e.g. a project's own `configs/` in the current folder, which `python -m` puts first:
  the commands stopped there with an AttributeError or ModuleNotFoundError traceback."""
  import configs  # pylint: disable=import-outside-toplevel
  if callable(getattr(configs, "locate", None)):
    return configs
  where = getattr(configs, "__file__", None) or ", ".join(getattr(configs, "__path__", ()))
  raise ValueError(
      f"`configs` is {where or 'another package'}, not sav-jax's configs package: a "
      f"configs/ (or configs.py) of your own in the current folder hides it; run `python -P -m "
      f"{command} ...` (Python 3.11+: leaves the current folder off the module path) or run "
      "from another folder")


def _package_dirs() -> tuple[str, ...]:
  """sav_jax's folder, and Flax's and JAX's where they are imported (a model call goes
  through them: `model.apply` -> Flax -> the module's checks)."""
  dirs = [os.path.dirname(os.path.abspath(__file__))]
  for name in ("flax", "jax"):
    module = sys.modules.get(name)
    if getattr(module, "__file__", None):
      dirs.append(os.path.dirname(os.path.abspath(module.__file__)))
  return tuple(d + os.sep for d in dirs)


def caller_stacklevel() -> int:
  """`warnings.warn`'s stacklevel that names the first caller outside sav_jax (and the
  Flax and JAX code a model call goes through).

  Called by the function that warns; a fixed stacklevel named a line inside the package
  when the warning came through another of its functions (e.g. `predict_video`).
  """
  packages = _package_dirs()
  frame, level = sys._getframe(1), 1  # pylint: disable=protected-access
  while frame is not None and frame.f_code.co_filename.startswith(packages):
    frame, level = frame.f_back, level + 1
  return level


def nonfinite_frames(video: np.ndarray) -> np.ndarray:
  """The indices of the frames of `video` (`[T, ...]`, float) that hold NaN or inf."""
  return np.flatnonzero(~np.isfinite(video).reshape(len(video), -1).all(axis=1))


def check_video_values(video: np.ndarray, name: str = "video", first: int = 0,
                       warn: bool = True) -> bool:
  """Raises ValueError unless `video` (`[T, ...]` frames) holds finite RGB values in 0..255.

  uint8 passes as is; other integers must not exceed 255 (convert 16-bit frames first) nor
  be negative; floats must be finite; float frames that look normalised (values below -1
  and none above 3: a mean and scale taken off) are refused; float frames that look like
  0..1 images (99.9% of a sample of their values at most 1.5, so a resize's overshoot or a
  few hot pixels do not hide it) or lie well outside 0..255 (below -64 or above 320, beyond
  a resize's overshoot) get a warning (the model expects 0..255, not 0..1 or 0..65535). `first`: the index of `video[0]` in the whole
  video (frames are named by their index there). Returns whether it warned (with `warn`
  False, whether it would have: the errors still raise).
  """
  kind = video.dtype.kind
  if kind == "u" and video.dtype.itemsize == 1:
    return False
  if kind not in "uif":
    raise ValueError(f"{name}: frames of dtype {video.dtype}; expected uint8 or float (0..255)")
  if not video.size:  # no values to check (numpy's min() of none failed: "zero-size array")
    return False
  if kind == "f":
    bad = nonfinite_frames(video)
    if bad.size:
      raise ValueError(f"{name}: non-finite values (NaN/inf) in frame(s) "
                       f"{(bad[:10] + first).tolist()}; the model would return NaN")
  lo, hi = float(video.min()), float(video.max())
  normalised = ("RGB frames are 0..255: negative values are no image's; normalised "
                "frames need their mean and scale put back")
  if kind in "ui" and (lo < 0 or hi > 255):
    flat = video.reshape(len(video), -1)
    bad = np.flatnonzero((flat.min(axis=1) < 0) | (flat.max(axis=1) > 255))
    raise ValueError(f"{name}: {video.dtype} values {lo:g}..{hi:g} are outside 0..255 in "
                     f"frame(s) {(bad[:10] + first).tolist()} ("
                     + ("convert 16-bit frames to 8-bit first, e.g. frames >> 8)" if lo >= 0 else
                        normalised + ")"))
  if kind != "f":
    return False
  if looks_normalised(lo, hi):
    raise ValueError(f"{name}: float frames with values {lo:g}..{hi:g} look normalised ("
                     f"{normalised}, e.g. (frames * std + mean) * 255)")
  looks, spread = float_frames_range(video, lo, hi)
  if not warn:
    return looks is not None
  if looks == "0..1":
    warnings.warn(f"{name}: float frames with values {lo:g}..{hi:g}{spread}: the model "
                  f"expects 0..255 ({unit_range_advice(lo)}; 0..255 frames of a very dark "
                  "scene can be left as they are)", stacklevel=caller_stacklevel())
  elif looks == "negative":
    warnings.warn(f"{name}: float frames with values {lo:g}..{hi:g}, outside 0..255, which the "
                  f"model expects ({normalised})", stacklevel=caller_stacklevel())
  elif looks == "16-bit":
    warnings.warn(f"{name}: float frames with values {lo:g}..{hi:g}, outside 0..255, which the "
                  "model expects (divide 16-bit frames by 257)", stacklevel=caller_stacklevel())
  return looks is not None


def looks_normalised(lo: float, hi: float) -> bool:
  """Whether float frames of values `lo..hi` look normalised (a mean and scale taken off):
  values below -1 and none above 3."""
  return lo < -1.0 and hi <= 3.0


def unit_range_advice(lo: float) -> str:
  """The way to 0..255 for float frames no brighter than ~1 whose minimum is `lo`: 0..1 ones
  are multiplied by 255; for -1..1 ones (`2 x / 255 - 1`, as the model normalises frames
  inside) that advice gave -255..255 frames."""
  if lo < -0.5:  # (a 0..1 image's resize overshoot stays above -0.15)
    return "(frames + 1) * 127.5 for -1..1 frames (2 * x / 255 - 1); multiply 0..1 images by 255"
  return "multiply 0..1 images by 255"


def _sample(video: np.ndarray, size: int = 200_000) -> np.ndarray:
  """About `size` values of `video`: its two largest axes (the frames' rows and columns, in
  either channel layout) strided alike, every channel and frame kept (a flat stride that is
  a multiple of the channel count would read one colour channel only); a strided view is
  not copied whole."""
  if video.size <= size or video.ndim < 2:
    return np.asarray(video, np.float32).reshape(-1)
  rows, cols = sorted(np.argsort(video.shape)[-2:])
  step = max(1, int(np.sqrt(video.size / size)))
  index = [slice(None)] * video.ndim
  index[rows] = index[cols] = slice(None, None, step)
  return np.asarray(video[tuple(index)], np.float32).reshape(-1)


def float_frames_range(video: np.ndarray, lo: float, hi: float) -> tuple[str | None, str]:
  """What float frames of values `lo..hi` look like, if not RGB 0..255: `("0..1", spread)`
  where 99.9% of a sample of their values are at most 1.5 (so a resize's overshoot or a few
  hot pixels do not hide 0..1 images; `spread` says so where the maximum is higher),
  `("negative", "")` below `OVERSHOOT_LOW` (-64: a mean taken off 0..255 frames),
  `("16-bit", "")` above `OVERSHOOT_HIGH` (320: 10- to 16-bit values); `(None, "")`
  otherwise. Between those bounds lie the overshoot of a bicubic or Lanczos resize of sharp
  edges (-38..293 measured) and unclipped noise, which are 0..255 frames still (they were
  warned about, with advice that would have damaged them: "divide by 257")."""
  bright = float(np.quantile(_sample(video), 0.999)) if hi > 1.5 else hi
  if 0 < bright <= 1.5:
    return "0..1", "" if bright == hi else f", 99.9% of them at most {bright:.3g}"
  if lo < OVERSHOOT_LOW:
    return "negative", ""
  if hi > OVERSHOOT_HIGH:
    return "16-bit", ""
  return None, ""


# Float 0..255 frames may go this far outside 0..255 without a warning (see float_frames_range).
OVERSHOOT_LOW, OVERSHOOT_HIGH = -64.0, 320.0

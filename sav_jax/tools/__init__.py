"""Sub-commands of the `sav-jax` command line (one module each).

Each module defines `HELP` (one line), `add_arguments(parser)` and `run(args) -> int`.
Heavy imports (jax, the model) happen inside `run`, so `sav-jax --help` is instant.
A `UsageError` (or ValueError / FileNotFoundError / FileExistsError) raised by
`run` is printed as one clean line and exits with status 2.
"""

import argparse
import contextlib
import logging
import os
import pathlib
import sys
import tempfile
import warnings


def user_path(value: str) -> str:
  """The argparse type of a path option: `~` and `~user` expanded, as the shell does not
  after `--option=` (`--out=~/runs` would otherwise make a folder named `~` here)."""
  return os.path.expanduser(value)


class UsageError(Exception):
  """Bad input from the user: reported without a traceback, exit status 2."""


def empty_path_problem(args, names) -> str | None:
  """The error for the first path option of `names` (argparse dests) given empty or as spaces
  (an unset shell variable, `--out "$OUT"`: "" would be the current folder or the default
  one), or None."""
  for name in names:
    value = getattr(args, name, None)
    if isinstance(value, str) and not value.strip():
      return f"--{name.replace('_', '-')} is empty; give a path"
  return None


def resolve_devices_option(value, name: str = "--devices", takes_all: bool = True) -> list:
  """The devices of a `--devices` value (`inference.resolve_devices`): a number n >= 1 of
  local devices, or 0 or "all" for every one. Bad values raise UsageError naming `name`.
  `takes_all`: whether the option can hold the word "all" (an integer config field cannot:
  the message then offers 0 alone)."""
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  text = str(value).strip().lower()
  if text != "all" and not text.isdecimal():  # (isdigit: "²", which int() refuses)
    every = "0 or 'all'" if takes_all else "0"
    raise UsageError(f"{name}: devices must be a number of local devices >= 1, or {every} "
                     f"for every one, got {value!r}")
  try:
    return inference.resolve_devices("all" if text in ("all", "0") else int(text))
  except ValueError as e:
    raise UsageError(f"{name}: {e}") from None


def add_matmul_precision_argument(p) -> None:
  """--matmul-precision default|high|highest (`jax.default_matmul_precision`)."""
  from sav_jax.runtime import MATMUL_PRECISIONS  # pylint: disable=import-outside-toplevel
  p.add_argument("--matmul-precision", choices=MATMUL_PRECISIONS, default=None,
                 help="precision of float32 matrix products and convolutions: 'default' is "
                      "XLA's choice (TF32 on recent NVIDIA GPUs, ~1e-3 px from the official "
                      "float32 output), 'highest' full float32 (slower there); no effect on "
                      "CPUs, which compute float32 fully (default: JAX's setting, e.g. "
                      "JAX_DEFAULT_MATMUL_PRECISION, else 'default')")


def matmul_precision(args):
  """`(context, name)`: the context that applies `--matmul-precision` (none when it is not
  given: JAX's own setting stays), and the name of the precision in effect."""
  import jax  # pylint: disable=import-outside-toplevel
  if args.matmul_precision is None:
    return contextlib.nullcontext(), str(jax.config.jax_default_matmul_precision or "default")
  return jax.default_matmul_precision(args.matmul_precision), args.matmul_precision


def add_devices_argument(p) -> None:
  """--devices N|all: how many local devices run windows at once."""
  p.add_argument("--devices", default="1", metavar="N",
                 help="run N consecutive windows at once, one per local device "
                      "(0 or 'all': every device of the default backend; default 1)")


def add_compile_cache_arguments(p, default_on: bool = True) -> None:
  """--compile-cache DIR / --no-compile-cache (JAX's persistent compilation cache)."""
  from sav_jax.runtime import (  # pylint: disable=import-outside-toplevel
      LOW_MEMORY_COMPILE_DEFAULT, default_cache_dir)
  g = p.add_mutually_exclusive_group()
  where = (f"default: JAX_COMPILATION_CACHE_DIR if set, else {default_cache_dir()}"
           if default_on else "default: off")
  g.add_argument("--compile-cache", metavar="DIR", type=user_path,
                 help=f"keep compiled programs in DIR for later runs ({where})")
  if default_on:
    g.add_argument("--no-compile-cache", action="store_true",
                   help="do not read or write the persistent compilation cache")
  p.add_argument("--low-memory-compile", action=argparse.BooleanOptionalAction,
                 default=LOW_MEMORY_COMPILE_DEFAULT,
                 help="CPU: compile with XLA's older loop emitters and plain reductions "
                      "(default: on; the per-frame program of long-video inference keeps "
                      "the newer emitters): ~0.6 GB less compiler memory, the same speed; "
                      "--no-low-memory-compile for XLA's default emitters. No effect with "
                      "jaxlib 0.11+, which has only the newer emitters")


def setup_compile_cache(args, default_on: bool = True):
  """Turns the cache on or off and sets the low-memory compile as the arguments say; off
  means off, a cache set by `JAX_COMPILATION_CACHE_DIR` included (`--no-compile-cache`;
  `sav-jax bench` without `--compile-cache`, which measures compiling).

  Returns:
    The cache folder, or None (also when the default folder cannot be created: a warning).
  """
  from sav_jax import runtime  # pylint: disable=import-outside-toplevel
  runtime.set_low_memory_compile(getattr(args, "low_memory_compile",
                                         runtime.LOW_MEMORY_COMPILE_DEFAULT))
  if args.compile_cache:
    return runtime.enable_compilation_cache(args.compile_cache)
  if default_on and not getattr(args, "no_compile_cache", False):
    try:
      return runtime.enable_compilation_cache()
    except ValueError as e:  # the default folder (a read-only home): no cache, as training
      logging.getLogger(__name__).warning("no compilation cache: %s (--compile-cache DIR "
                                          "names another folder)", e)
      return None
  runtime.disable_compilation_cache()
  return None


def check_output_dir(out, flag: str = "--out") -> pathlib.Path:
  """Raises UsageError unless `out` is, or can be created as, a writable folder.

  Run before any computation, so that a bad output path fails at once rather than after
  the model has run.
  """
  out = pathlib.Path(out)
  if out.exists() and not out.is_dir():
    raise UsageError(f"{flag} {out} is a file, not a folder")
  existing = out
  while not existing.exists():  # the nearest folder that exists: where mkdir will write
    if existing.is_symlink():  # mkdir would fail only after the run, with "File exists"
      raise UsageError(f"{flag} {out}: {existing} is a symbolic link to a missing folder "
                       f"({os.readlink(existing)}), or a loop of links")
    existing = existing.parent
  if not existing.is_dir():
    raise UsageError(f"{flag} {out}: {existing} is a file, not a folder")
  if not os.access(existing, os.W_OK | os.X_OK):
    raise UsageError(f"{flag} {out}: no permission to write in {existing}")
  try:  # os.access says yes to root everywhere: /proc, /sys and read-only mounts refuse later
    os.rmdir(tempfile.mkdtemp(prefix=".sav-jax-write-test-", dir=existing))
  except OSError as e:
    raise UsageError(f"{flag} {out}: cannot create anything in {existing} "
                     f"({e.strerror or e})") from e
  return out


@contextlib.contextmanager
def command_logging(verbose: bool):
  """Logging for a command run: INFO (DEBUG with `verbose`) to stderr, JAX's and absl's
  (orbax's) INFO lines quiet unless `verbose`; afterwards the root logger and those two are
  as they were (the command may be called from Python)."""
  root, quiet = logging.getLogger(), [logging.getLogger(n) for n in ("jax", "absl")]
  saved = (list(root.handlers), root.level, [q.level for q in quiet])
  level = logging.DEBUG if verbose else logging.INFO
  logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
  root.setLevel(level)  # also where the root logger already had handlers (a notebook's)
  if not verbose:  # JAX's (backends, cache resets) and orbax's INFO lines are not for users
    for q in quiet:
      q.setLevel(logging.WARNING)
  try:
    yield
  finally:
    for handler in root.handlers[len(saved[0]):]:
      root.removeHandler(handler)
    root.setLevel(saved[1])
    for q, level in zip(quiet, saved[2]):
      q.setLevel(level)


@contextlib.contextmanager
def printable_names():
  """A command's printed lines show the bytes of a name that is not UTF-8 (Latin-1 from a zip
  made on Windows, kept by Python as surrogates) as `\\udce9`, as its error lines on stderr
  do: the strict UTF-8 stdout of a UTF-8 locale failed on them with "surrogates not allowed"
  after the command's work (`sav-jax convert` reported an error for a file it had written).
  Afterwards stdout is as it was (the command may be called from Python)."""
  stream = sys.stdout
  errors = getattr(stream, "errors", None)
  if errors != "strict" or not hasattr(stream, "reconfigure"):
    yield  # (a C locale's surrogateescape writes the name's own bytes)
    return
  stream.reconfigure(errors="backslashreplace")
  try:
    yield
  finally:
    stream.reconfigure(errors=errors)


@contextlib.contextmanager
def one_line_warnings(prefix: str):
  """Python warnings met by a command run (e.g. a 16-bit frame's, `inference`'s) as one line
  each, `PREFIX: warning: ...`, not as a source file, line and its code."""
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

  def show(message, category, filename, lineno, file=None, line=None):
    del category, filename, lineno, line
    # (above a progress bar, not on its line)
    tqdm.write(f"{prefix}: warning: {message}", file=sys.stderr if file is None else file)

  with warnings.catch_warnings():
    warnings.showwarning = show
    yield


from sav_jax._lazy import submodule_getattr

__getattr__ = submodule_getattr(__name__)  # its other modules, on first use

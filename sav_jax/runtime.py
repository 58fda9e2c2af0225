"""Process-level settings: JAX's persistent compilation cache and freed host memory.

Compiling the model takes ~20 s on a 2-core CPU for one clip shape; with the
persistent compilation cache a later process with the same shape, model
settings and JAX version loads the executable instead (about a second) and never
runs the compiler, which also keeps the compiler's working memory out of the
process. The `sav-jax` commands `infer` and `demo` turn it on by default
(`--no-compile-cache` to skip, `--compile-cache DIR` to choose the folder).

`release_host_memory` hands freed heap memory back to the operating system. On
glibc, the allocator keeps what the compiler and the host-side weight
initialisation freed (hundreds of MB) in its arenas; the inference helpers call
it after every compile, so the peak RSS of a run is the compile's or the
execution's, not both stacked.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc
import logging
import os
import pathlib

import jax

log = logging.getLogger(__name__)


def default_cache_dir() -> pathlib.Path:
  """`$XDG_CACHE_HOME/sav-jax/xla` (`~/.cache/sav-jax/xla` when unset)."""
  base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
  return pathlib.Path(base) / "sav-jax" / "xla"


def enable_compilation_cache(path: str | os.PathLike | None = None,
                             min_compile_time_s: float = 1.0) -> pathlib.Path:
  """Turns on JAX's persistent compilation cache for this process.

  Args:
    path: cache folder (created if missing). None keeps a folder the user has
      already configured (`JAX_COMPILATION_CACHE_DIR` or
      `jax.config.update("jax_compilation_cache_dir", ...)`) with its settings
      untouched, else uses `default_cache_dir()`.
    min_compile_time_s: programs that compile faster than this are not stored
      (not applied when an existing setup is kept).

  Returns:
    The folder in use.

  Raises:
    ValueError: `path` exists and is not a folder, or cannot be created.
  """
  current = jax.config.jax_compilation_cache_dir
  if path is None and current:
    return pathlib.Path(current)  # the user's own setup, left as it is
  folder = (pathlib.Path(path) if path is not None else default_cache_dir()).expanduser()
  if folder.exists() and not folder.is_dir():
    raise ValueError(f"compilation cache {folder} exists and is not a folder")
  try:
    folder.mkdir(parents=True, exist_ok=True)
  except OSError as e:
    raise ValueError(f"cannot create the compilation cache folder {folder}: {e}") from e
  jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
  if str(folder) != current:
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # JAX decides once per process whether the cache is used; make it look again.
    from jax.experimental.compilation_cache import compilation_cache  # pylint: disable=import-outside-toplevel
    compilation_cache.reset_cache()
  log.debug("persistent compilation cache: %s", folder)
  return folder


@functools.cache
def _malloc_trim():
  if os.name != "posix":
    return None
  name = ctypes.util.find_library("c")
  try:
    libc = ctypes.CDLL(name)
    trim = libc.malloc_trim  # glibc only (musl, macOS: absent)
  except (OSError, AttributeError, TypeError):
    return None
  trim.argtypes = [ctypes.c_size_t]
  trim.restype = ctypes.c_int
  return trim


def release_host_memory() -> bool:
  """Returns freed heap memory to the operating system (glibc's `malloc_trim(0)`).

  Cheap (milliseconds) and safe to call at any time; nothing in use is touched.

  Returns:
    True if the C library offers it (glibc), False elsewhere (a no-op).
  """
  trim = _malloc_trim()
  if trim is None:
    return False
  gc.collect()  # tracing and lowering leave reference cycles behind
  trim(0)
  return True

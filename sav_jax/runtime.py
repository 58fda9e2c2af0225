"""Process-level settings: JAX's persistent compilation cache and freed host memory.

Compiling the model takes ~20 s on a 2-core CPU for one clip shape; with the
persistent compilation cache a later process with the same shape, model
settings and JAX version loads the executable instead (~4-7 s there: T=5 128x256,
21 s compile -> 7 s load; README, "Compilation cache") and never runs the compiler,
which also keeps the compiler's working memory out of the process. `sav-jax infer`,
`sav-jax demo` and `python -m eval` turn it on by default (`--no-compile-cache` to skip,
`--compile-cache DIR` to choose the folder); `sav-jax bench` only with `--compile-cache DIR`,
and `python -m train` with `--config.compile_cache`.

`release_host_memory` hands freed heap memory back to the operating system. On
glibc, the allocator keeps what the compiler and the host-side weight
initialisation freed (hundreds of MB) in its arenas; the inference helpers call
it after every compile, so the peak RSS of a run is the compile's or the
execution's, not both stacked.

`inference_compiler_options` are the XLA options the inference executables are
compiled with (on CPU: YNNPACK only for matrix products and convolutions, which
halved the forward's temporary memory at the same speed before the refinement's
single-step scan and needs no more than XLA's default since; see
`benchmarks/README.md`, "Memory"), and XLA's older loop emitters, which need
about half of the compiler's memory at the same speed, without XLA's tree reduction
rewriter, whose 32x32 reduce-windows those emitters unroll (with it they compiled the
whole forward 2x slower than the newer emitters; without it somewhat faster)
(`set_low_memory_compile(False)`, `--no-low-memory-compile` in the CLI, turns both off);
the per-frame program of long-video inference keeps the newer emitters, which compile
its twelve identical ViT blocks once (`inference_compiler_options(per_frame=True)`).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import gc
import logging
import os
import pathlib
import shlex
import sys

import numpy as np

from sav_jax._checks import check_utf8_path

# JAX is imported where it is used: `sav-jax --help` imports this module for its defaults.

log = logging.getLogger(__name__)


def draws_progress(stream=None) -> bool:
  """Whether a tqdm bar on `stream` (standard error by default) is drawn where it belongs: a
  terminal, or a Jupyter notebook (whose kernel's stderr is no terminal, but the notebook
  draws tqdm's updates). Not in a log file, `nohup`'s output or a batch job's, where the bar's
  carriage-return updates pile up on one line."""
  stream = sys.stderr if stream is None else stream
  isatty = getattr(stream, "isatty", None)
  try:
    terminal = bool(isatty()) if callable(isatty) else False
  except (OSError, ValueError):  # a closed stream
    terminal = False
  return terminal or "ipykernel" in sys.modules


def default_cache_dir() -> pathlib.Path:
  """`$XDG_CACHE_HOME/sav-jax/xla` (`~/.cache/sav-jax/xla` when it is unset, empty or a
  relative path, which the XDG specification says to ignore: a relative one put the cache
  in whatever folder a command ran from)."""
  base = os.environ.get("XDG_CACHE_HOME", "")
  if not os.path.isabs(base):
    base = pathlib.Path.home() / ".cache"
  return pathlib.Path(base) / "sav-jax" / "xla"


def enable_compilation_cache(path: str | os.PathLike | None = None,
                             min_compile_time_s: float = 1.0) -> pathlib.Path | None:
  """Turns on JAX's persistent compilation cache for this process.

  Args:
    path: cache folder (created if missing). None keeps a folder the user has
      already configured (`JAX_COMPILATION_CACHE_DIR` or
      `jax.config.update("jax_compilation_cache_dir", ...)`) with its settings
      untouched, else uses `default_cache_dir()`.
    min_compile_time_s: programs that compile faster than this are not stored
      (not applied when an existing setup is kept).

  Returns:
    The folder in use; None when JAX's cache is switched off
    (`JAX_ENABLE_COMPILATION_CACHE=false`): that choice is kept, with a warning.

  Raises:
    ValueError: `path` exists and is not a folder, or cannot be created.
  """
  import jax  # pylint: disable=import-outside-toplevel
  if not jax.config.jax_enable_compilation_cache:
    log.warning("JAX's persistent compilation cache is switched off "
                "(JAX_ENABLE_COMPILATION_CACHE / jax_enable_compilation_cache): not using %s",
                path if path is not None else "it")
    return None
  current = jax.config.jax_compilation_cache_dir
  if path is None and current:
    return pathlib.Path(current)  # the user's own setup, left as it is
  folder = (pathlib.Path(path) if path is not None else default_cache_dir()).expanduser()
  # (JAX's C++ options take no other bytes: a TypeError at the first compile)
  check_utf8_path(folder, "compilation cache folder")
  if folder.exists() and not folder.is_dir():
    raise ValueError(f"compilation cache {folder} exists and is not a folder")
  try:
    folder.mkdir(parents=True, exist_ok=True)
  except OSError as e:
    raise ValueError(f"cannot create the compilation cache folder {folder}: {e}") from e
  jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
  if str(folder) != current:
    _set_cache_dir(str(folder))
  log.debug("persistent compilation cache: %s", folder)
  return folder


def disable_compilation_cache() -> None:
  """Turns JAX's persistent compilation cache off for this process, including one set by
  `JAX_COMPILATION_CACHE_DIR` (`preserved_settings` puts it back)."""
  import jax  # pylint: disable=import-outside-toplevel
  if jax.config.jax_compilation_cache_dir:
    _set_cache_dir(None)


def _set_cache_dir(folder: str | None) -> None:
  """Sets `jax_compilation_cache_dir` (None: off) so that it takes effect: JAX decides once
  per process whether the cache is used, so it is made to look again."""
  import jax  # pylint: disable=import-outside-toplevel
  from jax.experimental.compilation_cache import compilation_cache  # pylint: disable=import-outside-toplevel
  jax.config.update("jax_compilation_cache_dir", folder)
  compilation_cache.reset_cache()


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


# XLA:CPU hands matrix products, convolutions and (by default) reductions with their
# elementwise neighbours to YNNPACK. A YNNPACK reduce fusion takes every broadcast
# operand (layer-norm scales, ReLU's zero) as a full-size buffer, so the forward keeps
# ~15 of them (10-20 MB each at 128x256) alive; leaving reductions to XLA's own
# emitter removes them at the same speed (forward) but costs ~9% in training steps.
_YNN_FUSION_FLAG = "xla_cpu_experimental_ynn_fusion_type"
_LEAN_YNN_FUSIONS = ",".join("LIBRARY_FUSION_TYPE_" + t for t in
                             ("DOT", "INDIVIDUAL_DOT", "INDIVIDUAL_CONVOLUTION"))
# XLA:CPU's MLIR fusion emitters need ~0.85 GB of compiler memory for the model; the
# older emitters ~0.25 GB, at the same run time and (without the pass below) no slower
# a compile. They compile each of the twelve identical ViT blocks anew, so the
# per-frame program keeps the newer ones.
_FUSION_EMITTERS_FLAG = "xla_cpu_use_fusion_emitters"
# XLA's tree reduction rewriter splits every reduction longer than 32 into 32-wide (32x32
# over two axes) reduce-windows for pairwise-like summation; the older emitters unroll
# each such window (~0.35 s of compile per instance norm, 38 in the encoders). Without
# it the whole forward compiles 1.7-1.9x faster (T=5 128x256 iters=8: 37-46 -> 20-24 s,
# against the newer emitters' 26 s) at the same speed; the norms' sums lose a little
# precision (max error of an instance norm of 360x640 maps: 1.0e-5 against 1.6e-6).
_DISABLED_PASSES_FLAG = "xla_disable_hlo_passes"
_DISABLED_PASSES = "tree_reduction_rewriter"
LOW_MEMORY_COMPILE_DEFAULT = True
_low_memory_compile = LOW_MEMORY_COMPILE_DEFAULT


# Names `jax.default_matmul_precision` takes, for the eval and training configs'
# `matmul_precision` ("default": XLA's choice, TF32 on recent NVIDIA GPUs).
MATMUL_PRECISIONS = ("default", "high", "highest")


def set_low_memory_compile(enabled: bool = True) -> None:
  """Whether later inference executables compile on CPU with XLA's older loop emitters
  (and without XLA's tree reduction rewriter, whose reduce-windows they unroll).

  On by default: the compiler's peak memory for the model drops by ~0.6 GB (whole
  forward at T=5 128x256 iters=8: 1.26 -> 0.64 GB peak RSS for the compile) and the
  forward runs at the same speed (`benchmarks/compile_options.py`); the compile is no
  slower (20-23 s against 26 s there on 2026-12-01; `benchmarks/compile_times.py`). The
  per-frame program of `predict_video` is compiled with the newer emitters either way
  (see `inference_compiler_options`). `set_low_memory_compile(False)` gives XLA's
  default emitters. Process-wide, like `enable_compilation_cache`.
  """
  global _low_memory_compile  # pylint: disable=global-statement
  if not isinstance(enabled, (bool, np.bool_)):  # bool("no") would be True
    raise TypeError(f"set_low_memory_compile takes True or False, got {enabled!r}")
  _low_memory_compile = bool(enabled)


@contextlib.contextmanager
def preserved_settings():
  """Puts this module's process-wide settings back on exit: the persistent compilation
  cache (`enable_compilation_cache`) and `set_low_memory_compile`.

  `sav_jax.cli.main` runs commands inside it, so calling the command line from Python
  (a notebook, a test) leaves the caller's JAX configuration as it was.
  """
  import jax  # pylint: disable=import-outside-toplevel
  folder = jax.config.jax_compilation_cache_dir
  min_time = jax.config.jax_persistent_cache_min_compile_time_secs
  low_memory = _low_memory_compile
  try:
    yield
  finally:
    set_low_memory_compile(low_memory)
    if jax.config.jax_persistent_cache_min_compile_time_secs != min_time:
      jax.config.update("jax_persistent_cache_min_compile_time_secs", min_time)
    if jax.config.jax_compilation_cache_dir != folder:
      _set_cache_dir(folder)


def out_of_memory(error: BaseException) -> str | None:
  """XLA's report that a device ran out of memory while compiling or running (an
  accelerator's, or the host's on CPU: `RESOURCE_EXHAUSTED`), as one line; None for any
  other error.

  The commands print it with what to change instead of the runtime's traceback and its
  buffer tables (hundreds of lines on a GPU). The line is cut at 300 characters.
  """
  import jax  # pylint: disable=import-outside-toplevel
  if not isinstance(error, jax.errors.JaxRuntimeError):
    return None
  lines = [line.strip() for line in str(error).splitlines() if "RESOURCE_EXHAUSTED" in line]
  if not lines:
    return None
  line = lines[0]
  return line if len(line) <= 300 else line[:297] + "..."


@functools.cache
def _accepts_options(platform: str, options: tuple) -> bool:
  """Whether this jaxlib compiles a trivial program with `options` on `platform`."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  try:
    x = jax.device_put(jnp.zeros((2,), jnp.float32), jax.devices(platform)[0])
    jax.jit(lambda x: x + 1).lower(x).compile(compiler_options=dict(options))
  except Exception as e:  # pylint: disable=broad-except  # an unknown option: any error type
    log.debug("XLA options %s not accepted: %s", options, e)
    return False
  return True


def _xla_flags() -> dict[str, str]:
  """The options `XLA_FLAGS` sets, as XLA reads them: `--name=value` (quotes removed) or a
  bare `--name` ("true")."""
  try:
    tokens = shlex.split(os.environ.get("XLA_FLAGS", ""))
  except ValueError:  # an unbalanced quote: XLA's own parser decides; take the plain words
    tokens = os.environ.get("XLA_FLAGS", "").split()
  flags = {}
  for token in tokens:
    if token.startswith("--"):
      name, _, value = token[2:].partition("=")
      flags[name] = value if _ else "true"
  return flags


def inference_compiler_options(platform: str | None = None,
                               per_frame: bool = False) -> dict[str, str | bool]:
  """XLA compiler options for the model's inference executables.

  On CPU, YNNPACK fusions are limited to matrix products and convolutions
  (`--xla_cpu_experimental_ynn_fusion_type`): the same values (within float32
  summation order), the same speed, and no more temporary memory than XLA's
  default (half of it while the refinement unrolled a last pair of steps).
  Unless `set_low_memory_compile(False)` or `per_frame`, also
  `xla_cpu_use_fusion_emitters=False` and `xla_disable_hlo_passes=tree_reduction_rewriter`
  (the older emitters unroll the rewriter's 32x32 reduce-windows: ~0.35 s of compile
  per instance norm; plain reductions sum in a different order, ~1e-5 max error for
  an instance norm over 360x640 maps, 1.8e-6 px on the output at T=2 368x640). Nothing
  on other backends; an option the user sets in `XLA_FLAGS` is left to them (their choice of
  emitters decides both low-memory options; passes they disable stay disabled), and one
  this jaxlib does not know is dropped. jaxlib 0.11 and later have only the newer
  emitters: there the low-memory compile asks for neither option (the rewriter's
  reduce-windows cost compile time only with the older emitters, so its more precise
  sums stay).

  Args:
    platform: the backend the program is compiled for (default: JAX's default).
    per_frame: options for a program of the per-frame part alone (DINOv2 tokens,
      fnet, cnet: `sav_jax.inference.compiled_frame_features`), which keeps XLA's
      newer fusion emitters: they compile the twelve identical ViT blocks' kernels
      once, where the older emitters (without the tree reduction rewriter) take about
      2x longer (T=5 128x256: 4.2 s against 7.9-8.5 s; with the rewriter 20-23 s) for
      0.54 against 0.62 GB peak RSS; the refinement's program compiles faster with
      the older ones.

  Returns:
    A dict for `jax.stages.Lowered.compile(compiler_options=...)`.
  """
  import jax  # pylint: disable=import-outside-toplevel
  platform = platform or jax.default_backend()
  if platform != "cpu":
    return {}
  user = _xla_flags()
  wanted = [] if _YNN_FUSION_FLAG in user else [(_YNN_FUSION_FLAG, _LEAN_YNN_FUSIONS)]
  older_emitters = ((_FUSION_EMITTERS_FLAG, False),)
  # The two low-memory options go together (the older emitters with the rewriter compile
  # slowly; the rewriter off with the newer ones loses precision for nothing): the user's
  # choice of emitters in XLA_FLAGS decides, and passes they disable stay disabled.
  older = user.get(_FUSION_EMITTERS_FLAG, "false").lower() in ("false", "0")
  if (_low_memory_compile and not per_frame and older
      and _accepts_options(platform, older_emitters)):
    if _FUSION_EMITTERS_FLAG not in user:
      wanted += older_emitters
    passes = [q for q in user.get(_DISABLED_PASSES_FLAG, "").split(",") if q]
    if _DISABLED_PASSES not in passes:  # a compile option replaces the XLA_FLAGS list
      wanted.append((_DISABLED_PASSES_FLAG, ",".join([*passes, _DISABLED_PASSES])))
  return {k: v for k, v in wanted if _accepts_options(platform, ((k, v),))}


# A cgroup memory limit at or above this is "no limit" (v1 writes 2**63 rounded to pages).
_CGROUP_NO_LIMIT = 1 << 60


def cgroup_free_bytes(proc_cgroup: str = "/proc/self/cgroup",
                      root: str = "/sys/fs/cgroup") -> int | None:
  """Memory left under the tightest cgroup memory limit above this process, or None.

  A container's limit (docker `--memory`, Kubernetes, SLURM) is not in `/proc/meminfo`,
  whose MemAvailable is the host's. Each group on this process's path, up to the mount,
  that sets a limit (v2 `memory.max`, v1 `memory.limit_in_bytes`) leaves `limit - (usage -
  inactive page cache)`; the least of them is returned. None where no group sets a limit
  or the files cannot be read.

  Args:
    proc_cgroup, root: where to read the process's groups and the cgroup mounts.
  """
  try:
    lines = pathlib.Path(proc_cgroup).read_text(encoding="ascii").splitlines()
  except (OSError, UnicodeDecodeError):
    return None
  root_dir = pathlib.Path(root)
  free = []
  for line in lines:
    parts = line.split(":", 2)
    if len(parts) != 3:
      continue
    hierarchy, controllers, path = parts
    if hierarchy == "0" and not controllers:  # v2 (unified), alone or beside v1
      base = root_dir if (root_dir / "cgroup.controllers").exists() else root_dir / "unified"
      files = ("memory.max", "memory.current", "inactive_file")
    elif "memory" in controllers.split(","):
      base = root_dir / "memory"
      files = ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
    else:
      continue
    group = base / path.lstrip("/")
    if not group.is_dir():  # in a cgroup namespace the mount is the process's own group
      group = base
    while True:
      left = _cgroup_group_free(group, *files)
      if left is not None:
        free.append(left)
      if group == base or base not in group.parents:
        break
      group = group.parent
  return min(free) if free else None


def _cgroup_group_free(group: pathlib.Path, limit_file: str, usage_file: str,
                       inactive_key: str) -> int | None:
  try:
    limit = (group / limit_file).read_text(encoding="ascii").strip()
    if limit == "max" or int(limit) >= _CGROUP_NO_LIMIT:
      return None
    usage = int((group / usage_file).read_text(encoding="ascii"))
  except (OSError, ValueError):
    return None
  inactive = 0
  try:
    for line in (group / "memory.stat").read_text(encoding="ascii").splitlines():
      key, _, value = line.partition(" ")
      if key == inactive_key:
        inactive = int(value)
  except (OSError, ValueError):
    pass
  return max(0, int(limit) - max(0, usage - inactive))

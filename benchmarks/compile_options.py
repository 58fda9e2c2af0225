"""XLA:CPU compile options for the forward: temporary memory, compile time, speed.

    python benchmarks/compile_options.py                          # T=5 128x256 iters=8
    python benchmarks/compile_options.py --height 256 --width 512 --iters 10 --repeats 3 \
        --sets 0,2                                                # two of the option sets

Compiles the same lowered forward (random weights, inference mode) once per option set
and calls the executables alternately, so that the load of other processes on a shared
machine falls on all of them alike; prints XLA's `temp` size, the compile time and the
median / min forward time per set, and the largest difference to the first set's output.
The compiler's peak memory is a process-wide high-water mark and cannot be separated
here: measure it with `sav-jax bench` (with and without `--low-memory-compile`) in fresh
processes.
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402  pylint: disable=wrong-import-position
import numpy as np  # noqa: E402  pylint: disable=wrong-import-position

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax import runtime  # noqa: E402  pylint: disable=wrong-import-position
from timing import (  # noqa: E402  pylint: disable=wrong-import-position
    add_clip_arguments, check_clip_arguments, random_forward)

_YNN = "xla_cpu_experimental_ynn_fusion_type"
_DOTS_CONVS = ",".join("LIBRARY_FUSION_TYPE_" + t for t in
                       ("DOT", "INDIVIDUAL_DOT", "INDIVIDUAL_CONVOLUTION"))
OPTION_SETS = {
    "xla default": {},
    "older emitters": {"xla_cpu_use_fusion_emitters": False},
    "ynn dots/convs (inference)": {_YNN: _DOTS_CONVS},
    "ynn dots/convs + older emitters (--low-memory-compile before 2026-12-01)": {
        _YNN: _DOTS_CONVS, "xla_cpu_use_fusion_emitters": False},
    "ynn dots/convs + older emitters + LLVM -O1": {
        _YNN: _DOTS_CONVS, "xla_cpu_use_fusion_emitters": False,
        "xla_backend_optimization_level": 1},
    "ynn dots/convs + older emitters, no tree reduction rewriter (--low-memory-compile)": {
        _YNN: _DOTS_CONVS, "xla_cpu_use_fusion_emitters": False,
        "xla_disable_hlo_passes": "tree_reduction_rewriter"},
}


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  add_clip_arguments(p)
  p.add_argument("--repeats", type=int, default=4)
  p.add_argument("--sets", default=",".join(map(str, range(len(OPTION_SETS)))),
                 help="indices into OPTION_SETS to compare (default: all)")
  a = p.parse_args()
  check_clip_arguments(p, a)
  names = list(OPTION_SETS)
  try:
    chosen = {names[int(i)]: OPTION_SETS[names[int(i)]] for i in a.sets.split(",")}
  except (ValueError, IndexError):
    p.error(f"--sets: comma-separated indices below {len(names)}, got {a.sets!r}")

  # Options this jaxlib lacks (0.11+ has only the newer emitters) would stop the run.
  platform = jax.default_backend()
  for name in [n for n, o in chosen.items()
               if not runtime._accepts_options(platform, tuple(sorted(o.items())))]:  # pylint: disable=protected-access
    print(f"skipped (this jaxlib does not take its options): {name}")
    del chosen[name]
  if not chosen:
    p.error("none of the chosen option sets compiles with this jaxlib")

  forward, variables, left, right = random_forward(sav_jax.SAVConfig(), a.frames, a.height,
                                                   a.width, a.iters)
  lowered = jax.jit(forward).lower(variables, left, right)

  compiled, compile_s = {}, {}
  for name, options in chosen.items():
    t0 = time.perf_counter()
    compiled[name] = lowered.compile(compiler_options=options)
    compile_s[name] = time.perf_counter() - t0
  outputs = {k: np.asarray(c(variables, left, right)) for k, c in compiled.items()}  # warm-up
  first = next(iter(outputs.values()))
  times = {k: [] for k in compiled}
  for _ in range(a.repeats):
    for name, c in compiled.items():
      t0 = time.perf_counter()
      c(variables, left, right).block_until_ready()
      times[name].append(time.perf_counter() - t0)

  print(f"T={a.frames} {a.height}x{a.width} iters={a.iters}, {a.repeats} alternated calls each "
        f"({jax.devices()[0].device_kind}, jax {jax.__version__})")
  print(f"{'options':56s} {'temp MB':>8s} {'compile s':>10s} {'median s':>9s} {'min s':>7s} "
        f"{'max |diff|':>10s}")
  for name, c in compiled.items():
    temp = c.memory_analysis().temp_size_in_bytes / 1e6
    diff = float(np.abs(outputs[name] - first).max())
    print(f"{name:56s} {temp:8.0f} {compile_s[name]:10.1f} {statistics.median(times[name]):9.2f} "
          f"{min(times[name]):7.2f} {diff:10.2e}")


if __name__ == "__main__":
  main()

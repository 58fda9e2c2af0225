"""Shared by the benchmark scripts: the median wall time of a compiled call."""

import statistics
import time

import jax


def timed(fn, *args, repeats=3):
  """Median seconds of `fn(*args)` over `repeats` calls, after one warm-up call."""
  jax.block_until_ready(fn(*args))
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - t0)
  return statistics.median(times)

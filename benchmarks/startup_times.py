"""What a process pays before the first compile: importing JAX, the parameter shapes, traces.

    python benchmarks/startup_times.py            # each figure in fresh processes, 3 runs
    python benchmarks/startup_times.py --runs 5 --json

Every `sav-jax`, `python -m train` or `python -m eval` run that computes (and every process
of the test suite that imports JAX) pays these before XLA compiles anything, or loads it
from the compilation cache:

  import_jax      `import jax` (ml_dtypes' import is part of it)
  shapes          `sav_jax.model.init.abstract_variables` of the paper's model, a process's
                  first trace (the converters, `init_variables` and the checkpoint checks)
  forward_trace   `jax.jit(model.apply).trace` at T=2 32x64 iters=2, the process's second
                  trace (after `shapes`)
  grad_trace      the same for the gradient of a loss over every prediction (a training
                  step's model part), the process's third trace

Each run is a fresh process (`python -c`), so a figure includes no cache of an earlier one.
The figures are medians over `--runs`, in seconds.
"""

import argparse
import json
import statistics
import subprocess
import sys

from sav_jax.tools.bench import cpu_model

_CHILD = """
import time
t0 = time.perf_counter()
import jax
import_s = time.perf_counter() - t0
import jax.numpy as jnp
import sav_jax
from sav_jax.model import init
cfg = sav_jax.SAVConfig()
t0 = time.perf_counter()
variables = init.abstract_variables(cfg)
shapes_s = time.perf_counter() - t0
model = sav_jax.StereoAnyVideo(cfg)
clip = jax.ShapeDtypeStruct((1, 2, 32, 64, 3), jnp.float32)
fwd = lambda v, l, r: model.apply(v, l, r, iters=2).disparities
t0 = time.perf_counter()
jax.jit(fwd).trace(variables, clip, clip)
fwd_s = time.perf_counter() - t0
grad = jax.grad(lambda v, l, r: jnp.mean(fwd(v, l, r)))
t0 = time.perf_counter()
jax.jit(grad).trace(variables, clip, clip)
grad_s = time.perf_counter() - t0
import importlib.metadata as md, json
print(json.dumps({"import_jax": import_s, "shapes": shapes_s, "forward_trace": fwd_s,
       "grad_trace": grad_s, "ml_dtypes": md.version("ml_dtypes"), "jax": jax.__version__,
       "flax": md.version("flax")}))
"""


def measure(runs: int) -> dict:
  """Medians (seconds) of `runs` fresh processes, with the versions they ran."""
  results = []
  for _ in range(runs):
    proc = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True,
                          check=False, timeout=600)
    if proc.returncode != 0:
      raise SystemExit(f"startup_times: the measuring process failed:\n{proc.stderr[-3000:]}")
    results.append(json.loads(proc.stdout.strip().splitlines()[-1]))
  out = {k: statistics.median(r[k] for r in results)
         for k in ("import_jax", "shapes", "forward_trace", "grad_trace")}
  out.update({k: results[0][k] for k in ("ml_dtypes", "jax", "flax")}, runs=runs,
             cpu=cpu_model())
  return out


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n", maxsplit=1)[0])
  p.add_argument("--runs", type=int, default=3, help="fresh processes per figure (median)")
  p.add_argument("--json", action="store_true", help="print the result as JSON")
  args = p.parse_args(argv)
  if args.runs < 1:
    p.error(f"--runs must be >= 1, got {args.runs}")
  res = measure(args.runs)
  if args.json:
    print(json.dumps(res))
  else:
    for k in ("import_jax", "shapes", "forward_trace", "grad_trace"):
      print(f"{k:14s} {res[k]:6.2f} s")
    print(f"(medians of {res['runs']} processes; jax {res['jax']}, flax {res['flax']}, "
          f"ml_dtypes {res['ml_dtypes']})")
  return 0


if __name__ == "__main__":
  sys.exit(main())

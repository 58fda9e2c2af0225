"""Compile time and the process's peak RSS of the inference programs, on this backend.

    python benchmarks/compile_times.py --frames 5 --height 128 --width 256 --iters 8
    python benchmarks/compile_times.py ... --whole      # the whole forward in one program

By default compiles what `predict_video` (and so `sav-jax infer` and `eval`) runs for one
window: the per-frame program (`inference.compiled_frame_features`) and the window's
refinement (`inference.compiled_window`), with the options `sav_jax.runtime` gives each.
`--whole` compiles `inference.compiled_forward` instead (one program, as `sav-jax bench`).
`--no-low-memory-compile` as in the CLI. Run each setting in a fresh process: the peak RSS
is the process's. No persistent compilation cache is used.
"""

import argparse
import json
import time

import jax

import sav_jax
from sav_jax import inference, runtime
from sav_jax.model.init import init_variables
from sav_jax.tools.bench import peak_rss_gb
from timing import check_clip_arguments  # benchmarks/timing.py


def measure(frames: int, height: int, width: int, iters: int, whole: bool = False) -> dict:
  """Seconds per compiled program (in compile order) and the peak RSS in GB afterwards."""
  cfg = sav_jax.SAVConfig()
  variables = jax.device_put(init_variables(cfg, 0))
  programs = ({"forward": lambda: inference.compiled_forward(
      variables, frames, height, width, cfg=cfg, iters=iters)} if whole else {
          "frames": lambda: inference.compiled_frame_features(variables, frames, height, width,
                                                              cfg=cfg),
          "window": lambda: inference.compiled_window(variables, frames, height, width, cfg=cfg,
                                                      iters=iters)})
  seconds = {}
  for name, compile_fn in programs.items():
    start = time.perf_counter()
    compile_fn()
    seconds[name] = time.perf_counter() - start
  return {"compile_s": seconds, "total_s": sum(seconds.values()), "peak_rss_gb": peak_rss_gb(),
          "frames": frames, "height": height, "width": width, "iters": iters,
          "device": jax.devices()[0].device_kind, "jax": jax.__version__}


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n", maxsplit=1)[0])
  p.add_argument("--frames", type=int, default=5)
  p.add_argument("--height", type=int, default=128)
  p.add_argument("--width", type=int, default=256)
  p.add_argument("--iters", type=int, default=8)
  p.add_argument("--whole", action="store_true", help="the whole forward as one program")
  p.add_argument("--low-memory-compile", action=argparse.BooleanOptionalAction, default=True)
  p.add_argument("--json", action="store_true", help="print the result as JSON")
  args = p.parse_args(argv)
  check_clip_arguments(p, args)  # (the model's trace failed on --iters 1 or --frames 99)
  with runtime.preserved_settings():
    runtime.disable_compilation_cache()
    runtime.set_low_memory_compile(args.low_memory_compile)
    result = measure(args.frames, args.height, args.width, args.iters, args.whole)
  result["low_memory_compile"] = args.low_memory_compile
  if args.json:
    print(json.dumps(result, indent=1))
  else:
    for name, s in result["compile_s"].items():
      print(f"{name:8s} {s:6.1f} s")
    print(f"total    {result['total_s']:6.1f} s   peak RSS {result['peak_rss_gb']:.2f} GB")
  return result


if __name__ == "__main__":
  main()

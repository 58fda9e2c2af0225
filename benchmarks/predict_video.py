"""Long-video inference: `predict_video` (per-frame features reused across windows) vs
running every window through the whole model (`compiled_forward`, no reuse), and with
`--devices N` also `predict_video(..., devices=N)` (N windows at once on N local devices).

    python benchmarks/predict_video.py --frames 40 --height 128 --width 256 --iters 8
    python benchmarks/predict_video.py --frames 200 --height 720 --width 1280 --iters 20 \
        --dtype bfloat16 --devices 8 --skip-whole     # a multi-GPU host

Random weights and a random video; every path runs the same official windows (20 frames,
stride 10) and is timed after a first run that compiles everything.
"""

import argparse
import time

import jax
import numpy as np

import sav_jax
from sav_jax import inference
from sav_jax.model.init import init_variables
from sav_jax.tools import UsageError, resolve_devices_option
from timing import add_clip_arguments  # benchmarks/timing.py


def without_reuse(variables, left, right, cfg, iters):
  pads = inference.pad_amounts(*left.shape[1:3])
  out = []
  for win in inference.window_plan(len(left)):
    sl = slice(win.start, win.start + win.length)
    lp = inference.pad_frames(left[sl].astype(np.float32), pads)
    rp = inference.pad_frames(right[sl].astype(np.float32), pads)
    fn = inference.compiled_forward(variables, *lp.shape[:3], cfg=cfg, iters=iters)
    raw = np.asarray(fn(variables, lp, rp))
    out.append(np.abs(inference.unpad(raw, pads)[win.keep_start:win.keep_stop]))
  return np.concatenate(out)


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  add_clip_arguments(p, frames=40)
  p.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
  p.add_argument("--devices", default="1", help="also run on N local devices (a number or 'all')")
  p.add_argument("--skip-whole", action="store_true", help="leave out the whole-model path")
  a = p.parse_args()
  if min(a.frames, a.height, a.width) < 1:  # (tracebacks after building the weights)
    p.error(f"--frames, --height and --width must be >= 1, got {a.frames} frames of "
            f"{a.height}x{a.width}")
  if a.iters < 2:
    p.error(f"--iters must be >= 2 (got {a.iters})")
  cfg = sav_jax.SAVConfig(dtype=a.dtype)
  try:
    devices = resolve_devices_option(a.devices)
  except UsageError as e:
    p.error(str(e))
  variables = jax.device_put(inference.model_variables(init_variables(cfg, seed=0)))
  rng = np.random.default_rng(0)
  left = rng.integers(0, 256, (a.frames, a.height, a.width, 3), dtype=np.uint8)
  right = np.roll(left, -4, axis=2)
  runs = {"predict_video (reuse)": lambda: inference.predict_video(
      variables, left, right, cfg=cfg, iters=a.iters)}
  if not a.skip_whole:
    runs["whole model per window"] = lambda: without_reuse(variables, left, right, cfg, a.iters)
  if len(devices) > 1:
    runs[f"predict_video, {len(devices)} devices"] = lambda: inference.predict_video(
        variables, left, right, cfg=cfg, iters=a.iters, devices=devices)
  results, seconds = {}, {}
  for name, fn in runs.items():
    fn()  # compiles
    t0 = time.perf_counter()
    results[name] = fn()
    seconds[name] = time.perf_counter() - t0
    sec = seconds[name]
    print(f"{name:28s} {sec:7.2f} s  ({a.frames / sec:.2f} frames/s, "
          f"{seconds['predict_video (reuse)'] / sec:.2f}x predict_video's speed)", flush=True)
  first = results.pop("predict_video (reuse)")
  for name, other in results.items():
    print(f"max |difference| from predict_video, {name}: {np.max(np.abs(first - other)):.2e} px")


if __name__ == "__main__":
  main()

"""Frames/s of `sav-jax infer`'s own work (reading, writing, the video), model left out.

The model is replaced by a stand-in that returns a precomputed smooth, textured disparity
map per frame (a few ms per window), so the time measured is what the command does around
the model: decoding the input (check pass and windows), the disparity files, the held
disparities' temporary file, the colour range, the side-by-side video, and with
`--calib` depth maps and PLY point clouds. `--profile` adds a cProfile breakdown by stage.

    python benchmarks/infer_throughput.py DATA --frames 60 --height 720 --width 1280 \
        [--input png|mp4] [--format png16] [--calib] [--depth-format npy] [--profile]

The first run writes the input (PNG folders `left/`, `right/` and `left.mp4`, `right.mp4`:
a synthetic textured scene shifted per frame, not noise) and a random-weight checkpoint into
DATA; later runs reuse them. Outputs go to DATA/out_<pid> (deleted unless --keep).
"""

import argparse
import cProfile
import json
import os
import pathlib
import pstats
import resource
import shutil
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax import cli, inference  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.model.init import init_variables  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools import infer as infer_tool  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools.bench import (  # noqa: E402  pylint: disable=wrong-import-position
    json_output_problem, peak_rss_gb)

from infer_memory import prepare_data  # noqa: E402  # benchmarks/infer_memory.py


def scene(height: int, width: int, seed: int = 0) -> np.ndarray:
  """A textured RGB image (blurred noise over gradients: compresses like a photo, not noise)."""
  rng = np.random.default_rng(seed)
  small = rng.integers(0, 255, (height // 8 + 1, width // 8 + 1, 3), np.uint8)
  img = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC).astype(np.float32)
  img += rng.normal(0, 6, img.shape).astype(np.float32)
  return np.clip(img, 0, 255).astype(np.uint8)


def write_data(root: pathlib.Path, frames: int, height: int, width: int) -> None:
  base = scene(height, width + 64)
  for side, shift in (("left", 0), ("right", 16)):
    (root / side).mkdir(parents=True, exist_ok=True)
    vw = cv2.VideoWriter(str(root / f"{side}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0,
                         (width, height))
    for i in range(frames):
      f = np.roll(base, 2 * i, axis=1)[:, shift:shift + width]
      cv2.imwrite(str(root / side / f"{i:05d}.png"), f)
      vw.write(np.ascontiguousarray(f))
    vw.release()
  sd = sav_jax.convert.state_dict_from_params(init_variables(sav_jax.SAVConfig(), 0))
  np.savez(root / "sav.npz", **sd)


_FIELD: dict = {}


def field(hp: int, wp: int) -> np.ndarray:
  """A smooth disparity field with some texture, 5..60 px (negative: the model's sign)."""
  if (hp, wp) not in _FIELD:
    y, x = np.mgrid[0:hp, 0:wp].astype(np.float32)
    tex = cv2.GaussianBlur(np.random.default_rng(1).normal(0, 1, (hp, wp)).astype(np.float32),
                           (0, 0), 3)
    d = 5 + 40 * y / hp + 8 * np.sin(x / 37.0) * np.cos(y / 53.0) + 3 * tex
    _FIELD[(hp, wp)] = -np.clip(d, 0.5, None).astype(np.float32)
  return _FIELD[(hp, wp)]


TIMERS = {"stand-in": 0.0, "load_checkpoint": 0.0}
CALLS = {"windows": 0}
MODEL_FPS = [0.0]


def stand_in(variables, left, right, *, cfg, iters, pads, check_memory, **_):
  """A window's raw output without the model: frame k of window n gets the field minus
  0.05 (k + n) px (distinct per window, as a model's would be)."""
  del variables, right, cfg, iters, check_memory
  start = time.perf_counter()
  hp, wp = left.shape[1] + pads[0] + pads[1], left.shape[2] + pads[2] + pads[3]
  f, n = field(hp, wp), CALLS["windows"]
  CALLS["windows"] += 1
  out = np.stack([f - np.float32(0.05 * (k + n)) for k in range(len(left))])
  if MODEL_FPS[0]:  # a GPU's time for the window (waiting on it holds no CPU and no GIL)
    time.sleep(max(0.0, len(left) / MODEL_FPS[0] - (time.perf_counter() - start)))
  TIMERS["stand-in"] += time.perf_counter() - start
  return out


def timed_load_checkpoint(*a, **k):
  start = time.perf_counter()
  try:
    return _LOAD(*a, **k)
  finally:
    TIMERS["load_checkpoint"] += time.perf_counter() - start


_LOAD = infer_tool.load_checkpoint


# Stages of the cProfile breakdown: (label, function names whose cumulative time counts).
STAGES = (
    ("stand-in model", ("stand_in",)),
    ("check pass: decode all frames once (open_stereo)", ("open_stereo",)),
    ("window frame reads (FrameSource.__getitem__, all)", ("__getitem__",)),
    ("png16 (write_png16)", ("write_png16",)),
    ("npy (np.save)", ("save",)),
    ("exr (write_exr)", ("write_exr",)),
    ("pfm (write_pfm)", ("write_pfm",)),
    ("depth_from_disparity", ("depth_from_disparity",)),
    ("point clouds (disparity_to_points)", ("disparity_to_points",)),
    ("point clouds (write_ply)", ("write_ply",)),
    ("colour range (disparity_range)", ("disparity_range",)),
    ("colorize", ("colorize",)),
    ("side_by_side", ("side_by_side",)),
    ("write_video (whole, incl. frames it draws)", ("write_video",)),
    ("  of which VideoWriter.write", ("write' of 'cv2.VideoWriter",)),
    ("write_outputs (whole)", ("write_outputs",)),
)


def stage_table(prof: cProfile.Profile) -> list[tuple[str, float]]:
  stats = pstats.Stats(prof).stats  # {(file, line, name): (cc, nc, tt, ct, callers)}
  rows = []
  for label, names in STAGES:
    total = 0.0
    for (_, _, fname), (_, _, _, ct, callers) in stats.items():
      if any(n == fname or n in fname for n in names):
        # cumulative time, not counted twice through recursion within the same names
        if not any(any(n == c[2] for n in names) for c in callers):
          total += ct
    rows.append((label, total))
  return rows


def main() -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("data", type=pathlib.Path)
  p.add_argument("--frames", type=int, default=60)
  p.add_argument("--height", type=int, default=720)
  p.add_argument("--width", type=int, default=1280)
  p.add_argument("--input", choices=("png", "mp4"), default="png")
  p.add_argument("--format", default="png16", help="sav-jax infer --format")
  p.add_argument("--calib", action="store_true", help="add a calibration: depth + PLY")
  p.add_argument("--depth-format", default=None)
  p.add_argument("--profile", action="store_true")
  p.add_argument("--model-fps", type=float, default=0.0,
                 help="the stand-in takes as long as a model running at this many frames/s "
                 "per window (e.g. 16: the H200's bfloat16 20-frame window at 720x1280, "
                 "1.25 s); 0: as little time as it can")
  p.add_argument("--keep", action="store_true", help="keep the outputs")
  p.add_argument("--json", type=pathlib.Path, default=None, help="append the result here")
  args = p.parse_args()
  # checked before the run (appending to an existing file is this option's use)
  problem = json_output_problem(str(args.json), True) if args.json is not None else None
  if problem:
    p.error(problem)
  prepare_data(p, args, write_data)
  name = "_run_window" if hasattr(inference, "_run_window") else "run_window"  # older code
  setattr(inference, name, stand_in)
  MODEL_FPS[0] = args.model_fps
  infer_tool.load_checkpoint = timed_load_checkpoint
  out = args.data / f"out_{os.getpid()}"
  if args.input == "png":
    lr = [str(args.data / "left"), str(args.data / "right")]
  else:
    lr = [str(args.data / "left.mp4"), str(args.data / "right.mp4")]
  argv = ["infer", "--left", lr[0], "--right", lr[1], "--checkpoint",
          str(args.data / "sav.npz"), "--out", str(out), "--iters", "2",
          "--format", args.format]
  if args.calib:
    argv += ["--fx", "1000", "--baseline", "0.12"]
    if args.depth_format:
      argv += ["--depth-format", args.depth_format]
  field(*[-(-s // 32) * 32 for s in (args.height, args.width)])  # (precomputed: not timed)
  prof = cProfile.Profile() if args.profile else None
  cpu = lambda: sum(resource.getrusage(resource.RUSAGE_SELF)[:2])  # noqa: E731 user + sys
  start, cpu0 = time.perf_counter(), cpu()
  if prof is not None:
    prof.enable()
  rc = cli.main(argv)
  if prof is not None:
    prof.disable()
  seconds, cpu_s = time.perf_counter() - start, cpu() - cpu0
  if rc != 0:  # infer named the problem: nothing was measured, nothing goes to --json
    if not args.keep:
      shutil.rmtree(out, ignore_errors=True)
    sys.exit(rc)
  summary = json.loads((out / "summary.json").read_text()) if rc == 0 else {}
  peak = peak_rss_gb()
  # infer's own per-frame work: the whole command less the weights' loading (a fixed cost)
  # and the stand-in model's time
  own = seconds - TIMERS["load_checkpoint"] - TIMERS["stand-in"]
  fps = args.frames / own
  end_to_end = args.frames / (seconds - TIMERS["load_checkpoint"])
  print(f"exit {rc}; {args.frames} frames of {args.height}x{args.width} ({args.input}, "
        f"--format {args.format}{', calib' if args.calib else ''}): {seconds:.1f} s in all, "
        f"{TIMERS['load_checkpoint']:.1f} s loading the weights, {TIMERS['stand-in']:.1f} s "
        f"stand-in model; infer's own work {own:.1f} s: {fps:.2f} frames/s; with the model "
        f"{end_to_end:.2f} frames/s (the model alone {args.frames / TIMERS['stand-in']:.2f}); "
        f"CPU time (all threads, weights' loading included) {cpu_s:.1f} s; "
        f"peak RSS {peak:.2f} GB")
  result = {"frames": args.frames, "height": args.height, "width": args.width,
            "input": args.input, "format": args.format, "calib": args.calib,
            "depth_format": args.depth_format, "seconds": round(seconds, 2),
            "load_checkpoint_s": round(TIMERS["load_checkpoint"], 2),
            "stand_in_s": round(TIMERS["stand-in"], 2), "own_seconds": round(own, 2),  # (with --model-fps: what the model did not hide)
            "frames_per_second": round(fps, 2), "model_fps": args.model_fps,
            "end_to_end_frames_per_second": round(end_to_end, 2),
            "model_alone_frames_per_second": round(args.frames / TIMERS["stand-in"], 2),
            "cpu_seconds": round(cpu_s, 2),
            "peak_rss_gb": round(peak, 3),
            "summary_seconds": summary.get("seconds"), "cpus": os.cpu_count(),
            "io_threads": os.environ.get("SAV_IO_THREADS"),
            "date": time.strftime("%Y-%m-%d")}
  if prof is not None:
    rows = stage_table(prof)
    result["stages_s"] = {label: round(t, 2) for label, t in rows}
    print("stage (cumulative, cProfile; nested rows overlap):")
    for label, t in rows:
      if t > 0:
        print(f"  {t:7.2f} s  {1000 * t / args.frames:7.1f} ms/frame  {label}")
  if args.json is not None:
    with open(args.json, "a", encoding="utf-8") as fh:
      fh.write(json.dumps(result) + "\n")
  if not args.keep:
    shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
  main()

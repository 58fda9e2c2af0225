"""Training-step time and peak memory: the jitted step of `python -m train`, on random data.

    python benchmarks/train_step.py                                   # the paper's shape
    python benchmarks/train_step.py --frames 3 --height 32 --width 64 --iters 2 --batch 2 \
        --no-remat                                                    # configs/synthetic.py
    python benchmarks/train_step.py --json benchmarks/results/train_cpu.json

Builds the same state, optimizer and step as `train/` (`configs/sceneflow.py` with the
shape overridden; official initialisation), feeds a random batch (the step's cost does
not depend on the values) and reports the compile time (with its trace, lowering and XLA
parts), the median step time, samples/s, and the peak memory (host RSS on CPU, device
peak on GPU), also divided by the batch.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402  pylint: disable=wrong-import-position
import numpy as np  # noqa: E402  pylint: disable=wrong-import-position

from configs import sceneflow  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.model.init import init_variables  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax import runtime  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools.bench import (  # noqa: E402  pylint: disable=wrong-import-position
    compile_cache_note, compile_cache_probe, device_peak_gb, json_output_problem, memory_lines,
    peak_rss_gb, write_json_result, xla_buffers_gb)
from sav_jax.tools import UsageError  # noqa: E402  pylint: disable=wrong-import-position
from train import optim, state as state_lib, step as step_lib  # noqa: E402  pylint: disable=wrong-import-position
from timing import (  # noqa: E402  pylint: disable=wrong-import-position
    add_clip_arguments, check_clip_arguments)
import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.config import resolve_gru_conv  # noqa: E402  pylint: disable=wrong-import-position


def build_config(a):
  config = sceneflow.get_config()
  config.data.frames = a.frames
  config.data.crop = (a.height, a.width)
  config.train.iters = a.iters
  config.train.batch_size = a.batch
  config.train.microbatches = a.microbatches
  config.model.remat = a.remat
  config.model.dtype = a.dtype
  config.model.gru_conv = a.gru_conv
  return config


def random_batch(config, seed=0):
  b, t, (h, w) = config.train.batch_size, config.data.frames, config.data.crop
  rng = np.random.default_rng(seed)
  left = rng.integers(0, 256, (b, t, h, w, 3), dtype=np.uint8)
  return dict(left=left, right=np.roll(left, -4, axis=3),
              disparity=rng.uniform(0, 40, (b, t, h, w)).astype(np.float32),
              valid=np.ones((b, t, h, w), np.float32))


def measure(config, repeats: int) -> dict:
  """Compiles and times the train step of `config` on all local devices."""
  mesh = state_lib.make_mesh()
  model = sav_jax.StereoAnyVideo(state_lib.model_config(config))
  abstract = state_lib.abstract_params(model, config)
  labels = optim.param_labels(abstract, config.optimizer.frozen)
  tx = optim.make_optimizer(config.optimizer, config.train.num_steps)
  params = state_lib.place_params(init_variables(model.cfg, seed=0)["params"], abstract, mesh)
  state, shardings = state_lib.create_train_state(model, tx, config, mesh, params)
  step = step_lib.jit_train_step(step_lib.make_train_step(model, tx, config, labels, mesh),
                                 shardings, mesh)
  batch = jax.device_put(random_batch(config), state_lib.data_sharding(mesh))
  c0 = time.perf_counter()
  traced = step.trace(state, batch)
  c1 = time.perf_counter()
  lowered = traced.lower()
  c2 = time.perf_counter()
  compiled = lowered.compile()
  c3 = time.perf_counter()
  compile_s = c3 - c0
  compile_peak = device_peak_gb(jax.devices()[0])  # the GPU compiler's autotuning scratch
  runtime.release_host_memory()  # as the training loop does after its first step
  state, metrics = compiled(state, batch)  # warm-up
  jax.block_until_ready(metrics)
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    state, metrics = compiled(state, batch)
    jax.block_until_ready(metrics)
    times.append(time.perf_counter() - t0)
  median = statistics.median(times)
  device = jax.devices()[0]
  b = config.train.batch_size
  rss, dev = peak_rss_gb(), device_peak_gb(device)
  return dict(
      frames=config.data.frames, height=config.data.crop[0], width=config.data.crop[1],
      iters=config.train.iters, batch=b, microbatches=config.train.microbatches,
      remat=config.model.remat, dtype=config.model.dtype,
      gru_conv=resolve_gru_conv(config.model.gru_conv, config.model.dtype),
      devices=mesh.size, compile_s=compile_s, trace_s=c1 - c0, lower_s=c2 - c1,
      xla_compile_s=c3 - c2, median_s=median, min_s=min(times),
      samples_per_s=b / median, peak_rss_gb=rss, peak_rss_gb_per_sample=rss / b,
      device_peak_gb=dev, device_peak_gb_per_sample=None if dev is None else dev / b,
      device_peak_compile_gb=compile_peak, **xla_buffers_gb(compiled),
      loss=float(metrics["loss"]), device=f"{device.platform}:{device.device_kind}",
      jax=jax.__version__, date=time.strftime("%Y-%m-%d"))


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  add_clip_arguments(p, height=256, width=512, iters=10)
  p.add_argument("--batch", type=int, default=1, help="global batch (divisible by devices)")
  p.add_argument("--microbatches", type=int, default=1,
                 help="train.microbatches: the batch as this many parts (gradient accumulation)")
  p.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
  p.add_argument("--no-remat", dest="remat", action="store_false")
  p.add_argument("--gru-conv", choices=("auto", "direct", "dft"), default="auto",
                 help="the GRU's 1x15 convolutions (SAVConfig.gru_conv)")
  p.add_argument("--repeats", type=int, default=3)
  p.add_argument("--json", help="write the results to this JSON file (a new file, or "
                 "--overwrite)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
  p.add_argument("--compile-cache", metavar="DIR",
                 help="keep the compiled step in DIR (JAX's persistent compilation cache); "
                      "a second run loads it instead of compiling, so on a GPU its device "
                      "peak is the step's own, without the autotuner's scratch (default: "
                      "JAX_COMPILATION_CACHE_DIR if set, else none)")
  a = p.parse_args()
  problem = json_output_problem(a.json, a.overwrite)
  if problem:  # before the long compile
    p.error(problem)
  check_clip_arguments(p, a)
  try:
    step_lib.check_microbatches(build_config(a))
  except ValueError as e:
    p.error(f"--microbatches {a.microbatches}: {e}")
  part, devices = a.batch // a.microbatches, jax.device_count()
  if part % devices:  # (the batch is sharded over every device: JAX's IndivisibleError)
    p.error(f"--batch {a.batch}" + (f" in --microbatches {a.microbatches} parts of {part}"
                                    if a.microbatches > 1 else "")
            + f" is not divisible by the {devices} devices the step runs on")
  # JAX reads JAX_COMPILATION_CACHE_DIR itself: the probe must look in that folder too (a
  # load from it was reported as a compile, cache_hit false).
  cache = None
  folder = a.compile_cache or os.environ.get("JAX_COMPILATION_CACHE_DIR")
  if folder:
    try:
      cache = runtime.enable_compilation_cache(folder)
    except ValueError as e:
      p.error(str(e))
  loaded = compile_cache_probe(cache)
  res = measure(build_config(a), a.repeats)
  res["cache_hit"] = loaded()  # as `sav-jax bench` records it
  res["repeats"] = a.repeats  # the median's sample size, as `sav-jax bench` records it
  print(f"device        {res['device']} x{res['devices']}  (jax {res['jax']})")
  print(f"step          B={res['batch']} T={res['frames']} {res['height']}x{res['width']} "
        f"iters={res['iters']} {res['dtype']} remat={res['remat']}")
  print(f"compile       {res['compile_s']:.1f} s (trace {res['trace_s']:.1f} s, lower "
        f"{res['lower_s']:.1f} s, XLA {res['xla_compile_s']:.1f} s)"
        f"{compile_cache_note(cache, res['cache_hit'])}")
  print(f"step time     median {res['median_s']:.2f} s (min {res['min_s']:.2f} s), "
        f"{res['samples_per_s']:.3f} samples/s")
  print("\n".join(memory_lines(res, batch=res["batch"])))
  if a.json:
    try:
      write_json_result(a.json, res, a.overwrite)
    except UsageError as e:  # (a file of that name made during the run: kept)
      p.error(str(e))


if __name__ == "__main__":
  main()

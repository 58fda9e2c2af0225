"""`sav-jax bench`: compile time, forward time, frames/s and peak memory of the model."""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import sys
import tempfile
import time

from sav_jax._checks import plural
from sav_jax.config import GRU_CONV, VIT_ATTENTION
from sav_jax.tools import (UsageError, add_compile_cache_arguments,
                           add_matmul_precision_argument, matmul_precision,
                           setup_compile_cache, user_path)

HELP = "benchmark the compiled forward pass (compile time, median time, fps, peak memory)"


def add_arguments(p: argparse.ArgumentParser) -> None:
  p.add_argument("--frames", type=int, default=5, help="frames per clip (T; default 5)")
  p.add_argument("--height", type=int, default=128, help="frame height (default 128)")
  p.add_argument("--width", type=int, default=256, help="frame width (default 256)")
  p.add_argument("--iters", type=int, default=8,
                 help="refinement iterations at 1/4 (>= 2; default 8)")
  p.add_argument("--batch", type=int, default=1, help="clips per call (default 1)")
  p.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                 help="compute dtype (default float32)")
  p.add_argument("--vit-attention", choices=VIT_ATTENTION, default="auto",
                 help="the depth prior's ViT attention (SAVConfig.vit_attention; 'cudnn': "
                      "fused flash attention, CUDA GPUs with --dtype bfloat16; 'auto' "
                      "(default): cudnn where it applies, else blocked)")
  p.add_argument("--gru-conv", choices=GRU_CONV, default="auto",
                 help="the GRU's 1x15 z/r convolutions (SAVConfig.gru_conv; 'dft': products "
                      "per frequency bin; 'auto' (default): dft on CPU in float32, else direct)")
  p.add_argument("--repeats", type=int, default=5,
                 help="timed calls after the warm-up call (default 5)")
  p.add_argument("--all-predictions", action="store_true",
                 help="return every refinement step (training view) instead of the final one")
  p.add_argument("--json", type=user_path, help="write the results to this JSON file (a new file, or an "
                                 "existing one with --overwrite)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
  p.add_argument("--compare", type=user_path, help="a JSON written by --json (or by benchmarks/official_torch.py, "
                                    "the official PyTorch forward): print the ratios against it")
  add_matmul_precision_argument(p)
  add_compile_cache_arguments(p, default_on=False)


def write_json_result(path, data, overwrite: bool) -> None:
  """Writes `data` to `path` as JSON after a run (`json_output_problem` checked it before):
  a new file, or with `overwrite` a replaced one. Raises UsageError where a file of that name
  was created during the run (two runs given one name): kept, not replaced."""
  try:
    f = open(path, "w" if overwrite else "x", encoding="utf-8")
  except FileExistsError as e:
    raise UsageError(f"--json {path} was created during the run; not replaced (the results "
                     "are above; pass --overwrite to replace it)") from e
  with f:
    json.dump(data, f, indent=1)


def json_output_problem(path: str | None, overwrite: bool, flag: str = "--json") -> str | None:
  """What is wrong with writing a results JSON at `path` (checked before a long run), or
  None: a symbolic link, a folder, an existing file without `overwrite`, a missing parent
  folder or one where nothing can be created; no `path` (none asked for) with `overwrite`."""
  if not path:
    return f"--overwrite replaces a {flag} file: name one with {flag}" if overwrite else None
  if os.path.islink(path):  # open() would write into the link's target, whatever it is
    return f"{flag} {path} is a symbolic link; give the path of a regular file"
  if os.path.isdir(path):
    return f"{flag} {path} is a folder; give a file name"
  if path.endswith(("/", os.sep)):  # a folder's name: open() would fail after the run
    return f"{flag} {path} ends in a slash; give a file name"
  if os.path.exists(path) and not overwrite:
    return f"{flag} {path} exists; pass --overwrite to replace it"
  parent = os.path.dirname(os.path.abspath(path))
  if not os.path.isdir(parent):
    what = "is a file, not a folder" if os.path.exists(parent) else "does not exist"
    return f"{flag} {path}: {parent} {what}"
  try:  # os.access says yes to root everywhere: /proc, /sys and read-only mounts refuse later
    os.rmdir(tempfile.mkdtemp(prefix=".sav-jax-write-test-", dir=parent))
  except OSError as e:
    return f"{flag} {path}: cannot create a file in {parent} ({e.strerror or e})"
  return None


def compile_cache_probe(folder):
  """Called before a compile: a function that says afterwards whether that compile was a
  load from the persistent compilation cache `folder` (the folder gained no entry);
  always False without a folder."""
  entries = lambda: set(os.listdir(folder)) if folder else set()  # noqa: E731
  before = entries()
  return lambda: bool(folder) and entries() == before


def compile_cache_note(folder, cache_hit: bool) -> str:
  """`" (loaded from the compilation cache)"`, `" (stored in FOLDER)"`, or `""` without one."""
  if folder is None:
    return ""
  return " (loaded from the compilation cache)" if cache_hit else f" (stored in {folder})"


def peak_rss_gb() -> float:
  """Peak resident set size of this process so far, in GB."""
  rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
  return rss / (1024 ** 3 if sys.platform == "darwin" else 1024 ** 2)


def device_peak_gb(device):
  """Peak device memory in GB, or None where the backend does not report it (CPU)."""
  try:
    stats = device.memory_stats() or {}
  except Exception:  # pylint: disable=broad-except  # CPU backends may not implement it
    return None
  peak = stats.get("peak_bytes_in_use")
  return None if peak is None else peak / 1024 ** 3


def xla_buffers_gb(compiled) -> dict:
  """XLA's own account of a compiled program's buffers, in GB: `xla_temp_gb` (the
  intermediates), `xla_args_gb`, `xla_out_gb`; None where the backend offers no analysis.

  Unlike the device peak, this excludes what the compiler itself allocated on the device
  (the GPU compiler's autotuning runs candidate kernels on scratch buffers)."""
  try:
    ma = compiled.memory_analysis()
    sizes = (ma.temp_size_in_bytes, ma.argument_size_in_bytes, ma.output_size_in_bytes)
  except Exception:  # pylint: disable=broad-except  # not offered by every backend
    sizes = (None,) * 3
  return {k: None if v is None else v / 1024 ** 3
          for k, v in zip(("xla_temp_gb", "xla_args_gb", "xla_out_gb"), sizes)}


def memory_lines(res: dict, batch: int | None = None) -> list[str]:
  """The memory report of a `measure` result (bench and benchmarks/train_step.py; with
  `batch`, the peaks per sample too)."""
  per = lambda gb: "" if batch is None else f", {gb / batch:.2f} GB/sample"  # noqa: E731
  lines = [f"peak host RSS {res['peak_rss_gb']:.2f} GB{per(res['peak_rss_gb'])}"]
  if res.get("device_peak_gb") is not None:
    lines.append(f"device peak   {res['device_peak_gb']:.2f} GB{per(res['device_peak_gb'])} "
                 f"(after compiling, before the first call: "
                 f"{res['device_peak_compile_gb']:.2f} GB)")
  if res.get("xla_temp_gb") is not None:
    lines.append(f"XLA buffers   {res['xla_temp_gb']:.2f} GB intermediates + "
                 f"{res['xla_args_gb']:.2f} GB arguments + {res['xla_out_gb']:.2f} GB outputs")
  return lines


def measure(frames, height, width, iters, batch=1, dtype="float32", repeats=5,
            final_only=True, compile_cache=None, vit_attention="auto", gru_conv="auto") -> dict:
  """Compiles and times the forward pass on random weights and a random clip.

  Like the inference helpers, it returns freed host memory to the OS after
  creating the weights and after compiling (`sav_jax.runtime.release_host_memory`).

  Args:
    compile_cache: the persistent compilation cache folder in use, if any (then
      `compile_s` is a cache load when `cache_hit`).

  Returns:
    dict with `compile_s`, `cache_hit`, `median_s`, `min_s`, `fps`, `peak_rss_gb`,
    `device_peak_gb` and `device_peak_compile_gb` (the peak after compiling, before the
    first call; None on CPU), XLA's buffer sizes (`xla_buffers_gb`) and the settings
    (`vit_attention`, `gru_conv`: the implementations that ran, "auto" resolved).
  """
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  import numpy as np  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax import runtime  # pylint: disable=import-outside-toplevel
  from sav_jax.config import (  # pylint: disable=import-outside-toplevel
      resolve_gru_conv, resolve_vit_attention)
  from sav_jax.model.init import init_variables  # pylint: disable=import-outside-toplevel

  cfg = sav_jax.SAVConfig(dtype=dtype, vit_attention=vit_attention, gru_conv=gru_conv)
  model = sav_jax.StereoAnyVideo(cfg)
  variables = jax.device_put(init_variables(cfg, seed=0))
  runtime.release_host_memory()
  rng = np.random.default_rng(0)
  left = jnp.asarray(rng.uniform(0, 255, (batch, frames, height, width, 3)), jnp.float32)
  right = jnp.roll(left, -4, axis=3)
  fwd = jax.jit(lambda v, l, r: model.apply(v, l, r, iters=iters, final_only=final_only).disparities)
  loaded = compile_cache_probe(compile_cache)
  t0 = time.perf_counter()
  options = runtime.inference_compiler_options()  # those of sav_jax.inference's executables
  compiled = fwd.lower(variables, left, right).compile(compiler_options=options)
  compile_s = time.perf_counter() - t0
  cache_hit = loaded()
  device = jax.devices()[0]
  compile_peak = device_peak_gb(device)
  runtime.release_host_memory()
  compiled(variables, left, right).block_until_ready()  # warm-up
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    compiled(variables, left, right).block_until_ready()
    times.append(time.perf_counter() - t0)
  median = statistics.median(times)
  return dict(
      frames=frames, height=height, width=width, iters=iters, batch=batch, dtype=dtype,
      vit_attention=resolve_vit_attention(vit_attention, cfg.compute_dtype),
      gru_conv=resolve_gru_conv(gru_conv, cfg.compute_dtype),
      final_only=final_only, compiler_options=options, compile_s=compile_s, cache_hit=cache_hit, median_s=median, min_s=min(times),
      fps=batch * frames / median, peak_rss_gb=peak_rss_gb(),
      device_peak_gb=device_peak_gb(device), device_peak_compile_gb=compile_peak,
      **xla_buffers_gb(compiled), device=f"{device.platform}:{device.device_kind}",
      host=platform.node(), cpu=cpu_model(), jax=jax.__version__,
      date=time.strftime("%Y-%m-%d"))


def cpu_model() -> str:
  """The host CPU's model name (`/proc/cpuinfo` on Linux, else `platform.processor()`):
  hosts of one name (a cloud's VMs) may differ in it."""
  try:
    with open("/proc/cpuinfo", encoding="utf-8") as f:
      for line in f:
        if line.lower().startswith("model name"):
          return line.partition(":")[2].strip()
  except OSError:
    pass
  return platform.processor() or "unknown"


_COMPARED = ("median_s", "compile_s", "peak_rss_gb")
_SHAPE = ("frames", "height", "width", "iters", "batch")  # a ratio needs the same work
# Keys only benchmarks/train_step.py's JSON has (a training step is not a forward).
_TRAIN_STEP_KEYS = ("samples_per_s", "remat", "loss")


def _read_baseline(path) -> dict:
  try:
    with open(path, encoding="utf-8") as f:
      base = json.load(f)
  except (OSError, ValueError) as e:
    raise UsageError(f"--compare {path}: cannot read a bench JSON ({e})") from e
  missing = [k for k in _COMPARED + _SHAPE if not isinstance(base, dict) or k not in base]
  if missing:
    raise UsageError(f"--compare {path}: not a `sav-jax bench --json` file (lacks {missing})")
  train = [k for k in _TRAIN_STEP_KEYS if k in base]
  if train:
    raise UsageError(f"--compare {path}: a training step's JSON (benchmarks/train_step.py: "
                     f"{train}), not a forward's")
  bad = {k: base[k] for k in _COMPARED
         if not (k == "compile_s" and base[k] is None)  # an eager baseline compiles nothing
         and (isinstance(base[k], bool) or not isinstance(base[k], (int, float))
              or not math.isfinite(base[k]) or base[k] < 0
              or (base[k] == 0 and k != "compile_s"))}
  if bad:
    raise UsageError(f"--compare {path}: expected positive numbers (compile_s: >= 0 or null), "
                     f"got {bad}")
  bad = {k: base[k] for k in _SHAPE if isinstance(base[k], bool) or not isinstance(base[k], int)}
  if bad:  # "2" against 2 read as another shape ("frames: 2 here, 2 there")
    raise UsageError(f"--compare {path}: expected integers for the shape, got {bad}")
  return base


def baseline_differences(args: argparse.Namespace, base: dict) -> dict:
  """`{key: (this run's, the baseline's)}` of the shape and settings that make a ratio
  meaningless (the compute dtype, all predictions or the last); settings a baseline does
  not record are not compared."""
  mine = {k: getattr(args, k) for k in _SHAPE}
  mine.update(dtype=args.dtype, final_only=not args.all_predictions)
  return {k: (v, base[k]) for k, v in mine.items() if k in base and base[k] != v}


def _difference(key: str, values: tuple) -> str:
  """One `baseline_differences` entry in the options' words: `(--iters: 2 here, 8 there)`."""
  if key == "final_only":  # (the JSON's key; the option is --all-predictions)
    said = {True: "the final prediction", False: "every prediction (--all-predictions)"}
    here, there = (said.get(v, f"final_only {v!r}") for v in values)  # (a hand-edited JSON)
    return f"({here} here, {there} there)"
  return f"(--{key}: {values[0]} here, {values[1]} there)"


def machine_note(res: dict, base: dict) -> str:
  """A warning when the baseline was measured on another device (platform, or GPU model),
  another host or with another ViT attention: a ratio needs both on the same machine in the
  same session. `""` when both agree or the baseline does not record them."""
  def device(d):
    platform_, _, kind = str(d).partition(":")
    return platform_, (kind if platform_ != "cpu" else "")  # CPU kinds name nothing useful
  differ = []
  if "device" in base:
    (p1, k1), (p2, k2) = device(res["device"]), device(base["device"])
    if p1 != p2 or (k1 and k2 and k1 != k2):
      differ.append(f"device {res['device']} here, {base['device']} there")
  for key in ("host", "cpu", "jax"):
    if base.get(key) is not None and base[key] != res.get(key):
      differ.append(f"{key} {res.get(key)} here, {base[key]} there")
  settings = [f"{key} {res.get(key)} here, {base[key]} there"
              for key in ("vit_attention", "gru_conv", "matmul_precision", "compiler_options")
              if base.get(key) is not None and base[key] != res.get(key)]
  if differ:
    return ("warning: the baseline was measured elsewhere (" + "; ".join(differ + settings)
            + "): the ratios compare machines, not code")
  lines = []
  if settings:  # e.g. --no-low-memory-compile: compile time and memory move with it
    lines.append("warning: the baseline was measured with other settings ("
                 + "; ".join(settings) + "): the ratios compare those settings, not code")
  if base.get("date") and base["date"] != res.get("date"):  # (also with other settings:
    # a --gru-conv direct run of another day compares the days too)
    lines.append(f"note: the baseline was measured on {base['date']}: machines of one kind "
                 "differ between sessions (up to 1.75x seen on CPUs), so remeasure it here for "
                 "a ratio of code alone")
  return "\n".join(lines)


def compare_line(res: dict, base: dict) -> str:
  """This run against a baseline: `forward x1.32 faster (0.75 s vs 0.99 s), ...`."""
  def ratio(name, now, before, unit, lower_is=("faster", "slower")):
    values = f"({now:.3g} {unit} vs {before:.3g} {unit})"
    if min(now, before) <= 0:  # (a compile of 0 s: a ratio says nothing)
      return f"{name} {values}"
    r = max(now, before) / min(now, before)
    if round(r, 2) == 1:
      return f"{name} the same {values}"
    return f"{name} x{r:.2f} {lower_is[0] if now < before else lower_is[1]} {values}"
  compile_part = (f"compile {res['compile_s']:.3g} s (the baseline compiles nothing)"
                  if base["compile_s"] is None
                  else ratio("compile", res["compile_s"], base["compile_s"], "s"))
  loads = [who for who, r in (("this run", res), ("the baseline", base)) if r.get("cache_hit")]
  if loads and len(loads) == 1:  # a cache load set against a compile
    compile_part += f" ({loads[0]} loaded it from the compilation cache)"
  parts = [ratio("forward", res["median_s"], base["median_s"], "s"), compile_part,
           ratio("peak RSS", res["peak_rss_gb"], base["peak_rss_gb"], "GB", ("lower", "higher"))]
  if res.get("device_peak_gb") and base.get("device_peak_gb"):  # a GPU's memory
    parts.append(ratio("device peak", res["device_peak_gb"], base["device_peak_gb"], "GB",
                       ("lower", "higher")))
  return ", ".join(parts)


def clip_problem(args: argparse.Namespace) -> str | None:
  """What is wrong with the clip options `frames`, `height`, `width`, `iters`, `batch`,
  `repeats` (bench and benchmarks/: the model's trace failed naming no flag), or None;
  `iters`, `batch` or `repeats` that `args` lacks (a script without the option) count as
  valid."""
  if min(args.height, args.width) < 16 or args.height % 16 or args.width % 16 or args.width < 32:
    return (f"--height/--width must be positive multiples of 16, the width at least 32 "
            f"(got {args.height}x{args.width})")
  if getattr(args, "iters", 2) < 2:
    return f"--iters must be >= 2 (got {args.iters})"
  for name in ("frames", "batch", "repeats"):
    if getattr(args, name, 1) < 1:
      return f"--{name} must be >= 1, got {getattr(args, name)}"
  from sav_jax.config import TEMPORAL_MAX_LEN  # pylint: disable=import-outside-toplevel
  if args.frames > TEMPORAL_MAX_LEN:
    return (f"--frames must be at most {TEMPORAL_MAX_LEN} (the depth prior's temporal "
            f"attention length; predict_video runs longer videos in windows), got "
            f"{args.frames}")
  return None


def run(args: argparse.Namespace) -> int:
  problem = clip_problem(args)
  if problem:
    raise UsageError(problem)
  if args.vit_attention == "cudnn" and args.dtype != "bfloat16":
    raise UsageError("--vit-attention cudnn needs --dtype bfloat16 (cuDNN's fused attention "
                     "has no float32 kernels)")
  if args.vit_attention == "cudnn":  # (the model's trace says so too, after the weights' init)
    import jax  # pylint: disable=import-outside-toplevel
    if jax.default_backend() != "gpu":
      raise UsageError(f"--vit-attention cudnn needs a CUDA GPU; JAX's backend is "
                       f"{jax.default_backend()!r} (use blocked, or the default auto)")
  problem = json_output_problem(args.json, args.overwrite)
  if problem:  # checked before the long run
    raise UsageError(problem)
  base = _read_baseline(args.compare) if args.compare else None  # before the long run
  if base is not None:
    differ = baseline_differences(args, base)
    if differ:
      raise UsageError(f"--compare {args.compare} was measured at another shape or setting "
                       + ", ".join(map(_difference, differ, differ.values())))
  cache = setup_compile_cache(args, default_on=False)
  precision, precision_name = matmul_precision(args)
  with precision:
    res = measure(args.frames, args.height, args.width, args.iters, args.batch, args.dtype,
                  args.repeats, final_only=not args.all_predictions, compile_cache=cache,
                  vit_attention=args.vit_attention, gru_conv=args.gru_conv)
  res["matmul_precision"] = precision_name
  res["repeats"] = args.repeats  # the median's sample size (the READMEs' "median of 3")
  platform, _, kind = res["device"].partition(":")
  print(f"device        {kind if kind and kind.lower() != platform else platform}"
        f"{f' ({platform})' if kind and kind.lower() != platform else ''}  (jax {res['jax']})")
  print(f"input         B={res['batch']} T={res['frames']} {res['height']}x{res['width']} "
        f"iters={res['iters']} {res['dtype']}"
        + ("" if res["final_only"] else ", every prediction (--all-predictions)")
        + ("" if res["vit_attention"] == "blocked" else f", ViT attention {res['vit_attention']}")
        + ("" if res["gru_conv"] == "direct" else f", GRU 1x15 convolutions {res['gru_conv']}"))
  if res["compiler_options"]:
    print("XLA options   " + ", ".join(f"{k}={v}" for k, v in res["compiler_options"].items()))
  print(f"compile       {res['compile_s']:.2f} s{compile_cache_note(cache, res['cache_hit'])}")
  print(f"forward       median {res['median_s']:.3f} s  (min {res['min_s']:.3f} s, "
        f"{plural(args.repeats, 'run')})")
  print(f"throughput    {res['fps']:.2f} frames/s")
  print("\n".join(memory_lines(res)))
  if base is not None:
    note = machine_note(res, base)
    if note:
      print(note)
    print(f"vs {args.compare}: " + compare_line(res, base))
  if args.json:
    write_json_result(args.json, res, args.overwrite)
    print(f"wrote {args.json}")
  return 0

"""The official PyTorch forward, timed on this machine: the baseline for `sav-jax bench --compare`.

    pip install torch==2.13.0 easydict einops opt_einsum unfoldNd scipy \
        opencv-python-headless tqdm
    git clone https://github.com/TomTomTommi/stereoanyvideo /path/to/stereoanyvideo
    python benchmarks/official_torch.py --repo /path/to/stereoanyvideo \
        --json benchmarks/results/cpu_official_torch_t5_128x256_it8.json
    sav-jax bench --compare benchmarks/results/cpu_official_torch_t5_128x256_it8.json

Issue 7's targets are ratios against the official release *on the same hardware*, and the
machines of one kind differ by up to ~1.75x in speed from day to day, so both sides of a ratio
are measured in the same session. This script imports the official code from the checkout
given with `--repo` (nothing of it is copied into this project), builds `StereoAnyVideo` with
random weights (its time does not depend on the values; the Video-Depth-Anything checkpoint
that the official constructor loads from `./models/...` is skipped), and times
`model(left, right, iters=ITERS, test_mode=True)` under `torch.inference_mode()` as its
evaluation does: one warm-up call, then the median of `--repeats` calls (`--by-module`: and
one more call timed per model part). Peak RSS is the
whole process's, as `sav-jax bench` reports it. Run it in an environment with torch (this
project does not need torch); the official code's unused imports (`timm`, `torchvision`'s
`Compose`) are replaced by empty stand-ins where they are not installed.
The JSON has the keys `sav-jax bench --compare` reads; `compile_s` is null (eager PyTorch
compiles nothing; the warm-up call's time is in `first_call_s`).
"""

from __future__ import annotations

import argparse
import atexit
import datetime
import importlib
import importlib.util
import json
import os
import pathlib
import platform
import resource
import shutil
import statistics
import sys
import tempfile
import time
import types
from unittest import mock


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--repo", required=True,
                 help="a checkout of github.com/TomTomTommi/stereoanyvideo")
  p.add_argument("--frames", type=int, default=5)
  p.add_argument("--height", type=int, default=128)
  p.add_argument("--width", type=int, default=256)
  p.add_argument("--iters", type=int, default=8)
  p.add_argument("--batch", type=int, default=1)
  p.add_argument("--repeats", type=int, default=3, help="timed calls after the warm-up call")
  p.add_argument("--threads", type=int, default=None,
                 help="torch.set_num_threads (default: torch's own, one per core)")
  p.add_argument("--by-module", action="store_true",
                 help="after the timed calls, one more call with the time of each model part "
                      "(forward hooks; the parts `benchmarks/stage_times.py` reports)")
  p.add_argument("--json", help="write the results here (a new file, or --overwrite)")
  p.add_argument("--overwrite", action="store_true")
  a = p.parse_args(argv)
  problem = repo_problem(a.repo)
  if problem:
    p.error(problem)
  a.repo = pathlib.Path(a.repo).expanduser().resolve()
  if a.iters < 2:
    p.error(f"--iters must be >= 2 (got {a.iters})")
  for name in ("frames", "height", "width", "batch", "threads"):  # (torch's traceback after
    if getattr(a, name) is not None and getattr(a, name) < 1:     # building the model)
      p.error(f"--{name} must be >= 1 (got {getattr(a, name)})")
  if a.repeats < 1:
    p.error(f"--repeats must be >= 1 (got {a.repeats})")
  # checked before the long run, as `sav-jax bench` does (its json_output_problem is not
  # imported: it would import JAX into the process whose memory is measured)
  if a.overwrite and not a.json:  # (the results would not be written)
    p.error("--overwrite replaces a --json file: name one with --json")
  if a.json:
    if os.path.islink(a.json):
      p.error(f"--json {a.json} is a symbolic link; give the path of a regular file")
    if os.path.isdir(a.json):
      p.error(f"--json {a.json} is a folder; give a file name")
    if a.json.endswith(("/", os.sep)):  # a folder's name: open() would fail after the run
      p.error(f"--json {a.json} ends in a slash; give a file name")
    if os.path.exists(a.json) and not a.overwrite:
      p.error(f"--json {a.json} exists; pass --overwrite to replace it")
    parent = os.path.dirname(os.path.abspath(a.json))
    if not os.path.isdir(parent):
      p.error(f"--json {a.json}: folder {parent} does not exist")
  return a


def repo_problem(repo) -> str | None:
  """What is wrong with `repo` as the official checkout (`--repo`), or None (also
  gradient_check.py's check, before its own side runs)."""
  if not (pathlib.Path(repo).expanduser() / "models" / "core" / "stereoanyvideo.py").is_file():
    return (f"--repo {repo}: no models/core/stereoanyvideo.py there; give a checkout of "
            "github.com/TomTomTommi/stereoanyvideo")
  return None


def cpu_model() -> str:
  """The host CPU's model name, as `sav-jax bench` records it (`cpu`): this project's VMs all
  call themselves `vm`, so `--compare` tells another machine by this (sav_jax's own function
  is not imported here: the environment with torch may not have sav_jax)."""
  try:
    with open("/proc/cpuinfo", encoding="utf-8") as f:
      for line in f:
        if line.lower().startswith("model name"):
          return line.partition(":")[2].strip()
  except OSError:
    pass
  return platform.processor() or "unknown"


def _stand_in(name: str, **attrs) -> None:
  """Registers an empty module `name` (and its parents) unless the real one imports."""
  try:
    importlib.import_module(name)
    return
  except Exception:  # pylint: disable=broad-except  # absent, or a torchvision that fails to load
    pass
  parts = name.split(".")
  for i in range(1, len(parts) + 1):
    sub = ".".join(parts[:i])
    if sub not in sys.modules or i == len(parts):
      sys.modules[sub] = types.ModuleType(sub)
      if i > 1:
        setattr(sys.modules[".".join(parts[:i - 1])], parts[i - 1], sys.modules[sub])
  for k, v in attrs.items():
    setattr(sys.modules[name], k, v)


def build_official_model(repo: pathlib.Path):
  """The official `StereoAnyVideo()` in eval mode, random weights, imported from `repo`."""
  import torch  # pylint: disable=import-outside-toplevel

  # The official code imports itself as the package `stereoanyvideo`.
  link_dir = pathlib.Path(tempfile.mkdtemp(prefix="sav_official_"))
  atexit.register(shutil.rmtree, link_dir, ignore_errors=True)  # removes the link, not `repo`
  (link_dir / "stereoanyvideo").symlink_to(repo, target_is_directory=True)
  sys.path.insert(0, str(link_dir))
  _stand_in("timm")
  _stand_in("torchvision.transforms", Compose=lambda transforms: transforms)
  module = importlib.import_module("stereoanyvideo.models.core.stereoanyvideo")
  torch.manual_seed(0)
  # DepthExtractor loads ./models/Video-Depth-Anything/checkpoints/*.pth: keep its random init.
  with mock.patch.object(torch, "load", lambda *a, **k: {}), \
       mock.patch.object(torch.nn.Module, "load_state_dict", lambda self, *a, **k: None):
    model = module.StereoAnyVideo()
  return model.eval()


# Model parts timed by --by-module (attribute paths of the official StereoAnyVideo).
PARTS = ("depthnet", "fnet", "cnet", "corr_mlp", "update_block.encoder",
         "update_block.time_attn", "update_block.space_attn", "update_block.gru",
         "update_block.flow_head", "update_block.mask3d")


def time_parts(model, call) -> dict:
  """Seconds spent in each of `PARTS` during one `call()`, summed over its invocations, keyed
  `"part @HxW"` by the spatial size of the part's first input (so the refinement scales come
  apart), each with its number of invocations; `total` is the call's time."""
  spent, counts = {}, {}
  handles = []
  for name in PARTS:
    module = model.get_submodule(name)
    start = []
    def pre(_m, inp, start=start, name=name):
      start.append((f"{name} @{inp[0].shape[-2]}x{inp[0].shape[-1]}", time.perf_counter()))
    def post(_m, _inp, _out, start=start):
      key, t0 = start.pop()
      spent[key] = spent.get(key, 0.0) + time.perf_counter() - t0
      counts[key] = counts.get(key, 0) + 1
    handles += [module.register_forward_pre_hook(pre), module.register_forward_hook(post)]
  try:
    t0 = time.perf_counter()
    call()
    total = time.perf_counter() - t0
  finally:
    for h in handles:
      h.remove()
  return {"total": total, "parts": {k: {"s": spent[k], "calls": counts[k]} for k in spent}}


def measure(a) -> dict:
  import numpy as np  # pylint: disable=import-outside-toplevel
  import torch  # pylint: disable=import-outside-toplevel

  if a.threads:
    torch.set_num_threads(a.threads)
  model = build_official_model(a.repo)
  rng = np.random.default_rng(0)
  left = torch.from_numpy(
      rng.uniform(0, 255, (a.batch, a.frames, 3, a.height, a.width)).astype(np.float32))
  right = torch.roll(left, -4, dims=4)

  def call():
    with torch.inference_mode():
      return model(left, right, iters=a.iters, test_mode=True)

  t0 = time.perf_counter()
  out = call()
  first = time.perf_counter() - t0
  times = []
  for _ in range(a.repeats):
    t0 = time.perf_counter()
    call()
    times.append(time.perf_counter() - t0)
  median = statistics.median(times)
  parts = time_parts(model, call) if a.by_module else None
  rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
  return {
      "implementation": "official PyTorch (github.com/TomTomTommi/stereoanyvideo)",
      "frames": a.frames, "height": a.height, "width": a.width, "iters": a.iters,
      "batch": a.batch, "dtype": "float32", "final_only": True,
      "output_shape": list(out.shape),
      "compile_s": None, "first_call_s": first, "median_s": median, "min_s": min(times),
      "fps": a.batch * a.frames / median,
      "peak_rss_gb": rss / (1024 ** 3 if sys.platform == "darwin" else 1024 ** 2),
      "device": "cpu", "threads": torch.get_num_threads(), "torch": torch.__version__,
      "host": platform.node(), "cpu": cpu_model(), "date": datetime.date.today().isoformat(),
      "parts_s": parts,
  }


def main(argv=None) -> int:
  a = parse_args(argv)
  if importlib.util.find_spec("torch") is None:
    raise SystemExit(f"torch is not installed in this Python ({sys.executable}): run the script "
                     "in an environment with torch (pip install torch==2.13.0 ...)")
  res = measure(a)
  print(f"official PyTorch {res['torch']}, {res['threads']} threads: B={a.batch} "
        f"T={a.frames} {a.height}x{a.width} iters={a.iters}")
  print(f"first call    {res['first_call_s']:.2f} s")
  print(f"forward       median {res['median_s']:.3f} s  (min {res['min_s']:.3f} s, "
        f"{a.repeats} runs)")
  print(f"peak host RSS {res['peak_rss_gb']:.2f} GB")
  if res["parts_s"]:
    parts = res["parts_s"]
    print(f"one more call, by part ({parts['total']:.2f} s in all):")
    for key, v in parts["parts"].items():
      print(f"  {key:34s} {v['s']:7.3f} s  ({v['calls']} calls, {v['s'] / v['calls']:.4f} s each)")
  if a.json:
    try:  # "x": a file of that name made during the run (checked before it) is kept
      f = open(a.json, "w" if a.overwrite else "x", encoding="utf-8")
    except FileExistsError:
      raise SystemExit(f"official_torch.py: --json {a.json} was created during the run; not "
                       "replaced (the results are above; pass --overwrite to replace it)")
    with f:
      json.dump(res, f, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())

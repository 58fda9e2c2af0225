"""Time of one RAFT flow as the evaluator computes it (`sav_jax.model.raft.raft_flow`).

    python benchmarks/raft_flow.py [--height 436 --width 1024 --iters 20 --repeats 3]
        [--official CHECKOUT]

Random weights of the official layout (the fixtures' make_weights.py recipe, found as the
tests find it: `--fixtures`, `SAV_FIXTURES` or ../shared/fixtures; the test manifest), a random
RGB frame and a copy moved by 3 px. Prints the first call (compile + run), the median of the
next `--repeats` calls and the process's peak RSS. `--official CHECKOUT` (a checkout of the
official Stereo Any Video repository; needs torch and scipy) times the official RAFT code
(`third_party/RAFT`, imported from the checkout, same padding and iterations) in the same
process, after ours.
"""

import argparse
import importlib
import importlib.util
import pathlib
import sys
import time
from types import SimpleNamespace

import jax
import numpy as np

from sav_jax.convert.raft import raft_variables_from_state_dict
from sav_jax.model.raft import raft_flow
from sav_jax.tools.bench import peak_rss_gb

from timing import (add_clip_arguments, fixtures_folder, make_weights_module,  # benchmarks/timing.py
                    timed)

ROOT = pathlib.Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "tests" / "fixtures" / "raft" / "raft_manifest.json"


def official_seconds(checkout, a, b, iters, repeats):
  import torch  # pylint: disable=import-outside-toplevel
  torch.set_grad_enabled(False)
  sys.path.insert(0, str(pathlib.Path(checkout) / "third_party" / "RAFT"))
  raft = importlib.import_module("core.raft")
  utils = importlib.import_module("core.utils.utils")
  model = raft.RAFT(SimpleNamespace(small=False, mixed_precision=False, dropout=0.0)).eval()
  t1, t2 = (torch.from_numpy(np.moveaxis(x, -1, 0)[None].copy()) for x in (a, b))
  t1, t2 = utils.InputPadder(t1.shape).pad(t1, t2)
  model(t1, t2, iters=iters, test_mode=True)  # warm-up, as ours gets
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    model(t1, t2, iters=iters, test_mode=True)
    times.append(time.perf_counter() - start)
  return float(np.median(times)), torch.get_num_threads()


def main():
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  add_clip_arguments(ap, frames=None, height=436, width=1024, iters=20)
  ap.add_argument("--repeats", type=int, default=3)
  ap.add_argument("--official", help="checkout of the official repository (times its RAFT)")
  ap.add_argument("--fixtures", help="oracle fixtures folder with make_weights.py (default: "
                  "SAV_FIXTURES, else ../shared/fixtures)")
  args = ap.parse_args()
  if args.repeats < 1:  # (the median of no call failed after the first, compiling one)
    ap.error(f"--repeats must be >= 1, got {args.repeats}")
  if args.official:  # checked before our run: a wrong path failed only after it, minutes later
    if not (pathlib.Path(args.official) / "third_party" / "RAFT" / "core" / "raft.py").is_file():
      ap.error(f"--official {args.official}: no third_party/RAFT/core/raft.py there; give a "
               "checkout of github.com/TomTomTommi/stereoanyvideo")
    if importlib.util.find_spec("torch") is None:
      ap.error("--official needs torch (and scipy) installed in this environment")
  make_weights = make_weights_module(fixtures_folder(args.fixtures), "raft_flow")
  sd = make_weights.make_state_dict(str(MANIFEST), 0)
  variables = jax.device_put(raft_variables_from_state_dict(sd))
  rng = np.random.default_rng(0)
  a = rng.uniform(0, 255, (args.height, args.width, 3)).astype(np.float32)
  b = np.roll(a, 3, axis=1)
  start = time.perf_counter()
  jax.block_until_ready(raft_flow(variables, a, b, args.iters))
  first = time.perf_counter() - start
  run = timed(lambda: raft_flow(variables, a, b, args.iters), repeats=args.repeats)
  rss = peak_rss_gb()
  print(f"sav-jax RAFT {args.height}x{args.width} iters={args.iters} ({jax.default_backend()}): "
        f"first call {first:.2f} s, then {run:.2f} s median; peak RSS {rss:.2f} GB")
  if args.official:
    sec, threads = official_seconds(args.official, a, b, args.iters, args.repeats)
    print(f"official RAFT (PyTorch, {threads} threads): {sec:.2f} s median")


if __name__ == "__main__":
  main()

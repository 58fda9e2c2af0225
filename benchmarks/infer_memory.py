"""Peak host memory of `sav-jax infer` on a long frame-folder video, model work left out.

The model is replaced by a stand-in (a constant map per frame), so the figure is what the
command itself holds: decoded frames, disparities, the side-by-side video and the weights.
Run it on two checkouts to compare them (e.g. before and after the streaming `infer`):

    python benchmarks/infer_memory.py DATA_DIR --frames 300 --height 480 --width 640

The first run writes the frames (PNG folders `left/`, `right/`) and a random-weight
checkpoint into DATA_DIR; later runs reuse them (and refuse other --frames/--height/--width). Outputs go to DATA_DIR/out_<pid>.
"""

import argparse
import os
import pathlib
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax import cli, inference  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.model.init import init_variables  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools.bench import peak_rss_gb  # noqa: E402  pylint: disable=wrong-import-position


def write_data(root: pathlib.Path, frames: int, height: int, width: int) -> None:
  base = np.random.default_rng(0).integers(0, 255, (height, width, 3), np.uint8)
  for side in ("left", "right"):
    (root / side).mkdir(parents=True, exist_ok=True)
    for i in range(frames):
      cv2.imwrite(str(root / side / f"{i:05d}.png"), np.roll(base, i, axis=1))
  sd = sav_jax.convert.state_dict_from_params(init_variables(sav_jax.SAVConfig(), 0))
  np.savez(root / "sav.npz", **sd)


def prepare_data(parser, args, write) -> None:
  """`write(DATA, frames, height, width)` into a new DATA folder; a DATA folder an earlier run
  wrote is reused if it holds the video asked for (else `parser.error`)."""
  if not (args.data / "sav.npz").exists():
    write(args.data, args.frames, args.height, args.width)
    return
  pngs = sorted((args.data / "left").glob("*.png"))
  size = cv2.imread(str(pngs[0])).shape[:2] if pngs else None
  if (len(pngs), size) != (args.frames, (args.height, args.width)):
    parser.error(f"{args.data} holds {len(pngs)} frames of {size} from an earlier run, not "
                 f"{args.frames} of {(args.height, args.width)}; name another DATA folder")


def stand_in(variables, left, right, *, cfg, iters, pads, check_memory, **_):
  """A window's raw output without the model: frame k of the window gets -(k + 1)."""
  del variables, right, cfg, iters, check_memory
  hp, wp = left.shape[1] + pads[0] + pads[1], left.shape[2] + pads[2] + pads[3]
  return -np.ones((len(left), hp, wp), np.float32) * (1 + np.arange(len(left))[:, None, None])


def main() -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("data", type=pathlib.Path)
  p.add_argument("--frames", type=int, default=300)
  p.add_argument("--height", type=int, default=480)
  p.add_argument("--width", type=int, default=640)
  args = p.parse_args()
  prepare_data(p, args, write_data)
  name = "_run_window" if hasattr(inference, "_run_window") else "run_window"  # older code
  setattr(inference, name, stand_in)
  start = time.perf_counter()
  rc = cli.main(["infer", "--left", str(args.data / "left"), "--right", str(args.data / "right"),
                 "--checkpoint", str(args.data / "sav.npz"), "--out",
                 str(args.data / f"out_{os.getpid()}"), "--iters", "2", "--format", "npy"])
  peak = peak_rss_gb()
  print(f"exit {rc}; {time.perf_counter() - start:.1f} s; peak RSS {peak:.2f} GB")


if __name__ == "__main__":
  main()

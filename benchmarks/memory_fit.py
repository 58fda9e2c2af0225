"""The data behind `inference.estimate_memory_bytes`: XLA's memory analysis over many shapes.

    python benchmarks/memory_fit.py

Compiles the forward (abstract inputs, nothing allocated; the same program as
`inference.compiled_forward` up to a leading batch axis of 1) for windows from 1x32x32 to 20x736x1280, and prints per shape the memory
the executable needs (temporaries + output + the two input windows, as the inference module
checks after compiling) next to the estimate and their ratio. The estimate must err high
(ratio >= 1) so that its cheap pre-compile check only refuses hopeless sizes.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax import inference  # noqa: E402  pylint: disable=wrong-import-position
from timing import compile_for_shape  # noqa: E402  pylint: disable=wrong-import-position

SHAPES = [(1, 32, 32, 20), (2, 64, 128, 20), (5, 128, 256, 4), (5, 128, 256, 20),
          (20, 128, 256, 20), (5, 256, 512, 20), (10, 256, 512, 20), (5, 448, 672, 20),
          (20, 448, 672, 20), (10, 736, 1280, 20), (20, 736, 1280, 20)]


def main():
  cfg = sav_jax.SAVConfig()
  print(f"{'T':>3s} {'H':>4s} {'W':>5s} {'iters':>5s} {'needed GiB':>10s} {'estimate GiB':>12s} "
        f"{'ratio':>6s}")
  for t, h, w, iters in SHAPES:
    compiled, seconds = compile_for_shape(cfg, t, h, w, iters)
    ma = compiled.memory_analysis()
    needed = ma.temp_size_in_bytes + ma.output_size_in_bytes + 2 * t * h * w * 3 * 4
    est = inference.estimate_memory_bytes(t, h, w, iters, cfg)
    print(f"{t:3d} {h:4d} {w:5d} {iters:5d} {needed / 2**30:10.3f} {est / 2**30:12.3f} "
          f"{est / needed:6.2f}   ({seconds:.0f} s)", flush=True)


if __name__ == "__main__":
  argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
  main()

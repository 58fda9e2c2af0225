"""Memory of the compiled forward at any shape, without running it (XLA's buffer assignment).

    python benchmarks/memory_projection.py                                   # paper's window
    python benchmarks/memory_projection.py --frames 20 --height 720 --width 1280 --iters 20 \
        --dtype bfloat16

Lowers the inference forward (`final_only=True`) for abstract inputs of the given shape and
compiles it for this machine's backend, which allocates nothing; prints XLA's accounting of the
executable: parameters (`argument`), output and `temp` (XLA's allocation for the
intermediate buffers under its schedule). On a CPU-only machine this projects what a GPU
needs for the same program: the GPU compiler fuses and schedules differently, so its figure
differs, but the large buffers (features, the GRU's inputs, attention maps) are the same
tensors. XLA:CPU computes bfloat16 convolutions and products in float32, so its bfloat16
figure includes float32 copies a GPU does not make. To see what is alive at the peak, add
`XLA_FLAGS="--xla_dump_to=DIR --xla_dump_hlo_as_text"` and read the "peak" section of
`DIR/*live-range.txt`.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402  pylint: disable=wrong-import-position

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.config import resolve_gru_conv  # noqa: E402  pylint: disable=wrong-import-position
from timing import (  # noqa: E402  pylint: disable=wrong-import-position
    add_clip_arguments, check_clip_arguments, compile_for_shape)


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  add_clip_arguments(p, frames=20, height=720, width=1280, iters=20)
  p.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"))
  p.add_argument("--frame-block-mb", type=float, default=None,
                 help="SAVConfig.frame_block_mb (default: the config's)")
  p.add_argument("--gru-conv", default="auto", choices=("auto", "direct", "dft"),
                 help="SAVConfig.gru_conv (default auto: on a CPU in float32 the DFT products, "
                      "which a GPU does not use; direct projects a GPU's program)")
  a = p.parse_args()
  check_clip_arguments(p, a)

  extra = {} if a.frame_block_mb is None else {"frame_block_mb": a.frame_block_mb}
  try:
    cfg = sav_jax.SAVConfig(dtype=a.dtype, gru_conv=a.gru_conv, **extra)
  except ValueError as e:  # (a --frame-block-mb of 0, negative or nan: a traceback)
    p.error(f"--frame-block-mb {a.frame_block_mb:g}: {e}")
  compiled, compile_s = compile_for_shape(cfg, a.frames, a.height, a.width, a.iters)
  m = compiled.memory_analysis()
  gb = lambda n: n / 2**30  # noqa: E731
  total = m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
  print(f"T={a.frames} {a.height}x{a.width} iters={a.iters} {a.dtype} "
        f"frame_block_mb={cfg.frame_block_mb:g} gru_conv={resolve_gru_conv(cfg.gru_conv, cfg.compute_dtype)} "
        f"({jax.devices()[0].platform}, jax {jax.__version__}, compiled in {compile_s:.0f} s)")
  print(f"  parameters {gb(m.argument_size_in_bytes):6.2f} GiB   output {gb(m.output_size_in_bytes):6.3f} GiB"
        f"   temp {gb(m.temp_size_in_bytes):6.2f} GiB   total {gb(total):6.2f} GiB")


if __name__ == "__main__":
  main()

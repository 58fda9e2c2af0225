"""The separable GRU with its 1x15 convolutions direct or as DFT products, at each scale.

    python benchmarks/gru_conv.py [--frames 5 --height 128 --width 256 --repeats 7]
                                  [--dtype float32|bfloat16]

Times `SKSepConvGRU3D` (random state, input and weights) with `wide_conv="direct"` (XLA's
convolutions) and `wide_conv="dft"` (`layers.dft_correlate_w`, `SAVConfig.gru_conv`) at the
1/16, 1/8 and 1/4 maps of a clip, compiled with the inference options, and prints the largest
difference between the two. The model's refinement loop computes the kernel bins once per
scale (XLA hoists them out of the loop); here each call computes them, so the DFT rows include
that cost. With `--dtype bfloat16` the direct form computes in bfloat16 and the DFT form in
float32 (its coefficients need it), so the difference is bfloat16's rounding.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from timing import add_clip_arguments, timed  # benchmarks/timing.py

from sav_jax import runtime
from sav_jax.model.update import SKSepConvGRU3D


def gru_times(frames, h, w, repeats, seed=0, dtype=jnp.float32):
  """`{form: seconds}` and the max difference of the two forms' outputs at `[frames, h, w]`."""
  rng = np.random.default_rng(seed)
  state = jnp.asarray(np.tanh(rng.standard_normal((1, frames, h, w, 128))), jnp.float32)
  x = jnp.asarray(rng.standard_normal((1, frames, h, w, 256)), jnp.float32)
  # the parameters do not depend on the map's size: initialised on a small one
  params = SKSepConvGRU3D().init(jax.random.key(seed), state[:, :1, :2, :4], x[:, :1, :2, :4])
  options = runtime.inference_compiler_options()
  times, outs = {}, {}
  for form in ("direct", "dft"):
    apply = SKSepConvGRU3D(dtype=dtype, wide_conv=form).apply
    fn = jax.jit(apply).lower(params, state, x).compile(compiler_options=options)
    times[form] = timed(fn, params, state, x, repeats=repeats)
    outs[form] = fn(params, state, x)
  diff = outs["dft"].astype(jnp.float32) - outs["direct"].astype(jnp.float32)
  return times, float(jnp.abs(diff).max())


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  add_clip_arguments(p, iters=None)
  p.add_argument("--repeats", type=int, default=7)
  p.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
  a = p.parse_args()
  if a.height % 64 or a.width % 64:
    p.error("--height and --width must be multiples of 64 (the 1/16 map)")
  print(f"separable GRU, T={a.frames} {a.height}x{a.width}, {a.dtype}, "
        f"{jax.devices()[0].platform}")
  for scale in (16, 8, 4):
    h, w = a.height // scale, a.width // scale
    times, diff = gru_times(a.frames, h, w, a.repeats, dtype=jnp.dtype(a.dtype))
    print(f"  1/{scale:<2d} [{a.frames}, {h}, {w}]  direct {times['direct'] * 1e3:7.1f} ms  "
          f"dft {times['dft'] * 1e3:7.1f} ms  ({times['direct'] / times['dft']:.2f}x)  "
          f"max |diff| {diff:.1e}")


if __name__ == "__main__":
  main()

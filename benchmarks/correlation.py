"""The window correlation (AAPC core): offset band products vs stacked window views.

    python benchmarks/correlation.py [--block 16]

`sav_jax.ops.correlation.window_correlation` computes the `(2wy-1)(2wx-1)` offset
maps as blocked band matrix products and slices the `n*n` pairs out of them. The
direct form, written here for comparison only, stacks the `n` shifted views of
both maps and contracts all pairs in one einsum. Printed per shape and window:
forward and gradient median time, and XLA's temporary memory of the forward.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from sav_jax.ops.correlation import SMALL_WINDOW, WIDE_WINDOW, window_correlation
from sav_jax.ops.pool import pad_replicate

from timing import timed  # benchmarks/timing.py

SHAPES = [(5, 32, 64, 128), (5, 64, 128, 128)]  # 1/4 of T=5 128x256 and 256x512


def stacked_views(left, right, window, groups=4):
  """All pairs from the stacked shifted views (the direct form)."""
  wy, wx = window
  n, h, w, c = left.shape

  def views(x):
    xp = pad_replicate(x, (wy // 2, wy // 2), (wx // 2, wx // 2))
    v = jnp.stack([xp[:, y:y + h, x_:x_ + w] for y in range(wy) for x_ in range(wx)], axis=3)
    return v.reshape(n, h, w, wy * wx, groups, c // groups)

  out = jnp.einsum("nhwagc,nhwbgc->nhwgab", views(left), views(right),
                   preferred_element_type=jnp.float32)
  return out.reshape(n, h, w, -1)


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--block", type=int, default=16)
  p.add_argument("--repeats", type=int, default=5)
  args = p.parse_args()
  rng = np.random.default_rng(0)
  print(f"{'shape':>18} {'window':>6} {'form':>8} {'fwd ms':>8} {'grad ms':>8} {'temp MB':>8}")
  for shape in SHAPES:
    left = jnp.asarray(rng.standard_normal(shape), jnp.float32)
    right = jnp.asarray(rng.standard_normal(shape), jnp.float32)
    for window in (WIDE_WINDOW, SMALL_WINDOW):
      forms = {"stacked": stacked_views,
               "band": lambda a, b, w: window_correlation(a, b, w, block=args.block)}
      outs = {}
      for name, fn in forms.items():
        fwd = jax.jit(lambda a, b, fn=fn: fn(a, b, window))
        grad = jax.jit(jax.grad(lambda a, b, fn=fn: jnp.sum(jnp.sin(fn(a, b, window))),
                                argnums=(0, 1)))
        outs[name] = fwd(left, right)
        temp = fwd.lower(left, right).compile().memory_analysis().temp_size_in_bytes / 1e6
        print(f"{str(shape):>18} {'x'.join(map(str, window)):>6} {name:>8} "
              f"{1e3 * timed(fwd, left, right, repeats=args.repeats):8.1f} "
              f"{1e3 * timed(grad, left, right, repeats=args.repeats):8.1f} {temp:8.1f}", flush=True)
      diff = float(jnp.abs(outs["stacked"] - outs["band"]).max())
      print(f"{'':>18} {'':>6} max |stacked - band| = {diff:.1e}")


if __name__ == "__main__":
  main()

"""Winograd (Toom-Cook) forms of the GRU's 5-tap convolutions vs XLA's direct convolution.

    python benchmarks/winograd_conv.py [--height 32]

A 5-tap correlation computed F(m, 5) at a time needs m + 4 products per m outputs instead of
5 m (F(4, 5): 2.5x fewer multiply-adds), at the price of an input transform (tiles of
m + 4 rows, mixed by a small matrix) and an output transform. The GRU's H and T passes and
its q convolution are such 5-tap convolutions (384 -> 128 channels, ~55% of its work).
Timed here at 1/4 of a T=5 128x256 clip (`[5, 32, 64, 384]`), along H, with the inference
compile options, one form per row (both transforms as fused sums of strided slices, or as
small matrix products over tiles), then the parts of the tiled F(4, 5) form: building the
tiles, the input transform, the batched products and the output transform.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from sav_jax.runtime import inference_compiler_options

from timing import timed  # benchmarks/timing.py

POINTS = (0.0, 1.0, -1.0, 2.0, -2.0, 0.5, -0.5, 3.0, -3.0)  # the finite interpolation points


def toom_cook(m: int, r: int):
  """`(AT [m, a], G [a, r], BT [a, a])` with `a = m + r - 1` for F(m, r): the m outputs of a
  r-tap correlation of a tile `d` of `a` inputs are `AT @ ((G @ g) * (BT @ d))`.

  From the Toom-Cook product of polynomials evaluated at `a - 1` points and infinity: the
  correlation is the transpose of that polynomial product.
  """
  a = m + r - 1
  pts = np.array(POINTS[:a - 1], np.float64)

  def vandermonde(cols):
    v = np.zeros((a, cols))
    v[:-1] = pts[:, None] ** np.arange(cols)
    v[-1, -1] = 1.0  # the point at infinity: the leading coefficient
    return v

  return vandermonde(m).T, vandermonde(r), np.linalg.inv(vandermonde(a)).T


def direct_h(x, w):
  """Zero-padded 'same' correlation of `x [N, H, W, C]` with taps `w [r, C, O]` along H."""
  r = w.shape[0]
  return jax.lax.conv_general_dilated(x, w[:, None], (1, 1), ((r // 2, r // 2), (0, 0)),
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


def tiles_h(x, m: int, r: int):
  """The overlapping tiles `[N, H/m, m + r - 1, W, C]` of the zero-padded `x` along H."""
  n, h, w, c = x.shape
  a, nt, p = m + r - 1, -(-h // m), r // 2
  blocks = -(-a // m)  # each tile is the next `blocks` groups of m rows, cut to a
  xp = jnp.pad(x, ((0, 0), (p, (nt + blocks - 1) * m - h - p), (0, 0), (0, 0)))
  parts = [xp[:, j * m:(nt + j) * m].reshape(n, nt, m, w, c) for j in range(blocks)]
  return jnp.concatenate(parts, axis=2)[:, :, :a]


def winograd_h(x, w, m: int = 4):
  """`direct_h(x, w)` as F(m, r) Winograd: tiles, input transform, one batched product per
  interpolation point, output transform."""
  n, h, width, _ = x.shape
  at, g, bt = (jnp.asarray(t, jnp.float32) for t in toom_cook(m, w.shape[0]))
  u = jnp.einsum("il,ntlwc->intwc", bt, tiles_h(x, m, w.shape[0]))
  v = jnp.einsum("ik,kco->ico", g, w)
  y = jnp.einsum("ki,intwo->ntkwo", at, jnp.einsum("intwc,ico->intwo", u, v))
  return y.reshape(n, -1, width, w.shape[-1])[:, :h]


def winograd_h_sums(x, w, m: int = 4):
  """`winograd_h` with both transforms as sums of strided row slices (elementwise work that
  XLA fuses) instead of small matrix products."""
  r = w.shape[0]
  a = m + r - 1
  at, g, bt = toom_cook(m, r)
  n, h, width, _ = x.shape
  nt, p = -(-h // m), r // 2
  xp = jnp.pad(x, ((0, 0), (p, (nt - 1) * m + a - h - p), (0, 0), (0, 0)))
  rows = [xp[:, l:l + (nt - 1) * m + 1:m] for l in range(a)]  # each [N, H/m, W, C]
  u = jnp.stack([sum(float(bt[i, l]) * rows[l] for l in range(a) if bt[i, l])
                 for i in range(a)])
  prod = jnp.einsum("inhwc,ico->inhwo", u, jnp.einsum("ik,kco->ico", jnp.asarray(g, jnp.float32), w))
  y = jnp.stack([sum(float(at[k, i]) * prod[i] for i in range(a) if at[k, i]) for k in range(m)],
                axis=2)
  return y.reshape(n, nt * m, width, -1)[:, :h]


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--height", type=int, default=32)
  args = p.parse_args()
  opts = inference_compiler_options()
  rng = np.random.default_rng(0)
  x = jnp.asarray(rng.standard_normal((5, args.height, 64, 384)), jnp.float32)
  w = jnp.asarray(0.05 * rng.standard_normal((5, 384, 128)), jnp.float32)
  ref = np.asarray(direct_h(x, w))
  flops = 2 * 5 * args.height * 64 * 5 * 384 * 128

  def run(name, fn, *fargs, check=True):
    compiled = jax.jit(fn).lower(*fargs).compile(opts)
    sec = timed(compiled, *fargs, repeats=5)
    err = f"  max diff {np.abs(np.asarray(compiled(*fargs)) - ref).max():.1e}" if check else ""
    print(f"  {name:34s} {sec * 1e3:7.1f} ms{err}", flush=True)

  print(f"5-tap convolution along H, [5, {args.height}, 64] x 384 -> 128 "
        f"({flops / 1e9:.1f} GFLOP direct); max |output| {np.abs(ref).max():.1f}")
  run("direct (XLA)", direct_h, x, w)
  for m in (2, 4, 6):
    run(f"F({m}, 5), transforms as sums", lambda x, w, m=m: winograd_h_sums(x, w, m), x, w)
    run(f"F({m}, 5), transforms as products", lambda x, w, m=m: winograd_h(x, w, m), x, w)
  print("parts of F(4, 5):")
  at, g, bt = (jnp.asarray(t, jnp.float32) for t in toom_cook(4, 5))
  nt = -(-args.height // 4)
  u = jnp.asarray(rng.standard_normal((8, 5, nt, 64, 384)), jnp.float32)
  v = jnp.einsum("ik,kco->ico", g, w)
  prod = jnp.asarray(rng.standard_normal((8, 5, nt, 64, 128)), jnp.float32)
  run("tiles", lambda x: tiles_h(x, 4, 5), x, check=False)
  run("tiles + input transform", lambda x: jnp.einsum("il,ntlwc->intwc", bt, tiles_h(x, 4, 5)),
      x, check=False)
  run("batched products alone", lambda u, v: jnp.einsum("intwc,ico->intwo", u, v), u, v,
      check=False)
  run("output transform alone", lambda y: jnp.einsum("ki,intwo->ntkwo", at, y), prod, check=False)


if __name__ == "__main__":
  main()

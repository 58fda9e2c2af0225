"""How close the convolutions of the update block run to the machine's peak, and their gradients.

    python benchmarks/conv_throughput.py [--dtype bfloat16]

1. Forward GFLOP/s of the update block's main convolutions at 1/4 of a T=5, 128x256 clip
   (the layers that make up ~90% of the model's work): the ceiling for any exact float32
   implementation on this machine. Beside each: the same convolution as one matrix product
   over gathered patches ("im2col": XLA builds the patch matrix, then one dot), and the
   bare matrix product of that size ([pixels, kh kw in] x [kh kw in, out], patches given):
   the rate of XLA's matrix products on this machine, which the convolutions already reach.
   With `--dtype bfloat16`: the same three forms on bfloat16 operands with float32 results
   (`preferred_element_type`, as the model's bfloat16 mode keeps its sums): where XLA:CPU
   takes the chip's bfloat16 dot products (AVX512_BF16) and where it does not.
2. Gradient of a 4-step `lax.scan` of 3x3 convolutions (the refinement loop's shape):
   XLA's own convolution gradient vs `sav_jax.model.layers.conv2d`'s canonical-form one,
   and the same loop unrolled.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from sav_jax.model.layers import conv2d

from timing import timed  # benchmarks/timing.py

SHAPES = [  # (name, kernel h, kernel w, in, out) at [5, 32, 64] (1/4 of T=5 128x256)
    ("GRU z/r first stage 1x15", 1, 15, 384, 128),
    ("GRU q / second stage 1x5", 1, 5, 384, 128),
    ("flow head, one frame tap 3x3", 3, 3, 128, 256),
    ("motion encoder convc2 3x3", 3, 3, 256, 192),
]


def xla_conv(x, k, padding, result=None):
  """`result`: the sums' dtype (`preferred_element_type`; default the operands')."""
  return jax.lax.conv_general_dilated(x, k, (1, 1), padding,
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                      preferred_element_type=result)


def im2col_conv(x, k, padding, result=None):
  """The convolution as one product of the gathered patches `[N, H, W, kh kw C]`."""
  kh, kw, cin, cout = k.shape
  h, w = x.shape[1:3]
  xp = jnp.pad(x, ((0, 0), *padding, (0, 0)))
  patches = jnp.concatenate([xp[:, i:i + h, j:j + w] for i in range(kh) for j in range(kw)],
                            axis=-1)
  return jnp.matmul(patches, k.reshape(kh * kw * cin, cout), preferred_element_type=result)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                      help="the operands' dtype (bfloat16: with float32 sums)")
  dtype = parser.parse_args(argv).dtype
  rng = np.random.default_rng(0)
  result = jnp.float32 if dtype == "bfloat16" else None
  print(f"forward convolutions, [5, 32, 64] pixels, {dtype}"
        + (" operands, float32 sums" if result else "")
        + ": direct | im2col + one product | the bare product of that size")
  for name, kh, kw, cin, cout in SHAPES:
    x = jnp.asarray(rng.standard_normal((5, 32, 64, cin)), dtype)
    k = jnp.asarray(0.01 * rng.standard_normal((kh, kw, cin, cout)), dtype)
    pad = ((kh // 2, kh // 2), (kw // 2, kw // 2))
    flops = 2 * 5 * 32 * 64 * kh * kw * cin * cout
    a = jnp.asarray(rng.standard_normal((5 * 32 * 64, kh * kw * cin)), dtype)
    row = []
    for fn, args in ((lambda x, k, pad=pad: xla_conv(x, k, pad, result), (x, k)),
                     (lambda x, k, pad=pad: im2col_conv(x, k, pad, result), (x, k)),
                     (lambda a, k: jnp.matmul(a, k.reshape(-1, k.shape[-1]),
                                              preferred_element_type=result), (a, k))):
      sec = timed(jax.jit(fn), *args)
      row.append(f"{sec * 1e3:7.1f} ms {flops / sec / 1e9:6.1f} GFLOP/s")
    print(f"  {name:32s} " + " | ".join(row))

  x = jnp.asarray(rng.standard_normal((6, 8, 16, 128)), jnp.float32)
  k = jnp.asarray(0.03 * rng.standard_normal((3, 3, 128, 128)), jnp.float32)
  pad = ((1, 1), (1, 1))

  def scanned(f):
    def loss(k, x):
      y, _ = jax.lax.scan(lambda c, _: (jnp.tanh(f(c, k, pad)), None), x, length=4)
      return jnp.sum(y ** 2)
    return jax.jit(jax.grad(loss, argnums=(0, 1)))

  def unrolled(k, x):
    for _ in range(4):
      x = jnp.tanh(xla_conv(x, k, pad))
    return jnp.sum(x ** 2)

  print("gradient of 4 scanned 3x3 convs (128 -> 128, [6, 8, 16]):")
  print(f"  lax.scan, XLA's gradient        {timed(scanned(xla_conv), k, x) * 1e3:7.1f} ms")
  print(f"  lax.scan, conv2d's gradient     {timed(scanned(conv2d), k, x) * 1e3:7.1f} ms")
  print(f"  unrolled, XLA's gradient        "
        f"{timed(jax.jit(jax.grad(unrolled, argnums=(0, 1))), k, x) * 1e3:7.1f} ms")


if __name__ == "__main__":
  main()

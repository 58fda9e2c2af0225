"""Would FFT convolutions speed up the GRU's 1x15 convolutions on CPU? (These forms: no; the
model's `layers.dft_correlate_w`, the last row: about 2x, 2.8x with its kernel bins computed
beforehand as in the model.)

    python benchmarks/fft_conv.py [--frames 5 --height 32 --width 64 --repeats 7]

The first stage of the GRU's z and r gates is a 1x15 convolution along the width (384 -> 128
channels each, ~22% of the update block's multiply-adds). Along one axis, a correlation with a
k-tap kernel is a product in the frequency domain: per frequency bin one complex
[channels_in x channels_out] product instead of k real ones per pixel. This script times, at
1/4 resolution of a T=5 128x256 clip:

1. XLA's direct convolutions, z and r separately (what the model runs);
2. the same with z and r fused into one 256-channel convolution;
3. the FFT form: one real FFT of the shared input along the width (zero-padded to `n`), one
   batched real product per bin (real and imaginary parts stacked: 2C x 2O), the inverse FFT,
   and the crop, with its parts timed alone;
4. the same with both DFTs as real matrix products (`dft_correlate`);
5. the model's form (`sav_jax.model.layers.dft_correlate_w`, `SAVConfig.gru_conv="dft"`): the
   DFTs as matrix products too, but a shorter period (n = W + k//2, no wrap-around into the
   kept outputs), three real products per bin (Karatsuba) and the layouts XLA:CPU's batched
   products run fastest in (its kernel bins are computed in each call here; the model's
   refinement loop computes them once per scale, outside the loop);

and prints the largest difference from the direct result.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from timing import timed  # benchmarks/timing.py

from sav_jax.model.layers import dft_correlate_w


def direct(x, kernel):
  """torch-style 'same' correlation along the width: x `[N, H, W, C]`, kernel `[1, k, C, O]`."""
  pad = kernel.shape[1] // 2
  return jax.lax.conv_general_dilated(x, kernel, (1, 1), ((0, 0), (pad, pad)),
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


def fft_size(width: int, taps: int) -> int:
  """The smallest even length >= width + taps - 1 (no circular wrap-around)."""
  n = width + taps - 1
  return n + n % 2


def spectrum_of_kernel(kernel, n):
  """`[n//2+1, 2C, 2O]` real block matrix of the flipped kernel's spectrum, so that
  `[Re X, Im X] @ it = [Re Y, Im Y]` for every frequency bin."""
  spec = jnp.fft.rfft(jnp.flip(kernel[0], 0), n=n, axis=0)  # [F, C, O]
  re, im = spec.real, spec.imag
  return jnp.concatenate([jnp.concatenate([re, im], -1), jnp.concatenate([-im, re], -1)], 1)


def _forward_fft(x, n):
  """`[N, H, W, C]` -> `[N, H, C, F]`: the input's spectrum along the width."""
  return jnp.fft.rfft(jnp.moveaxis(x, 2, -1), n=n, axis=-1)


def _bin_products(stacked, kspec):
  """`[N, H, 2C, F]` x `[F, 2C, 2O]` -> `[F, N, H, 2O]`: one real product per bin."""
  return jnp.einsum("nhcf,fco->fnho", stacked, kspec)


def _to_complex(y, o):
  """`[F, N, H, 2O]` -> complex `[N, H, O, F]`."""
  return jnp.moveaxis(jax.lax.complex(y[..., :o], y[..., o:]), 0, -1)


def _inverse_fft(y, n):
  """Complex `[N, H, O, F]` -> `[N, H, O, n]`."""
  return jnp.fft.irfft(y, n=n, axis=-1)


def fft_correlate(x, kernel):
  """`direct(x, kernel)` computed through real FFTs along the width."""
  w, taps, o = x.shape[2], kernel.shape[1], kernel.shape[3]
  n = fft_size(w, taps)
  spec = _forward_fft(x, n)
  stacked = jnp.concatenate([spec.real, spec.imag], axis=2)   # [N, H, 2C, F]
  y = _inverse_fft(_to_complex(_bin_products(stacked, spectrum_of_kernel(kernel, n)), o), n)
  pad = taps // 2
  return jnp.moveaxis(y[..., pad:pad + w], -1, 2)


def dft_correlate(x, kernel):
  """`direct(x, kernel)` with the DFTs along the width written as real matrix products
  (`[N, H, W, C] @ [W, 2F]` in, `[2F, W]` out): no FFT and no transposes asked for."""
  w, taps, o = x.shape[2], kernel.shape[1], kernel.shape[3]
  n = fft_size(w, taps)
  bins, pad = n // 2 + 1, taps // 2
  ang = 2 * np.pi * np.outer(np.arange(w), np.arange(bins)) / n
  forward = np.concatenate([np.cos(ang), -np.sin(ang)], 1).astype(np.float32)  # [W, 2F]
  weight = np.ones(bins)
  weight[1:bins - 1] = 2  # n is even: bins 0 and n/2 appear once in the real inverse
  ang = 2 * np.pi * np.outer(np.arange(bins), np.arange(w) + pad) / n
  inverse = (np.concatenate([weight[:, None] * np.cos(ang), -weight[:, None] * np.sin(ang)], 0)
             / n).astype(np.float32)  # [2F, W]: the cropped outputs only
  spec = jnp.einsum("nhwc,wg->nhgc", x, forward)
  spec = jnp.concatenate([spec[:, :, :bins], spec[:, :, bins:]], -1)  # [N, H, F, 2C]
  y = jnp.einsum("nhfc,fco->nhfo", spec, spectrum_of_kernel(kernel, n))
  y = jnp.concatenate([y[..., :o], y[..., o:]], 2)  # [N, H, 2F, O]
  return jnp.einsum("nhgo,gw->nhwo", y, inverse)


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--frames", type=int, default=5)
  p.add_argument("--height", type=int, default=32, help="rows at 1/4 resolution")
  p.add_argument("--width", type=int, default=64, help="columns at 1/4 resolution")
  p.add_argument("--repeats", type=int, default=7)
  args = p.parse_args()
  rng = np.random.default_rng(0)
  shape = (args.frames, args.height, args.width)
  x = jnp.asarray(rng.standard_normal((*shape, 384)), jnp.float32)
  kz, kr = (jnp.asarray(rng.standard_normal((1, 15, 384, 128)) / np.sqrt(15 * 384), jnp.float32)
            for _ in range(2))
  both = jnp.concatenate([kz, kr], -1)
  n = fft_size(args.width, 15)
  macs = 2 * np.prod(shape) * 15 * 384 * 128
  print(f"z and r first stage at [T, h, w] = {list(shape)}: {macs / 1e9:.2f} GMAC direct; "
        f"FFT length {n} ({n // 2 + 1} bins)")
  runs = {
      "direct, z and r apart": (jax.jit(lambda x, a, b: (direct(x, a), direct(x, b))), kz, kr),
      "direct, z and r fused": (jax.jit(direct), both, None),
      "FFT, z and r fused": (jax.jit(fft_correlate), both, None),
      "DFT products, fused": (jax.jit(dft_correlate), both, None),
      "model's dft_correlate_w": (jax.jit(lambda x, k: dft_correlate_w(x, k[0])), both, None),
  }
  ref = jnp.concatenate(runs["direct, z and r apart"][0](x, kz, kr), -1)
  for name, (fn, a, b) in runs.items():
    call_args = (x, a) if b is None else (x, a, b)
    sec = timed(fn, *call_args, repeats=args.repeats)
    out = fn(*call_args)
    out = jnp.concatenate(out, -1) if isinstance(out, tuple) else out
    err = float(jnp.abs(out - ref).max())
    print(f"  {name:24s} {sec * 1e3:7.1f} ms   max |diff| {err:.1e} (outputs up to "
          f"{float(jnp.abs(ref).max()):.1f})")
  spec_x = _forward_fft(x, n)
  stacked = jnp.concatenate([spec_x.real, spec_x.imag], axis=2)
  kspec = spectrum_of_kernel(both, n)
  yc = _to_complex(_bin_products(stacked, kspec), both.shape[3])
  parts = {
      "forward FFT of the input": (lambda x: _forward_fft(x, n), (x,)),
      "per-bin products": (_bin_products, (stacked, kspec)),
      "inverse FFT": (lambda y: _inverse_fft(y, n), (yc,)),
  }
  for name, (fn, call_args) in parts.items():
    print(f"    of which {name:24s} {timed(jax.jit(fn), *call_args, repeats=args.repeats) * 1e3:7.1f}"
          " ms")


if __name__ == "__main__":
  main()

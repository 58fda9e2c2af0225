"""Smooth, periodic, coloured procedural textures for the synthetic stereo generator.

Every texture is a square `[S, S, 3]` uint8 RGB image that tiles seamlessly
(period S along both axes), so a renderer may look it up with wrap-around borders on
an unbounded plane. Patterns are band-limited on purpose: the finest detail is set by
`min_cell` (texels), which keeps bilinear resampling of the rendered views close to
the exact point samples (this is what makes the stereo warp check tight).

All randomness comes from the `numpy.random.Generator` passed in, so a texture is a
pure function of the generator state.
"""

from __future__ import annotations

import cv2
import numpy as np

TEXTURE_KINDS = ("noise", "stripes", "checker", "gradient")


def _upsample_periodic(grid: np.ndarray, factor: int) -> np.ndarray:
  """Bicubic upsampling by an integer factor that keeps the grid periodic.

  The grid is wrap-padded by two nodes per side (the bicubic support) and exactly one
  period is cropped, so output texel j maps to node (j + 0.5)/factor - 0.5.
  """
  m = grid.shape[0]
  padded = cv2.copyMakeBorder(grid, 2, 2, 2, 2, cv2.BORDER_WRAP)
  up = cv2.resize(padded, ((m + 4) * factor, (m + 4) * factor), interpolation=cv2.INTER_CUBIC)
  # Contiguous, so that later OpenCV calls do not copy it again.
  return np.ascontiguousarray(up[2 * factor:2 * factor + m * factor,
                                 2 * factor:2 * factor + m * factor])


def value_noise(
    rng: np.random.Generator,
    size: int,
    min_cell: int = 4,
    max_cell: int = 64,
    falloff: float = 0.7,
) -> np.ndarray:
  """Multi-octave periodic value noise.

  Octave k is a grid of random values with `cell_k` texels between nodes; amplitudes
  go as `(cell/max_cell)**falloff` (a pink-ish spectrum: large structures dominate,
  fine detail stays visible). The octaves are accumulated coarse to fine on their own
  grids (upsampling the running sum by 2 at each level) and only the finest grid is
  upsampled to full size, which costs about one full-size resize instead of one per
  octave.

  Args:
    rng: random generator.
    size: side S of the output, a multiple of `min_cell`; octaves coarser than the
      largest power-of-two cell dividing S are dropped.
    min_cell: finest node spacing in texels (power of two, >= 2).
    max_cell: coarsest node spacing in texels (power of two).
    falloff: spectral slope; larger means smoother.

  Returns:
    `[S, S]` float32, zero mean, standard deviation about 1 (the node values have
    exactly 1), periodic with period S.
  """
  cell = max(max_cell, min_cell)  # a power of two: min(max_cell, size) need not be one
  while size % cell and cell > min_cell:  # coarsest octave must tile the period
    cell //= 2
  if size % cell:
    raise ValueError(f"size {size} is not a multiple of min_cell {min_cell}")
  acc = rng.standard_normal((size // cell, size // cell), dtype=np.float32)
  while cell > min_cell:
    cell //= 2
    acc = _upsample_periodic(acc, 2)
    noise = rng.standard_normal(acc.shape, dtype=np.float32)
    noise *= np.float32((cell / max_cell) ** falloff)
    acc += noise
  # Normalise on the node grid (cheap); interpolation keeps the mean and only
  # slightly lowers the standard deviation.
  acc -= acc.mean()
  acc *= 1.0 / max(float(acc.std()), 1e-6)
  return _upsample_periodic(acc, min_cell)


def _plane_wave(rng: np.random.Generator, size: int, min_period: float, max_period: float,
                angle: float | None = None) -> tuple[np.ndarray, np.ndarray]:
  """Separable phase `2*pi*(k . x)/S + phi` of a plane wave with integer wave vector k.

  The wave vector is integer so that the wave tiles with period S; its length is drawn
  so that the spatial period `S/|k|` lies in `[min_period, max_period]` where possible,
  and its direction is `angle` (random when None) up to the integer rounding.

  Returns:
    (phase_x [1, S], phase_y [S, 1]) float32; the phase is their broadcast sum.
  """
  period = rng.uniform(min_period, max_period)
  kmag = max(size / period, 1.0)
  if angle is None:
    angle = rng.uniform(0.0, np.pi)
  kx, ky = round(kmag * np.cos(angle)), round(kmag * np.sin(angle))
  if kx == 0 and ky == 0:
    kx = 1
  coords = np.arange(size, dtype=np.float32) * np.float32(2 * np.pi / size)
  phase_x = (np.float32(kx) * coords + np.float32(rng.uniform(0, 2 * np.pi)))[None, :]
  return phase_x, (np.float32(ky) * coords)[:, None]


def _sin(wave: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
  """sin(px + py) from the separable phase, by the addition theorem (no full-size sin)."""
  px, py = wave
  return np.sin(px) * np.cos(py) + np.cos(px) * np.sin(py)


def _soft_sign(x: np.ndarray, gain: float) -> np.ndarray:
  """A smooth (C1) saturating step: cubic smoothstep of clip(gain * x, -1, 1)."""
  x = np.clip(x * np.float32(gain), -1.0, 1.0)
  return x * (1.5 - 0.5 * x * x)


def _pattern(rng: np.random.Generator, kind: str, size: int, min_cell: int) -> np.ndarray:
  """A scalar `[S, S]` pattern field with values roughly in [-1, 1]."""
  if kind == "noise":
    return value_noise(rng, size, min_cell, falloff=rng.uniform(0.4, 1.0))
  if kind == "stripes":
    # Stripes bent by a smooth noise field; the period stays >= 4 min_cell texels.
    warp = value_noise(rng, size, max(min_cell, 16), falloff=1.0)
    px, py = _plane_wave(rng, size, 4 * min_cell, 12 * min_cell)
    warp *= np.float32(rng.uniform(0.5, 2.0))
    warp += px
    warp += py
    return np.sin(warp)
  if kind == "checker":
    # A soft checkerboard: the product of two crossing waves through a smooth step.
    angle = rng.uniform(0.0, np.pi)
    a = _sin(_plane_wave(rng, size, 6 * min_cell, 16 * min_cell, angle))
    a *= _sin(_plane_wave(rng, size, 6 * min_cell, 16 * min_cell, angle + np.pi / 2))
    return _soft_sign(a, 2.0)
  if kind == "gradient":
    # One period across the tile: a large-scale colour ramp that still tiles.
    return _sin(_plane_wave(rng, size, size, size))
  raise ValueError(f"unknown texture kind {kind!r}; expected one of {TEXTURE_KINDS}")


def make_texture(
    rng: np.random.Generator,
    size: int,
    kinds: tuple[str, ...] = TEXTURE_KINDS,
    min_cell: int = 4,
    contrast: float = 1.0,
) -> np.ndarray:
  """A random coloured texture: one pattern plus coloured detail noise.

  The pattern (one of `kinds`) gets a random colour direction; a second, independent
  fine-scale noise with another colour is always added, so that every texture has
  detail down to `min_cell` texels (flat regions would make stereo matching
  ill-posed, which is not what a default training set should contain).

  Args:
    rng: random generator.
    size: side S (a multiple of 64 keeps every octave periodic).
    kinds: pattern kinds to choose from (see `TEXTURE_KINDS`).
    min_cell: finest detail in texels.
    contrast: multiplies the colour amplitudes.

  Returns:
    `[S, S, 3]` uint8 RGB, periodic with period S. (8-bit storage makes the texture
    lookups fast; the quantised texture is simply the scene's texture, seen
    identically by both views.)
  """
  kind = kinds[rng.integers(len(kinds))]
  pattern = _pattern(rng, kind, size, min_cell)
  # Detail spans only the three finest octaves (min_cell .. 4 min_cell), which is the
  # band that makes local stereo matching well-posed.
  detail = value_noise(rng, size, min_cell, 4 * min_cell, falloff=rng.uniform(0.0, 0.5))
  base = rng.uniform(70.0, 185.0, 3)
  # Colour directions: random RGB vectors; the pattern gets the larger amplitude.
  c_pattern = rng.normal(0.0, 1.0, 3) * (contrast * rng.uniform(25.0, 45.0) / np.sqrt(3))
  c_pattern += np.sign(rng.normal()) * contrast * rng.uniform(15.0, 35.0)  # luminance part
  c_detail = rng.normal(0.0, 1.0, 3) * (contrast * rng.uniform(8.0, 18.0) / np.sqrt(3))
  c_detail += contrast * rng.uniform(12.0, 28.0)
  # addWeighted computes, rounds and saturates to uint8 in one pass per channel.
  channels = [
      cv2.addWeighted(pattern, float(c_pattern[i]), detail, float(c_detail[i]), float(base[i]),
                      dtype=cv2.CV_8U) for i in range(3)
  ]
  return cv2.merge(channels)

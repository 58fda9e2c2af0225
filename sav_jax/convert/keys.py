"""Generic torch <-> Flax naming and layout rules shared by all converters.

A torch key `a.b.3.c.weight` is the Flax path `('a', 'b_3', 'c', 'kernel')`: a list
index is joined to the name before it with an underscore. Leaves: `weight` of
ndim >= 2 -> `kernel` (Linear transposed, ConvNd `O, I, *k -> *k, I, O`), 1-D
`weight` -> `scale` (norms), everything else keeps its name.
"""

from __future__ import annotations

import re

import numpy as np


def torch_to_path(key: str, ndim: int) -> tuple[str, ...]:
  """`a.b.3.c.weight` -> `('a', 'b_3', 'c', 'kernel')` (`scale` for 1-D weights)."""
  parts = key.split(".")
  path: list[str] = []
  for p in parts[:-1]:
    if p.isdigit() and path:
      path[-1] = f"{path[-1]}_{p}"
    else:
      path.append(p)
  leaf = parts[-1]
  if leaf == "weight":
    leaf = "kernel" if ndim >= 2 else "scale"
  return (*path, leaf)


def path_to_torch(path: tuple[str, ...]) -> str:
  """Inverse of `torch_to_path`."""
  parts = [re.sub(r"_(\d+)$", r".\1", p) for p in path[:-1]]
  leaf = {"kernel": "weight", "scale": "weight"}.get(path[-1], path[-1])
  return ".".join([*parts, leaf])


def torch_to_flax_array(x: np.ndarray, leaf: str = "kernel") -> np.ndarray:
  """Layout of a torch tensor in Flax: only `kernel` leaves change.

  Linear `(out, in) -> (in, out)`; ConvNd `(O, I, *k) -> (*k, I, O)`. The same
  permutation serves torch's ConvTranspose2d `(I, O, kh, kw)` for a Flax
  `nn.ConvTranspose(transpose_kernel=True)`.
  """
  x = np.asarray(x)
  if leaf != "kernel" or x.ndim < 2:
    return x
  if x.ndim == 2:
    return x.T
  return np.transpose(x, (*range(2, x.ndim), 1, 0))


def flax_to_torch_array(x: np.ndarray, leaf: str = "kernel") -> np.ndarray:
  """Inverse of `torch_to_flax_array` (C-contiguous result)."""
  x = np.asarray(x)
  if leaf == "kernel" and x.ndim == 2:
    x = x.T
  elif leaf == "kernel" and x.ndim > 2:
    n = x.ndim
    x = np.transpose(x, (n - 1, n - 2, *range(n - 2)))
  return np.asarray(x, order="C")


def converted(key: str, value, leaf: str, shape: tuple[int, ...], model: str = "the model"):
  """`(float32 Flax array, None)` for the torch tensor `key`, or `(None, problem)`.

  The problem names the key: a shape that is not the model's (given in torch's layout),
  or a `value_problem`.
  """
  value = np.asarray(value)
  arr = torch_to_flax_array(value, leaf)
  if arr.shape != tuple(shape):
    return None, (f"key {key!r}: shape {value.shape} does not match {model} (expects "
                  f"{flax_to_torch_array(np.empty(shape), leaf).shape})")
  problem = value_problem(key, value)
  return (None, problem) if problem else (arr.astype(np.float32), None)


def value_problem(key: str, x: np.ndarray) -> str | None:
  """Why `x` cannot be the model parameter `key` (not floating point, or NaN/inf), else None.

  A float16, bfloat16 or float64 tensor is fine (converted to float32); an integer, bool
  or complex one is not a weight, and a NaN or inf (e.g. from a diverged training run)
  would silently turn every prediction into NaN.
  """
  x = np.asarray(x)
  if not (np.issubdtype(x.dtype, np.floating) or x.dtype.name == "bfloat16"):
    return f"key {key!r}: dtype {x.dtype}; expected a floating-point tensor"
  bad = x.size - int(np.count_nonzero(np.isfinite(x)))
  if bad:
    return f"key {key!r}: {bad} of {x.size} values are NaN or inf"
  return None

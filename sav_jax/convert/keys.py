"""Generic torch <-> Flax naming and layout rules shared by all converters.

A torch key `a.b.3.c.weight` is the Flax path `('a', 'b_3', 'c', 'kernel')`: a list
index is joined to the name before it with an underscore. Leaves: `weight` of
ndim >= 2 -> `kernel` (Linear transposed, ConvNd `O, I, *k -> *k, I, O`), 1-D
`weight` -> `scale` (norms), everything else keeps its name.
"""

from __future__ import annotations

import collections
from collections.abc import Mapping
import copy
import re

import numpy as np

from sav_jax._checks import plural, widened


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


def unused_array(value) -> np.ndarray:
  """A tensor kept beside the params (`torch_unused`): floating point as float32, like the
  params, so that an export from a float16 file is float32 throughout."""
  a = widened(np.asarray(value))
  return a.astype(np.float32) if np.issubdtype(a.dtype, np.floating) else a


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
  if problem:
    return None, problem
  wide = arr.dtype.itemsize > 4  # float64: values beyond float32's range become inf
  with np.errstate(over="ignore"):
    arr = arr.astype(np.float32)
  problem = value_problem(key, arr) if wide else None  # (narrower types stay finite)
  if problem:
    return None, f"{problem} once converted to float32 (values beyond its range)"
  return arr, None


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


class KeyProblems:
  """What keeps a state dict from being a model's, reported at once as one ValueError.

  Every problem is collected, but the report lists at most `limit` of each kind (other
  problems such as shapes and values first, then unexpected, then missing keys) and counts
  the rest: a checkpoint of another variant has hundreds of mismatches, and a report of
  hundreds of lines hides the first, telling one. When none of the state dict's keys is the
  model's, the report says so first.
  """

  def __init__(self, prefix: str = "", limit: int = 10):
    self.prefix, self.limit = prefix, limit
    self.missing: list[str] = []
    self.unexpected: list[str] = []
    self.other: list[str] = []
    self.notes: list[str] = []  # what the problems suggest, said before them

  def __len__(self) -> int:
    return len(self.missing) + len(self.unexpected) + len(self.other)

  def add_missing(self, key: str) -> None:
    self.missing.append(f"missing key {self.prefix + key!r}")

  def add_unexpected(self, key: str) -> None:
    self.unexpected.append(f"unexpected key {self.prefix + key!r}")

  def convert(self, key: str, value, path: tuple[str, ...] | None, shape: tuple[int, ...],
              model: str = "the model") -> np.ndarray | None:
    """`converted` for the torch tensor `key` of the model's Flax `path` (None: not a key of
    the model) and `shape`: the float32 Flax array, or None with the problem collected."""
    if path is None:
      self.add_unexpected(key)
      return None
    arr, problem = converted(self.prefix + key, value, path[-1], tuple(shape), model)
    self.add(problem)
    return arr

  def add_absent(self, keys, state_dict) -> None:
    """Each of `keys` that `state_dict` lacks is a missing key."""
    for key in keys:
      if key not in state_dict:
        self.add_missing(key)

  def add(self, problem: str | None) -> None:
    """A problem of one key (a shape, a value), written with the key's full name."""
    if problem:
      self.other.append(problem)

  def unused(self, tensors: Mapping, shapes: Mapping, model: str) -> dict[str, np.ndarray]:
    """`tensors` the model keeps beside its params (`unused_array`, for an exact export),
    each checked as a parameter is: the `shapes` it must have, floating point, finite (a
    bad one exported would fail the official `load_state_dict`)."""
    out = {}
    for key, value in tensors.items():
      a = unused_array(value)
      name = self.prefix + key
      if a.shape != tuple(shapes[key]):
        self.add(f"key {name!r}: shape {a.shape} does not match {model} (expects "
                 f"{tuple(shapes[key])})")
      else:
        self.add(value_problem(name, a))
      out[key] = a
    return out

  def scoped(self, prefix: str) -> KeyProblems:
    """A view of this collector that names each key with `prefix` before it (the part of a
    larger file that a sub-converter reads without its prefix); it collects into the same
    lists."""
    view = copy.copy(self)  # shallow: the lists are shared
    view.prefix = self.prefix + prefix
    return view

  def raise_if_any(self, what: str, keys_given: int) -> None:
    """Raises `ValueError("<what>: N problem(s) ...")` unless nothing was collected.

    Args:
      what: the header, e.g. "state dict does not match RAFT".
      keys_given: how many keys the state dict has (all unexpected: a note says so).
    """
    if not len(self):
      return
    kinds = [(self.other, "key", "of a wrong shape or value"),
             (self.unexpected, "unexpected key", ""), (self.missing, "missing key", "")]
    counts = ", ".join(_count(len(items), noun, tail) for items, noun, tail in kinds if items)
    lines = [f"{what}: {len(self)} problem(s)"
             + (f" ({counts})" if sum(bool(items) for items, _, _ in kinds) > 1 else "") + ":"]
    if keys_given and len(self.unexpected) == keys_given:
      lines.append(f"none of the state dict's {_count(keys_given, 'key', '')} is one of the "
                   "model's: is it a checkpoint of another model?")
    lines += self.notes
    for items, noun, tail in kinds:
      lines += items[:self.limit]
      rest = items[self.limit:]
      if rest:
        lines.append(f"... and {_count(len(rest), 'more ' + noun, tail)} (by module: "
                     + ", ".join(f"{m} {n}" for m, n in _by_module(rest)) + ")")
    raise ValueError("\n  ".join(lines))


def one_line(error: Exception) -> str:
  """`raise_if_any`'s report on one line, as the commands print it: its header (the number
  of problems) and, in brackets, the first problem or note."""
  lines = [l.strip() for l in str(error).splitlines() if l.strip()]
  return lines[0] + (f" (first: {lines[1]})" if len(lines) > 1 else "")


def _by_module(items: list[str]) -> list[tuple[str, int]]:
  """`[(module, count)]` of the keys quoted in `items`, most first, each module named by as
  many leading names as keep the groups as few as by the first name alone (`update_block.gru`
  when only it is concerned, not `update_block`); never by a key's last name."""
  keys = [re.search(r"'([^']*)'", item).group(1).split(".") for item in items]

  def grouped(depth):
    return collections.Counter(".".join(k[:max(1, min(depth, len(k) - 1))]) for k in keys)

  groups = grouped(1)
  for depth in range(2, max(map(len, keys))):
    finer = grouped(depth)
    if len(finer) > len(groups):
      break
    groups = finer
  return groups.most_common()


def _count(n: int, noun: str, tail: str) -> str:
  """`3 missing keys`, `1 key of a wrong shape`: the noun's last word takes the plural."""
  return plural(n, noun) + (f" {tail}" if tail else "")

"""Helpers for parity tests: fixture layouts -> channels last, tolerances."""

import numpy as np
from flax import traverse_util

from sav_jax.convert.keys import torch_to_flax_array, torch_to_path


def nchw_to_nhwc(x):
  """`[..., C, H, W]` -> `[..., H, W, C]`."""
  x = np.asarray(x)
  return np.moveaxis(x, -3, -1)


def subtree(sd, prefix):
  """Flax params of the submodule under `prefix` (official names, no VDA)."""
  flat = {}
  for k, v in sd.items():
    if k.startswith(prefix):
      path = torch_to_path(k[len(prefix):], np.ndim(v))
      flat[path] = torch_to_flax_array(v, path[-1])
  return traverse_util.unflatten_dict(flat)


def feature_close(actual, expected, rel=1e-4, abs_=1e-5):
  """The fixture README's feature criterion: |a-b| <= rel*max|b| + abs."""
  actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
  assert actual.shape == expected.shape, (actual.shape, expected.shape)
  err = np.abs(actual - expected).max()
  bound = rel * np.abs(expected).max() + abs_
  assert err <= bound, f"max abs error {err:.3g} > {bound:.3g} (max|ref| {np.abs(expected).max():.3g})"
  return err

"""Argument checks shared by the library's modules."""

from __future__ import annotations

import numbers
import os
import sys


def is_int(x) -> bool:
  """A Python or numpy integer, not a bool (which would pass as 0 or 1)."""
  return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def caller_stacklevel() -> int:
  """`warnings.warn`'s stacklevel that names the first caller outside sav_jax.

  Called by the function that warns; a fixed stacklevel named a line inside the package
  when the warning came through another of its functions (e.g. `predict_video`).
  """
  package = os.path.dirname(os.path.abspath(__file__)) + os.sep
  frame, level = sys._getframe(1), 1  # pylint: disable=protected-access
  while frame is not None and frame.f_code.co_filename.startswith(package):
    frame, level = frame.f_back, level + 1
  return level

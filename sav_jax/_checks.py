"""Argument checks shared by the library's modules."""

from __future__ import annotations

import numbers


def is_int(x) -> bool:
  """A Python or numpy integer, not a bool (which would pass as 0 or 1)."""
  return isinstance(x, numbers.Integral) and not isinstance(x, bool)

"""A package's submodules as attributes on first use.

`import sav_jax` imports no submodule (and not JAX), yet `sav_jax.model.init.init_variables`,
`sav_jax.tools.video_io.FrameSource` and the like work as written: a package's
`__getattr__` imports the submodule it is asked for.
"""

from __future__ import annotations

import importlib
import importlib.util


def submodule_getattr(package: str):
  """A module `__getattr__` for `package` that imports `package.<name>` when it exists."""

  def __getattr__(name: str):
    # (a dotted or otherwise non-identifier name is no submodule: find_spec would import
    # its first part and fail, where hasattr() must get an AttributeError)
    if (name.isidentifier() and not name.startswith("__")
        and importlib.util.find_spec(f"{package}.{name}") is not None):
      return importlib.import_module(f"{package}.{name}")
    raise AttributeError(f"module {package!r} has no attribute {name!r}")

  return __getattr__

"""Torch-compatible array primitives used by the model (pure functions)."""

from sav_jax._lazy import submodule_getattr

__getattr__ = submodule_getattr(__name__)  # its other modules, on first use

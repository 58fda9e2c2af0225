"""Flax linen modules of Stereo Any Video."""

from sav_jax._lazy import submodule_getattr

__getattr__ = submodule_getattr(__name__)  # its other modules, on first use

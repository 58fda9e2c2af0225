"""sav-jax: Stereo Any Video (ICCV 2025) in JAX/Flax.

    import sav_jax
    cfg = sav_jax.SAVConfig()
    model = sav_jax.StereoAnyVideo(cfg)
    variables = sav_jax.convert.params_from_state_dict(sav_jax.convert.load_state_dict(path), cfg)
    out = model.apply(variables, left, right, iters=20)   # out.disparities [P, B, T, H, W]

Every name here loads on first use, so `import sav_jax` (and the CLI's `--help`, a training
config file that imports `sav_jax.data.augment`) does not import JAX until it is needed.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from sav_jax._lazy import submodule_getattr

if TYPE_CHECKING:  # for type checkers and IDEs; at run time `__getattr__` loads these
  from sav_jax import convert, data, inference, metrics, model, runtime, viz
  from sav_jax.config import SAVConfig
  from sav_jax.model.stereo_any_video import SAVOutput, StereoAnyVideo

__version__ = "0.1.0"
__all__ = ["SAVConfig", "SAVOutput", "StereoAnyVideo", "convert", "inference", "data",
           "metrics", "model", "runtime", "viz"]
_NAMES = {"SAVConfig": "sav_jax.config", "SAVOutput": "sav_jax.model.stereo_any_video",
          "StereoAnyVideo": "sav_jax.model.stereo_any_video"}


_submodule = submodule_getattr(__name__)


def __getattr__(name):
  """`sav_jax.StereoAnyVideo`, `sav_jax.metrics`, `sav_jax.tools.video_io`, ...: each is
  imported on first use."""
  if name in _NAMES:
    value = getattr(importlib.import_module(_NAMES[name]), name)
    globals()[name] = value  # later lookups skip this function
    return value
  return _submodule(name)


def __dir__():
  return sorted(set(globals()) | set(__all__))

"""sav-jax: Stereo Any Video (ICCV 2025) in JAX/Flax.

    import sav_jax
    cfg = sav_jax.SAVConfig()
    model = sav_jax.StereoAnyVideo(cfg)
    variables = sav_jax.convert.params_from_state_dict(sav_jax.convert.load_state_dict(path), cfg)
    out = model.apply(variables, left, right, iters=20)   # out.disparities [P, B, T, H, W]
"""

from sav_jax import convert, inference
from sav_jax.config import SAVConfig
from sav_jax.model.stereo_any_video import SAVOutput, StereoAnyVideo

__version__ = "0.1.0"
__all__ = ["SAVConfig", "SAVOutput", "StereoAnyVideo", "convert", "inference", "data",
           "metrics", "model", "runtime", "viz"]
_LAZY = ("data", "metrics", "model", "runtime", "viz")


def __getattr__(name):
  """`sav_jax.metrics`, `sav_jax.viz`, ... without importing each first (loaded on use)."""
  if name in _LAZY:
    import importlib  # pylint: disable=import-outside-toplevel
    return importlib.import_module(f"sav_jax.{name}")
  raise AttributeError(f"module 'sav_jax' has no attribute {name!r}")

"""Datasets, the synthetic stereo-video generator, augmentation and grain pipelines."""

from sav_jax.data import frame_io
from sav_jax.data.augment import AugmentConfig, augment_clip
from sav_jax.data.base import DepthSequence, StereoSequence
from sav_jax.data import registry
from sav_jax.data.registry import (EVAL_FRAMES, TrainingClip, get_sequences,
                                   get_training_clips)
from sav_jax.data.synthetic import SyntheticConfig, SyntheticStereoVideo, generate_clip

__all__ = [
    "DATASETS",
    "EVAL_FRAMES",
    "AugmentConfig",
    "DepthSequence",
    "StereoSequence",
    "SyntheticConfig",
    "SyntheticStereoVideo",
    "TrainingClip",
    "augment_clip",
    "frame_io",
    "generate_clip",
    "get_sequences",
    "get_training_clips",
]

from sav_jax._lazy import submodule_getattr

_submodule = submodule_getattr(__name__)  # its other modules, on first use


def __getattr__(name: str):
  # `DATASETS` is read from the registry on every use: `register_dataset` replaces the
  # registry's tuple, so a copy bound here at import would miss the datasets added later.
  if name == "DATASETS":
    return registry.DATASETS
  return _submodule(name)


def __dir__():
  return sorted({*globals(), "DATASETS"})

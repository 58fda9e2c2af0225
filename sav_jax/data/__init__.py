"""Datasets, the synthetic stereo-video generator, augmentation and grain pipelines."""

"""Flax linen modules of Stereo Any Video."""

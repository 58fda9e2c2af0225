"""Torch-compatible array primitives used by the model (pure functions)."""

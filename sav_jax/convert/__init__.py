"""Checkpoints: reading PyTorch files safely, key mapping, orbax, export."""

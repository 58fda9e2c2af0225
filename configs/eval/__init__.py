"""Evaluation configs, one per benchmark (`python -m eval --config configs/eval/<name>.py`)."""

"""Tests of the training program (heavy ones run the model in subprocesses)."""

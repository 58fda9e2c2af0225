"""The sav-jax training program: `python -m train --config configs/<name>.py --workdir DIR`.

Modules: `loss` (official loss and metrics), `optim` (AdamW + OneCycle, frozen prior),
`state` (train state, mesh, shardings), `step` (the jitted update), `input` (grain
pipelines from a config), `evaluation` (held-out validation), `checkpoint` (orbax),
`logging_utils` (JSONL, TensorBoard, progress bar), `loop` (the program).
"""

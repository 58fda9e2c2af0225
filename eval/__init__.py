"""The evaluation program: the official SAV protocol on each benchmark, with reports.

    python -m eval --config configs/eval/sintel_final.py --checkpoint ckpt \\
        --data-root data/datasets [--out outputs/eval/sintel_final] [--baseline sgbm] \\
        [--config.iters=20]

Modules: `config` (config files and `--config.x=y` overrides), `data` (sequences per
dataset, the synthetic set), `runner` (inference and metrics per sequence), `report`
(Markdown / JSON / CSV tables) and `plots` (per-frame curves, disparity strips).
"""

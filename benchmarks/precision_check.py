"""Distance of the model's output from the official one, per compute mode, on this backend.

    python benchmarks/precision_check.py                       # fixtures at ../shared/fixtures
    SAV_FIXTURES=/path/to/fixtures python benchmarks/precision_check.py --json out.json

Runs the fixture clip (`golden_small`: 1x3x64x128, iters=4, make_weights.py seed 0) through
the inference forward in float32 at the matmul precisions "highest" and "default" (on GPUs
the default lets XLA use TF32 for float32 products and convolutions) and in bfloat16 (on a
GPU also with `SAVConfig.vit_attention="cudnn"`), and
prints the mean and max absolute difference from the official float32 test-mode output.
The parity tests require <= 1e-4 px max in float32 at "highest" and <= 0.05 px mean in
bfloat16; this script measures, it asserts nothing.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402  pylint: disable=wrong-import-position
import jax.numpy as jnp  # noqa: E402  pylint: disable=wrong-import-position
import numpy as np  # noqa: E402  pylint: disable=wrong-import-position

import sav_jax  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.config import resolve_gru_conv  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools import UsageError  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools.bench import json_output_problem, write_json_result  # noqa: E402  pylint: disable=wrong-import-position
from timing import fixtures_folder, make_weights_module  # noqa: E402  benchmarks/timing.py

MODES = (("float32", "highest", "blocked"), ("float32", "default", "blocked"),
         ("bfloat16", "default", "blocked"))
GPU_MODES = (("bfloat16", "default", "cudnn"),)  # the fused ViT attention, CUDA only


def load_fixture(fixtures: pathlib.Path):
  """`(state_dict, golden)`: make_weights.py's seed-0 weights and golden_small.npz."""
  for name in ("make_weights.py", "sav_manifest.json", "golden_small.npz"):
    if not (fixtures / name).is_file():
      raise SystemExit(f"precision_check: {fixtures / name} not found (set SAV_FIXTURES "
                       "or --fixtures to the oracle fixtures folder)")
  mod = make_weights_module(fixtures, "precision_check")
  state_dict = mod.make_state_dict(str(fixtures / "sav_manifest.json"), 0)
  return state_dict, dict(np.load(fixtures / "golden_small.npz"))


def measure(fixtures: pathlib.Path, iters: int = 4) -> list[dict]:
  state_dict, golden = load_fixture(fixtures)
  nhwc = lambda x: jnp.asarray(np.moveaxis(np.asarray(x), -3, -1))  # noqa: E731
  left, right = nhwc(golden["input_left"]), nhwc(golden["input_right"])
  ref = np.transpose(golden["test_mode_output"][:, :, 0], (1, 0, 2, 3))[None]
  # Parameters are float32 in every compute mode: one conversion serves all.
  variables = sav_jax.convert.params_from_state_dict(state_dict, sav_jax.SAVConfig())
  rows = []
  default_gru = resolve_gru_conv("auto", jnp.float32)
  other_gru = "direct" if default_gru == "dft" else "dft"
  modes = ([(*m, default_gru if m[0] == "float32" else "direct") for m in MODES]
           + [("float32", "highest", "blocked", other_gru)]
           + [(*m, "direct") for m in (GPU_MODES if jax.default_backend() == "gpu" else ())])
  for dtype, precision, attention, gru_conv in modes:
    cfg = sav_jax.SAVConfig(dtype=dtype, vit_attention=attention, gru_conv=gru_conv)
    model = sav_jax.StereoAnyVideo(cfg)
    fwd = jax.jit(lambda v, l, r, m=model: m.apply(v, l, r, iters=iters,
                                                     final_only=True).disparities)
    with jax.default_matmul_precision(precision):
      got = np.asarray(fwd(variables, left, right), np.float32)
    diff = np.abs(got - ref)
    rows.append(dict(dtype=dtype, precision=precision, vit_attention=attention, gru_conv=gru_conv,
                     mean_px=float(diff.mean()),
                     max_px=float(diff.max())))
  return rows


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--fixtures", default=str(fixtures_folder()), help="the oracle fixtures folder")
  p.add_argument("--json", help="write the rows to this JSON file (a new file, or --overwrite)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
  a = p.parse_args(argv)
  problem = json_output_problem(a.json, a.overwrite)  # (--overwrite alone: no --json named)
  if problem:  # before the long run
    p.error(problem)
  rows = measure(pathlib.Path(a.fixtures))
  device = jax.devices()[0]
  print(f"device {device.platform}:{device.device_kind} (jax {jax.__version__}); "
        "difference from the official float32 output, fixture clip 1x3x64x128 iters=4")
  print(f"{'dtype':<10}{'precision':<10}{'ViT attn':<10}{'GRU 1x15':<9}{'mean (px)':>12}"
        f"{'max (px)':>12}")
  for r in rows:
    print(f"{r['dtype']:<10}{r['precision']:<10}{r['vit_attention']:<10}{r['gru_conv']:<9}"
          f"{r['mean_px']:>12.2e}{r['max_px']:>12.2e}")
  if a.json:
    try:
      write_json_result(a.json, dict(device=f"{device.platform}:{device.device_kind}",
                                     jax=jax.__version__, rows=rows), a.overwrite)
    except UsageError as e:  # (a file of that name made during the run: kept)
      p.error(str(e))
  return 0


if __name__ == "__main__":
  sys.exit(main())

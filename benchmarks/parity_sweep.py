"""Forward parity with the official PyTorch model at shapes the fixtures do not cover.

    python benchmarks/parity_sweep.py --repo CHECKOUT --torch-interpreter TORCH_ENV/bin/python

The parity tests compare one fixture clip; this script runs both models on the fixtures'
deterministic weights (`make_weights.py`, seed 0, from `--fixtures`, default
`../shared/fixtures` or `SAV_FIXTURES`) at other clip lengths and sizes (odd sizes that
need padding, uneven padding, H > W, one frame, batches of clips) and prints the largest
and mean absolute differences of the final disparities, in px. The official side runs in a
separate Python with torch (`--torch-interpreter`, as `gradient_check.py`), importing the
official code from `--repo` (nothing of it is copied here), and does per window what its
evaluation's `forward_batch_test` does: `InputPadder(divis_by=32)` (replicate padding),
`forward(test_mode=True)`, unpad; the cases marked `fbt` also run `forward_batch_test`
itself (its `.cuda()` calls made no-ops) against `inference.forward_batch_test_official`.
sav-jax runs here in float32 at "highest" precision: `predict_video` (it pads itself, and
returns |disparity| as the evaluation does) and `run_window` (the signed padded output);
the `direct` cases call the model on unpadded batches of clips.

Each case is `name=KIND:BxTxHxW:FRAMES` in `--cases` (KIND `window`, `fbt` or `direct`;
FRAMES `noise` (uniform 0..255, right view 3 px off) or `smooth` (low-pass textures
drifting over time, right view 5 px off)); the default list takes ~3 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from gradient_check import official_outputs, weights  # noqa: E402  pylint: disable=wrong-import-position

DEFAULT_CASES = ("odd=window:1x3x72x136:smooth,uneven=window:1x3x71x135:smooth,"
                 "tall=window:1x2x130x70:smooth,single=window:1x1x64x128:noise,"
                 "stitched=fbt:1x7x40x72:smooth,batch=direct:2x2x64x96:noise")


def parse_cases(text: str) -> list[tuple[str, str, tuple[int, ...], str]]:
  """`[(name, kind, (B, T, H, W), frames)]` of a `--cases` string."""
  cases = []
  for item in text.split(","):
    try:
      name, spec = item.split("=")
      kind, dims, frames = spec.split(":")
      shape = tuple(int(d) for d in dims.split("x"))
    except ValueError:
      raise SystemExit(f"--cases: {item!r} is not NAME=KIND:BxTxHxW:FRAMES") from None
    if (kind not in ("window", "fbt", "direct") or frames not in ("noise", "smooth")
        or len(shape) != 4 or min(shape) < 1 or (kind != "direct" and shape[0] != 1)):
      raise SystemExit(f"--cases: {item!r}: KIND window/fbt/direct (B=1 but for direct), "
                       "FRAMES noise/smooth, four sizes >= 1")
    cases.append((name, kind, shape, frames))
  return cases


def clip(t: int, h: int, w: int, kind: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
  """`[T, H, W, 3]` float32 left and right views, the right one `left(x + shift)`."""
  rng = np.random.default_rng(seed)
  shift = 3 if kind == "noise" else 5
  if kind == "noise":
    wide = rng.uniform(0, 255, (t, h, w + shift, 3))
  else:  # textures at three scales and a ramp, drifting 2 px per frame
    base = np.zeros((h, w + shift + 2 * t, 3))
    ky = np.fft.fftfreq(base.shape[0])[:, None]
    kx = np.fft.fftfreq(base.shape[1])[None]
    for s in (3.0, 8.0, 20.0):
      f = np.fft.fft2(rng.standard_normal(base.shape), axes=(0, 1))
      f *= np.exp(-(ky ** 2 + kx ** 2) * (2 * np.pi * s) ** 2 / 2)[..., None]
      b = np.real(np.fft.ifft2(f, axes=(0, 1)))
      base += b / (b.std() + 1e-9)
    base += np.linspace(-1, 1, base.shape[1])[None, :, None]
    base = (base - base.min()) / (base.max() - base.min()) * 255
    wide = np.stack([base[:, 2 * i:2 * i + w + shift] for i in range(t)])
  wide = wide.astype(np.float32)
  return np.ascontiguousarray(wide[:, :, :w]), np.ascontiguousarray(wide[:, :, shift:])


def batch(shape, kind) -> tuple[np.ndarray, np.ndarray]:
  """`[B, T, H, W, 3]` views, clip b drawn with seed b."""
  views = [clip(*shape[1:], kind, seed=b) for b in range(shape[0])]
  return np.stack([v[0] for v in views]), np.stack([v[1] for v in views])


def torch_side(a) -> None:
  import torch  # pylint: disable=import-outside-toplevel
  from official_torch import build_official_model  # pylint: disable=import-outside-toplevel
  model = build_official_model(pathlib.Path(a.repo).resolve())
  model.load_state_dict({k: torch.from_numpy(np.asarray(v)) for k, v in weights(a).items()})
  model.eval()
  from stereoanyvideo.models.core.utils.utils import InputPadder  # pylint: disable=import-outside-toplevel
  chw = lambda x: torch.from_numpy(np.ascontiguousarray(np.moveaxis(x, -1, -3)))  # noqa: E731
  out = {}
  with torch.inference_mode():
    for name, kind, shape, frames in parse_cases(a.cases):
      if kind == "direct":  # [T, B, 1, H, W] -> [B, T, H, W]
        d = model(*(chw(x) for x in batch(shape, frames)), iters=a.iters, test_mode=True)
        out[f"{name}/direct"] = d[:, :, 0].numpy().transpose(1, 0, 2, 3)
        continue
      left, right = (chw(x) for x in clip(*shape[1:], frames))
      padder = InputPadder(left.shape, divis_by=32)
      lp, rp = padder.pad(left, right)
      d = model(lp[None], rp[None], iters=a.iters, test_mode=True)  # [T, 1, 1, Hp, Wp]
      out[f"{name}/padded"] = d[:, 0, 0].numpy()
      out[f"{name}/window"] = padder.unpad(d[:, 0])[:, 0].numpy()
      if kind == "fbt":
        torch.Tensor.cuda = lambda self, *args, **kwargs: self  # CPU: .cuda() as a no-op
        pred = model.forward_batch_test({"stereo_video": torch.stack([left, right], dim=1)},
                                        iters=a.iters)
        out[f"{name}/fbt"] = pred["disparity"][:, 0].numpy()
  np.savez(a.torch_out, **out)


def compare_row(name: str, shape, what: str, ours, official) -> dict:
  """One row of the sweep's table: the largest and mean |difference| in px."""
  ours, official = np.asarray(ours, np.float64), np.asarray(official, np.float64)
  if ours.shape != official.shape:
    raise ValueError(f"{name} ({what}): sav-jax gives shape {ours.shape}, the official side "
                     f"{official.shape}")
  row = dict(case=name, shape="x".join(map(str, shape)), what=what)
  if ours.size == 0:  # e.g. the official [:-5] trimming of a clip of <= 5 frames
    return dict(row, what=what + " (no frames, as the official)", max_px=0.0, mean_px=0.0,
                official_max_px=0.0)
  diff = np.abs(ours - official)
  return dict(row, max_px=float(diff.max()), mean_px=float(diff.mean()),
              official_max_px=float(np.abs(official).max()))


def jax_side(a, ref: dict) -> list[dict]:
  import jax  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  jax.config.update("jax_default_matmul_precision", "highest")
  cfg = sav_jax.SAVConfig()
  variables = jax.device_put(sav_jax.convert.params_from_state_dict(weights(a), cfg))
  model = sav_jax.StereoAnyVideo(cfg)
  direct = jax.jit(lambda v, l, r: model.apply(v, l, r, iters=a.iters,
                                               final_only=True).disparities[0])
  rows = []

  def compare(name, shape, what, ours, official):
    rows.append(compare_row(name, shape, what, ours, official))

  for name, kind, shape, frames in parse_cases(a.cases):
    if kind == "direct":
      compare(name, shape, "model, unpadded batch", direct(variables, *batch(shape, frames)),
              ref[f"{name}/direct"])
      continue
    left, right = clip(*shape[1:], frames)
    compare(name, shape, "predict_video vs |window|",
            inference.predict_video(variables, left, right, cfg=cfg, iters=a.iters),
            np.abs(ref[f"{name}/window"]))
    compare(name, shape, "run_window, padded, signed",
            inference.run_window(variables, left, right, cfg=cfg, iters=a.iters),
            ref[f"{name}/padded"])
    if kind == "fbt":
      compare(name, shape, "forward_batch_test_official",
              inference.forward_batch_test_official(variables, left, right, cfg=cfg,
                                                    iters=a.iters), ref[f"{name}/fbt"])
  return rows


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--repo", required=True, help="a checkout of the official stereoanyvideo")
  p.add_argument("--torch-interpreter", help="a Python with torch, for the official side")
  p.add_argument("--fixtures", default=os.environ.get("SAV_FIXTURES",
                                                      str(HERE.parents[1] / "shared/fixtures")),
                 help="the oracle fixtures folder (default: SAV_FIXTURES or ../shared/fixtures)")
  p.add_argument("--iters", type=int, default=4)
  p.add_argument("--cases", default=DEFAULT_CASES, help="NAME=KIND:BxTxHxW:FRAMES,...")
  p.add_argument("--json", help="also write the rows to this file (a new file, or --overwrite)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
  p.add_argument("--torch-out", help=argparse.SUPPRESS)  # the official side's own run
  a = p.parse_args(argv)
  parse_cases(a.cases)  # a typo fails before either model runs
  if a.iters < 2:
    p.error("--iters must be >= 2")
  if a.json and not a.torch_out:
    from sav_jax.tools.bench import json_output_problem  # pylint: disable=import-outside-toplevel
    problem = json_output_problem(a.json, a.overwrite)
    if problem:
      p.error(problem)
  return a


def main(argv=None) -> int:
  a = parse_args(argv)
  if a.torch_out:
    torch_side(a)
    return 0
  rows = jax_side(a, official_outputs(a, argv, __file__))
  print(f"iters={a.iters}; differences from the official model, px")
  for r in rows:
    print(f"{r['case']:10} {r['shape']:>14}  {r['what']:30} max {r['max_px']:.1e}  "
          f"mean {r['mean_px']:.1e}  (official |d| up to {r['official_max_px']:.2f})")
  if a.json:
    pathlib.Path(a.json).write_text(json.dumps(rows, indent=1))
  return 0


if __name__ == "__main__":
  sys.exit(main())

"""`sav-jax demo`: the whole pipeline on a built-in synthetic stereo video.

    sav-jax demo                       # 8 frames of 128x256 (HxW), iters 4: ~35 s on 2 CPU cores
                                       # (compiling included, no cache; 2026-12-06)
    sav-jax demo --checkpoint ckpt     # with trained weights

Generates a procedural stereo video with exact ground truth (`sav_jax.data.synthetic`),
runs the model (`--checkpoint`, else the bundled `sav_jax/assets/sav_synthetic` when it
exists, else seeded random weights, which it says plainly), runs OpenCV's StereoSGBM per
frame as a baseline, prints EPE / TEPE of both against the ground truth and writes, under
--out (default `outputs/demo`): `comparison.mp4` (left | ground truth | Stereo Any Video |
SGBM, one colour range), `side_by_side.mp4` (left | disparity), `disparity/frame_XXXXXX.png`
(16-bit, x256) and `metrics.json`. An earlier demo's outputs there (recognised by its
`metrics.json`) are replaced; other files of those names only with `--overwrite`.
"""

from __future__ import annotations

import argparse
import json
import logging
import pathlib
import time

import cv2
import numpy as np

from sav_jax._checks import is_int
from sav_jax.tools import (add_compile_cache_arguments, check_output_dir, setup_compile_cache,
                           user_path)

log = logging.getLogger(__name__)

HELP = "run the model on a built-in synthetic stereo video and compare with StereoSGBM"
BUNDLED = pathlib.Path(__file__).resolve().parents[1] / "assets" / "sav_synthetic"
TABLE = (("EPE", "disp_epe_mean"), ("bad-1px %", "disp_epe_bad_1px"),
         ("TEPE", "disp_temp_epe_mean"), ("δt-1px %", "disp_temp_epe_bad_1px"))


def add_arguments(p: argparse.ArgumentParser) -> None:
  p.add_argument("--checkpoint", type=user_path, help="orbax directory, a training run's WORKDIR, or a "
                                      ".pth/.pt/.safetensors/.npz state dict (default: "
                                      f"{BUNDLED} if present, else random weights)")
  p.add_argument("--out", default="outputs/demo", type=user_path, help="output folder (default outputs/demo)")
  p.add_argument("--frames", type=int, default=8, help="frames of the synthetic video (8)")
  p.add_argument("--height", type=int, default=128, help="frame height (128)")
  p.add_argument("--width", type=int, default=256, help="frame width (256)")
  p.add_argument("--iters", type=int, default=4, help="refinement iterations (>= 2; 4)")
  p.add_argument("--seed", type=int, default=0, help="seed of the synthetic scene (0)")
  p.add_argument("--dtype", choices=("float32", "bfloat16"), default=None,
                 help="compute dtype (default: the checkpoint's, float32)")
  p.add_argument("--overwrite", action="store_true",
                 help="replace files of the output names in --out that an earlier demo did not "
                      "write (an earlier demo's outputs are always replaced)")
  add_compile_cache_arguments(p)


def check_sgbm_args(max_disparity, block_size, prefix: str = "") -> None:
  """Raises ValueError unless `block_size` is an odd integer >= 1 and `max_disparity` a
  finite number >= 1 (OpenCV runs other block sizes without a word)."""
  if not is_int(block_size) or block_size < 1 or block_size % 2 == 0:
    raise ValueError(f"{prefix}block_size must be an odd integer >= 1, got {block_size!r}")
  if isinstance(max_disparity, bool) or not isinstance(max_disparity, (int, float, np.number)) \
      or not (np.isfinite(max_disparity) and max_disparity >= 1):
    raise ValueError(f"{prefix}max_disparity must be a finite number >= 1, got {max_disparity!r}")


_SGBM_CUTS: set = set()  # the (max disparity, width) pairs already warned about


def stereo_sgbm(left: np.ndarray, right: np.ndarray, max_disparity: float = 128.0,
                block_size: int = 5) -> np.ndarray:
  """OpenCV semi-global matching per frame, holes filled from the background.

  Args:
    left, right: `[T, H, W, 3]` uint8 RGB.
    max_disparity: largest disparity searched (rounded up to a multiple of 16, and cut to
      the largest multiple of 16 below the width, which OpenCV needs).
    block_size: matching block size (odd).

  Returns:
    `[T, H, W]` float32 disparity; pixels SGBM leaves invalid get the smaller of the
    nearest valid values on their row (KITTI's background interpolation).
  """
  check_sgbm_args(max_disparity, block_size)
  num = int(np.ceil(max(16.0, float(max_disparity)) / 16.0)) * 16
  width = left.shape[2]
  if num >= width:
    if width <= 16:
      raise ValueError(f"StereoSGBM needs frames wider than 16 px, got width {width}")
    num = (width - 1) // 16 * 16
    if (max_disparity, width) not in _SGBM_CUTS:  # once per size (eval: every sequence)
      _SGBM_CUTS.add((max_disparity, width))
      log.warning("StereoSGBM: max disparity %s cut to %d for %d-px-wide frames", max_disparity,
                  num, width)
  sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=block_size,
                               P1=8 * 3 * block_size ** 2, P2=32 * 3 * block_size ** 2,
                               disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                               speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
  out = np.empty(left.shape[:3], np.float32)
  for t in range(len(left)):
    d = sgbm.compute(np.ascontiguousarray(left[t]), np.ascontiguousarray(right[t]))
    out[t] = fill_invalid(d.astype(np.float32) / 16.0)
  return out


def fill_invalid(disp: np.ndarray) -> np.ndarray:
  """Fills `disp <= 0` per row with min(nearest valid left, nearest valid right); 0 if none."""
  h, w = disp.shape
  valid = disp > 0
  idx = np.where(valid, np.arange(w)[None], -1)
  left_idx = np.maximum.accumulate(idx, axis=1)
  right_idx = np.flip(np.minimum.accumulate(
      np.flip(np.where(valid, np.arange(w)[None], w), axis=1), axis=1), axis=1)
  rows = np.arange(h)[:, None]
  padded = np.concatenate([disp, np.full((h, 1), np.inf, np.float32)], axis=1)
  from_left = np.where(left_idx >= 0, padded[rows, np.maximum(left_idx, 0)], np.inf)
  from_right = padded[rows, right_idx]
  fill = np.minimum(from_left, from_right)
  out = np.where(valid, disp, np.where(np.isfinite(fill), fill, 0.0))
  return out.astype(np.float32)


def _weights(args, cfg_dtype):
  """`(variables, cfg, description)` from --checkpoint, the bundled one, or random."""
  from sav_jax.convert import is_variables_checkpoint  # pylint: disable=import-outside-toplevel
  from sav_jax.inference import resolve_config  # pylint: disable=import-outside-toplevel
  # pylint: disable-next=import-outside-toplevel
  from sav_jax.tools.infer import load_checkpoint, random_variables
  if args.checkpoint:
    return load_checkpoint(args.checkpoint, dtype=cfg_dtype)
  if is_variables_checkpoint(BUNDLED):
    return load_checkpoint(BUNDLED, dtype=cfg_dtype)
  cfg = resolve_config(None, cfg_dtype)
  return (random_variables(cfg, seed=0), cfg,
          "RANDOM (untrained) weights, initialised with seed 0: no --checkpoint given and no "
          f"bundled checkpoint at {BUNDLED}. The model's numbers below are meaningless; "
          "they only show that the pipeline runs")


OUTPUT_NAMES = ("comparison.mp4", "side_by_side.mp4", "metrics.json")


def _frame_path(out: pathlib.Path, t: int) -> pathlib.Path:
  """Where the demo writes frame `t`'s disparity."""
  return out / "disparity" / f"frame_{t:06d}.png"


def _earlier_demo_frames(out: pathlib.Path) -> int | None:
  """The frame count of an earlier demo in `out` (its metrics.json says so), else None."""
  try:
    summary = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return None
  if not (isinstance(summary, dict) and {"weights", "synthetic", "metrics"} <= summary.keys()):
    return None
  frames = summary["synthetic"].get("frames") if isinstance(summary["synthetic"], dict) else None
  return frames if isinstance(frames, int) and not isinstance(frames, bool) else 0


def check_demo_output(out: pathlib.Path, frames: int, overwrite: bool) -> list[pathlib.Path]:
  """The earlier demo's frame PNGs to delete; raises FileExistsError before anything is
  written if files of the demo's names exist that an earlier demo did not write (unless
  `overwrite`). Only frames an earlier demo in `out` wrote (below the count its
  metrics.json records) are ever deleted; other files are left alone, even with `overwrite`.
  """
  from sav_jax.tools.infer import check_overwrite  # pylint: disable=import-outside-toplevel
  earlier = _earlier_demo_frames(out)
  stale = [p for t in range(frames, earlier or 0) if (p := _frame_path(out, t)).is_file()]
  if earlier is None:
    check_overwrite([out / n for n in OUTPUT_NAMES]
                    + [_frame_path(out, t) for t in range(frames)], overwrite, out)
  else:  # what the earlier demo wrote is replaced; frames beyond its count it did not write
    # (a symbolic link among the replaced files is refused all the same)
    check_overwrite([out / n for n in OUTPUT_NAMES]
                    + [_frame_path(out, t) for t in range(min(earlier, frames))], True, out)
    check_overwrite([_frame_path(out, t) for t in range(earlier, frames)], overwrite, out)
  return stale


def _metrics(pred, clip):
  from sav_jax import metrics  # pylint: disable=import-outside-toplevel
  return metrics.eval_sequence(pred, clip["disparity"], clip["valid"].astype(np.float32))


def run(args: argparse.Namespace) -> int:
  from sav_jax import inference, viz  # pylint: disable=import-outside-toplevel
  from sav_jax.data import synthetic  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import UsageError, infer, video_io  # pylint: disable=import-outside-toplevel
  infer.check_model_args(args.iters, 20, 10)
  if args.frames < 2 or args.height < 16 or args.width < 32:  # TEPE needs two frames
    raise UsageError("need --frames >= 2 (the temporal metrics compare consecutive frames), "
                     "--height >= 16 and --width >= 32")
  if args.seed < 0:  # (the synthetic scene's check names SyntheticConfig.seed, after the weights)
    raise UsageError(f"--seed must be >= 0, got {args.seed}")
  out = check_output_dir(args.out)
  # (its disparity/frame_*.png there were read as the sequence's ground truth, as infer's)
  infer.check_not_sequence_folder(out)
  # (its videos: OpenCV's video writer cannot take other bytes, refused after the model ran)
  viz.check_utf8_path(out.absolute(), "--out folder")
  stale = check_demo_output(out, args.frames, args.overwrite)
  setup_compile_cache(args)
  variables, cfg, described = _weights(args, args.dtype)  # a bad checkpoint fails first
  scfg = synthetic.SyntheticConfig(frames=args.frames, height=args.height, width=args.width,
                                   max_disparity=min(64.0, args.width / 8), seed=args.seed)
  synthetic.check_host_memory(scfg)
  clip = synthetic.generate_clip(scfg, 0)
  print(f"weights: {described}")
  print(f"synthetic video: {args.frames} frames of {args.height}x{args.width} (seed {args.seed}), "
        f"iters {args.iters}, {cfg.dtype}")
  t0 = time.perf_counter()
  pred = inference.predict_video(variables, clip["left"], clip["right"], cfg=cfg,
                                 iters=args.iters, progress=True)
  t_model = time.perf_counter() - t0
  t0 = time.perf_counter()
  sgbm = stereo_sgbm(clip["left"], clip["right"], max_disparity=scfg.max_disparity * 1.25)
  t_sgbm = time.perf_counter() - t0
  results = {"Stereo Any Video": _metrics(pred, clip), "StereoSGBM": _metrics(sgbm, clip)}
  times = {"Stereo Any Video": t_model, "StereoSGBM": t_sgbm}
  print(_table(results, times))
  (out / "disparity").mkdir(parents=True, exist_ok=True)
  for path in stale:  # a longer earlier demo's frames
    path.unlink()
  vmin, vmax = viz.disparity_range(clip["disparity"], clip["valid"])
  col = lambda d, valid=None: viz.colorize(d, vmin, vmax, valid=valid)  # noqa: E731
  viz.write_video(out / "comparison.mp4", viz.side_by_side(
      clip["left"], col(clip["disparity"], clip["valid"]), col(pred), col(sgbm)), fps=5)
  viz.write_video(out / "side_by_side.mp4", viz.side_by_side(clip["left"], col(pred)), fps=5)
  for t in range(args.frames):
    video_io.write_map(_frame_path(out, t), pred[t], "png16")
  summary = {"weights": described, "synthetic": {"frames": args.frames, "height": args.height,
                                                 "width": args.width, "seed": args.seed},
             "iters": args.iters, "dtype": str(cfg.dtype), "metrics": results,
             "seconds": times}
  (out / "metrics.json").write_text(json.dumps(summary, indent=1))
  print(f"outputs in {out}: comparison.mp4 (left | ground truth | SAV | SGBM), "
        "side_by_side.mp4, disparity/*.png, metrics.json")
  return 0


def _table(results: dict, times: dict) -> str:
  head = f"{'method':<18}" + "".join(f"{name:>11}" for name, _ in TABLE) + f"{'seconds':>10}"
  lines = [head, "-" * len(head)]
  for method, res in results.items():
    lines.append(f"{method:<18}" + "".join(f"{res[key]:>11.3f}" for _, key in TABLE)
                 + f"{times[method]:>10.1f}")
  lines.append("(EPE/TEPE in px, official definitions; model time includes compilation)")
  return "\n".join(lines)

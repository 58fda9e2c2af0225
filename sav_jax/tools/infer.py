"""`sav-jax infer`: disparity (and depth, point clouds) for a stereo video.

    sav-jax infer --left demo/left --right demo/right --checkpoint ckpt --out outputs/run1
    sav-jax infer --left l.mp4 --right r.mp4 --checkpoint sav.pth --out out \\
        --format png16 --format npy --fx 725 --baseline 0.54

Outputs in --out: `disparity/<frame>.<png|npy|pfm|exr>` (16-bit PNGs use the KITTI
x256 convention), `side_by_side.mp4` (left | colourized disparity, one colour range for
the whole video, recorded in the summary), `summary.json`; with calibration also
`depth/<frame>.<npy|exr>` (in the baseline's unit, 0 where disparity + doffs is not positive)
and `pointclouds/<frame>.ply` (OpenCV camera axes: x right, y down, z forward). Inputs,
checkpoint and existing outputs are all checked before anything is computed; an error found
then writes nothing. Once the first window is
computed, a provisional `summary.json` (`"complete": false`) lists the run's files.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import itertools
import json
import logging
import os
import pathlib
import re
import shutil
import sys
import time

from typing import NamedTuple

import numpy as np

from sav_jax import runtime
from sav_jax._checks import loads_json, plural
from sav_jax._files import FREE_SPACE, free_space_note, write_text_atomic
from sav_jax.tools import (UsageError, add_compile_cache_arguments, add_devices_argument,
                           add_matmul_precision_argument, check_output_dir, matmul_precision,
                           parallel, resolve_devices_option, setup_compile_cache, user_path,
                           video_io)

HELP = "estimate disparity for a stereo video (frame folders or video files)"
log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
  p.add_argument("--left", required=True, type=user_path, help="left frames: a folder of images or a video file")
  p.add_argument("--right", required=True, type=user_path, help="right frames: a folder of images or a video file")
  p.add_argument("--checkpoint", required=True, type=user_path,
                 help="orbax directory from `sav-jax convert`, a training run's WORKDIR (latest "
                      "checkpoint) or WORKDIR/checkpoints/STEP, or a .pth/.pt/.safetensors/.npz "
                      "state dict (converted on the fly)")
  p.add_argument("--out", required=True, type=user_path, help="output folder")
  p.add_argument("--iters", type=int, default=20, help="refinement iterations (>= 2; default 20)")
  p.add_argument("--format", action="append", dest="formats", metavar="FMT",
                 help="disparity file format, repeatable or comma-separated: "
                      f"{', '.join(video_io.DISPARITY_FORMATS)} (default png16)")
  add_calibration_arguments(p)
  p.add_argument("--depth-format", choices=("npy", "exr"), default=None,
                 help="file format of metric depth (with calibration; default npy)")
  p.add_argument("--max-depth", type=float, default=None,
                 help="leave points farther than this (baseline's unit) out of the point "
                      "clouds (near-zero disparities of sky and far background give huge depths)")
  p.add_argument("--overwrite", action="store_true", help="replace existing output files")
  p.add_argument("--dtype", choices=("float32", "bfloat16"), default=None,
                 help="compute dtype (default: the checkpoint's, float32)")
  p.add_argument("--max-frames", type=int, default=None, help="use only the first N frames")
  p.add_argument("--resize", type=parse_size, default=None, metavar="HxW",
                 help="run the model on the frames resized to HxW (bilinear, align_corners as "
                      "the official demo.py, which uses 720x1280): less memory and time for "
                      "large frames; the disparities are resized back to the input size and "
                      "scaled to its pixels ((W-1)/(w-1) for align_corners); default: the "
                      "input size")
  p.add_argument("--window", type=int, default=20,
                 help="frames per sliding window (20; at most 32)")
  p.add_argument("--stride", type=int, default=10, help="sliding window stride (10)")
  p.add_argument("--fps", type=float, default=None,
                 help="frame rate of the output video (default: the left input video's, "
                      "10 for frame folders)")
  add_matmul_precision_argument(p)
  add_devices_argument(p)
  add_compile_cache_arguments(p)


def add_calibration_arguments(p: argparse.ArgumentParser) -> None:
  """--fx --fy --cx --cy --baseline | --calib FILE."""
  g = p.add_argument_group("calibration (for metric depth and point clouds)")
  g.add_argument("--fx", type=float, help="focal length of the left camera (px)")
  g.add_argument("--fy", type=float, help="vertical focal length (px; default fx)")
  g.add_argument("--cx", type=float, help="principal point x (px; default image centre)")
  g.add_argument("--cy", type=float, help="principal point y (px; default image centre)")
  g.add_argument("--baseline", type=float,
                 help="stereo baseline (metres; depth comes out in its unit)")
  g.add_argument("--doffs", type=float,
                 help="cx of the right camera minus cx of the left (px; default 0): "
                      "depth = fx * baseline / (disparity + doffs)")
  g.add_argument("--calib", type=user_path, help="calibration file: JSON or 'key value' text with fx, fy, "
                                  "cx, cy, baseline, doffs; a KITTI calib file (P_rect_02/"
                                  "P_rect_03 or P2/P3); or a Middlebury calib.txt (cam0, cam1, "
                                  "doffs, baseline in mm: depth in mm)")
  g.add_argument("--calib-cameras", type=parse_camera_pair, metavar="LEFT,RIGHT",
                 help="the KITTI cameras of --left and --right in a KITTI --calib file: 2,3 "
                      "(colour, image_2/image_3: the default) or 0,1 (grey, image_0/image_1; "
                      "used by default where a file has only P0/P1)")


def parse_camera_pair(text: str) -> tuple[int, int]:
  """`"0,1"` -> (0, 1): the KITTI camera numbers (0-3) of the left and right views."""
  parts = str(text).replace(" ", "").split(",")
  if len(parts) != 2 or not all(p in ("0", "1", "2", "3") for p in parts) or parts[0] == parts[1]:
    raise argparse.ArgumentTypeError(f"expected two different KITTI camera numbers 0-3 as "
                                     f"LEFT,RIGHT (2,3 colour, 0,1 grey), got {text!r}")
  return int(parts[0]), int(parts[1])


def parse_size(text: str) -> tuple[int, int]:
  """`"720x1280"` (or `720,1280`) -> (720, 1280): height and width, positive integers."""
  parts = re.split(r"[x,]", str(text).strip().lower())
  try:
    size = tuple(int(v) for v in parts)
  except ValueError:
    size = ()
  if len(size) != 2 or min(size) < 1:
    raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH, e.g. 720x1280, got {text!r}")
  return size


def flips_orientation(size: tuple[int, int], resized: tuple[int, int]) -> bool:
  """Whether `resized` (height, width) turns frames of `size` from landscape to portrait or
  the reverse: `--resize` given as width x height (1280x720 for 1280-wide frames) out of
  habit, which distorts every frame (square frames or sizes: never)."""
  (h, w), (rh, rw) = size, resized
  return (h - w) * (rh - rw) < 0


def parse_formats(values: list[str] | None) -> list[str]:
  """`--format` values (repeated and/or comma-separated) -> ordered unique formats."""
  out = []
  for value in values or ["png16"]:
    for fmt in (v.strip().lower() for v in value.split(",")):
      if fmt not in video_io.DISPARITY_FORMATS:
        raise UsageError(f"unknown --format {fmt!r}; choose from "
                         f"{', '.join(video_io.DISPARITY_FORMATS)}")
      if fmt not in out:
        out.append(fmt)
  return out


def output_paths(out: pathlib.Path, names: list[str], formats: list[str],
                 calib: Calibration | None, depth_format: str) -> list[pathlib.Path]:
  """Every file an `infer` run writes."""
  paths = [video_io.disparity_path(out / "disparity", n, f) for n in names for f in formats]
  paths += [out / "side_by_side.mp4", out / "summary.json"]
  if calib is not None:
    paths += [video_io.disparity_path(out / "depth", n, depth_format) for n in names]
    paths += [out / "pointclouds" / f"{n}.ply" for n in names]
  return paths


def check_overwrite(paths: list[pathlib.Path], overwrite: bool,
                    out: pathlib.Path | None = None,
                    listed: set[pathlib.Path] | None = None) -> None:
  """Raises FileExistsError if any output exists and `overwrite` is off, or if an output
  (or a folder it goes in) is something other than a file (folder), or a symbolic link,
  even with `overwrite`; so is a folder below `out` (`disparity/`, ...) that is a link.
  `listed` (`listed_outputs`): the files an earlier run wrote; the error names the others,
  which `--overwrite` would delete too."""
  checked = set()  # folders looked at already, with every folder above them
  existing = []
  for p in paths:
    for parent in p.parents:
      if parent in checked:
        break
      checked.add(parent)
      if out is not None and parent.is_symlink() and out in parent.parents:
        # the run would write (and --overwrite delete) files in the folder it points to
        raise FileExistsError(f"{parent} is a symbolic link (to {os.readlink(parent)}); move "
                              "it away (files are not written into its target, even with "
                              "--overwrite)")
      if parent.exists() and not parent.is_dir():
        raise FileExistsError(f"{parent} is a file, not a folder; move it away to write {p}")
    if p.is_symlink():  # writing would go through it, into a file elsewhere
      raise FileExistsError(f"{p} is a symbolic link (to {os.readlink(p)}); move it away (its "
                            "target is not written through, even with --overwrite)")
    if p.is_file():
      existing.append(p)
    elif p.exists():
      raise FileExistsError(f"{p} exists and is not a file; move it away (it is not replaced, "
                            "even with --overwrite)")
  if existing and not overwrite:
    shown = ", ".join(str(p) for p in existing[:3])
    more = f" and {len(existing) - 3} more" if len(existing) > 3 else ""
    unlisted = [p for p in existing if listed is not None and p.absolute() not in listed]
    others = "" if not unlisted else (
        f"; {len(unlisted)} of them ({unlisted[0]}{', ...' * (len(unlisted) > 1)}) no earlier "
        f"sav-jax infer run in {out} lists as its output: files of your own? --overwrite "
        "deletes them too, another --out keeps them")
    raise FileExistsError(f"output files exist ({shown}{more}); pass --overwrite to replace "
                          f"them{others}")


# Marks the `summary.json` this command writes: `--overwrite` trusts no other one's list.
SUMMARY_TOOL = "sav-jax infer"


def _is_output_name(rel: str) -> bool:
  """Whether `rel` (relative to --out) has the name of a file `infer` writes."""
  parts = pathlib.PurePosixPath(rel).parts
  if parts == ("side_by_side.mp4",):
    return True
  if len(parts) != 2 or parts[1].startswith(".") or ".." in parts:
    return False
  suffix = pathlib.PurePosixPath(parts[1]).suffix
  maps = set(video_io.DISPARITY_SUFFIXES)
  return suffix in {"disparity": maps, "depth": maps, "pointclouds": {".ply"}}.get(parts[0], ())


def _summary_outputs(out: pathlib.Path) -> list[pathlib.Path] | None:
  """The absolute paths of the files `out/summary.json` lists, in its order, where `infer`
  wrote it (None where not: another tool's `summary.json` may list anything), and of those
  only the files this command writes."""
  try:
    summary = loads_json((out / "summary.json").read_text())
  except (OSError, ValueError):  # none, or unreadable
    return None
  if not (isinstance(summary, dict) and summary.get("tool") == SUMMARY_TOOL
          and isinstance(summary.get("outputs"), list)):
    return None
  return [(out / rel).absolute() for rel in summary["outputs"]
          if isinstance(rel, str) and _is_output_name(rel)]


def listed_outputs(out: pathlib.Path) -> set[pathlib.Path]:
  """The absolute paths of the files `out/summary.json` lists, and its own, where `infer`
  wrote it (none else): what an earlier run wrote, or began to write (its provisional
  summary)."""
  listed = _summary_outputs(out)
  return set() if listed is None else {*listed, (out / "summary.json").absolute()}


def earlier_outputs(out: pathlib.Path, outputs: list[pathlib.Path]) -> list[pathlib.Path]:
  """The files an earlier run in `out` wrote (its `summary.json` lists them) that this run
  will not replace: other formats, frames beyond a shorter video, depth and point clouds
  of a run with calibration. `--overwrite` sets them aside as this run begins to write
  (`set_aside`) and deletes them once its summary is written (`drop_set_aside`), so that
  the folder holds one run's outputs; files the summary does not list (a user's own,
  or those of a run that failed before its summary) are never deleted."""
  keep = {p.absolute() for p in outputs}
  return [path for path in _summary_outputs(out) or ()
          if path not in keep and path.is_file() and not path.is_symlink()
          and not path.parent.is_symlink()]  # never deleted through a linked subfolder


# Where `--overwrite` keeps the earlier run's files while this run writes (in --out; not
# `python -m eval`'s `.earlier_run`), its name once this run is complete (a deletion cut
# short is finished by the next run, never undone), and the lock a run holds in --out.
SET_ASIDE = ".infer_earlier_run"
DONE = SET_ASIDE + ".done"
LOCK = ".infer.lock"


def output_lock(out: pathlib.Path):
  """Holds `out/.infer.lock` while a run works in `out` (`sav_jax._locks.output_lock`): a
  second run into the same folder took the first one's set-aside files for a killed run's
  and put them back under it. FileExistsError if another `infer` holds it."""
  from sav_jax import _locks  # pylint: disable=import-outside-toplevel
  return _locks.output_lock(out, LOCK, f"another sav-jax infer ({{holder}}) is writing into "
                            f"{out}: wait for it or choose another --out")


def set_aside(out: pathlib.Path, paths: list[pathlib.Path]) -> int:
  """Moves the earlier run's files `paths` (and its `summary.json`, first) into
  `out/.infer_earlier_run/`, keeping their places relative to `out`. Returns how many files moved.

  An interrupted `--overwrite` run left the folder with two runs' files mixed (the new
  run's frames so far beside the earlier run's others) and the earlier summary gone:
  `put_back` undoes the move after a failure, `drop_set_aside` deletes the files once the
  new run's summary is written.
  """
  aside = out / SET_ASIDE
  aside.mkdir(exist_ok=True)  # even empty: the mark of a run under way (`put_back`)
  moved = 0
  for path in [out / "summary.json", *paths]:
    if path.is_file() and not path.is_symlink():
      target = aside / path.absolute().relative_to(out.absolute())  # (--out may be relative)
      target.parent.mkdir(parents=True, exist_ok=True)
      path.replace(target)
      moved += path.name != "summary.json"
  for folder in {p.parent for p in paths} - {out}:  # e.g. depth/ of a run with calibration
    if folder.is_dir() and not any(folder.iterdir()):
      folder.rmdir()
  return moved


def put_back(out: pathlib.Path) -> int:
  """Undoes `set_aside` after a run that did not finish (an error, Ctrl-C, or a killed run
  found by the next one): deletes the files the unfinished run's provisional `summary.json`
  lists, then moves the earlier run's files back. Returns how many files came back.

  A run that finished (its complete summary written) is never undone: what it set aside is
  deleted (`drop_set_aside`, finished here if it was cut short)."""
  if (out / DONE).is_dir():
    shutil.rmtree(out / DONE)
  aside = out / SET_ASIDE
  if not aside.is_dir():
    return 0
  try:  # the unfinished run's list (none if it stopped before writing it)
    summary = loads_json((out / "summary.json").read_text())
  except (OSError, ValueError):
    summary = {}
  ours = isinstance(summary, dict) and summary.get("tool") == SUMMARY_TOOL
  if ours and summary.get("complete") is True:  # finished, killed before its drop_set_aside
    drop_set_aside(out)
    return 0
  if ours and summary.get("complete") is False and isinstance(summary.get("outputs"), list):
    for rel in summary["outputs"]:
      if isinstance(rel, str) and _is_output_name(rel):
        path = out / rel
        if path.is_file() and not path.is_symlink() and not path.parent.is_symlink():
          path.unlink()
    (out / "summary.json").unlink()
  restored = 0
  for path in sorted(p for p in aside.rglob("*") if p.is_file()):
    target = out / path.relative_to(aside)
    target.parent.mkdir(parents=True, exist_ok=True)
    path.replace(target)
    restored += target.name != "summary.json"
  shutil.rmtree(aside)
  for name in ("disparity", "depth", "pointclouds"):  # made by the unfinished run only
    folder = out / name
    if folder.is_dir() and not folder.is_symlink() and not any(folder.iterdir()):
      folder.rmdir()
  return restored


def drop_set_aside(out: pathlib.Path) -> None:
  """Deletes the set-aside files once the new run's summary is written: renamed first (one
  atomic step: from then on a stop cannot bring them back), then deleted."""
  if (out / SET_ASIDE).is_dir():
    (out / SET_ASIDE).replace(out / DONE)
  if (out / DONE).is_dir():
    shutil.rmtree(out / DONE)


@contextlib.contextmanager
def puts_back_on_failure(out: pathlib.Path):
  """`put_back` if the block fails (an error, Ctrl-C), then re-raises."""
  try:
    yield
  except BaseException:
    if put_back(out):
      print(f"the earlier run's files in {out} were put back", file=sys.stderr)
    raise


def check_not_inputs(paths: list[pathlib.Path], inputs, args=None) -> None:
  """Raises FileExistsError if an output would replace an input video file, or go into an
  input frame folder (even beside its frames: the next run would read it as a frame), or
  replace the checkpoint or calibration file of `args` (its `checkpoint`, `calib`; a
  checkpoint folder may hold the outputs). Holds with --overwrite too: a user's input data
  is never written over."""
  files, folders = {}, {}
  for source in inputs:
    source = pathlib.Path(source)
    (folders if source.is_dir() else files)[source.resolve()] = source
  for source in (getattr(args, "checkpoint", None), getattr(args, "calib", None)):
    if source:
      files[pathlib.Path(source).resolve()] = pathlib.Path(source)
  for p in paths:
    p_abs = p.resolve()
    if p_abs in files or p_abs in folders:
      source, how = files.get(p_abs) or folders[p_abs], "replace the input"
    elif p_abs.parent in folders:
      source = folders[p_abs.parent]
      how = ("replace a file of the input" if p_abs.exists()
             else "be written into the input frame folder")
    else:
      continue
    raise FileExistsError(f"output {p} would {how} {source}; choose another --out (inputs are "
                          "never written over or into, even with --overwrite)")


def check_not_sequence_folder(out: pathlib.Path) -> None:
  """Raises FileExistsError if `out` holds `left/` and `right/` folders: a sequence of the
  `folder` dataset (`sav_jax/data/stereo_folder.py`), whose `disparity/` the readers take for
  its ground truth, so the predictions written there were scored against themselves by
  `python -m eval` (EPE 0) and trained on as labels. Holds with --overwrite too."""
  if (out / "left").is_dir() and (out / "right").is_dir():
    raise FileExistsError(f"--out {out} holds left/ and right/ folders, a stereo folder "
                          "dataset's sequence, whose disparity/ is read as its ground truth: "
                          "the predictions would be taken for it; choose an --out outside "
                          "the dataset")


def check_model_args(iters: int, window: int, stride: int) -> None:
  if iters < 2:
    raise UsageError(f"--iters must be an integer >= 2, got {iters}")
  if not 1 <= stride <= window:
    raise UsageError(f"need 1 <= --stride <= --window, got stride {stride}, window {window}")
  from sav_jax.config import TEMPORAL_MAX_LEN  # pylint: disable=import-outside-toplevel
  if window > TEMPORAL_MAX_LEN:
    raise UsageError(f"--window must be at most {TEMPORAL_MAX_LEN} (the depth prior's temporal "
                     f"attention length), got {window}")


def run(args: argparse.Namespace) -> int:
  parallel.io_threads()  # (a bad SAV_IO_THREADS named now, not after the first window ran)
  formats = parse_formats(args.formats)
  check_model_args(args.iters, args.window, args.stride)
  from sav_jax import viz  # pylint: disable=import-outside-toplevel
  if args.fps is not None:
    viz.check_fps(args.fps, "--fps")
  calib_spec = calibration_from_args(args)
  ckpt = pathlib.Path(args.checkpoint)
  if not ckpt.exists():
    raise FileNotFoundError(f"checkpoint not found: {ckpt}")
  left, right, names = video_io.open_stereo(args.left, args.right, args.max_frames)
  t, h, w = left.shape[:3]
  if args.fps is None:  # the input video's rate, so that the output plays at its speed
    args.fps = getattr(left, "fps", None) or 10.0
  calib = None if calib_spec is None else calib_spec.resolve(w, h)
  if args.depth_format is not None and calib is None:
    raise UsageError("--depth-format applies to metric depth: give a calibration too")
  args.depth_format = args.depth_format or "npy"
  if args.max_depth is not None:
    if calib is None:
      raise UsageError("--max-depth applies to point clouds: give a calibration too")
    if not (np.isfinite(args.max_depth) and args.max_depth > 0):
      raise UsageError(f"--max-depth must be a finite positive number, got {args.max_depth}")
  out = check_output_dir(args.out)
  check_not_sequence_folder(out)
  outputs = output_paths(out, names, formats, calib, args.depth_format)
  for path in outputs:  # before anything is written (OpenCV crashed on such names)
    viz.check_utf8_path(path, "output file (named after --out and the frame)")
  check_not_inputs(outputs, (args.left, args.right), args)
  try:
    with output_lock(out):
      return _run_locked(args, out, outputs, left, right, names, formats, calib)
  finally:  # (an error or Ctrl-C: the frames being decoded ahead are not decoded after it)
    left.close()
    right.close()


def _run_locked(args, out, outputs, left, right, names, formats, calib) -> int:
  """`run`'s rest, holding the lock on `out`."""
  from sav_jax import viz  # pylint: disable=import-outside-toplevel
  ckpt = pathlib.Path(args.checkpoint)
  t, h, w = left.shape[:3]
  restored = put_back(out)  # files a killed --overwrite run had set aside
  if restored:
    print(f"put back {restored} files of an earlier run in {out} that an interrupted "
          "--overwrite run had set aside")
  check_overwrite(outputs, args.overwrite, out, listed_outputs(out))
  for folder in sorted({p.parent for p in outputs} - {out}):  # an earlier run's disparity/...
    if folder.is_dir():  # (not writable: found only once the model had run)
      check_output_dir(folder)
  # With --overwrite, the files this run replaces and those of the earlier run it does not
  # are set aside as it begins to write, and deleted when it ends.
  stale = earlier_outputs(out, outputs) if args.overwrite else []
  check_not_inputs(stale, (args.left, args.right), args)
  if args.overwrite:
    stale = [p for p in outputs if p.is_file()] + stale

  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  devices = resolve_devices_option(args.devices)
  # (fewer windows than devices: the others get no copy of the weights and no work)
  devices = devices[:len(inference.window_plan(t, args.window, args.stride))]
  setup_compile_cache(args)  # (after the devices are checked: it may create the folder)
  for source in (left, right):  # the reach of the windows' and the outputs' reads
    source.keep = args.window + (len(devices) - 1) * args.stride + 1
  resize = getattr(args, "resize", None)
  if resize == (h, w):
    resize = None
  if resize is not None and flips_orientation((h, w), resize):
    log.warning("--resize %dx%d is height x width: it turns the %dx%d (height x width) frames "
                "%s; for their orientation give --resize %dx%d", *resize, h, w,
                "from landscape to portrait" if w > h else "from portrait to landscape",
                resize[1], resize[0])
  variables, cfg, described = load_checkpoint(ckpt, dtype=args.dtype)
  print(f"weights: {described}")
  on = f"; {len(devices)} devices ({devices[0].platform})" if len(devices) > 1 else ""
  at = f", run at {resize[0]}x{resize[1]}" if resize else ""
  print(f"input: {plural(t, 'frame')} of {h}x{w} (height x width){at}; iters {args.iters}, "
        f"{cfg.dtype}{on}")
  start, compiled = time.perf_counter(), inference.compile_seconds()
  listed = [p.relative_to(out).as_posix() for p in outputs]
  # The windows are computed as write_outputs draws them, so the precision covers both.
  precision, precision_name = matmul_precision(args)
  with precision:
    model_left, model_right = ((left, right) if resize is None else
                               (video_io.ResizedSource(left, *resize),
                                video_io.ResizedSource(right, *resize)))
    chunks = inference.iter_predict_video(variables, model_left, model_right, cfg=cfg,
                                          iters=args.iters, window=args.window,
                                          stride=args.stride, progress=True, devices=devices)
    if resize is not None:  # back to the input size, in its pixels
      chunks = ((t0, video_io.disparities_to_input_size(d, h, w)) for t0, d in chunks)
    with puts_back_on_failure(out):
      written = write_outputs(out, names, left, chunks, formats, calib, args, listed,
                              stale=stale)
  seconds = time.perf_counter() - start
  compiling = inference.compile_seconds() - compiled
  summary = {"tool": SUMMARY_TOOL, "frames": t, "height": h, "width": w,
             "model_size": list(resize or (h, w)), "iters": args.iters,
             "dtype": cfg.dtype, "matmul_precision": precision_name,
             "window": args.window, "stride": args.stride,
             "video_fps": viz.mp4v_fps(args.fps),  # (the rate written: 119.8765 -> 119.88)
             "weights": described,
             "devices": [str(d) for d in devices],
             "left": str(args.left), "right": str(args.right), "formats": formats,
             "seconds": round(seconds, 3), "frames_per_second": round(t / seconds, 3),
             "compile_seconds": round(compiling, 3),
             "frames_per_second_without_compile": round(t / max(seconds - compiling, 1e-9), 3),
             "calibration": None if calib is None else calib._asdict(),
             "max_depth": args.max_depth, **written, "complete": True,
             "outputs": listed}  # for a later run with --overwrite into this folder
  with puts_back_on_failure(out):  # (a full disk here: the earlier run's files come back)
    with writing(out / "summary.json", remove=False):
      write_text_atomic(out / "summary.json", json.dumps(summary, indent=1))
  drop_set_aside(out)
  vmin, vmax = written["video_disparity_range"]
  print(f"side-by-side video colours: {vmin:.2f} px (dark) to {vmax:.2f} px (bright)")
  if written["png16_saturated_pixels"]:
    print(f"warning: {written['png16_saturated_pixels']} disparities above "
          f"{viz.PNG16_MAX_DISPARITY:.3f} px were stored as {viz.PNG16_MAX_DISPARITY:.3f} in the "
          "16-bit PNGs (the format's largest value); use --format npy, pfm or exr for them")
  if written["disparities_beyond_width"]:
    share = written["disparities_beyond_width"] / (t * h * w)
    print(f"warning: {written['disparities_beyond_width']} disparities ({share:.1%} of the "
          f"pixels) are at least the frame width ({w} px), where no pixel has a match: "
          "weights that are not trained (or not for this data), swapped --left and --right, "
          "or too few --iters?")
  if written["empty_point_clouds"]:
    limit = "" if args.max_depth is None else f" or deeper than --max-depth {args.max_depth:g}"
    print(f"warning: {written['empty_point_clouds']} of the {t} point clouds have no point: "
          f"every pixel's disparity + doffs was not positive{limit} (check the calibration)")
  print(f"{plural(t, 'frame')} in {seconds:.1f} s ({t / seconds:.2f} frames/s, writing included; "
        f"{compiling:.1f} s of it compiling); outputs in {out}")
  return 0


# Most disparity values the side-by-side video's colour range is computed from (a regular
# subsample of longer videos' frames).
RANGE_SAMPLE = 1 << 24


def write_outputs(out: pathlib.Path, names, left, chunks, formats, calib, args,
                  listed: list[str], stale=()) -> dict:
  """Disparity files, the side-by-side video and, with calibration, depth and PLY files.

  Once the first window has been computed: `stale`, an earlier run's files
  (`earlier_outputs`), are set aside in `SET_ASIDE` (deleted by the caller once the final
  summary is written, put back if the run fails), and a provisional `summary.json` lists
  this run's files (`listed`, relative to `out`; `"complete": false`) until the caller
  writes the final one, so that a later `--overwrite` run finds the files of a run that
  failed midway.

  `chunks` yields `(first frame, disparities [k, H, W])` in order
  (`inference.iter_predict_video`; at least one, computed before any folder is made).
  Each chunk's files are written as it comes; the disparities wait in a temporary file in
  `out` (written and read back with plain file I/O, not mapped: a memory map kept every
  frame written in the process's resident memory) for the video, whose one colour range
  needs them all (taken from a regular subsample gathered as the frames come).

  Returns:
    For the summary: `video_disparity_range` (the video's colour range, px) and
    `png16_saturated_pixels` (disparities stored as the 16-bit PNG's largest value),
    `disparities_beyond_width` and `empty_point_clouds` (PLY files without a point).
  """
  try:
    return _write_outputs(out, names, left, chunks, formats, calib, args, listed, stale)
  finally:  # a window generator stopped by an error: its progress bar ends its line, before
    close = getattr(chunks, "close", None)  # the error is printed (on that line, it was)
    if close is not None:
      close()


def _write_outputs(out, names, left, chunks, formats, calib, args, listed, stale) -> dict:
  import tempfile  # pylint: disable=import-outside-toplevel

  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

  from sav_jax import viz  # pylint: disable=import-outside-toplevel
  # The first window runs before anything is created: a run that cannot (e.g. too little
  # memory, found as it compiles) leaves no empty output folders behind.
  chunks = iter(chunks)
  chunks = itertools.chain([next(chunks)], chunks)
  moved = set_aside(out, stale)  # (nothing to move: marks the run as under way)
  if moved:  # (above the progress bar of the windows, not on its line)
    tqdm.write(f"setting aside {moved} files of the earlier run in {out / SET_ASIDE} "
               "(--overwrite; deleted when this run ends, put back if it does not)",
               file=sys.stdout)
  (out / "disparity").mkdir(parents=True, exist_ok=True)
  # (replaces an earlier run's summary, which would describe this run's files)
  write_text_atomic(out / "summary.json", json.dumps(
      {"tool": SUMMARY_TOOL, "complete": False, "outputs": listed}, indent=1))
  if calib is not None:
    (out / "depth").mkdir(exist_ok=True)
    (out / "pointclouds").mkdir(exist_ok=True)
  h, w = left.shape[1:3]
  saturated = beyond = empty_clouds = 0
  max_depth = getattr(args, "max_depth", None)
  with tempfile.TemporaryFile(dir=out, prefix=".disparity_", suffix=".tmp") as held:
    frame_bytes = h * w * np.dtype(np.float32).itemsize
    size = len(names) * frame_bytes
    held_file = f"the disparities' temporary file in {out}"
    with writing(out, size=size, remove=False, what=held_file):
      # Its blocks reserved now: a full disk is found before any map is written (a memory
      # map on a disk that filled up later got SIGBUS: "Bus error" and no message).
      _reserve(held, size)
    # The colour range's sample: every step-th row and column of every frame, at most
    # RANGE_SAMPLE values.
    step = max(1, int(np.ceil(np.sqrt(len(names) * h * w / RANGE_SAMPLE))))
    sample = np.empty((len(names), -(-h // step), -(-w // step)), np.float32)
    ply_comments = () if calib is None else (
        "sav-jax infer: the left view's pixels back-projected",
        "axes: x right, y down, z forward (OpenCV camera of the left view)",
        f"unit: the baseline's (fx {calib.fx:g} px, baseline {calib.baseline:g}, doffs "
        f"{calib.doffs:g} px)")
    fd = held.fileno()

    def write_frame(i: int, d: np.ndarray, frame) -> tuple[int, int, int]:
      """Frame i's files (in a writer thread): (saturated, beyond, empty cloud)."""
      name = names[i]
      d = np.ascontiguousarray(d, np.float32)
      with writing(out, remove=False, what=held_file):
        _pwrite_all(fd, memoryview(d).cast("B"), i * frame_bytes)
      sample[i] = d[::step, ::step]
      counts = [0, int(np.count_nonzero(d >= w)), 0]  # (beyond: no pixel can match that far)
      for fmt in formats:
        path = video_io.disparity_path(out / "disparity", name, fmt)
        with writing(path):
          counts[0] += video_io.write_map(path, d, fmt)
      if calib is not None:
        depth = viz.depth_from_disparity(d, calib.fx, calib.baseline, calib.doffs)
        path = video_io.disparity_path(out / "depth", name, args.depth_format)
        with writing(path):
          video_io.write_map(path, depth, args.depth_format)
        xyz, rgb = viz.disparity_to_points(d, frame, **calib._asdict(), max_depth=max_depth)
        counts[2] = int(len(xyz) == 0)
        path = out / "pointclouds" / f"{name}.ply"
        with writing(path):
          viz.write_ply(path, xyz, rgb, ply_comments)
      return counts

    totals = [0, 0, 0]

    def collect(counts) -> None:
      for j, c in enumerate(counts):
        totals[j] += c

    # Each frame's files are written by a few threads while the next window is computed (at
    # most `ahead` frames in flight: a window's worth up to 128 MB of disparities, but two
    # per thread at least, so more for small windows or frames over 8 MB); an error in one is
    # raised here, and an error or Ctrl-C waits for the files being written and drops the
    # rest before the run's clean-up.
    ahead = max(2 * parallel.io_threads(), min(int(args.window), (128 << 20) // frame_bytes))
    with parallel.Writer(collect, ahead=ahead) as writer:
      for t0, chunk in chunks:
        frames = left[t0:t0 + len(chunk)] if calib is not None else None
        for k, d in enumerate(chunk):
          writer.submit(write_frame, t0 + k, d, None if frames is None else frames[k])
    saturated, beyond, empty_clouds = totals
    vmin, vmax = viz.disparity_range(sample, percentiles=(1.0, 99.0))
    del sample
    batch = max(1, int(args.window))

    def held_frames(a: int, b: int) -> np.ndarray:
      d = np.empty((b - a, h, w), np.float32)
      held.seek(a * frame_bytes)
      if held.readinto(memoryview(d).cast("B")) != d.nbytes:
        raise OSError(f"{held_file}: frames {a}..{b - 1} could not be read back")
      return d

    def pairs():
      for a in tqdm(range(0, len(names), batch), desc="video", unit="batch",
                    disable=not runtime.draws_progress()):
        b = min(a + batch, len(names))
        yield from zip(left[a:b], held_frames(a, b))

    # (coloured by a few threads, in order, as the writer takes them; closed on an error or
    # Ctrl-C, so that its threads end before the run's clean-up, not when the error is freed)
    video_frames = contextlib.closing(parallel.ordered_map(
        lambda fd: viz.side_by_side(fd[0], viz.colorize(fd[1], vmin, vmax)), pairs()))

    held.flush()
    with writing(out / "side_by_side.mp4", remove=False), video_frames as frames:
      viz.write_video(out / "side_by_side.mp4", frames, fps=args.fps)  # (replaced if complete)
  return {"video_disparity_range": [round(float(vmin), 4), round(float(vmax), 4)],
          "png16_saturated_pixels": saturated, "disparities_beyond_width": beyond,
          "empty_point_clouds": empty_clouds}


@contextlib.contextmanager
def writing(path: pathlib.Path, size: int | None = None, remove: bool = True,
            what: str | None = None):
  """Writes `path` in its block: a failure (a full disk, a folder not writable) removes the
  partial file (`remove`; a truncated `.npy` was left behind) and becomes one OSError that
  names the file, the cause and the disk's free space (numpy's said only "2048 requested and
  992 written"); Ctrl-C removes the partial file too. `size`: the bytes it needs, if known;
  `what`: the file's name in the message, if not `path`."""
  try:
    yield
  except BaseException as e:
    if remove:
      path.unlink(missing_ok=True)
    if not isinstance(e, OSError) or isinstance(e, FileExistsError):  # (not the disk's)
      raise
    need = "" if size is None else f" ({size / 2**20:.1f} MB)"
    cause = os.strerror(e.errno) if e.errno else str(e)
    cause = cause[len(str(path)) + 2:] if cause.startswith(f"{path}: ") else cause
    free = "" if FREE_SPACE in cause else free_space_note(path if path.is_dir() else path.parent)
    raise OSError(f"cannot write {what or path}{need}: {cause}{free}") from e


def _pwrite_all(fd: int, data: memoryview, offset: int) -> None:
  """Writes all of `data` at `offset` of the file `fd` (thread-safe: no shared position)."""
  while data:
    n = os.pwrite(fd, data, offset)
    if n == 0:
      raise OSError(errno.EIO, "wrote nothing")
    data, offset = data[n:], offset + n


def _reserve(file, size: int) -> None:
  """Allocates `size` bytes of `file`'s blocks on disk (ENOSPC now, not SIGBUS later)."""
  if size == 0:
    return
  try:
    os.posix_fallocate(file.fileno(), 0, size)
  except AttributeError:  # not on this OS (macOS): the map grows as it is written
    file.truncate(size)
  except OSError as e:  # a file system without it (ZFS: EINVAL; some FUSE: EOPNOTSUPP)
    if e.errno not in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOSYS):
      raise
    file.truncate(size)


class Calibration(NamedTuple):
  """Left-camera intrinsics (px), the stereo baseline and the principal points' offset
  (`doffs`, px: depth = fx * baseline / (disparity + doffs))."""

  fx: float
  fy: float
  cx: float
  cy: float
  baseline: float
  doffs: float = 0.0


class CalibrationSpec(NamedTuple):
  """Calibration as given: missing fy / cx / cy are filled by `resolve`."""

  fx: float
  baseline: float
  fy: float | None = None
  cx: float | None = None
  cy: float | None = None
  doffs: float = 0.0
  width: float | None = None   # the image size the calibration is for, where a file says
  height: float | None = None

  @classmethod
  def from_mapping(cls, calib) -> "CalibrationSpec":
    """`read_calibration`'s dict (or options of the same names) as a spec, in floats."""
    return cls(**{k: float(v) for k, v in calib.items()})

  def resolve(self, width: int, height: int) -> Calibration:
    """Fills fy = fx and the principal point at the image centre where not given.

    Raises:
      UsageError: the calibration is for another image size (a file's width/height, or a
        principal point outside the frames: e.g. full-resolution intrinsics for resized
        frames).
    """
    rescale = ("scale fx, fy, cx, cy and doffs by the frames' resize factor (in a --calib "
               "file, and its width/height too), or use frames of the calibrated size")
    for name, want, got in (("width", self.width, width), ("height", self.height, height)):
      if want is not None and want != got:
        raise UsageError(f"the calibration is for images of {name} {want:g}, the frames' "
                         f"{name} is {got}: {rescale}")
    calib = Calibration(self.fx, self.fx if self.fy is None else self.fy,
                        (width - 1) / 2 if self.cx is None else self.cx,
                        (height - 1) / 2 if self.cy is None else self.cy, self.baseline,
                        self.doffs)
    from sav_jax import viz  # pylint: disable=import-outside-toplevel
    if not viz.principal_point_inside(calib.cx, calib.cy, height, width):
      raise UsageError(f"the calibration's principal point (cx {calib.cx:g}, cy {calib.cy:g}) "
                       f"is outside the {height}x{width} (height x width) frames: is it for "
                       f"another image size? {rescale[0].upper()}{rescale[1:]}")
    off = (abs(calib.cx - (width - 1) / 2) / width, abs(calib.cy - (height - 1) / 2) / height)
    if max(off) > OFF_CENTRE:  # real lenses: a few % (KITTI's 1242x375 frames: 1% and 4%)
      log.warning("the calibration's principal point (cx %g, cy %g) is %.0f%% of the frame "
                  "from the centre of the %dx%d (height x width) frames: is it for another "
                  "image size (full-resolution intrinsics for smaller frames)? If so, %s",
                  calib.cx, calib.cy, 100 * max(off), height, width, rescale)
    return calib


def calibration_from_args(args) -> CalibrationSpec | None:
  """--fx/--fy/--cx/--cy/--baseline or --calib -> a spec, or None without calibration."""
  given = {k: getattr(args, k, None) for k in _CALIB_KEYS}  # (a file may add width, height)
  given = {k: v for k, v in given.items() if v is not None}
  what = "calibration "  # the start of the messages
  if getattr(args, "calib", None):
    if given:
      raise UsageError("give either --calib or --fx/--fy/--cx/--cy/--baseline/--doffs, not both")
    given = read_calibration(args.calib, getattr(args, "calib_cameras", None))
    what = f"--calib {args.calib}: "
  elif getattr(args, "calib_cameras", None) is not None:
    raise UsageError("--calib-cameras picks the cameras of a KITTI --calib file: give --calib")
  if not given:
    return None
  missing = [k for k in ("fx", "baseline") if k not in given]
  if missing and getattr(args, "calib", None):
    raise UsageError(f"{what}no {' and no '.join(missing)} found (read: "
                     f"{', '.join(sorted(given))}); the file needs fx and baseline (fy, cx, "
                     "cy, doffs optional), KITTI P2/P3 or Middlebury cam0 + baseline")
  if missing:
    raise UsageError(f"calibration needs {' and '.join('--' + m for m in missing)} "
                     "(fy, cx, cy, doffs are optional)")
  from sav_jax import viz  # pylint: disable=import-outside-toplevel
  viz.check_intrinsics(what, **{k: v for k, v in given.items() if k not in _SIZE_KEYS})
  return CalibrationSpec.from_mapping(given)


_CALIB_KEYS = ("fx", "fy", "cx", "cy", "baseline", "doffs")
# A principal point farther than this fraction of the frame's width (height) from its centre
# gets a warning: intrinsics for another image size?
OFF_CENTRE = 0.25
_SIZE_KEYS = ("width", "height")  # the image size a calibration file is for (optional)


def read_calibration(path, cameras: tuple[int, int] | None = None) -> dict[str, float]:
  """Reads fx, fy, cx, cy, baseline (doffs) from JSON, `key value` text, a KITTI calib file
  or a Middlebury `calib.txt`.

  KITTI: `P_rect_02`/`P_rect_03` (raw data; `S_rect_02`, the rectified image size, gives
  `width` and `height` unless the file has `width` or `height` entries of its own, which
  take precedence) or `P2`/`P3` (odometry, stereo benchmarks);
  baseline = (P2[0,3] - P3[0,3]) / fx (P[0,3] alone, as is usual for KITTI: the rectified
  matrices' small z offsets, cx * P[2,3], would change it by ~0.1-0.2% in the raw data's
  files and are left out), doffs = P3[0,2] - P2[0,2] (0 unless the rectified
  principal points differ, as OpenCV's stereoRectify without CALIB_ZERO_DISPARITY gives;
  a warning when P2 is the right camera). Those are the colour cameras (image_2/image_3);
  `cameras=(0, 1)` reads the grey pair (P0/P1, P_rect_00/P_rect_01: image_0/image_1, a
  baseline ~1% longer), which is also the default of a file that has only those.
  Middlebury: `cam0=[fx 0 cx; 0 fy cy; 0 0 1]`, `baseline` (mm), `doffs` (else cam1's cx -
  cam0's cx). Any format may give `width` and `height`, the image size it is for, which the
  frames must then have.

  Raises:
    UsageError: no calibration in the file, a malformed line, or `cameras` given for a file
      without that KITTI pair.
  """
  if cameras is not None and (len(cameras) != 2 or not set(cameras) <= {0, 1, 2, 3}
                              or cameras[0] == cameras[1]):
    raise ValueError(f"cameras must be two different KITTI camera numbers 0-3, got {cameras!r}")
  path = pathlib.Path(path)
  if path.is_dir():
    raise ValueError(f"--calib {path} is a folder; give the calibration file")
  if not path.is_file():
    raise FileNotFoundError(f"calibration file not found: {path}")
  from sav_jax.data import frame_io  # pylint: disable=import-outside-toplevel
  text = frame_io.read_text(path, "calibration file")  # (a byte-order mark dropped a key)
  if text.lstrip().startswith("{"):
    if cameras is not None:
      raise UsageError(f"{path}: a JSON calibration has no KITTI cameras to choose "
                       f"({cameras[0]},{cameras[1]} given): leave --calib-cameras out")
    try:
      data = loads_json(text)
    except ValueError as e:
      raise UsageError(f"{path}: invalid JSON ({e})") from e
    if not isinstance(data, dict) or not any(k in data for k in _CALIB_KEYS):
      found = sorted(data)[:8] if isinstance(data, dict) else type(data).__name__
      raise UsageError(f"{path}: no calibration found: expected a JSON object with fx and "
                       f"baseline (fy, cx, cy optional) at the top level; found {found}")
    out = {}
    for k in (k for k in _CALIB_KEYS + _SIZE_KEYS if k in data):
      if isinstance(data[k], bool) or not isinstance(data[k], (int, float, str)):
        raise UsageError(f"{path}: {k} must be a number, got {data[k]!r}")
      try:
        out[k] = float(data[k])
      except (ValueError, OverflowError) as e:  # an integer beyond float's range
        raise UsageError(f"{path}: {k} must be a number, got {str(data[k])[:40]!r}") from e
    return out
  entries, lines = {}, {}
  for number, line in enumerate(text.splitlines(), 1):
    line = line.split("#", 1)[0].strip()  # comments
    if not line:
      continue
    match = re.match(r"([^\s:=]+)\s*[:=]?\s*(.*)$", line)  # 'k: v', 'k = v', 'k v'
    if match is None:
      raise UsageError(f"{path}, line {number}: expected 'key value' (or 'key: value', "
                       f"'key = value'), got {line!r}")
    key, rest = match.groups()
    earlier = entries.get(key)
    try:  # numbers, or a matrix written as [a b c; d e f; g h i] (Middlebury)
      entries[key] = [float(v) for v in re.sub(r"[,;\[\]]", " ", rest).split()]
    except ValueError:
      entries[key] = None  # text values (KITTI's calib_time, ...)
    if earlier is not None and entries[key] is not None and entries[key] != earlier:
      raise UsageError(f"{path}, lines {lines[key]} and {number}: {key} is given twice, with "
                       "different values; keep one")
    lines.setdefault(key, number)
    if key in _CALIB_KEYS + _SIZE_KEYS and (entries[key] is None or len(entries[key]) != 1):
      raise UsageError(f"{path}, line {number}: {key} must be one number (pixels, or metres "
                       f"for the baseline), got {rest!r}")
  size = {k: entries[k][0] for k in _SIZE_KEYS if k in entries}
  pairs = [cameras] if cameras is not None else [(2, 3), (0, 1)]
  kitti = [(f"P_rect_0{a}", f"P_rect_0{b}", f"S_rect_0{a}") for a, b in pairs]
  kitti += [(f"P{a}", f"P{b}", None) for a, b in pairs]
  if cameras is not None and not any(len(entries.get(p2) or ()) == 12
                                     and len(entries.get(p3) or ()) == 12
                                     for p2, p3, _ in kitti):
    found = sorted(k for k in entries if re.fullmatch(r"P(_rect_0)?\d", k))
    raise UsageError(f"{path}: no KITTI matrices of cameras {cameras[0]},{cameras[1]} "
                     f"({kitti[0][0]}/{kitti[0][1]} or {kitti[1][0]}/{kitti[1][1]}); the file "
                     f"has {', '.join(found) or 'none'}")
  for p2, p3, s2 in kitti:
    if len(entries.get(p2) or ()) == 12 and len(entries.get(p3) or ()) == 12:
      rect_size = entries.get(s2) or ()  # KITTI raw: S_rect_02 = W H
      if not size and len(rect_size) == 2:
        size = {"width": rect_size[0], "height": rect_size[1]}
      m2, m3 = np.reshape(entries[p2], (3, 4)), np.reshape(entries[p3], (3, 4))
      if m2[0, 3] < m3[0, 3]:  # P[0,3] = -fx * (the camera's x): the left one has the larger
        log.warning("%s: %s is to the right of %s (%s[0,3] %g < %s[0,3] %g): the matrices "
                    "look swapped; the disparities are the left view's (--left), so check "
                    "that --left is %s's camera", path, p2, p3, p2, m2[0, 3], p3, m3[0, 3], p2)
      with np.errstate(divide="ignore", invalid="ignore"):  # fx 0: refused by its checks
        baseline = abs(m2[0, 3] - m3[0, 3]) / m2[0, 0]  # (NumPy's warning came first)
      return {"fx": m2[0, 0], "fy": m2[1, 1], "cx": m2[0, 2], "cy": m2[1, 2],
              "baseline": baseline, "doffs": m3[0, 2] - m2[0, 2], **size}
  out = {k: entries[k][0] for k in _CALIB_KEYS if k in entries}
  if len(entries.get("cam0") or ()) == 9 and "fx" not in out:  # Middlebury
    k0 = np.reshape(entries["cam0"], (3, 3))
    out.update(fx=k0[0, 0], fy=k0[1, 1], cx=k0[0, 2], cy=k0[1, 2])
    if "doffs" not in out:
      if len(entries.get("cam1") or ()) != 9:
        raise UsageError(f"{path}: a Middlebury calibration (cam0) needs doffs or cam1: "
                         "depth = fx * baseline / (disparity + doffs)")
      out["doffs"] = entries["cam1"][2] - k0[0, 2]
  if not out:
    raise UsageError(f"{path}: no calibration found (expected JSON, 'fx 720' lines, KITTI "
                     "P_rect_02/P_rect_03 (or 00/01) matrices, P2/P3 (or P0/P1) or a Middlebury "
                     "calib.txt)")
  return {**out, **size}


def load_checkpoint(path, dtype: str | None = None):
  """Loads model weights from an orbax directory or an official state-dict file.

  Args:
    path: `sav-jax convert` orbax directory, a training run's workdir or checkpoint step
      folder (its params), or a .pth/.pt/.safetensors/.npz Stereo Any Video state dict
      (converted on the fly; no torch needed).
    dtype: compute dtype override ("float32" / "bfloat16").

  Returns:
    `(variables, cfg, description)`.

  Raises:
    FileNotFoundError: no such path.
    CheckpointError (a ValueError): not a checkpoint, or not one of this model.
  """
  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax import convert, inference  # pylint: disable=import-outside-toplevel
  path = pathlib.Path(path)
  if not path.exists():
    raise FileNotFoundError(f"checkpoint not found: {path}")
  if path.is_dir():  # (a path that is not UTF-8: refused by restore_variables, for orbax)
    variables, cfg_dict = convert.restore_variables(path)
    cfg = this_machines_settings(config_from_dict(cfg_dict, path), path)
    inference.check_variables(variables, cfg, path)  # NaN or inf weights too
    step = None if convert.is_variables_checkpoint(path) else convert.find_training_checkpoint(path)
    described = (f"orbax checkpoint {path}" if step is None
                 else f"training checkpoint {step} (params)")
    for notes in (convert.random_prior_note, convert.untrained_note):
      note = notes(cfg_dict, str(path if step is None else step))
      if note:
        log.warning("%s", note)
  else:
    sd = convert.load_state_dict_of_kind(
        path, "sav", {"vda": "`sav-jax convert --vda` turns it into an initialisation for "
                             "training"})
    cfg = sav_jax.SAVConfig(vda_encoder=convert.params.vda_encoder_of(sd) or "vits")
    try:
      variables = convert.params_from_state_dict(sd, cfg)
    except ValueError as e:  # one line for the command line; the full list in the debug log
      log.debug("%s", e)
      raise convert.CheckpointError(
          f"{path}: incompatible checkpoint: {convert.keys.one_line(e)}") from e
    del sd
    described = f"state dict {path} (converted on the fly)"
  runtime.release_host_memory()  # the reader's and converter's temporaries
  return variables, inference.resolve_config(cfg, dtype), described


def this_machines_settings(cfg, path):
  """`cfg` with the settings of how the model computes, other than its dtype, at their
  defaults (`sav_jax.model.init.MACHINE_FIELDS`): a checkpoint stores those of the machine it
  was trained or saved on (cuDNN's ViT attention, which runs on NVIDIA GPUs only; the GRU's
  convolutions; remat; a frame block budget), not what suits this one ("auto" picks)."""
  import dataclasses  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax.model.init import MACHINE_FIELDS  # pylint: disable=import-outside-toplevel
  defaults = sav_jax.SAVConfig()
  stored = {f: getattr(cfg, f) for f in MACHINE_FIELDS if getattr(cfg, f) != getattr(defaults, f)}
  noted = {k: v for k, v in stored.items()  # (remat changes nothing in a forward pass)
           if k not in ("remat", "remat_policy")}
  if noted:
    log.info("%s: the stored %s (the saving machine's settings) replaced by this machine's "
             "defaults", path, ", ".join(f"{k}={v!r}" for k, v in noted.items()))
  return dataclasses.replace(cfg, **{f: getattr(defaults, f) for f in stored})


def config_from_dict(cfg_dict, path):
  """The `SAVConfig` a checkpoint at `path` stores (`{"model": {...}}` or the fields
  themselves; unknown fields ignored with a warning naming them, none: the default with a
  warning).

  Raises:
    CheckpointError: the stored config is not a mapping of valid SAVConfig fields.
  """
  import dataclasses  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  if cfg_dict is None:
    cfg_dict = {}
  d = cfg_dict.get("model", cfg_dict) if isinstance(cfg_dict, dict) else cfg_dict
  if not isinstance(d, dict):
    raise sav_jax.convert.CheckpointError(
        f"{path}: invalid model config: the stored config's model is a {type(d).__name__}, "
        "not a mapping of SAVConfig fields")
  names = {f.name for f in dataclasses.fields(sav_jax.SAVConfig)}
  known = {k: v for k, v in d.items() if k in names}
  if known.get("remat_policy") is not None and not known.get("remat"):
    # Stored before SAVConfig refused the pair; without remat the policy never did anything.
    known.pop("remat_policy")
  unknown = sorted(str(k) for k in d if k not in names)
  if unknown:  # a typo (dtpye) or another version's field: never silently
    log.warning("%s: the stored model config has fields SAVConfig does not know, ignored: %s",
                path, ", ".join(unknown[:10]) + (" ..." if len(unknown) > 10 else ""))
  if not known:
    log.warning("%s: no model config stored%s; using the default SAVConfig", path,
                " (no SAVConfig field in it)" if unknown else "")
  try:
    return sav_jax.SAVConfig.from_dict(known)
  except (TypeError, ValueError) as e:
    raise sav_jax.convert.CheckpointError(f"{path}: invalid model config ({e})") from e


def random_variables(cfg=None, seed: int = 0) -> dict:
  """Untrained weights drawn with numpy from `seed` (no compilation).

  Kernels `N(0, 1) * 0.8 / sqrt(fan_in)`, norm scales and LayerScale `1 + 0.1 N`,
  everything else `0.02 N`, one generator per parameter path.
  """
  import zlib  # pylint: disable=import-outside-toplevel

  import jax  # pylint: disable=import-outside-toplevel

  from sav_jax import convert  # pylint: disable=import-outside-toplevel
  from sav_jax.config import SAVConfig  # pylint: disable=import-outside-toplevel
  abstract = convert.params.abstract_variables(SAVConfig() if cfg is None else cfg)["params"]

  def draw(path, leaf):
    name = jax.tree_util.keystr(path)
    rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
    x = rng.standard_normal(leaf.shape).astype(np.float32)
    last = str(getattr(path[-1], "key", path[-1]))
    if last == "kernel":
      return x * np.float32(0.8 / np.sqrt(max(1, int(np.prod(leaf.shape[:-1])))))
    if last in ("scale", "gamma"):
      return 1 + np.float32(0.1) * x
    return np.float32(0.02) * x

  return {"params": jax.tree_util.tree_map_with_path(draw, abstract)}

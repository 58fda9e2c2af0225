"""Training input throughput: how many clips per second the data pipeline of `python -m train`
delivers, and how much CPU a clip costs (reading, augmenting), so that a run can be given
enough cores per accelerator.

    python benchmarks/input_pipeline.py                 # a FlyingThings3D-format set it writes
    python benchmarks/input_pipeline.py --num-threads 2 --worker-count 2
    python benchmarks/input_pipeline.py --root data/datasets --dataset sceneflow   # real data
    python benchmarks/input_pipeline.py --json benchmarks/results/input_cpu.json

Without `--root` it writes `--sequences` sequences of `--sequence-frames` frames in the
FlyingThings3D layout (`frames_finalpass/TRAIN/A/NNNN/{left,right}/*.png`, `disparity/.../*.pfm`)
at SceneFlow's 540x960 into a temporary folder (removed afterwards), with the procedural
generator's textured layers as content (PNG files of about the size of SceneFlow's).

It reports, one thread: the time to read a clip (`sequence.gather`: decoding its 2T images and
T disparities) and to augment it (`configs/sceneflow.py`'s augmentation at `--crop`); then the
stream of `train.input.train_dataset` (the training config with these settings: shuffling,
reading threads, `--worker-count` processes, batching) in clips/s after `--warmup` batches,
and (threads only) its CPU seconds per clip. The files were just written, so reading is
decoding from the page cache: data on a cold disk or a network file system reads slower.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import statistics
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402  pylint: disable=wrong-import-position
import numpy as np  # noqa: E402  pylint: disable=wrong-import-position

from configs import sceneflow  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.data import frame_io, pipeline  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.data.synthetic import SyntheticConfig, generate_clip  # noqa: E402  pylint: disable=wrong-import-position
from sav_jax.tools.bench import json_output_problem, peak_rss_gb  # noqa: E402  pylint: disable=wrong-import-position
from train import input as input_lib  # noqa: E402  pylint: disable=wrong-import-position

SCENEFLOW_SIZE = (540, 960)


def write_flyingthings(root: pathlib.Path, sequences: int, frames: int,
                       size: tuple[int, int] = SCENEFLOW_SIZE) -> int:
  """`sequences` FlyingThings3D-layout sequences of `frames` frames under `root`; returns
  the bytes written."""
  h, w = size
  written = 0
  for s in range(sequences):
    clip = generate_clip(SyntheticConfig(frames=frames, height=h, width=w, seed=s), index=0)
    rel = pathlib.Path("TRAIN", "A", f"{s:04d}")
    for side in ("left", "right"):
      img_dir = root / "FlyingThings3D" / "frames_finalpass" / rel / side
      gt_dir = root / "FlyingThings3D" / "disparity" / rel / side
      img_dir.mkdir(parents=True)
      gt_dir.mkdir(parents=True)
      for t in range(frames):
        name = f"{6 + t:04d}"
        path = img_dir / f"{name}.png"
        if not cv2.imwrite(str(path), cv2.cvtColor(clip[side][t], cv2.COLOR_RGB2BGR)):
          raise OSError(f"could not write {path}")
        # The right view's disparity is not read for training; the reader wants the file.
        disp = np.where(clip["valid"][t], clip["disparity"][t], 0).astype(np.float32)
        frame_io.write_pfm(gt_dir / f"{name}.pfm", disp)
        written += path.stat().st_size + (gt_dir / f"{name}.pfm").stat().st_size
  return written


def training_config(a, root: str, dataset: str):
  config = sceneflow.get_config()
  config.data.root = root
  config.data.sources.sceneflow.dataset = dataset
  config.data.frames = a.frames
  config.data.crop = tuple(a.crop)
  config.data.num_threads = a.num_threads
  config.data.prefetch = a.prefetch
  config.data.worker_count = a.worker_count
  config.train.batch_size = a.batch
  return config


def per_clip(config, clips: int) -> dict:
  """Median read and augment seconds per clip, one thread, over `clips` training clips."""
  items = pipeline.registry_clips(config.data.sources.sceneflow.dataset, config.data.root,
                                  config.data.frames, seed=config.seed)
  augment = pipeline.Augment(tuple(config.data.crop), input_lib.augment_overrides(config))
  rng = np.random.default_rng(0)
  augment(items[0].sequence.gather(list(items[0].indices)), rng)  # PIL's HSV tables: once
  read_s, augment_s = [], []
  for i in range(min(clips, len(items))):
    sequence, indices = items[(i * 7919) % len(items)]
    t0 = time.perf_counter()
    clip = sequence.gather(list(indices))
    t1 = time.perf_counter()
    augment(clip, rng)
    t2 = time.perf_counter()
    read_s.append(t1 - t0)
    augment_s.append(t2 - t1)
  return dict(training_clips=len(items), read_s=statistics.median(read_s),
              augment_s=statistics.median(augment_s))


def cpu_s() -> float:
  """CPU seconds of this process and its ended children."""
  own = resource.getrusage(resource.RUSAGE_SELF)
  kids = resource.getrusage(resource.RUSAGE_CHILDREN)
  return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def stream(config, batches: int, warmup: int) -> dict:
  """Clips/s of the training stream over `batches` batches after `warmup` ones (the first
  starts the threads and workers; while it is awaited the others fill their buffers, which
  the warm-up batches drain, or a short measurement reads buffered clips as fast ones)."""
  w0 = time.perf_counter()
  it = iter(input_lib.train_dataset(config, process_index=0, process_count=1))
  next(it)
  first_s = time.perf_counter() - w0
  for _ in range(warmup - 1):
    next(it)
  c1, w1 = cpu_s(), time.perf_counter()
  for _ in range(batches):
    batch = next(it)
  wall = time.perf_counter() - w1
  cpu = cpu_s() - c1
  if hasattr(it, "close"):  # stop the threads and workers before the data is deleted
    it.close()
  clips = batches * config.train.batch_size
  if batch["left"].shape[:2] != (config.train.batch_size, config.data.frames):
    raise RuntimeError(f"the stream gave a batch of {batch['left'].shape}")
  # Worker processes' CPU time is not this process's (nor counted before they end).
  return dict(first_batch_s=first_s, clips_per_s=clips / wall, wall_s=wall,
              cpu_s_per_clip=None if config.data.worker_count else cpu / clips)


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--root", help="datasets root holding real data (default: write a "
                 "FlyingThings3D-format set into a temporary folder)")
  p.add_argument("--dataset", default="flyingthings3d",
                 help="registry dataset with training clips (with --root)")
  p.add_argument("--sequences", type=int, default=4, help="sequences written (no --root)")
  p.add_argument("--sequence-frames", type=int, default=10,
                 help="frames per written sequence (FlyingThings3D has 10)")
  p.add_argument("--frames", type=int, default=5, help="frames per clip, T")
  p.add_argument("--crop", type=int, nargs=2, default=(256, 512), metavar=("H", "W"))
  p.add_argument("--batch", type=int, default=8, help="clips per batch")
  p.add_argument("--warmup", type=int, default=2, help="batches read before timing")
  p.add_argument("--batches", type=int, default=6, help="batches timed after --warmup")
  p.add_argument("--clips", type=int, default=8, help="clips timed one by one")
  p.add_argument("--num-threads", type=int, default=8, help="config.data.num_threads")
  p.add_argument("--prefetch", type=int, default=16, help="config.data.prefetch")
  p.add_argument("--worker-count", type=int, default=0, help="config.data.worker_count")
  p.add_argument("--step-samples-per-s", type=float, default=3.0,
                 help="an accelerator's training rate to size the cores for (default: the "
                      "H200's at the paper's shape, benchmarks/README.md)")
  p.add_argument("--json", help="write the results to this JSON file (a new file, or "
                 "--overwrite)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
  a = p.parse_args()
  problem = json_output_problem(a.json, a.overwrite) if a.json else None
  if problem:
    p.error(problem)
  for flag in ("sequences", "sequence_frames", "frames", "batch", "warmup", "batches", "clips",
               "num_threads", "prefetch"):
    if getattr(a, flag) < 1:
      p.error(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(a, flag)}")
  if a.worker_count < 0:
    p.error(f"--worker-count must be >= 0, got {a.worker_count}")
  if min(a.crop) < 1:
    p.error(f"--crop must be positive, got {a.crop}")
  if a.root is None and a.frames > a.sequence_frames:
    p.error(f"--frames {a.frames} is more than --sequence-frames {a.sequence_frames}")
  if a.root is not None:  # a wrong root, dataset or split: one line, not a traceback
    try:
      pipeline.registry_clips(a.dataset, a.root, a.frames,
                              seed=training_config(a, a.root, a.dataset).seed)
    except (FileNotFoundError, ValueError) as e:
      p.error(str(e))

  with tempfile.TemporaryDirectory(prefix="sav_input_") as tmp:
    data = dict(root=a.root, dataset=a.dataset)
    if a.root is None:
      t0 = time.perf_counter()
      nbytes = write_flyingthings(pathlib.Path(tmp), a.sequences, a.sequence_frames,
                                  SCENEFLOW_SIZE)
      data = dict(root=tmp, dataset="flyingthings3d", written_gb=nbytes / 1e9,
                  write_s=time.perf_counter() - t0,
                  written=f"{a.sequences} x {a.sequence_frames} frames at "
                          f"{SCENEFLOW_SIZE[0]}x{SCENEFLOW_SIZE[1]}")
    config = training_config(a, data["root"], data["dataset"])
    res = dict(frames=a.frames, crop=list(a.crop), batch=a.batch,
               num_threads=a.num_threads, prefetch=a.prefetch, worker_count=a.worker_count,
               **per_clip(config, a.clips), **stream(config, a.batches, a.warmup))
  res.update(data_root=a.root, dataset=data["dataset"],
             **{k: data[k] for k in ("written", "written_gb") if k in data})
  clip_s = res["read_s"] + res["augment_s"]
  # Cores to feed one accelerator: from the one-thread cost, and from the stream's own
  # (threads only: it adds shuffling, batching and the threads' contention).
  stream_s = res["cpu_s_per_clip"]
  res.update(clip_cpu_s=clip_s, cores_per_accelerator=clip_s * a.step_samples_per_s,
             cores_per_accelerator_stream=(None if stream_s is None
                                           else stream_s * a.step_samples_per_s),
             step_samples_per_s=a.step_samples_per_s, peak_rss_gb=peak_rss_gb(),
             cpu_count=(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                        else os.cpu_count()),
             date=time.strftime("%Y-%m-%d"))

  print(f"data: {res['dataset']}" + (f", written: {res['written']} "
                                     f"({res['written_gb']:.2f} GB)" if a.root is None else
                                     f" under {a.root}") + f", {res['training_clips']} clips")
  print(f"one clip (T={a.frames}, crop {a.crop[0]}x{a.crop[1]}), one thread: read "
        f"{res['read_s']:.3f} s + augment {res['augment_s']:.3f} s = {clip_s:.3f} s")
  print(f"stream (batch {a.batch}, {a.num_threads} threads, {a.worker_count} workers, "
        f"{res['cpu_count']} cores): {res['clips_per_s']:.2f} clips/s over {a.batches} "
        f"batches after {a.warmup} (first batch {res['first_batch_s']:.1f} s)"
        + ("" if res["cpu_s_per_clip"] is None else
           f", {res['cpu_s_per_clip']:.3f} CPU s per clip"))
  stream_cores = ("" if stream_s is None else
                  f" ({res['cores_per_accelerator_stream']:.1f} at the stream's CPU per clip)")
  print(f"to feed {a.step_samples_per_s:g} clips/s per accelerator: ~"
        f"{res['cores_per_accelerator']:.1f} cores each{stream_cores}; peak RSS "
        f"{res['peak_rss_gb']:.2f} GB")
  if a.json:
    with open(a.json, "w") as f:
      json.dump(res, f, indent=2)
    print(f"wrote {a.json}")


if __name__ == "__main__":
  main()

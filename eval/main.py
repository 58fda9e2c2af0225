"""Command line of the evaluation program (`python -m eval`).

    python -m eval --config configs/eval/<dataset>.py --checkpoint CKPT \\
        --data-root data/datasets [--out DIR] [--baseline sgbm] [--overwrite | --resume] \\
        [--compile-cache DIR | --no-compile-cache] [--config.iters=20 --config.max_sequences=2 ...]

Writes to --out (default `outputs/eval/<dataset>`): `results.md` (the official evaluator's
metrics), `results.json` (config, weights, per-sequence and aggregate metrics), `results.csv`,
`plots/<sequence>_curves.png` (per-frame EPE and TEPE; sequences with ground truth) and
`plots/<sequence>_strip.png`
(colourized disparity), and with `--config.save_predictions=true`
`predictions/<sequence>.npy` (`<sequence>_sgbm.npy` for `--baseline sgbm`); `written_files.txt`
lists the prediction and plot files written. `--overwrite` sets those files and the earlier
reports aside in `.earlier_run/` while the new run goes, deletes them once it has written its
reports and puts them back if it fails (nothing else in the folder is touched).
While it runs, `progress.jsonl` records each finished sequence: `--resume` continues an
interrupted run (a frame that could not be read, a stop) without evaluating those again, if
its settings are the same. Bad input exits with status 2 and one line on stderr.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from eval import config as eval_config
from eval import report
from sav_jax import _signals, runtime
from sav_jax._checks import is_int, plural, sav_jax_configs
from sav_jax.config import DTYPES
# The evaluation's own modules (`eval.runner`, `sav_jax.inference`) import JAX: they are
# imported once the arguments and the config are checked, so `--help` and a bad config or
# override are answered at once.
from sav_jax.tools import (UsageError, add_compile_cache_arguments, check_output_dir,
                           command_logging, empty_path_problem, one_line_warnings,
                           printable_names, resolve_devices_option, setup_compile_cache,
                           user_path)


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(
      prog="python -m eval", description="Evaluate Stereo Any Video with the official protocol; "
      "override config fields with --config.<field>=<value>.",
      epilog=eval_config.fields_help(), allow_abbrev=False)  # (--over was --overwrite)
  p.add_argument("--config", required=True, type=user_path,
                 help="config file, e.g. configs/eval/sintel_final.py (optionally path.py:arg)")
  p.add_argument("--checkpoint", required=True, type=user_path,
                 help="orbax directory, a training run's WORKDIR (latest checkpoint) or "
                      "WORKDIR/checkpoints/STEP, or a .pth/.pt/.safetensors/.npz state dict")
  p.add_argument("--data-root", type=user_path,  # (None: DEFAULT_DATA_ROOT, see run)
                 help="datasets folder or the dataset's own folder (default data/datasets)")
  p.add_argument("--out", type=user_path, help="output folder (default outputs/eval/<dataset>)")
  p.add_argument("--baseline", action="append", choices=eval_config.BASELINES, default=[],
                 help="add a baseline row computed on the same frames (repeatable)")
  again = p.add_mutually_exclusive_group()
  again.add_argument("--overwrite", action="store_true", help="replace existing results")
  again.add_argument("--resume", action="store_true",
                     help="continue an interrupted run in --out with the same settings: its "
                          "finished sequences are not evaluated again")
  add_compile_cache_arguments(p)
  p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
  return p


def main(argv: list[str] | None = None) -> int:
  """`python -m eval` (argv None: sys.argv); from Python with `argv`, Ctrl-C propagates."""
  command_line = argv is None
  argv = sys.argv[1:] if argv is None else list(argv)
  try:
    rest, overrides = eval_config.split_overrides(argv)
    sav_jax_configs("eval")  # (the parser's help lists its fields)
    args = build_parser().parse_args(rest)
  except ValueError as e:
    print(f"eval: error: {e}", file=sys.stderr)
    return 2
  except KeyboardInterrupt:  # Ctrl-C while the arguments are read: one line, as below
    if not command_line:
      raise
    _signals.exit_interrupted("eval: interrupted")
  try:
    # (printable_names: a sequence or folder name that is not UTF-8 is printed as \udce9, as
    # results.md and results.csv show it)
    with (command_logging(args.verbose), printable_names(), one_line_warnings("eval"),
          _signals.remembered_interrupts()):
      return run(args, overrides)
  except (ValueError, OSError, UsageError) as e:  # OSError: a file that cannot be read or written
    text = str(e)
    if hasattr(e, "need"):  # inference's memory check: the remedies as config fields
      fewer = "fewer --config.devices, " if getattr(e, "devices", None) else ""
      text = (f"{e.need}; use {fewer}fewer frames per window (--config.window, "
              "--config.stride), fewer --config.iters or --config.dtype=bfloat16")
    print(f"eval: error: {text}", file=sys.stderr)
    return 2
  except MemoryError as e:  # numpy's: sizes far beyond this machine's memory
    print(f"eval: error: out of host memory: {e}", file=sys.stderr)
    return 2
  except Exception as e:  # pylint: disable=broad-except  # XLA's, compiling or running
    oom = runtime.out_of_memory(e)
    if oom is None:
      raise
    print(f"eval: error: out of memory on the device: {oom}; use fewer frames per window "
          "(--config.window, --config.stride), fewer --config.iters or --config.dtype=bfloat16; "
          + ("the earlier results in the output folder are kept" if args.overwrite else
             "the sequences it finished are recorded: --resume continues"), file=sys.stderr)
    return 2
  except KeyboardInterrupt:  # Ctrl-C at the command line: one line (the run can be resumed)
    if not command_line:
      raise
    from sav_jax._signals import exit_interrupted  # pylint: disable=import-outside-toplevel
    exit_interrupted("eval: interrupted; " + (
        "the earlier results in the output folder were put back" if args.overwrite else
        "the sequences it finished are recorded: run the same command with --resume to "
        "continue"))


# --data-root where none is given.
DEFAULT_DATA_ROOT = "data/datasets"


def run(args, overrides) -> int:
  """Loads config, data and weights, evaluates every sequence, writes the reports."""
  empty = empty_path_problem(args, ("out", "data_root", "compile_cache"))
  if empty:  # (the default folder, or "." for the data)
    raise UsageError(empty)
  config = eval_config.load_config(args.config)
  eval_config.check_fields(config, args.config)
  config = eval_config.apply_overrides(config, overrides)
  if not (is_int(config.iters) and config.iters >= 2):
    raise ValueError(f"config.iters must be an integer >= 2, got {config.iters!r}")
  for field in ("sample_len", "max_sequences"):  # a config file may set None
    if not is_int(config[field]):
      raise ValueError(f"config.{field} must be an integer (<= 0: all), got {config[field]!r}")
  if config.dtype not in DTYPES:  # before the checkpoint is read
    raise ValueError(f"config.dtype must be one of {DTYPES}, got {config.dtype!r}")
  if config.matmul_precision not in runtime.MATMUL_PRECISIONS:
    raise ValueError(f"config.matmul_precision must be one of {runtime.MATMUL_PRECISIONS}, got "
                     f"{config.matmul_precision!r}")
  if not (is_int(config.metrics.raft_iters) and config.metrics.raft_iters >= 1):
    raise ValueError(f"config.metrics.raft_iters must be a positive integer, got "
                     f"{config.metrics.raft_iters!r}")
  if not args.checkpoint.strip():
    raise UsageError("--checkpoint is empty: name the weights (an orbax directory, a training "
                     "run's WORKDIR or a .pth/.safetensors/.npz file)")
  for field, low in (("strip_frames", 1), ("tile_size", 16)):
    value = config.plots[field]
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= low):
      raise ValueError(f"config.plots.{field} must be an integer >= {low}, got {value!r}")
  if args.baseline:  # checked before any prediction (OpenCV accepts any block size)
    from sav_jax.tools.demo import check_sgbm_args  # pylint: disable=import-outside-toplevel
    check_sgbm_args(config.baseline.max_disparity, config.baseline.block_size,
                    "config.baseline.")
  if args.data_root is None:
    args.data_root = DEFAULT_DATA_ROOT
    from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
    if config.dataset in registry.DATASETS and not os.path.isdir(DEFAULT_DATA_ROOT):
      mine = (f"the folder that holds your videos' {config.split}/" if config.dataset == "folder"
              else "the datasets folder or the dataset's own")
      raise UsageError(f"no --data-root given, and its default {DEFAULT_DATA_ROOT}/ is not a "
                       f"folder here: pass --data-root DIR, {mine}")
  from eval import runner  # pylint: disable=import-outside-toplevel
  out = check_output_dir(args.out or f"outputs/eval/{config.dataset}")
  _refuse_out_in_dataset(out, config.dataset, args.data_root)
  with runner.output_lock(out):
    return _run_into(args, config, out)


def _refuse_out_in_dataset(out, dataset: str, data_root) -> None:
  """An output folder inside the dataset's folder would be read as one of its sequences."""
  from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
  if dataset not in registry.DATASETS:  # the synthetic set (or an unknown name: said later)
    return
  where = out.expanduser().resolve()
  for folder in registry.dataset_folders(dataset, data_root):
    if where.is_relative_to(folder.resolve()):
      raise UsageError(f"--out {out} is inside the dataset's folder {folder}: keep outputs "
                       "out of the dataset (where the reader looks, it would take them for "
                       "data); choose a folder outside it")


def _run_into(args, config, out) -> int:
  """`run` once it holds `out`'s lock."""
  from eval import data as eval_data  # pylint: disable=import-outside-toplevel
  from eval import runner  # pylint: disable=import-outside-toplevel
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  restored = runner.restore_set_aside(out)
  if restored:
    print(f"restored {len(restored)} prediction and plot files that an interrupted "
          f"--overwrite run had set aside in {out / runner.SET_ASIDE}")
  inference.check_window(config.window, config.stride)
  devices = resolve_devices_option(config.devices, "config.devices", takes_all=False)
  seqs, skipped = eval_data.load_sequences_and_skipped(config, args.data_root)
  depth_metrics = [f"metrics.{k}" for k in ("tcc", "raft") if config.metrics[k]]
  # The depth metrics measure the sequences with ground truth (the others, e.g. a folder
  # sequence without disparity/, get predictions and plots only): theirs need a scale.
  measured = [s for s in seqs if getattr(s, "has_gt", True)]
  if depth_metrics and not measured:
    raise ValueError(f"config.{' and config.'.join(depth_metrics)}: {config.dataset} has no "
                     "ground truth (a qualitative run: predictions and plots only), so there is "
                     f"nothing to measure: drop {' and '.join(depth_metrics)}")
  unscaled = [str(s.name) for s in measured if s.depth2disp_scale is None]
  if depth_metrics and unscaled:
    need = "needs" if len(depth_metrics) == 1 else "need"
    raise ValueError(f"config.{' and config.'.join(depth_metrics)} {need} depth, but "
                     f"{config.dataset} sequence {unscaled[0]} has no depth-to-disparity scale "
                     f"(no camera data; {len(unscaled)} of the {len(measured)} sequences with "
                     f"ground truth): drop {' and '.join(depth_metrics)}")
  short = [s for s in measured if len(s) < 2]
  if depth_metrics and short:
    raise ValueError(f"config.{' and config.'.join(depth_metrics)}: temporal consistency needs "
                     f"sequences of 2 frames or more, but {config.dataset} sequence "
                     f"{short[0].name} has {len(short[0])} ({len(short)} of the "
                     f"{len(measured)} sequences with ground truth)")
  earlier = [p for p in (*(out / r for r in runner.REPORTS),
                         out / runner.WRITTEN_LIST, out / runner.PROGRESS, out / "predictions",
                         out / "plots")
             if p.is_file() or (p.is_dir() and any(p.iterdir()))]
  if args.resume:  # without a progress file, only an empty folder starts afresh
    if not (out / runner.PROGRESS).is_file() and earlier:
      what = ("holds a finished evaluation" if (out / "results.json").is_file()
              else f"has no {runner.PROGRESS}")
      raise FileExistsError(f"nothing to resume: {out} {what} (found "
                            f"{', '.join(p.name for p in earlier)}); pass --overwrite to "
                            "replace it")
  elif earlier and not args.overwrite:  # also the predictions of an interrupted run
    interrupted = (out / runner.PROGRESS).is_file()
    raise FileExistsError(f"{', '.join(map(str, earlier))} exist; pass "
                          + ("--resume to continue that interrupted run, or " if interrupted
                             else "") + "--overwrite to replace them")
  setup_compile_cache(args)
  flow_fn = runner.raft_flow_fn(config)
  from sav_jax.tools.infer import load_checkpoint  # pylint: disable=import-outside-toplevel
  variables, model_cfg, described = load_checkpoint(args.checkpoint, dtype=config.dtype)
  methods = ["sav"] + [b for b in dict.fromkeys(args.baseline)]
  settings = runner.run_settings(config, variables, methods)
  done = (runner.read_progress(out, settings) or {}) if args.resume else {}
  for seq in seqs:
    earlier = done.get(str(seq.name))
    if earlier is None:
      continue
    if earlier.frames != len(seq):
      raise ValueError(f"cannot resume: sequence {seq.name} has {len(seq)} frames, the "
                       f"interrupted run evaluated {earlier.frames}; pass --overwrite to start "
                       "again")
    has_gt = getattr(seq, "has_gt", True)  # (a record with ground truth has metrics)
    if bool(earlier.metrics) != has_gt:  # e.g. a folder sequence's disparity/ added since
      raise ValueError(f"cannot resume: sequence {seq.name} has "
                       f"{'ground truth' if has_gt else 'no ground truth'} now, the interrupted "
                       f"run {'had none' if has_gt else 'measured it'}; pass --overwrite to "
                       "start again")
    source = runner.sequence_source(seq)  # the same dataset, not another copy of it
    if earlier.source is not None and source != earlier.source:
      raise ValueError(f"cannot resume: sequence {seq.name} is read from {source}, the "
                       f"interrupted run read it from {earlier.source}; run with the --data-root "
                       "it had, or pass --overwrite to start again")
  runner.refuse_unlisted_outputs(out, [
      p for s in seqs if str(s.name) not in done
      for p in runner.output_paths(out, s.name, methods, config,
                                   has_gt=getattr(s, "has_gt", True)).values()])
  run_args = (config, out, seqs, variables, model_cfg, described, methods, settings, done,
              devices, flow_fn, skipped)
  if not args.overwrite:
    return evaluate(*run_args, resumable=True)
  # The earlier run's files go aside, and come back if this run fails before its reports are
  # written (a frame that cannot be read, an interrupt): a failed run loses nothing. Once
  # they are, `evaluate` deletes them (`drop_set_aside`).
  try:
    moved = runner.set_aside_written(out)
    rc = evaluate(*run_args)
  except BaseException:
    runner.restore_set_aside(out)  # undoes nothing once `evaluate` has written the reports
    raise
  if moved:
    print(f"--overwrite: removed the earlier run's {len(moved)} prediction and plot files")
  return rc


def evaluate(config, out, seqs, variables, model_cfg, described, methods, settings, done,
             devices=None, flow_fn=None, skipped=(), resumable=False) -> int:
  """Evaluates every sequence (but those in `done`, a resumed run's finished ones), records
  each in the progress file, and writes the reports (which name the `skipped` sequences).
  With `resumable`, an error reading a sequence says that --resume continues the run."""
  from eval import runner  # pylint: disable=import-outside-toplevel
  on = f"; {len(devices)} {devices[0].platform} devices" if devices and len(devices) > 1 else ""
  print(f"{config.dataset}/{config.split}: {plural(len(seqs), 'sequence')}; "
        f"weights: {described}{on}")
  if done:
    print(f"--resume: {plural(len(done), 'sequence')} finished by the interrupted "
          f"run {'is' if len(done) == 1 else 'are'} not evaluated again")
  results = []
  for i, seq in enumerate(seqs):
    res = done.get(str(seq.name))
    if res is None:
      try:
        res = runner.evaluate_sequence(seq, methods, variables=variables, model_cfg=model_cfg,
                                       config=config, out=out, devices=devices, flow_fn=flow_fn)
      except (ValueError, OSError) as e:  # a frame that cannot be read, ...: say how to go on
        if not (results and resumable):
          raise
        raise ValueError(f"{e}; the {plural(len(results), 'sequence')} finished "
                         f"before it {'is' if len(results) == 1 else 'are'} recorded: fix it "
                         "and run the same command with --resume to continue") from e
      runner.append_progress(out, settings, res)
    results.append(res)
    line = "  ".join(f"{eval_config.METHOD_NAMES[m]}: EPE {r['disp_epe_mean']:.3f} TEPE "
                     f"{r['disp_temp_epe_mean']:.3f}" for m, r in res.metrics.items())
    again = "  (from the interrupted run)" if str(seq.name) in done else ""
    print(f"[{i + 1}/{len(seqs)}] {res.name} ({res.frames} frames)  {line}{again}")
  summary = build_summary(config, described, results, methods, settings.get("weights"),
                          skipped)
  paths = report.write_all(out, summary)
  runner.drop_set_aside(out)  # the commit point of an --overwrite run: nothing is undone after
  if not set(done) - {str(seq.name) for seq in seqs}:  # else kept: a later --resume over
    (out / runner.PROGRESS).unlink(missing_ok=True)   # more sequences reads those again
  print(report.markdown(summary).split("## Per sequence")[0].rstrip())
  print("wrote " + ", ".join(str(p) for p in paths))
  return 0


def build_summary(config, described: str, results: list, methods: list[str],
                  weights_digest: str | None = None, skipped=()) -> dict:
  """Everything `report` writes: config, weights (`described`, and `runner.weights_digest`
  of the parameters: the same weights from any path or format), sav-jax's version,
  per-sequence and aggregate metrics (with `measured_frames`, the frames of the sequences
  with ground truth: the aggregate's weight), and the `skipped` sequences' names."""
  import sav_jax  # pylint: disable=import-outside-toplevel
  from eval import runner  # pylint: disable=import-outside-toplevel
  frames = sum(r.frames for r in results)
  summary = {"dataset": config.dataset, "split": config.split, "config": config.to_dict(),
             "weights": described, "weights_digest": weights_digest,
             "sav_jax_version": sav_jax.__version__, "frames": frames,
             "metrics_seconds": sum(r.metrics_seconds for r in results),
             "created": time.strftime("%Y-%m-%d %H:%M:%S"), "methods": {}, "sequences": [],
             "skipped_sequences": list(skipped)}
  for m in methods:
    seconds = sum(r.seconds.get(m, 0.0) for r in results)
    summary["methods"][m] = {"name": eval_config.METHOD_NAMES[m],
                             "aggregate": runner.aggregate(results, m),
                             "measured_frames": sum(r.frames for r in results
                                                    if m in r.metrics),
                             "seconds": seconds,
                             "compile_seconds": sum(r.compile_seconds.get(m, 0.0)
                                                    for r in results),
                             "frames_per_second": frames / seconds if seconds > 0 else 0.0}
  for r in results:
    summary["sequences"].append({"name": r.name, "frames": r.frames, "source": r.source,
                                 "metrics": r.metrics, "seconds": r.seconds,
                                 "compile_seconds": r.compile_seconds,
                                 "metrics_seconds": r.metrics_seconds, "notes": r.notes})
  return summary

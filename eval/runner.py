"""Per-sequence inference and metrics (the official evaluator's steps).

For each sequence (already cut to its evaluated frames): predict every frame with
`sav_jax.inference.predict_video` (20-frame windows, stride 10, padding to /32,
`abs()`), optionally run StereoSGBM per frame, then `sav_jax.metrics.eval_sequence`
(prediction x round(valid), |GT|, EPE/TEPE with the non-zero-count denominators).
Aggregation over sequences is frame-weighted (`sav_jax.metrics.aggregate`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import pathlib
import re
import shutil
import time
import warnings

import jax
import numpy as np

from eval import data as eval_data
from eval import plots
from eval.config import BASELINES, METHOD_NAMES
from sav_jax import inference, metrics
from sav_jax import _locks
from sav_jax._checks import loads_json, plural
from sav_jax._files import write_text_atomic

log = logging.getLogger(__name__)


@dataclasses.dataclass
class SequenceResult:
  """Results of one sequence.

  Attributes:
    name: sequence name.
    frames: evaluated frames T (the aggregation weight).
    metrics: method -> metric dict of `metrics.eval_sequence` (empty without GT).
    curves: method -> (per-frame EPE `[T]`, per-frame-pair TEPE `[T-1]`; NaN where a
      frame (pair) has no valid GT pixel).
    seconds: method -> wall time of its predictions, compilation excluded.
    compile_seconds: method -> time spent compiling the model for them (0 once the
      executables of this sequence's shapes exist).
    metrics_seconds: time spent computing every method's metrics (with RAFT's flows
      when the flow-based metrics are on).
    source: the folder its left frames were read from (`sequence_source`); None for the
      synthetic set.
    notes: what the reader of its numbers should know (`gt_notes`: no valid ground-truth
      pixel, one frame), also logged as warnings.
  """

  name: str
  frames: int
  metrics: dict = dataclasses.field(default_factory=dict)
  curves: dict = dataclasses.field(default_factory=dict)
  seconds: dict = dataclasses.field(default_factory=dict)
  compile_seconds: dict = dataclasses.field(default_factory=dict)
  metrics_seconds: float = 0.0
  source: str | None = None
  notes: list = dataclasses.field(default_factory=list)


def safe_name(name: str) -> str:
  """A file-name-safe version of a sequence name, one per name: a name that had to change
  (characters other than letters, digits and `._-`, or leading/trailing `_`) gets 8 hex
  digits of its hash, so that "alley 1" and "alley_1" do not write the same files; so does a
  name that ends as a baseline's prediction file (`_sgbm`: "walk_sgbm.npy" is "walk"'s)."""
  name = str(name)
  safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "sequence"
  if safe == name and not name.endswith(tuple(f"_{b}" for b in BASELINES)):
    return safe
  return f"{safe}-{hashlib.sha256(name.encode('utf-8', 'surrogatepass')).hexdigest()[:8]}"


def per_frame_errors(pred, gt, valid) -> tuple[np.ndarray, np.ndarray]:
  """Per-frame EPE `[T]` and TEPE `[T-1]`, each frame reduced with the official rule.

  The evaluator's pre-processing (x * round(m), |y|) is applied first; each frame's
  value is `sum(e_t) / max(count_nonzero(e_t), 1e-5)`. A frame (pair) without any valid GT
  pixel, which that rule scores 0, is NaN here: no measurement, not a perfect one.
  """
  m = np.asarray(valid, np.float32)
  epe, tepe = metrics.endpoint_error_maps(np.asarray(pred, np.float32) * np.round(m),
                                          np.abs(np.asarray(gt, np.float32)), m)

  def reduce(e, mask):
    pixels = int(np.prod(e.shape[1:]))  # (reshape's -1 cannot size an empty T-1 = 0)
    e, mask = e.reshape(len(e), pixels), mask.reshape(len(mask), pixels)
    value = e.sum(axis=1, dtype=np.float64) / np.maximum(np.count_nonzero(e, axis=1), 1e-5)
    return np.where(mask.any(axis=1), value, np.nan)

  has = metrics.valid_pixels(m)
  return reduce(epe, has), reduce(tepe, has[:-1] & has[1:])


def gt_notes(name: str, valid, metric_keys=()) -> list[str]:
  """Notes on a sequence whose official scores are not all measurements
  (`metrics.not_measured_note`: no valid ground-truth pixel, one frame, no pixel valid in two
  consecutive frames, or, with the depth metrics of `metric_keys`, frame pairs without a
  valid pixel in both); its frames still count in the frame-weighted aggregate, as in the
  official evaluator."""
  note = metrics.not_measured_note(valid, metric_keys)
  if note is None:
    return []
  frames = plural(len(valid), "frame") + (" counts" if len(valid) == 1 else " count")
  return [f"sequence {name}: {note}; its {frames} in the aggregate"]


def predict(method: str, clip: dict, *, variables, model_cfg, config,
            devices=None) -> np.ndarray:
  """`[T, H, W]` disparity of one method on a sequence's frames (SAV's windows on `devices`,
  see `inference.resolve_devices`)."""
  if method == "sav":
    with jax.default_matmul_precision(config.matmul_precision):
      return inference.predict_video(variables, clip["left"], clip["right"], cfg=model_cfg,
                                     iters=config.iters, window=config.window,
                                     stride=config.stride, progress=True, devices=devices)
  if method == "sgbm":
    from sav_jax.tools.demo import stereo_sgbm  # pylint: disable=import-outside-toplevel
    return stereo_sgbm(clip["left"], clip["right"], max_disparity=config.baseline.max_disparity,
                       block_size=config.baseline.block_size)
  raise ValueError(f"unknown method {method!r}; baselines: {', '.join(BASELINES)}")


def raft_flow_fn(config):
  """The `flow_fn` of `config.metrics.raft` (a RAFT checkpoint file), or None when unset.

  RAFT runs at `config.matmul_precision`, as the stereo model.

  Raises:
    ValueError: the file is missing, unreadable or not a RAFT checkpoint (named).
  """
  metrics_config = config.metrics
  path = metrics_config.raft
  if not path:
    return None
  if not isinstance(path, str):
    raise ValueError(f"config.metrics.raft must be a file path, got {path!r}")
  path = os.path.expanduser(path)  # (`~` the shell left after --config.metrics.raft=)
  if not pathlib.Path(path).is_file():
    raise ValueError(f"config.metrics.raft: {path} is not a file (the official RAFT checkpoint, "
                     "raft-things.pth)")
  if not isinstance(metrics_config.raft_iters, int) or metrics_config.raft_iters < 1:
    raise ValueError(f"config.metrics.raft_iters must be a positive integer, got "
                     f"{metrics_config.raft_iters!r}")
  from sav_jax.convert.raft import load_raft  # pylint: disable=import-outside-toplevel
  from sav_jax.model import raft  # pylint: disable=import-outside-toplevel
  try:
    variables = load_raft(path)
  except ValueError as e:
    raise ValueError(f"config.metrics.raft: {e}") from None
  flow = raft.raft_flow_fn(variables, iters=metrics_config.raft_iters)

  def flow_fn(img1, img2):
    with jax.default_matmul_precision(config.matmul_precision):
      return flow(img1, img2)

  return flow_fn


def sequence_source(seq) -> str | None:
  """The folder `seq`'s left frames are read from, resolved: the same files reached through
  another `--data-root` (the common parent or the dataset's own folder, a link) give the same
  folder, another copy of the dataset another one. None for a sequence without files (the
  synthetic set)."""
  files = getattr(seq, "files", None)
  if not files or not files.get("left"):
    return None
  return str(pathlib.Path(files["left"][0]).resolve().parent)


def evaluate_sequence(seq, methods, *, variables, model_cfg, config,
                      out: pathlib.Path | None = None, devices=None,
                      flow_fn=None) -> SequenceResult:
  """Predicts and scores one sequence; writes its predictions and plots under `out`.

  With `flow_fn` (RAFT, `raft_flow_fn`), the flow-based TCM, OPW and RTC are computed too;
  the left video's flows are computed once and shared by the methods.
  """
  clip = eval_data.read_sequence(seq)
  res = SequenceResult(name=str(seq.name), frames=len(clip["left"]),
                       source=sequence_source(seq))
  has_gt = clip["disparity"] is not None
  depth = config.metrics.tcc or flow_fn is not None
  if has_gt:
    keys = ("disp_TCC",) * depth + ("disp_TCM", "disp_OPW") * (flow_fn is not None)
    res.notes = gt_notes(res.name, clip["valid"], keys)
    for note in res.notes:
      log.warning(note)
  scale = seq.depth2disp_scale if depth else None
  video = flows = None
  if has_gt and flow_fn is not None:
    start = time.perf_counter()
    video = np.moveaxis(clip["left"], -1, 1)  # [T, 3, H, W], RGB 0..255
    flows = metrics.video_flows_from_fn(video, flow_fn)
    res.metrics_seconds += time.perf_counter() - start
  preds = {}
  for method in methods:
    start, compiled = time.perf_counter(), inference.compile_seconds()
    pred = predict(method, clip, variables=variables, model_cfg=model_cfg, config=config,
                   devices=devices)
    res.compile_seconds[method] = inference.compile_seconds() - compiled
    res.seconds[method] = time.perf_counter() - start - res.compile_seconds[method]
    preds[method] = pred
    if has_gt:
      start = time.perf_counter()
      try:
        with warnings.catch_warnings():  # res.notes (gt_notes) say it once per sequence
          warnings.simplefilter("ignore", metrics.NotMeasuredWarning)
          res.metrics[method] = metrics.eval_sequence(
              pred, clip["disparity"], clip["valid"].astype(np.float32), flows, scale=scale,
              video=video, flow_fn=flow_fn)
      except ValueError as e:  # e.g. a NaN prediction: name the sequence and the method
        raise ValueError(f"sequence {res.name}, {METHOD_NAMES[method]}: {e}") from None
      res.metrics_seconds += time.perf_counter() - start
      res.curves[method] = per_frame_errors(pred, clip["disparity"], clip["valid"])
  if out is not None:
    _write_sequence_outputs(out, res, clip, preds, config)
  return res


def _write_sequence_outputs(out: pathlib.Path, res: SequenceResult, clip: dict, preds: dict,
                            config) -> None:
  """Writes a sequence's predictions and plots, each listed in `written_files.txt` before it
  is written (a run killed while writing one leaves no file that --overwrite would miss)."""
  paths = output_paths(out, res.name, list(preds), config, has_gt=bool(res.curves))

  def listed(path: pathlib.Path) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    record_written(out, [path])
    return path

  if config.save_predictions:
    for method, pred in preds.items():
      np.save(listed(paths[method]), pred.astype(np.float32))
  if config.plots.enabled:
    labelled = {METHOD_NAMES[m]: p for m, p in preds.items()}
    plots.write_strip(listed(paths["strip"]), clip, labelled,
                      frames=config.plots.strip_frames, tile=config.plots.tile_size)
    if res.curves:
      curves = {METHOD_NAMES[m]: c for m, c in res.curves.items()}
      plots.write_curves(listed(paths["curves"]), curves, title=res.name)


def output_paths(out: pathlib.Path, sequence: str, methods, config,
                 has_gt: bool = True) -> dict[str, pathlib.Path]:
  """The files `_write_sequence_outputs` writes for a sequence: each method's prediction
  (by method name) and the plots ("strip", and "curves" where the sequence has ground truth),
  as the config asks for them."""
  name, paths = safe_name(sequence), {}
  if config.save_predictions:
    for method in methods:
      suffix = "" if method == "sav" else f"_{method}"
      paths[method] = out / "predictions" / f"{name}{suffix}.npy"
  if config.plots.enabled:
    paths["strip"] = out / "plots" / f"{name}_strip.png"
    if has_gt:
      paths["curves"] = out / "plots" / f"{name}_curves.png"
  return paths


def refuse_unlisted_outputs(out: pathlib.Path, paths) -> None:
  """Raises FileExistsError if a file this run would write exists and no evaluation listed it
  in `written_files.txt` (a user's file, or a link): --overwrite and --resume replace only
  files an evaluation wrote."""
  ours = set(_listed_files(out))
  theirs = [p for p in paths if (p.exists() or p.is_symlink()) and p not in ours]
  if theirs:
    raise FileExistsError(
        f"{theirs[0]} exists, and no earlier evaluation wrote it (it is not in "
        f"{out / WRITTEN_LIST}); this run would write over it: move it away or choose another "
        f"--out ({len(theirs)} such file(s))")


# The prediction and plot files an evaluation wrote into its --out folder, one relative path
# per line, appended as they are written (so an interrupted run's list is complete too).
# `--overwrite` sets exactly these aside as a new run starts (`set_aside_written`) and deletes
# them once it has written its reports: a run over fewer sequences leaves no stale files of
# the earlier one, and files the user put there are never touched.
WRITTEN_LIST = "written_files.txt"
_OUTPUT_FOLDERS = ("predictions", "plots")


def record_written(out: pathlib.Path, paths) -> None:
  """Appends `paths` (files under `out`) to `out/written_files.txt`."""
  if paths:
    listing = out / WRITTEN_LIST
    # a line cut short by a kill is ended first, so that the next path is a line of its own
    cut = False
    if listing.is_file() and listing.stat().st_size:
      with open(listing, "rb") as f:
        f.seek(-1, os.SEEK_END)
        cut = f.read(1) != b"\n"
    with open(listing, "a", encoding="utf-8") as f:
      f.writelines(["\n"] * bool(cut) + [f"{p.relative_to(out).as_posix()}\n" for p in paths])


def _listed_files(out: pathlib.Path) -> list[pathlib.Path]:
  """The files `out/written_files.txt` lists that exist: plain files directly in
  `out/predictions` or `out/plots` (a line naming anything else, e.g. `../x`, is ignored)."""
  listing = out / WRITTEN_LIST
  if not listing.is_file():
    return []
  files = []
  for line in listing.read_text(encoding="utf-8").splitlines():
    parts = pathlib.PurePosixPath(line.strip()).parts
    if len(parts) != 2 or parts[0] not in _OUTPUT_FOLDERS or parts[1] in ("", ".", ".."):
      continue
    path = out / parts[0] / parts[1]
    if path.is_file() and not path.is_symlink():
      files.append(path)
  return list(dict.fromkeys(files))  # a resumed run lists a redone sequence's files again


def remove_written(out: pathlib.Path) -> list[pathlib.Path]:
  """Deletes the files an earlier run listed in `out/written_files.txt`, and the list.

  Only plain files directly in `out/predictions` or `out/plots` are deleted. Returns the
  deleted paths.
  """
  removed = _listed_files(out)
  for path in removed:
    path.unlink()
  (out / WRITTEN_LIST).unlink(missing_ok=True)
  return removed


# One JSON line per finished sequence (after a header line naming the run's settings),
# appended and flushed as each sequence ends: `--resume` reuses them after a crash or a stop,
# and a run that finishes deletes the file once its reports are written.
PROGRESS = "progress.jsonl"
_PROGRESS_VERSION = 1
# Config fields that do not change any written number or file: a resumed run may differ in them.
_RESUME_FREE = ("devices", "max_sequences")


def weights_digest(variables) -> str:
  """A digest of the parameters (names, shapes, dtypes, values): the same weights give the
  same digest from any path or format, other weights at the same path another one."""
  digest = hashlib.blake2b(digest_size=16)
  named = jax.tree_util.tree_leaves_with_path(variables["params"])
  for (path, _), value in zip(named, jax.device_get([v for _, v in named])):
    value = np.ascontiguousarray(value)
    digest.update(f"{jax.tree_util.keystr(path)} {value.shape} {value.dtype}\n".encode())
    digest.update(value.view(np.uint8).reshape(-1))
  return digest.hexdigest()


def run_settings(config, variables, methods) -> dict:
  """What a resumed run must share with the interrupted one: the config (but `devices` and
  `max_sequences`), the weights (`weights_digest`) and the methods, as JSON would store
  them."""
  settings = {k: v for k, v in config.to_dict().items() if k not in _RESUME_FREE}
  return json.loads(json.dumps({"config": settings, "weights": weights_digest(variables),
                                "methods": list(methods)}))


def _differences(old, new, prefix="") -> list[str]:
  if isinstance(old, dict) and isinstance(new, dict):
    return [d for k in sorted(set(old) | set(new), key=str)
            for d in _differences(old.get(k), new.get(k), f"{prefix}{k}.")]
  if old == new:
    return []
  if prefix == "weights.":  # digests: say what they mean
    return ["the weights: other parameter values than the interrupted run's"]
  return [f"{prefix[:-1]}: {old!r} then, {new!r} now"]


def read_progress(out: pathlib.Path, settings: dict) -> dict[str, SequenceResult] | None:
  """The finished sequences that `out/progress.jsonl` records, by name; None without the file
  (or with no complete line in it: the run was killed before its first record).

  A last line cut short (the run was killed while writing it) is dropped from the file
  (rewritten whole, then renamed over it); blank lines are skipped.

  Raises:
    ValueError: the file was written with other settings (the differences are named), or
      a line of it is not what `append_progress` writes.
  """
  path = out / PROGRESS
  if not path.is_file():
    return None
  text = path.read_text(encoding="utf-8")
  if text and not text.endswith("\n"):  # killed mid-line: that sequence is done again
    text = text[:text.rfind("\n") + 1]
    write_text_atomic(path, text)
  lines = [(number, line) for number, line in enumerate(text.splitlines(), 1) if line.strip()]
  if not lines:
    path.unlink()
    return None
  restart = "; pass --overwrite to start again"
  try:
    header = loads_json(lines[0][1])
  except ValueError:
    header = None
  if not (isinstance(header, dict) and header.get("sav_jax_eval_progress") == _PROGRESS_VERSION):
    raise ValueError(f"{path} is not an evaluation progress file of this version{restart}")
  differences = _differences({k: header.get(k) for k in settings}, settings)
  if differences:
    raise ValueError(f"cannot resume: the interrupted run in {out} used other settings ("
                     f"{'; '.join(differences[:3])}{'; ...' if len(differences) > 3 else ''})"
                     "; run with those, or pass --overwrite to start again")
  done = {}
  for number, line in lines[1:]:
    try:
      rec = loads_json(line)
      res = SequenceResult(name=rec["name"], frames=rec["frames"], metrics=rec["metrics"],
                           seconds=rec["seconds"], compile_seconds=rec["compile_seconds"],
                           metrics_seconds=rec["metrics_seconds"],
                           source=rec.get("source"),  # (absent from older records)
                           notes=rec.get("notes", []))
      kinds = ((res.name, str), (res.frames, int), (res.metrics, dict), (res.seconds, dict),
               (res.compile_seconds, dict), (res.metrics_seconds, (int, float)),
               (res.source, (str, type(None))), (res.notes, list))
      if not all(isinstance(v, t) and not isinstance(v, bool) for v, t in kinds):
        raise TypeError("a field of another type")
    except (ValueError, KeyError, TypeError) as e:
      raise ValueError(f"{path}: line {number} is not a finished sequence's record ("
                       f"{type(e).__name__}: {e}){restart}") from None
    done[res.name] = res
  return done


def append_progress(out: pathlib.Path, settings: dict, res: SequenceResult) -> None:
  """Records a finished sequence in `out/progress.jsonl` (the header first if the file is
  new), flushed to disk before returning."""
  path = out / PROGRESS
  lines = [] if path.is_file() else [{"sav_jax_eval_progress": _PROGRESS_VERSION, **settings}]
  lines.append({"name": res.name, "frames": res.frames, "metrics": res.metrics,
                "seconds": res.seconds, "compile_seconds": res.compile_seconds,
                "metrics_seconds": res.metrics_seconds, "source": res.source,
                "notes": res.notes})
  with open(path, "a", encoding="utf-8") as f:
    f.writelines(json.dumps(line) + "\n" for line in lines)
    f.flush()
    os.fsync(f.fileno())


SET_ASIDE = ".earlier_run"
LOCK = ".eval.lock"


def output_lock(out: pathlib.Path):
  """Holds `out/.eval.lock` while an evaluation writes into `out` (`sav_jax._locks`).

  A second evaluation into the same folder is refused before it touches anything (its
  start would otherwise take the running one's set-aside files for an interrupted run's).
  A lock file that no process holds (its run was killed) is taken over. `out` is created if
  needed, and removed again (with the folders made for it) if the run leaves it empty.

  Raises:
    FileExistsError: another evaluation holds the lock.
  """
  return _locks.output_lock(out, LOCK, f"another evaluation ({{holder}}) is writing into "
                            f"{out}: wait for it or choose another --out")


REPORTS = ("results.json", "results.csv", "results.md")
_COMMITTED = ".earlier_run.done"
_REPORTS_NOTE = ".reports"


def set_aside_written(out: pathlib.Path) -> list[pathlib.Path]:
  """Moves the files an earlier run listed (the list, its progress file and its reports
  too) into `out/.earlier_run/`.

  `--overwrite` sets the earlier run's files aside instead of deleting them:
  `drop_set_aside` deletes them once the new run has written its reports, and
  `restore_set_aside` puts them back if it fails before. The list goes first, so that a stop
  midway leaves no list in `out` naming the earlier files not yet moved (the restore would
  delete them as the failed run's). Returns the moved prediction and plot files (their
  places before the move).
  """
  aside = out / SET_ASIDE
  moved = _listed_files(out)
  # Which reports the earlier run has, noted before any move: a restore after a stop midway
  # tells an earlier report not moved yet (kept) from the failed run's (deleted).
  aside.mkdir(exist_ok=True)
  (aside / _REPORTS_NOTE).write_text(
      "".join(f"{r}\n" for r in REPORTS if (out / r).is_file()), encoding="utf-8")
  for path in [out / WRITTEN_LIST, out / PROGRESS, *(out / r for r in REPORTS), *moved]:
    if path.is_file():
      target = aside / path.relative_to(out)
      target.parent.mkdir(parents=True, exist_ok=True)
      path.replace(target)
  return moved


def restore_set_aside(out: pathlib.Path) -> list[pathlib.Path]:
  """Undoes `set_aside_written` after a failed (or killed) run: deletes the files the
  failed run listed, its progress file and any reports of it, then moves the earlier run's
  files back. Returns the prediction and plot files. A run that had written its reports
  (`drop_set_aside` begun) is not undone: what it left aside is deleted."""
  if (out / _COMMITTED).is_dir():
    shutil.rmtree(out / _COMMITTED)
  aside = out / SET_ASIDE
  if not aside.is_dir():
    return []
  remove_written(out)
  (out / PROGRESS).unlink(missing_ok=True)  # the failed run's
  note = aside / _REPORTS_NOTE
  if note.is_file():  # without it nothing was moved, and the run never started
    earlier = note.read_text(encoding="utf-8").split()
    for name in REPORTS:  # the failed run's: a moved earlier one's place, or one it never had
      if (aside / name).is_file() or name not in earlier:
        (out / name).unlink(missing_ok=True)
    note.unlink()
  restored = []
  for path in sorted(p for p in aside.rglob("*") if p.is_file()):
    target = out / path.relative_to(aside)
    target.parent.mkdir(parents=True, exist_ok=True)
    path.replace(target)
    restored.append(target)
  shutil.rmtree(aside)
  return [p for p in restored if p.name not in (WRITTEN_LIST, PROGRESS, *REPORTS)]


def drop_set_aside(out: pathlib.Path) -> None:
  """Deletes `out/.earlier_run/` (made by `set_aside_written`), if there is one: the new run
  has written its reports. Renamed first (one atomic step: from then on a stop cannot bring
  the earlier run back), then deleted, with the `predictions/` or `plots/` folder it left
  empty (a new run without `save_predictions` writes none there)."""
  if not (out / SET_ASIDE).is_dir() and not (out / _COMMITTED).is_dir():
    return
  if (out / SET_ASIDE).is_dir():
    (out / SET_ASIDE).replace(out / _COMMITTED)
  shutil.rmtree(out / _COMMITTED)
  for name in _OUTPUT_FOLDERS:  # the earlier run's, emptied by the set-aside: not this run's
    try:
      (out / name).rmdir()
    except OSError:  # not empty (this run's files, or the user's), or not there
      pass


def aggregate(results: list[SequenceResult], method: str) -> dict[str, float]:
  """Frame-weighted mean of a method's metrics over the sequences that have them."""
  return metrics.aggregate([(r.metrics[method], r.frames) for r in results
                            if method in r.metrics])

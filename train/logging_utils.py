"""Scalars to JSONL and TensorBoard, and the progress bar (process 0 writes, others no-op)."""

from __future__ import annotations

import json
import logging
import math
import pathlib
import sys
import time

import jax

from sav_jax import runtime
from sav_jax._checks import loads_json
from sav_jax._files import write_text_atomic

log = logging.getLogger(__name__)


class MetricWriter:
  """Appends `{"step": s, "split": ..., **scalars}` lines to `workdir/metrics.jsonl` and
  writes the same scalars as `<split>/<name>` to TensorBoard event files in `workdir/tb`.

  TensorBoard needs `tensorboardX`; without it only the JSONL file is written.

  A run resumed at `start_step` re-runs the steps that a killed run logged after its last
  checkpoint: those JSONL records move to `metrics.superseded.jsonl` and TensorBoard
  purges its events after `start_step`, so each step is logged once (a run restarted
  before its first checkpoint moves every record: it validates at step 0 again).

  Args:
    workdir: run directory.
    enabled: False on processes other than 0.
    start_step: the step the run starts from (the restored checkpoint's).
  """

  def __init__(self, workdir, enabled: bool = True, start_step: int = 0):
    self.enabled = enabled
    self._tb = None
    self._jsonl = None
    if not enabled:
      return
    workdir = pathlib.Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    _supersede(workdir / "metrics.jsonl", workdir / "metrics.superseded.jsonl", start_step)
    self._logged = _logged_steps(workdir / "metrics.jsonl")
    self._jsonl = open(workdir / "metrics.jsonl", "a", encoding="utf-8")
    try:
      from tensorboardX import SummaryWriter  # pylint: disable=g-import-not-at-top
      # TensorBoard drops the earlier files' events at and after purge_step (all of them from
      # step 0). The suffix keeps the file names apart (tensorboardX names them by the second
      # and opens them with "wb": a second writer within the same second, a run restarted at
      # once, emptied the first one's file) and in their order.
      self._tb = SummaryWriter(str(workdir / "tb"),
                               purge_step=start_step + 1 if start_step > 0 else 0,
                               filename_suffix=f".{time.time_ns()}")
      # It warns once per NaN scalar written ("NaN or Inf found in input tensor."): a
      # diverged validation's are said once by the evaluator, skipped steps' by the loop.
      logging.getLogger("tensorboardX.x2num").setLevel(logging.ERROR)
    except ImportError:
      log.warning("tensorboardX is not installed: TensorBoard events are not written")

  def logged(self, step: int, split: str) -> bool:
    """Whether the log holds a `split` record of `step` (False off process 0)."""
    return self.enabled and (int(step), split) in self._logged

  def write(self, step: int, scalars: dict, split: str = "train") -> None:
    if not self.enabled:
      return
    self._logged.add((int(step), split))
    clean = {k: float(v) for k, v in scalars.items()}
    record = {"step": int(step), "split": split, "time": time.time()}
    record.update({k: (v if math.isfinite(v) else str(v)) for k, v in clean.items()})
    self._jsonl.write(json.dumps(record) + "\n")
    self._jsonl.flush()
    if self._tb is not None:
      for k, v in clean.items():
        self._tb.add_scalar(f"{split}/{k}", v, int(step))
      self._tb.flush()

  def close(self) -> None:
    if self._jsonl is not None:
      self._jsonl.close()
      self._jsonl = None
    if self._tb is not None:
      self._tb.close()
      self._tb = None


def _logged_steps(path: pathlib.Path) -> set[tuple[int, str]]:
  """The `(step, split)` pairs of the records of `path` (none without the file)."""
  if not path.is_file():
    return set()
  pairs = set()
  for line in path.read_text(encoding="utf-8").splitlines():
    try:
      record = loads_json(line)
      pairs.add((int(record["step"]), str(record["split"])))
    except (ValueError, KeyError, TypeError):
      continue
  return pairs


def _supersede(path: pathlib.Path, aside: pathlib.Path, start_step: int) -> None:
  """Moves the records of `path` with a step after `start_step`, and broken lines, to the
  end of `aside`; from step 0, every record (a run restarted before its first checkpoint
  writes its at-start validation at step 0 again)."""
  if not path.is_file():
    return
  last_kept = start_step if start_step > 0 else -1
  keep, later = [], []
  for line in path.read_text(encoding="utf-8").splitlines(keepends=True):
    try:
      step = int(loads_json(line)["step"])
    except (ValueError, KeyError, TypeError):
      step = None  # a line cut by the kill: moved aside too
    (keep if step is not None and step <= last_kept and line.endswith("\n")
     else later).append(line)
  if not later:
    return
  # Each with its newline (a line cut by a kill had none: the records that the next resumed
  # run moved aside were appended to it, one line that no longer parsed).
  with open(aside, "a", encoding="utf-8") as f:
    f.writelines(l if l.endswith("\n") else l + "\n" for l in later)
  write_text_atomic(path, "".join(keep))  # the log is never half-written
  log.info("moved %d log records after step %d to %s", len(later), start_step, aside)


class Progress:
  """tqdm bar over steps with step rate, loss and EPE (no-op off process 0, without tqdm, or
  where standard error is not a terminal or a Jupyter notebook: a log file, `nohup`, a batch
  job, where the bar's carriage-return updates pile up; the training records are log lines
  there)."""

  def __init__(self, start: int, total: int, enabled: bool = True, stream=None):
    self._bar = None
    stream = sys.stderr if stream is None else stream
    if enabled and runtime.draws_progress(stream) and jax.process_index() == 0:
      try:
        from tqdm import tqdm  # pylint: disable=g-import-not-at-top
        self._bar = tqdm(total=total, initial=start, unit="step", dynamic_ncols=True,
                         file=stream)
      except ImportError:
        pass

  @property
  def shown(self) -> bool:
    """Whether the bar is drawn (else the training records are log lines)."""
    return self._bar is not None

  def update(self, n: int = 1, **postfix) -> None:
    if self._bar is None:
      return
    self._bar.update(n)
    if postfix:
      self._bar.set_postfix({k: f"{v:.4g}" for k, v in postfix.items()}, refresh=False)

  def close(self) -> None:
    if self._bar is not None:
      self._bar.close()

"""The evaluation program end to end: the synthetic set and a tiny on-disk VKITTI2.

Both runs use 4-frame clips of 32x64 and iters=2, so the model compiles once. The
reported numbers are checked against `sav_jax.metrics` applied to the saved predictions.
"""

import csv
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import types

import cv2
import jax
import numpy as np
import pytest

import sav_jax
from eval import config as eval_config
from eval import data as eval_data
from eval import plots as eval_plots
from eval import report as eval_report
from eval import runner as eval_runner
from eval.main import main
from sav_jax import inference, metrics
from sav_jax.data import synthetic
from tests.official_metrics import epe_tepe_by_hand

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs" / "eval"
T, H, W = 4, 32, 64
SMALL = ["--config.iters=2", f"--config.synthetic.frames={T}", f"--config.synthetic.height={H}",
         f"--config.synthetic.width={W}", "--config.synthetic.num_sequences=2",
         "--config.synthetic.max_disparity=6", "--config.synthetic.num_objects=2",
         "--config.baseline.max_disparity=16", "--config.save_predictions=true"]


# No `fast_compile` here: the module's programs run dozens of times (every `main` call
# predicts two sequences), and XLA's optimised code runs them ~2.5x faster; the module took
# 220 CPU-seconds without it against 267 with it (2026-12-07).


@pytest.fixture(scope="module")
def variables(sav_state_dict):
  return sav_jax.convert.params_from_state_dict(sav_state_dict, sav_jax.SAVConfig())


@pytest.fixture(scope="module")
def ckpt(module_tmp_path, sav_state_dict):
  """The weights as the official release's layout in a .safetensors file: read in 0.5 s
  (converted as read) where `save_variables`' orbax folder takes 2.1-2.6 s, and most tests
  here run the command several times (tests/test_cli_infer.py and the training runs read
  orbax checkpoints)."""
  path = module_tmp_path / "ckpt" / "sav.safetensors"
  path.parent.mkdir()
  return sav_jax.convert.save_state_dict(sav_state_dict, path)


@pytest.fixture(scope="module")
def synthetic_run(module_tmp_path, variables):
  """A whole run on the weights as `save_variables` writes them (an orbax folder: what
  training and `sav-jax convert` give)."""
  ckpt = module_tmp_path / "orbax" / "sav"
  sav_jax.convert.save_variables(ckpt, variables, {"model": sav_jax.SAVConfig().to_dict()})
  out = module_tmp_path / "eval" / "synthetic"
  rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), "--out", str(out),
             "--baseline", "sgbm", "--config.metrics.tcc=true", *SMALL])
  assert rc == 0
  return out


def _check_against_metrics(out, seqs, methods, with_scale):
  summary = json.loads((out / "results.json").read_text())
  assert [s["name"] for s in summary["sequences"]] == [s.name for s in seqs]
  per_method = {m: [] for m in methods}
  for seq, rec in zip(seqs, summary["sequences"]):
    clip = eval_data.read_sequence(seq)
    assert rec["frames"] == len(clip["left"])
    for m in methods:
      suffix = "" if m == "sav" else f"_{m}"
      pred = np.load(out / "predictions" / f"{eval_data_safe(seq.name)}{suffix}.npy")
      ref = metrics.eval_sequence(pred, clip["disparity"], clip["valid"].astype(np.float32),
                                  scale=seq.depth2disp_scale if with_scale else None)
      assert rec["metrics"][m] == pytest.approx(ref, rel=1e-12, abs=1e-12)
      per_method[m].append((ref, rec["frames"]))
  for m in methods:
    agg = metrics.aggregate(per_method[m])
    assert summary["methods"][m]["aggregate"] == pytest.approx(agg, rel=1e-12, abs=1e-12)
  return summary


def eval_data_safe(name):
  from eval.runner import safe_name
  return safe_name(name)


def test_synthetic_outputs_and_metrics(synthetic_run, variables):
  out = synthetic_run
  for name in ("results.json", "results.csv", "results.md"):
    assert (out / name).is_file()
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  seqs = eval_data.load_sequences(config, None)
  summary = _check_against_metrics(out, seqs, ["sav", "sgbm"], with_scale=True)
  assert "disp_TCC" in summary["methods"]["sav"]["aggregate"]
  # provenance: the parameters' digest (the same weights from any path or format)
  assert summary["weights_digest"] == eval_runner.weights_digest(variables)
  assert summary["weights"] == f"orbax checkpoint {out.parent.parent / 'orbax' / 'sav'}"
  assert summary["sav_jax_version"] == sav_jax.__version__
  for seq in seqs:  # predictions are predict_video's, frame for frame
    clip = eval_data.read_sequence(seq)
    expected = inference.predict_video(variables, clip["left"], clip["right"], iters=2)
    np.testing.assert_array_equal(np.load(out / "predictions" / f"{seq.name}.npy"), expected)
    for kind in ("curves", "strip"):
      img = cv2.imread(str(out / "plots" / f"{seq.name}_{kind}.png"))
      assert img is not None and img.shape[0] > 100
  rows = list(csv.DictReader(open(out / "results.csv", encoding="utf-8")))
  assert len(rows) == 2 * 2 + 2
  assert float(rows[0]["disp_epe_mean"]) == summary["sequences"][0]["metrics"]["sav"][
      "disp_epe_mean"]
  md = (out / "results.md").read_text()
  assert "| Stereo Any Video |" in md and "| StereoSGBM |" in md and "δt-1px %" in md
  assert "lower is better, except TCC" in md  # TCC: higher is better


def test_refuses_to_overwrite(synthetic_run, ckpt, capsys):
  before = (synthetic_run / "results.json").read_text()
  rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt),
             "--out", str(synthetic_run), *SMALL])
  assert rc == 2 and "--overwrite" in capsys.readouterr().err
  assert (synthetic_run / "results.json").read_text() == before
  interrupted = synthetic_run.parent / "interrupted"  # predictions, no results yet
  (interrupted / "predictions").mkdir(parents=True)
  (interrupted / "predictions" / "seq.npy").write_bytes(b"keep")
  (synthetic_run.parent / "a_file").write_text("keep")
  notes = synthetic_run.parent / "notes"  # the user's own results.md
  notes.mkdir()
  (notes / "results.md").write_text("keep")
  for out, message in ((interrupted, "predictions exist; pass --overwrite"),
                       (synthetic_run.parent / "a_file", "is a file, not a folder"),
                       (notes, "results.md exist; pass --overwrite")):
    rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt),
               "--out", str(out), *SMALL])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and err.count("\n") == 1, err
  assert (interrupted / "predictions" / "seq.npy").read_bytes() == b"keep"
  assert (synthetic_run.parent / "a_file").read_text() == "keep"
  assert (notes / "results.md").read_text() == "keep"


def test_overwrite_removes_only_the_earlier_runs_files(tmp_path, ckpt, capsys):
  out = tmp_path / "run"
  args = ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), "--out", str(out),
          *SMALL]
  assert main(args) == 0
  first = sorted(p.name for p in (out / "predictions").iterdir())
  assert len(first) == 2  # two sequences
  (out / "plots" / "notes.txt").write_text("mine")  # the user's own files stay
  (out / "keep.txt").write_text("mine")
  (out / "written_files.txt").open("a").write("../keep.txt\nplots/../../keep.txt\n")
  capsys.readouterr()
  assert main([*args, "--config.synthetic.num_sequences=1", "--overwrite"]) == 0
  assert "removed the earlier run's" in capsys.readouterr().out
  assert sorted(p.name for p in (out / "predictions").iterdir()) == first[:1]
  assert sorted(p.name for p in (out / "plots").iterdir()) == [
      "notes.txt", f"{first[0][:-4]}_curves.png", f"{first[0][:-4]}_strip.png"]
  assert (out / "plots" / "notes.txt").read_text() == "mine"
  assert (out / "keep.txt").read_text() == "mine"
  assert (out / "written_files.txt").read_text().splitlines() == [
      f"predictions/{first[0]}", f"plots/{first[0][:-4]}_strip.png",
      f"plots/{first[0][:-4]}_curves.png"]
  # A file of the user's where this run would write (no evaluation listed it) is refused
  # before anything runs, with --overwrite and --resume alike, and kept.
  (out / "predictions" / first[1]).write_bytes(b"mine")
  capsys.readouterr()
  assert main([*args, "--overwrite"]) == 2
  err = capsys.readouterr().err
  assert f"{out / 'predictions' / first[1]} exists, and no earlier evaluation wrote it" in err, err
  assert (out / "predictions" / first[1]).read_bytes() == b"mine"
  assert (out / "predictions" / first[0]).is_file()  # nothing set aside or removed
  # A rerun that saves no predictions leaves no empty predictions/ folder behind.
  (out / "predictions" / first[1]).unlink()
  assert main([*args, "--overwrite", "--config.save_predictions=false"]) == 0
  assert not (out / "predictions").exists() and (out / "plots" / "notes.txt").is_file()


def test_a_users_file_named_as_a_baselines_prediction_is_refused(tmp_path, ckpt, capsys):
  """--overwrite replaces only files an evaluation wrote: a file of the user's where a
  baseline's prediction would go is refused (before any prediction), as one where the model's
  would, and kept."""
  mine = tmp_path / "predictions" / "synthetic_001_sgbm.npy"
  mine.parent.mkdir()
  mine.write_bytes(b"mine")
  assert main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *SMALL,
               "--out", str(tmp_path), "--baseline", "sgbm", "--overwrite"]) == 2
  assert f"{mine} exists, and no earlier evaluation wrote it" in capsys.readouterr().err
  assert mine.read_bytes() == b"mine"


def _snapshot(out):
  return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
          if p.is_file()}


def test_failed_overwrite_run_loses_nothing(tmp_path, ckpt, capsys, monkeypatch):
  # The earlier run's files are set aside, not deleted: a run that fails halfway (here the
  # second sequence cannot be read), or is stopped before its end, puts them back.
  out = tmp_path / "run"
  args = ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), "--out", str(out),
          *SMALL]
  assert main(args) == 0
  before = _snapshot(out)
  assert len([k for k in before if k.startswith("predictions/")]) == 2
  assert main([*args, "--overwrite", "--config.window=0"]) == 2  # refused before any change
  assert "stride <= window" in capsys.readouterr().err
  assert _snapshot(out) == before
  real = eval_runner.evaluate_sequence
  calls = []

  def second_fails(seq, *a, **kw):
    calls.append(seq.name)
    if len(calls) == 2:
      assert (out / "predictions").is_dir() and (out / eval_runner.SET_ASIDE).is_dir()
      raise ValueError(f"{seq.name}: frame 1 cannot be read")
    return real(seq, *a, **kw)

  with monkeypatch.context() as m:
    m.setattr(eval_runner, "evaluate_sequence", second_fails)
    assert main([*args, "--overwrite", "--config.synthetic.max_disparity=5"]) == 2
  assert "cannot be read" in capsys.readouterr().err
  assert _snapshot(out) == before  # the first sequence's new prediction is gone again
  # The disk full while the reports are written: the earlier reports come back too (the new
  # results.json next to the earlier predictions before).
  real_write_csv = eval_report.write_csv

  def disk_full(path, summary):
    real_write_csv(path, summary)
    raise OSError(28, "No space left on device")

  with monkeypatch.context() as m:
    m.setattr(eval_report, "write_csv", disk_full)
    assert main([*args, "--overwrite", "--config.synthetic.max_disparity=5"]) == 2
  assert "No space left on device" in capsys.readouterr().err
  assert _snapshot(out) == before
  # Stopped once the reports are written: that run is done, nothing comes back.
  with monkeypatch.context() as m:
    m.setattr(eval_report, "markdown", lambda summary: (_ for _ in ()).throw(KeyboardInterrupt)
              if summary.get("stop") else "x")
    real_write_all = eval_report.write_all
    m.setattr(eval_report, "write_all",
              lambda out_, summary: [real_write_all(out_, summary), summary.update(stop=1)][0])
    with pytest.raises(KeyboardInterrupt):
      main([*args, "--overwrite", "--config.synthetic.max_disparity=5"])
  after = _snapshot(out)
  assert after["results.json"] != before["results.json"] and not (out / ".earlier_run").exists()
  assert json.loads(after["results.json"])["config"]["synthetic"]["max_disparity"] == 5
  assert main([*args, "--overwrite"]) == 0  # back to the first run's settings
  capsys.readouterr()
  before = _snapshot(out)
  # A run killed after setting the files aside: the next run puts them back first.
  eval_runner.set_aside_written(out)
  (out / "predictions" / "partial.npy").write_bytes(b"new")
  eval_runner.record_written(out, [out / "predictions" / "partial.npy"])
  assert main(args) == 2  # no --overwrite: refused, after the restore
  assert "restored 6 prediction and plot files" in capsys.readouterr().out
  assert _snapshot(out) == before
  # Stopped while setting the files aside (after the first move): the restore loses nothing.
  real_replace, moves = pathlib.Path.replace, []

  def stop_at_second(self, target):
    moves.append(self)
    if len(moves) == 2:
      raise KeyboardInterrupt
    return real_replace(self, target)

  with monkeypatch.context() as m:
    m.setattr(pathlib.Path, "replace", stop_at_second)
    with pytest.raises(KeyboardInterrupt):
      eval_runner.set_aside_written(out)
  eval_runner.restore_set_aside(out)
  assert _snapshot(out) == before
  # Another evaluation writing into the folder (it holds the lock file's flock): refused
  # before anything changes. A lock file that no process holds is taken over, even one that
  # names this very process (a restarted container gets the same host name and PID).
  import fcntl  # pylint: disable=import-outside-toplevel
  import socket  # pylint: disable=import-outside-toplevel
  lock = out / eval_runner.LOCK
  lock.write_text("otherhost 4242")
  with open(lock, "rb") as held:
    fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    assert main([*args, "--overwrite"]) == 2
    assert "another evaluation (otherhost 4242) is writing into" in capsys.readouterr().err
    assert {k: v for k, v in _snapshot(out).items() if k != eval_runner.LOCK} == before
  lock.write_text(f"{socket.gethostname()} {os.getpid()}")
  assert main(args) == 2  # refused for the earlier results, not for the lock
  assert "pass --overwrite" in capsys.readouterr().err and not lock.exists()


def test_resume_after_a_failed_run(tmp_path, ckpt, variables, capsys, monkeypatch):
  # A run that fails at its second sequence keeps the first one's record; --resume evaluates
  # only the second, with the same settings, and reports both as an uninterrupted run would.
  out = tmp_path / "run"
  args = ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), "--out", str(out),
          "--config.metrics.tcc=true", *SMALL]
  real_append, real_evaluate = eval_runner.append_progress, eval_runner.evaluate_sequence
  evaluated = []

  def second_fails(out_, settings, res):  # after the second sequence's files are written
    if len(evaluated) == 2:
      raise OSError(f"{res.name}: disk full")
    return real_append(out_, settings, res)

  def counting(seq, *a, **kw):
    evaluated.append(seq.name)
    return real_evaluate(seq, *a, **kw)

  monkeypatch.setattr(eval_runner, "evaluate_sequence", counting)
  with monkeypatch.context() as m:
    m.setattr(eval_runner, "append_progress", second_fails)
    assert main(args) == 2
  assert "synthetic_001: disk full" in capsys.readouterr().err
  progress_lines = (out / eval_runner.PROGRESS).read_text()
  records = progress_lines.splitlines()
  assert len(records) == 2 and json.loads(records[1])["name"] == "synthetic_000"
  assert main(args) == 2  # without --resume: refused, and told about it
  assert "pass --resume to continue that interrupted run, or --overwrite" in (
      capsys.readouterr().err)
  assert main([*args, "--resume", "--config.iters=4"]) == 2  # other settings: refused, named
  assert "cannot resume: the interrupted run in" in (err := capsys.readouterr().err)
  assert "iters: 2 then, 4 now" in err
  # Other weights at the same path: refused; the same weights by another path: resumed below.
  other = tmp_path / "other"
  sav_jax.convert.save_variables(other, jax.tree_util.tree_map(
      lambda x: np.asarray(x) * np.float32(1.0001), variables), {"model": {}})
  assert main([*args, "--checkpoint", str(other), "--resume"]) == 2
  assert "the weights: other parameter values than the interrupted run's" in (
      capsys.readouterr().err)
  with pytest.raises(SystemExit):  # argparse: not both
    main([*args, "--resume", "--overwrite"])
  assert "--overwrite: not allowed with argument --resume" in capsys.readouterr().err
  # A record cut short by a kill is dropped (that sequence is done again).
  with open(out / eval_runner.PROGRESS, "a", encoding="utf-8") as f:
    f.write('{"name": "synthetic_001", "fra')
  evaluated.clear()
  same = tmp_path / "same.npz"  # the same weights in another format and place
  sav_jax.convert.export_state_dict(variables, same)
  assert main([*args, "--checkpoint", str(same), "--resume", "--config.devices=1"]) == 0
  assert evaluated == ["synthetic_001"]
  printed = capsys.readouterr().out
  assert "--resume: 1 sequence finished by the interrupted run is not evaluated again" in printed
  assert "synthetic_000 (4 frames)" in printed and "(from the interrupted run)" in printed
  assert not (out / eval_runner.PROGRESS).exists()  # finished: nothing left to resume
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  summary = _check_against_metrics(out, eval_data.load_sequences(config, None), ["sav"],
                                   with_scale=True)
  assert "disp_TCC" in summary["methods"]["sav"]["aggregate"]
  assert main([*args, "--resume"]) == 2  # a finished run: nothing to resume
  assert f"nothing to resume: {out} holds a finished evaluation (found results.json" in (
      capsys.readouterr().err)
  # A resumed run over fewer sequences keeps the records of the others for a later one.
  second = json.loads(records[1]) | {"name": "synthetic_001"}  # as if it had finished too
  both = progress_lines + json.dumps(second) + "\n"
  (out / eval_runner.PROGRESS).write_text(both, encoding="utf-8")
  evaluated.clear()
  assert main([*args, "--resume", "--config.max_sequences=1"]) == 0
  assert evaluated == [] and (out / eval_runner.PROGRESS).read_text() == both
  assert main([*args, "--resume"]) == 0 and evaluated == []  # both read back
  assert not (out / eval_runner.PROGRESS).exists()
  # The second sequence's files are listed twice (the failed run's and the resumed one's):
  # --overwrite removes each once.
  listed = (out / eval_runner.WRITTEN_LIST).read_text().splitlines()
  assert len(listed) == 3 * 3 and len(set(listed)) == 6
  assert main([*args, "--overwrite", "--config.synthetic.num_sequences=1"]) == 0
  assert sorted(p.name for p in (out / "predictions").iterdir()) == ["synthetic_000.npy"]


def test_progress_files_and_listing_survive_kills_and_hand_edits(tmp_path, ckpt, capsys,
                                                                 monkeypatch):
  out = tmp_path / "run"
  args = ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), "--out", str(out),
          *SMALL]
  # Killed while a sequence's plot is written: its files are listed before they are written,
  # so a later --overwrite removes them too.
  with monkeypatch.context() as m:
    m.setattr(eval_plots, "write_curves", lambda *a, **k: (_ for _ in ()).throw(
        KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
      main(args)
  assert (out / eval_runner.WRITTEN_LIST).read_text().splitlines() == [
      "predictions/synthetic_000.npy", "plots/synthetic_000_strip.png",
      "plots/synthetic_000_curves.png"]
  # No progress file (killed in its first sequence), but its files: --resume is refused, not
  # a run over them.
  assert main([*args, "--resume"]) == 2
  assert f"nothing to resume: {out} has no progress.jsonl (found " in capsys.readouterr().err
  # Hand-edited or cut-short progress files.
  settings = {"x": 1}
  progress = out / eval_runner.PROGRESS
  for text, message in (("[1]\n", "is not an evaluation progress file"),
                        ('{"sav_jax_eval_progress": 1, "x": 1}\n{"name": "a", "frames": "4", '
                         '"metrics": {}, "seconds": {}, "compile_seconds": {}, '
                         '"metrics_seconds": 0}\n', "line 2 is not a finished sequence's"),
                        ('{"sav_jax_eval_progress": 1, "x": 1}\n' + "[" * 100_000 + "\n",
                         "line 2 is not a finished sequence's.*nested too deeply"),  # Recursion
                        ("[" * 100_000 + "\n", "is not an evaluation progress file")):
    progress.write_text(text)
    with pytest.raises(ValueError, match=message):
      eval_runner.read_progress(out, settings)
  record = {"name": "a", "frames": 4, "metrics": {}, "seconds": {}, "compile_seconds": {},
            "metrics_seconds": 0.5}
  progress.write_text('{"sav_jax_eval_progress": 1, "x": 1}\n\n' + json.dumps(record) + "\n\n")
  assert list(eval_runner.read_progress(out, settings)) == ["a"]  # blank lines skipped
  progress.write_text('{"sav_jax_eval_prog')  # killed writing the header: nothing done
  assert eval_runner.read_progress(out, settings) is None and not progress.exists()
  # A listing line cut short by a kill: the next path starts a line of its own.
  listing = out / eval_runner.WRITTEN_LIST
  listing.write_text("predictions/synthetic_000.npy\nplots/synth")
  eval_runner.record_written(out, [out / "plots" / "x.png"])
  assert listing.read_text().splitlines() == ["predictions/synthetic_000.npy", "plots/synth",
                                              "plots/x.png"]


def test_an_unreadable_sequence_after_finished_ones_says_resume_continues(tmp_path, no_model,
                                                                          capsys, monkeypatch):
  calls, error = [], [OSError("synthetic_001/frame_0003.png: cannot decode the image file")]

  def fake_predict(variables, left, right, **kw):
    calls.append(1)
    if len(calls) == 2:
      raise error[0]
    return np.ones(left.shape[:3], np.float32)

  monkeypatch.setattr(eval_runner.inference, "predict_video", fake_predict)
  args = _small_run(tmp_path / "a")
  assert main(args) == 2
  err = capsys.readouterr().err
  assert err == ("eval: error: synthetic_001/frame_0003.png: cannot decode the image file; the "
                 "1 sequence finished before it is recorded: fix it and run the same command "
                 "with --resume to continue\n"), err
  assert main([*args, "--resume"]) == 0
  assert len(calls) == 3  # the second sequence only
  calls[:] = [1]  # the first sequence fails: nothing to resume, the error as it is
  assert main([*args[:-1], str(tmp_path / "c")]) == 2
  assert capsys.readouterr().err.endswith("cannot decode the image file\n")
  calls.clear()  # an --overwrite run puts the earlier results back: nothing to resume either
  assert main([*args, "--overwrite"]) == 2
  assert capsys.readouterr().err == ("eval: error: synthetic_001/frame_0003.png: cannot decode "
                                     "the image file\n")
  assert (tmp_path / "a" / "results.json").is_file()
  calls.clear()  # stopped (Ctrl-C) in its second sequence: put back before it stops, too
  error[0] = KeyboardInterrupt()
  with pytest.raises(KeyboardInterrupt):
    main([*args, "--overwrite"])
  assert (tmp_path / "a" / "results.json").is_file()
  assert not (tmp_path / "a" / eval_runner.SET_ASIDE).exists()


def test_matmul_precision_of_the_predictions(tmp_path, ckpt, capsys, monkeypatch):
  seen = []

  def fake_predict(variables, left, right, **kw):
    seen.append(jax.config.jax_default_matmul_precision)
    assert kw["devices"] == jax.devices()[:1]  # config.devices = 1
    return np.ones(left.shape[:3], np.float32)

  monkeypatch.setattr(eval_runner.inference, "predict_video", fake_predict)
  args = ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *SMALL]
  assert main([*args, "--out", str(tmp_path / "a"), "--config.matmul_precision=highest"]) == 0
  assert main([*args, "--out", str(tmp_path / "b")]) == 0
  assert seen == ["highest", "highest", "default", "default"]  # two sequences each
  assert main([*args, "--out", str(tmp_path / "c"), "--config.matmul_precision=tf32"]) == 2
  assert "config.matmul_precision must be one of" in capsys.readouterr().err


@pytest.mark.parametrize("override,message", [
    ("--config.nope=1", "no such config field"), ("--config.iters=abc", "expected int"),
    ("--config.iters=1", "config.iters must be an integer >= 2, got 1"), ("--config.plots.enabled=maybe", "true/false"),
    ("--config.split=train", "only the split 'test'"),
    ("--config.devices=4", "config.devices: devices=4, but 1 local cpu device is available"),
    # (0 for every device; not 'all', which the integer field refuses)
    ("--config.devices=-1", "config.devices: devices must be a number of local devices >= 1, "
                            "or 0 for every one, got -1"),
    ("--config.plots.tile_size=0", "config.plots.tile_size must be an integer >= 16, got 0"),
    ("--config.metrics.raft_iters=0",  # also with RAFT off (it was accepted silently)
     "config.metrics.raft_iters must be a positive integer, got 0"),
    ("--checkpoint=", "--checkpoint is empty: name the weights"),
    ("--checkpoint= ", "--checkpoint is empty: name the weights"),  # (spaces: no file named)
    # (an unset $OUT: the default folder, whose results --overwrite replaced; "." for the data)
    ("--out=", "--out is empty; give a path"), ("--data-root=", "--data-root is empty"),
    ("--compile-cache=", "--compile-cache is empty"),
    ("--config.plots.strip_frames=0", "config.plots.strip_frames must be an integer >= 1"),
    ("--config.iters=1e400", "--config.iters: 1e400 is out of range"),  # (an OverflowError)
    ("--config.dtype=float64", "config.dtype must be one of ('float32', 'bfloat16'), got 'f"),
    ("--config.synthetic.num_sequences=0",
     "config.synthetic.num_sequences must be an integer >= 1, got 0"),
    ("--config.synthetic.min_disparity=0", "config.synthetic.min_disparity must be > 0, got 0"),
    ("--config.synthetic.max_disparity=300",
     "config.synthetic.max_disparity must be < width, got 300.0")])
def test_bad_overrides(tmp_path, ckpt, capsys, override, message):
  rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt),
             "--out", str(tmp_path / "o"), override])
  assert rc == 2 and message in capsys.readouterr().err
  assert not (tmp_path / "o").exists()


def test_abbreviated_options_are_refused(tmp_path, capsys):
  # argparse took --over for --overwrite (replacing results), silently
  with pytest.raises(SystemExit) as e:
    main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(tmp_path / "c"),
          "--out", str(tmp_path / "o"), "--over"])
  assert e.value.code == 2 and "unrecognized arguments: --over" in capsys.readouterr().err
  assert not (tmp_path / "o").exists()


def test_tcc_without_camera_data_is_refused_before_predicting(tmp_path, ckpt, capsys,
                                                               monkeypatch):
  load = eval_data.load_sequences_and_skipped

  def without_scale(config, root):
    seqs, skipped = load(config, root)
    for seq in seqs:
      seq.depth2disp_scale = None  # as a dataset without camera data (SceneFlow)
    return seqs, skipped

  monkeypatch.setattr(eval_data, "load_sequences_and_skipped", without_scale)
  monkeypatch.setattr(eval_runner.inference, "predict_video", None)  # must not be reached
  rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *SMALL,
             "--out", str(tmp_path / "o"), "--config.metrics.tcc=true"])
  err = capsys.readouterr().err
  assert rc == 2 and "config.metrics.tcc needs depth" in err and "synthetic_000" in err, err
  assert not (tmp_path / "o").exists()
  monkeypatch.setattr(eval_data, "load_sequences_and_skipped", load)
  one_frame = [a.replace(f"frames={T}", "frames=1") for a in SMALL]  # no temporal metric
  rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *one_frame,
             "--out", str(tmp_path / "o"), "--config.metrics.tcc=true"])
  err = capsys.readouterr().err
  assert rc == 2 and "config.metrics.tcc: temporal consistency needs sequences of 2 frames or " \
      "more, but synthetic sequence synthetic_000 has 1" in err, err
  assert not (tmp_path / "o").exists()


def test_python_warnings_are_one_line_each(tmp_path, ckpt, capsys, monkeypatch):
  """A Python warning met by the run (a 16-bit frame's) was shown as its source file, line and
  code, two lines among the run's one-line messages; now as `sav-jax` commands show them."""
  import warnings  # pylint: disable=import-outside-toplevel
  shown = warnings.showwarning

  def load(config, root):
    warnings.warn("a/left/0001.png is a 16-bit image whose values all fit in 0..255")
    raise ValueError("stop here")

  monkeypatch.setattr(eval_data, "load_sequences_and_skipped", load)
  rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *SMALL,
             "--out", str(tmp_path / "o")])
  err = capsys.readouterr().err
  assert rc == 2 and "eval: warning: a/left/0001.png is a 16-bit image whose values all fit in " \
      "0..255\n" in err and "UserWarning" not in err and "warnings.warn" not in err, err
  assert warnings.showwarning is shown  # put back


def test_compile_cache_options(tmp_path, ckpt, capsys, monkeypatch, restore_cache_config):
  """As `sav-jax infer`: on by default (here the test session's folder, which JAX was given),
  `--compile-cache DIR` for a folder, `--no-compile-cache` to leave JAX's setting alone; a
  folder that cannot be one is named before anything is written."""
  (tmp_path / "notes.txt").write_text("keep me")
  args = ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *SMALL,
          "--out", str(tmp_path / "o")]
  assert main([*args, "--compile-cache", str(tmp_path / "notes.txt")]) == 2
  err = capsys.readouterr().err
  assert f"compilation cache {tmp_path / 'notes.txt'} exists and is not a folder" in err, err
  assert not (tmp_path / "o").exists() and (tmp_path / "notes.txt").read_text() == "keep me"

  class Reached(Exception):
    pass

  def predict_video(*args, **kwargs):
    raise Reached(jax.config.jax_compilation_cache_dir)

  def folder_in_use(*extra):
    with pytest.raises(Reached) as seen:
      main([*args, *extra])
    return seen.value.args[0]

  monkeypatch.setattr(eval_runner.inference, "predict_video", predict_video)
  session = jax.config.jax_compilation_cache_dir
  assert folder_in_use() == session
  assert folder_in_use("--compile-cache", str(tmp_path / "xla")) == str(tmp_path / "xla")
  assert (tmp_path / "xla").is_dir()
  jax.config.update("jax_compilation_cache_dir", None)
  assert folder_in_use("--no-compile-cache") is None


def test_configs_paths_name_the_package_files_from_any_folder(tmp_path, monkeypatch):
  import configs  # pylint: disable=import-outside-toplevel
  monkeypatch.chdir(tmp_path)  # no configs/ here: the package's (a wheel user's folder)
  assert eval_config.load_config("configs/eval/synthetic.py").dataset == "synthetic"
  assert configs.locate("configs/eval/synthetic.py:x") == f"{CONFIGS / 'synthetic.py'}:x"
  with pytest.raises(FileNotFoundError, match="config file not found: configs/eval/nope.py"):
    eval_config.load_config("configs/eval/nope.py")
  (tmp_path / "configs" / "eval").mkdir(parents=True)  # the folder's own come first
  (tmp_path / "configs" / "eval" / "synthetic.py").write_text("def get_config():\n  return 1\n")
  assert configs.locate("configs/eval/synthetic.py") == "configs/eval/synthetic.py"
  assert configs.locate("other/synthetic.py") == "other/synthetic.py"


def test_config_files_that_cannot_be_used(tmp_path):
  broken = tmp_path / "broken.py"
  broken.write_text("def get_config(:\n")
  with pytest.raises(ValueError, match=f"{broken} does not parse: line 1"):
    eval_config.load_config(str(broken))
  # Any file name is read as Python (it was a traceback for a name without .py)
  binary = tmp_path / "frame.png"
  binary.write_bytes(b"\x89PNG\x00\x00")
  with pytest.raises(ValueError, match=f"{binary} does not parse: source code .*null bytes"):
    eval_config.load_config(str(binary))
  (tmp_path / "config.txt").write_text((CONFIGS / "synthetic.py").read_text())
  assert eval_config.load_config(str(tmp_path / "config.txt")).dataset == "synthetic"
  with pytest.raises(ValueError, match=r"synthetic.py: get_config\(\) cannot be called with the "
                     r"argument 'foo' \(from .*synthetic.py:foo\)"):
    eval_config.load_config(f"{CONFIGS / 'synthetic.py'}:foo")
  needs_arg = tmp_path / "needs_arg.py"
  needs_arg.write_text("def get_config(variant):\n  raise AssertionError\n")
  with pytest.raises(ValueError, match=r"get_config\(variant\) cannot be called without"):
    eval_config.load_config(str(needs_arg))
  # The config file's own errors name it (they were tracebacks, exit status 1).
  failing = tmp_path / "failing.py"
  failing.write_text("import no_such_module_here\n")
  with pytest.raises(ValueError, match=r"failing.py: importing it raised ModuleNotFoundError: "
                     "No module named 'no_such_module_here'"):
    eval_config.load_config(str(failing))
  failing.write_text("from configs.eval.common import eval_config\n"
                     "def get_config():\n  return eval_config('sintel_final', iter=4)\n")
  with pytest.raises(ValueError, match=r"failing.py: get_config\(\) raised TypeError: .*'iter'"):
    eval_config.load_config(str(failing))
  from eval import data as eval_data  # pylint: disable=import-outside-toplevel
  bare = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  del bare.synthetic
  with pytest.raises(ValueError, match="config.dataset='synthetic' needs a config.synthetic"):
    eval_data.load_sequences(bare, tmp_path)


@pytest.mark.parametrize("line, message", [
    ("c.iters = None", "config.iters must be an integer >= 2, got None"),
    ("c.max_sequences = None", "config.max_sequences must be an integer (<= 0: all), got None"),
    ("c.plots.strip_frames = True", "config.plots.strip_frames must be an integer >= 1, got True"),
    ("c.sample_len = None", "config.sample_len must be an integer (<= 0: all), got None"),
    ("c.plots.tile_size = 15", "config.plots.tile_size must be an integer >= 16, got 15"),
    ("c.metrics.raft_iters = True",
     "config.metrics.raft_iters must be a positive integer, got True"),
    ("c.metrics.raft_iters = 0", "config.metrics.raft_iters must be a positive integer, got 0"),
    ("c.window = 0", "need integers 1 <= stride <= window, got window=0, stride=10")])
def test_config_file_values_that_cannot_be_used_are_named(tmp_path, capsys, line, message):
  """Values that a config file of one's own sets (an override is parsed as the field's type):
  one line, status 2, before the weights are read."""
  config = tmp_path / "mine.py"
  config.write_text("from configs.eval import synthetic\n\n\ndef get_config():\n"
                    f"  c = synthetic.get_config()\n  {line}\n  return c\n")
  assert main(["--config", str(config), "--checkpoint", "x", "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == f"eval: error: {message}\n"


def test_a_config_files_argument_and_a_colon_in_its_folders_name(tmp_path):
  """`path.py:arg` calls get_config(arg) (big_vision's convention), and a ':' elsewhere (a
  folder named after a time) is part of the path; get_config() must return a ConfigDict."""
  folder = tmp_path / "run 10:30"
  folder.mkdir()
  variant = folder / "variant.py"
  variant.write_text("from configs.eval.common import eval_config\n"
                     "def get_config(name='sintel_final'):\n  return eval_config(name)\n")
  assert eval_config.load_config(str(variant)).dataset == "sintel_final"
  assert eval_config.load_config(f"{variant}:kitti_depth").dataset == "kitti_depth"
  variant.write_text("def get_config():\n  return {'iters': 20}\n")
  with pytest.raises(ValueError, match=r"variant.py: get_config\(\) returned dict, not a "
                                       "ConfigDict"):
    eval_config.load_config(str(variant))


def test_a_config_that_is_not_an_evaluation_config_is_named(tmp_path, ckpt, capsys):
  # The training config of the same name (configs/synthetic.py) was a traceback from
  # ml_collections (AttributeError: 'iters'), exit status 1.
  training = CONFIGS.parent / "synthetic.py"
  assert main(["--config", str(training), "--checkpoint", str(ckpt),
               "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert err.startswith(f"eval: error: {training} is not an evaluation config: it lacks ") and (
      "it is a training config (python -m train); evaluation configs build on "
      "configs/eval/common.py") in err and err.count("\n") == 1, err
  old = tmp_path / "old.py"  # an evaluation config of an earlier version: no plots
  old.write_text("from configs.eval.common import eval_config\n"
                 "def get_config():\n  c = eval_config('synthetic')\n  del c.plots\n"
                 "  return c\n")
  assert main(["--config", str(old), "--checkpoint", str(ckpt), "--out", str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert (f"{old} is not an evaluation config: it lacks plots.enabled, plots.strip_frames, "
          "plots.tile_size; evaluation configs build on") in err, err
  assert not (tmp_path / "o").exists()
  # A misspelt field, which nothing reads, is named (the run evaluated every frame, with plots)
  old.write_text("from configs.eval.common import eval_config\n"
                 "def get_config():\n  c = eval_config('synthetic')\n  c.sample_length = 2\n"
                 "  c.plots.enable = False\n  return c\n")
  assert main(["--config", str(old), "--checkpoint", str(ckpt), "--out", str(tmp_path / "o")]) == 2
  assert capsys.readouterr().err == (
      f"eval: error: {old}: no such config field plots.enable, sample_length (misspelt? it "
      "would be ignored; python -m eval --help lists the fields)\n")
  # None ("all frames"?) in a config file: ConfigDict takes it for any field; it was a
  # TypeError traceback from the sequence loader (int(None), None > 0)
  for field in ("sample_len", "max_sequences"):
    old.write_text("from configs.eval.common import eval_config\n"
                   f"def get_config():\n  c = eval_config('synthetic')\n  c.{field} = None\n"
                   "  return c\n")
    assert main(["--config", str(old), "--checkpoint", str(ckpt),
                 "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == (f"eval: error: config.{field} must be an integer "
                                       "(<= 0: all), got None\n")
  assert not (tmp_path / "o").exists()


def test_help_lists_the_config_fields_with_their_defaults(capsys):
  from configs.eval import common  # pylint: disable=g-import-not-at-top
  with pytest.raises(SystemExit) as e:
    main(["--help"])
  assert e.value.code == 0
  out = " ".join(capsys.readouterr().out.split())  # argparse wraps the epilog
  config = common.eval_config("x")
  assert f"iters={config.iters!r}" in out and "metrics.raft=''" in out
  for name, value in (("window", config.window), ("stride", config.stride),
                      ("plots.tile_size", config.plots.tile_size),
                      ("metrics.tcc", config.metrics.tcc)):
    assert f"{name}={value!r}" in out, name
  assert "sample_len=" not in out and "dataset=" not in out  # the dataset's config sets them


def test_override_values_are_parsed_as_written(capsys):
  with pytest.raises(ValueError, match=r"--config.save_predictions needs a value "
                                       r"\(--config.save_predictions=VALUE or"):
    eval_config.split_overrides(["--config.save_predictions", "--baseline", "sgbm"])
  with pytest.raises(ValueError, match="--config.iters needs a value"):  # the last argument
    eval_config.split_overrides(["--baseline", "sgbm", "--config.iters"])
  # the command: one line, status 2 (bad input)
  assert main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", "x",
               "--config.iters"]) == 2
  err = capsys.readouterr().err
  assert err.startswith("eval: error: --config.iters needs a value") and err.count("\n") == 1
  with pytest.raises(SystemExit) as info:  # argparse's usage error: --config is required
    main(["--checkpoint", "x"])
  assert info.value.code == 2
  assert "the following arguments are required: --config" in capsys.readouterr().err
  rest, ov = eval_config.split_overrides(["--config.iters", "-3", "--config.sample_len=0150"])
  assert ov == [("iters", "-3"), ("sample_len", "0150")]
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")), ov)
  assert config.iters == -3 and config.sample_len == 150  # decimal (int(x, 0) refused 0150)
  with pytest.raises(ValueError, match="--config.iters: expected int, got '0x10'"):
    eval_config.apply_overrides(config, [("iters", "0x10")])


def test_synthetic_set_takes_every_generator_field():
  config = eval_config.apply_overrides(
      eval_config.load_config(str(CONFIGS / "synthetic.py")),
      eval_config.split_overrides([*SMALL, "--config.synthetic.min_disparity=4",
                                   "--config.synthetic.noise_std=3"])[1])
  with config.unlocked():  # a field the file does not list, as a config file of one's own adds
    config.synthetic.textures = ["checker"]
  seqs = eval_data.load_sequences(config, None)
  cfg = seqs[0].cfg
  assert (cfg.min_disparity, cfg.noise_std, cfg.textures) == (4.0, 3.0, ("checker",))
  clip = eval_data.read_sequence(seqs[0])
  assert clip["disparity"][clip["valid"] > 0].min() >= 4.0 - 1e-4
  with config.unlocked():
    config.synthetic.max_disparty = 5.0
  with pytest.raises(ValueError, match="config.synthetic.max_disparty is not a field of the "
                     "synthetic generator; its fields: background_fraction, .*num_sequences"):
    eval_data.load_sequences(config, None)


def test_a_synthetic_sequence_beyond_host_memory_is_refused_before_rendering(monkeypatch):
  """`--config.synthetic.height=16000 --config.synthetic.width=16000`: the generator filled
  the host's memory until the kernel killed the process; now a MemoryError ("out of host
  memory", eval's one line) before anything is rendered, as `sav-jax demo`'s."""
  monkeypatch.setattr(eval_data.synthetic, "generate_clip", lambda cfg, index: 1 / 0)
  monkeypatch.setattr(inference, "available_memory_bytes", lambda device=None: 2**30)
  cfg = synthetic.SyntheticConfig(frames=8, height=2048, width=2048)
  with pytest.raises(MemoryError, match=r"synthetic video of 8 frames of 2048x2048 needs about "
                     r"1\.8 GB, but only 1\.0 GB"):
    eval_data.SyntheticSequence(cfg, 0)[0]  # pylint: disable=expression-not-assigned
  monkeypatch.undo()
  small = synthetic.SyntheticConfig(frames=2, height=32, width=64, num_objects=1,
                                    max_disparity=8.0)
  assert eval_data.SyntheticSequence(small, 0)[0]["left"].shape == (32, 64, 3)  # (it fits)


def test_synthetic_valid_rule_and_frame_bounds(monkeypatch):
  """Dense GT is valid where |d| < 512 and d != 0 (the official rule); frames outside a
  sequence or a head of it are IndexErrors, not NumPy's wrap-around from the end."""
  d = np.array([0.0, 5.0, -5.0, 511.9, 512.0, -600.0], np.float32)
  frames = np.arange(4, dtype=np.float32)[:, None, None] + d  # frame k: d + k
  clip = {"left": np.zeros((4, 1, 6, 3), np.uint8), "right": np.zeros((4, 1, 6, 3), np.uint8),
          "disparity": np.broadcast_to(d, (4, 1, 6)).copy(), "valid": np.ones((4, 1, 6), bool)}
  monkeypatch.setattr(eval_data.synthetic, "generate_clip", lambda cfg, index: clip)
  cfg = types.SimpleNamespace(frames=4, fx=1.0, baseline=1.0, width=6, height=1)
  seq = eval_data.SyntheticSequence(cfg, 0)
  assert seq[0]["valid"].tolist() == [[False, True, True, True, False, False]]
  with pytest.raises(IndexError):
    seq.clip(-1, 2)
  clip["disparity"] = frames  # (rendered lazily: the frames tell apart)
  strided = eval_data.SyntheticSequence(cfg, 0).clip(1, 2, stride=2)  # frames 1 and 3
  assert strided["disparity"][:, 0, 1].tolist() == [5.0 + 1, 5.0 + 3]
  with pytest.raises(IndexError):  # no frame at all
    seq.clip(0, 0)
  head = eval_data._Head(eval_data.SyntheticSequence(cfg, 0), 2)  # pylint: disable=protected-access
  assert head[-1]["disparity"][0, 1] == 5.0 + 1  # the head's last frame, 1
  for i in (-3, 2):
    with pytest.raises(IndexError):
      head[i]  # pylint: disable=pointless-statement
  for start, length, stride in ((1, 2, 1), (0, 2, 2)):  # frame 2, beyond the head's 0..1
    with pytest.raises(IndexError):
      head.clip(start, length, stride)


def test_read_sequence_gives_float32_disparity_and_a_boolean_mask():
  """A reader's float64 disparity (Sintel's is decoded in float64) and 0/1 mask are read as
  float32 and bool, the dtypes of the official evaluator's tensors."""
  class Seq:  # pylint: disable=too-few-public-methods
    def __len__(self):
      return 2

    def clip(self, start, length):
      assert (start, length) == (0, 2)
      return {"left": np.zeros((2, 1, 3, 3), np.uint8), "right": np.zeros((2, 1, 3, 3), np.uint8),
              "disparity": np.full((2, 1, 3), 1 / 3), "valid": np.ones((2, 1, 3), np.uint8)}

  clip = eval_data.read_sequence(Seq())
  assert clip["disparity"].dtype == np.float32 and clip["valid"].dtype == bool
  assert clip["disparity"][0, 0, 0] == np.float32(1 / 3) and clip["valid"].all()


def test_synthetic_depth_to_disparity_scale_is_fx_times_baseline():
  """The synthetic set's scale for the depth metrics is fx * baseline (d = fx B / Z), not fx:
  the generator's own disparity and depth agree with it."""
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  config.synthetic.num_sequences = 1
  (seq,) = eval_data.load_sequences(config, None)
  assert seq.depth2disp_scale == pytest.approx(W * 0.1)  # fx = width, baseline 0.1 m
  assert seq.depth2disp_scale == pytest.approx(seq.cfg.fx * seq.cfg.baseline)
  clip = synthetic.generate_clip(seq.cfg, 0)
  np.testing.assert_allclose(clip["disparity"] * clip["depth"], seq.depth2disp_scale, rtol=1e-5)


def test_sgbm_baseline_settings_are_checked_before_predicting(tmp_path, no_model, capsys):
  for value, message in (("4", "block_size must be an odd integer >= 1, got 4"),
                         ("0", "block_size must be an odd integer >= 1, got 0")):
    rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", "w", "--out",
               str(tmp_path / "o"), "--baseline", "sgbm", f"--config.baseline.block_size={value}",
               "--config.plots.strip_frames=1", "--config.plots.tile_size=16"])  # (the least)
    assert rc == 2 and f"config.baseline.{message}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists() and no_model.evaluated == []
  from sav_jax.tools.demo import stereo_sgbm  # pylint: disable=import-outside-toplevel
  frames = np.zeros((1, 8, 40, 3), np.uint8)
  with pytest.raises(ValueError, match="max_disparity must be a finite number >= 1"):
    stereo_sgbm(frames, frames, max_disparity=float("nan"))


def test_config_overrides_and_head():
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  rest, ov = eval_config.split_overrides(["--x", "--config.iters", "4",
                                          "--config.plots.enabled=false"])
  assert rest == ["--x"]
  eval_config.apply_overrides(config, ov)
  assert config.iters == 4 and config.plots.enabled is False
  config.synthetic.frames, config.synthetic.height, config.synthetic.width = 6, 16, 32
  config.synthetic.num_sequences, config.sample_len = 1, 4
  config.synthetic.max_disparity = 6.0
  (seq,) = eval_data.load_sequences(config, None)
  assert len(seq) == 4 and eval_data.read_sequence(seq)["left"].shape == (4, 16, 32, 3)
  for name in ("sintel_clean", "sintel_final", "dynamic_replica", "infinigen_sv", "vkitti2",
               "kitti_depth", "spring", "south_kensington", "tartanair"):
    c = eval_config.load_config(str(CONFIGS / f"{name}.py"))
    assert c.dataset == name and c.split == "test" and c.iters == 20 and c.window == 20


# configs/eval/<name>.py -> frames evaluated per sequence (datasets.md, section 1; <= 0: all).
OFFICIAL_SAMPLE_LEN = {"dynamic_replica": 150, "infinigen_sv": 150, "vkitti2": 300,
                       "kitti_depth": 300, "south_kensington": 300, "sintel_clean": 0,
                       "sintel_final": 0, "spring": 0, "tartanair": 0, "folder": 0,
                       "synthetic": 0}


def test_every_dataset_config_follows_the_official_protocol():
  """datasets.md: DR and Infinigen evaluate the first 150 frames, VKITTI2, KITTI depth and South
  Kensington the first 300, Sintel every frame; every config: the test split, windows of 20
  frames with stride 10, 20 GRU iterations, RAFT's 20 iterations, float32."""
  names = sorted(p.stem for p in CONFIGS.glob("*.py") if p.stem not in ("__init__", "common"))
  assert names == sorted(OFFICIAL_SAMPLE_LEN)  # a new config gets its official value here
  from configs.eval import common  # pylint: disable=import-outside-toplevel
  for name, sample_len in OFFICIAL_SAMPLE_LEN.items():
    c = eval_config.load_config(str(CONFIGS / f"{name}.py"))
    assert (c.dataset, c.split) == (name, "test"), name
    if sample_len:
      assert c.sample_len == sample_len, name
    else:
      assert c.sample_len <= 0, name
    assert (c.window, c.stride, c.iters, c.metrics.raft_iters) == (20, 10, 20, 20), name
    assert c.dtype == "float32" and c.max_sequences <= 0, name
    # Without a sample_len: the official one for the test split, every frame of the others
    assert max(common.eval_config(name).sample_len, 0) == sample_len, name
    assert common.eval_config(name, split="valid").sample_len <= 0, name
    # README: XLA's default precision; no predictions, TCC or RAFT unless asked for
    assert c.matmul_precision == "default" and not c.save_predictions, name
    assert not c.metrics.tcc and c.metrics.raft == "", name


def _write_vkitti2(root, clip, name, fx=725.0087):
  scene, variation = name.split("_", 1)
  seq = root / "vkitti2" / scene / variation
  for cam, view in (("Camera_0", "left"), ("Camera_1", "right")):
    (seq / "frames" / "rgb" / cam).mkdir(parents=True)
    (seq / "frames" / "depth" / cam).mkdir(parents=True)
    for t in range(len(clip[view])):
      cv2.imwrite(str(seq / "frames" / "rgb" / cam / f"rgb_{t:05d}.jpg"), clip[view][t][..., ::-1],
                  [cv2.IMWRITE_JPEG_QUALITY, 98])
      cm = np.clip(np.round(clip["depth"][t] * 100), 1, 65535).astype(np.uint16)
      cv2.imwrite(str(seq / "frames" / "depth" / cam / f"depth_{t:05d}.png"), cm)
  rows = ["frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]"]
  rows += [f"{t} {c} {fx} {fx} {(W - 1) / 2} {(H - 1) / 2}" for t in range(T) for c in (0, 1)]
  (seq / "intrinsic.txt").write_text("\n".join(rows) + "\n")


def test_vkitti2_on_disk(tmp_path, ckpt):
  from sav_jax.data import registry, vkitti2
  scfg = synthetic.SyntheticConfig(frames=T, height=H, width=W, focal=725.0087,
                                   baseline=vkitti2.BASELINE_M, max_disparity=6.0, num_objects=2)
  for i, name in enumerate(vkitti2.TEST):
    _write_vkitti2(tmp_path / "data", synthetic.generate_clip(scfg, i), name)
  out = tmp_path / "out"
  rc = main(["--config", str(CONFIGS / "vkitti2.py"), "--checkpoint", str(ckpt), "--data-root",
             str(tmp_path / "data"), "--out", str(out), "--config.iters=2",
             "--config.save_predictions=true", "--config.plots.enabled=false"])
  assert rc == 0
  seqs = registry.get_sequences("vkitti2", tmp_path / "data", "test", max_frames=300)
  summary = _check_against_metrics(out, seqs, ["sav"], with_scale=False)
  assert summary["frames"] == 5 * T and not (out / "plots").exists()
  assert [s["source"] for s in summary["sequences"]] == [
      str(seq.files["left"][0].resolve().parent) for seq in seqs]


def test_your_own_videos_in_the_folder_layout(tmp_path, ckpt):
  """`configs/eval/folder.py`: sequences of one's own, with PFM ground truth and without."""
  from sav_jax import viz
  from sav_jax.data import registry
  scfg = synthetic.SyntheticConfig(frames=T, height=H, width=W, max_disparity=6.0, num_objects=2)
  for i, name in enumerate(("a", "b")):
    clip, seq = synthetic.generate_clip(scfg, i), tmp_path / "mine" / "test" / name
    for t in range(T):
      for view in ("left", "right"):
        (seq / view).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(seq / view / f"{t}.png"), clip[view][t][..., ::-1])
      if name == "a":
        (seq / "disparity").mkdir(exist_ok=True)
        viz.write_pfm(seq / "disparity" / f"{t}.pfm", np.where(clip["valid"][t], clip["disparity"][t], 0))
  (tmp_path / "mine" / "test" / "a" / "calib.txt").write_text("fx 64\nbaseline 0.5\n")
  out = tmp_path / "out"
  # TCC measures "a": "b" has no ground truth, and no camera data, which it does not need
  # (the run was refused: "b has no depth-to-disparity scale")
  rc = main(["--config", str(CONFIGS / "folder.py"), "--checkpoint", str(ckpt), "--data-root",
             str(tmp_path / "mine"), "--out", str(out), "--config.iters=2",
             "--config.save_predictions=true", "--config.plots.enabled=false",
             "--config.metrics.tcc=true"])
  assert rc == 0
  seq = registry.get_sequences("folder", tmp_path / "mine", "test")[0]
  summary = json.loads((out / "results.json").read_text())
  assert [s["name"] for s in summary["sequences"]] == ["a", "b"]
  clip = eval_data.read_sequence(seq)
  ref = metrics.eval_sequence(np.load(out / "predictions" / "a.npy"), clip["disparity"],
                              clip["valid"].astype(np.float32), scale=32.0)
  assert "disp_TCC" in ref
  assert summary["sequences"][0]["metrics"]["sav"] == pytest.approx(ref, rel=1e-12, abs=1e-12)
  assert not summary["sequences"][1]["metrics"].get("sav")  # no ground truth: no metrics,
  assert np.load(out / "predictions" / "b.npy").shape == (T, H, W)  # but its predictions


def test_a_registered_datasets_eval_frames_are_what_eval_evaluates(tmp_path, ckpt, monkeypatch):
  """`register_dataset(..., eval_frames=L)` in one's evaluation config, which then calls
  `eval_config(name)`: the first L frames of each test sequence are evaluated, as
  `get_sequences` cuts them (every frame was: eval_config's default sample_len was -1)."""
  from sav_jax.data import registry
  for name in ("_LOADERS", "_FOLDERS", "SPLITS", "EVAL_FRAMES"):
    monkeypatch.setattr(registry, name, dict(getattr(registry, name)))
  for name in ("DATASETS", "STRIDED", "_SCENEFLOW"):
    monkeypatch.setattr(registry, name, getattr(registry, name))
  _folder_dataset(tmp_path / "mine", np.random.default_rng(3))  # a: 3, b: 5, c: 2 frames
  config = tmp_path / "mine.py"
  config.write_text("from sav_jax.data import registry, stereo_folder\n"
                    "registry.register_dataset('mine', stereo_folder.load_sequences, "
                    "splits=('test',), training=None, eval_frames=2)\n"
                    "from configs.eval.common import eval_config\n"
                    "def get_config():\n  return eval_config('mine')\n")
  monkeypatch.setattr(eval_runner.inference, "predict_video",
                      lambda variables, left, right, **kw: _stand_in_prediction(left))
  for extra, frames in (([], [2, 2, 2]), (["--config.sample_len=0"], [3, 5, 2])):
    out = tmp_path / f"out{len(extra)}"
    assert main(["--config", str(config), "--checkpoint", str(ckpt), "--data-root",
                 str(tmp_path / "mine"), "--out", str(out), "--config.plots.enabled=false",
                 *extra]) == 0
    summary = json.loads((out / "results.json").read_text())
    assert [s["frames"] for s in summary["sequences"]] == frames, extra
    assert summary["config"]["sample_len"] == (2 if not extra else 0)
  assert eval_config.load_config(str(CONFIGS / "folder.py")).sample_len == -1  # none: whole


def test_resume_reads_the_sequences_from_the_same_folder(tmp_path, ckpt, capsys, monkeypatch):
  # An interrupted run over one copy of the dataset is not resumed over another copy (its
  # finished sequences' metrics would be those of other files), but is over the same files
  # reached through the dataset's own folder.
  from sav_jax.data import vkitti2
  scfg = synthetic.SyntheticConfig(frames=T, height=H, width=W, focal=725.0087,
                                   baseline=vkitti2.BASELINE_M, max_disparity=6.0, num_objects=2)
  for i, name in enumerate(vkitti2.TEST):
    _write_vkitti2(tmp_path / "data", synthetic.generate_clip(scfg, i), name)
  shutil.copytree(tmp_path / "data", tmp_path / "copy")
  out = tmp_path / "out"
  args = ["--config", str(CONFIGS / "vkitti2.py"), "--checkpoint", str(ckpt), "--out", str(out),
          "--config.iters=2", "--config.plots.enabled=false", "--config.max_sequences=2"]
  real_append = eval_runner.append_progress

  def second_fails(out_, settings, res):
    if res.name != vkitti2.TEST[0]:
      raise OSError(f"{res.name}: disk full")
    return real_append(out_, settings, res)

  with monkeypatch.context() as m:
    m.setattr(eval_runner, "append_progress", second_fails)
    assert main([*args, "--data-root", str(tmp_path / "data")]) == 2
  assert "disk full" in capsys.readouterr().err
  record = json.loads((out / eval_runner.PROGRESS).read_text().splitlines()[1])
  first = (tmp_path / "data" / "vkitti2" / vkitti2.TEST[0].replace("_", "/", 1) / "frames"
           / "rgb" / "Camera_0")
  assert record["source"] == str(first.resolve())
  assert main([*args, "--data-root", str(tmp_path / "copy"), "--resume"]) == 2
  err = capsys.readouterr().err
  assert f"cannot resume: sequence {vkitti2.TEST[0]} is read from " in err
  assert str(tmp_path / "copy") in err and f"read it from {first.resolve()}" in err
  evaluated = []
  real_evaluate = eval_runner.evaluate_sequence
  monkeypatch.setattr(eval_runner, "evaluate_sequence",
                      lambda seq, *a, **k: evaluated.append(seq.name) or real_evaluate(seq, *a,
                                                                                       **k))
  assert main([*args, "--data-root", str(tmp_path / "data" / "vkitti2"), "--resume"]) == 0
  assert evaluated == [vkitti2.TEST[1]]
  assert "(from the interrupted run)" in capsys.readouterr().out


def test_speed_excludes_compilation_and_curves_leave_frames_without_gt_out(tmp_path,
                                                                          monkeypatch):
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  config.plots.enabled, config.save_predictions = True, False
  seq = eval_data.load_sequences(config, None)[0]
  clip = eval_data.read_sequence(seq)

  clock = [100.0]  # the runner's clock, advanced by the stand-in only (no timing flakes)

  def fake_predict(method, clip, **_):  # takes 0.5 s, 0.4 s of them "compiling"
    clock[0] += 0.5
    inference._compile_seconds += 0.4  # pylint: disable=protected-access
    return clip["disparity"].copy()

  monkeypatch.setattr(eval_runner, "predict", fake_predict)
  monkeypatch.setattr(eval_runner, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
  res = eval_runner.evaluate_sequence(seq, ["sav"], variables=None, model_cfg=None,
                                      config=config, out=tmp_path)
  assert res.compile_seconds == {"sav": pytest.approx(0.4)}
  assert res.seconds["sav"] == pytest.approx(0.1)  # the compilation is not in the speed
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  summary = build_summary(config, "test", [res], ["sav"])
  assert summary["methods"]["sav"]["compile_seconds"] == pytest.approx(0.4)
  assert summary["methods"]["sav"]["frames_per_second"] == pytest.approx(
      res.frames / res.seconds["sav"])
  assert "prediction time without compilation (compilation: Stereo Any Video 0.4 s)" in \
      eval_report.markdown(summary)
  # The metrics' seconds are every method's (here 0.25 s each), not the last one's.
  real_eval_sequence = eval_runner.metrics.eval_sequence

  def timed_eval_sequence(*args, **kwargs):
    clock[0] += 0.25
    return real_eval_sequence(*args, **kwargs)

  monkeypatch.setattr(eval_runner.metrics, "eval_sequence", timed_eval_sequence)
  res = eval_runner.evaluate_sequence(seq, ["sav", "sgbm"], variables=None, model_cfg=None,
                                      config=config)
  assert res.metrics_seconds == pytest.approx(2 * 0.25)
  # A frame without any valid GT pixel has no EPE (the official rule would say 0), and the
  # pairs it is part of no TEPE; the curves leave a gap there.
  valid = clip["valid"].copy()
  valid[1] = False
  pred = clip["disparity"] + 1.0
  epe, tepe = eval_runner.per_frame_errors(pred, clip["disparity"], valid)
  assert np.isnan(epe[1]) and np.isnan(tepe[0]) and np.isnan(tepe[1])
  np.testing.assert_allclose(np.delete(epe, 1), 1.0, rtol=1e-6)
  # pred - gt is the same 1 px in every frame: no temporal error (float32 rounding only)
  np.testing.assert_allclose(tepe[2:], 0, atol=1e-5)
  gap, zero = tmp_path / "gap.png", tmp_path / "zero.png"
  eval_plots.write_curves(gap, {"m": (epe, tepe)})
  eval_plots.write_curves(zero, {"m": (np.nan_to_num(epe), np.nan_to_num(tepe))})
  assert np.any(cv2.imread(str(gap)) != cv2.imread(str(zero)))
  # A lone frame with GT between frames without (no line reaches it) still gets its point,
  # in long series too (which draw no points otherwise).
  for n in (10, 100):
    series = np.full(n, np.nan)
    series[5] = 1.0
    img = eval_plots._panel({"m": series}, "", "frame")  # pylint: disable=protected-access
    blank = eval_plots._panel({"m": np.full(n, np.nan)}, "", "frame")  # pylint: disable=protected-access
    assert np.count_nonzero(np.any(img != blank, axis=-1)) > 10, n
    # in the method's colour (the y labels differ too), left of its legend (x >= 550): the
    # point is drawn, and frames without a value draw nothing (no line along 0)
    colour = eval_plots._COLOURS[0]  # pylint: disable=protected-access
    drawn = np.nonzero(np.all(img[:, :500] == colour, axis=-1).any(axis=0))[0]
    x = 70 + (760 - 70 - 20) * 5 / (n - 1)  # frame 5 (margins 70 and 20 px of 760)
    assert drawn.size and np.all(np.abs(drawn - x) <= 4), (n, drawn, x)  # a point, no line
    assert not np.all(blank[:, :500] == colour, axis=-1).any(), n
  # One frame: no pairs, no TEPE (an empty curve, not an error)
  epe1, tepe1 = eval_runner.per_frame_errors(pred[:1], clip["disparity"][:1], clip["valid"][:1])
  assert epe1.shape == (1,) and tepe1.shape == (0,)


@pytest.mark.parametrize("value, axis_end", [(7.0, 8.0), (6.5, 8.0), (0.1 * 3, 0.1 * 3)])
def test_curve_panels_y_axis_ends_at_the_step_above_the_largest_value(value, axis_end):
  # 7 px (or 6.5): steps of 2 (1.4 per tick of 5, rounded up to 2), the axis up to 8 px;
  # the line at 7 / 8 of the plot's height (rows top .. top + height), not clipped at its top.
  # 0.1 * 3 (0.30000000000000004): steps of 0.1, and 3 of them end at the value itself (its
  # rounding error above 3 steps is no fourth), the line at the top.
  img = eval_plots._panel({"m": np.array([value, value])}, "", "frame")  # pylint: disable=protected-access
  width, height = eval_plots._PANEL  # pylint: disable=protected-access
  left, right, top, bottom = eval_plots._MARGIN  # pylint: disable=protected-access
  row = top + (height - top - bottom) * (1 - value / axis_end)
  colour = eval_plots._COLOURS[0]  # pylint: disable=protected-access
  rows = np.nonzero(np.all(img[:, 100:500] == colour, axis=-1).any(axis=1))[0]
  assert rows.size and np.all(np.abs(rows - row) <= 2), (rows, row)
  assert (img[top - 8:top + 6, :60] < 128).any()  # the axis end's tick label, left of the plot
  assert (img[height - bottom + 3, [left, width - right]] == 0).all()  # frames 0 and 1's ticks


def test_south_kensington_has_no_metrics_but_predictions_and_strips(tmp_path, ckpt, variables,
                                                                     capsys):
  # Real stereo videos without ground truth (the official script's qualitative run).
  rng = np.random.default_rng(3)
  seq = tmp_path / "data" / "SouthKensington" / "data" / "indoor_1"
  frames = {side: rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8) for side in ("left", "right")}
  for side, video in frames.items():
    (seq / "images" / side).mkdir(parents=True)
    for t, f in enumerate(video):
      cv2.imwrite(str(seq / "images" / side / f"{side}{t:06d}.png"), f[..., ::-1])
  (seq / "tracking_data.txt").write_text("Intrinsic: [[500. 0. 32.]\n [0. 500. 16.]\n"
                                         " [0. 0. 1.]]\n")
  out = tmp_path / "out"
  rc = main(["--config", str(CONFIGS / "south_kensington.py"), "--checkpoint", str(ckpt),
             "--data-root", str(tmp_path / "data"), "--out", str(out), "--config.iters=2",
             "--config.save_predictions=true"])
  assert rc == 0
  summary = json.loads((out / "results.json").read_text())
  assert summary["sequences"][0]["metrics"] == {} and summary["frames"] == T
  assert eval_config.load_config(str(CONFIGS / "south_kensington.py")).sample_len == 300
  expected = inference.predict_video(variables, frames["left"], frames["right"], iters=2)
  np.testing.assert_array_equal(np.load(out / "predictions" / "indoor_1.npy"), expected)
  assert cv2.imread(str(out / "plots" / "indoor_1_strip.png")) is not None
  assert not (out / "plots" / "indoor_1_curves.png").exists()
  md = (out / "results.md").read_text()
  assert "| Stereo Any Video | " in md and "No ground truth in this dataset: no metrics" in md
  assert f"| indoor_1 | {T} | Stereo Any Video |\n" in md  # the sequence is listed
  assert f"Frames read from {summary['sequences'][0]['source']}\n" in md
  # TCC asked for on it ran and measured nothing, silently; refused before the run now.
  rc = main(["--config", str(CONFIGS / "south_kensington.py"), "--checkpoint", str(ckpt),
             "--data-root", str(tmp_path / "data"), "--out", str(tmp_path / "tcc"),
             "--config.iters=2", "--config.metrics.tcc=true"])
  assert rc == 2 and not (tmp_path / "tcc").exists()
  assert "config.metrics.tcc: south_kensington has no ground truth" in capsys.readouterr().err


def _stand_in_flow(img1, img2):
  """A cheap, image-dependent flow for 32x64 frames (RAFT needs 128x128)."""
  diff = (np.asarray(img2, np.float32) - np.asarray(img1, np.float32)).mean(axis=0)
  return np.stack([0.02 * diff, np.full_like(diff, 0.5)])


def test_raft_checkpoint_path_expands_the_home_folder(tmp_path, raft_state_dict, monkeypatch):
  """`--config.metrics.raft=~/raft.npz`: the shell leaves `~` after `=`; it was not found."""
  from sav_jax.model import raft
  monkeypatch.setenv("HOME", str(tmp_path))
  sav_jax.convert.save_state_dict(raft_state_dict, tmp_path / "raft-things.npz")
  monkeypatch.setattr(raft, "raft_flow_fn", lambda variables, iters: _stand_in_flow)
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  config.metrics.raft = "~/raft-things.npz"
  assert eval_runner.raft_flow_fn(config) is not None


def test_raft_flow_metrics(tmp_path, no_model, raft_state_dict, monkeypatch):
  """`--config.metrics.raft=FILE` reads the RAFT checkpoint and adds TCM, OPW and RTC, each
  as `metrics.eval_sequence` computes it with that flow function (a stand-in for RAFT's
  flow here: these frames are below RAFT's smallest size) on the saved predictions."""
  from sav_jax.convert.raft import raft_variables_from_state_dict
  from sav_jax.model import raft
  path = sav_jax.convert.save_state_dict(raft_state_dict, tmp_path / "raft-things.safetensors")
  got = {}

  def flow_fn_of(variables, iters):
    got.update(variables=variables, iters=iters)
    return _stand_in_flow

  monkeypatch.setattr(raft, "raft_flow_fn", flow_fn_of)
  out = tmp_path / "o"
  assert main(_small_run(out, f"--config.metrics.raft={path}",
                         "--config.metrics.raft_iters=7")) == 0
  assert got["iters"] == 7
  jax.tree_util.tree_map(np.testing.assert_array_equal, got["variables"],
                         raft_variables_from_state_dict(raft_state_dict))
  summary = json.loads((out / "results.json").read_text())
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  for seq, rec in zip(eval_data.load_sequences(config, None), summary["sequences"]):
    clip = eval_data.read_sequence(seq)
    pred = np.load(out / "predictions" / f"{eval_data_safe(seq.name)}.npy")
    ref = metrics.eval_sequence(pred, clip["disparity"], clip["valid"].astype(np.float32),
                                scale=seq.depth2disp_scale, video=np.moveaxis(clip["left"], -1, 1),
                                flow_fn=_stand_in_flow)
    for key in ("disp_TCC", "disp_TCM", "disp_OPW", "disp_OPW_30", "disp_RTC", "disp_RTC_30"):
      assert key in rec["metrics"]["sav"], key
    assert rec["metrics"]["sav"] == pytest.approx(ref, rel=1e-12, abs=1e-12)
  md = (out / "results.md").read_text()
  assert "| TCM | OPW | RTC |" in md and "lower is better, except TCC, TCM, RTC" in md
  seconds = [s["metrics_seconds"] for s in summary["sequences"]]
  assert all(s > 0 for s in seconds) and summary["metrics_seconds"] == pytest.approx(sum(seconds))
  assert f"Metrics: {summary['metrics_seconds']:.1f} s (RAFT's flows included)." in md


@pytest.mark.parametrize("override,message", [
    ("--config.metrics.raft=missing.pth", "config.metrics.raft: missing.pth is not a file"),
    ("--config.metrics.raft=SAV",
     "is a Stereo Any Video checkpoint, not a RAFT (optical flow) one"),
    ("--config.metrics.raft_iters=0", "config.metrics.raft_iters must be a positive integer")])
def test_bad_raft_settings_are_refused_before_predicting(tmp_path, ckpt, sav_state_dict,
                                                         raft_state_dict, capsys, monkeypatch,
                                                         override, message):
  sav = sav_jax.convert.save_state_dict(sav_state_dict, tmp_path / "sav.safetensors")
  good = sav_jax.convert.save_state_dict(raft_state_dict, tmp_path / "raft.safetensors")
  override = override.replace("SAV", str(sav))
  extra = [] if "metrics.raft=" in override else [f"--config.metrics.raft={good}"]
  monkeypatch.setattr(eval_runner.inference, "predict_video", None)  # must not be reached
  monkeypatch.chdir(tmp_path)
  rc = main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *SMALL,
             "--out", str(tmp_path / "o"), *extra, override])
  err = capsys.readouterr().err
  assert rc == 2 and message in err and err.count("\n") == 1, err
  assert not (tmp_path / "o").exists()


_DEVICE_OOM = jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to "
                                         "allocate 9.1GiB.\nBufferAssignment OOM Debugging.\n")


def test_an_interrupt_while_the_arguments_are_read_is_one_line(monkeypatch, capsys,
                                                               run_command):
  # Ctrl-C in the first half second (the imports, the arguments) gave a traceback
  from eval import main as eval_main  # pylint: disable=import-outside-toplevel

  def build_parser():
    raise KeyboardInterrupt

  monkeypatch.setattr(eval_main, "build_parser", build_parser)
  monkeypatch.setattr("sys.argv", ["eval", "--config", "x", "--checkpoint", "y"])
  assert run_command(lambda: eval_main.main()) == 130
  assert capsys.readouterr().err == "eval: interrupted\n"
  with pytest.raises(KeyboardInterrupt):  # called from Python with arguments: the caller's
    eval_main.main(["--config", "x", "--checkpoint", "y"])


@pytest.mark.parametrize("raised, rc, message", [
    (MemoryError("Unable to allocate 64.0 GiB"), 2, "eval: error: out of host memory: Unable"),
    (KeyboardInterrupt(), 130, "eval: interrupted"),
    (_DEVICE_OOM, 2, "eval: error: out of memory on the device: RESOURCE_EXHAUSTED: Out of memory "
     "while trying to allocate 9.1GiB.; use fewer frames per window"),
    # the memory check before compiling: config fields, not predict_video's arguments
    (sav_jax.inference.InsufficientMemoryError("a window needs 9 GB", "fewer (window/stride)"),
     2, "eval: error: a window needs 9 GB; use fewer frames per window (--config.window, "
     "--config.stride), fewer --config.iters or --config.dtype=bfloat16\n"),
    (sav_jax.inference.InsufficientMemoryError("8 windows at once need 9 GB", "fewer devices",
                                               devices=8),
     2, "eval: error: 8 windows at once need 9 GB; use fewer --config.devices, fewer frames"),
    # a file that cannot be read or written: bad input, as the module docstring says
    (PermissionError(13, "Permission denied", "out/results.md"), 2,
     "eval: error: [Errno 13] Permission denied: 'out/results.md'"),
    # --overwrite: nothing to resume, the earlier results are back in place
    (KeyboardInterrupt(), 130, "--overwrite: eval: interrupted; the earlier results in the "
     "output folder were put back\n"),
    (_DEVICE_OOM, 2, "--overwrite: eval: error: out of memory on the device: RESOURCE_EXHAUSTED: "
     "Out of memory while trying to allocate 9.1GiB.; use fewer frames per window (--config."
     "window, --config.stride), fewer --config.iters or --config.dtype=bfloat16; the earlier "
     "results in the output folder are kept\n")])
def test_memory_errors_and_interrupts_are_one_line(monkeypatch, capsys, raised, rc, message,
                                                   run_command):
  from eval import main as eval_main  # pylint: disable=import-outside-toplevel

  def run(args, overrides):
    raise raised

  monkeypatch.setattr(eval_main, "run", run)
  argv = ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", "x"]
  if message.startswith("--overwrite: "):
    argv, message = [*argv, "--overwrite"], message[len("--overwrite: "):]
  monkeypatch.setattr("sys.argv", ["eval", *argv])
  assert run_command(lambda: eval_main.main()) == rc  # (its immediate exit after Ctrl-C as status)
  err = capsys.readouterr().err
  assert err.startswith(message) and err.count("\n") == 1, err
  if "out of memory on the device" in message and "--overwrite" not in argv:  # what --resume does
    assert err.endswith("; the sequences it finished are recorded: --resume continues\n"), err
  if rc == 130:  # called from Python with arguments, the caller gets the interrupt
    with pytest.raises(KeyboardInterrupt):
      eval_main.main(argv)


def test_sequence_names_that_differ_write_different_files():
  # "alley 1" and "alley_1" both wrote predictions/alley_1.npy: the second overwrote the first.
  runner = eval_runner
  config = types.SimpleNamespace(save_predictions=True,
                                 plots=types.SimpleNamespace(enabled=True))
  names = ["alley_1", "alley 1", "alley/1", "alley_1_", "FlyingThings3D/TEST/A/0000", "été"]
  paths = [p for n in names
           for p in runner.output_paths(pathlib.Path("out"), n, ["sav", "sgbm"], config).values()]
  assert len(set(paths)) == len(paths) == 4 * len(names)
  assert runner.safe_name("alley_1") == "alley_1"  # names that are safe keep their files
  assert re.fullmatch(r"x-[0-9a-f]{8}", runner.safe_name("_x"))  # a leading "_" is a change
  out = pathlib.Path("out")  # SAV's prediction has no suffix; no curves without GT
  assert runner.output_paths(out, "walk", ["sav", "sgbm"], config, has_gt=False) == {
      "sav": out / "predictions" / "walk.npy", "sgbm": out / "predictions" / "walk_sgbm.npy",
      "strip": out / "plots" / "walk_strip.png"}
  # Stable across processes (a resumed or a later run finds the files an earlier one
  # wrote): not Python's hash(), which PYTHONHASHSEED salts per process.
  here = [runner.safe_name("alley 1"), runner.safe_name("été")]
  for seed in ("1", "2"):
    res = subprocess.run([sys.executable, "-c", "from eval import runner; "
                          "print(runner.safe_name('alley 1'), runner.safe_name('été'))"],
                         capture_output=True, text=True, encoding="utf-8", check=True,
                         cwd=ROOT, env={**os.environ, "PYTHONHASHSEED": seed,
                                        "PYTHONIOENCODING": "utf-8"})
    assert res.stdout.split() == here, (seed, res.stderr)
  assert re.fullmatch(r"alley_1-[0-9a-f]{8}", runner.safe_name("alley 1"))
  # "walk"'s SGBM prediction and "walk_sgbm"'s own were both predictions/walk_sgbm.npy
  names = ["walk", "walk_sgbm"]
  paths = [p for n in names
           for p in runner.output_paths(pathlib.Path("out"), n, ["sav", "sgbm"], config).values()]
  assert len(set(paths)) == len(paths) == 4 * len(names)
  assert re.fullmatch(r"walk_sgbm-[0-9a-f]{8}", runner.safe_name("walk_sgbm"))


@pytest.fixture
def colour_ranges(monkeypatch):
  """The (vmin, vmax) of every `sav_jax.viz.colorize` call, in order."""
  ranges = []
  real = sav_jax.viz.colorize

  def recording(d, vmin=None, vmax=None, **kw):
    ranges.append((vmin, vmax))
    return real(d, vmin, vmax, **kw)

  monkeypatch.setattr(sav_jax.viz, "colorize", recording)
  return ranges


def test_strip_colours_by_the_prediction_where_the_shown_frames_have_no_valid_gt(
    tmp_path, colour_ranges):
  """Fully occluded frames: the ground truth's range was (0, 1) px, and a 10..50 px
  prediction one saturated colour."""
  ranges = colour_ranges
  t, h, w = 3, 16, 24
  pred = np.broadcast_to(np.linspace(10, 50, w, dtype=np.float32), (t, h, w))
  clip = {"left": np.zeros((t, h, w, 3), np.uint8), "disparity": np.full((t, h, w), 5.0),
          "valid": np.zeros((t, h, w), bool)}
  eval_plots.write_strip(tmp_path / "s.png", clip, {"SAV": pred}, frames=3, tile=32)
  assert all(10 <= lo < 12 and 48 < hi <= 50 for lo, hi in ranges), ranges
  ranges.clear()
  spiked = pred.copy()
  spiked[:, 0, 0] = 1000.0  # one pixel of each frame, above the 99th percentile: no end
  eval_plots.write_strip(tmp_path / "s.png", clip, {"SAV": spiked}, frames=3, tile=32)
  assert ranges and all(10 <= lo < 12 and 48 < hi <= 50 for lo, hi in ranges), ranges
  ranges.clear()
  # the shown frames' prediction only: 2 columns of 5 frames show frames 0 and 4, and the
  # 1000 px of frames 1..3 set no end
  far = np.concatenate([pred[:1], np.full((3, h, w), 1000.0, np.float32), pred[:1]])
  eval_plots.write_strip(tmp_path / "s.png", {k: np.concatenate([v, v[:2]]) for k, v in
                                              clip.items()}, {"SAV": far}, frames=2, tile=32)
  assert ranges and all(10 <= lo < 12 and 48 < hi <= 50 for lo, hi in ranges), ranges
  ranges.clear()
  clip["valid"][:] = True  # with valid pixels: the ground truth's range (5 px everywhere)
  eval_plots.write_strip(tmp_path / "s.png", clip, {"SAV": pred}, frames=3, tile=32)
  assert ranges and all((lo, hi) == (5, 6) for lo, hi in ranges), ranges  # a constant: +1 px
  ranges.clear()
  clip["disparity"][:] = 0.0  # valid, but no disparity > 0 to take a range from
  eval_plots.write_strip(tmp_path / "s.png", clip, {"SAV": pred}, frames=3, tile=32)
  assert ranges and all(10 <= lo < 12 and 48 < hi <= 50 for lo, hi in ranges), ranges


def test_strip_colour_range_is_the_valid_ground_truths_1st_to_99th_percentile(
    tmp_path, colour_ranges):
  """Each frame's ground truth is 1..101 px, stored as -d: the percentile p of such values is
  1 + p, so the range is 2..100 px; with pixels above 51 px invalid, 1..51 px (each value three
  times: the 1st and 99th percentiles fall between equal values). Invalid pixels are white in
  the ground-truth row and black in the error row."""
  ranges = colour_ranges
  t, h, w = 3, 1, 101
  gt = np.broadcast_to(np.arange(1, w + 1, dtype=np.float32), (t, h, w))
  for valid, want in ((np.ones((t, h, w), bool), (2, 100)), (gt <= 51, (1, 51))):
    ranges.clear()
    clip = {"left": np.zeros((t, h, w, 3), np.uint8), "disparity": -gt, "valid": valid}
    path = eval_plots.write_strip(tmp_path / "s.png", clip, {"SAV": gt + 50}, frames=3,
                                  tile=128)
    assert ranges and all(r == want for r in ranges), (ranges, want)
  img = cv2.imread(str(path))[..., ::-1]
  label_w = img.shape[1] - t * w
  ground_truth, error = img[24 + 1, label_w:], img[24 + 3, label_w:]  # rows of one pixel
  assert tuple(ground_truth[w - 1]) == (255, 255, 255) and tuple(error[w - 1]) == (0, 0, 0)
  assert tuple(ground_truth[0]) != (255, 255, 255) and tuple(error[0]) != (0, 0, 0)


def test_strip_shows_each_methods_error_in_kittis_colours(tmp_path):
  t, h, w = 3, 16, 24
  gt = np.full((t, h, w), 20.0, np.float32)
  pred = gt.copy()
  pred[:, :, w // 2:] += 10.0  # the right half: 10 px off, an outlier
  clip = {"left": np.zeros((t, h, w, 3), np.uint8), "disparity": -gt,  # stored as -d
          "valid": np.ones((t, h, w), bool)}
  path = eval_plots.write_strip(tmp_path / "s.png", clip, {"SAV": pred}, frames=3, tile=32)
  img = cv2.imread(str(path))[..., ::-1]
  assert img.shape[0] == 24 + 4 * h  # header; left, ground truth, SAV, SAV error
  error_row = img[24 + 3 * h:, 150:]
  good, bad = (tuple(c) for c in np.asarray(sav_jax.viz.KITTI_ERROR_COLORS)[[0, 6]])
  assert tuple(error_row[h // 2, 2]) == good and tuple(error_row[h // 2, w - 2]) == bad
  no_gt = {"left": clip["left"], "disparity": None, "valid": None}
  path = eval_plots.write_strip(tmp_path / "n.png", no_gt, {"SAV": pred}, frames=3, tile=32)
  assert cv2.imread(str(path)).shape[0] == 24 + 2 * h  # no ground truth: no error row


def test_the_report_names_skipped_sequences(tmp_path):
  config = eval_config.load_config(str(CONFIGS / "dynamic_replica.py"))
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  summary = build_summary(config, "w", [], ["sav"], None, ["seq_a", "seq_c"])
  assert summary["skipped_sequences"] == ["seq_a", "seq_c"]
  text = eval_report.markdown(summary)
  assert ("- 2 sequences shorter than sample_len=150 frames skipped, as the official "
          "evaluation does: seq_a, seq_c.") in text, text
  assert "0 sequences, 0 frames" in text
  eval_report.write_all(tmp_path, summary)
  assert json.loads((tmp_path / "results.json").read_text())["skipped_sequences"] == [
      "seq_a", "seq_c"]
  # A name that is not UTF-8 (kept by Python as surrogates): results.md shows it escaped
  summary["skipped_sequences"] = ["caf\udce9"]
  out = tmp_path / "eval" / "dynamic_replica"  # (folders made as needed)
  eval_report.write_all(out, summary)
  assert "as the official evaluation does: caf\\udce9." in (out / "results.md").read_text()
  assert json.loads((out / "results.json").read_text())["skipped_sequences"] == ["caf\udce9"]


# results.md's column headings and the official metric keys they show.
REPORT_COLUMNS = {
    "EPE": "disp_epe_mean", "bad-0.5 %": "disp_epe_bad_0.5px", "bad-1 %": "disp_epe_bad_1px",
    "bad-2 %": "disp_epe_bad_2px", "bad-3 %": "disp_epe_bad_3px", "TEPE": "disp_temp_epe_mean",
    "δt-0.5px %": "disp_temp_epe_bad_0.5px", "δt-1px %": "disp_temp_epe_bad_1px",
    "δt-2px %": "disp_temp_epe_bad_2px", "δt-3px %": "disp_temp_epe_bad_3px",
    "TCC": "disp_TCC", "TCM": "disp_TCM", "OPW": "disp_OPW", "RTC": "disp_RTC"}


def _table(md, first):
  """The rows of the Markdown table whose heading row starts with `first`, as cell lists."""
  lines = md.splitlines()
  start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first} |"))
  rows = []
  for line in lines[start:]:
    if not line.startswith("|"):
      break
    rows.append([c.strip() for c in line.strip("|").split("|")])
  return rows[0], rows[2:]


def test_report_columns_show_the_metrics_they_name(tmp_path):
  """Each column of results.md holds the metric its heading names (a distinct value per key),
  in the aggregate and per-sequence tables; results.csv's aggregate rows carry the frames their
  means weigh (those with ground truth), the per-sequence rows their own."""
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  keys = list(REPORT_COLUMNS.values()) + ["disp_OPW_30", "disp_OPW_50", "disp_OPW_100",
                                          "disp_RTC_30"]
  results = [eval_runner.SequenceResult(
      name=name, frames=frames,
      metrics={"sav": {k: i + 0.25 * j + 0.0625 for i, k in enumerate(keys)}},
      seconds={"sav": 1.0}) for j, (name, frames) in enumerate((("seq_a", 3), ("seq_b", 5)))]
  config = eval_config.load_config(str(CONFIGS / "dynamic_replica.py"))
  summary = build_summary(config, "w", results, ["sav"])
  aggregate = summary["methods"]["sav"]["aggregate"]
  assert summary["frames"] == 8 and aggregate["disp_TCC"] == pytest.approx(10 + 0.0625 + 0.15625)
  md = eval_report.markdown(summary)
  assert "iters 20, window 20 / stride 10, float32; 2 sequences, 8 frames." in md, md
  head, rows = _table(md, "Method")
  assert head == ["Method", *REPORT_COLUMNS, "frames/s"] and len(rows) == 1
  assert rows[0][0] == "Stereo Any Video" and rows[0][-1] == "4.00"
  for heading, cell in zip(head[1:-1], rows[0][1:-1]):
    assert cell == f"{aggregate[REPORT_COLUMNS[heading]]:.3f}", heading
  head, rows = _table(md, "Sequence")
  assert head == ["Sequence", "Frames", "Method", *REPORT_COLUMNS] and len(rows) == 2
  for res, row in zip(results, rows):
    assert row[:3] == [res.name, str(res.frames), "Stereo Any Video"]
    for heading, cell in zip(head[3:], row[3:]):
      assert cell == f"{res.metrics['sav'][REPORT_COLUMNS[heading]]:.3f}", heading
  eval_report.write_csv(tmp_path / "results.csv", summary)
  with open(tmp_path / "results.csv", encoding="utf-8") as fh:
    assert next(csv.reader(fh)) == ["method", "sequence", "frames", *REPORT_COLUMNS.values(),
                                    "disp_OPW_100", "disp_OPW_30", "disp_OPW_50", "disp_RTC_30"]
  rows = list(csv.DictReader(open(tmp_path / "results.csv", encoding="utf-8")))
  assert [(r["sequence"], r["frames"]) for r in rows] == [
      ("seq_a", "3"), ("seq_b", "5"), (eval_report.ALL, "8")]
  for k in keys:
    assert float(rows[-1][k]) == pytest.approx(aggregate[k], rel=1e-12), k
    assert [float(r[k]) for r in rows[:2]] == [res.metrics["sav"][k] for res in results], k
  assert summary["methods"]["sav"]["measured_frames"] == 8 and "(8 with" not in md
  del summary["methods"]["sav"]["measured_frames"]  # results.json of a run before the field
  eval_report.write_csv(tmp_path / "results.csv", summary)
  assert list(csv.DictReader(open(tmp_path / "results.csv", encoding="utf-8")))[-1]["frames"] == "8"
  # A sequence without ground truth (no metrics): predicted, not in the means, and the
  # aggregate rows say which frames they weigh.
  results.append(eval_runner.SequenceResult(name="seq_c", frames=4, seconds={"sav": 1.0}))
  summary = build_summary(config, "w", results, ["sav"])
  assert summary["methods"]["sav"]["aggregate"] == aggregate
  assert summary["frames"] == 12 and summary["methods"]["sav"]["measured_frames"] == 8
  assert "3 sequences, 12 frames (8 with ground truth)." in eval_report.markdown(summary)
  eval_report.write_csv(tmp_path / "results.csv", summary)
  rows = list(csv.DictReader(open(tmp_path / "results.csv", encoding="utf-8")))
  assert [(r["sequence"], r["frames"]) for r in rows] == [
      ("seq_a", "3"), ("seq_b", "5"), (eval_report.ALL, "8")]


def test_report_shows_a_metric_that_any_method_has():
  """A column of results.md is shown when at least one method has its metric; a method
  without it shows "–" there (the columns were those of every method: none at all here). The
  aggregate heading names the metrics where higher is better: TCC, TCM and RTC (the share of
  consistent pixels), not OPW (a warping error)."""
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  sav = {"disp_epe_mean": 1.5, "disp_TCC": 0.75, "disp_TCM": 0.5, "disp_OPW": 2.25,
         "disp_RTC": 0.25}
  results = [eval_runner.SequenceResult(name="seq_a", frames=3,
                                        metrics={"sav": sav, "sgbm": {"disp_epe_mean": 2.5}},
                                        seconds={"sav": 1.0, "sgbm": 1.0})]
  config = eval_config.load_config(str(CONFIGS / "dynamic_replica.py"))
  md = eval_report.markdown(build_summary(config, "w", results, ["sav", "sgbm"]))
  head, rows = _table(md, "Method")
  assert head == ["Method", "EPE", "TCC", "TCM", "OPW", "RTC", "frames/s"], head
  assert rows[0][1:6] == ["1.500", "0.750", "0.500", "2.250", "0.250"]
  assert rows[1][:6] == ["StereoSGBM", "2.500", "–", "–", "–", "–"]
  assert "lower is better, except TCC, TCM, RTC)" in md
  # Each table's separator row has one cell per heading (one more and it is no table).
  lines = md.splitlines()
  for first in ("| Method |", "| Sequence |"):
    i = next(i for i, line in enumerate(lines) if line.startswith(first))
    assert lines[i + 1].count("|") == lines[i].count("|"), (lines[i], lines[i + 1])
  # Without ground truth anywhere no "(0 with ground truth)": the frames are all there is.
  results = [eval_runner.SequenceResult(name="seq_b", frames=4, seconds={"sav": 1.0})]
  md = eval_report.markdown(build_summary(config, "w", results, ["sav"]))
  assert "1 sequence, 4 frames." in md and "with ground truth" not in md, md
  assert "No ground truth in this dataset: no metrics (predictions and plots only)." in md, md
  assert _table(md, "Sequence") == (["Sequence", "Frames", "Method"],
                                    [["seq_b", "4", "Stereo Any Video"]])  # a row, no values
  # The notes of every sequence are listed, in order.
  results = [eval_runner.SequenceResult(name=n, frames=2, seconds={"sav": 1.0}, notes=[n + "!"])
             for n in ("seq_b", "seq_c")]
  md = eval_report.markdown(build_summary(config, "w", results, ["sav"]))
  assert "Notes:\n- seq_b!\n- seq_c!\n" in md, md


def test_summary_totals_are_sums_over_the_sequences():
  """build_summary adds up each method's prediction and compile seconds and the metrics'
  seconds over the sequences; frames/s is all frames over all of a method's seconds."""
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  results = [eval_runner.SequenceResult(
      name=name, frames=frames, metrics={"sav": {"disp_epe_mean": 1.0}},
      seconds={"sav": sav, "sgbm": sav / 4}, compile_seconds={"sav": compiled},
      metrics_seconds=metrics_s)
      for name, frames, sav, compiled, metrics_s in (("seq_a", 3, 1.0, 2.0, 0.5),
                                                     ("seq_b", 5, 3.0, 0.5, 1.0))]
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  config.metrics.tcc = True  # (not RAFT: the Metrics seconds name no flows)
  summary = build_summary(config, "w", results, ["sav", "sgbm"])
  assert summary["frames"] == 8 and summary["metrics_seconds"] == 1.5
  sav, sgbm = summary["methods"]["sav"], summary["methods"]["sgbm"]
  assert (sav["seconds"], sav["compile_seconds"], sav["frames_per_second"]) == (4.0, 2.5, 2.0)
  assert (sgbm["seconds"], sgbm["compile_seconds"], sgbm["frames_per_second"]) == (1.0, 0.0, 8.0)
  assert sav["measured_frames"] == 8 and sgbm["measured_frames"] == 0  # sgbm: no metrics
  md = eval_report.markdown(summary)
  assert "(compilation: Stereo Any Video 2.5 s). Metrics: 1.5 s.\n" in md, md
  config.metrics.raft = "raft-things.pth"
  md = eval_report.markdown(build_summary(config, "w", results, ["sav", "sgbm"]))
  assert "Metrics: 1.5 s (RAFT's flows included).\n" in md, md
  _, rows = _table(md, "Method")
  assert [row[-1] for row in rows] == ["2.00", "8.00"]


def test_a_training_config_is_named_and_the_fields_it_lacks_counted():
  """check_fields names the first 6 missing fields and counts the rest; a config with an
  `optimizer` block (or `train`) is said to be a training one."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  from configs.eval import common  # pylint: disable=import-outside-toplevel

  def leaves(c):
    return sum(leaves(v) if isinstance(v, ml_collections.ConfigDict) else 1 for v in c.values())

  n = leaves(common.eval_config("x", sample_len=-1))  # (it has none of them)
  with pytest.raises(ValueError, match=rf"t.py is not an evaluation config: it lacks "
                                       rf"([\w.]+, ){{5}}[\w.]+ and {n - 6} more; it is a "
                                       r"training config \(python -m train\)"):
    eval_config.check_fields(ml_collections.ConfigDict({"optimizer": {"lr": 0.1}}), "t.py")
  six = common.eval_config("x", sample_len=-1)  # without the blocks metrics (3) and plots (3)
  del six.metrics, six.plots
  with pytest.raises(ValueError) as e:
    eval_config.check_fields(six, "e.py")
  assert str(e.value) == (
      "e.py is not an evaluation config: it lacks metrics.raft, metrics.raft_iters, "
      "metrics.tcc, plots.enabled, plots.strip_frames, plots.tile_size; evaluation configs "
      "build on configs/eval/common.py (e.g. configs/eval/sintel_final.py)")


def test_short_dynamic_replica_sequences_are_dropped_and_named(tmp_path):
  """Dynamic Replica sequences shorter than sample_len are skipped (as the official loader does)
  and named for the report; one of exactly sample_len frames is kept, as are the short
  sequences of other datasets (Sintel's), whole."""
  from tests.data.test_readers import (  # pylint: disable=import-outside-toplevel
      _dynamic_replica, _sintel)
  rng = np.random.default_rng(0)
  _dynamic_replica(tmp_path, rng, "test", [("long", 4, "ndc_isotropic"),
                                           ("short", 2, "ndc_isotropic"),
                                           ("exact", 3, "ndc_isotropic")])
  config = eval_config.load_config(str(CONFIGS / "dynamic_replica.py"))
  config.sample_len = 3
  kept, skipped = eval_data.load_sequences_and_skipped(config, tmp_path)
  assert [(s.name, len(s)) for s in kept] == [("long", 3), ("exact", 3)]
  assert skipped == ["short"]
  config.sample_len = 5  # longer than all: the longest (4 frames) is named
  with pytest.raises(ValueError, match=r"all 3 dynamic_replica/test sequences under .* are "
                     r"shorter than config.sample_len=5 frames .* to at most 4 \(or 0"):
    eval_data.load_sequences_and_skipped(config, tmp_path)
  _sintel(tmp_path, rng, seqs=(("alley_1", 3), ("cave_2", 2)))
  config = eval_config.load_config(str(CONFIGS / "sintel_final.py"))
  config.sample_len = 3
  kept, skipped = eval_data.load_sequences_and_skipped(config, tmp_path)
  assert [(s.name, len(s)) for s in kept] == [("alley_1", 3), ("cave_2", 2)] and skipped == []


def test_an_output_folder_inside_the_dataset_is_refused(tmp_path, capsys, monkeypatch):
  left = tmp_path / "sintel_stereo" / "training" / "final_left"
  left.mkdir(parents=True)
  out = left / "evalout"
  monkeypatch.chdir(tmp_path)  # (and each path relative to it)
  for root, where in ((tmp_path, out), (tmp_path / "sintel_stereo", out), (".", out),
                      (tmp_path, out.relative_to(tmp_path))):
    assert main(["--config", str(CONFIGS / "sintel_final.py"), "--checkpoint", "w",
                 "--data-root", str(root), "--out", str(where)]) == 2
    err = capsys.readouterr().err
    folder = pathlib.Path(root) / "sintel_stereo" if root != tmp_path / "sintel_stereo" else root
    assert (f"--out {where} is inside the dataset's folder {os.path.normpath(folder)}: keep "
            "outputs out of the dataset") in err, err
    assert not out.exists()
  # The folder dataset: a split folder it has not made yet is where its reader would look.
  (tmp_path / "mine" / "test").mkdir(parents=True)
  assert main(["--config", str(CONFIGS / "folder.py"), "--checkpoint", "w", "--data-root",
               str(tmp_path / "mine"), "--out", str(tmp_path / "mine" / "val" / "o")]) == 2
  assert "is inside the dataset's folder" in capsys.readouterr().err
  assert not (tmp_path / "mine" / "val").exists()


def test_no_data_root_where_its_default_folder_is_missing_says_to_pass_one(
    tmp_path, monkeypatch, capsys, no_model):
  """Run from a folder without data/datasets/ (a wheel's user): the missing --data-root is
  named, not only the default path ("dataset folder not found: data/datasets"). Where there
  is one, it is read."""
  monkeypatch.chdir(tmp_path)
  for config, where in (("folder.py", "the folder that holds your videos' test/"),
                        ("sintel_final.py", "the datasets folder or the dataset's own")):
    assert main(["--config", str(CONFIGS / config), "--checkpoint", "c"]) == 2
    assert capsys.readouterr().err == (
        "eval: error: no --data-root given, and its default data/datasets/ is not a folder "
        f"here: pass --data-root DIR, {where}\n")
  assert list(tmp_path.iterdir()) == []
  _folder_dataset(tmp_path / "data" / "datasets", np.random.default_rng(5))
  assert main(["--config", str(CONFIGS / "folder.py"), "--checkpoint", "c", "--out", "o",
               "--config.iters=2", "--config.plots.enabled=false"]) == 0
  assert no_model.evaluated == ["a", "b", "c"]


def test_the_report_names_the_folder_the_frames_came_from():
  read_from = eval_report._read_from  # pylint: disable=protected-access
  assert read_from([]) is None
  assert read_from(["/d/sintel/training/final_left/a", "/d/sintel/training/final_left/b"]) == \
      "/d/sintel/training/final_left"
  assert read_from(["/mnt/a/s1", "/media/b/s2"]) == "/media/b/s2, /mnt/a/s1"  # only "/" shared
  assert read_from(["rel/s1", "/abs/s2"]) == "/abs/s2, rel/s1"  # commonpath raises on a mix
  assert read_from(["/d/s4", "/c/s3", "/b/s2", "/a/s1"]) == "/a/s1, /b/s2, /c/s3, ... (1 more)"


def test_sequences_whose_scores_are_not_measurements_are_noted(tmp_path, monkeypatch, caplog):
  """No valid ground-truth pixel (every metric 0 by the official rule) or one frame (TEPE 0):
  the numbers stay the official ones, and a warning, results.json and results.md say so; a
  NaN prediction is named with its sequence and method."""
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  config.plots.enabled, config.save_predictions = False, False
  seq = eval_data.load_sequences(config, None)[0]
  clip = eval_data.read_sequence(seq)
  fake = {"pred": clip["disparity"] + 2.0}
  monkeypatch.setattr(eval_runner, "predict", lambda method, clip, **_: fake["pred"])
  occluded = dict(clip, valid=np.zeros_like(clip["valid"]))
  monkeypatch.setattr(eval_runner.eval_data, "read_sequence", lambda s: occluded)
  with caplog.at_level("WARNING"):
    res = eval_runner.evaluate_sequence(seq, ["sav"], variables=None, model_cfg=None,
                                        config=config)
  assert res.metrics["sav"]["disp_epe_mean"] == 0  # the official rule
  assert res.notes == [f"sequence {seq.name}: valid has no pixel > 0.5 (no valid ground "
                       "truth): the official rule scores EPE, TEPE and their bad-pixel rates 0 "
                       f"(perfect), though nothing was measured; its {T} frames count in the "
                       "aggregate"]
  assert res.notes[0] in caplog.text
  eval_runner.append_progress(tmp_path, {"s": 1}, res)  # kept for --resume
  assert eval_runner.read_progress(tmp_path, {"s": 1})[res.name].notes == res.notes
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  summary = build_summary(config, "test", [res], ["sav"])
  assert summary["sequences"][0]["notes"] == res.notes
  assert f"Notes:\n- {res.notes[0]}" in eval_report.markdown(summary)
  one = dict(clip, **{k: clip[k][:1] for k in ("left", "right", "disparity", "valid")})
  monkeypatch.setattr(eval_runner.eval_data, "read_sequence", lambda s: one)
  fake["pred"] = one["disparity"] + 2.0
  res = eval_runner.evaluate_sequence(seq, ["sav"], variables=None, model_cfg=None,
                                      config=config)
  assert res.metrics["sav"]["disp_temp_epe_mean"] == 0 and len(res.notes) == 1
  assert "one frame (T=1), no frame pair: the official rule scores TEPE and its bad-pixel " \
      "rates (δt) 0" in res.notes[0] and res.notes[0].endswith(
          "; its 1 frame counts in the aggregate")  # (was "its 1 frames count")
  alternate = dict(clip, valid=clip["valid"].copy())
  alternate["valid"][1::2] = False  # valid pixels in every other frame: no TEPE pair
  assert eval_runner.gt_notes("s", alternate["valid"]) == [
      "sequence s: valid has no pixel valid in two consecutive frames (TEPE's pairs): the "
      "official rule scores TEPE and its bad-pixel rates (δt) 0, though nothing was measured; "
      f"its {T} frames count in the aggregate"]
  assert eval_runner.gt_notes("s", clip["valid"]) == []
  # One frame without GT: TEPE pools its pixels, but TCC (with the depth metrics) scores each
  # of its two pairs 1, "perfect", in a mean over T-1 pairs.
  gap = dict(clip, valid=clip["valid"].copy())
  gap["valid"][1] = False
  assert eval_runner.gt_notes("s", gap["valid"]) == []  # EPE and TEPE only: measured
  config.metrics.tcc = True
  monkeypatch.setattr(eval_runner.eval_data, "read_sequence", lambda s: gap)
  fake["pred"] = gap["disparity"] + 2.0
  with caplog.at_level("WARNING"):
    res = eval_runner.evaluate_sequence(seq, ["sav"], variables=None, model_cfg=None,
                                        config=config)
  assert res.notes == [f"sequence {seq.name}: 2 of the {T - 1} frame pairs have no pixel valid "
                       "in both frames: the official rule scores each such pair TCC 1 "
                       "(perfect) in the sequence's mean over its pairs, though nothing was "
                       f"measured there; its {T} frames count in the aggregate"]
  assert res.notes[0] in caplog.text and "disp_TCC" in res.metrics["sav"]
  config.metrics.tcc = False
  monkeypatch.setattr(eval_runner.eval_data, "read_sequence", lambda s: clip)
  fake["pred"] = clip["disparity"].copy()
  fake["pred"][1, 0, 0] = np.nan
  with pytest.raises(ValueError, match=rf"^sequence {seq.name}, Stereo Any Video: pred has NaN"):
    eval_runner.evaluate_sequence(seq, ["sav"], variables=None, model_cfg=None, config=config)


def test_strip_labels_are_not_cut(tmp_path):
  """"Stereo Any Video error" was cut to "Stereo Any Video err" by a fixed 150 px column."""
  t, h, w = 2, 16, 24
  gt = np.full((t, h, w), 20.0, np.float32)
  clip = {"left": np.zeros((t, h, w, 3), np.uint8), "disparity": gt,
          "valid": np.ones((t, h, w), bool)}
  path = eval_plots.write_strip(tmp_path / "s.png", clip, {"Stereo Any Video": gt + 1},
                                frames=2, tile=32)
  img = cv2.imread(str(path))
  text_w = cv2.getTextSize("Stereo Any Video error", cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)[0][0]
  label_w = img.shape[1] - 2 * w
  assert label_w >= text_w + 6, (label_w, text_w)
  error_row = img[24 + 3 * h:24 + 4 * h]
  assert (error_row[:, label_w - 4:label_w] == 255).all()  # white margin after the text


def _folder_dataset(root, rng):
  """Three sequences of the folder layout (`configs/eval/folder.py`) of 3, 5 and 2 frames:
  `a` with positive ground truth, `b` stored as -d (the evaluator scores |gt|), `c` without
  any. A fifth of the pixels has no ground truth (0), a tenth is predicted exactly (by the
  stand-in prediction `_stand_in_prediction`: an error of 0, left out of the official
  denominators). Returns `{name: (left, right, gt or None, valid or None)}` as written."""
  written = {}
  for name, frames, sign in (("a", 3, 1.0), ("b", 5, -1.0), ("c", 2, None)):
    folder = root / "test" / name
    left = rng.integers(0, 256, (frames, H, W, 3), dtype=np.uint8)
    right = np.roll(left, -4, axis=2)  # something for SGBM to match
    gt = valid = None
    if sign is not None:
      d = rng.uniform(1.0, 30.0, (frames, H, W)).astype(np.float32)
      exact = rng.random((frames, H, W)) < 0.1
      d[exact] = _stand_in_prediction(left)[exact]
      d[exact & (d == 0)] = 1.0  # (0 is "no ground truth")
      valid = rng.random((frames, H, W)) >= 0.2
      gt = np.where(valid, sign * d, 0).astype(np.float32)
      (folder / "disparity").mkdir(parents=True)
    for t in range(frames):
      for view, video in (("left", left), ("right", right)):
        (folder / view).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / view / f"{t:04d}.png"), video[t][..., ::-1])
      if gt is not None:
        np.save(folder / "disparity" / f"{t:04d}.npy", gt[t])
    written[name] = (left, right, gt, valid)
  return written


def _stand_in_prediction(left):
  """A prediction that depends on the frames only, so a test knows it without the model."""
  return np.asarray(left, np.float32)[..., 0] / 8 + np.asarray(left, np.float32)[..., 1] / 64


def _numbers(text):
  return [float(v) for v in re.findall(r"-?\d+\.\d+", text)]


def test_reported_numbers_are_the_official_metrics_of_the_files(tmp_path, ckpt, capsys,
                                                               monkeypatch):
  """A dataset of the folder layout, sequences of different lengths, partly valid ground truth
  (one sequence stored as -d, one without any), the model replaced by a known function of the
  frames and SGBM run as configured: every number of results.json, results.csv, results.md and
  the printed lines is the official metric computed here by hand in numpy from the files written,
  the aggregate a frame-weighted mean over the sequences with ground truth; the prediction files
  are the predictions, the strips and curves the plots of them with the configured settings."""
  from sav_jax.tools.demo import stereo_sgbm  # pylint: disable=import-outside-toplevel
  written = _folder_dataset(tmp_path / "mine", np.random.default_rng(7))
  calls = []

  def stand_in(variables, left, right, **kw):
    calls.append(kw)
    return _stand_in_prediction(left)

  monkeypatch.setattr(eval_runner.inference, "predict_video", stand_in)
  out = tmp_path / "out"
  # a file of the user's named as a curves plot of "c", which has no ground truth and so no
  # curves: --overwrite neither refuses it as a file it would write over nor touches it
  (out / "plots").mkdir(parents=True)
  (out / "plots" / "c_curves.png").write_bytes(b"the user's")
  capsys.readouterr()
  assert main(["--config", str(CONFIGS / "folder.py"), "--checkpoint", str(ckpt),
               "--data-root", str(tmp_path / "mine"), "--out", str(out), "--baseline", "sgbm",
               "--config.iters=3", "--config.window=4", "--config.stride=3",
               "--config.baseline.max_disparity=16", "--config.baseline.block_size=7",
               "--config.save_predictions=true", "--config.plots.strip_frames=2",
               "--config.plots.tile_size=24", "--overwrite"]) == 0
  printed = capsys.readouterr().out
  assert [(k["iters"], k["window"], k["stride"]) for k in calls] == [(3, 4, 3)] * 3
  summary = json.loads((out / "results.json").read_text())
  assert [(s["name"], s["frames"]) for s in summary["sequences"]] == [("a", 3), ("b", 5),
                                                                      ("c", 2)]
  expected, weighted = {}, {m: {} for m in ("sav", "sgbm")}
  for rec, (name, (left, right, gt, valid)) in zip(summary["sequences"], written.items()):
    preds = {"sav": _stand_in_prediction(left),
             "sgbm": stereo_sgbm(left, right, max_disparity=16, block_size=7)}
    for method, suffix in (("sav", ""), ("sgbm", "_sgbm")):
      np.testing.assert_array_equal(np.load(out / "predictions" / f"{name}{suffix}.npy"),
                                    preds[method])
    clip = {"left": left, "disparity": gt, "valid": valid}
    labelled = {eval_config.METHOD_NAMES[m]: p for m, p in preds.items()}
    eval_plots.write_strip(tmp_path / "strip.png", clip, labelled, frames=2, tile=24)
    np.testing.assert_array_equal(cv2.imread(str(out / "plots" / f"{name}_strip.png")),
                                  cv2.imread(str(tmp_path / "strip.png")))
    if gt is None:
      assert rec["metrics"] == {}
      assert (out / "plots" / f"{name}_curves.png").read_bytes() == b"the user's"
      continue
    curves = {eval_config.METHOD_NAMES[m]: eval_runner.per_frame_errors(p, gt, valid)
              for m, p in preds.items()}
    eval_plots.write_curves(tmp_path / "curves.png", curves, title=name)
    np.testing.assert_array_equal(cv2.imread(str(out / "plots" / f"{name}_curves.png")),
                                  cv2.imread(str(tmp_path / "curves.png")))
    for method, pred in preds.items():
      ref = expected[name, method] = {f"disp_{k}": v for k, v in
                                       epe_tepe_by_hand(pred, gt, valid).items()}
      assert rec["metrics"][method] == pytest.approx(ref, rel=1e-5, abs=1e-9), (name, method)
      for k, v in ref.items():
        weighted[method][k] = weighted[method].get(k, 0.0) + v * rec["frames"]
  aggregate = {m: {k: v / (3 + 5) for k, v in w.items()} for m, w in weighted.items()}
  for method in ("sav", "sgbm"):
    assert summary["methods"][method]["aggregate"] == pytest.approx(aggregate[method],
                                                                    rel=1e-5, abs=1e-9)
  # results.csv: a row per sequence with ground truth and method, then the aggregates
  rows = list(csv.DictReader(open(out / "results.csv", encoding="utf-8")))
  assert [(r["sequence"], r["method"]) for r in rows] == [
      ("a", "sav"), ("a", "sgbm"), ("b", "sav"), ("b", "sgbm"), (eval_report.ALL, "sav"),
      (eval_report.ALL, "sgbm")]
  assert [r["frames"] for r in rows[:4]] == ["3", "3", "5", "5"]
  for row in rows:
    ref = (aggregate[row["method"]] if row["sequence"] == eval_report.ALL
           else expected[row["sequence"], row["method"]])
    assert {k: float(row[k]) for k in ref} == pytest.approx(ref, rel=1e-5, abs=1e-9), row
  # results.md: both tables, each cell the metric its heading names, to 3 decimals
  names = {"Stereo Any Video": "sav", "StereoSGBM": "sgbm"}
  md = (out / "results.md").read_text()
  head, table = _table(md, "Method")
  assert [r[0] for r in table] == list(names)
  for row in table:
    for heading, cell in zip(head[1:-1], row[1:-1]):
      assert abs(float(cell) - aggregate[names[row[0]]][REPORT_COLUMNS[heading]]) <= 5.01e-4, (
          row[0], heading)
  head, table = _table(md, "Sequence")
  assert [r[:3] for r in table] == [
      [s, f, m] for s, f in (("a", "3"), ("b", "5")) for m in names] + [
          ["c", "2", "Stereo Any Video"], ["c", "2", "StereoSGBM"]]
  for row in table:
    for heading, cell in zip(head[3:], row[3:]):
      if row[0] == "c":
        assert cell == "–"
      else:
        ref = expected[row[0], names[row[2]]][REPORT_COLUMNS[heading]]
        assert abs(float(cell) - ref) <= 5.01e-4, (row[:3], heading)
  # printed: a line per sequence with each method's EPE and TEPE, then the aggregate table
  lines = [line for line in printed.splitlines() if line.startswith("[")]
  assert [line.split("  ")[0] for line in lines] == [
      "[1/3] a (3 frames)", "[2/3] b (5 frames)", "[3/3] c (2 frames)"]
  for line, name in zip(lines, ("a", "b")):
    assert "Stereo Any Video: EPE" in line and "StereoSGBM: EPE" in line
    got = _numbers(line.split("frames)", 1)[1])
    ref = [expected[name, m][k] for m in ("sav", "sgbm")
           for k in ("disp_epe_mean", "disp_temp_epe_mean")]
    assert np.allclose(got, ref, rtol=0, atol=5.01e-4), (line, ref)
  assert md.split("## Per sequence")[0].rstrip() in printed


def test_synthetic_sequences_are_the_generators_clips_with_its_valid_mask():
  """Each synthetic sequence holds clip i of the generator as it renders it, with its valid mask
  (occluded pixels, out of the right view, have no ground truth) and the official rule on top;
  sample_len and max_sequences <= 0 mean every frame and every sequence."""
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  config.synthetic.num_sequences = 3
  for sample_len, max_sequences in ((-1, -1), (0, 0)):
    config.sample_len, config.max_sequences = sample_len, max_sequences
    seqs = eval_data.load_sequences(config, None)
    assert [(s.name, len(s)) for s in seqs] == [(f"synthetic_00{i}", T) for i in range(3)]
  for i, seq in enumerate(seqs[:2]):
    clip = synthetic.generate_clip(seq.cfg, i)
    assert seq.cfg.seed == config.synthetic.seed
    assert not clip["valid"].all()  # (occlusions: what the mask leaves out)
    got = eval_data.read_sequence(seq)
    for key in ("left", "right", "disparity"):
      np.testing.assert_array_equal(got[key], clip[key], err_msg=key)
    d = clip["disparity"]
    np.testing.assert_array_equal(got["valid"], clip["valid"] & (d != 0) & (np.abs(d) < 512))
  config.sample_len, config.max_sequences = 2, 2
  heads = eval_data.load_sequences(config, None)
  assert [(s.name, len(s)) for s in heads] == [("synthetic_000", 2), ("synthetic_001", 2)]
  np.testing.assert_array_equal(eval_data.read_sequence(heads[1])["left"],
                                synthetic.generate_clip(seqs[1].cfg, 1)["left"][:2])


def test_the_synthetic_evaluation_set_is_not_the_training_set():
  """configs/eval/synthetic.py's clips come from another seed than the training config's
  generator (configs/synthetic.py): evaluated on its clips, a model would be scored on the very
  clips it was trained on. Its SGBM baseline searches the whole disparity range."""
  from configs import synthetic as training  # pylint: disable=import-outside-toplevel
  train_seed = training.get_config().data.synthetic.seed
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  assert config.synthetic.seed != train_seed
  assert eval_data.load_sequences(config, None)[0].cfg.seed == config.synthetic.seed
  # (and its SGBM baseline searches the whole disparity range of the clips)
  assert config.baseline.max_disparity >= config.synthetic.max_disparity


def test_per_frame_curves_scale_the_prediction_by_the_rounded_mask():
  """per_frame_errors multiplies the prediction by round(valid), as the evaluator does: a
  weight 0.64 (kept: > 0.5) leaves it whole, and the error is sqrt(0.64 * (1 - 0)^2) = 0.8
  (by valid itself, 0.64 * 0.8 = 0.512); a weight 0.3 drops the pixel (a frame of them
  has no valid pixel)."""
  pred = np.ones((3, 1, 3), np.float32)
  valid = np.array([0.64, 0.64, 0.3], np.float32)[None, None].repeat(3, axis=0)
  pred[:, :, 2] = 50.0
  valid[2] = 0.3  # frame 2: no pixel above 0.5, no measurement (NaN), not a perfect 0
  epe, tepe = eval_runner.per_frame_errors(pred, np.zeros_like(pred), valid)
  np.testing.assert_allclose(epe, [0.8, 0.8, np.nan], rtol=1e-6)
  np.testing.assert_array_equal(tepe, [0.0, np.nan])  # the same prediction in frames 0, 1


def test_per_frame_curves_are_the_official_rule_per_frame(monkeypatch):
  """The curves' values, written out in numpy: each frame's errors |pred x round(valid) - |gt||
  summed over its valid pixels and divided by their non-zero count (an exact pixel is left out,
  as in the official denominators); NaN for a frame (pair) without a valid pixel; a frame
  predicted exactly scores 0. `evaluate_sequence` keeps them per method."""
  rng = np.random.default_rng(11)
  t, h, w = 5, 6, 7
  gt = -rng.uniform(1.0, 20.0, (t, h, w)).astype(np.float32)  # stored as -d
  valid = rng.random((t, h, w)) > 0.3
  valid[2] = False  # no ground truth in frame 2
  pred = np.abs(gt) + rng.normal(0, 2, (t, h, w)).astype(np.float32)
  exact = rng.random((t, h, w)) < 0.2
  pred[exact] = np.abs(gt)[exact]  # some pixels exact
  pred[4] = np.abs(gt[4])  # frame 4 exact everywhere
  pred[~valid] = 99.0  # what the mask leaves out
  epe, tepe = eval_runner.per_frame_errors(pred, gt, valid)
  x, y = np.where(valid, pred, 0), np.where(valid, np.abs(gt), 0)
  e = np.abs(x - y)
  want_epe = [e[i].sum() / np.count_nonzero(e[i]) if valid[i].any() and e[i].any()
              else (0.0 if valid[i].any() else np.nan) for i in range(t)]
  both = valid[1:] & valid[:-1]
  te = np.where(both, np.abs(np.abs(x[1:] - x[:-1]) - np.abs(y[1:] - y[:-1])), 0)
  want_tepe = [te[i].sum() / np.count_nonzero(te[i]) if both[i].any() else np.nan
               for i in range(t - 1)]
  assert np.isnan(want_epe[2]) and want_epe[4] == 0 and np.isnan(want_tepe[1])
  np.testing.assert_allclose(epe, want_epe, rtol=1e-5)
  np.testing.assert_allclose(tepe, want_tepe, rtol=1e-5)
  # evaluate_sequence: each method's curves, of its own prediction against the ground truth
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  config.plots.enabled = False
  seq = types.SimpleNamespace(name="s", depth2disp_scale=None)
  clip = {"left": np.zeros((t, h, w, 3), np.uint8), "right": np.zeros((t, h, w, 3), np.uint8),
          "disparity": gt, "valid": valid}
  preds = {"sav": pred, "sgbm": np.abs(gt) + 1.5}
  monkeypatch.setattr(eval_runner.eval_data, "read_sequence", lambda s: clip)
  monkeypatch.setattr(eval_runner, "predict", lambda method, clip, **_: preds[method])
  res = eval_runner.evaluate_sequence(seq, ["sav", "sgbm"], variables=None, model_cfg=None,
                                      config=config)
  np.testing.assert_allclose(res.curves["sav"][0], want_epe, rtol=1e-5)
  np.testing.assert_allclose(res.curves["sav"][1], want_tepe, rtol=1e-5)
  np.testing.assert_allclose(res.curves["sgbm"][0], np.where(valid.any((1, 2)), 1.5, np.nan),
                             rtol=1e-5)


def test_override_values_of_each_type():
  """Booleans take true/false, 1/0, yes/no, on/off (any case); an integer field refuses a
  fraction instead of cutting it, and takes a whole number in scientific notation; a float
  field takes an integer; a string field keeps the text as written; a nested field is named
  with its block."""
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  for text, value in (("yes", True), ("No", False), ("ON", True), ("off", False), ("1", True),
                      ("0", False), ("True", True), ("false", False), (" on\n", True)):
    eval_config.apply_overrides(config, [("plots.enabled", text)])
    assert config.plots.enabled is value, text
  for bad in ("4.5", "1.25e1", "1e-1", "four"):
    with pytest.raises(ValueError, match=f"--config.iters: expected int, got '{bad}'"):
      eval_config.apply_overrides(config, [("iters", bad)])
  for text, value in (("4e0", 4), ("2E1", 20), ("1.2e2", 120)):  # whole: as training reads them
    eval_config.apply_overrides(config, [("iters", text)])
    assert config.iters == value and type(config.iters) is int, text
  eval_config.apply_overrides(config, [("synthetic.max_disparity", "7"), ("metrics.raft", "1"),
                                       ("dtype", "bfloat16")])
  assert config.synthetic.max_disparity == 7.0 and isinstance(config.synthetic.max_disparity,
                                                               float)
  assert config.metrics.raft == "1" and config.dtype == "bfloat16"
  with config.unlocked():  # a tuple field of a config file of one's own: a Python literal
    config.synthetic.textures = ("checker",)
  eval_config.apply_overrides(config, [("synthetic.textures", "('checker', 'noise')")])
  assert config.synthetic.textures == ("checker", "noise")
  with pytest.raises(ValueError, match="--config.synthetic.textures: "):  # not a literal
    eval_config.apply_overrides(config, [("synthetic.textures", "checker")])
  for name in ("plots", "metrics.raft.x", "iters.x", "synthetic"):  # a block, or below a leaf
    with pytest.raises(ValueError, match=f"--config.{name}: no such config field"):
      eval_config.apply_overrides(config, [(name, "1")])


def test_progress_records_are_appended_and_read_back(tmp_path):
  """Records appended one by one (the header once) are read back, by name; a record cut short by
  a kill is dropped and the file ends where the last whole line does, so that the next record
  starts a line of its own and is read back too."""
  settings = {"config": {"iters": 2}, "weights": "w", "methods": ["sav"]}
  results = [eval_runner.SequenceResult(name=n, frames=f, metrics={"sav": {"disp_epe_mean": e}},
                                        seconds={"sav": 0.5}, compile_seconds={"sav": 0.0},
                                        metrics_seconds=0.25, source=f"/d/{n}", notes=[n])
             for n, f, e in (("a", 3, 1.5), ("b", 4, 2.5), ("c", 5, 3.5))]
  for res in results[:2]:
    eval_runner.append_progress(tmp_path, settings, res)
  done = eval_runner.read_progress(tmp_path, settings)
  assert list(done) == ["a", "b"]
  for res in results[:2]:
    assert done[res.name] == res
  progress = tmp_path / eval_runner.PROGRESS
  whole = progress.read_text()
  progress.write_text(whole + '{"name": "c", "fra')  # killed while writing c's record
  assert list(eval_runner.read_progress(tmp_path, settings)) == ["a", "b"]
  assert progress.read_text() == whole
  eval_runner.append_progress(tmp_path, settings, results[2])
  assert eval_runner.read_progress(tmp_path, settings) == {r.name: r for r in results}
  # a setting that the interrupted run did not record (a field another version added) or
  # that this run no longer has is a difference too
  for config in ({"iters": 2, "window": 4}, {}):
    with pytest.raises(ValueError, match=r"config\.(window: None then, 4|iters: 2 then, None) "
                                         r"now\)"):
      eval_runner.read_progress(tmp_path, dict(settings, config=config))
  # a file of another version of the format (its records may mean other things): refused
  progress.write_text(whole.replace('"sav_jax_eval_progress": 1,', '"sav_jax_eval_progress": 2,'))
  with pytest.raises(ValueError, match="is not an evaluation progress file of this version"):
    eval_runner.read_progress(tmp_path, settings)


def test_a_sequence_counts_its_frames_and_flow_metrics_need_no_tcc(tmp_path, monkeypatch):
  """A sequence weighs its T frames in the frame-weighted aggregate, over the sequences with
  the method's metrics (ground truth) only; a flow function alone (no `metrics.tcc`) gives the depth
  metrics; a prediction is saved as float32, SAV's under the sequence's own name."""
  config = eval_config.apply_overrides(eval_config.load_config(str(CONFIGS / "synthetic.py")),
                                       eval_config.split_overrides(SMALL)[1])
  config.plots.enabled, config.metrics.tcc = False, False
  seq = eval_data.load_sequences(config, None)[0]
  # 2 px off at every valid pixel (the synthetic disparity is positive): EPE 2
  monkeypatch.setattr(eval_runner, "predict",
                      lambda method, clip, **_: clip["disparity"].astype(np.float64) + 2.0)
  res = eval_runner.evaluate_sequence(seq, ["sav"], variables=None, model_cfg=None,
                                      config=config, out=tmp_path, flow_fn=_stand_in_flow)
  assert res.frames == T
  assert res.metrics["sav"]["disp_epe_mean"] == pytest.approx(2.0, rel=1e-5)
  for key in ("disp_TCC", "disp_TCM", "disp_OPW"):
    assert key in res.metrics["sav"], key
  saved = np.load(tmp_path / "predictions" / f"{seq.name}.npy")
  assert saved.dtype == np.float32 and saved.shape == (T, H, W)
  # a sequence without ground truth: predicted, not scored
  clip = dict(eval_data.read_sequence(seq), disparity=None, valid=None)
  monkeypatch.setattr(eval_runner.eval_data, "read_sequence", lambda s: clip)
  monkeypatch.setattr(eval_runner, "predict", lambda method, clip, **_: np.ones((T, H, W)))
  res = eval_runner.evaluate_sequence(seq, ["sav"], variables=None, model_cfg=None,
                                      config=config, flow_fn=_stand_in_flow)
  assert res.frames == T and res.metrics == {} and res.curves == {}
  # (1 * 1 frame + 3 * 3 frames) / 4 frames; a sequence without ground truth is left out
  results = [eval_runner.SequenceResult(name=n, frames=f, metrics=m)
             for n, f, m in (("a", 1, {"sav": {"disp_epe_mean": 1.0}}),
                             ("b", 3, {"sav": {"disp_epe_mean": 3.0}}), ("c", 5, {}))]
  assert eval_runner.aggregate(results, "sav") == {"disp_epe_mean": pytest.approx(2.5)}
  assert eval_runner.aggregate(results, "sgbm") == {}


@pytest.mark.parametrize("field,value", [("frames", True), ("metrics_seconds", False)])
def test_a_progress_record_with_a_boolean_for_a_number_is_refused(tmp_path, field, value):
  # JSON's true and false are not the numbers 1 and 0: a hand-edited record, refused
  record = {"name": "a", "frames": 4, "metrics": {}, "seconds": {}, "compile_seconds": {},
            "metrics_seconds": 0.5, field: value}
  (tmp_path / eval_runner.PROGRESS).write_text(
      '{"sav_jax_eval_progress": 1, "x": 1}\n' + json.dumps(record) + "\n")
  with pytest.raises(ValueError, match="line 2 is not a finished sequence's record"):
    eval_runner.read_progress(tmp_path, {"x": 1})


def test_only_the_runs_own_files_are_removed_or_written_over(tmp_path):
  """written_files.txt names what --overwrite deletes: a line that leads out of predictions/ or
  plots/ (a hand edit), goes deeper than a file in them, or names a link, deletes nothing; a
  file listed twice is deleted once; a file or a broken link of the user's where a run would
  write is refused."""
  out = tmp_path / "out"
  (out / "predictions").mkdir(parents=True)
  (out / "plots").mkdir()
  (tmp_path / "victim.txt").write_text("mine")
  (out / "mine.txt").write_text("mine")
  (out / "predictions" / "a.npy").write_bytes(b"run")
  (out / "plots" / "link.png").symlink_to(out / "mine.txt")
  (out / "predictions" / "keep.npy").write_bytes(b"mine")
  (out / eval_runner.WRITTEN_LIST).write_text(  # (a resumed run lists a redone file again)
      "predictions/a.npy\n../victim.txt\nmine.txt\npredictions/../../victim.txt\n"
      "plots/link.png\npredictions/keep.npy/x\npredictions/a.npy\n")
  assert eval_runner.remove_written(out) == [out / "predictions" / "a.npy"]
  assert (out / "predictions" / "keep.npy").read_bytes() == b"mine"
  assert not (out / "predictions" / "a.npy").exists()
  assert not (out / eval_runner.WRITTEN_LIST).exists()  # (it would name a user's file later)
  assert (tmp_path / "victim.txt").read_text() == "mine" and (out / "mine.txt").is_file()
  assert (out / "plots" / "link.png").is_symlink()
  dangling = out / "predictions" / "b.npy"
  dangling.symlink_to(tmp_path / "elsewhere.npy")
  eval_runner.record_written(out, [out / "predictions" / "c.npy"])
  (out / "predictions" / "c.npy").write_bytes(b"run")
  eval_runner.refuse_unlisted_outputs(out, [out / "predictions" / "c.npy"])  # its own: fine
  with pytest.raises(FileExistsError, match="b.npy exists, and no earlier evaluation wrote it"):
    eval_runner.refuse_unlisted_outputs(out, [out / "predictions" / "c.npy", dangling])


@pytest.mark.parametrize("before", ["", "predictions/a.npy\nplots/a_str"])
def test_a_written_list_left_empty_or_cut_by_a_kill_takes_the_next_path(tmp_path, before):
  """A kill right after written_files.txt was created leaves it empty (no last byte to read),
  one while a line was written leaves it cut: either way the next path is a line of its own."""
  (tmp_path / eval_runner.WRITTEN_LIST).write_text(before)
  eval_runner.record_written(tmp_path, [tmp_path / "plots" / "b.png"])
  assert (tmp_path / eval_runner.WRITTEN_LIST).read_text().splitlines() == [
      *before.splitlines(), "plots/b.png"]


def test_a_resumed_run_may_differ_only_in_devices_and_max_sequences():
  variables = {"params": {"w": np.arange(3, dtype=np.float32)}}
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  settings = eval_runner.run_settings(config, variables, ["sav"])
  config.devices, config.max_sequences = 0, 1
  assert eval_runner.run_settings(config, variables, ["sav"]) == settings
  for name, value in (("iters", 3), ("sample_len", 2), ("save_predictions", True)):
    other = eval_config.load_config(str(CONFIGS / "synthetic.py"))
    setattr(other, name, value)
    assert eval_runner.run_settings(other, variables, ["sav"]) != settings, name
  assert eval_runner.run_settings(config, variables, ["sav", "sgbm"]) != settings
  other = {"params": {"w": np.arange(1, 4, dtype=np.float32)}}
  assert eval_runner.run_settings(config, other, ["sav"]) != settings


def test_curve_panels_show_epe_over_tepe(tmp_path):
  """The curves PNG is the EPE panel above the TEPE panel: each depends on its own series."""
  epe, tepe = np.array([1.0, 3.0, 2.0, 5.0]), np.array([0.5, 4.0, 1.0])
  images = {}
  for name, curves in (("base", (epe, tepe)), ("epe", (epe[::-1], tepe)),
                       ("tepe", (epe, tepe[::-1]))):
    path = eval_plots.write_curves(tmp_path / f"{name}.png", {"m": curves}, title="s")
    images[name] = cv2.imread(str(path))
  half = images["base"].shape[0] // 2
  assert images["base"].shape[0] == 2 * half
  top, bottom = slice(0, half), slice(half, None)
  assert np.array_equal(images["epe"][bottom], images["base"][bottom])
  assert not np.array_equal(images["epe"][top], images["base"][top])
  assert np.array_equal(images["tepe"][top], images["base"][top])
  assert not np.array_equal(images["tepe"][bottom], images["base"][bottom])


def test_strip_rows_show_the_frames_and_the_absolute_ground_truth(tmp_path):
  """The strip's first row is the left frames in their colours; the ground-truth row is |gt|
  (stored as -d it looks the same); a prediction equal to |gt| looks like it; a tile larger than
  tile_size is scaled down to it (longest side)."""
  t, h, w = 2, 16, 24
  rng = np.random.default_rng(5)
  left = np.zeros((t, h, w, 3), np.uint8)
  left[..., 0], left[..., 2] = 200, 30  # reddish, RGB
  gt = rng.uniform(5, 40, (t, h, w)).astype(np.float32)
  valid = np.ones((t, h, w), bool)
  strips = []
  for sign in (1, -1):
    clip = {"left": left, "disparity": sign * gt, "valid": valid}
    path = eval_plots.write_strip(tmp_path / f"s{sign}.png", clip, {"SAV": gt.copy()},
                                  frames=t, tile=32)
    strips.append(cv2.imread(str(path))[..., ::-1])  # RGB
  assert np.array_equal(strips[0], strips[1])
  img = strips[0]
  rows = [img[24 + k * h:24 + (k + 1) * h] for k in range(4)]  # left, GT, SAV, SAV error
  label_w = img.shape[1] - t * w
  assert (rows[0][:, label_w:] == (200, 0, 30)).all()
  assert np.array_equal(rows[1][:, label_w:], rows[2][:, label_w:])
  small = eval_plots.write_strip(tmp_path / "small.png", {"left": left, "disparity": gt,
                                                          "valid": valid},
                                 {"SAV": gt}, frames=t, tile=12)
  img = cv2.imread(str(small))
  assert img.shape[0] == 24 + 4 * 8 and img.shape[1] == label_w + t * 12  # 24x16 -> 12x8
  # The columns are frames spread evenly, rounded to the nearest: 4 of 11 frames are 0, 10/3,
  # 20/3 and 10, frames 0, 3, 7 and 10 (each frame here grey 20 x its index)
  ramp = np.repeat((np.arange(11) * 20).astype(np.uint8), h * w * 3).reshape(11, h, w, 3)
  img = cv2.imread(str(eval_plots.write_strip(tmp_path / "ramp.png", {"left": ramp},
                                              {"SAV": np.repeat(gt[:1], 11, 0)}, frames=4)))
  assert img[24 + h // 2, img.shape[1] - 4 * w + w // 2::w, 0].tolist() == [0, 60, 140, 200]


def test_default_output_folder_and_files(tmp_path, ckpt, monkeypatch):
  """Without --out the reports go to outputs/eval/<dataset>; predictions are written only when
  asked for, plots by default; --resume with nothing to resume (an empty folder) runs."""
  monkeypatch.setattr(eval_runner.inference, "predict_video",
                      lambda variables, left, right, **kw: _stand_in_prediction(left))
  monkeypatch.chdir(tmp_path)
  small = [a for a in SMALL if "save_predictions" not in a]
  assert main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt),
               *small]) == 0
  out = tmp_path / "outputs" / "eval" / "synthetic"
  assert sorted(p.name for p in out.iterdir()) == [
      "plots", "results.csv", "results.json", "results.md", "written_files.txt"]
  assert sorted(p.name for p in (out / "plots").iterdir()) == [
      f"synthetic_00{i}_{kind}.png" for i in range(2) for kind in ("curves", "strip")]
  (tmp_path / "empty").mkdir()
  assert main(["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", str(ckpt), *small,
               "--out", "empty", "--resume", "--config.plots.enabled=false"]) == 0
  assert (tmp_path / "empty" / "results.json").is_file()


def _interrupted_after_a(tmp_path, capsys, monkeypatch) -> list[str]:
  """Evaluates the folder dataset under `tmp_path / "mine"` with stand-in weights and
  predictions (`no_model`) into `tmp_path / "out"`, interrupted after sequence a (the next
  one's progress write fails: "disk full"); returns the run's arguments, for a --resume."""
  real_append = eval_runner.append_progress

  def only_a(out_, settings, res):
    if res.name != "a":
      raise OSError(f"{res.name}: disk full")
    return real_append(out_, settings, res)

  args = ["--config", str(CONFIGS / "folder.py"), "--checkpoint", "w", "--data-root",
          str(tmp_path / "mine"), "--out", str(tmp_path / "out"), "--config.iters=2",
          "--config.plots.enabled=false"]
  with monkeypatch.context() as m:
    m.setattr(eval_runner, "append_progress", only_a)
    assert main(args) == 2
  capsys.readouterr()
  # Its progress file is all it left (no plots or predictions): a run without --resume is
  # refused all the same, not run over it.
  assert [p.name for p in (tmp_path / "out").iterdir()] == [eval_runner.PROGRESS]
  assert main(args) == 2
  assert "pass --resume to continue that interrupted run" in capsys.readouterr().err
  return args


def test_resume_refuses_a_sequence_whose_frames_changed(tmp_path, no_model, capsys,
                                                        monkeypatch):
  """A sequence the interrupted run finished that has gained or lost a frame since (same folder,
  same settings) is not taken from the progress file: its numbers would be of other frames."""
  written = _folder_dataset(tmp_path / "mine", np.random.default_rng(8))
  args = _interrupted_after_a(tmp_path, capsys, monkeypatch)
  folder = tmp_path / "mine" / "test" / "a"
  left, right, gt, _ = written["a"]
  for view, video in (("left", left), ("right", right)):
    cv2.imwrite(str(folder / view / "0003.png"), video[0][..., ::-1])
  np.save(folder / "disparity" / "0003.npy", gt[0])
  assert main([*args, "--resume"]) == 2
  assert ("cannot resume: sequence a has 4 frames, the interrupted run evaluated 3; pass "
          "--overwrite to start again") in capsys.readouterr().err
  for t in (3, 2):  # or lost one
    for view in ("left", "right"):
      (folder / view / f"{t:04d}.png").unlink()
    (folder / "disparity" / f"{t:04d}.npy").unlink()
  assert main([*args, "--resume"]) == 2
  assert "cannot resume: sequence a has 2 frames, the interrupted run evaluated 3" in (
      capsys.readouterr().err)


def test_resume_refuses_a_sequence_whose_ground_truth_came_or_went(tmp_path, no_model, capsys,
                                                                 monkeypatch):
  """A sequence the interrupted run finished without ground truth (a folder sequence without
  disparity/) that has it now, or the reverse, is not taken from the progress file: it was
  read back without metrics and left out of the aggregates (or kept its old ones)."""
  _folder_dataset(tmp_path / "mine", np.random.default_rng(9))  # a, b with GT; c without
  gt_a = tmp_path / "mine" / "test" / "a" / "disparity"
  gt_a.rename(tmp_path / "gt_a")  # a has no ground truth in the interrupted run
  args = _interrupted_after_a(tmp_path, capsys, monkeypatch)
  (tmp_path / "gt_a").rename(gt_a)
  assert main([*args, "--resume"]) == 2
  assert ("cannot resume: sequence a has ground truth now, the interrupted run had none; pass "
          "--overwrite to start again") in capsys.readouterr().err
  shutil.rmtree(tmp_path / "out")
  _interrupted_after_a(tmp_path, capsys, monkeypatch)  # a measured, then its ground
  shutil.rmtree(gt_a)  # truth taken away
  assert main([*args, "--resume"]) == 2
  assert ("cannot resume: sequence a has no ground truth now, the interrupted run measured it; "
          "pass --overwrite to start again") in capsys.readouterr().err
  assert main([*args, "--overwrite"]) == 0  # starts again: the records are not read


def test_a_sequence_read_through_a_link_has_the_source_of_its_files(tmp_path):
  """`sequence_source` names the folder of the files themselves: the dataset reached through a
  link (--data-root on another path to the same files) gives the same source, so --resume
  accepts it; a copy of the dataset gives another."""
  from sav_jax.data import registry  # pylint: disable=import-outside-toplevel
  _folder_dataset(tmp_path / "mine", np.random.default_rng(9))
  (tmp_path / "link").symlink_to(tmp_path / "mine")
  shutil.copytree(tmp_path / "mine", tmp_path / "copy")
  sources = {root: [eval_runner.sequence_source(s)
                    for s in registry.get_sequences("folder", tmp_path / root, "test")]
             for root in ("mine", "link", "copy")}
  real = tmp_path.resolve() / "mine" / "test"
  assert sources["mine"] == sources["link"] == [str(real / n / "left") for n in "abc"]
  assert sources["copy"] == [str(tmp_path.resolve() / "copy" / "test" / n / "left")
                             for n in "abc"]
  assert eval_runner.sequence_source(types.SimpleNamespace(name="synthetic_000")) is None


def test_a_failed_overwrite_of_an_interrupted_run_puts_that_run_back(tmp_path):
  """An interrupted run (its progress file, predictions, no reports yet) replaced with
  --overwrite by a run that fails after writing some reports: its progress file comes back (it
  can still be resumed), and none of the failed run's files or reports stay."""
  out = tmp_path / "out"
  (out / "predictions").mkdir(parents=True)
  (out / "predictions" / "a.npy").write_bytes(b"earlier")
  eval_runner.record_written(out, [out / "predictions" / "a.npy"])
  (out / eval_runner.PROGRESS).write_text('{"earlier": 1}\n')
  (out / "notes.txt").write_text("mine")
  before = _snapshot(out)
  assert eval_runner.set_aside_written(out) == [out / "predictions" / "a.npy"]
  assert sorted(p.name for p in out.iterdir()) == [eval_runner.SET_ASIDE, "notes.txt",
                                                   "predictions"]
  # the failed run: a prediction, its progress, two of its three reports
  (out / "predictions" / "b.npy").write_bytes(b"failed")
  eval_runner.record_written(out, [out / "predictions" / "b.npy"])
  (out / eval_runner.PROGRESS).write_text('{"failed": 1}\n')
  for name in eval_runner.REPORTS[:2]:
    (out / name).write_text("failed")
  assert eval_runner.restore_set_aside(out) == [out / "predictions" / "a.npy"]
  assert _snapshot(out) == before


def test_report_shows_a_zero_as_a_number_and_a_missing_metric_as_a_dash():
  """A metric of 0 (a perfect score, or the official rule's 0 without valid pixels) is shown as
  0.000; only a metric a method lacks is a dash."""
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  results = [eval_runner.SequenceResult(
      name="s", frames=2, seconds={"sav": 1.0, "sgbm": 1.0},
      metrics={"sav": {"disp_epe_mean": 0.0, "disp_temp_epe_mean": 1.25},
               "sgbm": {"disp_epe_mean": 2.5}})]
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  md = eval_report.markdown(build_summary(config, "w", results, ["sav", "sgbm"]))
  for first in ("Method", "Sequence"):
    head, rows = _table(md, first)
    cells = [dict(zip(head, row)) for row in rows]
    assert [(c["EPE"], c["TEPE"]) for c in cells] == [("0.000", "1.250"), ("2.500", "–")], first


def test_plots_are_written_to_a_folder_whose_name_is_not_utf8(tmp_path):
  """Latin-1 bytes in --out (a zip made on Windows): OpenCV's imwrite crashed the process with
  a segmentation fault when the plots were written, after the model had run; so did its
  putText on a sequence name of such bytes (the curves' title), drawn with `?` for them."""
  from sav_jax.data import frame_io
  t, h, w = 2, 16, 24
  gt = np.full((t, h, w), 20.0, np.float32)
  clip = {"left": np.zeros((t, h, w, 3), np.uint8), "disparity": gt,
          "valid": np.ones((t, h, w), bool)}
  odd = tmp_path / os.fsdecode(b"caf\xe9")
  odd.mkdir()
  for folder in (tmp_path, odd):
    eval_plots.write_strip(folder / "s.png", clip, {"SAV": gt + 1}, frames=2, tile=32)
    for title, name in (("s?", "c.png"), (os.fsdecode(b"s\xe9"), "c_odd.png")):
      eval_plots.write_curves(folder / name, {"m": (np.ones(t), np.ones(t - 1))}, title=title)
  for name in ("s.png", "c.png", "c_odd.png"):
    assert np.array_equal(frame_io.read_image(odd / name), frame_io.read_image(tmp_path / name))
  assert np.array_equal(frame_io.read_image(odd / "c.png"), frame_io.read_image(odd / "c_odd.png"))


def test_folders_and_sequences_whose_names_are_not_utf8(tmp_path, sav_state_dict, capsys):
  """Latin-1 bytes (a zip made on Windows) in --data-root, a sequence's folder, --out and the
  checkpoint file's folder: the whole run was lost at its end, "eval: error: 'utf-8' codec
  can't encode character '\\udce9'" when the sequence's line was printed or results.md
  written (left empty). The reports show such bytes as \\udce9; results.json keeps them."""
  from sav_jax import viz
  root, out = tmp_path / os.fsdecode(b"d\xe9"), tmp_path / os.fsdecode(b"o\xe9")
  checkpoint = tmp_path / os.fsdecode(b"c\xe9") / "sav.npz"
  checkpoint.parent.mkdir()
  np.savez(checkpoint, **sav_state_dict)
  name = os.fsdecode(b"b\xe9")
  scfg = synthetic.SyntheticConfig(frames=T, height=H, width=W, max_disparity=6.0, num_objects=2)
  clip, seq = synthetic.generate_clip(scfg, 0), root / "test" / name
  for t in range(T):
    for view in ("left", "right"):
      (seq / view).mkdir(parents=True, exist_ok=True)
      (seq / view / f"{t}.png").write_bytes(cv2.imencode(".png", clip[view][t])[1].tobytes())
    (seq / "disparity").mkdir(exist_ok=True)
    viz.write_pfm(seq / "disparity" / f"{t}.pfm",
                  np.where(clip["valid"][t], clip["disparity"][t], 0))
  rc = main(["--config", str(CONFIGS / "folder.py"), "--checkpoint", str(checkpoint),
             "--data-root", str(root), "--out", str(out), "--config.iters=2"])
  std = capsys.readouterr()
  assert rc == 0, std.err
  assert "[1/1] b\\udce9 (4 frames)" in std.out and "c\\udce9" in std.out
  summary = json.loads((out / "results.json").read_text())
  assert [s["name"] for s in summary["sequences"]] == [name]
  assert summary["sequences"][0]["source"] == str((seq / "left").resolve())
  md = (out / "results.md").read_text(encoding="utf-8")
  assert "b\\udce9" in md and "d\\udce9" in md
  assert "b\\udce9" in (out / "results.csv").read_text(encoding="utf-8")
  assert len(list((out / "plots").iterdir())) == 2


# `python -m eval` without the model: its --resume and --overwrite handling, the refusals
# and the reports of a run, in milliseconds (no weights read, nothing compiled).


@pytest.fixture
def no_model(monkeypatch):
  """Any --checkpoint loads stand-in weights (`weights`, described as "stand-in PATH") and the
  model's predictions are `_stand_in_prediction`'s; the names of the sequences a run evaluates
  are appended to `evaluated`, and one named in `failing` cannot be read (an OSError)."""
  from sav_jax.tools import infer  # pylint: disable=import-outside-toplevel
  stand_in = types.SimpleNamespace(weights={"params": {"w": np.arange(3, dtype=np.float32)}},
                                   evaluated=[], failing=set())
  monkeypatch.setattr(infer, "load_checkpoint",
                      lambda path, dtype=None: (stand_in.weights, None, f"stand-in {path}"))
  monkeypatch.setattr(eval_runner.inference, "predict_video",
                      lambda variables, left, right, **kw: _stand_in_prediction(left))
  real = eval_runner.evaluate_sequence

  def evaluate_sequence(seq, *args, **kwargs):
    stand_in.evaluated.append(seq.name)
    if seq.name in stand_in.failing:
      raise OSError(f"{seq.name}: frame 2 cannot be read")
    return real(seq, *args, **kwargs)

  monkeypatch.setattr(eval_runner, "evaluate_sequence", evaluate_sequence)
  return stand_in


def _small_run(out, *extra):
  """The arguments of a run of the two small synthetic sequences (SMALL) into `out`."""
  return ["--config", str(CONFIGS / "synthetic.py"), "--checkpoint", "w", *SMALL,
          "--out", str(out), *extra]


def _interrupted(no_model, out, capsys):
  """A run into `out` stopped at synthetic_001, which cannot be read: synthetic_000 recorded."""
  no_model.failing.add("synthetic_001")
  assert main(_small_run(out)) == 2
  assert "the 1 sequence finished before it is recorded" in capsys.readouterr().err
  no_model.failing.clear()
  no_model.evaluated.clear()


@pytest.mark.parametrize("files, refused, resumed", [
    # what --out holds; why a plain run is refused and why --resume is ("": it runs)
    (["notes.txt", "predictions/", "plots/"], "", ""),  # the user's file, empty folders
    (["results.json"], "{out}/results.json exist; pass --overwrite to replace them\n",
     "nothing to resume: {out} holds a finished evaluation (found results.json); pass "
     "--overwrite to replace it\n"),
    (["written_files.txt"], "{out}/written_files.txt exist; pass --overwrite",
     "{out} has no progress.jsonl (found written_files.txt)"),
    (["predictions/a.npy", "plots/a_strip.png"], "{out}/predictions, {out}/plots exist; pass "
     "--overwrite", "{out} has no progress.jsonl (found predictions, plots)"),
    (["progress.jsonl"], "{out}/progress.jsonl exist; pass --resume to continue that "
     "interrupted run, or --overwrite to replace them\n",
     "{out}/progress.jsonl is not an evaluation progress file")])
def test_earlier_results_in_the_output_folder_are_named(tmp_path, no_model, capsys, files,
                                                        refused, resumed):
  """The files of an earlier evaluation in --out refuse a run without --overwrite, each named;
  --resume continues only a run that left a progress file. The user's own files, and empty
  predictions/ or plots/ folders, are no earlier results."""
  for again, message in (([], refused), (["--resume"], resumed)):
    out = tmp_path / ("resume" if again else "plain")
    for name in files:
      (out / name).parent.mkdir(parents=True, exist_ok=True)
      (out / name).mkdir() if name.endswith("/") else (out / name).write_text("x\n")
    rc = main(_small_run(out, *again))
    err = capsys.readouterr().err
    if message:
      assert rc == 2 and message.format(out=out) in err, err
      assert no_model.evaluated == []
    else:
      assert rc == 0 and (out / "results.json").is_file() and (out / "notes.txt").is_file()
    no_model.evaluated.clear()


def test_resume_evaluates_only_the_unfinished_sequences(tmp_path, no_model, capsys):
  """--resume takes the interrupted run's finished sequences from its progress file (a record
  whose frame count no longer fits the sequence, or another method, is refused) and reports
  as a run without the interruption would; its progress file is gone once the reports are
  written."""
  out = tmp_path / "out"
  _interrupted(no_model, out, capsys)
  progress = (out / eval_runner.PROGRESS).read_text()
  header, record = progress.splitlines()
  edited = json.loads(record) | {"name": "synthetic_001", "frames": T - 1}
  (out / eval_runner.PROGRESS).write_text(f"{header}\n{json.dumps(edited)}\n")
  assert main(_small_run(out, "--resume")) == 2
  assert ("cannot resume: sequence synthetic_001 has 4 frames, the interrupted run evaluated 3"
          in capsys.readouterr().err)
  (out / eval_runner.PROGRESS).write_text(progress)
  assert main(_small_run(out, "--resume", "--baseline", "sgbm")) == 2  # another method
  assert "methods: ['sav'] then, ['sav', 'sgbm'] now" in capsys.readouterr().err
  # (a lost file list: the finished sequence's files are not written again, so not refused)
  (out / eval_runner.WRITTEN_LIST).unlink()
  assert main(_small_run(out, "--resume")) == 0 and no_model.evaluated == ["synthetic_001"]
  printed = capsys.readouterr().out.splitlines()
  assert printed[:2] == [
      "synthetic/test: 2 sequences; weights: stand-in w",
      "--resume: 1 sequence finished by the interrupted run is not evaluated again"]
  assert printed[2].startswith("[1/2] synthetic_000 (4 frames)  Stereo Any Video: EPE ")
  assert printed[2].endswith("  (from the interrupted run)")
  assert printed[3].startswith("[2/2] synthetic_001 (4 frames)") and "interrupted" not in printed[3]
  assert not (out / eval_runner.PROGRESS).exists()
  assert main(_small_run(tmp_path / "whole")) == 0
  resumed, whole = (json.loads((folder / "results.json").read_text())
                    for folder in (out, tmp_path / "whole"))
  assert [s["metrics"] for s in resumed["sequences"]] == [s["metrics"] for s in whole["sequences"]]
  assert resumed["methods"]["sav"]["aggregate"] == whole["methods"]["sav"]["aggregate"]


def test_overwrite_replaces_an_interrupted_run(tmp_path, no_model, capsys, monkeypatch):
  """--overwrite evaluates every sequence again (the progress file is not read), and leaves none
  of the earlier run's files: its list, progress file and set-aside folder are gone. A run
  that fails or is stopped puts the earlier files back, a run killed with them set aside gets
  them back at the next start, and a run while another one writes into --out is refused."""
  out = tmp_path / "out"
  _interrupted(no_model, out, capsys)
  assert main(_small_run(out, "--overwrite")) == 0
  assert no_model.evaluated == ["synthetic_000", "synthetic_001"]
  # synthetic_000's prediction, strip and curves
  assert "--overwrite: removed the earlier run's 3 prediction and plot files" in (
      capsys.readouterr().out)
  assert not (out / eval_runner.PROGRESS).exists() and not (out / eval_runner.SET_ASIDE).exists()
  assert len((out / eval_runner.WRITTEN_LIST).read_text().splitlines()) == 6
  before = _snapshot(out)
  no_model.failing.add("synthetic_001")  # a new run that fails in its second sequence ...
  assert main(_small_run(out, "--overwrite")) == 2
  no_model.failing.clear()
  assert _snapshot(out) == before  # ... puts the earlier run's files back
  with monkeypatch.context() as m:  # as does one stopped (Ctrl-C) in its first
    m.setattr(eval_runner.inference, "predict_video",
              lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
      main(_small_run(out, "--overwrite"))
  assert _snapshot(out) == before
  eval_runner.set_aside_written(out)  # killed once its files were set aside
  assert main(_small_run(out)) == 2
  assert ("restored 6 prediction and plot files that an interrupted --overwrite run had set "
          f"aside in {out / eval_runner.SET_ASIDE}") in capsys.readouterr().out
  assert _snapshot(out) == before
  import fcntl  # pylint: disable=import-outside-toplevel
  (out / eval_runner.LOCK).write_text("otherhost 4242")
  no_model.evaluated.clear()
  with open(out / eval_runner.LOCK, "rb") as held:  # another evaluation writing into it
    fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    assert main(_small_run(out, "--overwrite")) == 2
  assert f"another evaluation (otherhost 4242) is writing into {out}: wait for it" in (
      capsys.readouterr().err)
  assert no_model.evaluated == []
  assert _snapshot(out) == {**before, eval_runner.LOCK: b"otherhost 4242"}


def test_a_users_file_where_the_run_writes_nothing_is_kept(tmp_path, no_model, capsys):
  """A folder sequence without ground truth gets no curves: the user's file of that name is no
  reason to refuse an --overwrite run, and stays; one where the run writes is refused."""
  _folder_dataset(tmp_path / "mine", np.random.default_rng(3))  # c has no ground truth
  plots = tmp_path / "out" / "plots"
  plots.mkdir(parents=True)
  for name in ("c_curves.png", "c_strip.png"):
    (plots / name).write_bytes(b"mine")
  args = ["--config", str(CONFIGS / "folder.py"), "--checkpoint", "w", "--data-root",
          str(tmp_path / "mine"), "--out", str(tmp_path / "out"), "--config.iters=2",
          "--overwrite"]
  assert main(args) == 2
  assert f"{plots / 'c_strip.png'} exists, and no earlier evaluation wrote it (" in (
      capsys.readouterr().err)
  (plots / "c_strip.png").unlink()
  assert main(args) == 0 and (plots / "c_curves.png").read_bytes() == b"mine"
  assert sorted(p.name for p in plots.iterdir()) == [
      "a_curves.png", "a_strip.png", "b_curves.png", "b_strip.png", "c_curves.png",
      "c_strip.png"]


def test_resume_checks_where_the_finished_sequences_were_read(tmp_path, no_model, capsys,
                                                              monkeypatch):
  """A finished sequence read from another copy of the dataset is refused; a record of an
  older version, without the folder, is taken as it is."""
  _folder_dataset(tmp_path / "mine", np.random.default_rng(4))
  args = _interrupted_after_a(tmp_path, capsys, monkeypatch)
  no_model.evaluated.clear()
  shutil.copytree(tmp_path / "mine", tmp_path / "copy")
  at = args.index("--data-root") + 1
  assert main([*args[:at], str(tmp_path / "copy"), *args[at + 1:], "--resume"]) == 2
  assert (f"cannot resume: sequence a is read from {(tmp_path / 'copy').resolve()}"
          in capsys.readouterr().err)
  progress = tmp_path / "out" / eval_runner.PROGRESS
  header, record = progress.read_text().splitlines()
  older = {k: v for k, v in json.loads(record).items() if k != "source"}
  progress.write_text(f"{header}\n{json.dumps(older)}\n")
  assert main([*args, "--resume"]) == 0 and no_model.evaluated == ["b", "c"]


_UNREADABLE = "synthetic_000: frame 2 cannot be read\n"  # (`no_model`'s failing sequence)


@pytest.mark.parametrize("changes, extra, message", [
    # sequence -> its changes; the depth metrics asked for; the refusal (or the stand-in's
    # error once the run has passed the checks: the first sequence cannot be read)
    ({0: "no gt", 1: "no gt"}, ["--config.metrics.tcc=true"],
     "config.metrics.tcc: synthetic has no ground truth (a qualitative run: predictions and "
     "plots only), so there is nothing to measure: drop metrics.tcc\n"),
    ({0: "unscaled", 1: "unscaled"}, ["--config.metrics.tcc=true", "--config.metrics.raft=r.pth"],
     "config.metrics.tcc and config.metrics.raft need depth, but synthetic sequence synthetic_000 "
     "has no depth-to-disparity scale (no camera data; 2 of the 2 sequences with ground truth): "
     "drop metrics.tcc and metrics.raft\n"),
    ({0: "unscaled", 1: "no gt"}, ["--config.metrics.tcc=true"], "config.metrics.tcc needs "
     "depth, but synthetic sequence synthetic_000 has no depth-to-disparity scale (no camera "
     "data; 1 of the 1 sequences with ground truth): drop metrics.tcc\n"),
    ({1: "short"}, ["--config.metrics.tcc=true"], "config.metrics.tcc: temporal consistency "
     "needs sequences of 2 frames or more, but synthetic sequence synthetic_001 has 1 (1 of the "
     "2 sequences with ground truth)\n"),
    # a sequence without ground truth is not measured: it needs neither a scale nor 2 frames
    ({1: "no gt, unscaled, short"}, ["--config.metrics.tcc=true"], _UNREADABLE),
    ({0: "short", 1: "short"}, [], _UNREADABLE)])  # no temporal metric asked for
def test_depth_metrics_need_measured_sequences_with_a_scale(tmp_path, no_model, capsys,
                                                           monkeypatch, changes, extra,
                                                           message):
  load = eval_data.load_sequences_and_skipped

  def changed(config, root):
    seqs, skipped = load(config, root)
    for i, change in changes.items():
      if "short" in change:
        seqs[i] = eval_data._Head(seqs[i], 1)  # pylint: disable=protected-access
      seqs[i].has_gt = "no gt" not in change
      if "unscaled" in change:
        seqs[i].depth2disp_scale = None
    return seqs, skipped

  monkeypatch.setattr(eval_data, "load_sequences_and_skipped", changed)
  no_model.failing.add("synthetic_000")
  assert main(_small_run(tmp_path / "o", *extra)) == 2
  err = capsys.readouterr().err
  assert err.startswith("eval: error: ") and err.endswith(message), err
  assert no_model.evaluated == (["synthetic_000"] if message == _UNREADABLE else [])


def test_summary_names_the_run_and_keeps_each_sequences_record():
  """build_summary: the dataset, split, config, weights (their description and digest), the
  skipped sequences, and each sequence's record as evaluated; a method that predicted nothing
  timed and measured nothing has 0 frames/s and an empty aggregate, not another method's."""
  from eval.main import build_summary  # pylint: disable=import-outside-toplevel
  res = eval_runner.SequenceResult(
      name="s", frames=3, metrics={"sav": {"disp_epe_mean": 2.0}}, seconds={"sav": 1.5},
      compile_seconds={"sav": 4.0}, metrics_seconds=0.25, source="/d/test/s/left",
      notes=["sequence s: a note"])
  config = eval_config.load_config(str(CONFIGS / "synthetic.py"))
  summary = build_summary(config, "orbax checkpoint w", [res], ["sav", "sgbm"], "d1", ["short"])
  assert {k: summary[k] for k in ("dataset", "split", "weights", "weights_digest",
                                  "skipped_sequences", "frames", "metrics_seconds")} == {
      "dataset": "synthetic", "split": "test", "weights": "orbax checkpoint w",
      "weights_digest": "d1", "skipped_sequences": ["short"], "frames": 3,
      "metrics_seconds": 0.25}
  assert summary["config"] == config.to_dict()
  assert summary["sequences"] == [{
      "name": "s", "frames": 3, "source": "/d/test/s/left", "metrics": res.metrics,
      "seconds": {"sav": 1.5}, "compile_seconds": {"sav": 4.0}, "metrics_seconds": 0.25,
      "notes": ["sequence s: a note"]}]
  sav, sgbm = summary["methods"]["sav"], summary["methods"]["sgbm"]
  assert (sav["name"], sav["aggregate"], sav["frames_per_second"]) == (
      "Stereo Any Video", {"disp_epe_mean": 2.0}, 2.0)
  assert (sgbm["aggregate"], sgbm["measured_frames"], sgbm["frames_per_second"]) == ({}, 0, 0.0)


def test_a_runs_reports_and_what_it_prints(tmp_path, no_model, capsys, monkeypatch):
  """The reports name the weights' digest and the sequences the reader skipped; a baseline
  named twice runs once per sequence; the run prints its head line, one line per sequence,
  the report's aggregate (not its per-sequence table) and the files it wrote."""
  from sav_jax.tools import demo  # pylint: disable=import-outside-toplevel
  load, sgbm_runs = eval_data.load_sequences_and_skipped, []
  monkeypatch.setattr(eval_data, "load_sequences_and_skipped",
                      lambda config, root: (load(config, root)[0], ["too_short"]))
  monkeypatch.setattr(demo, "stereo_sgbm", lambda left, right, **kw: sgbm_runs.append(1) or (
      _stand_in_prediction(left) + 1))
  out = tmp_path / "o"
  assert main(_small_run(out, "--baseline", "sgbm", "--baseline", "sgbm")) == 0
  summary = json.loads((out / "results.json").read_text())
  assert summary["weights_digest"] == eval_runner.weights_digest(no_model.weights)
  assert summary["skipped_sequences"] == ["too_short"] and list(summary["methods"]) == [
      "sav", "sgbm"]
  assert len(sgbm_runs) == 2
  printed = capsys.readouterr().out
  assert printed.startswith(
      "synthetic/test: 2 sequences; weights: stand-in w\n[1/2] synthetic_000 ")
  assert "## Aggregate" in printed and "## Per sequence" not in printed
  assert printed.endswith(f"\nwrote {out / 'results.json'}, {out / 'results.csv'}, "
                          f"{out / 'results.md'}\n")


def test_resume_or_overwrite_and_an_out_folder_in_the_home_folder(tmp_path, no_model, capsys,
                                                                  monkeypatch):
  """--resume and --overwrite exclude each other; `--out=~/o` (no shell expands that `~`) is
  the home folder's `o`, not a folder named `~` here."""
  with pytest.raises(SystemExit):
    main(_small_run(tmp_path / "o", "--resume", "--overwrite"))
  assert "argument --overwrite: not allowed with argument --resume" in capsys.readouterr().err
  monkeypatch.setenv("HOME", str(tmp_path / "home"))
  monkeypatch.chdir(tmp_path)
  assert main([*_small_run("x"), "--out=~/o"]) == 0
  assert sorted(p.name for p in tmp_path.iterdir()) == ["home"]
  assert (tmp_path / "home" / "o" / "results.json").is_file()

"""`sav-jax bench`: JSON record, --compare, and the persistent compilation cache."""

import json
import os
import re

import pytest

from sav_jax import cli
from tests.conftest import XLA_OLDER_EMITTERS

pytestmark = pytest.mark.usefixtures("fast_compile")

ARGS = ["bench", "--frames", "2", "--height", "32", "--width", "64", "--iters", "2",
        "--repeats", "1"]


@pytest.mark.usefixtures("without_suite_xla_flags")  # the options a user gets
def test_bench_records_compares_and_reuses_the_compile_cache(tmp_path, capsys,
                                                              restore_cache_config,
                                                              restore_low_memory_compile):
  cache = tmp_path / "xla"
  first, second = tmp_path / "first.json", tmp_path / "second.json"
  assert cli.main([*ARGS, "--json", str(first), "--compile-cache", str(cache)]) == 0
  out = capsys.readouterr().out
  assert f"(stored in {cache})" in out and "peak host RSS" in out
  rec = json.loads(first.read_text())
  assert rec["frames"] == 2 and rec["height"] == 32 and rec["iters"] == 2
  assert rec["median_s"] > 0 and rec["compile_s"] > 0 and rec["peak_rss_gb"] > 0.1
  assert rec["batch"] == 1 and rec["width"] == 64 and rec["dtype"] == "float32"
  assert rec["final_only"] is True and 0 < rec["min_s"] <= rec["median_s"]
  assert rec["fps"] == pytest.approx(2 / rec["median_s"])  # B * T frames per median call
  assert f"throughput    {rec['fps']:.2f} frames/s" in out
  assert rec["cache_hit"] is False and any(cache.iterdir())
  assert rec["vit_attention"] == "blocked"  # the default "auto", as resolved on the CPU
  assert rec["gru_conv"] == "dft"  # the same
  assert rec["matmul_precision"] == "default"  # JAX's setting: none in the tests
  assert "XLA buffers" in out and 0 < rec["xla_temp_gb"] < 1 and rec["xla_args_gb"] > 0.05

  assert cli.main([*ARGS, "--json", str(second), "--compile-cache", str(cache),
                   "--compare", str(first)]) == 0
  out = capsys.readouterr().out
  assert "(loaded from the compilation cache)" in out
  assert json.loads(second.read_text())["cache_hit"] is True
  assert re.search(rf"vs {re.escape(str(first))}: forward (x[\d.]+ (faster|slower)|the same) "
                   r"\(", out), out
  assert rec["compiler_options"] == json.loads(second.read_text())["compiler_options"]
  # the default, where this jaxlib has the older emitters (jaxlib 0.11+ has not)
  assert rec["compiler_options"].get("xla_cpu_use_fusion_emitters") is (
      False if XLA_OLDER_EMITTERS else None)

  # another compile setting is another program: compiled (not loaded) and recorded (with
  # only the newer emitters, as in jaxlib 0.11+, the setting changes nothing: loaded)
  assert cli.main([*ARGS, "--json", str(second), "--compile-cache", str(cache),
                   "--no-low-memory-compile", "--overwrite"]) == 0
  out = capsys.readouterr().out
  assert ("(stored in" in out) is XLA_OLDER_EMITTERS and "xla_cpu_use_fusion_emitters" not in out
  rec = json.loads(second.read_text())
  assert rec["cache_hit"] is not XLA_OLDER_EMITTERS
  assert "xla_cpu_use_fusion_emitters" not in rec["compiler_options"]


def test_bench_rejects_bad_sizes(capsys, monkeypatch):
  for height in ("30", "0", "-16"):
    assert cli.main(["bench", "--height", height]) == 2
    assert "--height/--width must be positive multiples of 16" in capsys.readouterr().err
  assert cli.main(["bench", "--width", "16"]) == 2  # the model refuses it (no reference)
  assert "the width at least 32 (got 128x16)" in capsys.readouterr().err
  assert cli.main(["bench", "--vit-attention", "cudnn"]) == 2
  assert "--vit-attention cudnn needs --dtype bfloat16" in capsys.readouterr().err
  import jax  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  if jax.default_backend() != "gpu":  # said before the weights' init and the trace
    monkeypatch.setattr(bench, "measure", lambda *a, **k: pytest.fail("measured"))
    assert cli.main(["bench", "--vit-attention", "cudnn", "--dtype", "bfloat16"]) == 2
    assert "--vit-attention cudnn needs a CUDA GPU" in capsys.readouterr().err


def test_clip_problem_takes_the_largest_clip_and_options_a_script_lacks():
  # --frames 32 is the depth prior's temporal attention length: allowed, 33 is not; a
  # script without --iters, --batch or --repeats (bf16_audit.py --gradients) has no problem.
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax.tools.bench import clip_problem  # pylint: disable=import-outside-toplevel
  clip = dict(frames=32, height=16, width=32)
  assert clip_problem(argparse.Namespace(**clip, iters=2, batch=1, repeats=1)) is None
  assert clip_problem(argparse.Namespace(**clip)) is None
  assert "--frames must be at most 32" in clip_problem(argparse.Namespace(**{**clip,
                                                                            "frames": 33}))

def test_memory_report_names_the_device_peak_after_compiling():
  """On GPU the device peak includes the compiler's autotuning scratch: the report gives
  the peak before the first call beside it, and XLA's buffer sizes when known."""
  from sav_jax.tools.bench import memory_lines  # pylint: disable=import-outside-toplevel
  res = dict(peak_rss_gb=6.2, device_peak_gb=29.9, device_peak_compile_gb=21.0,
             xla_temp_gb=13.5, xla_args_gb=0.5, xla_out_gb=0.07)
  text = "\n".join(memory_lines(res))
  assert "device peak   29.90 GB (after compiling, before the first call: 21.00 GB)" in text
  assert "13.50 GB intermediates + 0.50 GB arguments + 0.07 GB outputs" in text
  cpu = memory_lines(dict(peak_rss_gb=0.8, device_peak_gb=None, xla_temp_gb=None))
  assert cpu == ["peak host RSS 0.80 GB"]
  # benchmarks/train_step.py gives the batch: the peaks per sample beside them
  per_sample = memory_lines(dict(peak_rss_gb=6.0, device_peak_gb=30.0,
                                 device_peak_compile_gb=21.0), batch=4)
  assert per_sample == ["peak host RSS 6.00 GB, 1.50 GB/sample",
                        "device peak   30.00 GB, 7.50 GB/sample (after compiling, before the "
                        "first call: 21.00 GB)"]


def test_compare_wording_and_bad_baseline_before_running(tmp_path, capsys):
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  line = bench.compare_line({"median_s": 1.0, "compile_s": 4.0, "peak_rss_gb": 0.5},
                            {"median_s": 2.0, "compile_s": 2.0, "peak_rss_gb": 1.0})
  assert line == ("forward x2.00 faster (1 s vs 2 s), compile x2.00 slower (4 s vs 2 s), "
                  "peak RSS x2.00 lower (0.5 GB vs 1 GB)")
  eager = {"median_s": 3.0, "compile_s": None, "peak_rss_gb": 1.0}  # benchmarks/official_torch.py
  assert bench.compare_line({"median_s": 1.0, "compile_s": 4.0, "peak_rss_gb": 0.5}, eager) == (
      "forward x3.00 faster (1 s vs 3 s), compile 4 s (the baseline compiles nothing), "
      "peak RSS x2.00 lower (0.5 GB vs 1 GB)")
  # on a GPU the device's peak counts; a cache load is not a compile
  gpu = bench.compare_line(
      {"median_s": 1.0, "compile_s": 5.0, "peak_rss_gb": 6.0, "device_peak_gb": 6.67,
       "cache_hit": True},
      {"median_s": 1.0, "compile_s": 50.0, "peak_rss_gb": 6.0, "device_peak_gb": 29.86})
  assert gpu.endswith("device peak x4.48 lower (6.67 GB vs 29.9 GB)"), gpu
  assert "(this run loaded it from the compilation cache)" in gpu
  # a baseline from another machine is named (the official torch JSON says only "cpu")
  here = {"device": "cpu:cpu", "host": "vm", "vit_attention": "blocked"}
  assert bench.machine_note(here, {"device": "cpu", "host": "vm"}) == ""
  assert bench.machine_note(here, {"device": "cpu:x86_64", "host": "vm"}) == ""
  assert bench.machine_note({**here, "device": "gpu:NVIDIA H200"},
                            {"device": "gpu", "host": "vm"}) == ""  # no GPU model recorded
  assert bench.machine_note({**here, "device": "gpu:NVIDIA H200"},
                            {"device": "gpu:NVIDIA H200", "host": "vm"}) == ""
  note = bench.machine_note(here, {"device": "gpu:NVIDIA H200", "host": "gpu-box",
                                   "vit_attention": "cudnn"})
  assert note.startswith("warning: the baseline was measured elsewhere (device cpu:cpu here, "
                         "gpu:NVIDIA H200 there; host vm here, gpu-box there; vit_attention "
                         "blocked here, cudnn there)"), note
  assert "H100" in bench.machine_note({**here, "device": "gpu:NVIDIA H200"},
                                      {"device": "gpu:NVIDIA H100"})
  # Hosts of one name (every VM of a kind is "vm"): the CPU model, JAX and the date tell.
  here.update(cpu="AMD EPYC 9B14", jax="0.8.1", date="2026-12-05")
  assert "cpu AMD EPYC 9B14 here, AMD EPYC 7B13 there" in bench.machine_note(
      here, {**here, "cpu": "AMD EPYC 7B13"})
  assert "jax 0.8.1 here, 0.7.2 there" in bench.machine_note(here, {**here, "jax": "0.7.2"})
  assert bench.machine_note(here, {**here, "date": "2026-12-01"}).startswith(
      "note: the baseline was measured on 2026-12-01: machines of one kind differ")
  # the spread the note quotes: the same code at 8.37 s (2026-11-30) and 14.65 s (2026-12-01)
  assert "(up to 1.75x seen on CPUs)" in bench.machine_note(here, {**here, "date": "2026-12-01"})
  assert bench.machine_note(here, dict(here)) == ""
  assert bench.machine_note(here, {k: v for k, v in here.items() if k != "date"}) == ""
  assert bench.machine_note({**here, "gru_conv": "dft"}, {**here, "gru_conv": "direct"}) == (
      "warning: the baseline was measured with other settings (gru_conv dft here, direct "
      "there): the ratios compare those settings, not code")
  # another setting on another day: the warning and the day's note, one line each
  note = bench.machine_note({**here, "gru_conv": "dft"},
                            {**here, "gru_conv": "direct", "date": "2026-12-01"})
  assert note.splitlines()[0].endswith("the ratios compare those settings, not code"), note
  assert note.splitlines()[1].startswith("note: the baseline was measured on 2026-12-01"), note
  assert isinstance(bench.cpu_model(), str) and bench.cpu_model()
  # A compile of 0 s gives no ratio (it gave x10000000000000.00); equal values are the same.
  assert bench.compare_line({"median_s": 2.0, "compile_s": 4.0, "peak_rss_gb": 1.0},
                            {"median_s": 2.0, "compile_s": 0.0, "peak_rss_gb": 1.001}) == (
      "forward the same (2 s vs 2 s), compile (4 s vs 0 s), peak RSS the same (1 GB vs 1 GB)")
  shape = dict(frames=2, height=32, width=64, iters=2, batch=1)  # ARGS's
  eager = {**eager, **shape}
  baselines = {"eager": {**eager, "median_s": None}, "shape": {**eager, "iters": 8},
               "bad": {"median_s": 1}, "text": {**eager, "median_s": "x"},
               "zero": {**eager, "median_s": 0}, "no_shape": {**eager, "frames": None},
               "bf16": {**eager, "dtype": "bfloat16"}, "batch": {**eager, "batch": 2},
               "all": {**eager, "final_only": False}, "odd": {**eager, "final_only": "x"},
               "str_frames": {**eager, "frames": "2"},  # was "frames: 2 here, 2 there"
               # benchmarks/train_step.py's JSON has the same keys, and more
               "train": {**eager, "samples_per_s": 0.5, "remat": True, "loss": 1.0}}
  del baselines["no_shape"]["frames"]
  baselines["no_compile"] = {k: v for k, v in eager.items() if k != "compile_s"}
  for name, base in baselines.items():
    (tmp_path / f"{name}.json").write_text(json.dumps(base))
  for name, message in (("none", "cannot read"), ("bad", "lacks"),
                        ("no_shape", "lacks ['frames']"),
                        ("no_compile", "lacks ['compile_s']"),
                        ("text", "expected positive numbers"),
                        ("eager", "expected positive numbers"),
                        ("zero", "expected positive numbers"),
                        ("shape", "another shape or setting (--iters: 2 here, 8 there)"),
                        ("bf16", "(--dtype: float32 here, bfloat16 there)"),
                        ("batch", "(--batch: 1 here, 2 there)"),
                        ("all", "(the final prediction here, every prediction "
                                "(--all-predictions) there)"),
                        ("odd", "(the final prediction here, final_only 'x' there)"),
                        ("str_frames", "expected integers for the shape, got {'frames': '2'}"),
                        ("train", "a training step's JSON")):
    path = tmp_path / f"{name}.json"
    assert cli.main([*ARGS, "--compare", str(path)]) == 2  # refused before measuring
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
  mine = tmp_path / "mine.json"
  mine.write_text("precious")
  (tmp_path / "link.json").symlink_to(mine)  # --overwrite would have written into mine.json
  for extra, message in ((["--json", str(mine)], "exists; pass --overwrite"),
                         (["--json", str(tmp_path / "link.json"), "--overwrite"],
                          "link.json is a symbolic link; give the path of a regular file"),
                         (["--json", str(tmp_path)], "is a folder"),
                         (["--json", str(tmp_path / "no" / "r.json")], "does not exist"),
                         (["--repeats", "0"], "--repeats must be >= 1"),
                         (["--batch", "0"], "--batch must be >= 1"),
                         (["--frames", "33"], "--frames must be at most 32 (the depth prior"),
                         (["--overwrite"], "--overwrite replaces a --json file: name one"),
                         # a folder nothing can be created in (Linux's /proc; root included):
                         # the JSON was written, and failed, only after the run
                         *([(["--json", "/proc/sav-bench.json"],
                             "sav-bench.json: cannot create a file in /proc")]
                           if os.path.isdir("/proc/self") else [])):
    assert cli.main([*ARGS, *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
  assert mine.read_text() == "precious"


def test_bench_measures_under_the_matmul_precision_asked_and_notes_a_baseline_with_another(
    monkeypatch):
  import jax  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  seen = []

  def stop(*args, **kwargs):
    seen.append(str(jax.config.jax_default_matmul_precision))
    raise KeyboardInterrupt

  monkeypatch.setattr(bench, "measure", stop)
  for extra, want in ((["--matmul-precision", "highest"], "highest"), ([], "None")):
    with pytest.raises(KeyboardInterrupt):
      cli.main([*ARGS, *extra])
    assert seen[-1] == want
  assert seen == ["highest", "None"]
  res = {"device": "gpu:NVIDIA H200", "matmul_precision": "highest"}
  note = bench.machine_note(res, {**res, "matmul_precision": "default"})
  assert note == ("warning: the baseline was measured with other settings (matmul_precision "
                  "highest here, default there): the ratios compare those settings, not code")
  assert bench.machine_note(res, dict(res)) == ""
  # The XLA options (--no-low-memory-compile) move compile time and memory: named too.
  res["compiler_options"] = {"xla_cpu_use_thunk_runtime": False}
  note = bench.machine_note(res, {**res, "compiler_options": {}})
  assert "compiler_options {'xla_cpu_use_thunk_runtime': False} here, {} there" in note, note


def test_bench_passes_the_batch_dtype_and_every_prediction_to_the_measurement(monkeypatch,
                                                                            capsys):
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  calls = []

  def stop(*args, **kwargs):
    calls.append((args, kwargs))
    raise KeyboardInterrupt

  monkeypatch.setattr(bench, "measure", stop)
  with pytest.raises(KeyboardInterrupt):
    cli.main([*ARGS, "--batch", "3", "--dtype", "bfloat16", "--all-predictions",
              "--vit-attention", "blocked", "--gru-conv", "direct"])
  (args, kwargs), = calls
  assert args == (2, 32, 64, 2, 3, "bfloat16", 1)  # frames, H, W, iters, batch, dtype, repeats
  assert kwargs["final_only"] is False and kwargs["vit_attention"] == "blocked"
  assert kwargs["gru_conv"] == "direct"
  with pytest.raises(KeyboardInterrupt):
    cli.main(ARGS)
  assert calls[-1][0][4:6] == (1, "float32") and calls[-1][1]["final_only"] is True
  # The report's input line says when every prediction was measured.
  fake = {"device": "cpu:cpu", "jax": "x", "batch": 1, "frames": 2, "height": 32, "width": 64,
          "iters": 2, "dtype": "float32", "vit_attention": "blocked", "gru_conv": "dft",
          "compiler_options": {},
          "compile_s": 1.0, "cache_hit": False, "median_s": 1.0, "min_s": 1.0, "fps": 2.0,
          "peak_rss_gb": 0.5}
  for flags, final_only in (([], True), (["--all-predictions"], False)):
    monkeypatch.setattr(bench, "measure", lambda *a, **k: {**fake, "final_only": k["final_only"]})
    assert cli.main([*ARGS, *flags]) == 0
    line = next(l for l in capsys.readouterr().out.splitlines() if l.startswith("input"))
    assert ("every prediction (--all-predictions)" in line) is not final_only, line
    assert line.endswith(", GRU 1x15 convolutions dft"), line


def test_memory_and_cache_helpers_report_in_gb_from_what_they_are_given(tmp_path):
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel

  class Device:  # jax.Device.memory_stats: a dict, None, or an error (CPU backends)
    def __init__(self, stats):
      self.stats = stats

    def memory_stats(self):
      if isinstance(self.stats, Exception):
        raise self.stats
      return self.stats

  assert bench.device_peak_gb(Device({"peak_bytes_in_use": 3 * 2 ** 30, "bytes_in_use": 1})) == 3.0
  for stats in (None, {}, {"bytes_in_use": 5}, NotImplementedError("cpu")):
    assert bench.device_peak_gb(Device(stats)) is None

  class Analysis:
    temp_size_in_bytes, argument_size_in_bytes, output_size_in_bytes = 2 ** 30, 2 ** 29, 2 ** 28

  class Compiled:
    def __init__(self, analysis):
      self.analysis = analysis

    def memory_analysis(self):
      if self.analysis is None:
        raise NotImplementedError("no analysis here")
      return self.analysis

  assert bench.xla_buffers_gb(Compiled(Analysis())) == {
      "xla_temp_gb": 1.0, "xla_args_gb": 0.5, "xla_out_gb": 0.25}
  assert bench.xla_buffers_gb(Compiled(None)) == dict.fromkeys(
      ("xla_temp_gb", "xla_args_gb", "xla_out_gb"))
  # the peak RSS is the kernel's high-water mark (VmHWM, in kB) in GB (Linux's /proc here)
  if bench.sys.platform.startswith("linux"):
    def hwm_kb():
      with open("/proc/self/status", encoding="ascii") as f:
        return next(int(l.split()[1]) for l in f if l.startswith("VmHWM:"))
    before = hwm_kb()
    peak = bench.peak_rss_gb()
    assert before / 2 ** 20 * 0.98 <= peak <= hwm_kb() / 2 ** 20 * 1.02
    with pytest.MonkeyPatch.context() as mp:  # macOS counts ru_maxrss in bytes, not kB
      mp.setattr(bench.sys, "platform", "darwin")
      assert bench.peak_rss_gb() == pytest.approx(peak / 1024, rel=0.02)
  # a compile is a cache load when the cache folder gained no entry
  assert bench.compile_cache_note(None, True) == ""
  assert bench.compile_cache_note(tmp_path, True) == " (loaded from the compilation cache)"
  assert bench.compile_cache_note(tmp_path, False) == f" (stored in {tmp_path})"
  loaded = bench.compile_cache_probe(tmp_path)
  assert loaded() is True
  (tmp_path / "entry").write_text("x")
  assert loaded() is False and bench.compile_cache_probe(tmp_path)() is True
  assert bench.compile_cache_probe(None)() is False


def test_a_baseline_takes_any_positive_time_and_a_compile_of_0_s(tmp_path):
  from sav_jax.tools import UsageError, bench  # pylint: disable=import-outside-toplevel
  base = dict(frames=2, height=32, width=64, iters=2, batch=1, median_s=0.5, compile_s=0,
              peak_rss_gb=0.25)
  path = tmp_path / "base.json"
  path.write_text(json.dumps(base))
  assert bench._read_baseline(path) == base  # pylint: disable=protected-access
  # (json writes NaN and Infinity, and reads them back)
  for key, value in (("compile_s", -0.5), ("median_s", -0.5), ("peak_rss_gb", 0),
                     ("median_s", float("nan")), ("compile_s", float("inf")),
                     ("peak_rss_gb", True)):
    path.write_text(json.dumps({**base, key: value}))
    with pytest.raises(UsageError, match=rf"expected positive numbers .*'{key}'"):
      bench._read_baseline(path)  # pylint: disable=protected-access
  path.write_text(json.dumps({**base, "batch": True}))  # True == 1: ARGS's batch
  with pytest.raises(UsageError, match=r"expected integers for the shape, got \{'batch': True\}"):
    bench._read_baseline(path)  # pylint: disable=protected-access


def test_compare_line_rounds_ratios_to_2_places_and_notes_one_cache_load():
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  base = {"median_s": 1.0, "compile_s": 2.0, "peak_rss_gb": 1.0}
  line = bench.compare_line({"median_s": 1.04, "compile_s": 2.004, "peak_rss_gb": 1.0}, base)
  assert line.startswith("forward x1.04 slower (1.04 s vs 1 s), compile the same (2 s vs 2 s)")
  # both from the compilation cache: like against like, nothing to note
  line = bench.compare_line({**base, "cache_hit": True}, {**base, "cache_hit": True})
  assert "compilation cache" not in line
  line = bench.compare_line(base, {**base, "cache_hit": True})
  assert "compile the same (2 s vs 2 s) (the baseline loaded it from the compilation cache)" in line
  # a device peak on one side only (a GPU run against a CPU one): no ratio of it
  line = bench.compare_line({**base, "device_peak_gb": 3.0}, base)
  assert "device peak" not in line and line.endswith("peak RSS the same (1 GB vs 1 GB)")


def test_bench_takes_the_smallest_sizes(monkeypatch):
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  calls = []

  def stop(*args, **kwargs):
    calls.append(args)
    raise KeyboardInterrupt

  monkeypatch.setattr(bench, "measure", stop)
  with pytest.raises(KeyboardInterrupt):  # measured, not refused
    cli.main(["bench", "--frames", "1", "--height", "16", "--width", "32", "--iters", "2",
              "--repeats", "1", "--batch", "1"])
  assert calls == [(1, 16, 32, 2, 1, "float32", 1)]
  assert cli.main(["bench", "--iters", "1"]) == 2 and calls == [(1, 16, 32, 2, 1, "float32", 1)]
  with pytest.raises(KeyboardInterrupt):  # the largest clip: TEMPORAL_MAX_LEN frames
    cli.main(["bench", "--frames", "32"])
  assert calls[-1][0] == 32


def test_bench_report_json_and_compare_from_one_measurement(tmp_path, monkeypatch, capsys,
                                                            restore_cache_config,
                                                            restore_low_memory_compile):
  """The printed report, the --json record and the --compare lines, from a measurement given
  (nothing compiled); without --compile-cache the cache is off (bench measures compiling)."""
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  fake = {"device": "cpu:cpu", "jax": "x", "host": "here", "batch": 1, "frames": 2,
          "height": 32, "width": 64, "iters": 2, "dtype": "float32", "final_only": True,
          "vit_attention": "blocked", "gru_conv": "direct", "compiler_options": {"opt": 7},
          "compile_s": 3.0, "cache_hit": False, "median_s": 0.5, "min_s": 0.25, "fps": 4.0,
          "peak_rss_gb": 1.5}
  caches = []

  def measure(*args, **kwargs):
    caches.append(kwargs["compile_cache"])
    return dict(fake)

  monkeypatch.setattr(bench, "measure", measure)
  base = tmp_path / "base.json"
  base.write_text(json.dumps({**fake, "host": "there", "median_s": 1.0}))
  rec = tmp_path / "rec.json"
  assert cli.main([*ARGS, "--json", str(rec), "--compare", str(base)]) == 0
  assert caches == [None]
  lines = capsys.readouterr().out.splitlines()
  assert lines == [
      "device        cpu  (jax x)",
      "input         B=1 T=2 32x64 iters=2 float32",
      "XLA options   opt=7",
      "compile       3.00 s",
      "forward       median 0.500 s  (min 0.250 s, 1 run)",
      "throughput    4.00 frames/s",
      "peak host RSS 1.50 GB",
      "warning: the baseline was measured elsewhere (host here here, there there): the ratios "
      "compare machines, not code",
      f"vs {base}: forward x2.00 faster (0.5 s vs 1 s), compile the same (3 s vs 3 s), "
      "peak RSS the same (1.5 GB vs 1.5 GB)",
      f"wrote {rec}"], lines  # (where the record went: it said nothing)
  # the record says how many calls the median is of (ARGS: --repeats 1)
  assert json.loads(rec.read_text()) == {**fake, "matmul_precision": "default", "repeats": 1}
  # A GPU is named by its model; no XLA options, no line for them; the cache folder and
  # the matmul precision asked reach the measurement and the record.
  fake.update(device="gpu:NVIDIA H200", compiler_options={})
  assert cli.main([*ARGS, "--json", str(rec), "--overwrite", "--compile-cache",
                   str(tmp_path / "xla"), "--matmul-precision", "highest"]) == 0
  lines = capsys.readouterr().out.splitlines()
  assert caches[-1] is not None and os.path.samefile(caches[-1], tmp_path / "xla")
  assert lines[0] == "device        NVIDIA H200 (gpu)  (jax x)", lines
  assert lines[2] == f"compile       3.00 s (stored in {caches[-1]})", lines
  assert not any(l.startswith("XLA options") for l in lines), lines
  assert json.loads(rec.read_text())["matmul_precision"] == "highest"


def test_measure_reports_the_median_min_and_frames_per_second_of_the_timed_calls(monkeypatch):
  """`measure` with a stand-in model, compiler and clock (nothing of the model compiled):
  the model built and called as asked (dtype, clip shape, iters, every prediction),
  compile_s the compile's time, median_s and min_s those of the `repeats` timed calls after
  an untimed warm-up call, fps B * T frames per median call, the device peaks after
  compiling and at the end, and "auto" settings as resolved."""
  import types  # pylint: disable=import-outside-toplevel
  import jax  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  seen, events = {}, []  # events: the clock's readings ("t") and the forward's calls

  class Model:  # sav_jax.StereoAnyVideo's apply: the disparities of every frame
    def __init__(self, cfg):
      seen["dtype"] = cfg.dtype

    def apply(self, variables, left, right, iters, final_only):
      seen.update(shape=left.shape, iters=iters, final_only=final_only)
      return types.SimpleNamespace(disparities=(left - right)[..., 0] * variables["w"])

  class Jit:  # jax.jit(f).lower(*args).compile(...): a call of f per call of the program
    def __init__(self, f):
      self.f = f

    def lower(self, *args):
      return types.SimpleNamespace(compile=lambda compiler_options: self.call)

    def call(self, *args):
      events.append("call")
      return self.f(*args)

  monkeypatch.setattr(sav_jax, "StereoAnyVideo", Model)
  monkeypatch.setattr(jax, "jit", Jit)
  monkeypatch.setattr("sav_jax.model.init.init_variables", lambda cfg, seed: {"w": 1.0})
  # perf_counter: the compile from 100 s to 103 s, then the timed calls of 0.5, 2 and 1 s
  clock = iter([100.0, 103.0, 200.0, 200.5, 300.0, 302.0, 400.0, 401.0])
  monkeypatch.setattr(bench, "time", types.SimpleNamespace(
      perf_counter=lambda: events.append("t") or next(clock), strftime=bench.time.strftime))
  peaks = iter([21.0, 29.9])  # after compiling, then at the end
  monkeypatch.setattr(bench, "device_peak_gb", lambda device: next(peaks))
  res = bench.measure(frames=3, height=16, width=32, iters=3, batch=2, dtype="bfloat16",
                      repeats=3, final_only=False)
  assert next(clock, None) is None  # a perf_counter call before and after each of the 3
  assert events == ["t", "t", "call"] + ["t", "call", "t"] * 3  # the warm-up is not timed
  assert seen == dict(dtype="bfloat16", shape=(2, 3, 16, 32, 3), iters=3, final_only=False)
  assert res["compile_s"] == 3.0 and res["median_s"] == 1.0 and res["min_s"] == 0.5
  assert res["fps"] == 6.0  # 2 clips of 3 frames per median second
  assert res["device_peak_compile_gb"] == 21.0 and res["device_peak_gb"] == 29.9
  assert (res["frames"], res["height"], res["width"], res["iters"], res["batch"]) == (
      3, 16, 32, 3, 2)
  # "auto" on the CPU in bfloat16: blocked ViT attention (cudnn needs a CUDA GPU), direct
  # GRU convolutions (dft only in float32)
  assert (res["dtype"], res["final_only"]) == ("bfloat16", False)
  assert (res["vit_attention"], res["gru_conv"]) == ("blocked", "direct")


def test_json_output_check_takes_a_bare_file_name_and_leaves_nothing_behind(tmp_path,
                                                                           monkeypatch):
  """A bare file name is one in the working folder (whose parent is that folder, not "");
  the trial of creating something there removes what it created."""
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  monkeypatch.chdir(tmp_path)
  assert bench.json_output_problem("r.json", False) is None
  assert not any(tmp_path.iterdir())
  (tmp_path / "r.json").write_text("{}")
  assert bench.json_output_problem("r.json", False) == (
      "--json r.json exists; pass --overwrite to replace it")
  assert bench.json_output_problem("r.json", True) is None
  assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_json_output_check_refuses_a_path_ending_in_a_slash(tmp_path):
  """`new/` names a folder: open() would fail only after the long run, losing its results."""
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  for name in ("new/", "r.json/"):
    path = f"{tmp_path}/{name}"
    assert bench.json_output_problem(path, True) == (
        f"--json {path} ends in a slash; give a file name")


def test_json_output_check_says_a_file_stands_where_its_folder_should(tmp_path):
  """`mine.json/out.json` with `mine.json` a file: the parent is there, but not a folder."""
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  (tmp_path / "mine.json").write_text("{}")
  path = str(tmp_path / "mine.json" / "out.json")
  assert bench.json_output_problem(path, True) == (
      f"--json {path}: {tmp_path / 'mine.json'} is a file, not a folder")
  assert bench.json_output_problem(str(tmp_path / "no" / "r.json"), True) == (
      f"--json {tmp_path / 'no' / 'r.json'}: {tmp_path / 'no'} does not exist")


def test_bench_json_made_during_the_run_is_not_replaced_without_overwrite(tmp_path, monkeypatch,
                                                                           capsys):
  """The --json check runs before the long run; a file of that name made meanwhile (another
  bench writing the same name) is kept without --overwrite, and the error names it."""
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel
  rec = tmp_path / "rec.json"
  fake = {"device": "cpu:cpu", "jax": "x", "host": "h", "batch": 1, "frames": 2, "height": 32,
          "width": 64, "iters": 2, "dtype": "float32", "final_only": True,
          "vit_attention": "blocked", "gru_conv": "direct", "compiler_options": {},
          "compile_s": 3.0, "cache_hit": False, "median_s": 0.5, "min_s": 0.25, "fps": 4.0,
          "peak_rss_gb": 1.5}

  def measure(*args, **kwargs):
    rec.write_text("the other run's")
    return dict(fake)

  monkeypatch.setattr(bench, "measure", measure)
  assert cli.main([*ARGS, "--json", str(rec)]) == 2
  assert rec.read_text() == "the other run's"
  assert f"--json {rec} was created during the run" in capsys.readouterr().err
  assert cli.main([*ARGS, "--json", str(rec), "--overwrite"]) == 0
  assert json.loads(rec.read_text())["median_s"] == 0.5

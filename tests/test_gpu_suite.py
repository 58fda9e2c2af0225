"""benchmarks/gpu_suite.sh, checked without a GPU: in the `flags` step every flag set reaches
its benchmark and XLA accepts every flag (an unknown flag or enum value aborts the process,
which on a short GPU lease would cost a whole step); the float32 benchmark's warm rerun loads
the program the cold run stored."""

import os
import pathlib
import subprocess

from tests.conftest import xla_accepts

ROOT = pathlib.Path(__file__).resolve().parents[1]
SUITE = ROOT / "benchmarks" / "gpu_suite.sh"


def _run_steps(tmp_path, steps, flag_sets=None, rc=0, fail_on=None):
  """Runs suite steps with a stand-in Python that records its XLA_FLAGS and arguments
  (and fails where its arguments contain `fail_on`); returns the recorded
  `(XLA_FLAGS, argv)` of every benchmark call."""
  fake = tmp_path / "python"
  fail = f'[[ "$*" == *"{fail_on}"* ]] && exit 1\nexit 0\n' if fail_on else ""
  fake.write_text('#!/bin/bash\n[ "$1" = -c ] && exit 0\n'
                  'printf "%s\\t%s\\n" "$XLA_FLAGS" "$*" >> "$RECORD"\n' + fail)
  fake.chmod(0o755)
  env = dict(os.environ, PYTHON=str(fake), RECORD=str(tmp_path / "calls.tsv"), XLA_FLAGS="")
  env.pop("FLAG_SETS", None)
  if flag_sets is not None:
    env["FLAG_SETS"] = flag_sets
  proc = subprocess.run(["bash", str(SUITE), str(tmp_path / "out"), *steps], env=env,
                        capture_output=True, text=True, timeout=60, check=False)
  assert proc.returncode == rc, proc.stdout + proc.stderr
  record = tmp_path / "calls.tsv"
  rows = record.read_text().splitlines() if record.exists() else []
  return [tuple(r.split("\t")) for r in rows]


def _json(argv: str) -> str:
  """The --json file of a recorded call."""
  args = argv.split()
  return args[args.index("--json") + 1]


def test_every_flag_set_runs_the_window_benchmark_with_its_own_flags(tmp_path):
  calls = _run_steps(tmp_path, ["flags"])
  names = [_json(argv).split("_flags_")[-1].removesuffix(".json") for _, argv in calls]
  assert names == ["default", "cmdbuf_off", "cmdbuf_loop", "cublas", "exhaustive"]
  for (flags, argv), name in zip(calls, names):
    assert "-m sav_jax.cli bench --frames 20 --height 720 --width 1280 --iters 20" in argv
    assert "--dtype bfloat16" in argv
    if name == "default":
      assert flags.strip() == ""
    else:
      assert flags.strip().startswith("--xla_gpu_"), (name, flags)
  assert len({flags for flags, _ in calls}) == len(calls)  # no set repeats another's flags


def test_flag_sets_can_be_replaced(tmp_path):
  calls = _run_steps(tmp_path, ["flags"], "a=--xla_gpu_autotune_level=0;b=")
  assert [(f.strip(), _json(a).split("_flags_")[-1]) for f, a in calls] == [
      ("--xla_gpu_autotune_level=0", "a.json"), ("", "b.json")]


def test_xla_accepts_every_flag_of_the_default_sets(tmp_path):
  sets = [flags.strip() for flags, _ in _run_steps(tmp_path, ["flags"]) if flags.strip()]
  typo = "--xla_gpu_enable_comand_buffer="  # and the probe would catch a misspelt flag
  accepted = xla_accepts([*sets, typo])
  assert [f for f in sets if not accepted[f]] == []
  assert accepted[typo] is False


def test_the_warm_float32_benchmark_reads_the_cold_ones_compilation_cache(tmp_path):
  calls = _run_steps(tmp_path, ["bench_fp32", "bench_fp32_warm"])
  assert len(calls) == 2
  caches, jsons = [], []
  for flags, argv in calls:
    args = argv.split()
    assert args[:4] == ["-m", "sav_jax.cli", "bench", "--frames"] and flags.strip() == ""
    assert args[args.index("--dtype") + 1] == "float32"
    caches.append(args[args.index("--compile-cache") + 1])
    jsons.append(pathlib.Path(args[args.index("--json") + 1]).name)
  assert caches[0] == caches[1] == str(tmp_path / "out" / "xla_cache")
  assert jsons == ["gpu_t20_720x1280_it20_fp32.json", "gpu_t20_720x1280_it20_fp32_warm.json"]


def test_the_warm_train_step_reads_the_cold_ones_compilation_cache(tmp_path):
  calls = _run_steps(tmp_path, ["train", "train_warm"])
  assert [argv.split()[0] for _, argv in calls] == ["benchmarks/train_step.py"] * 2
  caches = [argv.split()[argv.split().index("--compile-cache") + 1] for _, argv in calls]
  assert caches[0] == caches[1] == str(tmp_path / "out" / "xla_cache")
  assert [pathlib.Path(_json(argv)).name for _, argv in calls] == [
      "gpu_train_t5_256x512_it10_remat_fp32.json", "gpu_train_t5_256x512_it10_remat_fp32_warm.json"]


def test_a_mistyped_step_fails_before_any_step_runs(tmp_path):
  assert _run_steps(tmp_path, ["bench_bf16", "bench_fb32"], rc=2) == []
  assert not (tmp_path / "out").exists()  # before OUTDIR, its log, nvidia-smi and an import


def test_a_failed_step_fails_the_suite_after_the_others_ran(tmp_path):
  # (a first step failing within 90 s stops the suite at once: the lease is not spent)
  calls = _run_steps(tmp_path, ["bench_bf16", "bench_fp32", "bench_blocked"], rc=1,
                     fail_on="--dtype float32")
  assert len(calls) == 3
  assert "some steps failed" in (tmp_path / "out" / "suite.log").read_text()


def test_rerunning_a_step_into_the_same_folder_replaces_its_json(tmp_path):
  calls = _run_steps(tmp_path, ["bench_bf16", "bench_fp32", "bench_fp32_warm", "bench_blocked",
                                "train", "train_warm", "precision"])
  assert len(calls) == 7
  for _, argv in calls:
    assert "--json" in argv and argv.split().count("--overwrite") == 1, argv


def test_gru_conv_step_times_both_forms_then_the_window_with_dft_products(tmp_path):
  calls = [argv for _, argv in _run_steps(tmp_path, ["gru_conv"])]
  assert [a.split()[0] for a in calls] == ["benchmarks/gru_conv.py"] * 2 + ["-m"]
  assert "--frames 20 --height 720 --width 1280" in calls[0] and "--dtype bfloat16" in calls[1]
  assert calls[2].startswith("-m sav_jax.cli bench --frames 20 --height 720 --width 1280 "
                             "--iters 20 --dtype float32 --gru-conv dft")
  assert _json(calls[2]).endswith("gpu_t20_720x1280_it20_fp32_gru_dft.json")


def test_without_a_gpu_the_suite_stops_in_one_line_before_any_step(tmp_path):
  """JAX on a CPU (or a jaxlib without CUDA): each step would run out its limit compiling the
  paper's window there; the suite says so and stops, exit 1."""
  import sys  # pylint: disable=import-outside-toplevel
  fake = tmp_path / "python"  # the real Python for the suite's checks, a recorder for steps
  fake.write_text(f'#!/bin/bash\n[ "$1" = -c ] && exec "{sys.executable}" "$@"\n'
                  'echo "$*" >> "$RECORD"\n')
  fake.chmod(0o755)
  env = dict(os.environ, PYTHON=str(fake), RECORD=str(tmp_path / "calls"), JAX_PLATFORMS="cpu")
  proc = subprocess.run(["bash", str(SUITE), str(tmp_path / "out"), "bench_bf16"], env=env,
                        capture_output=True, text=True, timeout=60, check=False)
  assert proc.returncode == 1, proc.stdout + proc.stderr
  assert "no GPU: JAX in" in proc.stdout and "runs on cpu" in proc.stdout
  assert not (tmp_path / "calls").exists()

"""`sav-jax bench`: JSON record, --compare, and the persistent compilation cache."""

import json

import pytest

from sav_jax import cli, runtime

pytestmark = pytest.mark.usefixtures("fast_compile")

ARGS = ["bench", "--frames", "2", "--height", "32", "--width", "64", "--iters", "2",
        "--repeats", "1"]


def test_bench_records_compares_and_reuses_the_compile_cache(tmp_path, capsys,
                                                              restore_cache_config,
                                                              low_memory_compile_off):
  cache = tmp_path / "xla"
  first, second = tmp_path / "first.json", tmp_path / "second.json"
  assert cli.main([*ARGS, "--json", str(first), "--compile-cache", str(cache)]) == 0
  out = capsys.readouterr().out
  assert f"(stored in {cache})" in out and "peak host RSS" in out
  rec = json.loads(first.read_text())
  assert rec["frames"] == 2 and rec["height"] == 32 and rec["iters"] == 2
  assert rec["median_s"] > 0 and rec["compile_s"] > 0 and rec["peak_rss_gb"] > 0.1
  assert rec["cache_hit"] is False and any(cache.iterdir())

  assert cli.main([*ARGS, "--json", str(second), "--compile-cache", str(cache),
                   "--compare", str(first)]) == 0
  out = capsys.readouterr().out
  assert "(loaded from the compilation cache)" in out
  assert json.loads(second.read_text())["cache_hit"] is True
  assert f"vs {first}: forward x" in out
  assert rec["compiler_options"] == json.loads(second.read_text())["compiler_options"]

  # another compile setting is another program: compiled (not loaded) and recorded
  assert cli.main([*ARGS, "--json", str(second), "--compile-cache", str(cache),
                   "--low-memory-compile"]) == 0
  out = capsys.readouterr().out
  assert "(stored in" in out and "xla_cpu_use_fusion_emitters=False" in out
  rec = json.loads(second.read_text())
  assert rec["cache_hit"] is False and rec["compiler_options"]["xla_cpu_use_fusion_emitters"] is False


def test_bench_rejects_bad_sizes(capsys):
  assert cli.main(["bench", "--height", "30"]) == 2
  assert "multiples of 16" in capsys.readouterr().err

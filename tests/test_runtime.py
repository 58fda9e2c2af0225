"""The persistent compilation cache switch and `release_host_memory`."""

import platform

import jax
import jax.numpy as jnp
import pytest

from sav_jax import cli, runtime


def test_explicit_folder_is_created_and_receives_compiled_programs(tmp_path, restore_cache_config):
  folder = runtime.enable_compilation_cache(tmp_path / "a" / "xla", min_compile_time_s=0)
  assert folder == tmp_path / "a" / "xla" and folder.is_dir()
  assert jax.config.jax_compilation_cache_dir == str(folder)
  jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.0)(jnp.arange(7.0)).block_until_ready()
  assert any(folder.iterdir()), "nothing was written to the compilation cache"


def test_without_a_folder_a_configured_one_is_kept(tmp_path, restore_cache_config):
  jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 5.0)
  assert runtime.enable_compilation_cache() == tmp_path / "mine"
  assert jax.config.jax_persistent_cache_min_compile_time_secs == 5.0


def test_without_any_configuration_the_default_folder_is_used(tmp_path, monkeypatch,
                                                              restore_cache_config):
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
  jax.config.update("jax_compilation_cache_dir", None)
  folder = runtime.enable_compilation_cache()
  assert folder == tmp_path / "xdg" / "sav-jax" / "xla" == runtime.default_cache_dir()
  assert folder.is_dir()


def test_a_file_in_the_way_is_refused(tmp_path, restore_cache_config):
  blocker = tmp_path / "cache"
  blocker.write_text("user data")
  with pytest.raises(ValueError, match="not a folder"):
    runtime.enable_compilation_cache(blocker)
  assert blocker.read_text() == "user data"


def test_release_host_memory_works_on_glibc():
  junk = [bytearray(1 << 20) for _ in range(64)]  # 64 MB allocated and freed
  del junk
  assert runtime.release_host_memory() is (platform.libc_ver()[0] == "glibc")


def test_cli_cache_flags_are_exclusive(capsys):
  with pytest.raises(SystemExit) as e:
    cli.main(["infer", "--left", "l", "--right", "r", "--checkpoint", "c", "--out", "o",
              "--compile-cache", "x", "--no-compile-cache"])
  assert e.value.code == 2
  assert "not allowed with" in capsys.readouterr().err

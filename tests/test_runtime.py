"""The persistent compilation cache switch and `release_host_memory`."""

import ctypes
import io
import platform
import sys
import types

import jax
import jax.numpy as jnp
import pytest

from sav_jax import cli, runtime
from tests.conftest import XLA_DEFAULT_EMITTERS, XLA_OLDER_EMITTERS


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


def test_jax_cache_switched_off_is_respected(tmp_path, restore_cache_config, caplog):
  jax.config.update("jax_enable_compilation_cache", False)
  try:
    assert runtime.enable_compilation_cache(tmp_path / "xla") is None
  finally:
    jax.config.update("jax_enable_compilation_cache", True)
  assert not (tmp_path / "xla").exists()
  assert "switched off" in caplog.text


def test_a_file_in_the_way_is_refused(tmp_path, restore_cache_config):
  blocker = tmp_path / "cache"
  blocker.write_text("user data")
  with pytest.raises(ValueError, match="not a folder"):
    runtime.enable_compilation_cache(blocker)
  assert blocker.read_text() == "user data"


def test_an_empty_or_relative_xdg_cache_home_and_a_tilde_mean_the_home_folder(
    tmp_path, monkeypatch, restore_cache_config):
  # XDG: an empty XDG_CACHE_HOME is unset (not a cache folder relative to where the command
  # runs); a --compile-cache "~/..." that the shell left unexpanded is the user's home.
  monkeypatch.chdir(tmp_path)  # (where a relative path would land)
  monkeypatch.setenv("HOME", str(tmp_path / "home"))
  for xdg in ("", "rel/cache"):  # a relative one is invalid too (XDG): not under the cwd
    monkeypatch.setenv("XDG_CACHE_HOME", xdg)
    assert runtime.default_cache_dir() == tmp_path / "home" / ".cache" / "sav-jax" / "xla"
  folder = runtime.enable_compilation_cache("~/xla", min_compile_time_s=0)
  assert folder == tmp_path / "home" / "xla" and folder.is_dir()
  assert jax.config.jax_compilation_cache_dir == str(folder)
  assert sorted(p.name for p in tmp_path.iterdir()) == ["home"]


def test_a_new_folder_takes_effect_after_the_cache_was_used(tmp_path, restore_cache_config):
  # JAX decides once per process whether (and where) it caches: a folder given after a first
  # compile must still receive the later programs.
  first = runtime.enable_compilation_cache(tmp_path / "first", min_compile_time_s=0)
  jax.jit(lambda x: jnp.tanh(x) * 7.0 - 3.0)(jnp.arange(9.0)).block_until_ready()
  assert any(first.iterdir())
  second = runtime.enable_compilation_cache(tmp_path / "second", min_compile_time_s=0)
  jax.jit(lambda x: jnp.cosh(x) * 11.0 + 2.0)(jnp.arange(6.0)).block_until_ready()
  assert any(second.iterdir()), "the program went to the first folder (or nowhere)"


def test_preserved_settings_puts_every_setting_back(tmp_path):
  before = (jax.config.jax_compilation_cache_dir,
            jax.config.jax_persistent_cache_min_compile_time_secs,
            runtime._low_memory_compile)  # pylint: disable=protected-access
  with runtime.preserved_settings():
    runtime.enable_compilation_cache(tmp_path / "elsewhere", min_compile_time_s=123.0)
    runtime.set_low_memory_compile(not before[2])
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "elsewhere")
  assert (jax.config.jax_compilation_cache_dir,
          jax.config.jax_persistent_cache_min_compile_time_secs,
          runtime._low_memory_compile) == before  # pylint: disable=protected-access
  with pytest.raises(KeyError), runtime.preserved_settings():  # and after an error
    runtime.disable_compilation_cache()
    runtime.set_low_memory_compile(not before[2])
    raise KeyError
  assert jax.config.jax_compilation_cache_dir == before[0]
  assert runtime._low_memory_compile == before[2]  # pylint: disable=protected-access


@pytest.mark.parametrize("flags,default_on", [({"no_compile_cache": True}, True), ({}, False)])
def test_cache_off_means_off_even_when_the_environment_sets_one(tmp_path, restore_cache_config,
                                                                flags, default_on):
  # `--no-compile-cache`, and `sav-jax bench` without `--compile-cache` (it measures
  # compiling): a JAX_COMPILATION_CACHE_DIR cache is neither read nor written.
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax import tools  # pylint: disable=import-outside-toplevel
  env_cache = tmp_path / "env"
  runtime.enable_compilation_cache(env_cache, min_compile_time_s=0)  # as the variable does
  args = argparse.Namespace(compile_cache=None, **flags)
  assert tools.setup_compile_cache(args, default_on=default_on) is None
  assert not jax.config.jax_compilation_cache_dir
  jax.jit(lambda x: jnp.cos(x) * 5.0 - 2.0)(jnp.arange(5.0)).block_until_ready()
  assert not any(env_cache.iterdir())


def test_a_default_folder_that_cannot_be_made_means_no_cache(tmp_path, monkeypatch,
                                                             restore_cache_config, caplog):
  # (a read-only home in a container): the command runs without the cache, as training does;
  # a folder the user names is still refused
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax import tools  # pylint: disable=import-outside-toplevel
  (tmp_path / "notes.txt").write_text("keep me")
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "notes.txt"))
  jax.config.update("jax_compilation_cache_dir", None)
  with caplog.at_level("WARNING"):
    assert tools.setup_compile_cache(argparse.Namespace(compile_cache=None)) is None
  assert "no compilation cache: cannot create the compilation cache folder" in caplog.text
  assert (tmp_path / "notes.txt").read_text() == "keep me"
  with pytest.raises(ValueError, match="cannot create"):
    tools.setup_compile_cache(argparse.Namespace(compile_cache=str(tmp_path / "notes.txt/x")))


@pytest.mark.parametrize("default_on", [True, False])
def test_compile_cache_options(tmp_path, restore_cache_config, default_on):
  """`--compile-cache DIR` is used (created); without it the cache is on where the command has
  it on by default (the folder JAX was given: the test session's), and off elsewhere;
  `--no-compile-cache` exists only where it is on by default; the low-memory compile is on
  unless `--no-low-memory-compile` (and where a command has no such option)."""
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax import tools  # pylint: disable=import-outside-toplevel
  session = jax.config.jax_compilation_cache_dir
  assert session
  p = argparse.ArgumentParser()
  tools.add_compile_cache_arguments(p, default_on=default_on)
  assert ("(default: off)" in " ".join(p.format_help().split())) != default_on
  args = p.parse_args([])
  assert args.compile_cache is None and args.low_memory_compile
  runtime.set_low_memory_compile(False)
  got = tools.setup_compile_cache(args, default_on=default_on)
  assert str(got) == session if default_on else got is None
  assert (jax.config.jax_compilation_cache_dir or None) == (session if default_on else None)
  assert runtime._low_memory_compile  # pylint: disable=protected-access
  args = p.parse_args(["--compile-cache", str(tmp_path / "xla"), "--no-low-memory-compile"])
  assert tools.setup_compile_cache(args, default_on=default_on) == tmp_path / "xla"
  assert jax.config.jax_compilation_cache_dir == str(tmp_path / "xla")
  assert (tmp_path / "xla").is_dir() and not runtime._low_memory_compile  # pylint: disable=protected-access
  runtime.set_low_memory_compile(False)
  args = argparse.Namespace(compile_cache=None)  # a command without these options
  got = tools.setup_compile_cache(args, default_on=default_on)
  assert got == (tmp_path / "xla" if default_on else None)  # (the folder now in use)
  assert runtime._low_memory_compile  # pylint: disable=protected-access
  if default_on:
    assert p.parse_args(["--no-compile-cache"]).no_compile_cache
  else:
    with pytest.raises(SystemExit):
      p.parse_args(["--no-compile-cache"])


def test_release_host_memory_works_on_glibc():
  junk = [bytearray(1 << 20) for _ in range(64)]  # 64 MB allocated and freed
  del junk
  assert runtime.release_host_memory() is (platform.libc_ver()[0] == "glibc")
  trim = runtime._malloc_trim()  # pylint: disable=protected-access
  if platform.libc_ver()[0] == "glibc":  # the real function, with its C signature declared
    assert trim.__name__ == "malloc_trim"
    assert trim.argtypes == [ctypes.c_size_t] and trim.restype is ctypes.c_int


def test_release_host_memory_collects_cycles_then_trims_with_no_padding(monkeypatch):
  calls = []
  monkeypatch.setattr(runtime.gc, "collect", lambda *a: calls.append("collect") or 0)
  monkeypatch.setattr(runtime, "_malloc_trim",
                      lambda: lambda pad: calls.append(("malloc_trim", pad)) or 1)
  assert runtime.release_host_memory() is True
  # malloc_trim(0): keep no padding at the heap's top; cycles freed first, so theirs goes too
  assert calls == ["collect", ("malloc_trim", 0)]
  calls.clear()
  monkeypatch.setattr(runtime, "_malloc_trim", lambda: None)  # a libc without it
  assert runtime.release_host_memory() is False
  assert not calls  # a no-op: not even the collection


@pytest.mark.parametrize("libc", ["without malloc_trim", "not loadable"])
def test_a_libc_without_malloc_trim_is_none(monkeypatch, libc):
  def cdll(name):
    if libc == "not loadable":
      raise OSError(f"{name}: cannot open shared object file")
    return types.SimpleNamespace(free=None)  # musl, macOS: no malloc_trim

  monkeypatch.setattr(runtime.ctypes, "CDLL", cdll)
  # (the lookup itself, past its cache)
  assert runtime._malloc_trim.__wrapped__() is None  # pylint: disable=protected-access


def test_cli_cache_flags_are_exclusive(capsys):
  with pytest.raises(SystemExit) as e:
    cli.main(["infer", "--left", "l", "--right", "r", "--checkpoint", "c", "--out", "o",
              "--compile-cache", "x", "--no-compile-cache"])
  assert e.value.code == 2
  assert "not allowed with" in capsys.readouterr().err


@pytest.mark.usefixtures("without_suite_xla_flags")
def test_inference_options_only_on_cpu_and_never_over_the_users_flag(monkeypatch,
                                                                    restore_low_memory_compile):
  assert runtime.LOW_MEMORY_COMPILE_DEFAULT is True  # the older emitters by default
  runtime.set_low_memory_compile(True)
  assert runtime.inference_compiler_options("gpu") == {}
  assert runtime.inference_compiler_options("tpu") == {}
  # jaxlib 0.11+ has no older emitters: then neither low-memory option (the rewriter's
  # reduce-windows only cost compile time with the older emitters)
  low_memory = {"xla_cpu_use_fusion_emitters", "xla_disable_hlo_passes"}
  assert set(runtime.inference_compiler_options("cpu")) == {
      "xla_cpu_experimental_ynn_fusion_type", *(low_memory if XLA_OLDER_EMITTERS else ())}
  # the per-frame program keeps the newer emitters (8x faster to compile there)
  assert set(runtime.inference_compiler_options("cpu", per_frame=True)) == {
      "xla_cpu_experimental_ynn_fusion_type"}
  # the two low-memory options go together: the user's choice of emitters decides both (the
  # older emitters with the rewriter on compile slowly; the rewriter off alone loses
  # precision for nothing), and passes the user disables stay disabled
  for flags in ("--xla_cpu_use_fusion_emitters=true", "--xla_cpu_use_fusion_emitters"):
    monkeypatch.setenv("XLA_FLAGS", flags)  # (a bare boolean flag is true, as XLA reads it)
    assert set(runtime.inference_compiler_options("cpu")) == {
        "xla_cpu_experimental_ynn_fusion_type"}, flags
  monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
  assert set(runtime.inference_compiler_options("cpu")) == (
      {"xla_cpu_experimental_ynn_fusion_type", "xla_disable_hlo_passes"} if XLA_OLDER_EMITTERS
      else {"xla_cpu_experimental_ynn_fusion_type"})
  monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=LIBRARY_FUSION_TYPE_DOT"
                     ' --xla_disable_hlo_passes="algsimp"')  # XLA removes the quotes
  assert runtime.inference_compiler_options("cpu") == ({
      "xla_cpu_use_fusion_emitters": False,
      "xla_disable_hlo_passes": "algsimp,tree_reduction_rewriter"} if XLA_OLDER_EMITTERS else {})
  runtime.set_low_memory_compile(False)
  assert runtime.inference_compiler_options("cpu") == {}
  for value in ("no", 1, None):  # an int is refused too, not taken for True
    with pytest.raises(TypeError, match=f"takes True or False, got {value!r}"):
      runtime.set_low_memory_compile(value)
  assert runtime.inference_compiler_options("cpu") == {}  # unchanged


def test_no_cpu_options_for_other_backends_that_would_take_them(monkeypatch,
                                                              restore_low_memory_compile):
  # On a GPU host every backend compiles with XLA's options (xla_cpu_* and the disabled
  # passes included): only the platform decides, not whether the options are accepted.
  monkeypatch.setattr(runtime, "_accepts_options", lambda platform, options: True)
  runtime.set_low_memory_compile(True)
  assert runtime.inference_compiler_options("cpu")
  for platform in ("gpu", "cuda", "rocm", "tpu"):
    assert runtime.inference_compiler_options(platform) == {}, platform
    assert runtime.inference_compiler_options(platform, per_frame=True) == {}, platform


@pytest.mark.usefixtures("without_suite_xla_flags")
def test_low_memory_compile_gives_the_same_values(restore_low_memory_compile):
  runtime.set_low_memory_compile(True)
  options = runtime.inference_compiler_options("cpu")
  assert options.get("xla_cpu_use_fusion_emitters") is (False if XLA_OLDER_EMITTERS else None)
  x = jnp.linspace(-3.0, 3.0, 4096).reshape(64, 64)
  fn = lambda x: jax.nn.gelu(x @ x.T).sum(axis=-1) / (1.0 + jnp.abs(x).max())  # noqa: E731
  lowered = jax.jit(fn).lower(x)
  want = lowered.compile(compiler_options=XLA_DEFAULT_EMITTERS)(x)
  got = lowered.compile(compiler_options=options)(x)
  assert jnp.allclose(got, want, rtol=1e-5, atol=1e-4), float(jnp.abs(got - want).max())


@pytest.mark.usefixtures("without_suite_xla_flags")
def test_low_memory_compile_keeps_long_reductions_whole(restore_low_memory_compile):
  """An instance norm over 96x128 maps: XLA's tree reduction rewriter would cut its sums
  into 32x32 reduce-windows, which the older emitters unroll (the encoders' 38 norms made
  up half the whole forward's compile); the low-memory options keep plain reductions,
  and the values stay within float32 summation error of the float64 norm."""
  import numpy as np  # pylint: disable=import-outside-toplevel

  from sav_jax.model.layers import instance_norm  # pylint: disable=import-outside-toplevel
  x = np.random.default_rng(0).normal(5.0, 3.0, (2, 96, 128, 8)).astype(np.float32)
  lowered = jax.jit(instance_norm).lower(x)
  runtime.set_low_memory_compile(True)
  lean = lowered.compile(compiler_options=runtime.inference_compiler_options("cpu"))
  runtime.set_low_memory_compile(False)
  newer = lowered.compile(compiler_options={
      **runtime.inference_compiler_options("cpu"), **XLA_DEFAULT_EMITTERS})
  assert "reduce-window" in newer.as_text()
  # kept whole where the older emitters are there (they would unroll the windows); a
  # jaxlib with only the newer emitters keeps the rewriter's more precise sums
  assert ("reduce-window" in lean.as_text()) is not XLA_OLDER_EMITTERS
  x64 = x.astype(np.float64)
  want = (x64 - x64.mean((1, 2), keepdims=True)) / np.sqrt(x64.var((1, 2), keepdims=True) + 1e-5)
  for compiled in (lean, newer):
    np.testing.assert_allclose(np.asarray(compiled(x)), want, atol=2e-5)


@pytest.mark.usefixtures("without_suite_xla_flags")
def test_inference_options_as_xla_reads_the_users_flags(monkeypatch, restore_low_memory_compile):
  runtime.set_low_memory_compile(True)
  ynn = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_DOT,"
         "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT,LIBRARY_FUSION_TYPE_INDIVIDUAL_CONVOLUTION"}
  older = {"xla_cpu_use_fusion_emitters": False,
           "xla_disable_hlo_passes": "tree_reduction_rewriter"} if XLA_OLDER_EMITTERS else {}
  assert runtime.inference_compiler_options("cpu") == {**ynn, **older}  # (no stray comma)
  # the older emitters asked for in XLA's other spellings of false: the pass goes with them
  for value in ("0", "False"):
    monkeypatch.setenv("XLA_FLAGS", f"--xla_cpu_use_fusion_emitters={value}")
    assert runtime.inference_compiler_options("cpu") == (
        {**ynn, "xla_disable_hlo_passes": "tree_reduction_rewriter"} if XLA_OLDER_EMITTERS
        else ynn), value
  # the rewriter already disabled by the user: their XLA_FLAGS list is left to apply
  monkeypatch.setenv("XLA_FLAGS", "--xla_disable_hlo_passes=tree_reduction_rewriter")
  assert runtime.inference_compiler_options("cpu") == (
      {**ynn, "xla_cpu_use_fusion_emitters": False} if XLA_OLDER_EMITTERS else ynn)
  # an unbalanced quote (XLA's parser decides what it means): the plain words, no error
  monkeypatch.setenv("XLA_FLAGS", '--xla_disable_hlo_passes="algsimp --xla_dump_to=/tmp/x')
  assert "xla_cpu_experimental_ynn_fusion_type" in runtime.inference_compiler_options("cpu")


@pytest.mark.usefixtures("without_suite_xla_flags")
def test_inference_options_this_jaxlib_refuses_are_dropped(monkeypatch, restore_low_memory_compile):
  runtime.set_low_memory_compile(True)
  monkeypatch.setattr(runtime, "_accepts_options", lambda platform, options: all(
      k != "xla_cpu_experimental_ynn_fusion_type" for k, _ in options))
  assert runtime.inference_compiler_options("cpu") == (
      {"xla_cpu_use_fusion_emitters": False, "xla_disable_hlo_passes": "tree_reduction_rewriter"}
      if XLA_OLDER_EMITTERS else {})


def test_unknown_xla_options_are_detected_not_raised():
  assert runtime._accepts_options("cpu", (("xla_sav_jax_no_such_option", "1"),)) is False  # pylint: disable=protected-access
  # ... while no options, and an option XLA has, are accepted (not False for everything)
  assert runtime._accepts_options("cpu", ()) is True  # pylint: disable=protected-access
  assert runtime._accepts_options("cpu", (("xla_backend_optimization_level", "1"),)) is True  # pylint: disable=protected-access


@pytest.mark.usefixtures("fast_compile",  # the last test here: the fixture is module-scoped
                         "without_suite_xla_flags")
def test_inference_forward_keeps_its_temporary_memory_small_with_the_same_values():
  """The whole model (the effect needs the refinement loop's context; a lone attention
  block shows none): T=2, 128x256, iters=2, most XLA optimisations off (the two compiles
  take 12 s instead of 42 s). The inference options' forward needs at most XLA's default
  `temp` and under 136 MB: 120 and 141 MB here; 62 and 65 MB before the GRU's 1x15
  convolutions became DFT products on CPU (`SAVConfig.gru_conv`), whose kernel bins at the
  three scales (42 + 24 + 14 MB, computed once outside the refinement loops) make most of
  the difference (107 MB with XLA's default options while the refinement scanned (1x9, 3x3)
  pairs beside an unrolled last pair, whose extra YNNPACK fusion buffers the options then
  halved; at T=5 iters=8 139 vs 142 MB, then 181 vs 348 MB)."""
  import numpy as np  # pylint: disable=import-outside-toplevel

  import sav_jax  # pylint: disable=import-outside-toplevel
  from sav_jax.model.init import init_variables  # pylint: disable=import-outside-toplevel

  options = runtime.inference_compiler_options("cpu")
  assert options, "this jaxlib should accept --xla_cpu_experimental_ynn_fusion_type"
  cfg = sav_jax.SAVConfig()
  model = sav_jax.StereoAnyVideo(cfg)
  variables = init_variables(cfg, seed=0)
  left = jnp.asarray(np.random.default_rng(0).uniform(0, 255, (1, 2, 128, 256, 3)), jnp.float32)
  right = jnp.roll(left, -4, axis=3)
  lowered = jax.jit(lambda v, l, r: model.apply(v, l, r, iters=2, final_only=True).disparities
                    ).lower(variables, left, right)
  default, lean = (lowered.compile(compiler_options=XLA_DEFAULT_EMITTERS),
                   lowered.compile(compiler_options=options))
  temp = lambda c: c.memory_analysis().temp_size_in_bytes  # noqa: E731
  assert temp(lean) <= temp(default) and temp(lean) < 136 * 2**20, (temp(lean), temp(default))
  np.testing.assert_allclose(np.asarray(lean(variables, left, right)),
                             np.asarray(default(variables, left, right)), atol=1e-4)


def _group(path, **files):
  path.mkdir(parents=True, exist_ok=True)
  for name, text in files.items():
    (path / name.replace("_", ".", 1)).write_text(text)


def test_cgroup_memory_limits_v1_and_v2(tmp_path):
  # v1 (beside an empty v2 hierarchy): the container's group limits to 8 GiB, its parent to
  # 6 GiB; 5 GiB used of which 1 GiB inactive page cache -> 6 - (5 - 1) = 2 GiB left.
  gib = 1 << 30
  proc = tmp_path / "cgroup"
  proc.write_text("5:cpu:/\n4:memory:/docker/abc\n0::/\n")
  v1 = tmp_path / "fs" / "memory"
  _group(v1, memory_limit_in_bytes=str(9223372036854771712), memory_usage_in_bytes=str(9 * gib))
  _group(v1 / "docker", memory_limit_in_bytes=str(6 * gib),
         memory_usage_in_bytes=str(5 * gib), memory_stat=f"total_inactive_file {gib}\n")
  _group(v1 / "docker" / "abc", memory_limit_in_bytes=str(8 * gib),
         memory_usage_in_bytes=str(5 * gib), memory_stat=f"total_inactive_file {gib}\n")
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) == 2 * gib
  # v2 in a cgroup namespace: the process's path is "/" and the mount is its group.
  proc.write_text("0::/\n")
  v2 = tmp_path / "v2"
  _group(v2, cgroup_controllers="memory", memory_max=str(4 * gib),
         memory_current=str(3 * gib), memory_stat=f"anon {gib}\ninactive_file {gib // 2}\n")
  assert runtime.cgroup_free_bytes(str(proc), str(v2)) == 4 * gib - 3 * gib + gib // 2
  # no limit anywhere, or nothing readable
  (v2 / "memory.max").write_text("max\n")
  assert runtime.cgroup_free_bytes(str(proc), str(v2)) is None
  assert runtime.cgroup_free_bytes(str(tmp_path / "none"), str(v2)) is None


def test_cpu_memory_check_follows_a_container_limit(monkeypatch):
  from sav_jax import inference  # pylint: disable=import-outside-toplevel
  cpu = jax.devices("cpu")[0]
  host = inference.available_memory_bytes(cpu)
  monkeypatch.setattr(runtime, "cgroup_free_bytes", lambda: 1 << 20)
  assert host > 1 << 20 and inference.available_memory_bytes(cpu) == 1 << 20
  monkeypatch.setattr(runtime, "cgroup_free_bytes", lambda: None)
  assert abs(inference.available_memory_bytes(cpu) - host) < 1 << 30


def test_memory_of_an_accelerator_without_statistics_is_unknown_not_the_hosts():
  # A GPU or TPU whose runtime gives no memory statistics was checked against the host's RAM:
  # a window refused for the host's 8 GB on a 80 GB device, or let through past 16 GB.
  from sav_jax import inference  # pylint: disable=import-outside-toplevel

  class Device:
    def __init__(self, platform, stats):
      self.platform, self.stats = platform, stats

    def memory_stats(self):
      if isinstance(self.stats, Exception):
        raise self.stats
      return self.stats

  for stats in (None, {}, NotImplementedError("memory_stats")):
    assert inference.available_memory_bytes(Device("gpu", stats)) is None
    assert inference.available_memory_bytes(Device("cpu", stats)) > 1 << 20  # the host's
  assert inference.available_memory_bytes(
      Device("tpu", {"bytes_limit": 16 << 30, "bytes_in_use": 1 << 30})) == 15 << 30


def test_cgroup_limits_at_their_edges(tmp_path):
  gib = 1 << 30
  proc = tmp_path / "cgroup"
  # v1's "no limit" (2**63 rounded down to pages) is no limit; a line that is not
  # "id:controllers:path" is skipped, not the end of the file
  proc.write_text("garbage\n4:memory:/job\n")
  v1 = tmp_path / "fs" / "memory"
  _group(v1, memory_limit_in_bytes=str(9223372036854771712), memory_usage_in_bytes=str(gib))
  _group(v1 / "job", memory_limit_in_bytes=str(9223372036854771712),
         memory_usage_in_bytes=str(gib))
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) is None
  (v1 / "job" / "memory.limit_in_bytes").write_text(str(4 * gib))
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) == 3 * gib
  # usage above the limit: nothing left (not a negative size); more inactive page cache than
  # usage (the two files are read at different times): the whole limit, not more
  (v1 / "job" / "memory.usage_in_bytes").write_text(str(5 * gib))
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) == 0
  (v1 / "job" / "memory.usage_in_bytes").write_text(str(gib))
  (v1 / "job" / "memory.stat").write_text(f"total_inactive_file {2 * gib}\n")
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) == 4 * gib
  # v1's memory.stat has this group's inactive_file beside the hierarchy's
  # total_inactive_file: the latter, whichever line comes first
  (v1 / "job" / "memory.stat").write_text(f"inactive_file {gib // 4}\n"
                                          f"total_inactive_file {gib // 2}\n"
                                          f"total_inactive_file_x {gib}\n")
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) == 4 * gib - gib // 2
  # 2**60 bytes and above are no limit; just below, a limit
  for limit, want in ((1 << 60, None), ((1 << 60) - 4096, (1 << 60) - 4096 - gib // 2)):
    (v1 / "job" / "memory.limit_in_bytes").write_text(str(limit))
    assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) == want
  # hybrid: the unified (v2) hierarchy under <root>/unified, the mount without
  # cgroup.controllers; the limit of the process's group's parent counts too
  proc.write_text("0::/user.slice/session\n")
  v2 = tmp_path / "fs" / "unified"
  _group(v2 / "user.slice", memory_max=str(3 * gib), memory_current=str(2 * gib))
  _group(v2 / "user.slice" / "session", memory_max="max\n", memory_current=str(gib))
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) == gib
  # a group path that is not ASCII: unknown, not an error
  proc.write_bytes("0::/caf\u00e9\n".encode())
  assert runtime.cgroup_free_bytes(str(proc), str(tmp_path / "fs")) is None


def test_draws_progress_on_terminals_and_in_notebooks(monkeypatch):
  class Terminal(io.StringIO):
    def isatty(self):
      return True

  closed = io.StringIO()
  closed.close()  # its isatty() raises ValueError
  monkeypatch.delitem(sys.modules, "ipykernel", raising=False)
  assert runtime.draws_progress(Terminal())
  assert not runtime.draws_progress(io.StringIO())
  assert not runtime.draws_progress(closed) and not runtime.draws_progress(object())
  monkeypatch.setitem(sys.modules, "ipykernel", types.ModuleType("ipykernel"))
  assert runtime.draws_progress(io.StringIO())

"""Shared test fixtures: paths to the oracle fixtures, the generated weights."""

import contextlib
import importlib.util
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
FIXTURES = pathlib.Path(os.environ.get("SAV_FIXTURES", ROOT.parent / "shared" / "fixtures"))

# XLA:CPU's older loop-fusion emitters: the suite's programs (most compiled with the
# `fast_compile` fixture) compile ~1/3 faster with them, e.g. the bfloat16 gradient program
# of tests/model/test_model.py in 22-26 s instead of 37 s, and test_model.py with
# test_model_parity.py take 308 instead of 404 CPU-seconds (2026-12-02); the values agree to
# float32 rounding. Set before JAX creates its CPU client (the first computation), and
# inherited by the subprocesses that keep os.environ's XLA_FLAGS (tests/train/conftest.py's
# jobs add it to theirs; tests/test_multi_device.py's child, whose compiles it would not
# speed up, keeps XLA's default). The end-to-end parity forward of
# tests/model/test_model_parity.py asks for XLA's default emitters.
# jaxlib 0.11+ (Python >= 3.12) has only the newer emitters and aborts the process on the
# unknown flag, so a subprocess asks this jaxlib first (once: pytest-xdist's workers inherit
# the answer through the environment).
_EMITTERS = "xla_cpu_use_fusion_emitters"
_KNOWN_ENV = "SAV_TEST_XLA_OLDER_EMITTERS"


def xla_accepts(flag_sets) -> dict[str, bool]:
  """Whether this jaxlib computes with each of `flag_sets` as its XLA_FLAGS (XLA aborts on
  an unknown flag or enum value). XLA reads XLA_FLAGS once per process, so each set gets its
  own interpreter; they run at once."""
  probe = "import jax.numpy as jnp; assert float(jnp.ones(3).sum()) == 3.0"
  procs = {f: subprocess.Popen([sys.executable, "-c", probe],
                               env={**os.environ, "XLA_FLAGS": f, "JAX_PLATFORMS": "cpu"},
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
           for f in flag_sets}
  return {f: p.wait(timeout=120) == 0 for f, p in procs.items()}


if _KNOWN_ENV not in os.environ:
  _older = f"--{_EMITTERS}=false"
  os.environ[_KNOWN_ENV] = str(int(xla_accepts([_older])[_older]))
# Whether this jaxlib has XLA:CPU's older emitters (what sav_jax.runtime's low-memory
# compile asks for, and the tests of it expect).
XLA_OLDER_EMITTERS = os.environ[_KNOWN_ENV] == "1"
TEST_XLA_FLAGS = f"--{_EMITTERS}=false" if XLA_OLDER_EMITTERS else ""
# Compiler options for a program that should compile with XLA's default emitters.
XLA_DEFAULT_EMITTERS = {_EMITTERS: True} if XLA_OLDER_EMITTERS else {}
if TEST_XLA_FLAGS and _EMITTERS not in os.environ.get("XLA_FLAGS", ""):  # else as asked
  os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()


def _load_make_weights():
  spec = importlib.util.spec_from_file_location("make_weights", FIXTURES / "make_weights.py")
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return mod


@pytest.fixture(scope="module")
def module_tmp_path(request, tmp_path_factory) -> pathlib.Path:
  """A folder for the files a test module shares (a ~140 MB full-size checkpoint, say),
  removed when the module's tests are done. pytest keeps `tmp_path_factory`'s folders to the
  session's end, and each passing test's `tmp_path` only to its teardown (pyproject's
  tmp_path_retention_policy): with both, the suite's peak on disk stays near 1-2 GB."""
  path = tmp_path_factory.mktemp(request.module.__name__.rsplit(".", 1)[-1])
  yield path
  shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="session")
def fixtures_dir() -> pathlib.Path:
  assert FIXTURES.is_dir(), f"oracle fixtures not found at {FIXTURES} (set SAV_FIXTURES)"
  return FIXTURES


@pytest.fixture(scope="session")
def golden_small(fixtures_dir):
  return dict(np.load(fixtures_dir / "golden_small.npz"))


@pytest.fixture(scope="session")
def sav_state_dict(fixtures_dir):
  """The official-layout state dict of make_weights.py, seed 0 (494 arrays)."""
  return _load_make_weights().make_state_dict(str(fixtures_dir / "sav_manifest.json"), 0)


@pytest.fixture(scope="module")
def npz_ckpt(module_tmp_path, sav_state_dict):
  """The state dict of `sav_state_dict` as an official-layout `.npz` file (a test module's)."""
  path = module_tmp_path / "sav.npz"
  np.savez(path, **sav_state_dict)
  return path


RAFT_FIXTURES = ROOT / "tests" / "fixtures" / "raft"


@pytest.fixture(scope="session")
def raft_state_dict(fixtures_dir):
  """The official RAFT's state dict (raft-things layout) from make_weights.py, seed 0: the
  weights of tests/fixtures/raft/raft_oracle.npz (written by make_raft_oracle.py)."""
  return _load_make_weights().make_state_dict(str(RAFT_FIXTURES / "raft_manifest.json"), 0)


@pytest.fixture(scope="session")
def raft_oracle():
  """Inputs and outputs of the official RAFT code for `raft_state_dict`."""
  return dict(np.load(RAFT_FIXTURES / "raft_oracle.npz"))


@pytest.fixture(scope="session")
def vda_state_dict(fixtures_dir):
  """The standalone VDA-S state dict of make_weights.py, seed 0 (351 arrays)."""
  return _load_make_weights().make_state_dict(str(fixtures_dir / "vda_vits_manifest.json"), 0)


@contextlib.contextmanager
def _most_optimizations_off():
  import jax  # pylint: disable=import-outside-toplevel
  old = jax.config.read("jax_disable_most_optimizations")
  jax.config.update("jax_disable_most_optimizations", True)
  try:
    yield
  finally:
    jax.config.update("jax_disable_most_optimizations", old)


@pytest.fixture(scope="module")
def fast_compile():
  """Most XLA optimisations off while a module compiles: about 2x faster on CPU, same
  float32 graph (parity stays ~1e-5 px). Use with `pytestmark = pytest.mark.usefixtures(...)`."""
  with _most_optimizations_off():
    yield


@pytest.fixture
def fast_compile_test():
  """`fast_compile` for one test, in a module whose other programs compile as users' do."""
  with _most_optimizations_off():
    yield


@pytest.fixture
def without_suite_xla_flags(monkeypatch):
  """No XLA_FLAGS in os.environ, as for a user who sets none: what
  `sav_jax.runtime.inference_compiler_options` gives then (the suite sets its own above)."""
  monkeypatch.delenv("XLA_FLAGS", raising=False)


@pytest.fixture
def restore_cache_config():
  """Puts the test session's compilation cache settings back afterwards."""
  from sav_jax import runtime  # pylint: disable=import-outside-toplevel
  with runtime.preserved_settings():
    yield


@pytest.fixture
def restore_low_memory_compile():
  """Puts `sav_jax.runtime.set_low_memory_compile` back afterwards."""
  from sav_jax import runtime  # pylint: disable=import-outside-toplevel
  with runtime.preserved_settings():
    yield


# The test files that take longest (CPU-seconds of their tests, 2026-12-07: the training
# subprocesses first, which run beside the other worker's tests while their own tests wait):
# first in the collection, which `make test` runs in this order (`--no-loadscope-reorder`).
# xdist's own order, the files with the most tests first, left them to the end of the run,
# where the subprocess jobs started last and ran on with one test worker idle.
LONGEST_FILES = (
    "train/test_training_runs.py", "train/test_sharding.py", "train/test_multihost.py",
    "test_multi_device.py", "model/test_model.py", "train/test_state.py", "test_cli_infer.py",
    "test_eval.py", "model/test_model_parity.py", "test_inference.py")


def pytest_collection_modifyitems(config, items):
  """The tests of `LONGEST_FILES` first, in that order; the others after them, as collected."""
  del config
  rank = {ROOT / "tests" / name: i for i, name in enumerate(LONGEST_FILES)}
  items.sort(key=lambda item: rank.get(item.path, len(rank)))  # (stable: files stay whole)


def pytest_configure(config):
  """Share XLA compilations between test processes of one run (and later runs)."""
  import jax  # pylint: disable=import-outside-toplevel
  cache = ROOT / ".jax_cache"
  jax.config.update("jax_compilation_cache_dir", str(cache))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 2.0)


@pytest.fixture
def run_command(monkeypatch):
  """`run_command(main)`: a command's exit status, where its immediate exit after a Ctrl-C
  (`sav_jax._signals.exit_interrupted`, `os._exit` at the command line) is caught as the
  status instead of ending pytest."""
  from sav_jax import _signals  # pylint: disable=import-outside-toplevel

  def exit_now(code):
    raise SystemExit(code)

  monkeypatch.setattr(_signals, "_exit", exit_now)

  def run(main):
    try:
      return main()
    except SystemExit as e:
      return e.code

  return run


def drop_ctrl_c_in_gc() -> None:
  """A Ctrl-C that Python drops: Python's SIGINT handler run inside a garbage-collection
  callback raises KeyboardInterrupt there, which Python reports as "Exception ignored" and
  drops (as one landing in JAX's `_xla_gc_callback` is)."""
  import gc  # pylint: disable=import-outside-toplevel
  import signal  # pylint: disable=import-outside-toplevel

  def in_gc(phase, info):
    if phase == "start":
      signal.getsignal(signal.SIGINT)(signal.SIGINT, None)

  gc.callbacks.append(in_gc)
  try:
    gc.collect()
  finally:
    gc.callbacks.remove(in_gc)

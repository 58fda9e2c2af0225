"""Shared test fixtures: paths to the oracle fixtures, the generated weights."""

import importlib.util
import os
import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
FIXTURES = pathlib.Path(os.environ.get("SAV_FIXTURES", ROOT.parent / "shared" / "fixtures"))


def _load_make_weights():
  spec = importlib.util.spec_from_file_location("make_weights", FIXTURES / "make_weights.py")
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return mod


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


@pytest.fixture(scope="session")
def vda_state_dict(fixtures_dir):
  """The standalone VDA-S state dict of make_weights.py, seed 0 (351 arrays)."""
  return _load_make_weights().make_state_dict(str(fixtures_dir / "vda_vits_manifest.json"), 0)


@pytest.fixture(scope="module")
def fast_compile():
  """Most XLA optimisations off while a module compiles: about 2x faster on CPU, same
  float32 graph (parity stays ~1e-5 px). Use with `pytestmark = pytest.mark.usefixtures(...)`."""
  import jax  # pylint: disable=import-outside-toplevel
  old = jax.config.read("jax_disable_most_optimizations")
  jax.config.update("jax_disable_most_optimizations", True)
  yield
  jax.config.update("jax_disable_most_optimizations", old)


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


def pytest_configure(config):
  """Share XLA compilations between test processes of one run (and later runs)."""
  import jax  # pylint: disable=import-outside-toplevel
  cache = ROOT / ".jax_cache"
  jax.config.update("jax_compilation_cache_dir", str(cache))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 2.0)

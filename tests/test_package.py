"""The package's top level: its names load on use, and the light entry points skip JAX."""

import subprocess
import sys

import pytest

import sav_jax
from tests.conftest import ROOT


def test_version_is_the_installed_distributions_and_the_cli_says_it(capsys):
  import importlib.metadata  # pylint: disable=import-outside-toplevel
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  assert importlib.metadata.version("sav-jax") == sav_jax.__version__  # pyproject reads it
  with pytest.raises(SystemExit) as e:
    cli.main(["--version"])
  assert e.value.code == 0 and capsys.readouterr().out == f"sav-jax {sav_jax.__version__}\n"


def test_names_and_submodules_load_on_use():
  from sav_jax import config, metrics, viz  # pylint: disable=import-outside-toplevel
  from sav_jax.model import stereo_any_video  # pylint: disable=import-outside-toplevel
  assert sav_jax.SAVConfig is config.SAVConfig
  assert sav_jax.StereoAnyVideo is stereo_any_video.StereoAnyVideo
  assert sav_jax.SAVOutput is stereo_any_video.SAVOutput
  assert sav_jax.viz is viz and sav_jax.metrics is metrics
  assert callable(sav_jax.runtime.enable_compilation_cache)
  assert callable(sav_jax.convert.params_from_state_dict)
  assert callable(sav_jax.inference.predict_video)
  assert set(sav_jax.__all__) <= set(dir(sav_jax))
  with pytest.raises(AttributeError, match="no attribute 'nope'"):
    sav_jax.nope  # pylint: disable=pointless-statement
  # hasattr/getattr with a name that is no identifier: False, not a ModuleNotFoundError
  assert not hasattr(sav_jax, "config.x") and not hasattr(sav_jax.model, "init.x")
  assert getattr(sav_jax, "metrics.eval_sequence", None) is None


# Importing JAX takes ~2 s on a 2-core machine: `sav-jax --help`, `python -m eval --help`, an
# argument error and a training config file that does not parse are reported without it.
_NO_JAX = """
import sys
import sav_jax, sav_jax.cli, eval.main
sav_jax.cli.build_parser(); eval.main.build_parser()
import configs.sceneflow, configs.synthetic, configs.mixed, configs.eval.sintel_final
configs.sceneflow.get_config(); configs.synthetic.get_config()
print(sorted(m for m in ("jax", "flax", "optax", "orbax") if m in sys.modules))
"""


def test_cli_parsers_and_configs_do_not_import_jax():
  result = subprocess.run([sys.executable, "-c", _NO_JAX], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, check=False)
  assert result.returncode == 0, result.stderr
  assert result.stdout.strip() == "[]", result.stdout


def test_every_sav_jax_option_has_help():
  """`sav-jax COMMAND --help` explains every option (bench's --dtype had no text)."""
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  sub, = [a for a in cli.build_parser()._actions  # pylint: disable=protected-access
          if isinstance(a, argparse._SubParsersAction)]  # pylint: disable=protected-access
  bare = [f"sav-jax {name} {action.option_strings[-1]}" for name, parser in sub.choices.items()
          for action in parser._actions  # pylint: disable=protected-access
          if action.option_strings and not action.help]
  assert not bare, bare

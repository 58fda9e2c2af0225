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


# -------------------------------------------------------- `sav_jax.cli.main` around a command
@pytest.fixture
def bench_runs(monkeypatch):
  """`bench_runs(fn)`: `sav-jax bench` runs `fn(args)` instead of the benchmark."""
  from sav_jax.tools import bench  # pylint: disable=import-outside-toplevel

  def use(fn):
    monkeypatch.setattr(bench, "run", fn)

  return use


def test_a_commands_status_is_mains(bench_runs):
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  bench_runs(lambda args: 3)
  assert cli.main(["bench"]) == 3
  bench_runs(lambda args: None)
  assert cli.main(["bench"]) == 0


def test_an_empty_compile_cache_is_refused(tmp_path, capsys, monkeypatch, bench_runs):
  # "" would put the compilation cache in the current folder
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  monkeypatch.chdir(tmp_path)
  bench_runs(lambda args: pytest.fail("the command ran"))
  assert cli.main(["bench", "--compile-cache", ""]) == 2
  assert "sav-jax bench: error: --compile-cache is empty; give a path" in capsys.readouterr().err
  assert not any(tmp_path.iterdir())


def test_abbreviated_options_are_refused(capsys, bench_runs):
  # argparse took an unambiguous prefix for the option (--over for --overwrite), silently
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  bench_runs(lambda args: pytest.fail("the command ran"))
  for argv, bad in ((["bench", "--over"], "--over"), (["--verb", "bench"], "--verb")):
    with pytest.raises(SystemExit) as e:
      cli.main(argv)
    assert e.value.code == 2, argv
    assert f"unrecognized arguments: {bad}" in capsys.readouterr().err, argv


def test_verbose_before_or_after_the_command(bench_runs):
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  seen = []
  bench_runs(lambda args: seen.append(args.verbose))
  for argv in (["bench"], ["-v", "bench"], ["bench", "-v"], ["bench", "--verbose"]):
    assert cli.main(argv) == 0, argv
  assert seen == [False, True, True, True]  # (after the command: refused, status 2)


def test_path_options_expand_the_home_folder(tmp_path, monkeypatch):
  """The shell leaves `~` after `--out=` as it is: every option naming a file or folder, of
  every command and of `python -m eval`, expands it (no folder named `~` made here)."""
  import argparse  # pylint: disable=import-outside-toplevel
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  from eval import main as eval_main  # pylint: disable=import-outside-toplevel
  monkeypatch.setenv("HOME", str(tmp_path))
  parsers = {name: action.choices[name] for action in cli.build_parser()._actions
             if isinstance(action, argparse._SubParsersAction) for name in action.choices}
  parsers["eval"] = eval_main.build_parser()
  required = {"infer": ["--left=l", "--right=r", "--checkpoint=c", "--out=o"],
              "convert": ["s", "d"], "eval": ["--config=c", "--checkpoint=c"]}
  seen = set()
  for name, parser in parsers.items():
    for action in parser._actions:
      if action.dest not in (*cli._PATH_ARGS, "data_root", "config"):
        continue
      seen.add(action.dest)
      if action.option_strings:  # the option given last wins over the required one
        argv = [*required.get(name, []), f"{action.option_strings[-1]}=~/{action.dest}"]
      else:  # convert's SRC and DST
        argv = [f"~/{d}" if d == action.dest else "x" for d in ("src", "dst")]
      got = vars(parser.parse_args(argv))[action.dest]
      assert got == str(tmp_path / action.dest), (name, action.dest, got)
  assert seen == {*cli._PATH_ARGS, "data_root", "config"}, seen
  import configs  # pylint: disable=import-outside-toplevel  # python -m train's --config=~/...
  assert configs.locate("~/mine.py:arg") == f"{tmp_path / 'mine.py'}:arg"


def test_a_commands_warnings_are_one_line_each_on_stderr(capsys, bench_runs):
  import warnings  # pylint: disable=import-outside-toplevel
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  shown = warnings.showwarning

  def warn(args):
    warnings.warn("frames 0..4 look swapped", UserWarning)
    return 0

  bench_runs(warn)
  assert cli.main(["bench"]) == 0
  captured = capsys.readouterr()
  assert captured.err == "sav-jax bench: warning: frames 0..4 look swapped\n"
  assert captured.out == ""
  assert warnings.showwarning is shown  # put back


def test_a_warning_shown_on_a_given_file_is_written_there():
  import io  # pylint: disable=import-outside-toplevel
  import warnings  # pylint: disable=import-outside-toplevel
  from sav_jax.tools import one_line_warnings  # pylint: disable=import-outside-toplevel
  f = io.StringIO()
  with one_line_warnings("eval"):
    warnings.showwarning("frames 0..4 look swapped", UserWarning, "x.py", 1, file=f)
  assert f.getvalue() == "eval: warning: frames 0..4 look swapped\n"


def test_main_leaves_the_callers_settings_and_logging(tmp_path, bench_runs):
  import logging  # pylint: disable=import-outside-toplevel
  import jax  # pylint: disable=import-outside-toplevel
  from sav_jax import cli, runtime  # pylint: disable=import-outside-toplevel
  seen = []

  def change_settings(args):
    seen.append(logging.getLogger().getEffectiveLevel())
    runtime.enable_compilation_cache(tmp_path / "cache", min_compile_time_s=77.0)
    runtime.set_low_memory_compile(not runtime._low_memory_compile)  # pylint: disable=protected-access
    return 0

  bench_runs(change_settings)
  before = (jax.config.jax_compilation_cache_dir,
            jax.config.jax_persistent_cache_min_compile_time_secs,
            runtime._low_memory_compile, logging.getLogger().level)  # pylint: disable=protected-access
  assert cli.main(["bench"]) == 0 and cli.main(["-v", "bench"]) == 0
  assert seen == [logging.INFO, logging.DEBUG]  # -v: debug messages too
  assert (jax.config.jax_compilation_cache_dir,
          jax.config.jax_persistent_cache_min_compile_time_secs,
          runtime._low_memory_compile, logging.getLogger().level) == before  # pylint: disable=protected-access


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # (the drop)
def test_a_ctrl_c_that_python_dropped_inside_a_command_is_raised_again(bench_runs):
  import signal  # pylint: disable=import-outside-toplevel
  from sav_jax import _signals, cli  # pylint: disable=import-outside-toplevel
  from tests.conftest import drop_ctrl_c_in_gc  # pylint: disable=import-outside-toplevel
  after = []

  def dropped(args):
    drop_ctrl_c_in_gc()  # (in JAX's garbage-collection callback, say)
    _signals.raise_if_interrupted()  # the command's next safe point (a window, a step)
    after.append("went on")
    return 0

  bench_runs(dropped)
  handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # (xdist ignores it)
  try:
    with pytest.raises(KeyboardInterrupt):
      cli.main(["bench"])
  finally:
    signal.signal(signal.SIGINT, handler)
  assert not after


def test_out_of_memory_before_compiling_names_the_commands_flags(capsys, bench_runs):
  from sav_jax import cli, inference  # pylint: disable=import-outside-toplevel

  def too_big(args):
    raise inference.InsufficientMemoryError("a window of 20 frames needs 41.3 GB, 7.9 GB free",
                                            "fewer frames per window (window/stride)")

  bench_runs(too_big)
  assert cli.main(["bench"]) == 2
  assert capsys.readouterr().err == (
      "sav-jax bench: error: a window of 20 frames needs 41.3 GB, 7.9 GB free; use a smaller "
      "--batch, fewer --frames, smaller --height/--width, fewer --iters or --dtype bfloat16\n")


def test_a_command_missing_a_dependency_fails_loudly(tmp_path, monkeypatch):
  # A command module that is not shipped is left out of the parser; one whose own import
  # fails (a missing dependency) is an error, not a command that silently disappears.
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  (tmp_path / "sav_test_command.py").write_text("import sav_no_such_dependency\n")
  monkeypatch.syspath_prepend(str(tmp_path))
  monkeypatch.setitem(cli.COMMANDS, "absent", "sav_jax.tools.sav_no_such_command")
  sub = lambda: next(a for a in cli.build_parser()._actions  # noqa: E731  # pylint: disable=protected-access
                     if a.choices and "bench" in a.choices).choices
  assert "absent" not in sub() and "infer" in sub()
  monkeypatch.setitem(cli.COMMANDS, "broken", "sav_test_command")
  with pytest.raises(ModuleNotFoundError, match="sav_no_such_dependency"):
    cli.build_parser()


# ------------------------------------------------------------- the source distribution's files
def _in_sdist(paths: list[str]) -> set[str]:
  """Which of `paths` (relative to the root) `python -m build --sdist` packs: the packages
  pyproject.toml's `packages.find` includes and what MANIFEST.in adds (building one needs
  setuptools >= 77 from the network; its MANIFEST.in reader is setuptools' own FileList)."""
  import re  # pylint: disable=import-outside-toplevel
  from setuptools._distutils.filelist import FileList  # pylint: disable=import-outside-toplevel
  found = re.search(r"\[tool\.setuptools\.packages\.find\]\s*include\s*=\s*\[([^\]]*)\]",
                    (ROOT / "pyproject.toml").read_text(encoding="utf-8"))
  packages = [p.rstrip("*") for p in re.findall(r'"([^"]+)"', found.group(1))]
  assert packages and all(p.isidentifier() for p in packages), packages
  manifest = FileList()
  manifest.allfiles = list(paths)
  for line in (ROOT / "MANIFEST.in").read_text(encoding="utf-8").splitlines():
    if line.strip() and not line.lstrip().startswith("#"):
      manifest.process_template_line(line)
  return set(manifest.files) | {p for p in paths if p.split("/")[0] in packages}


def test_the_sdist_holds_the_files_the_readme_and_tests_name():
  """An unpacked sdist passes tests/test_readme.py: the README's files (`.ci/run` was left
  out) and the tests themselves are in it, and `make install` runs there (its constraints)."""
  import re  # pylint: disable=import-outside-toplevel
  named = set(re.findall(r"(?<![\w/.-])((?:benchmarks|configs|sav_jax|train|eval|tests|\.ci)/"
                         r"[\w/.-]*\w)", (ROOT / "README.md").read_text(encoding="utf-8")))
  wanted = sorted({p.relative_to(ROOT).as_posix() for ref in named for p in ROOT.glob(ref + "*")
                   if p.is_file()}
                  | {p.relative_to(ROOT).as_posix() for p in (ROOT / "tests").rglob("*")
                     if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"}
                  | {"README.md", "LICENSE", "Makefile", "constraints.txt"})
  assert len(wanted) > 40 and ".ci/run" in wanted, wanted  # the references are still found
  packed = _in_sdist(wanted)
  assert [p for p in wanted if p not in packed] == []


def test_a_configs_package_of_the_current_folder_is_named_not_a_traceback(tmp_path):
  """A project's own `configs/` in the folder `python -m train` / `python -m eval` run from
  hides sav-jax's configs package: one line saying so and what to run (an AttributeError and a
  ModuleNotFoundError traceback before), and `python -P` runs them."""
  (tmp_path / "configs").mkdir()
  (tmp_path / "configs" / "__init__.py").write_text("")

  def run(*args):
    return subprocess.run([sys.executable, *args], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120, check=False)

  for command, args in (("train", ["--config", "configs/synthetic.py", "--workdir", "w"]),
                        ("eval", ["--help"])):
    result = run("-m", command, *args)
    assert result.returncode == 2, result.stderr
    assert result.stderr.splitlines() == [
        f"{command}: error: `configs` is {tmp_path / 'configs' / '__init__.py'}, not sav-jax's "
        "configs package: a configs/ (or configs.py) of your own in the current folder hides "
        f"it; run `python -P -m {command} ...` (Python 3.11+: leaves the current folder off the "
        "module path) or run from another folder"]
  if sys.version_info >= (3, 11):
    assert run("-P", "-m", "eval", "--help").returncode == 0
  assert not (tmp_path / "w").exists()

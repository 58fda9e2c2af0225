"""The READMEs' references stay true: the files, the Python names and the command-line flags
they name exist (a renamed flag or module would otherwise leave the documentation wrong)."""

import functools
import glob
import importlib
import json
import re
import subprocess
import sys
import textwrap

import pytest

from tests.conftest import ROOT

DOCS = ("README.md", "benchmarks/README.md")


def _prose(doc: str) -> str:
  """The text of `doc` without its fenced blocks (also those indented under a list item)."""
  return re.sub(r"^ *```.*?^ *```", "", (ROOT / doc).read_text(encoding="utf-8"),
                flags=re.S | re.M)


def _code(doc: str) -> str:
  """The text of the fenced blocks (also those indented under a list item) and inline code
  spans of `doc`."""
  text = (ROOT / doc).read_text(encoding="utf-8")
  blocks = re.findall(r"^ *```[^\n]*\n(.*?)^ *```", text, flags=re.S | re.M)
  return "\n".join(blocks + _prose_spans(doc))


def _command_lines(doc: str) -> list[str]:
  """The lines of `_code(doc)`, each command continued with a trailing backslash joined into
  one line (its flags on the next lines belong to it)."""
  return re.sub(r"\\\n[ \t]*", " ", _code(doc)).splitlines()


def _expand(pattern: str) -> list[str]:
  """`a_{x,y}_{1,2}.json` -> [a_x_1.json, a_x_2.json, a_y_1.json, a_y_2.json] (every brace
  group, as the shell expands them)."""
  m = re.search(r"\{([^{}]*)\}", pattern)
  if not m:
    return [pattern]
  return [path for alt in m.group(1).split(",")
          for path in _expand(pattern[:m.start()] + alt + pattern[m.end():])]


@pytest.mark.parametrize("doc", DOCS)
def test_named_files_exist(doc):
  text = (ROOT / doc).read_text(encoding="utf-8")
  refs = {(ROOT, ref) for ref in re.findall(
      r"(?<![\w/.-])((?:benchmarks|configs|sav_jax|train|eval|tests|\.ci)/[\w/.*{},-]*[\w*}])",
      text)}
  # a README below the root also names files relative to its folder (`results/x_{a,b}.json`)
  base = (ROOT / doc).parent
  local = sorted(p.name for p in base.iterdir()
                 if p.is_dir() and base != ROOT and not p.name.startswith(("_", ".")))
  if local:
    refs |= {(base, ref) for ref in re.findall(
        rf"(?<![\w/.-])((?:{'|'.join(map(re.escape, local))})/[\w/.*{{}},-]*[\w*}}])", text)}
  assert len(refs) > 10, refs  # the pattern still finds the references
  missing = [ref if path == ref else f"{ref} ({path})"
             for folder, ref in sorted(refs) for path in _expand(ref)
             if not glob.glob(str(folder / path)) and not glob.glob(str(folder / path) + "*")
             and not ref.startswith("sav_jax/assets/")]  # optional: a bundled checkpoint
  assert not missing, f"{doc} names files that do not exist: {missing}"


@pytest.mark.parametrize("doc", DOCS)
def test_named_python_objects_exist(doc):
  names = set(re.findall(r"\bsav_jax(?:\.\w+)+", (ROOT / doc).read_text(encoding="utf-8")))
  unresolved = []
  for name in sorted(names):
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
      try:
        obj = importlib.import_module(".".join(parts[:i]))
        break
      except ImportError:
        continue
    try:
      for attr in parts[i:]:
        obj = getattr(obj, attr)
    except AttributeError:
      unresolved.append(name)
  assert not unresolved, f"{doc} names Python objects that do not exist: {unresolved}"


# A file name such as `metrics.json` or `init.safetensors` is not a Python reference.
_FILE_SUFFIX = re.compile(r"\.(?:py|json|jsonl|md|txt|csv|png|jpg|exr|pfm|ply|npy|npz|mp4|zip|"
                          r"pth|safetensors|sh|log|yaml|toml)$")


def _prose_spans(doc: str) -> list[str]:
  """The inline code spans of `doc` outside its fenced blocks (where a `model` or `cfg` of the
  README's own snippets cannot be meant)."""
  return re.findall(r"`([^`\n]+)`", _prose(doc))


def _dotted_spans(doc: str, prefixes) -> list[tuple[str, str]]:
  """(span, dotted name) of each prose span that is a dotted name starting with one of
  `prefixes`, alone or followed by a call `(...)` or a value `=...` (the name before those)."""
  found = []
  for span in _prose_spans(doc):
    m = re.fullmatch(r"([A-Za-z_]\w*(?:\.\w+)+)(?:\(.*\)|=.*)?", span)
    if m and m.group(1).split(".")[0] in prefixes and not _FILE_SUFFIX.search(m.group(1)):
      found.append((span, m.group(1)))
  return found


def _resolves(module: str, attrs) -> bool:
  """`module`'s attribute chain `attrs` exists (a dataclass field without a class-level default,
  such as a `SAVConfig` field, counts)."""
  import dataclasses  # pylint: disable=import-outside-toplevel
  try:
    obj = importlib.import_module(module)
  except ImportError:
    return False
  for attr in attrs:
    if (isinstance(obj, type) and dataclasses.is_dataclass(obj)
        and attr in {f.name for f in dataclasses.fields(obj)}):
      obj = None  # the field's value is not a reference the README can go on with
      continue
    try:
      obj = getattr(obj, attr)
    except AttributeError:
      return False
  return True


def _short_names() -> dict[str, list[str]]:
  """Short name -> the full names it may stand for: every module of sav_jax by its last
  component (`viz`, `inference`, `layers`; `convert` is sav_jax.convert or
  sav_jax.tools.convert) and the classes `sav_jax` exports (`SAVConfig`, `StereoAnyVideo`)."""
  import pkgutil  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  names: dict[str, list[str]] = {}
  for info in pkgutil.walk_packages(sav_jax.__path__, "sav_jax."):
    names.setdefault(info.name.rsplit(".", 1)[1], []).append(info.name)
  for name in sav_jax.__all__:
    if name[0].isupper():
      names.setdefault(name, []).append(f"sav_jax.{name}")
  return names


def _config_sections() -> set[str]:
  """The config sections a README may name bare (`data.crop`, `model.remat`, `metrics.raft`):
  the training configs' and the eval configs' fields that hold fields, and `config` itself."""
  return {"config"} | {key for config in _configs() for key, value in config.items()
                       if hasattr(value, "keys")}


def _python_name_resolves(name: str, short: dict[str, list[str]]) -> bool:
  first, *attrs = name.split(".")
  for full in short.get(first, []):
    module, _, cls = full.rpartition(".") if full.split(".")[-1][0].isupper() else (full, "", "")
    if _resolves(module, [cls, *attrs] if cls else attrs):
      return True
  return False


@pytest.mark.parametrize("doc", DOCS)
def test_short_python_names_exist(doc):
  """`viz.colorize_error`, `inference.run_window`, `layers.dft_correlate_w`,
  `SAVConfig.frame_block_mb`: a prose span that starts with a sav_jax module's short name (or a
  class sav_jax exports) names something that exists. Names that start with a config section
  (`model.remat`, `data.augment`, `metrics.raft`) are test_config_fields_in_prose_exist's."""
  short = _short_names()
  spans = _dotted_spans(doc, set(short) - _config_sections())
  assert len(spans) > 5, spans  # the pattern still finds the short names
  unresolved = [span for span, name in spans if not _python_name_resolves(name, short)]
  assert not unresolved, f"{doc} names Python objects that do not exist: {unresolved}"


def test_named_python_objects_resolve_after_import_sav_jax():
  """`sav_jax.model.init.init_variables` as the README writes it works after `import sav_jax`
  alone (each package imports its submodules on first use), in a fresh interpreter."""
  names = sorted({n for doc in DOCS for n in re.findall(
      r"\bsav_jax(?:\.\w+)+", (ROOT / doc).read_text(encoding="utf-8"))})
  script = ("import sav_jax, sys\nbad = []\nfor name in sys.argv[1:]:\n  obj = sav_jax\n"
            "  try:\n    for attr in name.split('.')[1:]:\n      obj = getattr(obj, attr)\n"
            "  except AttributeError:\n    bad.append(name)\nprint(bad)\n")
  proc = subprocess.run([sys.executable, "-c", script, *names], capture_output=True, text=True,
                        cwd=ROOT, timeout=300, check=True)
  assert len(names) > 20 and proc.stdout.strip() == "[]", proc.stdout + proc.stderr


def _options(parser) -> set[str]:
  return {s for action in parser._actions for s in action.option_strings}  # pylint: disable=protected-access


@pytest.mark.parametrize("doc", DOCS)
def test_command_line_flags_exist(doc):
  from eval import main as eval_main  # pylint: disable=import-outside-toplevel
  from sav_jax import cli  # pylint: disable=import-outside-toplevel
  sub = next(a for a in cli.build_parser()._actions if a.choices and "infer" in a.choices)  # pylint: disable=protected-access
  commands = {f"sav-jax {name}": _options(p) for name, p in sub.choices.items()}
  commands["python -m eval"] = _options(eval_main.build_parser())
  # absl flags, defined in train/__main__.py (importing it would define them in this process)
  commands["python -m train"] = {"--" + name for name in re.findall(
      r"DEFINE_\w+\(\s*\"(\w+)\"", (ROOT / "train" / "__main__.py").read_text(encoding="utf-8"))}
  top_level = _options(cli.build_parser())  # `sav-jax -v infer ...`: before the sub-command
  bad, seen = [], 0
  for line in _command_lines(doc):
    for m in re.finditer(r"(?<![\w/.-])(sav-jax|python -m eval|python -m train)(?![\w/.-])(.*?)"
                         r"(?=sav-jax |python -m |$)", line):
      command, rest = m.group(1), m.group(2)
      if command == "sav-jax":
        parts = re.match(r"((?:\s+-[-\w]+)*)(?:\s+(\w+)(?![\w-]))?", rest)
        flags = re.findall(r"(?<![\w.-])(--?[a-z][\w-]*)", parts.group(1))
        seen += len(flags)
        bad += [f"sav-jax has no {flag} ({line.strip()!r})" for flag in flags
                if flag not in top_level]
        if not parts.group(2):
          continue
        command, rest = f"sav-jax {parts.group(2)}", rest[parts.end():]
      if command not in commands:
        bad.append(f"unknown command {command!r} in {line!r}")
        continue
      for flag in re.findall(r"(?<![\w.-])(--[a-z][\w-]*)", rest):
        seen += 1
        if flag not in commands[command]:
          bad.append(f"{command} has no {flag} ({line.strip()!r})")
  assert seen > 5, "the pattern still finds the commands' flags"
  assert not bad, f"{doc}: " + "; ".join(bad)


def _has_field(config, dotted: str) -> bool:
  node = config
  for name in dotted.split("."):
    if not hasattr(node, "keys") or name not in node:
      return False
    node = node[name]
  return True


@functools.cache
def _configs() -> tuple:
  """Every training config (configs/*.py) and every eval config (configs/eval/*.py), built."""
  from eval import config as eval_config  # pylint: disable=import-outside-toplevel
  configs = [importlib.import_module(f"configs.{path.stem}").get_config()
             for path in sorted((ROOT / "configs").glob("*.py")) if path.stem != "__init__"]
  configs += [eval_config.load_config(str(path))
              for path in sorted((ROOT / "configs" / "eval").glob("*.py"))
              if path.stem not in ("__init__", "common")]
  assert len(configs) > 10, configs
  return tuple(configs)


@pytest.mark.parametrize("doc", DOCS)
def test_config_overrides_name_config_fields(doc):
  """Every `--config.<field>`, in code or prose, is a field of the training configs or of the
  eval configs."""
  text = (ROOT / doc).read_text(encoding="utf-8")  # code and prose
  fields = set(re.findall(r"--config\.([a-z_][\w.]*\w)", text))
  unknown = sorted(f for f in fields if not any(_has_field(c, f) for c in _configs()))
  assert not unknown, f"{doc} overrides config fields that no config has: {unknown}"


def _import_resolves(name: str) -> bool:
  """`name` is a module of this repository (`train.optim`) or an attribute chain below one."""
  parts = name.split(".")
  for i in range(len(parts), 0, -1):
    try:
      importlib.import_module(".".join(parts[:i]))
    except ImportError:
      continue
    return _resolves(".".join(parts[:i]), parts[i:])
  return False


@pytest.mark.parametrize("doc", DOCS)
def test_config_fields_in_prose_exist(doc):
  """Config fields the prose names: `config.<field>` (in a code span or not, `config.py` and
  `sav_jax.config.x` aside) is a field of a training or an eval config; a code span that
  starts with a config section (`data.crop`, `model.dtype=bfloat16`, `optimizer.frozen`,
  `metrics.raft`) is such a field, unless it is a Python name the section's word also stands
  for: a sav_jax module by its short name (`metrics.not_measured_note`), the model
  (`model.apply`, `model.init`: StereoAnyVideo's methods) or this repository's train / eval
  package (`train.optim.TrainableVector`)."""
  prose = _prose(doc)
  prefixed = {f for f in re.findall(r"(?<![\w./-])config\.([a-z_][\w.]*\w)", prose)
              if not _FILE_SUFFIX.search("." + f)}
  unknown = sorted(f"config.{f}" for f in prefixed
                   if not any(_has_field(c, f) for c in _configs()))
  short = _short_names()
  spans = _dotted_spans(doc, _config_sections() - {"config"})
  for span, name in spans:
    section, rest = name.split(".", 1)
    if (any(_has_field(c, name) for c in _configs())
        or _python_name_resolves(name, short)
        or (section == "model" and _resolves("sav_jax.model.stereo_any_video",
                                             ["StereoAnyVideo", *rest.split(".")]))
        or (section in ("train", "eval") and _import_resolves(name))):
      continue
    unknown.append(span)
  assert len(prefixed) + len(spans) > (10 if doc == "README.md" else 1), (prefixed, spans)
  assert not unknown, f"{doc} names config fields that no config has: {unknown}"


# Imports each script named on the command line and runs its `main` until it parses its
# arguments, then prints the parser's options as JSON (the scripts build their parsers in
# `main`, some from helpers in benchmarks/timing.py).
_SCRIPT_OPTIONS = """
import argparse, importlib.util, json, pathlib, sys
sys.path.insert(0, "benchmarks")
class Parsed(Exception):
  pass
def parse(self, *args, **kwargs):
  raise Parsed(self)
argparse.ArgumentParser.parse_args = argparse.ArgumentParser.parse_known_args = parse
options = {}
for path in sys.argv[1:]:
  spec = importlib.util.spec_from_file_location("_script_" + pathlib.Path(path).stem, path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  try:
    module.main()
  except Parsed as e:
    options[path] = sorted(s for a in e.args[0]._actions for s in a.option_strings)
print(json.dumps(options))
"""


def test_benchmark_script_flags_exist():
  """`python benchmarks/X.py --flag` in either README: X.py's parser has `--flag`."""
  uses = []
  for doc in DOCS:
    for line in _command_lines(doc):
      for m in re.finditer(r"python (benchmarks/\w+\.py)(.*?)(?=python |sav-jax |$)", line):
        uses += [(doc, m.group(1), flag, line.strip())
                 for flag in re.findall(r"(?<![\w.-])(--[a-z][\w-]*)", m.group(2))]
  scripts = sorted({script for _, script, _, _ in uses})
  assert len(scripts) > 5, "the pattern still finds the scripts' flags"
  result = subprocess.run([sys.executable, "-c", _SCRIPT_OPTIONS, *scripts], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, check=False)
  assert result.returncode == 0, result.stderr[-3000:]
  options = json.loads(result.stdout.strip().splitlines()[-1])
  assert sorted(options) == scripts, "every script parses its arguments in main()"
  bad = [f"{doc}: {script} has no {flag} ({line!r})" for doc, script, flag, line in uses
         if flag not in options[script]]
  assert not bad, "; ".join(bad)


def test_the_random_weights_snippet_saves_weights_the_tools_flag(tmp_path, monkeypatch):
  """The Checkpoints section's "No weights yet?" block runs as written, and what it saves
  restores with the random-prior warning the tools print."""
  text = (ROOT / "README.md").read_text(encoding="utf-8")
  block, = [b for b in re.findall(r"^ *```python\n(.*?)^ *```", text, flags=re.S | re.M)
            if "init_variables(cfg, seed=0)" in b and "save_variables" in b]
  from sav_jax import convert  # pylint: disable=import-outside-toplevel
  monkeypatch.chdir(tmp_path)
  exec(textwrap.dedent(block), {})  # pylint: disable=exec-used
  variables, config = convert.restore_variables(tmp_path / "ckpt" / "random")
  assert "params" in variables and config["model"]["hidden_dim"] == 128
  assert "its frozen depth prior is random (init_variables)" in convert.random_prior_note(
      config, "ckpt/random")


@pytest.mark.parametrize("calib_text", [
    "fx 720\nbaseline 0.54\n",  # the key-value text the snippet's comment names: no fy, cx, cy
    "P2: 720 0 63.5 0 0 720 31.5 0 0 0 1 0\nP3: 720 0 63.5 -388.8 0 720 31.5 0 0 0 1 0\n"])
def test_the_viz_snippet_runs_as_written(tmp_path, monkeypatch, calib_text):
  """The "Looking at the results" block runs with the names the README defines before it
  (`left`, `right`, `variables`, `cfg`) and a ground truth, for a calibration file with or
  without fy / cx / cy; predict_video is stubbed (the block is about `viz`)."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  import sav_jax  # pylint: disable=import-outside-toplevel
  text = (ROOT / "README.md").read_text(encoding="utf-8")
  block, = [b for b in re.findall(r"^ *```python\n(.*?)^ *```", text, flags=re.S | re.M)
            if "viz.disparity_to_points" in b]
  rng = np.random.default_rng(0)
  left = rng.integers(0, 256, (1, 2, 64, 128, 3), dtype=np.uint8)
  disp = rng.uniform(1, 20, (2, 64, 128)).astype(np.float32)
  monkeypatch.setattr(sav_jax.inference, "predict_video", lambda *a, **k: disp)
  monkeypatch.chdir(tmp_path)
  (tmp_path / "calib_cam_to_cam.txt").write_text(calib_text, encoding="utf-8")
  scope = dict(sav_jax=sav_jax, variables=None, cfg=None, left=left, right=left,
               gt=disp + 1, valid=np.ones(disp.shape, bool))
  exec(textwrap.dedent(block), scope)  # pylint: disable=exec-used
  assert scope["xyz"].shape == (64 * 128, 3) and (tmp_path / "frame0.ply").is_file()
  assert scope["cam"].fy == 720 and (scope["cam"].cx, scope["cam"].cy) == (63.5, 31.5)
  np.testing.assert_allclose(scope["depth"], 720 * 0.54 / disp, rtol=1e-5)

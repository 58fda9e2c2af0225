"""Config files and command-line overrides (`--config.iters=4`, `--config.plots.enabled false`).

A config is a Python file with `get_config()` (or `get_config(arg)`, selected with
`path.py:arg` as in big_vision) returning an `ml_collections.ConfigDict`. Overrides
name an existing field; the value is parsed to that field's type (bool accepts
true/false/1/0/yes/no/on/off; integers are decimal, `010` is 10; tuples and lists are Python
literals).
"""

from __future__ import annotations

import ast
import importlib.machinery
import importlib.util
import inspect
import pathlib

import ml_collections

from sav_jax._checks import scientific_integer, within_int64

# The methods a run evaluates: the model, and the baselines `--baseline` adds.
METHOD_NAMES = {"sav": "Stereo Any Video", "sgbm": "StereoSGBM"}
BASELINES = ("sgbm",)


def load_config(spec: str) -> ml_collections.ConfigDict:
  """Loads `path/to/config.py` or `path/to/config.py:arg` (`configs/...` from any folder:
  `configs.locate`)."""
  import configs  # pylint: disable=import-outside-toplevel
  spec = configs.locate(spec)
  path, arg = (spec.split(".py:", 1)[0] + ".py", spec.split(".py:", 1)[1]) if ".py:" in spec \
      else (spec, "")
  file = pathlib.Path(path)
  if not file.is_file():
    raise FileNotFoundError(f"config file not found: {file}")
  name = f"_eval_config_{file.stem}"  # any file name: Python code, whatever its suffix
  module_spec = importlib.util.spec_from_file_location(
      name, file, loader=importlib.machinery.SourceFileLoader(name, str(file)))
  module = importlib.util.module_from_spec(module_spec)
  try:
    module_spec.loader.exec_module(module)
  except SyntaxError as e:
    where = f": line {e.lineno}" if e.lineno else ""
    raise ValueError(f"{file} does not parse{where}: {e.msg}") from e
  except Exception as e:  # pylint: disable=broad-except  # the user's code: name the file
    raise ValueError(f"{file}: importing it raised {type(e).__name__}: {e}") from e
  if not hasattr(module, "get_config"):
    raise ValueError(f"{file}: defines no get_config()")
  signature = inspect.signature(module.get_config)
  try:
    signature.bind(arg) if arg else signature.bind()  # pylint: disable=expression-not-assigned
  except TypeError as e:
    how = f"with the argument {arg!r} (from {spec})" if arg else "without an argument"
    raise ValueError(f"{file}: get_config{signature} cannot be called {how}") from e
  try:
    config = module.get_config(arg) if arg else module.get_config()
  except Exception as e:  # pylint: disable=broad-except  # the user's code: name the file
    raise ValueError(f"{file}: get_config() raised {type(e).__name__}: {e}") from e
  if not isinstance(config, ml_collections.ConfigDict):
    raise ValueError(f"{file}: get_config() returned {type(config).__name__}, not a ConfigDict")
  return config


def check_fields(config: ml_collections.ConfigDict, spec: str) -> None:
  """Raises ValueError naming the fields of an evaluation config (`configs/eval/common.py`)
  that `config`, loaded from `spec`, lacks (e.g. a training config given by mistake), or
  the fields it has that none has (a misspelt name, which nothing would read); the block
  `synthetic` is the synthetic set's (`eval.data`)."""
  from configs.eval import common  # pylint: disable=import-outside-toplevel
  fields = set(_flat_names(common.eval_config("x", sample_len=-1)))
  missing = sorted(fields - set(_flat_names(config)))
  if not missing:
    unknown = sorted(name for name in set(_flat_names(config)) - fields
                     if name.split(".")[0] != "synthetic")
    if unknown:
      raise ValueError(f"{spec}: no such config field {', '.join(unknown)} (misspelt? it would "
                       "be ignored; python -m eval --help lists the fields)")
    return
  training = "train" in config or "optimizer" in config
  raise ValueError(
      f"{spec} is not an evaluation config: it lacks "
      f"{', '.join(missing[:6])}{f' and {len(missing) - 6} more' if len(missing) > 6 else ''}"
      + ("; it is a training config (python -m train)" if training else "")
      + "; evaluation configs build on configs/eval/common.py (e.g. configs/eval/"
      "sintel_final.py)")


def fields_help() -> str:
  """The fields every evaluation config has, with `configs/eval/common.py`'s defaults (the
  dataset's own config sets `dataset`, `split` and `sample_len`): `python -m eval --help`."""
  from configs.eval import common  # pylint: disable=import-outside-toplevel
  config = common.eval_config("<dataset>", sample_len=-1)
  shown = [f"{name}={value!r}" for name, value in _flat_items(config)
           if name not in ("dataset", "split", "sample_len")]
  return ("config fields, overridden with --config.<field>=<value> (the dataset's config sets "
          "dataset, split and sample_len; configs/eval/common.py explains each): "
          + ", ".join(shown))


def split_overrides(argv: list[str]) -> tuple[list[str], list[tuple[str, str]]]:
  """Separates `--config.a.b=v` / `--config.a.b v` from the other arguments.

  Returns:
    `(other arguments, [(dotted field, value string), ...])`.
  """
  rest, overrides, i = [], [], 0
  while i < len(argv):
    arg = argv[i]
    if arg.startswith("--config."):
      name, eq, value = arg[len("--config."):].partition("=")
      if not eq:
        if i + 1 >= len(argv) or argv[i + 1].startswith("--"):  # not the next option
          raise ValueError(f"{arg} needs a value ({arg}=VALUE or {arg} VALUE)")
        value, i = argv[i + 1], i + 1
      overrides.append((name, value))
    else:
      rest.append(arg)
    i += 1
  return rest, overrides


def _parse(value: str, current, name: str):
  if isinstance(current, bool):
    low = value.strip().lower()
    if low in ("1", "true", "yes", "on"):
      return True
    if low in ("0", "false", "no", "off"):
      return False
    raise ValueError(f"--config.{name}: expected true/false, got {value!r}")
  if isinstance(current, (int, float)):
    try:
      number = type(current)(value)  # int: decimal (010 is 10, as on the training's side)
    except ValueError:
      # 1e3 is 1000, as on the training's side (int() refuses it)
      number = scientific_integer(value) if isinstance(current, int) else None
      if number is None:
        raise ValueError(f"--config.{name}: expected {type(current).__name__}, "
                         f"got {value!r}") from None
    if isinstance(current, int) and not within_int64(number):
      raise ValueError(f"--config.{name}: {value} is out of range (at most 2**63 - 1)")
    return number
  if isinstance(current, str):
    return value
  try:
    return ast.literal_eval(value)
  except (ValueError, SyntaxError):
    return value


def apply_overrides(config: ml_collections.ConfigDict,
                    overrides: list[tuple[str, str]]) -> ml_collections.ConfigDict:
  """Sets each dotted field (which must exist) to its parsed value, in place."""
  for name, value in overrides:
    *parents, leaf = name.split(".")
    node = config
    for part in parents:
      if part not in node or not isinstance(node[part], ml_collections.ConfigDict):
        raise ValueError(f"--config.{name}: no such config field (fields: "
                         f"{', '.join(sorted(_flat_names(config)))})")
      node = node[part]
    if leaf not in node or isinstance(node[leaf], ml_collections.ConfigDict):
      raise ValueError(f"--config.{name}: no such config field (fields: "
                       f"{', '.join(sorted(_flat_names(config)))})")
    try:
      setattr(node, leaf, _parse(value, node[leaf], name))
    except TypeError as e:
      raise ValueError(f"--config.{name}: {e}") from e
  return config


def _flat_items(config, prefix=""):
  """`(dotted name, value)` of every leaf field of `config`."""
  for k, v in config.items():
    if isinstance(v, ml_collections.ConfigDict):
      yield from _flat_items(v, f"{prefix}{k}.")
    else:
      yield prefix + k, v


def _flat_names(config):
  return (name for name, _ in _flat_items(config))

"""Experiment configs: Python files whose get_config() returns an ml_collections.ConfigDict."""

import os
import pathlib


def locate(spec: str) -> str:
  """The config file `spec` names (`path/to/config.py`, or `...py:arg`).

  A path that exists is kept. One that does not and starts with `configs/` (the checkout's
  layout, which the README's commands use) becomes this package's file when it has one:
  `python -m train --config configs/synthetic.py` then runs from any folder with the
  package installed (a wheel, not only the checkout). Anything else is kept, for the
  caller's "not found" error. A leading `~` is expanded (the shell leaves it after
  `--config=`).
  """
  spec = os.path.expanduser(str(spec))
  path, arg = spec.split(".py:", 1) if ".py:" in spec else (spec, None)
  path = path + ".py" if arg is not None else path
  parts = pathlib.PurePath(path).parts
  if pathlib.Path(path).exists() or not parts or parts[0] != "configs":
    return spec
  installed = pathlib.Path(__file__).parent.joinpath(*parts[1:])
  if not installed.is_file():
    return spec
  return str(installed) + ("" if arg is None else f":{arg}")


def lacking_fields(config, missing: list[str], what: str = "fields") -> str:
  """`lacks N <what> (a, b, ...)[; it is an evaluation config (python -m eval)]: build its
  get_config() on ...`: the words for a training config that lacks the `missing` fields of
  `configs.sceneflow.base_config()` (`train.loop.check_fields`, and `python -m train`'s
  parsing of overrides, which must not import JAX)."""
  evaluation = ("; it is an evaluation config (python -m eval)"
                if {"baseline", "window", "stride"} <= set(config.keys()) else "")
  return (f"lacks {len(missing)} {what} ({', '.join(missing[:8])}"
          f"{', ...' if len(missing) > 8 else ''}){evaluation}: build its get_config() on "
          "configs.sceneflow.base_config(), as configs/synthetic.py does")

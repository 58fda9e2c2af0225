"""The `sav-jax` command: demo, infer, convert, bench."""

from __future__ import annotations

import argparse
import importlib
import sys

try:
  from sav_jax import _signals
  from sav_jax.tools import (UsageError, command_logging, empty_path_problem,
                             one_line_warnings, printable_names)
except KeyboardInterrupt:  # Ctrl-C while the command loads: one line, not a traceback
  print("sav-jax: interrupted", file=sys.stderr)
  sys.exit(130)

COMMANDS = {
    "demo": "sav_jax.tools.demo",
    "infer": "sav_jax.tools.infer",
    "convert": "sav_jax.tools.convert",
    "bench": "sav_jax.tools.bench",
}


# Arguments that name files or folders, of any command: an empty one is refused.
_PATH_ARGS = ("left", "right", "checkpoint", "calib", "out", "src", "dst", "json", "compare",
              "compile_cache")

# What to change when a device runs out of memory (`runtime.out_of_memory`), per command.
_OUT_OF_MEMORY_HINTS = {
    "infer": "use fewer frames per window (--window, --stride), --resize HxW, fewer --iters, "
             "--dtype bfloat16 or a device with more memory",
    "demo": "use fewer --frames, smaller --height/--width, fewer --iters or --dtype bfloat16",
    "bench": "use a smaller --batch, fewer --frames, smaller --height/--width, fewer --iters "
             "or --dtype bfloat16",
}


def build_parser() -> argparse.ArgumentParser:
  parser = argparse.ArgumentParser(
      prog="sav-jax", description="Stereo Any Video in JAX: temporally consistent video stereo.",
      allow_abbrev=False)
  parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
  from sav_jax import __version__  # pylint: disable=import-outside-toplevel
  parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
  sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
  for name, module_name in COMMANDS.items():
    try:
      module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:  # a sub-command not shipped in this build
      if e.name != module_name:
        raise
      continue
    # (allow_abbrev: --over was taken for --overwrite, --check for --checkpoint, silently)
    p = sub.add_parser(name, help=module.HELP, description=module.HELP, allow_abbrev=False)
    module.add_arguments(p)
    # also after the command (`sav-jax infer ... -v` was refused); SUPPRESS keeps the
    # top-level value where the command's is not given
    p.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                   help="log debug messages")
    p.set_defaults(_run=module.run)
  return parser


def main(argv: list[str] | None = None) -> int:
  """Runs one command; called from Python, it leaves logging and JAX's settings as it found
  them (`sav_jax.runtime.preserved_settings`)."""
  try:
    parser = build_parser()
    args = parser.parse_args(argv)
  except KeyboardInterrupt:  # Ctrl-C while the sub-commands load: one line, as below
    if argv is not None:
      raise
    _signals.exit_interrupted("sav-jax: interrupted")
  empty = empty_path_problem(args, _PATH_ARGS)
  if empty:
    print(f"sav-jax {args.command}: error: {empty}", file=sys.stderr)
    return 2
  try:
    # (warnings met by the command, e.g. `inference.SwappedViewsWarning`, as one line each;
    # interrupts remembered before JAX is imported: a Ctrl-C its import's GC callback drops)
    with (_signals.remembered_interrupts(), command_logging(args.verbose),
          importlib.import_module("sav_jax.runtime").preserved_settings(), printable_names(),
          one_line_warnings(f"sav-jax {args.command}")):
      return int(args._run(args) or 0)
  except (UsageError, ValueError, OSError) as e:  # OSError: a disk full, a folder not writable
    text = str(e)
    if hasattr(e, "need") and args.command in _OUT_OF_MEMORY_HINTS:
      # inference's memory check: the remedies as this command's flags, not Python arguments
      hint = _OUT_OF_MEMORY_HINTS[args.command]
      if args.command == "infer" and getattr(e, "devices", None):  # windows at once
        hint = hint.replace("use ", f"use fewer --devices (here {e.devices}), ", 1)
      text = f"{e.need}; {hint}"
    print(f"sav-jax {args.command}: error: {text}", file=sys.stderr)
    return 2
  except MemoryError as e:  # numpy's: sizes far beyond this machine's memory
    print(f"sav-jax {args.command}: error: out of host memory: {e} (use smaller frames, fewer "
          "frames or a smaller batch)", file=sys.stderr)
    return 2
  except Exception as e:  # pylint: disable=broad-except  # XLA's, compiling or running
    from sav_jax import runtime  # pylint: disable=import-outside-toplevel  # jax: after --help
    oom = runtime.out_of_memory(e)
    if oom is None:
      raise
    hint = _OUT_OF_MEMORY_HINTS.get(args.command, "use smaller inputs")
    print(f"sav-jax {args.command}: error: out of memory on the device: {oom}; {hint}",
          file=sys.stderr)
    return 2
  except KeyboardInterrupt:  # Ctrl-C at the command line: one line, not a traceback (called
    if argv is not None:     # from Python with arguments, the caller gets the interrupt)
      raise
    from sav_jax._signals import exit_interrupted  # pylint: disable=import-outside-toplevel
    exit_interrupted(f"sav-jax {args.command}: interrupted")


if __name__ == "__main__":
  sys.exit(main())

"""Entry point: `python -m train --config configs/synthetic.py --workdir DIR [flags]`.

Single host, any number of local devices (1 CPU, N GPUs): nothing to add; the batch is
sharded over all devices. Several hosts: start one process per host with
`--coordinator_address=host0:1234 --num_processes=N --process_id=i` (or
`--distributed=auto` on TPU pods / SLURM, where JAX finds them itself).
Config fields are overridable: `--config.train.batch_size=16`. Bad input (a config value,
the workdir, weights or data that cannot be used) exits with status 2 and one line on
stderr; `-v 1` shows its traceback. On SIGTERM (a scheduler's preemption notice) the run
saves a checkpoint of the step it is on and exits with status 143; the same command resumes.
"""

import logging
import pathlib
import re
import sys
import traceback

try:
  from absl import app, flags
  from ml_collections import config_flags
except KeyboardInterrupt:  # Ctrl-C while the program loads: one line, not a traceback
  print("train: interrupted (Ctrl-C)", file=sys.stderr)
  sys.exit(130)

_CONFIG = config_flags.DEFINE_config_file("config", None, "Training config file.",
                                          lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run directory (checkpoints, logs).")
_COORD = flags.DEFINE_string("coordinator_address", None,
                             "host:port of process 0, for multi-process training.")
_NUM_PROC = flags.DEFINE_integer("num_processes", None, "Number of processes.")
_PROC_ID = flags.DEFINE_integer("process_id", None, "This process's index.")
_DISTRIBUTED = flags.DEFINE_enum("distributed", "off", ["off", "auto"],
                                 "'auto': jax.distributed.initialize() with no arguments "
                                 "(TPU pods, SLURM, ...).")
flags.mark_flags_as_required(["config", "workdir"])


def _fail(message: str) -> None:
  print(f"train: error: {message}", file=sys.stderr)
  sys.exit(2)


_HELP_FLAGS = {"--help", "-help", "-h", "-?", "--helpfull", "-helpfull", "--helpshort",
               "-helpshort"}


def last_overrides(argv: list[str]) -> list[str]:
  """`argv` with each `--config.<field>` override only at its last occurrence: the last one
  wins, as for any flag (ml_collections' tuple fields joined repeated values instead:
  `--config.data.crop=(32, 32) --config.data.crop=(48, 64)` became `(32, 32, 48, 64)`, as a
  script that appends a user's overrides to its own gives)."""
  items, i = [], 0  # (field or None, the arguments)
  while i < len(argv):
    arg = argv[i]
    if arg == "--":
      items.append((None, argv[i:]))
      break
    if arg.startswith("--config.") and "=" in arg:
      items.append((arg.split("=", 1)[0], [arg]))
    elif (arg.startswith("--config.") and i + 1 < len(argv)
          and not argv[i + 1].startswith("--")):  # `--config.a.b value`
      items.append((arg, argv[i:i + 2]))
      i += 1
    else:
      items.append((None, [arg]))
    i += 1
  last = {field: k for k, (field, _) in enumerate(items) if field is not None}
  return [a for k, (field, args) in enumerate(items) if field is None or last[field] == k
          for a in args]


def integral_numbers(argv: list[str]) -> list[str]:
  """`argv` with override values written as whole numbers in scientific notation (`1e3`,
  `1.2e5`) spelt as integers: ml_collections parses integer fields with `int()`, which
  refused `--config.train.num_steps=1e5` ("invalid literal"); float fields read the
  integer as well. Negative exponents (`1e-4`) and fractions stay as they are."""
  from sav_jax._checks import scientific_integer  # pylint: disable=g-import-not-at-top
  out, field = [], False
  for arg in argv:
    value = None
    if arg.startswith("--config.") and "=" in arg:
      key, value = arg.split("=", 1)
    elif field:  # the value after `--config.a.b`
      key, value = None, arg
    field = arg.startswith("--config.") and "=" not in arg
    whole = None if value is None else scientific_integer(value)
    if whole is not None:
      value = str(whole)
      arg = value if key is None else f"{key}={value}"
    out.append(arg)
  return out


def located_config(argv: list[str]) -> list[str]:
  """`argv` with its --config file found by `configs.locate`: `configs/...` names the
  installed package's file when the current folder has none (a configs/ of the folder's own
  that hides the package: one line naming it)."""
  from sav_jax._checks import sav_jax_configs  # pylint: disable=g-import-not-at-top

  def locate(spec):
    try:
      return sav_jax_configs("train").locate(spec)
    except ValueError as e:
      _fail(str(e))

  out = list(argv)
  for i, a in enumerate(out):
    if a in ("--config", "-config") and i + 1 < len(out):
      out[i + 1] = locate(out[i + 1])
    elif a.startswith(("--config=", "-config=")):
      flag, value = a.split("=", 1)
      out[i] = f"{flag}={locate(value)}"
  return out


def parse_flags(argv):
  """absl's flag parsing, with every error as one line and exit status 2: a flag value of the
  wrong type, a config file that does not parse, an override of a field that does not exist
  (ml_collections raises the last two from inside the parser, and absl would print their
  traceback); `--help` exits with status 0."""
  argv = located_config(integral_numbers(last_overrides(argv)))
  try:
    rest = flags.FLAGS(argv)
  except SystemExit as e:  # absl's --help/--helpfull print the flags and exit with status 1
    if e.code == 1 and _HELP_FLAGS & set(argv[1:]):
      sys.exit(0)
    raise
  except flags.Error as e:  # a value of the wrong type, a missing --workdir, an unknown flag
    _fail(f"{e} (--helpfull lists the flags)")
  except SyntaxError as e:  # the --config file is loaded while the flags are parsed
    where = f": line {e.lineno}" if e.lineno else ""
    _fail(f"the config file {e.filename or _config_arg(argv)} does not parse{where}: {e.msg}")
  except OSError as e:  # a missing --config file, met by an override
    _config_file_error(e)
  except (AttributeError, KeyError) as e:
    key_error = e if isinstance(e, KeyError) else e.__context__
    if not isinstance(key_error, KeyError) or not key_error.args:
      _config_code_error(argv, e)  # e.g. a file without get_config()
    detail = str(key_error.args[0]).strip().replace("\n", "; ")
    step = re.match(r"Attribute <class '([\w.]+)'>\.(\w+) .*Attempting to lookup: ([\w.]+)",
                    detail)
    if step and step[3].split(".")[0] == step[2]:  # the first step: the config is not one
      _not_a_config(argv, step[1])
    if step:  # a step through a value, e.g. --config.train.iters.x (iters is an int)
      path = step[3].split(".")
      parent = ".".join(path[:path.index(step[2])]) if step[2] in path else step[3]
      detail = f"{step[3]}: config.{parent} is {step[1]}, not a config block"
    _not_a_training_config(argv)  # an override into a block the file lacks: the file is wrong
    overrides = [a.split("=", 1)[0] for a in argv if a.startswith("--config.")]
    sources = ""
    if any(o.startswith("--config.data.sources.") for o in overrides):
      sources = ("; training sources are added or removed in a config file of your own (see "
                 "configs/mixed.py): the command line can only change an existing source's "
                 "fields")
    _fail(f"no such config field {detail} (overrides: {', '.join(overrides)}); the fields "
          f"are those of the --config file's get_config(){sources}")
  except Exception as e:  # pylint: disable=broad-except  # the config file's own code raised
    _config_code_error(argv, e)
  if len(rest) > 1:  # (main would drop them: `--config.model.remat false` left remat on)
    _unexpected_arguments(argv, rest[1:])
  return rest


def _unexpected_arguments(argv, extra) -> None:
  """Exits naming arguments that are no flag's: absl reads a true/false field given as
  `--config.a.b false` as `--config.a.b` (true) and leaves `false` over."""
  hint = ""
  k = next((k for k in range(1, len(argv)) if argv[k] == extra[0]), None)
  if k is not None and argv[k - 1].startswith("--config.") and "=" not in argv[k - 1]:
    hint = (f"; a true/false field takes its value after '=': {argv[k - 1]}={extra[0]} "
            f"({argv[k - 1]} alone means true)")
  _fail(f"unexpected argument {extra[0]!r}{hint}")


def _not_a_training_config(argv) -> None:
  """Exits naming the top-level fields of a training config that the --config file's config
  lacks, if it lacks any (an evaluation config given by mistake): an override into one of
  them (`--config.data.root=...`) was reported as a misspelt override, "no such config field
  'data'"."""
  try:  # (absl keeps no value of a flag whose parsing failed: the file is loaded again)
    config = flags.FLAGS["config"].parser.parse(_config_arg(argv))
    keys = set(config.keys())
  except Exception:  # pylint: disable=broad-except  # no config to look at: the caller reports
    return
  from configs import lacking_fields, sceneflow  # pylint: disable=g-import-not-at-top
  missing = [k for k in sceneflow.base_config() if k not in keys]
  if missing:  # (train.loop.check_fields checks every field, with the same words)
    what = "of a training config's fields"
    _fail(f"the config file {_config_arg(argv)} {lacking_fields(config, missing, what)}")


def _config_arg(argv) -> str:
  """The --config file named in `argv` (for messages)."""
  for i, a in enumerate(argv):
    if a in ("--config", "-config") and i + 1 < len(argv):
      return argv[i + 1]
    if a.startswith(("--config=", "-config=")):
      return a.split("=", 1)[1]
  return "(--config)"


def _config_code_error(argv, e: BaseException) -> None:
  _fail(f"the config file {_config_arg(argv)} cannot be used: loading it raised "
        f"{type(e).__name__}: {e} (it must define get_config() returning a ConfigDict)")


def _not_a_config(argv, kind: str) -> None:
  _fail(f"the config file {_config_arg(argv)} cannot be used: its get_config() returned "
        f"{kind}, not a ConfigDict")


def load_config():
  """The --config file's ConfigDict; a file that cannot be found is one line naming it
  (ml_collections defers that error to the first use of the config)."""
  config = _CONFIG.value
  try:
    config.keys()
  except OSError as e:
    _config_file_error(e)
  except AttributeError:  # get_config() returned a non-config
    _not_a_config(sys.argv, type(config).__name__)
  except Exception as e:  # pylint: disable=broad-except  # a config whose keys() raises
    _config_code_error(sys.argv, e)
  return config


def _config_file_error(e: OSError) -> None:
  """Exits with the last line of ml_collections' multi-line report (it names the file)."""
  lines = [l.strip() for l in str(e).splitlines() if l.strip()]
  _fail(f"cannot load the --config file: {lines[-1] if lines else e}")


def main(argv):
  del argv
  config = load_config()
  import jax  # pylint: disable=g-import-not-at-top
  if _COORD.value is not None:
    host, colon, port = _COORD.value.rpartition(":")
    if not (colon and host and port.isdigit()):  # (JAX's IndexError traceback without a port)
      _fail(f"--coordinator_address={_COORD.value!r}: expected host:port of process 0 (e.g. "
            "host0:1234)")
    n, i = _NUM_PROC.value, _PROC_ID.value
    if n is None or i is None or not (n >= 1 and 0 <= i < n):
      _fail(f"--coordinator_address needs --num_processes >= 1 and 0 <= --process_id < "
            f"--num_processes, got --num_processes={n} --process_id={i}")
    jax.distributed.initialize(_COORD.value, n, i)
  elif _NUM_PROC.value is not None or _PROC_ID.value is not None:
    _fail("--num_processes and --process_id need --coordinator_address (host:port of process 0)")
  elif _DISTRIBUTED.value == "auto":
    try:
      jax.distributed.initialize()
    except (ValueError, RuntimeError) as e:  # no cluster found (JAX alone: a traceback, status 1)
      _fail(f"--distributed=auto found no cluster to join (a TPU pod, a SLURM job, ...): {e}; "
            "elsewhere pass --coordinator_address=host:port --num_processes=N --process_id=i")
  # Implicit host-to-device copies are bugs in a training loop: make them errors. (Not the
  # device-to-host ones: XLA:CPU does not enforce that guard, so the tests could never show
  # the loop clean of them, and libraries copy implicitly there, e.g. orbax's checkpoint
  # save on a GPU or TPU: a crash at the first save that no CPU run would have met.)
  jax.config.update("jax_transfer_guard_host_to_device", "disallow")
  logging.getLogger().setLevel(logging.INFO)
  logging.getLogger("absl").setLevel(logging.WARNING)  # orbax logs every save at INFO
  # JAX's INFO lines ("Unable to initialize backend 'tpu'", the cache's "Resetting cache")
  # are noise in a training log, unless JAX_LOGGING_LEVEL asks for them.
  if jax.config.jax_logging_level in (None, "", "NOTSET"):
    logging.getLogger("jax").setLevel(logging.WARNING)
  from train import loop  # pylint: disable=g-import-not-at-top
  from sav_jax import _signals  # pylint: disable=g-import-not-at-top
  try:
    parts = loop.setup(config, _WORKDIR.value)
    _signals.raise_if_interrupted()  # one that Python dropped since the start (see below)
  # Bad input: config values, the workdir, weights or data the config names (CheckpointError
  # is a ValueError), all checked in `setup`. With absl's -v 1 (--verbosity=1) the traceback
  # is shown instead. Errors of the training itself keep their traceback.
  except (ValueError, OSError) as e:  # OSError: FileNotFoundError, PermissionError, ...
    if flags.FLAGS.verbosity >= 1:
      traceback.print_exc()
      print(f"train: error: {e}", file=sys.stderr)
    else:
      print(f"train: error: {e} (-v 1 for the traceback)", file=sys.stderr)
    sys.exit(2)
  except KeyboardInterrupt:
    _interrupted()
  except Exception as e:  # pylint: disable=broad-except  # XLA's, placing the initial state
    _exit_if_out_of_memory(e)
    raise
  try:
    loop.run(config, _WORKDIR.value, parts)
  except loop.Preempted as e:  # a checkpoint was saved; 143 = 128 + SIGTERM, 130 + SIGINT
    print(f"train: {e}", file=sys.stderr)
    sys.exit(130 if e.reason == loop.CTRL_C else 143)
  except loop.DataError as e:  # bad data met by the pipeline: one line, as bad input
    if flags.FLAGS.verbosity >= 1:
      traceback.print_exc()
    print(f"train: error: {e}", file=sys.stderr)
    sys.exit(2)
  except loop.Diverged as e:  # one line with where it resumes, status 1 (a failed run)
    if flags.FLAGS.verbosity >= 1:
      traceback.print_exc()
    print(f"train: error: {e}; {_resume_point()}", file=sys.stderr)
    sys.exit(1)
  except KeyboardInterrupt:
    _interrupted()
  except loop.ckpt_lib.CheckpointSaveError as e:  # a full disk: one line, not orbax's chains
    if flags.FLAGS.verbosity >= 1:
      traceback.print_exc()
    print(f"train: error: {e}", file=sys.stderr)
    # orbax's write coroutines still pending are collected as Python shuts down, each printing
    # "Exception ignored in ..." (hundreds): the error above says it all.
    sys.unraisablehook = lambda _: None
    sys.exit(1)
  except Exception as e:  # pylint: disable=broad-except  # XLA's, compiling or running a step
    _exit_if_out_of_memory(e)
    raise


def _exit_if_out_of_memory(e: Exception) -> None:
  """A device out of memory (`runtime.out_of_memory`): one line naming what makes a step
  smaller and where the run resumes, status 1 (XLA's traceback with -v 1)."""
  from sav_jax import runtime  # pylint: disable=g-import-not-at-top
  oom = runtime.out_of_memory(e)
  if oom is None:
    return
  if flags.FLAGS.verbosity >= 1:
    traceback.print_exception(e)
  print(f"train: error: out of memory on the device: {oom}; use "
        "--config.train.microbatches=K (the same batch as K parts), --config.model.remat=true, "
        "--config.model.dtype=bfloat16, a smaller --config.train.batch_size or "
        f"--config.data.crop, or fewer --config.train.iters; {_resume_point()}",
        file=sys.stderr)
  sys.exit(1)


def _interrupted() -> None:
  """Ctrl-C: one line that says where the run can resume from (not the traceback of where
  the interrupt landed), status 130 = 128 + SIGINT. A save in progress was finished first
  (`loop.interrupt_after`)."""
  from sav_jax._signals import exit_interrupted  # pylint: disable=g-import-not-at-top
  exit_interrupted(f"train: interrupted (Ctrl-C); {_resume_point()}")


def _resume_point() -> str:
  """Where the same command would resume the run: the workdir's last checkpoint."""
  from sav_jax.convert import orbax_io  # pylint: disable=g-import-not-at-top
  try:
    latest = orbax_io.find_training_checkpoint(pathlib.Path(_WORKDIR.value) / "checkpoints")
  except OSError:
    latest = None
  return (f"the last checkpoint is {latest}: the same command resumes from it" if latest
          else "no checkpoint was saved: the same command starts the run anew")


if __name__ == "__main__":
  try:
    from sav_jax import _signals  # pylint: disable=g-import-not-at-top
    # (remembered from before JAX's import: a Ctrl-C its GC callback drops, ~1 s after the
    # start, let the run go on to its last step and exit 0)
    with _signals.remembered_interrupts():
      app.run(main, flags_parser=parse_flags)
  except KeyboardInterrupt:  # Ctrl-C while the flags and the config file are read: one line
    if flags.FLAGS.is_parsed():
      _interrupted()
    from sav_jax._signals import exit_interrupted  # pylint: disable=g-import-not-at-top
    exit_interrupted("train: interrupted (Ctrl-C)")

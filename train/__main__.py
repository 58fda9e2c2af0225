"""Entry point: `python -m train --config configs/synthetic.py --workdir DIR [flags]`.

Single host, any number of local devices (1 CPU, N GPUs): nothing to add; the batch is
sharded over all devices. Several hosts: start one process per host with
`--coordinator_address=host0:1234 --num_processes=N --process_id=i` (or
`--distributed=auto` on TPU pods / SLURM, where JAX finds them itself).
Config fields are overridable: `--config.train.batch_size=16`. Bad input (a config value,
the workdir, weights or data that cannot be used) exits with status 2 and one line on
stderr; `-v 1` shows its traceback.
"""

import logging
import sys

from absl import app, flags
from ml_collections import config_flags

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


def main(argv):
  del argv
  import jax  # pylint: disable=g-import-not-at-top
  if _COORD.value is not None:
    jax.distributed.initialize(_COORD.value, _NUM_PROC.value, _PROC_ID.value)
  elif _DISTRIBUTED.value == "auto":
    jax.distributed.initialize()
  # Implicit host<->device copies are bugs in a training loop: make them errors.
  jax.config.update("jax_transfer_guard", "disallow")
  logging.getLogger().setLevel(logging.INFO)
  logging.getLogger("absl").setLevel(logging.WARNING)  # orbax logs every save at INFO
  from train import loop  # pylint: disable=g-import-not-at-top
  try:
    parts = loop.setup(_CONFIG.value, _WORKDIR.value)
  # Bad input: config values, the workdir, weights or data the config names (CheckpointError
  # is a ValueError), all checked in `setup`. With absl's -v 1 (--verbosity=1) the traceback
  # is shown instead. Errors of the training itself keep their traceback.
  except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError) as e:
    if flags.FLAGS.verbosity >= 1:
      raise
    print(f"train: error: {e} (-v 1 for the traceback)", file=sys.stderr)
    sys.exit(2)
  loop.run(_CONFIG.value, _WORKDIR.value, parts)


if __name__ == "__main__":
  app.run(main)

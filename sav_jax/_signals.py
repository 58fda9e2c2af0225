"""Ctrl-C (SIGINT) around work that must not be cut in the middle, and the command-line exit
after one."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading

log = logging.getLogger(__name__)


@contextlib.contextmanager
def interrupt_after(note: str | None = None):
  """Holds Ctrl-C (SIGINT) back while the block runs, and raises it (KeyboardInterrupt, or
  what the handler before does) once the block is done: orbax's checkpoint save or restore
  cut in its synchronous part drops the save, or reports a good checkpoint's cancelled reads
  as a corrupt file (and a Ctrl-C its reader threads met could be lost). Only in the main
  thread (Python's rule for signal handlers); elsewhere the block runs as it is. `note`: a
  warning logged when a Ctrl-C was held."""
  if threading.current_thread() is not threading.main_thread():
    yield
    return
  caught = []
  previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(frame))
  try:
    yield
  finally:
    signal.signal(signal.SIGINT, previous)
  if caught:
    if note:
      log.warning("%s", note)
    if callable(previous):
      previous(signal.SIGINT, caught[0])
    elif previous != signal.SIG_IGN:
      raise KeyboardInterrupt


def exit_interrupted(message: str) -> None:
  """Prints `message` on stderr and ends the process with status 130 (128 + SIGINT) at once.

  After a Ctrl-C, XLA's threads may still be at work (a compilation the interrupt did not
  wait for): Python's normal shutdown then tore them down mid-work (a segmentation fault
  after the message). The command's own clean-up has run (the interrupt unwound it); the
  standard streams are flushed first."""
  print(message, file=sys.stderr)
  for flush in [*(h.flush for h in logging.getLogger().handlers), sys.stdout.flush,
                sys.stderr.flush]:
    try:
      flush()
    except (OSError, ValueError):
      pass
  _exit(130)


_exit = os._exit  # pylint: disable=protected-access  # (tests replace it)

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
  if (threading.current_thread() is not threading.main_thread()
      or signal.getsignal(signal.SIGINT) == signal.SIG_IGN):  # ignored (a background job):
    yield  # nothing to hold back (it logged the note, then carried on)
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


_interrupted = threading.Event()


@contextlib.contextmanager
def remembered_interrupts():
  """Remembers a Ctrl-C (SIGINT) while the block runs, so that `raise_if_interrupted` raises
  it again at the caller's next safe point: Python drops a KeyboardInterrupt raised inside a
  garbage-collection callback (JAX's `_xla_gc_callback`: "Exception ignored in ..."), and a
  training run interrupted there went on to its last step and exited 0. The handler before
  still runs (KeyboardInterrupt where the signal lands). Only in the main thread, and not
  where SIGINT is ignored."""
  previous = signal.getsignal(signal.SIGINT)
  if (threading.current_thread() is not threading.main_thread() or not callable(previous)
      or getattr(previous, "remembers", False)):  # (nested: the outer block remembers)
    yield
    return

  def remember(signum, frame):
    try:
      previous(signum, frame)
    except BaseException:  # KeyboardInterrupt: remembered (a handler that stops the work
      _interrupted.set()   # its own way, as the training's first Ctrl-C, is not)
      raise

  remember.remembers = True

  _interrupted.clear()
  signal.signal(signal.SIGINT, remember)
  try:
    yield
  finally:
    signal.signal(signal.SIGINT, previous)
    _interrupted.clear()


def raise_if_interrupted() -> None:
  """Raises KeyboardInterrupt if a Ctrl-C came (inside `remembered_interrupts`) since the
  last call: one that Python dropped on its way."""
  if _interrupted.is_set():
    _interrupted.clear()
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

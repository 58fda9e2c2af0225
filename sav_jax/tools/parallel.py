"""Threads for `sav-jax infer`'s file work: decoding frames, writing outputs.

OpenCV's codecs and numpy's array work release the GIL, so a few threads decode and encode
frames at once while the main thread runs the model. Everything here keeps order and bounds
the work in flight (memory does not grow with the video's length), re-raises a worker's error
in the calling thread, and on an error or Ctrl-C there waits for the running tasks (each
writes whole files) and cancels the rest, so that no file is written after the caller's
clean-up.
"""

from __future__ import annotations

import collections
import concurrent.futures
import os
from typing import Callable, Iterable, Iterator

# Threads for decoding and writing (`SAV_IO_THREADS` overrides; 1: all in the calling thread).
_MAX_THREADS = 8


def io_threads() -> int:
  env = os.environ.get("SAV_IO_THREADS")
  if env:
    try:
      n = int(env)
    except ValueError:
      raise ValueError(f"SAV_IO_THREADS must be a positive integer, got {env!r}") from None
    if n < 1:
      raise ValueError(f"SAV_IO_THREADS must be a positive integer, got {env!r}")
    return n
  return max(1, min(_MAX_THREADS, os.cpu_count() or 1))


_PREFETCH: list = []


def prefetch_pool() -> concurrent.futures.ThreadPoolExecutor | None:
  """The threads that decode frames ahead of their reads (`video_io.FrameSource`); None with
  one I/O thread. Kept for the process (idle threads; their tasks only decode)."""
  if io_threads() <= 1:
    return None
  if not _PREFETCH:
    _PREFETCH.append(concurrent.futures.ThreadPoolExecutor(
        io_threads(), thread_name_prefix="sav-prefetch"))
  return _PREFETCH[0]


def ordered_map(fn: Callable, items: Iterable, ahead: int | None = None,
                threads: int | None = None) -> Iterator:
  """`fn(item)` for each item, in order, computed by up to `threads` threads with at most
  `ahead` results computed ahead of the one yielded (default: 2 per thread). A task's error
  is raised here when its result is due (the ones before it are yielded first); closing the
  generator or an error stops the rest."""
  threads = io_threads() if threads is None else threads
  if threads <= 1:
    yield from map(fn, items)
    return
  ahead = max(1, 2 * threads if ahead is None else ahead)
  pool = concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="sav-io")
  pending: collections.deque = collections.deque()
  try:
    for item in items:
      pending.append(pool.submit(fn, item))
      while len(pending) > ahead:
        yield pending.popleft().result()
    while pending:
      yield pending.popleft().result()
  finally:  # the tasks not started cancelled, the running ones waited for
    pool.shutdown(wait=True, cancel_futures=True)


class Writer:
  """Runs `submit(fn, *args)` tasks in threads, at most `ahead` unfinished at a time (the
  submit waits for the oldest beyond that, so memory stays bounded); `fn`'s results are
  handed to `collect` in submission order. A task's error is raised in the thread that
  submits (at the next submit after it failed; the first error in submission order) or
  calls `finish`; used as a context manager, an error or Ctrl-C in the block waits for the
  running tasks and drops the others before it propagates (nothing is written after that)."""

  def __init__(self, collect: Callable = lambda result: None, ahead: int | None = None,
               threads: int | None = None):
    self.threads = io_threads() if threads is None else threads
    self.ahead = max(1, 2 * self.threads if ahead is None else ahead)
    self.collect = collect
    self._pool = (concurrent.futures.ThreadPoolExecutor(self.threads,
                                                        thread_name_prefix="sav-write")
                  if self.threads > 1 else None)
    self._pending: collections.deque = collections.deque()

  def submit(self, fn: Callable, *args) -> None:
    if self._pool is None:
      self.collect(fn(*args))
      return
    # A task that failed stops the run now, not when it is due; `finish` raises the first
    # error in submission order (an earlier task still running may fail too), as one thread's.
    if any(f.done() and not f.cancelled() and f.exception() is not None
           for f in self._pending):
      self.finish()
    self._pending.append(self._pool.submit(fn, *args))
    while len(self._pending) > self.ahead:
      self.collect(self._pending.popleft().result())

  def finish(self) -> None:
    """Waits for every task (raising the first error)."""
    while self._pending:
      self.collect(self._pending.popleft().result())

  def __enter__(self) -> "Writer":
    return self

  def __exit__(self, exc_type, exc, tb) -> None:
    try:
      if exc_type is None:
        self.finish()
    finally:
      if self._pool is not None:  # (as ordered_map's)
        self._pool.shutdown(wait=True, cancel_futures=True)

"""An exclusive lock on a folder that one process writes into (an evaluation's --out, a
training run's WORKDIR): an `flock` on a lock file inside it, which the system releases when
the process ends however it ends (a lock file no process holds is taken over). The file names
the host and PID for the message of the process that is refused."""

from __future__ import annotations

import contextlib
import fcntl
import os
import pathlib
import socket


class FolderBusyError(FileExistsError):
  """Another process holds the folder's lock; `holder` is "host pid" (or "unknown")."""

  def __init__(self, folder: pathlib.Path, holder: str):
    super().__init__(f"{folder} is in use by {holder}")
    self.folder, self.holder = folder, holder


class FolderLock:
  """Holds `folder/name` from construction until `release()` (or garbage collection).

  Raises:
    FolderBusyError: another process (or another lock of this process) holds it.
  """

  def __init__(self, folder, name: str):
    self.path = pathlib.Path(folder) / name
    self._fd: int | None = None  # (until taken: __del__ of a refused lock does nothing)
    while True:
      fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
      try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
      except BlockingIOError:
        holder = os.read(fd, 256).decode("utf-8", "replace").strip()
        os.close(fd)
        raise FolderBusyError(pathlib.Path(folder), holder or "unknown") from None
      try:  # the path may name a newer file by now (the holder removed it as it ended)
        same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
      except FileNotFoundError:
        same = False
      if same:
        break
      os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{socket.gethostname()} {os.getpid()}".encode())
    self._fd = fd

  def release(self) -> None:
    """Removes the lock file and releases the lock (a second call does nothing)."""
    if self._fd is not None:
      self.path.unlink(missing_ok=True)
      os.close(self._fd)  # releases the flock
      self._fd = None

  def __del__(self):
    self.release()


@contextlib.contextmanager
def output_lock(out, name: str, busy: str):
  """Holds `out/name` while the block runs (a command writing into `out`). `out` is created
  if needed, and removed again (with the folders made for it) if the block leaves it empty:
  a run refused before writing leaves no empty folders behind.

  Raises:
    FileExistsError: another process holds the lock; the message is `busy` with `{holder}`
      put in (the path may hold braces).
  """
  out = pathlib.Path(out)
  created = [f for f in (out, *out.parents) if not f.exists()]  # (innermost first)
  out.mkdir(parents=True, exist_ok=True)
  try:
    lock = FolderLock(out, name)
  except FolderBusyError as e:
    raise FileExistsError(busy.replace("{holder}", e.holder)) from None
  try:
    yield
  finally:
    lock.release()
    for folder in created:
      if not (folder.is_dir() and not any(folder.iterdir())):
        break
      folder.rmdir()

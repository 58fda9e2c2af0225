"""Small file-writing helpers shared by the commands: a text file written whole or not at
all, and the free-space note of a write that failed."""

from __future__ import annotations

import os
import pathlib
import shutil

# How `free_space_note` ends: a message that holds it already names the free space.
FREE_SPACE = "MB free on its disk"


def write_text_atomic(path, text: str) -> None:
  """Writes `text` to `path` whole or not at all: a temporary file beside it (`.NAME.tmp`),
  renamed over it (a file cut by a full disk or a kill would not parse); the temporary file
  is removed if the write fails."""
  path = pathlib.Path(path)
  tmp = path.with_name(f".{path.name}.tmp")
  try:
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
  finally:
    tmp.unlink(missing_ok=True)


def free_space_note(folder) -> str:
  """`"; 12.3 MB free on its disk"` for the disk of `folder`, or "" if that is unknown: for
  the message of a write that failed (a full disk?)."""
  try:
    return f"; {shutil.disk_usage(folder).free / 2**20:.1f} {FREE_SPACE}"
  except OSError:
    return ""

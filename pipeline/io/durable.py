"""Durable file writes: what is on disk after a crash is the old file or the whole new one, never half of one.

The writer goes to ``<name>.part``, is flushed and fsynced, renamed over ``<name>``, and the folder is fsynced so
the rename survives a power cut (the job journal's rule for scans and artifacts, ``docs/daemon.md``). Scratch files
that a resumed job makes again (:func:`write_replacing`) are renamed into place without the fsyncs.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def fsync_dir(path: Path) -> None:
    """Make the entries of the folder ``path`` (a rename into it) durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_durably(path: Path, write: Callable[[BinaryIO], object]) -> int:
    """Write ``path`` through ``write(binary file)`` to a temporary name, fsync, rename, fsync the folder.

    Returns the size in bytes. Readers never see a half-written file at ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
        size = f.tell()
    os.replace(tmp, path)
    fsync_dir(path.parent)
    return size


def write_replacing(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``path`` through ``write(binary file)`` to a temporary name and rename it: readers see the whole file
    or none. Not fsynced: for scratch files that a job resumed after a crash writes again."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as f:
        write(f)
    os.replace(tmp, path)

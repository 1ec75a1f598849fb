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

    Returns the size in bytes. Readers never see a half-written file at ``path``; where ``write`` fails, the
    temporary file is removed and ``path`` is as it was."""
    path = Path(path)
    _write_and_rename(path, write, durable=True)
    fsync_dir(path.parent)
    return path.stat().st_size


def write_replacing(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``path`` through ``write(binary file)`` to a temporary name and rename it: readers see the whole file
    or none (where ``write`` fails, the temporary file is removed). Not fsynced: for scratch files that a job resumed
    after a crash writes again."""
    _write_and_rename(Path(path), write, durable=False)


def _write_and_rename(path: Path, write: Callable[[BinaryIO], object], durable: bool) -> None:
    """``write`` into ``<path>.part`` (fsynced where ``durable``), renamed over ``path``; the ``.part`` removed where
    anything before the rename fails."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    try:
        with open(tmp, "wb") as f:
            write(f)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise

"""Big arrays handed between processes by name instead of by value (POSIX shared memory, Linux ``/dev/shm``).

A full-resolution scan is 3.2 M points: 77 MB of float64 points and as much of normals. Pickled across a
process pipe it costs the receiving process a copy under its GIL (over 100 ms), which stalls an event loop.
:func:`share` puts an array in a file under ``/dev/shm`` and maps it; the result is a :class:`SharedArray`,
a plain ``numpy.ndarray`` whose pickle is only the file's name, so the receiver maps the same pages. Views
and results of arithmetic on it are ordinary arrays and pickle by value.

Lifetime: the process that made a block with :func:`share` owns it and removes the file when its array is
garbage-collected; a process that unpickles the array only borrows it, so the owner keeps its array until the
borrower is done (the daemon awaits its worker's answer). A worker returning a result gives its block away
with :func:`hand_over`: the result is a small :class:`SharedBlock` and the receiver's :meth:`SharedBlock.take`
makes it the owner. Files of a process killed before it could remove them go with :func:`remove_stale_blocks`.
Where ``/dev/shm`` is missing or too small, an ordinary array stands in (pickled by value).
"""

from __future__ import annotations

import logging
import mmap
import os
import shutil
import uuid
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

SHM_DIR = Path("/dev/shm")
PREFIX = "tandemscan-"
# below this size an array is cheaper to pickle than to map (bytes)
MIN_SHARED_BYTES = 1 << 20


class SharedArray(np.ndarray):
    """An array whose memory is a named shared-memory block; pickles as the block's name (no copy)."""

    _block: str | None

    def __array_finalize__(self, obj) -> None:
        self._block = None  # views and results of arithmetic are ordinary arrays: they pickle by value

    def __reduce_ex__(self, protocol):
        if self._block is None:
            return np.asarray(self).copy().__reduce_ex__(protocol)
        return _attach, (self._block, self.shape, self.dtype.str, False)


@dataclass(frozen=True)
class SharedBlock:
    """A block handed over by another process (see :func:`hand_over`): its name, shape and dtype."""

    name: str
    shape: tuple[int, ...]
    dtype: str

    def take(self) -> np.ndarray:
        """Map the block; this process owns it from now on."""
        return _attach(self.name, self.shape, self.dtype, True)

    def borrow(self) -> np.ndarray:
        """Map the block without owning it: the process that handed it on removes it (:meth:`discard`) once every
        process it went to is done with it."""
        return _attach(self.name, self.shape, self.dtype, False)

    def discard(self) -> None:
        """Remove the block without mapping it: a hand-over passed on to a process that has taken it or never
        will (its task done, failed or cancelled); nothing where it is gone already."""
        _unlink(SHM_DIR / self.name)


def take(value: SharedBlock | np.ndarray) -> np.ndarray:
    """The array of a :func:`hand_over` result (this process becomes its owner)."""
    return value.take() if isinstance(value, SharedBlock) else value


def _block_owner_pid(name: str) -> int | None:
    try:
        return int(name[len(PREFIX):].split("-", 1)[0])
    except ValueError:
        return None


def _map(name: str, shape: tuple[int, ...], dtype: str, *, create: bool) -> SharedArray:
    path = SHM_DIR / name
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    fd = os.open(path, os.O_RDWR | (os.O_CREAT | os.O_EXCL if create else 0), 0o600)
    try:
        if create:
            os.ftruncate(fd, max(nbytes, 1))
        buf = mmap.mmap(fd, max(nbytes, 1))
    finally:
        os.close(fd)
    arr = np.frombuffer(buf, dtype=dtype, count=int(np.prod(shape))).reshape(shape).view(SharedArray)
    arr._block = name
    return arr


def _own(arr: SharedArray) -> None:
    weakref.finalize(arr, _unlink, SHM_DIR / arr._block)


def _unlink(path: Path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def _attach(name: str, shape: tuple[int, ...], dtype: str, owner: bool) -> np.ndarray:
    arr = _map(name, shape, dtype, create=False)
    if owner:
        _own(arr)
    return arr


def _room_for(nbytes: int) -> bool:
    try:
        return SHM_DIR.is_dir() and shutil.disk_usage(SHM_DIR).free > 2 * nbytes
    except OSError:
        return False


def _new_block(array: np.ndarray, owner_pid: int) -> SharedArray | None:
    array = np.ascontiguousarray(array)
    if array.nbytes < MIN_SHARED_BYTES or array.dtype.hasobject or not _room_for(array.nbytes):
        return None
    out = _map(f"{PREFIX}{owner_pid}-{uuid.uuid4().hex}", array.shape, array.dtype.str, create=True)
    np.copyto(out, array)
    return out


def share(array: np.ndarray) -> np.ndarray:
    """``array`` in a shared-memory block this process owns (a :class:`SharedArray`; the same object when
    it already is one). Small arrays and a missing or full ``/dev/shm`` give the array itself."""
    if isinstance(array, SharedArray) and array._block is not None:
        return array
    out = _new_block(array, os.getpid())
    if out is None:
        return array
    _own(out)
    return out


def hand_over(array: np.ndarray) -> SharedBlock | np.ndarray:
    """Copy ``array`` into a block for the process that started this one (a worker's result); the parent
    calls :func:`take` on what it receives. Small arrays, or no room in ``/dev/shm``: the array itself."""
    out = _new_block(array, os.getppid())
    return array if out is None else SharedBlock(out._block, out.shape, out.dtype.str)


def remove_stale_blocks() -> int:
    """Remove blocks whose owning process is gone (killed before it could); returns how many."""
    removed = 0
    if not SHM_DIR.is_dir():
        return 0
    for path in SHM_DIR.glob(PREFIX + "*"):
        pid = _block_owner_pid(path.name)
        if pid is None or _alive(pid):
            continue
        _unlink(path)
        removed += 1
    if removed:
        log.info("removed %d shared-memory blocks left by killed processes", removed)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True

"""Where the end of a job's per-unit work runs (docs/compute.md): a compute backend maps a function over units.

A unit is small (scan references: file, pose; never the points) and its work is idempotent: the same unit gives the
same result wherever and however often it runs, so a unit lost with its worker is simply run again. Two backends:
:class:`LocalBackend` (threads of this process, one per core: numpy, SciPy's KD-trees and Open3D release the GIL)
and :class:`DaskBackend` (Dask distributed: a ``LocalCluster`` of worker processes on this PC, or a scheduler's
address, ``tcp://host:8786``, on a cluster whose workers reach the job's scans on a shared filesystem). The stages of
one end of a job share one backend (:class:`LazyBackend`: made at the first stage that needs it, closed once).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import os
import pickle
import shutil
import threading
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from tandemscan.config.models import ComputeConfig
from tandemscan.pipeline.registration.parallel import pair_threads

log = logging.getLogger(__name__)


class ComputeBackend(Protocol):
    """``map(fn, units, keys)``: ``[fn(u) for u in units]`` in order, the calls spread over the backend's workers;
    ``keys`` name the units (one unique string each: the same unit, the same key). With ``inputs`` (per unit a
    sequence of handles, :meth:`keep`) each call is ``fn(u, *values)``, the values those handles stand for, taken
    where they were left. ``keep`` is ``map`` whose results stay where they were computed: it returns their handles
    (on this process's threads the results themselves, on Dask its futures: a worker's result moves only to the
    workers whose units take it, never to this process), and a result is released with the last handle to it;
    ``put`` makes handles of values this process holds; ``trim`` hands the heap the workers freed back to the
    operating system (:func:`trim_heap`: between stages); ``cpu_seconds`` is the CPU time (user + system, s) this
    process and the backend's workers have spent so far (a difference of two readings: a stage's CPU)."""

    def map(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
            inputs: Sequence[Sequence[Any]] | None = None) -> list: ...

    def keep(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
             inputs: Sequence[Sequence[Any]] | None = None) -> list: ...

    def put(self, values: Sequence[Any]) -> list: ...

    def trim(self) -> None: ...

    def cpu_seconds(self) -> float: ...

    def close(self) -> None: ...


class LocalBackend:
    """The units on ``threads`` threads of this process (default one per core)."""

    def __init__(self, threads: int | None = None):
        self.threads = threads

    def map(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
            inputs: Sequence[Sequence[Any]] | None = None) -> list:
        """``[fn(u) for u in units]`` (with ``inputs``: ``fn(u, *inputs[k])``), in order (``keys`` are not needed
        here)."""
        with pair_threads(self.threads) as thread_map:
            if inputs is None:
                return thread_map(fn, units)
            return thread_map(lambda k: fn(units[k], *inputs[k]), range(len(units)))

    def keep(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
             inputs: Sequence[Sequence[Any]] | None = None) -> list:
        """:meth:`map`: the results are their own handles here."""
        return self.map(fn, units, keys, inputs)

    def put(self, values: Sequence[Any]) -> list:
        """The values themselves."""
        return list(values)

    def trim(self) -> None:
        """:func:`trim_heap` of this process (its threads are the workers)."""
        trim_heap()

    def cpu_seconds(self) -> float:
        """:func:`process_cpu_seconds` of this process (its threads are the workers)."""
        return process_cpu_seconds()

    def close(self) -> None:
        """Nothing to release: the threads end with each :meth:`map`."""


#: batches of messages each Dask stream this process opens keeps for its logs
#: (``distributed.admin.low-level-log-length``, 1000 by default): a batch carries its tasks' specs and arguments, so
#: the client's and, on a ``LocalCluster``, the scheduler's streams held the joint refinement's last 1000 batches
#: after it ended (growing with the scans); also the scheduler's transition log's length
MESSAGE_LOG = 10


class DaskBackend:
    """The units as Dask tasks: on the scheduler at ``scheduler`` (``tcp://host:8786``), or on a ``LocalCluster``
    of ``workers`` single-threaded processes where it is empty. Each unit is one task keyed by its unit key
    (``pure``: a unit submitted twice runs once), retried ``retries`` times when its worker is lost."""

    def __init__(self, scheduler: str = "", workers: int = 2, retries: int = 3):
        import dask
        from dask.distributed import Client, LocalCluster

        self.retries = retries
        with dask.config.set({"distributed.admin.low-level-log-length": MESSAGE_LOG}):  # the streams made here
            self._cluster = None if scheduler else LocalCluster(n_workers=workers, threads_per_worker=1,
                                                                processes=True, dashboard_address="127.0.0.1:0")
            self.client = Client(scheduler or self._cluster)
        log.info("compute: dask scheduler %s", self.client.scheduler.address)

    def map(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
            inputs: Sequence[Sequence[Any]] | None = None) -> list:
        """``[fn(u) for u in units]`` (with ``inputs``: ``fn(u, *inputs[k])``, futures) in order, each unit a task of
        key ``keys[k]``. Where a unit fails, its error is raised once every unit has ended, as on
        :class:`LocalBackend`'s threads: a stage that removes what its units wrote where one fails
        (``tiles.merge_tiles``) finds every file, none written by a unit still running after it cleaned up."""
        from dask.distributed import wait

        futures = self.keep(fn, units, keys, inputs)
        try:
            return self.client.gather(futures) if units else []
        except Exception:
            wait(futures)
            raise

    def keep(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
             inputs: Sequence[Sequence[Any]] | None = None) -> list:
        """The futures of :meth:`map`'s tasks: their results stay on the workers (a lost one is computed again from
        its unit and inputs)."""
        if not units:
            return []
        if inputs is None:
            return self.client.map(fn, list(units), key=list(keys), retries=self.retries, pure=True)
        return [self.client.submit(fn, u, *given, key=k, retries=self.retries, pure=True)
                for u, given, k in zip(units, inputs, keys, strict=True)]

    def put(self, values: Sequence[Any]) -> list:
        """Futures of ``values`` scattered to the workers (keyed by their contents)."""
        return self.client.scatter(list(values), hash=True) if len(values) else []

    def trim(self) -> None:
        """:func:`trim_heap` on every worker (Dask's remedy for the unmanaged memory a worker keeps after its tasks'
        results were released: the next stage starts from what it holds, not from the last one's peak)."""
        self.client.run(trim_heap)

    def cpu_seconds(self) -> float:
        """:func:`process_cpu_seconds` of this process and of each worker now connected (a worker lost and started
        again counts from its restart)."""
        return process_cpu_seconds() + sum(self.client.run(process_cpu_seconds).values())

    def close(self) -> None:
        """Disconnect, and stop the ``LocalCluster`` if this backend started one."""
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


@dataclass(frozen=True)
class StoredResult:
    """The handle of a unit's result kept in a file (:class:`StoredResults`): its ``path``."""

    path: str

    def read(self) -> Any:
        """The result, as the unit returned it (the same bits)."""
        with open(self.path, "rb") as f:
            return pickle.load(f)


def _read_stored(values: Sequence[Any]) -> list:
    """``values`` with each :class:`StoredResult` read."""
    return [v.read() if isinstance(v, StoredResult) else v for v in values]


def _reading_stored(unit: Any, *inputs: Any, fn: Callable[..., Any]) -> Any:
    """A unit of :meth:`StoredResults.map`: ``fn(unit, *inputs)``, the stored results among ``inputs`` read first."""
    return fn(unit, *_read_stored(inputs))


def _storing(unit_and_path: tuple[Any, str], *inputs: Any, fn: Callable[..., Any]) -> StoredResult:
    """A unit of :meth:`StoredResults.keep`: ``fn(unit, *inputs)`` (the stored results among ``inputs`` read first)
    written to ``path`` (through a temporary file: a unit run again, or twice at once, leaves the same whole file)."""
    unit, path = unit_and_path
    result = fn(unit, *_read_stored(inputs))
    tmp = f"{path}.{os.getpid()}-{threading.get_ident()}.tmp"
    with open(tmp, "wb") as f:
        pickle.dump(result, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)
    return StoredResult(path)


class StoredResults:
    """A compute backend whose kept results are files in ``folder`` (a folder of the job's scan store, which every
    worker reaches), not data held where they were computed: :meth:`keep` runs its units on ``backend`` (its
    :meth:`map`), each writing its result to a file named by its key and handing back its :class:`StoredResult`, and
    each unit given such handles (:meth:`map`, :meth:`keep`) reads them first. So a worker holds no result between
    units: its memory is a unit's, not its share of the results kept (on Dask: no future's data waits on a worker,
    and a unit lost with its worker runs again from its files). A result's file is removed with the last handle to it
    in this process, as a Dask future's result is released (the handles sent to units are copies); :meth:`close`
    (also the end of a ``with`` block) removes the folder, never closing ``backend`` (the caller's). ``put``,
    ``trim`` and ``cpu_seconds`` are ``backend``'s. docs/compute.md."""

    def __init__(self, backend: ComputeBackend, folder: str | Path):
        self.backend, self.folder = backend, Path(folder)

    def map(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
            inputs: Sequence[Sequence[Any]] | None = None) -> list:
        """``backend``'s map, the stored results among ``inputs`` read in each unit."""
        if inputs is None:
            return self.backend.map(fn, units, keys)
        return self.backend.map(functools.partial(_reading_stored, fn=fn), units, keys, inputs)

    def keep(self, fn: Callable[..., Any], units: Sequence[Any], keys: Sequence[str],
             inputs: Sequence[Sequence[Any]] | None = None) -> list:
        """:meth:`map` whose results are written to files of the folder (``<key>.pickle``): their handles."""
        if not units:
            return []
        self.folder.mkdir(parents=True, exist_ok=True)
        paths = [str(self.folder / f"{key}.pickle") for key in keys]
        handles = self.backend.map(functools.partial(_storing, fn=fn), list(zip(units, paths, strict=True)), keys,
                                   [()] * len(units) if inputs is None else inputs)
        for handle in handles:
            weakref.finalize(handle, Path(handle.path).unlink, missing_ok=True)  # its last handle here gone
        return handles

    def put(self, values: Sequence[Any]) -> list:
        """``backend``'s put."""
        return self.backend.put(values)

    def trim(self) -> None:
        """``backend``'s trim."""
        self.backend.trim()

    def cpu_seconds(self) -> float:
        """``backend``'s CPU seconds."""
        return self.backend.cpu_seconds()

    def close(self) -> None:
        """Remove the folder and every result in it (``backend`` stays open)."""
        shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> StoredResults:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def trim_heap() -> int:
    """Hand the heap this process freed back to the operating system (glibc's ``malloc_trim(0)``; it keeps freed
    memory for reuse otherwise, so that a process's RSS stays at its last peak): 1 where memory was released, 0
    where none was or where the C library has no ``malloc_trim``."""
    try:
        return int(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return 0


def process_cpu_seconds() -> float:
    """CPU time (user + system, s) of this process, all its threads."""
    t = os.times()
    return t.user + t.system


def backend_for(cfg: ComputeConfig) -> ComputeBackend:
    """The backend of ``[compute]``."""
    if cfg.backend == "dask":
        return DaskBackend(cfg.scheduler, cfg.dask_workers, cfg.retries)
    return LocalBackend()


class LazyBackend:
    """The one backend of ``[compute]`` (:func:`backend_for`) that the stages of one end of a job share
    (docs/compute.md): made at the first :meth:`get` (a job whose stages all run in this process starts no
    cluster), the same one handed to every later stage (on Dask one ``LocalCluster``, or one client of the
    scheduler at ``scheduler``, whose workers keep what they cached between stages), closed by :meth:`close`, also
    as a context manager: when the end of the job is done, fails or is cancelled."""

    def __init__(self, cfg: ComputeConfig):
        self.cfg = cfg
        self._backend: ComputeBackend | None = None

    def get(self) -> ComputeBackend:
        """The backend, made now where no stage asked for it before."""
        if self._backend is None:
            self._backend = backend_for(self.cfg)
        return self._backend

    def close(self) -> None:
        """Close the backend where one was made (once: a later :meth:`get` makes a new one)."""
        backend, self._backend = self._backend, None
        if backend is not None:
            backend.close()

    def __enter__(self) -> LazyBackend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

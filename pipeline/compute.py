"""Where the end of a job's per-unit work runs (docs/compute.md): a compute backend maps a function over units.

A unit is small (scan references: file, pose; never the points) and its work is idempotent: the same unit gives the
same result wherever and however often it runs, so a unit lost with its worker is simply run again. Two backends:
:class:`LocalBackend` (threads of this process, one per core: numpy, SciPy's KD-trees and Open3D release the GIL)
and :class:`DaskBackend` (Dask distributed: a ``LocalCluster`` of worker processes on this PC, or a scheduler's
address, ``tcp://host:8786``, on a cluster whose workers reach the job's scans on a shared filesystem).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from tandemscan.config.models import ComputeConfig
from tandemscan.pipeline.registration.parallel import pair_threads

log = logging.getLogger(__name__)


class ComputeBackend(Protocol):
    """``map(fn, units, keys)``: ``[fn(u) for u in units]`` in order, the calls spread over the backend's workers;
    ``keys`` name the units (one unique string each: the same unit, the same key)."""

    def map(self, fn: Callable[[Any], Any], units: Sequence[Any], keys: Sequence[str]) -> list: ...

    def close(self) -> None: ...


class LocalBackend:
    """The units on ``threads`` threads of this process (default one per core)."""

    def __init__(self, threads: int | None = None):
        self.threads = threads

    def map(self, fn: Callable[[Any], Any], units: Sequence[Any], keys: Sequence[str]) -> list:
        """``[fn(u) for u in units]``, in order (``keys`` are not needed here)."""
        with pair_threads(self.threads) as thread_map:
            return thread_map(fn, units)

    def close(self) -> None:
        """Nothing to release: the threads end with each :meth:`map`."""


class DaskBackend:
    """The units as Dask tasks: on the scheduler at ``scheduler`` (``tcp://host:8786``), or on a ``LocalCluster``
    of ``workers`` single-threaded processes where it is empty. Each unit is one task keyed by its unit key
    (``pure``: a unit submitted twice runs once), retried ``retries`` times when its worker is lost."""

    def __init__(self, scheduler: str = "", workers: int = 2, retries: int = 3):
        from dask.distributed import Client, LocalCluster

        self.retries = retries
        self._cluster = None if scheduler else LocalCluster(n_workers=workers, threads_per_worker=1,
                                                            processes=True, dashboard_address="127.0.0.1:0")
        self.client = Client(scheduler or self._cluster)
        log.info("compute: dask scheduler %s", self.client.scheduler.address)

    def map(self, fn: Callable[[Any], Any], units: Sequence[Any], keys: Sequence[str]) -> list:
        """``[fn(u) for u in units]`` in order, each unit a task of key ``keys[k]``."""
        if not units:
            return []
        futures = self.client.map(fn, list(units), key=list(keys), retries=self.retries, pure=True)
        return self.client.gather(futures)

    def close(self) -> None:
        """Disconnect, and stop the ``LocalCluster`` if this backend started one."""
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def backend_for(cfg: ComputeConfig) -> ComputeBackend:
    """The backend of ``[compute]``."""
    if cfg.backend == "dask":
        return DaskBackend(cfg.scheduler, cfg.dask_workers, cfg.retries)
    return LocalBackend()

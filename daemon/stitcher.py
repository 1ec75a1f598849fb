"""The job's world map and its end-of-job work, in a worker process for the daemon or in this one.

Both maps have one interface: ``await add_scan(file, T_W_S, arrays)`` persists a raw scan (when ``arrays`` is
given: written and fsynced first) and merges it into the voxel grid (Eq. 1, points in S, map in W, mm);
``await run(fn, job, *args)`` runs ``fn(job, *args)`` where the map lives, with ``job.worldmap`` set to it
(correction, report, exports), and adopts the map ``fn`` leaves there.

:class:`ProcessWorldMap` (the daemon) keeps its grid in a one-process pool, so no stitch, scan write or export
holds the daemon's GIL: a full-resolution scan (3.2 M points) merged or written in a thread stalled the event
loop for over half a second. Scan arrays go to it as shared memory (:mod:`tandemscan.drivers.shared_array`),
never pickled by value. :class:`LocalWorldMap` (``tandemscan measure``) does the same work in threads.
"""

from __future__ import annotations

import asyncio
import multiprocessing
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from tandemscan.daemon.snapshot import JobSnapshot
from tandemscan.drivers.shared_array import share
from tandemscan.drivers.worker import init_worker, stop_pool
from tandemscan.pipeline.io.raw_scan import read_raw_scan, write_raw_scan
from tandemscan.pipeline.stitching.worldmap import VoxelMap

_MAP: VoxelMap | None = None  # the worker's map


def _init(voxel_mm: float, niceness: int) -> None:
    global _MAP
    init_worker(niceness)
    _MAP = VoxelMap(voxel_mm)


def _add(path: str, T_W_S: np.ndarray, arrays: dict[str, np.ndarray] | None) -> int:
    if arrays is not None:
        write_raw_scan(Path(path), **arrays)
    _MAP.add_scan(T_W_S, *read_raw_scan(path))  # from the file, as a resumed job rebuilds it
    return len(_MAP)


def _run(fn: Callable[..., Any], job: JobSnapshot, args: tuple) -> tuple[Any, int]:
    global _MAP
    job.worldmap = _MAP
    out = fn(job, *args)
    _MAP = job.worldmap
    return out, len(_MAP)


def correct(job: JobSnapshot) -> tuple[dict, list[np.ndarray]]:
    """:func:`tandemscan.daemon.correction.correct_job`, imported where it runs: torch takes seconds to
    import, which must not happen on the daemon's event loop."""
    from tandemscan.daemon.correction import correct_job

    return correct_job(job)


def export(job: JobSnapshot, seconds: float, measured_at: float) -> dict:
    """:func:`tandemscan.daemon.job_outputs.export_job` (E57, Open3D I/O, matplotlib), imported where it runs."""
    from tandemscan.daemon.job_outputs import export_job

    return export_job(job, seconds, measured_at)


def _share_big(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: share(v) for k, v in arrays.items()}


class ProcessWorldMap:
    """The job's :class:`VoxelMap` in its own process; call :meth:`close` when the job is done."""

    def __init__(self, voxel_mm: float, niceness: int = 0):
        self.voxel_mm = float(voxel_mm)
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init, initargs=(self.voxel_mm, niceness))
        self._len = 0

    async def add_scan(self, file: Path, T_W_S: np.ndarray, arrays: dict[str, np.ndarray] | None = None) -> None:
        """Write ``arrays`` (if given) durably to ``file``, then merge the scan in ``file`` placed at ``T_W_S``.
        The caller keeps ``arrays`` until this returns (the worker maps their shared memory)."""
        if arrays is not None:
            arrays = await asyncio.to_thread(_share_big, arrays)
        self._len = await asyncio.wrap_future(
            self._pool.submit(_add, str(file), np.asarray(T_W_S, float), arrays))

    async def run(self, fn: Callable[..., Any], job: JobSnapshot, *args: Any) -> Any:
        """``fn(job, *args)`` in the worker with ``job.worldmap`` = its map; ``fn`` and its result pickle."""
        out, self._len = await asyncio.wrap_future(self._pool.submit(_run, fn, job, args))
        return out

    def __len__(self) -> int:
        return self._len

    def close(self) -> None:
        """Stop the worker; work still under way (a job interrupted by shutdown) is abandoned, not awaited."""
        stop_pool(self._pool)


class LocalWorldMap:
    """The job's :class:`VoxelMap` in this process, its work in threads (``tandemscan measure``)."""

    def __init__(self, voxel_mm: float):
        self.voxel_mm = float(voxel_mm)
        self.map = VoxelMap(self.voxel_mm)

    async def add_scan(self, file: Path, T_W_S: np.ndarray, arrays: dict[str, np.ndarray] | None = None) -> None:
        """As :meth:`ProcessWorldMap.add_scan`; given arrays are merged as they are (float64)."""
        if arrays is None:
            await asyncio.to_thread(lambda: self.map.add_scan(T_W_S, *read_raw_scan(file)))
            return
        await asyncio.to_thread(write_raw_scan, Path(file), **arrays)
        await asyncio.to_thread(self.map.add_scan, T_W_S, arrays["points_S_mm"], arrays.get("normals_S"))

    async def run(self, fn: Callable[..., Any], job: JobSnapshot, *args: Any) -> Any:
        """``fn(job, *args)`` in a thread with ``job.worldmap`` = this map."""
        job.worldmap = self.map
        out = await asyncio.to_thread(fn, job, *args)
        self.map = job.worldmap
        return out

    def __len__(self) -> int:
        return len(self.map)

    def close(self) -> None:
        return None

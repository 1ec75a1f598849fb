"""The world map in a worker process, so that stitching never holds the daemon's GIL.

:class:`ProcessWorldMap` has the read interface of :class:`tandemscan.pipeline.worldmap.VoxelMap`
(``points()``, ``normals()``, ``len()``, ``voxel_mm``) but its voxel grid lives in a one-process pool: a scan
is added by its file and world pose (Eq. 1 is applied there), so no point array crosses the pipe on the way in.
A full-resolution scan (3.2 M points) merged in a thread held the GIL long enough to stall the event loop for
over half a second; in the worker it costs the loop nothing. Frames: points in S in the file, map in W (mm).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

_MAP = None  # the worker's VoxelMap


def _init(voxel_mm: float) -> None:
    global _MAP
    from tandemscan.pipeline.worldmap import VoxelMap

    _MAP = VoxelMap(voxel_mm)


def _add_file(path: str, T_W_S: np.ndarray) -> int:
    from tandemscan.pipeline.cloud_io import read_raw_scan

    _MAP.add_scan(T_W_S, *read_raw_scan(path))
    return len(_MAP)


def _cloud() -> tuple[np.ndarray, np.ndarray]:
    return _MAP.points(), _MAP.normals()


class ProcessWorldMap:
    """A :class:`VoxelMap` in its own process; call :meth:`close` when the job is done."""

    def __init__(self, voxel_mm: float):
        self.voxel_mm = float(voxel_mm)
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init, initargs=(self.voxel_mm,))
        self._len = 0
        self._cloud: tuple[np.ndarray, np.ndarray] | None = None

    def add_file(self, path: Path, T_W_S: np.ndarray) -> None:
        """Merge the scan stored in ``path`` (``points_S_mm``, ``normals_S``) placed at ``T_W_S``; blocks the
        calling thread (not the GIL) until merged."""
        self._len = self._pool.submit(_add_file, str(path), np.asarray(T_W_S, float)).result()
        self._cloud = None

    def _fetch(self) -> tuple[np.ndarray, np.ndarray]:
        if self._cloud is None:
            self._cloud = self._pool.submit(_cloud).result()
        return self._cloud

    def points(self) -> np.ndarray:
        return self._fetch()[0]

    def normals(self) -> np.ndarray:
        return self._fetch()[1]

    def __len__(self) -> int:
        return self._len

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

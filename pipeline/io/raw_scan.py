"""The job's raw scan file (``scans/scan-0007.npz``): one scanner capture with what placed it, read and written here.

Arrays (frame S is the scanner's, mm, rad, s): ``points_S_mm`` (N, 3) and ``normals_S`` (N, 3, optional; both
stored as float32), ``T_C_T`` and ``tracker_covariance`` (the tracker reading: 4x4 mm and 6x6 in the order
translation then rotation), ``joints_rad`` (6), ``scan_timestamp_s``, ``tracker_timestamp_s``, ``T_W_C`` (the
tracker camera in the world, 4x4 mm). Written durably (:func:`tandemscan.pipeline.io.durable.write_durably`) before
the journal commits the scan (``docs/daemon.md``, how a job survives a crash).
"""

from __future__ import annotations

import logging
import shutil
import zipfile
from pathlib import Path

import numpy as np
from tandemscan.pipeline.io.durable import write_durably, write_replacing
from tandemscan.pipeline.registration.sampling import voxel_downsample

log = logging.getLogger(__name__)

_FLOAT32_ARRAYS = ("points_S_mm", "normals_S")  # stored as float32 (mm, unit vectors)


class RawScanError(ValueError):
    """Arrays that do not make a raw scan (points not (N, 3), normals not matching them); names the file."""


def write_raw_scan(path: Path, **arrays: np.ndarray) -> int:
    """Write a raw scan ``.npz`` of ``arrays`` (the module's names) durably; returns its size in bytes.

    Raises :class:`RawScanError` when ``points_S_mm`` is missing or not ``(N, 3)``, or ``normals_S`` does not
    match it."""
    points = np.asarray(arrays.get("points_S_mm", np.empty((0, 0))))
    if points.ndim != 2 or points.shape[1] != 3:
        raise RawScanError(f"{Path(path).name}: scan points must be (N, 3) mm, got {points.shape}")
    if "normals_S" in arrays and np.shape(arrays["normals_S"]) != points.shape:
        raise RawScanError(f"{Path(path).name}: normals {np.shape(arrays['normals_S'])} do not match points "
                           f"{points.shape}")
    arrays = {k: v.astype(np.float32) if k in _FLOAT32_ARRAYS else v for k, v in arrays.items()}
    return write_durably(Path(path), lambda f: np.savez(f, **arrays))


def read_raw_scan(path: Path | str, dtype: type = np.float64) -> tuple[np.ndarray, np.ndarray | None]:
    """(points_S (N, 3) mm, normals_S or None) of a raw scan file, as ``dtype`` (float32: as stored, half the
    memory of float64)."""
    with np.load(path) as data:
        points = data["points_S_mm"].astype(dtype, copy=False)
        normals = data["normals_S"].astype(dtype, copy=False) if "normals_S" in data.files else None
    return points, normals


def read_thinned_scan(path: Path | str, voxel_mm: float) -> np.ndarray:
    """The points of a raw scan file (S, mm) thinned to the centroid of each occupied voxel of edge
    ``voxel_mm`` (float64; ``registration.sampling.voxel_downsample``, which leaves them as they are): the
    small copy the end of a job keeps of a scan (docs/end-of-job.md). Where that would
    not halve the scan (a coarse scan, points over a voxel apart) the scan itself is returned (float32, as
    stored): it is hardly larger, and a thinning at a coarser voxel of it is that of the scan. Read from the copy
    kept beside the job's scans (:func:`keep_thinned_copy`) where there is one of this file at ``voxel_mm``."""
    kept = _kept_copy(Path(path), voxel_mm)
    if kept is not None:
        return kept
    with np.load(path) as data:
        points = data["points_S_mm"]  # the normals stay on disk
    return thin_scan(points, voxel_mm)


#: the folder beside a job's ``scans/`` that holds their thinned copies while the job runs (:func:`keep_thinned_copy`)
THINNED_FOLDER = "thinned"


def keep_thinned_copy(path: Path | str, copy: np.ndarray, voxel_mm: float) -> None:
    """Keep ``copy``, :func:`thin_scan` at ``voxel_mm`` of the raw scan file ``path`` (written), in the job's
    :data:`THINNED_FOLDER` (``<job>/thinned/<file name>``), with the file's size and modification time:
    :func:`read_thinned_scan` of that file reads it there instead of the raw scan. For the end of a job whose
    workers read the scans from the scan store (docs/compute.md); the job removes the folder when it ends
    (:func:`remove_thinned_copies`), and a resumed job keeps the copies again as it rebuilds its map."""
    path = Path(path)
    stat = np.array([path.stat().st_size, path.stat().st_mtime_ns], np.int64)
    write_replacing(path.parent.parent / THINNED_FOLDER / path.name, lambda f: np.savez(
        f, points_S_mm=copy, voxel_mm=np.float64(voxel_mm), raw_size_mtime_ns=stat))


def _kept_copy(path: Path, voxel_mm: float) -> np.ndarray | None:
    """The copy :func:`keep_thinned_copy` kept of the raw scan file ``path`` at ``voxel_mm``, or None (none kept,
    another voxel, the file changed since, or a copy that cannot be read: written, not fsynced, before a power
    loss)."""
    kept = path.parent.parent / THINNED_FOLDER / path.name
    if not kept.is_file():
        return None
    try:
        if not zipfile.is_zipfile(kept):  # before np.load, which leaves the file open where it is no zip
            raise ValueError("not a whole .npz")
        with np.load(kept) as data:
            stat = path.stat()
            if (float(data["voxel_mm"]) == voxel_mm
                    and data["raw_size_mtime_ns"].tolist() == [stat.st_size, stat.st_mtime_ns]):
                return data["points_S_mm"]
    except FileNotFoundError:  # removed meanwhile (the job ended)
        pass
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        log.warning("thinned copy %s not read (%s): the raw scan is read", kept, e)
    return None


def remove_thinned_copies(job_dir: Path | str) -> None:
    """Remove the job's :data:`THINNED_FOLDER` (``job_dir``: the job folder that holds its ``scans/``)."""
    shutil.rmtree(Path(job_dir) / THINNED_FOLDER, ignore_errors=True)


def thin_scan(points_S: np.ndarray, voxel_mm: float) -> np.ndarray:
    """:func:`read_thinned_scan` of a scan whose points (S, mm) are at hand: the same copy, from its points as a
    raw scan file stores them (float32), so a scan thinned as it is written needs no read of its file."""
    points = np.asarray(points_S, np.float32)
    thinned = voxel_downsample(points, voxel_mm)
    return thinned if 2 * len(thinned) <= len(points) else np.array(points, np.float32)  # a copy of its own

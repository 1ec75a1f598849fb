"""A raw scan's thinned copy kept beside the job's scans (``raw_scan.keep_thinned_copy``, docs/compute.md): read in
place of the raw file, the same array to the bit, and never where it is not the copy of that file at that voxel."""

from __future__ import annotations

import numpy as np
from tandemscan.pipeline.io.raw_scan import (
    THINNED_FOLDER,
    keep_thinned_copy,
    read_thinned_scan,
    remove_thinned_copies,
    thin_scan,
    write_raw_scan,
)


def _points(n: int, spacing_mm: float, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, spacing_mm * n ** (1 / 2), (n, 3)) * [1, 1, 0.01]


def test_a_kept_copy_is_read_instead_of_the_raw_scan(tmp_path, scan_reads):
    job = tmp_path / "job"
    for name, points, voxel in (("dense.npz", _points(20_000, 0.2), 1.0), ("coarse.npz", _points(2_000, 3.0), 1.0)):
        raw = job / "scans" / name
        write_raw_scan(raw, points_S_mm=points)
        thinned = read_thinned_scan(raw, voxel)
        assert scan_reads[name] == 1
        keep_thinned_copy(raw, thin_scan(points, voxel), voxel)
        kept = read_thinned_scan(raw, voxel)
        assert scan_reads[name] == 1  # the copy, not the raw file
        assert kept.dtype == thinned.dtype and np.array_equal(kept, thinned)  # float64 thinned, float32 whole
        read_thinned_scan(raw, 2 * voxel)  # another voxel: the raw file
        assert scan_reads[name] == 2
    assert (job / THINNED_FOLDER / "dense.npz").is_file()
    write_raw_scan(job / "scans" / "dense.npz", points_S_mm=_points(19_000, 0.2, seed=2))  # measured again: changed
    again = read_thinned_scan(job / "scans" / "dense.npz", 1.0)
    assert scan_reads["dense.npz"] == 3 and np.array_equal(again, thin_scan(_points(19_000, 0.2, seed=2), 1.0))
    remove_thinned_copies(job)
    assert not (job / THINNED_FOLDER).exists() and (job / "scans" / "dense.npz").is_file()


def test_a_kept_copy_that_cannot_be_read_is_as_none(tmp_path, scan_reads):
    """Kept copies are written without fsync (scratch): after a power loss one may be empty or cut short. A job
    resumed then reads the raw scan instead (the same copy), not fail on it."""
    raw = tmp_path / "job" / "scans" / "dense.npz"
    points = _points(20_000, 0.2)
    write_raw_scan(raw, points_S_mm=points)
    keep_thinned_copy(raw, thin_scan(points, 1.0), 1.0)
    kept = tmp_path / "job" / THINNED_FOLDER / "dense.npz"
    whole = kept.read_bytes()
    for damaged in (b"", whole[: len(whole) // 2]):
        kept.write_bytes(damaged)
        reads = scan_reads["dense.npz"]
        assert np.array_equal(read_thinned_scan(raw, 1.0), thin_scan(points, 1.0))
        assert scan_reads["dense.npz"] == reads + 1

"""Where the end of a job reads the scans from the store (``ComputeConfig.reads_scan_store``), the job's map process
merges no scan and keeps of each only its stitch-view points and reach, not its thinned copy (daemon/jobs/stitcher.py,
docs/compute.md): what the end of the job takes from it there is the same as on the local backend."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from tandemscan.config.models import ComputeConfig
from tandemscan.daemon.jobs.finish import load_scans
from tandemscan.daemon.jobs.outputs import STITCH_VIEW_POINTS, stitch_view_points
from tandemscan.daemon.jobs.stitcher import ProcessWorldMap
from tandemscan.pipeline.io.raw_scan import write_raw_scan
from tandemscan.pipeline.stitching.tiles import ScanReach, scan_x_extent

PLACEMENT = {"T_W_C": np.eye(4), "T_C_T": np.eye(4), "tracker_covariance": np.eye(6) * 1e-4}


def _scans(n: int) -> list[dict[str, np.ndarray]]:
    """``n`` overlapping fine scans (S, mm): 250 k points over 350 x 350 mm, about 2 a 1 mm voxel."""
    rng = np.random.default_rng(11)
    scans = []
    for _ in range(n):
        xy = rng.uniform(0.0, 350.0, (250_000, 2))
        scans.append({"points_S_mm": np.c_[xy, 500.0 + 0.01 * np.sin(xy[:, 0] / 20.0)], **PLACEMENT})
    return scans


async def _measured(folder: Path, lean: bool, backend: str) -> tuple[dict, int, object]:
    """Three scans written and merged by a daemon's map process (``lean`` as the job's ``[compute]`` asks), a
    fourth written before and merged from its file (a job rebuilt after a restart): what the process holds of the
    scans, its map's voxels and what the end of the job loads there (``finish.load_scans``); the scans' poses."""
    folder.mkdir()
    compute = ComputeConfig(backend=backend)
    assert compute.reads_scan_store == lean
    worldmap = ProcessWorldMap(1.0, lean=lean)
    files = [folder / f"scan-{k:04d}.npz" for k in range(4)]
    poses = [np.eye(4) for _ in files]
    try:
        for k, arrays in enumerate(_scans(4)):
            T_W_S = poses[k]
            T_W_S[0, 3] = 80.0 * k
            if k < 3:
                await worldmap.add_scan(files[k], T_W_S, arrays)
            else:
                write_raw_scan(files[k], **arrays)
                await worldmap.add_scan(files[k], T_W_S)
        job = SimpleNamespace(scans=[SimpleNamespace(file=f, T_W_S=T) for f, T in zip(files, poses, strict=True)],
                              config=SimpleNamespace(job=SimpleNamespace(voxel_mm=1.0), compute=compute))
        held = await worldmap.run(getattr, job, "scan_copies")  # what the map's process holds of the scans
        loaded = await worldmap.run(load_scans, job)
        return held, len(worldmap), loaded
    finally:
        worldmap.close()


@pytest.mark.slow
async def test_on_the_scan_store_path_the_maps_process_keeps_only_each_scans_stitch_view_points(tmp_path):
    thinned, voxels, local = await _measured(tmp_path / "local", False, "local")
    kept, store_voxels, store = await _measured(tmp_path / "store", True, "dask")
    assert voxels > 100_000 and store_voxels == 0  # no whole-part map: the end merges the cloud from the files
    assert len(kept) == len(thinned) == 4
    for file, copy in thinned.items():
        assert len(copy) > 2 * STITCH_VIEW_POINTS  # a thinned copy, held on the local backend
        view, reach = kept[file.replace("/local/", "/store/")]
        assert len(view) <= 2 * STITCH_VIEW_POINTS and view.nbytes <= 2 * STITCH_VIEW_POINTS * 12  # float32
        np.testing.assert_array_equal(view, stitch_view_points(copy))
        again = ScanReach.of(reach.T_W_S, copy)  # the copy's reach at its tracker pose
        assert (reach.x_min_mm, reach.x_max_mm, reach.reach_mm) == (again.x_min_mm, again.x_max_mm, again.reach_mm)
    assert sum(v.nbytes for v, _ in kept.values()) < sum(c.nbytes for c in thinned.values()) / 4
    # the end of the job loads the stitch-view points, the same as the local backend's exports make of its copies,
    # and each scan's reach at its tracker pose, the bounds of x the local backend takes from its copies
    assert store.voxel_mm == local.voxel_mm == 1.0 and len(store.reaches) == 4 and not local.reaches
    for view, reach, copy, scan in zip(store.points_S, store.reaches, local.points_S, _poses(), strict=True):
        np.testing.assert_array_equal(view, stitch_view_points(copy))
        assert reach.x_bound(scan, 1.0, 1.0) == scan_x_extent(scan, copy, 1.0, 1.0)


def _poses() -> list[np.ndarray]:
    return [np.array([[1, 0, 0, 80.0 * k], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float) for k in range(4)]


async def test_a_lean_map_replays_a_scan_from_the_copy_an_earlier_attempt_kept_else_from_its_points_alone(
        tmp_path, scan_reads):
    """A job rebuilt after a restart on the scan-store path replays its scans from their files: where the earlier
    attempt's thinned copy is still beside them (a crash) that copy is taken and the raw scan not read; where it is
    not, the raw scan's points alone are read (its normals, half the file, are not needed there). Either way the
    same copy as the scan made when it was measured."""
    from tandemscan.daemon.jobs.stitcher import LocalWorldMap
    from tandemscan.pipeline.io.raw_scan import THINNED_FOLDER, remove_thinned_copies

    job = tmp_path / "job"
    (job / "scans").mkdir(parents=True)
    file = job / "scans" / "scan-0000.npz"
    arrays = _scans(1)[0]
    measured = LocalWorldMap(1.0, lean=True)
    await measured.add_scan(file, np.eye(4), arrays | {"normals_S": np.tile([0.0, 0.0, 1.0], (250_000, 1))})
    assert (job / THINNED_FOLDER / file.name).is_file() and scan_reads[file.name] == 0
    after_a_crash = LocalWorldMap(1.0, lean=True)
    await after_a_crash.add_scan(file, np.eye(4))
    assert scan_reads[file.name] == 0  # the kept copy, not the raw scan
    remove_thinned_copies(job)
    with np.load(file) as data:  # the raw scan again, its normals unreadable here
        np.savez(file, **{k: data[k] for k in data.files if k != "normals_S"}, normals_S=np.array([None], object))
    scan_reads.clear()
    after_a_stop = LocalWorldMap(1.0, lean=True)
    await after_a_stop.add_scan(file, np.eye(4))
    assert scan_reads[file.name] == 1
    view, reach = measured.copies[str(file)]
    for replayed in (after_a_crash, after_a_stop):
        view_again, reach_again = replayed.copies[str(file)]
        np.testing.assert_array_equal(view_again, view)
        assert (reach_again.x_min_mm, reach_again.x_max_mm, reach_again.reach_mm) == (
            reach.x_min_mm, reach.x_max_mm, reach.reach_mm)

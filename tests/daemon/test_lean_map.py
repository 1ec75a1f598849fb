"""Where the correction reads the scans from the store (``[compute] reads_scan_store``), the job's map process keeps of
each scan only its stitch-view points, not its thinned copy (daemon/jobs/stitcher.py, docs/compute.md): what the
end of the job takes from it there is the same as on the local backend."""

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

PLACEMENT = {"T_W_C": np.eye(4), "T_C_T": np.eye(4), "tracker_covariance": np.eye(6) * 1e-4}


def _scans(n: int) -> list[dict[str, np.ndarray]]:
    """``n`` overlapping fine scans (S, mm): 250 k points over 350 x 350 mm, about 2 a 1 mm voxel."""
    rng = np.random.default_rng(11)
    scans = []
    for _ in range(n):
        xy = rng.uniform(0.0, 350.0, (250_000, 2))
        scans.append({"points_S_mm": np.c_[xy, 500.0 + 0.01 * np.sin(xy[:, 0] / 20.0)], **PLACEMENT})
    return scans


async def _measured(folder: Path, views_only: bool, backend: str) -> tuple[dict, int, object]:
    """Three scans written and merged by a daemon's map process (``views_only`` as the job's ``[compute]`` asks), a
    fourth written before and merged from its file (a job rebuilt after a restart): what the process holds of the
    scans, its map's voxels and what the end of the job loads there (``finish.load_scans``)."""
    folder.mkdir()
    compute = ComputeConfig(backend=backend)
    assert compute.reads_scan_store == views_only
    worldmap = ProcessWorldMap(1.0, views_only=views_only)
    files = [folder / f"scan-{k:04d}.npz" for k in range(4)]
    try:
        for k, arrays in enumerate(_scans(4)):
            T_W_S = np.eye(4)
            T_W_S[0, 3] = 80.0 * k
            if k < 3:
                await worldmap.add_scan(files[k], T_W_S, arrays)
            else:
                write_raw_scan(files[k], **arrays)
                await worldmap.add_scan(files[k], T_W_S)
        job = SimpleNamespace(scans=[SimpleNamespace(file=f) for f in files],
                              config=SimpleNamespace(job=SimpleNamespace(voxel_mm=1.0), compute=compute))
        held = await worldmap.run(getattr, job, "scan_copies")  # what the map's process holds of the scans
        loaded = await worldmap.run(load_scans, job)
        return held, len(worldmap), loaded
    finally:
        worldmap.close()


@pytest.mark.slow
async def test_on_the_scan_store_path_the_maps_process_keeps_only_each_scans_stitch_view_points(tmp_path):
    thinned, voxels, local = await _measured(tmp_path / "local", False, "local")
    views, store_voxels, store = await _measured(tmp_path / "store", True, "dask")
    assert store_voxels == voxels > 100_000  # the same map
    assert len(views) == len(thinned) == 4
    for file, copy in thinned.items():
        assert len(copy) > 2 * STITCH_VIEW_POINTS  # a thinned copy, held on the local backend
        view = views[file.replace("/local/", "/store/")]
        assert len(view) <= 2 * STITCH_VIEW_POINTS and view.nbytes <= 2 * STITCH_VIEW_POINTS * 24
        np.testing.assert_array_equal(view, stitch_view_points(copy))
    assert sum(v.nbytes for v in views.values()) < sum(c.nbytes for c in thinned.values()) / 4
    # the end of the job loads the stitch-view points, the same as the local backend's exports make of its copies
    assert store.voxel_mm == local.voxel_mm == 1.0
    for view, copy in zip(store.points_S, local.points_S, strict=True):
        np.testing.assert_array_equal(view, stitch_view_points(copy))

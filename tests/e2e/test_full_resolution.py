"""The end of a job at full resolution (docs/end-of-job.md): only thinned copies of the scans
stay in memory, the re-merge and the E57 stream the full scans from their files, and the result is the one the
scans held in memory gave."""

from __future__ import annotations

import csv
from types import SimpleNamespace

import numpy as np
import pye57
import pytest
from job_reports import report_with_ground_truth
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.finish import merge_stage, merged_cloud, scan_x_bounds
from tandemscan.daemon.jobs.outputs import _point_blocks, _write_cloud_ply, write_job_outputs
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.compute import LazyBackend
from tandemscan.pipeline.geometry.frames import from_rpy
from tandemscan.pipeline.io.cloud_io import read_ply
from tandemscan.pipeline.io.export import PosedScan, write_e57
from tandemscan.pipeline.io.raw_scan import read_raw_scan, read_thinned_scan, write_raw_scan
from tandemscan.pipeline.planning.plan import Plan, Scan
from tandemscan.pipeline.registration.sampling import voxel_downsample
from tandemscan.pipeline.stitching.worldmap import VoxelMap
from tandemscan.sim_drivers.cell import with_surveyed_mounts


def _scan(seed: int, n: int = 60_000) -> dict[str, np.ndarray]:
    """A noisy curved patch 440 mm in front of the scanner, dense (0.1-0.2 mm apart), with unit normals."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-40, 40, (n, 2))
    z = 440 + 5 * np.sin(xy[:, 0] / 17) + rng.normal(0, 0.05, n)
    normals = np.c_[rng.normal(0, 0.1, (n, 2)), -np.ones(n)]
    return {"points_S_mm": np.c_[xy, z], "normals_S": normals / np.linalg.norm(normals, axis=1, keepdims=True)}


@pytest.fixture
def scan_files(tmp_path):
    """Three raw scan files, their arrays and poses (one scan saw nothing)."""
    rng = np.random.default_rng(5)
    arrays = [_scan(0), _scan(1), {"points_S_mm": np.zeros((0, 3))}]
    poses = [from_rpy(rng.uniform(-800, 800, 3), rng.uniform(-np.pi, np.pi, 3)) for _ in arrays]
    files = []
    for k, a in enumerate(arrays):
        files.append(tmp_path / "scans" / f"scan-{k:04d}.npz")
        write_raw_scan(files[-1], **a)
    return files, arrays, poses


@pytest.mark.parametrize("voxel_mm", [1.0, 0.7])
def test_thinned_copy_is_what_the_correction_thins_the_full_scan_to(scan_files, voxel_mm):
    files, _, _ = scan_files
    for f in files[:2]:
        full, _ = read_raw_scan(f, np.float32)
        thinned = read_thinned_scan(f, voxel_mm)
        assert len(thinned) < len(full) / 3  # the point of it: dense points into voxels 0.7-1 mm wide
        # the correction's first step (voxel_downsample at [job] voxel_mm, on float64) gives the same cloud
        # whether it is handed the full scan or the thinned copy: bit for bit, in the same order
        np.testing.assert_array_equal(voxel_downsample(np.asarray(thinned, float), voxel_mm),
                                      voxel_downsample(np.asarray(full, float), voxel_mm))
        # ... and the thinned copy itself, not a copy of it (a whole part's copies take about a gigabyte),
        # while the same points in another order are put in voxel order
        assert voxel_downsample(thinned, voxel_mm) is thinned
        np.testing.assert_array_equal(voxel_downsample(thinned[::-1], voxel_mm), thinned)


def test_streamed_merge_equals_the_merge_of_scans_in_memory(scan_files):
    files, arrays, poses = scan_files
    streamed = merge_stage(1.0, files, poses)
    in_memory = VoxelMap(1.0)
    for T, a in zip(poses, arrays, strict=True):
        in_memory.add_scan(T, a["points_S_mm"], a.get("normals_S"))
    assert len(streamed) == len(in_memory) > 1000
    np.testing.assert_array_equal(streamed.counts(), in_memory.counts())
    # merged in groups of scans on two threads, combined once: the same sums, added in another order
    np.testing.assert_allclose(streamed.points(), in_memory.points(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(streamed.normals(), in_memory.normals(), rtol=0, atol=1e-9)


def test_the_cloud_merged_by_tiles_on_the_backend_is_the_one_merged_here(scan_files, sim_config, tmp_path):
    files, _, poses = scan_files
    tiled_config = sim_config.model_copy(update={"compute": sim_config.compute.model_copy(update={"tile_mm": 50.0})})
    job = SimpleNamespace(job_dir=tmp_path, scans=[SimpleNamespace(file=f) for f in files], config=tiled_config)
    bounds = scan_x_bounds(job, 1.0, poses, [read_thinned_scan(f, 1.0) for f in files])
    with LazyBackend(tiled_config.compute) as backend:
        tiled = merged_cloud(job, 1.0, poses, bounds, backend)
    here = merge_stage(1.0, files, poses).frozen()
    whole = tiled.every_kth(1)
    assert len(tiled) == len(here) > 1000
    np.testing.assert_array_equal(whole.counts, here.counts())
    np.testing.assert_allclose(whole.points_mm, here.points(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(whole.normals, here.normals(), rtol=0, atol=1e-9)
    # the exports read it a tile at a time: cloud.ply and the E57's merged scan as of the cloud in memory
    for name, cloud in (("tiled", tiled), ("here", here)):
        _write_cloud_ply(tmp_path / f"{name}.ply", cloud)
        write_e57(tmp_path / f"{name}.e57", [], _point_blocks(cloud))
    (a_points, a_normals), (b_points, b_normals) = (read_ply(tmp_path / f"{n}.ply") for n in ("tiled", "here"))
    np.testing.assert_allclose(a_points, b_points, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a_normals, b_normals, rtol=0, atol=1e-6)  # float32 in the file
    ((_, _, _, a_m),), ((_, _, _, b_m),) = (_read_e57(tmp_path / f"{n}.e57") for n in ("tiled", "here"))
    np.testing.assert_allclose(a_m, b_m, rtol=0, atol=1e-7)  # single precision, metres
    tiled.remove()
    assert not list((tmp_path / "tiles").iterdir())  # the tiles' files go once the exports hold the cloud


def _read_e57(path) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, rotation, translation, points m) of every scan of an E57 file."""
    e57 = pye57.E57(str(path))
    try:
        out = []
        for i in range(e57.scan_count):
            header, raw = e57.get_header(i), e57.read_scan_raw(i)
            out.append((header["name"].value(), header.rotation, header.translation,
                        np.c_[raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]]))
        return out
    finally:
        e57.close()


def test_e57_written_from_a_generator_equals_the_one_from_a_list(scan_files, tmp_path):
    files, _, poses = scan_files
    merged = np.random.default_rng(2).uniform(-500, 500, (3000, 3))

    def scans():
        for k, (f, T) in enumerate(zip(files[:2], poses, strict=False)):
            yield PosedScan(f"scan-{k}", T, read_raw_scan(f, np.float32)[0])

    from_list = _read_e57(write_e57(tmp_path / "list.e57", list(scans()), merged))
    from_generator = _read_e57(write_e57(tmp_path / "generator.e57", scans(), merged))
    assert [s[0] for s in from_generator] == ["scan-0", "scan-1", "merged"]
    for a, b in zip(from_list, from_generator, strict=True):
        for x, y in zip(a[1:], b[1:], strict=True):
            np.testing.assert_array_equal(x, y)


def test_job_exports_hold_the_full_scans_while_the_job_holds_thinned_ones(scan_files, sim_config, tmp_path):
    files, arrays, poses = scan_files
    reading = SimpleNamespace(timestamp_s=1.0)
    records = [SimpleNamespace(file=f, T_W_S=T, tracker_station=0, reading=reading, joints_rad=np.zeros(6),
                               point_count=len(a["points_S_mm"])) for f, T, a in zip(files, poses, arrays, strict=True)]
    cloud = VoxelMap(1.0)
    for T, a in zip(poses, arrays, strict=True):
        cloud.add_scan(T, a["points_S_mm"])
    off = sim_config.model_copy(update={"inspection": sim_config.inspection.model_copy(update={"in_job": False})})
    job = SimpleNamespace(job_dir=tmp_path, scans=records, worldmap=cloud, T_F_W=None, config=off)
    thinned = [read_thinned_scan(f, 1.0) for f in files]
    failed = {}
    write_job_outputs(job, {}, thinned, failed=failed, backend=LazyBackend(off.compute))  # untiled: makes none
    assert failed == {}
    e57 = _read_e57(tmp_path / "cloud.e57")
    assert [s[0] for s in e57] == ["scan-0000", "scan-0001", "merged"]  # the empty scan is left out
    for (_, _, _, points_m), a in zip(e57[:2], arrays[:2], strict=True):  # every point, not the thinned copy
        np.testing.assert_allclose(points_m * 1000.0, a["points_S_mm"], atol=1e-3)
    assert len(e57[2][3]) == len(cloud)
    with (tmp_path / "poses.csv").open() as f:
        assert [int(r["points"]) for r in csv.DictReader(f)] == [len(a["points_S_mm"]) for a in arrays]


def _keys(tree, prefix=""):
    """Every key path of a JSON tree (dicts only; a list's first dict stands for its items)."""
    if isinstance(tree, dict):
        return {p for k, v in tree.items() for p in {prefix + k} | _keys(v, prefix + k + ".")}
    if isinstance(tree, list) and tree and isinstance(tree[0], dict):
        return _keys(tree[0], prefix + "[].")
    return set()


@pytest.mark.slow
@pytest.mark.timeout(900)  # two 3.2 M-point scans through the simulator, the correction and the exports
async def test_full_resolution_job_reports_as_a_coarse_one(sim_config, tmp_path):
    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    plan = plan.model_copy(update={"steps": plan.steps[: scans[1] + 1]})  # the first two scans
    inspection = sim_config.inspection.model_copy(update={"views": ("isometric",), "map_width_px": 300})
    reports = {}
    for resolution in ("coarse", "full"):
        scanner = sim_config.scanner.model_copy(update={"resolution": resolution})
        config = sim_config.model_copy(update={"inspection": inspection, "scanner": scanner})
        async with CellSession(config) as session:
            config = with_surveyed_mounts(config, session.cell.simulation, tmp_path)
            result = await JobRunner(session, plan, config, tmp_path / resolution).run()
        reports[resolution] = report_with_ground_truth(result.job_dir)
    coarse, full = reports["coarse"], reports["full"]
    assert _keys(full) == _keys(coarse)
    for resolution, whole in (("coarse", True), ("full", False)):  # what the end of the job kept of each scan
        for f in sorted((tmp_path / resolution / "scans").glob("*.npz")):
            stored, kept = read_raw_scan(f, np.float32)[0], read_thinned_scan(f, sim_config.job.voxel_mm)
            if whole:
                assert kept.dtype == np.float32 and np.array_equal(kept, stored)
            else:
                assert len(kept) < len(stored) / 10
    points = [e["points"] for e in full["scan_log"]]
    assert min(points) > 30 * max(e["points"] for e in coarse["scan_log"]) / 2  # 3.2 M pixels vs 41 k
    for report in (coarse, full):  # the pairs registered while measuring, from the full scans, are reused
        c = report["correction"]   # at the end from the thinned copies: the same thinned clouds, the same keys
        assert c["enabled"] and c["pairs"] >= 1
        assert c["pairs_registered_while_measuring"] >= c["pairs"] + len(c["pairs_dropped"])
    assert full["ground_truth"]["cloud_rms_mm"] < 0.1 and "alignment" in full["inspection"]
    header = pye57.E57(str(tmp_path / "full" / "cloud.e57"))
    try:
        assert [header.get_header(i).point_count for i in range(2)] == points
    finally:
        header.close()


def test_a_coarse_scan_is_kept_whole(tmp_path):
    """A scan whose points lie over a voxel apart is not halved by thinning: the end of the job keeps it as
    stored, so the correction at coarse resolution sees what it saw before (its joint refinement included)."""
    grid = np.stack(np.meshgrid(np.arange(100) * 1.56, np.arange(80) * 1.56), -1).reshape(-1, 2)
    points = np.c_[grid, 440 + np.random.default_rng(3).normal(0, 0.05, len(grid))]
    write_raw_scan(tmp_path / "coarse.npz", points_S_mm=points)
    kept = read_thinned_scan(tmp_path / "coarse.npz", 1.0)
    np.testing.assert_array_equal(kept, read_raw_scan(tmp_path / "coarse.npz", np.float32)[0])


def test_the_stitch_view_takes_the_same_points_from_its_copy():
    """The end of the job keeps only :func:`stitch_view_points` of a scan after its correction; the stitch
    view, thinning those, shows what it showed of the whole scan."""
    from tandemscan.daemon.jobs.outputs import _thin, stitch_view_points

    for n in (0, 7, 19_999, 40_001, 143_118, 3_186_816):
        points = np.arange(3 * n, dtype=np.float32).reshape(n, 3)
        view = stitch_view_points(points)
        np.testing.assert_array_equal(_thin(view), _thin(points))
        assert view.base is None  # a copy: the scan itself can be freed
    centroids = np.random.default_rng(5).uniform(-900, 900, (143_118, 3))  # a thinned copy (float64, mm)
    view = stitch_view_points(centroids)  # held until the inspection: float32, 12 B a point
    assert view.dtype == np.float32 and view.nbytes == 12 * len(_thin(centroids))
    np.testing.assert_allclose(view, _thin(centroids), rtol=0, atol=3.1e-5)  # float32's half step at 900 mm

"""The merge, the inspection and the exports tile by tile (docs/compute.md, "Tiles"): the tiled cloud, its deviations
from the CAD, the report's figures and the PLYs are those of the untiled end of the job, to 1e-9 mm."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import PartConfig
from tandemscan.daemon.jobs.finish import merge_stage
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.geometry.frames import from_rpy, invert, rotate_vectors, transform_points
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.inspection import tile_inspection
from tandemscan.pipeline.inspection.inspect import CadSurface, DeviationStats, ToleranceResult
from tandemscan.pipeline.inspection.tile_inspection import (
    deviation_figures,
    inspect_tiles,
    write_cad,
    write_deviation_ply,
)
from tandemscan.pipeline.io.export import ExportError, PlyChunk, write_ply, write_ply_streamed
from tandemscan.pipeline.io.raw_scan import read_thinned_scan, write_raw_scan
from tandemscan.pipeline.stitching import tiles as tiles_module
from tandemscan.pipeline.stitching.tiles import (
    ScanReach,
    TileGrid,
    TileScan,
    every_kth,
    merge_tile,
    merge_tiles,
    place_scan,
    place_units,
    read_tile,
    scan_x_extent,
    tile_units,
    write_cloud_ply,
)

VOXEL_MM = 1.0
TILE_MM = 37.0  # narrower than a scan (80 mm): every scan reaches two or three tiles
T_F_W = from_rpy([120.0, -40.0, 15.0], np.radians([3.0, -2.0, 20.0]))  # the job's world W in the CAD frame F


def _height(x: np.ndarray) -> np.ndarray:
    return 4.0 * np.sin(x / 30.0)


def cad_mesh() -> o3d.geometry.TriangleMesh:
    """A wavy sheet z = 4 sin(x / 30) mm over x in [-60, 380], y in [-70, 70] (F, mm), normals up."""
    x, y = np.meshgrid(np.linspace(-60, 380, 221), np.linspace(-70, 70, 71), indexing="ij")
    vertices = np.c_[x.ravel(), y.ravel(), _height(x.ravel())]
    i, j = np.meshgrid(np.arange(220), np.arange(70), indexing="ij")
    a = (i * 71 + j).ravel()
    triangles = np.r_[np.c_[a, a + 71, a + 1], np.c_[a + 1, a + 71, a + 72]]
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))


def stored_job(store: Path, scans: int = 6, points: int = 30_000, seed: int = 3) -> tuple[list[TileScan], Path]:
    """Raw scans of the sheet (80 x 80 mm patches 50 mm apart along x, 0.05 mm noise, normals) under
    ``store/scans``, each with its final pose and x bound, and the CAD mesh's file."""
    rng = np.random.default_rng(seed)
    T_W_F = invert(T_F_W)
    refs = []
    for k in range(scans):
        x = rng.uniform(-40, 40, points) + 50.0 * k
        y = rng.uniform(-40, 40, points)
        p_F = np.c_[x, y, _height(x) + rng.normal(0, 0.05, points)]
        n_F = np.c_[-4.0 / 30.0 * np.cos(x / 30.0), np.zeros(points), np.ones(points)]
        n_F /= np.linalg.norm(n_F, axis=1, keepdims=True)
        T_W_S = from_rpy(transform_points(T_W_F, [50.0 * k, 0.0, 300.0]), rng.uniform(-np.pi, np.pi, 3))
        T_S_F = invert(T_W_S) @ T_W_F
        file = f"scans/scan-{k:04d}.npz"
        write_raw_scan(store / file, points_S_mm=transform_points(T_S_F, p_F), normals_S=rotate_vectors(T_S_F, n_F))
        x_min, x_max = scan_x_extent(T_W_S, read_thinned_scan(store / file, VOXEL_MM), VOXEL_MM, VOXEL_MM)
        refs.append(TileScan(file, T_W_S, x_min, x_max))
    cad = store / "cad"  # the job's CAD as the inspection hands it to the units (write_cad), beside the tiles' folder
    return refs, cad / write_cad(cad, CadSurface(cad_mesh()))


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """The stored job, its untiled cloud (``finish.merge_stage``) and its tiled one (the local backend)."""
    store = tmp_path_factory.mktemp("store")
    refs, mesh_file = stored_job(store)
    untiled = merge_stage(VOXEL_MM, [store / s.file for s in refs], [s.T_W_S for s in refs]).frozen()
    tiles = merge_tiles(refs, VOXEL_MM, TILE_MM, store, LocalBackend())
    return store, refs, mesh_file, untiled, tiles


def concatenated(store: Path, tiles) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    clouds = [read_tile(store, t) for t in tiles]
    return tuple(np.concatenate([getattr(c, a) for c in clouds]) for a in ("points_mm", "normals", "counts"))


def test_the_tiles_cut_the_scans_and_their_clouds_are_the_untiled_cloud(job):
    store, refs, _, untiled, tiles = job
    grid = TileGrid.over(refs, VOXEL_MM, TILE_MM)
    assert len(tiles) == len(grid) >= 10
    assert all(len(_tiles_reached(s, grid)) >= 2 for s in refs)  # scans cross tile borders
    assert all(t.voxels for t in tiles)
    points, normals, counts = concatenated(store, tiles)
    assert len(points) == len(untiled) > 30_000
    np.testing.assert_array_equal(counts, untiled.counts())  # the same voxels, in the same order
    np.testing.assert_allclose(points, untiled.points(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(normals, untiled.normals(), rtol=0, atol=1e-9)
    step = 7
    sub = every_kth(store, tiles, step)
    np.testing.assert_allclose(sub.points_mm, untiled.points()[::step], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(sub.counts, untiled.counts()[::step])


def _tiles_reached(scan: TileScan, grid: TileGrid) -> list[int]:
    """The tiles of ``grid`` whose slab the scan's bound of x meets."""
    slabs = [grid.bounds_mm(k) for k in range(len(grid))]
    return [k for k, (x0, x1) in enumerate(slabs) if scan.x_max_mm >= x0 and scan.x_min_mm < x1]


def test_a_tile_merge_run_again_writes_the_same_cloud(job, tmp_path):
    """Run again on one thread once the tiles are gone: the same files, the same bits. A unit run again once its tile
    was written (its shards removed, as where its worker was lost before it returned) hands back that tile."""
    store, refs, _, _, tiles = job
    before = concatenated(store, tiles)
    for t in tiles:
        (store / t.file).unlink()
    again = merge_tiles(refs, VOXEL_MM, TILE_MM, store, LocalBackend(threads=1))
    assert again == tiles
    for a, b in zip(concatenated(store, again), before, strict=True):
        np.testing.assert_array_equal(a, b)
    shutil.copytree(store / "scans", tmp_path / "scans")
    grid = TileGrid.over(refs, VOXEL_MM, TILE_MM)
    units = tile_units([place_scan(u) for u in place_units(refs, grid, str(tmp_path))], grid, str(tmp_path))
    first = [merge_tile(u) for u in units]
    assert first == [merge_tile(u) for u in units] == list(tiles)  # the second run: from the tiles, no shard left
    assert sorted(p.name for p in (tmp_path / "tiles").iterdir()) == sorted(Path(t.file).name for t in tiles) + [
        Path(units[0].shards[0]).parent.name]  # the merge's folder of shards, empty (merge_tiles removes it)
    assert not list((tmp_path / "tiles" / Path(units[0].shards[0]).parent.name).iterdir())


def test_the_tiled_merge_reads_each_scan_once_and_leaves_only_its_tiles(tmp_path, monkeypatch, scan_reads):
    """However many tiles a scan reaches, the merge reads its raw file once (placing it, ``tiles.place_scan``); once
    done only the tiles' files are left beside the scans. Where a tile's unit fails, the merge leaves neither shards
    nor tiles."""
    refs, _ = stored_job(tmp_path, scans=3, points=5000)
    scan_reads.clear()  # those of stored_job's bounds
    tiles = merge_tiles(refs, VOXEL_MM, TILE_MM, tmp_path, LocalBackend())
    grid = TileGrid.over(refs, VOXEL_MM, TILE_MM)
    assert all(len(_tiles_reached(s, grid)) >= 3 for s in refs) and sum(t.voxels > 0 for t in tiles) >= 5
    assert scan_reads == {Path(s.file).name: 1 for s in refs}
    assert sorted(p.name for p in (tmp_path / "tiles").iterdir()) == sorted(Path(t.file).name for t in tiles)
    for t in tiles:
        (tmp_path / t.file).unlink()

    def merge_or_fail(unit):
        if unit.index == len(tiles) // 2:
            raise OSError(28, "No space left on device")
        return merge_tile(unit)

    monkeypatch.setattr(tiles_module, "merge_tile", merge_or_fail)
    with pytest.raises(OSError, match="No space left"):
        merge_tiles(refs, VOXEL_MM, TILE_MM, tmp_path, LocalBackend())
    assert not list((tmp_path / "tiles").iterdir())


def test_a_scan_whose_bound_of_x_misses_its_points_stops_the_merge_not_its_voxels(tmp_path):
    """The waves merge a tile once the scans whose bound of x reaches it are placed: a scan whose bound starts past
    its points (a wrong ``x_min_mm``) would put voxels in tiles already merged. The merge raises, naming the scan,
    and leaves neither shards nor tiles."""
    refs, _ = stored_job(tmp_path, scans=3, points=5000)
    grid = TileGrid.over(refs, VOXEL_MM, TILE_MM)
    first = min(range(len(refs)), key=lambda i: refs[i].x_min_mm)
    assert grid.tile_of(refs[first].x_min_mm) < len(grid) - 1  # it has points before the last tile
    wrong = list(refs)
    end = max(s.x_max_mm for s in refs)
    wrong[first] = dataclasses.replace(refs[first], x_min_mm=end - 1.0, x_max_mm=end)  # placed in the last wave
    with pytest.raises(ValueError, match=f"scan {first} .* merged before its wave"):
        merge_tiles(wrong, VOXEL_MM, TILE_MM, tmp_path, LocalBackend())
    assert not list((tmp_path / "tiles").iterdir())


def _vertices(path: Path) -> tuple[bytes, np.ndarray]:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end]
    names = [line.split()[-1].decode() for line in header.splitlines() if line.startswith(b"property")]
    kinds = ["<f8" if b"double" in line else "<f4" for line in header.splitlines() if line.startswith(b"property")]
    return header, np.frombuffer(data[end:], np.dtype(list(zip(names, kinds, strict=True))))


def test_cloud_ply_streamed_from_the_tiles_is_the_untiled_one(job, tmp_path):
    store, _, _, untiled, tiles = job
    tiled = write_cloud_ply(tmp_path / "tiled.ply", store, tiles)
    whole = write_ply(tmp_path / "whole.ply", untiled.points(), untiled.normals())
    (h1, v1), (h2, v2) = _vertices(tiled), _vertices(whole)
    assert h1 == h2 and len(v1) == len(v2) == len(untiled)
    for name in ("x", "y", "z"):
        np.testing.assert_allclose(v1[name], v2[name], rtol=0, atol=1e-9)
    for name in ("nx", "ny", "nz"):
        np.testing.assert_allclose(v1[name], v2[name], rtol=0, atol=1e-6)  # float32 of normals equal to 1e-9
    points, normals, _ = concatenated(store, tiles)  # the same arrays: the same bytes
    assert tiled.read_bytes() == write_ply(tmp_path / "same.ply", points, normals).read_bytes()


def test_a_streamed_ply_whose_count_is_wrong_is_refused_and_removed(tmp_path):
    chunks = [PlyChunk(np.zeros((3, 3))), PlyChunk(np.ones((2, 3)))]
    assert write_ply_streamed(tmp_path / "ok.ply", 5, chunks).read_bytes() == write_ply(
        tmp_path / "one.ply", np.r_[np.zeros((3, 3)), np.ones((2, 3))]).read_bytes()
    with pytest.raises(ExportError, match="5 vertices written, the header says 4"):
        write_ply_streamed(tmp_path / "bad.ply", 4, chunks)
    with pytest.raises(ExportError, match="differ"):
        write_ply_streamed(tmp_path / "mixed.ply", 5, [chunks[0], PlyChunk(np.ones((2, 3)), np.ones((2, 3)))])
    assert not (tmp_path / "bad.ply").exists() and not (tmp_path / "mixed.ply").exists()


def test_the_tiles_deviations_and_report_figures_are_the_untiled_ones(job, tmp_path):
    store, _, mesh_file, untiled, tiles = job
    lower, upper = -0.02, 0.02  # about the noise of a voxel's mean
    inspected = inspect_tiles(tiles, store, mesh_file, T_F_W, lower, upper, LocalBackend())
    points_F = transform_points(T_F_W, untiled.points())
    d = CadSurface(cad_mesh()).closest(points_F).signed_mm
    figures = deviation_figures(store, inspected, lower, upper)
    expected = DeviationStats.of(d)
    for name in ("mean_mm", "sigma_mm", "rms_mm", "min_mm", "max_mm", "p5_mm", "p95_mm"):
        assert getattr(figures.stats, name) == pytest.approx(getattr(expected, name), rel=0, abs=1e-9), name
    assert figures.stats.count == expected.count == len(untiled)
    tolerance = ToleranceResult.of(d, lower, upper)
    assert 0 < tolerance.above_pct < 50 and 0 < tolerance.below_pct < 50  # the band cuts the noise
    for name in ("in_pct", "above_pct", "below_pct"):
        assert getattr(figures.tolerance, name) == pytest.approx(getattr(tolerance, name), rel=0, abs=1e-9)
    tiled = write_deviation_ply(tmp_path / "tiled.ply", store, inspected)
    whole = write_ply(tmp_path / "whole.ply", points_F, rotate_vectors(T_F_W, untiled.normals()),
                      {"deviation_mm": d})
    (h1, v1), (h2, v2) = _vertices(tiled), _vertices(whole)
    assert h1 == h2
    for name in ("x", "y", "z"):
        np.testing.assert_allclose(v1[name], v2[name], rtol=0, atol=1e-9)
    np.testing.assert_allclose(v1["deviation_mm"], v2["deviation_mm"], rtol=0, atol=1e-6)  # float32 in the file


def test_a_tile_inspection_that_fails_leaves_no_deviations_behind(job, monkeypatch):
    """Where one tile's unit fails, the deviations the others wrote beside the tiles are removed with it (the caller
    holds none of their names to remove)."""
    store, _, mesh_file, _, tiles = job
    before = sorted(p.name for p in (store / "tiles").iterdir())
    inspect, ran = tile_inspection.inspect_tile, []

    def inspect_or_fail(unit):
        if unit.tile.index == len(tiles) // 2:
            raise OSError(28, "No space left on device")
        ran.append(inspect(unit))
        return ran[-1]

    monkeypatch.setattr(tile_inspection, "inspect_tile", inspect_or_fail)
    with pytest.raises(OSError, match="No space left"):
        inspect_tiles(tiles, store, mesh_file, T_F_W, -0.03, 0.03, LocalBackend())
    assert len(ran) >= len(tiles) // 2  # the other units wrote theirs
    assert sorted(p.name for p in (store / "tiles").iterdir()) == before


def test_a_scans_reach_bounds_its_x_at_a_moved_pose(tmp_path):
    """``ScanReach`` (made where the scan is read) bounds the scan's points' x at the corrected pose without its points:
    at the summarised pose it is ``scan_x_extent`` to the bit; moved by up to 0.5 mm and 1 mrad it still holds every
    point of the raw scan, and it is at most the move's reach wider than the extent at the moved pose."""
    refs, _ = stored_job(tmp_path, scans=2)
    rng = np.random.default_rng(5)
    for ref in refs:
        thinned = read_thinned_scan(tmp_path / ref.file, VOXEL_MM)
        reach = ScanReach.of(ref.T_W_S, thinned)
        assert reach.x_bound(ref.T_W_S, VOXEL_MM, VOXEL_MM) == scan_x_extent(ref.T_W_S, thinned, VOXEL_MM, VOXEL_MM)
        with np.load(tmp_path / ref.file) as data:
            raw = data["points_S_mm"].astype(float)
        for _ in range(10):
            moved = from_rpy(rng.uniform(-0.5, 0.5, 3), rng.uniform(-1e-3, 1e-3, 3)) @ ref.T_W_S
            lo, hi = reach.x_bound(moved, VOXEL_MM, VOXEL_MM)
            x = transform_points(moved, raw)[:, 0]
            assert lo <= x.min() and x.max() <= hi
            exact_lo, exact_hi = scan_x_extent(moved, thinned, VOXEL_MM, VOXEL_MM)
            slack = 0.5 * np.sqrt(3) + np.sqrt(3) * 1e-3 * reach.reach_mm  # the move's translation and turn
            assert exact_lo - slack <= lo <= exact_lo and exact_hi <= hi <= exact_hi + slack


def test_the_tiles_are_inspected_against_the_cad_as_the_job_reads_it(job, tmp_path):
    """A CAD file in metres with a fifth of its triangles wound the other way, as the job reads it (``[part] mesh``
    and ``mesh_units``: in mm, wound outward) and hands it to the units (``write_cad``, its triangles' orientation
    beside): each tile's deviations are those from the job's CAD, not from the file's raw coordinates and winding."""
    store, _, _, untiled, tiles = job
    mesh = cad_mesh()
    triangles = np.asarray(mesh.triangles)
    triangles[::5] = triangles[::5, ::-1]
    in_metres = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices) / 1000.0),
                                          o3d.utility.Vector3iVector(triangles))
    mesh_file = tmp_path / "cad_m.ply"
    o3d.io.write_triangle_mesh(str(mesh_file), in_metres)
    surface = CadSurface(load_part_mesh(PartConfig(mesh=mesh_file, mesh_units="m")))
    inspected = inspect_tiles(tiles, store, tmp_path / write_cad(tmp_path, surface), T_F_W, -0.02, 0.02,
                              LocalBackend(), surface.reversed)
    (d,) = zip(*(_read(store, t.file, "deviation_mm") for t in inspected), strict=True)
    expected = surface.closest(transform_points(T_F_W, untiled.points())).signed_mm
    np.testing.assert_allclose(np.concatenate(d), expected, rtol=0, atol=1e-9)
    assert np.abs(expected).max() < 0.5  # the sheet's noise, every point on the measured side


def _read(store: Path, file: str, *names: str) -> list[np.ndarray]:
    with np.load(store / file) as data:
        return [data[name] for name in names]

"""The deviation areas of a tiled cloud from every point, tile by tile (``tile_inspection.tile_areas``, docs/compute.md
"Tiles"): the untiled cloud's areas and verdict, an area across a tile boundary joined, and a small dent that the
report's even sample does not see found all the same.

A generated part: the wavy sheet of ``tests/pipeline/stitching/test_tiles.py`` (CAD frame F) sampled on a jittered
0.8 mm grid, with 0.02 mm noise, placed in the job's world W by ``T_F_W`` and cut into three slabs across W's x
(the tiles of ``tiles.merge_tiles``, written as it writes them), each point's stated U 0.02 mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.geometry.frames import invert, rotate_vectors, transform_points
from tandemscan.pipeline.inspection import tile_inspection
from tandemscan.pipeline.inspection.deviation_areas import DeviationCloud, find_deviation_areas
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.pipeline.inspection.inspection_job import (
    AlignmentStart,
    InspectionSettings,
    Measurement,
    ReportOutput,
    align_and_inspect,
)
from tandemscan.pipeline.inspection.point_uncertainty import GivenUncertainty
from tandemscan.pipeline.inspection.report import InspectedPart
from tandemscan.pipeline.inspection.tile_inspection import AreaBounds, TiledInspection, WholeCloud
from tandemscan.pipeline.stitching.tiles import TILES_FOLDER, TileCloud, TiledCloud

from tests.pipeline.stitching.test_tiles import T_F_W, _height, cad_mesh

SPACING_MM = 0.8
X_F_MM, Y_F_MM = (0.0, 240.0), (-40.0, 40.0)  # the generated part's extent on the sheet (F)


def _grid_F(rng: np.random.Generator) -> np.ndarray:
    """(N, 2) x, y (F, mm) of the jittered grid."""
    x, y = np.meshgrid(np.arange(*X_F_MM, SPACING_MM), np.arange(*Y_F_MM, SPACING_MM), indexing="ij")
    xy = np.c_[x.ravel(), y.ravel()]
    return xy + rng.uniform(-0.3, 0.3, xy.shape) * SPACING_MM


def _x_W(xy_F: np.ndarray) -> np.ndarray:
    """x in W of the sheet's points at ``xy_F``."""
    return transform_points(invert(T_F_W), np.c_[xy_F, _height(xy_F[:, 0])])[:, 0]


def tiled_part(store: Path, xy_F: np.ndarray, defects: list[tuple[float, float, float, float]], edges_x_W: list[float],
               seed: int = 5) -> TiledCloud:
    """The sheet's points at ``xy_F`` with ``defects`` ((x, y, height, sigma) mm, F: Gaussian bumps and dents) and
    0.02 mm noise, in W, as the tiles of slabs cut at ``edges_x_W`` (W, mm), each in W's voxel key order."""
    rng = np.random.default_rng(seed)
    x, y = xy_F[:, 0], xy_F[:, 1]
    z = _height(x) + rng.normal(0.0, 0.02, len(x))
    for cx, cy, h, sigma in defects:
        z = z + h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2))
    n_F = np.c_[-4.0 / 30.0 * np.cos(x / 30.0), np.zeros(len(x)), np.ones(len(x))]
    T_W_F = invert(T_F_W)
    p_W = transform_points(T_W_F, np.c_[x, y, z])
    n_W = rotate_vectors(T_W_F, n_F / np.linalg.norm(n_F, axis=1, keepdims=True))
    return written_tiles(store, p_W, n_W, edges_x_W)


def written_tiles(store: Path, p_W: np.ndarray, n_W: np.ndarray, edges_x_W: list[float]) -> TiledCloud:
    """The points ``p_W`` with their normals ``n_W`` (W, mm) as the tiles of slabs cut at ``edges_x_W`` (W, mm), each
    in W's voxel key order (1 mm voxels), written into ``store`` as ``tiles.merge_tiles`` writes them."""
    keys = np.floor(p_W).astype(np.int64)
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
    p_W, n_W, keys = p_W[order], n_W[order], keys[order]
    cut = np.searchsorted(keys[:, 0], np.floor(edges_x_W))  # slabs on voxel faces (1 mm)
    tiles = []
    for k, (lo, hi) in enumerate(zip(np.r_[0, cut], np.r_[cut, len(p_W)], strict=True)):
        file = f"{TILES_FOLDER}/generated-{k:02d}.npz"
        (store / TILES_FOLDER).mkdir(exist_ok=True)
        np.savez(store / file, points=p_W[lo:hi], normals=n_W[lo:hi], counts=np.ones(hi - lo, np.int64))
        tiles.append(TileCloud(k, file, int(hi - lo)))
    return TiledCloud(1.0, str(store), tuple(tiles))


def whole_cloud(cloud: TiledCloud, *inspected) -> WholeCloud:
    """What the tiled inspection of ``cloud`` finds of every point (``TiledInspection.inspected`` of the arguments
    ``inspected``, on this process's threads), its units' files removed."""
    with TiledInspection(cloud.tiles, cloud.store, LocalBackend()).inspected(*inspected) as tiles:
        return tiles.whole


def _inspected(out: Path, points_W: np.ndarray, normals_W: np.ndarray, whole: TiledInspection | None = None):
    settings = InspectionSettings.from_section(InspectionConfig(
        views=("isometric",), map_width_px=200, regions=(), reference_spheres=(), alignment="none"))
    measured = Measurement(points_W, normals_W, GivenUncertainty(0.02))
    return align_and_inspect(measured, InspectedPart(CadSurface(cad_mesh())), settings,
                             ReportOutput(out, json_name=None), AlignmentStart(T_F_W, "the sheet's anchor", T_F_W),
                             whole=whole)


def _same_areas(tiled, untiled) -> None:
    assert [(a.side, a.points, a.decision, a.uncertainty_mm) for a in tiled] == [
        (a.side, a.points, a.decision, a.uncertainty_mm) for a in untiled]
    for a, b in zip(tiled, untiled, strict=True):
        np.testing.assert_allclose(a.centroid_mm, b.centroid_mm, rtol=0, atol=1e-9)
        for name in ("area_mm2", "extreme_mm", "mean_mm"):
            assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-9, abs=1e-12), name


@pytest.fixture(scope="module")
def straddling(tmp_path_factory):
    """The part with a bump across the first tile boundary and a dip inside the last tile."""
    xy = _grid_F(np.random.default_rng(1))
    x_W = _x_W(xy)
    edges = [float(np.quantile(x_W, 1 / 3)), float(np.quantile(x_W, 2 / 3))]
    on_edge = xy[np.abs(xy[:, 1]) < 1.0][np.argmin(np.abs(x_W[np.abs(xy[:, 1]) < 1.0] - edges[0]))]
    defects = [(float(on_edge[0]), 0.0, 0.4, 6.0), (210.0, 15.0, -0.3, 5.0)]
    store = tmp_path_factory.mktemp("store")
    return tiled_part(store, xy, defects, edges), edges


def test_the_tiled_areas_are_the_untiled_clouds_with_one_joined_across_a_tile_boundary(straddling, tmp_path,
                                                                                      monkeypatch):
    cloud, edges = straddling
    points_W = cloud.points()
    d = CadSurface(cad_mesh()).closest(transform_points(T_F_W, points_W)).signed_mm
    untiled = find_deviation_areas(DeviationCloud(transform_points(T_F_W, points_W), d), -0.1, 0.1, 4.0, 50.0)
    joined = []
    join = tile_inspection.joined_areas
    monkeypatch.setattr(tile_inspection, "joined_areas", lambda tiles, *a: joined.append(tiles) or join(tiles, *a))
    found = whole_cloud(cloud, CadSurface(cad_mesh()), T_F_W, (-0.1, 0.1), None, (), tmp_path / "deviation.ply",
                        AreaBounds(-0.1, 0.1, 4.0, 50.0)).areas
    assert [a.side for a in untiled] == ["upper", "lower"]
    _same_areas(found, untiled)
    # the bump lies across the first boundary: each of the first two tiles holds a piece of it, joined here
    (tiles,) = joined
    assert [sum(p.side == "upper" and p.area_mm2 > 10.0 for p in t.pieces) for t in tiles] == [1, 1, 0]
    assert abs(_x_W(np.array([found[0].centroid_mm[:2]]))[0] - edges[0]) < 2.0


def test_a_tiled_clouds_verdict_and_areas_are_the_untiled_clouds(straddling, tmp_path):
    """Through the job's inspection: the untiled cloud inspected whole, against its even sample (every third
    point) with the tiles; the verdict's guard band and the areas' U the same (the sample at the cloud's density)."""
    cloud, _ = straddling
    whole = _inspected(tmp_path / "whole", cloud.points(), np.concatenate([
        np.load(Path(cloud.store) / t.file)["normals"] for t in cloud.tiles]))
    sample = cloud.every_kth(3)
    tiled = _inspected(tmp_path / "tiled", sample.points_mm, sample.normals,
                       TiledInspection(cloud.tiles, cloud.store, LocalBackend()))
    assert whole.result.verdict == tiled.result.verdict == "fail"
    assert [a.decision for a in whole.result.areas] == ["nonconforming", "nonconforming"]
    _same_areas(tiled.result.areas, whole.result.areas)


def test_a_small_dent_the_reports_sample_misses_is_an_area_of_the_tiled_cloud(tmp_path):
    """A dent 0.8 mm deep and about 13 mm across beyond the band, where the sample (every 120th point, about 9 mm apart)
    has no point within 7 mm: the sample alone passes the part; the tiles find the dent at full density."""
    xy = _grid_F(np.random.default_rng(2))
    x_W = _x_W(xy)
    edges = [float(np.quantile(x_W, 1 / 3)), float(np.quantile(x_W, 2 / 3))]
    flat = tiled_part(tmp_path, xy, [], edges)
    sample = flat.every_kth(120)
    sample_F = transform_points(T_F_W, sample.points_mm)[:, :2]
    inside = xy[(xy[:, 0] > 20) & (xy[:, 0] < 220) & (np.abs(xy[:, 1]) < 25)]
    gap, at = cKDTree(sample_F).query(inside)
    dent = inside[np.argmax(gap)]
    assert gap.max() > 7.0  # 0.8 exp(-7^2 / 18) mm: no sample point lies beyond the band
    cloud = tiled_part(tmp_path, xy, [(float(dent[0]), float(dent[1]), -0.8, 3.0)], edges)
    sample = cloud.every_kth(120)  # the same points as the flat part's, the dent's heights
    alone = _inspected(tmp_path / "sample", sample.points_mm, sample.normals)
    assert alone.result.verdict == "pass" and alone.result.areas == ()
    tiled = _inspected(tmp_path / "tiled", sample.points_mm, sample.normals,
                       TiledInspection(cloud.tiles, cloud.store, LocalBackend()))
    assert tiled.result.verdict == "fail"
    (area,) = tiled.result.areas
    assert area.side == "lower" and area.decision == "nonconforming"
    assert np.linalg.norm(np.subtract(area.centroid_mm[:2], dent)) < 1.0
    assert area.extreme_mm < -0.3 and area.area_mm2 > 50.0


def test_screened_tiled_areas_are_the_screened_untiled_clouds(straddling, tmp_path, monkeypatch):
    """Where the whole cloud is large enough to be screened (here: the threshold lowered), each tile screens its
    points with its halo: the areas of the untiled cloud screened."""
    cloud, _ = straddling
    points_F = transform_points(T_F_W, cloud.points())
    d = CadSurface(cad_mesh()).closest(points_F).signed_mm
    untiled = find_deviation_areas(DeviationCloud(points_F, d), -0.1, 0.1, 4.0, 50.0, screen=True)
    monkeypatch.setattr(tile_inspection, "THIN_ABOVE_POINTS", len(points_F) - 1)
    units = []
    area_units = tile_inspection.area_units
    monkeypatch.setattr(tile_inspection, "area_units", lambda *a: units.append(area_units(*a)) or units[-1])
    found = whole_cloud(cloud, CadSurface(cad_mesh()), T_F_W, (-0.1, 0.1), None, (), tmp_path / "deviation.ply",
                        AreaBounds(-0.1, 0.1, 4.0, 50.0)).areas
    assert all(u.screen for u in units[0]) and len(untiled) == 2
    _same_areas(found, untiled)


def test_on_a_sparse_cloud_the_tiles_link_at_three_spacings(tmp_path, monkeypatch):
    """A cloud 1.8 mm apart links its areas at three spacings, longer than the smoothing radius (4 mm): the units,
    run first at the smoothing radius, run again at the bound of the spacing the tiles report (0.01 mm above its
    median), and find the untiled cloud's areas."""
    rng = np.random.default_rng(3)
    x, y = np.meshgrid(np.arange(*X_F_MM, 1.8), np.arange(*Y_F_MM, 1.8), indexing="ij")
    xy = np.c_[x.ravel(), y.ravel()] + rng.uniform(-0.3, 0.3, (x.size, 2))
    x_W = _x_W(xy)
    edges = [float(np.quantile(x_W, 1 / 3)), float(np.quantile(x_W, 2 / 3))]
    cloud = tiled_part(tmp_path, xy, [(100.0, 0.0, 0.4, 8.0), (180.0, 10.0, -0.4, 8.0)], edges)
    points_F = transform_points(T_F_W, cloud.points())
    d = CadSurface(cad_mesh()).closest(points_F).signed_mm
    whole = DeviationCloud(points_F, d)
    untiled = find_deviation_areas(whole, -0.1, 0.1, 4.0, 50.0)
    links = []
    area_units = tile_inspection.area_units
    monkeypatch.setattr(tile_inspection, "area_units", lambda *a: links.append(a[-1]) or area_units(*a))
    found = whole_cloud(cloud, CadSurface(cad_mesh()), T_F_W, (-0.1, 0.1), None, (), tmp_path / "deviation.ply",
                        AreaBounds(-0.1, 0.1, 4.0, 50.0)).areas
    spacing = float(np.median(whole.tree.query(points_F, k=2)[0][:, 1]))
    assert links[0] == 4.0 and 3 * spacing <= links[1] <= 3 * spacing + 0.03 and len(links) == 2
    assert len(untiled) == 2
    _same_areas(found, untiled)

"""A tiled cloud's inspection as the job runs it (``align_and_inspect(..., whole=TiledInspection)``, docs/compute.md
"Tiles"): the report of an even sample of the cloud with the whole cloud's deviation figures, areas and PLY, tile by
tile, against the inspection of the whole cloud in one process.

The sheet of ``tests/pipeline/stitching/test_tiles.py`` with a bump and a dip beyond the band, scanned in six
patches; each point's stated U grows along x. What may differ and by how much: the alignment is fitted on the
sample (every third voxel), and the areas' U is that of the sample's point nearest their centroid, not the whole
cloud's (U grows along x). The whole cloud's deviation figures are exact at the sample's alignment
(``test_tile_areas.py``: the areas too, where the alignment and U are the same).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tandemscan.config.models import InspectionConfig
from tandemscan.daemon.jobs.finish import merge_stage
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.geometry.frames import from_rpy, invert, rotate_vectors, transform_points
from tandemscan.pipeline.inspection.inspect import CadSurface, DeviationStats, ToleranceResult
from tandemscan.pipeline.inspection.inspection_job import (
    AlignmentStart,
    InspectionSettings,
    Measurement,
    ReportOutput,
    align_and_inspect,
)
from tandemscan.pipeline.inspection.point_uncertainty import GivenUncertainty
from tandemscan.pipeline.inspection.report import InspectedPart
from tandemscan.pipeline.inspection.tile_inspection import TiledInspection, UncertaintyField
from tandemscan.pipeline.io.cloud_io import read_ply_vertices
from tandemscan.pipeline.io.raw_scan import read_thinned_scan, write_raw_scan
from tandemscan.pipeline.stitching.tiles import TiledCloud, TileScan, merge_tiles, scan_x_extent

from tests.pipeline.inspection.test_tile_areas import whole_cloud
from tests.pipeline.stitching.test_tiles import T_F_W, TILE_MM, VOXEL_MM, _height, cad_mesh

STEP = 3  # the report's sample: every third voxel
DEFECTS = ((100.0, 10.0, 0.4), (220.0, -20.0, -0.4))  # (x, y, height mm) of a bump and a dip, 8 mm wide (F)


def _surface_mm(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    z = _height(x)
    for cx, cy, h in DEFECTS:
        z = z + h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * 8.0**2))
    return z


def _stated_u(points_W: np.ndarray) -> np.ndarray:
    """Each point's stated U (mm): 0.01 mm growing by 0.03 mm over the sheet's length along F's x."""
    return 0.01 + 1e-4 * (transform_points(T_F_W, points_W)[:, 0] + 60.0)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """Six 80 x 80 mm patches of the defective sheet (50 mm apart, 40,000 points each, 0.05 mm noise) stored as
    raw scans, merged whole (``finish.merge_stage``) and by tiles."""
    store = tmp_path_factory.mktemp("store")
    rng = np.random.default_rng(11)
    T_W_F = invert(T_F_W)
    refs = []
    for k in range(6):
        x, y = rng.uniform(-40, 40, 40_000) + 50.0 * k, rng.uniform(-40, 40, 40_000)
        p_F = np.c_[x, y, _surface_mm(x, y) + rng.normal(0, 0.05, len(x))]
        n_F = np.c_[-4.0 / 30.0 * np.cos(x / 30.0), np.zeros(len(x)), np.ones(len(x))]
        n_F /= np.linalg.norm(n_F, axis=1, keepdims=True)
        T_W_S = from_rpy(transform_points(T_W_F, [50.0 * k, 0.0, 300.0]), rng.uniform(-np.pi, np.pi, 3))
        T_S_F = invert(T_W_S) @ T_W_F
        file = f"scans/scan-{k:04d}.npz"
        write_raw_scan(store / file, points_S_mm=transform_points(T_S_F, p_F), normals_S=rotate_vectors(T_S_F, n_F))
        refs.append(TileScan(file, T_W_S, *scan_x_extent(T_W_S, read_thinned_scan(store / file, VOXEL_MM), VOXEL_MM,
                                                         VOXEL_MM)))
    untiled = merge_stage(VOXEL_MM, [store / s.file for s in refs], [s.T_W_S for s in refs]).frozen()
    tiles = TiledCloud(VOXEL_MM, str(store), merge_tiles(refs, VOXEL_MM, TILE_MM, store, LocalBackend()))
    return store, untiled, tiles


def _inspected(out: Path, points_W, normals_W, whole: TiledInspection | None = None):
    settings = InspectionSettings.from_section(InspectionConfig(views=("isometric",), map_width_px=200, regions=(),
                                                                reference_spheres=()))
    measured = Measurement(points_W, normals_W, GivenUncertainty(_stated_u(points_W)))
    return align_and_inspect(measured, InspectedPart(CadSurface(cad_mesh())), settings,
                             ReportOutput(out, json_name=None), AlignmentStart(T_F_W, "the sheet's anchor", T_F_W),
                             whole=whole)


def test_a_tiled_clouds_report_is_the_whole_clouds_within_what_its_sample_implies(job, tmp_path):
    store, untiled, tiles = job
    whole = _inspected(tmp_path / "whole", untiled.points(), untiled.normals())
    sample = tiles.every_kth(STEP)
    tiled = _inspected(tmp_path / "tiled", sample.points_mm, sample.normals,
                       TiledInspection(tiles.tiles, tiles.store, LocalBackend()))
    a, b = whole.data, tiled.data
    assert a["verdict"] == b["verdict"] == "fail"
    assert [(x["side"], x["decision"]) for x in a["deviations"]] == [(x["side"], x["decision"]) for x in
                                                                      b["deviations"]]
    assert len(a["deviations"]) == 2  # the bump and the dip
    for x, y in zip(a["deviations"], b["deviations"], strict=True):  # every point's, at the sample's alignment
        assert np.linalg.norm(np.subtract(x["centroid_mm"], y["centroid_mm"])) < 0.3
        assert y["area_mm2"] == pytest.approx(x["area_mm2"], rel=0.03)
        assert y["extreme_mm"] == pytest.approx(x["extreme_mm"], abs=0.003)
        assert y["uncertainty_mm"] == pytest.approx(x["uncertainty_mm"], rel=0.1)  # at the sample's nearest point
    for name in ("median_mm", "p95_mm"):  # U smooth along x: the sample's spread is the cloud's
        assert b["uncertainty"][name] == pytest.approx(a["uncertainty"][name], rel=0.01)
    assert [f["name"] for f in a["figures"]] == [f["name"] for f in b["figures"]]
    # the whole cloud's deviation figures: every point, exact at the sample's alignment, near the whole's
    T = np.asarray(b["alignment"]["T_F_W"])
    d = CadSurface(cad_mesh()).closest(transform_points(T, untiled.points())).signed_mm
    stats, band = DeviationStats.of(d), ToleranceResult.of(d, -0.1, 0.1)
    assert b["as_measured"]["stats"]["count"] == len(untiled) == a["as_measured"]["stats"]["count"]
    for name in ("mean_mm", "sigma_mm", "rms_mm", "min_mm", "max_mm", "p5_mm", "p95_mm"):
        assert b["as_measured"]["stats"][name] == pytest.approx(getattr(stats, name), rel=0, abs=1e-9), name
        assert b["as_measured"]["stats"][name] == pytest.approx(a["as_measured"]["stats"][name], abs=2e-3), name
    for name in ("in_pct", "above_pct", "below_pct"):
        assert b["as_measured"]["tolerance"][name] == pytest.approx(getattr(band, name), rel=0, abs=1e-9), name
    # cloud_deviation.ply: every point, each with the U of the sample's nearest
    ply = read_ply_vertices(tmp_path / "tiled" / "cloud_deviation.ply")
    assert len(ply["deviation_mm"]) == len(untiled)
    np.testing.assert_allclose(ply["deviation_mm"], d, rtol=0, atol=1e-6)  # float32 in the file
    np.testing.assert_allclose(ply["uncertainty_mm"], _stated_u(untiled.points()), rtol=0, atol=5e-4)
    assert sorted(p.name for p in (Path(store) / "tiles").iterdir()) == sorted(Path(t.file).name
                                                                               for t in tiles.tiles)


def test_the_tiles_leave_out_the_points_the_samples_alignment_left_out(job, tmp_path):
    """The points in a ball the alignment left out of the sample (a reference sphere and its base:
    ``alignment.sphere_balls``) are left out of the whole cloud's figures and PLY too."""
    store, untiled, tiles = job
    points = untiled.points()
    centre = points[len(points) // 2]  # a ball across the sheet, reaching into two or three tiles
    surface = CadSurface(cad_mesh())
    figures = whole_cloud(tiles, surface, T_F_W, (-0.1, 0.1), None, [(centre, 30.0)],
                          tmp_path / "deviation.ply").figures
    outside = np.linalg.norm(points - centre, axis=1) > 30.0
    assert 0.05 < 1 - outside.mean() < 0.5
    d = surface.closest(transform_points(T_F_W, points[outside])).signed_mm
    expected = DeviationStats.of(d)
    assert figures.stats.count == expected.count == len(read_ply_vertices(tmp_path / "deviation.ply")["x"])
    for name in ("mean_mm", "sigma_mm", "min_mm", "max_mm", "p5_mm", "p95_mm"):
        assert getattr(figures.stats, name) == pytest.approx(getattr(expected, name), rel=0, abs=1e-9), name


def test_an_inspection_whose_uncertainty_cannot_be_written_leaves_no_cad_behind(job, tmp_path, monkeypatch):
    """The job's CAD is written for the units first; where the U field's file then fails (a full disk), the CAD's file
    is removed with the rest: the tiles' folder holds the tiles alone."""
    store, untiled, tiles = job
    before = sorted(p.name for p in (Path(store) / "tiles").iterdir())

    def full_disk(self, store):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(UncertaintyField, "write", full_disk)
    sample_F = transform_points(T_F_W, untiled.points()[::50])
    field = UncertaintyField(sample_F, np.full(len(sample_F), 0.02))
    with pytest.raises(OSError, match="No space left"):
        whole_cloud(tiles, CadSurface(cad_mesh()), T_F_W, (-0.1, 0.1), field, (), tmp_path / "deviation.ply")
    assert sorted(p.name for p in (Path(store) / "tiles").iterdir()) == before

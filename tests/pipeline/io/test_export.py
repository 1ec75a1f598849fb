"""Export: E57 read back with pye57 (points, per-scan poses, counts, metres), PLY fields, pose log CSV."""

from __future__ import annotations

import csv

import numpy as np
import open3d as o3d
import pye57
import pytest
from tandemscan.pipeline.geometry.frames import from_quaternion, from_rpy, pose_error
from tandemscan.pipeline.io import export
from tandemscan.pipeline.io.export import ExportError, PosedScan, write_e57, write_ply, write_pose_log


def make_scans(n_scans=3, seed=0):
    rng = np.random.default_rng(seed)
    scans = []
    for i in range(n_scans):
        T = from_rpy(rng.uniform(-1500, 1500, 3), rng.uniform(-np.pi, np.pi, 3))
        pts = rng.uniform(-150, 150, (200 + 37 * i, 3)) + [0, 0, 442.0]  # scanner frame: z along the view
        scans.append(PosedScan(f"pose-{i:03d}", T, pts, {"t_s": 1.5 * i, "station": f"s{i // 2}"}))
    return scans


def test_e57_round_trip_points_poses_counts(tmp_path):
    scans = make_scans()
    merged = np.vstack([s.points_W_mm() for s in scans])
    path = write_e57(tmp_path / "job.e57", scans, merged)
    e57 = pye57.E57(str(path))
    try:
        assert e57.scan_count == len(scans) + 1
        for i, scan in enumerate(scans):
            header = e57.get_header(i)
            assert header["name"].value() == scan.name
            assert header.point_count == len(scan.points_S_mm)
            w, x, y, z = header.rotation
            T = from_quaternion(header.translation * 1000.0, [x, y, z, w])  # file is in metres
            np.testing.assert_allclose(T, scan.T_W_S, rtol=0, atol=1e-9)  # rotation and mm both exact
            raw = e57.read_scan_raw(i)
            local = np.c_[raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]] * 1000.0
            np.testing.assert_allclose(local, scan.points_S_mm, atol=1e-9)
            world = e57.read_scan(i, ignore_missing_fields=True)  # pye57 applies the pose
            world = np.c_[world["cartesianX"], world["cartesianY"], world["cartesianZ"]] * 1000.0
            np.testing.assert_allclose(world, scan.points_W_mm(), atol=1e-6)
        last = e57.get_header(len(scans))
        assert last["name"].value() == "merged" and last.point_count == len(merged)
        np.testing.assert_allclose(last.translation, 0.0)
    finally:
        e57.close()


def _e57_scans(path):
    """Every scan of an E57 file read back: its header's fields (name, pose, bounds, index bounds, the points'
    prototype limits) and its raw points (m)."""
    e57 = pye57.E57(str(path))
    try:
        out = []
        for i in range(e57.scan_count):
            header = e57.get_header(i)
            node = header.node
            fields = {"name": header["name"].value(), "count": header.point_count,
                      "rotation": tuple(header.rotation), "translation": tuple(header.translation)}
            for group in ("cartesianBounds", "indexBounds"):
                fields |= {f"{group}.{c.elementName()}": c.value() for c in (node[group][k] for k in
                                                                            range(node[group].childCount()))}
            prototype = pye57.libe57.StructureNode(header.points.prototype())
            for axis in ("cartesianX", "cartesianY", "cartesianZ"):
                f = pye57.libe57.FloatNode(prototype.get(axis))
                fields[axis] = (f.minimum(), f.maximum(), f.precision())
            raw = e57.read_scan_raw(i)
            out.append((fields, np.c_[raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]]))
        return out
    finally:
        e57.close()


def test_e57_merged_cloud_written_a_block_at_a_time_is_the_whole_one(tmp_path, monkeypatch):
    """The merged cloud streamed a block at a time (blocks of 7 points, handed in tiles of uneven size, float32 as a
    tile may hold it) reads back as pye57's ``write_scan_raw`` of the whole cloud writes it: the same header
    fields (bounds, pose, counts, prototype limits) and the same points."""
    monkeypatch.setattr(export, "E57_BLOCK_POINTS", 7)
    scans = make_scans()
    merged = np.vstack([s.points_W_mm() for s in scans]).astype(np.float32)

    class Tiles:
        count = len(merged)

        def bounds_mm(self):
            cuts = np.split(merged, [50, 51, 300])
            return (np.min([c.astype(float).min(axis=0) for c in cuts], axis=0),
                    np.max([c.astype(float).max(axis=0) for c in cuts], axis=0))

        def blocks(self):
            yield from np.split(merged, [50, 51, 300])

    whole = tmp_path / "whole.e57"
    e57 = pye57.E57(str(whole), mode="w")
    for scan in scans:
        rotation, translation = export._e57_pose(scan.T_W_S)
        e57.write_scan_raw(export._e57_xyz(scan.points_S_mm), name=scan.name, rotation=rotation,
                           translation=translation)
    e57.write_scan_raw(export._e57_xyz(merged), name="merged", rotation=np.array([1.0, 0, 0, 0]),
                       translation=np.zeros(3))
    e57.close()
    by_blocks = _e57_scans(write_e57(tmp_path / "blocks.e57", scans, Tiles()))
    in_memory = _e57_scans(write_e57(tmp_path / "array.e57", scans, merged))
    for got in (by_blocks, in_memory):
        assert len(got) == len(scans) + 1
        for (fields, points), (want_fields, want_points) in zip(got, _e57_scans(whole), strict=True):
            assert fields == want_fields
            np.testing.assert_array_equal(points, want_points)


def test_e57_refuses_empty_input(tmp_path):
    with pytest.raises(ExportError, match="nothing to write"):
        write_e57(tmp_path / "x.e57", [])
    bad = PosedScan("empty", np.eye(4), np.zeros((0, 3)))
    with pytest.raises(ExportError, match="empty"):
        write_e57(tmp_path / "x.e57", [bad])


@pytest.mark.parametrize("chunk_points", [1_000_000, 7])  # one chunk; records formed a few at a time
def test_ply_binary_with_normals_and_deviation(tmp_path, monkeypatch, chunk_points):
    monkeypatch.setattr(export, "PLY_CHUNK_POINTS", chunk_points)
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1500, 1500, (500, 3))
    nrm = rng.normal(size=(500, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    dev = rng.normal(0, 0.05, 500)
    path = write_ply(tmp_path / "cloud.ply", pts, nrm, {"deviation_mm": dev})
    assert b"format binary_little_endian" in path.read_bytes()[:100]
    cloud = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(cloud.point.positions.numpy(), pts)  # float64: no loss
    np.testing.assert_allclose(cloud.point.normals.numpy(), nrm, atol=1e-6)
    np.testing.assert_allclose(cloud.point.deviation_mm.numpy().ravel(), dev, atol=1e-7)
    with pytest.raises(ExportError, match="deviation_mm"):
        write_ply(tmp_path / "bad.ply", pts, None, {"deviation_mm": dev[:10]})


def test_pose_log_csv(tmp_path):
    scans = make_scans()
    path = write_pose_log(tmp_path / "poses.csv", scans)
    with path.open() as f:
        rows = list(csv.DictReader(f))
    assert [r["name"] for r in rows] == [s.name for s in scans]
    for r, s in zip(rows, scans, strict=True):
        xyz = [float(r[k]) for k in ("x_mm", "y_mm", "z_mm")]
        T = from_quaternion(xyz, [float(r[k]) for k in ("qx", "qy", "qz", "qw")])
        dt, dr = pose_error(T, s.T_W_S)
        assert dt < 1e-5 and dr < 1e-8
        assert int(r["points"]) == len(s.points_S_mm) and float(r["t_s"]) == s.meta["t_s"]
        T_rpy = from_rpy([float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"])],
                         np.radians([float(r[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg")]))
        assert pose_error(T_rpy, s.T_W_S)[1] < 1e-7

"""The part mesh and the arm kinematics the sim cell and the planner build on."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import PartConfig
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.geometry.part import (
    PartMeshError,
    load_part_mesh,
    read_mesh_file,
    signed_volume_mm3,
    train_nose_mesh,
    triangles_closed,
)


def test_train_nose_is_a_closed_part_of_the_configured_size():
    mesh = train_nose_mesh(PartConfig())
    assert triangles_closed(np.asarray(mesh.triangles)) and signed_volume_mm3(mesh) > 0  # closed, outward normals
    assert signed_volume_mm3(mesh) == pytest.approx(3.0e9 * 2.0 * 1.6 * 0.7, rel=0.3)
    lo, hi = mesh.get_min_bound(), mesh.get_max_bound()
    np.testing.assert_allclose(hi[:2] - lo[:2], [3000, 2000], rtol=0.03)
    assert lo[2] == pytest.approx(0.0) and hi[2] == pytest.approx(1600.0)
    # the nose narrows and lowers towards +x
    v = np.asarray(mesh.vertices)
    front, back = v[v[:, 0] > 1200], v[v[:, 0] < -1000]
    assert np.abs(front[:, 1]).max() < 0.6 * np.abs(back[:, 1]).max()
    assert front[:, 2].max() < 0.7 * back[:, 2].max()


def test_closed_and_volume_checks_on_a_box():
    box = o3d.geometry.TriangleMesh.create_box(10, 20, 30)
    assert triangles_closed(np.asarray(box.triangles)) and signed_volume_mm3(box) == pytest.approx(6000.0)
    open_box = o3d.geometry.TriangleMesh(box.vertices, o3d.utility.Vector3iVector(np.asarray(box.triangles)[1:]))
    assert not triangles_closed(np.asarray(open_box.triangles))


def test_mesh_file_replaces_the_parametric_part(tmp_path):
    box = o3d.geometry.TriangleMesh.create_box(1000, 500, 300)
    path = tmp_path / "box.stl"
    box.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(path), box)
    mesh = load_part_mesh(PartConfig(mesh=path))
    np.testing.assert_allclose(mesh.get_max_bound() - mesh.get_min_bound(), [1000, 500, 300])


@pytest.mark.parametrize("name, content, reason", [
    ("missing.stl", None, "not found"),
    ("part.xyz", "1 2 3\n", "unsupported mesh format"),
    ("empty.ply", "ply\nformat ascii 1.0\nelement vertex 0\nend_header\n", "no triangles"),
])
def test_bad_mesh_files_give_clear_errors(tmp_path, name, content, reason):
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    with pytest.raises(PartMeshError, match=reason):
        read_mesh_file(path)


def test_inverse_kinematics_recovers_reachable_poses(sim_config):
    kin = ArmKinematics(sim_config.arm)
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = rng.uniform(np.maximum(kin.q_min, -2.5), np.minimum(kin.q_max, 2.5))
        T = kin.forward(q)
        q_ik = kin.inverse(T, seed_rad=q + rng.normal(0, 0.1, 6))
        assert q_ik is not None and kin.within_limits(q_ik)
        np.testing.assert_allclose(kin.forward(q_ik), T, atol=1e-6)


def test_forward_kinematics_matches_the_dh_geometry(sim_config):
    """At zero joints the Zu 7 DH chain stretches along base x by a2 + a3 (mm)."""
    kin = ArmKinematics(sim_config.arm)
    T = kin.forward(np.zeros(6))
    assert T[0, 3] == pytest.approx(360.0 + 303.5 + 0.0)
    assert T[2, 3] == pytest.approx(120.15 - 113.5)


def test_unreachable_pose_and_limits(sim_config):
    kin = ArmKinematics(sim_config.arm)
    far = np.eye(4)
    far[:3, 3] = (2000.0, 0.0, 0.0)  # beyond the 0.8 m reach
    assert kin.inverse(far, restarts=2) is None
    assert not kin.within_limits(np.radians([0, -90, 0, 0, 0, 0]))  # J2 min is -85 deg

"""The vectorised planning helpers answer as their one-pose counterparts do (docs/planning.md, steps 3 and 6)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config.models import CellConfig, ScannerConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.raycast import ScannerModel, make_scene
from tandemscan.pipeline.planning.ik import AnalyticIK


@pytest.mark.parametrize("model", ["zu7", "zu12"])
def test_reachable_agrees_with_the_seeded_solver(model):
    ik = AnalyticIK(CellConfig.model_validate({"arm": {"model": model}}).arm)
    rng = np.random.default_rng(5)
    q = rng.uniform(ik.kin.q_min, ik.kin.q_max, (200, 6))
    T = ik.kin.forward_many(q)
    assert np.allclose(T[17], ik.kin.forward(q[17])) and np.allclose(T[150], ik.kin.forward(q[150]))
    T[100:, :3, 3] *= rng.uniform(0.6, 1.6, (100, 1))  # half of them moved, many out of reach
    batch = ik.reachable(T)
    one_by_one = np.array([ik(t, s) is not None for t, s in zip(T, q, strict=True)])
    assert np.array_equal(batch, one_by_one)
    assert batch[:100].all() and not batch[100:].all()


def test_seen_primitives_are_the_triangles_under_the_kept_hits():
    mesh = o3d.geometry.TriangleMesh.create_box(800.0, 600.0, 400.0).subdivide_midpoint(3)
    scene = make_scene(mesh)
    model = ScannerModel(ScannerConfig().model_copy(update={"resolution": "coarse", "coarse_pixels": (40, 30)}))
    look_down = F.from_rotvec(np.zeros(3), np.array([np.pi, 0.0, 0.0]))  # S z along -z of F
    poses = []
    for x, tilt in ((200.0, 0.0), (400.0, 0.6), (650.0, -0.9), (5000.0, 0.0)):  # the last sees nothing
        T = look_down @ F.from_rotvec(np.zeros(3), np.array([0.0, tilt, 0.0]))
        T[:3, 3] = (x, 300.0, 400.0 + 450.0)
        poses.append(T)
    expected = set()
    for T in poses:
        hits = model.cast(scene, T)
        d = F.rotate_vectors(T, hits.points_mm / np.linalg.norm(hits.points_mm, axis=1, keepdims=True))
        if len(d):
            ans = scene.cast_rays(o3d.core.Tensor(np.c_[np.broadcast_to(T[:3, 3], d.shape), d].astype(np.float32)))
            expected |= set(ans["primitive_ids"].numpy().tolist())
    seen = model.seen_primitives(scene, np.array(poses))
    assert len(expected) > 10 and set(seen.tolist()) == expected

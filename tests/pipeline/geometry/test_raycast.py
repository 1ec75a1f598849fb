"""The simulated scanner's ray casting (``geometry.raycast``, docs/planning.md, step 6): a capture's hits are those
of its rays cast in the plain way, whatever the arrays' layout the cast uses for speed (docs/capacity.md)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from tandemscan.config.models import ScannerConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.raycast import ScannerModel, make_scene


def _plain_cast(model: ScannerModel, scene, T_F_S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each ray turned into F by ``T_F_S``'s rotation and cast, its hit's point, normal (facing the scanner) and
    incidence in S, kept by the scanner's range and incidence limit."""
    R = T_F_S[:3, :3]
    dirs_F = model.directions_S @ R.T.astype(np.float32)
    rays = np.c_[np.broadcast_to(T_F_S[:3, 3].astype(np.float32), dirs_F.shape), dirs_F]
    ans = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
    t = ans["t_hit"].numpy().astype(float)
    hit = np.isfinite(t)
    d_S = model.directions_S[hit].astype(float)
    n_S = ans["primitive_normals"].numpy()[hit].astype(float) @ R
    cos = -np.sum(n_S * d_S, axis=1)
    n_S[cos < 0] *= -1
    cos = np.abs(cos)
    points = d_S * t[hit][:, None]
    keep = ((points[:, 2] >= model.cfg.range_min_mm) & (points[:, 2] <= model.cfg.range_max_mm)
            & (cos >= np.cos(np.radians(model.cfg.max_incidence_deg))))
    return points[keep], n_S[keep], np.arccos(np.clip(cos[keep], -1, 1))


def test_a_casts_hits_are_those_of_its_rays_cast_the_plain_way():
    mesh = o3d.geometry.TriangleMesh.create_sphere(300.0, 40)  # its rim beyond the working range
    scene = make_scene(mesh)
    model = ScannerModel(ScannerConfig().model_copy(update={"resolution": "coarse", "coarse_pixels": (160, 120)}))
    T = F.from_rotvec(np.array([40.0, -25.0, 750.0]), np.array([np.pi - 0.2, 0.15, 0.3]))  # S z towards the sphere
    hits = model.cast(scene, T)
    points, normals, incidence = _plain_cast(model, scene, T)
    assert 1000 < len(points) < len(model.directions_S)
    np.testing.assert_allclose(hits.points_mm, points, rtol=0, atol=1e-9)
    np.testing.assert_allclose(hits.normals, normals, rtol=0, atol=1e-12)
    np.testing.assert_allclose(hits.incidence_rad, incidence, rtol=0, atol=1e-9)
    # with noise along each ray: the same draws, each point moved by its own over its range
    noisy, _ = model.scan(scene, T, np.random.default_rng(2))
    draws = np.random.default_rng(2).normal(0.0, model.cfg.noise_sigma_mm, (len(points), 1))
    np.testing.assert_allclose(noisy, points * (1.0 + draws / np.linalg.norm(points, axis=1, keepdims=True)),
                               rtol=0, atol=1e-9)

"""Structured-light scanner geometry (PhoXi 3D Scanner S) by ray casting on a triangle mesh.

Scanner optical frame S: origin at the optical centre, z along the view, x right, y down. A pixel grid of
rays spans the field of view given at the sweet spot; a point is kept when its depth (S z, mm) is inside
the working range and the surface is not seen more grazing than the incidence limit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from tandemscan.config.models import ScannerConfig


def make_scene(mesh: o3d.geometry.TriangleMesh) -> o3d.t.geometry.RaycastingScene:
    """A ray-casting scene holding one legacy triangle mesh (mm)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


@dataclass(frozen=True)
class ScanHits:
    """Surface hits of one scan in frame S: points (N, 3) mm, unit normals facing the scanner, incidence rad."""

    points_mm: np.ndarray
    normals: np.ndarray
    incidence_rad: np.ndarray


class ScannerModel:
    """Ray geometry, working range and noise of the configured scanner."""

    def __init__(self, scanner: ScannerConfig):
        self.cfg = scanner
        cols, rows = scanner.pixels
        tan_x = 0.5 * scanner.width_at_sweet_spot_mm / scanner.sweet_spot_mm
        tan_y = 0.5 * scanner.height_at_sweet_spot_mm / scanner.sweet_spot_mm
        u, v = np.meshgrid(np.linspace(-tan_x, tan_x, cols), np.linspace(-tan_y, tan_y, rows))
        d = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
        self.directions_S = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
        self._direction_rows_S = np.ascontiguousarray(self.directions_S.T)  # (3, P): rotated as one long product
        self.half_angles_rad = (float(np.arctan(tan_x)), float(np.arctan(tan_y)))

    @property
    def sweet_spot_mm(self) -> float:
        """The distance (S z, mm) at which the field of view is given."""
        return self.cfg.sweet_spot_mm

    def with_pixels(self, pixels: tuple[int, int]) -> ScannerModel:
        """The same scanner with a grid of ``pixels`` (columns, rows) rays, noise-free casts made cheaper."""
        return ScannerModel(self.cfg.model_copy(update={"resolution": "coarse", "coarse_pixels": pixels}))

    def cast(self, scene: o3d.t.geometry.RaycastingScene, T_F_S: np.ndarray) -> ScanHits:
        """Noise-free hits of the scanner at pose ``T_F_S`` (scene in frame F), returned in frame S.

        The rays are rotated into F as one (3, 3) x (3, P) product and handed to Open3D without a copy; only the hit
        rays' values are taken on in float64 (a full-resolution capture: 3.2 M rays)."""
        T = np.asarray(T_F_S, float)
        R = T[:3, :3]
        rays = np.empty((len(self.directions_S), 6), np.float32)
        rays[:, :3] = T[:3, 3].astype(np.float32)
        rays[:, 3:] = (R.astype(np.float32) @ self._direction_rows_S).T
        ans = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t_all = ans["t_hit"].numpy()
        hit = np.flatnonzero(np.isfinite(t_all))
        t = t_all[hit].astype(float)
        d_S = self.directions_S[hit].astype(float)
        n_S = (R.T @ ans["primitive_normals"].numpy()[hit].astype(float).T).T  # = n_F R
        cos_inc = -np.einsum("ij,ij->i", n_S, d_S)
        n_S[cos_inc < 0] *= -1  # face the scanner whatever the mesh winding
        cos_inc = np.abs(cos_inc)
        points = d_S
        points *= t[:, None]
        keep = self._kept(points[:, 2], cos_inc)
        return ScanHits(points[keep], n_S[keep], np.arccos(np.clip(cos_inc[keep], -1, 1)))

    def _kept(self, depth_mm: np.ndarray, cos_incidence: np.ndarray) -> np.ndarray:
        """Which hits the scanner keeps: depth (S z, mm) inside the working range, incidence inside the limit."""
        return ((depth_mm >= self.cfg.range_min_mm) & (depth_mm <= self.cfg.range_max_mm)
                & (cos_incidence >= np.cos(np.radians(self.cfg.max_incidence_deg))))

    def seen_primitives(self, scene: o3d.t.geometry.RaycastingScene, T_F_S: np.ndarray) -> np.ndarray:
        """Ids of the scene's triangles that the scanner keeps a hit on from any of the ``(K, 4, 4)`` poses
        ``T_F_S`` (frame F, mm): the hits of :meth:`cast`, all poses in one ray cast."""
        T = np.asarray(T_F_S, float).reshape(-1, 4, 4)
        dirs_F = np.einsum("pj,kij->kpi", self.directions_S, T[:, :3, :3]).astype(np.float32)  # (K, P, 3)
        origins = np.broadcast_to(T[:, None, :3, 3].astype(np.float32), dirs_F.shape)
        ans = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(np.concatenate([origins, dirs_F], axis=2))))
        t = ans["t_hit"].numpy()
        cos_inc = np.abs(np.sum(ans["primitive_normals"].numpy() * dirs_F, axis=2))
        keep = np.isfinite(t) & self._kept(t * self.directions_S[None, :, 2], cos_inc)
        return np.unique(ans["primitive_ids"].numpy()[keep])

    def scan(
        self, scene: o3d.t.geometry.RaycastingScene, T_F_S: np.ndarray, rng: np.random.Generator | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(points_S mm, normals_S) of a scan; with ``rng``, Gaussian noise of ``noise_sigma_mm`` along each ray."""
        hits = self.cast(scene, T_F_S)
        points = hits.points_mm
        if rng is not None and len(points):
            scale = rng.normal(0.0, self.cfg.noise_sigma_mm, len(points))
            scale /= np.sqrt(np.einsum("ij,ij->i", points, points))  # the noise over each point's range
            scale += 1.0
            points *= scale[:, None]  # cast's own array
        return points, hits.normals

"""A simulated calibration plate: its mesh for the sim world and an exact analytic scan of it.

The plate frame ``P`` is that of :mod:`tandemscan.pipeline.calibration.plate`: sphere centres at z = 0,
the plate top at ``z = -(radius + stem)``. The analytic scan intersects a pinhole grid of rays from the
scanner origin (frame S: z along the view, x right, y down) with the spheres and the plate top exactly, so
tests know the true centres to machine precision.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike
from tandemscan.config.models import CalibrationConfig, ScannerConfig
from tandemscan.pipeline.calibration.plate import nominal_centres_P
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, transform_points
from tandemscan.pipeline.geometry.raycast import make_scene
from tandemscan.sim_drivers.config import TrackerNoiseConfig
from tandemscan.sim_drivers.world import SimWorld


def plate_top_z_mm(cfg: CalibrationConfig) -> float:
    """z of the plate's top face in frame P (mm)."""
    return -(cfg.sphere_diameter_mm / 2.0 + cfg.stem_mm)


def plate_mesh(cfg: CalibrationConfig, thickness_mm: float = 20.0) -> o3d.geometry.TriangleMesh:
    """Watertight-enough mesh of the plate (box + stems + spheres) in frame P (mm)."""
    r = cfg.sphere_diameter_mm / 2.0
    top = plate_top_z_mm(cfg)
    w, h = cfg.plate_size_mm
    mesh = o3d.geometry.TriangleMesh.create_box(w, h, thickness_mm)
    mesh.translate((-w / 2.0, -h / 2.0 + 40.0, top - thickness_mm))
    for c in nominal_centres_P(cfg):
        # fine tessellation: a coarse polyhedron would bias the sphere fits by hundredths of a mm
        s = o3d.geometry.TriangleMesh.create_sphere(radius=r, resolution=200)
        s.translate(c)
        stem = o3d.geometry.TriangleMesh.create_cylinder(radius=r / 3.0, height=cfg.stem_mm + r)
        stem.translate((c[0], c[1], top + (cfg.stem_mm + r) / 2.0))
        mesh += s + stem
    mesh.compute_vertex_normals()
    return mesh


def _ray_grid(scanner: ScannerConfig) -> np.ndarray:
    """(N, 3) unit ray directions of the scanner's pixel grid in frame S."""
    cols, rows = scanner.pixels
    hx = scanner.width_at_sweet_spot_mm / 2.0 / scanner.sweet_spot_mm
    hy = scanner.height_at_sweet_spot_mm / 2.0 / scanner.sweet_spot_mm
    u, v = np.meshgrid(np.linspace(-hx, hx, cols), np.linspace(-hy, hy, rows))
    d = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def scan_plate(
    cfg: CalibrationConfig,
    scanner: ScannerConfig,
    T_S_P: ArrayLike,
    *,
    rng: np.random.Generator | None = None,
    noise_mm: float | None = None,
    hidden: tuple[str, ...] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """Exact scan of the plate seen at ``T_S_P``: (points_S (N, 3) mm, normals_S (N, 3)).

    Gaussian noise along the ray (``noise_mm``, default the scanner's) when ``rng`` is given; spheres named
    in ``hidden`` are left out (a plate with a missing sphere). Range and grazing filters as the scanner's.
    """
    T = np.asarray(T_S_P, dtype=float)
    r = cfg.sphere_diameter_mm / 2.0
    D = _ray_grid(scanner)
    n = len(D)
    depth = np.full(n, np.inf)
    normal = np.zeros((n, 3))
    centres = transform_points(T, nominal_centres_P(cfg))
    for name, c in zip(("A", "X", "Y"), centres, strict=True):
        if name in hidden:
            continue
        b = D @ c
        disc = b * b - (c @ c - r * r)
        hit = disc >= 0
        t = np.where(hit, b - np.sqrt(np.where(hit, disc, 0.0)), np.inf)
        closer = (t > 0) & (t < depth)
        depth[closer] = t[closer]
        p = D[closer] * t[closer, None]
        normal[closer] = (p - c) / r
    # plate top: plane z_P = top within the plate rectangle
    nz = T[:3, 2]
    p0 = transform_points(T, [[0.0, 0.0, plate_top_z_mm(cfg)]])[0]
    denom = D @ nz
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p0 @ nz) / denom
    q = transform_points(invert(T), D * t[:, None])
    w, h = cfg.plate_size_mm
    inside = (np.abs(q[:, 0]) <= w / 2.0) & (q[:, 1] >= -h / 2.0 + 40.0) & (q[:, 1] <= h / 2.0 + 40.0)
    closer = inside & (t > 0) & (t < depth)
    depth[closer] = t[closer]
    normal[closer] = np.sign(-denom[closer])[:, None] * nz
    ok = np.isfinite(depth)
    cos_inc = -np.einsum("ij,ij->i", D, normal)
    ok &= cos_inc > np.cos(np.radians(scanner.max_incidence_deg))
    ok &= (depth * D[:, 2] >= scanner.range_min_mm) & (depth * D[:, 2] <= scanner.range_max_mm)
    d = depth[ok]
    if rng is not None:
        sigma = scanner.noise_sigma_mm if noise_mm is None else noise_mm
        d = d + rng.normal(0.0, sigma, d.shape)
    return D[ok] * d[:, None], normal[ok]


@dataclass(frozen=True)
class HandEyeData:
    """Simulated hand-eye data: noisy ``T_C_T`` and ``T_S_P`` per pose, and the truth they come from."""

    T_C_T: np.ndarray
    T_S_P: np.ndarray
    T_T_S: np.ndarray
    T_C_P: np.ndarray
    tracker_sigma: tuple[float, float]
    #: (N, 6, 6) per reading, as the tracker driver reports it (translation mm then rotation rad, frame C)
    tracker_covariances: np.ndarray


def _perturb(T: np.ndarray, rng: np.random.Generator, sigma_mm: float, sigma_rad: float) -> np.ndarray:
    """Noise as the sim tracker makes it: rotation (rad) about T's origin in the outer frame, translation (mm)
    added in the outer frame."""
    out = from_rotvec(np.zeros(3), rng.normal(0.0, sigma_rad, 3)) @ T
    out[:3, 3] = T[:3, 3] + rng.normal(0.0, sigma_mm, 3)
    return out


def hand_eye_dataset(
    rng: np.random.Generator,
    views_T_P_S: list[np.ndarray],
    T_T_S: np.ndarray,
    T_C_P: np.ndarray,
    tracker: TrackerNoiseConfig,
    *,
    plate_sigma: tuple[float, float] = (0.005, float(np.radians(0.002))),
    plate_fit: Callable[[np.ndarray], np.ndarray] | None = None,
) -> HandEyeData:
    """Tracker and plate readings for scanner views ``T_P_S`` of a plate standing at ``T_C_P``.

    Tracker noise follows the config's distance model, in the camera frame as the sim tracker applies it.
    Plate poses get ``plate_sigma`` = (mm, rad) noise, or come from ``plate_fit(true T_S_P)`` (e.g. scan +
    sphere fit). ``tracker_sigma`` of the result is (mm, rad) of the last reading.
    """
    T_C_T, T_S_P, covs = [], [], []
    sig = (0.0, 0.0)
    for T_P_S in views_T_P_S:
        true_T_C_T = T_C_P @ T_P_S @ invert(T_T_S)
        sig = tracker.sigma(float(np.linalg.norm(true_T_C_T[:3, 3])))
        covs.append(np.diag(np.repeat(np.square(sig), 3)))
        T_C_T.append(_perturb(true_T_C_T, rng, *sig))
        true_T_S_P = invert(T_P_S)
        T_S_P.append(plate_fit(true_T_S_P) if plate_fit is not None else _perturb(true_T_S_P, rng, *plate_sigma))
    return HandEyeData(np.array(T_C_T), np.array(T_S_P), T_T_S, T_C_P, sig, np.array(covs))


def install_calibration_plate(world: SimWorld, cfg: CalibrationConfig) -> np.ndarray:
    """Put the plate into the sim world's scene at the measurement chassis' true pose times ``cfg.T_V2_P``.

    Returns the true ``T_F_P`` (mm). The part stays in the scene; scans then see both.
    """
    T_F_P = world.T_F_V2 @ cfg.T_V2_P.matrix()
    plate = plate_mesh(cfg)
    plate.transform(T_F_P)
    world.scene = make_scene(world.mesh + plate)
    world.T_F_P = T_F_P
    return T_F_P

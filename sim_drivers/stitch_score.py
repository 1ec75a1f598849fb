"""Ground-truth scores of a simulated job's stitch: per-scan pose errors and cloud-to-mesh distances (mm, deg); the
simulator's, as :mod:`tandemscan.sim_drivers.inspection_score` is of its inspection (the product never imports it)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from tandemscan.pipeline.geometry import frames as F


def pose_errors(estimates: list[np.ndarray], truths: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-scan (translation error mm, rotation error deg) of estimated vs true ``T_W_S``."""
    errs = [F.pose_error(e, t) for e, t in zip(estimates, truths, strict=True)]
    mm = np.array([e[0] for e in errs])
    deg = np.degrees([e[1] for e in errs])
    return mm, deg


SCORE_CHUNK = 1_000_000  # points placed and measured at a time by :func:`cloud_to_mesh_distances`


def cloud_to_mesh_distances(scene: o3d.t.geometry.RaycastingScene, points_mm: np.ndarray,
                            T_scene_points: np.ndarray | None = None) -> np.ndarray:
    """Unsigned distance (mm) of every point to the mesh in ``scene``, the points first placed in the scene's
    frame by ``T_scene_points`` (4x4, mm; None: they are in it). :data:`SCORE_CHUNK` points at a time, so a
    whole part's cloud of 18 M points is scored with no float64 copies of it."""
    out = np.empty(len(points_mm))
    for lo in range(0, len(points_mm), SCORE_CHUNK):
        chunk = points_mm[lo:lo + SCORE_CHUNK]
        if T_scene_points is not None:
            chunk = F.transform_points(T_scene_points, chunk)
        out[lo:lo + SCORE_CHUNK] = scene.compute_distance(o3d.core.Tensor(np.asarray(chunk, np.float32))).numpy()
    return out


def distance_stats(d_mm: np.ndarray) -> dict[str, float]:
    """RMS, P95 and max of distances (mm)."""
    if len(d_mm) == 0:
        return {"rms_mm": float("nan"), "p95_mm": float("nan"), "max_mm": float("nan")}
    return {
        "rms_mm": float(np.sqrt(np.mean(d_mm**2))),
        "p95_mm": float(np.percentile(d_mm, 95)),
        "max_mm": float(np.max(d_mm)),
    }

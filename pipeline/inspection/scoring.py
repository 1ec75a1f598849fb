"""Ground-truth scores of a simulated job: per-scan pose errors and cloud-to-mesh distances (mm, deg)."""

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


def cloud_to_mesh_distances(scene: o3d.t.geometry.RaycastingScene, points_mm: np.ndarray) -> np.ndarray:
    """Unsigned distance (mm) of every point to the mesh in ``scene`` (same frame as the points)."""
    if len(points_mm) == 0:
        return np.empty(0)
    q = o3d.core.Tensor(np.asarray(points_mm, np.float32))
    return scene.compute_distance(q).numpy().astype(float)


def distance_stats(d_mm: np.ndarray) -> dict[str, float]:
    """RMS, P95 and max of distances (mm)."""
    if len(d_mm) == 0:
        return {"rms_mm": float("nan"), "p95_mm": float("nan"), "max_mm": float("nan")}
    return {
        "rms_mm": float(np.sqrt(np.mean(d_mm**2))),
        "p95_mm": float(np.percentile(d_mm, 95)),
        "max_mm": float(np.max(d_mm)),
    }

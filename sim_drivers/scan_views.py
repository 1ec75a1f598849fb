"""The simulated scanner's captures of one spot of the part, without a plan or robots: scanner poses on a
grid over the spot, each at the sweet-spot distance along the surface normal and turned about it, for tests
and benchmarks of what a characteristic reads from the scanner's own noise and ray casting (frame F, mm)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from tandemscan.pipeline.geometry import frames as F
from tandemscan.sim_drivers.world import SimWorld


def views_over(world: SimWorld, centres_mm: Sequence[Sequence[float]], normal: Sequence[float],
               u_axis: Sequence[float], turns_deg: Sequence[float], rng: np.random.Generator) -> np.ndarray:
    """The points (F, mm) of one capture from each of ``centres_mm`` x ``turns_deg``: the scanner's z axis
    along ``-normal`` (the surface's outward normal there), its x along ``u_axis``, turned by each angle about
    the surface's ``v`` = normal x u (the view tilted across u: one wall of a recess seen at an angle)."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.asarray(u_axis, float) - (np.asarray(u_axis, float) @ n) * n
    u /= np.linalg.norm(u)
    facing = np.column_stack([u, np.cross(-n, u), -n])
    out = []
    for centre in centres_mm:
        for turn in turns_deg:
            R = F.from_rotvec([0.0, 0.0, 0.0], np.radians(turn) * np.cross(n, u))[:3, :3] @ facing
            T_F_S = F.make_transform(R, np.asarray(centre, float) - world.config.scanner.sweet_spot_mm * R[:, 2])
            out.append(F.transform_points(T_F_S, world.scanner_model.scan(world.scene, T_F_S, rng)[0]))
    return np.vstack(out)

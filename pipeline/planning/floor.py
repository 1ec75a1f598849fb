"""The floor under the part: where a scanner pose has room (docs/planning.md, "Coverage").

The part frame F has the floor at z = 0 (mm); a mesh that reaches below stands on the floor at its lowest
point. A surface point has room for a scanner pose when even the most upward view within the incidence limit
puts the scanner (at the sweet spot along the view) above the floor clearance: the underside of a part on
supports does, the underside of a part resting on the floor does not.
"""

from __future__ import annotations

import numpy as np

FLOOR_CLEARANCE_MM = 150.0  # the scanner body needs this much room above the floor


def floor_z_mm(lowest_z_mm: float) -> float:
    """The floor's height in F (mm) under a part whose lowest point is at ``lowest_z_mm``: z = 0, or that point
    where it reaches below (a part stands on the floor, never in it)."""
    return min(0.0, float(lowest_z_mm))


def no_pose_fits(points: np.ndarray, normals: np.ndarray, floor_z: float, sweet_spot_mm: float,
                 incidence_limit_rad: float) -> np.ndarray:
    """Per surface point (F, mm) with its outward unit normal: even the most upward view within the incidence
    limit puts the scanner under the floor clearance (``floor_z``: the floor's height, mm)."""
    elevation = np.arcsin(np.clip(np.asarray(normals)[:, 2], -1.0, 1.0))
    best = np.minimum(elevation + incidence_limit_rad, np.pi / 2)
    return np.asarray(points)[:, 2] + sweet_spot_mm * np.sin(best) < floor_z + FLOOR_CLEARANCE_MM

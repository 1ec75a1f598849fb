"""Where the measurement AGV really stands, from the tracker, and the joints that put the scanner where planned.

A chassis drifts (wheel slip, odometry scale), so after a drive it stands some centimetres from where the
plan put it, more than the scanner's depth window forgives. The tracker sees the target on the scanner, so the
chassis' pose in the world W follows from one reading and the arm's joints (Eq. 5:
``T_W_V2 = T_W_T inv(T_V2_B T_B_E T_E_T)``). With ``T_F_W``, the world's place in the plan's frame F (the
odometry frame of the job's start, which is the part frame), the chassis' pose in F is ``T_F_W T_W_V2``, and
the arm's inverse kinematics is solved again for the planned scanner pose ``T_F_S`` from there. Where that pose
is out of reach from where the AGV stands, a nearby view of the same surface point is tried (turned half
about the view, moved along it within the depth window, tilted a few degrees), nearest first.

All mm, rad, 4x4 float64; the mounts are those the job stitches with (:class:`Installation`).
"""

from __future__ import annotations

import numpy as np
from tandemscan.config.models import ArmConfig, ScannerConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics, arm_base_on_column
from tandemscan.pipeline.planning.ik import default_ik
from tandemscan.pipeline.stitching.installation import Installation

_STANDOFF_STEPS_MM = (20.0, 40.0)  # well inside the 384-520 mm window around the 442 mm sweet spot
_TILT_STEPS_DEG = (5.0, 10.0)


def nearby_views(T_F_S: np.ndarray, sweet_spot_mm: float) -> list[tuple[str, np.ndarray]]:
    """Scanner poses looking at the same surface point as ``T_F_S`` (its sweet spot), each with what changed,
    nearest first: a half turn about the view (the same footprint), then per step the view moved along itself
    (closer, farther) and tilted about the point (about S x and y, both ways)."""
    T_F_S = np.asarray(T_F_S, float)
    out = [("turned half about the view", T_F_S @ F.from_rotvec(np.zeros(3), [0.0, 0.0, np.pi]))]
    to_point = F.from_rotvec([0.0, 0.0, sweet_spot_mm], np.zeros(3))
    for d, a in zip(_STANDOFF_STEPS_MM, _TILT_STEPS_DEG, strict=True):
        for sign in (1.0, -1.0):
            out.append((f"standoff {-sign * d:+.0f} mm", T_F_S @ F.from_rotvec([0.0, 0.0, sign * d], np.zeros(3))))
        for axis, sign in ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)):
            rot = np.zeros(3)
            rot[axis] = sign * np.radians(a)
            tilt = to_point @ F.from_rotvec(np.zeros(3), rot) @ F.invert(to_point)
            out.append((f"tilted {sign * a:+.0f} deg about S {'xy'[axis]}", T_F_S @ tilt))
    return out


class Relocaliser:
    """Eq. 5 and the re-solved arm IK for one cell's arm, scanner and mounts."""

    def __init__(self, arm: ArmConfig, scanner: ScannerConfig, installation: Installation):
        self.installation = installation
        self.kinematics = ArmKinematics(arm)
        self.ik = default_ik(arm)
        self.sweet_spot_mm = scanner.sweet_spot_mm

    def agv_in_world(self, T_W_T: np.ndarray, joints_rad: np.ndarray, lift_mm: float = 0.0) -> np.ndarray:
        """``T_W_V2`` of the measurement chassis from the target's world pose, the arm's joints and the lifting
        column's height (mm; 0 without a column) (Eq. 5)."""
        inst = self.installation
        return F.measurement_agv_in_world(T_W_T, arm_base_on_column(inst.T_V2_B, lift_mm),
                                          self.kinematics.forward(np.asarray(joints_rad, float)), inst.T_E_T)

    def joints_for(self, T_F_V2: np.ndarray, T_F_S: np.ndarray, seed_rad: np.ndarray,
                   lift_mm: float = 0.0) -> np.ndarray | None:
        """Joints (rad, inside the limits, nearest ``seed_rad``) putting the scanner at ``T_F_S`` with the
        chassis at ``T_F_V2`` and the column at ``lift_mm``; None when that pose is out of the arm's reach there."""
        inst = self.installation
        T_B_E = F.compose(F.invert(T_F_V2 @ arm_base_on_column(inst.T_V2_B, lift_mm)), T_F_S, F.invert(inst.T_E_S))
        q = self.ik(T_B_E, np.asarray(seed_rad, float))
        return None if q is None else np.asarray(q, float)

    def resolve(self, T_F_V2: np.ndarray, T_F_S: np.ndarray, seed_rad: np.ndarray,
                lift_mm: float = 0.0) -> tuple[np.ndarray | None, str]:
        """Joints for the planned scanner pose ``T_F_S`` from ``T_F_V2`` (column at ``lift_mm``) or else for the
        nearest reachable of :func:`nearby_views`, and what was changed ("" for the planned pose); (None, "")
        when none is reachable."""
        q = self.joints_for(T_F_V2, T_F_S, seed_rad, lift_mm)
        if q is not None:
            return q, ""
        for what, T in nearby_views(T_F_S, self.sweet_spot_mm):
            q = self.joints_for(T_F_V2, T, seed_rad, lift_mm)
            if q is not None:
                return q, what
        return None, ""

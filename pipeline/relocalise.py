"""Where the measurement AGV really stands, from the tracker, and the joints that put the scanner where planned.

A chassis drifts (wheel slip, odometry scale), so after a drive it stands some centimetres from where the
plan put it, more than the scanner's depth window forgives. The tracker sees the target on the scanner, so the
chassis' pose in the world W follows from one reading and the arm's joints (Eq. 5:
``T_W_V2 = T_W_T inv(T_V2_B T_B_E T_E_T)``). With ``T_F_W``, the world's place in the plan's frame F (the
odometry frame of the job's start, which is the part frame), the chassis' pose in F is ``T_F_W T_W_V2``, and
the arm's inverse kinematics is solved again for the planned scanner pose ``T_F_S`` from there.

All mm, rad, 4x4 float64; the mounts are those the job stitches with (:class:`Installation`).
"""

from __future__ import annotations

import numpy as np
from tandemscan.config.models import ArmConfig
from tandemscan.pipeline import frames as F
from tandemscan.pipeline.installation import Installation
from tandemscan.pipeline.kinematics import ArmKinematics
from tandemscan.pipeline.planning.ik import default_ik


class Relocaliser:
    """Eq. 5 and the re-solved arm IK for one cell's arm and mounts."""

    def __init__(self, arm: ArmConfig, installation: Installation):
        self.installation = installation
        self.kinematics = ArmKinematics(arm)
        self.ik = default_ik(arm)

    def agv_in_world(self, T_W_T: np.ndarray, joints_rad: np.ndarray) -> np.ndarray:
        """``T_W_V2`` of the measurement chassis from the target's world pose and the arm's joints (Eq. 5)."""
        inst = self.installation
        return F.measurement_agv_in_world(T_W_T, inst.T_V2_B, self.kinematics.forward(np.asarray(joints_rad, float)),
                                          inst.T_E_T)

    def joints_for(self, T_F_V2: np.ndarray, T_F_S: np.ndarray, seed_rad: np.ndarray) -> np.ndarray | None:
        """Joints (rad, inside the limits, nearest ``seed_rad``) putting the scanner at ``T_F_S`` with the
        chassis at ``T_F_V2``; None when that pose is out of the arm's reach from there."""
        inst = self.installation
        T_B_E = F.compose(F.invert(T_F_V2 @ inst.T_V2_B), T_F_S, F.invert(inst.T_E_S))
        q = self.ik(T_B_E, np.asarray(seed_rad, float))
        return None if q is None else np.asarray(q, float)

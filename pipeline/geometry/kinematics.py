"""Forward and inverse kinematics of a six-axis arm from standard DH parameters (mm, rad).

``T_B_E`` is the flange E in the arm base B. Each link: ``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from tandemscan.config.models import ArmConfig

# Weight of orientation against position in the IK residual: 1 rad counts as this many mm.
_ROTATION_WEIGHT_MM = 500.0


class ArmKinematics:
    """Kinematics and joint limits of the configured arm (JAKA Zu 7 by default)."""

    def __init__(self, arm: ArmConfig):
        self.d = np.array(arm.dh_d_mm, float)
        self.a = np.array(arm.dh_a_mm, float)
        self.alpha = np.array(arm.dh_alpha_rad, float)
        self.q_min = np.radians(arm.joint_min_deg)
        self.q_max = np.radians(arm.joint_max_deg)

    def forward(self, q_rad: np.ndarray) -> np.ndarray:
        """``T_B_E`` (mm) for joint angles ``q_rad`` (6,)."""
        T = np.eye(4)
        for theta, d, a, al in zip(np.asarray(q_rad, float), self.d, self.a, self.alpha, strict=True):
            ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(al), np.sin(al)
            T = T @ np.array(
                [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]]
            )
        return T

    def forward_many(self, q_rad: np.ndarray) -> np.ndarray:
        """``(M, 4, 4)`` flange poses ``T_B_E`` (mm) for ``(M, 6)`` joint angles (rad), vectorised."""
        q = np.asarray(q_rad, float).reshape(-1, 6)
        T = np.broadcast_to(np.eye(4), (len(q), 4, 4))
        ca, sa = np.cos(self.alpha), np.sin(self.alpha)
        for j in range(6):
            ct, st = np.cos(q[:, j]), np.sin(q[:, j])
            z, o = np.zeros_like(ct), np.ones_like(ct)
            A = np.stack([np.stack([ct, -st * ca[j], st * sa[j], self.a[j] * ct], -1),
                          np.stack([st, ct * ca[j], -ct * sa[j], self.a[j] * st], -1),
                          np.stack([z, z + sa[j], z + ca[j], z + self.d[j]], -1), np.stack([z, z, z, o], -1)], axis=-2)
            T = T @ A
        return T

    def within_limits(self, q_rad: np.ndarray) -> bool:
        """True when every joint is inside its limits."""
        q = np.asarray(q_rad, float)
        return bool(np.all(q >= self.q_min - 1e-9) and np.all(q <= self.q_max + 1e-9))

    def inverse(
        self,
        T_B_E: np.ndarray,
        seed_rad: np.ndarray | None = None,
        tol_mm: float = 0.01,
        tol_rad: float = 1e-5,
        restarts: int = 16,
    ) -> np.ndarray | None:
        """Joint angles (rad) reaching ``T_B_E`` within the limits, nearest the seed; None if unreachable.

        Numerical (bounded least squares), started from the seed and then from ``restarts`` seeded
        random configurations; the solution closest to the seed in joint space wins.
        """
        target = np.asarray(T_B_E, float)
        R_target_inv = target[:3, :3].T
        seed = np.zeros(6) if seed_rad is None else np.clip(np.asarray(seed_rad, float), self.q_min, self.q_max)

        def residual(q: np.ndarray) -> np.ndarray:
            T = self.forward(q)
            rot = Rotation.from_matrix(R_target_inv @ T[:3, :3]).as_rotvec()
            return np.r_[T[:3, 3] - target[:3, 3], _ROTATION_WEIGHT_MM * rot]

        rng = np.random.default_rng(0)
        starts = [seed] + [rng.uniform(np.maximum(self.q_min, -np.pi), np.minimum(self.q_max, np.pi))
                           for _ in range(restarts)]
        best = None
        for start in starts:
            sol = least_squares(residual, start, bounds=(self.q_min, self.q_max), xtol=1e-12, ftol=1e-12)
            r = residual(sol.x)
            if np.linalg.norm(r[:3]) <= tol_mm and np.linalg.norm(r[3:]) / _ROTATION_WEIGHT_MM <= tol_rad:
                if best is None or np.linalg.norm(sol.x - seed) < np.linalg.norm(best - seed):
                    best = sol.x
                if best is sol.x and np.linalg.norm(sol.x - seed) < 1.0:
                    break
        return best


def arm_base_on_column(T_V2_B: np.ndarray, height_mm: float) -> np.ndarray:
    """``T_V2_B`` of an arm on a lifting column raised ``height_mm`` (mm): the mount moved up the chassis z."""
    T = np.array(T_V2_B, float)
    T[2, 3] += height_mm
    return T

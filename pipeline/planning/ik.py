"""Closed-form inverse kinematics for six-axis arms whose joints 2-4 are parallel (UR-style DH, JAKA Zu).

The planner checks thousands of scanner poses, so it needs an IK that answers in well under a millisecond.
With standard DH ``d = (d1, 0, 0, d4, d5, d6)``, ``a = (0, a2, a3, 0, 0, 0)``,
``alpha = (pi/2, 0, 0, pi/2, -pi/2, 0)``, the flange orientation seen from frame 1 is
``Rz(q2 + q3 + q4) Ry(-q5) Rz(q6)`` (a z-y-z Euler triple), the wrist point fixes ``q1`` and a planar two-link
problem gives ``q2, q3``. Up to eight solutions; each is checked with ``ArmKinematics.forward`` and moved
into the joint limits by whole turns, and the one nearest the seed is returned.
"""

from __future__ import annotations

import numpy as np
from tandemscan.config.models import ArmConfig
from tandemscan.pipeline.geometry.kinematics import ArmKinematics

_ALPHA_PATTERN = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])


class AnalyticIK:
    """Callable ``(T_B_E, seed_rad) -> q_rad | None`` with the same contract as ``ArmKinematics.inverse``."""

    def __init__(self, arm: ArmConfig, tol_mm: float = 0.01, tol_rad: float = 1e-5):
        self.kin = ArmKinematics(arm)
        k = self.kin
        if not (np.allclose(k.alpha, _ALPHA_PATTERN) and np.allclose(k.a[[0, 3, 4, 5]], 0)
                and np.allclose(k.d[[1, 2]], 0)):
            raise ValueError("closed-form IK needs UR-style DH parameters (joints 2-4 parallel)")
        self.tol_mm, self.tol_rad = tol_mm, tol_rad

    def maybe_reachable(self, T_B_E: np.ndarray) -> np.ndarray:
        """Necessary condition, vectorised over ``(N, 4, 4)``: the wrist point lies inside the arm's shell.

        The wrist point ``p05 = p - d6 z`` sits at ``p13 + d4 z1 + d5 z4`` from the shoulder with ``p13, z4``
        orthogonal to ``z1`` and ``|p13| <= a2 + a3``; poses failing this have no solution, so IK can skip them.
        """
        d1, d4, d5, d6 = self.kin.d[0], self.kin.d[3], self.kin.d[4], self.kin.d[5]
        a2, a3 = self.kin.a[1], self.kin.a[2]
        T = np.asarray(T_B_E, float).reshape(-1, 4, 4)
        p05 = T[:, :3, 3] - d6 * T[:, :3, 2]
        p05[:, 2] -= d1
        far = np.sum(p05**2, axis=1) <= (abs(a2) + abs(a3) + abs(d5)) ** 2 + d4**2 + 1e-6
        return far & (np.hypot(p05[:, 0], p05[:, 1]) >= abs(d4) - 1e-9)

    def solutions(self, T_B_E: np.ndarray) -> list[np.ndarray]:
        """Every closed-form solution (rad, not yet moved into the limits, not yet verified)."""
        q = self.solution_array(np.asarray(T_B_E, float)[None])[0]
        return list(q[~np.isnan(q).any(axis=1)])

    def solution_array(self, T_B_E: np.ndarray) -> np.ndarray:
        """The closed-form solutions of ``(N, 4, 4)`` flange poses as ``(N, 8, 6)`` joint angles (rad, not yet
        moved into the limits, not yet verified): branches shoulder x wrist x elbow, NaN rows where a branch
        has no solution."""
        d1, d4, d5, d6 = self.kin.d[0], self.kin.d[3], self.kin.d[4], self.kin.d[5]
        a2, a3 = self.kin.a[1], self.kin.a[2]
        T = np.asarray(T_B_E, float).reshape(-1, 4, 4)
        n = len(T)
        p05 = T[:, :3, 3] - d6 * T[:, :3, 2]
        r = np.hypot(p05[:, 0], p05[:, 1])
        shell = (r >= abs(d4)) & (r >= 1e-9)
        phi = np.arctan2(p05[:, 1], p05[:, 0])
        s = np.arcsin(np.clip(d4 / np.where(shell, r, 1.0), -1.0, 1.0))
        q1 = np.stack([phi + s, phi + np.pi - s], axis=1)  # (N, 2)
        c1, s1 = np.cos(q1), np.sin(q1)
        zero, one = np.zeros_like(c1), np.ones_like(c1)
        # frame 1: Rz(q1) Tz(d1) Rx(pi/2)
        R01 = np.stack([np.stack([c1, zero, s1], -1), np.stack([s1, zero, -c1], -1), np.stack([zero, one, zero], -1)],
                       axis=-2)  # (N, 2, 3, 3)
        R16 = np.swapaxes(R01, -1, -2) @ T[:, None, :3, :3]
        p16 = np.einsum("nkji,nj->nki", R01, T[:, :3, 3] - np.array([0.0, 0.0, d1]))
        R16, p16 = R16[:, :, None], p16[:, :, None]  # (N, 2, 1, 3, 3), (N, 2, 1, 3): a wrist axis next
        cb = np.clip(R16[..., 2, 2], -1.0, 1.0)
        beta = np.array([1.0, -1.0]) * np.arccos(cb)  # (N, 2, 2)
        sb = np.sin(beta)
        singular = np.abs(sb) < 1e-9  # wrist singular: q4 and q6 share one rotation; put it all on q6
        sb_safe = np.where(singular, 1.0, sb)
        flip = np.where(cb > 0, 1.0, -1.0)
        q234 = np.where(singular, 0.0, np.arctan2(R16[..., 1, 2] / sb_safe, R16[..., 0, 2] / sb_safe))
        q6 = np.where(singular, np.arctan2(flip * R16[..., 1, 0], flip * R16[..., 0, 0]),
                      np.arctan2(R16[..., 2, 1] / sb_safe, -R16[..., 2, 0] / sb_safe))
        z4 = np.stack([np.sin(q234), -np.cos(q234), np.zeros_like(q234)], axis=-1)
        p13 = p16 - d4 * np.array([0.0, 0.0, 1.0]) - d5 * z4 - d6 * R16[..., :, 2]
        x, y = p13[..., 0], p13[..., 1]
        c3 = (x * x + y * y - a2 * a2 - a3 * a3) / (2 * a2 * a3)
        ok = shell[:, None, None] & (np.abs(c3) <= 1.0 + 1e-9)
        q3 = np.array([1.0, -1.0]) * np.arccos(np.clip(c3, -1.0, 1.0))[..., None]  # (N, 2, 2, 2): elbow last
        q2 = np.arctan2(y, x)[..., None] - np.arctan2(a3 * np.sin(q3), a2 + a3 * np.cos(q3))
        q4 = q234[..., None] - q2 - q3
        full = lambda v: np.broadcast_to(v[..., None], q3.shape)  # noqa: E731 - one branch value per elbow
        q = np.stack([full(np.broadcast_to(q1[:, :, None], beta.shape)), q2, q3, q4, full(-beta), full(q6)], axis=-1)
        q[~np.broadcast_to(ok[..., None], q3.shape)] = np.nan
        return q.reshape(n, 8, 6)

    def reachable(self, T_B_E: np.ndarray) -> np.ndarray:
        """``(N,)`` whether each of ``(N, 4, 4)`` flange poses has a joint solution within the limits (what
        ``self(T, seed) is not None`` answers, for many poses at once; no seed is needed to say whether)."""
        T = np.asarray(T_B_E, float).reshape(-1, 4, 4)
        q = self.solution_array(T)  # (N, 8, 6)
        turn = 2 * np.pi
        fits = np.all(np.ceil((self.kin.q_min - 1e-9 - q) / turn) <= np.floor((self.kin.q_max + 1e-9 - q) / turn),
                      axis=2)  # some whole-turn shift puts every joint inside its limits (False for NaN)
        Tq = self.kin.forward_many(np.nan_to_num(q.reshape(-1, 6))).reshape(len(T), 8, 4, 4)
        position = np.linalg.norm(Tq[..., :3, 3] - T[:, None, :3, 3], axis=-1) <= self.tol_mm
        c = np.clip((np.einsum("nkij,nij->nk", Tq[..., :3, :3], T[:, :3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        return np.any(fits & position & (np.arccos(c) <= self.tol_rad), axis=1)

    def _into_limits(self, q: np.ndarray, seed: np.ndarray) -> np.ndarray:
        """Solutions ``(N, 6)`` moved by whole turns into the limits, nearest the seed; NaN rows cannot fit."""
        q = np.atleast_2d(q)
        base = q + 2 * np.pi * np.round((seed - q) / (2 * np.pi))
        options = base[:, :, None] + 2 * np.pi * np.array([-1.0, 0.0, 1.0])  # (N, 6, 3)
        inside = (options >= self.kin.q_min[None, :, None] - 1e-9) & (options <= self.kin.q_max[None, :, None] + 1e-9)
        dist = np.where(inside, np.abs(options - seed[None, :, None]), np.inf)
        pick = np.take_along_axis(options, np.argmin(dist, axis=2)[:, :, None], axis=2)[:, :, 0]
        pick[~inside.any(axis=2).all(axis=1)] = np.nan
        return pick

    def __call__(self, T_B_E: np.ndarray, seed_rad: np.ndarray | None = None) -> np.ndarray | None:
        """Joint angles (rad) reaching ``T_B_E`` within the limits, nearest the seed; None if unreachable."""
        T = np.asarray(T_B_E, float)
        seed = np.zeros(6) if seed_rad is None else np.asarray(seed_rad, float)
        sols = self.solutions(T)
        if not sols:
            return None
        qs = self._into_limits(np.array(sols), seed)
        qs = qs[~np.isnan(qs).any(axis=1)]
        for q in qs[np.argsort(np.max(np.abs(qs - seed), axis=1))]:  # nearest first; check until one holds
            F_ = self.kin.forward(q)
            if np.linalg.norm(F_[:3, 3] - T[:3, 3]) > self.tol_mm:
                continue
            c = np.clip((np.trace(F_[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
            if np.arccos(c) <= self.tol_rad:
                return q
        return None


def default_ik(arm: ArmConfig):
    """``(T_B_E, seed_rad) -> q_rad | None``: the closed-form IK where the arm's DH allows it, else the numerical
    ``ArmKinematics.inverse``."""
    try:
        return AnalyticIK(arm)
    except ValueError:
        return ArmKinematics(arm).inverse

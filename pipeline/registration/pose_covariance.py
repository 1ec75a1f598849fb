"""The joint covariance of a job's scan pose errors, as the per-point uncertainty needs it (docs/verdict.md,
"Per-point uncertainty").

A scan's pose error is a small world motion ``e_i`` about its origin ``o_i`` (W axes; t mm, then rotation vector
rad), as in the joint refinement's model (``joint`` module doc): ``e = A theta`` with the unknowns ``theta`` (each
scan's tracker reading, each coordinate transfer and, where estimated, the shared scanner mount ``T_T_S``) of
covariance ``C``: the joint refinement's posterior where it ran, else the tracker chain's prior. The scans' errors
are correlated (a transfer moves every scan of its station, the mount every scan), so the whole ``A C A^T``
is kept, as a factor ``G`` with ``G G^T = A C A^T``; ``installation_columns`` names the unknowns of the mount, so
that its share can be told apart in an uncertainty budget.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse


@dataclass(frozen=True)
class PoseCovariance:
    """``e = A theta``, ``theta`` of covariance ``theta_covariance``, for the scans ``scan_ids`` (indices into the
    job's scans) whose origins in W are ``origins_mm`` (n, 3); ``A`` is (6n, m), kept sparse (CSR; a dense one
    given is converted: a scan's row uses a few of the thousands of columns). ``source`` says where ``C``
    came from ("joint refinement posterior" or "tracker chain prior"); ``installation_columns``: the columns of
    ``theta`` that are the mount's (empty: the mount is taken as known, or its error is not modelled)."""

    scan_ids: np.ndarray = field(repr=False)
    origins_mm: np.ndarray = field(repr=False)
    A: np.ndarray = field(repr=False)
    theta_covariance: np.ndarray = field(repr=False)
    source: str
    installation_columns: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not sparse.isspmatrix_csr(self.A):
            object.__setattr__(self, "A", sparse.csr_matrix(self.A))
        n, m = len(self.scan_ids), self.theta_covariance.shape[0]
        if self.A.shape != (6 * n, m) or self.origins_mm.shape != (n, 3) or self.theta_covariance.shape != (m, m):
            raise ValueError(f"pose covariance: A {self.A.shape}, origins {self.origins_mm.shape} and C "
                             f"{self.theta_covariance.shape} do not fit {n} scans")

    def _columns(self, part: str) -> np.ndarray:
        """Which columns of ``theta`` are ``part``'s (bool, m): "all", the mount's ("installation") or the rest
        ("scan_poses")."""
        mount = np.isin(np.arange(self.A.shape[1]), self.installation_columns)
        return {"all": np.ones_like(mount), "installation": mount, "scan_poses": ~mount}[part]

    def factor(self, part: str = "all") -> np.ndarray:
        """(6n, r) ``G`` with ``G G^T`` the covariance of ``e`` (``part`` "all"), of the mount's share alone
        ("installation") or of the readings' and transfers' alone ("scan_poses"); cross terms of the parts are in
        "all" only."""
        keep = self._columns(part)
        if not keep.any():
            return np.zeros((self.A.shape[0], 0))
        C = self.theta_covariance[np.ix_(keep, keep)]
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        w = np.clip(w, 0.0, None)
        big = w > 1e-12 * max(float(w.max()), 1e-300)
        return np.asarray(self.A[:, np.flatnonzero(keep)] @ (V[:, big] * np.sqrt(w[big])))

    def covariance(self, part: str = "all") -> np.ndarray:
        """(6n, 6n) covariance of ``e`` from ``part``'s unknowns, as :meth:`factor` splits them: ``A C A^T`` of
        those columns, formed through ``A``'s sparsity (a scan's error depends on its reading, its station's
        transfers and the mount: a few columns of the thousands), so it costs milliseconds where the factor's
        eigendecomposition costs seconds. Its ``C`` block is taken as positive semi-definite (a posterior, a
        prior); :meth:`factor` clips what rounding makes negative."""
        keep = self._columns(part)
        if not keep.any():
            return np.zeros((self.A.shape[0], self.A.shape[0]))
        C = self.theta_covariance[np.ix_(keep, keep)]
        A = self.A[:, np.flatnonzero(keep)]
        AC = np.asarray(A @ (0.5 * (C + C.T)))  # (6n, m)
        return np.asarray((A @ AC.T).T)

    def with_installation_at_prior(self) -> PoseCovariance:
        """The same with the mount's unknowns at their prior, uncorrelated with the rest: the joint refinement
        whitens them by the prior's Cholesky factor (``joint`` module doc), so their prior covariance is the
        identity. A job's own estimate of the mount is not counted on (on nominal mounts the default band's
        cloud stays 0.65 mm RMS from the part where that posterior says 0.05 mm)."""
        if not self.installation_columns:
            return self
        C = self.theta_covariance.copy()
        m = np.asarray(self.installation_columns)
        C[m, :] = 0.0
        C[:, m] = 0.0
        C[np.ix_(m, m)] = np.eye(len(m))
        return PoseCovariance(self.scan_ids, self.origins_mm, self.A, C, self.source, self.installation_columns)

    def full(self) -> np.ndarray:
        """(6n, 6n) covariance of the stacked ``e``."""
        return np.asarray((self.A @ (self.A @ self.theta_covariance).T).T)

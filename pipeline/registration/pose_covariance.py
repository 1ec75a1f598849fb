"""The joint covariance of a job's scan pose errors, as the per-point uncertainty needs it (docs/verdict.md,
"Per-point uncertainty").

A scan's pose error is a small world motion ``e_i`` about its origin ``o_i`` (W axes; t mm, then rotation vector
rad), as in the joint refinement's model (``joint`` module doc): ``e = A theta`` with the unknowns ``theta`` (each
scan's tracker reading, each coordinate transfer and, where estimated, the shared scanner mount ``T_T_S``) of
covariance ``C = H^-1 I H^-1``: ``H`` the normal matrix the estimate was solved with, ``I`` the information its
errors carry (the joint refinement's posterior; the tracker chain's prior where no correction ran: ``H = I`` its
information). ``H`` and ``I`` are kept sparse; ``C`` is dense (3.9 GB for the 3,700 scans of a 20 m car), so it is
never formed: what is asked of it are its blocks where scans share a point or a pair (``selected_inverse``) and
its products with a few vectors (sparse solves).

The scans' errors are correlated (a transfer moves every scan of its station, the mount every scan). Each scan's
own unknowns are one 6-column block of ``theta`` (its reading: the first block that only its rows use); the
others (transfers, mount) are shared, few, and their covariance with every scan's own block is kept whole, so
that ``Cov(e_i, e_l) = A_io C_il A_lo^T + X_i R_l^T + R_i X_l^T + R_i C_RR R_l^T`` (``A_io`` scan ``i``'s own block of
``A``, ``R_i`` its shared columns, ``X_i = A_io C_{i,R}``) needs of the own blocks only those of the pairs asked for
(:class:`ScanErrors`). ``installation_columns`` names the unknowns of the mount, so that its share can be told
apart in an uncertainty budget.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from tandemscan.pipeline.registration.selected_inverse import NODE, SelectedCovariance, selected_covariance

PARTS = ("all", "scan_poses", "installation")  # whose unknowns: all, the readings' and transfers', the mount's


@dataclass(frozen=True)
class ScanErrors:
    """The covariance of the scans' errors ``e`` as the blocks a point's variance needs: ``Cov(e_i, e_l) = own(i, l)
    + cross_i lever_l^T + lever_i cross_l^T + lever_i shared lever_l^T`` (module doc), ``own`` for the scan pairs
    ``keys`` only (sorted, ``i * n + l`` of scan rows, both orders); per part of :data:`PARTS` the shared columns'
    terms of that part's (``installation``: which shared columns are the mount's; the scans' own unknowns are
    "scan_poses")."""

    scans: int
    keys: np.ndarray = field(repr=False)
    own: np.ndarray = field(repr=False)           # (P, 6, 6) own(i, l)
    lever: np.ndarray = field(repr=False)         # (n, 6, r) each scan's shared columns of A
    cross: np.ndarray = field(repr=False)         # (n, 6, r) A_io C_{i,R}
    shared: np.ndarray = field(repr=False)        # (r, r) C_RR
    installation: np.ndarray = field(repr=False)  # (r,) bool

    def _own(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(..., 6, 6) ``own(a, b)`` of scan rows ``a``, ``b`` (broadcast together; each pair among ``keys``)."""
        a, b = np.broadcast_arrays(a, b)
        key = (a * self.scans + b).ravel()
        at = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
        if np.any(self.keys[at] != key):
            raise KeyError("scan errors: a pair of scans was not asked for")
        return self.own[at].reshape(*np.shape(a), NODE, NODE)

    def _keep(self, part: str) -> np.ndarray:
        """(r,) bool: the shared columns that are ``part``'s."""
        return {"all": np.ones_like(self.installation), "scan_poses": ~self.installation,
                "installation": self.installation}[part]

    def covariance(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(K, 6, 6) ``Cov(e_a, e_b)`` for scan rows ``a``, ``b`` ((K,) each); a part's share of a point's variance:
        :meth:`variances`."""
        a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
        La, Lb, Xa, Xb = self.lever[a], self.lever[b], self.cross[a], self.cross[b]
        return (self._own(a, b) + Xa @ Lb.transpose(0, 2, 1) + La @ Xb.transpose(0, 2, 1)
                + La @ self.shared @ Lb.transpose(0, 2, 1))

    def variances(self, rows: np.ndarray, g: np.ndarray) -> dict[str, np.ndarray]:
        """Per part (M,) ``Var(sum_k g_k . e_{rows_k})`` of each point: ``rows`` (M, K) scan rows, ``g`` (M, K, 6)
        gradients."""
        # einsum's own loops: products of a few dozen rows and columns, which BLAS would hand to its threads
        own_term = np.einsum("mkj,mkljq,mlq->m", g, self._own(rows[:, :, None], rows[:, None, :]), g)
        h = np.einsum("mkj,mkjr->mr", g, self.lever[rows])          # the shared columns' gradient, (M, r)
        w = np.einsum("mkj,mkjr->mr", g, self.cross[rows])
        out = {}
        for part in PARTS:
            hk = h * self._keep(part)
            out[part] = np.einsum("mr,rs,ms->m", hk, self.shared, hk)
            if part != "installation":        # the scans' own unknowns and their cross terms are not the mount's
                out[part] += own_term + 2.0 * np.einsum("mr,mr->m", w, hk)
        return out


@dataclass(frozen=True)
class _Layout:
    """How ``A`` uses ``theta``'s 6-column blocks (nodes): each scan's own node and that block of ``A`` (n, 6, 6),
    the shared nodes (sorted) and each scan's block of their columns (n, 6, r), and which of those columns are
    the mount's."""

    own: np.ndarray
    own_A: np.ndarray
    shared: np.ndarray
    shared_A: np.ndarray
    installation: np.ndarray  # (r,) bool


@dataclass(frozen=True)
class PoseCovariance:
    """``e = A theta``, ``theta`` of covariance ``H^-1 I H^-1`` (``normal`` ``H``, ``information`` ``I``, both
    (m, m) sparse), for the scans ``scan_ids`` (indices into the job's scans) whose origins in W are ``origins_mm``
    (n, 3); ``A`` is (6n, m), kept sparse (CSR; a dense one given is converted). ``source`` says where ``C`` came
    from ("joint refinement posterior" or "tracker chain prior"); ``installation_columns``: the columns of
    ``theta`` that are the mount's (empty: the mount is taken as known, or its error is not modelled);
    ``installation_at_prior``: those are taken at their prior, uncorrelated with the rest
    (:meth:`with_installation_at_prior`)."""

    scan_ids: np.ndarray = field(repr=False)
    origins_mm: np.ndarray = field(repr=False)
    A: sparse.csr_matrix = field(repr=False)
    normal: sparse.spmatrix = field(repr=False)
    information: sparse.spmatrix = field(repr=False)
    source: str
    installation_columns: tuple[int, ...] = ()
    installation_at_prior: bool = False

    def __post_init__(self) -> None:
        if not sparse.isspmatrix_csr(self.A):
            object.__setattr__(self, "A", sparse.csr_matrix(self.A))
        object.__setattr__(self, "normal", sparse.csc_matrix(self.normal))
        object.__setattr__(self, "information", sparse.csr_matrix(self.information))
        n, m = len(self.scan_ids), self.normal.shape[0]
        if (self.A.shape != (6 * n, m) or self.origins_mm.shape != (n, 3) or self.normal.shape != (m, m)
                or self.information.shape != (m, m) or m % NODE):
            raise ValueError(f"pose covariance: A {self.A.shape}, origins {self.origins_mm.shape}, H "
                             f"{self.normal.shape} and I {self.information.shape} do not fit {n} scans")

    @functools.cached_property
    def _layout(self) -> _Layout:
        """Each scan's own node: the first 6-column block of ``theta`` that only its rows use; the rest shared."""
        n, nodes = len(self.scan_ids), self.normal.shape[0] // NODE
        coo = self.A.tocoo()
        scan, node = coo.row // NODE, coo.col // NODE
        used = np.unique(scan * nodes + node)
        users = np.bincount(used % nodes, minlength=nodes)
        alone = users[used % nodes] == 1
        own = np.full(n, nodes)
        np.minimum.at(own, used[alone] // nodes, used[alone] % nodes)
        if np.any(own == nodes):
            raise ValueError("pose covariance: a scan has no unknowns of its own (a 6-column block only its rows use)")
        shared = np.setdiff1d(np.arange(nodes), own)
        mount = np.asarray(self.installation_columns, np.int64)
        if np.isin(mount // NODE, own).any():
            raise ValueError("pose covariance: the mount's columns are one scan's own")
        columns = (NODE * shared[:, None] + np.arange(NODE)).ravel()
        where = np.full(self.normal.shape[0], -1)
        where[columns] = np.arange(len(columns))
        own_A, shared_A = np.zeros((n, NODE, NODE)), np.zeros((n, NODE, len(columns)))
        mine = node == own[scan]
        own_A[scan[mine], coo.row[mine] % NODE, coo.col[mine] % NODE] = coo.data[mine]
        rest = ~mine
        shared_A[scan[rest], coo.row[rest] % NODE, where[coo.col[rest]]] = coo.data[rest]
        return _Layout(own, own_A, shared, shared_A, np.isin(columns, mount))

    def _selected(self, scan_pairs: np.ndarray) -> SelectedCovariance:
        """``C``'s blocks where ``H`` or ``I`` couple two nodes, of every own node with every shared one, of the
        shared ones, and of the own nodes of ``scan_pairs`` ((K, 2) scan rows)."""
        lay = self._layout
        own, shared = lay.own, lay.shared
        o, s = np.meshgrid(own, shared, indexing="ij")
        a, b = np.meshgrid(shared, shared, indexing="ij")
        pairs = np.r_[np.c_[own[scan_pairs[:, 0]], own[scan_pairs[:, 1]]], np.c_[o.ravel(), s.ravel()],
                      np.c_[a.ravel(), b.ravel()]]
        return selected_covariance(self.normal, self.information, pairs, shared)

    @functools.cached_property
    def _pattern_selected(self) -> SelectedCovariance:
        """:meth:`_selected` with no scan pairs beyond those ``H`` and ``I`` couple."""
        return self._selected(np.zeros((0, 2), np.int64))

    def _at_prior(self, C: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """``C`` over ``theta``'s ``columns`` with the mount's at their prior where :attr:`installation_at_prior`
        (zero with the rest, the identity among themselves: the joint refinement whitens them by the prior's
        Cholesky factor)."""
        if not self.installation_at_prior:
            return C
        mount = np.isin(columns, self.installation_columns)
        C = C.copy()
        C[mount, :] = 0.0
        C[:, mount] = 0.0
        C[mount, mount] = 1.0
        return C

    def theta_covariance(self, columns: np.ndarray) -> np.ndarray:
        """(k, k) ``C`` over ``theta``'s ``columns`` (each node among them coupled with the others in ``H`` or
        ``I``, or shared: a pair's, a scan's columns)."""
        columns = np.asarray(columns, np.int64)
        nodes, at = np.unique(columns // NODE, return_inverse=True)
        C = self._pattern_selected.dense(nodes)
        index = NODE * at.ravel() + columns % NODE
        return self._at_prior(C[np.ix_(index, index)], columns)

    def scan_errors(self, scan_pairs: np.ndarray) -> ScanErrors:
        """The covariance of the scans' errors (:class:`ScanErrors`) with the own blocks of ``scan_pairs`` ((K, 2)
        scan rows, any order; the diagonal ones are added)."""
        lay = self._layout
        n = len(self.scan_ids)
        pairs = np.asarray(scan_pairs, np.int64).reshape(-1, 2)
        keys = np.unique(np.r_[np.maximum(pairs[:, 0], pairs[:, 1]) * n + np.minimum(pairs[:, 0], pairs[:, 1]),
                               np.arange(n) * (n + 1)])
        hi, lo = keys // n, keys % n
        selected = self.__dict__.get("_pattern_selected")   # the pattern's blocks, where already formed
        if selected is None or not selected.holds(lay.own[hi], lay.own[lo]):
            selected = self._selected(np.c_[hi, lo])        # else an inversion with these pairs in it
        own = lay.own_A[hi] @ selected.pairs(lay.own[hi], lay.own[lo]) @ lay.own_A[lo].transpose(0, 2, 1)
        columns = (NODE * lay.shared[:, None] + np.arange(NODE)).ravel()
        r = len(columns)
        C_oR = selected.pairs(np.repeat(lay.own, len(lay.shared)), np.tile(lay.shared, n)).reshape(
            n, len(lay.shared), NODE, NODE).transpose(0, 2, 1, 3).reshape(n, NODE, r)
        if self.installation_at_prior:
            C_oR[:, :, lay.installation] = 0.0
        both = np.r_[keys, lo * n + hi]                       # each pair in both orders, transposed
        order = np.argsort(both, kind="stable")
        both, at = np.unique(both[order], return_index=True)
        blocks = np.concatenate([own, own.transpose(0, 2, 1)])[order[at]]
        return ScanErrors(n, both, blocks, lay.shared_A, lay.own_A @ C_oR,
                          self._at_prior(selected.dense(lay.shared), columns), lay.installation)

    def scan_covariances(self) -> np.ndarray:
        """(n, 6, 6) each scan's error covariance ``A_i C A_i^T``."""
        rows = np.arange(len(self.scan_ids))
        return self.scan_errors(np.zeros((0, 2), np.int64)).covariance(rows, rows)

    def times(self, X: np.ndarray) -> dict[str, np.ndarray]:
        """Per part of :data:`PARTS` (6n, k) the covariance of ``e`` from that part's unknowns times ``X`` (6n, k):
        ``A C A^T X`` over those columns, ``C`` applied as ``H^-1 (I (H^-1 Y))``: ``H`` scaled to a unit diagonal
        (millimetres and radians at one scale), factored once (sparse LU, symmetric pivoting) and each solve
        refined once by its residual."""
        s = 1.0 / np.sqrt(self.normal.diagonal())
        lu = splu(sparse.csc_matrix(self.normal.multiply(s[:, None]).multiply(s[None, :])),
                  permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

        def solve(Y: np.ndarray) -> np.ndarray:
            Z = s[:, None] * lu.solve(s[:, None] * Y)
            return Z + s[:, None] * lu.solve(s[:, None] * (Y - self.normal @ Z))

        mount = self._columns("installation")
        at_prior = mount if self.installation_at_prior else np.zeros_like(mount)
        AX = np.asarray(self.A.T @ X)
        Y = np.concatenate([AX * self._columns(part)[:, None] for part in PARTS], axis=1)   # every part at once
        Z = solve(np.asarray(self.information @ solve(np.where(at_prior[:, None], 0.0, Y))))
        Z[at_prior] = Y[at_prior]
        k = AX.shape[1]
        return {part: np.asarray(self.A @ (Z[:, i * k:(i + 1) * k] * self._columns(part)[:, None]))
                for i, part in enumerate(PARTS)}

    def _columns(self, part: str) -> np.ndarray:
        """Which columns of ``theta`` are ``part``'s (bool, m): "all", the mount's ("installation") or the rest
        ("scan_poses")."""
        mount = np.isin(np.arange(self.A.shape[1]), self.installation_columns)
        return {"all": np.ones_like(mount), "installation": mount, "scan_poses": ~mount}[part]

    def with_installation_at_prior(self) -> PoseCovariance:
        """The same with the mount's unknowns at their prior, uncorrelated with the rest: the joint refinement
        whitens them by the prior's Cholesky factor (``joint`` module doc), so their prior covariance is the
        identity. A job's own estimate of the mount is not counted on (on nominal mounts the default band's
        cloud stays 0.65 mm RMS from the part where that posterior says 0.05 mm)."""
        if not self.installation_columns or self.installation_at_prior:
            return self
        return PoseCovariance(self.scan_ids, self.origins_mm, self.A, self.normal, self.information, self.source,
                              self.installation_columns, True)

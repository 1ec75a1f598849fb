"""Selected blocks of a sandwich covariance ``C = H^-1 I H^-1`` from the sparse ``H`` and ``I``, never ``C`` whole
(docs/verdict.md, "Per-point uncertainty").

The joint refinement's estimate has that covariance (``joint._posterior``): ``H`` the normal matrix it
was solved with, ``I`` the information its errors carry. Both are sparse in 6x6 blocks ("nodes": a scan's
reading, a transfer, the mount; a block where two nodes share a pair's residuals or a scan's error model), ``C``
is dense: (6 x 3,700)^2 float64, 3.9 GB, for the 3,700 scans of a 20 m car. What the per-point uncertainty and
the joint's own checks read of it are the blocks of nodes that share a pair, a point or a scan, so only those
are formed, by a selected inversion:

- ``H = L D L^T`` block by block (``L`` unit lower, ``D`` the 6x6 pivots) in a fill-reducing order (minimum
  degree of the node graph, the ``last`` nodes that every scan uses at the end), on the node pattern of
  the filled graph, the requested pairs added to it as explicit zeros;
- the symmetric indefinite ``M = [[-I, H], [H, 0]]``, whose inverse is ``[[0, H^-1], [H^-1, C]]``, factored in
  the same order with 2 x 2 node pivots ``[[-I'_kk, D_k], [D_k, 0]]`` (``I'`` the Schur complement of ``I``
  under the same elimination, never singular as ``D_k`` is positive definite): its factor is
  ``[[L, Q], [0, L]]`` with ``Q_jk = (L_jk I'_kk - I'_jk) D_k^-1``;
- Takahashi's recurrence on that factor (Z = D^-1 L^-1 + (1 - L^T) Z, from the last node back), which gives
  ``M^-1`` on the filled pattern: ``S = H^-1`` and ``C`` there,
  ``S_Jk = -S_JJ L_Jk``, ``C_Jk = -(S_JJ Q_Jk + C_JJ L_Jk)``, ``S_kk = D_k^-1 - L_Jk^T S_Jk``,
  ``C_kk = D_k^-1 I'_kk D_k^-1 - Q_Jk^T S_Jk - L_Jk^T C_Jk`` (``J`` the nodes of column ``k`` of ``L``).

Cost: per node the dense products of its column's ``6|J|`` rows, about ``n |J|^2`` 6x6 blocks in all, linear
in the scans where the part is long; the same blocks as the dense ``H^-1 I H^-1`` to the rounding (a test).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu

NODE = 6  # unknowns a node: a rigid motion (t mm, rotation vector rad)


@dataclass(frozen=True)
class SelectedCovariance:
    """The 6x6 blocks of ``C`` on a set of node pairs (nodes numbered as ``H``'s 6-column blocks): ``keys`` sorted,
    ``hi * nodes + lo`` for the block ``C[hi, lo]`` (rows of node ``hi``, columns of node ``lo``, ``hi >= lo``)."""

    nodes: int
    keys: np.ndarray = field(repr=False)
    blocks: np.ndarray = field(repr=False)  # (P, 6, 6)

    def _find(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The places of the blocks ``(rows[k], cols[k])`` among ``keys`` and whether each is there."""
        key = np.maximum(rows, cols) * self.nodes + np.minimum(rows, cols)
        at = np.minimum(np.searchsorted(self.keys, key), max(len(self.keys) - 1, 0))
        return at, (self.keys[at] == key) if len(self.keys) else np.zeros(len(key), bool)

    def holds(self, rows: np.ndarray, cols: np.ndarray) -> bool:
        """Whether every block ``C[rows[k], cols[k]]`` is selected."""
        return bool(self._find(np.asarray(rows, np.int64), np.asarray(cols, np.int64))[1].all())

    def pairs(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(K, 6, 6) the blocks ``C[rows[k], cols[k]]`` (node indices); KeyError where one is not selected."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        at, found = self._find(rows, cols)
        if not found.all():
            k = int(np.flatnonzero(~found)[0])
            raise KeyError(f"selected covariance: block ({rows[k]}, {cols[k]}) was not selected")
        out = self.blocks[at]
        upper = rows < cols
        out[upper] = out[upper].transpose(0, 2, 1)
        return out

    def dense(self, nodes: np.ndarray) -> np.ndarray:
        """(6k, 6k) ``C`` over the ``nodes`` (k of them, in that order), every pair of them selected."""
        nodes = np.asarray(nodes, np.int64)
        r, c = np.meshgrid(nodes, nodes, indexing="ij")
        k = len(nodes)
        return self.pairs(r.ravel(), c.ravel()).reshape(k, k, NODE, NODE).transpose(0, 2, 1, 3).reshape(
            NODE * k, NODE * k)


@dataclass(frozen=True)
class _Pattern:
    """The filled node pattern of ``L`` in the elimination order: per column ``k`` its rows ``struct[k]`` (nodes
    after ``k``, ascending), its blocks at ``start[k]`` (the pivot) and ``start[k] + 1 ..`` (the rows), and the
    sorted keys ``row * nodes + column`` of every block with their positions."""

    order: np.ndarray  # elimination position -> node
    struct: list[np.ndarray]
    start: np.ndarray
    keys: np.ndarray
    positions: np.ndarray

    def at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Positions of the blocks ``(rows, cols)`` (elimination positions, ``rows >= cols``)."""
        n = len(self.order)
        return self.positions[np.searchsorted(self.keys, rows * n + cols)]


def _minimum_degree(graph: sparse.csr_matrix) -> np.ndarray:
    """A fill-reducing elimination order of the symmetric ``graph``'s nodes: SuperLU's multiple minimum degree on
    its pattern (a diagonally dominant matrix of it, factored without pivoting; ``perm_c`` places each node)."""
    if graph.shape[0] < 2:
        return np.arange(graph.shape[0])
    M = (graph + sparse.identity(graph.shape[0]) * (graph.sum(axis=1).max() + 1.0)).tocsc()
    lu = splu(M, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.argsort(lu.perm_c)


def _pattern(graph: sparse.csr_matrix, last: np.ndarray) -> _Pattern:
    """The elimination order (minimum degree of the nodes but ``last``, then ``last``) and the filled pattern of
    the symmetric node ``graph`` (N x N, its nonzeros the coupled pairs)."""
    n = graph.shape[0]
    rest = np.setdiff1d(np.arange(n), last)
    order = np.r_[rest[_minimum_degree(sparse.csr_matrix(graph[rest][:, rest]))], np.sort(last)]
    place = np.empty(n, np.int64)
    place[order] = np.arange(n)
    g = sparse.csr_matrix(graph)
    children: list[list[int]] = [[] for _ in range(n)]
    struct = []
    for k in range(n):
        adj = place[g.indices[g.indptr[order[k]]:g.indptr[order[k] + 1]]]
        rows = np.unique(np.concatenate([adj[adj > k], *[struct[c][1:] for c in children[k]]]).astype(np.int64))
        struct.append(rows)
        if len(rows):
            children[int(rows[0])].append(k)
    sizes = np.array([1 + len(s) for s in struct])
    start = np.r_[0, np.cumsum(sizes)[:-1]]
    cols = np.repeat(np.arange(n), sizes)
    rows = np.concatenate([np.r_[k, s] for k, s in enumerate(struct)]).astype(np.int64)
    keys = rows * n + cols
    sort = np.argsort(keys)
    return _Pattern(order, struct, start, keys[sort], sort)


def _blocks_of(M: sparse.spmatrix, pattern: _Pattern) -> np.ndarray:
    """The lower node blocks of the symmetric ``M`` (m x m) on the pattern, (P, 6, 6) (the pivots whole)."""
    coo = sparse.coo_matrix(M)
    n = len(pattern.order)
    place = np.empty(n, np.int64)
    place[pattern.order] = np.arange(n)
    r, c = place[coo.row // NODE], place[coo.col // NODE]
    keep = r >= c
    out = np.zeros((len(pattern.keys), NODE, NODE))
    np.add.at(out, (pattern.at(r[keep], c[keep]), coo.row[keep] % NODE, coo.col[keep] % NODE), coo.data[keep])
    return out


def _lower(pattern: _Pattern, J: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lower block pairs ``(a, b)`` (``a >= b``) of the positions ``J`` (ascending) and their blocks' places."""
    a, b = np.tril_indices(len(J))
    return a, b, pattern.at(J[a], J[b])


def _gather(blocks: np.ndarray, lower: tuple[np.ndarray, np.ndarray, np.ndarray], k: int) -> np.ndarray:
    """(6k, 6k) the symmetric matrix of ``blocks`` (their lower ones at ``lower``, :func:`_lower`, of k positions)."""
    a, b, at = lower
    G = np.empty((k, NODE, k, NODE))
    T = blocks[at]
    G[a, :, b, :] = T
    G[b, :, a, :] = T.transpose(0, 2, 1)
    return G.reshape(NODE * k, NODE * k)


def _lower_blocks(U: np.ndarray, lower: tuple[np.ndarray, np.ndarray, np.ndarray], k: int) -> np.ndarray:
    """The lower blocks (as :func:`_lower` lists them) of ``U + U^T`` (U: (6k, 6k))."""
    a, b, _ = lower
    U4 = U.reshape(k, NODE, k, NODE)
    return U4[a, :, b, :] + U4[b, :, a, :].transpose(0, 2, 1)


def _node_graph(H: sparse.spmatrix, I: sparse.spmatrix, pairs: np.ndarray) -> sparse.csr_matrix:  # noqa: E741
    """(N, N) the node pairs (symmetric, no diagonal) that ``H`` or ``I`` couple, and ``pairs`` ((K, 2) nodes)."""
    n = H.shape[0] // NODE
    coo = sparse.coo_matrix(abs(sparse.csr_matrix(H)) + abs(sparse.csr_matrix(I)))
    r, c = np.r_[coo.row // NODE, pairs[:, 0]], np.r_[coo.col // NODE, pairs[:, 1]]
    r, c = r[r != c], c[r != c]
    return sparse.csr_matrix((np.ones(2 * len(r)), (np.r_[r, c], np.r_[c, r])), shape=(n, n))


def _factor(Hb: np.ndarray, Ib: np.ndarray, pattern: _Pattern) -> tuple[np.ndarray, np.ndarray]:
    """``M = [[-I, H], [H, 0]]`` factored in place (module doc): ``L`` into ``Hb``'s and ``Q`` into ``Ib``'s column
    blocks; returns each node's ``D_k^-1`` and ``D_k^-1 I'_kk D_k^-1`` ((N, 6, 6) each)."""
    n = len(pattern.order)
    pivots_inv, own = np.empty((n, NODE, NODE)), np.empty((n, NODE, NODE))
    for k in range(n):
        J, p = pattern.struct[k], pattern.start[k]
        rows = slice(p + 1, p + 1 + len(J))
        D, Ikk = Hb[p], 0.5 * (Ib[p] + Ib[p].T)
        Dinv = np.linalg.inv(0.5 * (D + D.T))
        pivots_inv[k], own[k] = Dinv, Dinv @ Ikk @ Dinv
        if not len(J):
            continue
        lower = _lower(pattern, J)
        HJ, IJ = Hb[rows].reshape(-1, NODE), Ib[rows].reshape(-1, NODE)
        L = HJ @ Dinv
        LI = L @ Ikk
        Hb[lower[2]] -= _lower_blocks(0.5 * (L @ HJ.T), lower, len(J))      # H_JJ - L D L^T
        Ib[lower[2]] -= _lower_blocks(L @ (IJ - 0.5 * LI).T, lower, len(J))  # I_JJ - L I_kJ - I_Jk L^T + L I_kk L^T
        Hb[rows] = L.reshape(-1, NODE, NODE)
        Ib[rows] = ((LI - IJ) @ Dinv).reshape(-1, NODE, NODE)
    return pivots_inv, own


def _takahashi(S: np.ndarray, C: np.ndarray, pattern: _Pattern, pivots_inv: np.ndarray, own: np.ndarray) -> None:
    """Takahashi's recurrence from the last node back (module doc): ``S`` (holding ``L``) and ``C`` (holding ``Q``)
    become ``H^-1`` and ``C`` on the factor's blocks, in place."""
    for k in range(len(pattern.order) - 1, -1, -1):
        J, p = pattern.struct[k], pattern.start[k]
        rows = slice(p + 1, p + 1 + len(J))
        if len(J):
            lower = _lower(pattern, J)
            LQ = np.concatenate([S[rows].reshape(-1, NODE), C[rows].reshape(-1, NODE)], axis=1)
            L, Q = LQ[:, :NODE], LQ[:, NODE:]
            SLQ = _gather(S, lower, len(J)) @ LQ
            S_Jk = -SLQ[:, :NODE]
            C_Jk = -(SLQ[:, NODE:] + _gather(C, lower, len(J)) @ L)
            S_kk = pivots_inv[k] - L.T @ S_Jk
            C_kk = own[k] - Q.T @ S_Jk - L.T @ C_Jk
            S[rows], C[rows] = S_Jk.reshape(-1, NODE, NODE), C_Jk.reshape(-1, NODE, NODE)
        else:
            S_kk, C_kk = pivots_inv[k], own[k]
        S[p], C[p] = 0.5 * (S_kk + S_kk.T), 0.5 * (C_kk + C_kk.T)


def selected_covariance(H: sparse.spmatrix, I: sparse.spmatrix, pairs: np.ndarray,  # noqa: E741 (the math's I)
                        last: np.ndarray) -> SelectedCovariance:
    """The blocks of ``C = H^-1 I H^-1`` (``H`` positive definite, ``I`` symmetric; m x m, m = 6 N) on the node
    pairs where ``H`` or ``I`` couple two nodes, on ``pairs`` ((K, 2) node indices) and on what the elimination
    fills in between them (module doc); ``last``: nodes eliminated last (those most nodes are coupled to)."""
    m = H.shape[0]
    if m % NODE or H.shape != I.shape or H.shape != (m, m):
        raise ValueError(f"selected covariance: H {H.shape} and I {I.shape} are not square in {NODE}-blocks")
    n = m // NODE
    pattern = _pattern(_node_graph(H, I, np.asarray(pairs, np.int64).reshape(-1, 2)), np.asarray(last, np.int64))
    S, C = _blocks_of(H, pattern), _blocks_of(I, pattern)
    _takahashi(S, C, pattern, *_factor(S, C, pattern))
    hi, lo = pattern.order[pattern.keys // n], pattern.order[pattern.keys % n]   # the nodes' own numbering
    blocks = C[pattern.positions]
    swap = hi < lo
    blocks[swap] = blocks[swap].transpose(0, 2, 1)
    keys = np.maximum(hi, lo) * n + np.minimum(hi, lo)
    sort = np.argsort(keys)
    return SelectedCovariance(n, keys[sort], blocks[sort])

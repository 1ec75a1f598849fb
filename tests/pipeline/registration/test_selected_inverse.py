"""The selected blocks of ``C = H^-1 I H^-1`` (pipeline/registration/selected_inverse.py) against the dense
formula: on the pattern of ``H`` and ``I``, on pairs asked for beyond it, with nodes eliminated last."""

import numpy as np
import pytest
from scipy import sparse
from tandemscan.pipeline.registration.selected_inverse import selected_covariance


def coupled_chain(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(6(n+1))^2 ``H``, ``I``: ``n`` nodes in a chain (each with its two neighbours) and one node coupled to all
    (as the mount is to every scan), units mixed (mm and rad: diagonal scales 1 and 1e6); ``I`` of the same
    pattern, another weighting of the same rows (positive semi-definite)."""
    rng = np.random.default_rng(seed)
    m = 6 * (n + 1)
    scale = np.tile([1.0] * 3 + [1e3] * 3, n + 1)
    H, info = np.eye(m) * 0.1, np.eye(m) * 0.05
    links = [(k, k + 1) for k in range(n - 1)] + [(k, k + 2) for k in range(0, n - 2, 3)] + [(k, n) for k in range(n)]
    for a, b in links:
        idx = np.r_[6 * a:6 * a + 6, 6 * b:6 * b + 6]
        J = rng.standard_normal((20, 12)) * scale[idx]
        w = rng.uniform(0.2, 2.0, 20)
        H[np.ix_(idx, idx)] += J.T @ (w[:, None] * J)
        info[np.ix_(idx, idx)] += J.T @ (w[:, None] ** 2 * J)
    return H, info


@pytest.mark.parametrize("seed", [1, 2])
def test_selected_blocks_are_those_of_the_dense_sandwich(seed):
    n = 25
    H, info = coupled_chain(n, seed)
    H_inv = np.linalg.inv(H)
    C = H_inv @ info @ H_inv
    asked = np.array([[0, n - 1], [3, 17], [20, 2]])          # far apart in the chain: not in H's pattern
    sel = selected_covariance(sparse.csr_matrix(H), sparse.csr_matrix(info), asked, np.array([n]))
    nodes = n + 1
    hi, lo = sel.keys // nodes, sel.keys % nodes
    assert np.all(hi >= lo)
    want = C.reshape(nodes, 6, nodes, 6).transpose(0, 2, 1, 3)[hi, lo]
    sd = np.sqrt(np.diag(C)).reshape(nodes, 6)
    assert np.all(np.abs(sel.blocks - want) <= 1e-9 * sd[hi][:, :, None] * sd[lo][:, None, :])
    for a, b in np.r_[asked, [[k, n] for k in range(n)], [[k, k + 1] for k in range(n - 1)]]:
        block = sel.pairs(np.array([a]), np.array([b]))[0]
        assert np.all(np.abs(block - C[6 * a:6 * a + 6, 6 * b:6 * b + 6]) <= 1e-9 * np.outer(sd[a], sd[b]))
    first = np.arange(3)
    assert np.abs(sel.dense(first) - C[:18, :18]).max() <= 1e-9 * np.abs(C[:18, :18]).max()
    assert sel.holds(np.array([0]), np.array([n - 1])) and len(sel.keys) < nodes * (nodes + 1) // 2
    absent = next((a, b) for a in range(n) for b in range(a) if not sel.holds(np.array([a]), np.array([b])))
    with pytest.raises(KeyError, match="not selected"):
        sel.pairs(np.array([absent[0]]), np.array([absent[1]]))

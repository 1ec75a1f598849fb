"""Which way the CAD surface faces: the winding a deviation's sign is read from (docs/inspection-method.md,
"Alignment": sign on any mesh).

A customer's mesh may be open (a panel) and wound either way, or inconsistently from patch to patch. Before
deviations are signed, each connected patch of the mesh is wound consistently (neighbouring triangles
traverse their shared edge in opposite directions), then turned as a whole so that its normals point to the
measured side: outward for a closed patch (positive enclosed volume), toward the scanner for an open one,
from the measured points near it and where they were seen from (the job's scanner positions, or the cloud's
normals as a scanner writes them). A patch no measured point votes for keeps the file's majority winding.
Frame F, millimetres.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components
from tandemscan.pipeline.geometry.part import enclosed_volume_mm3, triangles_closed

log = logging.getLogger(__name__)

#: a patch is turned by the measured side only where this share of its voting points agree
CLEAR_MAJORITY = 0.6


@dataclass(frozen=True)
class CadOrientation:
    """How the CAD's triangles are wound for signing: ``reversed`` (T,) bool, the triangles taken against the
    file's winding; ``patches`` the connected patches of the mesh; ``by`` what decided ("closed volume",
    "scanner positions", "cloud normals", "the file": per patch, the strongest); ``note`` a warning for the
    report where the file's winding disagreed (empty where it did not); ``closed`` (T,) bool, the triangles of
    closed patches (whose outside is known from their volume, whatever the measured side)."""

    reversed: np.ndarray
    patches: int
    by: str
    note: str = ""
    closed: np.ndarray | None = None


def consistent_winding(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle of the (T, 3) vertex indices: whether to reverse it so that every patch is wound
    consistently with its first triangle, and the patch it belongs to (triangles linked through edges shared
    by exactly two). A non-orientable patch keeps the flips of a spanning tree."""
    t = np.asarray(triangles, np.int64)
    n_t = len(t)
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    owner = np.tile(np.arange(n_t), 3)
    key = np.minimum(directed[:, 0], directed[:, 1]) * (int(t.max()) + 1) + np.maximum(directed[:, 0], directed[:, 1])
    order = np.argsort(key, kind="stable")
    k = key[order]
    first = np.flatnonzero((k[:-1] == k[1:]) & np.r_[True, k[1:-1] != k[:-2]] & np.r_[k[2:] != k[1:-1], True])
    a, b = order[first], order[first + 1]  # the two uses of each edge shared by exactly two triangles
    same_way = directed[a, 0] == directed[b, 0]  # both traverse it the same way: one of them must turn
    graph = coo_matrix((np.ones(len(a)), (owner[a], owner[b])), shape=(n_t, n_t)).tocsr()
    graph = graph + graph.T
    patches, label = connected_components(graph, directed=False)
    parity = coo_matrix((same_way.astype(float) + 1.0, (owner[a], owner[b])), shape=(n_t, n_t)).tocsr()
    parity = parity + parity.T  # 1: consistent, 2: opposite
    flip = [False] * n_t
    roots = np.unique(label, return_index=True)[1]
    for root in roots:
        tree, pred = breadth_first_order(graph, int(root), directed=False, return_predecessors=True)
        tree = tree[1:]
        turns = (np.asarray(parity[tree, pred[tree]]).ravel() == 2.0).tolist()
        for node, up, turn in zip(tree.tolist(), pred[tree].tolist(), turns, strict=True):
            flip[node] = flip[up] ^ turn
    return np.array(flip, bool), label


def _normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    v = vertices[triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def orient(vertices_mm: np.ndarray, triangles: np.ndarray, closest_triangles: np.ndarray | None = None,
           toward: np.ndarray | None = None, by: str = "the measured side") -> CadOrientation:
    """The winding to sign deviations by. ``closest_triangles`` (N,) are the closest triangles of measured
    points and ``toward`` (N, 3) the directions from each point to where it was seen from (``by`` names them);
    without them only closed patches are decided (by their volume) and open ones keep the file's majority."""
    V, t = np.asarray(vertices_mm, float), np.asarray(triangles, np.int64)
    _, same = np.unique(V, axis=0, return_inverse=True)  # an STL repeats a vertex in every triangle holding it
    flip, label = consistent_winding(same.ravel()[t])
    patches = int(label.max()) + 1 if len(label) else 0
    n = _normals(V, np.where(flip[:, None], t[:, ::-1], t))
    area = 0.5 * np.linalg.norm(np.cross(V[t[:, 1]] - V[t[:, 0]], V[t[:, 2]] - V[t[:, 0]]), axis=1)
    votes = np.zeros(patches)
    counts = np.zeros(patches)
    if closest_triangles is not None and toward is not None and len(closest_triangles):
        ids = np.asarray(closest_triangles, np.int64)
        d = np.asarray(toward, float)
        ok = np.linalg.norm(d, axis=1) > 0
        s = np.sign(np.einsum("ij,ij->i", n[ids[ok]], d[ok]))
        votes = np.bincount(label[ids[ok]], s, patches)
        counts = np.bincount(label[ids[ok]], minlength=patches).astype(float)
    deciders, undecided = set(), 0
    closed = np.zeros(len(t), bool)
    merged = same.ravel()[t]  # closed or not by the vertices' positions, not by how the file numbers them
    for patch in range(patches):
        mine = label == patch
        tri = np.where(flip[mine, None], t[mine][:, ::-1], t[mine])
        if triangles_closed(np.where(flip[mine, None], merged[mine][:, ::-1], merged[mine])):
            turn = enclosed_volume_mm3(V - V.mean(axis=0), tri) < 0.0
            closed[mine] = True
            deciders.add("closed volume")
        elif counts[patch] and abs(votes[patch]) >= CLEAR_MAJORITY * counts[patch]:
            turn = votes[patch] < 0.0
            deciders.add(by)
        else:  # nothing says: the file's winding of most of the patch's area
            turn = float(area[mine][flip[mine]].sum()) > 0.5 * float(area[mine].sum())
            deciders.add("the file")
            undecided += 1
        if turn:
            flip[mine] = ~flip[mine]
    notes = []
    if flip.any():
        share = float(area[flip].sum() / max(area.sum(), 1e-300))
        against = "/".join(sorted(deciders - {"the file"})) or "its own majority (wound inconsistently)"
        notes.append(f"the CAD file's winding disagrees with {against} on "
                     f"{int(flip.sum())} of {len(t)} triangles ({100 * share:.1f} % of the area): deviations are "
                     "signed with them reversed")
    if undecided:
        notes.append(f"{undecided} open patch{'es' if undecided > 1 else ''} of the CAD signed by the file's "
                     f"winding: no clear measured side ({by}) near {'them' if undecided > 1 else 'it'}")
    for note in notes:
        log.warning("%s", note)
    return CadOrientation(flip, patches, ", ".join(sorted(deciders)), "; ".join(notes), closed)

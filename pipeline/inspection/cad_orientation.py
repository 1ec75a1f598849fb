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
    roots = np.unique(label, return_index=True)[1]
    hub = coo_matrix((np.ones(len(roots)), (np.full(len(roots), n_t), roots)), shape=(n_t + 1, n_t + 1)).tocsr()
    g = graph.tocoo()
    joined = hub + hub.T + coo_matrix((g.data, (g.row, g.col)), shape=(n_t + 1, n_t + 1)).tocsr()  # one walk
    tree, pred = breadth_first_order(joined, n_t, directed=False, return_predecessors=True)
    tree = tree[1:]
    inner = pred[tree] < n_t  # a patch's first triangle hangs from the hub and keeps its winding
    turns = np.zeros(len(tree), bool)
    if inner.any():  # (a sparse matrix indexed by nothing is no array)
        turns[inner] = np.asarray(parity[tree[inner], pred[tree][inner]]).ravel() == 2.0
    flip = [False] * (n_t + 1)
    for node, up, turn in zip(tree.tolist(), pred[tree].tolist(), turns.tolist(), strict=True):
        flip[node] = flip[up] ^ turn
    return np.array(flip[:n_t], bool), label


def same_position(vertices_mm: np.ndarray) -> np.ndarray:
    """(V,) for every vertex the index of the first vertex at exactly its position (``np.unique(axis=0)``'s
    grouping, by a sort of the three columns: several times faster on a million vertices)."""
    V = np.asarray(vertices_mm, float)
    if not len(V):
        return np.zeros(0, np.int64)
    order = np.lexsort((V[:, 2], V[:, 1], V[:, 0]))
    s = V[order]
    new = np.r_[True, np.any(s[1:] != s[:-1], axis=1)]
    group = np.empty(len(V), np.int64)
    group[order] = np.cumsum(new) - 1
    return group


def closed_patches(wound: np.ndarray, label: np.ndarray, patches: int) -> np.ndarray:
    """(patches,) bool: which patches of the consistently ``wound`` (T, 3) triangles (vertex indices merged by
    position; ``label`` each triangle's patch) are closed (``part.triangles_closed`` for all patches at once):
    every edge of the patch held by exactly two triangles traversing it in opposite directions (two triangles
    sharing an edge are of one patch, so the edges are counted over the whole mesh)."""
    t = np.asarray(wound, np.int64)
    if not len(t):
        return np.zeros(patches, bool)
    n = int(t.max()) + 1
    a = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
    b = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    owner = np.tile(np.asarray(label), 3)
    undirected = np.minimum(a, b) * n + np.maximum(a, b)
    order = np.argsort(undirected, kind="stable")
    u, forward = undirected[order], (a < b)[order]
    start = np.r_[True, u[1:] != u[:-1]]
    group = np.cumsum(start) - 1
    uses = np.bincount(group)
    ways = np.bincount(group, forward.astype(np.int64))  # of an edge's two uses, one each way
    good_edge = (uses == 2) & (ways == 1)
    bad = np.zeros(patches, bool)
    bad[owner[order][~good_edge[group]]] = True
    return ~bad


def _normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    v = vertices[triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def orient(vertices_mm: np.ndarray, triangles: np.ndarray, closest_triangles: np.ndarray | None = None,
           toward: np.ndarray | None = None, by: str = "the measured side",
           patches: MeshPatches | None = None) -> CadOrientation:
    """The winding to sign deviations by (:func:`wind`), its notes logged as warnings."""
    o = wind(vertices_mm, triangles, closest_triangles, toward, by, patches)
    for note in filter(None, o.note.split("; ")):
        log.warning("%s", note)
    return o


@dataclass(frozen=True)
class MeshPatches:
    """What :func:`wind` decides from the mesh alone, whatever the measured side: ``flip`` (T,) bool, the
    triangles taken against the file to wind each connected patch consistently (:func:`consistent_winding`);
    ``label`` (T,) each triangle's patch; ``closed`` (patches,) bool (:func:`closed_patches`); ``inward``
    (patches,) bool, the closed patches whose volume, wound by ``flip``, is negative; ``area`` (T,) mm^2;
    ``normals`` (T, 3) unit, wound by ``flip``."""

    flip: np.ndarray
    label: np.ndarray
    closed: np.ndarray
    inward: np.ndarray
    area: np.ndarray
    normals: np.ndarray

    @property
    def count(self) -> int:
        """How many patches."""
        return len(self.closed)


def mesh_patches(vertices_mm: np.ndarray, triangles: np.ndarray) -> MeshPatches:
    """:class:`MeshPatches` of the mesh (frame F, mm): computed once a CAD surface
    (``inspect.CadSurface.patches``)."""
    V, t = np.asarray(vertices_mm, float), np.asarray(triangles, np.int64)
    same = same_position(V)  # an STL repeats a vertex in every triangle holding it
    flip, label = consistent_winding(same.ravel()[t])
    patches = int(label.max()) + 1 if len(label) else 0
    wound = np.where(flip[:, None], t[:, ::-1], t)
    area = 0.5 * np.linalg.norm(np.cross(V[t[:, 1]] - V[t[:, 0]], V[t[:, 2]] - V[t[:, 0]]), axis=1)
    shut = closed_patches(np.where(flip[:, None], same.ravel()[t][:, ::-1], same.ravel()[t]), label, patches)
    c = V - V.mean(axis=0)
    volume = np.bincount(label, np.einsum("ij,ij->i", c[wound[:, 0]], np.cross(c[wound[:, 1]], c[wound[:, 2]])),
                         patches)
    return MeshPatches(flip, label, shut, shut & (volume < 0.0), area, _normals(V, wound))


def wind(vertices_mm: np.ndarray, triangles: np.ndarray, closest_triangles: np.ndarray | None = None,
         toward: np.ndarray | None = None, by: str = "the measured side",
         patches: MeshPatches | None = None) -> CadOrientation:
    """The winding to sign deviations by. ``closest_triangles`` (N,) are the closest triangles of measured
    points and ``toward`` (N, 3) the directions from each point to where it was seen from (``by`` names them);
    without them only closed patches are decided (by their volume) and open ones keep the file's majority.
    ``patches``: the mesh's :func:`mesh_patches` where the caller has them."""
    t = np.asarray(triangles, np.int64)
    mp = mesh_patches(vertices_mm, t) if patches is None else patches
    label, shut, area, n, n_patches = mp.label, mp.closed, mp.area, mp.normals, mp.count
    votes = np.zeros(n_patches)
    counts = np.zeros(n_patches)
    if closest_triangles is not None and toward is not None and len(closest_triangles):
        ids = np.asarray(closest_triangles, np.int64)
        d = np.asarray(toward, float)
        ok = np.linalg.norm(d, axis=1) > 0
        s = np.sign(np.einsum("ij,ij->i", n[ids[ok]], d[ok]))
        votes = np.bincount(label[ids[ok]], s, n_patches)
        counts = np.bincount(label[ids[ok]], minlength=n_patches).astype(float)
    voted = ~shut & (counts > 0) & (np.abs(votes) >= CLEAR_MAJORITY * counts)
    undecided_patch = ~shut & ~voted  # nothing says: the file's winding of most of the patch's area
    turn = np.where(shut, mp.inward, np.where(voted, votes < 0.0, np.bincount(label, area * mp.flip, n_patches)
                                               > 0.5 * np.bincount(label, area, n_patches)))
    flip = mp.flip ^ turn[label]
    closed = shut[label]
    deciders = {name for name, used in (("closed volume", shut.any()), (by, voted.any()),
                                        ("the file", undecided_patch.any())) if used}
    undecided = int(undecided_patch.sum())
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
    return CadOrientation(flip, n_patches, ", ".join(sorted(deciders)), "; ".join(notes), closed)

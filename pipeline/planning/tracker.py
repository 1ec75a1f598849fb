"""Tracker stations: candidates, ``cover(t)`` and the fewest stations whose covers chain (paper Eq. 16-18).

A measuring point is where the stereo target sits (frame F, mm) when the scanner captures, with the target's
visible normal. ``cover(t)`` is the set of measuring points that a tracker at candidate station ``t`` sees:
inside its field of view, between its least range and its best-accuracy range ``d2``, the target turned
towards the camera, and the sight line not blocked by the part. The chosen stations, in order, must cover
every coverable point and consecutive covers must intersect (the coordinate transfer needs a target pose
seen from both stations).

Two solvers: an integer program (``scipy.optimize.milp``, exact) for instances small enough to finish in
seconds, and a greedy chain for the rest. Both report a lower bound on the optimum.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.optimize import Bounds, LinearConstraint, linprog, milp
from scipy.sparse import bmat, csr_matrix, identity, kron, vstack
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.planning.parameters import ChainLimits, TrackerView

log = logging.getLogger(__name__)

# The sight line counts as blocked when the part is hit this much (mm) before the target.
_OCCLUSION_MARGIN_MM = 5.0


class TrackerPlanningError(ValueError):
    """The tracker stations cannot be chosen (no candidates, or covers that cannot chain)."""


@dataclass(frozen=True)
class TrackerSolution:
    """An ordered chain of candidate indices, how it was found and a lower bound on the optimum count."""

    chain: tuple[int, ...]
    solver: str  # "milp" or "greedy"
    optimal: bool
    lower_bound: int
    seconds: float
    uncovered: tuple[int, ...] = ()  # measuring points that no candidate covers

    @property
    def count(self) -> int:
        return len(self.chain)


# ------------------------------------------------------------------ candidates and covers


def candidate_poses(ring_xy_mm: np.ndarray, inward_xy: np.ndarray, offsets_rad: tuple[float, ...]) -> np.ndarray:
    """Candidate tracking-AGV poses ``(K, 3)`` = x mm, y mm, heading rad: each ring point times each offset.

    ``inward_xy`` (unit, per ring point) points at the part; heading 0 means the chassis faces +x. The
    camera looks along the chassis heading (installation ``T_V1_C``, docs/architecture.md "Frames").
    """
    base = np.arctan2(inward_xy[:, 1], inward_xy[:, 0])
    rows = [np.c_[ring_xy_mm, base + o] for o in offsets_rad]
    return np.vstack(rows) if rows else np.zeros((0, 3))


def cover_matrix(
    candidates: np.ndarray,
    T_V1_C: np.ndarray,
    target_points_F: np.ndarray,
    target_normals_F: np.ndarray,
    scene: o3d.t.geometry.RaycastingScene | None,
    view: TrackerView,
) -> np.ndarray:
    """Boolean ``(K, M)``: candidate ``k`` sees measuring point ``m`` (field of view, range, facing, sight line)."""
    pts = np.asarray(target_points_F, float)
    nrm = np.asarray(target_normals_F, float)
    K, M = len(candidates), len(pts)
    out = np.zeros((K, M), bool)
    if K == 0 or M == 0:
        return out
    tan_h = np.tan(view.half_fov_horizontal_rad)
    tan_v = np.tan(view.half_fov_vertical_rad)
    cos_cone = np.cos(view.view_cone_rad)
    far = view.range_max_mm
    origins, dirs, where = [], [], []
    for k, (x, y, h) in enumerate(candidates):
        T_F_C = F.planar_pose(x, y, h) @ T_V1_C
        p_C = F.transform_points(F.invert(T_F_C), pts)
        dist = np.linalg.norm(p_C, axis=1)
        z = p_C[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = (z > 0) & (np.abs(p_C[:, 0]) <= tan_h * z) & (np.abs(p_C[:, 1]) <= tan_v * z)
        ok &= (dist <= far) & (dist >= view.range_min_mm)
        to_cam = T_F_C[:3, 3] - pts
        ok &= np.einsum("ij,ij->i", nrm, to_cam) >= cos_cone * np.linalg.norm(to_cam, axis=1)
        idx = np.flatnonzero(ok)
        out[k, idx] = True
        if scene is not None and len(idx):
            d = -to_cam[idx]
            origins.append(np.broadcast_to(T_F_C[:3, 3], d.shape))
            dirs.append(d)
            where.append(np.c_[np.full(len(idx), k), idx])
    if scene is not None and origins:
        d = np.vstack(dirs)
        length = np.linalg.norm(d, axis=1)
        rays = np.c_[np.vstack(origins), d / length[:, None]].astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))["t_hit"].numpy()
        blocked = t_hit < length - _OCCLUSION_MARGIN_MM
        kw = np.vstack(where)[blocked]
        out[kw[:, 0], kw[:, 1]] = False
    return out


# ------------------------------------------------------------------ the chain condition


def is_valid_chain(cover: np.ndarray, chain: tuple[int, ...] | list[int], required: np.ndarray | None = None) -> bool:
    """True when the chain covers every required point and consecutive covers intersect (Eq. 17-18)."""
    cover = np.asarray(cover, bool)
    if len(chain) == 0:
        return False
    need = cover.any(axis=0) if required is None else np.asarray(required, bool)
    covered = cover[list(chain)].any(axis=0)
    if np.any(need & ~covered):
        return False
    return all(np.any(cover[a] & cover[b]) for a, b in itertools.pairwise(chain))


# ------------------------------------------------------------------ reductions (exact: keep the optimum)


def _reduce(cover: np.ndarray, first: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kept station indices, witness columns, columns that must be covered) of an equivalent smaller problem.

    Stations whose cover is inside another's are dropped (swapping one for a superset keeps coverage and every
    intersection). Identical point columns are merged. A column whose covering stations include all those of
    another column is covered whenever that one is, so only the minimal columns need a coverage constraint;
    every distinct column stays as a possible transfer witness. A fixed ``first`` station is always kept.
    """
    cov = cover[:, cover.any(axis=0)]
    _, firsts = np.unique(cov, axis=0, return_index=True)
    stations = np.sort(firsts)
    stations = stations[~_strictly_inside_another(cov[stations])]
    if first is not None and first not in stations:
        stations = np.sort(np.r_[stations, first])
    cols = np.unique(cov[stations].T, axis=0)  # (P, K') distinct point columns (as rows)
    minimal = ~_strictly_contains_another(cols)
    return stations, cols.T, cols[minimal].T


def _contained(rows: np.ndarray) -> np.ndarray:
    """``[i, j]``: row i's True set lies inside row j's (distinct rows only)."""
    a = rows.astype(np.float32)
    out = (a @ (1.0 - a).T) < 0.5
    np.fill_diagonal(out, False)
    return out


def _strictly_inside_another(rows: np.ndarray) -> np.ndarray:
    return _contained(rows).any(axis=1)


def _strictly_contains_another(rows: np.ndarray) -> np.ndarray:
    return _contained(rows).any(axis=0)


def lp_lower_bound(cover: np.ndarray) -> int:
    """Ceiling of the set-cover LP relaxation: no chain can use fewer stations."""
    need = cover[:, cover.any(axis=0)]
    if need.shape[1] == 0:
        return 0
    res = linprog(np.ones(need.shape[0]), A_ub=-need.T.astype(float), b_ub=-np.ones(need.shape[1]),
                  bounds=(0, 1), method="highs")
    return int(np.ceil(res.fun - 1e-6)) if res.status == 0 else 1


# ------------------------------------------------------------------ greedy chain


def _greedy_from(cover: np.ndarray, adjacency: np.ndarray, start: int) -> list[int] | None:
    need = cover.any(axis=0)
    uncovered = need & ~cover[start]
    chain = [start]
    while uncovered.any():
        gain = cover[:, uncovered].sum(axis=1)
        last = chain[-1]
        near = adjacency[last] & (gain > 0)
        if near.any():
            nxt = int(np.argmax(np.where(near, gain, -1)))
            chain.append(nxt)
        else:  # bridge: the shortest path in the intersection graph to any station with gain
            path = _shortest_path(adjacency, last, gain > 0)
            if path is None:
                return None
            chain.extend(path)
        uncovered &= ~cover[chain[-1]]
    return chain


def _run_length(covered_by: np.ndarray, f: int) -> np.ndarray:
    """Per station: how many consecutive points from ``f`` on (cyclic) it covers or are already covered."""
    rolled = np.roll(covered_by, -f, axis=1)
    misses = ~rolled
    first_miss = np.where(misses.any(axis=1), np.argmax(misses, axis=1), rolled.shape[1])
    return first_miss


def _sweep_from(cover: np.ndarray, adjacency: np.ndarray, start: int) -> list[int] | None:
    """Farthest-reach chain along the measuring order (columns are in measuring order, cyclic).

    From the first uncovered point, the next station is the one sharing a point with the last that covers
    that point and reaches farthest along the order; a bridge through the intersection graph when none does.
    """
    need = cover.any(axis=0)
    covered = ~need | cover[start]
    chain = [start]
    while not covered.all():
        f = int(np.argmin(covered))
        ok = adjacency[chain[-1]] & cover[:, f]
        if not ok.any():
            path = _shortest_path(adjacency, chain[-1], cover[:, f])
            if path is None:
                return None
            chain.extend(path)
        else:
            reach = _run_length(cover | covered[None, :], f)
            chain.append(int(np.argmax(np.where(ok, reach, -1))))
        covered |= cover[chain[-1]]
    return chain


def _sweep_back_from(cover: np.ndarray, adjacency: np.ndarray, start: int) -> list[int] | None:
    """The sweep against the measuring order."""
    return _sweep_from(cover[:, ::-1], adjacency, start)


def _prune(cover: np.ndarray, adjacency: np.ndarray, chain: list[int], keep_first: bool) -> list[int]:
    """Local search: drop a station, or swap two neighbours for one, while the chain stays valid."""
    need = cover.any(axis=0)
    lo = 1 if keep_first else 0
    improved = True
    while improved and len(chain) > 1:
        improved = False
        for i in sorted(range(lo, len(chain)), key=lambda i: cover[chain[i]].sum()):
            trial = chain[:i] + chain[i + 1:]
            if is_valid_chain(cover, trial, need):
                chain, improved = trial, True
                break
        if improved:
            continue
        for i in range(lo, len(chain) - 1):
            rest = chain[:i] + chain[i + 2:]
            missing = need & ~(cover[rest].any(axis=0) if rest else np.zeros_like(need))
            ok = cover[:, missing].all(axis=1)
            if i > 0:
                ok &= adjacency[chain[i - 1]]
            if i + 2 < len(chain):
                ok &= adjacency[chain[i + 2]]
            if ok.any():
                t = int(np.argmax(np.where(ok, cover.sum(axis=1), -1)))
                chain, improved = chain[:i] + [t] + chain[i + 2:], True
                break
    return chain


def _shortest_path(adjacency: np.ndarray, source: int, goal: np.ndarray) -> list[int] | None:
    parent = np.full(len(adjacency), -1)
    seen = np.zeros(len(adjacency), bool)
    seen[source] = True
    frontier = [source]
    while frontier:
        nxt = []
        for u in frontier:
            for v in np.flatnonzero(adjacency[u] & ~seen):
                seen[v] = True
                parent[v] = u
                if goal[v]:
                    path = [int(v)]
                    while parent[path[-1]] != source:
                        path.append(int(parent[path[-1]]))
                    return path[::-1]
                nxt.append(v)
        frontier = nxt
    return None


def solve_greedy(cover: np.ndarray, starts: int = 8, first: int | None = None) -> TrackerSolution:
    """A valid chain grown from several start stations (largest covers, rarest point); bound by LP.

    Three growth rules are tried from each start, most new points next and farthest reach along or against
    the measuring order (the columns' order); after a local search the shortest chain wins.

    With ``first`` the chain starts at that station (where the tracking robot stands when the job begins).
    """
    t0 = time.perf_counter()
    cover = np.asarray(cover, bool)
    uncovered = tuple(np.flatnonzero(~cover.any(axis=0)).tolist())
    if not cover.any():
        raise TrackerPlanningError("no candidate tracker station sees any measuring point")
    sizes = cover.sum(axis=1)
    tries = list(np.argsort(-sizes)[:starts])
    counts = cover.sum(axis=0)
    rare = int(np.argmin(np.where(counts > 0, counts, np.iinfo(np.int64).max)))
    tries += list(np.flatnonzero(cover[:, rare])[np.argsort(-sizes[cover[:, rare]])][:starts])
    if first is not None:
        if not cover[first].any():
            raise TrackerPlanningError("the tracker's start station sees none of the measuring points")
        tries = [first]
    c32 = cover.astype(np.float32)
    adjacency = (c32 @ c32.T) > 0.5  # stations whose covers intersect
    bound = lp_lower_bound(cover)
    best = None
    for s in dict.fromkeys(int(t) for t in tries):
        for grow in (_sweep_from, _sweep_back_from, _greedy_from):
            chain = grow(cover, adjacency, s)
            if chain is not None:
                chain = _prune(cover, adjacency, chain, keep_first=first is not None)
            if chain is not None and (best is None or len(chain) < len(best)):
                best = chain
            if best is not None and len(best) <= bound:  # cannot do better than the LP bound
                break
        if best is not None and len(best) <= bound:
            break
    if best is None:
        raise TrackerPlanningError("the covers of the candidate tracker stations cannot be chained")
    return TrackerSolution(tuple(best), "greedy", len(best) == bound, bound, time.perf_counter() - t0, uncovered)


# ------------------------------------------------------------------ exact integer program


def solve_exact(
    cover: np.ndarray, time_limit_s: float = 5.0, max_variables: int = 20000, first: int | None = None,
    greedy: TrackerSolution | None = None,
) -> TrackerSolution | None:
    """The fewest chained stations by an integer program; None when the instance is too large or times out.
    ``greedy``: the heuristic's chain for this ``cover`` and ``first`` when the caller has it (else solved here).

    When the heuristic chain already meets the LP lower bound it is optimal and returned as is. Otherwise:
    slots ``s = 0..S-1`` (S = the heuristic count). Binary ``x[t, s]``: station t in slot s; binary ``u[s]``:
    slot used, ``u[s] >= u[s+1]``, ``sum_t x[t, s] = u[s]``; every required point covered by some slot; a
    witness ``y[c, s] in [0, 1]`` per distinct point column and slot pair with ``y <= cover of slot s``,
    ``y <= cover of slot s+1`` and ``sum_c y[c, s] >= u[s+1]`` (consecutive covers intersect). A fixed
    ``first`` station occupies slot 0.
    """
    t0 = time.perf_counter()
    cover = np.asarray(cover, bool)
    greedy = greedy if greedy is not None else solve_greedy(cover, first=first)
    if greedy.optimal:  # the heuristic met the LP bound: proven optimal, no integer program needed
        return greedy
    stations, witness, required = _reduce(cover, first)
    K, C, R, S = len(stations), witness.shape[1], required.shape[1], greedy.count
    n_x, n_u, n_y = K * S, S, C * (S - 1)
    if n_x + n_u + n_y > max_variables:
        return None
    n = n_x + n_u + n_y
    W = csr_matrix(witness.astype(float))  # (K, C)
    I_S = identity(S, format="csr")
    shift = lambda k: csr_matrix(np.eye(S - 1, S, k))  # noqa: E731 - picks slot s (k=0) or s+1 (k=1)
    Z = lambda r, c: csr_matrix((r, c))  # noqa: E731
    blocks = [
        # one station per used slot: sum_t x[t, s] - u[s] = 0
        ([kron(I_S, np.ones((1, K))), -I_S, Z(S, n_y)], 0.0, 0.0),
        # used slots first: u[s] - u[s+1] >= 0
        ([Z(S - 1, n_x), shift(0) - shift(1), Z(S - 1, n_y)], 0.0, np.inf),
        # every required point covered: sum_{s, t} R[t, c] x[t, s] >= 1
        ([kron(np.ones((1, S)), csr_matrix(required.T.astype(float))), Z(R, n_u), Z(R, n_y)], 1.0, np.inf),
        # witness only where slot s sees it: y[c, s] - sum_t W[t, c] x[t, s] <= 0
        ([-kron(shift(0), W.T), Z(n_y, n_u), identity(n_y)], -np.inf, 0.0),
        # ... and slot s+1 sees it
        ([-kron(shift(1), W.T), Z(n_y, n_u), identity(n_y)], -np.inf, 0.0),
        # consecutive used slots share a witness: sum_c y[c, s] - u[s+1] >= 0
        ([Z(S - 1, n_x), -shift(1), kron(identity(S - 1), np.ones((1, C)))], 0.0, np.inf),
    ]
    rows = [bmat([parts]) for parts, _, _ in blocks]
    A = vstack(rows, format="csr")
    lo = np.concatenate([np.full(r.shape[0], low) for r, (_, low, _) in zip(rows, blocks, strict=True)])
    hi = np.concatenate([np.full(r.shape[0], high) for r, (_, _, high) in zip(rows, blocks, strict=True)])
    cost = np.zeros(n)
    cost[n_x:n_x + n_u] = 1.0
    integrality = np.r_[np.ones(n_x + n_u), np.zeros(n_y)]
    lower = np.zeros(n)
    if first is not None:
        lower[int(np.flatnonzero(stations == first)[0])] = 1.0  # x[first, slot 0]
    res = milp(cost, constraints=LinearConstraint(A, lo, hi), integrality=integrality, bounds=Bounds(lower, 1),
               options={"time_limit": time_limit_s, "disp": False})
    if res.status != 0 or res.x is None:
        log.info("tracker integer program stopped (%s); using the greedy chain", res.message)
        return None
    x = res.x[:n_x].reshape(S, K)
    chain = tuple(int(stations[np.argmax(x[s])]) for s in range(S) if res.x[n_x + s] > 0.5)
    if not is_valid_chain(cover, chain):  # numerical safety: never hand out an invalid chain
        log.warning("tracker integer program returned an invalid chain; using the greedy chain")
        return None
    return TrackerSolution(chain, "milp", True, len(chain), time.perf_counter() - t0, greedy.uncovered)


def choose_stations(cover: np.ndarray, limits: ChainLimits, first: int | None = None) -> TrackerSolution:
    """The exact solver where it finishes within ``limits``, else the greedy chain (solved once)."""
    greedy = solve_greedy(cover, first=first)
    exact = solve_exact(cover, limits.time_limit_s, limits.max_variables, first, greedy)
    return exact if exact is not None else greedy


__all__ = [
    "TrackerPlanningError",
    "TrackerSolution",
    "candidate_poses",
    "choose_stations",
    "cover_matrix",
    "is_valid_chain",
    "lp_lower_bound",
    "solve_exact",
    "solve_greedy",
]

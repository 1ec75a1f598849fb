"""Scanner poses at one measurement-AGV station: a boustrophedon raster on the part surface (paper Eq. 15).

At a station (frame F, mm) the raster has ``j = ceil(s / m) + 1`` columns along the contour (``s`` the
station step, ``m`` the useful scan width), evenly from ``-s/2`` to ``+s/2`` so no more than ``m`` apart; the
edge columns coincide with the neighbouring stations' (each is scanned once, by the later station) and, per
column, ``i = ceil(h / n)`` rows ``n`` apart along the surface profile on the station's side of the part
(``h`` its length: the height for a vertical wall, plus the roof up to the part's middle). Each cell is a
surface point with its normal; the scanner looks along the negative normal from the sweet spot, tilted
towards the arm by at most the incidence limit when the square-on pose is out of reach. A cell is kept only
where the inverse kinematics finds joint angles inside the limits, at one of the lifting column's heights
where the AGV has one (docs/planning.md); the others are reported with their reason. The kept poses are
grouped by column height and ordered (column- or row-wise snake, whichever moves the joints less).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from tandemscan.config.models import ArmConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import arm_base_on_column
from tandemscan.pipeline.planning.floor import floor_z_mm, no_pose_fits
from tandemscan.pipeline.planning.parameters import AgvMargin, ScanFootprint, StationSpacing
from tandemscan.pipeline.planning.stations import AgvStation

log = logging.getLogger(__name__)

IkSolver = Callable[[np.ndarray, np.ndarray], "np.ndarray | None"]
"""``(T_B_E, seed_rad) -> q_rad or None``: the contract of ``ArmKinematics.inverse``."""

_PROFILE_STEP_MM = 20.0
_TILT_STEP_DEG = 15.0
_UNDERSIDE_DEG = 30.0  # an underside row's surface normal lies this close to straight down


@dataclass(frozen=True)
class RasterCell:
    """A surface point to scan (F, mm) with its outward unit normal; row/column in the station's raster."""

    row: int
    col: int
    point_F: np.ndarray
    normal_F: np.ndarray


@dataclass(frozen=True)
class ScanPose:
    """A reachable scanner pose: ``T_F_S`` (mm), the joints that reach it (rad), the view tilt off the normal;
    ``robust``: still reachable with the AGV off its station by the planning margin (``agv_margin_*``);
    ``lift_mm``: the lifting column's height the joints assume (0 without a column)."""

    station: int
    cell: RasterCell
    T_F_S: np.ndarray
    joints_rad: np.ndarray
    tilt_rad: float
    robust: bool = True
    lift_mm: float = 0.0


@dataclass(frozen=True)
class Unreached:
    """A raster cell the arm cannot scan from its station, and why."""

    station: int
    cell: RasterCell
    reason: str


@dataclass(frozen=True)
class StationRaster:
    """The raster of one station: its size (Eq. 15), the ordered reachable poses and what was left out."""

    station: AgvStation
    rows: int
    cols: int
    poses: tuple[ScanPose, ...]
    unreached: tuple[Unreached, ...]
    joint_travel_rad: float


@dataclass(frozen=True)
class ArmSetup:
    """The robot as the raster sees it: IK, arm (limits, DH), mounts ``T_V2_B`` and ``T_E_S`` (mm), one scan's
    footprint, the stations' spacing (the section's reach), the AGV's margin off its station, and the lifting
    column's heights to try (mm above the mount; ``(0,)`` without a column)."""

    ik: IkSolver
    arm: ArmConfig
    T_V2_B: np.ndarray
    T_E_S: np.ndarray
    footprint: ScanFootprint
    spacing: StationSpacing
    margin: AgvMargin
    lift_heights_mm: tuple[float, ...] = (0.0,)


def column_count(step_mm: float, m_mm: float) -> int:
    """``j = ceil(s / m) + 1`` columns, fence posts over the step ``s`` at most ``m`` apart (Eq. 15)."""
    return int(math.ceil(step_mm / m_mm - 1e-9)) + 1


def row_count(h_mm: float, n_mm: float) -> int:
    """``i = ceil(h / n)`` rows over a profile of length ``h`` (Eq. 15); at least one."""
    return max(int(math.ceil(h_mm / n_mm - 1e-9)), 1)


def _cast(scene: o3d.t.geometry.RaycastingScene, origins: np.ndarray, dirs: np.ndarray):
    rays = np.c_[origins, dirs].astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
    return ans["t_hit"].numpy().astype(float), ans["primitive_normals"].numpy().astype(float)


def half_section(
    scene: o3d.t.geometry.RaycastingScene, base_xy: np.ndarray, inward: np.ndarray, z_range: tuple[float, float],
    reach_mm: float, underside: Underside | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Surface points and outward normals (F, mm) on the vertical half-section seen from ``base_xy``.

    Horizontal rays towards the part at every height and vertical rays down onto the roof, kept up to the
    part's middle (halfway between the near and far side) and ordered from the floor up and over the top; with
    ``underside``, the part's underside where a scanner has room under it first, from the middle out
    (:func:`underside_profile`). Empty arrays when the rays miss the part.
    """
    z0, z1 = z_range
    up = np.array([0.0, 0.0, 1.0])
    v = np.array([inward[0], inward[1], 0.0])
    base = np.array([base_xy[0], base_xy[1], 0.0])
    zs = np.arange(z0 + 0.5 * _PROFILE_STEP_MM, z1, _PROFILE_STEP_MM)
    org_h = base + zs[:, None] * up
    t_near, n_h = _cast(scene, org_h, np.tile(v, (len(zs), 1)))
    t_back, _ = _cast(scene, org_h + reach_mm * v, np.tile(-v, (len(zs), 1)))
    both = np.isfinite(t_near) & np.isfinite(t_back)
    if not both.any():
        return np.zeros((0, 3)), np.zeros((0, 3))
    t_mid = float(np.median(0.5 * (t_near[both] + reach_mm - t_back[both])))
    ts = np.arange(0.5 * _PROFILE_STEP_MM, t_mid, _PROFILE_STEP_MM)
    org_v = base + ts[:, None] * v + (z1 + 100.0) * up
    t_down, n_v = _cast(scene, org_v, np.tile(-up, (len(ts), 1)))
    hit_h = np.isfinite(t_near) & (t_near <= t_mid)
    hit_v = np.isfinite(t_down)
    pts = np.vstack([org_h[hit_h] + t_near[hit_h, None] * v, org_v[hit_v] - t_down[hit_v, None] * up])
    nrm = np.vstack([n_h[hit_h], n_v[hit_v]])
    dirs = np.vstack([np.tile(v, (hit_h.sum(), 1)), np.tile(-up, (hit_v.sum(), 1))])
    flip = np.einsum("ij,ij->i", nrm, dirs) > 0  # face the ray whatever the mesh winding
    nrm[flip] *= -1
    rel_t = (pts - base) @ v
    angle = np.arctan2(pts[:, 2] - z0, t_mid - rel_t)
    order = np.argsort(angle, kind="stable")
    if underside is None:
        return pts[order], nrm[order]
    below, below_n = underside_profile(scene, base, v, ts, underside)
    return np.vstack([below, pts[order]]), np.vstack([below_n, nrm[order]])


def _in_front(scene: o3d.t.geometry.RaycastingScene, base: np.ndarray, v: np.ndarray, z: np.ndarray,
              along: np.ndarray) -> np.ndarray:
    """Per height ``z`` (mm): a horizontal ray from ``base`` along ``v`` meets the part before ``along`` (mm)."""
    level = base + np.asarray(z)[:, None] * np.array([0.0, 0.0, 1.0])
    t, _ = _cast(scene, level, np.tile(v, (len(level), 1)))
    return t < along


@dataclass(frozen=True)
class Underside:
    """What the underside rows need: the floor's height in F, the scanner's sweet spot and the incidence limit
    (mm, rad)."""

    floor_z_mm: float
    sweet_spot_mm: float
    incidence_limit_rad: float


def underside_profile(scene: o3d.t.geometry.RaycastingScene, base: np.ndarray, v: np.ndarray, ts: np.ndarray,
                      underside: Underside) -> tuple[np.ndarray, np.ndarray]:
    """The part's underside on the half-section from ``base`` (on the floor, F mm) along ``v`` at the distances
    ``ts`` (mm): rays up from under the floor, kept where the surface faces down (within ``_UNDERSIDE_DEG``; the
    horizontal rays find the steeper rest), where a scanner pose has room above the floor
    (``floor.no_pose_fits``: a part on supports, not one resting on the floor) and where the scanner, square on
    at the sweet spot, stands in free space the station reaches at its height (no part between: not inside an
    arch); ordered from the part's middle out to the station's side. Points and outward normals (mm)."""
    up = np.array([0.0, 0.0, 1.0])
    org = base + ts[:, None] * v + (underside.floor_z_mm - 1.0) * up
    t_up, n_up = _cast(scene, org, np.tile(up, (len(ts), 1)))
    hit = np.isfinite(t_up)
    pts, nrm = org[hit] + t_up[hit, None] * up, n_up[hit]
    nrm[nrm @ up > 0] *= -1  # face the ray (down) whatever the mesh winding
    keep = nrm[:, 2] < -math.cos(math.radians(_UNDERSIDE_DEG))  # the horizontal rays find the steeper rest
    keep &= ~no_pose_fits(pts, nrm, underside.floor_z_mm, underside.sweet_spot_mm, underside.incidence_limit_rad)
    scanner = pts + underside.sweet_spot_mm * nrm
    if len(pts):
        keep &= ~_in_front(scene, base, v, scanner[:, 2], (scanner - base) @ v)  # the scanner's place is free
    order = np.argsort(-((pts[keep] - base) @ v), kind="stable")
    return pts[keep][order], nrm[keep][order]


def _sample_profile(pts: np.ndarray, nrm: np.ndarray, n_mm: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Rows ``n`` apart along the ordered profile: (points, smoothed unit normals).

    Where the profile's samples lie farther apart than ``n`` (a shallow slope met by the horizontal rays) two
    rows can fall on the same sample; it is scanned once.
    """
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    arc = np.r_[0.0, np.cumsum(seg)]
    h = float(arc[-1])
    rows = row_count(h, n_mm)
    out_p, out_n, used = [], [], set()
    for r in range(rows):
        s = (r + 0.5) * h / rows
        k = int(np.argmin(np.abs(arc - s)))
        if k in used:
            continue
        used.add(k)
        near = np.abs(arc - arc[k]) <= 0.25 * n_mm
        normal = nrm[near].sum(axis=0)
        out_p.append(pts[k])
        out_n.append(normal / np.linalg.norm(normal))
    return out_p, out_n


def raster_cells(
    scene: o3d.t.geometry.RaycastingScene,
    station: AgvStation,
    step_mm: float,
    z_range: tuple[float, float],
    reach_mm: float,
    footprint: ScanFootprint,
    shared_last_column: bool = False,
) -> tuple[list[RasterCell], int, int]:
    """The raster's surface cells at ``station`` with its (rows, columns); rows is the largest column's count.

    With ``shared_last_column`` the last column is left to the next station, whose first column is the same.
    """
    m, n = footprint.width_mm, footprint.height_mm
    underside = Underside(floor_z_mm(z_range[0]), footprint.sweet_spot_mm, footprint.incidence_limit_rad)
    cols = column_count(step_mm, m)
    cells, rows = [], 0
    for c in range(cols - 1 if shared_last_column else cols):
        offset = (c / (cols - 1) - 0.5) * step_mm
        base = station.xy + offset * station.tangent
        pts, nrm = half_section(scene, base, station.towards_part, z_range, reach_mm, underside)
        if len(pts) < 2:
            continue
        ps, ns = _sample_profile(pts, nrm, n)
        rows = max(rows, len(ps))
        cells += [RasterCell(r, c, p, q) for r, (p, q) in enumerate(zip(ps, ns, strict=True))]
    return cells, rows, cols


def scanner_poses(points_F: np.ndarray, views_F: np.ndarray, sweet_spot_mm: float, inward: np.ndarray,
                  roll_half_turn: np.ndarray | bool = False) -> np.ndarray:
    """``T_F_S`` stack ``(K, 4, 4)`` looking along ``views_F`` at ``points_F`` from the sweet spot (mm).

    Image y (S y) points as near "down" as it can; when the view is (almost) vertical it points away from the
    station (``inward``). A half-turn roll about the view flips x and y (same footprint, other wrist pose).
    """
    pts = np.atleast_2d(np.asarray(points_F, float))
    z = np.atleast_2d(np.asarray(views_F, float))
    z = z / np.linalg.norm(z, axis=1, keepdims=True)
    down = np.tile([0.0, 0.0, -1.0], (len(z), 1))
    vertical = np.abs(z[:, 2]) > 0.95
    down[vertical] = [inward[0], inward[1], 0.0]
    y = down - np.sum(down * z, axis=1, keepdims=True) * z
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    x = np.c_[y[:, 1] * z[:, 2] - y[:, 2] * z[:, 1], y[:, 2] * z[:, 0] - y[:, 0] * z[:, 2],
              y[:, 0] * z[:, 1] - y[:, 1] * z[:, 0]]
    flip = np.where(np.broadcast_to(np.asarray(roll_half_turn), (len(z),)), -1.0, 1.0)[:, None]
    T = np.tile(np.eye(4), (len(z), 1, 1))
    T[:, :3, 0] = flip * x
    T[:, :3, 1] = flip * y
    T[:, :3, 2] = z
    T[:, :3, 3] = pts - sweet_spot_mm * z
    return T


def reach_bound_mm(arm: ArmConfig) -> float:
    """No flange pose is farther than this from the shoulder (base z = d1): the sum of the other links (mm)."""
    return float(np.sum(np.abs(arm.dh_a_mm)) + np.sum(np.abs(arm.dh_d_mm[1:])))


def _views(cell: RasterCell, base_F: np.ndarray, limit_rad: float) -> list[tuple[float, np.ndarray]]:
    """View directions for a cell: square on, then tilted towards the arm base in steps up to the limit."""
    n = cell.normal_F
    to_base = base_F - cell.point_F
    b = to_base - (to_base @ n) * n
    nb = np.linalg.norm(b)
    out = [(0.0, -n)]
    if nb < 1e-9:
        return out
    b /= nb
    for deg in np.arange(_TILT_STEP_DEG, math.degrees(limit_rad) + 1e-9, _TILT_STEP_DEG):
        a = math.radians(deg)
        out.append((a, -(n * math.cos(a) + b * math.sin(a))))
    return out


def margin_moves(T_V2_B: np.ndarray, margin: AgvMargin) -> np.ndarray:
    """``(K, 4, 4)`` maps ``M`` with ``T_B'_E = M T_B_E``: the flange target seen from the arm base when the AGV
    stands off its station by the planning margin (forward, back, left, right, each way round; mm, rad); none
    when the margin is zero."""
    m, h = margin.distance_mm, margin.heading_rad
    offsets = [o for o in ((m, 0.0, 0.0), (-m, 0.0, 0.0), (0.0, m, 0.0), (0.0, -m, 0.0), (0.0, 0.0, h), (0.0, 0.0, -h))
               if any(o)]
    T_B_V2 = F.invert(T_V2_B)
    return np.array([T_B_V2 @ F.invert(F.planar_pose(x, y, a)) @ T_V2_B for x, y, a in offsets]).reshape(-1, 4, 4)


def _robust(ik: IkSolver, T_B_E: np.ndarray, q: np.ndarray, moves: np.ndarray) -> bool:
    """Whether ``T_B_E`` stays reachable (seeded from ``q``) under every AGV offset in ``moves``; all offsets at
    once where the IK answers reachability for many poses (``AnalyticIK.reachable``)."""
    reachable = getattr(ik, "reachable", None)
    if reachable is not None:
        return bool(np.all(reachable(moves @ T_B_E)))
    return all(ik(M @ T_B_E, q) is not None for M in moves)


def _travel(qs: list[np.ndarray]) -> float:
    """Joint travel of a sequence: sum over moves of the largest joint change (rad), a proxy for motion time."""
    return float(sum(np.max(np.abs(b - a)) for a, b in zip(qs[:-1], qs[1:], strict=True)))


def _snake(cells: list[tuple[int, int]], column_major: bool) -> list[int]:
    """Indices of (row, col) cells in boustrophedon order."""
    major = 1 if column_major else 0
    minor = 1 - major
    keys = sorted({c[major] for c in cells})
    order = []
    for k, key in enumerate(keys):
        group = sorted((i for i, c in enumerate(cells) if c[major] == key), key=lambda i: cells[i][minor])
        order += group if k % 2 == 0 else group[::-1]
    return order


def plan_station(
    station: AgvStation,
    cells: list[RasterCell],
    rows: int,
    cols: int,
    setup: ArmSetup,
    seed_rad: np.ndarray,
) -> StationRaster:
    """Reachable scanner poses for the cells of one station, ordered to move the joints (and the column) least.

    Per cell the views are tried square on first, then tilted towards the arm, each with both rolls; poses
    whose flange lies beyond the arm's reach bound skip the IK. With a lifting column the column's heights are
    tried lowest first (fewer column moves; the target faces out to the tracker). The first view that stays
    reachable with the AGV off its station by the planning margin wins (the runner re-solves the joints
    where the AGV really stands); a cell with no such view keeps its first reachable one, marked not robust.
    The poses are grouped by column height, lowest first, each group in the order that moves the joints least.
    """
    ik, arm, footprint = setup.ik, setup.arm, setup.footprint
    heights = np.asarray(setup.lift_heights_mm, float)
    T_F_V2 = F.planar_pose(station.x_mm, station.y_mm, station.heading_rad)
    T_B_F = np.array([F.invert(T_F_V2 @ arm_base_on_column(setup.T_V2_B, h)) for h in heights])  # (L, 4, 4)
    T_S_E = F.invert(setup.T_E_S)
    limit = footprint.incidence_limit_rad
    base_F = (T_F_V2 @ arm_base_on_column(setup.T_V2_B, float(np.median(heights))))[:3, 3]
    order = _snake([(c.row, c.col) for c in cells], column_major=True)
    owner, tilts, pts, views, rolls = [], [], [], [], []
    for i in order:
        for tilt, view in _views(cells[i], base_F, limit):
            for roll in (False, True):
                owner.append(i)
                tilts.append(tilt)
                pts.append(cells[i].point_F)
                views.append(view)
                rolls.append(roll)
    found: list[ScanPose] = []
    unreached: list[Unreached] = []
    if owner:
        T_F_S = scanner_poses(np.array(pts), np.array(views), footprint.sweet_spot_mm, station.towards_part,
                              np.array(rolls))
        T_B_E = T_B_F[:, None] @ (T_F_S @ T_S_E)[None]  # (L, K, 4, 4)
        shoulder = np.array([0.0, 0.0, arm.dh_d_mm[0]])
        to_shoulder = np.linalg.norm(T_B_E[:, :, :3, 3] - shoulder, axis=2)  # (L, K)
        in_reach = to_shoulder <= reach_bound_mm(arm)
        prefilter = getattr(ik, "maybe_reachable", None)
        if prefilter is not None:
            in_reach &= prefilter(T_B_E.reshape(-1, 4, 4)).reshape(in_reach.shape)
        owner_arr = np.array(owner)
        seeds = [np.asarray(seed_rad, float)] * len(heights)
        moves = margin_moves(setup.T_V2_B, setup.margin)  # a column's lift commutes with the AGV's planar offsets
        for i in order:
            ks = np.flatnonzero(owner_arr == i)
            best = None  # (level, k, q, robust)
            for level in range(len(heights)):  # lowest first: fewer column moves, targets facing out
                view = _best_view(ik, T_B_E[level], ks[in_reach[level, ks]], seeds[level], moves)
                if view is not None and (best is None or (view[2] and not best[3])):
                    best = (int(level), *view)
                if best is not None and best[3]:
                    break
            if best is None:
                column = f" at any column height {heights[0]:.0f}-{heights[-1]:.0f} mm" if len(heights) > 1 else ""
                unreached.append(Unreached(station.index, cells[i], "no joint solution within the limits for any "
                                           f"view within {math.degrees(limit):.0f} deg of the surface normal{column}"))
            else:
                level, k, q, robust = best
                found.append(ScanPose(station.index, cells[i], T_F_S[k], q, tilts[k], robust, float(heights[level])))
                seeds[level] = q
    ordered, travel = [], 0.0
    for h in sorted({p.lift_mm for p in found}):
        group, group_travel = _least_travel_order([p for p in found if p.lift_mm == h])
        ordered += group
        travel += group_travel
    return StationRaster(station, rows, cols, tuple(ordered), tuple(unreached), travel)


def _best_view(ik: IkSolver, T_B_E: np.ndarray, candidates: np.ndarray, seed: np.ndarray,
               moves: np.ndarray) -> tuple[int, np.ndarray, bool] | None:
    """``(k, q, robust)`` of the first of ``candidates`` (indices into ``T_B_E``, in preference order) that IK
    reaches and that stays reachable under the AGV ``moves``, else of the first reachable one; None if none is."""
    first = None
    for k in candidates:
        q = ik(T_B_E[k], seed)
        if q is None:
            continue
        if _robust(ik, T_B_E[k], q, moves):
            return int(k), np.asarray(q, float), True
        if first is None:
            first = (int(k), np.asarray(q, float), False)
    return first


def _least_travel_order(found: list[ScanPose]) -> tuple[list[ScanPose], float]:
    """The poses in the column snake, the row snake or either reversed, whichever moves the joints least."""
    best, best_travel = found, _travel([p.joints_rad for p in found])
    if len(found) > 2:
        alt = [found[k] for k in _snake([(p.cell.row, p.cell.col) for p in found], column_major=False)]
        for cand in (alt, alt[::-1], found[::-1]):
            t = _travel([p.joints_rad for p in cand])
            if t < best_travel - 1e-9:
                best, best_travel = cand, t
    return best, best_travel


def plan_arm(
    scene: o3d.t.geometry.RaycastingScene,
    mesh_bounds: tuple[np.ndarray, np.ndarray],
    stations: tuple[AgvStation, ...],
    step_mm: float,
    path_length_mm: float,
    setup: ArmSetup,
    home_rad: np.ndarray,
) -> list[StationRaster]:
    """The raster of every station, the joint seed carried from one station to the next.

    Stations sit ``step_mm`` apart on a closed path of ``path_length_mm``; a station whose successor on the path
    is planned leaves their shared fence-post column to it.
    """
    spacing = setup.spacing
    lo, hi = (np.asarray(b, float) for b in mesh_bounds)
    reach = float(np.linalg.norm(hi - lo)) + 4.0 * spacing.arm_standoff_max_mm + spacing.agv_width_mm
    out = []
    seed = np.asarray(home_rad, float)
    arcs = np.array([st.arc_mm for st in stations])
    for st in stations:
        after = (st.arc_mm + step_mm) % path_length_mm if path_length_mm > 0 else np.inf
        shared = len(stations) > 1 and bool(np.any(np.abs(arcs - after) < 1.0) or (
            abs(after - path_length_mm) < 1.0 and np.any(arcs < 1.0)))
        cells, rows, cols = raster_cells(scene, st, step_mm, (float(lo[2]), float(hi[2])), reach, setup.footprint,
                                         shared)
        raster = plan_station(st, cells, rows, cols, setup, seed)
        if raster.poses:
            seed = raster.poses[-1].joints_rad
        out.append(raster)
        log.debug("station %d: %d of %d cells reachable", st.index, len(raster.poses), len(cells))
    return out

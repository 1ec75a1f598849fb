"""Openings cut into a part's surface: a rectangular hatch recessed with 45 deg walls, whose edges an
inspection template measures as trimmed edges (docs/inspection.md, "Openings"). Frame F, millimetres.

The mesh is split (1 into 4) near the opening's outline until its triangles are short against the depth, then
every vertex near the surface inside the outline is moved inward along its normal by the depth times its
distance inside the outline over the depth, clipped to 1: a wall of 45 deg and a floor ``depth_mm`` down.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import open3d as o3d
from tandemscan.config.models import OpeningConfig

EDGE_FRACTION = 0.2  # triangles near an outline are split below this share of the opening's depth
NEAR_SURFACE_MM = 50.0  # vertices further than this from the opening's centre along its normal are not moved


def split_triangles(vertices: np.ndarray, triangles: np.ndarray,
                    needs: Callable[[np.ndarray, np.ndarray], np.ndarray], rounds: int = 8
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint-split (1 into 4) the triangles ``needs(centroids, longest edges)`` marks, until none is."""
    V, T = vertices, triangles
    for _ in range(rounds):
        a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
        longest = np.max(np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                                   np.linalg.norm(a - c, axis=1)]), axis=0)
        mask = needs((a + b + c) / 3.0, longest)
        if not mask.any():
            break
        sel = T[mask]
        edges = np.sort(np.stack([sel[:, [0, 1]], sel[:, [1, 2]], sel[:, [2, 0]]], axis=1).reshape(-1, 2), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = len(V) + inverse.reshape(-1, 3)  # midpoints of edges 01, 12, 20
        V = np.vstack([V, 0.5 * (V[unique[:, 0]] + V[unique[:, 1]])])
        v0, v1, v2 = sel[:, 0], sel[:, 1], sel[:, 2]
        m01, m12, m20 = mid[:, 0], mid[:, 1], mid[:, 2]
        T = np.vstack([T[~mask], np.column_stack([v0, m01, m20]), np.column_stack([m01, v1, m12]),
                       np.column_stack([m20, m12, v2]), np.column_stack([m01, m12, m20])])
    return V, T


def _axes(o: OpeningConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u = np.asarray(o.u_axis, float)
    u /= np.linalg.norm(u)
    v = np.asarray(o.v_axis, float)
    v = v - (v @ u) * u
    v /= np.linalg.norm(v)
    return u, v, np.cross(u, v)


def inside_distance(o: OpeningConfig, points_mm: np.ndarray) -> np.ndarray:
    """(N,) how far inside the opening's outline each point lies in its plane (mm, negative outside), with the
    edges moved outward by ``edge_offsets_mm``; -inf for points more than :data:`NEAR_SURFACE_MM` off its
    plane."""
    u, v, n = _axes(o)
    q = np.asarray(points_mm, float) - np.asarray(o.centre_mm, float)
    pu, pv, pn = q @ u, q @ v, q @ n
    du_lo, du_hi, dv_lo, dv_hi = o.edge_offsets_mm
    d = np.minimum.reduce([pu + o.half_u_mm + du_lo, o.half_u_mm + du_hi - pu,
                           pv + o.half_v_mm + dv_lo, o.half_v_mm + dv_hi - pv])
    return np.where(np.abs(pn) <= NEAR_SURFACE_MM, d, -np.inf)


def cut_openings(mesh: o3d.geometry.TriangleMesh, openings: tuple[OpeningConfig, ...]) -> o3d.geometry.TriangleMesh:
    """The mesh (frame F, mm, outward normals) with each opening recessed into it (module docstring)."""
    V, T = np.asarray(mesh.vertices, float), np.asarray(mesh.triangles, np.int64)
    for o in openings:
        target = EDGE_FRACTION * o.depth_mm

        def needs(c: np.ndarray, e: np.ndarray, o: OpeningConfig = o, target: float = target) -> np.ndarray:
            d = inside_distance(o, c)
            return (e > target) & (d > -2.0 * e) & (d < o.depth_mm + 2.0 * e)

        V, T = split_triangles(V, T, needs, rounds=12)
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
    out.compute_vertex_normals()
    n = np.asarray(out.vertex_normals)
    moved = V.copy()
    for o in openings:
        sink = o.depth_mm * np.clip(inside_distance(o, V) / o.depth_mm, 0.0, 1.0)
        moved -= sink[:, None] * n
    out.vertices = o3d.utility.Vector3dVector(moved)
    out.compute_vertex_normals()
    out.compute_triangle_normals()
    return out

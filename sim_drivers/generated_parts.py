"""Generated parts of different kinds for the alignment and inspection tests and benchmarks: a CAD mesh as a
customer's file may have it (open, wound either way), a measured cloud of the side a scanner sees, with
seeded dents and bulges, and a random misplacement of it (docs/inspection-method.md, "Alignment").

- :func:`arch_panel`: a 120 deg cylinder arch (2.2 m radius, crown at 1.6 m, 4 m long) with a door-surround
  pad at its crown, an open mesh wound with its normals toward the axis;
- :func:`extrusion`: a 3 m straight extrusion of a convex, lopsided profile with end caps (closed);
- :func:`double_curved`: a closed, lopsided egg (double curvature everywhere).

Frame F, millimetres. The truth (outward normals, the defects, the misplacement) stays here: the product
sees the mesh and the points only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from tandemscan.pipeline.geometry import frames as F


@dataclass(frozen=True)
class SurfaceDefect:
    """A smooth dent (depth < 0) or bulge (> 0) of the measured surface along its outward normal: a raised
    cosine of ``radius_mm`` about ``centre_mm`` (a point of the CAD surface, frame F)."""

    centre_mm: tuple[float, float, float]
    radius_mm: float
    depth_mm: float

    def displacement_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """(N,) displacement along the outward normal at ``points_mm`` (mm)."""
        d = np.linalg.norm(np.asarray(points_mm, float) - self.centre_mm, axis=1)
        return np.where(d < self.radius_mm, 0.5 * self.depth_mm * (1.0 + np.cos(np.pi * d / self.radius_mm)), 0.0)


@dataclass(frozen=True)
class GeneratedPart:
    """A part's CAD mesh (``mesh``: as the file has it), the true outward unit normal of each of its triangles,
    which triangles a scanner sees (``seen``) and the seeded defects."""

    name: str
    mesh: o3d.geometry.TriangleMesh
    outward: np.ndarray  # (T, 3)
    seen: np.ndarray  # (T,) bool
    defects: tuple[SurfaceDefect, ...]

    def measured(self, n: int, noise_mm: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """About ``n`` points (frame F, mm) spread evenly over the seen triangles (random ones thinned to one a
        cube of the spacing, as even as a scanner's grid), moved by the defects and by Gaussian noise of
        ``noise_mm`` along the outward normal, and their outward unit normals (toward the scanner)."""
        V, T = np.asarray(self.mesh.vertices), np.asarray(self.mesh.triangles)
        tri = np.flatnonzero(self.seen)
        a, b, c = V[T[tri, 0]], V[T[tri, 1]], V[T[tri, 2]]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        spacing = np.sqrt(area.sum() / n)
        pick = rng.choice(len(tri), 6 * n, p=area / area.sum())
        u = rng.uniform(size=(len(pick), 2))
        u = np.where(u.sum(axis=1, keepdims=True) > 1.0, 1.0 - u, u)
        p = a[pick] + u[:, :1] * (b[pick] - a[pick]) + u[:, 1:] * (c[pick] - a[pick])
        _, first = np.unique(np.floor(p / spacing).astype(np.int64), axis=0, return_index=True)
        p, pick = p[first], pick[first]
        n = len(p)
        normal = self.outward[tri[pick]]
        shift = rng.normal(0.0, noise_mm, n) + sum((d.displacement_mm(p) for d in self.defects), np.zeros(n))
        return p + shift[:, None] * normal, normal


def random_misplacement(rng: np.random.Generator, max_deg: float = 30.0, max_mm: float = 300.0) -> np.ndarray:
    """``T_W_F``: a turn of up to ``max_deg`` about a random axis through the CAD origin, then a move of up to
    ``max_mm`` in a random direction."""
    axis, move = rng.normal(size=3), rng.normal(size=3)
    angle = np.radians(rng.uniform(0.0, max_deg))
    return F.from_rotvec(move / np.linalg.norm(move) * rng.uniform(0.0, max_mm), axis / np.linalg.norm(axis) * angle)


def _grid_mesh(xyz: np.ndarray) -> o3d.geometry.TriangleMesh:
    """A triangle mesh of an (nu, nv, 3) grid of vertices, two triangles a cell, wound by the grid's order."""
    nu, nv = xyz.shape[:2]
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(xyz.reshape(-1, 3)), o3d.utility.Vector3iVector(tris))


def _normals(mesh: o3d.geometry.TriangleMesh) -> np.ndarray:
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _smoothstep(x: np.ndarray, edge: float, width: float) -> np.ndarray:
    """1 inside ``|x| < edge``, 0 beyond ``edge + width``, a smooth cosine between."""
    t = np.clip((np.abs(x) - edge) / width, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * t))


def arch_panel(step_mm: float = 50.0) -> GeneratedPart:
    """The fuselage barrel panel: a 120 deg arch of radius 2.2 m about an axis along x at z = -600 mm (crown at
    1.6 m), 4 m long (x -2000..2000), a 12 mm door-surround pad of 800 x 700 mm at its crown (x 500); an open
    mesh wound with its normals toward the axis, as the customer's file was. Defects: a dent on the crown, a
    bulge on each flank."""
    R, axis_z = 2200.0, -600.0
    x = np.linspace(-2000.0, 2000.0, int(4000 / step_mm) + 1)
    th = np.linspace(-np.radians(60.0), np.radians(60.0), int(R * np.radians(120.0) / step_mm) + 1)
    X, TH = np.meshgrid(x, th, indexing="ij")
    r = R + 12.0 * _smoothstep(X - 500.0, 300.0, 100.0) * _smoothstep(R * TH, 250.0, 100.0)
    grid = np.stack([X, r * np.sin(TH), axis_z + r * np.cos(TH)], axis=-1)
    outward = _grid_mesh(grid)  # x then the angle toward +y: the normal points away from the axis
    normals = _normals(outward)
    if np.mean(np.einsum("ij,ij->i", normals, np.asarray(outward.vertices)[np.asarray(outward.triangles)[:, 0]]
                         - [0.0, 0.0, axis_z])) < 0:
        normals = -normals
        outward.triangles = o3d.utility.Vector3iVector(np.asarray(outward.triangles)[:, ::-1].copy())
    inward = o3d.geometry.TriangleMesh(outward.vertices, o3d.utility.Vector3iVector(
        np.asarray(outward.triangles)[:, ::-1].copy()))

    def on_arch(x_mm: float, deg: float) -> tuple[float, float, float]:
        t = np.radians(deg)
        return (x_mm, R * np.sin(t), axis_z + R * np.cos(t))

    defects = (SurfaceDefect(on_arch(-900.0, 8.0), 120.0, -0.4), SurfaceDefect(on_arch(1300.0, -40.0), 120.0, 0.4),
               SurfaceDefect(on_arch(-300.0, 45.0), 120.0, 0.4))
    return GeneratedPart("arch", inward, normals, np.ones(len(normals), bool), defects)


#: a convex profile in (x, z), mm, counter-clockwise seen from +y, no symmetry
_PROFILE = np.array([[0.0, 0.0], [300.0, 0.0], [300.0, 90.0], [200.0, 170.0], [40.0, 150.0], [0.0, 100.0]])


def extrusion(length_mm: float = 3000.0, step_mm: float = 100.0) -> GeneratedPart:
    """A straight extrusion of a lopsided convex profile along y (0..``length_mm``), closed by its end caps and
    wound outward; the scanner sees every face but the bottom (z = 0) it lies on. Defects: a dent on the top
    face, a bulge on a slanted side, a dent on an end cap."""
    y = np.linspace(0.0, length_mm, int(length_mm / step_mm) + 1)
    k = len(_PROFILE)
    verts = np.array([[px, yy, pz] for yy in y for px, pz in _PROFILE])
    tris = []
    for j in range(len(y) - 1):
        for i in range(k):
            a, b = j * k + i, j * k + (i + 1) % k
            tris += [[a, b + k, b], [a, a + k, b + k]]
    end = (len(y) - 1) * k
    tris += [[0, i, i + 1] for i in range(1, k - 1)] + [[end, end + i + 1, end + i] for i in range(1, k - 1)]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(np.array(tris)))
    normals = _normals(mesh)
    centroids = verts[np.array(tris)].mean(axis=1)
    if np.mean(np.einsum("ij,ij->i", normals, centroids - centroids.mean(axis=0))) < 0:
        mesh.triangles = o3d.utility.Vector3iVector(np.array(tris)[:, ::-1].copy())
        normals = -normals
    seen = ~((np.abs(normals[:, 2] + 1.0) < 1e-9) & (centroids[:, 2] < 1e-6))
    defects = (SurfaceDefect((120.0, 1100.0, 160.0), 80.0, -0.4),
               SurfaceDefect((250.0, 2200.0, 130.0), 70.0, 0.4), SurfaceDefect((150.0, 0.0, 70.0), 50.0, -0.4))
    return GeneratedPart("extrusion", mesh, normals, seen, defects)


def double_curved(resolution: int = 60) -> GeneratedPart:
    """A closed egg, about 1.6 x 0.9 x 0.6 m, lopsided in every direction (no rigid symmetry), standing on
    z = 100 mm, wound outward; the scanner sees its upper two thirds. Defects: a dent on top, a bulge on a
    side."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution)
    v = np.asarray(sphere.vertices)
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    shaped = np.c_[800.0 * x, 450.0 * y * (1.0 + 0.3 * x),
                   300.0 * z * (1.0 + 0.2 * x) + 80.0 * x * y + 60.0 * y * y + 400.0]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(shaped), sphere.triangles)
    normals = _normals(mesh)
    centroids = shaped[np.asarray(mesh.triangles)].mean(axis=1)
    seen = centroids[:, 2] > 300.0
    top = shaped[np.argmax(shaped[:, 2] - 0.001 * shaped[:, 0])]
    side = shaped[np.argmin(np.abs(shaped[:, 2] - 480.0) + np.abs(shaped[:, 0] - 300.0) + 1e3 * (shaped[:, 1] < 0))]
    defects = (SurfaceDefect(tuple(top), 120.0, -0.4), SurfaceDefect(tuple(side), 120.0, 0.4))
    return GeneratedPart("double-curved", mesh, normals, seen, defects)


PARTS = {"arch": arch_panel, "extrusion": extrusion, "double-curved": double_curved}

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


# --- parts a new customer brings (docs/inspection-method.md, "Alignment") ----------------------------------------


def _soup_to_closed(pieces: list[tuple[np.ndarray, np.ndarray]]) -> o3d.geometry.TriangleMesh:
    """One mesh of (vertices, triangles) pieces whose touching edges share exact vertex positions, the positions
    merged (so that the pieces' seams are closed), degenerate triangles dropped."""
    verts, tris, base = [], [], 0
    for v, t in pieces:
        verts.append(np.asarray(v, float))
        tris.append(np.asarray(t, np.int64) + base)
        base += len(v)
    V, T = np.vstack(verts), np.vstack(tris)
    key, inverse = np.unique(np.round(V, 6), axis=0, return_inverse=True)
    T = inverse.ravel()[T]
    T = T[(T[:, 0] != T[:, 1]) & (T[:, 1] != T[:, 2]) & (T[:, 0] != T[:, 2])]
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(key), o3d.utility.Vector3iVector(T))


def _outward(mesh: o3d.geometry.TriangleMesh) -> tuple[o3d.geometry.TriangleMesh, np.ndarray]:
    """A closed mesh wound outward (positive enclosed volume) and its unit triangle normals."""
    from tandemscan.pipeline.geometry.part import signed_volume_mm3

    if signed_volume_mm3(mesh) < 0:
        mesh.triangles = o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[:, ::-1].copy())
    return mesh, _normals(mesh)


def _cap(polygon, z_mm: float, up: bool) -> tuple[np.ndarray, np.ndarray]:
    """A planar face at height ``z_mm``: a shapely polygon (holes allowed) triangulated on its own vertices,
    wound with its normal up (+z) or down."""
    import shapely

    tri = shapely.constrained_delaunay_triangles(polygon)
    verts, tris = [], []
    for t in tri.geoms:
        xy = np.asarray(t.exterior.coords)[:3]
        a = np.cross(np.r_[xy[1] - xy[0], 0.0], np.r_[xy[2] - xy[0], 0.0])[2]
        if (a > 0) != up:
            xy = xy[::-1]
        tris.append(np.arange(len(verts), len(verts) + 3))
        verts += [[x, y, z_mm] for x, y in xy]
    return np.array(verts), np.array(tris)


def _walls(ring_xy: np.ndarray, z0_mm: float, z1_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertical quads (two triangles each) along a closed ring of (x, y) between two heights."""
    ring = np.asarray(ring_xy, float)
    if np.allclose(ring[0], ring[-1]):
        ring = ring[:-1]
    k = len(ring)
    V = np.r_[np.c_[ring, np.full(k, z0_mm)], np.c_[ring, np.full(k, z1_mm)]]
    i = np.arange(k)
    j = (i + 1) % k
    return V, np.r_[np.c_[i, j, j + k], np.c_[i, j + k, i + k]]


def _prism(polygon, z0_mm: float, z1_mm: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """A shapely polygon (holes allowed) extruded from ``z0_mm`` to ``z1_mm``: bottom, top and every ring's wall,
    wound outward (the outline counter-clockwise, the holes clockwise, seen from +z)."""
    import shapely

    polygon = shapely.orient_polygons(polygon)
    pieces = [_cap(polygon, z0_mm, False), _cap(polygon, z1_mm, True), _walls(polygon.exterior.coords, z0_mm, z1_mm)]
    return pieces + [_walls(h.coords, z0_mm, z1_mm) for h in polygon.interiors]


def _sample_edges(ring, step_mm: float):
    """A shapely ring or polygon with its edges split to at most ``step_mm`` (a sharp outline, finer triangles)."""
    import shapely

    return shapely.segmentize(ring, step_mm)


def _taper(x_mm: float, span_mm: float) -> float:
    """A blade section's scale at span position ``x_mm``: 1 at the root (-span/2), 0.8 at the tip."""
    return 1.0 - 0.2 * (x_mm / span_mm + 0.5)


def twisted_blade(span_mm: float = 1500.0, chord_mm: float = 500.0, twist_deg: float = 25.0) -> GeneratedPart:
    """A wind-blade segment: an 8 % thick cambered airfoil (NACA 2408 shape, trailing edge 0.7 mm thick) of
    ``chord_mm`` along y at the root, 0.8 of it at the tip, swept ``span_mm`` along x and twisted by ``twist_deg``
    about its quarter-chord line
    (z = 900 mm, held by a fixture the mesh does not show); closed by a thin trailing-edge face and flat tip
    faces, wound outward; the scanner sees every face but the tips. Defects: a dent on the suction side, a
    bulge near the trailing edge on the pressure side."""
    n_chord, n_span = 60, 31
    beta = np.linspace(0.0, np.pi, n_chord)
    xc = 0.5 * (1.0 - np.cos(beta))  # cosine spacing: fine at both edges
    t, m, p = 0.08, 0.02, 0.4
    yt = 5 * t * (0.2969 * np.sqrt(xc) - 0.1260 * xc - 0.3516 * xc**2 + 0.2843 * xc**3 - 0.1015 * xc**4)
    yc = np.where(xc < p, m / p**2 * (2 * p * xc - xc**2), m / (1 - p) ** 2 * (1 - 2 * p + 2 * p * xc - xc**2))
    upper = np.c_[xc, yc + yt]
    lower = np.c_[xc, yc - yt]
    ring = np.r_[upper[::-1], lower[1:]] * chord_mm  # TE upper -> LE -> TE lower: (chord, thickness) mm
    ring[:, 0] -= 0.25 * chord_mm
    xs = np.linspace(-0.5 * span_mm, 0.5 * span_mm, n_span)
    k = len(ring)
    rows = []
    for x in xs:
        a = np.radians(twist_deg) * (x / span_mm + 0.5)
        c, s = np.cos(a), np.sin(a)
        q = ring * _taper(x, span_mm)
        rows.append(np.c_[np.full(k, x), c * q[:, 0] - s * q[:, 1], 900.0 + s * q[:, 0] + c * q[:, 1]])
    V = np.vstack(rows)
    idx = np.arange(n_span * k).reshape(n_span, k)
    i = np.arange(k)
    j = (i + 1) % k  # the last edge closes the ring across the trailing edge: the thin TE face
    tris = [np.c_[idx[:-1, i].ravel(), idx[1:, i].ravel(), idx[1:, j].ravel()],
            np.c_[idx[:-1, i].ravel(), idx[1:, j].ravel(), idx[:-1, j].ravel()]]
    for end, sign in ((idx[0], 1), (idx[-1], -1)):  # tip faces: fans from the ring's centroid
        centre = len(V)
        V = np.r_[V, [V[end].mean(axis=0)]]
        fan = np.c_[np.full(k, centre), end[i], end[j]] if sign > 0 else np.c_[np.full(k, centre), end[j], end[i]]
        tris.append(fan)
    mesh, normals = _outward(o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V),
                                                       o3d.utility.Vector3iVector(np.vstack(tris))))
    seen = np.abs(normals[:, 0]) < 0.9

    def on_side(x_mm: float, chord_share: float, upper_side: bool) -> tuple[float, float, float]:
        a = np.radians(twist_deg) * (x_mm / span_mm + 0.5)
        u = int(np.argmin(np.abs(xc - chord_share)))
        q = ((upper if upper_side else lower)[u] * chord_mm - [0.25 * chord_mm, 0.0]) * _taper(x_mm, span_mm)
        return (x_mm, np.cos(a) * q[0] - np.sin(a) * q[1], 900.0 + np.sin(a) * q[0] + np.cos(a) * q[1])

    defects = (SurfaceDefect(on_side(-300.0, 0.35, True), 60.0, -0.4), SurfaceDefect(on_side(350.0, 0.7, False),
                                                                                      40.0, 0.4))
    return GeneratedPart("twisted-blade", mesh, normals, seen, defects)


def stiffened_panel() -> GeneratedPart:
    """A flat 1600 x 900 x 4 mm skin lying on the floor, three 30 mm stringers (4 mm blades) along x on top
    and four lightening holes through it (two round, one slot, one square); closed pieces, each wound outward,
    the stringers standing on the skin (separate bodies, as a CAD export of an assembly has them). The scanner
    sees every face but the skin's underside. Defects: a dent and a bulge on the skin, a bulge on a stringer."""
    import shapely

    skin = shapely.box(-800.0, -450.0, 800.0, 450.0)
    holes = [shapely.Point(-450.0, -225.0).buffer(90.0, 16), shapely.Point(350.0, 225.0).buffer(70.0, 16),
             shapely.box(-120.0, 150.0, 180.0, 300.0), shapely.box(420.0, -320.0, 560.0, -180.0)]
    skin = _sample_edges(skin.difference(shapely.union_all(holes)), 100.0)
    pieces = _prism(skin, 0.0, 4.0)
    for y in (-300.0, 0.0, 330.0):
        pieces += _prism(_sample_edges(shapely.box(-780.0, y - 2.0, 780.0, y + 2.0), 100.0), 4.0, 34.0)
    mesh = _soup_to_closed(pieces)
    normals = _normals(mesh)
    c = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    seen = ~((normals[:, 2] < -0.9) & (c[:, 2] < 1e-6))
    defects = (SurfaceDefect((-250.0, -150.0, 4.0), 60.0, -0.4), SurfaceDefect((300.0, -380.0, 4.0), 50.0, 0.4),
               SurfaceDefect((0.0, 2.0, 20.0), 30.0, 0.4))
    return GeneratedPart("stiffened-panel", mesh, normals, seen, defects)


def barrel_shell(length_mm: float = 2000.0, radius_mm: float = 1800.0, skin_mm: float = 3.0,
                 half_angle_deg: float = 70.0, step_mm: float = 50.0) -> GeneratedPart:
    """An open fuselage barrel section: a 3 mm skin of ``radius_mm`` (outside), ``length_mm`` along x, from
    -``half_angle_deg`` to + about the crown, its axis at z = 200 mm (the edges 0.8 m up on a fixture the mesh
    does not show), a 4 mm doubler pad of 700 x 600 mm on its outside (x 450 mm, 20 deg off the crown); a closed
    thin solid wound outward, measured on both sides (outside and inside). Defects: a dent on the outside of the
    crown, a bulge on the inside (toward the axis) of a flank."""
    axis_z = 200.0
    x = np.linspace(-0.5 * length_mm, 0.5 * length_mm, int(length_mm / step_mm) + 1)
    th = np.linspace(-np.radians(half_angle_deg), np.radians(half_angle_deg),
                     int(radius_mm * np.radians(2 * half_angle_deg) / step_mm) + 1)
    X, TH = np.meshgrid(x, th, indexing="ij")
    pieces = []
    pad = 4.0 * _smoothstep(X - 450.0, 250.0, 100.0) * _smoothstep(radius_mm * (TH - np.radians(20.0)), 200.0, 100.0)
    grids = [np.stack([X, r * np.sin(TH), axis_z + r * np.cos(TH)], axis=-1) for r in (radius_mm + pad,
                                                                                      radius_mm - skin_mm)]
    for g in grids:
        m = _grid_mesh(g)
        pieces.append((np.asarray(m.vertices), np.asarray(m.triangles)))
    outer, inner = grids
    for a, b in ((outer[0], inner[0]), (outer[-1], inner[-1]), (outer[:, 0], inner[:, 0]),
                 (outer[:, -1], inner[:, -1])):
        m = _grid_mesh(np.stack([a, b], axis=1))  # the skin's cut faces: strips between the outer and inner edge
        pieces.append((np.asarray(m.vertices), np.asarray(m.triangles)))
    mesh = _soup_to_closed(pieces)
    from tandemscan.pipeline.inspection.cad_orientation import consistent_winding

    flip, _ = consistent_winding(np.asarray(mesh.triangles))
    mesh.triangles = o3d.utility.Vector3iVector(np.where(flip[:, None], np.asarray(mesh.triangles)[:, ::-1],
                                                         np.asarray(mesh.triangles)))
    mesh, normals = _outward(mesh)
    c = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    r = np.hypot(c[:, 1], c[:, 2] - axis_z)
    radial = np.abs(np.einsum("ij,ij->i", normals, np.c_[np.zeros(len(c)), c[:, 1], c[:, 2] - axis_z] / r[:, None]))
    seen = radial > 0.9  # both skins, not the 3 mm cut faces

    def on_skin(x_mm: float, deg: float, r_mm: float) -> tuple[float, float, float]:
        t = np.radians(deg)
        return (x_mm, r_mm * np.sin(t), axis_z + r_mm * np.cos(t))

    defects = (SurfaceDefect(on_skin(-400.0, 5.0, radius_mm), 80.0, -0.4),
               SurfaceDefect(on_skin(500.0, -35.0, radius_mm - skin_mm), 80.0, 0.4))
    return GeneratedPart("barrel-shell", mesh, normals, seen, defects)


def pocket_box() -> GeneratedPart:
    """A machined block, 900 x 600 x 350 mm on the floor, sharp edges, with a 300 x 200 x 60 mm pocket
    recessed into its top off the centre (toward +x +y) and a 40 x 40 mm chamfer-free step notch on one top
    edge; closed, wound outward; the scanner sees every face but the bottom. Defects: a dent on the top, a
    bulge on a side, a bulge on the pocket's floor."""
    import shapely

    top_outline = _sample_edges(shapely.box(-450.0, -300.0, 450.0, 300.0), 150.0)
    pocket = _sample_edges(shapely.box(50.0, 20.0, 350.0, 220.0), 100.0)
    pieces = [_cap(shapely.orient_polygons(top_outline), 0.0, False),
              _walls(shapely.orient_polygons(top_outline).exterior.coords, 0.0, 350.0),
              _cap(shapely.orient_polygons(top_outline.difference(pocket)), 350.0, True),
              _cap(pocket, 290.0, True)]
    v, t = _walls(shapely.orient_polygons(pocket).exterior.coords, 290.0, 350.0)
    pieces.append((v, t[:, ::-1]))  # the pocket's walls face into the pocket
    mesh, normals = _outward(_soup_to_closed(pieces))
    c = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    seen = ~((normals[:, 2] < -0.9) & (c[:, 2] < 1e-6))
    defects = (SurfaceDefect((-200.0, -100.0, 350.0), 60.0, -0.4), SurfaceDefect((100.0, -300.0, 200.0), 50.0, 0.4),
               SurfaceDefect((200.0, 120.0, 290.0), 40.0, 0.4))
    return GeneratedPart("pocket-box", mesh, normals, seen, defects)


def near_symmetric(boss_mm: float = 15.0) -> GeneratedPart:
    """A cover plate, 1000 x 600 x 60 mm on the floor, symmetric but for one small boss (radius and height
    ``boss_mm``) near a corner of its top: turned 180 deg about z it fits all but 0.2 % of its area. Closed pieces
    wound outward; the scanner sees every face but the bottom. Defects: a dent and a bulge on the top."""
    import shapely

    plate = _prism(_sample_edges(shapely.box(-500.0, -300.0, 500.0, 300.0), 100.0), 0.0, 60.0)
    boss = _prism(shapely.Point(380.0, 200.0).buffer(boss_mm, 8), 60.0, 60.0 + boss_mm)
    mesh = _soup_to_closed(plate + boss)
    normals = _normals(mesh)
    c = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    seen = ~((normals[:, 2] < -0.9) & (c[:, 2] < 1e-6))
    defects = (SurfaceDefect((-250.0, -100.0, 60.0), 60.0, -0.4), SurfaceDefect((150.0, 120.0, 60.0), 60.0, 0.4))
    return GeneratedPart("near-symmetric", mesh, normals, seen, defects)


def chamfered_bar(chamfer_mm: float = 10.0) -> GeneratedPart:
    """A bar, 800 x 120 x 80 mm on the floor along x, symmetric but for a 45 deg chamfer of ``chamfer_mm`` on the top
    edge of its +x end: turned 180 deg about any of its axes it fits all but that edge. Closed, wound outward; the
    scanner sees every face but the bottom. Defects: a dent on the top, a bulge on a side."""
    import shapely

    c = chamfer_mm
    profile = shapely.Polygon([(-400.0, 0.0), (400.0, 0.0), (400.0, 80.0 - c), (400.0 - c, 80.0), (-400.0, 80.0)])
    pieces = [(v[:, [0, 2, 1]], t) for v, t in _prism(_sample_edges(profile, 40.0), -60.0, 60.0)]  # (x, z) along y
    mesh, normals = _outward(_soup_to_closed(pieces))
    tc = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    seen = ~((normals[:, 2] < -0.9) & (tc[:, 2] < 1e-6))
    defects = (SurfaceDefect((-200.0, 20.0, 80.0), 40.0, -0.4), SurfaceDefect((100.0, -60.0, 40.0), 30.0, 0.4))
    return GeneratedPart("chamfered-bar", mesh, normals, seen, defects)


CUSTOMER_PARTS = {"twisted-blade": twisted_blade, "stiffened-panel": stiffened_panel, "barrel-shell": barrel_shell,
                  "pocket-box": pocket_box, "near-symmetric": near_symmetric, "chamfered-bar": chamfered_bar}
"""Parts unlike the shipped ones and :data:`PARTS`, as a new customer brings them."""


@dataclass(frozen=True)
class CadExport:
    """How a customer's CAD export departs from a clean, outward-wound millimetre mesh: ``winding`` "outward",
    "inward" or "mixed" (each triangle turned with probability 0.4), ``open_share`` of the triangles left out
    (an open, non-watertight mesh), ``soup`` (every triangle its own three vertices, as STL stores them),
    ``scale`` (0.001: the file in metres), ``subdivide`` (midpoint splits, each 4x the triangles)."""

    winding: str = "outward"
    open_share: float = 0.0
    soup: bool = False
    scale: float = 1.0
    subdivide: int = 0

    def write(self, part: GeneratedPart, path, seed: int = 0):
        """Write ``part``'s mesh so changed to ``path`` (.stl .ply .obj by its suffix); returns the path."""
        rng = np.random.default_rng(seed)
        mesh = part.mesh
        if self.subdivide:
            mesh = mesh.subdivide_midpoint(self.subdivide)
        V, T = np.asarray(mesh.vertices) * self.scale, np.asarray(mesh.triangles).copy()
        if self.winding == "inward":
            T = T[:, ::-1]
        elif self.winding == "mixed":
            turn = rng.uniform(size=len(T)) < 0.4
            T[turn] = T[turn][:, ::-1]
        if self.open_share:
            T = T[rng.uniform(size=len(T)) >= self.open_share]
        if self.soup:
            V, T = V[T.ravel()], np.arange(3 * len(T)).reshape(-1, 3)
        out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
        out.compute_triangle_normals()
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # OBJ: "no triangle normals"
            written = o3d.io.write_triangle_mesh(str(path), out, write_vertex_normals=False)
        if not written:
            raise OSError(f"{path}: not written")
        return path

"""The measured part as a CAD triangle mesh (mm): loaded from a file or the parametric train nose.

Part frame F (the floor frame of the simulated cell): floor at z = 0, part centred on x = y = 0, length
along x with the nose towards +x.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np
import open3d as o3d
from tandemscan.config.models import PartConfig
from tandemscan.pipeline.geometry.openings import cut_openings
from tandemscan.pipeline.geometry.units import MM_PER_UNIT
from tandemscan.pipeline.io.cloud_io import has_ply_magic
from tandemscan.pipeline.planning.plan import PartIdentity

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".stl", ".ply", ".obj", ".off", ".gltf", ".glb")


class PartMeshError(Exception):
    """The part mesh is missing, unreadable or empty."""


def load_part_mesh(part: PartConfig) -> o3d.geometry.TriangleMesh:
    """The CAD mesh of ``part``: the file ``part.mesh`` (mm, in ``part.mesh_units``; :func:`wound_outward`) or,
    when unset, :func:`train_nose_mesh`; with ``part.openings`` cut into it
    (:func:`~tandemscan.pipeline.geometry.openings.cut_openings`)."""
    if part.mesh is None:
        mesh = train_nose_mesh(part)
    else:
        mesh = read_cad_mesh(part.mesh, part.mesh_units)
    return cut_openings(mesh, part.openings) if part.openings else mesh


def read_cad_mesh(path: Path | str, units: str = "mm", what: str = "mesh") -> o3d.geometry.TriangleMesh:
    """A CAD mesh file as a job takes it (``[part] mesh``, without its openings): read into millimetres from
    ``units`` (:func:`read_mesh_file`) and wound outward (:func:`wound_outward`)."""
    return wound_outward(read_mesh_file(Path(path), what, units), str(path))


def wound_outward(mesh: o3d.geometry.TriangleMesh, name: str) -> o3d.geometry.TriangleMesh:
    """``mesh`` with each connected patch wound consistently, a closed one outward by its volume, an open one as
    most of its area is in the file (:func:`~tandemscan.pipeline.inspection.cad_orientation.wind`): the planner
    looks along the normals and the simulator moves its deviations along them, so a file wound inward or
    inconsistently (each triangle as its exporter pleased) would have them look from inside. Says so in the log
    (``name``: the file) where it turned triangles; the mesh itself where none."""
    from tandemscan.pipeline.inspection.cad_orientation import wind  # the winding rules of the inspection's sign

    T = np.asarray(mesh.triangles)
    o = wind(np.asarray(mesh.vertices), T)
    if not o.reversed.any():
        return mesh
    log.warning("%s: %s", name, o.note.replace("deviations are signed with them reversed", "planned and simulated "
                                                "with them reversed"))
    mesh.triangles = o3d.utility.Vector3iVector(np.where(o.reversed[:, None], T[:, ::-1], T))
    mesh.compute_vertex_normals()
    return mesh


def read_mesh_file(path: Path, what: str = "mesh", units: str = "mm") -> o3d.geometry.TriangleMesh:
    """Read an STL/PLY/OBJ mesh into millimetres (its coordinates in ``units``, a key of
    :data:`~tandemscan.pipeline.geometry.units.MM_PER_UNIT`), with vertex normals; raises :class:`PartMeshError`
    whose message names the file and calls it ``what`` (e.g. ``"CAD mesh"``)."""
    path = Path(path)
    if not path.is_file():
        raise PartMeshError(f"{path}: {what} file not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise PartMeshError(f"{path}: unsupported mesh format (use one of {', '.join(MESH_SUFFIXES)})")
    if not has_ply_magic(path):
        raise PartMeshError(f"{path}: not a PLY file (no 'ply' magic at the start)")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # we raise our own error
        mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise PartMeshError(f"{path}: no triangles could be read (formats: {' '.join(MESH_SUFFIXES)})")
    if MM_PER_UNIT[units] != 1.0:
        mesh.scale(MM_PER_UNIT[units], center=np.zeros(3))
    mesh.compute_vertex_normals()
    return mesh


def enclosed_volume_mm3(vertices_mm: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume (mm^3) enclosed by the (M, 3) vertex-index ``triangles``: positive when a closed surface
    (:func:`triangles_closed`) is wound counter-clockwise seen from outside, i.e. its normals point outward."""
    v, t = np.asarray(vertices_mm, dtype=np.float64), np.asarray(triangles, dtype=np.int64)
    return float(np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6.0)


def signed_volume_mm3(mesh: o3d.geometry.TriangleMesh) -> float:
    """:func:`enclosed_volume_mm3` of an Open3D mesh (mm^3)."""
    return enclosed_volume_mm3(np.asarray(mesh.vertices), np.asarray(mesh.triangles))


def triangles_closed(t: np.ndarray) -> bool:
    """True when every edge of the (M, 3) vertex-index triangles is shared by exactly two triangles that traverse
    it in opposite directions: a closed, consistently oriented surface, whose signed volume means something."""
    t = np.asarray(t, dtype=np.int64)
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    n = int(t.max()) + 1 if len(t) else 0
    forward = np.unique(directed[:, 0] * n + directed[:, 1], return_counts=True)
    backward = np.unique(directed[:, 1] * n + directed[:, 0])
    return bool(np.all(forward[1] == 1) and len(forward[0]) == len(backward) and np.array_equal(forward[0], backward))


def _section_profile(s: np.ndarray, part: PartConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-width, bottom height and top height (mm) of the cross-section at nose progress ``s`` in [0, 1]."""
    half_width = 0.5 * part.width_mm * np.sqrt(np.clip(1.0 - s**2, 0.0, None))
    bottom = 0.15 * part.height_mm * s**2
    top = bottom + (part.height_mm - bottom) * np.clip(1.0 - s**1.8, 0.0, None) ** 0.6
    return half_width, bottom, top


def train_nose_mesh(
    part: PartConfig, n_along: int = 140, n_around: int = 180, exponent: float = 3.0
) -> o3d.geometry.TriangleMesh:
    """A watertight parametric high-speed-train nose (mm), outward normals.

    A constant rounded-box section (superellipse of ``exponent``) for ``body_length_mm``, then a nose
    whose width and height shrink smoothly to a blunt tip at x = +length/2; both ends are capped.
    """
    L = part.length_mm
    x0 = -0.5 * L
    nose_start = x0 + min(part.body_length_mm, 0.9 * L)
    s_tip = 0.97
    x = np.linspace(x0, 0.5 * L, n_along)
    s = np.clip((x - nose_start) / (0.5 * L - nose_start), 0.0, 1.0) * s_tip
    half_width, bottom, top = _section_profile(s, part)

    phi = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    c, si = np.cos(phi), np.sin(phi)
    ey = np.sign(c) * np.abs(c) ** (2.0 / exponent)
    ez = np.sign(si) * np.abs(si) ** (2.0 / exponent)
    zc = 0.5 * (top + bottom)
    half_h = 0.5 * (top - bottom)
    vx = np.repeat(x, n_around)
    vy = (half_width[:, None] * ey[None, :]).ravel()
    vz = (zc[:, None] + half_h[:, None] * ez[None, :]).ravel()
    vertices = [np.c_[vx, vy, vz]]

    tris = []
    idx = np.arange(n_along * n_around).reshape(n_along, n_around)
    a = idx[:-1, :]
    b = np.roll(idx[:-1, :], -1, axis=1)
    cc = idx[1:, :]
    d = np.roll(idx[1:, :], -1, axis=1)
    tris.append(np.c_[a.ravel(), cc.ravel(), b.ravel()])
    tris.append(np.c_[b.ravel(), cc.ravel(), d.ravel()])

    # caps: a fan to a centre vertex at each end (the tip one slightly forward: a rounded nose)
    n = n_along * n_around
    back_centre = [x0, 0.0, zc[0]]
    tip_centre = [0.5 * L + 0.25 * half_h[-1], 0.0, zc[-1]]
    vertices.append(np.array([back_centre, tip_centre]))
    ring0, ring1 = idx[0], idx[-1]
    tris.append(np.c_[np.full(n_around, n), ring0, np.roll(ring0, -1)])
    tris.append(np.c_[np.full(n_around, n + 1), np.roll(ring1, -1), ring1])

    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.vstack(vertices)), o3d.utility.Vector3iVector(np.vstack(tris))
    )
    if signed_volume_mm3(mesh) < 0:  # make normals point outward whatever the winding above produced
        mesh.triangles = o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[:, ::-1])
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    return mesh


def part_identity(mesh: o3d.geometry.TriangleMesh) -> PartIdentity:
    """What a plan records of the part it was made for: the mesh's SHA-256 (vertices rounded to 1 um, as int64,
    then the triangles) and its bounding box (F, mm)."""
    v = np.asarray(mesh.vertices)
    t = np.asarray(mesh.triangles)
    digest = hashlib.sha256(np.round(v * 1000.0).astype(np.int64).tobytes())
    digest.update(t.astype(np.int64).tobytes())
    return PartIdentity(sha256=digest.hexdigest(), bbox_min_mm=tuple(round(float(x), 3) for x in v.min(axis=0)),
                        bbox_max_mm=tuple(round(float(x), 3) for x in v.max(axis=0)), triangles=len(t))


def barrel_panel_mesh(length_mm: float = 4000.0, radius_mm: float = 2200.0, crown_mm: float = 1600.0,
                      n_around: int = 121, n_along: int = 80) -> o3d.geometry.TriangleMesh:
    """A fuselage barrel panel standing on the floor (mm, outward normals, watertight): the circular segment of
    ``radius_mm`` whose crown stands ``crown_mm`` above the floor (z = 0), ``length_mm`` along x, centred on
    x = y = 0, closed by the floor and two end faces."""
    zc = crown_mm - radius_mm  # the barrel's axis height (below the floor for a panel lower than its radius)
    half_angle = np.arccos(np.clip(-zc / radius_mm, -1.0, 1.0))  # from the crown to where the arc meets the floor
    phi = np.linspace(-half_angle, half_angle, n_around)
    y = radius_mm * np.sin(phi)
    z = zc + radius_mm * np.cos(phi)
    z[[0, -1]] = 0.0
    x = np.linspace(-0.5 * length_mm, 0.5 * length_mm, n_along)
    vertices = np.c_[np.repeat(x, n_around), np.tile(y, n_along), np.tile(z, n_along)]
    idx = np.arange(n_along * n_around).reshape(n_along, n_around)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tris = [np.c_[a.ravel(), b.ravel(), c.ravel()], np.c_[b.ravel(), d.ravel(), c.ravel()]]  # the skin
    a, b, c, d = idx[:-1, 0], idx[1:, 0], idx[:-1, -1], idx[1:, -1]
    tris += [np.c_[a, b, c], np.c_[c, b, d]]  # the floor face between the two floor edges
    n = len(vertices)  # end faces: fans from a point inside each segment
    vertices = np.vstack([vertices, [[x[0], 0.0, 0.3 * crown_mm], [x[-1], 0.0, 0.3 * crown_mm]]])
    tris += [np.c_[np.full(n_around, n), np.roll(idx[0], -1), idx[0]],
             np.c_[np.full(n_around, n + 1), idx[-1], np.roll(idx[-1], -1)]]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(np.vstack(tris)))
    if signed_volume_mm3(mesh) < 0:
        mesh.triangles = o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[:, ::-1])
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    return mesh

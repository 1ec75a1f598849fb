"""The simulated part as built: the CAD mesh with the deviations of ``[sim.as_built]`` applied, plus the
fixture's reference spheres (``[sim] reference_spheres``), and the truth of each deviation for scoring.

The world scans this mesh; the planner and the inspection see only the CAD mesh. A deviation's truth is
its displacement of the surface along the CAD normal at any CAD point (frame F, mm, + = material above
CAD), known here only (docs/inspection-method.md, "As-built part in the simulator").

Dents and steps are local: the CAD triangles near them are split (midpoints, 1 into 4) until their edges
are short against the dent's radius, so the bell is resolved; the split stops far enough outside a dent
that the displacement there is zero and the surface stays closed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import open3d as o3d
from tandemscan.config.models import CellConfig, PartConfig
from tandemscan.pipeline.geometry.openings import split_triangles
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.sim_drivers.config import DentConfig, StepConfig, WarpConfig

log = logging.getLogger(__name__)

Deviation = DentConfig | WarpConfig | StepConfig
_DENT_EDGE_FRACTION = 0.1  # triangle edges under a dent are split below this share of its radius
_STEP_EDGE_MM = 2.0  # and near a stepped patch below this
_SPHERE_RESOLUTION = 120  # a coarse polyhedron would bias the sphere fits by hundredths of a mm


def dent_centre_on_cad(surface: CadSurface, dent: DentConfig) -> np.ndarray:
    """The dent's centre projected onto the CAD surface (frame F, mm)."""
    return surface.closest(np.array([dent.centre_mm], float)).points_mm[0]


def _bell(rho: np.ndarray) -> np.ndarray:
    """Cosine bell: 1 at rho = 0 falling smoothly to 0 at rho >= 1."""
    return np.where(rho < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.clip(rho, 0.0, 1.0))), 0.0)


def _ramp(x: np.ndarray, warp: WarpConfig) -> np.ndarray:
    return np.clip((x - warp.start_x_mm) / (warp.end_x_mm - warp.start_x_mm), 0.0, 1.0) ** 2


def displacement(dev: Deviation, points_mm: np.ndarray, normals: np.ndarray,
                 centre_mm: np.ndarray | None) -> np.ndarray:
    """(N, 3) displacement (mm, frame F) of the CAD surface points with outward ``normals`` by one
    deviation; ``centre_mm`` is a dent's centre on the CAD surface (:func:`dent_centre_on_cad`)."""
    p, n = np.asarray(points_mm, float), np.asarray(normals, float)
    if isinstance(dev, DentConfig):
        sign = 1.0 if dev.kind == "bulge" else -1.0
        rho = np.linalg.norm(p - centre_mm, axis=1) / dev.radius_mm
        return (sign * dev.depth_mm * _bell(rho))[:, None] * n
    if isinstance(dev, StepConfig):
        inside = np.all((p >= dev.min_mm) & (p <= dev.max_mm), axis=1)
        return (dev.step_mm * inside)[:, None] * n
    g = _ramp(p[:, 0], dev)
    if dev.kind == "bend":
        u = np.asarray(dev.direction, float)
        return dev.amplitude_mm * g[:, None] * (u / np.linalg.norm(u))
    angle = dev.amplitude_mm / 1000.0 * g  # rad: amplitude_mm at 1 m from the axis
    y, z = p[:, 1] - dev.axis_yz_mm[0], p[:, 2] - dev.axis_yz_mm[1]
    c, s = np.cos(angle), np.sin(angle)
    return np.column_stack([np.zeros(len(p)), c * y - s * z - y, s * y + c * z - z])


def normal_deviation(dev: Deviation, surface: CadSurface, points_F_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The truth of one deviation at the CAD points closest to ``points_F_mm``: (closest CAD points (N, 3),
    signed deviation along the outward CAD normal (N,), mm)."""
    cp = surface.closest(points_F_mm)
    centre = dent_centre_on_cad(surface, dev) if isinstance(dev, DentConfig) else None
    return cp.points_mm, np.einsum("ij,ij->i", displacement(dev, cp.points_mm, cp.normals, centre), cp.normals)


def _refinement_test(dev: Deviation,
                     centre: np.ndarray | None) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
    """For a local deviation, which triangles (centroids (N, 3), longest edges (N,)) still need splitting."""
    if isinstance(dev, DentConfig):
        target = _DENT_EDGE_FRACTION * dev.radius_mm
        return lambda c, e: (e > target) & (np.linalg.norm(c - centre, axis=1) < dev.radius_mm + 2.0 * e)
    if isinstance(dev, StepConfig):
        lo, hi = np.asarray(dev.min_mm), np.asarray(dev.max_mm)
        return lambda c, e: (e > _STEP_EDGE_MM) & np.all((c >= lo - 2.0 * e[:, None]) & (c <= hi + 2.0 * e[:, None]),
                                                         axis=1)
    return None


def as_built_mesh(cad: o3d.geometry.TriangleMesh, deviations: tuple[Deviation, ...]) -> o3d.geometry.TriangleMesh:
    """The CAD mesh (frame F, mm) with ``deviations`` applied: split where a local one needs it, then every
    vertex moved by the sum of their displacements (along the CAD vertex normals)."""
    surface = CadSurface(cad)
    centres = [dent_centre_on_cad(surface, d) if isinstance(d, DentConfig) else None for d in deviations]
    V, T = np.asarray(cad.vertices, float), np.asarray(cad.triangles, np.int64)
    for dev, centre in zip(deviations, centres, strict=True):
        needs = _refinement_test(dev, centre)
        if needs is not None:
            V, T = split_triangles(V, T, needs)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(T))
    mesh.compute_vertex_normals()
    n = np.asarray(mesh.vertex_normals)
    moved = V + sum((displacement(d, V, n, c) for d, c in zip(deviations, centres, strict=True)), np.zeros_like(V))
    mesh.vertices = o3d.utility.Vector3dVector(moved)
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    log.info("as-built part: %d deviations, %d triangles (CAD %d)", len(deviations), len(T), len(cad.triangles))
    return mesh


def reference_sphere_meshes(config: CellConfig) -> o3d.geometry.TriangleMesh:
    """The fixture's reference spheres at their CAD centres ([inspection] reference_spheres), frame F."""
    out = o3d.geometry.TriangleMesh()
    r = 0.5 * config.inspection.reference_sphere_diameter_mm
    for sphere in config.inspection.reference_spheres:
        s = o3d.geometry.TriangleMesh.create_sphere(radius=r, resolution=_SPHERE_RESOLUTION)
        out += s.translate(np.array(sphere.centre_mm, float))
    return out


def as_built_part(config: CellConfig) -> PartConfig:
    """``[part]`` with its openings' edges where ``[sim.as_built] openings`` moves them."""
    names = {o.name for o in config.part.openings}
    unknown = sorted({e.opening for e in config.sim.as_built.openings} - names)
    if unknown:
        raise ValueError(f"[sim.as_built] openings {unknown}: no such [part] opening (have {sorted(names)})")
    moved = {e.opening: e.edge_offsets_mm for e in config.sim.as_built.openings}
    openings = tuple(o.model_copy(update={"edge_offsets_mm": tuple(
        a + b for a, b in zip(o.edge_offsets_mm, moved[o.name], strict=True))}) if o.name in moved else o
        for o in config.part.openings)
    return config.part.model_copy(update={"openings": openings})


def scanned_part_mesh(config: CellConfig) -> o3d.geometry.TriangleMesh:
    """What the simulated scanner sees (frame F, mm): the part as built, with the reference spheres when
    ``[sim] reference_spheres``; the CAD mesh itself when neither is configured."""
    mesh = load_part_mesh(as_built_part(config))
    if config.sim.as_built.deviations:
        mesh = as_built_mesh(mesh, config.sim.as_built.deviations)
    if config.sim.reference_spheres:
        mesh += reference_sphere_meshes(config)
        mesh.compute_triangle_normals()
    return mesh

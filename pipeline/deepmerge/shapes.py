"""Varied surfaces for DeepMerge training pairs, generated in code (mm).

Families: smooth blobs (a sphere with random low-frequency radial relief and anisotropic scale), panels
(height fields with bumps and waves, one-sided like a scanned skin), and assemblies of boxes, cylinders,
cones and tori (sharp edges). When the project's part generator is importable the simulated part
(``tandemscan.pipeline.geometry.part.load_part_mesh``) joins the pool.
"""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d

log = logging.getLogger(__name__)

FAMILIES = ("blob", "panel", "assembly")


def _mesh(vertices: np.ndarray, triangles: np.ndarray) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    m.compute_vertex_normals()
    return m


def blob(rng: np.random.Generator, size_mm: float) -> o3d.geometry.TriangleMesh:
    """A sphere with 3-8 random sinusoidal radial reliefs and an anisotropic scale, ``size_mm`` across."""
    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=48)
    v = np.asarray(m.vertices)
    r = np.ones(len(v))
    for _ in range(rng.integers(3, 9)):
        d = rng.normal(size=3)
        r += rng.uniform(0.03, 0.15) * np.sin(rng.uniform(1.0, 5.0) * v @ (d / np.linalg.norm(d)) + rng.uniform(0, 6.3))
    v = v * r[:, None] * rng.uniform(0.5, 1.0, size=3)
    return _mesh(v * size_mm / 2.0, np.asarray(m.triangles))


def panel(rng: np.random.Generator, size_mm: float, n: int = 90) -> o3d.geometry.TriangleMesh:
    """A height field ``size_mm`` square: gaussian bumps, dents and a long wave on a curved sheet."""
    u = np.linspace(-1.0, 1.0, n)
    X, Y = np.meshgrid(u, u)
    Z = rng.uniform(-0.3, 0.3) * X**2 + rng.uniform(-0.3, 0.3) * Y**2
    for _ in range(rng.integers(2, 10)):
        cx, cy = rng.uniform(-1, 1, 2)
        Z += rng.uniform(-0.25, 0.25) * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / rng.uniform(0.01, 0.2))
    Z += rng.uniform(0, 0.08) * np.sin(rng.uniform(2, 8) * (X * np.cos(a := rng.uniform(0, 3.2)) + Y * np.sin(a)))
    V = np.c_[X.ravel(), Y.ravel(), Z.ravel()] * size_mm / 2.0
    i = np.arange(n - 1)
    rows, cols = np.meshgrid(i, i)
    a0 = (rows * n + cols).ravel()
    tri = np.r_[np.c_[a0, a0 + n, a0 + 1], np.c_[a0 + 1, a0 + n, a0 + n + 1]]
    return _mesh(V, tri)


def assembly(rng: np.random.Generator, size_mm: float) -> o3d.geometry.TriangleMesh:
    """Two to four primitives (box, cylinder, cone, torus), randomly sized, turned and placed."""
    G = o3d.geometry.TriangleMesh
    out = G()
    for _ in range(rng.integers(2, 5)):
        kind = rng.integers(4)
        s = rng.uniform(0.3, 0.7, 3)
        if kind == 0:
            m = G.create_box(*s)
            m.translate(-s / 2)
        elif kind == 1:
            m = G.create_cylinder(radius=s[0] / 2, height=s[1], resolution=40, split=8)
        elif kind == 2:
            m = G.create_cone(radius=s[0] / 2, height=s[1], resolution=40, split=8)
        else:
            m = G.create_torus(torus_radius=s[0] / 2, tube_radius=s[2] / 5, radial_resolution=40, tubular_resolution=20)
        m.rotate(o3d.geometry.get_rotation_matrix_from_axis_angle(rng.normal(size=3)), center=(0, 0, 0))
        m.translate(rng.uniform(-0.3, 0.3, 3))
        out += m
    out.scale(size_mm, center=(0, 0, 0))
    out.compute_vertex_normals()
    return out


def simulated_part_mesh() -> o3d.geometry.TriangleMesh | None:
    """The default simulated part, when the part generator is part of this install; else None."""
    try:
        from tandemscan.config.models import PartConfig
        from tandemscan.pipeline.geometry.part import load_part_mesh
    except ImportError:
        return None
    return load_part_mesh(PartConfig())


def random_shape(rng: np.random.Generator, family: str | None = None) -> o3d.geometry.TriangleMesh:
    """One shape of ``family`` (default: a random one), 150-450 mm across."""
    family = family or FAMILIES[rng.integers(len(FAMILIES))]
    size = rng.uniform(150.0, 450.0)
    return {"blob": blob, "panel": panel, "assembly": assembly}[family](rng, size)

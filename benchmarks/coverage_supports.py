"""Coverage of a part on supports: a blade-like slab (2.5 m long, an elliptic section 600 mm x 120 mm) planned on
the default cell resting on the floor and standing 1 m above it; one JSON object on the last line.

For each: coverage of the surface where a scanner pose fits (%), the area booked as facing the floor with no
room for a pose (m^2), the underside seen (m^2: triangles facing more than 60 deg down), scans planned looking
up, the scans and the planning time (s, wall; a shared machine overstates it).
Run: ``nice .venv/bin/python benchmarks/coverage_supports.py``.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import open3d as o3d
from results import publish
from tandemscan.config import load_config
from tandemscan.pipeline.geometry.raycast import make_scene
from tandemscan.pipeline.planning.coverage import seen_triangles, triangle_geometry
from tandemscan.pipeline.planning.parameters import PartPlanning
from tandemscan.pipeline.planning.planner import plan_part


def blade(bottom_mm: float) -> o3d.geometry.TriangleMesh:
    """The slab along x, its lowest point ``bottom_mm`` above the floor (mm)."""
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=1.0, height=2500.0, resolution=48, split=20)
    mesh.rotate(mesh.get_rotation_matrix_from_xyz((0.0, np.pi / 2, 0.0)), center=(0.0, 0.0, 0.0))
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * [1.0, 300.0, 60.0]
                                               + [0.0, 0.0, bottom_mm + 60.0])
    return mesh.compute_vertex_normals()


def bench(bottom_mm: float) -> dict:
    config = load_config()
    start = config.sim.tracking_start
    mesh = blade(bottom_mm)
    cell = PartPlanning.from_config(config)
    t = time.perf_counter()
    plan = plan_part(mesh, cell, tracker_start=(start.x_mm, start.y_mm, np.radians(start.heading_deg)))
    seconds = time.perf_counter() - t
    area, normal, _ = triangle_geometry(mesh)
    seen = seen_triangles(mesh, make_scene(mesh), [p.T_F_S for p in plan.poses], cell.scanner)
    under = normal[:, 2] < -np.cos(np.radians(30.0))
    return {"coverage_pct": round(plan.coverage.coverage_pct, 2),
            "faces_the_floor_m2": round(plan.coverage.floor_contact_mm2 / 1e6, 3),
            "underside_m2": round(float(area[under].sum()) / 1e6, 3),
            "underside_seen_m2": round(float(area[under & seen].sum()) / 1e6, 3),
            "scans_looking_up": int(sum(p.T_F_S[2, 2] > 0.5 for p in plan.poses)),
            "scans": plan.summary()["scans"], "plan_seconds": round(seconds, 2)}


def main() -> int:
    out = {}
    for name, bottom in (("on_floor", 0.0), ("on_supports_1m", 1000.0)):
        figures = bench(bottom)
        print(json.dumps({"blade": name, **figures}), file=sys.stderr)
        out |= {f"{name}_{k}": v for k, v in figures.items()}
    publish("coverage_supports", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A customer's part mesh wound as its exporter pleased (docs/planning.md): the part is read wound outward, so the
planner looks at it from outside and plans what it plans for the clean file."""

from __future__ import annotations

import numpy as np
from tandemscan.config import load_config
from tandemscan.daemon.plans import plan_configured_part
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.sim_drivers.generated_parts import CadExport, pocket_box


def test_a_mesh_wound_every_which_way_is_read_outward_and_planned_as_the_clean_one(tmp_path):
    part = pocket_box()
    plans = {}
    for name, export in (("clean", CadExport()), ("mixed", CadExport(winding="mixed", soup=True))):
        config = load_config(None)
        config = config.model_copy(update={"part": config.part.model_copy(
            update={"mesh": export.write(part, tmp_path / f"{name}.stl")})})
        mesh = load_part_mesh(config.part)
        V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
        assert (np.einsum("ij,ij->i", n, part.outward) > 0).all()  # the soup keeps the triangles' order
        plans[name] = plan_configured_part(config, name)[1]
    assert plans["mixed"].summary()["scans"] == plans["clean"].summary()["scans"]
    assert abs(plans["mixed"].coverage.coverage_pct - plans["clean"].coverage.coverage_pct) < 0.5

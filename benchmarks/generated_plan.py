"""The whole configured part planned as ``tandemscan plan`` does, the tracker chain starting where the simulated
tracking robot stands (``[sim] tracking_start``): the ``--plan generated`` of the benchmarks that run a job."""

from __future__ import annotations

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.pipeline.planning.plan import Plan


def generated_plan(config: CellConfig) -> Plan:
    """The plan of the configured part (mesh file or parametric nose), named ``generated``."""
    from tandemscan.pipeline.geometry.part import load_part_mesh
    from tandemscan.pipeline.planning.parameters import PartPlanning
    from tandemscan.pipeline.planning.planner import plan_part

    start = config.sim.tracking_start
    return plan_part(load_part_mesh(config.part), PartPlanning.from_config(config), name="generated",
                     tracker_start=(start.x_mm, start.y_mm, np.radians(start.heading_deg))).sequence.plan

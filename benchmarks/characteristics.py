"""What the shipped templates' characteristics read from the simulated scanner's own captures (its noise and
ray casting, no plan, no stitching: the part in the CAD frame), and how long their evaluation takes.

- the hatch of ``config/hatch-example.toml`` (its +x edge 0.5 mm out as built): the four edges' actuals from
  twelve views over the hatch (``sim_drivers/scan_views.py``);
- the as-built default part (``config/as-built-example.toml``) over the band the shipped plan scans (views
  every 300 mm along it at two heights, each along the CAD normal there): the default template's statuses and
  actuals (the profiles and sections under the example's general tolerance, +-0.3 mm), and the evaluation's
  seconds per million points.

Prints one JSON object last (mm, s). ``nice python benchmarks/characteristics.py [--seed 1]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config import load_config
from tandemscan.config.inspection_template import load_template, shipped_template
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.inspection.characteristics import MeasuredCloud, evaluate
from tandemscan.pipeline.inspection.decision import DecisionRule
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.sim_drivers.scan_views import views_over
from tandemscan.sim_drivers.world import SimWorld

U_MM = 0.02  # the per-point expanded uncertainty given to the characteristics (no job: no U model)


def characteristics_of(config_file: str, template_file: str, views, rng) -> tuple[dict, float, int]:
    """({id: [status, actual mm]}, evaluation seconds, points) of the template on the captures ``views``
    returns for the simulated world of ``config_file``."""
    config = load_config(config_file)
    world = SimWorld(config)
    cad = CadSurface(load_part_mesh(config.part))
    p = views(world, cad, rng)
    cp = cad.closest(p)
    cloud = MeasuredCloud(p, cp.signed_mm, cp.triangle_ids, np.full(len(p), U_MM), cad)
    t = time.perf_counter()
    band = config.inspection  # the general tolerance of the profiles and sections
    template = load_template(shipped_template(template_file))
    out = evaluate(template.with_general_tolerance(band.tolerance_lower_mm, band.tolerance_upper_mm), cloud,
                   DecisionRule())
    seconds = time.perf_counter() - t
    return {c.id: [c.status, round(c.actual_mm, 4)] for c in out}, seconds, len(p)


def hatch_views(world, cad, rng):
    centres = [(x, 1000.0, z) for x in (-1080.0, -950.0, -820.0) for z in (690.0, 830.0)]
    return views_over(world, centres, (0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (-15.0, 15.0), rng)


def band_views(world, cad, rng):
    centres = np.array([(x, 1100.0, z) for x in range(-1300, 1101, 300) for z in (650.0, 870.0)], float)
    on = cad.closest(centres)
    return np.vstack([views_over(world, [c], n, (1.0, 0.0, 0.0), (0.0,), rng)
                      for c, n in zip(on.points_mm, on.normals, strict=True)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    clean_exit_on_sigterm()
    rng = np.random.default_rng(args.seed)
    hatch, _, hatch_points = characteristics_of("config/hatch-example.toml", "hatch-part.toml", hatch_views, rng)
    band, seconds, points = characteristics_of("config/as-built-example.toml", "default-part.toml", band_views, rng)
    publish("characteristics", {"hatch_edge_offset_seeded_mm": -0.5, "hatch": hatch, "hatch_points": hatch_points,
                                "as_built_default_part": band, "as_built_points": points,
                                "evaluation_s": round(seconds, 2),
                                "evaluation_s_per_million_points": round(seconds / points * 1e6, 2)})


if __name__ == "__main__":
    main()

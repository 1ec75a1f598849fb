"""CPU seconds and traced memory of the units that gather a tiled cloud's points in the characteristics' regions and
the close-ups' squares (docs/compute.md "Tiles", "Characteristics and close-ups from every point"), what the process
that writes the report then holds, and a small dent's profile from those points against the report's sample's.

Usage: nice -n 10 python benchmarks/tile_regions.py [--tiles 3] [--tile-mm 500] [--width-mm 1500] [--report-points N]

The flat part of ``benchmarks/tile_areas.py`` (1 mm jittered grid, its dent 0.5 mm deep, sigma 3 mm) and a template
of six 100 mm square profiles, a 30 mm square profile over the dent, a flatness and a section across the part. The
tiles are inspected and their areas found (``tile_inspection``), then each tile's ``region_points.RegionTile`` unit
runs in this process: per unit its CPU seconds and traced peak (``tracemalloc``) per tile point. ``gathered``: the
points that come back (all regions), ``evaluate_s``: the characteristics on them here; ``dent_profile``: its status
from those points and from every k-th point up to ``--report-points`` (the report's sample).
Timings on a shared machine are unreliable: run it idle.
"""

from __future__ import annotations

import time

import numpy as np
from results import publish
from tandemscan.config.inspection_template import InspectionTemplate
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.inspection import region_points
from tandemscan.pipeline.inspection.characteristics import MeasuredCloud, evaluate
from tandemscan.pipeline.inspection.decision import DecisionRule
from tandemscan.pipeline.inspection.region_points import (
    REGION_POINTS,
    RegionPoints,
    budgeted,
    characteristic_region,
    closeup_region,
)
from tandemscan.pipeline.inspection.tile_inspection import inspect_tiles, tile_areas
from tile_areas import BOUNDS, arguments, flat_part, measured


def sheet_template(tile_mm: float, width_mm: float, dent: tuple[float, float]) -> InspectionTemplate:
    """Six 100 mm squares, a 30 mm square over the dent, a 200 mm flatness and a section across x (F = W, mm)."""
    def box(x: float, y: float, half: float) -> dict:
        return {"min_mm": [x - half, y - half, -5.0], "max_mm": [x + half, y + half, 5.0]}

    squares = [{"id": f"SP-{k}", "name": f"square {k}", "kind": "surface_profile",
                "region": box((0.3 + 0.4 * k) * tile_mm, (0.2 + 0.12 * k) * width_mm, 50.0)} for k in range(6)]
    return InspectionTemplate.model_validate({
        "part": "flat sheet", "part_number": "FLAT-1", "characteristics": [
            *squares,
            {"id": "SP-DENT", "name": "the dent's square", "kind": "surface_profile", "region": box(*dent, 15.0)},
            {"id": "FL-1", "name": "flatness", "kind": "flatness", "region": box(0.5 * tile_mm, 0.5 * width_mm, 100.0),
             "upper_mm": 0.5},
            {"id": "SEC-1", "name": "across", "kind": "section", "point_mm": [1.5 * tile_mm, 0.0, 0.0],
             "normal": [1.0, 0.0, 0.0]}]}).with_general_tolerance(BOUNDS.lower_mm, BOUNDS.upper_mm)


def main() -> None:
    args = arguments(__doc__.split("\n\n")[0])
    with flat_part(args, "tile-regions-") as part:
        store, dent, cloud, surface = part.store, part.dent_mm, part.cloud, part.surface
        template = sheet_template(args.tile_mm, args.width_mm, dent)
        backend = LocalBackend(1)
        inspected = inspect_tiles(cloud.tiles, store, store / part.cad, np.eye(4), BOUNDS.lower_mm, BOUNDS.upper_mm,
                                  backend)
        areas = tile_areas(inspected, store, np.eye(4), BOUNDS, backend)
        sample = cloud.every_kth(-(-len(cloud) // args.report_points))
        closest = surface.closest(sample.points_mm)
        in_sample = MeasuredCloud(sample.points_mm, closest.signed_mm, closest.triangle_ids,
                                  np.zeros(len(sample.points_mm)), surface)
        wanted = [characteristic_region(spec, template, surface) for spec in template.characteristics]
        regions = budgeted([*wanted, *(closeup_region(a) for a in areas[:12])], in_sample.points_mm,
                           in_sample.triangle_ids, len(cloud) / len(sample.points_mm), REGION_POINTS)
        log: list[tuple[float, int]] = []
        region_points.tile_region_points = measured(region_points.tile_region_points, log)
        t = time.perf_counter()
        found = region_points.gather([i.file for i in inspected], store, regions, backend)
        gather_s = time.perf_counter() - t
        own = found[: len(wanted)]
        ends = np.cumsum([0, *(len(f) for f in own)]).tolist()
        t = time.process_time()
        results = evaluate(template, RegionPoints.joined(own, 1).measured(surface), DecisionRule(),
                           tuple(map(slice, ends[:-1], ends[1:])))
        evaluate_s = time.process_time() - t
        from_sample = evaluate(template, in_sample, DecisionRule())
        points = np.array([t.voxels for t in cloud.tiles], float)
        publish("tile_regions", {
            "tiles": len(cloud.tiles), "points": len(cloud), "points_per_tile": int(points.max()),
            "regions": len(regions), "closeups": len(regions) - len(wanted),
            "unit_cpu_s": [round(c, 2) for c, _ in log],
            "unit_traced_peak_bytes_per_point": [round(b / n) for (_, b), n in zip(log, points, strict=True)],
            "gather_wall_s": round(gather_s, 2), "gathered": int(sum(len(f) for f in found)),
            "gathered_bytes": int(sum(f.points_mm.nbytes + f.deviations_mm.nbytes + f.triangle_ids.nbytes
                                      + f.uncertainty_mm.nbytes for f in found)),
            "evaluate_s": round(evaluate_s, 2), "report_points": len(sample.points_mm),
            "dent_profile": {"tiles": results[6].status, "tiles_points": results[6].points,
                             "sample": from_sample[6].status, "sample_points": from_sample[6].points}})


if __name__ == "__main__":
    main()

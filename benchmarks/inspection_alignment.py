"""Inspection on the simulated cell without ground truth: registration of the job's world W to CAD and the
deviation areas found on an as-built part, scored against the simulator's truth. Prints one JSON object last.

Usage: nice python benchmarks/inspection_alignment.py [--config FILE] [--plan FILE]

Runs the default job twice with the fixture's reference spheres: on the defect-free part (the config as
given) and on the part of ``config/as-built-example.toml``. Per run: ``T_F_W`` from the AGV stations
(coarse), the robust best fit and RPS, each against the truth at the part's centre (mm, deg); the areas
beyond the default band (found, missed, false regions, centroid and extreme errors). Then ``tandemscan
inspect``'s path on the defect-free cloud turned 20 deg and moved 200 mm: the best fit from there.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d
from tandemscan.config import load_config
from tandemscan.config.models import CellConfig
from tandemscan.daemon.cli import default_plan_path
from tandemscan.daemon.runner import JobRunner
from tandemscan.pipeline import frames as F
from tandemscan.pipeline.alignment import align_plan_stations
from tandemscan.pipeline.cloud_io import read_ply
from tandemscan.pipeline.export import write_ply
from tandemscan.pipeline.inspect import CadSurface
from tandemscan.pipeline.inspection_job import align_and_inspect, inspect_files
from tandemscan.pipeline.kinematics import ArmKinematics
from tandemscan.pipeline.part import load_part_mesh
from tandemscan.pipeline.plan import Plan
from tandemscan.sim_drivers.cell import build_cell
from tandemscan.sim_drivers.inspection_score import alignment_error, deviation_truths, score_areas

AS_BUILT = Path(__file__).resolve().parents[1] / "config" / "as-built-example.toml"


async def measure(config: CellConfig, plan: Plan, job_dir: Path) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Run the job; (cloud in W mm, per-scan T_W_V2 by Eq. 5, true T_F_W)."""
    cell = build_cell(config)
    await cell.connect()
    try:
        runner = JobRunner(cell, plan, config, job_dir)
        result = await runner.run()
    finally:
        await cell.close()
    inst, kin = runner.installation, ArmKinematics(config.arm)
    T_W_V2 = [F.measurement_agv_in_world(s.T_W_C @ s.reading.T_C_T, inst.T_V2_B, kin.forward(s.joints_rad), inst.T_E_T)
              for s in result.scans]
    cloud, _ = read_ply(result.cloud_file)
    return cloud, T_W_V2, F.invert(cell.world.T_W_F)


def rounded(err: tuple[float, float]) -> dict:
    return {"mm": round(err[0], 4), "deg": round(err[1], 5)}


def one_part(config: CellConfig, plan: Plan, tmp: Path, name: str) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """The figures of one part, its cloud (W), the true T_F_W and the best fit's."""
    t0 = time.perf_counter()
    cloud_W, T_W_V2, T_F_W_true = asyncio.run(measure(config, plan, tmp / f"job-{name}"))
    cad = load_part_mesh(config.part)
    surface = CadSurface(cad)
    centre = 0.5 * (np.asarray(cad.vertices).min(axis=0) + np.asarray(cad.vertices).max(axis=0))
    stations = align_plan_stations(plan, T_W_V2)
    out: dict = {"points": len(cloud_W), "job_s": round(time.perf_counter() - t0, 1),
                 "stations_T_F_W_err": rounded(alignment_error(stations.T_F_W, T_F_W_true, centre)),
                 "stations_residual_mm": round(stations.residual_mm, 1)}
    truth_points = F.transform_points(T_F_W_true, cloud_W)
    truths = deviation_truths(config, surface, truth_points)
    found: dict[str, np.ndarray] = {}
    for method in ("best-fit", "rps"):
        cfg = config.inspection.model_copy(update={"alignment": method})
        t0 = time.perf_counter()
        outputs = align_and_inspect(cloud_W, surface, tmp / f"{name}-{method}", cfg, start_T_F_W=stations.T_F_W,
                                    start="the AGV stations", json_name=None)
        res, T = outputs.result, np.array(outputs.data["alignment"]["T_F_W"])
        found[method] = T
        fig = {"T_F_W_err_at_part_centre": rounded(alignment_error(T, T_F_W_true, centre)),
               "T_F_W_err_at_cloud_centre": rounded(alignment_error(T, T_F_W_true, truth_points.mean(axis=0))),
               "residual_mm": round(outputs.data["alignment"]["residual_mm"], 4),
               "verdict": res.verdict, "areas": len(res.areas),
               "area_mm2_max": round(max((x.area_mm2 for x in res.areas), default=0.0), 1),
               "seconds": round(time.perf_counter() - t0, 1)}
        if config.sim.as_built.deviations:
            fig |= score_areas(truths, res.areas)
        out[method] = fig
    return out, cloud_W, T_F_W_true, found["best-fit"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=None)
    ap.add_argument("--plan", default=None)
    args = ap.parse_args()
    base = load_config(args.config)
    base = base.model_copy(update={
        "sim": base.sim.model_copy(update={"reference_spheres": True}),
        "inspection": base.inspection.model_copy(update={"in_job": False, "views": ("isometric",),
                                                         "map_width_px": 400}),
    })
    plan = Plan.load(Path(args.plan) if args.plan else default_plan_path())
    deviations = load_config(AS_BUILT).sim.as_built
    as_built = base.model_copy(update={"sim": base.sim.model_copy(update={"as_built": deviations})})
    figures: dict = {"benchmark": "inspection_alignment", "plan": plan.name}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        figures["defect_free"], cloud_W, T_F_W_true, T_F_W_fit = one_part(base, plan, tmp, "defect-free")
        figures["as_built"], *_ = one_part(as_built, plan, tmp, "as-built")
        # tandemscan inspect's path: the cloud in F turned 20 deg about a tilted axis and moved 200 mm
        offset = F.from_rotvec(np.array([120.0, -140.0, 80.0]) * 200.0 / np.linalg.norm([120.0, -140.0, 80.0]),
                               np.radians(20.0) * np.array([0.3, 0.4, 0.866]) / np.linalg.norm([0.3, 0.4, 0.866]))
        cloud_file = write_ply(tmp / "moved.ply", F.transform_points(offset @ T_F_W_true, cloud_W))
        cad = load_part_mesh(base.part)
        centre = 0.5 * (np.asarray(cad.vertices).min(axis=0) + np.asarray(cad.vertices).max(axis=0))
        mesh_file = tmp / "cad.ply"
        o3d.io.write_triangle_mesh(str(mesh_file), cad)
        t0 = time.perf_counter()
        res = inspect_files(cloud_file, mesh_file, tmp / "moved", base.inspection)
        T = np.array(res.data["alignment"]["T_F_W"]) @ offset @ T_F_W_true  # back to the job's W
        figures["inspect_moved_20deg_200mm"] = {
            "T_F_W_err_at_part_centre": rounded(alignment_error(T, T_F_W_true, centre)),
            "vs_job_best_fit": rounded(alignment_error(T, T_F_W_fit, centre)), "verdict": res.result.verdict,
            "areas": len(res.result.areas),
            "seconds": round(time.perf_counter() - t0, 1)}
    print(json.dumps(figures))


if __name__ == "__main__":
    main()

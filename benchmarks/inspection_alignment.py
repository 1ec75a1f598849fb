"""Inspection on the simulated cell without ground truth: registration of the job's world W to CAD and the
deviation areas found on an as-built part, scored against the simulator's truth. Prints one JSON object last.

Usage: nice python benchmarks/inspection_alignment.py [--config FILE] [--plan FILE|generated] [--defect-free-only]

``--plan generated`` plans the whole configured part first (``tandemscan plan``); ``--defect-free-only`` skips
the as-built run (the whole-part job alone is 15+ minutes on the shared 2-core machine).

Runs the default job twice with the fixture's reference spheres: on the defect-free part (the config as
given) and on the part of ``config/as-built-example.toml``. Per run: ``T_F_W`` from the anchor reading (where
the job starts its alignment) and from the AGV stations (coarse), the robust best fit and RPS, each against the
truth at the part's centre (mm, deg); the areas beyond the default band (found, missed, false regions, centroid
and extreme errors). Then ``tandemscan inspect``'s path on the defect-free cloud turned 20 deg and moved 200 mm:
the best fit from there.

What the stitched cloud allows (defect-free part, docs/inspection-method.md "How close `T_F_W` can come"): the cloud's
own rigid error (the least-squares rigid motion of every scan point from where the job's poses put it to where
the true poses do), and both alignments of the cloud stitched with the true poses and of the tracker-only
stitch (Eq. 1), against the truth and against the truth moved by that rigid error (the best any alignment of
this cloud can reach). The truth comes through the job's observer only.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from clean_exit import clean_exit_on_sigterm
from generated_plan import generated_plan
from pose_bound import bound_model  # benchmarks/pose_bound.py: the bound's error model
from results import publish
from tandemscan.config import load_config
from tandemscan.config.models import CellConfig
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.runner import JobResult, JobRunner, ScanRecord
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.geometry.uncertainty import recentre
from tandemscan.pipeline.inspection.alignment import AlignmentCriteria, align, align_plan_stations, fit_rigid
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.pipeline.inspection.inspection_job import (
    AlignmentStart,
    InspectionSettings,
    Measurement,
    ReportOutput,
    align_and_inspect,
    inspect_files,
)
from tandemscan.pipeline.inspection.report import InspectedPart
from tandemscan.pipeline.io.cloud_io import read_ply
from tandemscan.pipeline.io.export import write_ply
from tandemscan.pipeline.io.raw_scan import read_raw_scan
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.sim_drivers.cell import with_surveyed_mounts
from tandemscan.sim_drivers.inspection_score import alignment_error, deviation_truths, score_areas

AS_BUILT = Path(__file__).resolve().parents[1] / "config" / "as-built-example.toml"


@dataclass(frozen=True)
class Measured:
    """One job: its cloud (W, mm), scans, the anchor's T_F_W, per-scan T_W_V2 (Eq. 5), the tracker-only scan
    poses (Eq. 1), the job's result and ``T_T_S`` and, from the observer, the true scan poses and the true T_F_W."""

    cloud_W: np.ndarray
    scans: list[ScanRecord]
    anchor_T_F_W: np.ndarray
    T_W_V2: list[np.ndarray]
    tracker_only_T_W_S: list[np.ndarray]
    true_T_W_S: list[np.ndarray]
    T_F_W_true: np.ndarray
    result: JobResult
    T_T_S: np.ndarray


async def measure(config: CellConfig, plan: Plan, job_dir: Path) -> Measured:
    """Run the job on the simulated cell; the truth only from its observer's scorer."""
    async with CellSession(config) as session:
        config = with_surveyed_mounts(config, session.cell.simulation, job_dir.parent)
        runner = JobRunner(session, plan, config, job_dir)
        result = await runner.run()
        scorer = runner.observer.scorer()
    inst, kin = runner.installation, ArmKinematics(config.arm)
    T_W_V2 = [F.measurement_agv_in_world(s.T_W_C @ s.reading.T_C_T, inst.T_V2_B, kin.forward(s.joints_rad), inst.T_E_T)
              for s in result.scans]
    tracker_only = [F.compose(s.T_W_C, s.reading.T_C_T, inst.T_T_S) for s in result.scans]
    cloud, _ = read_ply(result.cloud_file)
    return Measured(cloud, list(result.scans), np.array(runner.state.relocalisation.T_F_W), T_W_V2, tracker_only,
                    [scorer.T_W_S_true[s.index] for s in result.scans], F.invert(scorer.world.T_W_F), result,
                    inst.T_T_S)


def stitch(scans: list[ScanRecord], poses: list[np.ndarray], voxel_mm: float) -> np.ndarray:
    """The scans' raw points placed by ``poses`` (W, mm), thinned to one point per ``voxel_mm`` voxel."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        np.vstack([F.transform_points(T, read_raw_scan(s.file)[0]) for s, T in zip(scans, poses, strict=True)])))
    return np.asarray(cloud.voxel_down_sample(voxel_mm).points)


def cloud_rigid_error(scans: list[ScanRecord], poses: list[np.ndarray], true_poses: list[np.ndarray]) -> np.ndarray:
    """``T_Wtrue_W``: the least-squares rigid motion of every 20th scan point from where ``poses`` put it to where
    ``true_poses`` do (mm): the part of the cloud's error no alignment can tell from a misplaced part."""
    src, dst = [], []
    for s, T, T_true in zip(scans, poses, true_poses, strict=True):
        p = read_raw_scan(s.file)[0][::20]
        src.append(F.transform_points(T, p))
        dst.append(F.transform_points(T_true, p))
    return fit_rigid(np.vstack(src), np.vstack(dst))


def what_the_cloud_allows(config: CellConfig, m: Measured, surface: CadSurface, centre: np.ndarray) -> dict:
    """The stitched cloud's rigid error at the part's centre and each alignment of three stitches of the same
    scans (the job's poses, the true poses, the tracker-only poses) against the truth and against the best this
    stitch can reach (the truth moved by its rigid error)."""
    job_poses = [s.T_W_S for s in m.scans]
    out: dict = {}
    for name, poses in (("job", job_poses), ("true_poses", m.true_T_W_S), ("tracker_only", m.tracker_only_T_W_S)):
        rigid = cloud_rigid_error(m.scans, poses, m.true_T_W_S)
        reachable = m.T_F_W_true @ rigid
        points = m.cloud_W if name == "job" else stitch(m.scans, poses, config.job.voxel_mm)
        fig: dict = {"cloud_rigid_err": rounded(alignment_error(reachable, m.T_F_W_true, centre))}
        for method in ("best-fit", "rps"):
            cfg = AlignmentCriteria.from_section(config.inspection, alignment=method)
            T = align(surface, points, cfg, m.anchor_T_F_W, "the anchor reading").T_F_W
            fig[method] = {"vs_truth": rounded(alignment_error(T, m.T_F_W_true, centre)),
                           "vs_reachable": rounded(alignment_error(T, reachable, centre))}
        out[name] = fig
    return out


#: draws for the expected norms of the rigid error
_DRAWS = 20000
#: issue 19's target for T_F_W at the part's centre (mm, deg)
_TARGET = (0.05, 0.005)


def rigid_error_map(scans: list[ScanRecord], true_poses: list[np.ndarray], centre_W: np.ndarray) -> np.ndarray:
    """(6, 6n): the scans' small pose errors (world motions, t mm and r rad about each scan's true origin,
    stacked in scan order) to the least-squares rigid motion of every 20th scan point about ``centre_W`` (mm):
    :func:`cloud_rigid_error`, linearised. It is the scans' errors restated about the centre and averaged,
    each weighted by its points' 6x6 moment ``sum J^T J``, ``J = [I, -skew(p - centre)]``."""
    moment, blocks = np.zeros((6, 6)), []
    for s, T in zip(scans, true_poses, strict=True):
        p = F.transform_points(T, read_raw_scan(s.file)[0][::20]) - centre_W
        J = np.zeros((len(p), 3, 6))
        J[:, :, :3] = np.eye(3)
        J[:, 0, 4], J[:, 0, 5], J[:, 1, 3] = p[:, 2], -p[:, 1], -p[:, 2]   # r x p as -skew(p) r
        J[:, 1, 5], J[:, 2, 3], J[:, 2, 4] = p[:, 0], p[:, 1], -p[:, 0]
        M = np.einsum("kai,kaj->ij", J, J)
        moment += M
        blocks.append(M @ recentre(T[:3, 3], centre_W))
    return np.linalg.solve(moment, np.hstack(blocks))


def rigid_error_figures(cov: np.ndarray, rng: np.random.Generator) -> dict:
    """Expected translation (mm) and rotation (deg) norms of a rigid error ``N(0, cov)`` (t mm, r rad), their
    95th percentiles, and the chance that each and both are within issue 19's target."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    x = rng.standard_normal((_DRAWS, 6)) * np.sqrt(np.clip(w, 0.0, None)) @ V.T
    t, r = np.linalg.norm(x[:, :3], axis=1), np.degrees(np.linalg.norm(x[:, 3:], axis=1))
    return {"mm_mean": round(float(t.mean()), 4), "mm_p95": round(float(np.percentile(t, 95)), 4),
            "deg_mean": round(float(r.mean()), 5), "deg_p95": round(float(np.percentile(r, 95)), 5),
            "sigma_xyz_mm": np.round(np.sqrt(np.diag(cov)[:3]), 4).tolist(),
            "p_mm_within_target": round(float(np.mean(t <= _TARGET[0])), 3),
            "p_deg_within_target": round(float(np.mean(r <= _TARGET[1])), 3),
            "p_both_within_target": round(float(np.mean((t <= _TARGET[0]) & (r <= _TARGET[1]))), 3)}


def rigid_error_bound(config: CellConfig, m: Measured, centre_F: np.ndarray) -> dict:
    """What the bound (benchmarks/pose_bound.py's model) implies for the cloud's rigid error at the part's
    centre: its distribution tracker-only and at the bound (no estimator from these scans and readings does
    better in expectation), beside the job's realised rigid error (linearised, and as a point-weighted and a
    plain mean of the scans' pose errors)."""
    true = {s.index: T for s, T in zip(m.scans, m.true_T_W_S, strict=True)}
    model = bound_model(m.result, m.T_T_S, config, true)
    A, prior, posterior, origins = model.A, model.prior, model.posterior, model.origins
    centre_W = F.transform_points(F.invert(m.T_F_W_true), centre_F[None])[0]
    G = rigid_error_map(m.scans, m.true_T_W_S, centre_W)
    mean = np.hstack([recentre(o, centre_W) for o in origins]) / len(origins)
    rng = np.random.default_rng(0)
    out: dict = {"target": {"mm": _TARGET[0], "deg": _TARGET[1]}, "pairs_in_bound": len(model.pairs)}
    for name, cov in (("tracker_only", prior), ("bound", posterior)):
        out[name] = rigid_error_figures(G @ A @ cov @ A.T @ G.T, rng)
        out[name]["plain_mean_mm_mean"] = rigid_error_figures(mean @ A @ cov @ A.T @ mean.T, rng)["mm_mean"]
    errors = []   # the job's per-scan errors as world motions about each true origin
    for s, T_true in zip(m.scans, m.true_T_W_S, strict=True):
        D = s.T_W_S @ F.invert(T_true)
        errors.append(np.r_[D[:3, :3] @ T_true[:3, 3] + D[:3, 3] - T_true[:3, 3], F.to_rotvec(D)[1]])
    e = np.concatenate(errors)
    for name, M in (("job_weighted", G), ("job_plain_mean", mean)):
        x = M @ e
        out[name] = {"mm": round(float(np.linalg.norm(x[:3])), 4),
                     "deg": round(float(np.degrees(np.linalg.norm(x[3:]))), 5)}
    return out


def rounded(err: tuple[float, float]) -> dict:
    return {"mm": round(err[0], 4), "deg": round(err[1], 5)}


def one_part(config: CellConfig, plan: Plan, tmp: Path, name: str) -> tuple[dict, Measured, np.ndarray]:
    """The figures of one part, its job and the best fit's T_F_W."""
    t0 = time.perf_counter()
    m = asyncio.run(measure(config, plan, tmp / f"job-{name}"))
    cloud_W, T_F_W_true = m.cloud_W, m.T_F_W_true
    cad = load_part_mesh(config.part)
    surface = CadSurface(cad)
    centre = part_centre(cad)
    stations = align_plan_stations(plan, m.T_W_V2)
    out: dict = {"points": len(cloud_W), "job_s": round(time.perf_counter() - t0, 1),
                 "anchor_T_F_W_err": rounded(alignment_error(m.anchor_T_F_W, T_F_W_true, centre)),
                 "stations_T_F_W_err": rounded(alignment_error(stations.T_F_W, T_F_W_true, centre)),
                 "stations_residual_mm": round(stations.residual_mm, 1)}
    truth_points = F.transform_points(T_F_W_true, cloud_W)
    truths = deviation_truths(config, surface, truth_points)
    found: dict[str, np.ndarray] = {}
    for method in ("best-fit", "rps"):
        cfg = config.inspection.model_copy(update={"alignment": method})
        t0 = time.perf_counter()
        outputs = align_and_inspect(Measurement(cloud_W), InspectedPart(surface), InspectionSettings.from_section(cfg),
                                    ReportOutput(tmp / f"{name}-{method}", json_name=None),
                                    AlignmentStart(m.anchor_T_F_W, "the anchor reading"))
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
    if not config.sim.as_built.deviations:
        out["what_the_cloud_allows"] = what_the_cloud_allows(config, m, surface, centre)
        out["rigid_error_bound"] = rigid_error_bound(config, m, centre)
    return out, m, found["best-fit"]


def part_centre(cad: o3d.geometry.TriangleMesh) -> np.ndarray:
    """The centre of the CAD's bounding box (F, mm): where the alignment errors are taken."""
    v = np.asarray(cad.vertices)
    return 0.5 * (v.min(axis=0) + v.max(axis=0))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=None)
    ap.add_argument("--plan", default=None, help="plan file, or 'generated' to plan the whole part")
    ap.add_argument("--defect-free-only", action="store_true", help="skip the as-built part's run")
    args = ap.parse_args()
    base = load_config(args.config)
    base = base.model_copy(update={
        "sim": base.sim.model_copy(update={"reference_spheres": True}),
        "inspection": base.inspection.model_copy(update={"in_job": False, "views": ("isometric",),
                                                         "map_width_px": 400}),
    })
    plan = generated_plan(base) if args.plan == "generated" else Plan.load(Path(args.plan) if args.plan
                                                                          else default_plan_path())
    deviations = load_config(AS_BUILT).sim.as_built
    as_built = base.model_copy(update={"sim": base.sim.model_copy(update={"as_built": deviations})})
    figures: dict = {"benchmark": "inspection_alignment", "plan": plan.name}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        figures["defect_free"], m, T_F_W_fit = one_part(base, plan, tmp, "defect-free")
        cloud_W, T_F_W_true = m.cloud_W, m.T_F_W_true
        if not args.defect_free_only:
            figures["as_built"], *_ = one_part(as_built, plan, tmp, "as-built")
        # tandemscan inspect's path: the cloud in F turned 20 deg about a tilted axis and moved 200 mm
        offset = F.from_rotvec(np.array([120.0, -140.0, 80.0]) * 200.0 / np.linalg.norm([120.0, -140.0, 80.0]),
                               np.radians(20.0) * np.array([0.3, 0.4, 0.866]) / np.linalg.norm([0.3, 0.4, 0.866]))
        cloud_file = write_ply(tmp / "moved.ply", F.transform_points(offset @ T_F_W_true, cloud_W))
        cad = load_part_mesh(base.part)
        centre = part_centre(cad)
        mesh_file = tmp / "cad.ply"
        o3d.io.write_triangle_mesh(str(mesh_file), cad)
        t0 = time.perf_counter()
        res = inspect_files(cloud_file, mesh_file, tmp / "moved", InspectionSettings.from_section(base.inspection))
        T = np.array(res.data["alignment"]["T_F_W"]) @ offset @ T_F_W_true  # back to the job's W
        figures["inspect_moved_20deg_200mm"] = {
            "T_F_W_err_at_part_centre": rounded(alignment_error(T, T_F_W_true, centre)),
            "vs_job_best_fit": rounded(alignment_error(T, T_F_W_fit, centre)), "verdict": res.result.verdict,
            "areas": len(res.result.areas),
            "seconds": round(time.perf_counter() - t0, 1)}
    publish("inspection_alignment" + (f"-{plan.name}" if args.plan else ""), figures)


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

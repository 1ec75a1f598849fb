"""Where the tracker-only stitch's error comes from, per scan, on a generated plan: print it as JSON.

Usage: ``nice .venv/bin/python benchmarks/stitch_chain.py [--config CELL.toml] [--part default|barrel]
[--runs N] [--transfer-samples N] [--still-fraction F] [--transfer-arm-poses K [K ...]]
[--transfer-arm-reach MM]``.

A diagnostic on the simulator's ground truth (scoring only, never the product path): the part is planned as
``tandemscan measure --part`` does it, then the plan's steps are walked on a :class:`SimWorld` without scanning:
the chassis stand where the plan puts them (no slip: drift does not enter the tracker-only stitch, which is
``T_W_S = T_W_C T_C_T T_T_S``), the column at its height, the arm at its joints; the tracker reads the target
with the simulator's noise model at each scan and on both sides of each coordinate transfer (Eq. 2), exactly as
the runner does (``tracker.transfer_samples`` readings averaged on each side, ``--transfer-samples`` to
override; the simulator keeps ``tracker.still_noise_fraction`` of a reading's variance over a still period,
``--still-fraction`` to override), at ``tracker.transfer_arm_poses`` arm poses on each side where that is more
than one (``--transfer-arm-poses`` to override: the runner's choice of poses and estimate, the simulated arm
landing each move within ``sim.arm_repeatability``; several counts are compared on one plan and the same
seeds). The error is taken where it matters for the cloud: at the scanner's sweet spot on the view axis
(``p_S = (0, 0, sweet_spot_mm)``), its component along the view (the surface normal, which cloud-to-mesh
distance measures) and its size. Three variants over ``--runs`` seeds (``sim.seed`` on; a seed
whose installation hides a transfer's target is left out and named, as the job would pause there; a scan whose
target is hidden is left out, as the runner does) split the total: ``readings`` (only the scan's own reading
noisy: transfers exact), ``transfers`` (only the transfer readings noisy) and ``both``. Each is reported
overall, by tracker station (transfer accumulation grows per station) and by column height (a chain error would
grow with height), with the mean tracker-to-target distance.
"""

from __future__ import annotations

import argparse
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np
import open3d as o3d
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config import load_config
from tandemscan.daemon.cell.tracker_reading import averaged_covariance
from tandemscan.daemon.jobs.coordinate_transfer import (
    PoseReading,
    camera_move,
    choose_transfer_poses,
    pose_transfer,
    transfer_joints,
)
from tandemscan.daemon.plans import plan_configured_part
from tandemscan.drivers.errors import TargetNotVisible
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import barrel_panel_mesh
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, MoveTracker, Scan
from tandemscan.sim_drivers.world import SimWorld

VARIANTS = ("readings", "transfers", "both")


def _reading(world: SimWorld, noisy: bool, samples: int = 1) -> np.ndarray:
    """``T_C_T`` now: the mean of ``samples`` of the simulator's noisy readings (as ``read_at_rest``), or the
    truth."""
    if noisy:
        return F.mean_pose([world.measure_target()[0] for _ in range(samples)])
    return F.invert(world.T_F_C()) @ world.T_F_T()


def _pose_reading(world: SimWorld, noisy: bool, samples: int) -> PoseReading:
    """The averaged ``T_C_T`` at the arm's pose now (:func:`_reading`) with the covariance the runner would carry
    (the simulated tracker's model, averaged as ``read_at_rest`` does)."""
    T = _reading(world, noisy, samples)
    if world.target_visibility() is not None:
        raise TargetNotVisible("tracker", world.target_visibility())
    sigma_mm, sigma_rad = world.config.sim.tracker_noise.sigma(float(np.linalg.norm(T[:3, 3])))
    cov = averaged_covariance(np.diag([sigma_mm**2] * 3 + [sigma_rad**2] * 3), samples,
                              world.config.tracker.still_noise_fraction)
    return PoseReading(world.joints_rad.copy(), T, cov)


def _poses_transfer(world: SimWorld, config, plan, i: int, T_W_C: np.ndarray, noisy: bool) -> tuple[np.ndarray, int]:
    """The runner's transfer over ``tracker.transfer_arm_poses`` arm poses at step ``i``, on the simulated world:
    the new ``T_W_C`` and the number of pairs used."""
    step, samples = plan.steps[i], config.tracker.transfer_samples
    q0, others = transfer_joints(plan, i, {})
    before = [_pose_reading(world, noisy, samples)]
    T_F_V1 = world.chassis["tracking_chassis"].true_pose
    odometry = (T_F_V1[0, 3], T_F_V1[1, 3], float(np.arctan2(T_F_V1[1, 0], T_F_V1[0, 0])))
    chosen, _ = choose_transfer_poses(q0, others, before[0].T_C_T, camera_move(world.truth, odometry, step),
                                      config.tracker.transfer_arm_poses, config, world.truth)
    for q in chosen:
        world.move_arm(q)
        try:
            before.append(_pose_reading(world, noisy, samples))
        except TargetNotVisible:
            continue
    world.chassis["tracking_chassis"].true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
    pairs = []
    for k, b in reversed(list(enumerate(before))):
        world.move_arm(b.joints_rad)
        try:
            pairs.append((b, _pose_reading(world, noisy, samples), k != len(before) - 1))
        except TargetNotVisible:
            if k == 0:
                raise
    pairs.reverse()
    est = pose_transfer(T_W_C, [b for b, _, _ in pairs], [a for _, a, _ in pairs], [m for _, _, m in pairs],
                        config, world.truth)
    return est.T_W_C, len(pairs)


def walk(config, plan, seed: int, variant: str, pairs_log: list[int] | None = None) -> list[dict]:
    """One run of ``plan``'s steps on a fresh world (seed ``seed``); per scan: station, column height (mm),
    tracker distance (mm) and the error at the sweet spot (mm, along the view and its size). The pose pairs each
    transfer used are appended to ``pairs_log``."""
    world = SimWorld(config.model_copy(update={"sim": config.sim.model_copy(update={"seed": seed})}))
    scan_noise, transfer_noise = variant in ("readings", "both"), variant in ("transfers", "both")
    chassis = {"tracking": world.chassis["tracking_chassis"], "measure": world.chassis["measure_chassis"]}
    p_S = np.array([0.0, 0.0, config.scanner.sweet_spot_mm, 1.0])
    T_W_C, station, scanned, rows = None, 0, False, []
    for i, step in enumerate(plan.steps):
        if isinstance(step, MoveTracker):
            if not scanned:  # a plain relocation before the first scan: W is the camera frame where it stops
                chassis["tracking"].true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
                continue
            if config.tracker.transfer_arm_poses > 1:
                T_W_C, pairs = _poses_transfer(world, config, plan, i, T_W_C, transfer_noise)
                if pairs_log is not None:
                    pairs_log.append(pairs)
                station += 1
                continue
            samples = config.tracker.transfer_samples
            before = _reading(world, transfer_noise, samples)
            chassis["tracking"].true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
            T_W_C = F.coordinate_transfer(T_W_C, before, _reading(world, transfer_noise, samples))
            station += 1
        elif isinstance(step, MoveMeasure):
            chassis["measure"].true_pose = F.planar_pose(step.x_mm, step.y_mm, step.heading_rad)
        elif isinstance(step, MoveLift):
            world.lift_mm = step.height_mm
        elif isinstance(step, MoveArm):
            world.move_arm(np.array(step.joints_rad, float))
        elif isinstance(step, Scan):
            if not scanned:
                world.define_world()
                T_W_C, scanned = world.T_W_F @ world.T_F_C(), True
            if world.target_visibility() is not None:  # the runner leaves such a scan out
                continue
            T_C_T = _reading(world, scan_noise)
            T_W_S = F.compose(T_W_C, T_C_T, world.truth.T_T_S)
            T_W_S_true = world.T_W_S()
            e = (T_W_S @ p_S - T_W_S_true @ p_S)[:3]
            rows.append({"station": station, "lift_mm": world.lift_mm,
                         "distance_mm": float(np.linalg.norm(T_C_T[:3, 3])),
                         "along_view_mm": float(e @ T_W_S_true[:3, 2]), "size_mm": float(np.linalg.norm(e))})
    return rows


def _summary(rows: list[dict]) -> dict:
    along = np.array([r["along_view_mm"] for r in rows])
    size = np.array([r["size_mm"] for r in rows])
    return {"scans": len(rows), "rms_along_view_mm": round(float(np.sqrt(np.mean(along**2))), 4),
            "rms_size_mm": round(float(np.sqrt(np.mean(size**2))), 4),
            "mean_tracker_distance_m": round(float(np.mean([r["distance_mm"] for r in rows])) / 1000, 2)}


def _grouped(rows: list[dict], key) -> dict:
    groups = defaultdict(list)
    for r in rows:
        groups[key(r)].append(r)
    return {str(k): _summary(v) for k, v in sorted(groups.items())}


def _with_arm_poses(config, count: int):
    return config.model_copy(update={"tracker": config.tracker.model_copy(update={"transfer_arm_poses": count})})


def _variants(config, plan, seeds, skipped) -> dict:
    """The three variants over ``seeds`` but ``skipped``, and the pose pairs the transfers used."""
    out, pairs = {}, []
    for variant in VARIANTS:
        rows = [r for seed in seeds if seed not in skipped for r in walk(config, plan, seed, variant, pairs)]
        out[variant] = {"all": _summary(rows), "by_station": _grouped(rows, lambda r: r["station"]),
                        "by_lift_mm": _grouped(rows, lambda r: int(round(r["lift_mm"])))}
    if config.tracker.transfer_arm_poses > 1 and pairs:
        out["arm_poses_used"] = {"mean": round(float(np.mean(pairs)), 2), "min": int(np.min(pairs))}
    return out


def run(args: argparse.Namespace) -> dict:
    config = load_config(args.config)
    tracker = {k: v for k, v in (("transfer_samples", args.transfer_samples),
                                 ("still_noise_fraction", args.still_fraction),
                                 ("transfer_arm_reach_mm", args.transfer_arm_reach)) if v is not None}
    config = config.model_copy(update={"tracker": config.tracker.model_copy(update=tracker)})
    counts = args.transfer_arm_poses or [config.tracker.transfer_arm_poses]
    with tempfile.TemporaryDirectory() as tmp:  # the simulated world reads the mesh file too
        if args.part == "barrel":
            mesh_file = Path(tmp) / "barrel-panel.ply"
            o3d.io.write_triangle_mesh(str(mesh_file), barrel_panel_mesh())
            config = config.model_copy(update={"part": config.part.model_copy(update={"mesh": mesh_file})})
        _, part_plan = plan_configured_part(config, f"chain {args.part}")
        plan = part_plan.sequence.plan  # one plan for every count compared (the planner's chain can vary)
        seeds = range(config.sim.seed, config.sim.seed + args.runs)
        out = {"cell": config.name, "part": args.part, "seeds": [seeds.start, seeds.stop - 1],
               "transfer_samples": config.tracker.transfer_samples,
               "still_noise_fraction": config.tracker.still_noise_fraction,
               "transfer_arm_poses": counts if len(counts) > 1 else counts[0],
               "transfer_arm_reach_mm": config.tracker.transfer_arm_reach_mm,
               "arm_repeatability": config.sim.arm_repeatability.model_dump(),
               "tracker_moves": sum(isinstance(s, MoveTracker) for s in plan.steps)}
        skipped = {}
        for count in counts:  # a transfer whose target is hidden pauses a job: such a seed is left out (of all)
            for seed in seeds:
                try:
                    walk(_with_arm_poses(config, count), plan, seed, "transfers")
                except TargetNotVisible as e:
                    skipped.setdefault(seed, e.reason)
        out["seeds_left_out"] = skipped
        results = {count: _variants(_with_arm_poses(config, count), plan, seeds, skipped) for count in counts}
        if len(counts) == 1:
            return out | results[counts[0]]
        out["summary_rms_along_view_mm"] = {
            str(c): {v: r[v]["all"]["rms_along_view_mm"] for v in VARIANTS} for c, r in results.items()}
        out["by_transfer_arm_poses"] = {str(c): r for c, r in results.items()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, help="cell configuration (default: the simulated cell)")
    parser.add_argument("--part", choices=["default", "barrel"], default="default")
    parser.add_argument("--runs", type=int, default=10, help="seeds per variant, from the config's sim.seed on")
    parser.add_argument("--transfer-samples", type=int, help="readings averaged on each side of a transfer "
                                                             "(default: the config's tracker.transfer_samples)")
    parser.add_argument("--still-fraction", type=float, help="share of a reading's noise variance common to one "
                                                             "still period (default: tracker.still_noise_fraction)")
    parser.add_argument("--transfer-arm-poses", type=int, nargs="+",
                        help="arm poses the target is read at on each side of a transfer (default: "
                             "tracker.transfer_arm_poses); several: each compared on the same plan and seeds")
    parser.add_argument("--transfer-arm-reach", type=float, help="mm the extra poses move the scanner across its "
                                                                  "view (default: tracker.transfer_arm_reach_mm)")
    args = parser.parse_args()
    publish("stitch_chain" + ("" if args.part == "default" else f"-{args.part}"), run(args))


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

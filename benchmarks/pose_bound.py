"""How well could any correction place the scans? The Cramer-Rao bound of the simulated job's per-scan pose error.

Usage: python benchmarks/pose_bound.py [--plan FILE|generated] [--seeds 7 8 9] [--resolution coarse|full]
(band plan: about 1 min a seed on the 2-core machine; the whole part, --plan generated: about 25 min)

For each seed the default job runs on the simulated cell with its correction (``[correction]``) and the cell's
surveyed mounts (a calibration file exact to 0.1 um, ``sim_drivers.cell.with_surveyed_mounts``: the bound is
that of the correction, apart from the calibration's error), and the
realised figures (tracker-only and corrected median pose error, mm) are put beside the bound of the same
job: the posterior covariance of every scan pose given everything the job measured, under the simulator's
own noise models, for an ideal estimator.

- Unknowns: each scan's tracker-reading error, carried to the scan origin (``scan_pose_covariance``), and each
  coordinate transfer's error about the still target (``transfer_covariance``, from the journaled entry);
  scan ``i`` errs by its own error plus every transfer up to its station (first order, world motions).
- Data: every overlapping pair (not only those the correction registers), points placed at their true poses
  and within 1 mm of the other scan, target normals, each point a point-to-plane measurement of the pair's
  relative error: the simulator's noise is independent per point and along its ray (sigma), so a row's
  variance is sigma^2 times the sum of its two points' squared cosines between ray and normal; where k scans
  cover a place, the surface there is unknown and its pairs share each scan's noise, so each row counts
  2 / k of its information (``row_weights``). No method that uses these scans and tracker readings can do
  better in expectation.
- Figures: expected median over the scans of the translation error (mm) at the scan origin, tracker-only and
  at the bound, by sampling (2,000 draws), and their ratio; ``bound_pose_err_mm_median`` is their median
  over seeds; ``sigma_xyz_mm_per_station``: per tracker station the mean 1-sigma of the scan origins along
  the world axes (W = the first station's camera frame; on the default band x runs along the part, y up
  the flank, z along the line of sight), tracker-only, at the bound and (``joint_posterior``) the joint
  refinement's own posterior (``report.json`` ``correction.joint``); ``corrected_over_bound`` per seed (of the
  figures to 0.01 um, so that no ratio near a line is one of rounded figures) and
  ``corrected_over_bound_mean`` (mean corrected error over mean bound) put the correction against the bound;
  ``after_last_scan_s`` / ``correction_cpu_s`` are the job's ``timings``. The bound is an expectation over noise
  draws, and one job's median scatters about it even for an ideal estimator: ``bound_mm_p95`` is the 95th
  percentile of that estimator's median over the draws and ``ideal_above_1_2x_bound_fraction`` the share of
  draws in which it exceeds 1.2 times the bound; ``corrected_above_ideal_fraction`` the share in which it
  exceeds this job's corrected median (small: the correction left error an ideal estimator would not).
- The draw itself: ``corrected_from_truth_mm`` (per station as well) is the correction's joint refinement of
  the job started at the true poses (correspondences, weights and linearisation at the truth, priors as in the
  job): what its measurement model makes of this draw's data once the start contributes no error.
  ``overlap_chi2_per_dof`` checks its measurement model: the median over the pairs (within each station,
  across stations, all) of how much of the correction's residuals at the truth a rigid motion of the pair
  explains, per degree of freedom (1 for independent zero-mean noise): near 1, what the truth start leaves
  is this draw's noise, not a bias another residual could remove (docs/correction.md, "What the measurements
  showed").

The last line of output is one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from clean_exit import clean_exit_on_sigterm
from generated_plan import generated_plan
from results import publish
from scipy.spatial import cKDTree
from tandemscan.config import load_config
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.finish import merge_stage
from tandemscan.daemon.jobs.pose_correction import mount_prior, transfer_priors
from tandemscan.daemon.jobs.runner import JobResult, JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.geometry.frames import invert, to_rotvec, transform_points
from tandemscan.pipeline.geometry.uncertainty import recentre, scan_pose_covariance
from tandemscan.pipeline.io.raw_scan import read_raw_scan
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.pipeline.registration.correction import joint_scan
from tandemscan.pipeline.registration.joint import (
    MIN_NORMAL_COSINE,
    JointSettings,
    noise_shares,
    ray_variances,
    refine_jointly,
    symmetric_normals,
)
from tandemscan.pipeline.registration.mount_unknown import MountPrior
from tandemscan.pipeline.registration.normals import estimate_normals
from tandemscan.pipeline.registration.overlap import extract_overlap, overlapping_pairs
from tandemscan.pipeline.registration.pose_graph import ScanPrior
from tandemscan.pipeline.registration.sampling import voxel_downsample
from tandemscan.sim_drivers.cell import with_surveyed_mounts
from tandemscan.sim_drivers.stitch_score import cloud_to_mesh_distances, distance_stats
from tandemscan.sim_drivers.truth_observer import TruthScorer

OVERLAP_MM = 1.0
#: neighbours of a point's normal, as the correction's (``joint.JointScan.from_points``)
NORMAL_NEIGHBOURS = 20
DRAWS = 2000


def error_model(result: JobResult, T_T_S: np.ndarray,
                true_T_W_S: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A, prior, origins)``: scan errors ``e = A theta`` (6 per scan, world, about its origin) from the
    unknowns ``theta`` (6 per scan reading, then 6 per transfer) with prior covariance ``prior``."""
    scans, transfers = result.scans, result.report["transfer_log"]
    n, k = len(scans), len(transfers)
    origins = np.array([true_T_W_S[s.index][:3, 3] for s in scans])
    A = np.zeros((6 * n, 6 * (n + k)))
    prior = np.zeros((6 * (n + k), 6 * (n + k)))
    for i, s in enumerate(scans):
        A[6 * i:6 * i + 6, 6 * i:6 * i + 6] = np.eye(6)
        prior[6 * i:6 * i + 6, 6 * i:6 * i + 6] = scan_pose_covariance(s.T_W_C, s.reading.T_C_T, T_T_S,
                                                                       s.reading.covariance)
    for m, t in enumerate(transfers):
        col = 6 * (n + m)
        prior[col:col + 6, col:col + 6] = np.array(t["covariance"])
        for i, s in enumerate(scans):
            if s.tracker_station >= t["station"]:
                A[6 * i:6 * i + 6, col:col + 6] = recentre(t["target_W_mm"], origins[i])
    return A, prior, origins


@dataclass(frozen=True)
class PairData:
    """One overlapping pair ``(i, j)`` at the true poses (points of scan j against the surface of scan i):
    ``centre`` (W, mm) and ``information`` (``J^T W J``, t then r about the centre, ``W`` the rows' weights,
    :func:`row_weights`) of its point-to-plane rows ``J`` along the target's normals, what the bound counts;
    ``chi2_per_dof``: how far the correction's residuals ``r`` (mm) at the truth are from independent zero-mean
    noise, the share of their own variance that a rigid motion of the pair explains,
    ``r^T J (J^T J)^-1 J^T r / (6 s^2)`` (``s^2`` their mean square; about 1 for such noise, above where they hold
    structure that acts like a relative pose error)."""

    i: int
    j: int
    centre: np.ndarray
    information: np.ndarray
    chi2_per_dof: float


def overlap_information(result: JobResult, true_T_W_S: dict[int, np.ndarray], voxel_mm: float, sigma_mm: float,
                        cell_mm: float) -> list[PairData]:
    """The :class:`PairData` of every overlapping pair at the true poses: the points of j within ``OVERLAP_MM`` of
    scan i, each against its nearest point there. The bound's rows use the target's normals (estimated on its
    overlap points), each weighted by :func:`row_weights`; the check uses the correction's residual: along the
    mean of the two points' unit normals (each from its own whole scan, ``NORMAL_NEIGHBOURS`` nearest points),
    where they agree within its gate (``joint.MIN_NORMAL_COSINE``)."""
    points_S = [voxel_downsample(read_raw_scan(s.file)[0], voxel_mm) for s in result.scans]
    poses = [true_T_W_S[s.index] for s in result.scans]
    clouds = [transform_points(T, P) for T, P in zip(poses, points_S, strict=True)]
    rays = [P @ T[:3, :3].T for T, P in zip(poses, points_S, strict=True)]      # from each scanner origin, W
    trees = [cKDTree(c) for c in clouds]
    normals = [estimate_normals(c, NORMAL_NEIGHBOURS, t) for c, t in zip(clouds, trees, strict=True)]
    stations = [s.tracker_station for s in result.scans]
    overlaps = [(i, j, extract_overlap(clouds[j], clouds[i], OVERLAP_MM))
                for i, j in overlapping_pairs(clouds, stations, cell_mm, len(clouds))]
    covering = [np.ones(len(c), np.int64) for c in clouds]
    for i, j, ov in overlaps:
        covering[j][ov.source_idx] += 1
        covering[i][ov.target_idx] += 1
    out = []
    for i, j, ov in overlaps:
        if ov.size < 20:
            continue
        target_idx = ov.target_idx
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(clouds[i][target_idx]))
        target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
        P = clouds[j][ov.source_idx]
        _, nearest = cKDTree(np.asarray(target.points)).query(P)
        N = np.asarray(target.normals)[nearest]
        w = row_weights(N, rays[j][ov.source_idx], rays[i][target_idx[nearest]], covering[j][ov.source_idx],
                        sigma_mm)
        c = P.mean(axis=0)
        J = np.c_[N, np.cross(P - c, N)]
        out.append(PairData(i, j, c, (J * w[:, None]).T @ J,
                            residual_chi2_per_dof(clouds[i], trees[i], normals[i], P, normals[j][ov.source_idx])))
    return out


def row_weights(normals: np.ndarray, source_rays: np.ndarray, target_rays: np.ndarray, covering: np.ndarray,
                sigma_mm: float) -> np.ndarray:
    """The information (1/mm^2) of each point-to-plane row of a pair: a source point against its nearest target
    point, along the unit ``normals`` (W). Each point errs by ``sigma_mm`` along its ray (``*_rays``, any length, W: the
    simulator's noise, ``raycast.ScannerModel``), so by ``sigma_mm |n . ray|`` along the normal: the row's variance
    is ``2 sigma_mm^2`` times the correction's ``joint.ray_variances`` (grazing rows floored alike). ``covering``:
    how many scans cover the source point (its own and every other within ``OVERLAP_MM``); where ``k`` do, the
    pairs there share each scan's noise and each row counts ``2 / k`` of its information (``joint.noise_shares``: exact
    for an unknown surface; counting each row at full weight counts every point's noise once per partner,
    ``k / 2`` times too much). docs/correction.md, "Shared noise and the scanner's rays"."""
    variance = 2.0 * sigma_mm**2 * ray_variances(normals, source_rays, target_rays)
    return noise_shares(covering) / variance


def residual_chi2_per_dof(target: np.ndarray, target_tree: cKDTree, target_normals: np.ndarray, source: np.ndarray,
                          source_normals: np.ndarray) -> float:
    """:class:`PairData` ``chi2_per_dof`` of the ``source`` points (unit normals ``source_normals``) against the
    ``target`` cloud (its KD-tree, its unit normals; all W, mm, at the true poses) with the correction's symmetric,
    gated residual (``joint.symmetric_normals``); NaN with fewer than 20 points kept."""
    _, nearest = target_tree.query(source)
    N, cosine = symmetric_normals(target_normals[nearest], source_normals)
    keep = np.abs(cosine) >= MIN_NORMAL_COSINE
    if keep.sum() < 20:
        return float("nan")
    P, N = source[keep], N[keep]
    r = np.einsum("ij,ij->i", N, P - target[nearest[keep]])
    J = np.c_[N, np.cross(P - P.mean(axis=0), N)]
    Jtr = J.T @ r
    return float(Jtr @ np.linalg.lstsq(J.T @ J, Jtr, rcond=None)[0]) / (6.0 * max(float(np.mean(r**2)), 1e-30))


def world_error(T_estimate: np.ndarray, T_truth: np.ndarray) -> np.ndarray:
    """The small world motion (t mm, r rad) about the true origin that takes ``T_truth`` to ``T_estimate``."""
    _, r = to_rotvec(T_estimate @ invert(T_truth))
    return np.r_[T_estimate[:3, 3] - T_truth[:3, 3], r]


def median_draws(A: np.ndarray, cov: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """The median over the scans of the translation error norm (mm) in each of ``DRAWS`` draws of
    ``theta ~ N(0, cov)``: its mean is the expected median, its spread how far one job's median may fall from it."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    theta = rng.standard_normal((DRAWS, len(w))) * np.sqrt(np.clip(w, 0, None)) @ V.T
    t = (theta @ A.T).reshape(DRAWS, n, 6)[:, :, :3]
    return np.median(np.linalg.norm(t, axis=2), axis=1)


@dataclass(frozen=True)
class BoundModel:
    """The linear error model of a job at its true poses: scan errors ``A theta`` (6 a scan, about its origin,
    world; mm, rad), the unknowns' covariance tracker-only (``prior``) and at the bound (``posterior``: every
    overlap point added), the scans' true origins in W (mm, what ``A`` is about) and the pairs in it."""

    A: np.ndarray
    prior: np.ndarray
    posterior: np.ndarray
    origins: tuple[np.ndarray, ...]
    pairs: tuple[PairData, ...]


def bound_model(result: JobResult, T_T_S: np.ndarray, config, true_T_W_S: dict[int, np.ndarray]) -> BoundModel:
    """The :class:`BoundModel` of the job ``result``."""
    A, prior, origins = error_model(result, T_T_S, true_T_W_S)
    info = np.linalg.inv(prior)
    pairs = overlap_information(result, true_T_W_S, config.job.voxel_mm, config.scanner.noise_sigma_mm,
                                config.correction.pair_cell_mm)
    for pair in pairs:
        i, j = pair.i, pair.j
        to_j, to_i = recentre(origins[j], pair.centre), recentre(origins[i], pair.centre)
        H = to_j @ A[6 * j:6 * j + 6] - to_i @ A[6 * i:6 * i + 6]
        cols = np.flatnonzero(np.any(H != 0.0, axis=0))  # the two scans' and their transfers' unknowns
        info[np.ix_(cols, cols)] += H[:, cols].T @ pair.information @ H[:, cols]
    return BoundModel(A, prior, np.linalg.inv(info), tuple(origins), tuple(pairs))


def chi2_summary(pairs: Sequence[PairData], stations: np.ndarray) -> dict:
    """Median ``chi2_per_dof`` of the pairs within each tracker station, across stations and over all."""
    groups = {"all": list(pairs), "across_stations": [p for p in pairs if stations[p.i] != stations[p.j]]}
    groups |= {f"station_{k}": [p for p in pairs if stations[p.i] == stations[p.j] == k] for k in np.unique(stations)}
    return {name: round(float(np.nanmedian([p.chi2_per_dof for p in group])), 3)
            for name, group in groups.items() if group}


def bound(result: JobResult, T_T_S: np.ndarray, config, true_T_W_S: dict[int, np.ndarray],
          corrected_mm: float | None = None) -> dict:
    """Tracker-only and best-possible expected median pose error (mm) of the job ``result`` (``true_T_W_S``:
    the scans' true poses, from the ground-truth observer), and the check of the correction's residual at the
    truth (``overlap_chi2_per_dof``)."""
    model = bound_model(result, T_T_S, config, true_T_W_S)
    A, prior, posterior = model.A, model.prior, model.posterior
    n = len(result.scans)
    rng = np.random.default_rng(0)
    tracker_only = float(np.mean(median_draws(A, prior, n, rng)))
    ideal = median_draws(A, posterior, n, rng)   # an efficient estimator's median, job by job
    best = float(np.mean(ideal))
    stations = np.array([s.tracker_station for s in result.scans])
    sigma = {}
    for name, cov in (("tracker_only", prior), ("bound", posterior)):
        A_t = A.reshape(n, 6, -1)[:, :3].reshape(3 * n, -1)             # the translation rows
        per_scan = np.sqrt(np.sum((A_t @ cov) * A_t, axis=1)).reshape(n, 3)
        sigma[name] = {int(k): np.round(per_scan[stations == k].mean(axis=0), 4).tolist() for k in np.unique(stations)}
    return {"pairs_in_bound": len(model.pairs), "expected_tracker_only_mm": round(tracker_only, 4),
            "bound_mm": round(best, 5), "bound_ratio": round(tracker_only / best, 2),
            "bound_mm_p95": round(float(np.percentile(ideal, 95)), 4),
            "ideal_above_1_2x_bound_fraction": round(float(np.mean(ideal > 1.2 * best)), 3),
            **({} if corrected_mm is None else
               {"corrected_above_ideal_fraction": round(float(np.mean(ideal >= corrected_mm)), 4)}),
            "overlap_chi2_per_dof": chi2_summary(model.pairs, stations),
            "sigma_xyz_mm_per_station": sigma}


def corrected_from_truth(result: JobResult, T_T_S: np.ndarray, config, scorer: TruthScorer,
                         tracker_T_W_S: list[np.ndarray], mount: MountPrior | None) -> dict:
    """The correction's joint refinement of the job (its settings, scans, tracker and transfer priors, ``mount``
    prior) started at the true poses instead of the tracker poses: its correspondences found, its residuals
    weighted and linearised at the truth. It removes every error of the start (correspondences and weights at
    poses that are off); its median pose error (mm, per station as well) is what the correction's measurement
    model makes of this draw's data. ``corrected_from_truth_cloud_rms_mm``: the cloud merged at those poses,
    scored as the job's (``scorer``, the simulator's)."""
    cfg, true_T_W_S = config.correction, scorer.T_W_S_true
    seen = [k for k, s in enumerate(result.scans) if s.point_count > 0]      # the scans the job corrects
    scans = [result.scans[k] for k in seen]
    thinned = [joint_scan(read_raw_scan(s.file)[0], cfg.joint_voxel_mm) for s in scans]
    priors = [ScanPrior(tracker_T_W_S[k], scan_pose_covariance(s.T_W_C, s.reading.T_C_T, T_T_S, s.reading.covariance),
                        s.tracker_station) for k, s in zip(seen, scans, strict=True)]
    world = [transform_points(p.T_W_S, t.points_S) for p, t in zip(priors, thinned, strict=True)]
    pairs = overlapping_pairs(world, [s.tracker_station for s in scans], cfg.pair_cell_mm,
                              cfg.joint_max_partners_per_scan)
    joint = refine_jointly(thinned, priors, pairs, [true_T_W_S[s.index] for s in scans],
                           transfer_priors(result.report["transfer_log"]), mount, JointSettings.from_section(cfg))
    poses = list(tracker_T_W_S)
    for k, T in zip(seen, joint.poses, strict=True):
        poses[k] = T
    mm = np.array([np.linalg.norm(world_error(T, true_T_W_S[s.index])[:3]) for s, T in zip(result.scans, poses,
                                                                                           strict=True)])
    stations = np.array([s.tracker_station for s in result.scans])
    return {"corrected_from_truth_mm": round(float(np.median(mm)), 5),
            "corrected_from_truth_cloud_rms_mm": round(cloud_rms_mm(result, poses, scorer, config.job.voxel_mm), 4),
            "corrected_from_truth_mm_per_station": {int(k): round(float(np.median(mm[stations == k])), 4)
                                                    for k in np.unique(stations)}}


def cloud_rms_mm(result: JobResult, poses: list[np.ndarray], scorer: TruthScorer, voxel_mm: float) -> float:
    """RMS distance (mm) to the part of the job's scans merged at ``poses`` (W) into a ``voxel_mm`` map, as the
    job merges and the simulator scores its cloud."""
    cloud = merge_stage(voxel_mm, [s.file for s in result.scans], poses).points()
    distances = cloud_to_mesh_distances(scorer.world.scene, cloud, invert(scorer.world.T_W_F))
    return float(distance_stats(distances)["rms_mm"])


async def one_seed(config, plan: Plan, seed: int) -> dict:
    config = config.model_copy(update={"sim": config.sim.model_copy(update={"seed": seed})})
    with tempfile.TemporaryDirectory() as tmp:
        async with CellSession(config) as session:
            config = with_surveyed_mounts(config, session.cell.simulation, Path(tmp))
            runner = JobRunner(session, plan, config, Path(tmp) / "job")
            result = await runner.run()
        r = result.report
        before, after = r["correction"].get("before", r["ground_truth"]), r["ground_truth"]
        figures = {"seed": seed, "scans": r["scans"], "transfers": r["transfers"],
                   "tracker_only_mm": round(before["pose_err_mm_median"], 4),
                   "corrected_mm": round(after["pose_err_mm_median"], 5),
                   "ratio": round(before["pose_err_mm_median"] / after["pose_err_mm_median"], 2),
                   "cloud_rms_mm": round(before["cloud_rms_mm"], 4),
                   "corrected_cloud_rms_mm": round(after["cloud_rms_mm"], 4)}
        figures |= {k: r.get("timings", {}).get(k) for k in ("after_last_scan_s", "correction_cpu_s")}
        tracker = [np.asarray(e.get("T_W_S_tracker", e["T_W_S"])) for e in r["scan_log"]]
        scorer, T_T_S = runner.observer.scorer(), runner.installation.T_T_S
        figures |= bound(result, T_T_S, config, scorer.T_W_S_true, after["pose_err_mm_median"])
        mount, _ = mount_prior(config, runner.installation)
        figures |= corrected_from_truth(result, T_T_S, config, scorer, tracker, mount)
        joint = r["correction"].get("joint")
        if joint is not None:   # the joint refinement's own posterior, beside the bound's
            figures["sigma_xyz_mm_per_station"]["joint_posterior"] = joint["sigma_xyz_mm_per_station"]["posterior"]
        figures["corrected_over_bound"] = round(figures["corrected_mm"] / figures["bound_mm"], 3)
        figures["corrected_from_truth_over_bound"] = round(figures["corrected_from_truth_mm"] / figures["bound_mm"], 3)
        return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plan", help="plan file, or 'generated' to plan the whole part (default: the band plan)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[7])
    parser.add_argument("--resolution", choices=["coarse", "full"], default="coarse")
    args = parser.parse_args()
    config = load_config(None)
    config = config.model_copy(update={"scanner": config.scanner.model_copy(update={"resolution": args.resolution})})
    if args.plan == "generated":
        plan = generated_plan(config)
    else:
        plan = Plan.load(Path(args.plan) if args.plan else default_plan_path())
    runs = []
    for seed in args.seeds:
        runs.append(asyncio.run(one_seed(config, plan, seed)))
        print(json.dumps(runs[-1]), flush=True)
    mean = {k: round(float(np.mean([r[k] for r in runs])), 5) for k in ("corrected_mm", "bound_mm")}
    med = {k: float(np.median([r[k] for r in runs])) for k in
           ("tracker_only_mm", "corrected_mm", "ratio", "expected_tracker_only_mm", "bound_mm", "bound_ratio")}
    name = f"pose_bound-{plan.name}" + ("-full" if args.resolution == "full" else "")
    publish(name, {"plan": plan.name, "seeds": args.seeds, "runs": runs,
                      "pose_err_mm_median": med["tracker_only_mm"], "corrected_pose_err_mm_median": med["corrected_mm"],
                      "ratio_median": med["ratio"], "bound_pose_err_mm_median": med["bound_mm"],
                      "expected_tracker_only_mm_median": med["expected_tracker_only_mm"],
                      "bound_ratio_median": med["bound_ratio"], "five_x_within_bound": med["bound_ratio"] >= 5.0,
                      "corrected_mm_mean": mean["corrected_mm"], "bound_mm_mean": mean["bound_mm"],
                      "corrected_over_bound_mean": round(mean["corrected_mm"] / mean["bound_mm"], 3),
                      "corrected_over_bound_max": max(r["corrected_over_bound"] for r in runs)})


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

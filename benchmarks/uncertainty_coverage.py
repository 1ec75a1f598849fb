"""Is the per-point expanded uncertainty U honest? Its coverage on a defect-free part, and a Monte Carlo check.

Usage: python benchmarks/uncertainty_coverage.py [--plan FILE] [--seeds 7 8 9] [--draws 200]
(band plan: about 1.5 min a seed on the idle 2-core machine; the whole part, a plan file of `tandemscan plan`:
far longer)

For each seed the default job runs on the simulated cell, calibrated (the cell's surveyed mounts, a calibration
file exact to 0.1 um, ``sim_drivers.cell.with_surveyed_mounts``), on the default part, which is its own CAD: every
point's true deviation is zero, so its measured deviation (``cloud_deviation.ply`` ``deviation_mm``) should lie
within +-U (``uncertainty_mm``, k = 2) for about 95 % of the points (target 93 to 97.5 %), overall and among the
points whose largest share comes from each tracker station's scans (``coverage_pct``,
``coverage_pct_per_station``).

The Monte Carlo check (GUM Supplement 1, JCGM 101:2008) draws what the first-order propagation linearises
(docs/verdict.md, "Per-point uncertainty"): the scans' pose errors from the job's own joint covariance (the
model the job evaluated, captured from ``daemon.jobs.outputs.job_uncertainty``), each scan moved by its exact rigid
motion (not the linearised one) and the points by their voxels' shares of the scans, the noise along the normal;
then the real best fit to the CAD (``inspect.best_fit``, point-to-plane ICP on the CAD surface, trimmed at
``best_fit_max_distance_mm``) on an even subsample, and the real signed distances of an even subsample of
evaluation points. ``mc_ratio_median``: the median over those points of first-order U over 2 x the draws' standard
deviation (target within 10 % of 1). Attribution of points to scans and the evaluation at the nearest centre are
shared by both, so the check is of the linearisation and of the best fit's absorption.

``model_coverage_pct_per_station``: the same draws read as coverage, per tracker station (:func:`model_coverage`):
the spread of a station's share within +-U that the job's own model predicts from one job to the next. A station's
points share its transfers' and scans' pose errors, so its coverage in one job is one draw of that spread (whole
part: about +-1 %, skewed low); ``stations_outside_model_5_95`` lists the stations measured outside it.

``truth_split_per_station`` tells which part of U falls short where coverage does (:func:`truth_split`): the
systematic part from the simulator's true scan poses against U's non-noise part, the noise against the model's,
and the scans' true pose errors against the job's pose covariance.

The last line of output is one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
from pathlib import Path

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config import load_config
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs import outputs as job_outputs
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, to_rotvec, transform_points
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.inspection.inspect import CadSurface, best_fit
from tandemscan.pipeline.io.cloud_io import read_ply_vertices
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.sim_drivers.cell import with_surveyed_mounts

#: evaluation points of the Monte Carlo: enough that a station's share of them within +-U in one draw is not
#: itself noise (5,000 points of a station: 0.3 % binomial scatter against the ~1 % its pose errors give)
EVAL_POINTS = 20000
FIT_POINTS = 6000


def capture_models() -> list:
    """Every ``(JobUncertainty, JobSnapshot)`` a job evaluates in this process, appended to the list returned (the
    snapshot's ``scorer`` holds the simulator's true scan poses, for :func:`truth_split` only)."""
    models = []
    plain = job_outputs.job_uncertainty

    def kept(job, *args, **kwargs):
        m = plain(job, *args, **kwargs)
        models.append((m, job))
        return m

    job_outputs.job_uncertainty = kept
    return models


def pose_error_factor(poses) -> np.ndarray:
    """(6n, r) ``G`` with ``G G^T`` the covariance of the job's scans' pose errors jointly (``poses``: its
    ``PoseCovariance``): the blocks of every pair of scans (``PoseCovariance.scan_errors``) formed whole and
    factored by their eigendecomposition, so that ``G z`` (``z`` standard normal) draws the errors. Dense: a job of a
    few hundred scans."""
    n = len(poses.scan_ids)
    errors = poses.scan_errors(np.c_[np.triu_indices(n)])
    full = np.concatenate([errors.covariance(np.full(n, i), np.arange(n)).transpose(1, 0, 2).reshape(6, 6 * n)
                           for i in range(n)])
    w, V = np.linalg.eigh(0.5 * (full + full.T))
    w = np.clip(w, 0.0, None)
    big = w > 1e-12 * max(float(w.max()), 1e-300)
    return V[:, big] * np.sqrt(w[big])


def monte_carlo(model, surface: CadSurface, p_F: np.ndarray, T_F_W: np.ndarray, draws: int, max_mm: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(evaluation point indices, their fitted deviations in each of ``draws``: (draws, points) mm)."""
    ev = np.arange(len(p_F))[:: max(1, len(p_F) // EVAL_POINTS)]
    fit = np.arange(len(p_F))[:: max(1, len(p_F) // FIT_POINTS)]
    idx = np.r_[ev, fit]
    cp = surface.closest(p_F[idx])
    true_F, n_F = cp.points_mm, cp.normals                      # the part's surface where the points are
    T_W_F = invert(T_F_W)
    true_W = transform_points(T_W_F, true_F)
    scans, w = model.cover.shares(true_W)
    rows = model._pose_rows()[scans]
    n_W = true_W.shape[0]
    noise_sd = np.sqrt(model.noise_sigma_mm**2 * model._ray_cosines_sq(true_W, n_F @ T_F_W[:3, :3], (scans, w))
                       / np.maximum(1.0 if model.counts is None else model.counts[idx], 1.0))
    G = pose_error_factor(model.poses)
    origins = model.poses.origins_mm
    out = np.empty((draws, len(ev)))
    for d in range(draws):
        e = (G @ rng.standard_normal(G.shape[1])).reshape(-1, 6)
        moved = np.zeros((n_W, 3))
        for k in range(rows.shape[1]):
            for r in np.unique(rows[:, k]):
                at = rows[:, k] == r
                o = origins[r]
                T = from_rotvec(o, [0, 0, 0]) @ from_rotvec(e[r, :3], e[r, 3:]) @ from_rotvec(-o, [0, 0, 0])
                moved[at] += w[at, k, None] * (transform_points(T, true_W[at]) - true_W[at])
        q_F = transform_points(T_F_W, true_W + moved) + (noise_sd * rng.standard_normal(n_W))[:, None] * n_F
        fit = best_fit(surface, q_F[len(ev):], max_mm, iterations=30)
        out[d] = surface.signed_distance(transform_points(fit.T_F_M, q_F[: len(ev)]))
    return ev, out


def model_coverage(inside: np.ndarray, stations: np.ndarray) -> dict:
    """What coverage each tracker station's points would show if the job's own error model were the truth: per
    station the 5th, 50th and 95th percentile over the Monte Carlo draws of the share (%) of its evaluation points
    within +-U (``inside``: draws x points), and the share of draws (%) below 93 % and above 97.5 %. A station's
    points err together (its transfers, its scans' poses), so one job is one draw of its coverage: its measured
    share is judged against this spread, not against the mean."""
    out = {}
    for s in np.unique(stations):
        share = 100.0 * inside[:, stations == s].mean(axis=1)
        out[int(s)] = {"p5_p50_p95": [round(float(v), 2) for v in np.percentile(share, [5, 50, 95])],
                       "below_93_pct": round(100.0 * float(np.mean(share < 93.0)), 1),
                       "above_97_5_pct": round(100.0 * float(np.mean(share > 97.5)), 1)}
    return out


def truth_split(model, job, surface: CadSurface, p_F: np.ndarray, d: np.ndarray, U: np.ndarray, T_F_W: np.ndarray,
                T_W_F_true: np.ndarray, station_of_scan: np.ndarray, rng: np.random.Generator) -> dict:
    """Where U falls short, from the simulator's truth, per tracker station (an even sample of the points, each
    counted for the station of its largest share): each point's systematic deviation (its scans' true pose errors
    by their shares, through the job's alignment against the true placement) against U's non-noise part
    (``systematic_rms_mm``, ``systematic_predicted_rms_mm``), the rest over the model's noise (``noise_z``, 1 when
    honest), and the mean chi-square of the scans' true pose errors (about their origins) under the job's pose
    covariance (``pose_chi2_mean``, 6 when honest)."""
    at = rng.choice(len(p_F), min(300_000, len(p_F)), replace=False)
    p, dd, UU = p_F[at], d[at], U[at]
    n_F = surface.closest(p).normals
    noise = model.evaluate(p, n_F, 2.0, T_F_W, "best-fit", at, None).noise_variance_mm2
    p_W = transform_points(invert(T_F_W), p)
    idx, w = model.cover.shares(p_W)
    scans = model.cover.scan_ids[idx]
    error = np.array([np.asarray(s.T_W_S) @ invert(job.scorer.T_W_S_true[s.index]) for s in job.scans])
    moved = sum(w[:, k, None] * (transform_points_each(error[scans[:, k]], p_W) - p_W) for k in range(idx.shape[1]))
    systematic = np.einsum("ij,ij->i", p - transform_points(invert(T_W_F_true), p_W - moved), n_F)
    predicted = np.clip((UU / 2.0) ** 2 - noise, 0.0, None)
    station = station_of_scan[scans[:, 0]]
    covariances = model.poses.scan_covariances()
    chi2 = {}
    for r, s in enumerate(model.poses.scan_ids):
        o = model.poses.origins_mm[r]
        t, rv = to_rotvec(from_rotvec(-o, [0, 0, 0]) @ error[s] @ from_rotvec(o, [0, 0, 0]))
        e = np.r_[t, rv]
        chi2.setdefault(int(station_of_scan[s]), []).append(float(e @ np.linalg.solve(covariances[r], e)))
    out = {}
    for k in np.unique(station):
        m = station == k
        out[int(k)] = {"systematic_rms_mm": round(float(np.sqrt(np.mean(systematic[m] ** 2))), 4),
                       "systematic_predicted_rms_mm": round(float(np.sqrt(np.mean(predicted[m]))), 4),
                       "noise_z": round(float(np.std((dd[m] - systematic[m]) / np.sqrt(noise[m]))), 3),
                       "pose_chi2_mean": round(float(np.mean(chi2.get(int(k), [np.nan]))), 2)}
    return out


def transform_points_each(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, 3) each point ``p[i]`` moved by its own 4x4 ``T[i]`` (mm)."""
    return np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]


async def one_seed(config, plan: Plan, seed: int, draws: int, models: list) -> dict:
    config = config.model_copy(update={"sim": config.sim.model_copy(update={"seed": seed})})
    with tempfile.TemporaryDirectory() as tmp:
        async with CellSession(config) as session:
            config = with_surveyed_mounts(config, session.cell.simulation, Path(tmp))
            result = await JobRunner(session, plan, config, Path(tmp) / "job").run()
            T_W_F_true = np.asarray(session.cell.simulation.world.T_W_F, float)  # the truth: scoring only
        ins = result.report["inspection"]
        ply = read_ply_vertices(Path(tmp) / "job" / ins["files"]["deviation_ply"])
    model, job = models[-1]
    p_F = np.column_stack([ply[a] for a in "xyz"]).astype(float)
    d, U = ply["deviation_mm"].astype(float), ply["uncertainty_mm"].astype(float)
    inside = np.abs(d) <= U
    T_F_W = np.asarray(ins["T_F_W"], float)
    scans = model.cover.shares(transform_points(invert(T_F_W), p_F), k=1)[0][:, 0]
    stations = np.array([s.tracker_station for s in result.scans])[model.cover.scan_ids[scans]]
    surface = CadSurface(load_part_mesh(config.part))
    ev, drawn = monte_carlo(model, surface, p_F, T_F_W, draws, config.inspection.best_fit_max_distance_mm,
                            np.random.default_rng(seed))
    ratio = U[ev] / (2.0 * drawn.std(axis=0))
    split = truth_split(model, job, surface, p_F, d, U, T_F_W, T_W_F_true,
                        np.array([s.tracker_station for s in job.scans]), np.random.default_rng(seed))
    return {"seed": seed, "points": int(len(d)), "scans": result.report["scans"],
            "coverage_pct": round(100.0 * float(inside.mean()), 2),
            "coverage_pct_per_station": {int(s): round(100.0 * float(inside[stations == s].mean()), 2)
                                         for s in np.unique(stations)},
            "points_per_station": {int(s): int((stations == s).sum()) for s in np.unique(stations)},
            "U_median_mm": round(float(np.median(U)), 4), "U_p95_mm": round(float(np.percentile(U, 95)), 4),
            "deviation_rms_mm": round(float(np.sqrt(np.mean(d**2))), 4),
            "budget_mm": ins["uncertainty"]["budget_mm"], "verdict": ins["verdict"],
            "mc_draws": draws, "mc_points": int(len(ev)), "mc_ratio_median": round(float(np.median(ratio)), 3),
            "mc_ratio_p5_p95": [round(float(v), 3) for v in np.percentile(ratio, [5, 95])],
            "model_coverage_pct_per_station": model_coverage(np.abs(drawn) <= U[ev], stations[ev]),
            "truth_split_per_station": split}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plan", help="plan file (default: the band plan; the whole part: `tandemscan plan` first)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[7, 8, 9])
    parser.add_argument("--draws", type=int, default=200, help="Monte Carlo draws a seed")
    args = parser.parse_args()
    config = load_config(None)
    plan = Plan.load(Path(args.plan or default_plan_path()))
    models = capture_models()
    runs = []
    for seed in args.seeds:
        runs.append(asyncio.run(one_seed(config, plan, seed, args.draws, models)))
        print(json.dumps(runs[-1]), flush=True)
    per_station = [v for r in runs for v in r["coverage_pct_per_station"].values()]
    cov = [r["coverage_pct"] for r in runs]
    publish(f"uncertainty_coverage-{plan.name}", {
        "plan": plan.name, "seeds": args.seeds, "runs": runs,
        "coverage_pct_min": min(cov), "coverage_pct_max": max(cov),
        "coverage_pct_per_station_min": min(per_station), "coverage_pct_per_station_max": max(per_station),
        "coverage_within_93_97_5": all(93.0 <= v <= 97.5 for v in cov + per_station),
        "stations_outside_model_5_95": [
            {"seed": r["seed"], "station": s, "coverage_pct": v,
             "model_p5_p95": [r["model_coverage_pct_per_station"][s]["p5_p50_p95"][k] for k in (0, 2)]}
            for r in runs for s, v in r["coverage_pct_per_station"].items()
            if not (r["model_coverage_pct_per_station"][s]["p5_p50_p95"][0] <= v
                    <= r["model_coverage_pct_per_station"][s]["p5_p50_p95"][2])],
        "mc_ratio_median": float(np.median([r["mc_ratio_median"] for r in runs])),
        "mc_within_10_pct": all(abs(r["mc_ratio_median"] - 1.0) <= 0.1 for r in runs)})


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

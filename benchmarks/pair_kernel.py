"""The pair registration kernel on the job's pairs, beside small_gicp and Open3D, and the pair stage on 1 and 2
workers; prints one JSON object (last line).

The default band job runs on the simulated cell (coarse resolution, correction off); its scans are taken as the end
of the job takes them (``read_thinned_scan``, ``daemon.jobs.pose_correction.stitched_scans``) and its pairs as the
correction selects them (``overlap.overlapping_pairs``), each scored against the simulator's truth: ``rot_err_deg`` and
``trans_err_mm`` (at the source's centroid) of the pair's correction against the true one, medians and 90th
percentiles over the pairs; ``stitch`` is the tracker stitch itself (no correction). Kernels, each on one thread and
each preparing its target per pair:

- ``numpy_icp_50``: the fine stage as the job's pairs ran it until now (``correct_pair`` with 50 iterations a level)
- ``numpy_icp``: the same at ``[correction] job_pair_iterations`` (the default)
- ``numpy_icp_shared_targets``: ``numpy_icp`` with each target prepared once and kept for its later pairs (its KD-tree
  and normals, counted in the pair that first needs them), as the pair stage and the online pairs run it
- ``small_gicp_plane_icp`` / ``small_gicp_gicp``: small_gicp's point-to-plane ICP / GICP (normals or covariances
  of 20 neighbours, its KD-tree), coarse to fine as ours: each level on the source overlap at the estimate thinned
  to ``icp_max_points``, the distance shrinking from the overlap threshold to ``icp_max_distance_mm``
- ``open3d_icp``: Open3D's point-to-plane ``registration_icp`` at the overlap threshold, then at the final distance

``seconds_per_pair_median`` / ``_mean`` (wall, one thread), ``cpu_s_per_pair_mean`` (the thread's CPU seconds: far
less sensitive to a shared CPU's load), ``speedup_vs_numpy_icp_50`` and ``cpu_speedup_vs_numpy_icp_50`` (means).
``stage``: the pair stage of the job (``pair_stage.register_units``, every pair, one unit a target) at the default
kernel on ``LocalBackend`` with 1 and with 2 threads, and on a Dask ``LocalCluster`` of 1 and 2 single-threaded
worker processes reading the scans from the job folder (``StoredScans``), after a warm-up; ``pairs_per_s`` (the best
of ``--rounds`` runs, 1 and 2 alternating), ``cpu_s_per_pair`` of that run (this process's CPU, or the workers') and
``throughput_ratio_2_vs_1`` of each. The CPU is shared with whatever
else runs: run it with ``nice -n 10`` and read the seconds as an upper bound; the errors do not depend on it.

Usage: python benchmarks/pair_kernel.py [--kernels numpy_icp,numpy_icp_50,...] [--no-stage] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
import small_gicp
from clean_exit import clean_exit_on_sigterm
from results import publish
from scipy.spatial import cKDTree
from tandemscan.config import load_config
from tandemscan.config.models import CorrectionConfig
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.pose_correction import stitched_scans, transfer_priors
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.compute import DaskBackend, LocalBackend
from tandemscan.pipeline.geometry.frames import invert, rotation_angle, transform_points
from tandemscan.pipeline.io.raw_scan import read_thinned_scan
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.pipeline.registration.correction import pair_covariance
from tandemscan.pipeline.registration.icp import target_with_normals
from tandemscan.pipeline.registration.overlap import overlap_at, overlapping_pairs
from tandemscan.pipeline.registration.pair_stage import (
    HeldScans,
    ScanRef,
    StoredScans,
    TargetPairs,
    register_stitched_pair,
    register_units,
)
from tandemscan.pipeline.registration.pairs import JobPairSettings, pair_delta
from tandemscan.pipeline.registration.sampling import thin_evenly, voxel_downsample
from tandemscan.sim_drivers.cell import with_surveyed_mounts

#: small_gicp / Open3D: iterations a level and the convergence of a level (rad, mm): as tight as ours
OTHER_ITERATIONS, ROTATION_EPS_RAD, TRANSLATION_EPS_MM = 50, 1e-7, 1e-6


class JobPairs:
    """The band job's scans (as the correction takes them), its pairs, their covariances and true corrections."""

    def __init__(self, folder: Path):
        config = load_config(None)
        config = config.model_copy(update={"correction": config.correction.model_copy(update={"enabled": False})})

        async def run():
            async with CellSession(config) as session:
                surveyed = with_surveyed_mounts(config, session.cell.simulation, folder)
                runner = JobRunner(session, Plan.load(default_plan_path()), surveyed, folder / "job")
                await runner.run()
                return runner.snapshot()

        job = asyncio.run(run())
        self.folder, self.cfg, self.voxel_mm = job.job_dir, CorrectionConfig(), config.job.voxel_mm
        self.scans = stitched_scans(job, [read_thinned_scan(s.file, self.voxel_mm) for s in job.scans])
        transfers = transfer_priors(job.transfers)
        self.world = [transform_points(s.T_W_S, voxel_downsample(np.asarray(s.points_S, float), self.voxel_mm))
                      for s in self.scans]
        self.pairs = overlapping_pairs(self.world, [s.station for s in self.scans], self.cfg.pair_cell_mm,
                                       self.cfg.max_partners_per_scan)
        self.covariances = [pair_covariance(self.scans[i], self.scans[j], transfers) for i, j in self.pairs]
        truth = job.scorer.T_W_S_true
        self.true_corrections = [self.scans[i].T_W_S @ invert(truth[job.scans[i].index]) @ truth[job.scans[j].index]
                                 @ invert(self.scans[j].T_W_S) for i, j in self.pairs]

    def error(self, k: int, T: np.ndarray) -> tuple[float, float]:
        """(deg, mm at the source's centroid) of pair ``k``'s correction ``T`` against the true one."""
        D = T @ invert(self.true_corrections[k])
        c = self.world[self.pairs[k][1]].mean(axis=0)
        return float(np.degrees(rotation_angle(D))), float(np.linalg.norm(transform_points(D, c[None])[0] - c))

    def units(self) -> list[TargetPairs]:
        """The pair stage's units: one a target, its sources in pair order."""
        by_target: dict[int, list[int]] = {}
        for k, (i, _) in enumerate(self.pairs):
            by_target.setdefault(i, []).append(k)

        def ref(n: int) -> ScanRef:
            return ScanRef(n, self.scans[n].file, self.scans[n].T_W_S)

        return [TargetPairs(ref(i), tuple(ref(self.pairs[k][1]) for k in ks), tuple(self.covariances[k] for k in ks))
                for i, ks in by_target.items()]


def ours(iterations: int, shared_targets: bool = False) -> Callable:
    """Our kernel at ``iterations`` a level; ``shared_targets``: each target prepared once (KD-tree, normals where
    first needed) and kept for its later pairs, as the pair stage and the online pairs do."""
    prepared: dict[int, object] = {}

    def kernel(source: np.ndarray, target: np.ndarray, cov: np.ndarray, cfg: CorrectionConfig) -> np.ndarray:
        c = cfg.model_copy(update={"job_pair_iterations": iterations})
        if not shared_targets or id(target) not in prepared:
            prepared[id(target)] = target_with_normals(target)
        tgt = prepared[id(target)]
        out = register_stitched_pair(source, tgt, cov, JobPairSettings.from_section(c))
        return np.eye(4) if out.transformation is None else out.transformation
    return kernel


def small_gicp_kernel(kind: str) -> Callable:
    def kernel(source: np.ndarray, target: np.ndarray, cov: np.ndarray, cfg: CorrectionConfig) -> np.ndarray:
        tgt = small_gicp.PointCloud(target)
        tree = small_gicp.KdTree(tgt)
        if kind == "GICP":
            small_gicp.estimate_covariances(tgt, tree, 20)
        else:
            small_gicp.estimate_normals(tgt, tree, 20)
        source_tree, target_tree = cKDTree(source), cKDTree(target)
        M, final = np.eye(4), cfg.icp_max_distance_mm
        d = max(pair_delta(target, JobPairSettings.from_section(cfg), cov), final)
        while True:
            ov = overlap_at(source, source_tree, target, target_tree, M, d)
            if ov.size >= 10:
                src = small_gicp.PointCloud(source[thin_evenly(ov.source_idx, cfg.icp_max_points)])
                if kind == "GICP":
                    small_gicp.estimate_covariances(src, small_gicp.KdTree(src), 20)
                r = small_gicp.align(tgt, src, tree, M, registration_type=kind, max_correspondence_distance=d,
                                     max_iterations=OTHER_ITERATIONS, rotation_epsilon=ROTATION_EPS_RAD,
                                     translation_epsilon=TRANSLATION_EPS_MM)
                M = r.T_target_source
            if d <= final:
                return M
            d = max(final, 0.5 * d)
    return kernel


def open3d_kernel(source: np.ndarray, target: np.ndarray, cov: np.ndarray, cfg: CorrectionConfig) -> np.ndarray:
    reg = o3d.pipelines.registration
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    M = np.eye(4)
    for d in (max(pair_delta(target, JobPairSettings.from_section(cfg), cov), cfg.icp_max_distance_mm),
              cfg.icp_max_distance_mm):
        M = reg.registration_icp(src, tgt, d, M, reg.TransformationEstimationPointToPlane(),
                                 reg.ICPConvergenceCriteria(1e-9, 1e-9, OTHER_ITERATIONS)).transformation
    return M


def kernels(cfg: CorrectionConfig) -> dict[str, Callable]:
    return {"numpy_icp_50": ours(50), "numpy_icp": ours(cfg.job_pair_iterations),
            "numpy_icp_shared_targets": ours(cfg.job_pair_iterations, shared_targets=True),
            "small_gicp_plane_icp": small_gicp_kernel("PLANE_ICP"), "small_gicp_gicp": small_gicp_kernel("GICP"),
            "open3d_icp": open3d_kernel}


def errors_figures(errors: list[tuple[float, float]]) -> dict[str, float]:
    e = np.asarray(errors)
    return {"rot_err_deg_median": round(float(np.median(e[:, 0])), 6),
            "rot_err_deg_p90": round(float(np.percentile(e[:, 0], 90)), 6),
            "trans_err_mm_median": round(float(np.median(e[:, 1])), 5),
            "trans_err_mm_p90": round(float(np.percentile(e[:, 1], 90)), 5)}


def score_kernel(job: JobPairs, kernel: Callable) -> dict:
    seconds, cpu, errors = [], [], []
    for k, (i, j) in enumerate(job.pairs):
        t, c = time.perf_counter(), time.thread_time()
        T = kernel(job.world[j], job.world[i], job.covariances[k], job.cfg)
        seconds.append(time.perf_counter() - t)
        cpu.append(time.thread_time() - c)
        errors.append(job.error(k, T))
    return {**errors_figures(errors), "seconds_per_pair_median": round(float(np.median(seconds)), 4),
            "seconds_per_pair_mean": round(float(np.mean(seconds)), 4),
            "cpu_s_per_pair_mean": round(float(np.mean(cpu)), 4)}


def stage_throughput(job: JobPairs, backend, scans) -> tuple[float, float]:
    """(pairs a second, CPU seconds a pair) of the whole pair stage on ``backend`` (the CPU of this process, or of
    the Dask workers)."""
    def cpu_s() -> float:
        if isinstance(backend, DaskBackend):
            return sum(backend.client.run(time.process_time).values())
        return time.process_time()

    units, c = job.units(), cpu_s()
    t = time.perf_counter()
    register_units(units, scans, JobPairSettings.from_section(job.cfg), job.voxel_mm, backend)
    wall = time.perf_counter() - t
    return len(job.pairs) / wall, (cpu_s() - c) / len(job.pairs)


def forgotten(backend: DaskBackend, timeout_s: float = 30.0) -> None:
    """Wait until the scheduler holds no task (the round before's results are released, not reused: the keys are
    the same)."""
    deadline = time.monotonic() + timeout_s
    while backend.client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) and \
            time.monotonic() < deadline:
        time.sleep(0.1)


def stage(job: JobPairs, rounds: int) -> dict:
    """Pairs a second of the pair stage on 1 and 2 threads (``LocalBackend``) and Dask workers (``LocalCluster``):
    the best of ``rounds`` runs each, 1 and 2 alternating (a shared CPU's load comes and goes)."""
    local = {n: max(stage_throughput(job, LocalBackend(n), HeldScans(job.world)) for _ in range(rounds))
             for n in (1, 2)}  # the best round by its pairs a second
    clusters = {n: DaskBackend(workers=n, retries=0) for n in (1, 2)}
    try:
        for backend in clusters.values():
            backend.client.run(lambda: __import__("tandemscan.pipeline.registration.pair_stage"))  # warm up
        stored = StoredScans(str(job.folder), job.voxel_mm)
        runs = {n: [] for n in clusters}
        for _ in range(rounds):
            for n, backend in clusters.items():
                forgotten(backend)
                runs[n].append(stage_throughput(job, backend, stored))
    finally:
        for backend in clusters.values():
            backend.close()
    dask = {n: max(r) for n, r in runs.items()}
    out = {"rounds": rounds}
    for kind, best in (("local_threads", local), ("dask_workers", dask)):
        for n, (rate, cpu) in best.items():
            out |= {f"{kind}_{n}.pairs_per_s": round(rate, 3), f"{kind}_{n}.cpu_s_per_pair": round(cpu, 4)}
        out[f"{kind}.throughput_ratio_2_vs_1"] = round(best[2][0] / best[1][0], 3)
    return out


def main() -> None:
    clean_exit_on_sigterm()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kernels", default="numpy_icp_50,numpy_icp,numpy_icp_shared_targets,small_gicp_plane_icp,"
                        "small_gicp_gicp,open3d_icp")
    parser.add_argument("--no-stage", action="store_true", help="skip the 1 vs 2 workers figures")
    parser.add_argument("--rounds", type=int, default=3, help="runs of the stage on 1 and 2 workers (the best)")
    args = parser.parse_args()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    o3d.utility.set_max_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        job = JobPairs(Path(tmp))
        result = {"pairs": len(job.pairs), "scans": len(job.scans), "job_pair_iterations": job.cfg.job_pair_iterations,
                  "stitch": errors_figures([job.error(k, np.eye(4)) for k in range(len(job.pairs))])}
        available = kernels(job.cfg)
        for name in args.kernels.split(","):
            result[name] = score_kernel(job, available[name])
        if "numpy_icp_50" in result:
            base = result["numpy_icp_50"]["seconds_per_pair_mean"]
            base_cpu = result["numpy_icp_50"]["cpu_s_per_pair_mean"]
            for name in args.kernels.split(","):
                result[name]["speedup_vs_numpy_icp_50"] = round(base / result[name]["seconds_per_pair_mean"], 2)
                result[name]["cpu_speedup_vs_numpy_icp_50"] = round(base_cpu / result[name]["cpu_s_per_pair_mean"], 2)
        if not args.no_stage:
            result["stage"] = stage(job, args.rounds)
    publish("pair_kernel", result)


if __name__ == "__main__":
    main()

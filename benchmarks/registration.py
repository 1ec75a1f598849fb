"""Registration of overlapping scan pairs: our stages and methods beside Open3D's; prints one JSON object (last line).

Sets:
- ``real``: two overlapping crops (30-70 % overlap) of one real Stanford bunny scan (../shared/data, never
  copied into the repository), split into disjoint random halves so no point is shared, the source moved by
  a known tracker-like error (0.25-0.75 deg about a random axis, 1-3 mm): exact ground truth.
- ``real_arbitrary``: the same pairs with 5-45 deg and 2-10 mm (the paper's Fig. 24), no usable start.
- ``real_conf``: neighbouring bunny scans with Stanford's poses as reference (good to 0.1-0.6 deg and
  0.1-1.3 mm only), tracker-like error added; read it as a success rate.
- ``sim``: the default job on the simulated cell (coarse resolution, correction off), every overlapping
  scan pair as the tracker and its coordinate transfers stitched it, scored against the simulator's truth.
Every method gets the same two clouds (the whole moved source crop and the target crop) from the same start
(the identity), as ``tandemscan register`` would: ``icp`` (our fine stage: coarse-to-fine point-to-plane ICP
from the start, the overlap re-selected at each level, starting at the set's overlap threshold: 5 mm, 3 mm
for ``sim``, 10 m for ``real_arbitrary``, i.e. every point), ``deepmerge`` (the network's own answer, no
verification: DeepMerge alone),
``deepmerge+icp``, ``fpfh+icp`` (our FPFH + RANSAC, then the fine stage) and ``auto`` (the default of
``register``: the fine stage and FPFH + RANSAC, the network where they disagree, the best verified fit).
Anchors, what a user would pick instead: ``open3d_icp`` (Open3D point-to-plane ICP at the overlap threshold,
5 mm on ``real_arbitrary``) and ``open3d_fpfh_ransac_icp`` (FPFH + RANSAC as in ``global_registration``, then
Open3D point-to-plane ICP at 0.4 voxel, the Open3D tutorial's pipeline). Keys
``<set>.<method>.rot_err_deg_median``, ``.trans_err_mm_median`` (at the source's centroid), ``.success_rate``
(below 1 deg and 1 % of the pair's extent; a failed verification is no success), ``.failed`` (verification
failures: exit 3 in ``register``), ``.zero_inliers_exit0`` (results with no inlier that were not refused:
must be 0), ``.seconds_median`` (wall clock per pair, one thread); ``<set>.auto.stage_wins.<stage>``,
``<set>.auto.gate_mm_median`` (the correspondence gate of the final refinement).
Our verified methods refine their winner at its gate as ``register`` does (``pairs.REFINE_SIGMAS``) on the
real sets; on ``sim`` they run as the job's correction does, without it.
Repeatable: every random draw is seeded and Open3D runs on one thread (``o3d.utility.set_max_threads(1)``;
its RANSAC on several threads draws in the order its threads get to the generator, so the anchor moved
by 0.0015 deg between runs before), so two runs print the same figures, the seconds apart.
Set ``timing``: ``inference_2048``, DeepMerge on a pair of 2,048-point overlaps, one thread; ``register_cli``,
the wall clock and CPU time (user + system) of a ``tandemscan register`` call on two 30 k-point bunny scans,
the process start included, per method.

Usage: python benchmarks/registration.py [--pairs-per-scan 3] [--weights FILE] [--data DIR] [--sets real,sim,...]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from clean_exit import clean_exit_on_sigterm
from results import publish
from scipy.spatial.transform import Rotation
from tandemscan.config.models import CorrectionConfig, DeepMergeConfig
from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar
from tandemscan.pipeline.geometry.frames import from_quaternion, invert, make_transform, transform_points
from tandemscan.pipeline.registration.global_registration import FeatureMatching, fpfh_ransac
from tandemscan.pipeline.registration.icp import target_with_normals
from tandemscan.pipeline.registration.overlap import extract_overlap
from tandemscan.pipeline.registration.pairs import REFINE_SIGMAS, PairCriteria, RegistrationFailed, register_pair

VERIFIED = ("icp", "deepmerge+icp", "fpfh+icp", "auto")     # ours, verified as ``register`` runs them
ANCHORS = ("open3d_icp", "open3d_fpfh_ransac_icp")
METHODS = ("deepmerge", *VERIFIED, *ANCHORS)
SETS = ("real", "real_arbitrary", "real_conf", "sim", "timing")
NEIGHBOURS = {"bun000": ("bun045", "bun315"), "bun045": ("bun090",), "bun315": ("bun270",),
              "bun270": ("bun180",), "bun180": ("bun090",), "top2": ("bun000",), "chin": ("bun000",)}


def find_data(explicit: str | None) -> Path:
    """The bunny folder: --data, $TANDEMSCAN_DATA, or shared/data next to a parent of this checkout."""
    cands = [Path(explicit)] if explicit else []
    if os.environ.get("TANDEMSCAN_DATA"):
        cands.append(Path(os.environ["TANDEMSCAN_DATA"]))
    here = Path(__file__).resolve().parent
    cands += [p / "shared" / "data" for p in here.parents]
    for c in cands:
        if (c / "stanford-bunny" / "bun.conf").is_file():
            return c / "stanford-bunny"
    raise SystemExit("real data not found: pass --data or set TANDEMSCAN_DATA (../shared/data)")


def load_scans(folder: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (points mm in the scan frame, T_world_scan mm) with the README's pose convention."""
    out = {}
    for line in (folder / "bun.conf").read_text().splitlines():
        f = line.split()
        if not f or f[0] != "bmesh":
            continue
        t = np.array(f[2:5], float) * 1000.0
        R = from_quaternion([0, 0, 0], np.array(f[5:9], float))[:3, :3].T
        pts = np.asarray(o3d.io.read_point_cloud(str(folder / f[1])).points) * 1000.0
        out[Path(f[1]).stem] = (pts, make_transform(R, t))
    return out


def error_of(M: np.ndarray, M_true: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm at ``centre``) of an estimated vs true source->target transform.

    The angle comes from the nearest rotation matrix (scipy), not from the trace alone, which rounds
    errors below about 0.01 deg of a not exactly orthonormal matrix to zero.
    """
    rot = np.degrees(Rotation.from_matrix((M @ invert(M_true))[:3, :3]).magnitude())
    return float(rot), float(np.linalg.norm(transform_points(M, centre[None]) - transform_points(M_true, centre[None])))


def perturbation(rng, deg: tuple[float, float], mm: tuple[float, float], centre: np.ndarray) -> np.ndarray:
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(rng.uniform(*deg))).as_matrix()
    d = rng.normal(size=3)
    t = d / np.linalg.norm(d) * rng.uniform(*mm)
    return make_transform(R, centre - R @ centre + t)


def crop_pairs(scans, per_scan: int, rng) -> list[tuple[np.ndarray, np.ndarray]]:
    """Aligned (source, target) crops of single scans, 30-70 % overlap, disjoint random halves."""
    pairs = []
    for name in sorted(scans):
        P = scans[name][0]
        for _ in range(per_scan):
            d = rng.normal(size=3)
            d[2] = 0.0
            u = (P @ d).argsort().argsort() / len(P)
            L = 1.0 / (2.0 - rng.uniform(0.3, 0.7))
            half = rng.random(len(P)) < 0.5
            pairs.append((P[(u < L) & half], P[(u > 1.0 - L) & ~half]))
    return pairs


class MemoNetwork:
    """The network with its last answer kept, so that the methods of one pair share one inference."""

    def __init__(self, registrar: DeepMergeRegistrar) -> None:
        self.registrar = registrar
        self.key: tuple | None = None
        self.answer = np.eye(4)
        self.seconds = 0.0

    def register(self, source_mm: np.ndarray, target_mm: np.ndarray) -> np.ndarray:
        key = (source_mm.shape, float(source_mm.sum()), target_mm.shape, float(target_mm.sum()))
        if key != self.key:
            t0 = time.perf_counter()
            self.key, self.answer = key, self.registrar.register(source_mm, target_mm)
            self.seconds = time.perf_counter() - t0
        return self.answer


def open3d_icp(source, target, init, distance_mm) -> np.ndarray:
    """Open3D point-to-plane ICP as a user would call it (target normals from 30 neighbours)."""
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    return np.asarray(reg.registration_icp(src, tgt, distance_mm, init, reg.TransformationEstimationPointToPlane(),
                                           reg.ICPConvergenceCriteria(max_iteration=50)).transformation)


def run_pair(source, target, M_true, delta, cfg, network, refine_sigmas) -> dict[str, tuple]:
    """Register the moved source onto the target by each method: (rot deg, trans mm, seconds, extent, failed,
    zero inliers, stage, gate mm). The network runs once per pair; its time is added to each method that used
    it."""
    extent = float(np.linalg.norm(np.ptp(np.r_[source, target], axis=0)))
    c = source.mean(axis=0)
    out = {}
    network.key = None
    t0 = time.perf_counter()
    M = network.register(source, target)
    out["deepmerge"] = (*error_of(M, M_true, c), time.perf_counter() - t0, extent, False, False, "deepmerge", 0.0)
    for m in VERIFIED:
        t0 = time.perf_counter()
        try:
            tgt = target_with_normals(target)
            res = register_pair(source, tgt, PairCriteria.from_section(cfg, method=m), network, delta, refine_sigmas)
            rot, tr = error_of(res.transformation, M_true, c)
            failed, zero, stage, gate = False, res.fit.inliers == 0, res.stage, res.gate_mm or float("nan")
        except RegistrationFailed:
            rot, tr, failed, zero, stage, gate = float("inf"), float("inf"), True, False, "failed", float("nan")
        sec = time.perf_counter() - t0 + (network.seconds if stage_used_network(m, stage) else 0.0)
        out[m] = (rot, tr, sec, extent, failed, zero, stage, gate)
    anchor_icp = 5.0 if delta > 100 else delta
    t0 = time.perf_counter()
    M = open3d_icp(source, target, np.eye(4), anchor_icp)
    out["open3d_icp"] = (*error_of(M, M_true, c), time.perf_counter() - t0, extent, False, False, "init", 0.0)
    t0 = time.perf_counter()
    matching = FeatureMatching(cfg.global_voxel_fraction)
    M = open3d_icp(source, target, fpfh_ransac(source, target, matching), 0.4 * matching.voxel_mm(target))
    out["open3d_fpfh_ransac_icp"] = (*error_of(M, M_true, c), time.perf_counter() - t0, extent, False, False, "fpfh",
                                     0.0)
    return out


def stage_used_network(method: str, stage: str) -> bool:
    """Whether the network ran for this method (its inference was shared with an earlier method)."""
    return method == "deepmerge+icp" or (method == "auto" and stage == "deepmerge")


def summarise(results: list[dict[str, tuple]], prefix: str) -> dict[str, float]:
    """Medians, success and failure counts per method, and how often each stage won for ``auto``."""
    out: dict[str, float] = {f"{prefix}.pairs": len(results)}
    for m in METHODS:
        r = np.array([res[m][:6] for res in results], dtype=float)
        ok = (r[:, 0] < 1.0) & (r[:, 1] < 0.01 * r[:, 3])
        out[f"{prefix}.{m}.rot_err_deg_median"] = float(np.median(r[:, 0]))
        out[f"{prefix}.{m}.trans_err_mm_median"] = float(np.median(r[:, 1]))
        out[f"{prefix}.{m}.success_rate"] = float(np.mean(ok))
        out[f"{prefix}.{m}.seconds_median"] = float(np.median(r[:, 2]))
        if m in VERIFIED:
            out[f"{prefix}.{m}.failed"] = int(r[:, 4].sum())
            out[f"{prefix}.{m}.zero_inliers_exit0"] = int(r[:, 5].sum())
    for stage, n in sorted(Counter(res["auto"][6] for res in results).items()):
        out[f"{prefix}.auto.stage_wins.{stage}"] = n
    gates = [res["auto"][7] for res in results if np.isfinite(res["auto"][7])]
    if gates:
        out[f"{prefix}.auto.gate_mm_median"] = float(np.median(gates))
    out[f"{prefix}.rot_err_deg_median_before"] = float(np.median([res["before"][0] for res in results]))
    out[f"{prefix}.trans_err_mm_median_before"] = float(np.median([res["before"][1] for res in results]))
    return out


def scored(source, target, M_true, delta, cfg, network, refine_sigmas=REFINE_SIGMAS) -> dict[str, tuple]:
    """:func:`run_pair` plus the initial error (``before``)."""
    res = run_pair(source, target, M_true, delta, cfg, network, refine_sigmas)
    res["before"] = error_of(np.eye(4), M_true, source.mean(axis=0))
    return res


def real_sets(scans, sets, args, cfg, network, rng) -> dict[str, float]:
    out: dict[str, float] = {}
    tracker, arbitrary = [], []
    for src, tgt in crop_pairs(scans, args.pairs_per_scan, rng):
        c = src.mean(axis=0)
        for rows, deg, mm, delta in ((tracker, (0.25, 0.75), (1.0, 3.0), 5.0),
                                     (arbitrary, (5.0, 45.0), (2.0, 10.0), 1e4)):
            D = perturbation(rng, deg, mm, c)
            if rows is tracker and "real" in sets or rows is arbitrary and "real_arbitrary" in sets:
                rows.append(scored(transform_points(D, src), tgt, invert(D), delta, cfg, network))
    if tracker:
        out |= summarise(tracker, "real")
    if arbitrary:
        out |= summarise(arbitrary, "real_arbitrary")
    if "real_conf" in sets:
        conf = []
        for a, bs in NEIGHBOURS.items():
            for b in bs:
                (Pa, Ta), (Pb, Tb) = scans[a], scans[b]
                src, tgt = transform_points(Tb, Pb), transform_points(Ta, Pa)
                D = perturbation(rng, (0.25, 0.75), (1.0, 3.0), src.mean(axis=0))
                conf.append(scored(transform_points(D, src), tgt, invert(D), 5.0, cfg, network))
        out |= summarise(conf, "real_conf")
    return out


def sim_pairs(min_overlap: int = 200, delta_mm: float = 3.0):
    """(source, target, true correction) of every overlapping pair of the default simulated job (world, mm).

    The job runs with the correction off; scans are thinned to the job's voxel as the correction does.
    """
    from tandemscan.config import load_config
    from tandemscan.daemon.cell.session import CellSession
    from tandemscan.daemon.jobs.runner import JobRunner
    from tandemscan.daemon.plans import default_plan_path
    from tandemscan.pipeline.io.raw_scan import read_raw_scan
    from tandemscan.pipeline.planning.plan import Plan
    from tandemscan.pipeline.registration.sampling import voxel_downsample
    from tandemscan.sim_drivers.cell import with_surveyed_mounts

    config = load_config(None)
    config = config.model_copy(update={
        "scanner": config.scanner.model_copy(update={"resolution": "coarse"}),
        "correction": config.correction.model_copy(update={"enabled": False})})

    async def job():
        async with CellSession(config) as session:
            with tempfile.TemporaryDirectory() as tmp:
                surveyed = with_surveyed_mounts(config, session.cell.simulation, Path(tmp))
                runner = JobRunner(session, Plan.load(default_plan_path()), surveyed, Path(tmp) / "job")
                res = await runner.run()
                clouds = [voxel_downsample(read_raw_scan(s.file)[0], config.job.voxel_mm) for s in res.scans]
        return res.scans, clouds, runner.observer.scorer().T_W_S_true

    scans, clouds, true_T_W_S = asyncio.run(job())
    world = [transform_points(s.T_W_S, P) for s, P in zip(scans, clouds, strict=True)]
    pairs = []
    for i in range(len(scans)):
        for j in range(i + 1, len(scans)):
            if extract_overlap(world[j], world[i], delta_mm).size < min_overlap:
                continue
            Ti, Tj = scans[i].T_W_S, scans[j].T_W_S
            M_true = Ti @ invert(true_T_W_S[i]) @ true_T_W_S[j] @ invert(Tj)
            pairs.append((world[j], world[i], M_true))
    return pairs, delta_mm


def timing(scans, registrar, rng) -> dict[str, float]:
    """DeepMerge on a pair of 2,048-point overlaps cut from a real scan, one thread, median of 5."""
    src, tgt = crop_pairs({"bun000": scans["bun000"]}, 1, rng)[0]
    ov = extract_overlap(src, tgt, 5.0)
    S = src[ov.source_idx][rng.choice(ov.source_idx.size, 2048, replace=False)]
    T = tgt[ov.target_idx][rng.choice(ov.target_idx.size, 2048, replace=False)]
    times, cpu = [], []
    for _ in range(5):
        t0, c0 = time.perf_counter(), time.thread_time()
        registrar.register(S, T)
        times.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    return {"inference_2048.seconds_median": float(np.median(times)),
            "inference_2048.thread_cpu_seconds_median": float(np.median(cpu)),
            "inference_2048.network_points": int(min(registrar.num_points, 2048)),
            "inference_2048.iterations": registrar.iterations,
            "inference_2048.coarse_iterations": registrar.coarse_iterations,
            "inference_2048.coarse_points": registrar.coarse_points,
            "inference_2048.rounds_at_most": registrar.rounds}


def register_cli(scans, repeats: int = 3) -> dict[str, float]:
    """Wall clock (s, median of ``repeats``) of ``tandemscan register`` on two neighbouring bunny scans cut to
    30,000 points each (Stanford's poses as the start), per method, with the exit status of the last call."""
    rng = np.random.default_rng(1)
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for name in ("bun045", "bun000"):
            P, T = scans[name]
            P = transform_points(T, P[rng.choice(len(P), 30_000, replace=False)])
            paths.append(str(Path(tmp) / f"{name}.ply"))
            o3d.io.write_point_cloud(paths[-1], o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P)))
        for method in ("icp", "auto"):
            times, cpu, rc = [], [], None
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
                rc = subprocess.run([sys.executable, "-m", "tandemscan.daemon.cli", "register", *paths, "--method",
                                     method], capture_output=True, check=False).returncode
                c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                times.append(time.perf_counter() - t0)
                cpu.append(c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime)
            out[f"register_cli.{method}.seconds_median"] = float(np.median(times))
            out[f"register_cli.{method}.cpu_seconds_median"] = float(np.median(cpu))
            out[f"register_cli.{method}.exit_status"] = rc
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs-per-scan", type=int, default=3)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--data", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=DeepMergeConfig().rounds, help="DeepMerge re-embedding rounds")
    ap.add_argument("--points", type=int, default=None, help="network points per cloud (default: the weights' own)")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated subset of {', '.join(SETS)}")
    args = ap.parse_args()
    sets = set(args.sets.split(","))
    if not sets <= set(SETS):
        raise SystemExit(f"unknown sets {sorted(sets - set(SETS))}")
    torch.set_num_threads(1)
    o3d.utility.set_max_threads(1)
    rng = np.random.default_rng(args.seed)
    cfg = CorrectionConfig(icp_max_distance_mm=1.5)
    registrar = DeepMergeRegistrar.load(args.weights, num_points=args.points, rounds=args.rounds)
    network = MemoNetwork(registrar)
    out: dict[str, float] = {"threads": 1, "rounds": registrar.rounds}
    if sets & {"real", "real_arbitrary", "real_conf", "timing"}:
        scans = load_scans(find_data(args.data))
        out |= real_sets(scans, sets, args, cfg, network, rng)
        if "timing" in sets:
            out |= timing(scans, registrar, rng) | register_cli(scans)
    if "sim" in sets:
        pairs, delta = sim_pairs()
        out |= summarise([scored(s, t, M, delta, CorrectionConfig(), network, None) for s, t, M in pairs], "sim")
    out["load_average_1min"] = os.getloadavg()[0]
    publish("registration" + ("" if args.sets == ",".join(SETS) else "-" + args.sets.replace(",", "-")), out)


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

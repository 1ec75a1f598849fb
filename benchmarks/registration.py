"""Registration of overlapping scan pairs: DeepMerge vs point-to-plane ICP; prints one JSON object (last line).

Sets:
- ``real``: two overlapping crops (30-70 % overlap) of one real Stanford bunny scan (../shared/data, never
  copied into the repository), split into disjoint random halves so no point is shared, the source moved by
  a known tracker-like error (0.25-0.75 deg about a random axis, 1-3 mm): exact ground truth.
- ``real_arbitrary``: the same pairs with 5-45 deg and 2-10 mm (the paper's Fig. 24), whole crops.
- ``real_conf``: neighbouring bunny scans with Stanford's poses as reference (good to 0.1-0.6 deg and
  0.1-1.3 mm only), tracker-like error added; read it as a success rate.
- ``sim``: the default job on the simulated cell (coarse resolution, correction off), every overlapping
  scan pair as the tracker and its coordinate transfers stitched it, scored against the simulator's truth.
Methods, all from the same initial guess on the same overlap: ``icp`` (point-to-plane, coarse at the
overlap threshold then fine), ``deepmerge`` (the network's own answer), ``deepmerge_guarded`` (the
pipeline's: the network's answer kept only when it fits the overlap better than the initial guess),
``deepmerge+icp`` (the pipeline's: guarded DeepMerge then fine ICP). Keys ``<set>.<method>.rot_err_deg_median``,
``.trans_err_mm_median`` (at the source overlap's centroid), ``.success_rate`` (below 1 deg and 1 % of the
pair's extent), ``.seconds_median`` (wall clock per pair, one thread); ``<set>.<method>.success_rate_where_icp_fails``
on ``real_arbitrary``. ``inference_2048``: DeepMerge on a pair of 2,048-point overlaps, one thread (wall
clock and the thread's CPU time, which a loaded machine inflates less). The ``icp`` baseline's coarse stage
uses the overlap threshold as correspondence distance (5 mm; 10 m for ``real_arbitrary``, i.e. every point;
3 mm for ``sim``).

Usage: python benchmarks/registration.py [--pairs-per-scan 3] [--weights FILE] [--data DIR] [--sets real,sim,...]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from scipy.spatial.transform import Rotation
from tandemscan.config.models import CorrectionConfig
from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar
from tandemscan.pipeline.frames import from_quaternion, invert, make_transform, transform_points
from tandemscan.pipeline.registration.icp import icp_point_to_plane, target_with_normals
from tandemscan.pipeline.registration.overlap import extract_overlap
from tandemscan.pipeline.registration.pairs import keep_if_better, register_overlap

METHODS = ("icp", "deepmerge", "deepmerge_guarded", "deepmerge+icp")
SETS = ("real", "real_arbitrary", "real_conf", "sim")
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


def run_pair(source, target, M_true, delta, cfg, registrar) -> dict[str, tuple]:
    """Register the moved source onto the target by each method: (rot deg, trans mm, seconds, extent).

    The network runs once; the guarded and the fine-ICP results build on its answer and their times
    include its time.
    """
    ov = extract_overlap(source, target, delta)
    S, T = source[ov.source_idx], target[ov.target_idx]
    extent = float(np.linalg.norm(np.ptp(np.r_[S, T], axis=0)))
    tgt = target_with_normals(T)
    c = S.mean(axis=0)
    t0 = time.perf_counter()
    M_icp = register_overlap(S, tgt, "icp", cfg, None, delta)
    t1 = time.perf_counter()
    M_net = registrar.register(S, T)
    t2 = time.perf_counter()
    M_guard = keep_if_better(S, tgt, M_net, delta)
    t3 = time.perf_counter()
    M_fine = icp_point_to_plane(S, tgt, M_guard, cfg.icp_max_distance_mm, cfg.icp_iterations).transformation
    t4 = time.perf_counter()
    results = {"icp": (M_icp, t1 - t0), "deepmerge": (M_net, t2 - t1), "deepmerge_guarded": (M_guard, t3 - t1),
               "deepmerge+icp": (M_fine, t4 - t1)}
    return {m: (*error_of(M, M_true, c), sec, extent) for m, (M, sec) in results.items()}


def summarise(results: list[dict[str, tuple]], prefix: str) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Medians and success rates per method, and the per-pair success of each method."""
    out: dict[str, float] = {f"{prefix}.pairs": len(results)}
    ok = {}
    for m in METHODS:
        r = np.array([res[m] for res in results])
        ok[m] = (r[:, 0] < 1.0) & (r[:, 1] < 0.01 * r[:, 3])
        out[f"{prefix}.{m}.rot_err_deg_median"] = float(np.median(r[:, 0]))
        out[f"{prefix}.{m}.trans_err_mm_median"] = float(np.median(r[:, 1]))
        out[f"{prefix}.{m}.success_rate"] = float(np.mean(ok[m]))
        out[f"{prefix}.{m}.seconds_median"] = float(np.median(r[:, 2]))
    out[f"{prefix}.rot_err_deg_median_before"] = float(np.median([res["before"][0] for res in results]))
    out[f"{prefix}.trans_err_mm_median_before"] = float(np.median([res["before"][1] for res in results]))
    return out, ok


def where_icp_fails(ok: dict[str, np.ndarray], prefix: str) -> dict[str, float]:
    """Success rates of the DeepMerge methods on the pairs where ICP alone fails."""
    fails = ~ok["icp"]
    out: dict[str, float] = {f"{prefix}.icp_failures": int(fails.sum())}
    for m in METHODS[1:]:
        out[f"{prefix}.{m}.success_rate_where_icp_fails"] = float(np.mean(ok[m][fails])) if fails.any() else 1.0
    return out


def scored(source, target, M_true, delta, cfg, registrar) -> dict[str, tuple]:
    """:func:`run_pair` plus the initial error (``before``)."""
    res = run_pair(source, target, M_true, delta, cfg, registrar)
    res["before"] = error_of(np.eye(4), M_true, source.mean(axis=0))
    return res


def real_sets(scans, sets, args, cfg, registrar, rng) -> dict[str, float]:
    out: dict[str, float] = {}
    tracker, arbitrary = [], []
    for src, tgt in crop_pairs(scans, args.pairs_per_scan, rng):
        c = src.mean(axis=0)
        for rows, deg, mm, delta in ((tracker, (0.25, 0.75), (1.0, 3.0), 5.0),
                                     (arbitrary, (5.0, 45.0), (2.0, 10.0), 1e4)):
            D = perturbation(rng, deg, mm, c)
            if rows is tracker and "real" in sets or rows is arbitrary and "real_arbitrary" in sets:
                rows.append(scored(transform_points(D, src), tgt, invert(D), delta, cfg, registrar))
    if tracker:
        out |= summarise(tracker, "real")[0]
    if arbitrary:
        summary, ok = summarise(arbitrary, "real_arbitrary")
        out |= summary | where_icp_fails(ok, "real_arbitrary")
    if "real_conf" in sets:
        conf = []
        for a, bs in NEIGHBOURS.items():
            for b in bs:
                (Pa, Ta), (Pb, Tb) = scans[a], scans[b]
                src, tgt = transform_points(Tb, Pb), transform_points(Ta, Pa)
                D = perturbation(rng, (0.25, 0.75), (1.0, 3.0), src.mean(axis=0))
                conf.append(scored(transform_points(D, src), tgt, invert(D), 5.0, cfg, registrar))
        out |= summarise(conf, "real_conf")[0]
    return out


def sim_pairs(min_overlap: int = 200, delta_mm: float = 3.0):
    """(source, target, true correction) of every overlapping pair of the default simulated job (world, mm).

    The job runs with the correction off; scans are thinned to the job's voxel as the correction does.
    """
    from tandemscan.config import load_config
    from tandemscan.daemon.cli import default_plan_path
    from tandemscan.daemon.runner import JobRunner
    from tandemscan.daemon.session import CellSession
    from tandemscan.pipeline.raw_scan import read_raw_scan
    from tandemscan.pipeline.plan import Plan
    from tandemscan.pipeline.registration.sampling import voxel_downsample

    config = load_config(None)
    config = config.model_copy(update={
        "scanner": config.scanner.model_copy(update={"resolution": "coarse"}),
        "correction": config.correction.model_copy(update={"enabled": False})})

    async def job():
        async with CellSession(config) as session:
            with tempfile.TemporaryDirectory() as tmp:
                runner = JobRunner(session, Plan.load(default_plan_path()), config, Path(tmp) / "job")
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
            "inference_2048.coarse_points": registrar.coarse_points}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs-per-scan", type=int, default=3)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--data", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=None, help="head iterations (default: the weights' own)")
    ap.add_argument("--coarse-iterations", type=int, default=None, help="head iterations on a point subset first")
    ap.add_argument("--coarse-points", type=int, default=None, help="points of that subset")
    ap.add_argument("--points", type=int, default=None, help="network points per cloud (default: the weights' own)")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated subset of {', '.join(SETS)}")
    args = ap.parse_args()
    sets = set(args.sets.split(","))
    if not sets <= set(SETS):
        raise SystemExit(f"unknown sets {sorted(sets - set(SETS))}")
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    cfg = CorrectionConfig(icp_max_distance_mm=1.5)
    registrar = DeepMergeRegistrar.load(args.weights, num_points=args.points)
    if args.iterations:
        registrar.iterations = args.iterations
    if args.coarse_iterations is not None:
        registrar.coarse_iterations = args.coarse_iterations
    if args.coarse_points:
        registrar.coarse_points = args.coarse_points
    out: dict[str, float] = {"threads": 1, "iterations": registrar.iterations}
    if sets & {"real", "real_arbitrary", "real_conf"}:
        scans = load_scans(find_data(args.data))
        out |= real_sets(scans, sets, args, cfg, registrar, rng) | timing(scans, registrar, rng)
    if "sim" in sets:
        pairs, delta = sim_pairs()
        sim_cfg = CorrectionConfig()
        out |= summarise([scored(s, t, M, delta, sim_cfg, registrar) for s, t, M in pairs], "sim")[0]
    out["load_average_1min"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()

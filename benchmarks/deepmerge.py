"""DeepMerge vs point-to-plane ICP on the real Stanford bunny scans; prints one JSON object (last line).

Sets (all from ../shared/data/stanford-bunny, never copied into the repository):
- ``real``: two overlapping crops (30-70 % overlap) of one real scan, split into disjoint random halves so
  no point is shared, the source moved by a known tracker-like error (0.25-0.75 deg about a random axis,
  1-3 mm): exact ground truth.
- ``real_arbitrary``: the same pairs with 5-45 deg and 2-10 mm.
- ``real_conf``: neighbouring scans of the bunny with Stanford's poses as reference (good to 0.1-0.6 deg and
  0.1-1.3 mm only), tracker-like error added; read it as a success rate.
Methods: ``icp`` (point-to-plane, coarse at the overlap threshold then fine), ``deepmerge``,
``deepmerge+icp`` (fine ICP only), all from the same initial guess on the same overlap. Errors: rotation
angle (deg) and translation at the source's centroid (mm); success: below 1 deg and 1 % of the pair's
extent. ``inference_2048``: DeepMerge on a pair of 2,048-point overlaps, one thread (wall clock and the
thread's CPU time, which a loaded machine inflates less). ``deepmerge`` includes the pipeline's guard: the
network's answer is kept only when it fits the overlap better than the initial guess. The ``icp`` baseline's
coarse stage uses the overlap threshold as correspondence distance (5 mm; 10 m for ``real_arbitrary``,
i.e. every point, which handicaps it there).

Usage: python benchmarks/deepmerge.py [--pairs-per-scan 3] [--weights FILE] [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from scipy.spatial.transform import Rotation
from tandemscan.config.models import DeepMergeConfig
from tandemscan.pipeline.deepmerge.correct import register_overlap
from tandemscan.pipeline.deepmerge.overlap import extract_overlap
from tandemscan.pipeline.deepmerge.register import DeepMergeRegistrar
from tandemscan.pipeline.frames import from_quaternion, invert, make_transform, rotation_angle, transform_points

METHODS = ("icp", "deepmerge", "deepmerge+icp")
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
    """(rotation deg, translation mm at ``centre``) of an estimated vs true source->target transform."""
    rot = np.degrees(rotation_angle(M @ invert(M_true)))
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


def run_pair(source, target, M_true, delta, cfg, registrar, methods=METHODS) -> dict[str, tuple]:
    """Register the moved source onto the target by each method: (rot deg, trans mm, seconds, extent)."""
    ov = extract_overlap(source, target, delta)
    S, T = source[ov.source_idx], target[ov.target_idx]
    extent = float(np.linalg.norm(np.ptp(np.r_[S, T], axis=0)))
    out = {}
    for m in methods:
        t0 = time.perf_counter()
        M = register_overlap(S, T, m, cfg, registrar, delta)
        out[m] = (*error_of(M, M_true, S.mean(axis=0)), time.perf_counter() - t0, extent)
    return out


def summarise(results: list[dict[str, tuple]], prefix: str) -> dict[str, float]:
    out: dict[str, float] = {f"{prefix}.pairs": len(results)}
    for m in METHODS:
        r = np.array([res[m] for res in results])
        out[f"{prefix}.{m}.rot_err_deg_median"] = float(np.median(r[:, 0]))
        out[f"{prefix}.{m}.trans_err_mm_median"] = float(np.median(r[:, 1]))
        out[f"{prefix}.{m}.success_rate"] = float(np.mean((r[:, 0] < 1.0) & (r[:, 1] < 0.01 * r[:, 3])))
        out[f"{prefix}.{m}.seconds_median"] = float(np.median(r[:, 2]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs-per-scan", type=int, default=3)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--data", default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    scans = load_scans(find_data(args.data))
    cfg = DeepMergeConfig(icp_max_distance_mm=1.5)
    registrar = DeepMergeRegistrar.load(args.weights)
    out: dict[str, float] = {"threads": 1}
    tracker, arbitrary = [], []
    for src, tgt in crop_pairs(scans, args.pairs_per_scan, rng):
        c = src.mean(axis=0)
        for rows, deg, mm, delta in ((tracker, (0.25, 0.75), (1.0, 3.0), 5.0),
                                     (arbitrary, (5.0, 45.0), (2.0, 10.0), 1e4)):
            D = perturbation(rng, deg, mm, c)
            rows.append(run_pair(transform_points(D, src), tgt, invert(D), delta, cfg, registrar))
    out |= summarise(tracker, "real") | summarise(arbitrary, "real_arbitrary")
    conf = []
    for a, bs in NEIGHBOURS.items():
        for b in bs:
            (Pa, Ta), (Pb, Tb) = scans[a], scans[b]
            src, tgt = transform_points(Tb, Pb), transform_points(Ta, Pa)
            D = perturbation(rng, (0.25, 0.75), (1.0, 3.0), src.mean(axis=0))
            conf.append(run_pair(transform_points(D, src), tgt, invert(D), 5.0, cfg, registrar))
    out |= summarise(conf, "real_conf")
    # inference time on a pair of 2,048-point overlaps
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
    out["inference_2048.seconds_median"] = float(np.median(times))
    out["inference_2048.thread_cpu_seconds_median"] = float(np.median(cpu))
    out["inference_2048.network_points"] = int(min(registrar.num_points, 2048))
    out["load_average_1min"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()

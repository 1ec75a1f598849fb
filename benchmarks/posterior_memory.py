"""Peak memory and CPU seconds of a job's pose posterior and per-point U against the scan count (docs/verdict.md,
"Per-point uncertainty": the posterior is kept sparse, its blocks selected; before, ``C = H^-1 I H^-1`` was dense).

Usage: nice -n 10 python benchmarks/posterior_memory.py [--scans 369 708] [--points 400000]

A synthetic job of ``n`` scans on a grid over a long part (a cylinder of 400 mm radius, :data:`ROWS` scans around
it, 150 mm apart along it; four tracker stations along it, a coordinate transfer each after the first, the scanner
mount): each pair of neighbouring scans gives the 12x12 point-to-plane information of 200 points of its overlap
(their lever arms to the two scans' origins, 0.05 mm of noise), assembled through the joint refinement's error model
(``joint._Model``) into ``H`` (the normal matrix: data and priors) and ``I`` (the information its errors carry:
the same points weighted otherwise), as the joint refinement's end has them. Measured, each scan count in a
process of its own: the posterior as the joint refinement's end forms it (``PoseCovariance``; per pair its
unknowns' block, as the pairs' dispersion test reads it; the mount's block; each scan's block), then U of a cloud of
``--points`` points over the part (``JobUncertainty.evaluate``, best fit, the mount at its prior: the job's path).
Figures per scan count: CPU seconds of each, the traced peak (``tracemalloc``: numpy's and SciPy's arrays) and the
process's peak RSS over its RSS before (MiB). Run with a checkout from before the selected inversion (a
``PoseCovariance`` with a dense ``theta_covariance``), the same script forms ``C`` densely as that code did and
publishes as ``posterior_memory-dense``. Timings on a shared machine are unreliable: run it idle.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
import tracemalloc

import numpy as np
from results import publish
from scipy import sparse
from tandemscan.pipeline.geometry.frames import from_rotvec
from tandemscan.pipeline.inspection.point_uncertainty import JobUncertainty, ScanCover
from tandemscan.pipeline.registration.joint import _Model
from tandemscan.pipeline.registration.mount_unknown import MountPrior
from tandemscan.pipeline.registration.pose_covariance import PoseCovariance
from tandemscan.pipeline.registration.pose_graph import ScanPrior, TransferPrior

ROWS = 8                      # scans around the part
RADIUS_MM = 400.0             # 314 mm of arc between rows: a 400 mm window overlaps its neighbours by 86 mm
STEP_MM = 150.0               # along the part
HALF_WINDOW_MM = 200.0
STANDOFF_MM = 450.0
STATIONS = 4
NOISE_MM = 0.05
TRACKER = np.diag([0.03**2] * 3 + [np.radians(0.003) ** 2] * 3)
DENSE = "theta_covariance" in PoseCovariance.__dataclass_fields__   # the code before the selected inversion


def surface(x: np.ndarray, angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (mm) and outward unit normals of the part at ``x`` (mm) and ``angle`` (rad)."""
    n = np.c_[np.zeros_like(x), np.cos(angle), np.sin(angle)]
    return np.c_[x, RADIUS_MM * n[:, 1], RADIUS_MM * n[:, 2]], n


def job(n: int, rng: np.random.Generator) -> tuple[_Model, sparse.spmatrix, sparse.spmatrix, list, np.ndarray]:
    """The error model, ``H``, ``I``, the scans' neighbour pairs and each scan's (column, row) on the grid."""
    grid = np.array([(k // ROWS, k % ROWS) for k in range(n)])
    cols = grid[:, 0].max() + 1
    station = np.minimum(grid[:, 0] * STATIONS // cols, STATIONS - 1)
    centre, normal = surface(grid[:, 0] * STEP_MM, grid[:, 1] * 2 * np.pi / ROWS)
    origins = centre + STANDOFF_MM * normal
    priors = [ScanPrior(from_rotvec(o, [0.0, 0.0, 0.0]), TRACKER, int(s))
              for o, s in zip(origins, station, strict=True)]
    transfers = [TransferPrior(s, np.array([(s * cols / STATIONS) * STEP_MM, 0.0, 0.0]),
                               np.diag([0.02**2] * 3 + [1e-9] * 3)) for s in range(1, STATIONS)]
    model = _Model(priors, transfers, MountPrior(np.diag([0.05**2] * 3 + [np.radians(0.01) ** 2] * 3)))
    index = {tuple(g): k for k, g in enumerate(grid)}
    pairs = sorted({(min(i, j), max(i, j)) for i, (c, r) in enumerate(grid) for dc in (0, 1) for dr in (-1, 0, 1)
                    if (dc, dr) != (0, 0) and (j := index.get((c + dc, (r + dr) % ROWS))) is not None and j != i})
    rows, cols_, data, data2 = [], [], [], []
    for i, j in pairs:
        x = 0.5 * (centre[i, 0] + centre[j, 0]) + rng.uniform(-50, 50, 200)
        a = np.arctan2(centre[i, 2] + centre[j, 2], centre[i, 1] + centre[j, 1]) + rng.uniform(-0.1, 0.1, 200)
        p, nn = surface(x, a)
        nn = nn + rng.normal(0, 0.05, nn.shape)
        J = np.hstack([nn, np.cross(p - origins[j], nn), -nn, -np.cross(p - origins[i], nn)]) / NOISE_MM
        w = rng.uniform(0.8, 1.2, len(p)) * 20.0           # 200 points standing for the overlap's thousands
        idx = np.r_[6 * j:6 * j + 6, 6 * i:6 * i + 6]
        r, c = np.meshgrid(idx, idx, indexing="ij")
        rows.append(r.ravel())
        cols_.append(c.ravel())
        data.append((J.T @ (w[:, None] * J)).ravel())
        data2.append((J.T @ (w[:, None] ** 2 / 20.0 * J)).ravel())
    shape = (6 * n, 6 * n)
    H_e = sparse.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols_))), shape=shape)
    N_e = sparse.csr_matrix((np.concatenate(data2), (np.concatenate(rows), np.concatenate(cols_))), shape=shape)
    H = (model.A.T @ H_e @ model.A + model.prior_information).tocsc()
    info = model.prior_information + model.A.T @ N_e @ model.A
    return model, H, info, pairs, grid


def cloud(grid: np.ndarray, points: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, ScanCover]:
    """``points`` points (and normals) over the scanned part and each scan's thinned copy of its window."""
    length = grid[:, 0].max() * STEP_MM
    p, n = surface(rng.uniform(0, length, points), rng.uniform(0, 2 * np.pi, points))
    copies = []
    for c, r in grid:
        x = c * STEP_MM + rng.uniform(-HALF_WINDOW_MM, HALF_WINDOW_MM, 400)
        a = r * 2 * np.pi / ROWS + rng.uniform(-HALF_WINDOW_MM, HALF_WINDOW_MM, 400) / RADIUS_MM
        copies.append(surface(x, a)[0])
    centre, normal = surface(grid[:, 0] * STEP_MM, grid[:, 1] * 2 * np.pi / ROWS)
    return p, n, ScanCover(copies, np.full(len(grid), 50_000.0), centre + STANDOFF_MM * normal, np.arange(len(grid)))


def posterior(model: _Model, H: sparse.spmatrix, info: sparse.spmatrix, pairs: list) -> PoseCovariance:
    """The posterior as the joint refinement's end forms and reads it: each pair's unknowns' block, the mount's,
    each scan's (module doc)."""
    columns = model.scan_columns
    if DENSE:
        H_inv = np.linalg.inv(H.toarray())
        C = H_inv @ info.toarray() @ H_inv
        pc = model.pose_covariance(C, "joint refinement posterior")

        def block(cols: np.ndarray) -> np.ndarray:
            return C[np.ix_(cols, cols)]
        model.scan_covariances(C)
    else:
        pc = model.pose_covariance(H, info, "joint refinement posterior")
        block = pc.theta_covariance
    for i, j in pairs:
        block(np.union1d(columns[i][0], columns[j][0]))
    block(np.arange(model.size - 6, model.size))
    if not DENSE:
        pc.scan_covariances()
    return pc


def one(n: int, points: int, seed: int) -> dict:
    """The figures of ``n`` scans (module doc), measured in this process."""
    rng = np.random.default_rng(seed)
    model, H, info, pairs, grid = job(n, rng)
    p, nn, cover = cloud(grid, points, rng)
    with open("/proc/self/statm") as f:
        rss0 = int(f.read().split()[1]) * resource.getpagesize()
    tracemalloc.start()
    cpu = time.process_time()
    pc = posterior(model, H, info, pairs)
    cpu_posterior = time.process_time() - cpu
    _, peak_posterior = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    cpu = time.process_time()
    u = JobUncertainty(pc.with_installation_at_prior(), cover, NOISE_MM).evaluate(p, nn, 2.0, np.eye(4), "best-fit",
                                                                                  None, None)
    cpu_u = time.process_time() - cpu
    _, peak_u = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"scans": n, "unknowns": model.size, "pairs": len(pairs), "points": points,
            "cpu_s_posterior": round(cpu_posterior, 2), "cpu_s_u": round(cpu_u, 2),
            "traced_peak_mib_posterior": round(peak_posterior / 2**20, 1),
            "traced_peak_mib_u": round(peak_u / 2**20, 1),
            "rss_growth_mib": round((peak_rss - rss0) / 2**20, 1),
            "u_median_mm": round(float(np.median(u.expanded_mm)), 6),
            "budget_mm": {k: round(v, 6) for k, v in u.budget_mm.items()}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, nargs="+", default=[369, 708])
    ap.add_argument("--points", type=int, default=400_000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)    # a scan count measured in this process
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.points, args.seed)), flush=True)
        return
    runs = []
    for n in args.scans:
        out = subprocess.run([sys.executable, __file__, "--one", str(n), "--points", str(args.points),
                              "--seed", str(args.seed)], capture_output=True, text=True, check=True).stdout
        runs.append(json.loads(out.strip().splitlines()[-1]))
        print(json.dumps(runs[-1]), flush=True)
    publish("posterior_memory" + ("-dense" if DENSE else ""), {"route": "dense" if DENSE else "selected",
                                                               "runs": runs})


if __name__ == "__main__":
    main()

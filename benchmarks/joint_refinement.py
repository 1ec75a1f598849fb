"""CPU seconds, wall seconds and traced peak memory of the joint refinement (``joint.refine_jointly``, the correction
stage's joint part after the last scan, docs/end-of-job.md) on a synthetic strip of scans, at one or more scan
counts: the job's settings (``[correction]`` defaults: two linearisations, the second's correspondences found anew
where a pair moved), noisy scans of a curved strip thinned like the job's (2 mm grid), two tracker stations with a
coordinate transfer between them, and the scanner mount estimated.

Scan ``k`` sees a 300 x 200 mm window of the strip starting at ``k x 100`` mm (pairs with its two neighbours on
either side), 0.05 mm of noise along the scanner's z; the tracker poses are the truth moved by 0.1 mm and 0.01 deg
(1 sigma). Prints, per scan count, the seconds, the traced peak (MiB, ``tracemalloc``: numpy's and SciPy's arrays,
not the interpreter's own), the correspondences, the pose error against the truth (median mm) and whether the
posterior's objects stay sparse-sized (``pose_covariance.A`` sparse, its stored bytes; the posterior's normal and
information matrices, sparse, their stored bytes). With ``--against REV`` the same
problems also run on ``pipeline/registration/joint.py`` as it was at git revision ``REV`` (the rest of the package as
it is now), after this code, and the figures add its seconds and the largest difference of the two codes' poses (mm,
and of their rotation matrices' entries). Timings on a shared machine are unreliable: run it idle.

Usage: nice -n 10 python benchmarks/joint_refinement.py [--scans 60 120] [--threads 2] [--against f4b0c1c]
"""

from __future__ import annotations

import argparse
import functools
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from types import ModuleType

import numpy as np
from results import publish
from tandemscan.config.models import CorrectionConfig
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, pose_error, transform_points
from tandemscan.pipeline.registration import parallel
from tandemscan.pipeline.registration.joint import JointScan, JointSettings, refine_jointly
from tandemscan.pipeline.registration.mount_unknown import MountPrior
from tandemscan.pipeline.registration.pose_graph import ScanPrior, TransferPrior

GRID_MM = 2.0
WINDOW_MM = (300.0, 200.0)
STEP_MM = 100.0
NOISE_MM = 0.05
TRACKER = np.diag([0.1**2] * 3 + [np.radians(0.01) ** 2] * 3)


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A strip curved enough that each 300 mm window fixes all six degrees of freedom (mm)."""
    return 10 * np.sin(x / 17.0) * np.cos(y / 13.0) + 6 * np.cos(x / 23.0 + y / 19.0)


def strip_problem(n: int, seed: int) -> dict:
    """``refine_jointly``'s arguments for ``n`` scans of the strip (module doc) and the true poses (``truth``)."""
    rng = np.random.default_rng(seed)
    length = (n - 1) * STEP_MM + WINDOW_MM[0]
    x, y = np.meshgrid(np.arange(0.0, length + GRID_MM / 2, GRID_MM),
                       np.arange(-WINDOW_MM[1] / 2, WINDOW_MM[1] / 2 + GRID_MM / 2, GRID_MM))
    world = np.c_[x.ravel(), y.ravel(), surface(x.ravel(), y.ravel())]
    station = np.minimum(np.arange(n) * 2 // n, 1)
    truth, scans, priors, start = [], [], [], []
    for k in range(n):
        lo = k * STEP_MM
        inside = (world[:, 0] >= lo) & (world[:, 0] <= lo + WINDOW_MM[0])
        T = from_rotvec([lo + WINDOW_MM[0] / 2, 0.0, 400.0], [np.pi, 0.0, 0.0])
        P = transform_points(invert(T), world[inside])
        P[:, 2] += rng.normal(0.0, NOISE_MM, len(P))
        tracker = from_rotvec(rng.normal(0, 0.1, 3), rng.normal(0, np.radians(0.01), 3)) @ T
        truth.append(T)
        scans.append(JointScan.from_points(P))
        priors.append(ScanPrior(tracker, TRACKER, int(station[k])))
        start.append(tracker)
    pairs = [(i, j) for i in range(n) for j in (i + 1, i + 2) if j < n]
    transfers = [TransferPrior(1, np.array([length / 2, 0.0, 400.0]), np.diag([0.05**2] * 3 + [1e-8] * 3))]
    settings = JointSettings.from_section(CorrectionConfig())
    return {"scans": scans, "priors": priors, "pairs": pairs, "start_poses": start, "transfers": transfers,
            "mount_prior": MountPrior(np.diag([0.01**2] * 3 + [np.radians(0.001) ** 2] * 3)), "settings": settings,
            "truth": truth}


def joint_at(revision: str) -> ModuleType:
    """``pipeline/registration/joint.py`` as it was at git ``revision``, loaded as a module of its own."""
    root = Path(__file__).resolve().parent.parent
    source = subprocess.run(["git", "-C", str(root), "show", f"{revision}:pipeline/registration/joint.py"],
                            capture_output=True, text=True, check=True).stdout
    path = Path(tempfile.mkdtemp()) / f"joint_{revision}.py"
    path.write_text(source, encoding="utf-8")
    module = ModuleType(f"joint_{revision}")
    module.__file__ = str(path)
    sys.modules[module.__name__] = module          # its dataclasses look their module up
    exec(compile(source, str(path), "exec"), module.__dict__)  # noqa: S102 - the repository's own file
    return module


def timed(refine, problem: dict):
    """``refine(**problem)`` with its CPU and wall seconds and the traced peak (bytes)."""
    tracemalloc.start()
    cpu, wall = time.process_time(), time.perf_counter()
    result = refine(**problem)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return result, cpu, wall, peak


def measure(n: int, seed: int, against: ModuleType | None, threads: int) -> dict:
    """The figures of one scan count (module doc), the pairs' work on ``threads`` threads (0: one per core)."""
    problem = strip_problem(n, seed)
    truth = problem.pop("truth")
    result, cpu, wall, peak = timed(functools.partial(refine_jointly, backend=LocalBackend(threads or None)), problem)
    A = result.pose_covariance.A
    figures = {"scans": n, "pairs": result.pairs, "correspondences": result.correspondences,
               "cpu_s": round(cpu, 2), "wall_s": round(wall, 2), "traced_peak_mib": round(peak / 2**20, 1),
               "pose_error_mm_median": round(float(np.median([pose_error(P, T)[0] for P, T in
                                                             zip(result.poses, truth, strict=True)])), 5),
               "A_sparse": bool(hasattr(A, "nnz")),
               "A_stored_mib": round((A.data.nbytes + A.indices.nbytes + A.indptr.nbytes) / 2**20, 3),
               "posterior_stored_mib": round(sum(M.data.nbytes + M.indices.nbytes + M.indptr.nbytes for M in (
                   result.pose_covariance.normal, result.pose_covariance.information)) / 2**20, 1)}
    if against is not None:
        before, cpu, wall, peak = timed(against.refine_jointly, problem)
        P, Q = np.stack(result.poses), np.stack(before.poses)
        figures["before"] = {"cpu_s": round(cpu, 2), "wall_s": round(wall, 2),
                             "traced_peak_mib": round(peak / 2**20, 1),
                             "pose_difference_mm": float(np.abs(P[:, :3, 3] - Q[:, :3, 3]).max()),
                             "rotation_difference": float(np.abs(P[:, :3, :3] - Q[:, :3, :3]).max())}
    return figures


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, nargs="+", default=[60, 120])
    ap.add_argument("--threads", type=int, default=0, help="threads of the pair work (0: one per core)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--against", default="", help="a git revision whose joint.py runs the same problems too")
    args = ap.parse_args()
    against = joint_at(args.against) if args.against else None
    if args.threads and against is not None and hasattr(against, "pair_threads"):   # a joint.py before its backend
        threads = parallel.pair_threads
        against.pair_threads = lambda: threads(args.threads)
    publish("joint_refinement", {"threads": args.threads or "cores", "against": args.against or None,
                                 "runs": [measure(n, args.seed, against, args.threads) for n in args.scans]})


if __name__ == "__main__":
    main()

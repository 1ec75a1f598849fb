"""Start-up of ``tandemscan register``: wall clock of one call on two 30 k-point clouds, process start
included; prints one JSON object (last line).

The clouds are two independently sampled, partly overlapping 30,000-point crops of a synthetic doubly curved
patch (mm, 0.02 mm noise), the source moved by a known 0.5 deg / 2 mm offset; each method
(``--method icp``, ``--method auto``) runs ``--repeats`` times as a subprocess (``python -m
tandemscan.daemon.cli register``). Keys ``<method>.seconds_median`` (wall), ``.cpu_seconds_median`` (user +
system of the child), ``.exit_status`` (of the last call), ``.rot_err_deg`` and ``.trans_err_mm`` (of the
printed 4x4 against the known offset, at the source's centroid), and the imports the ``icp`` call made of
torch and open3d (``icp.imports_torch``, ``icp.imports_open3d``, from ``-X importtime``). Run it niced on a
loaded machine: the figures then include the wait for a core.

Usage: python benchmarks/register_startup.py [--repeats 5] [--points 30000]
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, pose_error, transform_points
from tandemscan.pipeline.io.export import write_ply

_BUMPS = np.random.default_rng(5).uniform([-110, -110, 10, -12], [110, 110, 35, 12], (30, 4))


def patch(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (mm) of the curved patch: a cylinder-like bend plus 30 bumps at fixed random places."""
    z = 0.002 * x**2 - 0.001 * y**2
    for cx, cy, r, h in _BUMPS:
        z += h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r**2))
    return z


def clouds(n: int, T_true: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(source moved by ``T_true^-1``, target): crops x in [-100, 40] and [-40, 100], y in [-100, 100]."""
    rng = np.random.default_rng(seed)
    out = []
    for lo, hi in ((-100.0, 40.0), (-40.0, 100.0)):
        xy = np.c_[rng.uniform(lo, hi, n), rng.uniform(-100, 100, n)]
        out.append(np.c_[xy, patch(xy[:, 0], xy[:, 1])] + rng.normal(0, 0.02, (n, 3)))
    return transform_points(invert(T_true), out[0]), out[1]


def call(paths: list[str], method: str, extra: tuple[str, ...] = ()
         ) -> tuple[float, float, subprocess.CompletedProcess]:
    """(wall s, child CPU s, the finished process) of one ``register`` call."""
    t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run([sys.executable, *extra, "-m", "tandemscan.daemon.cli", "register", *paths,
                           "--method", method], capture_output=True, text=True, check=False)
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (time.perf_counter() - t0, c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime, proc)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--points", type=int, default=30_000)
    args = ap.parse_args()
    T_true = from_rotvec([1.2, -1.0, 1.1], np.radians(0.5) * np.array([0.6, -0.48, 0.64]))
    source, target = clouds(args.points, T_true)
    out: dict[str, float | int | bool] = {"points": args.points}
    with tempfile.TemporaryDirectory() as tmp:
        paths = [str(write_ply(Path(tmp) / "source.ply", source)), str(write_ply(Path(tmp) / "target.ply", target))]
        for method in ("icp", "auto"):
            runs = [call(paths, method) for _ in range(args.repeats)]
            proc = runs[-1][2]
            out[f"{method}.seconds_median"] = float(np.median([r[0] for r in runs]))
            out[f"{method}.cpu_seconds_median"] = float(np.median([r[1] for r in runs]))
            out[f"{method}.exit_status"] = proc.returncode
            try:
                M = np.array([[float(v) for v in line.split()] for line in proc.stdout.splitlines()[:4]])
                dt, dr = pose_error(M, T_true)
                c = source.mean(axis=0)
                dt = float(np.linalg.norm(transform_points(M, c[None]) - transform_points(T_true, c[None])))
                out[f"{method}.rot_err_deg"], out[f"{method}.trans_err_mm"] = float(np.degrees(dr)), dt
            except ValueError:
                out[f"{method}.stdout"] = proc.stdout[-300:] + proc.stderr[-300:]
        _, _, proc = call(paths, "icp", ("-X", "importtime"))
        modules = {line.split("|")[-1].strip() for line in proc.stderr.splitlines() if line.startswith("import time")}
        out["icp.imports_torch"] = "torch" in modules
        out["icp.imports_open3d"] = "open3d" in modules
    publish("register_startup", out)


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

"""Size and write/read time of one full-resolution raw scan file (3.2 M points with normals), stored as the
job stores it (float32, ``np.savez``, fsynced) and compressed (``np.savez_compressed``) for comparison.

Usage: python benchmarks/raw_scan_io.py [--points 3200000] [--repeat 3] [--scan scans/scan-0007.npz]

The scan is the organised grid of ``benchmarks/worldmap_merge.py`` (a curved patch 400 mm in front of the
scanner) with scanner noise of 0.05 mm, or with ``--scan`` a job's raw scan file (a full-resolution one of the
simulated cell: ``benchmarks/whole_part.py --resolution full``); the figures are medians over ``--repeat``
writes into a temporary folder (wall and CPU seconds, MB; ``*_read_cold_s``: the file's pages dropped from the
page cache first). The last line of output is one JSON object.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.pipeline.io.durable import write_durably
from tandemscan.pipeline.io.raw_scan import read_raw_scan, write_raw_scan


def _scan(points: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    columns = 2064
    x, y = np.meshgrid(0.15 * np.arange(columns), 0.15 * (np.arange(points // columns) - points // columns / 2))
    z = 400 + 8 * np.sin(x / 40) * np.cos(y / 30) + rng.normal(0, 0.05, x.shape)
    P = np.c_[x.ravel(), y.ravel(), z.ravel()]
    n = np.c_[-0.2 * np.cos(x.ravel() / 40), 0.1 * np.sin(y.ravel() / 30), -np.ones(len(P))]
    return {"points_S_mm": P, "normals_S": n / np.linalg.norm(n, axis=1, keepdims=True),
            "T_C_T": np.eye(4), "tracker_covariance": np.eye(6), "T_W_C": np.eye(4)}


def _time(fn, repeat: int) -> tuple[float, float]:
    wall, cpu = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return round(float(np.median(wall)), 3), round(float(np.median(cpu)), 3)


def _read_cold(path: Path) -> None:
    """Read the scan after dropping this file's pages from the page cache (as the end of a full-resolution
    job reads most of its 369 scans: 28 GB of them do not stay cached in 24 GB)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)
    read_raw_scan(path, np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=3_200_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--scan", type=Path, help="a raw scan file to measure instead of the synthetic grid")
    args = parser.parse_args()
    if args.scan:
        with np.load(args.scan) as data:
            arrays = {k: data[k] for k in data.files}
    else:
        arrays = _scan(args.points)
    out: dict = {"scan": str(args.scan or "synthetic grid"), "points": len(arrays["points_S_mm"])}
    with tempfile.TemporaryDirectory() as tmp:
        plain, packed = Path(tmp) / "plain.npz", Path(tmp) / "packed.npz"
        out["float32_write_s"], out["float32_write_cpu_s"] = _time(lambda: write_raw_scan(plain, **arrays),
                                                                   args.repeat)
        out["float32_mb"] = round(os.path.getsize(plain) / 1e6, 1)
        out["float32_read_s"], _ = _time(lambda: read_raw_scan(plain, np.float32), args.repeat)
        out["float32_read_cold_s"], _ = _time(lambda: _read_cold(plain), args.repeat)
        f32 = {k: v.astype(np.float32) if k in ("points_S_mm", "normals_S") else v for k, v in arrays.items()}
        out["compressed_write_s"], out["compressed_write_cpu_s"] = _time(
            lambda: write_durably(packed, lambda f: np.savez_compressed(f, **f32)), args.repeat)
        out["compressed_mb"] = round(os.path.getsize(packed) / 1e6, 1)
        out["compressed_read_s"], out["compressed_read_cpu_s"] = _time(lambda: read_raw_scan(packed, np.float32),
                                                                       args.repeat)
        out["compressed_read_cold_s"], _ = _time(lambda: _read_cold(packed), args.repeat)
        out["float64_mb"] = round(sum(np.asarray(v, np.float64).nbytes for v in arrays.values()) / 1e6, 1)
    out["load_average_1min"] = round(os.getloadavg()[0], 2)
    publish("raw_scan_io" + ("-scan" if args.scan else ""), out)


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

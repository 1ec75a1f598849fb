"""Time merging one full-resolution scan (3.2 M points with normals) into a world map that already holds
740 k voxels (docs/daemon.md, "Keeping the event loop free"), on one core.

Usage: python benchmarks/worldmap_merge.py [--points 3200000] [--map-voxels 740000] [--repeat 5]

The scan is a synthetic organised grid (2,064 x 1,544 points at about 0.15 mm spacing, the PhoXi's full
resolution) on a curved patch, with its normals, in the scanner frame 400 mm in front of it; the map is
filled first with other patches of the same surface until it holds the requested voxel count (1 mm voxels),
so that the scan's voxels partly hit existing ones. Figures: the median wall-clock seconds of
``VoxelMap.add_scan`` (what a scan costs when it arrives: its voxels join the map's batch) over ``--repeat``
merges (each into a copy of the same map) and its CPU seconds (the figure to read on a loaded machine), also
for the scan given as float32 (as the job's map reads a raw scan file); the CPU seconds of merging that batch
into the sorted map (``batch_merge_into_map_cpu_s``: one sort of map and batch, which the map does once the
batch holds as many voxels as the map, i.e. once per doubling, or when it is read); the scan's voxel count,
and for comparison Open3D's one-shot ``voxel_down_sample`` of the same scan (1 mm), wall and CPU. The last
line of output is one JSON object.
"""

from __future__ import annotations

import argparse
import copy
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402
from results import publish
from tandemscan.pipeline.geometry.frames import from_rotvec, invert, transform_points  # noqa: E402
from tandemscan.pipeline.stitching.worldmap import VoxelMap  # noqa: E402


def patch(x0_mm: float, columns: int, rows: int, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """World points (mm) and unit normals of a grid on z = 8 sin(x/40) cos(y/30) starting at x0."""
    x, y = np.meshgrid(x0_mm + spacing_mm * np.arange(columns), spacing_mm * (np.arange(rows) - rows / 2))
    x, y = x.ravel(), y.ravel()
    z = 8 * np.sin(x / 40) * np.cos(y / 30)
    n = np.c_[-8 / 40 * np.cos(x / 40) * np.cos(y / 30), 8 / 30 * np.sin(x / 40) * np.sin(y / 30), np.ones_like(x)]
    return np.c_[x, y, z], n / np.linalg.norm(n, axis=1, keepdims=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=3_200_000)
    parser.add_argument("--map-voxels", type=int, default=740_000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    columns = 2064
    rows = args.points // columns
    scan_W, normals_W = patch(0.0, columns, rows, 0.15)
    T_W_S = from_rotvec([150.0, 0, 400.0], [np.pi, 0, 0])
    points_S = transform_points(invert(T_W_S), scan_W)
    normals_S = normals_W @ T_W_S[:3, :3]
    base = VoxelMap(1.0)
    x0 = 0.5 * columns * 0.15                      # half over the scan, then beside it
    while len(base) < args.map_voxels:
        P, N = patch(x0, 300, 240, 1.0)
        base.add(P, N)
        x0 += 150.0
    seconds, cpu, cpu32, flush_cpu = [], [], [], []
    points32, normals32 = points_S.astype(np.float32), normals_S.astype(np.float32)  # as a raw scan file holds them
    for _ in range(args.repeat):
        m = copy.deepcopy(base)
        t, c = time.perf_counter(), time.process_time()
        m.add_scan(T_W_S, points_S, normals_S)
        seconds.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        c = time.process_time()
        len(m)                                      # merges the batch into the sorted map (once per doubling)
        flush_cpu.append(time.process_time() - c)
        m32 = copy.deepcopy(base)
        c = time.process_time()
        m32.add_scan(T_W_S, points32, normals32)
        cpu32.append(time.process_time() - c)
    t, c = time.perf_counter(), time.process_time()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan_W))
    pcd.normals = o3d.utility.Vector3dVector(normals_W)
    o3d_voxels = len(pcd.voxel_down_sample(1.0).points)
    o3d_s, o3d_cpu = time.perf_counter() - t, time.process_time() - c
    publish("worldmap_merge", {"scan_points": len(points_S), "map_voxels_before": len(base), "map_voxels_after": len(m),
                      "scan_voxels": o3d_voxels, "merge_s_median": round(float(np.median(seconds)), 3),
                      "merge_s_min": round(min(seconds), 3),
                      "merge_cpu_s_median": round(float(np.median(cpu)), 3),
                      "merge_cpu_s_min": round(min(cpu), 3),
                      "merge_float32_cpu_s_median": round(float(np.median(cpu32)), 3),
                      "merge_float32_cpu_s_min": round(min(cpu32), 3),
                      "batch_merge_into_map_cpu_s_median": round(float(np.median(flush_cpu)), 3),
                      "open3d_voxel_down_sample_s": round(o3d_s, 3), "open3d_cpu_s": round(o3d_cpu, 3),
                      "load_average_1min": round(os.getloadavg()[0], 2)})


if __name__ == "__main__":
    main()

"""Capacity of the end of a job: seconds and peak memory of every stage against the scans and points, at two part
sizes and on 1 and 2 Dask workers, and from them the estimate for a 20 m railway car (docs/compute.md, "Capacity").

Each size is a job of the parametric train nose (``geometry.part.train_nose_mesh``: the 3 m nose, and the same
nose on a body ``--length-factor`` times as long), its scans ray cast by the simulated scanner
(``geometry.raycast.ScannerModel`` at ``--resolution``) from views spread evenly over the part's upper surface
(Poisson disk on the mesh, the sweet spot along each normal; ``--scans`` on the nose, in proportion to the area on
the longer part), each stored pose off the true one by the tracker's noise. The job is written as raw scan files
(``scans/``, the scan store), then the end of the job's stages run one after the other on a Dask ``LocalCluster`` of
1 and 2 single-threaded workers, this process holding no scan's points (as the daemon on the dask backend):
``correction`` (``correction.correct_scans`` given only the scans' references: each scan read and summarised on the
workers, ``correction.summarise_scan``, its pairs and the overlap RMS there, the joint refinement here; without the
correction ``summaries``: only the scans' bounds of x), ``merge`` (``tiles.merge_tiles`` on the workers),
``cloud_ply`` (streamed from the tiles, here), ``inspect`` (``tile_inspection.inspect_tiles`` on the workers),
``figures`` (the report's deviation figures from the tiles' summaries, here), ``deviation_ply`` (streamed, here) and
``e57`` (the full scans streamed, here). Each stage's
wall seconds and peak RSS (GiB; the peak is reset before each stage, Linux ``/proc/<pid>/clear_refs``): of the
process that runs the stages (``main_gib``, and ``main_start_gib`` what it held as the stage started; a fresh
process for each size and worker count) and of each worker (``worker_gib``, their largest). ``--density-views``
checks that a reduced ``--resolution`` stands for full resolution in the main process's memory
(:func:`density_check`).

The model, per stage: on one worker ``t1 = a + b x`` through the two sizes, ``x`` the stage's driver (raw points,
scans or merged voxels: :data:`DRIVERS`); on N workers Amdahl's law with the stage's serial share ``f = 2 t2 / t1 -
1`` (clipped to [0, 1]) measured at the larger size; the peak of a worker is the larger of the two sizes' (bounded by
the tile and the scan, not the part), that of this process ``a + b scans``. The car: :data:`CAR` (scans, raw
points), its merged voxels those of the larger size's per raw point. Prints one JSON object on its last line and
keeps it in ``benchmarks/results/capacity.json`` (``results.publish``).

The per-process peaks (``peaks``, first in the JSON): per worker count and size the largest peak over the stages of
the process running them and of a worker, with the stage, and issue 43's memory line on them (a worker at most
3 GiB and within 15 % of it on the longer part, the main process under 1.5 GiB); each size's also on stderr as it
ends. ``--band-share`` keeps the views of a band across each part's body (the same share of its length from its
tail, the end cap left out, so twice the scans on the longer part) where the whole parts do not fit the time at hand.

Usage: ``nice -n 10 .venv/bin/python benchmarks/capacity.py [--resolution coarse|full|COLSxROWS] [--scans 369]
[--length-factor 2] [--tile-mm 500] [--workers 1 2] [--folder DIR] [--no-e57] [--band-share 1] [--sizes nose
long]``. Full resolution writes about
28 GB of raw scans for the nose and 57 GB for the longer part (one size at a time, removed after it; the E57 adds
half as much again: ``--no-e57`` where the disk has less room) and runs for tens of minutes: an idle machine's job.
"""

from __future__ import annotations

import argparse
import functools
import json
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from results import publish
from tandemscan.config.models import CorrectionConfig, PartConfig, ScannerConfig
from tandemscan.pipeline.compute import DaskBackend
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import train_nose_mesh
from tandemscan.pipeline.geometry.raycast import ScannerModel, make_scene
from tandemscan.pipeline.inspection.tile_inspection import deviation_figures, inspect_tiles, write_deviation_ply
from tandemscan.pipeline.io.export import PosedScan, write_e57
from tandemscan.pipeline.io.raw_scan import read_raw_scan, thin_scan, write_raw_scan
from tandemscan.pipeline.registration.correction import (
    CorrectionSettings,
    StitchedJob,
    StitchedScan,
    correct_scans,
    summarise_stored_scan,
)
from tandemscan.pipeline.registration.pair_stage import ScanRef, StoredScans
from tandemscan.pipeline.registration.sampling import voxel_centroids
from tandemscan.pipeline.stitching.tiles import TileScan, merge_tiles, write_cloud_ply

VOXEL_MM = 1.0
#: the 20 m railway car on the larger cell at full resolution (issue 43): scans and raw points
CAR = {"scans": 3700, "raw_points": 12e9}
#: what each stage's time grows with
DRIVERS = {"summaries": "raw_points", "correction": "scans", "merge": "raw_points", "cloud_ply": "voxels",
           "inspect": "voxels", "figures": "voxels", "deviation_ply": "voxels", "e57": "raw_points"}
TRACKER_SIGMA = (0.03, 5e-5)  # mm, rad (1 sigma) of the stored poses' error
GIB = float(1 << 30)


def reset_peak() -> None:
    """Restart this process's peak RSS count (Linux: ``5`` to ``/proc/self/clear_refs`` resets ``VmHWM``)."""
    with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
        f.write("5")


def peak_gib() -> float:
    """This process's peak RSS since the last :func:`reset_peak`, GiB."""
    with open("/proc/self/status", encoding="ascii") as f:
        kib = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    return kib * 1024 / GIB


@dataclass(frozen=True)
class Job:
    """A simulated job in ``folder`` (the scan store): its scans' files, stored (tracker) poses, the CAD file."""

    folder: Path
    files: tuple[str, ...]
    poses: tuple[np.ndarray, ...]
    mesh_file: Path
    raw_points: int


def _pixels(resolution: str) -> tuple[int, int]:
    if resolution in ("coarse", "full"):
        return ScannerConfig(resolution=resolution).pixels
    cols, rows = resolution.lower().split("x")
    return int(cols), int(rows)


def make_job(folder: Path, part: PartConfig, scans: int, pixels: tuple[int, int], seed: int,
             band_share: float = 1.0) -> Job:
    """``scans`` views spread over the part's upper surface (Poisson disk; normals facing down left out), of them
    with ``band_share`` under 1 those on the body whose centre lies in the first ``band_share`` of the part's length
    from its tail (x from ``-length/2``; the tail's end cap left out, a wall across x whose views fill one tile: a
    band across the part, the same density of views, twice the scans on a part twice as long), each ray cast at the
    sweet spot along the normal and written as a raw scan (frame S, mm) with its pose off the true one by
    :data:`TRACKER_SIGMA`; W is the CAD frame F."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    mesh = train_nose_mesh(part)
    mesh.compute_triangle_normals()
    mesh_file = folder / "cad.ply"
    o3d.io.write_triangle_mesh(str(mesh_file), mesh)
    scanner = ScannerConfig(coarse_pixels=pixels, resolution="coarse")
    model, scene = ScannerModel(scanner), make_scene(mesh)
    files, poses, raw = [], [], 0
    for T_F_S in view_poses(mesh, part, scans, band_share, scanner.sweet_spot_mm):
        points, normals_S = model.scan(scene, T_F_S, rng)
        if len(points) < 1000:  # a view past the part's edge: a job keeps no such scan
            continue
        file = f"scans/scan-{len(files):04d}.npz"
        write_raw_scan(folder / file, points_S_mm=points, normals_S=normals_S)
        error = F.from_rotvec(rng.normal(0, TRACKER_SIGMA[0], 3), rng.normal(0, TRACKER_SIGMA[1], 3))
        files.append(file)
        poses.append(error @ T_F_S)
        raw += len(points)
    return Job(folder, tuple(files), tuple(poses), mesh_file, raw)


def view_poses(mesh, part: PartConfig, scans: int, band_share: float, sweet_spot_mm: float) -> list[np.ndarray]:
    """:func:`make_job`'s views ``T_F_S`` (mm): Poisson disk on the part's upper surface, the scanner at the sweet
    spot along each normal, looking at it."""
    up_share = _upper_share(mesh, np.asarray(mesh.triangle_normals))
    views = mesh.sample_points_poisson_disk(max(2, round(scans / up_share)), use_triangle_normal=True)
    centres, facing = np.asarray(views.points), np.asarray(views.normals)
    keep = facing[:, 2] > -0.3
    if band_share < 1.0:  # the body's views only: the tail's end cap (centres on x = -length/2) is one x slab
        tail = -0.5 * part.length_mm
        keep &= (centres[:, 0] > tail + 1.0) & (centres[:, 0] <= tail + band_share * part.length_mm)
    out = []
    for c, n in zip(centres[keep], facing[keep], strict=True):
        z = -n / np.linalg.norm(n)
        x = np.cross([0.0, 0.0, 1.0], z) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x -= (x @ z) * z
        x /= np.linalg.norm(x)
        out.append(F.make_transform(np.column_stack([x, np.cross(z, x), z]), c - sweet_spot_mm * z))
    return out


def density_check(part: PartConfig, pixels: tuple[int, int], views: int, seed: int) -> dict:
    """How well scans of ``pixels`` stand for full-resolution ones in the main process's memory, which holds no
    scan's points but, per scan, its copy thinned at the joint refinement's voxel (``correction.joint_scan``):
    on ``views`` views of ``part`` (evenly among :func:`view_poses`) ray cast at both resolutions, the points of the
    copies thinned at :data:`VOXEL_MM` (the merge's and the pairs') and at ``[correction] joint_voxel_mm``, summed,
    and their ratio to full resolution's."""
    mesh = train_nose_mesh(part)
    mesh.compute_triangle_normals()
    scene, rng = make_scene(mesh), np.random.default_rng(seed)
    joint_mm = CorrectionConfig().joint_voxel_mm
    poses = view_poses(mesh, part, 369, 1.0, ScannerConfig().sweet_spot_mm)
    sums = {}
    for label, px in (("full", ScannerConfig().full_pixels), ("run", pixels)):
        model = ScannerModel(ScannerConfig(coarse_pixels=px, resolution="coarse"))
        counts = np.zeros(3)
        for T in poses[:: max(1, len(poses) // views)][:views]:
            points, _ = model.scan(scene, T, rng)
            thinned = thin_scan(points, VOXEL_MM)
            counts += (len(points), len(thinned), len(voxel_centroids(np.asarray(thinned, float), joint_mm)[1]))
        sums[label] = counts
    return {"views": views, "pixels_full": list(ScannerConfig().full_pixels), "pixels_run": list(pixels),
            "points": {k: int(v[0]) for k, v in sums.items()},
            "thinned_1mm_ratio": round(sums["run"][1] / sums["full"][1], 4),
            "joint_ratio": round(sums["run"][2] / sums["full"][2], 4)}


def _upper_share(mesh, normals: np.ndarray) -> float:
    """The share of the mesh's area whose normal does not face down (where the views are kept)."""
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    return float(area[normals[:, 2] > -0.3].sum() / area.sum())


def _stage(name: str, backend: DaskBackend, record: dict, fn: Callable[[], object]) -> object:
    """``fn()`` timed, with this process's and each worker's peak RSS during it, into ``record[name]``."""
    reset_peak()
    backend.client.run(reset_peak)
    start = peak_gib()  # the peak just reset: what the process holds as the stage starts
    t = time.perf_counter()
    out = fn()
    wall = time.perf_counter() - t
    workers = sorted(backend.client.run(peak_gib).values())
    record[name] = {"wall_s": round(wall, 3), "main_gib": round(peak_gib(), 3), "main_start_gib": round(start, 3),
                    "worker_gib": round(max(workers), 3), "workers_gib": [round(w, 3) for w in workers]}
    print(f"{name}: {record[name]}", file=sys.stderr, flush=True)
    return out


def run_stages(job: Job, workers: int, tile_mm: float, e57: bool = True, correct: bool = True) -> tuple[dict, dict]:
    """Every stage of the end of the job on a ``LocalCluster`` of ``workers`` (the E57 where ``e57``; without
    ``correct`` no correction, the tiles merged at the stored poses): (per stage figures, drivers)."""
    store = str(job.folder)
    stages: dict = {}
    cov = np.diag([TRACKER_SIGMA[0] ** 2] * 3 + [TRACKER_SIGMA[1] ** 2] * 3)
    backend = DaskBackend("", workers)
    try:
        backend.client.wait_for_workers(workers, timeout=120)
        scans = [StitchedScan(None, T, cov, 0, f) for T, f in zip(job.poses, job.files, strict=True)]  # no points here
        settings = CorrectionSettings.from_section(CorrectionConfig())
        if correct:  # each scan read and summarised on the workers (correction.summarise_scan), its pairs there too
            result = _stage("correction", backend, stages, lambda: correct_scans(
                StitchedJob(scans, voxel_mm=VOXEL_MM), settings, backend=backend, scan_store=store))
            poses, reaches = result.poses, result.reaches
        else:  # only the scans' bounds of x, read on the workers
            refs = [ScanRef(k, f, T) for k, (f, T) in enumerate(zip(job.files, job.poses, strict=True))]
            fn = functools.partial(summarise_stored_scan, store=StoredScans(store, VOXEL_MM), cfg=settings,
                                   digest=False, joint=False)
            keys = [f"reach-{r.file}" for r in refs]
            read = _stage("summaries", backend, stages, lambda: backend.map(fn, refs, keys))
            poses, reaches, result = job.poses, [r.summary.reach for r in read], None
        refs = [TileScan(f, T, *reach.x_bound(T, VOXEL_MM, VOXEL_MM))
                for f, T, reach in zip(job.files, poses, reaches, strict=True)]
        tiles = _stage("merge", backend, stages, lambda: merge_tiles(refs, VOXEL_MM, tile_mm, store, backend))
        _stage("cloud_ply", backend, stages, lambda: write_cloud_ply(job.folder / "cloud.ply", store, tiles))
        inspected = _stage("inspect", backend, stages, lambda: inspect_tiles(
            tiles, store, job.mesh_file, np.eye(4), -0.5, 0.5, backend))
        _stage("figures", backend, stages, lambda: deviation_figures(store, inspected, -0.5, 0.5))
        _stage("deviation_ply", backend, stages,
               lambda: write_deviation_ply(job.folder / "cloud_deviation.ply", store, inspected))
        if e57:
            _stage("e57", backend, stages, lambda: write_e57(job.folder / "cloud.e57", (
                PosedScan(Path(f).stem, T, read_raw_scan(job.folder / f, np.float32)[0])
                for f, T in zip(job.files, poses, strict=True) if _has_points(job.folder / f))))
    finally:
        backend.close()
    shutil.rmtree(job.folder / "tiles", ignore_errors=True)
    for name in ("cloud.ply", "cloud_deviation.ply", "cloud.e57"):
        (job.folder / name).unlink(missing_ok=True)
    drivers = {"scans": len(job.files), "raw_points": job.raw_points, "voxels": sum(t.voxels for t in tiles),
               "tiles": len(tiles), "tile_voxels_max": max((t.voxels for t in tiles), default=0),
               "pairs": len(result.edges) if correct else None}
    return stages, drivers


def _has_points(path: Path) -> bool:
    with np.load(path) as data:
        return len(data["points_S_mm"]) > 0


def model(sizes: list[dict], workers: list[int], car_workers: tuple[int, ...]) -> dict:
    """Per stage the fitted ``a + b x`` on one worker, the serial share, the peaks, and the car's estimate on
    ``car_workers`` workers (module doc)."""
    small, large = sizes[0], sizes[-1]
    one, two = str(min(workers)), str(max(workers))
    per_point = large["drivers"]["voxels"] / large["drivers"]["raw_points"]
    car = {"scans": CAR["scans"], "raw_points": CAR["raw_points"], "voxels": CAR["raw_points"] * per_point}
    stages, seconds = {}, dict.fromkeys(car_workers, 0.0)
    for name, driver in DRIVERS.items():
        if name not in large["runs"][one]:  # a stage left out of the run
            continue
        x0, x1 = small["drivers"][driver], large["drivers"][driver]
        t0, t1 = small["runs"][one][name]["wall_s"], large["runs"][one][name]["wall_s"]
        b = max((t1 - t0) / (x1 - x0), 0.0) if x1 != x0 else t1 / x1  # no less time for more (noise)
        a = t1 - b * x1
        serial = (min(1.0, max(0.0, 2.0 * large["runs"][two][name]["wall_s"] / t1 - 1.0)) if t1 > 0 and one != two
                  else 1.0)
        car_t1 = max(a + b * car[driver], 0.0)
        worker = max(s["runs"][w][name]["worker_gib"] for s in sizes for w in (one, two))
        main = [s["runs"][one][name]["main_gib"] for s in sizes]
        scans = [s["drivers"]["scans"] for s in sizes]
        slope = (main[-1] - main[0]) / (scans[-1] - scans[0]) if scans[-1] != scans[0] else 0.0
        stages[name] = {"driver": driver, "a_s": round(a, 4), "b_s_per_unit": b, "serial_share": round(serial, 3),
                        "worker_peak_gib": worker, "main_peak_gib_car": round(main[-1] + slope * (car["scans"] -
                                                                                                  scans[-1]), 2)}
        for n in car_workers:
            seconds[n] += car_t1 * (serial + (1.0 - serial) / n)
    return {"car_inputs": car, "stages": stages,
            "car_minutes_on_n_workers": {str(n): round(s / 60.0, 1) for n, s in seconds.items()},
            "car_main_peak_gib": max(s["main_peak_gib_car"] for s in stages.values()),
            "car_worker_peak_gib": max(s["worker_peak_gib"] for s in stages.values())}


def peaks(sizes: list[dict]) -> dict:
    """Per worker count the peak RSS (GiB) over the stages of the process running them (``main_gib``) and of the
    largest worker (``worker_gib``) at each size, their stages, the larger size's worker peak over the smaller's
    (``worker_growth``) and issue 43's memory line on them: a worker at most 3 GiB and within 15 % of it on the
    larger part, the main process under 1.5 GiB."""
    out = {}
    for w in sizes[0]["runs"]:
        by_size = {}
        for size in sizes:
            stages = size["runs"][w]
            main, worker = (max(stages, key=lambda name, k=k: stages[name][k]) for k in ("main_gib", "worker_gib"))
            by_size[size["part"]] = {"scans": size["drivers"]["scans"], "raw_points": size["drivers"]["raw_points"],
                                     "main_gib": stages[main]["main_gib"], "main_stage": main,
                                     "worker_gib": stages[worker]["worker_gib"], "worker_stage": worker}
        out[w] = {**by_size, "worker_at_most_3_gib": max(s["worker_gib"] for s in by_size.values()) <= 3.0,
                  "main_under_1_5_gib": max(s["main_gib"] for s in by_size.values()) < 1.5}
        if len(sizes) > 1:
            growth = by_size[sizes[-1]["part"]]["worker_gib"] / by_size[sizes[0]["part"]]["worker_gib"]
            out[w] |= {"worker_growth": round(growth, 3), "worker_within_15_percent": growth <= 1.15}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--resolution", default="coarse", help="coarse, full or COLSxROWS of the scanner")
    ap.add_argument("--scans", type=int, default=369, help="scans of the nose (the larger part: by its area)")
    ap.add_argument("--length-factor", type=float, default=2.0, help="the larger part's length over the nose's")
    ap.add_argument("--tile-mm", type=float, default=500.0)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--folder", type=Path, default=None, help="where the jobs are written (default: a temp dir)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--band-share", type=float, default=1.0, help="only the views in this share of each part's "
                    "length from its tail (a band across it: the nose's and, twice as long, the longer part's)")
    ap.add_argument("--sizes", nargs="+", choices=("nose", "long"), default=["nose", "long"],
                    help="which parts to run (the model and the growth need both)")
    ap.add_argument("--no-correction", action="store_true", help="the tile stages at the stored poses, without the "
                    "correction (its pair units read every scan several times: at full resolution the longest stage)")
    ap.add_argument("--density-views", type=int, default=0, help="ray cast this many views at full resolution too "
                    "and compare the thinned copies' points (whether --resolution stands for full in memory)")
    ap.add_argument("--no-e57", action="store_true", help="leave the E57 out (at full resolution the longer part's "
                    "E57 is about 28 GB beside its 57 GB of raw scans)")
    args = ap.parse_args()
    pixels = _pixels(args.resolution)
    nose = PartConfig()
    long = PartConfig(length_mm=nose.length_mm * args.length_factor,
                      body_length_mm=nose.body_length_mm + nose.length_mm * (args.length_factor - 1.0))
    area = {id(p): train_nose_mesh(p).get_surface_area() for p in (nose, long)}
    density = density_check(nose, pixels, args.density_views, args.seed) if args.density_views else None
    if density:
        print(f"density: {json.dumps(density)}", file=sys.stderr, flush=True)
    root = Path(tempfile.mkdtemp(prefix="capacity-", dir=args.folder))
    sizes = []
    try:
        for label, part in (("nose", nose), ("long", long)):
            if label not in args.sizes:
                continue
            folder = root / label
            folder.mkdir()
            scans = round(args.scans * area[id(part)] / area[id(nose)])
            t = time.perf_counter()
            job = make_job(folder, part, scans, pixels, args.seed, args.band_share)
            made = time.perf_counter() - t
            print(f"{label}: {len(job.files)} scans, {job.raw_points} points written in {made:.0f} s",
                  file=sys.stderr, flush=True)
            runs, drivers = {}, {}
            for w in args.workers:  # each run in a fresh process: its peaks are its own, not an earlier run's heap
                with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
                    runs[str(w)], drivers = pool.submit(run_stages, job, w, args.tile_mm, not args.no_e57,
                                                                 not args.no_correction).result()
            sizes.append({"part": label, "length_mm": part.length_mm, "drivers": drivers,
                          "job_written_s": round(made, 1), "runs": runs})
            print(f"{label}: peaks {json.dumps(peaks(sizes[-1:]))}", file=sys.stderr, flush=True)
            shutil.rmtree(folder)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    figures = {"resolution": args.resolution, "pixels": list(pixels), "tile_mm": args.tile_mm, "density": density,
               "band_share": args.band_share, "peaks": peaks(sizes), "sizes": sizes,
               "model": model(sizes, args.workers, (1, 2, 8, 32, 64)) if len(sizes) > 1 else None,
               "note": "wall seconds on a shared machine are upper bounds; the model is only as good as the run"}
    variant = "" if args.resolution == "coarse" and args.band_share == 1.0 else f"-{args.resolution}"
    variant += f"-band{args.band_share:g}" if args.band_share < 1.0 else ""
    variant += "-no-correction" if args.no_correction else ""
    publish(f"capacity{variant}" + ("" if len(sizes) > 1 else f"-{sizes[0]['part']}"), figures)


if __name__ == "__main__":
    main()

"""Capacity of the end of a job: seconds and peak memory of every stage against the scans and points, at two part
sizes and on 1 and 2 Dask workers, and from them the estimate for a 20 m railway car (docs/capacity.md).

Each size is a job of the parametric train nose (``geometry.part.train_nose_mesh``: the 3 m nose, and the same
nose on a body ``--length-factor`` times as long), its scans ray cast by the simulated scanner
(``geometry.raycast.ScannerModel`` at ``--resolution``) from views spread evenly over the part's upper surface
(Poisson disk on the mesh, the sweet spot along each normal; ``--scans`` on the nose, in proportion to the area on
the longer part), each stored pose off the true one by the tracker's noise. The job is written as raw scan files
(``scans/``, the scan store), then the daemon's own end of the job runs on it, on a Dask ``LocalCluster`` of 1 and
2 single-threaded workers given as ``[compute] scheduler`` (``backend = "dask"``, ``scan_store`` the job folder,
``tile_mm``): first what the daemon's map process does while the job measures (``measure``: each scan merged into
the map at its tracker pose and its thinned copy kept, ``stitcher.merge_scan``), then ``finish.finish_outputs`` on the
job's snapshot (``snapshot.JobSnapshot``: the scans' records, W the CAD frame), as the map process runs it after the
last scan. Its stages are the product's functions, each timed by name where the product calls it: ``read``
(``finish.load_scans``), ``correction`` (``finish.correct_stage``: every scan read and summarised on the workers, its
pairs and the joint's per-pair work there), ``merge`` (``finish.merged_cloud``, tiles on the workers), ``exports``
(``outputs.export_job``) and within it, side by side as in the product, ``cloud_ply`` and ``inspection``
(``outputs._inspection_section``: the report's sample here, then ``inspect`` on the workers, ``figures`` and
``deviation_ply``, ``tile_inspection``; the E57 and pose log in a process of their own, not sampled). Each stage's
wall seconds and peak RSS (GiB): of the process that runs the end of the job (``main_gib``, and ``main_start_gib``
what it held as the stage started; a fresh process for each size and worker count) and of each worker
(``worker_gib``, their largest), the largest of samples taken every :data:`SAMPLE_S` on a thread of each process
(stages that run side by side share their samples). The merge's scratch on disk: the largest sum of its shards'
bytes (``merge``'s ``shards_peak_gb``, the files under ``tiles/shards-*/`` summed every :data:`DISK_SAMPLE_S`) and of
the whole ``tiles/`` folder (``tiles_folder_peak_gb``: the tiles' clouds too), every shard's (``shards_written_gb``:
the peak of a merge that kept them all until the last scan was placed), beside the raw scans' (``raw_scans_gb``).
``--density-views`` checks that a reduced ``--resolution`` stands for full resolution in the main process's memory
(:func:`density_check`).

The model, per stage of :data:`DRIVERS` (the end of the job's stages one after the other): on one worker
``t1 = a + b x`` through the two sizes, ``x`` the stage's driver (raw points or scans); on N workers Amdahl's law
with the stage's serial share ``f = 2 t2 / t1 - 1`` (clipped to [0, 1]) measured at the larger size; the peak of a
worker is the larger of the two sizes' (bounded by the tile and the scan, not the part), that of this process
``a + b scans``. The car: :data:`CAR` (scans, raw
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
import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from results import publish
from tandemscan.config.models import ComputeConfig, CorrectionConfig, PartConfig, ScannerConfig
from tandemscan.pipeline.compute import DaskBackend
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import train_nose_mesh
from tandemscan.pipeline.geometry.raycast import ScannerModel, make_scene
from tandemscan.pipeline.io.raw_scan import remove_thinned_copies, thin_scan, write_raw_scan
from tandemscan.pipeline.registration.sampling import voxel_centroids

VOXEL_MM = 1.0
#: the 20 m railway car on the larger cell at full resolution (issue 43): scans and raw points
CAR = {"scans": 3700, "raw_points": 12e9}
#: what each stage's time grows with
DRIVERS = {"read": "scans", "correction": "scans", "merge": "raw_points", "exports": "raw_points"}
TRACKER_SIGMA = (0.03, 5e-5)  # mm, rad (1 sigma) of the stored poses' error
GIB = float(1 << 30)


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
    for T_F_S in view_poses(mesh, part, scans, band_share, scanner.sweet_spot_mm, seed):
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


def view_poses(mesh, part: PartConfig, scans: int, band_share: float, sweet_spot_mm: float, seed: int
               ) -> list[np.ndarray]:
    """:func:`make_job`'s views ``T_F_S`` (mm): Poisson disk on the part's upper surface (Open3D's sampler seeded with
    ``seed``: the same views every run), the scanner at the sweet spot along each normal, looking at it."""
    import open3d as o3d

    o3d.utility.random.seed(seed)
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
    poses = view_poses(mesh, part, 369, 1.0, ScannerConfig().sweet_spot_mm, seed)
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


#: how often each process's resident memory is sampled (s): the stages run side by side in the product (cloud.ply,
#: the E57 and the inspection), so a stage's peak is the largest sample in its window, not a reset high-water mark
SAMPLE_S = 0.02
#: how often the merge's scratch files on disk are summed (s): shards live from their scan's placing to their
#: tile's merge, several seconds
DISK_SAMPLE_S = 0.2
#: the daemon's end-of-job functions each stage is (module, function): its window is their call
STAGES = (("finish", "load_scans", "read"), ("finish", "correct_stage", "correction"),
          ("finish", "merged_cloud", "merge"), ("finish", "export_job", "exports"),
          ("outputs", "_write_cloud_ply", "cloud_ply"),
          ("outputs", "_inspection_section", "inspection"), ("tile_inspection", "inspect_tiles", "inspect"),
          ("tile_inspection", "deviation_figures", "figures"), ("tile_inspection", "tile_areas", "areas"),
          ("tile_inspection", "write_deviation_ply", "deviation_ply"))


def rss_gib() -> float:
    """This process's resident memory now, GiB (``VmRSS``)."""
    with open("/proc/self/status", encoding="ascii") as f:
        kib = next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
    return kib * 1024 / GIB


def start_sampling(dask_worker=None) -> list:
    """Sample this process's RSS every :data:`SAMPLE_S` on a thread of its own: (time.time(), GiB) appended to the
    returned list (on a Dask worker, ``client.run``, kept on the worker: :func:`worker_samples`)."""
    import threading

    samples: list = []

    def sample() -> None:
        while True:
            samples.append((time.time(), rss_gib()))
            time.sleep(SAMPLE_S)

    threading.Thread(target=sample, daemon=True, name="rss-samples").start()
    if dask_worker is not None:
        dask_worker.capacity_rss_samples = samples
    return samples


def start_disk_sampling(store: Path) -> list:
    """Sum the bytes of the merge's scratch files every :data:`DISK_SAMPLE_S` on a thread of its own:
    (time.time(), the shards' bytes, the whole ``tiles/`` folder's bytes, the bytes of every shard seen so far)
    appended to the returned list, the shards the files under ``<store>/tiles/shards-*/`` (``tiles.place_scan``;
    each lives from its scan's placing to its tile's merge, a map at least, so nearly all are seen: one that lives
    less than :data:`DISK_SAMPLE_S` may be missed), the folder also the tiles' clouds and their deviations. What every
    shard takes (a lower bound) is what a merge that placed every scan before merging a tile held at its peak."""
    import threading

    from tandemscan.pipeline.stitching.tiles import TILES_FOLDER

    samples: list = []
    seen: dict[str, int] = {}  # every shard file's size, by its name once written (``<name>.part`` while it is)

    def folder_bytes(folder: Path, shards: bool = False) -> tuple[int, int]:  # (its shards', all): files vanish
        in_shards = total = 0
        try:
            entries = list(os.scandir(folder))
        except FileNotFoundError:
            return 0, 0
        for entry in entries:
            with contextlib.suppress(FileNotFoundError):
                if entry.is_dir(follow_symlinks=False):
                    inner = folder_bytes(Path(entry.path), entry.name.startswith("shards-"))
                    in_shards, total = in_shards + inner[0], total + inner[1]
                else:
                    size = entry.stat(follow_symlinks=False).st_size
                    total += size
                    if shards:
                        in_shards += size
                        name = entry.path.removesuffix(".part")  # write_replacing's temporary name: one shard
                        seen[name] = max(size, seen.get(name, 0))
        return in_shards, total

    def sample() -> None:
        while True:
            samples.append((time.time(), *folder_bytes(store / TILES_FOLDER), sum(seen.values())))
            time.sleep(DISK_SAMPLE_S)

    threading.Thread(target=sample, daemon=True, name="disk-samples").start()
    return samples


def _scratch_in(window: tuple, disk: list) -> dict:
    """The merge's scratch on disk in a stage's ``window`` (name, start, end, ...), GB: the largest sample of the
    shards' bytes and of the ``tiles/`` folder's, and every shard's (:func:`start_disk_sampling`)."""
    inside = [s for s in disk if window[1] <= s[0] <= window[2]] or [(0.0, 0, 0, 0)]
    return {"shards_peak_gb": round(max(s[1] for s in inside) / 1e9, 3),
            "tiles_folder_peak_gb": round(max(s[2] for s in inside) / 1e9, 3),
            "shards_written_gb": round(max(s[3] for s in inside) / 1e9, 3)}


def worker_samples(dask_worker=None) -> list:
    """The samples :func:`start_sampling` keeps on this Dask worker."""
    return list(dask_worker.capacity_rss_samples)


def _timed_stages(windows: list) -> contextlib.ExitStack:
    """Each function of :data:`STAGES` replaced, until the returned stack closes, by one that appends its stage's
    (name, start, end) (time.time()) and its result to ``windows``: the product calls its own functions by these
    names, so their windows are the product's stages."""
    from tandemscan.daemon.jobs import finish, outputs
    from tandemscan.pipeline.inspection import tile_inspection

    modules = {"finish": finish, "outputs": outputs, "tile_inspection": tile_inspection}
    stack = contextlib.ExitStack()
    for module, function, stage in STAGES:
        real = getattr(modules[module], function)

        def timed(*args, _real=real, _stage=stage, **kwargs):
            t = time.time()
            out = _real(*args, **kwargs)
            windows.append((_stage, t, time.time(), out))
            print(f"{_stage}: {time.time() - t:.1f} s", file=sys.stderr, flush=True)
            return out

        setattr(modules[module], function, timed)
        stack.callback(setattr, modules[module], function, real)
    return stack


def _peaks_in(windows: list, main: list, workers: dict) -> dict:
    """Per stage (its first window): wall seconds, the largest sample of this process and of each worker in it, and
    the samples of this process and of the largest worker as it started (what the stage inherits)."""
    out = {}
    for stage, t0, t1, _ in windows:
        if stage in out:
            continue
        inside = [g for t, g in main if t0 <= t <= t1] or [min(main, key=lambda s: abs(s[0] - t0))[1]]
        before = [g for t, g in main if t <= t0] or inside
        each = sorted(max([g for t, g in w if t0 <= t <= t1] or [w[-1][1]]) for w in workers.values())
        start = max(([g for t, g in w if t <= t0] or [w[0][1]])[-1] for w in workers.values())
        out[stage] = {"wall_s": round(t1 - t0, 3), "main_gib": round(max(inside), 3),
                      "main_start_gib": round(before[-1], 3), "worker_gib": round(each[-1], 3),
                      "workers_gib": [round(g, 3) for g in each], "worker_start_gib": round(start, 3)}
    return out


def snapshot(job: Job, part: PartConfig, compute: ComputeConfig, correct: bool):
    """The job as the daemon's map process holds it at its last scan (``snapshot.JobSnapshot``): the scans' records
    (each pose its tracker reading's, W the CAD frame F, ``T_F_W`` the identity), a configuration of the simulated
    cell with ``part``, ``compute`` and, without ``correct``, the correction off; what its map process keeps of the
    scans is made by :func:`measure`."""
    from tandemscan.config.models import CellConfig
    from tandemscan.daemon.jobs.records import ScanRecord
    from tandemscan.daemon.jobs.snapshot import JobSnapshot
    from tandemscan.drivers.interfaces import TrackerReading
    from tandemscan.pipeline.stitching.installation import Installation

    cov = np.diag([TRACKER_SIGMA[0] ** 2] * 3 + [TRACKER_SIGMA[1] ** 2] * 3)
    config = CellConfig(part=part, compute=compute, correction=CorrectionConfig(enabled=correct),
                        job={"voxel_mm": VOXEL_MM})
    scans = []
    for k, (file, T) in enumerate(zip(job.files, job.poses, strict=True)):
        with np.load(job.folder / file) as data:
            count = len(data["points_S_mm"])
        scans.append(ScanRecord(k, 0, job.folder / file, TrackerReading(np.eye(4), cov, float(k), k), np.zeros(6),
                                np.asarray(T, float), np.asarray(T, float), count))
    plan = SimpleNamespace(name="capacity", coverage_pct=None, left_out=(), scan_count=len(scans))
    return JobSnapshot(job.folder, plan, config, Installation(*[np.eye(4)] * 4), scans, [], {}, None, np.eye(4))


def measure(job) -> None:
    """What the daemon's map process does while the job measures (``stitcher.merge_scan``, each scan read here from
    its file): on the scan-store path (``ComputeConfig.reads_scan_store``, always here) only each scan's stitch-view
    points and reach kept, no scan merged."""
    from tandemscan.daemon.jobs.stitcher import merge_scan
    from tandemscan.pipeline.stitching.worldmap import VoxelMap

    job.worldmap, job.scan_copies = VoxelMap(job.config.job.voxel_mm), {}
    for s in job.scans:
        merge_scan(job.worldmap, job.scan_copies, str(s.file), s.T_W_S, None, job.config.compute.reads_scan_store)


def run_stages(job: Job, part: PartConfig, workers: int, tile_mm: float, e57: bool = True, correct: bool = True
               ) -> tuple[dict, dict]:
    """The daemon's end of the job (``finish.finish_outputs``, the map process's work after the last scan) on a
    ``LocalCluster`` of ``workers`` as ``[compute] scheduler`` (the E57 where ``e57``; without ``correct`` the
    correction off), after :func:`measure`: (per stage figures, drivers).

    Six parameters: the job and its part, the cluster's size, the tiles, and two stages left out."""
    from tandemscan.daemon.jobs import finish, outputs

    backend = DaskBackend("", workers)
    windows: list = []
    try:
        backend.client.wait_for_workers(workers, timeout=120)
        main = start_sampling()
        disk = start_disk_sampling(job.folder)
        backend.client.run(start_sampling)
        compute = ComputeConfig(backend="dask", scheduler=backend.client.scheduler.address, tile_mm=tile_mm,
                                scan_store=job.folder, dask_workers=workers)
        snap = snapshot(job, part, compute, correct)
        with _timed_stages(windows) as stack:
            if not e57:  # its disk (at full resolution half the raw scans again), not the product's choice
                stack.enter_context(_without_e57(outputs))
            t = time.time()
            measure(snap)
            windows.append(("measure", t, time.time(), None))
            kept = finish.finish_outputs(snap, time.monotonic(), time.monotonic())
        time.sleep(2 * SAMPLE_S)
        stages = _peaks_in(windows, list(main), backend.client.run(worker_samples))
        stages["merge"] |= _scratch_in(next(w for w in windows if w[0] == "merge"), list(disk))
        finish.drop_outputs(kept)  # its tiles and its client of this cluster, while the scheduler runs
    finally:
        backend.close()
    cloud = kept.final.worldmap  # tiles (their files removed), or with tile_mm 0 the cloud merged in one process
    for name in ("cloud.ply", "cloud_deviation.ply", "cloud.e57", "poses.csv", "report.html"):
        (job.folder / name).unlink(missing_ok=True)
    shutil.rmtree(job.folder / "figures", ignore_errors=True)
    remove_thinned_copies(job.folder)  # what measure() kept for the workers, as the job's runner removes it
    tiles = getattr(cloud, "tiles", ())
    drivers = {"scans": len(job.files), "raw_points": job.raw_points,
               "raw_scans_gb": round(sum((job.folder / f).stat().st_size for f in job.files) / 1e9, 3),
               "voxels": len(cloud), "tiles": len(tiles),
               "tile_voxels_max": max((t.voxels for t in tiles), default=0),
               "pairs": kept.correction.section.get("pairs") if correct else None,
               "verdict": kept.exports.inspection.get("verdict")}
    return stages, drivers


def pose_log_only(exports) -> None:
    """``export.write_scan_exports`` without the E57: the pose log alone (in the exports' own process, which imports
    this module by name)."""
    from tandemscan.pipeline.io.export import write_pose_log

    write_pose_log(exports.pose_log, exports.scans)


@contextlib.contextmanager
def _without_e57(outputs):
    """The job's E57 left out (``daemon.jobs.outputs`` hands its exports' process :func:`pose_log_only`)."""
    real = outputs.write_scan_exports
    outputs.write_scan_exports = pose_log_only
    try:
        yield
    finally:
        outputs.write_scan_exports = real


def model(sizes: list[dict], workers: list[int], car_workers: tuple[int, ...]) -> dict:
    """Per stage the fitted ``a + b x`` on one worker, the serial share, the peaks, and the car's estimate on
    ``car_workers`` workers (module doc)."""
    small, large = sizes[0], sizes[-1]
    one, two = str(min(workers)), str(max(workers))
    per_point = large["drivers"]["voxels"] / large["drivers"]["raw_points"]
    car = {"scans": CAR["scans"], "raw_points": CAR["raw_points"], "voxels": CAR["raw_points"] * per_point}
    stages, seconds = {}, dict.fromkeys(car_workers, 0.0)
    for name, driver in DRIVERS.items():
        if any(name not in s["runs"][w] for s in sizes for w in (one, two)):  # a stage left out of a run
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
    larger part, the main process under 1.5 GiB; per size the merge's shards' peak on disk (GB) beside the raw
    scans', and its growth on the larger part (``shards_growth``)."""
    out = {}
    for w in sizes[0]["runs"]:
        by_size = {}
        for size in sizes:
            stages = size["runs"][w]
            main, worker = (max(stages, key=lambda name, k=k: stages[name][k]) for k in ("main_gib", "worker_gib"))
            by_size[size["part"]] = {"scans": size["drivers"]["scans"], "raw_points": size["drivers"]["raw_points"],
                                     "main_gib": stages[main]["main_gib"], "main_stage": main,
                                     "worker_gib": stages[worker]["worker_gib"], "worker_stage": worker,
                                     "raw_scans_gb": size["drivers"]["raw_scans_gb"],
                                     "shards_peak_gb": stages["merge"]["shards_peak_gb"],
                                     "shards_written_gb": stages["merge"]["shards_written_gb"]}
        out[w] = {**by_size, "worker_at_most_3_gib": max(s["worker_gib"] for s in by_size.values()) <= 3.0,
                  "main_under_1_5_gib": max(s["main_gib"] for s in by_size.values()) < 1.5}
        if len(sizes) > 1:
            growth = by_size[sizes[-1]["part"]]["worker_gib"] / by_size[sizes[0]["part"]]["worker_gib"]
            shards = [by_size[s["part"]]["shards_peak_gb"] for s in (sizes[0], sizes[-1])]
            out[w] |= {"worker_growth": round(growth, 3), "worker_within_15_percent": growth <= 1.15,
                       "shards_growth": round(shards[1] / shards[0], 3) if shards[0] else None}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--resolution", default="coarse", help="coarse, full or COLSxROWS of the scanner")
    ap.add_argument("--scans", type=int, default=369, help="scans of the nose (the larger part: by its area)")
    ap.add_argument("--length-factor", type=float, default=2.0, help="the larger part's length over the nose's")
    ap.add_argument("--tile-mm", type=float, default=500.0)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--folder", type=Path, default=None, help="where the jobs are written, made with its parents "
                    "where missing (default: a temp dir)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--band-share", type=float, default=1.0, help="only the views in this share of each part's "
                    "length from its tail (a band across it: the nose's and, twice as long, the longer part's)")
    ap.add_argument("--sizes", nargs="+", choices=("nose", "long"), default=["nose", "long"],
                    help="which parts to run (the model and the growth need both)")
    ap.add_argument("--no-correction", action="store_true", help="[correction] enabled = false: the cloud merged at "
                    "the tracker poses (finish.merged_cloud: on the scan-store path no map is merged while measuring)")
    ap.add_argument("--density-views", type=int, default=0, help="ray cast this many views at full resolution too "
                    "and compare the thinned copies' points (whether --resolution stands for full in memory)")
    ap.add_argument("--no-e57", action="store_true", help="leave the E57 out (at full resolution the longer part's "
                    "E57 is about 28 GB beside its 57 GB of raw scans)")
    args = ap.parse_args()
    if args.folder is not None:
        args.folder.mkdir(parents=True, exist_ok=True)  # tempfile.mkdtemp(dir=...) needs it to exist
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
                    runs[str(w)], drivers = pool.submit(run_stages, job, part, w, args.tile_mm, not args.no_e57,
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

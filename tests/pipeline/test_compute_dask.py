"""The pair stage on a real Dask cluster on loopback (docs/compute.md): a ``dask scheduler`` and two ``dask worker``
processes on 127.0.0.1, the workers reading the scans by reference from the scan store; the outcomes and the poses
are those of the local backend to 1e-9 mm, also when a worker is killed while it registers pairs."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from dask.distributed import get_task_stream
from tandemscan.config.models import ComputeConfig, CorrectionConfig, DeepMergeConfig
from tandemscan.pipeline.compute import (
    MESSAGE_LOG,
    DaskBackend,
    LazyBackend,
    LocalBackend,
    StoredResult,
    backend_for,
    process_cpu_seconds,
)
from tandemscan.pipeline.inspection.region_points import Region, gather
from tandemscan.pipeline.inspection.tile_inspection import AreaBounds, inspect_tiles, tile_areas
from tandemscan.pipeline.io.raw_scan import read_thinned_scan, write_raw_scan
from tandemscan.pipeline.registration.correction import (
    CorrectionSettings,
    ReadScan,
    StitchedJob,
    StitchedScan,
    correct_scans,
)
from tandemscan.pipeline.registration.joint import JointScan, StoredJointScan, _Match
from tandemscan.pipeline.registration.pairs import LazyNetwork
from tandemscan.pipeline.stitching.tiles import merge_tiles

from tests.pipeline.registration.test_registration_correction import scans_with_drift
from tests.pipeline.stitching.test_tiles import T_F_W, TILE_MM, concatenated, stored_job

pytestmark = pytest.mark.slow
VOXEL_MM = 1.0
# the pose graph: poses from the pairs
CFG = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100, joint=False))
# the joint refinement (the default): poses from the tracker start, the check pairs registered on the backend
JOINT = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100))
# the tiles' deviation areas: where the noise (0.05 mm a point, about 0.007 averaged) leaves the band
AREAS = AreaBounds(-0.01, 0.01, 4.0, 50.0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


@pytest.fixture
def cluster():
    """The address of a scheduler with two single-threaded workers on 127.0.0.1, and the workers' processes."""
    address = f"tcp://127.0.0.1:{_free_port()}"
    scheduler = _start("distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                       "--no-dashboard")
    workers = [_start("distributed.cli.dask_worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                      "--no-dashboard", "--no-nanny") for _ in range(2)]
    try:
        yield address, workers
    finally:
        for p in [*workers, scheduler]:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
            p.wait(timeout=30)


def _stored_job(folder: Path) -> list[StitchedScan]:
    """The drift scenario's scans written as raw scan files under ``folder/scans`` (the store), each held here as
    the end of a job holds it (``read_thinned_scan``) and named by its file relative to ``folder``."""
    _, scans, transfers = scans_with_drift(n=6, per_station=2)
    (folder / "scans").mkdir()
    stored = []
    for k, s in enumerate(scans):
        file = f"scans/scan-{k:04d}.npz"
        write_raw_scan(folder / file, points_S_mm=s.points_S)
        stored.append(StitchedScan(read_thinned_scan(folder / file, VOXEL_MM), s.T_W_S, s.covariance, s.station,
                                   file))
    return stored, transfers


def _same(a, b) -> None:
    assert [(i, j) for i, j, _ in a.edges] == [(i, j) for i, j, _ in b.edges]
    for (_, _, x), (_, _, y) in zip(a.edges, b.edges, strict=True):
        np.testing.assert_allclose(x.transformation, y.transformation, rtol=0, atol=1e-9)
        np.testing.assert_allclose(x.information, y.information, rtol=1e-9, atol=0)
    for P, Q in zip(a.poses, b.poses, strict=True):
        np.testing.assert_allclose(P, Q, rtol=0, atol=1e-9)


class _Watched(DaskBackend):
    """A Dask backend that notes the types of what its units hand back to this process and the stages' keys."""

    def __init__(self, address: str):
        super().__init__(address)
        self.returned, self.keys = set(), []

    def keep(self, fn, units, keys, inputs=None):
        self.keys += list(keys)
        return super().keep(fn, units, keys, inputs)

    def map(self, fn, units, keys, inputs=None):
        self.keys += list(keys)
        out = super().map(fn, units, keys, inputs)
        self.returned |= {type(x) for r in out for x in (r if isinstance(r, tuple) else (r,))}
        self.returned |= {type(r.joint) for r in out if isinstance(r, ReadScan)}
        return out


def _held_by_workers(backend: DaskBackend) -> dict[str, list[str]]:
    """The keys the workers still hold, once the releases sent to them have arrived (within 10 s)."""
    deadline = time.monotonic() + 10
    while True:
        # a lambda: pickled by value (this module is not importable on the workers)
        held = {w: keys for w, keys in backend.client.run(lambda dask_worker: sorted(map(str, dask_worker.data))
                                                          ).items() if keys}
        if not held or time.monotonic() > deadline:
            return held
        time.sleep(0.1)


def test_the_pair_stage_on_two_dask_workers_gives_the_local_result(cluster, tmp_path):
    address, _ = cluster
    scans, transfers = _stored_job(tmp_path)
    network = LazyNetwork(DeepMergeConfig())  # as the job passes it: pickled to the workers, loaded only where used
    local = correct_scans(StitchedJob(scans, transfers, voxel_mm=VOXEL_MM), CFG, network, backend=LocalBackend())
    assert len(local.edges) >= 5
    local_joint = correct_scans(StitchedJob(scans, transfers, voxel_mm=VOXEL_MM), JOINT, network,
                                backend=LocalBackend())
    assert 0 < len(local_joint.edges) <= len(local.edges)  # the check pairs only
    backend = _Watched(address)
    try:
        backend.client.wait_for_workers(2, timeout=60)
        with get_task_stream(backend.client) as stream:
            remote = correct_scans(StitchedJob(scans, transfers, voxel_mm=VOXEL_MM), CFG, network, backend=backend,
                                   scan_store=str(tmp_path))
        # this process without the scans' points: their summaries, joint scans and overlap RMS read on the workers
        unheld = [dataclasses.replace(s, points_S=None) for s in scans]
        remote_joint = correct_scans(StitchedJob(unheld, transfers, voxel_mm=VOXEL_MM), JOINT, network,
                                     backend=backend, scan_store=str(tmp_path))
        # the correction returned: nothing of it is left on the workers, nor its joint scans in the store
        assert _held_by_workers(backend) == {}
        assert not (tmp_path / "joint").exists()
    finally:
        backend.close()
    _same(local, remote)
    _same(local_joint, remote_joint)
    assert local_joint.report["joint"] == remote_joint.report["joint"]
    for key in ("overlap_rms_mm_median_before", "overlap_rms_mm_median_after", "pairs", "stages"):
        assert local_joint.report[key] == remote_joint.report[key], key
    assert len(remote_joint.reaches) == len(scans)  # the tiled merge's bounds of x, from the workers' reads
    assert [(a.x_min_mm, a.x_max_mm, a.reach_mm) for a in local_joint.reaches] == [
        (b.x_min_mm, b.x_max_mm, b.reach_mm) for b in remote_joint.reaches]
    assert len({task["worker"] for task in stream.data}) == 2  # both workers registered pairs
    # the joint refinement's scans stayed in the store (each unit read those it took) and so did its pairs'
    # correspondences between its stages (compute.StoredResults): its per-pair units ran on the workers and handed
    # this process only the files' handles, sizes, residuals and normal equations
    assert any(k.startswith("joint-near-") for k in backend.keys)
    assert {StoredJointScan, StoredResult} <= backend.returned
    assert not backend.returned & {JointScan, _Match}
    assert np.ndarray in backend.returned


@pytest.mark.parametrize(("cfg", "stage"), [(CFG, ""), (JOINT, r"joint-[a-z-]+-[0-9a-f]{32}-\d+-\d+$")],
                         ids=["pair stage", "joint refinement's per-pair stages"])
def test_a_worker_killed_mid_stage_leaves_the_result_unchanged(cluster, tmp_path, cfg, stage):
    """A worker killed while it runs a unit (the first unit of the pair stage, or one of the joint refinement's
    per-pair stages, keys ``joint-<stage>-<run>-<n>-<k>``, whose results wait in the store between them): the units
    run again, the same poses."""
    address, workers = cluster
    scans, transfers = _stored_job(tmp_path)
    local = correct_scans(StitchedJob(scans, transfers, voxel_mm=VOXEL_MM), cfg, backend=LocalBackend())
    backend = DaskBackend(address)
    killed = []
    try:
        backend.client.wait_for_workers(2, timeout=60)
        pids = backend.client.run(os.getpid)  # worker address -> process id
        by_pid = {p.pid: p for p in workers}

        def kill_a_busy_worker() -> None:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not killed:
                busy = [w for w, tasks in backend.client.processing().items()
                        if any(re.match(stage, str(k)) for k in tasks)]
                if busy:
                    os.kill(by_pid[pids[busy[0]]].pid, signal.SIGKILL)
                    killed.append(busy[0])
                time.sleep(0.005)

        killer = threading.Thread(target=kill_a_busy_worker)
        killer.start()
        # this process without the scans' points, as on the product's dask path (a scan it holds is scattered to the
        # workers, ``put``: lost with its worker)
        unheld = [dataclasses.replace(s, points_S=None) for s in scans]
        remote = correct_scans(StitchedJob(unheld, transfers, voxel_mm=VOXEL_MM), cfg, backend=backend,
                               scan_store=str(tmp_path))
        killer.join()
    finally:
        backend.close()
    assert killed, "no worker was busy to be killed"
    assert by_pid[pids[killed[0]]].wait(timeout=10) == -signal.SIGKILL
    _same(local, remote)


def _deviations(store: Path, inspected) -> list[np.ndarray]:
    out = []
    for t in inspected:
        with np.load(store / t.file) as data:
            out += [data[name] for name in ("points_F", "normals_F", "deviation_mm")]
    return out


def test_the_tile_stages_on_two_dask_workers_give_the_local_result(cluster, tmp_path):
    address, _ = cluster
    refs, mesh_file = stored_job(tmp_path, scans=4, points=15_000)
    local = merge_tiles(refs, VOXEL_MM, TILE_MM, tmp_path, LocalBackend())
    local_cloud = concatenated(tmp_path, local)
    local_inspected = inspect_tiles(local, tmp_path, mesh_file, T_F_W, -0.08, 0.08, LocalBackend())
    local_deviations = _deviations(tmp_path, local_inspected)
    local_areas = tile_areas(local_inspected, tmp_path, T_F_W, AREAS, LocalBackend())
    centre = np.asarray(local_areas[0].centroid_mm)  # a box about the first area and a slab across x through it
    regions = (Region.box(centre - 20.0, centre + 20.0), Region(np.eye(3)[:1], centre[:1], np.array([2.0])))
    local_near = gather([t.file for t in local_inspected], tmp_path, regions, LocalBackend())
    shutil.rmtree(tmp_path / "tiles")  # the workers write their own
    backend = DaskBackend(address)
    try:
        backend.client.wait_for_workers(2, timeout=60)
        with get_task_stream(backend.client) as stream:
            remote = merge_tiles(refs, VOXEL_MM, TILE_MM, tmp_path, backend)
            remote_inspected = inspect_tiles(remote, tmp_path, mesh_file, T_F_W, -0.08, 0.08, backend)
            remote_areas = tile_areas(remote_inspected, tmp_path, T_F_W, AREAS, backend)
            remote_near = gather([t.file for t in remote_inspected], tmp_path, regions, backend)
    finally:
        backend.close()
    assert remote == local  # the same tiles, files and voxel counts
    for a, b in zip(concatenated(tmp_path, remote), local_cloud, strict=True):
        np.testing.assert_array_equal(a, b)
    assert [(t.count, t.mean_mm, t.below, t.above) for t in remote_inspected] == [
        (t.count, t.mean_mm, t.below, t.above) for t in local_inspected]
    for a, b in zip(_deviations(tmp_path, remote_inspected), local_deviations, strict=True):
        np.testing.assert_array_equal(a, b)
    assert local_areas and remote_areas == local_areas  # the deviation areas, joined across the tiles
    for a, b in zip(remote_near, local_near, strict=True):  # the points of small regions (the characteristics')
        assert len(b) > 100
        for name in ("points_mm", "deviations_mm", "triangle_ids", "uncertainty_mm"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len({task["worker"] for task in stream.data}) == 2  # both workers merged or inspected tiles


def test_the_compute_config_picks_the_backend_and_a_local_cluster_maps_units_in_order():
    assert isinstance(backend_for(ComputeConfig()), LocalBackend)
    backend = backend_for(ComputeConfig(backend="dask", dask_workers=2))
    try:
        assert isinstance(backend, DaskBackend)
        units = list(range(-6, 6))
        assert backend.map(abs, units, [f"abs-{u}" for u in units]) == [abs(u) for u in units]
        assert len(backend.client.scheduler_info()["workers"]) == 2
    finally:
        backend.close()


def test_a_local_clusters_streams_keep_a_short_log_of_the_batches_they_sent():
    """Each Dask stream keeps its last batches of messages (their tasks' specs and arguments) for its logs: in the
    process of the end of a job, its client's and its LocalCluster's scheduler's, at most :data:`MESSAGE_LOG`."""
    backend = DaskBackend("", 1)
    try:
        for round_ in range(3 * MESSAGE_LOG):  # a batch a round at least
            backend.map(abs, [-round_], [f"abs-log-{round_}"])
        scheduler = backend._cluster.scheduler
        streams = [backend.client.scheduler_comm, *scheduler.stream_comms.values(), *scheduler.client_comms.values()]
        assert len(streams) >= 3 and len(backend.client.scheduler_comm.recent_message_log) == MESSAGE_LOG
        assert all(s.recent_message_log.maxlen == MESSAGE_LOG for s in streams)
    finally:
        backend.close()


def test_one_lazy_backend_is_one_client_of_the_scheduler_for_every_stage(cluster, tmp_path):
    """``[compute] scheduler`` an address: the stages of one end of a job share one client, made at the first
    stage, closed with the end of the job; its CPU seconds count the workers' (they are no child of this
    process)."""
    address, _ = cluster
    refs, mesh_file = stored_job(tmp_path, scans=2, points=5_000)

    def busy(seconds: float) -> float:  # a unit spinning on its worker's CPU (local: pickled by value)
        start = process_cpu_seconds()
        while process_cpu_seconds() - start < seconds:
            pass
        return seconds

    with LazyBackend(ComputeConfig(backend="dask", scheduler=address)) as lazy:
        backend = lazy.get()
        backend.client.wait_for_workers(2, timeout=60)
        tiles = merge_tiles(refs, VOXEL_MM, TILE_MM, tmp_path, lazy.get())
        assert lazy.get() is backend
        inspect_tiles(tiles, tmp_path, mesh_file, T_F_W, -0.08, 0.08, lazy.get())
        assert lazy.get() is backend
        before, here = backend.cpu_seconds(), process_cpu_seconds()
        assert backend.map(busy, [0.2, 0.2], ["busy-0", "busy-1"]) == [0.2, 0.2]
        assert backend.cpu_seconds() - before > 0.4 + (process_cpu_seconds() - here)
    assert backend.client.status == "closed"


def test_a_failed_map_raises_once_every_unit_has_ended(cluster, tmp_path):
    """As on the local backend's threads, a unit's error is raised once the other units have ended: a stage that
    removes what its units wrote where one fails (``tiles.merge_tiles``, ``tile_inspection.inspect_tiles``) finds
    every file, none written by a unit still running after it cleaned up."""
    address, _ = cluster
    folder = str(tmp_path)

    def unit(k: int) -> int:
        if k == 0:
            raise OSError(28, "No space left on device")
        time.sleep(1.0)
        (Path(folder) / f"unit-{k}.npz").write_bytes(b"written")
        return k

    backend = DaskBackend(address, retries=0)  # the failure at once, not after retries queued behind the slow unit
    try:
        with pytest.raises(OSError, match="No space left"):
            backend.map(unit, [0, 1], ["failing-unit-0", "slow-unit-1"])
        assert (tmp_path / "unit-1.npz").is_file()
    finally:
        backend.close()

"""The daemon's worker processes: scan arrays cross by shared memory, the out-of-process sim scanner gives
the in-process capture, and workers die with a daemon killed by SIGKILL."""

from __future__ import annotations

import gc
import json
import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from tandemscan.config import load_config
from tandemscan.daemon.plans import default_plan_path
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.drivers.shared_array import PREFIX, SHM_DIR, SharedArray, hand_over, remove_stale_blocks, share, take
from tandemscan.pipeline.planning.plan import MoveArm, MoveMeasure, Plan
from tandemscan.sim_drivers.scan_process import ScanProcess
from tandemscan.sim_drivers.world import SimWorld

pytestmark = pytest.mark.skipif(not SHM_DIR.is_dir(), reason="needs POSIX shared memory in /dev/shm")


def _blocks() -> set[str]:
    return {p.name for p in SHM_DIR.glob(f"{PREFIX}{os.getpid()}-*")}


def test_shared_array_pickles_by_name_and_its_owner_removes_it():
    big = np.random.default_rng(0).normal(size=(100_000, 3))
    shared = share(big)
    assert isinstance(shared, SharedArray) and len(_blocks()) == 1
    data = pickle.dumps(shared)
    assert len(data) < 500  # the name, not 2.4 MB of points
    borrowed = pickle.loads(data)
    np.testing.assert_array_equal(borrowed, big)
    del borrowed
    gc.collect()
    assert len(_blocks()) == 1  # a borrower never removes the block
    assert len(pickle.dumps(shared[::2])) > big.nbytes // 2  # a view is an ordinary array: by value
    del shared
    gc.collect()
    assert _blocks() == set()
    small = np.ones(3)
    assert share(small) is small


def test_a_worker_hands_its_result_over_to_the_parent():
    before = _blocks()
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        block = pool.submit(hand_over, np.arange(300_000, dtype=np.float64)).result()
    assert len(pickle.dumps(block)) < 500
    arr = take(block)
    np.testing.assert_array_equal(arr, np.arange(300_000))
    assert len(_blocks() - before) == 1
    del arr
    gc.collect()
    assert _blocks() == before  # the parent owns it now


def test_blocks_of_dead_processes_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = SHM_DIR / f"{PREFIX}{int(dead.stdout)}-test"
    stale.write_bytes(b"x")
    mine = share(np.zeros(200_000))
    assert remove_stale_blocks() >= 1
    assert not stale.exists() and len(_blocks()) == 1
    del mine


def _at_first_scan(world: SimWorld) -> None:
    """Drive the world to the first scan pose of the default plan."""
    for step in Plan.load(default_plan_path()).steps[:2]:
        if isinstance(step, MoveMeasure):
            world.chassis["measure_chassis"].apply_move(ChassisPose(step.x_mm, step.y_mm, step.heading_rad),
                                                        world.rng)
        elif isinstance(step, MoveArm):
            world.move_arm(np.array(step.joints_rad))


@pytest.mark.slow
@pytest.mark.parametrize("cell", [None, "config/as-built-example.toml"])
async def test_scan_process_captures_what_the_world_captures(cell):
    sim_config = load_config(cell)  # the as-built part: the worker scans it too, not the CAD
    here, there = SimWorld(sim_config), SimWorld(sim_config)
    _at_first_scan(here)
    _at_first_scan(there)
    process = ScanProcess(sim_config)
    try:
        points, normals = await process.scan(there.T_F_S(), there.rng)
    finally:
        process.close()
    expected_points, expected_normals = here.scan()
    assert len(points) > 10_000
    np.testing.assert_array_equal(points, expected_points)  # same seed, same cloud, bit for bit
    np.testing.assert_array_equal(normals, expected_normals)
    assert here.rng.normal() == there.rng.normal()  # the random stream goes on at the same place


_ORPHAN_SCRIPT = """
import os, time
from concurrent.futures import ProcessPoolExecutor
import multiprocessing
from tandemscan.drivers.worker import die_with_parent
if __name__ == "__main__":
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=die_with_parent)
    print(pool.submit(os.getpid).result(), flush=True)
    time.sleep(60)
"""


def _running(pid: int) -> bool:
    """Alive and not a zombie (an orphan's exit is reaped by whatever adopted it, maybe later)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_workers_die_with_a_killed_parent(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(_ORPHAN_SCRIPT)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        worker = int(parent.stdout.readline())
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if not _running(worker):
                return
            time.sleep(0.05)
        os.kill(worker, signal.SIGKILL)
        raise AssertionError("the worker outlived its killed parent")
    finally:
        if parent.poll() is None:
            parent.kill()
        parent.stdout.close()


def test_the_daemon_process_never_loads_the_heavy_pipeline():
    """torch (correction), matplotlib and pye57 (exports) take seconds to import: only worker processes
    load them, never the daemon's event loop (the runner hands them over by thin wrappers)."""
    code = ("import sys, tandemscan.daemon.service, tandemscan.daemon.api.app, tandemscan.daemon.jobs.journal, "
            "tandemscan.daemon.jobs.runner; "
            "print(sorted(m for m in ('torch', 'matplotlib', 'pye57') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="threads listed by /proc (Linux)")
def test_yield_cores_renices_every_thread_of_the_process():
    """The pair worker's check pairs yield the cores once the job has measured: every thread of its process, the
    pool threads registering them included, is reniced (niceness is a thread's on Linux), not only the caller."""
    code = """
import json, os, threading
from tandemscan.drivers.worker import yield_cores
started, stop = threading.Event(), threading.Event()
tid = []
def run():
    tid.append(threading.get_native_id())
    started.set()
    stop.wait()
t = threading.Thread(target=run)
t.start()
started.wait()
before = [os.getpriority(os.PRIO_PROCESS, k) for k in (threading.get_native_id(), tid[0])]
yield_cores(3)
after = [os.getpriority(os.PRIO_PROCESS, k) for k in (threading.get_native_id(), tid[0])]
stop.set()
t.join()
print(json.dumps([before, after]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    before, after = json.loads(out.stdout)
    assert after == [min(19, b + 3) for b in before]

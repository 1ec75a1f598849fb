"""A daemon job on a full disk, run by ``tests/e2e/test_daemon_disk_full.py`` inside ``unshare --user --map-root-user
--mount`` so that it can mount a small tmpfs as its state folder: the simulated cell (twins) on a box part, the
trimmed default plan; the disk is filled after the first scan commits (``scan``) or once every step is committed,
as the end-of-job export starts (``export``), and freed after the job paused; or, with no job (``events``), filled
while operator stops and resets raise safety events. Prints one JSON object (the outcome) as its last line. Usage:
``disk_full_child.py WORK_DIR [scan|export|events]``."""

from __future__ import annotations

import asyncio
import errno
import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import open3d as o3d
from tandemscan.config import load_config
from tandemscan.daemon.notify import Notifier
from tandemscan.daemon.plans import default_plan_path
from tandemscan.daemon.service import Daemon
from tandemscan.pipeline.planning.plan import Plan

PLAN_STEPS = (0, 1, 2, 3, 4, 13, 14, 15, 16)
TMPFS_MB = 64


def box(path: Path) -> Path:
    mesh = o3d.geometry.TriangleMesh.create_box(3000.0, 2000.0, 1600.0).translate((-1500.0, -1000.0, 0.0))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def fill(path: Path) -> int:
    """Write zeros to ``path`` until the file system is full; returns the bytes written."""
    written = 0
    with open(path, "wb", buffering=0) as f:
        chunk = b"\0" * (1 << 20)
        while True:
            try:
                written += f.write(chunk)
            except OSError as e:
                if e.errno != errno.ENOSPC:
                    raise
                if len(chunk) == 1:
                    return written
                chunk = chunk[: len(chunk) // 2]


async def wait_for(predicate, timeout_s: float, period_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(period_s)
    return True


async def main(work: Path, phase: str) -> dict:
    state = work / "state"
    cfg = load_config()
    cfg = cfg.model_copy(update={
        "part": cfg.part.model_copy(update={"mesh": box(work / "box.stl")}),
        "inspection": cfg.inspection.model_copy(update={"in_job": False}),
        "correction": cfg.correction.model_copy(update={"enabled": False}),
        "daemon": cfg.daemon.model_copy(update={"reserve_free_bytes": 4_000_000, "scan_bytes_estimate": 1_000_000}),
    })
    plan = Plan.load(default_plan_path())
    plan = plan.model_copy(update={"steps": [plan.steps[i] for i in PLAN_STEPS]})
    daemon = Daemon(cfg, state, connect_timeout_s=30.0)
    await daemon.start()
    out: dict = {}
    try:
        mgr, store = daemon.manager, daemon.store
        job, _ = await mgr.submit("trimmed", {"plan": plan.model_dump(mode="json"), "label": None}, len(plan.steps),
                                  None, None)
        if phase == "export":
            await wait_for(lambda: store.steps_done(job.id) == len(plan.steps), 120, period_s=0.002)
        else:
            await wait_for(lambda: len(store.scans(job.id)) >= 1, 120)
        t0 = time.monotonic()
        filler = state / "filler.bin"
        out["filled_bytes"] = fill(filler)
        left = await wait_for(lambda: mgr.get(job.id).state != "running", 60)
        out["left_running_s"] = round(time.monotonic() - t0, 3) if left else None
        paused = mgr.get(job.id)
        out |= {"state_on_full_disk": paused.state, "reason": paused.error}
        out["committed_scans_on_full_disk"] = [s.step_idx for s in store.scans(job.id)]
        out["health_on_full_disk"] = daemon.health()
        out["guard_free_bytes"] = daemon.free_bytes()
        out["guard_needs_bytes"] = daemon.bytes_needed(3)
        filler.unlink()
        await wait_for(lambda: mgr.storage_error is None, 30)
        out["journaled_state_after_space_returned"] = store.get_job(job.id).state
        out["health_after_space_returned"] = daemon.health()["status"]
        await mgr.resume(job.id)
        await wait_for(lambda: mgr.get(job.id).state in ("succeeded", "failed"), 180)
        done = mgr.get(job.id)
        out |= {"final_state": done.state, "final_error": done.error,
                "scan_steps": [s.step_idx for s in store.scans(job.id)],
                "scan_files": sorted(p.name for p in (store.job_dir(job.id) / "scans").iterdir())}
        if done.state == "succeeded":
            report = json.loads((store.job_dir(job.id) / "report.json").read_text())
            out |= {"report_scans": report["scans"], "report_attempts": report["attempts"],
                    "report_resumes": report["resumes"]}
    finally:
        await daemon.close()
    return out


async def events(work: Path) -> dict:
    """Safety events while the journal cannot write: what subscribers and systemd got, what health said, what the
    journal holds once space returns, and every exception the event loop saw unhandled."""
    loop_errors: list[str] = []
    asyncio.get_running_loop().set_exception_handler(lambda loop, ctx: loop_errors.append(ctx["message"]))
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(work / "notify.sock"))
    notify.setblocking(False)
    state = work / "state"
    daemon = Daemon(load_config(), state, notifier=Notifier({"NOTIFY_SOCKET": str(work / "notify.sock")}),
                    connect_timeout_s=30.0)
    await daemon.start()
    out: dict = {}
    sub = daemon.bus.subscribe(maxsize=10000)
    try:
        filler = state / "filler.bin"
        out["filled_bytes"] = fill(filler)
        reasons, published = [], []
        for i in range(40):  # until the journal refuses one (a write may still fit in a page it holds)
            reasons.append(f"operator stop {i}")
            await daemon.supervisor.trip(reasons[-1])
            await daemon.supervisor.reset_safety()
            while len(published) < 2 * len(reasons):  # its stop and its reset
                if (event := await asyncio.wait_for(sub.get(), 5.0)).kind == "safety":
                    published.append(event)
            if daemon.device_events.failed_writes:
                break
        out["published_reasons"] = [e.data["reason"] for e in published if e.data["latched"]]
        out["published_unjournaled"] = sum(e.seq is None for e in published)
        statuses = []
        while True:
            try:
                statuses.append(notify.recv(4096).decode())
            except BlockingIOError:
                break
        out["notified"] = [line for m in statuses for line in m.splitlines() if line.startswith("STATUS=safety")]
        out["health_while_full"] = daemon.health()
        filler.unlink()
        await wait_for(lambda: daemon.device_events.not_journaled == 0, 15)
        out["health_after"] = daemon.health()
        journaled = [e for e in daemon.store.events(0, None, 100000) if e.kind == "safety"]
        out["journaled_reasons"] = [e.data["reason"] for e in journaled if e.data["latched"]]
        out["reasons"] = reasons
    finally:
        sub.close()
        await daemon.close()
        notify.close()
    out["loop_errors"] = loop_errors
    return out


if __name__ == "__main__":
    work = Path(sys.argv[1])
    (work / "state").mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_MB}m", "tmpfs", str(work / "state")], check=True)
    phase = sys.argv[2] if len(sys.argv) > 2 else "scan"
    print(json.dumps(asyncio.run(events(work) if phase == "events" else main(work, phase))))

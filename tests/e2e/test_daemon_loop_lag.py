"""The REST handlers never read the job store on the daemon's event loop, while a job runs and a client hammers them.

A daemon on the simulated cell runs the real job path (journaled runner, scan process) behind uvicorn in this
process. Its journal already holds 100 earlier jobs, each with its plan, so that a page of 100 jobs or a replay
of the event journal is real work: read on the loop, one page decodes about a megabyte of JSON and blocks the
loop for tens of ms on a shared machine (docs/daemon.md, event loop). A child process
(``tests/e2e/loop_lag_hammer.py``, so that the client's own work is not on this loop) cycles ``GET /v1/jobs/{id}``,
``GET /v1/jobs?limit=100``, ``GET /v1/devices`` and an event replay a fixed number of rounds while the job runs.

The store's read methods are instrumented on the daemon's instance (each call still runs the real method) to
record the thread it runs on: none may be the loop's. A behaviour, not a timing: the loop's lag under this load is
a figure of ``benchmarks/daemon.py`` (``event_loop_lag_p99_ms``), never a bound here.
"""

from __future__ import annotations

import asyncio
import functools
import json
import subprocess
import sys
import threading
from collections import Counter
from pathlib import Path

import httpx
from serving import running_server
from tandemscan.daemon.api.app import create_app
from tandemscan.daemon.job_state import JobState
from tandemscan.daemon.plans import PlanCatalog
from tandemscan.daemon.service import Daemon
from tandemscan.daemon.store.job_store import JobStore

TOKEN = "lag-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
ROUNDS = 8
EARLIER_JOBS = 100
# the JobStore methods that read the journal (the handlers' reads; the writes are the runner's)
READS = ("get_job", "list_jobs", "count_by_state", "next_queued", "notes", "resumes", "committed_steps",
         "steps_done", "scans", "damaged_scans", "events", "last_event_seq", "committed_scan_files", "active_jobs")


def _seed(state: Path, default_plan: str) -> None:
    """``EARLIER_JOBS`` cancelled jobs of the default plan in the journal."""
    plan = PlanCatalog([PlanCatalog.shipped_folder()], default_plan).get(None)
    store = JobStore(state)
    try:
        for i in range(EARLIER_JOBS):
            job, _ = store.create_job(plan.name, {"plan": plan.model_dump(mode="json"), "label": f"order {i}"},
                                      len(plan.steps))
            store.set_state(job.id, JobState.CANCELLED)
    finally:
        store.close()


API_PACKAGE = str(Path(create_app.__code__.co_filename).parent)


def _called_from_api() -> bool:
    """Whether a REST handler (a frame of ``tandemscan.daemon.api``) is on the caller's stack: the job's runner
    shares the loop and reads its own step's journal notes there; those are not the handlers' reads."""
    frame = sys._getframe(2)
    while frame is not None:
        if frame.f_code.co_filename.startswith(API_PACKAGE):
            return True
        frame = frame.f_back
    return False


def _record_read_threads(store: JobStore, threads: list[tuple[str, int, bool]]) -> None:
    """Wrap ``store``'s read methods (on this instance) so that each call appends ``(method, thread id, called
    from a handler)`` to ``threads`` and then runs the real method."""
    for name in READS:
        real = getattr(store, name)

        @functools.wraps(real)
        def recorded(*args, _real=real, _name=name, **kwargs):
            threads.append((_name, threading.get_ident(), _called_from_api()))
            return _real(*args, **kwargs)

        setattr(store, name, recorded)


async def _hammered_job(url: str, store: JobStore) -> dict:
    """The client's counts and the store reads (method -> count) made on the loop's thread and off it while the
    child client hammers the handlers during a running job."""
    loop_thread = threading.get_ident()
    async with httpx.AsyncClient(base_url=url, timeout=60) as client:
        job = (await client.post("/v1/jobs", json={}, headers=AUTH)).json()
        for _ in range(500):
            if (await client.get(f"/v1/jobs/{job['id']}")).json()["state"] == JobState.RUNNING:
                break
            await asyncio.sleep(0.02)
        threads: list[tuple[str, int, bool]] = []
        _record_read_threads(store, threads)
        hammer = await asyncio.create_subprocess_exec(
            sys.executable, str(Path(__file__).with_name("loop_lag_hammer.py")), url, job["id"], str(ROUNDS),
            stdout=subprocess.PIPE)
        out, _ = await hammer.communicate()
        after = (await client.get(f"/v1/jobs/{job['id']}")).json()
        state = after["state"]
        if state not in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED):
            await client.post(f"/v1/jobs/{job['id']}/cancel", headers=AUTH)
    counts = json.loads(out.decode().strip().splitlines()[-1])
    return counts | {
        "reads_on_loop": dict(Counter(name for name, t, api in threads if t == loop_thread and api)),
        "runner_reads_on_loop": dict(Counter(name for name, t, api in threads if t == loop_thread and not api)),
        "reads_off_loop": dict(Counter(name for name, t, _ in threads if t != loop_thread)),
        "job_state_after": state, "job_error": after["error"]}


async def test_rest_handlers_under_a_running_job_read_the_store_off_the_event_loop(tmp_path, sim_config):
    state = tmp_path / "state"
    _seed(state, sim_config.daemon.default_plan)
    # the simulated tracker's readings run on this loop (a ray cast for occlusion, the world state saved after
    # each): 30 a side of a coordinate transfer would measure the simulator, not the handlers (a real tracker's
    # reading is a frame off the network), so the transfers here read the target once
    tracker = sim_config.tracker.model_copy(update={"transfer_samples": 1})
    daemon = Daemon(sim_config.model_copy(update={"tracker": tracker}), state, token=TOKEN)
    async with running_server(create_app(daemon, manage_lifecycle=True)) as url:
        figures = await _hammered_job(url, daemon.store)
    print(json.dumps(figures))
    assert figures["errors"] == [] and figures["calls"] == dict.fromkeys(figures["calls"], ROUNDS), figures
    assert figures["job_state_after"] in (JobState.RUNNING, JobState.SUCCEEDED), figures  # a job ran meanwhile
    assert figures["reads_on_loop"] == {}, figures
    # the hammer's routes did read the store (a page, a job, a replay), all of it off the loop
    assert {"list_jobs", "get_job", "events"} <= figures["reads_off_loop"].keys(), figures

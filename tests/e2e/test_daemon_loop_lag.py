"""The REST handlers never block the daemon's event loop: its lag while a job runs and a client hammers them.

A daemon on the simulated cell runs the real job path (journaled runner, scan process) behind uvicorn in this
process. Its journal already holds 100 earlier jobs, each with its plan, so that a page of 100 jobs or a replay
of the event journal is real work: read on the loop, one page decodes about a megabyte of JSON. A child process
(``tests/e2e/loop_lag_hammer.py``, so that the client's own work is not on this loop) cycles ``GET /v1/jobs/{id}``,
``GET /v1/jobs?limit=100``, ``GET /v1/devices`` and an event replay as fast as the daemon answers while the job
runs; a ticker task here records how late the loop wakes it (every 5 ms).

The bound: p99 lag at most 5 ms above the p99 of the floor, the same ticker with the daemon idle and no client.
On a shared 2-core machine the floor is what the other processes alone cost a waking task (scheduler latency);
it is not the handlers' doing, so it is added rather than folded into the 5 ms. A handler that reads the store
on the loop breaks the bound many times over (docs/daemon.md, event loop: a page of jobs read synchronously
blocks the loop for tens of ms on such a machine).
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
from serving import running_server
from tandemscan.daemon.api.app import create_app
from tandemscan.daemon.job_state import JobState
from tandemscan.daemon.plans import PlanCatalog
from tandemscan.daemon.service import Daemon
from tandemscan.daemon.store.job_store import JobStore

TOKEN = "lag-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
TICK_S = 0.005
FLOOR_S = 3.0
HAMMER_S = 15.0
EARLIER_JOBS = 100
BOUND_MS = 5.0


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


async def _tick(samples: list[tuple[float, float]]) -> None:
    """Per sleep of ``TICK_S``: how late the loop wakes this task (s, wall clock) and how much CPU time the loop's
    thread used meanwhile (s): a late wake-up with no CPU used is the machine's doing, not the loop's."""
    while True:
        t0, cpu0 = time.perf_counter(), time.thread_time()
        await asyncio.sleep(TICK_S)
        samples.append((time.perf_counter() - t0 - TICK_S, time.thread_time() - cpu0))


async def _lag_over(seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(wall lag, lag the loop's own work explains: min(wall lag, its CPU time)) of each tick, ms."""
    samples: list[tuple[float, float]] = []
    ticker = asyncio.create_task(_tick(samples))
    await asyncio.sleep(seconds)
    ticker.cancel()
    await asyncio.gather(ticker, return_exceptions=True)
    wall, cpu = np.array(samples).T * 1000.0
    return wall, np.minimum(wall, cpu)


async def _hammered_job(url: str) -> dict:
    """The figures (ms) of an idle floor and of a job hammered by the child client, and the client's counts."""
    async with httpx.AsyncClient(base_url=url, timeout=60) as client:
        floor_wall, _ = await _lag_over(FLOOR_S)
        job = (await client.post("/v1/jobs", json={}, headers=AUTH)).json()
        for _ in range(500):
            if (await client.get(f"/v1/jobs/{job['id']}")).json()["state"] == JobState.RUNNING:
                break
            await asyncio.sleep(0.02)
        hammer = await asyncio.create_subprocess_exec(
            sys.executable, str(Path(__file__).with_name("loop_lag_hammer.py")), url, job["id"], str(HAMMER_S),
            stdout=subprocess.PIPE)
        wall, busy = await _lag_over(HAMMER_S)
        out, _ = await hammer.communicate()
        after = (await client.get(f"/v1/jobs/{job['id']}")).json()
        state = after["state"]
        if state not in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED):
            await client.post(f"/v1/jobs/{job['id']}/cancel", headers=AUTH)
    ms = {"floor_wall_p99": np.percentile(floor_wall, 99), "wall_p50": np.percentile(wall, 50),
          "wall_p99": np.percentile(wall, 99), "busy_p99": np.percentile(busy, 99), "busy_max": busy.max()}
    counts = json.loads(out.decode().strip().splitlines()[-1])
    return {f"{k}_ms": round(float(v), 3) for k, v in ms.items()} | counts | {
        "ticks": len(wall), "job_state_after": state, "job_error": after["error"]}


async def test_rest_handlers_under_a_running_job_keep_the_loop_lag_p99_within_5_ms(tmp_path, sim_config):
    state = tmp_path / "state"
    _seed(state, sim_config.daemon.default_plan)
    # the simulated tracker's readings run on this loop (a ray cast for occlusion, the world state saved after
    # each): 30 a side of a coordinate transfer would measure the simulator, not the handlers (a real tracker's
    # reading is a frame off the network), so the transfers here read the target once
    tracker = sim_config.tracker.model_copy(update={"transfer_samples": 1})
    daemon = Daemon(sim_config.model_copy(update={"tracker": tracker}), state, token=TOKEN)
    async with running_server(create_app(daemon, manage_lifecycle=True)) as url:
        figures = await _hammered_job(url)
    print(json.dumps(figures))
    assert figures["errors"] == [] and min(figures["calls"].values()) >= 5, figures  # the handlers were hammered
    assert figures["job_state_after"] in (JobState.RUNNING, JobState.SUCCEEDED), figures  # a job ran meanwhile
    assert figures["busy_p99_ms"] <= BOUND_MS, figures

"""Ten serials of the as-built default part measured on the simulated cell, each job on a fresh cell of its
own seed, queued through the daemon's facade (what ``POST /v1/jobs`` calls) with its serial number; then each
characteristic's trend as ``GET /v1/parts/{part}/characteristics/{id}/trend`` serves it (docs/quality.md,
"Serials and trends").

The plan is the shipped band plan's first two AGV stations (twelve scans from x -1190 to +490 mm over the
as-built part's bend, its 0.3 mm dent and its bulge, one coordinate transfer), a few minutes a job. Prints
one JSON object last: per characteristic the ten values (mm), their statuses, mean, std, control limits,
Cp/Cpk and drift.

    nice python benchmarks/serial_trend.py [--jobs 10] [--first-seed 7]
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config import load_config
from tandemscan.daemon.api.facade import ServiceFacade
from tandemscan.daemon.api.models import JobRequest, trend_body
from tandemscan.daemon.job_state import FINAL_STATES
from tandemscan.daemon.plans import default_plan_path
from tandemscan.daemon.service import WORLD_STATE_FILE, Daemon
from tandemscan.daemon.store.part_results import PartResults
from tandemscan.pipeline.planning.plan import Plan
from tandemscan.sim_drivers.cell import Simulation, with_surveyed_mounts

AS_BUILT = Path(__file__).resolve().parents[1] / "config" / "as-built-example.toml"
TWO_STATIONS_STEPS = 27  # the band plan's first two stations: their six scans each and the transfer between


async def one_job(state: Path, seed: int, serial: str) -> str:
    """A job on a fresh simulated cell of ``seed`` (the daemon on ``state``); returns its final state."""
    config = load_config(AS_BUILT)
    config = config.model_copy(update={"sim": config.sim.model_copy(update={"seed": seed})})
    (state / WORLD_STATE_FILE).unlink(missing_ok=True)  # a fresh cell: not the last job's world
    daemon = Daemon(with_surveyed_mounts(config, Simulation(config), state.parent / f"mounts-{seed}"), state)
    facade = ServiceFacade(daemon)
    await daemon.start()
    try:
        job, _ = await facade.submit(JobRequest(plan="two-stations", serial_number=serial), None)
        while (final := daemon.manager.get(job.id).state) not in FINAL_STATES:
            await asyncio.sleep(1.0)
    finally:
        await daemon.close()
        facade.close()
    return str(final)


def trends(state: Path, part: str) -> dict:
    """Every characteristic's trend of ``part`` as the REST API serves it (its body)."""
    results = PartResults(state)
    try:
        return {cid: trend_body(results.trend(part, cid)).model_dump(mode="json")
                for cid in results.characteristics(part)}
    finally:
        results.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=7)
    args = parser.parse_args()
    clean_exit_on_sigterm()
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / "state"
        (state / "plans").mkdir(parents=True)
        band = Plan.load(default_plan_path())
        band.model_copy(update={"name": "two-stations", "steps": band.steps[:TWO_STATIONS_STEPS]}).save(
            state / "plans" / "two-stations.toml")
        t0, finals = time.perf_counter(), []
        for k in range(args.jobs):
            finals.append(asyncio.run(one_job(state, args.first_seed + k, f"SN-{k + 1:04d}")))
        seconds = time.perf_counter() - t0
        served = trends(state, "TS-NOSE-3000")
    figures = {"jobs": args.jobs, "job_states": finals, "seconds": round(seconds, 1), "characteristics": {
        cid: {"values": [p["actual_mm"] and round(p["actual_mm"], 4) for p in t["points"]],
              "statuses": [p["status"] for p in t["points"]], "serials": [p["serial"] for p in t["points"]],
              **{k: t[k] if not isinstance(t[k], float) else round(t[k], 4)
                 for k in ("mean_mm", "std_mm", "ucl_mm", "lcl_mm", "cp", "cpk", "drift")}}
        for cid, t in served.items()}}
    publish("serial_trend", figures)


if __name__ == "__main__":
    main()

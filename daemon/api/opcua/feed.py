"""The variables of the address space fed from the daemon: the journaled events SSE streams (job states and
progress, devices, the safety latch) and, ten times a second, what only the supervisor's memory holds (which robot
moves, the safety inputs). See docs/opcua.md.

The feed is one task reading its own bounded subscription of the event bus (a subscriber that falls behind loses
the oldest events, never blocks the publisher) and writing values into the server's address space in memory;
asyncua sends the data changes to each client from its own tasks, so a slow client never holds the loop.
A job's plan, part and serial are read once, off the loop, when it starts.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Iterable

from asyncua import Server, ua
from tandemscan.daemon.api.facade import ServiceFacade
from tandemscan.daemon.api.opcua.model import CellNodes
from tandemscan.daemon.job_state import COMPLETED_STATES, FINAL_STATES, JobState
from tandemscan.daemon.jobs.manager import JobRequestError
from tandemscan.daemon.store.job_store import Event, JobRecord

log = logging.getLogger(__name__)
VT = ua.VariantType
#: how often the supervisor's memory (moving robot, safety inputs) is looked at (s)
POLL_PERIOD_S = 0.1


class CellFeed:
    """Writes the cell's state into ``nodes``; ``on_completed(job_id)`` is called once a job completed (succeeded,
    with gaps or without)."""

    def __init__(self, server: Server, nodes: CellNodes, facade: ServiceFacade,
                 on_completed: Callable[[str], None]):
        self.server, self.nodes, self.facade = server, nodes, facade
        self.on_completed = on_completed
        self._values: dict[str, object] = {}
        self._job_state = ""

    async def write(self, path: str, value, vt: VT) -> None:
        """Set one variable; unchanged values are not written (no data change)."""
        if self._values.get(path, ...) == value:
            return
        self._values[path] = value
        await self.server.write_attribute_value(self.nodes.nodeid(path), ua.DataValue(ua.Variant(value, vt)))

    async def run(self) -> None:
        """Follow the event bus until cancelled: the snapshot first, then every event."""
        with self.facade.subscribe() as sub:
            await self.snapshot()
            poll = asyncio.create_task(self._poll(), name="opcua-poll")
            try:
                while True:
                    await self.apply(await sub.get())
            finally:
                poll.cancel()
                await asyncio.gather(poll, return_exceptions=True)

    async def snapshot(self) -> None:
        """Every variable from the daemon now: devices, latch, the active (or last) job."""
        snap = self.facade.devices()
        for device in snap["devices"]:
            await self.device(device)
        await self.safety(snap["safety"])
        await self.memory()
        job = await self.facade.read(self._last_job)
        if job is not None:
            await self.job(job)

    def _last_job(self) -> JobRecord | None:
        """(store thread) The active job, else the newest one."""
        manager = self.facade.daemon.manager
        if manager.active_id is not None:
            return manager.get(manager.active_id)
        jobs, _ = self.facade.daemon.store.list_jobs(limit=1)
        return manager.current(jobs[0]) if jobs else None

    async def apply(self, ev: Event) -> None:
        """One journaled event into the variables."""
        try:
            if ev.kind == "device":
                await self.device(ev.data)
            elif ev.kind == "safety":
                await self.safety(ev.data)
            elif ev.kind == "progress" and ev.job_id == self._values.get("Production.ActiveJob.JobId"):
                await self.progress(ev.data)
            elif ev.kind == "state" and ev.job_id is not None:
                await self.state(ev.job_id, ev.data)
        except JobRequestError as e:  # the job went away between the event and its read: nothing to show
            log.info("OPC UA feed: %s", e)
        await self.machinery_state()

    async def device(self, d: dict) -> None:
        base = f"Monitoring.Devices.{d['name']}"
        if f"{base}.Connected" not in self.nodes.variables:
            return
        await self.write(f"{base}.Connected", bool(d["connected"]), VT.Boolean)
        await self.write(f"{base}.State", str(d["state"]), VT.String)
        await self.write(f"{base}.LastError", d.get("last_error") or "", VT.String)
        await self.write(f"{base}.Reconnects", int(d.get("reconnects", 0)), VT.UInt32)

    async def safety(self, s: dict) -> None:
        await self.write("Monitoring.Safety.Latched", bool(s["latched"]), VT.Boolean)
        await self.write("Monitoring.Safety.Reason", s.get("reason") or "", VT.String)

    async def progress(self, p: dict) -> None:
        await self.write("Production.ActiveJob.Progress", float(p["progress"]), VT.Double)
        step = p.get("current_step")
        await self.write("Production.ActiveJob.CurrentStep", -1 if step is None else int(step), VT.Int32)

    async def state(self, job_id: str, data: dict) -> None:
        """A job's state change: a job that starts (or is the one shown) becomes the active job."""
        state = data["state"]
        shown = self._values.get("Production.ActiveJob.JobId")
        if job_id != shown and state in (JobState.QUEUED, *FINAL_STATES):
            if state in COMPLETED_STATES:
                self.on_completed(job_id)
            return  # another job queued or ended: the one shown stays
        if job_id != shown:
            await self.job(await self.facade.job_record(job_id))
        else:
            await self.write("Production.ActiveJob.State", state, VT.String)
            await self.write("Production.ActiveJob.Error", data.get("error") or "", VT.String)
        if state in COMPLETED_STATES:
            await self.write("Production.ActiveJob.Progress", 100.0, VT.Double)
            self.on_completed(job_id)

    async def job(self, job: JobRecord) -> None:
        """Show ``job`` as the active one."""
        await self.write("Production.ActiveJob.JobId", job.id, VT.String)
        await self.write("Production.ActiveJob.State", str(job.state), VT.String)
        await self.write("Production.ActiveJob.Progress", float(job.progress), VT.Double)
        await self.write("Production.ActiveJob.CurrentStep", -1 if job.current_step is None else job.current_step,
                         VT.Int32)
        await self.write("Production.ActiveJob.StepsTotal", int(job.n_steps), VT.Int32)
        await self.write("Production.ActiveJob.Plan", job.plan_name, VT.String)
        await self.write("Production.ActiveJob.PartNumber", job.plan.get("part_number") or "", VT.String)
        await self.write("Production.ActiveJob.SerialNumber", job.plan.get("serial_number") or "", VT.String)
        await self.write("Production.ActiveJob.Error", job.error or "", VT.String)

    async def _poll(self) -> None:
        while True:
            await asyncio.sleep(POLL_PERIOD_S)
            await self.memory()

    async def memory(self) -> None:
        """What has no event: the robot moving, the safety inputs, the connection summary."""
        snap = self.facade.devices()
        await self.write("Monitoring.MovingRobot", ",".join(snap["moving"]), VT.String)
        await self.write("Monitoring.AllConnected", bool(snap["all_connected"]), VT.Boolean)
        inputs = self.facade.safety_inputs()
        if inputs is not None:
            await self.write("Monitoring.Safety.EStop", bool(inputs.estop), VT.Boolean)
            await self.write("Monitoring.Safety.LightCurtainBroken", bool(inputs.light_curtain_broken), VT.Boolean)
        await self.machinery_state()

    async def machinery_state(self) -> None:
        """OPC 40001-1's MachineryItemState of the cell from what the feed shows."""
        v = self._values
        if not v.get("Monitoring.AllConnected") or v.get("Monitoring.Safety.Latched"):
            state = "OutOfService"
        elif v.get("Production.ActiveJob.State") == JobState.RUNNING:
            state = "Executing"
        else:
            state = "NotExecuting"
        await self.write("Monitoring.MachineryItemState", state, VT.String)


def device_names(facade: ServiceFacade) -> Iterable[str]:
    """The cell's device names, as the supervisor knows them."""
    return [d["name"] for d in facade.devices()["devices"]]

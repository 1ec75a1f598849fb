"""The supervisor on the simulated cell: connection and health, reconnects, the safety latch, the motion gate."""

from __future__ import annotations

import asyncio
import random

import numpy as np
import pytest
from tandemscan.daemon.cell.devices import Cell
from tandemscan.daemon.cell.motion import Robot
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.cell.supervisor import MotionInterlock, backoff_delays
from tandemscan.drivers.errors import NotConnected, SafetyStop
from tandemscan.drivers.factory import ROLES
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.sim_drivers.cell import Simulation
from tandemscan.sim_drivers.world import SimWorld


@pytest.fixture(scope="module")
def slow_world():
    """Motion in real time (time_scale 1): a 3 m chassis move takes 10 s."""
    from tandemscan.config import load_config

    cfg = load_config()
    return SimWorld(cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"time_scale": 1.0})}))


@pytest.fixture
async def sup(slow_world):
    slow_world.safety.estop = False
    slow_world.motion.violations.clear()
    events = []
    sim = Simulation(slow_world.config, world=slow_world)
    twins = {role: sim.device(role) for role in ROLES}  # the supervisor's gate alone: the test moves the twins
    cell = Cell(**twins, simulation=sim)
    s = CellSession(slow_world.config, cell=cell, on_event=lambda k, d: events.append((k, d))).supervisor
    s.reconnect_initial_s = 0.05
    s.health_period_s = 0.05
    await s.start()
    s.cell, s.twins, s.events = cell, twins, events
    yield s
    await s.close()


def start_long_tracker_move(sup) -> asyncio.Task:
    """The tracking chassis driving 3 m (10 s) through the motion gate, as a task."""
    chassis = sup.twins["tracking_chassis"]

    async def move():
        async with sup.motion(Robot.TRACKING):
            o = await chassis.odometry()
            await chassis.move_to(ChassisPose(o.x_mm + 3000.0, o.y_mm, o.heading_rad))

    return asyncio.create_task(move())


async def test_connects_every_device(sup):
    await sup.wait_connected(10.0)  # only against a hang
    snap = sup.snapshot()
    assert snap["all_connected"] and len(snap["devices"]) == 6 and snap["moving"] == []
    assert not snap["safety"]["latched"]


async def test_estop_halts_motion_mid_move(sup, slow_world):
    chassis = sup.twins["tracking_chassis"]
    real_elapse, travelled_s = chassis._elapse, []

    async def elapse(seconds: float) -> None:  # the twin's own wait runs; what ran to its end is recorded
        await real_elapse(seconds)
        travelled_s.append(seconds)

    chassis._elapse = elapse
    task = start_long_tracker_move(sup)
    await asyncio.sleep(0.1)
    assert sup.moving_robots == [Robot.TRACKING]
    slow_world.safety.estop = True
    with pytest.raises(SafetyStop, match="e-stop"):
        await task
    assert travelled_s == []  # the 10 s move was cut by the safety poll, not finished and then refused
    assert sup.moving_robots == [] and sup.latched_reason == "e-stop pressed"
    assert ("safety", {"latched": True, "reason": "e-stop pressed"}) in sup.events


async def test_motion_refused_while_latched_and_reset_needs_clear_inputs(sup, slow_world):
    slow_world.safety.light_curtain_broken = True
    try:
        async with asyncio.timeout(10):  # only against a hang: the safety poll latches it, however late it runs
            while not sup.latched_reason:
                await asyncio.sleep(0.01)
        assert sup.latched_reason == "light curtain broken"
        with pytest.raises(SafetyStop, match="latched"):
            async with sup.motion(Robot.MEASURE):
                pass
        with pytest.raises(SafetyStop, match="cannot reset"):
            await sup.reset_safety()
    finally:
        slow_world.safety.light_curtain_broken = False
    await sup.reset_safety()
    async with sup.motion(Robot.MEASURE):
        assert sup.moving_robots == [Robot.MEASURE]


async def test_never_both_robots_moving(sup, slow_world):
    task = start_long_tracker_move(sup)
    await asyncio.sleep(0.05)
    with pytest.raises(MotionInterlock, match="measure robot may not move while tracking robot is moving"):
        async with sup.motion(Robot.MEASURE):
            await sup.twins["arm"].move_joints(await sup.cell.arm.joints())
    async with sup.motion(Robot.TRACKING):  # the same robot's other devices may go on
        pass
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert slow_world.motion.violations == []
    with pytest.raises(ValueError, match="unknown robot"):
        async with sup.motion("crane"):
            pass


async def test_device_safety_stop_latches_the_cell(sup, slow_world):
    slow_world.safety.estop = True  # the twin refuses before the poll notices
    with pytest.raises(SafetyStop):
        async with sup.motion(Robot.MEASURE):
            await sup.twins["arm"].move_joints(np.zeros(6))
    assert sup.latched_reason is not None


async def test_dropped_device_is_reconnected(sup):
    await sup.cell.tracker.close()
    h = await sup.poll_device("tracker")
    assert not h.connected and not sup.all_connected
    assert ("device", h.as_dict()) in sup.events or any(k == "device" and not d["connected"] for k, d in sup.events)
    await sup.wait_connected(2.0)
    assert sup.health["tracker"].connected and sup.health["tracker"].reconnects >= 1


def test_backoff_doubles_to_a_cap():
    delays = backoff_delays(0.5, 4.0, jitter=0.0)
    assert [next(delays) for _ in range(6)] == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    jittered = backoff_delays(1.0, 8.0, jitter=0.1, rng=random.Random(1))
    first = [next(jittered) for _ in range(4)]
    assert all(0.9 * b <= d <= 1.1 * b for d, b in zip(first, [1, 2, 4, 8], strict=True))


async def test_a_task_that_swallows_one_cancel_is_still_stopped():
    from tandemscan.drivers.tasks import cancel_and_wait

    swallowed = []

    async def stubborn():  # what a wait_for race in Python 3.11 does to a loop task
        while True:
            try:
                await asyncio.sleep(0.01)
            except asyncio.CancelledError:
                if swallowed:
                    raise
                swallowed.append(True)
                asyncio.current_task().uncancel()

    task = asyncio.create_task(stubborn())
    await asyncio.sleep(0.02)
    await asyncio.wait_for(cancel_and_wait(task, None, retry_s=0.05), 5)
    assert task.cancelled() and swallowed == [True]


async def test_a_robot_whose_device_is_down_may_not_move_until_it_is_reconnected(sup):
    chassis = sup.twins["tracking_chassis"]
    await chassis.close()
    assert not (await sup.poll_device(chassis.name)).up  # a reconnect is now scheduled
    with pytest.raises(NotConnected, match=f"motion refused: tracking robot's {chassis.name} is down"):
        async with sup.motion(Robot.TRACKING):
            pass
    async with sup.motion(Robot.MEASURE):  # the other robot's devices are up
        pass
    await sup.wait_connected(2.0)
    async with sup.motion(Robot.TRACKING):
        assert sup.moving_robots == [Robot.TRACKING]


async def test_opening_a_session_takes_the_live_heap_out_of_the_collectors_full_scans():
    """A full collection scans every tracked object (about 80 ms for the daemon's imported stack, a stall of the
    50 Hz control loop): the session freezes what is alive when it opens, before the loop runs."""
    import gc

    from tandemscan.config import load_config

    gc.unfreeze()
    alive = [{"a container": "alive across the open"}]
    session = CellSession(load_config())
    await session.open()
    try:
        assert gc.get_freeze_count() > 0
        scanned = {id(o) for o in gc.get_objects(generation=2)}
        assert id(alive) not in scanned and id(alive[0]) not in scanned
    finally:
        await session.close()
    assert gc.get_freeze_count() == 0  # thawed at close: the closed session's reference cycles are collectable

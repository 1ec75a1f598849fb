"""Hardware-in-the-loop: the Modbus safety I/O driver against pymodbus' server on 127.0.0.1."""

from __future__ import annotations

import asyncio
import re
import time

import pytest
from tandemscan.config.models import SafetyConfig, SafetyModbusConfig
from tandemscan.daemon.cell.supervisor import Supervisor
from tandemscan.drivers import DeviceFault, DeviceTimeout, NotConnected, SafetyIO, SafetyState, SafetyStop
from tandemscan.drivers.interfaces import PushesSafetyChanges
from tandemscan.drivers.safety_modbus import ModbusSafetyIO
from tandemscan.sim_drivers.emulators.safety_modbus import SafetyIoEmulator

# normally-closed e-stop chain on input 4, light curtain on input 2, light on coil 3
WIRING = dict(estop_input=4, estop_active_high=False, light_curtain_input=2, target_light_coil=3, beacon_coil=5,
              device_id=2, timeout_s=0.3)


@pytest.fixture
async def emulator():
    emu = SafetyIoEmulator(SafetyModbusConfig(**WIRING))
    await emu.start()
    await emu.press_estop(False)
    yield emu
    await emu.stop()


@pytest.fixture
async def io(emulator):
    drv = ModbusSafetyIO(SafetyConfig(poll_period_s=0.02,
                                      modbus=SafetyModbusConfig(host="127.0.0.1", port=emulator.port, **WIRING)))
    await drv.connect()
    yield drv
    await drv.close()


async def wait_for_state(io: ModbusSafetyIO, predicate, timeout_s: float = 1.0) -> SafetyState:
    deadline = time.monotonic() + timeout_s
    while True:
        state = await io.read()
        if predicate(state) or time.monotonic() > deadline:
            return state
        await asyncio.sleep(0.01)


async def test_inputs_polled_and_listeners_hear_changes(emulator, io):
    assert isinstance(io, SafetyIO)
    heard: list[SafetyState] = []
    io.add_listener(heard.append)
    assert (await io.read()).motion_allowed
    await emulator.press_estop()
    state = await wait_for_state(io, lambda s: s.estop)
    assert state.estop and not state.motion_allowed
    await emulator.press_estop(False)
    await emulator.break_light_curtain()
    state = await wait_for_state(io, lambda s: s.light_curtain_broken and not s.estop)
    assert state.light_curtain_broken and not state.estop
    assert heard[0].estop and heard[-1].light_curtain_broken
    assert (await io.status()).state == "stopped"


async def test_target_light_and_beacon_outputs(emulator, io):
    await io.set_target_light(True)
    assert await emulator.coil(3)
    await io.set_beacon(True)
    assert await emulator.coil(5)
    assert (await wait_for_state(io, lambda s: s.target_light_on)).target_light_on
    await io.set_target_light(False)
    assert not await emulator.coil(3)


async def first_safety_stop(io: ModbusSafetyIO) -> str:
    """Read ``io`` until a read is refused with :class:`SafetyStop`: its reason (the timeout only against a hang)."""
    async with asyncio.timeout(5):
        while True:
            try:
                await io.read()
            except SafetyStop as e:
                return e.reason
            await asyncio.sleep(0.005)


async def test_exception_reply_is_fault_and_counts_as_safety_stop(emulator, io):
    emulator.faults.exception_replies = True
    with pytest.raises(DeviceFault, match="safety: write target light: exception response"):
        await io.set_target_light(True)
    assert re.search("link lost.*exception response", await first_safety_stop(io))
    assert (await io.status()).state == "fault"


async def test_silent_module_times_out_and_reads_as_safety_stop(emulator, io):
    heard: list[SafetyState] = []
    io.add_listener(heard.append)
    emulator.faults.silent = True
    with pytest.raises(DeviceTimeout, match="no reply within 0.3 s"):
        await io.set_beacon(True)
    await asyncio.sleep(0.4)
    with pytest.raises(SafetyStop):
        await io.read()
    assert heard and heard[-1].estop  # listeners were told to stop motion


async def test_lost_connection_is_safety_stop_then_reconnect(emulator, io):
    await emulator.restart()
    await asyncio.sleep(0.2)
    with pytest.raises(SafetyStop, match="link lost"):
        await io.read()
    await io.connect()
    assert (await io.read()).motion_allowed


async def test_no_module_and_not_connected():
    drv = ModbusSafetyIO(SafetyConfig(modbus=SafetyModbusConfig(host="127.0.0.1", port=1, timeout_s=0.3)))
    with pytest.raises(NotConnected):
        await drv.read()
    with pytest.raises(NotConnected, match="cannot connect"):
        await drv.connect()
    await drv.close()


async def test_stack_light_outputs_are_holding_registers():
    """PATLITE-style: one holding register per tier, the configured value for on, 0 for off."""
    wiring = dict(WIRING, target_light_output="holding_register", target_light_coil=0, target_light_on_value=0x0101,
                  beacon_output="holding_register", beacon_coil=2, beacon_on_value=0x0102)
    emu = SafetyIoEmulator(SafetyModbusConfig(**wiring))
    await emu.start()
    await emu.press_estop(False)
    drv = ModbusSafetyIO(SafetyConfig(poll_period_s=0.02,
                                      modbus=SafetyModbusConfig(host="127.0.0.1", port=emu.port, **wiring)))
    try:
        await drv.connect()
        assert not (await drv.read()).target_light_on
        await drv.set_target_light(True)
        await drv.set_beacon(True)
        assert await emu.register(0) == 0x0101 and await emu.register(2) == 0x0102
        assert not await emu.coil(0)  # nothing went to the coils
        await drv.set_target_light(False)
        assert await emu.register(0) == 0
        await drv.set_target_light(True)
        await drv.connect()  # the light's state is read back from its register
        assert (await drv.read()).target_light_on
    finally:
        await drv.close()
        await emu.stop()


async def test_a_silent_module_is_a_safety_stop_before_its_request_times_out(emulator, io):
    """The poll in flight unanswered for two poll periods: read() stops, while the request still waits (0.3 s)."""
    await io.read()
    emulator.faults.silent = True
    reason = await first_safety_stop(io)
    assert reason.startswith("safety I/O silent")  # the stale poll, not the request timing out (link lost)
    emulator.faults.silent = False
    await io.connect()
    assert (await io.read()).motion_allowed


async def test_the_module_answers_while_the_drivers_event_loop_is_held_up(emulator, io):
    """The emulated module is hardware of its own (its own event loop and thread): a poll sent just before the
    driver's event loop is held up (blocking work in the daemon, 0.12 s) is answered meanwhile, so the first read
    after the stall finds the reply, not a module silent for 0.12 s. Ten times."""
    for _ in range(10):
        await io.read()
        while io._poll_sent_at is None:  # a poll in flight, the module not yet asked
            await asyncio.sleep(0)
        time.sleep(0.12)  # the loop held up, six poll periods
        assert (await io.read()).motion_allowed


async def test_the_supervisor_rides_out_a_stalled_event_loop_and_latches_on_a_silent_module(emulator, io):
    """A stall of the supervisor's own event loop (a garbage collection, a starved CPU: 0.12 s here, thirty
    times) delays the poll's reply and the supervisor's read alike; it is not a silent module and latches
    nothing. A module that stays silent latches the cell within a few control periods."""
    sup = Supervisor([], {}, io, control_period_s=0.02)
    await sup.start()
    try:
        for k in range(30):
            time.sleep(0.12)  # the loop blocked, as by a long garbage collection
            await asyncio.sleep(0.005 * (1 + k % 7))  # at every phase of the poll
        assert sup.latched_reason is None
        emulator.faults.silent = True
        async with asyncio.timeout(2):
            while sup.latched_reason is None:
                await asyncio.sleep(0.005)
        # the stale poll, before the request's own timeout (which would be "no reply within 0.3 s")
        assert sup.latched_reason.startswith("safety I/O unreadable: safety: safety I/O silent")
    finally:
        emulator.faults.silent = False
        await sup.close()


async def test_the_supervisor_latches_an_estop_as_the_module_pushes_it_not_at_its_next_tick(emulator, io):
    """The driver polls at 20 ms and pushes each change; the supervisor, whose control period here is 600 s (no tick
    in the test's life after the first), reads the safety I/O as the change arrives and latches, without counting
    the read as a control tick."""
    assert isinstance(io, PushesSafetyChanges)
    sup = Supervisor([], {}, io, control_period_s=600.0)
    await sup.start()
    try:
        await asyncio.sleep(0.1)
        await emulator.press_estop()
        async with asyncio.timeout(3):
            while sup.latched_reason is None:
                await asyncio.sleep(0.005)
        assert sup.latched_reason == "e-stop pressed"
        assert len(sup.control_lateness_s) == 0  # latched on the pushed change: no control tick (600 s) yet
    finally:
        await emulator.press_estop(False)
        await sup.close()


async def test_a_link_lost_before_the_first_control_tick_still_latches_the_cell(emulator, io):
    """The lost link is pushed (as an e-stop state) before the supervisor's first tick, and the read it wakes
    fails: the loop reads again at its tick and latches; it does not end."""
    sup = Supervisor([], {}, io, control_period_s=0.5)
    await sup.start()
    try:
        await emulator.restart()  # drops the connection at once
        async with asyncio.timeout(3):
            while sup.latched_reason is None:
                await asyncio.sleep(0.01)
        assert "link lost" in sup.latched_reason
        assert not any(t.done() for t in sup._tasks)  # the safety loop runs on
    finally:
        await sup.close()

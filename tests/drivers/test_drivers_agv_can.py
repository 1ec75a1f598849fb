"""Hardware-in-the-loop: the CAN chassis driver against the chassis emulator on a python-can virtual bus."""

from __future__ import annotations

import asyncio
import math
import time
import uuid

import numpy as np
import pytest
from tandemscan.config.models import ChassisCanConfig, ChassisConfig
from tandemscan.daemon.cell.supervisor import Supervisor
from tandemscan.drivers import Chassis, ChassisPose, DeviceError, DeviceFault, DeviceTimeout, NotConnected, SafetyStop
from tandemscan.drivers.agv_can import AgvCanChassis
from tandemscan.drivers.can_link import load_dbc
from tandemscan.sim_drivers.emulators.agv_can import ChassisEmulator


async def wait_until(predicate, timeout_s: float = 2.0) -> None:
    """Poll ``predicate`` until true (loaded CI machines schedule late); fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        await asyncio.sleep(0.01)


def chassis_config(channel: str, **can_kw) -> ChassisConfig:
    return ChassisConfig(can=ChassisCanConfig(interface="virtual", channel=channel, **can_kw), timeout_s=10.0)


@pytest.fixture
async def emulator():
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = ChassisEmulator(chassis_config(channel), channel, time_scale=0.1, seed=3)
    await emu.start()
    yield emu
    await emu.stop()


@pytest.fixture
async def chassis(emulator):
    drv = AgvCanChassis(chassis_config(emulator._link.channel), name="measure_chassis")
    await drv.connect()
    yield drv
    await drv.close()


def test_dbc_is_big_endian_agilex_v2_layout():
    db = load_dbc()
    cmd = db.get_message_by_frame_id(0x111)
    data = cmd.encode({"LinearVelocity": -300, "AngularVelocity": 0.5, "LateralVelocity": 0, "SteeringAngle": 0})
    assert data == bytes.fromhex("fed401f400000000")
    assert db.get_message_by_frame_id(0x421).name == "ControlModeSet"
    odo = db.get_message_by_frame_id(0x311).decode(bytes.fromhex("0000 1000 ffff fff0"))
    assert odo == {"LeftWheelOdometry": 4096, "RightWheelOdometry": -16}


async def test_connect_enters_can_mode_and_heartbeat_runs(emulator, chassis):
    assert isinstance(chassis, Chassis)
    assert emulator.mode == 1
    before = emulator.commands_received
    await wait_until(lambda: emulator.commands_received - before >= 10)  # the heartbeat keeps coming
    assert not emulator.watchdog_tripped
    assert (await chassis.status()).state == "idle"


async def test_move_to_pose_closed_loop_on_odometry(emulator, chassis):
    target = ChassisPose(400.0, -150.0, math.radians(30.0))
    pose = await chassis.move_to(target)
    assert math.hypot(pose.x_mm - target.x_mm, pose.y_mm - target.y_mm) <= 5.0
    assert abs(pose.heading_rad - target.heading_rad) <= math.radians(0.5)
    assert await chassis.odometry() == pose
    # the body slipped: the truth is near the target but not on it
    truth = emulator.true_pose
    err = math.hypot(truth.x_mm - target.x_mm, truth.y_mm - target.y_mm)
    assert 0.0 < err < 40.0
    await asyncio.sleep(0.1)
    assert emulator.velocity == (0.0, 0.0)
    back = await chassis.move_to(ChassisPose(0.0, 0.0, 0.0))  # behind the chassis: it reverses
    assert math.hypot(back.x_mm, back.y_mm) <= 5.0


async def test_estop_during_move_zeroes_velocity_and_raises(emulator, chassis):
    move = asyncio.create_task(chassis.move_to(ChassisPose(3000.0, 0.0, 0.0)))
    await wait_until(lambda: emulator.velocity[0] > 0)
    emulator.faults.estop = True
    with pytest.raises(SafetyStop, match="measure_chassis.*emergency stop"):
        await move
    stopped_at = emulator.true_pose
    assert stopped_at.x_mm < 3000.0 - 40.0  # the e-stop ended the move short of its target (beyond the slip, above)
    assert chassis._setpoint == (0.0, 0.0)
    await wait_until(lambda: emulator.command == (0.0, 0.0))  # the zero command reaches the chassis
    assert emulator.velocity == (0.0, 0.0) and emulator.true_pose == stopped_at  # and the body stays there
    with pytest.raises(SafetyStop):  # a standing e-stop refuses the next move
        await chassis.move_to(ChassisPose(100.0, 0.0, 0.0))
    emulator.faults.estop = False
    await chassis.move_to(ChassisPose(100.0, 0.0, 0.0))


async def test_stop_aborts_a_move_at_once(emulator, chassis):
    move = asyncio.create_task(chassis.move_to(ChassisPose(3000.0, 0.0, 0.0)))
    await wait_until(lambda: emulator.velocity[0] > 0)
    await chassis.stop()
    with pytest.raises(SafetyStop, match="stop requested"):
        await move
    await wait_until(lambda: emulator.command == (0.0, 0.0))  # the zero command reaches the chassis


@pytest.mark.parametrize(
    ("fault", "value", "match"),
    [
        ("error_code", 0x0100, "0x0100: motor driver"),
        ("driver_state", 0x02, "motor 1 driver: motor overheat"),
        ("rc_override", True, "left CAN mode"),
        ("bad_dlc_next", True, "DLC 3, expected 8"),
    ],
)
async def test_chassis_faults_become_typed_errors(emulator, chassis, fault, value, match):
    move = asyncio.create_task(chassis.move_to(ChassisPose(3000.0, 0.0, 0.0)))
    await wait_until(lambda: emulator.velocity[0] > 0)
    setattr(emulator.faults, fault, value)
    with pytest.raises(DeviceFault, match=match):
        await move  # the fault ends it (the chassis' own 10 s timeout bounds it)
    assert chassis._setpoint == (0.0, 0.0)
    assert (await chassis.status()).state == "fault"


async def test_silent_chassis_is_link_loss_within_feedback_timeout(emulator, chassis):
    move = asyncio.create_task(chassis.move_to(ChassisPose(3000.0, 0.0, 0.0)))
    await asyncio.sleep(0.1)
    emulator.faults.silent = True
    with pytest.raises(DeviceTimeout, match="no (feedback|status frame)"):  # the watchdog, not the move's 10 s
        await move
    emulator.faults.silent = False
    await chassis.close()
    await chassis.connect()  # reconnect after the link came back
    await chassis.move_to(ChassisPose(50.0, 0.0, 0.0))


async def test_chassis_watchdog_stops_when_host_goes_quiet(emulator, chassis):
    move = asyncio.create_task(chassis.move_to(ChassisPose(5000.0, 0.0, 0.0)))
    await wait_until(lambda: emulator.velocity[0] > 0)
    emulator.faults.ignore_commands = True  # as if the host's frames stopped arriving
    await wait_until(lambda: emulator.watchdog_tripped, timeout_s=10.0)  # only against a hang, however late
    assert emulator.velocity == (0.0, 0.0)
    move.cancel()
    with pytest.raises(asyncio.CancelledError):
        await move
    assert chassis._setpoint == (0.0, 0.0)


async def test_dropped_feedback_frames_still_arrive(emulator, chassis):
    emulator.faults.drop_feedback_fraction = 0.3
    pose = await chassis.move_to(ChassisPose(200.0, 0.0, 0.0))
    assert abs(pose.x_mm - 200.0) <= 5.0


async def test_move_timeout_stops(emulator, chassis):
    with pytest.raises(DeviceTimeout, match="not finished within 0.2 s"):
        await chassis.move_to(ChassisPose(10000.0, 0.0, 0.0), timeout_s=0.2)
    await wait_until(lambda: emulator.command == (0.0, 0.0))  # the zero command reaches the chassis


async def test_no_chassis_on_the_bus_times_out_and_calls_need_a_link():
    drv = AgvCanChassis(chassis_config(f"empty-{uuid.uuid4().hex[:8]}", feedback_timeout_s=0.2))
    with pytest.raises(NotConnected):
        await drv.odometry()
    with pytest.raises(DeviceTimeout, match="did not enter CAN mode.*no status frame"):
        await drv.connect()
    assert (await drv.status()).state == "disconnected"
    await drv.close()


async def test_a_failed_reconnect_keeps_the_cause_for_the_next_call(emulator, chassis):
    """The supervisor's reconnect of a silent chassis fails; the step's next call names the silence (a timeout),
    not a bare "not connected", and a connect once the chassis talks again clears it."""
    emulator.faults.silent = True
    await chassis.close()
    with pytest.raises(DeviceTimeout, match="did not enter CAN mode"):
        await chassis.connect()
    with pytest.raises(DeviceTimeout, match="did not enter CAN mode"):
        await chassis.odometry()
    with pytest.raises(DeviceTimeout):
        await chassis.move_to(ChassisPose(50.0, 0.0, 0.0))
    emulator.faults.silent = False
    await chassis.connect()
    await chassis.odometry()


async def test_odometry_frame_survives_reconnect(emulator, chassis):
    await chassis.move_to(ChassisPose(150.0, 0.0, 0.0))
    before = await chassis.odometry()
    await chassis.close()
    await chassis.connect()
    await asyncio.sleep(0.1)
    after = await chassis.odometry()
    assert np.allclose([after.x_mm, after.y_mm, after.heading_rad], [before.x_mm, before.y_mm, before.heading_rad])


# ---------------------------------------------------------------- vendor behaviour (issue 15)


async def vendor_pair(channel: str, **emu_kw):
    """An emulator whose motor drivers report 0x40 ("driver enabled") in normal running, and its driver."""
    emu = ChassisEmulator(chassis_config(channel), channel, time_scale=0.1, seed=3, driver_state_flags=0x40, **emu_kw)
    await emu.start()
    return emu


async def test_driver_enabled_flag_is_state_not_a_fault():
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = await vendor_pair(channel)
    drv = AgvCanChassis(chassis_config(channel))
    try:
        await drv.connect()
        await drv.move_to(ChassisPose(200.0, 0.0, 0.0))  # 0x40 on every motor, all the way
        assert (await drv.status()).state == "idle"
        move = asyncio.create_task(drv.move_to(ChassisPose(3000.0, 0.0, 0.0)))
        await wait_until(lambda: emu.velocity[0] > 0)
        emu.faults.driver_state = 0x04  # a real fault beside the state flag
        with pytest.raises(DeviceFault, match="motor 1 driver: overload$"):
            await move  # the fault ends it (the chassis' own 10 s timeout bounds it)
    finally:
        await drv.close()
        await emu.stop()


async def test_a_low_supply_voltage_is_a_warning_that_drives_on_and_clears(caplog):
    """DriverState 0x01 (supply voltage low, as under acceleration on a part-charged battery) does not stop a move:
    the status lists it while the drivers report it and the log says so once; a fault bit beside it still does."""
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = await vendor_pair(channel)
    drv = AgvCanChassis(chassis_config(channel))
    try:
        await drv.connect()
        emu.faults.driver_state = 0x01
        await drv.move_to(ChassisPose(200.0, 0.0, 0.0))
        status = await drv.status()
        assert status.state == "idle" and status.detail["warnings"] == ["motor 1 driver: supply voltage low"]
        assert sum("supply voltage low" in r.getMessage() for r in caplog.records) == 1
        emu.faults.driver_state = 0
        await wait_until(lambda: not drv._warnings)
        assert (await drv.status()).detail["warnings"] == []
        move = asyncio.create_task(drv.move_to(ChassisPose(3000.0, 0.0, 0.0)))
        await wait_until(lambda: emu.velocity[0] > 0)
        emu.faults.driver_state = 0x03
        with pytest.raises(DeviceFault, match="motor 1 driver: motor overheat$"):
            await move  # the fault ends it (the chassis' own 10 s timeout bounds it)
    finally:
        await drv.close()
        await emu.stop()


async def test_a_count_of_encoder_noise_at_standstill_is_rest_not_motion():
    """A chassis whose motion state shows 1 mm/s while it stands still (its encoders' speed): the move ends
    and the chassis reads idle; a driver that waited for exactly zero would wait for ever (here: its timeout)."""
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = await vendor_pair(channel, standstill_speed_mm_s=1.0)
    drv = AgvCanChassis(chassis_config(channel))
    strict = AgvCanChassis(chassis_config(channel, standstill_mm_s=0.0))
    try:
        await drv.connect()
        pose = await drv.move_to(ChassisPose(200.0, 0.0, 0.0))
        assert abs(pose.x_mm - 200.0) <= 5.0
        assert (await drv.status()).state == "idle"
        await drv.close()
        await strict.connect()
        assert (await strict.status()).state == "moving"
        with pytest.raises(DeviceTimeout, match="still moving"):
            await strict.move_to(ChassisPose(300.0, 0.0, 0.0))
    finally:
        await drv.close()
        await strict.close()
        await emu.stop()


async def test_odometry_counts_are_scaled_by_the_configured_unit():
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = await vendor_pair(channel, odometry_mm_per_count=0.1)  # counts of 0.1 mm
    drv = AgvCanChassis(chassis_config(channel, odometry_mm_per_count=0.1))
    try:
        await drv.connect()
        pose = await drv.move_to(ChassisPose(300.0, 0.0, 0.0))
        assert abs(pose.x_mm - 300.0) <= 5.0
        assert abs(emu.true_pose.x_mm - 300.0) < 20.0  # the body went 300 mm, not 30 or 3000
    finally:
        await drv.close()
        await emu.stop()


async def test_uart_control_mode_is_named(emulator, chassis):
    emulator.mode = 2
    with pytest.raises(DeviceFault, match=r"left CAN mode \(UART has control\)"):
        await chassis.move_to(ChassisPose(100.0, 0.0, 0.0))


async def test_approach_decelerates_to_the_target_and_reports_the_residual():
    """The move does not stop at the edge of the tolerance (5 mm short every time before): the residual is
    well inside it. Emulated time runs at 2x here; much faster, one 20 ms control period covers more travel
    than on a real chassis and overshoot hides where the approach stops."""
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = ChassisEmulator(chassis_config(channel), channel, time_scale=0.5, seed=3, driver_state_flags=0x40)
    await emu.start()
    drv = AgvCanChassis(chassis_config(channel))
    tol = drv._can.position_tolerance_mm
    try:
        await drv.connect()
        for target in (ChassisPose(60.0, 0.0, 0.0), ChassisPose(0.0, 0.0, 0.0)):
            pose = await drv.move_to(target)
            residual = math.hypot(pose.x_mm - target.x_mm, pose.y_mm - target.y_mm)
            assert drv.last_residual_mm == pytest.approx(residual)
            assert residual < 0.5 * tol
            assert (await drv.status()).detail["last_residual_mm"] == pytest.approx(residual)
    finally:
        await drv.close()
        await emu.stop()


async def test_a_chassis_reporting_no_host_until_commanded_connects_and_a_lapse_after_is_a_fault():
    """A chassis may report error 0x0200 (host communication: no motion command within its 500 ms watchdog) from
    its boot until the first command arrives: connect() takes it to CAN mode all the same and the heartbeat clears
    it. Once the chassis has heard the host, the same report (its commands lost) is a fault."""
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = ChassisEmulator(chassis_config(channel), channel, time_scale=0.1, seed=3, reports_host_timeout=True)
    await emu.start()
    drv = AgvCanChassis(chassis_config(channel), name="measure_chassis")
    try:
        await drv.connect()
        pose = await drv.move_to(ChassisPose(100.0, 0.0, 0.0))
        assert math.hypot(pose.x_mm - 100.0, pose.y_mm) <= 5.0
        emu.faults.ignore_commands = True  # the chassis stops hearing the host
        async with asyncio.timeout(5):
            while (await drv.status()).state != "fault":
                await asyncio.sleep(0.01)
        assert "host communication" in (await drv.status()).detail["fault"]
        with pytest.raises(DeviceFault, match="host communication"):
            await drv.move_to(ChassisPose(0.0, 0.0, 0.0))
    finally:
        await drv.close()
        await emu.stop()


# ---------------------------------------------------------------- a lost link, RC lost, odometry wrap


@pytest.fixture
async def created_tasks():
    """Every task the running loop creates during the test (to see how each one ended)."""
    loop = asyncio.get_running_loop()
    created: list[asyncio.Task] = []
    previous = loop.get_task_factory()

    def recording(loop, coro, **kw):
        task = asyncio.Task(coro, loop=loop, **kw)
        created.append(task)
        return task

    loop.set_task_factory(recording)
    yield created
    loop.set_task_factory(previous)


async def test_link_drops_during_commands_and_overlapping_connects_recover_and_kill_no_task(created_tasks):
    """The emulated link drops (the chassis silent and deaf) again and again while moves and the heartbeat send,
    while the supervisor reconnects and while further connects overlap it (a reconnect started beside a connect
    in progress). A move ends with the link it started on; no driver or supervisor task ends with an exception (a
    heartbeat of one connect running on as another closed the link died with AssertionError, or ran on orphaned);
    the supervisor sees the chassis down and, once the link is back, up again, and it moves."""
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    cfg = chassis_config(channel, feedback_timeout_s=0.2)
    emu = ChassisEmulator(cfg, channel, time_scale=0.1, seed=3)
    await emu.start()
    drv = AgvCanChassis(cfg, name="measure_chassis")
    sup = Supervisor([drv], {}, None, health_period_s=0.05, reconnect_initial_s=0.05, reconnect_max_s=0.1)
    moved: list[ChassisPose | BaseException] = []
    connected: list[BaseException | None] = []
    try:
        await sup.start()
        await sup.wait_connected(2.0)
        for i in range(4):
            moves = [asyncio.create_task(drv.move_to(ChassisPose(3000.0, 0.0, 0.0), timeout_s=2.0))]
            connects = [asyncio.create_task(drv.connect()) for _ in range(2)]
            await asyncio.sleep(0.03 * i)  # the link drops at another point of the connects each round
            emu.faults.silent = emu.faults.ignore_commands = True
            await wait_until(lambda: not sup.health["measure_chassis"].up)  # a fault, or no connection
            emu.faults.silent = emu.faults.ignore_commands = False
            moved += await asyncio.gather(*moves, return_exceptions=True)
            connected += await asyncio.gather(*connects, return_exceptions=True)
        health = sup.health["measure_chassis"]
        await wait_until(lambda: health.up and health.next_retry_s is None, 5.0)  # reconnected, none pending
        assert health.reconnects >= 1
        pose = await drv.move_to(ChassisPose(100.0, 0.0, 0.0))
        assert math.hypot(pose.x_mm - 100.0, pose.y_mm) <= 5.0
    finally:
        await sup.close()
        await emu.stop()
    assert all(isinstance(m, DeviceError) for m in moved), moved  # a move never runs on across a reconnect
    assert all(c is None or isinstance(c, DeviceError) for c in connected), connected
    mine = [t for t in created_tasks if t.get_name().startswith(("measure_chassis-", "reconnect-", "supervisor-"))]
    assert {t.get_name() for t in mine} >= {"measure_chassis-rx", "measure_chassis-tx", "reconnect-measure_chassis"}
    assert all(t.done() for t in mine), [t.get_name() for t in mine if not t.done()]
    died = [(t.get_name(), t.exception()) for t in mine if not t.cancelled() and t.exception() is not None]
    assert not died


async def test_rc_lost_in_can_mode_is_a_warning_that_drives_on(emulator, chassis):
    """Error 0x0004 (RC lost): in CAN mode the transmitter may simply be off; the move goes on and the status lists
    the warning, cleared when the bit goes."""
    emulator.faults.error_code = 0x0004
    pose = await chassis.move_to(ChassisPose(200.0, 0.0, 0.0))
    assert abs(pose.x_mm - 200.0) <= 5.0
    status = await chassis.status()
    assert status.state == "idle" and status.detail["warnings"] == ["RC signal lost"]
    emulator.faults.error_code = 0
    await wait_until(lambda: not chassis._warnings)


async def test_rc_lost_while_the_rc_has_control_is_a_fault(emulator, chassis):
    emulator.faults.rc_override = True
    emulator.faults.error_code = 0x0004
    with pytest.raises(DeviceFault, match=r"0x0004: RC signal lost"):
        await chassis.move_to(ChassisPose(200.0, 0.0, 0.0))
    assert (await chassis.status()).state == "fault"


@pytest.mark.parametrize(("start_counts", "target_x_mm"), [(2**31 - 100, 300.0), (-(2**31) + 100, -300.0)])
async def test_odometry_counters_wrapping_at_2_pow_31_count_on(start_counts, target_x_mm):
    """The int32 wheel counters start 100 counts from their limit and wrap during the drive (forwards past +2^31,
    backwards past -2^31): the pose counts on across the wrap, and the body went where the odometry says."""
    channel = f"agv-{uuid.uuid4().hex[:8]}"
    emu = ChassisEmulator(chassis_config(channel), channel, time_scale=0.1, seed=3, odometry_start_counts=start_counts)
    await emu.start()
    drv = AgvCanChassis(chassis_config(channel))
    try:
        await drv.connect()
        pose = await drv.move_to(ChassisPose(target_x_mm, 0.0, 0.0), timeout_s=5.0)
        assert math.hypot(pose.x_mm - target_x_mm, pose.y_mm) <= 5.0
        assert abs(emu.true_pose.x_mm - target_x_mm) < 30.0
        assert abs(drv._wheels[0] - start_counts) > 2**31  # the counters did wrap
    finally:
        await drv.close()
        await emu.stop()

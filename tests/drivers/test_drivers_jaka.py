"""Hardware-in-the-loop: the JAKA TCP driver against the controller emulator over 127.0.0.1."""

from __future__ import annotations

import asyncio
import re

import numpy as np
import pytest
from tandemscan.config.models import ArmConfig, JakaTcpConfig
from tandemscan.drivers import Arm, DeviceFault, DeviceTimeout, NotConnected, OutOfReach, SafetyStop
from tandemscan.drivers.jaka_tcp import JakaTcpArm
from tandemscan.drivers.json_stream import JsonFramingError, JsonObjectFramer
from tandemscan.pipeline.geometry.frames import from_rotvec, pose_error
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.sim_drivers.emulators.jaka import JakaBehaviour, JakaEmulator

Q_HOME = np.radians([0.0, 90.0, -60.0, 90.0, 90.0, 0.0])
Q_TARGET = np.radians([20.0, 100.0, -70.0, 80.0, 95.0, 10.0])


@pytest.fixture
async def emulator():
    emu = JakaEmulator(ArmConfig(), time_scale=0.005, initial_joints_rad=Q_HOME)
    await emu.start()
    yield emu
    await emu.stop()


def arm_for(emu: JakaEmulator, reply_timeout_s: float = 0.5) -> JakaTcpArm:
    jaka = JakaTcpConfig(host="127.0.0.1", command_port=emu._commands.port, status_port=emu._status.port,
                         reply_timeout_s=reply_timeout_s)
    return JakaTcpArm(ArmConfig(jaka=jaka, timeout_s=5.0))


@pytest.fixture
async def arm(emulator):
    arm = arm_for(emulator)
    await arm.connect()
    await arm.enable()
    yield arm
    await arm.close()


async def test_happy_path_joint_and_linear_moves(emulator, arm):
    assert isinstance(arm, Arm)
    np.testing.assert_allclose(await arm.joints(), Q_HOME, atol=1e-9)
    await arm.move_joints(Q_TARGET)
    # completion comes from the status stream: the emulator's motion is over when the call returns
    assert emulator.motion.in_position(emulator.sim_time())
    np.testing.assert_allclose(await arm.joints(), Q_TARGET, atol=1e-9)
    kin = ArmKinematics(ArmConfig())
    dt, dr = pose_error(await arm.flange_pose(), kin.forward(Q_TARGET))
    assert dt < 1e-6 and dr < 1e-9

    goal = kin.forward(Q_TARGET)
    goal[:3, 3] += [30.0, -20.0, 15.0]
    await arm.move_linear(goal)
    dt, dr = pose_error(await arm.flange_pose(), goal)
    assert dt < 0.05 and dr < 1e-4
    assert (await arm.status()).state == "idle"
    assert [c for c in emulator.commands[:6] if c != "get_robot_state"] == ["power_on", "enable_robot"]


async def test_a_linear_move_that_only_turns_the_flange_waits_for_the_turn(emulator, arm):
    """A controller starts a move a little after its reply and meanwhile still shows the last move's ``inpos``;
    a linear move to the same position at another orientation must not return on that flag."""
    emulator.behaviour = JakaBehaviour(move_start_delay_s=0.05)
    kin = ArmKinematics(ArmConfig())
    goal = kin.forward(Q_HOME) @ from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0, np.radians(5.0)])  # the same position
    await arm.move_linear(goal)
    assert emulator.motion.in_position(emulator.sim_time())
    dt, dr = pose_error(await arm.flange_pose(), goal)
    assert dt < 0.05 and dr < 1e-4


async def test_move_waits_for_motion_in_simulated_time(emulator, arm):
    """A move returns once the controller's motion is over: 20 deg at 60 deg/s last 1/3 s of its time."""
    emulator.time_scale = 0.01
    await arm.move_joints(Q_TARGET)
    emulator.time_scale = 0.5  # 1/3 s simulated = 170 ms wall: many status periods after the reply
    t0 = emulator.sim_time()
    await arm.move_joints(Q_HOME)
    assert emulator.sim_time() - t0 >= 20.0 / ArmConfig().joint_speed_deg_s
    assert emulator.motion.done(emulator.sim_time())
    np.testing.assert_allclose(await arm.joints(), Q_HOME, atol=1e-9)


async def test_a_linear_move_takes_its_path_at_the_commanded_speed(emulator):
    """``moveL`` carries the flange's speed (mm/s): 60 mm at 20 mm/s last at least 3 s of the controller's time,
    though the joints alone could make it in a tenth of that; the driver waits for all of it."""
    jaka = JakaTcpConfig(host="127.0.0.1", command_port=emulator._commands.port,
                         status_port=emulator._status.port, linear_speed_mm_s=20.0)
    arm = JakaTcpArm(ArmConfig(jaka=jaka, timeout_s=10.0))
    await arm.connect()
    try:
        await arm.enable()
        emulator.time_scale = 0.05
        goal = ArmKinematics(ArmConfig()).forward(Q_HOME)
        goal[:3, 3] += [40.0, 0.0, -44.7]
        t0 = emulator.sim_time()
        await arm.move_linear(goal)
        assert emulator.sim_time() - t0 >= 60.0 / 20.0
        dt, _ = pose_error(await arm.flange_pose(), goal)
        assert dt < 0.05
    finally:
        await arm.close()


async def test_joint_target_outside_limits_is_refused_before_sending(emulator, arm):
    bad = Q_TARGET.copy()
    bad[1] = np.radians(-100.0)
    sent = len(emulator.commands)
    with pytest.raises(OutOfReach, match="arm"):
        await arm.move_joints(bad)
    assert len(emulator.commands) == sent


async def test_unreachable_linear_target_is_out_of_reach(arm):
    far = np.eye(4)
    far[:3, 3] = [3000.0, 0.0, 0.0]
    with pytest.raises(OutOfReach, match="error 2"):
        await arm.move_linear(far)


async def test_estop_during_move_is_safety_stop_and_sends_stop(emulator, arm):
    emulator.time_scale = 1.0  # a slow move
    move = asyncio.create_task(arm.move_joints(Q_TARGET))
    while emulator.motion.in_position(emulator.sim_time()):  # the move has started
        await asyncio.sleep(0.005)
    emulator.faults.estop = True
    with pytest.raises(SafetyStop, match="emergency stop"):  # from the status stream, not the move's timeout
        await move
    assert emulator.commands[-1] == "stop_program"
    with pytest.raises(SafetyStop):
        await arm.move_joints(Q_HOME)


async def test_move_timeout_stops_the_arm(emulator, arm):
    emulator.time_scale = 1.0
    with pytest.raises(DeviceTimeout, match="joint move completion not seen within 0.1 s"):
        await arm.move_joints(Q_TARGET, timeout_s=0.1)
    assert emulator.commands[-1] == "stop_program"
    assert not emulator.motion.in_position(emulator.sim_time()) or np.allclose(
        emulator.joints_deg(), emulator.motion.position(emulator.sim_time())
    )
    q_after = emulator.joints_deg()
    await asyncio.sleep(0.05)
    np.testing.assert_allclose(emulator.joints_deg(), q_after)  # halted, not still moving


async def test_a_stop_after_a_late_reply_dropped_the_command_link_goes_out_on_a_new_connection(emulator, arm):
    """A command's reply is late while a move runs: the driver drops the command link (a late reply would answer
    the next command) and raises; the stop that follows (the supervisor's halt) must still reach the arm, which is
    moving."""
    emulator.time_scale = 1.0
    move = asyncio.create_task(arm.move_joints(Q_HOME + np.radians([90.0, 0, 0, 0, 0, 0]), timeout_s=30.0))
    while emulator.motion.in_position(emulator.sim_time()):  # the move has started: seconds at joint speed
        await asyncio.sleep(0.005)
    emulator.faults.reply_delay_s = 2.0
    with pytest.raises(DeviceTimeout, match="get_joint_pos: no reply"):
        await arm.joints()
    emulator.faults.reply_delay_s = 0.0
    assert not emulator.motion.in_position(emulator.sim_time())  # the move runs
    await arm.stop()
    assert emulator.commands[-1] == "stop_program"
    q_after = emulator.joints_deg()
    await asyncio.sleep(0.05)
    np.testing.assert_allclose(emulator.joints_deg(), q_after)  # halted
    np.testing.assert_allclose(await arm.joints(), np.radians(q_after), atol=1e-9)  # the new link serves commands
    move.cancel()
    await asyncio.gather(move, return_exceptions=True)


async def test_a_controller_that_answers_a_move_when_it_is_done(emulator, arm):
    """Some firmware (and client code) treats a move as blocking: its reply comes when the motion is over, long
    after the reply timeout (0.5 s here). The move completes from the status stream; the late replies are read
    and not taken for the next commands' (the link is kept)."""
    emulator.behaviour = JakaBehaviour(reply_moves_when_done=True)
    emulator.time_scale = 3.0  # 20 deg at 60 deg/s: 1/3 s of the controller's time, 1 s wall
    clients = emulator._commands.client_count
    await arm.move_joints(Q_TARGET)
    np.testing.assert_allclose(await arm.joints(), Q_TARGET, atol=1e-9)
    await arm.move_joints(Q_HOME)
    emulator.time_scale = 0.05
    goal = ArmKinematics(ArmConfig()).forward(Q_HOME)
    goal[:3, 3] += [20.0, 0.0, -10.0]
    await arm.move_linear(goal)
    assert pose_error(await arm.flange_pose(), goal)[0] < 0.05
    assert emulator._commands.client_count == clients == 1
    assert emulator.commands.count("power_on") == 1  # never reconnected and re-enabled


async def test_a_move_neither_answered_nor_started_fails_after_the_reply_timeout(emulator, arm):
    """A late move reply is tolerated only while the status shows the arm moving: a controller whose command task
    hangs (the status still pushed) fails the move after twice the reply timeout, not the move's own (5 s)."""
    emulator.faults.ignore_commands = True
    with pytest.raises(DeviceTimeout, match="joint_move: no reply within 0.5 s and the arm did not start"):
        await arm.move_joints(Q_TARGET)
    with pytest.raises(NotConnected):  # the command link was dropped
        await arm.joints()
    emulator.faults.ignore_commands = False
    await arm.connect()
    await arm.move_joints(Q_TARGET)
    np.testing.assert_allclose(await arm.joints(), Q_TARGET, atol=1e-9)


async def test_a_status_stream_configured_without_inpos_still_completes_moves(emulator, arm):
    """The status content is a setting of the controller: where it leaves ``inpos`` out, a move completes when the
    actual joints (or the flange) reach the target."""
    emulator.behaviour = JakaBehaviour(status_leaves_out=("inpos",), move_start_delay_s=0.02)
    emulator.time_scale = 0.05
    await arm.move_joints(Q_TARGET)
    assert emulator.motion.done(emulator.sim_time())
    goal = ArmKinematics(ArmConfig()).forward(Q_TARGET)
    goal[:3, 3] += [0.0, 15.0, 10.0]
    await arm.move_linear(goal)
    assert pose_error(await arm.flange_pose(), goal)[0] < 0.05


async def test_a_tool_or_user_frame_selected_on_the_controller_is_refused_for_cartesian_poses(emulator, arm):
    """``get_tcp_pos``, ``actual_position`` and ``moveL`` speak of the selected tool in the selected user frame
    (status ``current_tool_id`` / ``current_user_id``): the driver's flange poses need tool 0 and user frame 0."""
    kin = ArmKinematics(ArmConfig())
    tool = from_rotvec([0.0, 0.0, 120.0], [0.0, 0.0, 0.0])  # a scanner's TCP 120 mm out along the flange's z
    emulator.select_frames((1, tool), (0, np.eye(4)))
    while (await arm.status()).detail["current_tool_id"] != 1:  # the status stream shows it
        await asyncio.sleep(0.01)
    with pytest.raises(DeviceFault, match="tool 1"):
        await arm.flange_pose()
    sent = len(emulator.commands)
    with pytest.raises(DeviceFault, match="tool 1"):
        await arm.move_linear(kin.forward(Q_TARGET))
    assert len(emulator.commands) == sent  # refused before sending
    await arm.move_joints(Q_TARGET)  # joint moves do not depend on it
    emulator.select_frames((0, np.eye(4)), (2, from_rotvec([100.0, 0.0, 0.0], [0.0, 0.0, 0.0])))
    while (await arm.status()).detail["current_user_id"] != 2:
        await asyncio.sleep(0.01)
    with pytest.raises(DeviceFault, match="user frame 2"):
        await arm.flange_pose()
    emulator.select_frames((0, np.eye(4)), (0, np.eye(4)))
    while (await arm.status()).detail["current_user_id"] != 0:
        await asyncio.sleep(0.01)
    dt, dr = pose_error(await arm.flange_pose(), kin.forward(Q_TARGET))
    assert dt < 1e-6 and dr < 1e-9


async def test_a_controller_that_refuses_a_second_client_still_gets_the_stop(emulator):
    """Only one client may hold the command port: a controller may close a new connection at once while it still
    serves the old one (here: it has not let go of the link the driver dropped after a late reply, 1.2 s late for a
    1 s timeout). The stop on a new connection is tried again until the controller takes it."""
    emulator.behaviour = JakaBehaviour(refuse_second_client=True)
    arm = arm_for(emulator, reply_timeout_s=1.0)
    await arm.connect()
    try:
        await arm.enable()
        emulator.time_scale = 1.0
        move = asyncio.create_task(arm.move_joints(Q_HOME + np.radians([90.0, 0, 0, 0, 0, 0]), timeout_s=30.0))
        while emulator.motion.in_position(emulator.sim_time()):  # the move has started
            await asyncio.sleep(0.005)
        emulator.faults.reply_delay_s = 1.2
        with pytest.raises(DeviceTimeout, match="get_joint_pos: no reply"):
            await arm.joints()
        emulator.faults.reply_delay_s = 0.0
        await arm.stop()
        assert emulator.commands[-1] == "stop_program"
        q_after = emulator.joints_deg()
        await asyncio.sleep(0.05)
        np.testing.assert_allclose(emulator.joints_deg(), q_after)  # halted
        move.cancel()
        await asyncio.gather(move, return_exceptions=True)
    finally:
        await arm.close()


async def test_a_stop_beside_a_reconnect_leaves_one_command_link_that_serves(emulator, arm):
    """The command link was dropped (a late reply) while the status stream runs; the supervisor reconnects the arm
    while a stop goes out. The controller serves one command client (a new one replaces the old), so a stop that
    reopened its own link beside the reconnect's would leave the driver on a link the controller had closed."""
    emulator.faults.reply_delay_s = 1.0
    with pytest.raises(DeviceTimeout):
        await arm.joints()
    emulator.faults.reply_delay_s = 0.0
    await asyncio.gather(arm.stop(), arm.connect())
    assert emulator._commands.client_count == 1 and "stop_program" in emulator.commands
    np.testing.assert_allclose(await arm.joints(), Q_HOME, atol=1e-9)
    await asyncio.gather(arm.connect(), arm.stop())  # the other way round: the stop waits for the new link
    assert emulator._commands.client_count == 1 and emulator.commands[-1] == "stop_program"
    np.testing.assert_allclose(await arm.joints(), Q_HOME, atol=1e-9)


async def test_a_controller_that_pushes_its_status_slowly_is_not_taken_for_a_lost_link():
    """The status push period is a setting of the controller: at 0.5 s (beyond the default 0.3 s watchdog gap) the
    driver times the period at connect and watches for a gap of four of them instead."""
    emulator = JakaEmulator(ArmConfig(), time_scale=0.005, initial_joints_rad=Q_HOME, status_period_s=0.5)
    await emulator.start()
    arm = arm_for(emulator, reply_timeout_s=1.0)  # each status message awaited at connect for up to this long
    try:
        await arm.connect()
        await arm.enable()
        await arm.move_joints(Q_TARGET)
        np.testing.assert_allclose(await arm.joints(), Q_TARGET, atol=1e-9)
        emulator.faults.status_silent = True  # and a stream that stops is still a lost link, after 4 periods
        with pytest.raises(NotConnected, match=r"no status message for \d\.\d+ s") as lost:
            await arm.move_joints(Q_HOME)
        gap_s = float(re.search(r"for (\d\.\d+) s", str(lost.value)).group(1))
        assert gap_s > 1.0  # four of the timed 0.5 s periods, not the default 0.3 s
    finally:
        await arm.close()
        await emulator.stop()


@pytest.mark.parametrize("fault", ["reply_delay_s", "silent"])
async def test_slow_or_silent_controller_times_out_then_reconnects(emulator, arm, fault):
    setattr(emulator.faults, fault, 1.0 if fault == "reply_delay_s" else True)
    with pytest.raises(DeviceTimeout, match="get_joint_pos: no reply within 0.5 s"):
        await arm.joints()
    with pytest.raises(NotConnected):  # the link is dropped: a late reply must not answer the next call
        await arm.joints()
    setattr(emulator.faults, fault, 0.0 if fault == "reply_delay_s" else False)
    await arm.connect()
    np.testing.assert_allclose(await arm.joints(), Q_HOME, atol=1e-9)


async def test_truncated_reply_is_a_fault_then_reconnects(emulator, arm):
    emulator.faults.truncate_next_reply = True
    with pytest.raises(DeviceFault, match="truncated"):
        await arm.joints()
    await arm.connect()
    await arm.move_joints(Q_TARGET)


async def test_disconnect_mid_move_then_reconnect(emulator, arm):
    emulator.time_scale = 1.0
    emulator.faults.disconnect_on_move = True
    with pytest.raises(NotConnected, match="status stream"):
        await arm.move_joints(Q_TARGET)
    assert (await arm.status()).state == "disconnected"  # the stop attempt found the command link gone too
    emulator.faults.disconnect_on_move = False
    emulator.time_scale = 0.005
    await arm.connect()
    await arm.move_joints(Q_TARGET)
    np.testing.assert_allclose(await arm.joints(), Q_TARGET, atol=1e-9)


async def test_nan_in_status_is_a_fault_and_stops(emulator, arm):
    emulator.time_scale = 1.0
    emulator.faults.nan_in_status = True
    with pytest.raises(DeviceFault, match="malformed status"):
        await arm.move_joints(Q_TARGET)
    assert emulator.commands[-1] == "stop_program"


async def test_calls_before_connect_and_refused_connection():
    arm = JakaTcpArm(ArmConfig(jaka=JakaTcpConfig(host="127.0.0.1", command_port=1, status_port=1)))
    with pytest.raises(NotConnected, match="arm"):
        await arm.joints()
    with pytest.raises(NotConnected, match="cannot connect"):
        await arm.connect()
    await arm.close()
    await arm.close()


async def test_second_client_replaces_the_first(emulator, arm):
    other = arm_for(emulator)
    await other.connect()
    assert np.allclose(await other.joints(), Q_HOME)
    with pytest.raises(NotConnected):
        await arm.joints()
    await other.close()


def test_framer_splits_objects_at_any_byte_boundary():
    stream = b'{"a":"}{\\"","b":[1,{"c":2}]} \n{"cmdName":"x","errorCode":"0"}'
    for cut in range(len(stream) + 1):
        framer = JsonObjectFramer()
        objs = framer.feed(stream[:cut]) + framer.feed(stream[cut:])
        assert objs == [{"a": '}{"', "b": [1, {"c": 2}]}, {"cmdName": "x", "errorCode": "0"}]
        assert not framer.pending


@pytest.mark.parametrize("bad", [b"[1,2]", b"hello", b'{"a":NaN}', b'{"a":1,}'])
def test_framer_rejects_garbage(bad):
    with pytest.raises(JsonFramingError):
        JsonObjectFramer().feed(bad)


def test_framer_bounds_memory():
    framer = JsonObjectFramer(max_object_bytes=100)
    with pytest.raises(JsonFramingError, match="larger"):
        framer.feed(b'{"a":"' + b"x" * 200)


# ---------------------------------------------------------------- vendor behaviour (issue 15)

VENDOR_LIKE = JakaBehaviour(power_on_delay_s=0.3, enable_delay_s=0.1, segment_bytes=500, numeric_error_codes=True,
                            status_bytes=6000, move_start_delay_s=0.02)


@pytest.fixture
async def vendor_emulator():
    emu = JakaEmulator(ArmConfig(), time_scale=0.005, initial_joints_rad=Q_HOME, behaviour=VENDOR_LIKE)
    await emu.start()
    yield emu
    await emu.stop()


async def test_enable_waits_for_asynchronous_power_on_and_enable(vendor_emulator):
    """A reply means "received": power_on takes 0.3 s, enable_robot 0.1 s after their replies."""
    arm = arm_for(vendor_emulator)
    await arm.connect()
    try:
        await arm.enable()  # one call, no "not powered on" on the way
        assert vendor_emulator.powered and vendor_emulator.enabled
        assert vendor_emulator.commands.count("power_on") == 1
        assert vendor_emulator.commands.count("enable_robot") == 1
        await arm.move_joints(Q_TARGET)  # status objects of 6 kB in 500-byte segments, numeric error codes
        np.testing.assert_allclose(await arm.joints(), Q_TARGET, atol=1e-9)
        await arm.enable()  # already enabled: nothing is sent again
        assert vendor_emulator.commands.count("power_on") == 1
    finally:
        await arm.close()


async def test_enable_that_never_completes_times_out(emulator):
    emulator.behaviour = JakaBehaviour(power_on_delay_s=10.0)
    arm = JakaTcpArm(ArmConfig(jaka=JakaTcpConfig(host="127.0.0.1", command_port=emulator._commands.port,
                                                  status_port=emulator._status.port, power_on_timeout_s=0.3)))
    await arm.connect()
    try:
        with pytest.raises(DeviceTimeout, match="'power' still 'powered_off'"):
            await arm.enable()
    finally:
        await arm.close()


@pytest.mark.parametrize("numeric", [False, True])
async def test_refused_move_is_a_fault_with_the_reason_not_out_of_reach(emulator, arm, numeric):
    """The controller answers errorCode 2 for any refused move; only kine_inverse tells unreachable apart."""
    emulator.behaviour = JakaBehaviour(numeric_error_codes=numeric)
    kin = ArmKinematics(ArmConfig())
    reachable = kin.forward(Q_TARGET)
    emulator.set_power(True, False)  # powered, servos disabled
    with pytest.raises(DeviceFault, match="moveL: error 2: robot is not enabled") as info:
        await arm.move_linear(reachable)
    assert not isinstance(info.value, OutOfReach)
    assert emulator.commands[-1] == "kine_inverse"
    far = np.eye(4)
    far[:3, 3] = [3000.0, 0.0, 0.0]
    with pytest.raises(OutOfReach, match="kine_inverse: error 2: inverse kinematics failed"):
        await arm.move_linear(far)
    emulator.set_power(True, True)
    await arm.move_linear(reachable)


async def test_a_refusal_is_out_of_reach_only_when_kine_inverse_says_so(emulator, arm):
    """Issue 42 row 8: on a controller that does not know ``kine_inverse``, a move refused because the robot is
    not enabled is a fault with the controller's text and state, and so is one whose reach cannot be asked."""
    emulator.behaviour = JakaBehaviour(knows_kine_inverse=False)
    reachable = ArmKinematics(ArmConfig()).forward(Q_TARGET)
    emulator.set_power(True, False)  # powered, servos disabled
    await asyncio.sleep(0.05)  # the status stream shows it
    with pytest.raises(DeviceFault, match="robot is not enabled; reachability unknown: kine_inverse: error 1: "
                                          r"unknown command 'kine_inverse' \(status: robot not enabled\)") as info:
        await arm.move_linear(reachable)
    assert not isinstance(info.value, OutOfReach)
    emulator.set_power(True, True)
    far = np.eye(4)
    far[:3, 3] = [3000.0, 0.0, 0.0]
    with pytest.raises(DeviceFault, match="moveL: error 2: inverse kinematics failed; reachability unknown") as info:
        await arm.move_linear(far)
    assert not isinstance(info.value, OutOfReach)
    await arm.move_linear(reachable)


async def status_reaches(arm, predicate) -> None:
    """Wait until ``predicate(the arm's status state)`` holds (the timeout only against a hang)."""
    async with asyncio.timeout(10):
        while not predicate((await arm.status()).state):
            await asyncio.sleep(0.005)


async def test_protective_stop_refuses_moves_as_safety_stop(emulator, arm):
    emulator.faults.protective_stop = True
    await status_reaches(arm, lambda state: state == "stopped")  # through the status stream
    with pytest.raises(SafetyStop, match="protective stop"):
        await arm.move_joints(Q_TARGET)


async def test_a_controller_error_during_a_move_is_a_fault_until_cleared(emulator, arm):
    """The status stream's ``errcode`` (a string, "0x0" when none) turns non-zero mid-move: the move ends with a
    DeviceFault naming it, the arm reads "fault"; after ``clear_error`` it moves again."""
    emulator.time_scale = 1.0  # a slow move
    move = asyncio.create_task(arm.move_joints(Q_TARGET))
    while emulator.motion.in_position(emulator.sim_time()):  # the move has started
        await asyncio.sleep(0.005)
    emulator.faults.controller_error = "0x10030001"
    with pytest.raises(DeviceFault, match="controller error 0x10030001: servo error"):
        await move
    assert (await arm.status()).state == "fault"
    await arm.clear_error()
    await status_reaches(arm, lambda state: state != "fault")  # the cleared state, through the status stream
    emulator.time_scale = 0.01
    await arm.move_joints(Q_HOME)
    assert (await arm.status()).state == "idle"


@pytest.mark.parametrize(("faults", "state"), [(("status_silent",), "fault"),
                                               (("status_silent", "silent"), "disconnected")])
async def test_silent_controller_is_a_lost_link_after_a_status_gap(emulator, arm, faults, state):
    """The status push stops (a hung controller), or nothing comes back at all (a pulled cable): the move
    fails on the status watchdog, not after its timeout."""
    emulator.time_scale = 1.0
    move = asyncio.create_task(arm.move_joints(Q_TARGET, timeout_s=4.0))
    while emulator.motion.in_position(emulator.sim_time()):
        await asyncio.sleep(0.005)
    for fault in faults:
        setattr(emulator.faults, fault, True)
    with pytest.raises(NotConnected, match="no status message for 0.3 s"):
        await move
    assert emulator.commands[-1] == "stop_program"  # tried, bounded by the same gap
    assert (await arm.status()).state == state  # the stop's reply timed out on a pulled cable: link dropped
    with pytest.raises(NotConnected):  # later waits fail at once, until reconnect
        await arm.move_joints(Q_HOME)
    for fault in faults:
        setattr(emulator.faults, fault, False)
    emulator.time_scale = 0.005
    await arm.connect()
    await arm.move_joints(Q_TARGET)


def test_framer_handles_split_and_coalesced_status_objects():
    """6 kB status objects back to back, cut into segments that end anywhere, strings with escapes."""
    emu_msg = {"joint_actual_position": [1.5] * 6, "errmsg": 'a "quoted" \\ text {', "din": [0] * 144,
               "extio": {"setup": [{"name": "x}", "v": [1, 2]}]}}
    raw = b"".join(json_bytes(emu_msg | {"n": i}) for i in range(5))
    for segment in (1, 7, 1448, len(raw)):
        framer = JsonObjectFramer()
        objs = []
        for i in range(0, len(raw), segment):
            objs += framer.feed(raw[i : i + segment])
        assert [o["n"] for o in objs] == list(range(5))
        assert objs[3]["errmsg"] == emu_msg["errmsg"]
        assert not framer.pending


def json_bytes(obj: dict) -> bytes:
    import json

    return json.dumps(obj).encode() + b"\r\n"


def test_framer_string_ends_after_backslash_runs_at_any_cut():
    stream = b'{"p":"c:\\\\","q":"\\\\\\"}","r":[{"s":"\\\\\\\\"}]}{"n":1}'
    expected = [{"p": "c:\\", "q": '\\"}', "r": [{"s": "\\\\"}]}, {"n": 1}]
    for cut in range(len(stream) + 1):
        framer = JsonObjectFramer()
        assert framer.feed(stream[:cut]) + framer.feed(stream[cut:]) == expected

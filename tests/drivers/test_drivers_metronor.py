"""Hardware-in-the-loop: the tracker driver against the pose-stream emulator over TCP and a pty serial line."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import time

import numpy as np
import pytest
from tandemscan.config.models import TrackerConfig, TrackerStreamConfig
from tandemscan.drivers import DeviceFault, DeviceTimeout, NotConnected, TargetNotVisible, Tracker
from tandemscan.drivers.metronor import MetronorTracker
from tandemscan.drivers.pose_stream import PoseFrameError, PoseSample, PoseStreamAdapter
from tandemscan.pipeline.geometry.frames import from_rpy, pose_error
from tandemscan.sim_drivers.emulators.tracker import TrackerStreamEmulator, fixed_pose_source

T_TRUE = from_rpy([120.0, -340.0, 2900.0], np.radians([170.0, 12.0, -35.0]))
MATRIX_FIELDS = ("frame", "status", "x_mm", "y_mm", "z_mm", *(f"r{i}{j}" for i in range(3) for j in range(3)),
                 "rms_mm", "device_time_s")


def tracker_for(stream: TrackerStreamConfig, **kw) -> MetronorTracker:
    return MetronorTracker(TrackerConfig(stream=stream, timeout_s=0.5, **kw))


@pytest.fixture
async def tcp_pair():
    stream = TrackerStreamConfig(host="127.0.0.1", port=0)
    emu = TrackerStreamEmulator(stream, fixed_pose_source(T_TRUE), rate_hz=200)
    port = await emu.start_tcp()
    tracker = tracker_for(stream.model_copy(update={"port": port}))
    await tracker.connect()
    yield emu, tracker
    await tracker.close()
    await emu.stop()


async def test_tcp_happy_path_pose_covariance_frame_number(tcp_pair):
    emu, tracker = tcp_pair
    assert isinstance(tracker, Tracker)
    t_call = time.time()
    r1 = await tracker.read_pose()
    r2 = await tracker.read_pose()
    dt, dr = pose_error(r1.T_C_T, T_TRUE)
    assert dt < 1e-5 and dr < 1e-6
    assert r1.covariance.shape == (6, 6)
    assert r1.covariance[0, 0] == pytest.approx(1e-4, rel=1e-3)  # (0.01 mm)^2
    assert r2.frame_number > r1.frame_number
    assert r1.timestamp_s >= t_call  # fresh, never a frame from before the call
    assert (await tracker.status()).state == "idle"


async def test_target_not_visible_is_typed(tcp_pair):
    emu, tracker = tcp_pair

    def hidden():
        raise TargetNotVisible("sim", "occluded")

    emu.source = hidden
    with pytest.raises(TargetNotVisible, match="tracker: target not visible.*MISSING"):
        for _ in range(5):  # frames already in flight when the target disappeared may still arrive
            await tracker.read_pose()


@pytest.mark.parametrize("fault", ["corrupt_next", "nan_next", "truncate_next"])
async def test_malformed_frames_are_device_faults_then_recover(tcp_pair, fault):
    emu, tracker = tcp_pair
    await tracker.read_pose()
    emu.faults.stall = True
    await asyncio.sleep(0.02)
    setattr(emu.faults, fault, True)
    emu.faults.stall = False
    with pytest.raises(DeviceFault, match="bad pose frame"):
        await tracker.read_pose()
    r = await tracker.read_pose()
    assert pose_error(r.T_C_T, T_TRUE)[0] < 1e-5


async def test_stalled_stream_times_out_within_timeout(tcp_pair):
    emu, tracker = tcp_pair
    emu.faults.stall = True
    with pytest.raises(DeviceTimeout, match="no pose frame within 0.2 s"):  # its own timeout, not the stream's
        await tracker.read_pose(timeout_s=0.2)


async def test_dropped_frames_and_reconnect_after_disconnect(tcp_pair):
    emu, tracker = tcp_pair
    emu.faults.drop_fraction = 0.5
    await tracker.read_pose()
    emu.faults.drop_fraction = 0.0
    await emu.drop_connections()
    with pytest.raises(NotConnected, match="closed by the tracker"):
        await tracker.read_pose()
    assert (await tracker.status()).state == "fault"
    await tracker.connect()
    assert pose_error((await tracker.read_pose()).T_C_T, T_TRUE)[0] < 1e-5


async def test_serial_transport_over_a_pty_with_matrix_framing():
    master, slave = os.openpty()
    stream = TrackerStreamConfig(transport="serial", serial_device=os.ttyname(slave), fields=MATRIX_FIELDS,
                                 start_marker="$TRK", checksum=False)
    emu = TrackerStreamEmulator(stream, fixed_pose_source(T_TRUE, sigma_mm=0.02), rate_hz=200)
    await emu.start_serial(master)
    tracker = tracker_for(stream)
    try:
        await tracker.connect()
        r = await tracker.read_pose()
        assert pose_error(r.T_C_T, T_TRUE)[0] < 1e-5
        assert r.covariance[2, 2] == pytest.approx(4e-4, rel=1e-2)
    finally:
        await tracker.close()
        await emu.stop()
        os.close(master)
        os.close(slave)


async def test_connect_errors_and_not_connected():
    tracker = tracker_for(TrackerStreamConfig(host="127.0.0.1", port=1))
    with pytest.raises(NotConnected, match="tracker"):
        await tracker.read_pose()
    with pytest.raises(NotConnected, match="cannot connect"):
        await tracker.connect()
    serial_tracker = tracker_for(TrackerStreamConfig(transport="serial", serial_device="/dev/does-not-exist"))
    with pytest.raises(NotConnected, match="does-not-exist"):
        await serial_tracker.connect()
    await tracker.close()


def test_adapter_resyncs_on_garbage_and_split_frames():
    cfg = TrackerStreamConfig()
    adapter = PoseStreamAdapter(cfg)
    frame = adapter.encode(7, 1.5, T_TRUE, np.eye(6) * 1e-4)
    stream = b"noise\x00\xff" + frame + frame[:20] + frame
    parsed = []
    for i in range(0, len(stream), 13):
        parsed += adapter.feed(stream[i : i + 13])
    assert [type(p) for p in parsed] == [PoseSample, PoseFrameError, PoseSample]
    assert parsed[0].frame == 7 and pose_error(parsed[0].T_C_T, T_TRUE)[0] < 1e-5


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda f: f.replace(b",OK,", b",OK,1,"), "checksum"),
        (lambda f: f.split(b"*")[0] + b"\r\n", "without checksum"),
    ],
)
def test_adapter_rejects_bad_frames(edit, match):
    adapter = PoseStreamAdapter(TrackerStreamConfig())
    (out,) = adapter.feed(edit(adapter.encode(1, 0.0, T_TRUE, None)))
    assert isinstance(out, PoseFrameError) and match in str(out)


def test_adapter_rejects_non_unit_quaternion_and_bad_config():
    cfg = TrackerStreamConfig(checksum=False)
    adapter = PoseStreamAdapter(cfg)
    line = adapter.encode(1, 0.0, T_TRUE, None).decode().strip().split(",")
    line[7] = "0.9"  # qx
    (out,) = adapter.feed((",".join(line) + "\n").encode())
    assert isinstance(out, PoseFrameError) and "quaternion" in str(out)
    with pytest.raises(ValueError, match="unknown field"):
        PoseStreamAdapter(TrackerStreamConfig(fields=("frame", "status", "speed")))


# ---------------------------------------------------------------- trackers that must be asked (issue 15)


@contextlib.asynccontextmanager
async def pair_for(stream: TrackerStreamConfig, **emu_kw):
    """A connected tracker driver on a TCP emulator of ``stream`` (fixed pose), closed after the block."""
    emu = TrackerStreamEmulator(stream, fixed_pose_source(T_TRUE), rate_hz=200, **emu_kw)
    port = await emu.start_tcp()
    tracker = tracker_for(stream.model_copy(update={"port": port}))
    await tracker.connect()
    try:
        yield emu, tracker
    finally:
        await tracker.close()
        await emu.stop()


async def test_tracker_that_needs_a_start_command():
    stream = TrackerStreamConfig(host="127.0.0.1", port=0, start_command="TSTART\r")
    async with pair_for(stream, requires_start=True) as (emu, tracker):
        r = await tracker.read_pose()
        assert pose_error(r.T_C_T, T_TRUE)[0] < 1e-5


async def test_polled_tracker_answers_one_frame_per_poll():
    stream = TrackerStreamConfig(host="127.0.0.1", port=0, start_command="TSTART\r", poll_command="BX 0801\r")
    async with pair_for(stream, requires_start=True) as (emu, tracker):
        numbers = [(await tracker.read_pose()).frame_number for _ in range(3)]
        assert numbers == sorted(set(numbers))
        await asyncio.sleep(0.05)  # no poll, no frame: nothing arrived after the third polled one
        assert tracker.last_sample.frame == numbers[-1]


async def test_length_prefixed_binary_frames_over_tcp():
    stream = TrackerStreamConfig(host="127.0.0.1", port=0, framing="length_prefixed", length_prefix="u16be",
                                 record="binary", binary_byte_order="big", fields=MATRIX_FIELDS)
    async with pair_for(stream) as (emu, tracker):
        r = await tracker.read_pose()
        assert pose_error(r.T_C_T, T_TRUE)[0] < 1e-5
        assert r.covariance[0, 0] == pytest.approx(1e-4, rel=1e-3)
        emu.faults.truncate_next = True  # the stream is out of step after a cut frame, then resynchronises
        for _ in range(5):
            with contextlib.suppress(DeviceFault):
                r = await tracker.read_pose()
        assert pose_error(r.T_C_T, T_TRUE)[0] < 1e-5


async def test_udp_datagrams():
    stream = TrackerStreamConfig(transport="udp", host="127.0.0.1", port=free_udp_port())
    emu = TrackerStreamEmulator(stream, fixed_pose_source(T_TRUE), rate_hz=200)
    tracker = tracker_for(stream)
    await tracker.connect()
    await emu.start_udp(stream.host, stream.port)
    try:
        r = await tracker.read_pose()
        assert pose_error(r.T_C_T, T_TRUE)[0] < 1e-5
    finally:
        await tracker.close()
        await emu.stop()


async def test_frames_arriving_together_are_timestamped_each_and_stale_ones_skipped():
    """Three frames per write: the reading is never one generated before the call, and each frame has its
    own time (dated back from the newest by the device-time difference)."""
    stream = TrackerStreamConfig(host="127.0.0.1", port=0)
    async with pair_for(stream) as (emu, tracker):
        emu.period_s = 0.02
        emu.faults.burst = 3
        loop = asyncio.get_running_loop()
        await tracker.read_pose()
        readings = []
        for _ in range(6):
            await asyncio.sleep(0.03)  # the call lands in the middle of a burst's frames
            called = loop.time()
            r = await tracker.read_pose()
            assert emu.device_times[r.frame_number] >= called - 1e-3
            readings.append(r)
        stamps = [r.timestamp_s for r in readings]
        assert stamps == sorted(stamps)


def test_udp_with_a_command_is_a_config_error():
    with pytest.raises(ValueError, match="need transport tcp or serial"):
        TrackerStreamConfig(transport="udp", start_command="TSTART\r")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]

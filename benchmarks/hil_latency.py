"""Round-trip latency of each real driver's basic call against its emulator, over the real transport, and
the CAN command-period jitter while a scan is stitched into the world map in a worker thread.

Calls: arm ``joints()`` (JSON request/reply on TCP), chassis ``move_to(current pose)`` (one CAN feedback
cycle and the standstill check), tracker ``read_pose()`` (next fresh frame of a 60 Hz stream), safety
``set_target_light()`` (Modbus write-coil request/reply), scanner ``capture()`` (fake GenTL, 64 x 48 frame).
Prints one JSON object on its last line: median and p99 in ms per call, jitter p99 in ms.
"""

from __future__ import annotations

import asyncio
import time
import uuid
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config.models import (
    ArmConfig,
    ChassisCanConfig,
    ChassisConfig,
    JakaTcpConfig,
    PhoxiConfig,
    SafetyConfig,
    SafetyModbusConfig,
    ScannerConfig,
    TrackerConfig,
    TrackerStreamConfig,
)
from tandemscan.drivers.agv_can import AgvCanChassis
from tandemscan.drivers.jaka_tcp import JakaTcpArm
from tandemscan.drivers.metronor import MetronorTracker
from tandemscan.drivers.phoxi import PhoxiScanner
from tandemscan.drivers.safety_modbus import ModbusSafetyIO
from tandemscan.pipeline.geometry.frames import from_rpy
from tandemscan.pipeline.stitching.worldmap import VoxelMap
from tandemscan.sim_drivers.emulators.agv_can import ChassisEmulator
from tandemscan.sim_drivers.emulators.jaka import JakaEmulator
from tandemscan.sim_drivers.emulators.safety_modbus import SafetyIoEmulator
from tandemscan.sim_drivers.emulators.tracker import TrackerStreamEmulator, fixed_pose_source
from tandemscan.sim_drivers.fake_harvesters import core as fake_harvesters

N_CALLS = 200


def stats_ms(samples_s: list[float]) -> dict[str, float]:
    a = np.asarray(samples_s) * 1000.0
    return {"median_ms": round(float(np.median(a)), 3), "p99_ms": round(float(np.percentile(a, 99)), 3)}


async def timed(call, n: int = N_CALLS) -> dict[str, float]:
    samples = []
    for _ in range(n):
        t0 = time.perf_counter()
        await call()
        samples.append(time.perf_counter() - t0)
    return stats_ms(samples)


async def bench_arm() -> dict[str, float]:
    emu = JakaEmulator(ArmConfig())
    cmd, status = await emu.start()
    arm = JakaTcpArm(ArmConfig(jaka=JakaTcpConfig(host="127.0.0.1", command_port=cmd, status_port=status)))
    await arm.connect()
    try:
        return await timed(arm.joints)
    finally:
        await arm.close()
        await emu.stop()


async def bench_tracker() -> dict[str, float]:
    stream = TrackerStreamConfig(host="127.0.0.1", port=0)
    emu = TrackerStreamEmulator(stream, fixed_pose_source(from_rpy([0, 0, 3000.0], [3.1, 0.1, 0.2])), rate_hz=60)
    port = await emu.start_tcp()
    tracker = MetronorTracker(TrackerConfig(stream=stream.model_copy(update={"port": port})))
    await tracker.connect()
    try:
        return await timed(tracker.read_pose, 100)
    finally:
        await tracker.close()
        await emu.stop()


async def bench_safety() -> dict[str, float]:
    emu = SafetyIoEmulator(SafetyModbusConfig())
    port = await emu.start()
    io = ModbusSafetyIO(SafetyConfig(modbus=SafetyModbusConfig(host="127.0.0.1", port=port)))
    await io.connect()
    try:
        state = [False]

        async def toggle():
            state[0] = not state[0]
            await io.set_target_light(state[0])

        return await timed(toggle)
    finally:
        await io.close()
        await emu.stop()


async def bench_scanner() -> dict[str, float]:
    with TemporaryDirectory() as tmp:
        producer = Path(tmp) / "fake.cti"
        producer.write_text("fake")
        fake_harvesters.CAMERA.reset()
        cfg = PhoxiConfig(producer_path=producer, harvesters_module=fake_harvesters.__name__)
        scanner = PhoxiScanner(ScannerConfig(phoxi=cfg))
        await scanner.connect()
        try:
            return await timed(scanner.capture, 100)
        finally:
            await scanner.close()


async def bench_chassis() -> tuple[dict[str, float], dict[str, float]]:
    """``move_to(current pose)`` latency, then command-period jitter while a scan is stitched in a thread."""
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    cfg = ChassisConfig(can=ChassisCanConfig(interface="virtual", channel=channel))
    emu = ChassisEmulator(cfg, channel)
    await emu.start()
    chassis = AgvCanChassis(cfg)
    await chassis.connect()
    try:
        latency = await timed(_stay(chassis), 50)
        rng = np.random.default_rng(0)
        scan = rng.uniform(-200, 200, (3_200_000, 3))  # one full-resolution PhoXi frame, mm

        def stitch() -> None:
            VoxelMap(1.0).add(scan)

        chassis.command_times.clear()
        await asyncio.to_thread(stitch)
        period = cfg.can.command_period_s
        gaps = np.diff(np.asarray(chassis.command_times))
        jitter = np.abs(gaps - period)
        return latency, {"p99_ms": round(float(np.percentile(jitter, 99)) * 1000, 3),
                         "max_ms": round(float(jitter.max()) * 1000, 3), "periods": int(len(gaps))}
    finally:
        await chassis.close()
        await emu.stop()


def _stay(chassis: AgvCanChassis):
    async def call() -> None:
        await chassis.move_to(await chassis.odometry())

    return call


async def main() -> dict[str, object]:
    chassis_latency, jitter = await bench_chassis()
    return {
        "arm_joints": await bench_arm(),
        "chassis_move_to_here": chassis_latency,
        "tracker_read_pose": await bench_tracker(),
        "safety_write_coil": await bench_safety(),
        "scanner_capture": await bench_scanner(),
        "can_command_jitter_during_stitch": jitter,
    }


if __name__ == "__main__":
    clean_exit_on_sigterm()
    publish("hil_latency", asyncio.run(main()))

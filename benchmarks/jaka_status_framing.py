"""CPU cost of framing and decoding the JAKA status stream, in % of one core at the controller's push rate.

The status port pushes one JSON object every 8 ms (125 Hz); real objects are 5-9 kB, public notes give up to
15 kB. The objects are the emulator's status padded with the vendor's I/O keys to 6 kB and 15 kB, fed to the
driver's :class:`~tandemscan.drivers.json_stream.JsonObjectFramer` in 1448-byte TCP segments (boundaries fall
anywhere inside objects, two objects share a segment). CPU time is the process time of the framing alone.
Prints one JSON object on its last line: ``{"6kB_125Hz": {"object_bytes": ..., "core_pct": ...}, ...}``.
"""

from __future__ import annotations

import asyncio
import time

from results import publish
from tandemscan.config.models import ArmConfig
from tandemscan.drivers.json_stream import JsonObjectFramer, encode
from tandemscan.sim_drivers.emulators.jaka import JakaBehaviour, JakaEmulator

RATE_HZ = 125.0
SEGMENT_BYTES = 1448
N_OBJECTS = 2000


async def status_object(size_bytes: int) -> bytes:
    emu = JakaEmulator(ArmConfig(), behaviour=JakaBehaviour(status_bytes=size_bytes))
    await emu.start()
    try:
        return encode(emu.status_message())
    finally:
        await emu.stop()


def framing_core_pct(raw_object: bytes) -> float:
    """% of one core that framing ``RATE_HZ`` objects per second like ``raw_object`` costs."""
    stream = raw_object * N_OBJECTS
    segments = [stream[i : i + SEGMENT_BYTES] for i in range(0, len(stream), SEGMENT_BYTES)]
    framer = JsonObjectFramer()
    t0 = time.process_time()
    n = 0
    for segment in segments:
        n += len(framer.feed(segment))
    cpu_s = time.process_time() - t0
    assert n == N_OBJECTS, f"framed {n} of {N_OBJECTS} objects"
    return 100.0 * cpu_s / N_OBJECTS * RATE_HZ


async def main() -> dict[str, dict[str, float]]:
    out = {}
    for label, size in (("6kB_125Hz", 6000), ("15kB_125Hz", 15000)):
        raw = await status_object(size)
        out[label] = {"object_bytes": len(raw), "core_pct": round(framing_core_pct(raw), 2)}
    return out


if __name__ == "__main__":
    publish("jaka_status_framing", asyncio.run(main()))

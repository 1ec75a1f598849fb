"""A small hardware-in-the-loop cell on free local ports: the shipped ``config/hil-cell.toml`` with a 3 x 2 x 1.6 m
box as the part (it builds in a second) and the shipped band plan's steps stated for that box.

Used by the e-stop tests and ``benchmarks/estop_cli.py`` (docs/daemon.md); every emulator listens on 127.0.0.1.
"""

from __future__ import annotations

import random
import socket
import tomllib
from pathlib import Path

import open3d as o3d
import tomli_w
from tandemscan.config import load_config
from tandemscan.config.loader import default_config_path
from tandemscan.pipeline.geometry.part import part_identity, read_mesh_file
from tandemscan.pipeline.planning.plan import Plan

BOX_PLAN = "box-band.toml"


#: the lowest port of the kernel's ephemeral range (``net.ipv4.ip_local_port_range``) where it cannot be read
_EPHEMERAL_LOW_DEFAULT = 32768
#: the lowest port :func:`free_port` hands out
_LOWEST_PORT = 10000
_handed_out: set[int] = set()


def _ephemeral_low() -> int:
    """The lowest port the kernel gives a connection as its local port (and ``bind(0)``)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text(encoding="ascii").split()[0])
    except (OSError, ValueError, IndexError):
        return _EPHEMERAL_LOW_DEFAULT


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now and not handed out before by this process, for an emulator to
    listen on later. It lies below the kernel's ephemeral range: a port ``bind(0)`` gives is in that range, and
    a connection opened before the emulator listens (a driver's to an emulator started earlier) could be given
    it as its local port, so that the emulator could not bind it ("address already in use")."""
    below = range(_LOWEST_PORT, max(_LOWEST_PORT, _ephemeral_low()))
    for port in random.SystemRandom().sample(below, min(200, len(below))):
        if port in _handed_out:
            continue
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    with socket.socket() as s:  # no room below the ephemeral range: any port free now
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_hil_box_cell(folder: Path, band_plan: Path, channel_prefix: str, arm_time_scale: float | None = None
                       ) -> Path:
    """Write ``hil-cell.toml`` (free ports, CAN channels named ``channel_prefix``-..., 6 calibration poses, the
    emulated arm at ``arm_time_scale`` of real time if given), ``box.stl`` and :data:`BOX_PLAN` (the steps of
    ``band_plan`` stated for the box) into ``folder``; returns the config file."""
    mesh = o3d.geometry.TriangleMesh.create_box(3000.0, 2000.0, 1600.0).translate((-1500.0, -1000.0, 0.0))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(folder / "box.stl"), mesh)
    shipped = default_config_path().parent / "hil-cell.toml"
    data = tomllib.loads(shipped.read_text(encoding="utf-8"))
    data["part"] = {"mesh": str(folder / "box.stl")}
    data["scanner"]["phoxi"]["producer_path"] = str(load_config(shipped).scanner.phoxi.producer_path)
    data["arm"]["jaka"] |= {"command_port": free_port(), "status_port": free_port()}
    data["tracker"]["stream"]["port"] = free_port()
    data["safety"]["modbus"]["port"] = free_port()
    data["measure_chassis"]["can"]["channel"] = f"{channel_prefix}-m-{free_port()}"
    data["tracking_chassis"]["can"]["channel"] = f"{channel_prefix}-t-{free_port()}"
    data["calibration"] = {"poses": 6}
    if arm_time_scale is not None:
        data["hil"]["arm_time_scale"] = arm_time_scale
    path = folder / "hil-cell.toml"
    path.write_bytes(tomli_w.dumps(data).encode())
    band = Plan.load(band_plan)
    Plan(name="band on the box", part="box.stl", part_identity=part_identity(read_mesh_file(folder / "box.stl")),
         steps=band.steps).save(folder / BOX_PLAN)
    return path

"""systemd integration: the unit verifies cleanly and is hardened; sd_notify READY/STATUS/WATCHDOG over a fake
``$NOTIFY_SOCKET``; the watchdog pings come from the event loop (a blocked loop stops them)."""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from tandemscan.daemon.notify import Notifier

SYSTEMD = Path(__file__).resolve().parents[2] / "systemd"
UNIT = SYSTEMD / "tandemscan.service"


def unit_settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if line and not line.startswith(("#", "[")) and "=" in line:
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_unit_verifies_without_any_output(tmp_path):
    # verify checks that ExecStart exists: point it at this checkout's console script
    exe = Path(sys.executable).parent / "tandemscan"
    assert exe.exists(), "install the package (pip install -e .) first"
    unit = tmp_path / "tandemscan.service"
    unit.write_text(UNIT.read_text().replace("/opt/tandemscan/bin/tandemscan", str(exe)))
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout == "" and r.stderr == "", r.stdout + r.stderr
    sec = subprocess.run(["systemd-analyze", "security", "--offline=true", "--threshold=30", str(unit)],
                         capture_output=True, text=True, timeout=60)
    assert sec.returncode == 0, sec.stdout[-2000:]  # exposure <= 3.0 on systemd's 0-10 display scale


def test_unit_is_a_hardened_notify_service():
    s = unit_settings()
    assert s["Type"] == ["notify"] and s["Restart"] == ["on-failure"] and s["StateDirectory"] == ["tandemscan"]
    assert float(s["WatchdogSec"][0].rstrip("s")) > 0
    for key in ("NoNewPrivileges", "PrivateTmp", "ProtectHome"):
        assert s[key] == ["yes"], key
    assert s["ProtectSystem"] == ["strict"]
    assert set(s["RestrictAddressFamilies"][0].split()) == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_CAN"}
    assert any("ttyUSB" in d for d in s["DeviceAllow"]) and s["DevicePolicy"] == ["closed"]
    assert "PrivateNetwork" not in s  # CAN is a network interface


def _namespaces_work() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "true"], capture_output=True)
    return probe.returncode == 0


def _serve(state: Path, port: int, wrap: list[str] = ()) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "tandemscan"
    env = {**os.environ, "TANDEMSCAN_STATE_DIR": str(state)}
    return subprocess.run([*wrap, str(exe), "serve", "--port", str(port)], capture_output=True, text=True, env=env,
                          timeout=120)


def _one_line(r: subprocess.CompletedProcess, status: int, start: str) -> str:
    lines = r.stderr.strip().splitlines()
    assert r.returncode == status and len(lines) == 1 and lines[0].startswith(start), (r.returncode, r.stderr)
    return lines[0]


@pytest.mark.slow
def test_start_up_errors_are_one_line_and_a_status_systemd_does_not_restart_on(tmp_path):
    """Issue 42 row 5: an unusable state directory or a taken port ends ``serve`` in one line and its own exit
    status (documented), before any device is touched; the unit does not restart on a permanent one."""
    in_the_way = tmp_path / "state"
    in_the_way.write_text("a file where the state directory should be")
    line = _one_line(_serve(in_the_way, 0), 78, "daemon not started: state directory")
    assert str(in_the_way) in line
    if _namespaces_work():  # a read-only mount, as on a site whose /var/lib went read-only
        ro = tmp_path / "ro"
        ro.mkdir()
        script = f'mount -t tmpfs -o ro tmpfs {ro} && exec "$@"'
        r = _serve(ro, 0, ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script, "sh"])
        assert "Read-only file system" in _one_line(r, 78, "daemon not started: state directory")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = _serve(tmp_path / "fresh", port)
    assert "in use" in _one_line(r, 75, f"daemon not started: cannot listen on 127.0.0.1:{port}")
    assert not (tmp_path / "fresh").exists()  # refused before the state or any device was touched
    assert unit_settings()["RestartPreventExitStatus"] == ["2 78"]
    exit_table = (SYSTEMD.parent / "docs" / "cli.md").read_text()  # the exit statuses of the command line
    assert "| 78 | `daemon not started:` |" in exit_table and "| 75 | `daemon not started:` |" in exit_table


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None or shutil.which("systemd-tmpfiles") is None,
                    reason="systemd-sysusers/systemd-tmpfiles not installed")
def test_sysusers_and_tmpfiles_apply_to_an_empty_root(tmp_path):
    (tmp_path / "etc").mkdir()
    subprocess.run(["systemd-sysusers", f"--root={tmp_path}", str(SYSTEMD / "tandemscan.sysusers")], check=True,
                   capture_output=True, timeout=60)
    passwd = (tmp_path / "etc" / "passwd").read_text()
    assert passwd.startswith("tandemscan:") and "/var/lib/tandemscan" in passwd
    assert "dialout:x:" in (tmp_path / "etc" / "group").read_text()
    subprocess.run(["systemd-tmpfiles", "--create", f"--root={tmp_path}", str(SYSTEMD / "tandemscan.tmpfiles")],
                   check=True, capture_output=True, timeout=60)
    env = tmp_path / "etc" / "tandemscan" / "tandemscan.env"
    assert env.is_file() and (env.stat().st_mode & 0o777) == 0o600


@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.setblocking(False)
    yield sock, str(path)
    sock.close()


def received(sock) -> list[tuple[float, str]]:
    out = []
    while True:
        try:
            out.append((time.monotonic(), sock.recv(4096).decode()))
        except BlockingIOError:
            return out


async def pings(n: Notifier, count: int) -> None:
    """Wait until ``n`` has sent ``count`` watchdog pings (the timeout only against a hang)."""
    async with asyncio.timeout(10):
        while len(n.ping_times_s) < count:
            await asyncio.sleep(0.005)


async def test_ready_status_and_watchdog_reach_the_socket(notify_socket):
    sock, path = notify_socket
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "100000", "WATCHDOG_PID": str(os.getpid())}
    n = Notifier(env)
    assert n.enabled and n.watchdog_s == pytest.approx(0.1)
    assert n.ready("all devices connected")
    task = asyncio.create_task(n.watchdog_loop())
    await pings(n, 3)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    msgs = [m for _, m in received(sock)]
    assert msgs[0] == "READY=1\nSTATUS=all devices connected"
    assert msgs[1:].count("WATCHDOG=1") == len(n.ping_times_s) >= 3
    times = list(n.ping_times_s)
    # every 50 ms (half the interval), never sooner (a loaded machine can only make the gaps longer)
    assert min(b - a for a, b in zip(times, times[1:], strict=False)) >= 0.045


async def test_a_blocked_event_loop_stops_the_watchdog(notify_socket):
    sock, path = notify_socket
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "40000"})
    task = asyncio.create_task(n.watchdog_loop())
    await pings(n, 2)
    blocked_from = time.monotonic()
    time.sleep(0.3)  # the loop is stuck: no ping may go out meanwhile
    blocked_to = time.monotonic()
    await pings(n, len(n.ping_times_s) + 1)  # the loop free again: the pings resume
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert set(m for _, m in received(sock)) == {"WATCHDOG=1"}
    times = list(n.ping_times_s)  # when the loop sent each ping
    assert [t for t in times if blocked_from < t < blocked_to] == [] and times[-1] >= blocked_to, times


def test_outside_systemd_nothing_is_sent():
    n = Notifier({})
    assert not n.enabled and not n.ready() and n.watchdog_s is None
    assert Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}).watchdog_s is None
    assert not Notifier({"NOTIFY_SOCKET": "/nonexistent/notify.sock"}).status("x")


async def test_abstract_socket_address():
    name = f"tandemscan-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    try:
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).status("hello")
        assert sock.recv(100) == b"STATUS=hello"
    finally:
        sock.close()


async def test_daemon_says_ready_once_devices_are_connected(notify_socket, tmp_path, sim_config):
    from tandemscan.daemon.service import Daemon

    sock, path = notify_socket
    daemon = Daemon(sim_config, tmp_path / "state", notifier=Notifier({"NOTIFY_SOCKET": path}))
    await daemon.start()
    try:
        msgs = [m for _, m in received(sock)]
        assert daemon.supervisor.all_connected
        assert msgs == ["STATUS=connecting devices", "READY=1\nSTATUS=ready: all devices connected"]
    finally:
        await daemon.close()
    assert [m for _, m in received(sock)] == ["STOPPING=1"]

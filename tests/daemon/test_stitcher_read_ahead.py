"""The end of a job reads its scans while the last scans' pairs still register (daemon/jobs/stitcher.py)."""

from __future__ import annotations

import asyncio
import threading
import time
from types import SimpleNamespace

import pytest
from tandemscan.daemon.jobs import finish, stitcher


@pytest.fixture
def end_of_job(monkeypatch):
    """``finish.load_scans`` and ``finish.finish_job`` replaced by recorders (the scans read: an event set when
    read; a read waits for ``release`` first) and the reads kept ahead in a fresh ``stitcher._LOADED``."""
    read, release, handed = threading.Event(), threading.Event(), {}
    release.set()
    loaded = object()

    def load_scans(job):
        assert release.wait(10.0)
        read.set()
        return loaded

    def finish_job(job, started, measured_at, online, stages, loaded=None):
        handed.update(loaded=loaded, stages=stages, online=online)
        return "finished"

    monkeypatch.setattr(finish, "load_scans", load_scans)
    monkeypatch.setattr(finish, "finish_job", finish_job)
    monkeypatch.setattr(stitcher, "_LOADED", {})
    return SimpleNamespace(read=read, release=release, handed=handed, loaded=loaded)


async def _settled(worldmap: stitcher.LocalWorldMap) -> None:
    """Wait until the map is back with its owner (a read ahead still running holds it)."""
    for _ in range(200):
        if worldmap.map is not None:
            return
        await asyncio.sleep(0.05)


async def test_the_scans_are_read_while_the_last_pairs_register(end_of_job, monkeypatch, tmp_path):
    worldmap = stitcher.LocalWorldMap(1.0)

    async def pair_outcomes():  # the last pairs finish only once the scans were read: read after them, it hangs
        assert await asyncio.to_thread(end_of_job.read.wait, 10.0), "scans not read while the pairs registered"
        return "online work", 1.5

    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    job = SimpleNamespace(job_dir=tmp_path / "job", worldmap=None)
    assert await worldmap.finish(job, 0.0, time.monotonic()) == "finished"
    handed = end_of_job.handed
    assert handed["loaded"] is end_of_job.loaded and handed["online"] == "online work"
    assert "read_s" in handed["stages"] and handed["stages"]["pairs_cpu_s_while_measuring"] == 1.5
    assert stitcher._LOADED == {}  # handed over, not kept
    assert worldmap.map is not None  # the map is back with its owner


@pytest.mark.parametrize("ending", ["pair worker died", "cancelled"])
async def test_a_job_ended_before_its_end_leaves_no_scans_behind(end_of_job, monkeypatch, tmp_path, ending):
    worldmap = stitcher.LocalWorldMap(1.0)
    end_of_job.release.clear()  # the read is still under way when the job ends
    waiting = asyncio.Event()

    async def pair_outcomes():
        waiting.set()
        if ending == "cancelled":
            await asyncio.sleep(30.0)
        raise RuntimeError("pair worker died")

    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    job = SimpleNamespace(job_dir=tmp_path / "job", worldmap=None)
    finishing = asyncio.ensure_future(worldmap.finish(job, 0.0, time.monotonic()))
    await waiting.wait()
    if ending == "cancelled":
        finishing.cancel()
    with pytest.raises(asyncio.CancelledError if ending == "cancelled" else RuntimeError):
        await finishing
    assert not end_of_job.read.is_set()  # the job ended without waiting for the read
    end_of_job.release.set()
    await _settled(worldmap)
    assert end_of_job.read.is_set() and worldmap.map is not None
    async with asyncio.timeout(10):  # the read's task ends after the map is handed back (only against a hang)
        while stitcher._LOADED != {}:  # nothing kept
            await asyncio.sleep(0.005)
    assert not end_of_job.handed  # the end of the job did not run


async def test_scans_that_could_not_be_read_ahead_are_read_by_the_end_of_the_job(end_of_job, monkeypatch, tmp_path):
    def load_scans(job):
        raise OSError("disk hiccup")

    monkeypatch.setattr(finish, "load_scans", load_scans)
    worldmap = stitcher.LocalWorldMap(1.0)

    async def pair_outcomes():
        return None, 0.0

    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    job = SimpleNamespace(job_dir=tmp_path / "job", worldmap=None)
    assert await worldmap.finish(job, 0.0, time.monotonic()) == "finished"
    handed = end_of_job.handed
    assert handed["loaded"] is None and "read_s" not in handed["stages"]  # finish_job reads them itself

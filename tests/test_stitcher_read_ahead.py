"""The end of a job reads its scans while the last scans' pairs still register (daemon/stitcher.py)."""

from __future__ import annotations

import asyncio
import threading
import time
from types import SimpleNamespace

import pytest
from tandemscan.daemon import finish, stitcher


@pytest.fixture
def end_of_job(monkeypatch):
    """``finish.load_scans`` and ``finish.finish_job`` replaced by recorders: the scans read (an event set
    when read) and what the end of the job was handed."""
    read, handed = threading.Event(), {}
    loaded = object()

    def load_scans(job):
        read.set()
        return loaded

    def finish_job(job, started, measured_at, online, stages, loaded=None):
        handed.update(loaded=loaded, stages=stages, online=online)
        return "finished"

    monkeypatch.setattr(finish, "load_scans", load_scans)
    monkeypatch.setattr(finish, "finish_job", finish_job)
    return SimpleNamespace(read=read, handed=handed, loaded=loaded)


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
    assert handed["stages"]["read_s"] >= 0.0 and handed["stages"]["pairs_cpu_s_while_measuring"] == 1.5
    assert str(job.job_dir) not in stitcher._LOADED  # handed over, not kept
    assert worldmap.map is not None  # the map is back with its owner


async def test_a_failed_pair_hand_over_leaves_no_scans_behind(end_of_job, monkeypatch, tmp_path):
    worldmap = stitcher.LocalWorldMap(1.0)

    async def pair_outcomes():
        await asyncio.to_thread(end_of_job.read.wait, 10.0)
        raise RuntimeError("pair worker died")

    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    job = SimpleNamespace(job_dir=tmp_path / "job", worldmap=None)
    with pytest.raises(RuntimeError, match="pair worker died"):
        await worldmap.finish(job, 0.0, time.monotonic())
    assert end_of_job.read.is_set() and str(job.job_dir) not in stitcher._LOADED
    assert not end_of_job.handed  # the end of the job did not run


async def test_scans_that_could_not_be_read_ahead_are_read_by_the_end_of_the_job(monkeypatch, tmp_path):
    handed = {}

    def load_scans(job):
        raise OSError("disk hiccup")

    def finish_job(job, started, measured_at, online, stages, loaded=None):
        handed.update(loaded=loaded, stages=stages)
        return "finished"

    monkeypatch.setattr(finish, "load_scans", load_scans)
    monkeypatch.setattr(finish, "finish_job", finish_job)
    worldmap = stitcher.LocalWorldMap(1.0)

    async def pair_outcomes():
        return None, 0.0

    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    job = SimpleNamespace(job_dir=tmp_path / "job", worldmap=None)
    assert await worldmap.finish(job, 0.0, time.monotonic()) == "finished"
    assert handed["loaded"] is None and "read_s" not in handed["stages"]  # finish_job reads them itself

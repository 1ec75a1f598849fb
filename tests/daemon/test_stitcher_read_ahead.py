"""The end of a job where the map lives (daemon/jobs/stitcher.py): its scans read while the pair worker finishes
the last scans, and with the joint refinement its outputs made while the check pairs still register, the report
alone waiting for them."""

from __future__ import annotations

import asyncio
import threading
import time
from types import SimpleNamespace

import pytest
from tandemscan.daemon.jobs import finish, stitcher


@pytest.fixture
def end_of_job(monkeypatch):
    """``finish.load_scans``, ``finish.finish_outputs`` and ``finish.report_job`` replaced by recorders (the scans
    read: an event set when read; a read waits for ``release`` first; ``events``: the order of the end's stages)
    and the reads and outputs kept in fresh ``stitcher._LOADED`` / ``_OUTPUTS``."""
    read, release, handed, events = threading.Event(), threading.Event(), {}, []
    release.set()
    loaded, outputs = object(), SimpleNamespace(final=SimpleNamespace(worldmap=None))  # no tiles to remove

    def load_scans(job):
        assert release.wait(10.0)
        read.set()
        return loaded

    def finish_outputs(job, started, measured_at, online, stages, loaded=None):
        events.append("outputs")
        handed.update(loaded=loaded, stages=dict(stages), online=online)
        return outputs

    def report_job(kept, measured_at, later, stages=None):
        events.append("report")
        handed.update(outputs=kept, later=later, later_stages=dict(stages or {}))
        return "finished"

    monkeypatch.setattr(finish, "load_scans", load_scans)
    monkeypatch.setattr(finish, "finish_outputs", finish_outputs)
    monkeypatch.setattr(finish, "report_job", report_job)
    monkeypatch.setattr(stitcher, "_LOADED", {})
    monkeypatch.setattr(stitcher, "_OUTPUTS", {})
    return SimpleNamespace(read=read, release=release, handed=handed, loaded=loaded, outputs=outputs, events=events)


def _job(tmp_path, joint: bool) -> SimpleNamespace:
    return SimpleNamespace(job_dir=tmp_path / "job", worldmap=None,
                           config=SimpleNamespace(correction=SimpleNamespace(joint=joint)))


def _check_pairs_registering(worldmap, monkeypatch) -> None:
    """``worldmap``'s pair worker replaced: nothing for the joint refinement, its check pairs registering for 30 s."""

    async def joint_work():
        return None

    async def pair_outcomes():
        await asyncio.sleep(30.0)

    monkeypatch.setattr(worldmap, "_joint_work", joint_work)
    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)


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
    assert await worldmap.finish(_job(tmp_path, joint=False), 0.0, time.monotonic()) == "finished"
    handed = end_of_job.handed
    assert handed["loaded"] is end_of_job.loaded and handed["online"] == "online work"
    assert "read_s" in handed["stages"] and handed["stages"]["pairs_cpu_s_while_measuring"] == 1.5
    assert handed["outputs"] is end_of_job.outputs and handed["later"] is None  # the graph took every pair
    assert stitcher._LOADED == {} and stitcher._OUTPUTS == {}  # handed over, not kept
    assert worldmap.map is not None  # the map is back with its owner


async def test_with_the_joint_refinement_the_outputs_do_not_wait_for_the_check_pairs(end_of_job, monkeypatch,
                                                                                     tmp_path):
    """The order of events, not timings: the check pairs are handed over only once the outputs were made (were
    the outputs waiting for them, this would hang), and the report comes after both."""
    worldmap = stitcher.LocalWorldMap(1.0)
    events = end_of_job.events

    async def joint_work():
        events.append("joint work")
        return "prepared scans"

    async def pair_outcomes():
        async with asyncio.timeout(10):  # only against a hang
            while "outputs" not in events:
                await asyncio.sleep(0.005)
        events.append("check pairs")
        return "check pairs", 2.5

    monkeypatch.setattr(worldmap, "_joint_work", joint_work)
    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    assert await worldmap.finish(_job(tmp_path, joint=True), 0.0, time.monotonic()) == "finished"
    assert events == ["joint work", "outputs", "check pairs", "report"]
    handed = end_of_job.handed
    assert handed["online"] == "prepared scans" and "joint_backlog_s" in handed["stages"]
    assert "pair_backlog_s" not in handed["stages"]
    assert handed["later"] == "check pairs" and handed["later_stages"]["pairs_cpu_s_while_measuring"] == 2.5
    assert handed["later_stages"]["pair_backlog_s"] >= 0
    assert stitcher._OUTPUTS == {} and worldmap.map is not None


async def test_check_pairs_the_worker_could_not_hand_over_leave_the_report_to_register_them(end_of_job, monkeypatch,
                                                                                          tmp_path):
    worldmap = stitcher.LocalWorldMap(1.0)

    async def joint_work():
        return "prepared scans"

    async def pair_outcomes():
        raise RuntimeError("pair worker died")

    monkeypatch.setattr(worldmap, "_joint_work", joint_work)
    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    assert await worldmap.finish(_job(tmp_path, joint=True), 0.0, time.monotonic()) == "finished"
    assert end_of_job.events == ["outputs", "report"]
    assert end_of_job.handed["later"] is None and end_of_job.handed["later_stages"] == {}


async def test_a_job_cancelled_while_its_check_pairs_register_keeps_no_outputs(end_of_job, monkeypatch, tmp_path):
    worldmap = stitcher.LocalWorldMap(1.0)
    stopped = asyncio.Event()

    async def joint_work():
        return "prepared scans"

    async def pair_outcomes():
        try:
            await asyncio.sleep(30.0)
        finally:
            stopped.set()

    monkeypatch.setattr(worldmap, "_joint_work", joint_work)
    monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
    finishing = asyncio.ensure_future(worldmap.finish(_job(tmp_path, joint=True), 0.0, time.monotonic()))
    async with asyncio.timeout(10):  # only against a hang
        while "outputs" not in end_of_job.events or stitcher._OUTPUTS == {}:
            await asyncio.sleep(0.005)
    finishing.cancel()
    with pytest.raises(asyncio.CancelledError):
        await finishing
    assert stopped.is_set()  # the check pairs' wait ended with the job (the pair worker stops)
    assert stitcher._OUTPUTS == {} and "report" not in end_of_job.events


def test_the_outputs_of_a_cancelled_job_are_dropped_off_the_event_loop_before_it_closes(end_of_job, monkeypatch,
                                                                                        tmp_path):
    """A job of the map in this process (``LocalWorldMap``) cancelled after its outputs were made: dropping them (its
    tiles' files removed, its compute backend closed: blocking I/O) runs in a thread, not on the event loop, and is
    done once the loop's run has ended."""
    dropped = []

    def drop_outputs(outputs):
        time.sleep(0.3)  # as slow as a Dask client's close
        dropped.append((outputs, threading.current_thread()))

    monkeypatch.setattr(finish, "drop_outputs", drop_outputs)

    async def cancelled_after_its_outputs() -> threading.Thread:
        worldmap = stitcher.LocalWorldMap(1.0)

        _check_pairs_registering(worldmap, monkeypatch)
        finishing = asyncio.ensure_future(worldmap.finish(_job(tmp_path, joint=True), 0.0, time.monotonic()))
        async with asyncio.timeout(10):  # only against a hang
            while stitcher._OUTPUTS == {}:
                await asyncio.sleep(0.005)
        finishing.cancel()
        with pytest.raises(asyncio.CancelledError):
            await finishing
        async with asyncio.timeout(10):  # handed to the drop (only against a hang)
            while stitcher._OUTPUTS != {}:
                await asyncio.sleep(0.005)
        return threading.current_thread()

    loop_thread = asyncio.run(cancelled_after_its_outputs())
    assert [outputs for outputs, _ in dropped] == [end_of_job.outputs]  # done when the loop's run returned
    assert dropped[0][1] is not loop_thread


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
    finishing = asyncio.ensure_future(worldmap.finish(_job(tmp_path, joint=False), 0.0, time.monotonic()))
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
    assert await worldmap.finish(_job(tmp_path, joint=False), 0.0, time.monotonic()) == "finished"
    handed = end_of_job.handed
    assert handed["loaded"] is None and "read_s" not in handed["stages"]  # finish_outputs reads them itself


_REAL_FINISH_OUTPUTS = stitcher._finish_outputs  # imported in the map's process too: the real one there


def finish_outputs_leaving_a_tile(job, key, started, measured_at, online, stages):
    """In the map's process (a module function: it pickles by name): the real ``stitcher._finish_outputs`` around a
    ``finish.finish_outputs`` whose outputs hold a tiled cloud of one tile file, written here."""
    from tandemscan.pipeline.stitching.tiles import TileCloud, TiledCloud

    tile = TileCloud(0, "tiles/merge-tile-00000.npz", 1)
    (job.job_dir / "tiles").mkdir(parents=True, exist_ok=True)
    (job.job_dir / tile.file).write_bytes(b"tile")
    cloud = TiledCloud(1.0, str(job.job_dir), (tile,))
    finish.finish_outputs = lambda *args: SimpleNamespace(final=SimpleNamespace(worldmap=cloud))
    return _REAL_FINISH_OUTPUTS(job, key, started, measured_at, online, stages)


async def test_a_job_cancelled_between_its_outputs_and_its_report_leaves_no_tiles_where_its_map_lives_apart(
        monkeypatch, tmp_path):
    """The daemon's map in its own process (``ProcessWorldMap``): a job with a tiled cloud cancelled while its
    check pairs register, after its outputs were made, leaves none of its tiles' files (removed from the job's
    process, which never held the outputs)."""
    worldmap = stitcher.ProcessWorldMap(1.0)
    try:
        monkeypatch.setattr(stitcher, "_finish_outputs", finish_outputs_leaving_a_tile)
        made = asyncio.Event()

        async def joint_work():
            return None

        async def pair_outcomes():
            made.set()  # the outputs run beside the check pairs: wait for their tile below
            await asyncio.sleep(30.0)

        monkeypatch.setattr(worldmap, "_joint_work", joint_work)
        monkeypatch.setattr(worldmap, "pair_outcomes", pair_outcomes)
        job = _job(tmp_path, joint=True)
        tile = job.job_dir / "tiles" / "merge-tile-00000.npz"
        finishing = asyncio.ensure_future(worldmap.finish(job, 0.0, time.monotonic()))
        await made.wait()
        async with asyncio.timeout(60):  # only against a hang (the map's process starts and imports first)
            while not tile.exists():
                await asyncio.sleep(0.02)
            await asyncio.sleep(0.5)  # the outputs' run hands its result back
        finishing.cancel()
        with pytest.raises(asyncio.CancelledError):
            await finishing
        async with asyncio.timeout(10):
            while tile.exists():
                await asyncio.sleep(0.02)
        assert not list((job.job_dir / "tiles").iterdir())
    finally:
        worldmap.close()


def ending_at_length(job, key, started, measured_at, online, stages):
    """In the map's process (a module function: it pickles by name): the end of a job under way, its scratch files
    written as its stages write them (a scan prepared for the joint refinement, a scan's shard of the tiled merge in
    the scan store, the job folder; a thinned copy kept beside the scans, as a lean map's merge keeps it) and more
    to come."""
    from tandemscan.pipeline.io.raw_scan import THINNED_FOLDER
    from tandemscan.pipeline.registration.correction import JOINT_FOLDER
    from tandemscan.pipeline.stitching.tiles import TILES_FOLDER

    for file in (f"{JOINT_FOLDER}/prepared.npz", f"{TILES_FOLDER}/shards-0/0.npz", f"{THINNED_FOLDER}/scan-0000.npz"):
        (job.job_dir / file).parent.mkdir(parents=True, exist_ok=True)
        (job.job_dir / file).write_bytes(b"scratch")
    time.sleep(60.0)


async def test_a_job_cancelled_in_its_end_leaves_no_scratch_files_once_its_map_is_closed(monkeypatch, tmp_path):
    """The daemon's map in its own process, cancelled while the end of the job runs there: the journal closes the
    map (its process ends, the end's work and its clean-up with it) and removes what that work left in the scan
    store (the scans prepared for the joint refinement, the tiles) and the thinned copies beside the scans."""
    from tandemscan.daemon.jobs.journal import close_map

    worldmap = stitcher.ProcessWorldMap(1.0)
    job = _job(tmp_path, joint=True)
    scratch = [job.job_dir / name for name in ("joint", "tiles", "thinned")]
    try:
        monkeypatch.setattr(stitcher, "_finish_outputs", ending_at_length)

        _check_pairs_registering(worldmap, monkeypatch)
        finishing = asyncio.ensure_future(worldmap.finish(job, 0.0, time.monotonic()))
        async with asyncio.timeout(60):  # only against a hang (the map's process starts and imports first)
            while not all(folder.exists() for folder in scratch):
                await asyncio.sleep(0.02)
        finishing.cancel()
        with pytest.raises(asyncio.CancelledError):
            await finishing
    finally:
        await asyncio.to_thread(close_map, worldmap, job.job_dir, job.job_dir)
    assert job.job_dir.exists() and not any(folder.exists() for folder in scratch)

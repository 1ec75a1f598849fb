"""The end of a job's file I/O on a small band job: report.json built once with the journal's resumes in it and
written once by its one writer (``pipeline.job_report.write_job_report``), the simulator's scores after it beside it,
and each raw scan file read at most twice after it is written (docs/end-of-job.md)."""

from __future__ import annotations

import json
import os
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest
from job_reports import report_with_ground_truth
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.io.raw_scan import THINNED_FOLDER
from tandemscan.pipeline.job_report import REPORT_FILE, JobHistory, JobReport, write_job_report
from tandemscan.pipeline.planning.plan import Plan, Scan
from tandemscan.sim_drivers.cell import with_surveyed_mounts

READ_COUNTER = '''"""Installed by tests/e2e/test_end_of_job_io.py in every Python process the job starts (the E57's,
the pair and map workers): each np.load of a file in a scans/ folder appends its name to $SCAN_READ_LOG."""
import os
from pathlib import Path

import numpy as np

_load = np.load


def _counting_load(file, *args, **kwargs):
    if Path(file).parent.name == "scans":
        with open(os.environ["SCAN_READ_LOG"], "a", encoding="utf-8") as log:
            log.write(Path(file).name + "\\n")
    return _load(file, *args, **kwargs)


np.load = _counting_load
'''


def count_reads_in_child_processes(folder: Path, monkeypatch) -> Callable[[], Counter[str]]:
    """Count the raw scan reads of the processes the job starts from now on (spawned: they import
    ``sitecustomize`` from ``PYTHONPATH`` at start-up, here :data:`READ_COUNTER`); the counts by file name so far."""
    folder.mkdir()
    (folder / "sitecustomize.py").write_text(READ_COUNTER, encoding="utf-8")
    log = folder / "reads.log"
    log.touch()
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, (str(folder), os.environ.get("PYTHONPATH")))))
    monkeypatch.setenv("SCAN_READ_LOG", str(log))
    return lambda: Counter(log.read_text(encoding="utf-8").split())


@pytest.mark.parametrize(("backend", "tile_mm"), [("local", 0.0), ("local", 20.0),
                                                  pytest.param("dask", 20.0, marks=pytest.mark.slow)],
                         ids=["one-map", "tiles", "dask-tiles"])
async def test_a_job_writes_report_json_once_and_reads_each_scan_file_at_most_twice(sim_config, tmp_path,
                                                                                      monkeypatch, backend, tile_mm,
                                                                                      scan_reads):
    """A two-scan band job on the simulated cell with a journal's history: report.json does not exist before the
    one writer's call, is written by it once, and nothing writes it after; it holds the journal's resumes and reads
    back into the model written; the simulator's observer scores the job after it, into ground_truth.json beside
    it, and the two read back into the model the job returned. Each raw scan file is read twice after it
    was written (the merge at the corrected poses, the E57 in a process of its own: counted there and in every
    process the job starts), its scores included: the map and the thinned copies
    are made from the scan's arrays, the pair worker is handed the copy, the tracker stitch's score takes the map
    stitched while measuring. Merged by tiles of 20 mm (``[compute] tile_mm``: each scan reaches about twenty), the
    same: each scan is read once and cut into its tiles' shards (``tiles.place_scan``), and only the tiles are left
    until the exports have read them. On the dask backend (a ``LocalCluster`` of one worker) too: the workers'
    correction and check pairs read the thinned copies the map's process kept beside the scans
    (``raw_scan.keep_thinned_copy``, removed when the job ends), the workers place each scan once; this process
    reads each scan once, for the simulator's score of the tracker stitch alone (no map was stitched while
    measuring there)."""
    from tandemscan.daemon.jobs import finish
    from tandemscan.pipeline.stitching import tiles

    child_reads = count_reads_in_child_processes(tmp_path / "child-reads", monkeypatch)
    writes: list[tuple[JobReport, tuple[int, int, int]]] = []

    def writer(report: JobReport, job_dir: Path) -> Path:
        assert not (Path(job_dir) / REPORT_FILE).exists()  # nobody wrote it before the one writer
        path = write_job_report(report, job_dir)
        st = path.stat()
        writes.append((report, (st.st_ino, st.st_mtime_ns, st.st_size)))
        return path

    monkeypatch.setattr(finish, "write_job_report", writer)
    score = finish.score_ground_truth
    scored_after: list[bool] = []

    def observer(job, inspection, tracker_stitch):
        scored_after.append((Path(job.job_dir) / REPORT_FILE).is_file())
        return score(job, inspection, tracker_stitch)

    monkeypatch.setattr(finish, "score_ground_truth", observer)
    tiles_reached: list[int] = []  # per scan placed, the tiles its shards went to
    place = tiles.place_scan

    def place_scan(unit):
        shards = place(unit)
        tiles_reached.append(len(shards))
        return shards

    monkeypatch.setattr(tiles, "place_scan", place_scan)
    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    plan = plan.model_copy(update={"steps": plan.steps[: scans[1] + 1]})  # the first two scans only
    compute = sim_config.compute.model_copy(update={"tile_mm": tile_mm, "backend": backend, "dask_workers": 1})
    config = sim_config.model_copy(update={"inspection": sim_config.inspection.model_copy(update={"in_job": False}),
                                           "compute": compute})
    history = JobHistory(({"step": scans[1], "kind": "scan", "fresh_reading": True},), 2)

    async def journal_history() -> JobHistory:
        return history

    async with CellSession(config) as session:
        config = with_surveyed_mounts(config, session.cell.simulation, tmp_path)
        result = await JobRunner(session, plan, config, tmp_path / "job", history=journal_history).run()
    ((report, written),) = writes
    st = result.report_file.stat()
    assert (st.st_ino, st.st_mtime_ns, st.st_size) == written  # nothing wrote it after
    doc = json.loads(result.report_file.read_text())
    assert json.loads(json.dumps(report.to_json())) == doc
    assert report.scan_log == result.job_report.scan_log and report.history == history
    assert doc["resumes"] == [dict(history.resumes[0])] and doc["attempts"] == 2
    # the simulator's observer scored the job once report.json was written, into its own file beside it
    assert scored_after == [True] and "ground_truth" not in doc and "before" not in doc["correction"]
    assert result.job_report == replace(report, ground_truth=result.job_report.ground_truth)
    full = json.loads(json.dumps(result.report))
    assert full == report_with_ground_truth(result.job_dir)
    assert full["scans"] == 2 and full["correction"]["enabled"] and "before" in full["correction"]
    assert full["ground_truth"]["pose_err_mm_median"] > 0 and full["ground_truth"]["scoring_s"] >= 0
    files = [entry["file"] for entry in doc["scan_log"]]
    if backend == "dask":  # the product's reads in the workers and the E57's process; here the observer's alone
        assert child_reads() == dict.fromkeys(files, 2) and scan_reads == dict.fromkeys(files, 1)
    else:
        assert scan_reads + child_reads() == dict.fromkeys(files, 2)
        assert len(tiles_reached) == (2 if tile_mm else 0) and all(n >= 5 for n in tiles_reached)  # scans span tiles
    assert not (result.job_dir / "tiles").exists() or not list((result.job_dir / "tiles").iterdir())
    assert not (result.job_dir / THINNED_FOLDER).exists()
    # the pair worker's copies are the end of the job's: its pairs are taken from the cache by their keys
    c = doc["correction"]
    assert c["pairs"] >= 1 and c["pairs_registered_while_measuring"] >= c["pairs"] + len(c["pairs_dropped"])


async def test_a_job_merged_by_tiles_exports_from_them_and_removes_them(sim_config, tmp_path):
    """The two-scan band job with ``[compute] tile_mm``: the cloud stays in its tiles' files (``tiles.TiledCloud``),
    cloud.ply, the E57's merged scan and the inspection read them, the report counts the same cloud, and the tiles'
    files are gone once the job is done."""
    import pye57
    from tandemscan.pipeline.io.cloud_io import read_ply

    plan = Plan.load(default_plan_path())
    scans = [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]
    plan = plan.model_copy(update={"steps": plan.steps[: scans[1] + 1]})
    inspection = sim_config.inspection.model_copy(update={"views": ("isometric",), "map_width_px": 300})
    config = sim_config.model_copy(update={"inspection": inspection,
                                           "compute": sim_config.compute.model_copy(update={"tile_mm": 100.0})})
    async with CellSession(config) as session:
        config = with_surveyed_mounts(config, session.cell.simulation, tmp_path)
        result = await JobRunner(session, plan, config, tmp_path / "job").run()
    report = result.report
    assert report["correction"]["enabled"] and report["points_cloud"] > 10_000
    assert len(read_ply(result.job_dir / "cloud.ply")[0]) == report["points_cloud"]
    assert report["inspection"]["as_measured"]["stats"]["count"] == report["points_cloud"]
    e57 = pye57.E57(str(result.job_dir / "cloud.e57"))
    try:
        assert e57.get_header(e57.scan_count - 1).point_count == report["points_cloud"]
    finally:
        e57.close()
    assert not list((result.job_dir / "tiles").glob("*"))
    assert report["ground_truth"]["cloud_rms_mm"] < 0.2  # the observer read the tiles before they went

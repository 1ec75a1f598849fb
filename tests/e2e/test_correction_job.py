"""The job runner applies correct + refine after stitching and reports the figures before and after."""

from __future__ import annotations

import multiprocessing

import numpy as np
import pytest
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.jobs.finish import merge_stage
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.io.cloud_io import read_ply
from tandemscan.pipeline.io.raw_scan import read_raw_scan
from tandemscan.pipeline.planning.plan import Plan, Scan
from tandemscan.pipeline.stitching.worldmap import VoxelMap
from tandemscan.sim_drivers.cell import with_surveyed_mounts


def _first_scans(plan: Plan, n: int) -> Plan:
    """The plan up to and including its n-th scan."""
    seen = 0
    for i, step in enumerate(plan.steps):
        seen += isinstance(step, Scan)
        if seen == n:
            return plan.model_copy(update={"steps": plan.steps[: i + 1]})
    return plan


@pytest.mark.slow
async def test_runner_corrects_the_stitch_and_reports_before_and_after(sim_config, tmp_path):
    cfg = sim_config.model_copy(update={"correction": sim_config.correction.model_copy(update={"method": "icp"})})
    async with CellSession(cfg) as session:
        cfg = with_surveyed_mounts(cfg, session.cell.simulation, tmp_path)
        result = await JobRunner(session, _first_scans(Plan.load(default_plan_path()), 2), cfg, tmp_path / "job").run()
    corr = result.report["correction"]
    assert corr["enabled"] and corr["method"] == "icp" and corr["pairs"] == 1
    before, after = corr["before"], result.report["ground_truth"]
    assert after["cloud_rms_mm"] < before["cloud_rms_mm"]
    assert corr["overlap_rms_mm_median_after"] < corr["overlap_rms_mm_median_before"]
    # the shared mount unknown is reported; the surveyed (true) mount has a tight prior and stays put
    assert corr["mount"]["estimated"] and corr["mount"]["prior"] == "calibration file"
    assert len(corr["mount"]["information_ratio"]) == 6 and max(map(abs, corr["mount"]["correction_mm"])) < 1e-3
    # the scan log carries the refined poses
    assert result.report["scan_log"][1]["T_W_S"] == result.scans[1].T_W_S.tolist()


@pytest.fixture
def dask_made(monkeypatch):
    """The ``LocalCluster``s and ``Client``s ``dask.distributed`` makes for the compute backend (``DaskBackend``
    takes both from there), each noted as made: {"clusters": [...], "clients": [...]}."""
    import dask.distributed

    made = {"clusters": [], "clients": []}

    class NotedCluster(dask.distributed.LocalCluster):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made["clusters"].append(self)

    class NotedClient(dask.distributed.Client):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made["clients"].append(self)

    monkeypatch.setattr(dask.distributed, "LocalCluster", NotedCluster)
    monkeypatch.setattr(dask.distributed, "Client", NotedClient)
    return made


def _all_closed(made: dict, children_before: set) -> None:
    """The clusters and clients of ``made`` closed and no child process left beside ``children_before``."""
    assert all(c.status.name == "closed" for c in made["clusters"])
    assert all(c.status == "closed" for c in made["clients"])
    assert set(multiprocessing.active_children()) <= children_before


def _dask_config(sim_config):
    compute = sim_config.compute.model_copy(update={"backend": "dask", "dask_workers": 1, "tile_mm": 200.0})
    return sim_config.model_copy(update={"compute": compute})


@pytest.mark.slow
async def test_on_the_dask_backend_the_job_holds_no_scan_for_its_correction(sim_config, tmp_path, monkeypatch,
                                                                           dask_made):
    """``[compute] backend = "dask"`` with tiles: the correction is given no scan's points (the workers read and
    summarise them from the job folder, ``correction.summarise_scan``: the same poses as from held points,
    ``tests/pipeline/test_compute_dask.py``) and the tiled merge takes its bounds of x from those summaries: the
    cloud is the one merged here from every scan at the final poses. The correction, its check pairs, the tiled
    merge and the tiles' inspection ran on one ``LocalCluster``, closed when the job was done."""
    from tandemscan.pipeline.registration import correction

    given = []
    real = correction.correct_scans
    monkeypatch.setattr("tandemscan.daemon.jobs.pose_correction.correct_scans",
                        lambda job, *a, **k: given.append([s.points_S for s in job.scans]) or real(job, *a, **k))
    cfg, children = _dask_config(sim_config), set(multiprocessing.active_children())
    async with CellSession(cfg) as session:
        cfg = with_surveyed_mounts(cfg, session.cell.simulation, tmp_path)
        result = await JobRunner(session, _first_scans(Plan.load(default_plan_path()), 2), cfg, tmp_path / "job").run()
        _all_closed(dask_made, children)
    assert len(dask_made["clusters"]) == len(dask_made["clients"]) == 1  # one for the whole end of the job
    assert result.report["inspection"]["as_measured"]["stats"]["count"] == len(read_ply(tmp_path / "job" /
                                                                                          "cloud.ply")[0])
    assert len(given) == 1 and len(given[0]) == 2 and all(p is None for p in given[0])
    assert result.report["correction"]["enabled"] and result.report["correction"]["joint"]["pairs"] >= 1
    here = merge_stage(cfg.job.voxel_mm, [s.file for s in result.scans], [s.T_W_S for s in result.scans]).frozen()
    points, _ = read_ply(tmp_path / "job" / "cloud.ply")
    assert len(points) == len(here) > 1000
    np.testing.assert_allclose(points, here.points(), rtol=0, atol=1e-9)
    assert "cloud_rms_mm" in result.report["correction"]["before"]  # the tracker stitch merged from the files, scored


@pytest.mark.slow
async def test_the_dask_backend_of_a_failed_end_of_job_is_closed(sim_config, tmp_path, monkeypatch, dask_made):
    """A stage that fails once the end of the job's ``LocalCluster`` runs (the tiled merge, after its tiles are
    merged): the job fails and the cluster, its worker processes and its client are closed."""
    from tandemscan.daemon.jobs import finish

    real = finish.merge_tiles

    def merge_then_fail(*args):
        real(*args)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(finish, "merge_tiles", merge_then_fail)
    cfg, children = _dask_config(sim_config), set(multiprocessing.active_children())
    async with CellSession(cfg) as session:
        cfg = with_surveyed_mounts(cfg, session.cell.simulation, tmp_path)
        with pytest.raises(Exception, match="No space left on device"):
            await JobRunner(session, _first_scans(Plan.load(default_plan_path()), 2), cfg, tmp_path / "job").run()
        _all_closed(dask_made, children)
    assert len(dask_made["clusters"]) == 1  # the correction's, still running at the merge


@pytest.mark.slow
async def test_uncorrected_on_the_dask_backend_the_cloud_is_the_tracker_stitch_merged_from_the_files(sim_config,
                                                                                                     tmp_path):
    """``[compute] backend = "dask"`` with the correction off: the job's map process merged no scan while measuring
    (``stitcher.merge_scan``), the cloud is merged from the scan files at the tracker poses by tiles on the backend:
    the map the local backend merges while measuring, to 1e-9 mm."""
    off = sim_config.correction.model_copy(update={"enabled": False})
    cfg = _dask_config(sim_config).model_copy(update={"correction": off})
    async with CellSession(cfg) as session:
        cfg = with_surveyed_mounts(cfg, session.cell.simulation, tmp_path)
        result = await JobRunner(session, _first_scans(Plan.load(default_plan_path()), 2), cfg, tmp_path / "job").run()
    assert not result.report["correction"]["enabled"]
    measured = VoxelMap(cfg.job.voxel_mm)  # what the local backend's map process merges while measuring
    for s in result.scans:
        measured.add_scan(s.T_W_S, *read_raw_scan(s.file, np.float32))
    points, _ = read_ply(tmp_path / "job" / "cloud.ply")
    here = measured.points()
    assert len(points) == len(here) > 1000
    np.testing.assert_allclose(points[np.lexsort(points.T)], here[np.lexsort(here.T)], rtol=0, atol=1e-9)

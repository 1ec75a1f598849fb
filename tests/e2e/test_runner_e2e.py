"""End to end on the simulated cell: a short plan with a coordinate transfer, scored against ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.cli import main
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.io.cloud_io import read_ply
from tandemscan.pipeline.planning.plan import MoveTracker, Plan, Scan
from tandemscan.sim_drivers.cell import with_surveyed_mounts


def short_plan() -> Plan:
    """The shipped plan up to three scans after its first coordinate transfer."""
    full = Plan.load(default_plan_path())
    steps, after_transfer = [], None
    for step in full.steps:
        steps.append(step)
        if isinstance(step, MoveTracker):
            after_transfer = 0
        elif isinstance(step, Scan) and after_transfer is not None:
            after_transfer += 1
            if after_transfer == 3:
                break
    return Plan(name="short", steps=steps)


@pytest.fixture
def stitch_only_config(sim_config):
    """The sim cell with the tracker-only stitch: no correction, no HTML report (their own tests cover them)."""
    return sim_config.model_copy(update={
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
    })


async def run(config, plan, job_dir, surveyed=True):
    """The job, with the cell's surveyed mounts (``surveyed``) or the config's (the CAD nominal ones)."""
    async with CellSession(config) as session:
        if surveyed:
            config = with_surveyed_mounts(config, session.cell.simulation, job_dir.parent)
        return await JobRunner(session, plan, config, job_dir).run()


async def test_short_job_writes_cloud_scans_and_a_report_within_noise_bounds(stitch_only_config, tmp_path):
    plan = short_plan()
    result = await run(stitch_only_config, plan, tmp_path / "job")
    report = result.report
    assert report["scans"] == plan.scan_count and report["transfers"] == 1

    points, normals = read_ply(result.cloud_file)
    assert len(points) == report["points_cloud"] > 50_000 and normals is not None
    raw = sorted((tmp_path / "job" / "scans").glob("scan-*.npz"))
    assert len(raw) == plan.scan_count
    with np.load(raw[0]) as first:
        assert first["T_C_T"].shape == (4, 4) and first["joints_rad"].shape == (6,)
        assert len(first["points_S_mm"]) == report["scan_log"][0]["points"]

    truth = report["ground_truth"]
    assert truth["robots_moved_together"] == []
    # Before any transfer a scan's pose error is one tracker reading: sigma_p per axis at ~3 m is
    # 0.025 mm, the target-to-scanner lever adds a little; the median of a 3-D error is about 1.5 sigma.
    station0 = truth["per_tracker_station"][0]
    assert station0["pose_err_mm_median"] < 0.15
    assert 0.01 < truth["cloud_rms_mm"] < 0.3
    transfer = report["transfer_log"][0]
    assert truth["transfers"][0]["station"] == 1 and truth["transfers"][0]["tracker_pose_err_mm"] < 0.5
    # the transfer's error prior: where the still target stood (the last scan of station 0 read it there too)
    last = result.scans[transfer["after_scan"] - 1]
    target_W = (last.T_W_C @ last.reading.T_C_T)[:3, 3]
    assert np.linalg.norm(np.array(transfer["target_W_mm"]) - target_W) < 0.2
    C = np.array(transfer["covariance"])
    np.testing.assert_allclose(C, C.T, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(C) > 0) and np.trace(C[:3, :3]) > np.trace(last.reading.covariance[:3, :3])


async def test_nominal_installation_stitches_visibly_worse_than_calibrated(stitch_only_config, tmp_path):
    plan = short_plan()
    assert stitch_only_config.job.installation_source == "nominal"
    good = (await run(stitch_only_config, plan, tmp_path / "a" / "job")).report["ground_truth"]
    bad = (await run(stitch_only_config, plan, tmp_path / "b" / "job", surveyed=False)).report["ground_truth"]
    assert bad["cloud_rms_mm"] > 3 * good["cloud_rms_mm"]
    assert bad["pose_err_mm_median"] > 0.5


def test_cli_measure_runs_a_plan_and_writes_the_job(tmp_path, capsys):
    """The command's path with the shipped settings (correction and inspection on), on the plan's first two scans:
    the whole band plan through ``measure`` is tests/e2e/test_verdict_job.py's."""
    plan = short_plan()
    second = [i for i, step in enumerate(plan.steps) if isinstance(step, Scan)][1]
    plan_file = tmp_path / "short.json"
    Plan(name="short", steps=plan.steps[: second + 1]).save(plan_file)
    assert main(["measure", "--plan", str(plan_file), "--out", str(tmp_path / "out")]) == 0
    (job_dir,) = (tmp_path / "out").iterdir()
    report = json.loads((job_dir / "report.json").read_text())
    assert (job_dir / "cloud.ply").is_file() and report["plan"] == "short"
    assert "scans" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--config", "/nonexistent/cell.toml"], "cell.toml: file not found"),
    (["--plan", "/nonexistent/plan.toml"], "plan.toml: file not found"),
    (["--part", "/nonexistent/part.stl"], "part.stl: mesh file not found"),
])
def test_cli_bad_input_is_one_line_and_exit_2(args, message, capsys):
    assert main(["measure", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err

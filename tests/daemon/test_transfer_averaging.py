"""Coordinate transfers read the still target ``tracker.transfer_samples`` times on each side, and the simulated
tracker keeps the share of its noise that averaging cannot remove (docs/planning.md, "Averaging a transfer's
readings")."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.daemon.cell.session import CellSession
from tandemscan.daemon.cell.tracker_reading import averaged_covariance
from tandemscan.daemon.jobs.runner import JobRunner
from tandemscan.daemon.plans import default_plan_path
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.planning.plan import MoveTracker, Plan, Scan
from tandemscan.sim_drivers.world import SimWorld


def through_first_transfer() -> Plan:
    """The shipped plan up to and including the first scan after its first coordinate transfer."""
    steps = Plan.load(default_plan_path()).steps
    first = next(i for i, s in enumerate(steps) if isinstance(s, MoveTracker) and any(
        isinstance(t, Scan) for t in steps[:i]))
    last = next(i for i in range(first, len(steps)) if isinstance(steps[i], Scan))
    return Plan(name="through first transfer", steps=steps[:last + 1])


def _tracker(config, **update):
    return config.model_copy(update={"tracker": config.tracker.model_copy(update=update)})


@pytest.fixture
def stitch_only_config(sim_config):
    return sim_config.model_copy(update={
        "correction": sim_config.correction.model_copy(update={"enabled": False}),
        "inspection": sim_config.inspection.model_copy(update={"in_job": False}),
    })


async def _job(config, plan, job_dir) -> tuple[dict, int]:
    """Run ``plan``; the report and how many frames the simulated tracker produced."""
    async with CellSession(config) as session:
        result = await JobRunner(session, plan, config, job_dir).run()
        return result.report, session.cell.simulation.world.tracker_frames


async def test_a_transfer_reads_the_configured_frames_on_both_sides_and_journals_a_smaller_covariance(
        stitch_only_config, tmp_path):
    plan = through_first_transfer()
    single, frames_single = await _job(_tracker(stitch_only_config, transfer_samples=1), plan, tmp_path / "one")
    averaged, frames_averaged = await _job(_tracker(stitch_only_config, transfer_samples=12), plan, tmp_path / "av")
    assert single["transfers"] == averaged["transfers"] == 1
    # the same plan, every other reading the same: only the transfer's two sides read 11 more frames each
    assert frames_averaged - frames_single == 2 * 11
    # the journaled prior of the transfer shrinks by what averaging removes (the still share stays)
    f = stitch_only_config.tracker.still_noise_fraction
    assert 0 < f < 1
    C1 = np.array(single["transfer_log"][0]["covariance"])
    C12 = np.array(averaged["transfer_log"][0]["covariance"])
    ratio = np.trace(C12) / np.trace(C1)
    assert ratio == pytest.approx(f + (1 - f) / 12, rel=0.05)
    assert np.all(np.linalg.eigvalsh(C1 - C12) > 0)


@pytest.fixture(scope="module")
def world():
    from tandemscan.config import load_config

    return SimWorld(load_config(None))


def _errors(world: SimWorld, periods: int, samples: int) -> np.ndarray:
    """Per still period (the arm's last joint turned a little between them): the translation error (mm) of the
    mean of ``samples`` readings, and one reading's 1-sigma (mm)."""
    home = world.joints_rad.copy()
    out = []
    for k in range(periods):
        world.joints_rad = home + np.r_[np.zeros(5), 1e-4 * k]
        T_true = F.invert(world.T_F_C()) @ world.T_F_T()
        readings = [world.measure_target() for _ in range(samples)]
        mean = F.mean_pose([T for T, _ in readings])
        out.append(mean[:3, 3] - T_true[:3, 3])
    world.joints_rad = home
    return np.array(out), np.sqrt(readings[0][1][0, 0])


@pytest.mark.slow
@pytest.mark.parametrize("still", [0.0, 0.5, 1.0])
def test_the_simulated_tracker_keeps_its_still_share_when_averaged(world, still):
    world.config = _tracker(world.config, still_noise_fraction=still)
    single, sigma = _errors(world, 300, 1)
    averaged, _ = _errors(world, 300, 20)
    # one reading's error is the configured sigma whatever the split
    assert np.std(single) == pytest.approx(sigma, rel=0.1)
    # the mean of 20 keeps the still share: variance f + (1 - f) / 20 of one reading's
    expected = sigma * np.sqrt(still + (1 - still) / 20)
    assert np.std(averaged) == pytest.approx(expected, rel=0.1)


def test_the_averaged_covariance_counts_only_the_fresh_share():
    C = np.diag([4.0, 4.0, 4.0, 1e-6, 1e-6, 1e-6])
    np.testing.assert_allclose(averaged_covariance(C, 1, 0.5), C)
    np.testing.assert_allclose(averaged_covariance(C, 10, 0.0), C / 10)
    np.testing.assert_allclose(averaged_covariance(C, 10, 0.5), C * 0.55)
    np.testing.assert_allclose(averaged_covariance(C, 10, 1.0), C)

"""Interim verification on the calibration plate (daemon/calibration/verify.py, `tandemscan verify`): the sphere-spacing
error through the whole chain within 2U of the simulator's truth (the plate is exactly its calibrated layout), a
cell on nominal mounts failing it, and a job after an expired or failed verification held indeterminate."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json

import pytest
from tandemscan.daemon.calibration.verify import last_verification, record, run_verification, verdict_context
from tandemscan.daemon.cell.session import CellSession
from tandemscan.sim_drivers.cell import with_surveyed_mounts


def verified_config(sim_config, tmp_path):
    ver = sim_config.verification.model_copy(update={"output_file": tmp_path / "verification.json", "views": 4})
    return sim_config.model_copy(update={"verification": ver})


@pytest.mark.slow
async def test_verify_reports_the_sphere_spacing_within_2u_of_the_truth_and_records_it(sim_config, tmp_path):
    config = verified_config(sim_config, tmp_path)
    async with CellSession(config) as session:
        calibrated = with_surveyed_mounts(config, session.cell.simulation, tmp_path)
        result = await run_verification(session, calibrated)
        nominal = await run_verification(session, config)
    # the simulated plate is its calibrated layout: the true spacing error is 0
    assert result.result == "pass" and abs(result.sphere_spacing_error_mm) <= 2.0 * result.sphere_spacing_uncertainty_mm
    assert result.views == 4 and result.spacings == 4 * 3 * 6
    assert abs(result.probing_size_mm) < result.mpe_probing_size_mm and result.installation["source"] == "calibration"
    # the nominal mounts misplace the views against each other by millimetres
    assert nominal.result == "fail" and abs(nominal.sphere_spacing_error_mm) > 0.5
    assert any("sphere-spacing error" in why for why in nominal.failures)
    journal = (tmp_path / "verification.jsonl").read_text().splitlines()
    assert [json.loads(line)["result"] for line in journal] == ["pass", "fail"]
    last = last_verification(config)
    assert last["result"] == "fail" and last["age_h"] < 1.0 and "sphere spacing" in last["summary"]


def test_an_expired_or_failed_verification_holds_the_verdict_and_a_fresh_pass_does_not(sim_config, tmp_path):
    config = verified_config(sim_config, tmp_path)
    assert verdict_context(config).verification is None and verdict_context(config).holds == ()
    passed = {"result": "pass", "sphere_spacing_error_mm": 0.01, "sphere_spacing_uncertainty_mm": 0.02,
              "probing_form_mm": 0.05, "probing_size_mm": 0.01, "mpe_sphere_spacing_mm": 0.15,
              "mpe_probing_form_mm": 0.1, "mpe_probing_size_mm": 0.1, "views": 4, "spacings": 72,
              "installation": {"source": "calibration"}}
    from tandemscan.daemon.calibration.verify import VerificationResult

    fresh = VerificationResult(created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), **passed)
    record(config, fresh)
    assert verdict_context(config).holds == () and verdict_context(config).verification["result"] == "pass"
    old = dataclasses.replace(fresh, created_utc=(dt.datetime.now(dt.UTC) - dt.timedelta(hours=30)).isoformat())
    record(config, old)
    (why,) = verdict_context(config).holds
    assert "30 h old, more than [verification] max_age_h 24 h" in why
    record(config, dataclasses.replace(fresh, result="fail", failures=("sphere-spacing error 0.3 mm",)))
    (why,) = verdict_context(config).holds
    assert "last verification failed" in why

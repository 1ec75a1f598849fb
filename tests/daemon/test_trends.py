"""Serials and trends: SPC of a characteristic as the textbook computes it, drift found, the daemon's job
carrying its part's identity and history, each job's characteristics stored by serial and served as a trend
with mean, standard deviation, control limits and Cp/Cpk."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
from serving import running_server
from tandemscan.config import load_config
from tandemscan.config.inspection_template import load_template, shipped_template
from tandemscan.daemon.api.app import create_app
from tandemscan.daemon.service import Daemon
from tandemscan.daemon.store.part_results import HISTORY_FILE, PartResults, prepare_part, record_part
from tandemscan.pipeline.inspection.characteristics import evaluate
from tandemscan.pipeline.inspection.decision import DecisionRule
from tandemscan.pipeline.inspection.spc import individuals_chart
from test_daemon_api import GatedRunner, sim_cell, world  # noqa: F401 (world: the module fixture)

from tests.pipeline.inspection.test_characteristics import sampled_cloud


def test_individuals_chart_and_capability_as_the_textbook_computes_them():
    """Five values, LSL 9, USL 11: mean 10.08, moving ranges 0.4 0.3 0.3 0.5 (mean 0.375), sigma within
    0.375 / 1.128 = 0.332447, limits 10.08 +/- 0.997340, Cp = 2 / (6 x 0.332447), Cpk = 0.92 / (3 x 0.332447);
    overall s = sqrt(0.228 / 4) = 0.238747: Pp = 2 / (6 s), Ppk = 0.92 / (3 s)."""
    c = individuals_chart([10.2, 9.8, 10.1, 10.4, 9.9], 9.0, 11.0)
    assert c.mean_mm == pytest.approx(10.08)
    assert c.sigma_within_mm == pytest.approx(0.332447, abs=1e-6) and c.std_mm == pytest.approx(0.238747, abs=1e-6)
    assert c.ucl_mm == pytest.approx(11.077340, abs=1e-6) and c.lcl_mm == pytest.approx(9.082660, abs=1e-6)
    assert c.cp == pytest.approx(1.002667, abs=1e-6) and c.cpk == pytest.approx(0.922453, abs=1e-6)
    assert c.pp == pytest.approx(1.396180, abs=1e-6) and c.ppk == pytest.approx(1.284485, abs=1e-6)
    assert c.drift == "" and c.beyond_limits == ()


def test_drift_is_a_point_beyond_the_limits_a_run_or_a_trend():
    rng = np.random.default_rng(3)
    steady = 0.02 * rng.standard_normal(20)
    assert individuals_chart(steady, -0.1, 0.1).drift == ""
    assert "beyond the control limits" in individuals_chart([*steady, 0.3], -0.1, 0.1).drift
    assert "steadily rising" in individuals_chart([*steady[:10], *np.linspace(0.0, 0.02, 6)], -0.1, 0.1).drift
    shifted = individuals_chart([*steady, *(0.01 + 0.002 * rng.standard_normal(7) + 0.05)], -0.1, 0.1)
    assert shifted.drift in ("the last 7 values on one side of the mean", "1 value(s) beyond the control limits")
    assert individuals_chart([0.01], -0.1, 0.1).cp is None


def test_a_job_takes_its_part_identity_from_the_request_and_gets_its_history(tmp_path):
    config = load_config()
    results = PartResults(tmp_path)
    results.record("job-1", "TS-NOSE-3000", "SN-1", [{"id": "SP-2", "name": "n", "actual_mm": -0.3, "lower_mm": -0.1,
                                                     "upper_mm": 0.1, "uncertainty_mm": 0.02, "status": "fail"}])
    results.close()
    job_dir = tmp_path / "jobs" / "job-2"
    job_dir.mkdir(parents=True)
    out = prepare_part(config, {"serial_number": "SN-2"}, job_dir, tmp_path)
    assert out.job.serial == "SN-2" and out.job.part_number is None  # the template's part number applies
    history = json.loads((job_dir / HISTORY_FILE).read_text())
    assert history["characteristics"]["SP-2"] == [{"serial": "SN-1", "job": "job-1", "actual_mm": -0.3,
                                                   "status": "fail"}]
    named = prepare_part(config, {"part_number": "P-9", "serial_number": "S"}, job_dir, tmp_path)
    assert named.job.part_number == "P-9"


@pytest.fixture(scope="module")
def ten_serials(tmp_path_factory):
    """Ten inspections of the as-built dent region (different noise seeds), one serial each, recorded as the
    daemon records a job's report.json (its ``inspection.part`` and ``inspection.characteristics``)."""
    state = tmp_path_factory.mktemp("state")
    template = load_template(shipped_template()).with_general_tolerance(-0.1, 0.1)  # the dent at 3x the limit
    for k in range(10):
        cloud = sampled_cloud("config/as-built-example.toml", (-430.0, 900.0, 600.0), (-270.0, 1100.0, 760.0), 0.3,
                              20 + k)
        measured = evaluate(template, cloud, DecisionRule())
        inspection = {"part": {"part_number": "TS-NOSE-3000", "serial": f"SN-{k:04d}"},
                      "characteristics": [c.summary() for c in measured]}
        assert record_part(state, f"job-{k}", {"inspection": inspection}) == len(template.characteristics)
    return state


@pytest.mark.slow
async def test_trend_endpoint_serves_the_ten_serials_with_their_chart(ten_serials, sim_config, world):  # noqa: F811
    world.safety.estop = False
    daemon = Daemon(sim_config, ten_serials, GatedRunner(), cell=sim_cell(sim_config, world))
    async with running_server(create_app(daemon, manage_lifecycle=True)) as url:
        async with httpx.AsyncClient(base_url=url, timeout=10) as api:
            ids = (await api.get("/v1/parts/TS-NOSE-3000/characteristics")).json()
            assert ids[:3] == ["SP-1", "SP-2", "SP-3"]
            body = (await api.get("/v1/parts/TS-NOSE-3000/characteristics/SP-2/trend")).json()
            assert [p["serial"] for p in body["points"]] == [f"SN-{k:04d}" for k in range(10)]
            values = [p["actual_mm"] for p in body["points"]]
            assert all(v == pytest.approx(-0.3, abs=0.07) for v in values)
            chart = individuals_chart(values, -0.1, 0.1)
            assert body["mean_mm"] == pytest.approx(chart.mean_mm) and body["cpk"] == pytest.approx(chart.cpk)
            assert body["cpk"] < 0 and body["ucl_mm"] > body["mean_mm"] > body["lcl_mm"]
            assert body["std_mm"] == pytest.approx(np.std(values, ddof=1))
            last3 = (await api.get("/v1/parts/TS-NOSE-3000/characteristics/SP-2/trend?last=3")).json()
            assert [p["serial"] for p in last3["points"]] == ["SN-0007", "SN-0008", "SN-0009"]
            r = await api.get("/v1/parts/TS-NOSE-3000/characteristics/NOPE/trend")
            assert r.status_code == 404


def test_the_report_shows_the_trend_of_a_failing_characteristic(tmp_path):
    from tandemscan.config.models import InspectionConfig
    from tandemscan.pipeline.inspection.inspection_job import (
        InspectionSettings,
        Measurement,
        ReportOutput,
        run_inspection,
    )
    from tandemscan.pipeline.inspection.report import InspectedPart

    cloud = sampled_cloud("config/as-built-example.toml", (-430.0, 900.0, 600.0), (-270.0, 1100.0, 760.0), 0.3, 9)
    history = {"SP-2": [{"serial": f"SN-{k}", "actual_mm": -0.28 - 0.002 * k, "status": "fail"} for k in range(9)],
               "SEC-2": [{"serial": "SN-0", "actual_mm": 0.0, "status": "pass"}]}
    cfg = InspectionConfig(views=("right",), map_width_px=150, best_fit=False, regions=())
    part = InspectedPart(cloud.surface, load_template(shipped_template()), {"serial": "SN-9"}, history)
    out = run_inspection(Measurement(cloud.points_mm), part, InspectionSettings.from_section(cfg),
                         ReportOutput(tmp_path))
    trends = {t["id"]: t for t in out.data["trends"]}
    assert set(trends) == {"SP-2"}  # SEC-1 fails with no history; SEC-2 was not measured here
    assert trends["SP-2"]["serials"] == [*(f"SN-{k}" for k in range(9)), "SN-9"] and len(trends["SP-2"]["values"]) == 10
    assert (tmp_path / "figures" / "trend-SP-2.png").is_file()
    html = (tmp_path / "report.html").read_text()
    assert html.index('id="characteristics"') < html.index('id="trend-SP-2"') < html.index('id="verdict"')


def test_a_broken_template_does_not_stop_the_job_from_running(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("part = 'p'\n")
    config = load_config()
    config = config.model_copy(update={"inspection": config.inspection.model_copy(update={"template": bad})})
    (tmp_path / "jobs" / "j").mkdir(parents=True)
    out = prepare_part(config, {"serial_number": "SN-1"}, tmp_path / "jobs" / "j", tmp_path)
    assert out.job.serial == "SN-1" and not (tmp_path / "jobs" / "j" / HISTORY_FILE).exists()

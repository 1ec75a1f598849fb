"""The report's even sample of a job's cloud (daemon/jobs/outputs.py): bounded by the smaller of the settings that
apply, and report.html names that one."""

from __future__ import annotations

from tandemscan.daemon.jobs.outputs import points_inspected, sample_bound


def _bounded(sim_config, max_points: int, report_points: int):
    return sim_config.model_copy(update={
        "inspection": sim_config.inspection.model_copy(update={"max_points": max_points}),
        "compute": sim_config.compute.model_copy(update={"report_points": report_points})})


def test_a_tiled_clouds_sample_is_bounded_by_the_smaller_setting_and_the_report_names_it(sim_config):
    below = _bounded(sim_config, 2_000, 5_000)  # [inspection] max_points below [compute] report_points
    assert sample_bound(below, tiled=True) == (2_000, "[inspection] max_points")
    assert "([inspection] max_points)" in points_inspected(2_000, 90_000, True, below)
    above = _bounded(sim_config, 8_000, 5_000)
    assert sample_bound(above, tiled=True) == (5_000, "[compute] report_points")
    assert "([compute] report_points)" in points_inspected(5_000, 90_000, True, above)


def test_an_untiled_clouds_sample_is_bounded_by_max_points_alone(sim_config):
    config = _bounded(sim_config, 8_000, 5_000)
    assert sample_bound(config, tiled=False) == (8_000, "[inspection] max_points")
    assert points_inspected(8_000, 90_000, False, config) == "8000 of the cloud's 90000 ([inspection] max_points)"
    assert points_inspected(90_000, 90_000, False, config) == "90000"

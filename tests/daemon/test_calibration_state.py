"""The cell's current calibration: made for a cell configuration, expiring, resolved for a job, and named in
the report's installation record (daemon/calibration/current.py)."""

import datetime as dt
import json

from tandemscan.config import load_config
from tandemscan.daemon.calibration.current import (
    cell_fingerprint,
    current_calibration,
    installation_for_job,
    installation_record,
    resolve_installation,
)
from tandemscan.pipeline.stitching.installation import Installation


def current_config(tmp_path, **calibration):
    config = load_config()  # the shipped sim cell: installation_source = "current"
    cal = config.calibration.model_copy(update={"output_file": tmp_path / "calibration.json", **calibration})
    return config.model_copy(update={"calibration": cal})


def write(config, made_for=None, created=None):
    data = Installation.nominal(config.installation).to_json()
    data["T_T_S"][0][3] += 1.5  # a calibrated mount, told apart from the nominal one
    data |= {"made_for": made_for or cell_fingerprint(config),
             "created_utc": (created or dt.datetime.now(dt.UTC)).isoformat(timespec="seconds")}
    config.calibration.output_file.write_text(json.dumps(data))


def test_the_shipped_cell_uses_its_current_calibration_and_nominal_mounts_until_there_is_one(tmp_path):
    config = current_config(tmp_path)
    assert config.job.installation_source == "current"
    path, why = current_calibration(config)
    assert path is None and "no current calibration" in why and "tandemscan calibrate" in why
    assert resolve_installation(config).job.installation_source == "nominal"
    record = installation_record(config)
    assert record["source"] == "nominal" and "no current calibration" in record["note"]
    write(config)
    resolved = resolve_installation(config)
    assert resolved.job.installation_source == "calibration"
    assert resolved.job.calibration_file == config.calibration.output_file
    assert installation_for_job(config).T_T_S[0, 3] == Installation.nominal(config.installation).T_T_S[0, 3] + 1.5
    record = installation_record(config)
    assert record["source"] == "calibration" and record["file"] == str(config.calibration.output_file)
    assert record["date"].startswith(str(dt.datetime.now(dt.UTC).year))


def test_another_cell_configuration_or_an_old_calibration_is_not_used(tmp_path):
    config = current_config(tmp_path, max_age_h=24.0)
    other = config.model_copy(update={"sim": config.sim.model_copy(update={"seed": 8})})
    assert cell_fingerprint(other) != cell_fingerprint(config)
    job_only = config.model_copy(update={"job": config.job.model_copy(update={"voxel_mm": 2.0})})
    assert cell_fingerprint(job_only) == cell_fingerprint(config)  # a job setting needs no new calibration
    write(other)
    assert "another cell configuration" in current_calibration(config)[1]
    write(config, created=dt.datetime.now(dt.UTC) - dt.timedelta(hours=30))
    path, why = current_calibration(config)
    assert path is None and "expired: 30 h old, more than 24 h" in why
    assert installation_record(config)["note"] == why
    named = config.model_copy(update={"job": config.job.model_copy(update={"installation_source": "nominal"})})
    assert resolve_installation(named) is named

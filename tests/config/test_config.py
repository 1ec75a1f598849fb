"""Configuration loading: defaults run the sim cell; bad files name the file, key and reason."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.config import ConfigError, load_config


def test_default_config_is_the_sim_cell(sim_config):
    assert sim_config.scanner.driver == "sim" and sim_config.tracker.driver == "sim"
    assert sim_config.scanner.range_min_mm == 384 and sim_config.scanner.range_max_mm == 520
    T = sim_config.installation.T_V1_C.matrix()
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_bad_value_names_file_key_and_reason(tmp_path):
    bad = tmp_path / "cell.toml"
    bad.write_text('[scanner]\nnoise_sigma_mm = -1.0\n')
    with pytest.raises(ConfigError) as e:
        load_config(bad)
    msg = str(e.value)
    assert str(bad) in msg and "scanner.noise_sigma_mm" in msg and "greater than or equal to 0" in msg


def test_unknown_key_is_an_error(tmp_path):
    bad = tmp_path / "cell.toml"
    bad.write_text('[tracker]\nrange_mx_mm = 3.0\n')
    with pytest.raises(ConfigError, match="tracker.range_mx_mm"):
        load_config(bad)


def test_the_simulators_truth_is_not_an_installation_source(tmp_path):
    old = tmp_path / "cell.toml"
    old.write_text('[job]\ninstallation_source = "truth"\n')
    with pytest.raises(ConfigError, match="job.installation_source: Input should be 'nominal', 'calibration' or "
                                          "'current'"):  # the simulator's true mounts are for scoring only
        load_config(old)
    assert load_config().job.installation_source == "current"  # the current calibration, else nominal


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[scanner\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(broken)


def test_relative_mesh_path_resolves_against_the_file(tmp_path):
    (tmp_path / "c.toml").write_text('[part]\nmesh = "part.stl"\n')
    assert load_config(tmp_path / "c.toml").part.mesh == tmp_path / "part.stl"


def test_keys_in_their_old_sections_are_refused_with_the_file_the_key_and_the_reason(tmp_path):
    """The correction keys once read from ``[deepmerge]`` and the simulator's noise once read from a device
    section are unknown keys there now (the deprecation shims went before any release)."""
    for section, key, value in (("deepmerge", "method", '"icp"'), ("tracker", "position_noise_mm", "0.02"),
                                ("measure_chassis", "slip_heading_deg", "1.5")):
        old = tmp_path / f"{section}.toml"
        old.write_text(f"[{section}]\n{key} = {value}\n")
        with pytest.raises(ConfigError, match=rf"{section}\.toml.*{section}\.{key}"):
            load_config(old)


def test_the_network_section_rejects_what_is_no_correction_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[deepmerge]\nicp_max_distanse_mm = 2.0\n')
    with pytest.raises(ConfigError, match="deepmerge.icp_max_distanse_mm"):
        load_config(bad)


def test_every_shipped_cell_file_loads_with_the_simulators_own_tables():
    """Every ``config/*.toml`` loads; its ``[sim]`` and ``[hil]`` tables are validated by the simulator's own
    models (``sim_drivers/config.py``, registered in ``tandemscan.simulator``), not the product's."""
    from tandemscan.config import default_config_path
    from tandemscan.sim_drivers.config import HilConfig, SimWorldConfig

    files = sorted(default_config_path().parent.glob("*.toml"))
    cells = [f for f in files if f.name != "arm_models.toml"]
    assert len(cells) >= 5
    for path in cells:
        config = load_config(path)
        assert isinstance(config.sim, SimWorldConfig) and isinstance(config.hil, HilConfig), path
    hil = load_config(default_config_path().parent / "hil-cell.toml")
    assert hil.hil.enabled and hil.sim.seed == load_config().sim.seed  # the tables' keys arrive


def test_a_bad_simulator_setting_names_file_key_and_reason(tmp_path):
    for table, key, value, reason in (("sim", "install_error_mm", "-1.0", "greater than or equal to 0"),
                                      ("sim.tracker_noise", "angle_noise_deg", '"big"', "valid number"),
                                      ("hil", "chassis_driver_state_flags", "1", "only the state flags"),
                                      ("hil", "arm_time_scal", "0.1", "Extra inputs are not permitted")):
        bad = tmp_path / f"{key}.toml"
        bad.write_text(f"[{table}]\n{key} = {value}\n")
        with pytest.raises(ConfigError) as e:
            load_config(bad)
        assert str(bad) in str(e.value) and f"{table}.{key}: " in str(e.value) and reason in str(e.value)


def test_the_product_models_hold_no_simulator_settings():
    """The product's models know the simulator's tables only as tables to hand on."""
    from tandemscan.config import models

    assert not {"SimWorldConfig", "HilConfig", "AsBuiltConfig", "TrackerNoiseConfig", "ChassisSlipConfig"} & set(
        vars(models))
    assert models.CellConfig().sim.seed == 7 and models.CellConfig().hil.enabled is False  # the defaults


def test_the_plans_starts_are_planning_settings_not_the_simulators(tmp_path):
    """The planner starts the arm's IK from ``[planning] arm_start_deg`` and the tracker chain at ``[planning]
    tracker_start`` (a real cell's settings too); where the simulated robots start stays the simulator's (``[sim]
    arm_home_deg``, ``tracking_start``), the same by default."""
    config = load_config()
    assert config.planning.arm_start_deg == config.sim.arm_home_deg == (0.0, 90.0, 0.0, 90.0, 0.0, 0.0)
    assert config.planning.tracker_start == config.sim.tracking_start  # the same pose, two meanings
    bad = tmp_path / "cell.toml"
    bad.write_text("[planning]\narm_start_deg = [0.0, 90.0]\n")
    with pytest.raises(ConfigError, match="planning.arm_start_deg: .*needs 6 values"):
        load_config(bad)

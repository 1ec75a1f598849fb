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
    with pytest.raises(ConfigError, match="job.installation_source.*scoring only.*tandemscan calibrate"):
        load_config(old)
    assert load_config().job.installation_source == "nominal"


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


def test_correction_keys_under_deepmerge_still_work_with_a_deprecation_warning(tmp_path, caplog):
    old = tmp_path / "old.toml"
    old.write_text('[deepmerge]\nenabled = false\nmethod = "deepmerge+icp"\nnum_points = 512\n')
    with caplog.at_level("WARNING", logger="tandemscan.config.models"):
        config = load_config(old)
    assert not config.correction.enabled and config.correction.method == "deepmerge+icp"
    assert config.deepmerge.num_points == 512
    warned = [r.getMessage() for r in caplog.records if "deprecated" in r.getMessage()]
    assert len(warned) == 2 and any("enabled" in w for w in warned) and all("[correction]" in w for w in warned)


def test_a_correction_key_in_both_sections_is_an_error(tmp_path):
    both = tmp_path / "both.toml"
    both.write_text('[deepmerge]\nmethod = "icp"\n[correction]\nmethod = "deepmerge"\n')
    with pytest.raises(ConfigError, match=r"deepmerge\.method is set in \[deepmerge\] and \[correction\]"):
        load_config(both)


def test_simulation_keys_in_a_device_section_move_under_sim_with_a_deprecation_warning(tmp_path, caplog):
    old = tmp_path / "old.toml"
    old.write_text("[tracker]\nposition_noise_mm = 0.02\nsamples_per_reading = 3\n"
                   "[tracking_chassis]\nslip_heading_deg = 1.5\n[sim]\nseed = 3\n")
    with caplog.at_level("WARNING", logger="tandemscan.config.models"):
        config = load_config(old)
    assert config.sim.tracker_noise.position_noise_mm == 0.02 and config.tracker.samples_per_reading == 3
    assert config.sim.tracking_chassis_slip.slip_heading_deg == 1.5
    assert config.sim.measure_chassis_slip.slip_heading_deg == 0.3 and config.sim.seed == 3
    warned = [r.getMessage() for r in caplog.records if "deprecated" in r.getMessage()]
    assert sorted(w.split("]")[0] for w in warned) == ["config: [tracker", "config: [tracking_chassis"]
    assert any("[sim.tracker_noise]" in w for w in warned) and any("[sim.tracking_chassis_slip]" in w for w in warned)


def test_a_simulation_key_in_both_places_is_an_error(tmp_path):
    both = tmp_path / "both.toml"
    both.write_text("[measure_chassis]\nslip_distance_fraction = 0.02\n"
                    "[sim.measure_chassis_slip]\nslip_distance_fraction = 0.03\n")
    with pytest.raises(ConfigError, match=r"measure_chassis\.slip_distance_fraction is set in \[measure_chassis\]"):
        load_config(both)


def test_the_network_section_rejects_what_is_no_correction_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[deepmerge]\nicp_max_distanse_mm = 2.0\n')
    with pytest.raises(ConfigError, match="deepmerge.icp_max_distanse_mm"):
        load_config(bad)

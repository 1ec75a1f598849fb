"""Drivers as plugins (docs/howto/add-a-device-driver.md): a second tracker vendor, the ACME tracker of
``tests/plugins/acme_tracker/`` (its driver, settings model and emulator), is registered through its
``pyproject.toml``'s entry points alone, and a cell built from a configuration naming it reads the tracker through
the plugin's driver against the plugin's emulator on the simulated world."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from tandemscan.config import ConfigError, load_config
from tandemscan.config.device_registry import DEVICE_GROUP, device_class, registered
from tandemscan.daemon.cell.devices import build_cell
from tandemscan.pipeline.geometry import frames as F
from tandemscan.sim_drivers.hil_box import free_port

PLUGIN = Path(__file__).resolve().parents[1] / "plugins" / "acme_tracker"


@pytest.fixture
def acme_installed(tmp_path, monkeypatch) -> None:
    """The plugin installed as pip would: its package importable and a ``.dist-info`` folder on ``sys.path``
    holding the entry points its ``pyproject.toml`` declares."""
    project = tomllib.loads((PLUGIN / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    dist_info = tmp_path / "site" / f"acme_tracker-{project['version']}.dist-info"
    dist_info.mkdir(parents=True)
    (dist_info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\n"
                                        f"Version: {project['version']}\n", encoding="utf-8")
    (dist_info / "entry_points.txt").write_text("".join(
        f"[{group}]\n" + "".join(f"{name} = {value}\n" for name, value in entries.items())
        for group, entries in project["entry-points"].items()), encoding="utf-8")
    monkeypatch.syspath_prepend(str(PLUGIN))
    monkeypatch.syspath_prepend(str(tmp_path / "site"))


@pytest.fixture
def box_part(tmp_path) -> Path:
    """A 3 x 2 x 1.6 m box as the part (mm): the world builds in a second."""
    mesh = o3d.geometry.TriangleMesh.create_box(3000.0, 2000.0, 1600.0).translate((-1500.0, -1000.0, 0.0))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / "box.stl"), mesh)
    return tmp_path / "box.stl"


def cell_toml(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "cell.toml"
    path.write_text(body, encoding="utf-8")
    return path


def test_the_built_in_drivers_are_registered_as_entry_points():
    """Every role registers its simulator's twin; every role but the lifting column the built-in vendor's."""
    for role in ("measure_chassis", "tracking_chassis", "arm", "scanner", "tracker", "safety"):
        assert set(registered(DEVICE_GROUP, role)) == {"real", "sim"}
    assert set(registered(DEVICE_GROUP, "lift")) == {"sim"}
    assert device_class("tracker", "real").__name__ == "MetronorTracker"


def test_a_plugin_driver_gets_its_own_validated_settings(acme_installed, tmp_path):
    config = load_config(cell_toml(tmp_path, '[tracker]\ndriver = "acme"\ntimeout_s = 3.0\n\n'
                                             '[tracker.acme]\nport = 9100\n'))
    assert type(config.tracker.settings).__name__ == "AcmeSettings"
    assert config.tracker.settings.port == 9100 and config.tracker.settings.reply_timeout_s == 2.0
    assert config.tracker.timeout_s == 3.0  # the role's own keys stay the section's
    with pytest.raises(ConfigError, match=r"tracker\.acme\.bogus: Extra inputs are not permitted"):
        load_config(cell_toml(tmp_path, '[tracker]\ndriver = "acme"\n\n[tracker.acme]\nbogus = 1\n'))
    with pytest.raises(ConfigError, match=r"tracker\.acme\.port: Input should be less than or equal to 65535"):
        load_config(cell_toml(tmp_path, '[tracker]\ndriver = "acme"\n\n[tracker.acme]\nport = 70000\n'))
    with pytest.raises(ConfigError, match=r"no driver 'acne' registered in tandemscan.devices \(registered: acme, "
                                          r"real, sim\)"):
        load_config(cell_toml(tmp_path, '[tracker]\ndriver = "acne"\n'))
    with pytest.raises(ConfigError, match="tracker.acme: Extra inputs are not permitted"):  # not a plugin's
        load_config(cell_toml(tmp_path, '[tracker]\ndriver = "real"\n\n[tracker.acme]\nport = 9100\n'))


def test_a_plugin_driver_is_unknown_without_its_plugin(tmp_path):
    with pytest.raises(ConfigError, match=r"tracker: no driver 'acme' registered .*registered: real, sim\)"):
        load_config(cell_toml(tmp_path, '[tracker]\ndriver = "acme"\n'))


async def test_the_cell_reads_the_tracker_through_the_plugin_against_its_emulator(acme_installed, tmp_path,
                                                                                  box_part):
    """Hardware in the loop: the cell builds the plugin's driver for the tracker, the simulation starts the
    plugin's emulator on its world, and a reading is the world's target pose within the reading's own noise."""
    config = load_config(cell_toml(tmp_path, f'[part]\nmesh = "{box_part}"\n\n[hil]\nenabled = true\n\n'
                                             f'[tracker]\ndriver = "acme"\n\n[tracker.acme]\nport = {free_port()}\n'))
    cell = build_cell(config)
    assert type(cell.tracker).__name__ == "AcmeTracker"
    world = cell.simulation.world
    await cell.simulation.start()
    emulator = cell.simulation.emulators.running["tracker"]
    try:
        await cell.tracker.connect()
        reading = await cell.tracker.read_pose()
        status = await cell.tracker.status()
        await cell.tracker.close()
    finally:
        await cell.simulation.stop()
    assert type(emulator).__name__ == "AcmeEmulator" and emulator.requests == 1 and status.connected
    T_true = F.invert(world.T_F_C()) @ world.T_F_T()
    dt_mm, dr_rad = F.pose_error(reading.T_C_T, T_true)
    sigma_mm, sigma_rad = np.sqrt(reading.covariance[0, 0]), np.sqrt(reading.covariance[3, 3])
    assert 0 < dt_mm < 6 * sigma_mm * np.sqrt(3) and dr_rad < 6 * sigma_rad * np.sqrt(3)
    assert np.allclose(reading.T_C_T[:3, :3] @ reading.T_C_T[:3, :3].T, np.eye(3), atol=1e-9)

"""The PhoXi driver through the fake harvesters module (no GenTL producer can run here)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from tandemscan.config.models import PhoxiConfig, ScannerConfig
from tandemscan.drivers import DeviceFault, DeviceTimeout, NotConnected, Scanner
from tandemscan.drivers.phoxi import PhoxiScanner
from tandemscan.sim_drivers.fake_harvesters import core as fake

FAKE = "tandemscan.sim_drivers.fake_harvesters.core"


@pytest.fixture
def producer(tmp_path):
    cti = tmp_path / "photoneo.cti"
    cti.write_bytes(b"\x7fELF fake producer")
    fake.CAMERA.reset()
    yield cti
    fake.CAMERA.reset()


def scanner_for(producer, **phoxi) -> PhoxiScanner:
    cfg = PhoxiConfig(producer_path=producer, **{"harvesters_module": FAKE, **phoxi})
    return PhoxiScanner(ScannerConfig(driver="real", phoxi=cfg, timeout_s=0.5))


async def test_capture_photoneo_path(producer):
    scanner = scanner_for(producer)
    assert isinstance(scanner, Scanner)
    await scanner.connect()
    assert fake.CAMERA.node_values["PhotoneoTriggerMode"] == "Software"
    assert fake.CAMERA.node_values["SendPointCloud"] is True
    frame = await scanner.capture()
    xyz_grid, n_grid, conf_grid = fake.CAMERA.scene()
    valid = np.any(xyz_grid.reshape(-1, 3) != 0, axis=1)
    assert frame.points_mm.shape == (valid.sum(), 3) and frame.points_mm.dtype == np.float64
    assert not np.any(np.all(frame.points_mm == 0, axis=1))  # invalid pixels dropped
    np.testing.assert_allclose(frame.points_mm, xyz_grid.reshape(-1, 3)[valid])
    assert 440.0 <= frame.points_mm[:, 2].min() and frame.points_mm[:, 2].max() < 460.0  # mm at the sweet spot
    np.testing.assert_allclose(np.linalg.norm(frame.normals, axis=1), 1.0, atol=1e-5)
    assert frame.confidence.shape == (valid.sum(),)
    assert fake.CAMERA.triggers == 1
    await scanner.close()
    assert fake.CAMERA.open_acquirers == 0
    assert (await scanner.status()).state == "disconnected"


async def test_gige_vision_selects_components_and_matches_parts_by_component_id(producer):
    """The device boots with Intensity and Range on; Normal's ID is above Confidence's, so the parts arrive
    Range, Confidence, Normal. The driver switches every component and matches parts by ID."""
    fake.CAMERA.interface = "gige_vision"
    scanner = scanner_for(producer, interface="gige_vision")
    await scanner.connect()
    values = fake.CAMERA.node_values
    assert values["TriggerSource"] == "Software"
    assert values["Scan3dOutputMode"] == "CalibratedABC_Grid"
    assert values["ComponentEnable[Intensity]"] is False and values["ComponentEnable[Event]"] is False
    assert values["ComponentEnable[Range]"] is True and values["ComponentEnable[Normal]"] is True
    assert values["PixelFormat[Confidence]"] == "Confidence8"
    assert values["NormalsEstimationRadius"] == 2
    frame = await scanner.capture()
    xyz_grid, n_grid, conf_grid = fake.CAMERA.scene()
    valid = np.any(xyz_grid.reshape(-1, 3) != 0, axis=1)
    np.testing.assert_allclose(frame.points_mm, xyz_grid.reshape(-1, 3)[valid])
    np.testing.assert_allclose(frame.normals, n_grid.reshape(-1, 3)[valid], atol=1e-6)
    # Confidence8 (0..255) and PhoXi Control's map mean the same after normalising: 0 invalid, 1 best
    np.testing.assert_allclose(frame.confidence, np.round(0.9 * 255) / 255)
    await scanner.close()


async def test_confidence_has_one_meaning_on_both_interfaces(producer):
    frames = {}
    for interface in ("photoneo_gentl", "gige_vision"):
        fake.CAMERA.interface = interface
        scanner = scanner_for(producer, interface=interface)
        await scanner.connect()
        frames[interface] = await scanner.capture()
        await scanner.close()
    np.testing.assert_allclose(frames["gige_vision"].confidence, frames["photoneo_gentl"].confidence, atol=1 / 255)
    assert 0.0 < frames["gige_vision"].confidence.min() <= frames["gige_vision"].confidence.max() <= 1.0


async def test_gige_part_in_an_unexpected_pixel_format_is_a_fault(producer):
    fake.CAMERA.interface = "gige_vision"
    scanner = scanner_for(producer, interface="gige_vision")
    await scanner.connect()
    fake.CAMERA.node_values["PixelFormat[Confidence]"] = "Confidence16"  # changed behind the driver's back
    with pytest.raises(DeviceFault, match="Confidence part is Confidence16, expected Confidence8"):
        await scanner.capture()
    await scanner.close()


async def test_slow_scan_times_out_then_recovers(producer):
    scanner = scanner_for(producer)
    await scanner.connect()
    fake.CAMERA.fetch_delay_s = 5.0
    with pytest.raises(DeviceTimeout, match="scanner: no scan within 0.2 s"):  # not stuck for the scan's 5 s
        await scanner.capture(timeout_s=0.2)
    fake.CAMERA.fetch_delay_s = 0.0
    assert len((await scanner.capture()).points_mm) > 0
    await scanner.close()


async def test_a_scan_that_completes_after_its_fetch_timed_out_is_not_taken_for_the_next(producer):
    """The scan of a timed-out fetch still completes into the producer's output queue; the next capture (at
    another arm pose) must return its own scan, not that one."""
    scanner = scanner_for(producer)
    await scanner.connect()
    fake.CAMERA.fetch_delay_s = 0.3
    with pytest.raises(DeviceTimeout, match="no scan within 0.1 s"):
        await scanner.capture(timeout_s=0.1)
    await asyncio.sleep(0.3)  # the late scan is now complete and queued
    fake.CAMERA.fetch_delay_s = 0.0
    fake.CAMERA.scene = fake.recorded_style_scene(distance_mm=600.0)  # the arm moved on
    frame = await scanner.capture()
    assert frame.points_mm[:, 2].min() >= 600.0
    assert len((await scanner.capture()).points_mm) == len(frame.points_mm)  # nothing queued behind it
    await scanner.close()


async def test_malformed_buffer_is_a_fault(producer):
    scanner = scanner_for(producer)
    await scanner.connect()
    fake.CAMERA.scene = lambda: (np.zeros((4, 5, 3), np.float32), np.zeros((4, 5, 3), np.float32),
                                 np.zeros((3, 5), np.float32))  # confidence disagrees with the image size
    with pytest.raises(DeviceFault, match="capture failed"):
        await scanner.capture()
    await scanner.close()


async def test_missing_pieces_are_named(producer, tmp_path):
    with pytest.raises(NotConnected, match="not_a_module.*pip install harvesters"):
        await scanner_for(producer, harvesters_module="not_a_module").connect()
    with pytest.raises(NotConnected, match="no GenTL producer configured"):
        await scanner_for(None).connect()
    with pytest.raises(NotConnected, match="producer not found.*missing.cti"):
        await scanner_for(tmp_path / "missing.cti").connect()
    with pytest.raises(NotConnected, match="no scanner identified as 'OTHER' .found: .*FAKE-001"):
        await scanner_for(producer, serial_number="OTHER").connect()
    with pytest.raises(NotConnected):
        await scanner_for(producer).capture()
    assert fake.CAMERA.open_acquirers == 0


@pytest.mark.parametrize(("interface", "identity"), [
    ("photoneo_gentl", "FAKE-001"), ("photoneo_gentl", "PhotoneoTL_DEV_FAKE-001"), ("photoneo_gentl", "PHOXI-FAKE-1"),
    ("gige_vision", "FAKE-001"), ("gige_vision", "scanner-left")])
async def test_the_scanner_is_found_by_any_of_its_identities(producer, interface, identity):
    """PhoXi Control's producer lists a scanner as ``id_`` ``PhotoneoTL_DEV_<ID>`` beside a serial number of its own
    (Photoneo's GenTL examples open it by ``id_``), a GigE Vision producer with the ID as its serial number (the
    GigE examples open it by ``serial_number``): the configured scanner may be named by either, by the bare ID or
    by its user-defined name."""
    fake.CAMERA.interface = interface
    fake.CAMERA.user_defined_name = "scanner-left"
    scanner = scanner_for(producer, interface=interface, serial_number=identity)
    await scanner.connect()
    try:
        assert len((await scanner.capture()).points_mm) > 0
    finally:
        await scanner.close()

"""Photoneo PhoXi 3D Scanner through harvesters and a GenTL producer (settings in ``ScannerConfig.phoxi``).

Two producer paths (shared/protocols/README.md):
- ``photoneo_gentl``: PhoXi Control's ``photoneo.cti``; ``PhotoneoTriggerMode = "Software"``, ``Send*`` booleans
  switch components, ``TriggerFrame`` fires a scan; components arrive in a fixed order (point cloud third,
  normal map fourth, confidence map sixth).
- ``gige_vision``: firmware >= 1.13 with a standard producer; ``TriggerMode/TriggerSource`` software trigger,
  ``ComponentSelector/ComponentEnable`` for Range, Normal, Confidence (taken to arrive in that order [U]),
  ``Scan3dOutputMode = CalibratedABC_Grid`` for XYZ per pixel.
Point clouds are in mm in the scanner frame S; invalid pixels (all zeros or non-finite) are dropped. harvesters
and the producer are optional at install time: ``connect()`` names whichever is missing. GenTL calls block, so
they run in a worker thread, one at a time.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import time
from types import ModuleType
from typing import Any

import numpy as np
from tandemscan.config.models import ScannerConfig
from tandemscan.drivers.errors import DeviceError, DeviceFault, DeviceTimeout, NotConnected
from tandemscan.drivers.interfaces import DeviceStatus, ScanFrame

log = logging.getLogger(__name__)

# (point cloud, normals, confidence) component indices per producer path
_COMPONENTS = {"photoneo_gentl": (2, 3, 5), "gige_vision": (0, 1, 2)}
_PHOTONEO_SEND = {"SendPointCloud": True, "SendNormalMap": True, "SendConfidenceMap": True,
                  "SendTexture": False, "SendDepthMap": False}
_THREAD_MARGIN_S = 2.0


class PhoxiScanner:
    """The :class:`~tandemscan.drivers.interfaces.Scanner` on a PhoXi through harvesters."""

    def __init__(self, config: ScannerConfig, name: str = "scanner"):
        self.name = name
        self._cfg = config
        self._px = config.phoxi
        self._harvester: Any = None
        self._acquirer: Any = None
        self._lock = asyncio.Lock()
        self._broken: DeviceError | None = None

    async def connect(self) -> None:
        await self.close()
        async with self._lock:
            await asyncio.to_thread(self._open)
        self._broken = None

    async def close(self) -> None:
        async with self._lock:
            acquirer, harvester = self._acquirer, self._harvester
            self._acquirer = self._harvester = None
            if acquirer is not None or harvester is not None:
                await asyncio.to_thread(_release, acquirer, harvester)

    async def status(self) -> DeviceStatus:
        if self._acquirer is None:
            return DeviceStatus(self.name, False, "disconnected")
        if self._broken is not None:
            return DeviceStatus(self.name, True, "fault", {"error": str(self._broken)})
        return DeviceStatus(self.name, True, "idle", {"interface": self._px.interface})

    async def capture(self, timeout_s: float | None = None) -> ScanFrame:
        """Trigger one scan and return its points (mm, frame S), normals and confidence."""
        timeout = self._cfg.timeout_s if timeout_s is None else timeout_s
        if self._acquirer is None:
            raise NotConnected(self.name, "not connected")
        if self._broken is not None:
            raise self._broken
        async with self._lock:
            try:
                return await asyncio.wait_for(asyncio.to_thread(self._capture, timeout), timeout + _THREAD_MARGIN_S)
            except TimeoutError as e:
                # the GenTL call is stuck past its own timeout: the acquirer cannot be trusted until reconnect
                self._broken = DeviceTimeout(self.name, f"producer stuck in fetch for {timeout + _THREAD_MARGIN_S} s")
                raise self._broken from e

    # ------------------------------------------------------------------ worker-thread side

    def _open(self) -> None:
        module = self._import_harvesters()
        producer = self._px.producer_path
        if producer is None:
            raise NotConnected(self.name, "no GenTL producer configured (scanner.phoxi.producer_path; PhoXi Control "
                                          "installs photoneo.cti)")
        if not producer.is_file():
            raise NotConnected(self.name, f"GenTL producer not found: {producer} (is PhoXi Control installed?)")
        harvester = module.Harvester()
        try:
            harvester.add_file(str(producer))
            harvester.update()
            if not harvester.device_info_list:
                raise NotConnected(self.name, f"no scanner found through {producer.name}")
            key = {"serial_number": self._px.serial_number} if self._px.serial_number else None
            acquirer = harvester.create(key)
        except DeviceError:
            harvester.reset()
            raise
        except Exception as e:  # vendor boundary: GenTL errors have no common base class
            harvester.reset()
            raise NotConnected(self.name, f"cannot open the scanner: {type(e).__name__}: {e}") from e
        try:
            self._configure(acquirer.remote_device.node_map)
            acquirer.start()
        except Exception as e:  # vendor boundary
            _release(acquirer, harvester)
            raise DeviceFault(self.name, f"cannot configure the scanner: {type(e).__name__}: {e}") from e
        self._harvester, self._acquirer = harvester, acquirer
        log.info("%s: opened through %s (%s)", self.name, producer, self._px.interface)

    def _import_harvesters(self) -> ModuleType:
        try:
            return importlib.import_module(self._px.harvesters_module)
        except ImportError as e:
            raise NotConnected(self.name, f"{self._px.harvesters_module} is not importable: install harvesters "
                                          f"(pip install harvesters) to use a real PhoXi ({e})") from e

    def _configure(self, nodes: Any) -> None:
        if self._px.interface == "photoneo_gentl":
            nodes.PhotoneoTriggerMode.value = "Software"
            for node, on in _PHOTONEO_SEND.items():
                getattr(nodes, node).value = on
        else:
            nodes.TriggerSelector.value = "FrameStart"
            nodes.TriggerMode.value = "On"
            nodes.TriggerSource.value = "Software"
            nodes.Scan3dOutputMode.value = "CalibratedABC_Grid"
            for component in ("Range", "Normal", "Confidence"):
                nodes.ComponentSelector.value = component
                nodes.ComponentEnable.value = True

    def _capture(self, timeout: float) -> ScanFrame:
        nodes = self._acquirer.remote_device.node_map
        try:
            (nodes.TriggerFrame if self._px.interface == "photoneo_gentl" else nodes.TriggerSoftware).execute()
            with self._acquirer.fetch(timeout=timeout) as buffer:
                comps = list(buffer.payload.components)
                return self._decode(comps)
        except DeviceError:
            raise
        except Exception as e:  # vendor boundary: map by kind
            if "timeout" in type(e).__name__.lower():
                raise DeviceTimeout(self.name, f"no scan within {timeout} s") from e
            raise DeviceFault(self.name, f"capture failed: {type(e).__name__}: {e}") from e

    def _decode(self, comps: list[Any]) -> ScanFrame:
        i_xyz, i_n, i_c = _COMPONENTS[self._px.interface]
        if len(comps) <= max(i_xyz, i_n, i_c):
            raise DeviceFault(self.name, f"buffer has {len(comps)} components, expected at least {max(i_xyz, i_n, i_c) + 1}")
        xyz = _pixels(comps[i_xyz], 3)
        if xyz is None or len(xyz) == 0:
            raise DeviceFault(self.name, "buffer has no point cloud (SendPointCloud off?)")
        normals, conf = _pixels(comps[i_n], 3), _pixels(comps[i_c], 1)
        valid = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0, axis=1)
        return ScanFrame(
            points_mm=xyz[valid].astype(np.float64),
            normals=normals[valid].astype(np.float64) if normals is not None and len(normals) == len(xyz) else None,
            confidence=conf[valid, 0].astype(np.float64) if conf is not None and len(conf) == len(xyz) else None,
            timestamp_s=time.time(),
        )


def _pixels(component: Any, channels: int) -> np.ndarray | None:
    """A component's data as ``(width * height, channels)`` float, or None when the component is empty."""
    n = int(component.width) * int(component.height)
    if n == 0 or component.data is None or component.data.size == 0:
        return None
    data = np.asarray(component.data, dtype=np.float32)
    if data.size != n * channels:
        raise ValueError(f"component of {data.size} values for {component.width}x{component.height}x{channels}")
    return data.reshape(n, channels).copy()


def _release(acquirer: Any, harvester: Any) -> None:
    for step in (getattr(acquirer, "stop", None), getattr(acquirer, "destroy", None), getattr(harvester, "reset", None)):
        if step is not None:
            with contextlib.suppress(Exception):  # best effort while tearing down a vendor stack
                step()

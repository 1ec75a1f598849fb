"""Photoneo PhoXi 3D Scanner through harvesters and a GenTL producer (settings in ``ScannerConfig.phoxi``).

Two producer paths (docs/drivers.md, "PhoXi"):
- ``photoneo_gentl``: PhoXi Control's ``photoneo.cti``; ``PhotoneoTriggerMode = "Software"``, ``Send*`` booleans
  switch components, ``TriggerFrame`` fires a scan; components arrive in a fixed order (point cloud third,
  normal map fourth, confidence map sixth).
- ``gige_vision``: firmware >= 1.13 with a standard producer; ``TriggerMode/TriggerSource`` software trigger,
  ``Scan3dOutputMode = CalibratedABC_Grid`` for XYZ per pixel. Every entry of ``ComponentSelector`` is
  switched: Range, Normal and Confidence on (with their pixel formats), all others off; the parts of a buffer
  come in increasing ``ComponentIDValue`` of the enabled components (as Photoneo's examples match them).
  ``NormalsEstimationRadius`` is set (0 would send no normals); confidence is ``Confidence8`` (0 invalid).
Point clouds are in mm in the scanner frame S; invalid pixels (all zeros, non-finite, or confidence 0) are
dropped. Confidence is normalised to one meaning on both paths: 0 invalid, 1 best. harvesters
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
from tandemscan.drivers.interfaces import DeviceState, DeviceStatus, ScanFrame

log = logging.getLogger(__name__)

# (point cloud, normals, confidence) component indices of PhoXi Control's producer
_PHOTONEO_COMPONENTS = (2, 3, 5)
_GIGE_CONFIDENCE_BEST = 255.0  # Confidence8
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
        self._gige_order: tuple[str, ...] = ()  # enabled GigE components in increasing ComponentIDValue
        self._late_scan_possible = False  # a fetch timed out: its scan may still reach the output queue
        default_best = _GIGE_CONFIDENCE_BEST if self._px.interface == "gige_vision" else 1.0
        self._confidence_best = self._px.confidence_best or default_best
        self._gige_formats = {"Range": self._px.range_pixel_format, "Normal": self._px.normal_pixel_format,
                              "Confidence": self._px.confidence_pixel_format}

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
            return DeviceStatus(self.name, False, DeviceState.DISCONNECTED)
        if self._broken is not None:
            return DeviceStatus(self.name, True, DeviceState.FAULT, {"error": str(self._broken)})
        return DeviceStatus(self.name, True, DeviceState.IDLE, {"interface": self._px.interface})

    async def capture(self, timeout_s: float | None = None) -> ScanFrame:
        """Trigger one scan and return its points (mm, frame S), normals and confidence."""
        timeout = self._cfg.timeout_s if timeout_s is None else timeout_s
        if self._acquirer is None:
            raise NotConnected(self.name, "not connected")
        if self._broken is not None:
            raise self._broken
        async with self._lock:
            try:
                async with asyncio.timeout(timeout + _THREAD_MARGIN_S):
                    return await asyncio.to_thread(self._capture, timeout)
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
            acquirer = harvester.create(self._device_index(harvester.device_info_list))
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
        self._harvester, self._acquirer, self._late_scan_possible = harvester, acquirer, False
        log.info("%s: opened through %s (%s)", self.name, producer, self._px.interface)

    def _device_index(self, infos: list[Any]) -> int:
        """Index of the configured scanner (``phoxi.serial_number``) in the producer's device list: the device that
        has it as its serial number, its ID (``id_``, or that without PhoXi Control's ``PhotoneoTL_DEV_`` or a
        GigE producer's ``..._DEV_`` prefix) or its user-defined name; the first device where none is configured.
        :class:`NotConnected` naming what was found where no device, or several, have it."""
        wanted = self._px.serial_number.strip()
        if not wanted:
            return 0
        found = [_identities(info) for info in infos]
        matches = [i for i, ids in enumerate(found) if wanted in ids]
        if len(matches) != 1:
            listed = "; ".join(", ".join(sorted(ids)) for ids in found)
            raise NotConnected(self.name, f"{'no' if not matches else 'more than one'} scanner identified as "
                                          f"{wanted!r} (found: {listed})")
        return matches[0]

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
            self._gige_order = self._select_components(nodes)
            nodes.NormalsEstimationRadius.value = self._px.normals_estimation_radius

    def _select_components(self, nodes: Any) -> tuple[str, ...]:
        """Enable Range, Normal, Confidence with their pixel formats and disable every other component; the
        wanted components in the order their parts arrive (increasing ``ComponentIDValue``)."""
        formats = self._gige_formats
        offered = list(nodes.ComponentSelector.symbolics)
        missing = [c for c in formats if c not in offered]
        if missing:
            raise DeviceFault(self.name, f"the scanner offers no {', '.join(missing)} component ({offered})")
        ids: dict[str, int] = {}
        for component in offered:
            nodes.ComponentSelector.value = component
            wanted = component in formats
            nodes.ComponentEnable.value = wanted
            if wanted:
                nodes.PixelFormat.value = formats[component]
                ids[component] = int(nodes.ComponentIDValue.value)
        return tuple(sorted(ids, key=ids.__getitem__))

    def _capture(self, timeout: float) -> ScanFrame:
        """Trigger, fetch and decode one scan. After a fetch that timed out, the acquisition is stopped and
        started first: its scan may still complete, and the output queue would hand it to this fetch in place of
        the scan triggered now (taken at another arm pose)."""
        nodes = self._acquirer.remote_device.node_map
        try:
            if self._late_scan_possible:
                self._acquirer.stop()  # flushes the queues (GenTL ACQ_QUEUE_ALL_DISCARD)
                self._acquirer.start()
                self._late_scan_possible = False
            (nodes.TriggerFrame if self._px.interface == "photoneo_gentl" else nodes.TriggerSoftware).execute()
            with self._acquirer.fetch(timeout=timeout) as buffer:
                comps = list(buffer.payload.components)
                return self._decode(comps)
        except DeviceError:
            raise
        except Exception as e:  # vendor boundary: map by kind
            if "timeout" in type(e).__name__.lower():
                self._late_scan_possible = True
                raise DeviceTimeout(self.name, f"no scan within {timeout} s") from e
            raise DeviceFault(self.name, f"capture failed: {type(e).__name__}: {e}") from e

    def _decode(self, comps: list[Any]) -> ScanFrame:
        if self._px.interface == "gige_vision":
            if len(comps) != len(self._gige_order):
                raise DeviceFault(self.name, f"buffer has {len(comps)} parts for the {len(self._gige_order)} "
                                             f"enabled components {self._gige_order}")
            parts = dict(zip(self._gige_order, comps, strict=True))
            self._check_formats(parts)
            xyz_c, n_c, conf_c = parts["Range"], parts["Normal"], parts["Confidence"]
        else:
            needed = max(_PHOTONEO_COMPONENTS) + 1
            if len(comps) < needed:
                raise DeviceFault(self.name, f"buffer has {len(comps)} components, expected at least {needed}")
            xyz_c, n_c, conf_c = (comps[i] for i in _PHOTONEO_COMPONENTS)
        xyz = _pixels(xyz_c, 3)
        if xyz is None or len(xyz) == 0:
            raise DeviceFault(self.name, "buffer has no point cloud (SendPointCloud / Range off?)")
        normals, conf = _pixels(n_c, 3), _pixels(conf_c, 1)
        if conf is not None and len(conf) == len(xyz):
            conf = np.clip(conf[:, 0] / self._confidence_best, 0.0, 1.0)
        else:
            conf = None
        valid = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0, axis=1)
        if conf is not None:
            valid &= conf > 0
        if normals is not None and (len(normals) != len(xyz) or not np.any(normals[valid])):
            normals = None  # no normal map, or an all-zero one (NormalsEstimationRadius 0)
        return ScanFrame(
            points_mm=xyz[valid].astype(np.float64),
            normals=normals[valid].astype(np.float64) if normals is not None else None,
            confidence=conf[valid].astype(np.float64) if conf is not None else None,
            timestamp_s=time.time(),
        )

    def _check_formats(self, parts: dict[str, Any]) -> None:
        """Each GigE part's pixel format (where the producer reports it) must be the configured one."""
        formats = self._gige_formats
        for name, part in parts.items():
            got = getattr(part, "data_format", None)
            if got is not None and got != formats[name]:
                raise DeviceFault(self.name, f"{name} part is {got}, expected {formats[name]}")


def _pixels(component: Any, channels: int) -> np.ndarray | None:
    """A component's data as ``(width * height, channels)`` float, or None when the component is empty."""
    n = int(component.width) * int(component.height)
    if n == 0 or component.data is None or component.data.size == 0:
        return None
    data = np.asarray(component.data, dtype=np.float32)
    if data.size != n * channels:
        raise ValueError(f"component of {data.size} values for {component.width}x{component.height}x{channels}")
    return data.reshape(n, channels).copy()


def _identities(info: Any) -> set[str]:
    """What identifies a device in harvesters' device list (its ``property_dict``): serial number, ID with and
    without the producer's ``<producer>_DEV_`` prefix, user-defined name; empty values left out."""
    props = getattr(info, "property_dict", info)
    ids = {str(props.get(key) or "") for key in ("serial_number", "id_", "user_defined_name")}
    device_id = str(props.get("id_") or "")
    if "_DEV_" in device_id:
        ids.add(device_id.split("_DEV_", 1)[1])
    return ids - {""}


def _release(acquirer: Any, harvester: Any) -> None:
    steps = (getattr(acquirer, "stop", None), getattr(acquirer, "destroy", None), getattr(harvester, "reset", None))
    for step in steps:
        if step is not None:
            with contextlib.suppress(Exception):  # best effort while tearing down a vendor stack
                step()

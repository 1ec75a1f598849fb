"""The fake ``harvesters.core``: one simulated PhoXi camera (``CAMERA``) behind a GenTL-like API.

``CAMERA.interface`` picks the buffer layout: ``photoneo_gentl`` (PhoXi Control's eight components in a fixed
order, switched by ``Send*`` nodes) or ``gige_vision`` (GenICam component selection: ``ComponentSelector``
with ``ComponentEnable``, ``PixelFormat`` and ``ComponentIDValue`` per component; a buffer has one part per
enabled component in increasing ID; Intensity and Range are enabled at power-up, as on a device fresh from
the factory; Confidence is ``Confidence8``, 0 invalid, 255 best; ``NormalsEstimationRadius`` 0 sends zeros).

Each software trigger starts a scan of the ``scene`` callable set then, complete ``fetch_delay_s`` later (the
callable runs at fetch: one that reads a live world, as the hil cell's does, shows it as it is then); ``fetch``
takes the scans in the order they complete, so a scan whose fetch timed out is still delivered to a later
fetch unless the acquisition was stopped in between (GenTL's stop flushes the output queue, as harvesters'
``ImageAcquirer.stop`` does with ``ACQ_QUEUE_ALL_DISCARD``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Component order of PhoXi Control's GenTL producer (Photoneo's harvesters examples).
PHOTONEO_COMPONENTS = ("Texture", "TextureRGB", "PointCloud", "NormalMap", "DepthMap", "ConfidenceMap",
                       "EventMap", "ColorCameraImage")
# Photoneo nodes that switch each component on, in the same order.
PHOTONEO_SEND_NODES = ("SendTexture", "SendTextureRGB", "SendPointCloud", "SendNormalMap", "SendDepthMap",
                       "SendConfidenceMap", "SendEventMap", "SendColorCameraImage")

# GigE Vision components of the fake: ComponentIDValue, enabled at power-up. Intensity, Range and Confidence
# carry their GenICam SFNC IDs; the others stand for vendor-specific ones above them.
GIGE_COMPONENTS = {"Intensity": (1, True), "Range": (4, True), "Confidence": (6, False), "Normal": (0x8001, False),
                   "Event": (0x8002, False), "ColorCamera": (0x8003, False)}
_PER_COMPONENT_NODES = ("ComponentEnable", "PixelFormat")
_DEFAULT_PIXEL_FORMATS = {"Intensity": "Mono16", "Range": "Coord3D_ABC32f", "Confidence": "Confidence8",
                          "Normal": "Coord3D_ABC32f", "Event": "Mono8", "ColorCamera": "RGB8"}

Scene = Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]


class TimeoutException(Exception):
    """Raised by ``fetch`` when no frame arrives in time (GenTL's timeout error)."""


def recorded_style_scene(width: int = 64, height: int = 48, distance_mm: float = 442.0) -> Scene:
    """A frame like a PhoXi S capture of a gently curved panel at the sweet spot: ``(xyz, normals, confidence)``
    each ``(height, width, ...)`` float32 in the scanner frame (mm), corner pixels invalid (zeros)."""

    def scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u, v = np.meshgrid(np.linspace(-170, 170, width), np.linspace(-130, 130, height))
        z = distance_mm + 2e-4 * u**2
        xyz = np.stack([u, v, z], axis=-1)
        n = np.stack([-4e-4 * u, np.zeros_like(u), -np.ones_like(u)], axis=-1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        conf = np.full(u.shape, 0.9)
        invalid = (np.abs(u) > 150) & (np.abs(v) > 110)
        xyz[invalid] = 0.0
        n[invalid] = 0.0
        conf[invalid] = 0.0
        return xyz.astype(np.float32), n.astype(np.float32), conf.astype(np.float32)

    return scene


@dataclass
class FakeCamera:
    """The camera state tests and the hil cell set: scene, a fetch delay (slow scan), and what was written."""

    device_id: str = "FAKE-001"  # Photoneo's ID of the device (on its label, in PhoXi Control)
    serial_number: str = "PHOXI-FAKE-1"  # what PhoXi Control's producer lists as serial_number (not the ID)
    user_defined_name: str = ""  # GigE Vision DeviceUserID
    interface: str = "photoneo_gentl"  # or "gige_vision": which producer the fake stands for
    scene: Scene = field(default_factory=recorded_style_scene)
    fetch_delay_s: float = 0.0
    node_values: dict[str, object] = field(default_factory=dict)
    triggers: int = 0
    open_acquirers: int = 0
    scans: list[tuple[float, Scene]] = field(default_factory=list)  # per trigger: (time.monotonic() done, scene)

    def reset(self) -> None:
        self.__init__()  # type: ignore[misc]


CAMERA = FakeCamera()


class _Node:
    """One GenICam node; ``ComponentEnable`` and ``PixelFormat`` hold a value per selected component."""

    def __init__(self, name: str, camera: FakeCamera):
        self._name, self._camera = name, camera

    @property
    def _key(self) -> str:
        if self._name in _PER_COMPONENT_NODES:
            return f"{self._name}[{self._camera.node_values.get('ComponentSelector')}]"
        return self._name

    @property
    def value(self) -> object:
        selected = str(self._camera.node_values.get("ComponentSelector"))
        if self._name == "ComponentIDValue":
            return GIGE_COMPONENTS[selected][0]
        if self._key not in self._camera.node_values:
            if self._name == "ComponentEnable":
                return GIGE_COMPONENTS.get(selected, (0, False))[1]
            if self._name == "PixelFormat":
                return _DEFAULT_PIXEL_FORMATS.get(selected)
        return self._camera.node_values.get(self._key)

    @value.setter
    def value(self, v: object) -> None:
        if self._name == "ComponentSelector" and v not in GIGE_COMPONENTS:
            raise ValueError(f"ComponentSelector has no entry {v!r}")
        self._camera.node_values[self._key] = v

    @property
    def symbolics(self) -> tuple[str, ...]:
        """The entries of an enumeration node (only ComponentSelector has them here)."""
        return tuple(GIGE_COMPONENTS) if self._name == "ComponentSelector" else ()

    def execute(self) -> None:
        """A software trigger: a scan of the scene as it is now, complete after the camera's fetch delay."""
        cam = self._camera
        cam.node_values[self._name] = "executed"
        cam.triggers += 1
        cam.scans.append((time.monotonic() + cam.fetch_delay_s, cam.scene))


class _NodeMap:
    def __init__(self, camera: FakeCamera):
        object.__setattr__(self, "_camera", camera)

    def __getattr__(self, name: str) -> _Node:
        return _Node(name, self._camera)


@dataclass
class _Component:
    data: np.ndarray
    width: int
    height: int
    data_format: str | None = None


@dataclass
class _Payload:
    components: list[_Component]


class _Buffer:
    def __init__(self, components: list[_Component]):
        self.payload = _Payload(components)
        self.timestamp_ns = time.time_ns()

    def __enter__(self) -> _Buffer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.queue()

    def queue(self) -> None:
        self.payload = _Payload([])


class _RemoteDevice:
    def __init__(self, camera: FakeCamera):
        self.node_map = _NodeMap(camera)


class ImageAcquirer:
    def __init__(self, camera: FakeCamera):
        self._camera = camera
        self.remote_device = _RemoteDevice(camera)
        self._taken = set(range(len(camera.scans)))  # scans delivered or discarded (triggered before it opened)
        self._started = False
        camera.open_acquirers += 1

    def start(self) -> None:
        self._started = True

    def stop(self) -> None:
        """Stop acquiring and flush the queues: scans under way or complete and not fetched are discarded."""
        self._started = False
        self._taken.update(range(len(self._camera.scans)))

    def destroy(self) -> None:
        self._camera.open_acquirers -= 1

    def fetch(self, timeout: float = 0) -> _Buffer:
        """The first scan to complete of those not yet fetched; ``TimeoutException`` after ``timeout`` s without
        one."""
        cam = self._camera
        waiting = [(done, k) for k, (done, _) in enumerate(cam.scans) if k not in self._taken]
        done, k = min(waiting) if waiting and self._started else (math.inf, -1)
        wait_s = done - time.monotonic()
        if wait_s > timeout:
            time.sleep(timeout)  # a blocking GenTL call: the driver makes it on a worker thread
            raise TimeoutException(f"no buffer within {timeout} s")
        time.sleep(max(0.0, wait_s))
        self._taken.add(k)
        xyz, normals, conf = cam.scans[k][1]()
        return _Buffer(_gige_parts(cam, xyz, normals, conf) if cam.interface == "gige_vision"
                       else _photoneo_components(cam, xyz, normals, conf))


def _photoneo_components(cam: FakeCamera, xyz: np.ndarray, normals: np.ndarray, conf: np.ndarray) -> list[_Component]:
    """PhoXi Control's layout: all eight components, those not sent empty."""
    h, w = conf.shape
    comps = []
    for name, send in zip(PHOTONEO_COMPONENTS, PHOTONEO_SEND_NODES, strict=True):
        enabled = cam.node_values.get(send) is True
        data = {"PointCloud": xyz, "NormalMap": normals, "ConfidenceMap": conf}.get(name)
        if enabled and data is not None:
            comps.append(_Component(np.ascontiguousarray(data).reshape(-1), w, h))
        else:
            comps.append(_Component(np.zeros(0, np.float32), 0, 0))
    return comps


def _gige_parts(cam: FakeCamera, xyz: np.ndarray, normals: np.ndarray, conf: np.ndarray) -> list[_Component]:
    """One part per enabled GigE component, in increasing ComponentIDValue, in its pixel format."""
    h, w = conf.shape
    if cam.node_values.get("NormalsEstimationRadius", 2) == 0:
        normals = np.zeros_like(normals)
    data = {
        "Intensity": np.full((h, w), 1000, np.uint16), "Range": xyz.astype(np.float32),
        "Confidence": np.round(np.clip(conf, 0, 1) * 255).astype(np.uint8), "Normal": normals.astype(np.float32),
        "Event": np.zeros((h, w), np.uint8), "ColorCamera": np.zeros((h, w, 3), np.uint8),
    }
    parts = []
    for name, (_, enabled_at_boot) in sorted(GIGE_COMPONENTS.items(), key=lambda item: item[1][0]):
        if cam.node_values.get(f"ComponentEnable[{name}]", enabled_at_boot) is True:
            fmt = cam.node_values.get(f"PixelFormat[{name}]", _DEFAULT_PIXEL_FORMATS[name])
            parts.append(_Component(np.ascontiguousarray(data[name]).reshape(-1), w, h, str(fmt)))
    return parts


@dataclass(frozen=True)
class DeviceInfo:
    """harvesters' device info: the GenTL producer's properties of one device (``property_dict``)."""

    property_dict: dict[str, str]


def device_info(cam: FakeCamera) -> DeviceInfo:
    """How the producer lists the camera: PhoXi Control's as ``id_`` ``PhotoneoTL_DEV_<ID>`` beside a serial
    number of its own (Photoneo's GenTL examples open ``{"id_": ...}``); a GigE Vision producer with the ID as the
    serial number (Photoneo's GigE examples open ``{"serial_number": ...}``)."""
    gige = cam.interface == "gige_vision"
    return DeviceInfo({"id_": f"{'GEV' if gige else 'PhotoneoTL'}_DEV_{cam.device_id}",
                       "serial_number": cam.device_id if gige else cam.serial_number,
                       "user_defined_name": cam.user_defined_name, "vendor": "Photoneo", "model": "PhoXi3DScanner-S"})


class Harvester:
    """``add_file`` a producer, ``update``, then ``create`` an acquirer for the one fake camera."""

    def __init__(self) -> None:
        self.files: list[str] = []
        self.device_info_list: list[DeviceInfo] = []

    def add_file(self, file_path: str) -> None:
        if not Path(file_path).is_file():
            raise FileNotFoundError(file_path)
        self.files.append(file_path)

    def update(self) -> None:
        self.device_info_list = [device_info(CAMERA)] if self.files else []

    def create(self, search_key: dict[str, str] | int | None = None) -> ImageAcquirer:
        """An acquirer for the device at index ``search_key``, or the one whose properties have every value of the
        dict ``search_key``, or the first; ValueError when none is."""
        infos = self.device_info_list
        if isinstance(search_key, dict):
            infos = [i for i in infos if all(i.property_dict.get(k) == v for k, v in search_key.items())]
        elif isinstance(search_key, int):
            infos = infos[search_key : search_key + 1]
        if not infos:
            raise ValueError(f"no device matches {search_key}")
        return ImageAcquirer(CAMERA)

    def reset(self) -> None:
        self.files.clear()
        self.device_info_list.clear()

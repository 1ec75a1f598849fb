"""The fake ``harvesters.core``: one simulated PhoXi camera (``CAMERA``) behind a GenTL-like API."""

from __future__ import annotations

import threading
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

    serial_number: str = "PHOXI-FAKE-1"
    scene: Scene = field(default_factory=recorded_style_scene)
    fetch_delay_s: float = 0.0
    node_values: dict[str, object] = field(default_factory=dict)
    triggers: int = 0
    open_acquirers: int = 0

    def reset(self) -> None:
        self.__init__()  # type: ignore[misc]


CAMERA = FakeCamera()


class _Node:
    def __init__(self, name: str, camera: FakeCamera):
        self._name, self._camera = name, camera

    @property
    def value(self) -> object:
        return self._camera.node_values.get(self._name)

    @value.setter
    def value(self, v: object) -> None:
        self._camera.node_values[self._name] = v

    def execute(self) -> None:
        self._camera.node_values[self._name] = "executed"
        self._camera.triggers += 1


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
        self._pending = 0
        self._lock = threading.Lock()
        self._started = False
        camera.open_acquirers += 1

    def start(self) -> None:
        self._started = True

    def stop(self) -> None:
        self._started = False

    def destroy(self) -> None:
        self._camera.open_acquirers -= 1

    def fetch(self, timeout: float = 0) -> _Buffer:
        """One buffer per software trigger; ``TimeoutException`` after ``timeout`` s without one."""
        cam = self._camera
        delay = cam.fetch_delay_s
        if not self._started or cam.triggers <= self._pending or delay > timeout:
            time.sleep(timeout)
            raise TimeoutException(f"no buffer within {timeout} s")
        time.sleep(delay)
        with self._lock:
            self._pending = cam.triggers
        xyz, normals, conf = cam.scene()
        h, w = conf.shape
        comps = []
        for name, send in zip(PHOTONEO_COMPONENTS, PHOTONEO_SEND_NODES, strict=True):
            enabled = cam.node_values.get(send) is True
            data = {"PointCloud": xyz, "NormalMap": normals, "ConfidenceMap": conf}.get(name)
            if enabled and data is not None:
                comps.append(_Component(np.ascontiguousarray(data).reshape(-1), w, h))
            else:
                comps.append(_Component(np.zeros(0, np.float32), 0, 0))
        return _Buffer(comps)


class Harvester:
    """``add_file`` a producer, ``update``, then ``create`` an acquirer for the one fake camera."""

    def __init__(self) -> None:
        self.files: list[str] = []
        self.device_info_list: list[dict[str, str]] = []

    def add_file(self, file_path: str) -> None:
        if not Path(file_path).is_file():
            raise FileNotFoundError(file_path)
        self.files.append(file_path)

    def update(self) -> None:
        self.device_info_list = [{"serial_number": CAMERA.serial_number}] if self.files else []

    def create(self, search_key: dict[str, str] | int | None = None) -> ImageAcquirer:
        if isinstance(search_key, dict) and search_key.get("serial_number") not in (None, CAMERA.serial_number):
            raise ValueError(f"no device matches {search_key}")
        if not self.device_info_list:
            raise ValueError("no device found")
        return ImageAcquirer(CAMERA)

    def reset(self) -> None:
        self.files.clear()
        self.device_info_list.clear()

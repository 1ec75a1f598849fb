"""The simulated scanner's ray casting in a worker process, so that it never holds the daemon's GIL.

Open3D's ``RaycastingScene.cast_rays`` of a full-resolution capture (3.2 M rays) holds the GIL for up to
2.6 s; run in a thread of the daemon it stalls the event loop, the REST API and the 50 Hz safety loop. The
worker builds its own copy of the world's scene (the part as built, the fixture's spheres) from the
configuration, is fed the true scanner pose ``T_F_S`` (mm) and the state of the world's random generator,
and returns the points and normals in frame S as shared-memory arrays (:mod:`tandemscan.drivers.shared_array`)
together with the generator's new state. The noise is drawn from the same stream in the same order as
:meth:`SimWorld.scan`, so a capture is identical to the in-process one: same seed, same cloud.
"""

from __future__ import annotations

import asyncio
import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from tandemscan.config.models import CellConfig
from tandemscan.drivers.shared_array import hand_over, take
from tandemscan.drivers.worker import init_worker, stop_pool

_SCENE = None
_MODEL = None


def _init(config: CellConfig, niceness: int) -> None:
    global _SCENE, _MODEL
    from tandemscan.pipeline.geometry.raycast import ScannerModel, make_scene
    from tandemscan.sim_drivers.as_built import scanned_part_mesh

    init_worker(niceness)
    _SCENE = make_scene(scanned_part_mesh(config))  # what the world scans: the part as built, the spheres
    _MODEL = ScannerModel(config.scanner)


def _ready() -> bool:
    return _SCENE is not None


def generator_from_state(state: dict) -> np.random.Generator:
    """A generator that continues the stream of ``bit_generator.state`` ``state``."""
    bit_generator = getattr(np.random, state["bit_generator"])()
    bit_generator.state = state
    return np.random.Generator(bit_generator)


def _scan(T_F_S: np.ndarray, rng_state: dict) -> tuple:
    rng = generator_from_state(rng_state)
    points, normals = _MODEL.scan(_SCENE, T_F_S, rng)
    return hand_over(points), hand_over(normals), rng.bit_generator.state


class ScanProcess:
    """One worker process casting the scanner's rays on its own copy of the part the world of ``config`` scans
    (close it when done)."""

    def __init__(self, config: CellConfig, niceness: int = 0):
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init, initargs=(config, niceness))
        self._warm = self._pool.submit(_ready)  # start building the scene now, not at the first capture

    async def scan(self, T_F_S: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(points_S mm, normals_S) at the true pose ``T_F_S``; advances ``rng`` as the in-process scan does."""
        state = rng.bit_generator.state
        points, normals, new_state = await asyncio.wrap_future(
            self._pool.submit(_scan, np.asarray(T_F_S, float), state))
        rng.bit_generator.state = new_state
        return take(points), take(normals)

    def close(self) -> None:
        stop_pool(self._pool)

"""Issue 43's memory line for the correction at a small size (docs/capacity.md): a Dask worker's memory in the
correction is a unit's, not its share of the part's pairs. The joint refinement's per-pair results (each pair's
matches, 26 B a correspondence) wait between its stages in files of the scan store (``compute.StoredResults``), not
on the workers, so that a worker's peak on a part twice as long stays within 15 % of that on the shorter one.

A strip of 14 and of 28 scans (:func:`stored_strip`: each overlapping its seven neighbours on either side, as a part's
scans do) written as raw scans to a scan store and corrected on :class:`OneWorker`: the units run one at a time in
this process as on one Dask worker, which keeps what :meth:`ComputeBackend.keep` leaves with it until its last handle
is released. Memory is traced (``tracemalloc``: NumPy reports every array it allocates), so the figures are exact and
repeatable; a Dask worker's own bookkeeping of a stage's tasks (a few KB a task) and the full-resolution figures come
from ``benchmarks/capacity.py``.
"""

from __future__ import annotations

import pickle
import tracemalloc
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from tandemscan.config.models import CorrectionConfig
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.geometry.frames import compose, from_rotvec, invert, transform_points
from tandemscan.pipeline.io.raw_scan import write_raw_scan
from tandemscan.pipeline.registration.correction import (
    CorrectionSettings,
    StitchedJob,
    StitchedScan,
    correct_scans,
)

from tests.pipeline.registration.test_registration_correction import surface

pytestmark = pytest.mark.slow  # two corrections traced: about 5 CPU seconds
#: a worker's peak on the part twice as long, at most this times the shorter one's (issue 43: 15 %)
GROWTH = 1.15
VOXEL_MM = 1.0
#: the joint refinement (the default) without check pairs and with the report's overlap RMS on one partner a scan:
#: units of their own, bounded by their scans, whose time the test need not spend
JOINT = CorrectionSettings.from_section(CorrectionConfig(method="icp", min_overlap_points=100,
                                                         check_partners_per_scan=0, max_partners_per_scan=1))


def stored_strip(store: Path, scans: int, seed: int = 0) -> StitchedJob:
    """A strip of ``scans`` scans of the drift scenario's surface (``test_registration_correction.surface``), each a
    160 x 60 mm patch of 9,600 points (0.05 mm noise along the view) every 20 mm along x, so that each overlaps its
    seven neighbours on either side as a part's scans do (a scan's correspondences, not its points, are what the
    refinement's pairs hold); its tracker pose off the truth by 0.01 mm and 0.001 deg; one tracker station. Each is
    written as a raw scan under ``store/scans`` and referenced by its file only (the end of a job on the scan store
    holds no scan's points)."""
    rng = np.random.default_rng(seed)
    (store / "scans").mkdir(parents=True)
    cov = np.diag([0.01**2] * 3 + [np.radians(0.001) ** 2] * 3)
    out = []
    for k in range(scans):
        xy = np.c_[rng.uniform(20.0 * k - 80, 20.0 * k + 80, 9600), rng.uniform(-30, 30, 9600)]
        T_W_S = from_rotvec([20.0 * k, 0, 440.0], [np.pi, 0, 0])
        P_S = transform_points(invert(T_W_S), np.c_[xy, surface(xy[:, 0], xy[:, 1])])
        P_S[:, 2] += rng.normal(0, 0.05, len(P_S))
        file = f"scans/scan-{k:04d}.npz"
        write_raw_scan(store / file, points_S_mm=P_S)
        noise = from_rotvec(rng.normal(0, 0.01, 3), rng.normal(0, np.radians(0.001), 3))
        out.append(StitchedScan(None, compose(noise, T_W_S), cov, 0, file))
    return StitchedJob(out, voxel_mm=VOXEL_MM)


@dataclass(eq=False)
class Held:
    """A result :class:`OneWorker` keeps: its handle (as a Dask future), the value on the worker."""

    value: Any


class OneWorker(LocalBackend):
    """The units one at a time in this process, as one single-threaded Dask worker runs them: :meth:`keep`'s results
    stay with it (:class:`Held`, their pickled bytes counted as held until this process drops the handle, as a worker
    holds a future's data), the inputs given as handles are taken there. ``peak``: the most a unit's traced peak and
    the bytes held as it ran came to (bytes); ``held_peak``: the most bytes held at once."""

    def __init__(self) -> None:
        super().__init__(1)
        self.held = self.peak = self.held_peak = 0

    def _release(self, size: int) -> None:
        self.held -= size

    def map(self, fn: Callable, units: Sequence, keys: Sequence[str], inputs: Sequence[Sequence] | None = None
            ) -> list:
        out = []
        for k, unit in enumerate(units):
            given = [x.value if isinstance(x, Held) else x for x in (inputs[k] if inputs is not None else ())]
            tracemalloc.reset_peak()
            start = tracemalloc.get_traced_memory()[0]
            out.append(fn(unit, *given))
            self.peak = max(self.peak, self.held + tracemalloc.get_traced_memory()[1] - start)
        return out

    def keep(self, fn: Callable, units: Sequence, keys: Sequence[str], inputs: Sequence[Sequence] | None = None
             ) -> list:
        handles = [Held(v) for v in self.map(fn, units, keys, inputs)]
        for h in handles:
            size = len(pickle.dumps(h.value))
            self.held += size
            weakref.finalize(h, self._release, size)
        self.held_peak = max(self.held_peak, self.held)
        return handles


@pytest.fixture(scope="module")
def strips(tmp_path_factory) -> dict[int, tuple[OneWorker, dict]]:
    """Per strip length (14 and 28 scans) the worker it was corrected on and the correction's report."""
    out = {}
    tracemalloc.start()
    try:
        for scans in (14, 28):
            store = tmp_path_factory.mktemp(f"part{scans}")
            worker = OneWorker()
            report = correct_scans(stored_strip(store, scans), JOINT, backend=worker, scan_store=str(store)).report
            out[scans] = worker, report
    finally:
        tracemalloc.stop()
    return out


def test_a_workers_correction_peak_does_not_grow_with_the_part(strips):
    """The worker holds none of the pairs' matches between the refinement's stages (they wait in the store's files),
    and its peak on the strip twice as long is within 15 % of the shorter one's; with the matches kept on it
    (``ComputeBackend.keep`` on Dask) it grew with the pairs (the figures: docs/capacity.md)."""
    (short, short_report), (long_, long_report) = (strips[n] for n in (14, 28))
    assert long_report["joint"]["pairs"] > 2 * short_report["joint"]["pairs"]
    assert long_report["joint"]["correspondences"] > 2 * short_report["joint"]["correspondences"]
    assert long_.held_peak == long_.held == 0        # nothing waits on the worker between its units
    assert long_.peak <= GROWTH * short.peak, (short.peak, long_.peak)

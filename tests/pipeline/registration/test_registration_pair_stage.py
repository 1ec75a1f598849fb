"""The pair stage's units on a backend: handed out largest first, their outcomes returned in the units' order."""

from __future__ import annotations

import numpy as np
from tandemscan.config.models import CorrectionConfig
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.registration import pair_stage
from tandemscan.pipeline.registration.pair_stage import HeldScans, PairOutcome, ScanRef, TargetPairs, register_units
from tandemscan.pipeline.registration.pairs import JobPairSettings


def test_units_run_largest_first_and_come_back_in_order(monkeypatch):
    def ref(i: int) -> ScanRef:
        return ScanRef(i, f"scan-{i}.npz", np.eye(4))

    sizes = [1, 3, 2, 3, 1]
    units = [TargetPairs(ref(t), tuple(ref(10 * t + s) for s in range(n)), tuple(np.eye(6) for _ in range(n)))
             for t, n in enumerate(sizes)]
    ran = []

    def record(unit: TargetPairs, scans, cfg, network):
        ran.append(unit.target.index)
        return [PairOutcome(inliers=s.index) for s in unit.sources]

    monkeypatch.setattr(pair_stage, "register_unit", record)
    out = register_units(units, HeldScans([]), JobPairSettings.from_section(CorrectionConfig()), 1.0,
                         LocalBackend(1))
    assert ran == [1, 3, 2, 0, 4]                     # most sources first, ties in their order
    assert [[o.inliers for o in group] for group in out] == [[s.index for s in u.sources] for u in units]

"""The job's records read the journal as the daemon has written it since it first resumed jobs, and ``apply``
changes the job's state as the runner's steps do (the journaled-job replay itself: tests/daemon/test_relocalise.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tandemscan.daemon.jobs.records import (
    AnchorEntry,
    MeasureMove,
    RelocalisationEntry,
    ScanRecord,
    TransferRecord,
    UntrackedScan,
    record_from_json,
)
from tandemscan.daemon.jobs.run_state import RelocalisationState, RunState, apply, replay_journal
from tandemscan.pipeline.planning.plan import MoveArm, MoveLift, MoveMeasure, MoveTracker, Scan


def pose(x: float, y: float = 0.0, z: float = 0.0) -> list[list[float]]:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T.tolist()


COV = (np.eye(6) * 1e-4).tolist()
RELOC = {"T_F_W": pose(5.0), "T_F_V2": pose(7.0, 1.0), "planned_T_F_V2": pose(7.0), "anchor": {
    "step": 0, "placed": True, "source": "measurement AGV where its odometry says"},
    "located": {"step": 3, "off_plan_mm": 1.0, "off_plan_deg": 0.01}, "unresolved": None, "adjusted": None}
SCAN = {"index": 0, "station": 0, "file": "scan-0000.npz", "points": 1234, "T_C_T": pose(1.0, 2.0, 3000.0),
        "covariance": COV, "timestamp_s": 12.5, "frame_number": 7, "joints_rad": [0.1, -0.2, 0.3, 0.0, 0.5, 0.6],
        "T_W_C": pose(0.0), "T_W_S": pose(1.5, 2.0, 3100.0)}
TRANSFER = {"T_W_C": pose(-800.0, 10.0), "station": 1, "transfer": {
    "station": 1, "after_scan": 1, "target_W_mm": [1.0, 2.0, 3000.0], "covariance": COV},
    "before": pose(1.0, 2.0, 3000.0), "after": pose(801.0, -8.0, 3000.0), "odometry": [1500.0, -200.0, 0.25]}
# every step kind as an earlier version journaled it: (step, committed result)
JOURNAL = [
    (MoveTracker(x_mm=0.0, y_mm=0.0, heading_rad=0.0), {"relocation": True, "odometry": [0.0, 1.0, 0.5],
                                                        "relocalisation": RELOC | {"located": None}}),
    (MoveMeasure(x_mm=7.0, y_mm=0.0, heading_rad=0.0), {"odometry": [7.1, 0.2, 0.001], "relocalisation": RELOC}),
    (MoveLift(height_mm=300.0), {"height_mm": 299.98}),
    (MoveArm(joints_rad=(0.1, -0.2, 0.3, 0.0, 0.5, 0.6)), {"joints_rad": [0.1, -0.2, 0.3, 0.0, 0.5, 0.6]}),
    (Scan(label="a"), SCAN),
    (MoveTracker(x_mm=1500.0, y_mm=-200.0, heading_rad=0.25), TRANSFER),
    (Scan(label="b"), {"untracked": {"step": 6, "label": "b", "reason": "target occluded"}}),
]


@pytest.mark.parametrize("step, result", JOURNAL, ids=[f"{i}-{s.kind}" for i, (s, _) in enumerate(JOURNAL)])
def test_a_journaled_result_reads_into_its_record_and_back_unchanged(step, result, tmp_path):
    stored = json.loads(json.dumps(result))  # as the store keeps it
    record = record_from_json(step, stored, tmp_path)
    again = json.loads(json.dumps(record.to_json()))
    assert json.dumps(again) == json.dumps(stored)  # same keys, same order, same values
    if isinstance(record, ScanRecord):
        assert record.file == tmp_path / "scans" / "scan-0000.npz" and record.reading.frame_number == 7


def test_apply_builds_the_state_the_steps_left():
    job_dir = Path("/job")
    state = replay_journal(RunState(relocalisation=RelocalisationState(enabled=True)),
                           (record_from_json(step, result, job_dir) for step, result in JOURNAL))
    reloc = state.relocalisation
    assert np.array_equal(reloc.T_F_W, np.array(RELOC["T_F_W"])) and reloc.anchor == RELOC["anchor"]
    assert reloc.located == (RELOC["located"],) and reloc.unresolved == ()  # the relocation located nothing
    assert reloc.untracked == ({"step": 6, "label": "b", "reason": "target occluded"},)
    assert state.lift_mm == 299.98 and len(state.scans) == 1 and state.tracker_station == 1
    assert isinstance(state.transfers[0], TransferRecord) and state.transfers[0].entry() == TRANSFER["transfer"]
    assert np.array_equal(state.T_W_C, np.array(TRANSFER["T_W_C"]))
    assert np.array_equal(state.last_still_T_C_T, np.array(TRANSFER["after"]))  # the still target after the move
    moved = apply(state, record_from_json(MoveArm(joints_rad=(0.0,) * 6), {"joints_rad": [0.0] * 6}, job_dir))
    assert moved.last_still_T_C_T is None and state.last_still_T_C_T is not None  # a new state, the old one kept
    untracked = UntrackedScan(9, "c", "occluded")
    assert apply(moved, untracked).relocalisation.untracked[-1] == untracked.entry()


def test_an_anchor_noted_at_the_start_places_the_world_and_the_planned_station():
    note = {"step": 0, "placed": True, "source": "measurement AGV where its odometry says",
            "T_F_W": pose(5.0), "T_F_V2": pose(7.0)}
    entry = AnchorEntry.from_json(json.loads(json.dumps(note)))
    assert entry.to_json() == note
    reloc = apply(RunState(), entry).relocalisation
    assert np.array_equal(reloc.planned_T_F_V2, np.array(pose(7.0))) and reloc.anchor == {
        k: note[k] for k in ("step", "placed", "source")}
    unseen = apply(RunState(), AnchorEntry(0, False, reason="occluded", planned_T_F_V2=np.eye(4))).relocalisation
    assert unseen.T_F_W is None and unseen.anchor == {"step": 0, "placed": False, "reason": "occluded"}


def test_a_drive_the_job_did_not_measure_leaves_no_stale_agv_pose():
    """A drive without a relocalisation entry (the job re-solves no scanner pose, so it does not locate the AGV)
    leaves the AGV unmeasured: the state no longer says it stands where it was measured and planned before the
    drive (the restart check's last fallback compared a fresh location with that; a later anchor would place W
    from it); W stays placed. A drive with an entry takes the entry's."""
    T_F_W, before = np.array(pose(5.0)), np.array(pose(7.0, 1.0))
    anchored = apply(RunState(), AnchorEntry(0, True, "measurement AGV where its odometry says", None, T_F_W, before,
                                             before))
    driven = apply(anchored, MeasureMove((1500.0, 0.0, 0.0), None)).relocalisation
    assert driven.T_F_V2 is None and driven.planned_T_F_V2 is None
    assert np.array_equal(driven.T_F_W, T_F_W) and driven.anchor == anchored.relocalisation.anchor
    after = np.array(pose(1507.0, 2.0))
    entry = RelocalisationEntry(T_F_W, after, np.array(pose(1500.0)), anchored.relocalisation.anchor,
                                {"step": 1, "off_plan_mm": 7.3, "off_plan_deg": 0.0})
    located = apply(anchored, MeasureMove((1500.0, 0.0, 0.0), entry)).relocalisation
    assert np.array_equal(located.T_F_V2, after) and located.located == (entry.located,)

"""The unified command sequence: alternation, transfers at shared poses, every seen pose scanned once."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.pipeline.planning.plan import MoveArm, MoveMeasure, MoveTracker, Plan, Scan
from tandemscan.pipeline.planning.sequence import PoseRef, SequenceError, build_sequence

HOME = np.zeros(6)


def poses(n: int, per_station: int = 3) -> list[PoseRef]:
    return [PoseRef(i // per_station, (1000.0 * (i // per_station), 0.0, 0.0), (0.1 * (i + 1),) * 6, f"p{i}")
            for i in range(n)]


def test_sequence_scans_each_seen_pose_once_and_transfers_at_a_shared_pose(tmp_path):
    ps = poses(9)
    cover = np.array([
        [1, 1, 1, 1, 1, 0, 0, 0, 0],
        [0, 0, 0, 0, 1, 1, 1, 1, 0],
    ], bool)
    seq = build_sequence(ps, [(0.0, 5000.0, -1.5), (3000.0, 5000.0, -1.5)], cover, HOME, "t")
    assert sorted(seq.scan_order) == list(range(8))  # pose 8 is seen by no station: left out
    assert seq.transfer_poses == (4,)  # the last scan under station 0 is seen by station 1: no extra move
    steps = seq.plan.steps
    i_transfer = next(i for i, s in enumerate(steps) if isinstance(s, MoveTracker))
    # the transfer happens with the arm at pose 4 and right after scanning it
    assert isinstance(steps[i_transfer - 1], Scan) and steps[i_transfer - 1].label == "p4"
    # scans after the transfer are all read from station 1
    assert all(k == 1 for k, i in zip(seq.scan_tracker_station, seq.scan_order, strict=True) if i in (5, 6, 7))
    # the arm folds home before each AGV drive
    for a, b in zip(steps[:-1], steps[1:], strict=True):
        if isinstance(b, MoveMeasure) and a is not steps[0]:
            assert isinstance(a, MoveArm) and a.joints_rad == tuple(HOME)
    seq.plan.save(tmp_path / "p.toml")
    assert Plan.load(tmp_path / "p.toml").scan_count == 8


def test_a_transfer_names_the_other_shared_poses_at_its_station_nearest_first(tmp_path):
    """Poses 2-5 are seen from both tracker stations; the transfer at pose 5 (AGV station 1) names 4 and 3, the
    nearer in joints first, and not 2 (another AGV station) or 6 (seen from the second tracker station only)."""
    ps = poses(9)
    cover = np.array([[1, 1, 1, 1, 1, 1, 0, 0, 0], [0, 0, 1, 1, 1, 1, 1, 1, 1]], bool)
    seq = build_sequence(ps, [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)], cover, HOME, "t")
    assert seq.transfer_poses == (5,)
    (transfer,) = [s for s in seq.plan.steps if isinstance(s, MoveTracker)]
    assert transfer.alternatives == ("p4", "p3")
    seq.plan.save(tmp_path / "p.toml")
    (loaded,) = [s for s in Plan.load(tmp_path / "p.toml").steps if isinstance(s, MoveTracker)]
    assert loaded == transfer


def test_transfer_goes_back_to_a_shared_pose_when_the_last_scan_is_not_shared():
    ps = poses(6)
    cover = np.array([[1, 1, 1, 1, 0, 0], [0, 1, 0, 0, 1, 1]], bool)
    seq = build_sequence(ps, [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)], cover, HOME, "t")
    assert seq.transfer_poses == (1,)
    steps = seq.plan.steps
    i_transfer = next(i for i, s in enumerate(steps) if isinstance(s, MoveTracker))
    assert isinstance(steps[i_transfer - 1], MoveArm) and steps[i_transfer - 1].joints_rad == ps[1].joints_rad


def test_one_robot_moves_at_a_time_and_a_free_start_moves_the_tracker_first():
    ps = poses(3)
    cover = np.ones((1, 3), bool)
    seq = build_sequence(ps, [(0.0, 0.0, 0.0)], cover, HOME, "t", tracker_starts_at_first=False)
    assert isinstance(seq.plan.steps[0], MoveTracker)
    assert seq.plan.scan_count == 3


def test_chain_without_shared_pose_is_an_error():
    with pytest.raises(SequenceError, match="share no measuring point"):
        build_sequence(poses(4), [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)], np.array([[1, 1, 0, 0], [0, 0, 1, 1]], bool),
                       HOME, "t")

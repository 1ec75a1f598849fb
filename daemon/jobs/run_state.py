"""A job's state as its steps build it, and the one function that changes it: :func:`apply`.

The runner (:class:`tandemscan.daemon.jobs.runner.JobRunner`) measures a step on the devices into a record
(:mod:`tandemscan.daemon.jobs.records`), commits it to the journal and applies it; a resumed job applies the
committed records (:func:`replay_journal`), so running a step and replaying it change the state alike.
Frames and units as in :mod:`tandemscan.daemon.jobs.records`: W the job's world frame, C the tracker camera, T the
target, F the plan's frame, V2 the measurement AGV; mm, rad.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from functools import singledispatch
from pathlib import Path

import numpy as np
from tandemscan.daemon.jobs.records import (
    AnchorEntry,
    ArmMove,
    LiftMove,
    MeasureMove,
    RelocalisationEntry,
    ScanRecord,
    StepRecord,
    TrackerRelocation,
    TransferRecord,
    UntrackedScan,
    record_from_json,
)
from tandemscan.pipeline.planning.plan import MoveTracker, Plan


@dataclass(frozen=True)
class RelocalisationState:
    """Where W and the measurement AGV stand in the plan's frame F (mm; None until measured, ``T_F_V2`` None since
    the AGV drove unmeasured), where the plan puts the AGV, and the report's log: the anchor, the stations
    located, the scan poses not re-solved or scanned with a nearby view, the scans left out (untracked).
    ``enabled``: the job re-solves the arm for the plan's scanner poses."""

    enabled: bool = False
    T_F_W: np.ndarray | None = None
    T_F_V2: np.ndarray | None = None
    planned_T_F_V2: np.ndarray | None = None
    anchor: dict | None = None
    located: tuple[dict, ...] = ()
    unresolved: tuple[dict, ...] = ()
    adjusted: tuple[dict, ...] = ()
    untracked: tuple[dict, ...] = ()

    def entry(self, located: dict | None = None, unresolved: dict | None = None,
              adjusted: dict | None = None) -> RelocalisationEntry:
        """A step's journal entry: this state and the report entries the step adds."""
        return RelocalisationEntry(self.T_F_W, self.T_F_V2, self.planned_T_F_V2, self.anchor, located, unresolved,
                                   adjusted)

    def report(self) -> dict:
        """The report's ``relocalisation`` section before its figures (``report.relocalisation_summary``)."""
        return {"enabled": self.enabled, "anchor": self.anchor, "located": list(self.located),
                "unresolved": list(self.unresolved), "adjusted": list(self.adjusted),
                "untracked": list(self.untracked)}


@dataclass(frozen=True)
class RunState:
    """The job's state after its steps so far: the tracker's station and camera pose in W (``T_W_C``, mm; W is the
    camera frame at its first station), the still target's last reading (``last_still_T_C_T``; None since the
    target moved), the lifting column's height (mm), the AGV relocalisation, the scans and transfers."""

    T_W_C: np.ndarray = field(default_factory=lambda: np.eye(4))
    tracker_station: int = 0
    last_still_T_C_T: np.ndarray | None = None
    lift_mm: float = 0.0
    relocalisation: RelocalisationState = RelocalisationState()
    scans: tuple[ScanRecord, ...] = ()
    transfers: tuple[TransferRecord, ...] = ()


def relocalised(state: RelocalisationState, entry: RelocalisationEntry | None) -> RelocalisationState:
    """``state`` after a step's relocalisation entry: its matrices and anchor, its report entries appended."""
    if entry is None:
        return state
    grown = {key: getattr(state, key) + (value,) for key, value in (
        ("located", entry.located), ("unresolved", entry.unresolved), ("adjusted", entry.adjusted))
        if value is not None}
    return replace(state, T_F_W=entry.T_F_W, T_F_V2=entry.T_F_V2, planned_T_F_V2=entry.planned_T_F_V2,
                   anchor=entry.anchor, **grown)


def apply(state: RunState, record: StepRecord | AnchorEntry) -> RunState:
    """``state`` after ``record``; pure: the devices are the runner's."""
    return _apply(record, state)


@singledispatch
def _apply(record: StepRecord | AnchorEntry, state: RunState) -> RunState:
    raise TypeError(f"not a job record: {type(record).__name__}")


@_apply.register
def _(record: ScanRecord, state: RunState) -> RunState:
    # the scan carries the camera pose it was placed with: one re-established at a resume is kept by a replay
    return replace(state, scans=(*state.scans, record), last_still_T_C_T=record.reading.T_C_T, T_W_C=record.T_W_C)


@_apply.register
def _(record: UntrackedScan, state: RunState) -> RunState:
    reloc = state.relocalisation
    return replace(state, relocalisation=replace(reloc, untracked=(*reloc.untracked, record.entry())))


@_apply.register
def _(record: TransferRecord, state: RunState) -> RunState:
    return replace(state, T_W_C=record.T_W_C, tracker_station=record.station, last_still_T_C_T=record.after_T_C_T,
                   transfers=(*state.transfers, record))


@_apply.register
def _(record: TrackerRelocation, state: RunState) -> RunState:
    return replace(state, T_W_C=np.eye(4), last_still_T_C_T=None,
                   relocalisation=relocalised(state.relocalisation, record.relocalisation))


@_apply.register
def _(record: MeasureMove, state: RunState) -> RunState:
    # a drive without a relocalisation entry (the job re-solves nothing) leaves the AGV unmeasured: where it was
    # measured and planned before the drive is forgotten, never kept as where it stands now (docs/relocalisation.md)
    reloc = state.relocalisation if record.relocalisation is not None else replace(
        state.relocalisation, T_F_V2=None, planned_T_F_V2=None)
    return replace(state, last_still_T_C_T=None, relocalisation=relocalised(reloc, record.relocalisation))


@_apply.register
def _(record: ArmMove, state: RunState) -> RunState:
    return replace(state, last_still_T_C_T=None, relocalisation=relocalised(state.relocalisation,
                                                                            record.relocalisation))


@_apply.register
def _(record: LiftMove, state: RunState) -> RunState:
    return replace(state, last_still_T_C_T=None, lift_mm=record.height_mm)


@_apply.register
def _(record: AnchorEntry, state: RunState) -> RunState:
    reloc = state.relocalisation
    T_F_V2 = record.T_F_V2 if record.placed else reloc.T_F_V2
    return replace(state, relocalisation=replace(reloc, T_F_W=record.T_F_W, T_F_V2=T_F_V2, anchor=record.report(),
                                                 planned_T_F_V2=record.planned_T_F_V2))


def journal_records(plan: Plan, committed: dict[int, dict], notes: Callable[[int], dict[str, dict]],
                    job_dir: Path, opening_anchor: bool) -> Iterable[StepRecord | AnchorEntry]:
    """The records of a job's journal in step order: the anchor noted before its first step (``opening_anchor``:
    the job relocalises and does not open with a tracker move), then each committed step's."""
    if opening_anchor and 0 in committed and (noted := notes(0).get("anchor")) is not None:
        yield AnchorEntry.from_json(noted)
    for i in sorted(committed):
        yield record_from_json(plan.steps[i], committed[i], job_dir)


def replay_journal(state: RunState, records: Iterable[StepRecord | AnchorEntry]) -> RunState:
    """``state`` after every record of a journal (:func:`journal_records`), in order."""
    for record in records:
        state = apply(state, record)
    return state


def opens_with_anchor(plan: Plan, relocalise: bool) -> bool:
    """Whether a job places W in the plan's frame before its first step: it relocalises and the plan does not
    open with a tracker move (which redefines W: the anchor follows it)."""
    return relocalise and bool(plan.steps) and not isinstance(plan.steps[0], MoveTracker)

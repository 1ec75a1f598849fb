"""The job's states and the changes between them: one definition for the store, the manager, the API and the client.

``queued -> running -> succeeded | succeeded_with_gaps | failed | cancelled`` (``succeeded_with_gaps``: the outputs
are written but scans the plan could measure were left out, the tracker not seeing the target; its ``error`` says
which); ``running <-> paused`` (operator), ``paused_safety`` (a
safety stop), ``paused_fault`` (a recoverable fault, ``docs/daemon.md``, faults); a paused job resumes to
``running`` or is cancelled; an active job goes back to ``queued`` when a restart finds more than one active.
A final state is never left. Writing a state again (a queued job's waiting reason, a held state flushed) is no
change and always allowed.
"""

from __future__ import annotations

from enum import StrEnum


class JobState(StrEnum):
    """A job's state; the value is its name in the journal and on the wire."""

    QUEUED = "queued"
    RUNNING = "running"
    PAUSED = "paused"
    PAUSED_SAFETY = "paused_safety"
    PAUSED_FAULT = "paused_fault"
    SUCCEEDED = "succeeded"
    SUCCEEDED_WITH_GAPS = "succeeded_with_gaps"
    FAILED = "failed"
    CANCELLED = "cancelled"


#: the job ran to its end and wrote its outputs (cloud, report, exports)
COMPLETED_STATES = frozenset({JobState.SUCCEEDED, JobState.SUCCEEDED_WITH_GAPS})
FINAL_STATES = frozenset({*COMPLETED_STATES, JobState.FAILED, JobState.CANCELLED})
PAUSED_STATES = frozenset({JobState.PAUSED, JobState.PAUSED_SAFETY, JobState.PAUSED_FAULT})
ACTIVE_STATES = frozenset({JobState.RUNNING, *PAUSED_STATES})

_LEAVING_PAUSE = frozenset({JobState.RUNNING, JobState.CANCELLED, JobState.FAILED, JobState.QUEUED, *PAUSED_STATES})
TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.QUEUED: frozenset({JobState.RUNNING, JobState.CANCELLED}),
    JobState.RUNNING: frozenset({*PAUSED_STATES, *FINAL_STATES, JobState.QUEUED}),
    **{paused: _LEAVING_PAUSE for paused in PAUSED_STATES},
    **{final: frozenset() for final in FINAL_STATES},
}


class TransitionError(ValueError):
    """A state change the job's state machine does not have."""


def check_transition(current: str, new: str) -> JobState:
    """``new`` as a :class:`JobState` when a job in ``current`` may change to it; else :class:`TransitionError`."""
    try:
        state = JobState(new)
    except ValueError:
        raise TransitionError(f"unknown job state {new!r}") from None
    before = JobState(current)
    if state != before and state not in TRANSITIONS[before]:
        raise TransitionError(f"a {before} job cannot become {state}")
    return state

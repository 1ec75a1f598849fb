"""Storage faults told by what they are (a full device, an OSError without errno, a library's text), not by errno;
an event the journal has not taken goes out without an id. The full-disk jobs themselves are
``tests/e2e/test_daemon_disk_full.py``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tandemscan.daemon.jobs.faults import classify_fault
from tandemscan.daemon.store.events import sse_text
from tandemscan.daemon.store.job_store import Event
from tandemscan.drivers.errors import NotConnected


def test_an_event_the_journal_has_not_taken_is_sent_without_an_id():
    journaled, not_yet = Event(7, None, "safety", {"latched": True}, 1.0), Event(None, None, "safety", {}, 1.0)
    assert sse_text(journaled).startswith("id: 7\nevent: safety\n")
    assert sse_text(not_yet).startswith("event: safety\ndata: ")


def _raised(write) -> BaseException:
    try:
        write()
    except Exception as e:  # noqa: BLE001 - what the library raises is the point
        return e
    raise AssertionError("the write to /dev/full did not fail")


@pytest.mark.skipif(not Path("/dev/full").is_char_device(), reason="needs /dev/full")
def test_storage_faults_are_recognised_by_what_they_are_not_by_errno():
    """numpy's ``tofile`` raises on a full device without an errno; so does pye57 (its text, not run here: it
    removes the file it could not write): both are storage faults, a device's error stays the device's."""
    def numpy_tofile():
        with open("/dev/full", "wb") as f:
            np.zeros(1 << 17).tofile(f)

    exc = _raised(numpy_tofile)
    assert isinstance(exc, OSError) and exc.errno is None
    fault = classify_fault(exc)
    assert fault is not None and fault.reason.startswith("storage fault (disk full)"), exc
    assert classify_fault(RuntimeError("write() failed (ErrorWriteFailed)")).kind == "storage"
    link = NotConnected("tracker", "link lost")
    link.__cause__ = OSError(5, "Input/output error")
    assert classify_fault(link).kind == "device"
    assert classify_fault(ValueError("bad plan")) is None

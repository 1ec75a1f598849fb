"""The pair worker is handed each scan's thinned copy through shared memory (daemon/stitcher.py): no block is left
in ``/dev/shm`` once its task ran, and none of the tasks a closed worker never ran (docs/end-of-job.md)."""

from __future__ import annotations

import time

import numpy as np
from tandemscan.daemon.stitcher import PairWorker
from tandemscan.drivers.shared_array import SHM_DIR, SharedBlock, hand_over
from tandemscan.pipeline.registration.correction import CorrectionSettings

PLACEMENT = {"T_W_C": np.eye(4), "T_C_T": np.eye(4), "tracker_covariance": np.eye(6) * 1e-4}


def _copies(n: int) -> list[SharedBlock]:
    """``n`` scan copies of 100 k points (S, mm) handed over as a map's process hands them."""
    rng = np.random.default_rng(5)
    blocks = [hand_over(rng.uniform(0.0, 200.0, (100_000, 3))) for _ in range(n)]
    assert all(isinstance(b, SharedBlock) and (SHM_DIR / b.name).exists() for b in blocks)
    return blocks


def _gone(blocks: list[SharedBlock], timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while any((SHM_DIR / b.name).exists() for b in blocks) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not any((SHM_DIR / b.name).exists() for b in blocks)


async def test_the_pair_workers_copies_leave_no_shared_memory(sim_config):
    settings = CorrectionSettings.from_section(sim_config.correction)
    worker = PairWorker(settings, 1.0, 0)
    try:
        ran = _copies(1)
        worker.submit(ran[0], np.eye(4), PLACEMENT, np.eye(4), 0, [])
        online, _ = await worker.outcomes()
        assert online is not None and _gone(ran)  # taken, copied, removed
        never_ran = _copies(4)
        for block in never_ran:
            worker.submit(block, np.eye(4), PLACEMENT, np.eye(4), 0, [])
    finally:
        worker.close()  # the job ended: its queued scans are dropped
    assert _gone(never_ran)

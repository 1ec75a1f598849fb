"""The pair worker is handed each scan's thinned copy through shared memory (daemon/jobs/stitcher.py): no block is left
in ``/dev/shm`` once its task ran, and none of the tasks a closed worker never ran (docs/end-of-job.md)."""

from __future__ import annotations

import asyncio
import os
import time

import numpy as np
import pytest
from tandemscan.daemon.jobs.stitcher import PairWorker, ProcessWorldMap
from tandemscan.drivers.shared_array import PREFIX, SHM_DIR, SharedBlock, hand_over
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


@pytest.mark.slow
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


async def _two_fine_scans(worldmap, correction, folder) -> None:
    """Two overlapping fine scans (S, mm; 2 points a 1 mm voxel) written to ``folder`` and merged in ``worldmap``, their
    pairs queued with the job's ``correction``."""
    rng = np.random.default_rng(8)
    for k in range(2):
        xy = rng.uniform(0.0, 250.0, (130_000, 2))
        arrays = {"points_S_mm": np.c_[xy, 500.0 + 0.01 * np.sin(xy[:, 0] / 20.0)], **PLACEMENT}
        T_W_S = np.eye(4)
        T_W_S[0, 3] = 40.0 * k
        await worldmap.add_scan(folder / f"scan-{k:04d}.npz", T_W_S, arrays,
                                pairs={"correction": correction, "station": 0, "transfers": [], "T_T_S": np.eye(4)})


@pytest.mark.slow
async def test_the_maps_process_hands_a_fine_scans_copy_to_the_pair_worker(sim_config, tmp_path):
    """Two overlapping fine scans (2 points a 1 mm voxel: their copies, over 1 MB, go through shared memory) written
    and merged in a :class:`ProcessWorldMap`: the pair worker prepares both for the joint refinement from the copies
    it was handed, and no block is left."""
    before = set(SHM_DIR.glob(f"{PREFIX}{os.getpid()}-*"))
    worldmap = ProcessWorldMap(1.0)
    try:
        await _two_fine_scans(worldmap, sim_config.correction, tmp_path)
        online, _ = await worldmap.pair_outcomes()
    finally:
        worldmap.close()
    assert len(online.joint_scans) == 2
    assert set(SHM_DIR.glob(f"{PREFIX}{os.getpid()}-*")) <= before


@pytest.mark.slow
async def test_the_joint_preparation_is_handed_over_from_its_own_worker_while_check_pairs_register(sim_config):
    """With the joint refinement the scans are prepared for it in a worker of their own beside the check pairs': once
    the job has measured, :meth:`PairWorker.joint_work` hands over every scan prepared and the pairs' nearest
    neighbours found at the tracker poses, with the check pairs still registering named, and stops that worker; the
    pairs come later (:meth:`PairWorker.outcomes`), every block lent to the two workers removed."""
    rng = np.random.default_rng(9)
    settings = CorrectionSettings.from_section(sim_config.correction)
    assert settings.joint and settings.registered_partners > 0
    worker = PairWorker(settings, 1.0, 0)
    blocks = []
    try:
        for k in range(3):
            xy = rng.uniform(0.0, 250.0, (130_000, 2))
            T_W_S = np.eye(4)
            T_W_S[0, 3] = 40.0 * k
            blocks.append(hand_over(np.c_[xy - [40.0 * k, 0.0], 500.0 + 5.0 * np.sin(xy[:, 0] / 20.0)]))
            worker.submit(blocks[-1], T_W_S, PLACEMENT, np.eye(4), 0, [])
        # the job measures more slowly than the worker prepares: every scan is prepared before the last is measured
        await asyncio.gather(*map(asyncio.wrap_future, worker._joint_pending))
        early = await worker.joint_work()
        assert len(early.joint_scans) == 3 and len(early.associations) >= 2
        assert len(early.pairs) + len(early.pending) >= 2  # every check pair registered or named
        later, cpu_s = await worker.outcomes()
        assert later.joint_scans == {} and later.pairs.keys() >= early.pending and cpu_s > 0
    finally:
        worker.close()
    assert _gone(blocks)


@pytest.mark.slow
async def test_on_the_scan_store_path_no_scan_is_prepared_for_the_joint_refinement_while_measuring(sim_config,
                                                                                                  tmp_path):
    """A lean map (``ComputeConfig.reads_scan_store``: the end of the job reads the scans from the store, its units
    prepare them for the joint refinement there) with the joint refinement on: the pair worker registers the check
    pairs, but no scan is prepared and no nearest neighbour found while measuring (they would go unused, the
    whole part's in one process), so the hand-over holds none."""
    from tandemscan.daemon.jobs.stitcher import LocalWorldMap

    assert sim_config.correction.joint
    worldmap = LocalWorldMap(1.0, lean=True)
    try:
        await _two_fine_scans(worldmap, sim_config.correction, tmp_path)
        # whatever was queued for a preparation has run (none, where none is made)
        await asyncio.gather(*map(asyncio.wrap_future, worldmap._pairs._joint_pending))
        handed = await worldmap._joint_work()
        later, _ = await worldmap.pair_outcomes()
    finally:
        worldmap.close()
    assert handed.joint_scans == {} and handed.associations == {}
    assert len(handed.pairs) + len(handed.pending) == 1 and later.pairs.keys() >= handed.pending  # the check pair

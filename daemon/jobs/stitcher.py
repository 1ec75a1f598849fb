"""The job's world map and its end-of-job work, in a worker process for the daemon or in this one.

Both maps have one interface: ``await add_scan(file, T_W_S, arrays)`` persists a raw scan (when ``arrays`` is
given: written and fsynced first) and merges it into the voxel grid (Eq. 1, points in S, map in W, mm), keeping
its copy thinned at the map's voxel for the end of the job (:func:`merge_scan`: a scan written here is merged and
thinned from its arrays, one replayed after a restart read once, so neither reads its file again; where the end
reads the scans from the store, ``ComputeConfig.reads_scan_store``, nothing is merged and only each scan's stitch-view
points and reach are kept: the map's process holds no whole-part map there);
``await run(fn, job, *args)`` runs ``fn(job, *args)`` where the map lives, with ``job.worldmap`` set to it
(correction, report, exports) and handed over: ``fn`` owns the map while it runs (no other reference to it is
kept, so the end of a job can free it), and the map or cloud it leaves there is adopted.

:class:`ProcessWorldMap` (the daemon) keeps its grid in a one-process pool, so no stitch, scan write or export
holds the daemon's GIL: a full-resolution scan (3.2 M points) merged or written in a thread stalled the event
loop for over half a second. Scan arrays go to it as shared memory (:mod:`tandemscan.drivers.shared_array`),
never pickled by value. :class:`LocalWorldMap` (``tandemscan measure``) does the same work in threads.

Both register each scan's overlapping pairs as it arrives when given the job's ``[correction]`` settings
(:class:`PairWorker`: a second process at the map's priority, so both cores work and the event loop stays
free, and with the joint refinement a third beside it that prepares the scans for it;
``pipeline.registration.online_pairs``), handing them the scan's thinned copy (through shared memory from the
map's process, :mod:`tandemscan.drivers.shared_array`), not its file; :meth:`pair_outcomes` hands their outcomes to
the correction after the last scan.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import logging
import multiprocessing
import time
import uuid
from collections.abc import Awaitable, Callable
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tandemscan.config.models import CorrectionConfig
from tandemscan.daemon.jobs.snapshot import JobSnapshot
from tandemscan.drivers.shared_array import SharedBlock, hand_over, share
from tandemscan.drivers.worker import init_worker, stop_pool, yield_cores
from tandemscan.pipeline.io.raw_scan import (
    keep_thinned_copy,
    read_raw_scan,
    read_thinned_scan,
    thin_scan,
    write_raw_scan,
)
from tandemscan.pipeline.stitching.tiles import ScanReach
from tandemscan.pipeline.stitching.worldmap import VoxelMap

if TYPE_CHECKING:
    from tandemscan.pipeline.registration.correction import CorrectionSettings, OnlineWork

log = logging.getLogger(__name__)
_MAP: VoxelMap | None = None  # the worker's map
_COPIES: dict[str, Any] = {}  # what the worker keeps of the scans as they are merged (merge_scan), by file
_LEAN = False  # the worker merges no scan, keeps only each scan's stitch-view points and reach (merge_scan)
_PAIRS: Any = None  # the pair worker's OnlinePairs
_JOINT: Any = None  # the joint worker's OnlineJoint (PairWorker)
#: niceness the pair worker adds once the job has measured (:func:`_pairs_so_far`): its check pairs run on the
#: cores the end of the job leaves free, and on all once only they are left
CHECKS_NICENESS = 10
_MEASURED: Any = None  # the joint worker's event set once the job has measured its last scan (PairWorker)
_LOADED: dict[str, Any] = {}  # where the map lives: finishing jobs' scans read ahead (finish.LoadedScans)
_OUTPUTS: dict[str, Any] = {}  # where the map lives: finishing jobs' outputs until their report (finish.JobOutputs)


def _init(voxel_mm: float, niceness: int, lean: bool) -> None:
    global _MAP, _LEAN
    init_worker(niceness)
    _MAP, _LEAN = VoxelMap(voxel_mm), lean


def merge_scan(worldmap: VoxelMap, copies: dict[str, Any], file: str, T_W_S: np.ndarray,
               arrays: dict[str, np.ndarray] | None, lean: bool = False) -> np.ndarray:
    """Merge the scan of ``file`` into ``worldmap`` at ``T_W_S`` (W, mm) from its ``arrays`` where given (written
    already; the map rotates them in float32, as the file stores them), else from the file, read once (a job
    rebuilt after a restart), and keep in ``copies`` its copy thinned at the map's voxel
    (``raw_scan.thin_scan``, the copy ``raw_scan.read_thinned_scan`` would read: ``finish.load_scans`` takes it
    from there). ``lean`` (``ComputeConfig.reads_scan_store``: the end of the job reads the scans from the store on the
    backend's workers and merges its cloud there): the scan is not merged here and only what the end takes of it
    is kept, small and bounded a scan: its stitch-view points (``outputs.stitch_view_points``, at most 40 k, float32,
    under 0.5 MB) and its ``tiles.ScanReach`` at ``T_W_S`` (``finish.load_scans``), and the thinned copy is written
    beside the job's scans (``raw_scan.keep_thinned_copy``: the workers read it there, not the raw scan); one replayed
    from its file is read as ``raw_scan.read_thinned_scan`` reads it (the copy kept there where an earlier attempt
    left one, else the points alone: its normals are not needed). Returns the thinned copy (for the pair worker)."""
    if lean:
        from tandemscan.daemon.jobs.outputs import stitch_view_points  # the exports' stack, where the map lives

        copy = (read_thinned_scan(file, worldmap.voxel_mm) if arrays is None
                else thin_scan(arrays["points_S_mm"], worldmap.voxel_mm))
        copies[file] = (stitch_view_points(copy), ScanReach.of(T_W_S, copy))
        keep_thinned_copy(file, copy, worldmap.voxel_mm)
        return copy
    if arrays is None:
        points, normals = read_raw_scan(file, np.float32)
    else:
        points, normals = arrays["points_S_mm"], arrays.get("normals_S")
    copy = thin_scan(points, worldmap.voxel_mm)
    worldmap.add_scan(T_W_S, points, normals)
    copies[file] = copy
    return copy


def _add(path: str, T_W_S: np.ndarray, arrays: dict[str, np.ndarray] | None, lend: bool
         ) -> tuple[int, SharedBlock | np.ndarray | None]:
    """In the map's process: write ``arrays`` (if given) durably to ``path`` and merge the scan (:func:`merge_scan`);
    returns the map's size and, where ``lend``, the scan's thinned copy handed over for the pair worker."""
    if arrays is not None:
        write_raw_scan(Path(path), **arrays)
    copy = merge_scan(_MAP, _COPIES, path, T_W_S, arrays, _LEAN)
    return len(_MAP), hand_over(copy) if lend else None


def _run(fn: Callable[..., Any], job: JobSnapshot, args: tuple) -> tuple[Any, int]:
    global _MAP
    job.worldmap, _MAP = _MAP, None  # fn owns the map while it runs (it may replace it and free the old one)
    job.scan_copies = _COPIES
    try:
        out = fn(job, *args)
    finally:
        _MAP = job.worldmap
    return out, len(_MAP)


def _lent(points: SharedBlock | np.ndarray) -> np.ndarray:
    """A scan's copy handed to a worker (:meth:`PairWorker.submit`): the block mapped (the submitter removes it once
    every worker it went to is done with it), or the array itself."""
    return points.borrow() if isinstance(points, SharedBlock) else points


def _pairs_add(points: SharedBlock | np.ndarray, T_W_S: np.ndarray, placement: dict[str, np.ndarray],
               T_T_S: np.ndarray, station: int, transfers: list[dict], cfg: CorrectionSettings,
               voxel_mm: float) -> int:
    """In the pair worker: register the pairs of a scan (``points``: its thinned copy, S, mm, lent by the map's
    process; ``placement``: its raw file's ``T_W_C``, ``T_C_T`` and ``tracker_covariance``) with the earlier ones.

    Eight parameters: a task sent to the worker process takes plain picklable values, each one the pair
    registration of this scan needs."""
    global _PAIRS
    points = np.array(_lent(points))  # a copy of its own: the block is removed once both workers are done with it
    from tandemscan.daemon.jobs.pose_correction import transfer_priors
    from tandemscan.pipeline.geometry.uncertainty import scan_pose_covariance
    from tandemscan.pipeline.registration.online_pairs import OnlinePairs

    if _PAIRS is None:  # the joint refinement's preparation runs in the joint worker (_joint_add)
        _PAIRS = OnlinePairs(cfg, voxel_mm, joint=False)
    cov = scan_pose_covariance(placement["T_W_C"], placement["T_C_T"], T_T_S, placement["tracker_covariance"])
    return _PAIRS.add(points, T_W_S, cov, station, transfer_priors(transfers))


def _joint_add(points: SharedBlock | np.ndarray, T_W_S: np.ndarray, station: int, cfg: CorrectionSettings) -> None:
    """In the joint worker: prepare a scan for the joint refinement and find its pairs' nearest neighbours
    (``online_pairs.OnlineJoint.add``; ``points``: its thinned copy, S, mm, lent by the map's process), unless the
    job has measured its last scan: the end of the job, which waits for this, prepares the rest itself."""
    global _JOINT
    from tandemscan.pipeline.registration.online_pairs import OnlineJoint

    if _JOINT is None:
        _JOINT = OnlineJoint(cfg)
    if _MEASURED.is_set():
        _JOINT.stop_preparing()
    _JOINT.add(_lent(points), T_W_S, station)


def _init_joint(niceness: int, measured: Any) -> None:
    global _MEASURED
    init_worker(niceness)
    _MEASURED = measured


def _pairs_outcomes() -> tuple[OnlineWork | None, float]:
    return (None, 0.0) if _PAIRS is None else (_PAIRS.work(), _PAIRS.cpu_s)


def _pairs_so_far() -> OnlineWork | None:
    """In the pair worker once the job has measured: the pairs registered so far and the keys of those still
    registering (``OnlinePairs.joint_work``); those then yield the cores to the end of the job
    (:data:`CHECKS_NICENESS`), which needs them only for its report."""
    if _PAIRS is None:
        return None
    work = _PAIRS.joint_work()
    yield_cores(CHECKS_NICENESS)
    return work


def _joint_outcomes() -> tuple[dict, dict, float]:
    """In the joint worker: the prepared scans and their pairs' nearest neighbours (``OnlineJoint.hand_over``) and
    this process's CPU seconds."""
    scans, associations = ({}, {}) if _JOINT is None else _JOINT.hand_over()
    return scans, associations, time.process_time()


def _discard_after(block: SharedBlock, futures: list[Future]) -> None:
    """Remove ``block`` once every one of ``futures`` (the tasks it was lent to) is done, failed or cancelled."""
    if not futures:
        block.discard()
    else:
        futures[0].add_done_callback(lambda _: _discard_after(block, futures[1:]))


async def _settled(futures: list[Future], failed: str) -> None:
    """Wait for ``futures``; a task that failed is logged (``failed`` % its error): the end of the job computes
    what it missed."""
    for future in futures:
        try:
            await asyncio.wrap_future(future)
        except Exception as e:  # noqa: BLE001 - the end of the job computes what is missing
            log.warning(failed, e)


def _read_ahead(job: JobSnapshot, key: str) -> float:
    """Where the map lives: read the scans the end of ``job`` starts from (``finish.load_scans``) and keep them
    under ``key`` for :func:`_finish_outputs`; returns the seconds it took."""
    from tandemscan.daemon.jobs.finish import load_scans

    t = time.perf_counter()
    _LOADED[key] = load_scans(job)
    return time.perf_counter() - t


def _drop_read_ahead(key: str, reading: asyncio.Future) -> None:
    """Drop what the read ahead for a job kept when the job ended before its end ran (the read's own error, if
    any, is only logged: the job has failed of its own)."""
    _LOADED.pop(key, None)
    if not reading.cancelled() and reading.exception() is not None:
        log.debug("read ahead for an ended job failed: %s", reading.exception())


def _finish_outputs(job: JobSnapshot, key: str, started: float, measured_at: float, online: OnlineWork | None,
                    stages: dict) -> Any:
    """:func:`tandemscan.daemon.jobs.finish.finish_outputs`, imported where it runs (the registration stack, E57,
    Open3D I/O, matplotlib), from the scans :func:`_read_ahead` kept under ``key`` (read again where it failed);
    what it returns is kept there under ``key`` for :func:`_report`. Returns the files the outputs leave until
    their report (``finish.left_on_disk``: small, it pickles), for the job's process to remove where the job ends
    before its report (:func:`_drop_outputs`)."""
    from tandemscan.daemon.jobs.finish import finish_outputs, left_on_disk

    _OUTPUTS[key] = outputs = finish_outputs(job, started, measured_at, online, stages, _LOADED.pop(key, None))
    return left_on_disk(outputs)


def _report(job: JobSnapshot, key: str, measured_at: float, later: OnlineWork | None, stages: dict) -> Any:
    """:func:`tandemscan.daemon.jobs.finish.report_job` of the outputs :func:`_finish_outputs` kept under ``key``
    (``job`` is not used: the outputs hold the job at its final poses)."""
    from tandemscan.daemon.jobs.finish import report_job

    return report_job(_OUTPUTS.pop(key), measured_at, later, stages)


def _drop_outputs(key: str, running: asyncio.Future) -> None:
    """Drop the outputs of a job that ended before its report, once their run (``running``, of
    :func:`_finish_outputs`) ended: the files they left (its result, a tiled cloud's tiles) removed, and what is
    kept under ``key`` where this process holds it (the map in this process, ``LocalWorldMap``; a daemon job's map
    process ends with the job), its compute backend closed. A done-callback on the event loop: the removal and the
    close (file I/O, a Dask client's shutdown) run on the loop's executor (:func:`_let_go`), whose threads the loop's
    shutdown waits for (``asyncio.run``); where it no longer takes work, here. Its own error, if any, is only logged:
    the job has failed of its own."""
    from tandemscan.daemon.jobs.finish import drop_outputs

    outputs = _OUTPUTS.pop(key, None)
    if outputs is not None:
        drop = functools.partial(drop_outputs, outputs)  # its tiles too: what the run returned names the same files
    elif running.cancelled():
        return
    elif running.exception() is not None:
        log.debug("outputs of an ended job failed: %s", running.exception())
        return
    elif running.result() is not None:
        drop = running.result().remove
    else:
        return
    try:
        running.get_loop().run_in_executor(None, _let_go, drop)
    except RuntimeError:  # the loop's executor is shut down already: not lost, done here
        _let_go(drop)


def _let_go(drop: Callable[[], None]) -> None:
    """``drop()`` (:func:`_drop_outputs`), its error logged: nobody awaits it."""
    try:
        drop()
    except Exception as e:  # noqa: BLE001 - the job has failed of its own; its files stay
        log.warning("outputs of an ended job not dropped: %s", e)


async def _first(pair: Awaitable[tuple[Any, Any]]) -> Any:
    """The first of what ``pair`` gives."""
    return (await pair)[0]


class PairWorker:
    """A process registering each scan's pairs as it arrives (``online_pairs.OnlinePairs``) and, with the joint
    refinement, a second one beside it preparing each scan for that (``online_pairs.OnlineJoint``: the end of the
    job waits for it, not for the check pairs, and the two no longer share one process's interpreter); tasks queue in
    scan order and nobody waits for them until :meth:`joint_work` or :meth:`outcomes`."""

    def __init__(self, cfg: CorrectionSettings, voxel_mm: float, niceness: int, prepares_joint: bool = True):
        """``prepares_joint``: with the joint refinement (``cfg.joint``), whether its worker prepares the scans; not
        where the end of the job reads them from the scan store (``ComputeConfig.reads_scan_store``): its units
        prepare them there, so that no process holds the part's prepared scans (:meth:`_Pairs._pair_worker`)."""
        self.cfg, self.voxel_mm = cfg, float(voxel_mm)
        context = multiprocessing.get_context("spawn")
        self._measured = context.Event()  # set by :meth:`joint_work`: the scans still queued are not prepared
        self._pool = ProcessPoolExecutor(1, mp_context=context, initializer=init_worker, initargs=(niceness,))
        self._joint = (ProcessPoolExecutor(1, mp_context=context, initializer=_init_joint,
                                           initargs=(niceness, self._measured)) if cfg.joint and prepares_joint
                       else None)
        self._pending: list[Any] = []  # the pairs' tasks
        self._joint_pending: list[Any] = []  # the joint preparation's tasks
        self._joint_cpu_s = 0.0  # the joint worker's CPU seconds, once it handed its work over

    def submit(self, points: SharedBlock | np.ndarray, T_W_S: np.ndarray, placement: dict[str, np.ndarray],
               T_T_S: np.ndarray, station: int, transfers: list[dict]) -> None:
        """Queue the pairs of a scan and, with the joint refinement, its preparation for that: its copy thinned at the
        map's voxel (S, mm; a block of shared memory lent to the workers, removed once they are done with it, or the
        array), placed at ``T_W_S`` (mm), with its raw file's ``T_W_C``, ``T_C_T`` and ``tracker_covariance``
        (``placement``) and the mount ``T_T_S``."""
        T_W_S = np.asarray(T_W_S, float)
        futures = [self._pool.submit(_pairs_add, points, T_W_S, placement, np.asarray(T_T_S, float), int(station),
                                     list(transfers), self.cfg, self.voxel_mm)]
        self._pending.append(futures[0])
        if self._joint is not None:
            futures.append(self._joint.submit(_joint_add, points, T_W_S, int(station), self.cfg))
            self._joint_pending.append(futures[-1])
        if isinstance(points, SharedBlock):  # once its tasks are done, failed or cancelled, no block is left behind
            _discard_after(points, futures)

    async def joint_work(self) -> OnlineWork | None:
        """Once the job has measured its last scan: what the workers computed for the joint refinement so far
        (``online_pairs.OnlineJoint.hand_over``: prepared scans and their nearest neighbours) with the pairs registered
        so far and the keys of those still registering (``OnlinePairs.joint_work``). The scans still queued are not
        prepared any more (``OnlineJoint.stop_preparing``: the end of the job prepares them itself on every core
        instead of waiting for this one process), only their pairs queued; a scan whose task failed is logged and left
        to the end of the job. The joint worker stops once it has handed its work over; :meth:`outcomes` gives the
        pairs once they are done."""
        self._measured.set()
        pairs = asyncio.wrap_future(self._pool.submit(_pairs_so_far))  # behind the scans queued there
        return await self._with_joint_work(pairs)

    async def _with_joint_work(self, pairs: Awaitable[OnlineWork | None]) -> OnlineWork | None:
        """The pair worker's work (``pairs``) with, where the joint worker runs, its prepared scans and associations
        (:meth:`_joint_handed_over`, beside ``pairs``)."""
        if self._joint is None:
            return await pairs
        (scans, associations), work = await asyncio.gather(self._joint_handed_over(), pairs)
        return None if work is None else dataclasses.replace(work, joint_scans=scans, associations=associations)

    async def _joint_handed_over(self) -> tuple[dict, dict]:
        """The joint worker's prepared scans and associations, once its queued scans are done; it stops then (its
        memory, every prepared scan, goes with it)."""
        await _settled(self._joint_pending, "a scan not prepared while measuring: %s")
        self._joint_pending = []
        try:
            scans, associations, self._joint_cpu_s = await asyncio.wrap_future(self._joint.submit(_joint_outcomes))
        finally:
            stop_pool(self._joint)
            self._joint = None
        return scans, associations

    async def outcomes(self) -> tuple[OnlineWork | None, float]:
        """Wait for the queued scans, then what the workers computed (``registration.correction.OnlineWork``: pair
        outcomes and, where :meth:`joint_work` did not take them, the prepared joint scans; a failed task only leaves
        its work to the end of the job) and their CPU seconds."""
        await _settled(self._pending, "pairs of a scan not registered while measuring: %s")
        self._pending = []
        outcomes = asyncio.wrap_future(self._pool.submit(_pairs_outcomes))
        work = await self._with_joint_work(_first(outcomes))
        return work, outcomes.result()[1] + self._joint_cpu_s

    def close(self) -> None:
        stop_pool(self._pool)
        if self._joint is not None:
            stop_pool(self._joint)
            self._joint = None


class _Pairs:
    """The pair registration and end of the job both maps share: a :class:`PairWorker` started at the first scan
    that asks for it."""

    voxel_mm: float
    lean: bool = False  # the end of the job reads the scans from the scan store (merge_scan)
    _pair_niceness: int = 0
    _pairs: PairWorker | None = None

    def _pair_worker(self, pairs: dict | None) -> PairWorker | None:
        """The pair worker for a scan with these ``pairs`` settings (started at the first that asks for one); None
        where its pairs are not registered while measuring. Where the map is :attr:`lean` it prepares no scan for
        the joint refinement: the end of the job reads the scans from the store and its units prepare them there
        and find their pairs' nearest neighbours (``correction.summarise_stored_scan``): a scan prepared while
        measuring would go unused there, and the neighbours, the whole part's, would gather with the prepared scans
        in one process and travel through the scheduler; one core is left to the measurement."""
        if not pairs:
            return None
        cfg: CorrectionConfig = pairs["correction"]
        if self._pairs is None:
            from tandemscan.pipeline.registration.correction import CorrectionSettings
            from tandemscan.pipeline.registration.pairs import NETWORK_METHODS

            if not cfg.enabled or cfg.method in NETWORK_METHODS:
                return None
            self._pairs = PairWorker(CorrectionSettings.from_section(cfg), self.voxel_mm, self._pair_niceness,
                                     prepares_joint=not self.lean)
        return self._pairs

    @staticmethod
    def _queue_pairs(worker: PairWorker, copy: SharedBlock | np.ndarray, T_W_S: np.ndarray,
                     arrays: dict[str, np.ndarray], pairs: dict) -> None:
        placement = {k: np.asarray(arrays[k]) for k in ("T_W_C", "T_C_T", "tracker_covariance")}
        worker.submit(copy, T_W_S, placement, pairs["T_T_S"], pairs["station"], pairs["transfers"])

    async def pair_outcomes(self) -> tuple[OnlineWork | None, float]:
        """What the pair worker computed while the job measured (``registration.correction.OnlineWork``; None without a
        pair worker) and the CPU seconds spent on it; the worker stops after handing it over."""
        if self._pairs is None:
            return None, 0.0
        try:
            return await self._pairs.outcomes()
        finally:
            self._pairs.close()
            self._pairs = None

    async def finish(self, job: JobSnapshot, started: float, measured_at: float) -> Any:
        """The end of the job (``finish.finish_outputs`` then ``finish.report_job``: a ``finish.FinishedJob``) where
        the map lives; ``started`` and ``measured_at`` as ``time.monotonic()``. It starts once the pair worker has
        prepared the last scans for the joint refinement (``joint_backlog_s``) or, without the joint refinement,
        whose pose graph takes every pair, once their pairs are registered (``pair_backlog_s``). The scans are read
        meanwhile, so the wait and the reading share the two cores: ``read_s`` (the read's own seconds) runs beside
        it, and where the read outlasts that wait its rest belongs to no stage. With the joint refinement the check
        pairs still registering (its poses take none of them) register beside the correction, merge, exports and
        inspection (``pair_backlog_s``: until they are handed over) and only the report waits for them."""
        key = uuid.uuid4().hex  # this finish's read and outputs, never another's
        reading = asyncio.ensure_future(self.run(_read_ahead, job, key))
        joint = job.config.correction.joint
        try:
            if joint:
                online = await self._joint_work()
            else:
                online, pair_cpu_s = await self.pair_outcomes()
        except BaseException:
            # the job ends here: the read runs on where the map lives and what it kept is dropped once it ends (a
            # daemon job's map process ends with the job anyway); no second run of the map starts meanwhile
            reading.add_done_callback(functools.partial(_drop_read_ahead, key))
            raise
        waited = round(time.monotonic() - measured_at, 3)
        stages = ({"joint_backlog_s": waited} if joint
                  else {"pair_backlog_s": waited, "pairs_cpu_s_while_measuring": round(pair_cpu_s, 3)})
        checks = asyncio.ensure_future(self._checks(measured_at)) if joint else None
        outputs = None
        try:
            try:
                stages["read_s"] = round(await reading, 3)
            except Exception as e:  # noqa: BLE001 - the end of the job reads them itself
                log.warning("scans not read ahead of the end of the job: %s", e)
            outputs = asyncio.ensure_future(self.run(_finish_outputs, job, key, started, measured_at, online, stages))
            await asyncio.shield(outputs)
            later, later_stages = (None, {}) if checks is None else await checks
        except BaseException:
            if checks is not None:
                checks.cancel()  # the pair worker stops (pair_outcomes)
            if outputs is not None:  # once the map is free, what the outputs kept is dropped
                outputs.add_done_callback(functools.partial(_drop_outputs, key))
            raise
        return await self.run(_report, job, key, measured_at, later, later_stages)

    async def _joint_work(self) -> OnlineWork | None:
        return None if self._pairs is None else await self._pairs.joint_work()

    async def _checks(self, measured_at: float) -> tuple[OnlineWork | None, dict[str, float]]:
        """The check pairs the pair worker still registered at the end of the job, once done (None where they
        could not be handed over: the report registers those it misses), and the stages' seconds of it."""
        try:
            later, cpu_s = await self.pair_outcomes()
        except Exception as e:  # noqa: BLE001 - the report registers the pairs it misses
            log.warning("check pairs not handed over by the pair worker: %s", e)
            return None, {}
        return later, {"pair_backlog_s": round(time.monotonic() - measured_at, 3),
                       "pairs_cpu_s_while_measuring": round(cpu_s, 3)}

    def _close_pairs(self) -> None:
        if self._pairs is not None:
            self._pairs.close()
            self._pairs = None


def _share_big(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: share(v) for k, v in arrays.items()}


class ProcessWorldMap(_Pairs):
    """The job's :class:`VoxelMap` in its own process; call :meth:`close` when the job is done. ``lean``:
    no scan merged, each scan's stitch-view points and reach kept, not its thinned copy (:func:`merge_scan`)."""

    def __init__(self, voxel_mm: float, niceness: int = 0, lean: bool = False):
        self.voxel_mm, self.lean = float(voxel_mm), lean
        self._pair_niceness = niceness
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init, initargs=(self.voxel_mm, niceness, lean))
        self._len = 0

    async def add_scan(self, file: Path, T_W_S: np.ndarray, arrays: dict[str, np.ndarray] | None = None,
                       pairs: dict | None = None) -> None:
        """Write ``arrays`` (if given) durably to ``file``, then merge the scan in ``file`` placed at ``T_W_S``.
        The caller keeps ``arrays`` until this returns (the worker maps their shared memory). ``pairs``
        (``correction``: the job's ``[correction]``, ``station``, ``transfers``: the runner's transfer entries
        so far, ``T_T_S``: the mount, mm) queues the scan's pair registration."""
        worker = None if arrays is None else self._pair_worker(pairs)
        if arrays is not None:
            arrays = await asyncio.to_thread(_share_big, arrays)
        self._len, copy = await asyncio.wrap_future(
            self._pool.submit(_add, str(file), np.asarray(T_W_S, float), arrays, worker is not None))
        if worker is not None:
            self._queue_pairs(worker, copy, T_W_S, arrays, pairs)

    async def run(self, fn: Callable[..., Any], job: JobSnapshot, *args: Any) -> Any:
        """``fn(job, *args)`` in the worker with ``job.worldmap`` = its map; ``fn`` and its result pickle."""
        out, self._len = await asyncio.wrap_future(self._pool.submit(_run, fn, job, args))
        return out

    def __len__(self) -> int:
        return self._len

    def close(self) -> None:
        """Stop the worker; work still under way (a job interrupted by shutdown) is abandoned, not awaited."""
        stop_pool(self._pool)
        self._close_pairs()


class LocalWorldMap(_Pairs):
    """The job's :class:`VoxelMap` in this process, its work in threads (``tandemscan measure``); its pair
    registration in a process. ``lean`` as :class:`ProcessWorldMap`."""

    def __init__(self, voxel_mm: float, lean: bool = False):
        self.voxel_mm = float(voxel_mm)
        self.map = VoxelMap(self.voxel_mm)
        self.lean = lean
        self.copies: dict[str, Any] = {}  # what is kept of the scans as they are merged (merge_scan)

    async def add_scan(self, file: Path, T_W_S: np.ndarray, arrays: dict[str, np.ndarray] | None = None,
                       pairs: dict | None = None) -> None:
        """As :meth:`ProcessWorldMap.add_scan`."""
        if arrays is not None:
            await asyncio.to_thread(write_raw_scan, Path(file), **arrays)
        copy = await asyncio.to_thread(merge_scan, self.map, self.copies, str(file), T_W_S, arrays,
                                       self.lean)
        worker = None if arrays is None else self._pair_worker(pairs)
        if worker is not None:
            self._queue_pairs(worker, copy, T_W_S, arrays, pairs)

    async def run(self, fn: Callable[..., Any], job: JobSnapshot, *args: Any) -> Any:
        """``fn(job, *args)`` in a thread with ``job.worldmap`` = this map, which ``fn`` owns while it runs."""
        job.worldmap, self.map = self.map, None
        job.scan_copies = self.copies
        try:
            return await asyncio.to_thread(fn, job, *args)
        finally:
            self.map = job.worldmap

    def __len__(self) -> int:
        return len(self.map)

    def close(self) -> None:
        self._close_pairs()

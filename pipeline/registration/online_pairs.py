"""Pair registration while the job measures (docs/pairs-while-measuring.md).

As each scan is stitched (its points in the scanner frame S, its tracker pose ``T_W_S`` in the world W, mm),
:class:`OnlinePairs` finds its possible partners among the scans already measured
(``overlap.PairSelector``: a superset of the pairs ``overlap.overlapping_pairs`` selects over the whole job)
and registers those pairs as the correction would (``pair_stage.register_stitched_pair``, one pair a thread, a
thread a core, beside the next scans), keeping each outcome under ``correction.pair_key``; with ``[correction]
joint`` it also prepares each scan for the joint refinement (``correction.joint_scan``: thinned, with normals)
under ``correction.joint_scan_key`` and finds the nearest neighbours of its pairs there at the tracker poses
(``joint.associate``: the refinement's association, the costly part of it) under
``correction.association_key`` (:class:`OnlineJoint`, which the daemon's pair worker runs in a process of its own
beside the pairs': ``stitcher.PairWorker``). After the last scan
``correction.correct_scans`` takes the outcomes of the pairs it selects, the prepared scans and the
associations from these caches and computes only the others (a job resumed after a restart, a scan whose pose
changed), so its result never depends on what was done here.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from tandemscan.pipeline.geometry.frames import invert, transform_points
from tandemscan.pipeline.registration.correction import (
    CorrectionSettings,
    OnlineWork,
    StitchedScan,
    association_key,
    cloud_digest,
    joint_scan,
    joint_scan_key,
    pair_covariance,
    pair_key,
)
from tandemscan.pipeline.registration.icp import target_with_normals
from tandemscan.pipeline.registration.joint import Association, JointScan, associate, joint_tree
from tandemscan.pipeline.registration.overlap import PairSelector
from tandemscan.pipeline.registration.pair_stage import PairOutcome, register_stitched_pair
from tandemscan.pipeline.registration.pairs import NETWORK_METHODS
from tandemscan.pipeline.registration.parallel import pair_threads
from tandemscan.pipeline.registration.pose_graph import TransferPrior
from tandemscan.pipeline.registration.sampling import voxel_downsample

log = logging.getLogger(__name__)

#: targets with normals, and KD trees of prepared scans, kept for the next scans' pairs (most partners are the
#: last few scans; an older one is made again)
_TARGETS_KEPT = 24


class _Recent:
    """``make(i)`` of scan ``i``, the last ``size`` used kept."""

    def __init__(self, make: Callable[[int], Any], size: int = _TARGETS_KEPT):
        self._make, self._size, self._kept = make, size, OrderedDict()

    def __call__(self, i: int) -> Any:
        if i in self._kept:
            self._kept.move_to_end(i)
        else:
            self._kept[i] = self._make(i)
            if len(self._kept) > self._size:
                self._kept.popitem(last=False)
        return self._kept[i]


@dataclass(frozen=True)
class OnlineScan:
    """A scan's cloud as the correction sees it: thinned, in the world (mm), with its digest; ``scan`` holds
    its pose, covariance and station (not its points)."""

    world_mm: np.ndarray
    digest: bytes
    scan: StitchedScan


class OnlineJoint:
    """The scans of a job prepared for the joint refinement as they arrive (``correction.joint_scan``, under
    ``correction.joint_scan_key``) and the nearest neighbours of their pairs at the tracker poses
    (``joint.associate``, under ``correction.association_key``): one instance per job, where the work runs.
    ``cfg`` must be the job's ``[correction]`` settings (:class:`CorrectionSettings`, ``joint`` on)."""

    def __init__(self, cfg: CorrectionSettings):
        self.cfg = cfg
        self.joint_scans: dict[str, JointScan] = {}
        self.associations: dict[str, Association] = {}
        self._selector = PairSelector(cfg.pair_cell_mm, cfg.joint_max_partners_per_scan)
        self._starts: list[tuple[str, np.ndarray]] = []  # each prepared scan's key and tracker pose
        self._tree = _Recent(lambda i: joint_tree(self.joint_scans[self._starts[i][0]]))
        self.preparing = True  # scans prepared as they arrive (:meth:`stop_preparing`)

    def add(self, points_S: np.ndarray, T_W_S: np.ndarray, station: int) -> None:
        """Prepare the next scan (``points_S`` (N, 3) mm as the end of the job loads them, its tracker pose ``T_W_S``
        and station) and find, at the tracker poses, the nearest neighbours of its points in every earlier prepared
        scan it may be paired with there (``correction._refine_jointly`` pairs the prepared scans sharing a grid
        cell); nothing once :meth:`stop_preparing` was called. Not queued behind anything: each search holds its
        partner's KD tree (a few megabytes at full resolution) until it has run."""
        if not self.preparing or len(points_S) == 0:
            return
        T_W_S = np.asarray(T_W_S, float)
        key = joint_scan_key(points_S, self.cfg.joint_voxel_mm)
        prepared = self.joint_scans[key] = joint_scan(points_S, self.cfg.joint_voxel_mm)
        partners = self._selector.add(transform_points(T_W_S, prepared.points_S), int(station))
        self._starts.append((key, T_W_S))
        todo = {}  # association key -> (prepared scan, its KD-tree, relative start pose) of each partner
        for i in partners:
            key_i, T_W_S_i = self._starts[i]
            todo[association_key(key_i, key, T_W_S_i, T_W_S, self.cfg.joint_refinement.max_distance_mm)] = (
                self.joint_scans[key_i], self._tree(i), invert(T_W_S_i) @ T_W_S)
        with pair_threads() as pair_map:
            self.associations |= zip(todo, pair_map(
                lambda job: associate(job[0], job[1], prepared, job[2], self.cfg.joint_refinement.max_distance_mm),
                todo.values()), strict=True)

    def stop_preparing(self) -> None:
        """The job has measured its last scan: the scans still to come here are not prepared (the end of the job,
        which waits for that, prepares them itself on every core, to the same poses)."""
        self.preparing = False

    def hand_over(self) -> tuple[dict[str, JointScan], dict[str, Association]]:
        """The prepared scans and their pairs' nearest neighbours so far, no longer kept here."""
        out = self.joint_scans, self.associations
        self.joint_scans, self.associations = {}, {}
        return out


class OnlinePairs:
    """The pair outcomes of a job, registered as its scans arrive (one instance per job, where the work runs), and
    with ``[correction] joint`` and ``joint`` (the default) its scans prepared for the joint refinement here too
    (:class:`OnlineJoint`, :attr:`joint`; the daemon's pair worker prepares them in a process of its own instead).

    :meth:`add` queues a scan's pairs on a pool of one thread per core and returns: the
    pairs of the next scans queue behind them, so no core waits at the end of a scan's pairs. A queued pair that a
    later scan displaced before it started (``overlap.PairSelector.kept``: the end of the job never selects it) is
    not registered. :meth:`work` waits for what is queued. ``cfg`` and ``voxel_mm`` must be the job's
    ``[correction]`` settings (:class:`CorrectionSettings`) and ``[job] voxel_mm``, as the end of the job uses them;
    a method that needs the DeepMerge network registers nothing here (the network is loaded at the end only)."""

    def __init__(self, cfg: CorrectionSettings, voxel_mm: float, joint: bool = True):
        self.cfg, self.voxel_mm = cfg, float(voxel_mm)
        self.enabled = cfg.enabled and cfg.method not in NETWORK_METHODS
        # the pairs registered (``CorrectionSettings.registered_partners``; None: none)
        self.selector = PairSelector(cfg.pair_cell_mm, cfg.registered_partners) if cfg.registered_partners else None
        self.scans: list[OnlineScan] = []
        self.outcomes: dict[str, PairOutcome] = {}
        # the scans prepared for the joint refinement here (None: not here)
        self.joint = OnlineJoint(cfg) if cfg.joint and joint and self.enabled else None
        self._target = _Recent(lambda i: target_with_normals(self.scans[i].world_mm))
        self._queued: dict[str, Future] = {}  # pair key -> its outcome (None: displaced before it started)
        self._pool: ThreadPoolExecutor | None = None
        self._shared = threading.Lock()  # the selector and the kept targets, which the pool's threads read
        self._cpu_start = time.process_time()
        self.cpu_s = 0.0  # CPU time (s) of this process from its start to the last :meth:`work`
        self.pair_cpu_s = 0.0  # CPU time (s) of the pair registrations' threads

    def add(self, points_S: np.ndarray, T_W_S: np.ndarray, covariance: np.ndarray, station: int,
            transfers: Sequence[TransferPrior]) -> int:
        """Take the next scan with points (``points_S`` (N, 3) mm as the end of the job loads them,
        ``finish.load_scans``; its 6x6 pose covariance, ``uncertainty.scan_pose_covariance``; its tracker
        station; the transfer priors known so far), queue the registration of its pairs and, with :attr:`joint`,
        prepare it for the joint refinement and find the nearest neighbours of its pairs there
        (:meth:`OnlineJoint.add`); returns how many partners it has."""
        if not self.enabled or len(points_S) == 0:
            return 0
        scan = StitchedScan(np.empty((0, 3)), np.asarray(T_W_S, float), np.asarray(covariance, float), int(station))
        partners = [] if self.selector is None else self._queue_pairs(points_S, scan, transfers)
        if self.joint is not None:
            self.joint.add(points_S, scan.T_W_S, scan.station)
        return len(partners)

    def stop_preparing(self) -> None:
        """The job has measured its last scan: :meth:`OnlineJoint.stop_preparing` (their pairs still register)."""
        if self.joint is not None:
            self.joint.stop_preparing()

    def _queue_pairs(self, points_S: np.ndarray, scan: StitchedScan, transfers: Sequence[TransferPrior]
                     ) -> list[int]:
        """Place the scan (thinned, in W), select its partners and queue the registration of its pairs; returns
        the partners."""
        world = transform_points(scan.T_W_S, voxel_downsample(np.asarray(points_S, float), self.voxel_mm))
        new = OnlineScan(world, cloud_digest(world), scan)
        with self._shared:
            partners = self.selector.add(world, scan.station)
            self.scans.append(new)
        j = len(self.scans) - 1
        for i in partners:
            old = self.scans[i]
            cov = pair_covariance(old.scan, scan, transfers)
            key = pair_key(old.digest, new.digest, cov, self.cfg.pairs)
            if key not in self.outcomes and key not in self._queued:
                self._queued[key] = self._threads().submit(self._register, i, j, cov)
        log.debug("online pairs: scan %d, %d partners", j, len(partners))
        return partners

    def _threads(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(os.cpu_count() or 1, thread_name_prefix="online-pairs")
        return self._pool

    def _register(self, i: int, j: int, covariance: np.ndarray) -> PairOutcome | None:
        """Pair ``(i, j)`` registered, or None where a later scan displaced it (the end never selects it); its
        thread's CPU seconds (the target's preparation where it is made here included) add to :attr:`pair_cpu_s`."""
        started = time.thread_time()
        with self._shared:
            if not self.selector.kept(i, j):
                return None
            target = self._target(i)
        outcome = register_stitched_pair(self.scans[j].world_mm, target, covariance, self.cfg.pairs)
        with self._shared:
            self.pair_cpu_s += time.thread_time() - started
        return outcome

    def work(self) -> OnlineWork:
        """Wait for the queued pairs, then the pair outcomes, prepared joint scans and their pairs' nearest neighbours
        so far (a pair whose task failed is logged and left to the end of the job)."""
        self.outcomes |= {k: o for k, o in _results(self._queued).items() if o is not None}
        self._queued = {}
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        self.cpu_s = time.process_time() - self._cpu_start
        scans, associations = (self.joint.joint_scans, self.joint.associations) if self.joint is not None else ({}, {})
        return OnlineWork(self.outcomes, scans, associations, self.pair_cpu_s)

    def joint_work(self) -> OnlineWork:
        """Once the last scan is added: what the joint refinement takes (the prepared scans and their pairs' nearest
        neighbours, handed over and no longer kept here: :meth:`OnlineJoint.hand_over`) and the pairs registered so
        far, without waiting for the pairs still queued, whose keys it names (``OnlineWork.pending``: their outcomes
        come with :meth:`work`; with the joint refinement no pose waits for them, docs/end-of-job.md)."""
        done = {k: f for k, f in self._queued.items() if f.done()}
        self.outcomes |= {k: o for k, o in _results(done).items() if o is not None}
        self._queued = {k: f for k, f in self._queued.items() if k not in done}
        scans, associations = self.joint.hand_over() if self.joint is not None else ({}, {})
        return OnlineWork(dict(self.outcomes), scans, associations, self.pair_cpu_s, frozenset(self._queued))


def _results(futures: dict[str, Future]) -> dict[str, Any]:
    """Each future's result by its key, those that raised left out (logged)."""
    out = {}
    for key, future in futures.items():
        try:
            out[key] = future.result()
        except Exception as e:  # noqa: BLE001 - the end of the job computes what is missing
            log.warning("online pairs: a task failed, left to the end of the job: %s", e)
    return out

"""The pair stage of the end of a job over scan references (docs/compute.md): units of one target scan and the
scans registered onto it, run by a compute backend (``pipeline.compute``).

A :class:`TargetPairs` unit names its scans by :class:`ScanRef` (the raw scan file in the scan store, the tracker
pose ``T_W_S`` in the world W, mm), never by their points: where the unit runs they are placed by a
:class:`HeldScans` (the clouds this process holds) or a :class:`StoredScans` (read from the store, thinned at the
job's voxel and placed at ``T_W_S``: the copy the end of the job holds, ``raw_scan.read_thinned_scan``, which a
second thinning leaves as it is). The target's normals are computed once a unit and each source registered onto
it (:func:`register_stitched_pair`); a unit's outcomes (:class:`PairOutcome`: 4x4, 6x6 and a centre) are all
that comes back. The same unit gives the same outcomes bit for bit wherever and however often it runs.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tandemscan.pipeline.compute import ComputeBackend
from tandemscan.pipeline.geometry.frames import transform_points
from tandemscan.pipeline.io.raw_scan import read_thinned_scan
from tandemscan.pipeline.registration.icp import point_to_plane_information, target_with_normals
from tandemscan.pipeline.registration.pairs import (
    JobPairSettings,
    PairCorrection,
    Registrar,
    RegistrationFailed,
    correct_pair,
)
from tandemscan.pipeline.registration.pose_graph import constrained_edge
from tandemscan.pipeline.registration.sampling import voxel_downsample


@dataclass(frozen=True)
class PairOutcome:
    """What the pose graph and the report keep of one pair's registration (world frame W, mm, rad).

    ``transformation`` (4x4, ``T`` moving the source onto the target) is None when the overlap was too small
    or the registration failed its verification (``dropped`` says why); ``information`` (6x6, about
    ``centre_mm``, only the directions the overlap constrains) is None for a fit of fewer than 6 inliers,
    which makes no graph edge."""

    transformation: np.ndarray | None = None
    information: np.ndarray | None = None
    centre_mm: np.ndarray | None = None
    inliers: int = 0
    stage: str = ""
    dropped: str = ""


def _outcome(pc: PairCorrection, cfg: JobPairSettings) -> PairOutcome:
    """The pose-graph edge of a pair correction, keeping only the directions the overlap constrains."""
    if pc.fit.inliers < 6:
        return PairOutcome(pc.transformation, None, pc.centre_mm, pc.fit.inliers, pc.stage)
    info = point_to_plane_information(pc.fit.points_mm, pc.fit.normals, pc.centre_mm, max(pc.fit.rmse_mm, 0.005),
                                      cfg.edge_effective_points)
    size = float(np.sqrt(((pc.fit.points_mm - pc.centre_mm) ** 2).sum(axis=1).mean()))
    T, info = constrained_edge(pc.transformation, info, pc.centre_mm, max(size, 1.0), cfg.edge_min_eigen_ratio)
    return PairOutcome(T, info, pc.centre_mm, pc.fit.inliers, pc.stage)


def register_stitched_pair(source_W: np.ndarray, target: object, covariance: np.ndarray, cfg: JobPairSettings,
                           network: Registrar | None = None) -> PairOutcome:
    """Register one stitched pair (``pairs.correct_pair``: the source's world cloud, mm, onto the target with
    normals, ``icp.target_with_normals``; ``covariance`` of their relative pose, :func:`pair_covariance`)."""
    try:
        pc = correct_pair(source_W, target, cfg, network, covariance)
    except RegistrationFailed as e:
        return PairOutcome(dropped=str(e))
    return PairOutcome() if pc is None else _outcome(pc, cfg)


@dataclass(frozen=True)
class ScanRef:
    """A scan by reference: its index in the job, its raw scan file (relative to the scan store) and its tracker
    pose ``T_W_S`` (4x4, W, mm)."""

    index: int
    file: str
    T_W_S: np.ndarray


@dataclass(frozen=True)
class TargetPairs:
    """One unit of the pair stage: a target scan and the sources registered onto it, each with the 6x6 covariance
    of its pose relative to the target's (``correction.pair_covariance``)."""

    target: ScanRef
    sources: tuple[ScanRef, ...]
    covariances: tuple[np.ndarray, ...]

    def key(self, cfg: JobPairSettings, voxel_mm: float) -> str:
        """The unit's name: everything its outcomes depend on (files, poses, covariances, settings, voxel)."""
        h = hashlib.blake2b(digest_size=16)
        for ref in (self.target, *self.sources):
            h.update(ref.file.encode())
            h.update(np.ascontiguousarray(ref.T_W_S, np.float64).tobytes())
        for cov in self.covariances:
            h.update(np.ascontiguousarray(cov, np.float64).tobytes())
        h.update(repr(cfg).encode())
        h.update(np.float64(voxel_mm).tobytes())
        return f"pairs-{h.hexdigest()}"


@dataclass(frozen=True)
class HeldScans:
    """The scans' clouds this process holds, thinned and placed in W (mm), by :attr:`ScanRef.index` (a sequence of
    every scan's, or a mapping of those the units name)."""

    world_mm: Sequence[np.ndarray] | Mapping[int, np.ndarray]

    def __call__(self, ref: ScanRef) -> np.ndarray:
        return self.world_mm[ref.index]


@dataclass(frozen=True)
class StoredScans:
    """A scan's cloud read from the scan store (a folder every worker reaches), thinned to ``voxel_mm`` as the end
    of the job thins it (``raw_scan.read_thinned_scan``, then ``sampling.voxel_downsample``) and placed in W."""

    store: str
    voxel_mm: float

    def __call__(self, ref: ScanRef) -> np.ndarray:
        return transform_points(ref.T_W_S, self.thinned(ref))

    def loaded(self, ref: ScanRef) -> np.ndarray:
        """The scan's copy as the end of the job loads it (``raw_scan.read_thinned_scan`` at ``voxel_mm``; S, mm)."""
        return read_thinned_scan(Path(self.store) / ref.file, self.voxel_mm)

    def thinned(self, ref: ScanRef) -> np.ndarray:
        """:meth:`loaded`, thinned as the correction thins it (float64, S, mm)."""
        return voxel_downsample(np.asarray(self.loaded(ref), float), self.voxel_mm)


def register_unit(unit: TargetPairs, scans: HeldScans | StoredScans, cfg: JobPairSettings,
                  network: Registrar | None = None) -> list[PairOutcome]:
    """The outcome of each pair of ``unit``: the target's normals once, each source registered onto it."""
    target = target_with_normals(scans(unit.target))
    return [register_stitched_pair(scans(s), target, cov, cfg, network)
            for s, cov in zip(unit.sources, unit.covariances, strict=True)]


def register_units(units: Sequence[TargetPairs], scans: HeldScans | StoredScans, cfg: JobPairSettings,
                   voxel_mm: float, backend: ComputeBackend, network: Registrar | None = None
                   ) -> list[list[PairOutcome]]:
    """:func:`register_unit` of every unit on ``backend``, in order (each unit a task named by
    :meth:`TargetPairs.key`). The units are handed out largest first (most sources), so the workers finish
    together rather than one of them registering a large unit alone at the end."""
    fn = functools.partial(register_unit, scans=scans, cfg=cfg, network=network)
    order = sorted(range(len(units)), key=lambda k: -len(units[k].sources))  # stable: ties keep their order
    done = backend.map(fn, [units[k] for k in order], [units[k].key(cfg, voxel_mm) for k in order])
    out: list[list[PairOutcome]] = [[] for _ in units]
    for k, outcomes in zip(order, done, strict=True):
        out[k] = outcomes
    return out

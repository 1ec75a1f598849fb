"""Correct + refine stage of the end of a job (docs/registration.md): the runner's scans in, refined poses out.

Given the scans' points (read once by :mod:`tandemscan.daemon.jobs.finish`), carries each tracker reading's
covariance to its scan pose, takes each coordinate transfer's error prior from its journaled entry and runs
``pipeline.registration.correction.correct_scans`` (pairwise DeepMerge/ICP corrections, those registered while
the job measured reused, then the joint refinement over all scans and tracker stations, or the pose graph where it
is off). Report
figures before and after are returned for ``report.json``.

With ``correction.estimate_mount`` the refinement (or the graph) also estimates the shared correction of the
scanner mount ``T_T_S`` (``registration.mount_unknown.MountPrior``), with a prior per ``job.installation_source``: the
calibration file's hand-eye covariance (a benchmark's surveyed mounts state a tight one) or the CAD tolerance
``correction.mount_nominal_sigma_*`` for nominal mounts.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tandemscan.pipeline.geometry.uncertainty import scan_pose_covariance
from tandemscan.pipeline.registration.correction import (
    CorrectionSettings,
    StitchedJob,
    StitchedScan,
    complete_pair_checks,
    correct_scans,
)
from tandemscan.pipeline.registration.joint import chain_covariance
from tandemscan.pipeline.registration.mount_unknown import MountPrior
from tandemscan.pipeline.registration.pairs import LazyNetwork
from tandemscan.pipeline.registration.pose_covariance import PoseCovariance
from tandemscan.pipeline.registration.pose_graph import ScanPrior, TransferPrior

if TYPE_CHECKING:
    from tandemscan.config.models import CellConfig
    from tandemscan.daemon.jobs.records import ScanRecord
    from tandemscan.daemon.jobs.snapshot import JobSnapshot
    from tandemscan.pipeline.compute import ComputeBackend
    from tandemscan.pipeline.registration.correction import OnlineWork, PairChecks
    from tandemscan.pipeline.stitching.installation import Installation
    from tandemscan.pipeline.stitching.tiles import ScanReach

log = logging.getLogger(__name__)


def _diagonal(sigma_mm: float, sigma_rad: float) -> np.ndarray:
    return np.diag([sigma_mm**2] * 3 + [sigma_rad**2] * 3)


def mount_prior(cfg: CellConfig, installation: Installation) -> tuple[MountPrior | None, str]:
    """The prior of the shared ``T_T_S`` correction (mm, rad) for a job configured by ``cfg`` that stitches with
    the mounts ``installation``, and where it came from."""
    dm = cfg.correction
    if not dm.estimate_mount:
        return None, "off"
    source = cfg.job.installation_source
    cov, label = _diagonal(dm.mount_nominal_sigma_mm, np.radians(dm.mount_nominal_sigma_deg)), "CAD tolerance"
    if source == "calibration":
        if installation.T_T_S_covariance is not None:
            cov, label = installation.T_T_S_covariance, "calibration file"
        else:
            log.warning("calibration file %s has no T_T_S covariance; the mount prior is the CAD tolerance",
                        cfg.job.calibration_file)
    return MountPrior(cov, dm.mount_min_information_ratio), label


def transfer_priors(transfers: list[dict]) -> list[TransferPrior]:
    """The pose graph's prior of each coordinate transfer, from the runner's transfer entries (W, mm)."""
    return [TransferPrior(t["station"], np.array(t["target_W_mm"]), np.array(t["covariance"])) for t in transfers]


def _reading_covariance(job: JobSnapshot, scan: ScanRecord) -> np.ndarray:
    """6x6 covariance of a scan's tracker pose (t mm^2 at its origin, r rad^2; W axes) from its reading's."""
    return scan_pose_covariance(scan.T_W_C, scan.reading.T_C_T, job.installation.T_T_S, scan.reading.covariance)


def tracker_chain_covariance(job: JobSnapshot) -> PoseCovariance:
    """The scans' errors jointly where no correction ran: the tracker readings', the transfers' and the mount's
    priors (the mount's as :func:`mount_prior` gives it, also where ``estimate_mount`` is off)."""
    priors = [ScanPrior(s.T_W_S, _reading_covariance(job, s), s.tracker_station) for s in job.scans]
    with_mount = job.config.model_copy(update={"correction": job.config.correction.model_copy(
        update={"estimate_mount": True})})
    return chain_covariance(priors, transfer_priors(job.transfers), mount_prior(with_mount, job.installation)[0])


def stitched_scans(job: JobSnapshot, points_S: Sequence[np.ndarray]) -> list[StitchedScan]:
    """The scans of ``job.scans`` as the correction takes them: their points ``points_S`` (S, mm), tracker poses
    with each reading's covariance carried to the scan pose, stations, and files (:func:`in_job`)."""
    return [StitchedScan(P, s.T_W_S, _reading_covariance(job, s), s.tracker_station, in_job(Path(s.file), job.job_dir))
            for s, P in zip(job.scans, points_S, strict=True)]


def in_job(file: Path, job_dir: Path) -> str:
    """``file`` relative to the job folder (its place in a scan store holding the job folder), or as it is where it
    lies elsewhere."""
    return (file.relative_to(job_dir) if file.is_relative_to(job_dir) else file).as_posix()


def correct_job(job: JobSnapshot, points_S: Sequence[np.ndarray | None], online: OnlineWork | None,
                backend: ComputeBackend
                ) -> tuple[dict, list[np.ndarray], PoseCovariance | None, PairChecks | None, tuple[ScanReach, ...]]:
    """The refined pose ``T_W_S`` (W, mm) of every scan of ``job.scans``, whose points in the scanner frame S
    (mm) are ``points_S`` (None: read from the scan store by the backend's workers, not on the local backend); ``job``
    is not changed. ``online``: what the job computed while it measured
    (``registration.correction.OnlineWork``: registered pairs, scans prepared for the joint refinement and their pairs'
    nearest neighbours, reused by ``correction.correct_scans`` where their keys match); ``backend``: the end of the
    job's compute backend (``compute.LazyBackend.get``), left open.

    Returns the ``correction`` section of the report (the settings, pair and graph figures; on the simulated
    cell ``job_report.score_ground_truth`` adds those of the tracker-only stitch, ``before``, once the job's outputs
    are written), the refined poses in scan order, the covariance of their errors (``pose_covariance``, scans
    numbered as in ``job.scans``), the check pairs still registering where ``online`` named some
    (``correction.PairChecks``: the section has no pair figures until :func:`complete_checks` gives them) and
    each scan's ``tiles.ScanReach`` (the tiled merge's bound of its x at the refined pose).
    """
    cfg, compute = job.config.correction, job.config.compute
    started, cpu = time.monotonic(), backend.cpu_seconds()  # this process's and the workers'
    prior, prior_source = mount_prior(job.config, job.installation)
    # on a cluster the pair stage's workers read the scans from the store by reference (docs/compute.md)
    store = str(compute.store_of(job.job_dir)) if compute.backend != "local" else None
    stitched = StitchedJob(stitched_scans(job, points_S), transfer_priors(job.transfers), prior,
                           job.config.job.voxel_mm)
    result = correct_scans(stitched, CorrectionSettings.from_section(cfg), LazyNetwork(job.config.deepmerge),
                           online, backend, store)
    section = {"enabled": True, **result.report, "seconds": round(time.monotonic() - started, 3),
               "cpu_seconds": round(backend.cpu_seconds() - cpu, 3)}
    section["mount"] = {"estimated": result.mount is not None, "prior": prior_source}
    if result.mount is not None:
        section["mount"] |= result.mount.observability(job.config.scanner.sweet_spot_mm)
        section["mount"]["T_T_S_refined"] = (job.installation.T_T_S @ result.mount.correction).tolist()
    log.info("stitch corrected in %.1f s", section["seconds"])
    return section, list(result.poses), result.pose_covariance, result.checks, result.reaches


def complete_checks(job: JobSnapshot, checks: PairChecks, later: OnlineWork | None, backend: ComputeBackend
                    ) -> dict:
    """The pair figures of the correction section :func:`correct_job` left with ``checks`` still registering
    (``correction.complete_pair_checks``: from ``later``, the pair worker's outcomes once its pairs were done, None
    where they could not be handed over; a pair missing there registered here, its scans read from the scan store,
    ``[compute] scan_store`` or the job folder, on ``backend``, the end of the job's, left open)."""
    compute = job.config.compute
    return complete_pair_checks(checks, CorrectionSettings.from_section(job.config.correction), later,
                                str(compute.store_of(job.job_dir)), job.config.job.voxel_mm, backend,
                                LazyNetwork(job.config.deepmerge))

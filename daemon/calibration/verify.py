"""Interim verification of the cell, VDI/VDE 2634 part 3 style (docs/calibration.md, "Interim verification").

``tandemscan verify`` measures the calibration plate, a calibrated artefact of three spheres whose centre
distances are known (``[calibration] centre_*_mm``; the simulator places it where ``[calibration] T_V2_P`` says),
through the whole chain: from ``[verification] views`` arm poses the tracker reads the target at rest and the
scanner scans the plate; each sphere's centre is placed in the tracker's frame C by ``T_C_T T_T_S`` with the
mounts a job would use now. The plate stands still, so a centre of one view and another sphere's centre of
another view lie the calibrated distance apart: their differences are the sphere-spacing errors (SD), each with
its expanded uncertainty (k = 2) from the sphere fits, the tracker readings and the mount's covariance. The probing
errors are those of the single fits: form (the RMS of the radial residuals; VDI's PF is their range) and size
(the free fit's diameter against the calibrated one). Each is compared with its maximum permissible error; the
result is recorded in ``[verification] output_file`` and appended to the journal beside it (``.jsonl``).
"""

from __future__ import annotations

import asyncio
import datetime as dt
import itertools
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tandemscan.daemon.calibration.calibrate import scan_plate_views
from tandemscan.daemon.calibration.current import installation_for_job, installation_record
from tandemscan.pipeline.calibration.plate import SPHERE_NAMES, nominal_centres_P
from tandemscan.pipeline.geometry.frames import transform_points
from tandemscan.pipeline.geometry.kinematics import ArmKinematics
from tandemscan.pipeline.geometry.uncertainty import covariance_about
from tandemscan.pipeline.inspection.verdict import VerdictContext
from tandemscan.pipeline.io.durable import write_durably

if TYPE_CHECKING:
    from tandemscan.config.models import CellConfig
    from tandemscan.daemon.calibration.calibrate import PlateViews
    from tandemscan.daemon.cell.session import CellSession
    from tandemscan.pipeline.stitching.installation import Installation

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VerificationResult:
    """One verification: the largest sphere-spacing error (mm, signed) and its U (k = 2), the probing form and size
    errors (mm, the largest over the fits), each against its MPE, the result ("pass" or "fail"), when, with which
    mounts (``installation``) and from how many views."""

    created_utc: str
    result: str
    sphere_spacing_error_mm: float
    sphere_spacing_uncertainty_mm: float
    probing_form_mm: float
    probing_size_mm: float
    mpe_sphere_spacing_mm: float
    mpe_probing_form_mm: float
    mpe_probing_size_mm: float
    views: int
    spacings: int
    installation: dict
    failures: tuple[str, ...] = ()

    def summary(self) -> str:
        """One line: result, errors against their MPEs, and when."""
        return (f"{self.result} at {self.created_utc}: sphere spacing {self.sphere_spacing_error_mm:+.4f} mm "
                f"(U {self.sphere_spacing_uncertainty_mm:.4f}, MPE {self.mpe_sphere_spacing_mm:g}), probing form "
                f"{self.probing_form_mm:.4f} mm (MPE {self.mpe_probing_form_mm:g}), size {self.probing_size_mm:+.4f} "
                f"mm (MPE {self.mpe_probing_size_mm:g})")


def _centres_C(views: PlateViews, installation: Installation) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3, 3) sphere centres A, X, Y of each view in C (mm) and their (V, 3, 3, 3) covariances: the fits', the
    tracker reading's (about the target's origin) and the mount's (right-perturbation of ``T_T_S``)."""
    centres, covs = [], []
    mount = installation.T_T_S_covariance
    for T_C_T, reading_cov, c_S, c_cov in zip(views.target_poses, views.covariances, views.centres,
                                               views.centre_covariances, strict=True):
        T_C_S = np.asarray(T_C_T) @ installation.T_T_S
        R = T_C_S[:3, :3]
        c_C = transform_points(T_C_S, c_S)
        cov = np.einsum("ij,ajk,lk->ail", R, c_cov, R)
        for a in range(3):
            cov[a] += covariance_about(reading_cov, np.zeros(3), c_C[a] - T_C_T[:3, 3])[:3, :3]
            if mount is not None:
                R6 = np.kron(np.eye(2), R)
                cov[a] += covariance_about(R6 @ mount @ R6.T, np.zeros(3), R @ c_S[a])[:3, :3]
        centres.append(c_C)
        covs.append(cov)
    return np.array(centres), np.array(covs)


def sphere_spacing_errors(views: PlateViews, installation: Installation, nominal_P: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Every spacing of a sphere in one view and another sphere in another view against the calibrated one:
    (errors mm, their expanded uncertainties k = 2)."""
    c, cov = _centres_C(views, installation)
    errors, expanded = [], []
    for v, w in itertools.permutations(range(len(c)), 2):
        for a, b in itertools.permutations(range(3), 2):
            d = c[v, a] - c[w, b]
            length = float(np.linalg.norm(d))
            u = d / length
            errors.append(length - float(np.linalg.norm(nominal_P[a] - nominal_P[b])))
            expanded.append(2.0 * float(np.sqrt(u @ (cov[v, a] + cov[w, b]) @ u)))
    return np.array(errors), np.array(expanded)


def evaluate(views: PlateViews, installation: Installation, config: CellConfig) -> VerificationResult:
    """The verification's figures from the plate views (module doc)."""
    ver, cal = config.verification, config.calibration
    errors, U = sphere_spacing_errors(views, installation, nominal_centres_P(cal))
    worst = int(np.argmax(np.abs(errors)))
    fits = [f.spheres[n] for view in views.fits for f in view for n in SPHERE_NAMES]
    form = max(f.rms_mm for f in fits)
    sizes = [2.0 * f.free_radius_mm - cal.sphere_diameter_mm for f in fits]
    size = sizes[int(np.argmax(np.abs(sizes)))]
    failures = tuple(
        f"{what} {value:.4f} mm beyond its MPE {mpe:g} mm"
        for what, value, mpe in (("sphere-spacing error", abs(errors[worst]), ver.mpe_sphere_spacing_mm),
                                 ("probing form error", form, ver.mpe_probing_form_mm),
                                 ("probing size error", abs(size), ver.mpe_probing_size_mm))
        if value > mpe)
    return VerificationResult(
        dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "fail" if failures else "pass",
        float(errors[worst]), float(U[worst]), float(form), float(size), ver.mpe_sphere_spacing_mm,
        ver.mpe_probing_form_mm, ver.mpe_probing_size_mm, len(views.target_poses), len(errors),
        installation_record(config), failures)


async def run_verification(session: CellSession, config: CellConfig,
                           progress: Callable[[int, int, str], None] | None = None) -> VerificationResult:
    """Measure the plate from ``[verification] views`` poses with the mounts a job would use now, evaluate and
    record the result (``[verification] output_file`` and its journal)."""
    progress = progress or (lambda done, total, msg: None)
    installation = await asyncio.to_thread(installation_for_job, config)
    observer = session.calibration_observer()
    if observer is not None:  # the simulator places the plate
        await asyncio.to_thread(observer.calibration_started)
    views_cfg = config.model_copy(update={"calibration": config.calibration.model_copy(
        update={"poses": config.verification.views})})
    views, skipped = await scan_plate_views(session, views_cfg, installation, ArmKinematics(config.arm), progress)
    result = evaluate(views, installation, config)
    await asyncio.to_thread(record, config, result)
    log.info("verification %s (%d views, %d skipped)", result.summary(), result.views, len(skipped))
    return result


def record(config: CellConfig, result: VerificationResult) -> None:
    """Write ``result`` as the last verification and append it to the journal beside it (one JSON a line)."""
    path = Path(config.verification.output_file)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.dumps(asdict(result))
    write_durably(path, lambda f: f.write(data.encode("utf-8")))
    with path.with_suffix(".jsonl").open("a", encoding="utf-8") as journal:
        journal.write(data + "\n")


def last_verification(config: CellConfig, now: dt.datetime | None = None) -> dict | None:
    """The last verification on record (its fields, ``age_h`` and ``summary``), None where there is none."""
    path = Path(config.verification.output_file)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        created = dt.datetime.fromisoformat(data["created_utc"])
    except (OSError, ValueError, KeyError):
        return None
    age_h = ((now or dt.datetime.now(dt.UTC)) - created).total_seconds() / 3600.0
    failures = tuple(data.get("failures", ()))
    known = {k: data[k] for k in VerificationResult.__dataclass_fields__ if k in data} | {"failures": failures}
    return data | {"age_h": round(age_h, 2), "summary": VerificationResult(**known).summary()}


def verification_holds(config: CellConfig, last: dict | None) -> tuple[str, ...]:
    """Reasons the last verification holds a verdict back: failed, or older than ``[verification] max_age_h``."""
    if last is None:
        return ()
    if last.get("result") != "pass":
        return (f"the last verification failed ({last['summary']}): the cell is not verified",)
    if last["age_h"] > config.verification.max_age_h:
        return (f"the last verification is {last['age_h']:.0f} h old, more than [verification] max_age_h "
                f"{config.verification.max_age_h:g} h: the cell is overdue for verification",)
    return ()


def verdict_context(config: CellConfig) -> VerdictContext:
    """What the verdict of a job configured by ``config`` is made in: the installation it stitched with and the
    last verification, which holds the verdict back where it failed or is overdue (:func:`verification_holds`)."""
    last = last_verification(config)
    return VerdictContext(installation=installation_record(config), verification=last,
                          holds=verification_holds(config, last))

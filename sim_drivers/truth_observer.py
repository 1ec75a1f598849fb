"""Ground truth as an observer: the simulated cell's scoring of a job and of a calibration.

:class:`TruthObserver` implements :class:`tandemscan.daemon.cell.observer.JobObserver`: as the runner reports what
it measured it records the truth at that moment (the true scanner pose ``T_W_S`` of each scan, the true
tracker camera pose of each transfer, the true measurement-AGV pose of each located station) in the world's
``scoring`` log, which the world state saves with itself, so a resumed job is scored as one run.
:class:`TruthScorer` (picklable) turns the log, the job's final poses and its cloud into the report's
``ground_truth`` section where the job's world map lives. Frames: W the job's world frame (the tracker camera
frame at its first station), F the part frame; mm, deg in the report.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.part import load_part_mesh
from tandemscan.pipeline.inspection.deviation_areas import DeviationArea
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.pipeline.stitching.installation import Installation
from tandemscan.sim_drivers.inspection_score import alignment_error, deviation_truths, score_areas
from tandemscan.sim_drivers.stitch_score import cloud_to_mesh_distances, distance_stats, pose_errors
from tandemscan.sim_drivers.world import SimWorld, WorldTruth

if TYPE_CHECKING:
    from tandemscan.daemon.jobs.snapshot import JobSnapshot


def _error(T: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    mm, rad = F.pose_error(T, T_true)
    return {"mm": mm, "deg": float(np.degrees(rad))}


class TruthObserver:
    """Records the truth of one job (``job_key``) as the runner measures it; see the module docstring."""

    def __init__(self, world: SimWorld, job_key: str, resumed: bool, keep_state) -> None:
        self.world, self.keep_state = world, keep_state
        if not resumed or job_key not in world.scoring:
            world.scoring[job_key] = {"T_W_S_true": {}, "transfers": [], "located": []}
        self.log = world.scoring[job_key]
        if not resumed:
            self.world_defined()

    def world_defined(self) -> None:
        self.world.define_world()
        self.keep_state()

    def scan_measured(self, index: int) -> None:
        self.log["T_W_S_true"][str(index)] = self.world.T_W_S().tolist()
        self.keep_state()

    def tracker_transferred(self, station: int, T_W_C: np.ndarray) -> None:
        err = _error(T_W_C, self.world.T_W_F @ self.world.T_F_C())
        self.log["transfers"] = [t for t in self.log["transfers"] if t["station"] != station]
        self.log["transfers"].append({"station": station, "tracker_pose_err_mm": err["mm"],
                                      "tracker_pose_err_deg": err["deg"]})
        self.keep_state()

    def agv_located(self, step: int, T_F_V2: np.ndarray) -> None:
        err = _error(T_F_V2, self.world.T_F_V2)
        self.log["located"] = [e for e in self.log["located"] if e["step"] != step]
        self.log["located"].append({"step": step, "err_to_truth_mm": err["mm"], "err_to_truth_deg": err["deg"]})
        self.keep_state()

    def scorer(self) -> TruthScorer:
        return TruthScorer(self.world.scoring_truth(), {int(k): np.array(v) for k, v in self.log["T_W_S_true"].items()},
                           list(self.log["transfers"]), list(self.log["located"]))


@dataclass
class TruthScorer:
    """The truth a job was observed at; :meth:`score` writes its ``ground_truth`` report section."""

    world: WorldTruth
    T_W_S_true: dict[int, np.ndarray]  # per scan index, mm
    transfers: list[dict]
    located: list[dict]

    def score(self, job: JobSnapshot) -> dict:
        """Pose errors per scan and per tracker station, the stitched cloud's distance to the part, and the
        errors of each coordinate transfer and AGV location (mm, deg)."""
        scans = job.scans
        mm, deg = pose_errors([s.T_W_S for s in scans], [self.T_W_S_true[s.index] for s in scans])
        stations = np.array([s.tracker_station for s in scans])
        growth = [
            {"tracker_station": int(k), "scans": int(np.sum(stations == k)),
             "pose_err_mm_median": float(np.median(mm[stations == k])),
             "pose_err_deg_median": float(np.median(deg[stations == k]))}
            for k in np.unique(stations)
        ]
        cloud = distance_stats(cloud_to_mesh_distances(self.world.scene, job.worldmap.points(),
                                                       F.invert(self.world.T_W_F)))
        located = {"located": self.located}
        for key in ("err_to_truth_mm", "err_to_truth_deg"):
            if self.located:
                located[f"{key}_max"] = float(np.max([e[key] for e in self.located]))
        return {
            "pose_err_mm_median": float(np.median(mm)),
            "pose_err_mm_max": float(np.max(mm)),
            "pose_err_deg_median": float(np.median(deg)),
            "pose_err_deg_max": float(np.max(deg)),
            "per_scan": [{"index": s.index, "pose_err_mm": float(a), "pose_err_deg": float(b)}
                         for s, a, b in zip(scans, mm, deg, strict=True)],
            "per_tracker_station": growth,
            "cloud_rms_mm": cloud["rms_mm"],
            "cloud_p95_mm": cloud["p95_mm"],
            "cloud_max_mm": cloud["max_mm"],
            "transfers": sorted(self.transfers, key=lambda t: t["station"]),
            "relocalisation": located,
            "robots_moved_together": list(self.world.robots_moved_together),
        }

    def score_inspection(self, job: JobSnapshot, inspection: dict) -> dict:
        """The alignment's ``T_F_W`` and the anchor's against the truth at the part's centre (the CAD's bounding
        box centre; mm, deg), and the report's deviation areas against the ``[sim.as_built]`` deviations
        (found, missed, false regions, errors: :func:`score_areas`; on a defect-free part every area is false)."""
        cad = load_part_mesh(job.config.part)
        vertices = np.asarray(cad.vertices)
        centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        T_F_W_true = F.invert(self.world.T_W_F)
        out: dict = {"method": inspection["alignment"]["method"]}
        for key, label in (("T_F_W", "T_F_W_err"), ("T_F_W_anchor", "anchor_T_F_W_err")):
            mm, deg = alignment_error(np.asarray(inspection[key], float), T_F_W_true, centre)
            out |= {f"{label}_mm": mm, f"{label}_deg": deg}
        truths = deviation_truths(self.world.config, CadSurface(cad),
                                  F.transform_points(T_F_W_true, job.worldmap.points()))
        areas = tuple(DeviationArea(**{**a, "centroid_mm": tuple(a["centroid_mm"])})
                      for a in inspection.get("deviations", []))  # none where the alignment failed
        return out | score_areas(truths, areas)


class CalibrationTruth:
    """The observer of a calibration job: sets up the plate and, where ``scores``, scores the mounts against the
    world's truth."""

    def __init__(self, world: SimWorld, scores: bool) -> None:
        self.world, self.scores = world, scores

    def calibration_started(self) -> None:
        from tandemscan.sim_drivers.plate import install_calibration_plate

        install_calibration_plate(self.world, self.world.config.calibration)

    def calibration_scored(self, nominal: Installation, calibrated: Installation) -> dict[str, float] | None:
        if not self.scores:
            return None
        out: dict[str, float] = {}
        for k in ("T_T_S", "T_E_S", "T_V1_C", "T_V2_B"):
            truth = getattr(self.world.truth, k)
            for label, inst in (("", calibrated), ("nominal_", nominal)):
                err = _error(getattr(inst, k), truth)
                out[f"{label}{k}_err_mm"] = err["mm"]
                out[f"{label}{k}_err_deg"] = err["deg"]
        return out

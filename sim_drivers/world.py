"""The simulated cell: one object owns the ground truth that every twin reads and moves.

Frames (docs/architecture.md, "Frames"): F is the floor/part frame (the part mesh's frame); W is the tracker camera
frame at its first station (fixed when the world is made). All mm, rad, 4x4 float64. The pipeline never sees
the truth held here; only the scoring of a simulated job does.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d
from tandemscan.config.models import CellConfig
from tandemscan.drivers.errors import OutOfReach, TargetNotVisible
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.geometry.kinematics import ArmKinematics, arm_base_on_column
from tandemscan.pipeline.geometry.raycast import ScannerModel, make_scene
from tandemscan.pipeline.stitching.installation import Installation
from tandemscan.sim_drivers.as_built import scanned_part_mesh
from tandemscan.sim_drivers.config import ChassisSlipConfig, FloorPoseConfig

log = logging.getLogger(__name__)

# The target counts as occluded when the part is hit this much (mm) before the target along the sight line.
_OCCLUSION_MARGIN_MM = 5.0
# Each chassis's slip stream: [sim] seed and this number (the tracker's still error is 1, the arm's repeatability 2)
_SLIP_STREAMS = {"tracking_chassis": 3, "measure_chassis": 4}


@dataclass
class ChassisTruth:
    """One AGV: its true floor pose, what its odometry believes, and its slip/drift model.

    The odometry frame is F at the start (the start pose is surveyed); it drifts from there on. ``slip_rng`` is the
    stream an emulated chassis draws its slip from (the hardware-in-the-loop cell, ``sim_drivers.hil``): kept with
    the world's state, so that a restarted daemon's chassis goes on with the stream, not a replay of its first draws.
    """

    name: str
    cfg: ChassisSlipConfig
    true_pose: np.ndarray  # T_F_V, mm
    odometry: ChassisPose
    scale_bias: float  # systematic odometry scale error (drift), drawn once
    moves: int = 0
    slip_rng: np.random.Generator = field(default_factory=np.random.default_rng)

    def apply_move(self, target: ChassisPose, rng: np.random.Generator) -> tuple[float, float]:
        """Drive from the odometry pose to ``target``: the odometry lands exactly on it (closed loop on the
        wheels), the true chassis lands with slip and drift. Returns (path length mm, turn rad)."""
        T_odo_now = F.planar_pose(self.odometry.x_mm, self.odometry.y_mm, self.odometry.heading_rad)
        T_odo_target = F.planar_pose(target.x_mm, target.y_mm, target.heading_rad)
        delta = F.invert(T_odo_now) @ T_odo_target  # commanded motion in the chassis frame
        distance = float(np.linalg.norm(delta[:2, 3]))
        turn = float(np.arctan2(delta[1, 0], delta[0, 0]))
        scale = 1.0 + self.scale_bias + rng.normal(0.0, self.cfg.slip_distance_fraction)
        heading_error = rng.normal(0.0, np.radians(self.cfg.slip_heading_deg)) * (1.0 if distance > 1 else 0.2)
        actual = F.planar_pose(delta[0, 3] * scale, delta[1, 3] * scale, turn + heading_error)
        self.true_pose = self.true_pose @ actual
        self.odometry = target
        self.moves += 1
        return distance, abs(turn)


@dataclass
class SafetyTruth:
    """The cell's safety inputs and signal outputs."""

    estop: bool = False
    light_curtain_broken: bool = False
    target_light_on: bool = False


@dataclass
class MotionLog:
    """Which robots are moving now, and any time both moved at once (a violation of the cell's rule)."""

    moving: set[str] = field(default_factory=set)
    violations: list[str] = field(default_factory=list)

    def start(self, robot: str) -> None:
        others = self.moving - {robot}
        if others:
            self.violations.append(f"{robot} moved while {sorted(others)} moving")
            log.error("both robots moving: %s while %s", robot, sorted(others))
        self.moving.add(robot)

    def stop(self, robot: str) -> None:
        self.moving.discard(robot)


@dataclass
class WorldTruth:
    """What scoring a simulated job needs of the world: the world frame W in the part frame F (``T_W_F``,
    mm), the mesh the scanner saw (the part as built, with the fixture's spheres) and its ray-casting scene,
    and every moment both robots moved.

    Pickles without the mesh and scene: a worker process rebuilds them from ``config`` on first use (the
    as-built mesh, not the CAD)."""

    config: CellConfig
    T_W_F: np.ndarray
    robots_moved_together: list[str]
    _mesh: o3d.geometry.TriangleMesh | None = None
    _scene: o3d.t.geometry.RaycastingScene | None = None

    @property
    def mesh(self) -> o3d.geometry.TriangleMesh:
        if self._mesh is None:
            self._mesh = scanned_part_mesh(self.config)
        return self._mesh

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        if self._scene is None:
            self._scene = make_scene(self.mesh)
        return self._scene

    def __getstate__(self) -> dict:
        return self.__dict__ | {"_mesh": None, "_scene": None}


def _floor_pose(p: FloorPoseConfig) -> np.ndarray:
    return F.planar_pose(p.x_mm, p.y_mm, np.radians(p.heading_deg))


@dataclass
class SightBlock:
    """Something in the tracker's sight line (:meth:`SimWorld.block_sight`): why, and how many more readings see
    past it before it is there."""

    reason: str
    after_reads: int = 0


class SimWorld:
    """Ground truth of the simulated cell, seeded: the same config gives the same run."""

    MEASURE_ROBOT = "measurement robot"
    TRACKING_ROBOT = "tracking robot"

    def __init__(self, config: CellConfig):
        self.config = config
        self.rng = np.random.default_rng(config.sim.seed)
        self.mesh = scanned_part_mesh(config)  # the part as built (and the fixture's spheres), not its CAD
        self.scene = make_scene(self.mesh)
        self.kinematics = ArmKinematics(config.arm)
        self.scanner_model = ScannerModel(config.scanner)
        self.nominal = Installation.nominal(config.installation)
        self.truth = self.nominal.perturbed(
            self.rng, config.sim.install_error_mm, np.radians(config.sim.install_error_deg)
        )
        self.chassis = {
            "tracking_chassis": self._make_chassis("tracking_chassis", config.sim.tracking_chassis_slip,
                                                   config.sim.tracking_start),
            "measure_chassis": self._make_chassis("measure_chassis", config.sim.measure_chassis_slip,
                                                  config.sim.measure_start),
        }
        self.joints_rad = np.radians(np.array(config.sim.arm_home_deg, float))
        self.lift_mm = config.lift.min_mm if config.lift.enabled else 0.0  # lifting column height, mm
        self.safety = SafetyTruth()
        self.motion = MotionLog()
        self.captures = 0
        self.tracker_frames = 0
        self.sight_blocked: SightBlock | None = None  # something in the tracker's sight line (block_sight)
        self.blocked_reads = 0  # tracker reads refused by a sight block
        # the tracker's still error: drawn once per still period (the true T_C_T unchanged), its own stream
        self.still_rng = np.random.default_rng([config.sim.seed, 1])
        self.still_T_C_T: np.ndarray | None = None
        self.still_unit = np.zeros(6)
        # the arm's repeatability: each move lands the flange off by a fresh offset (flange axes), its own stream
        self.arm_rng = np.random.default_rng([config.sim.seed, 2])
        self.flange_offset = np.eye(4)
        self.scoring: dict[str, dict] = {}  # the ground-truth observers' logs, per job (sim_drivers.truth_observer)
        self.state_file: Path | None = None  # where the twins keep this state (sim_drivers.persist)
        self.define_world()  # W = the tracker camera frame at its first station

    def define_world(self) -> None:
        """W becomes the tracker camera frame where it stands now: a job that moves the tracker before its first
        scan (a plain relocation) defines its world there, and the truth follows."""
        self.T_W_F = F.invert(self.T_F_C())

    def _make_chassis(self, name: str, cfg: ChassisSlipConfig, start: FloorPoseConfig) -> ChassisTruth:
        pose = ChassisPose(start.x_mm, start.y_mm, np.radians(start.heading_deg))
        bias = self.rng.normal(0.0, cfg.odometry_drift_fraction)
        return ChassisTruth(name, cfg, _floor_pose(start), pose, bias,
                            slip_rng=np.random.default_rng([self.config.sim.seed, _SLIP_STREAMS[name]]))

    def scoring_truth(self) -> WorldTruth:
        """The scoring view of the world now (shares this world's mesh and scene)."""
        return WorldTruth(self.config, self.T_W_F.copy(), list(self.motion.violations), self.mesh, self.scene)

    # ------------------------------------------------------------ true poses in F

    @property
    def T_F_V1(self) -> np.ndarray:
        return self.chassis["tracking_chassis"].true_pose

    @property
    def T_F_V2(self) -> np.ndarray:
        return self.chassis["measure_chassis"].true_pose

    def T_F_C(self) -> np.ndarray:
        """Tracker camera in the floor frame."""
        return self.T_F_V1 @ self.truth.T_V1_C

    def T_F_E(self) -> np.ndarray:
        """Arm flange in the floor frame."""
        T_V2_B = arm_base_on_column(self.truth.T_V2_B, self.lift_mm)  # the column raises the arm's mount
        return self.T_F_V2 @ T_V2_B @ self.kinematics.forward(self.joints_rad) @ self.flange_offset

    def T_F_S(self) -> np.ndarray:
        """Scanner optical frame in the floor frame."""
        return self.T_F_E() @ self.truth.T_E_S

    def T_F_T(self) -> np.ndarray:
        """Target in the floor frame."""
        return self.T_F_S() @ F.invert(self.truth.T_T_S)

    def T_W_S(self) -> np.ndarray:
        """True scanner pose in the world frame W (what a perfect stitch would use)."""
        return self.T_W_F @ self.T_F_S()

    # ------------------------------------------------------------ physics of each device

    def move_arm(self, joints_rad: np.ndarray) -> float:
        """Set the joints; returns the largest joint travel (rad). Raises OutOfReach outside the limits. A move
        that travels lands the flange off its kinematic pose by a fresh offset (``sim.arm_repeatability``: the
        same joints give the same flange pose only that closely); one of no travel keeps it."""
        q = np.asarray(joints_rad, float)
        if q.shape != (6,) or not self.kinematics.within_limits(q):
            raise OutOfReach("arm", f"joint target {np.degrees(q).round(2).tolist()} deg outside the joint limits")
        travel = float(np.max(np.abs(q - self.joints_rad)))
        self.joints_rad = q
        if travel > 0:
            sigma_mm, sigma_rad = self.config.sim.arm_repeatability.sigma()
            self.flange_offset = F.from_rotvec(self.arm_rng.normal(0, sigma_mm, 3),
                                               self.arm_rng.normal(0, sigma_rad, 3))
        return travel

    def scan(self) -> tuple[np.ndarray, np.ndarray]:
        """A noisy capture at the true scanner pose: (points_S mm, normals_S)."""
        self.captures += 1
        return self.scanner_model.scan(self.scene, self.T_F_S(), self.rng)

    def block_sight(self, reason: str | None, after_reads: int = 0) -> None:
        """Put something in the tracker's sight line (``reason``, e.g. a person walking through) once ``after_reads``
        more readings were taken, or take it away (None); not part of the saved world state."""
        self.sight_blocked = None if reason is None else SightBlock(reason, after_reads)

    def target_visibility(self) -> str | None:
        """Why the tracker cannot see the target now, or None when it can."""
        block = self.sight_blocked
        if block is not None and block.after_reads <= 0:
            return f"occluded: {block.reason}"
        cfg = self.config.tracker
        T_C_T = F.invert(self.T_F_C()) @ self.T_F_T()
        p = T_C_T[:3, 3]
        distance = float(np.linalg.norm(p))
        if distance > cfg.range_max_mm:
            return f"target {distance / 1000:.1f} m away, beyond the {cfg.range_max_mm / 1000:.0f} m range"
        if p[2] <= 0 or abs(np.degrees(np.arctan2(p[0], p[2]))) > cfg.fov_horizontal_deg / 2 or abs(
            np.degrees(np.arctan2(p[1], p[2]))
        ) > cfg.fov_vertical_deg / 2:
            return "target outside the field of view"
        facing = float(np.degrees(np.arccos(np.clip(-T_C_T[:3, 2] @ p / distance, -1, 1))))
        if facing > cfg.target_view_cone_deg:
            return f"target turned {facing:.0f} deg away from the camera"
        origin = self.T_F_C()[:3, 3]
        to_target = self.T_F_T()[:3, 3] - origin
        ray = np.r_[origin, to_target / distance][None, :].astype(np.float32)
        t_hit = float(self.scene.cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])
        if t_hit < distance - _OCCLUSION_MARGIN_MM:
            return f"target hidden behind the part ({t_hit:.0f} mm along the {distance:.0f} mm sight line)"
        return None

    def measure_target(self) -> tuple[np.ndarray, np.ndarray]:
        """One noisy ``T_C_T`` and its 6x6 covariance (one reading's, the still share included); raises
        TargetNotVisible with the reason.

        The noise has two parts (``tracker.still_noise_fraction`` of the variance the second): one drawn afresh
        at every frame, and one that stays while neither the target nor the tracker moves (turbulence and
        refraction change over seconds, the camera's calibration residual with where the target sits in the
        image), so averaging the readings of one still period reduces only the first, as on a real tracker."""
        reason = self.target_visibility()
        if reason is not None:
            if self.sight_blocked is not None and self.sight_blocked.after_reads <= 0:
                self.blocked_reads += 1
            raise TargetNotVisible("tracker", reason)
        if self.sight_blocked is not None:
            self.sight_blocked.after_reads -= 1
        T_true = F.invert(self.T_F_C()) @ self.T_F_T()
        sigma_p, sigma_r = self.config.sim.tracker_noise.sigma(float(np.linalg.norm(T_true[:3, 3])))
        if self.still_T_C_T is None or not np.array_equal(self.still_T_C_T, T_true):
            self.still_T_C_T, self.still_unit = T_true, self.still_rng.normal(0, 1, 6)
        f = self.config.tracker.still_noise_fraction
        fresh, still = np.sqrt(1.0 - f), np.sqrt(f)
        rotvec = self.rng.normal(0, sigma_r, 3) * fresh + self.still_unit[3:] * sigma_r * still
        T_meas = F.from_rotvec(np.zeros(3), rotvec) @ T_true
        T_meas[:3, 3] = T_true[:3, 3] + self.rng.normal(0, sigma_p, 3) * fresh + self.still_unit[:3] * sigma_p * still
        self.tracker_frames += 1
        return T_meas, np.diag([sigma_p**2] * 3 + [sigma_r**2] * 3)

"""Pydantic models of the cell configuration.

Units: millimetres, radians inside. Where a TOML key is a human-facing angle it says so in its name
(``*_deg``) and the model converts it. Every field has a default that runs the simulated cell.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

DriverKind = Literal["sim", "real"]


class _Strict(BaseModel):
    """Base: unknown keys are errors, so a typo in a TOML file is reported, not ignored."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class TransformConfig(_Strict):
    """A rigid transform ``T_a_b``: translation in mm and roll-pitch-yaw in degrees (fixed axes x, y, z)."""

    xyz_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """The 4x4 float64 matrix (mm)."""
        from tandemscan.pipeline.frames import from_rpy  # local: config must not need the pipeline at import

        return from_rpy(np.array(self.xyz_mm), np.radians(self.rpy_deg))


class PartConfig(_Strict):
    """The measured part: a CAD mesh file, or the parametric train nose when ``mesh`` is empty."""

    mesh: Path | None = None
    length_mm: float = Field(3000.0, gt=0)
    width_mm: float = Field(2000.0, gt=0)
    height_mm: float = Field(1600.0, gt=0)
    body_length_mm: float = Field(1000.0, ge=0, description="constant-section length before the nose, mm")


class ScannerConfig(_Strict):
    """PhoXi 3D Scanner S: working range along the optical axis (mm), field of view and noise."""

    driver: DriverKind = "sim"
    range_min_mm: float = 384.0
    range_max_mm: float = 520.0
    sweet_spot_mm: float = 442.0
    width_at_sweet_spot_mm: float = 360.0
    height_at_sweet_spot_mm: float = 280.0
    noise_sigma_mm: float = Field(0.05, ge=0, description="1-sigma noise along the ray, mm")
    max_incidence_deg: float = Field(75.0, gt=0, lt=90, description="points seen more grazing are dropped")
    resolution: Literal["coarse", "full"] = "coarse"
    coarse_pixels: tuple[int, int] = (230, 180)
    full_pixels: tuple[int, int] = (2064, 1544)
    timeout_s: float = 10.0

    @property
    def pixels(self) -> tuple[int, int]:
        """(columns, rows) of the active resolution."""
        return self.full_pixels if self.resolution == "full" else self.coarse_pixels


class TrackerConfig(_Strict):
    """Metronor optical tracker: field of view, range, and the pose noise model (1-sigma)."""

    driver: DriverKind = "sim"
    range_max_mm: float = 30000.0
    fov_horizontal_deg: float = 70.0
    fov_vertical_deg: float = 55.0
    target_view_cone_deg: float = Field(80.0, description="target visible while its normal is this close to the camera")
    position_noise_mm: float = Field(0.010, ge=0, description="at zero distance")
    position_noise_mm_per_m: float = Field(0.005, ge=0, description="growth with distance")
    angle_noise_deg: float = Field(0.0010, ge=0, description="at zero distance")
    angle_noise_deg_per_m: float = Field(0.0005, ge=0, description="growth with distance")
    samples_per_reading: int = Field(1, ge=1, description="readings averaged at rest per pose")
    timeout_s: float = 5.0


class ArmConfig(_Strict):
    """JAKA Zu 7 arm: standard DH parameters (mm, rad) and joint limits (deg at this edge)."""

    driver: DriverKind = "sim"
    # Standard DH of the Zu 7 (shared/protocols/README.md: a public Rust JAKA client cross-checked with
    # JAKA's ROS 2 URDF). Alpha signs differ between sources; this is the UR-style reading.
    dh_d_mm: tuple[float, ...] = (120.15, 0.0, 0.0, 115.01, 113.5, 107.0)
    dh_a_mm: tuple[float, ...] = (0.0, 360.0, 303.5, 0.0, 0.0, 0.0)
    dh_alpha_rad: tuple[float, ...] = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
    joint_min_deg: tuple[float, ...] = (-360.0, -85.0, -175.0, -85.0, -360.0, -360.0)
    joint_max_deg: tuple[float, ...] = (360.0, 265.0, 175.0, 265.0, 360.0, 360.0)
    joint_speed_deg_s: float = Field(60.0, gt=0)
    timeout_s: float = 60.0

    @field_validator("dh_d_mm", "dh_a_mm", "dh_alpha_rad", "joint_min_deg", "joint_max_deg")
    @classmethod
    def _six(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) != 6:
            raise ValueError(f"needs 6 values, got {len(v)}")
        return v


class ChassisConfig(_Strict):
    """An AGV chassis (skid steering): speed and the simulated slip and odometry drift."""

    driver: DriverKind = "sim"
    speed_mm_s: float = Field(300.0, gt=0)
    turn_rate_deg_s: float = Field(20.0, gt=0)
    slip_distance_fraction: float = Field(0.01, ge=0, description="1-sigma relative distance error")
    slip_heading_deg: float = Field(0.3, ge=0, description="1-sigma heading error per move")
    odometry_drift_fraction: float = Field(0.005, ge=0, description="1-sigma odometry scale error")
    timeout_s: float = 120.0


class SafetyConfig(_Strict):
    """Cell safety I/O (e-stop, light curtain, target light)."""

    driver: DriverKind = "sim"
    poll_period_s: float = Field(0.02, gt=0)


class InstallationConfig(_Strict):
    """Nominal (CAD) installation transforms; the pipeline only ever uses calibrated estimates of them.

    Frames (DESIGN.md section 2): ``V1`` tracking chassis, ``C`` tracker camera (z along the optical axis,
    x right, y down), ``V2`` measurement chassis, ``B`` arm base, ``E`` flange, ``S`` scanner optical frame
    (z along the view), ``T`` stereo target (z along its visible normal).
    """

    T_V1_C: TransformConfig = TransformConfig(xyz_mm=(0.0, 0.0, 1900.0), rpy_deg=(-100.0, 0.0, -90.0))
    T_V2_B: TransformConfig = TransformConfig(xyz_mm=(0.0, 0.0, 750.0))
    T_E_S: TransformConfig = TransformConfig(xyz_mm=(0.0, 60.0, 90.0))
    T_T_S: TransformConfig = TransformConfig(xyz_mm=(0.0, -90.0, 40.0), rpy_deg=(180.0, 0.0, 0.0))


class FloorPoseConfig(_Strict):
    """A chassis pose on the floor (part frame F): position mm and heading in degrees about +z."""

    x_mm: float = 0.0
    y_mm: float = 0.0
    heading_deg: float = 0.0


class SimWorldConfig(_Strict):
    """Ground truth of the simulated cell: how far the real installation is from nominal, time scale."""

    seed: int = 7
    tracking_start: FloorPoseConfig = FloorPoseConfig(x_mm=-1400.0, y_mm=4600.0, heading_deg=-90.0)
    measure_start: FloorPoseConfig = FloorPoseConfig(x_mm=-1800.0, y_mm=2300.0, heading_deg=0.0)
    arm_home_deg: tuple[float, ...] = (0.0, 90.0, 0.0, 90.0, 0.0, 0.0)
    install_error_mm: float = Field(2.0, ge=0, description="1-sigma per axis of true vs nominal mounts")
    install_error_deg: float = Field(0.3, ge=0, description="1-sigma per axis of true vs nominal mounts")
    time_scale: float = Field(0.0, ge=0, description="simulated motion time x this = wall time; 0 = instant")
    fault_scanner_timeout_every: int = Field(0, ge=0, description="every n-th capture times out; 0 = never")
    fault_estop_after_moves: int = Field(0, ge=0, description="e-stop after n chassis moves; 0 = never")


class JobConfig(_Strict):
    """Measurement job settings."""

    out_dir: Path = Path("out")
    voxel_mm: float = Field(1.0, gt=0, description="world map voxel edge, mm")
    installation_source: Literal["truth", "nominal", "calibration"] = Field(
        "truth", description="which T_T_S etc. the stitch uses: sim ground truth, CAD nominal or calibration_file"
    )
    calibration_file: Path | None = None


class DaemonConfig(_Strict):
    """The daemon: REST bind address, API token, device health polling and reconnect backoff (seconds)."""

    host: str = "127.0.0.1"
    port: int = Field(8470, ge=0, le=65535, description="0 = any free port")
    api_token: str | None = Field(None, description="bearer token of mutating calls; TANDEMSCAN_API_TOKEN wins")
    health_period_s: float = Field(1.0, gt=0)
    device_timeout_s: float = Field(2.0, gt=0, description="limit of one status() or connect() call")
    reconnect_initial_s: float = Field(0.5, gt=0)
    reconnect_max_s: float = Field(30.0, gt=0)
    default_plan: str = Field("default-band", description="plan of a job posted without one")


class CellConfig(_Strict):
    """The whole cell."""

    name: str = "simulated cell"
    part: PartConfig = PartConfig()
    scanner: ScannerConfig = ScannerConfig()
    tracker: TrackerConfig = TrackerConfig()
    arm: ArmConfig = ArmConfig()
    measure_chassis: ChassisConfig = ChassisConfig()
    tracking_chassis: ChassisConfig = ChassisConfig()
    safety: SafetyConfig = SafetyConfig()
    installation: InstallationConfig = InstallationConfig()
    sim: SimWorldConfig = SimWorldConfig()
    job: JobConfig = JobConfig()
    daemon: DaemonConfig = DaemonConfig()

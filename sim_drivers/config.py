"""The simulator's own settings: the ``[sim]`` table (the simulated cell's ground truth, noise, faults and the part
as built) and the ``[hil]`` table (the protocol emulators of a hardware-in-the-loop cell).

The product's configuration (:class:`~tandemscan.config.models.CellConfig`) does not know these models: the
simulator registers them as entry points of group :data:`~tandemscan.config.device_registry.SIMULATOR_GROUP` (in
``pyproject.toml``, as its device classes in ``tandemscan.devices``), and the cell configuration hands each its own
table to validate (docs/architecture.md, "The cell layer"). Units: mm and degrees at this edge (``*_deg`` keys),
as the product's settings.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator
from tandemscan.config.models import ArmRepeatabilityConfig, FloorPoseConfig


class _Strict(BaseModel):
    """Base: unknown keys are errors, so a typo in a TOML file is reported, not ignored."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class DentConfig(_Strict):
    """A dent (material below CAD) or bulge (above): a cosine bell of ``depth_mm`` along the surface normal
    within ``radius_mm`` of ``centre_mm`` (frame F; projected onto the CAD surface)."""

    kind: Literal["dent", "bulge"]
    centre_mm: tuple[float, float, float]
    radius_mm: float = Field(gt=0)
    depth_mm: float = Field(gt=0)


class WarpConfig(_Strict):
    """A bend (every point moved by ``amplitude_mm`` along ``direction``) or a twist (turned about the
    part's length axis x through ``axis_yz_mm``, ``amplitude_mm`` at 1 m from it), growing as the square
    of the way from ``start_x_mm`` (none) to ``end_x_mm`` (full), full beyond; frame F, mm."""

    kind: Literal["bend", "twist"]
    start_x_mm: float
    end_x_mm: float
    amplitude_mm: float
    direction: tuple[float, float, float] = (0.0, 1.0, 0.0)
    axis_yz_mm: tuple[float, float] = (0.0, 800.0)

    @field_validator("end_x_mm")
    @classmethod
    def _not_empty(cls, v: float, info) -> float:
        if v == info.data.get("start_x_mm"):
            raise ValueError("end_x_mm must differ from start_x_mm")
        return v


class StepConfig(_Strict):
    """A patch of the surface inside a box (frame F, mm) offset by ``step_mm`` along its normal."""

    kind: Literal["step"]
    min_mm: tuple[float, float, float]
    max_mm: tuple[float, float, float]
    step_mm: float


class OpeningEdgeConfig(_Strict):
    """An opening's edges as built: ``edge_offsets_mm`` (-u, +u, -v, +v) moved outward (the opening larger)
    from where the part's opening ``opening`` (its name) has them."""

    opening: str
    edge_offsets_mm: tuple[float, float, float, float]


class AsBuiltConfig(_Strict):
    """How the simulated part as built departs from its CAD model; the world scans this part while the
    planner and the inspection use the CAD mesh. Empty: the part is its CAD model."""

    deviations: tuple[Annotated[DentConfig | WarpConfig | StepConfig, Field(discriminator="kind")], ...] = ()
    openings: tuple[OpeningEdgeConfig, ...] = Field(
        (), description="the part's openings' edges as built (their CAD edges: [part] openings)")


class TrackerNoiseConfig(_Strict):
    """The simulated tracker's reading noise, 1-sigma per axis, growing with the target's distance (simulation
    only; the share that every reading of one still period shares is ``[tracker] still_noise_fraction``)."""

    position_noise_mm: float = Field(0.010, ge=0, description="at zero distance")
    position_noise_mm_per_m: float = Field(0.005, ge=0, description="growth with distance")
    angle_noise_deg: float = Field(0.0010, ge=0, description="at zero distance")
    angle_noise_deg_per_m: float = Field(0.0005, ge=0, description="growth with distance")

    def sigma(self, distance_mm: float) -> tuple[float, float]:
        """1-sigma per axis of one reading at ``distance_mm``: (translation mm, rotation rad)."""
        d_m = distance_mm / 1000.0
        return (self.position_noise_mm + self.position_noise_mm_per_m * d_m,
                math.radians(self.angle_noise_deg + self.angle_noise_deg_per_m * d_m))


class ChassisSlipConfig(_Strict):
    """How a simulated chassis misses its commanded moves and how its odometry drifts (simulation only)."""

    slip_distance_fraction: float = Field(0.01, ge=0, description="1-sigma relative distance error")
    slip_heading_deg: float = Field(0.3, ge=0, description="1-sigma heading error per move")
    odometry_drift_fraction: float = Field(0.005, ge=0, description="1-sigma odometry scale error")


class SimWorldConfig(_Strict):
    """Ground truth of the simulated cell: how far the real installation is from nominal, time scale."""

    seed: int = 7
    tracker_noise: TrackerNoiseConfig = TrackerNoiseConfig()
    arm_repeatability: ArmRepeatabilityConfig = Field(
        ArmRepeatabilityConfig(), description="the simulated arm: each move lands its flange off by a fresh "
                                              "random offset of this size (a move of no travel keeps it)")
    measure_chassis_slip: ChassisSlipConfig = ChassisSlipConfig()
    tracking_chassis_slip: ChassisSlipConfig = ChassisSlipConfig()
    tracking_start: FloorPoseConfig = FloorPoseConfig(x_mm=-1400.0, y_mm=4600.0, heading_deg=-90.0)
    measure_start: FloorPoseConfig = FloorPoseConfig(x_mm=-1800.0, y_mm=2300.0, heading_deg=0.0)
    arm_home_deg: tuple[float, ...] = Field(
        (0.0, 90.0, 0.0, 90.0, 0.0, 0.0), description="the simulated arm's joints at start, deg (the plans start "
        "from [planning] arm_start_deg)")
    install_error_mm: float = Field(2.0, ge=0, description="1-sigma per axis of true vs nominal mounts")
    install_error_deg: float = Field(0.3, ge=0, description="1-sigma per axis of true vs nominal mounts")
    time_scale: float = Field(0.0, ge=0, description="simulated motion time x this = wall time; 0 = instant")
    fault_scanner_timeout_every: int = Field(0, ge=0, description="every n-th capture times out; 0 = never")
    fault_estop_after_moves: int = Field(0, ge=0, description="e-stop after n chassis moves; 0 = never")
    fault_arm_after_moves: int = Field(0, ge=0, description="the n-th arm move and every later one fail with a servo "
                                                            "fault; 0 = never")
    fault_tracker_after_frames: int = Field(0, ge=0, description="after n tracker frames the tracker stops answering "
                                                                 "(every reading times out); 0 = never")
    as_built: AsBuiltConfig = AsBuiltConfig()
    reference_spheres: bool = Field(
        False, description="the fixture carries the reference spheres of [inspection] (at their CAD centres)"
    )


class HilConfig(_Strict):
    """Hardware-in-the-loop: run the protocol emulators, backed by the simulated world, in the daemon's process
    so that the ``driver = "real"`` devices talk to them over real transports (127.0.0.1, virtual CAN)."""

    enabled: bool = False
    arm_time_scale: float = Field(0.01, ge=0, description="emulated arm: wall s per simulated s; 0 = instant")
    chassis_time_scale: float = Field(0.05, gt=0, description="emulated chassis: wall s per simulated s")
    tracker_rate_hz: float = Field(60.0, gt=0)
    # how closely the emulators follow the vendors' behaviour (docs/drivers.md); the defaults are forgiving
    arm_power_on_delay_s: float = Field(0.0, ge=0, description="power_on completes this long after its reply")
    arm_enable_delay_s: float = Field(0.0, ge=0, description="enable_robot completes this long after its reply")
    arm_segment_bytes: int = Field(0, ge=0, description="replies and status cut into TCP segments this size; 0 = whole")
    arm_numeric_error_codes: bool = Field(False, description="errorCode as a number instead of a string")
    arm_status_bytes: int = Field(0, ge=0, description="status objects padded to about this size (real: 5-9 kB)")
    chassis_driver_state_flags: int = Field(0, ge=0, le=0xC0, description="motor DriverState in normal running "
                                                                             "(0x40 driver enabled)")
    chassis_odometry_start_counts: int = Field(
        0, ge=-(1 << 31), lt=1 << 31,
        description="the 0x311 odometry counters at boot (raw int32; near 2^31 they wrap soon)")
    tracker_requires_start: bool = Field(False, description="the stream starts only after tracker.stream.start_command")

    @field_validator("chassis_driver_state_flags")
    @classmethod
    def _state_flags_only(cls, v: int) -> int:
        if v & 0x3F:
            raise ValueError("only the state flags 0x40 (driver enabled) and 0x80 (driver reset); 0x01 (supply "
                             "voltage low) is a warning and 0x02-0x20 are faults, not normal running")
        return v



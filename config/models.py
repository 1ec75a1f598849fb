"""Pydantic models of the cell configuration.

Units: millimetres, radians inside. Where a TOML key is a human-facing angle it says so in its name
(``*_deg``) and the model converts it. Every field has a default that runs the simulated cell.
"""

from __future__ import annotations

import math
import tomllib
from functools import cache
from importlib import resources
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, SerializeAsAny, ValidationError, field_validator, model_validator
from pydantic_core import InitErrorDetails
from tandemscan.config.device_registry import (
    BUILT_IN_DRIVERS,
    DriverKind,
    plugin_settings_model,
    simulator_settings_model,
)

OutputKind = Literal["coil", "holding_register"]


class _Strict(BaseModel):
    """Base: unknown keys are errors, so a typo in a TOML file is reported, not ignored."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class DeviceSection(_Strict):
    """A device role's section: its ``driver`` and, for a plugin's driver, the plugin's own settings.

    ``driver = "sim"`` (the simulator's twin) or ``"real"`` (the built-in vendor's driver, its settings in the
    section's own tables), or the name a plugin registered for the role (:mod:`tandemscan.config.device_registry`): its
    ``[<role>.<driver>]`` table is validated by the plugin's ``Settings`` model into ``settings``
    (docs/howto/add-a-device-driver.md)."""

    #: the roles whose sections this model is (a plugin's driver is looked up for them)
    ROLES: ClassVar[tuple[str, ...]]

    driver: DriverKind = "sim"
    settings: SerializeAsAny[BaseModel] | None = Field(None, description="a plugin's driver: its own settings")

    @model_validator(mode="before")
    @classmethod
    def _plugin_settings(cls, data: object) -> object:
        """Validate a plugin driver's ``[<role>.<driver>]`` table by the plugin's model into ``settings``."""
        if not isinstance(data, dict) or data.get("driver", "sim") in BUILT_IN_DRIVERS:
            return data
        driver = data["driver"]
        if driver in cls.model_fields:
            raise ValueError(f"driver {driver!r} is the name of a key of the section; a plugin needs another name")
        data = dict(data)
        raw = data.pop(driver, data.get("settings") or {})
        model = plugin_settings_model(cls.ROLES, driver)
        try:
            data["settings"] = model.model_validate(raw)
        except ValidationError as e:  # the errors at [<role>.<driver>.key], not at the section's keys
            raise ValidationError.from_exception_data(e.title, [InitErrorDetails(
                type=err["type"], loc=(driver, *err["loc"]), input=err["input"], ctx=err.get("ctx", {}))
                for err in e.errors()]) from e
        return data

    @model_validator(mode="after")
    def _settings_only_for_a_plugin(self) -> DeviceSection:
        if self.driver in BUILT_IN_DRIVERS and self.settings is not None:
            raise ValueError(f"settings are a plugin driver's; driver {self.driver!r} takes the section's own keys")
        return self


class TransformConfig(_Strict):
    """A rigid transform ``T_a_b``: translation in mm and roll-pitch-yaw in degrees (fixed axes x, y, z)."""

    xyz_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """The 4x4 float64 matrix (mm)."""
        from scipy.spatial.transform import Rotation  # here, not at import: SciPy's spatial package is ~0.3 s

        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", np.radians(self.rpy_deg)).as_matrix()  # fixed axes x-y-z
        T[:3, 3] = self.xyz_mm
        return T


class OpeningConfig(_Strict):
    """A rectangular recessed opening (a hatch) cut into the part's surface: centred at ``centre_mm`` (frame F,
    near the surface), ``half_u_mm`` along ``u_axis`` and ``half_v_mm`` along ``v_axis`` (both in the surface),
    its walls dropping at 45 deg to ``depth_mm`` below the surface (docs/inspection.md, "Openings").
    ``edge_offsets_mm`` move its four edges (-u, +u, -v, +v) outward, the opening larger: an as-built part's."""

    name: str = Field(min_length=1)
    centre_mm: tuple[float, float, float]
    u_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    v_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    half_u_mm: float = Field(gt=0)
    half_v_mm: float = Field(gt=0)
    depth_mm: float = Field(10.0, gt=0)
    edge_offsets_mm: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


class PartConfig(_Strict):
    """The measured part: a CAD mesh file, or the parametric train nose when ``mesh`` is empty; with
    ``openings`` cut into either."""

    mesh: Path | None = None
    mesh_units: Literal["mm", "cm", "m", "in"] = Field(
        "mm", description="the unit of the mesh file's coordinates, read into millimetres (--part-units)")
    length_mm: float = Field(3000.0, gt=0)
    width_mm: float = Field(2000.0, gt=0)
    height_mm: float = Field(1600.0, gt=0)
    body_length_mm: float = Field(1000.0, ge=0, description="constant-section length before the nose, mm")
    openings: tuple[OpeningConfig, ...] = ()


class PhoxiConfig(_Strict):
    """Real PhoXi over harvesters + a GenTL producer (``driver = "real"``)."""

    producer_path: Path | None = Field(None, description="GenTL producer (.cti), e.g. PhoXi Control's photoneo.cti")
    interface: Literal["photoneo_gentl", "gige_vision"] = "photoneo_gentl"
    serial_number: str = Field("", description="the scanner to open: its serial number, its ID (with or without "
                               "PhoXi Control's PhotoneoTL_DEV_ prefix) or its user-defined name; empty = the first "
                               "device found")
    harvesters_module: str = Field(
        "harvesters.core", description="module providing Harvester (the fake one for hardware-in-the-loop runs)"
    )
    range_pixel_format: str = Field("Coord3D_ABC32f", description="gige_vision: PixelFormat of Range (XYZ mm)")
    normal_pixel_format: str = Field("Coord3D_ABC32f", description="gige_vision: PixelFormat of Normal")
    confidence_pixel_format: str = Field("Confidence8", description="gige_vision: PixelFormat of Confidence")
    normals_estimation_radius: int = Field(
        2, ge=1, description="gige_vision: NormalsEstimationRadius, pixels (0 would send no normals)")
    confidence_best: float | None = Field(
        None, gt=0, description="raw confidence of the best pixel, mapped to 1 (0 stays invalid); empty = 255 "
                                "for gige_vision (Confidence8), 1 for photoneo_gentl (unverified)")


class ScannerConfig(DeviceSection):
    """PhoXi 3D Scanner S: working range along the optical axis (mm), field of view and noise."""

    ROLES = ("scanner",)
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
    phoxi: PhoxiConfig = PhoxiConfig()

    @property
    def pixels(self) -> tuple[int, int]:
        """(columns, rows) of the active resolution."""
        return self.full_pixels if self.resolution == "full" else self.coarse_pixels


class TrackerStreamConfig(_Strict):
    """Real tracker pose stream (``driver = "real"``): transport, framing, record layout and commands.

    ``transport``: TCP ``host:port`` (the tracker's), a serial device, or UDP datagrams arriving on the local
    ``host:port`` (ART DTrack style). ``framing``: one text line per frame, or a length prefix before each
    frame. ``record``: comma-separated text fields, or a packed binary record of the same ``fields``.
    ``start_command`` is sent once after connecting (NDI ``TSTART``), ``poll_command`` before every reading
    (NDI ``BX``). See docs/drivers.md.
    """

    transport: Literal["tcp", "serial", "udp"] = "tcp"
    host: str = "127.0.0.1"
    port: int = Field(8765, ge=0, le=65535)
    serial_device: str = "/dev/ttyUSB0"
    baudrate: int = Field(115200, gt=0)
    framing: Literal["line", "length_prefixed"] = "line"
    length_prefix: Literal["u16le", "u16be", "u32le", "u32be"] = Field(
        "u32le", description="length_prefixed: the prefix, counting the record's bytes after it")
    record: Literal["text", "binary"] = "text"
    binary_byte_order: Literal["little", "big"] = "little"
    start_marker: str = Field("$POSE", description="text records: the first field of every frame")
    fields: tuple[str, ...] = (
        "frame", "device_time_s", "status", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw",
        "sx_mm", "sy_mm", "sz_mm", "srx_rad", "sry_rad", "srz_rad",
    )
    checksum: bool = True
    start_command: str = Field("", description="sent once after connecting (tcp, serial), e.g. \"TSTART\\r\"")
    poll_command: str = Field("", description="sent before every reading (tcp, serial), e.g. \"BX 0801\\r\"")

    @model_validator(mode="after")
    def _commands_need_a_stream(self) -> TrackerStreamConfig:
        if (self.start_command or self.poll_command) and self.transport == "udp":
            raise ValueError("start_command / poll_command need transport tcp or serial")
        return self


class TrackerConfig(DeviceSection):
    """Metronor optical tracker: field of view, range, how readings at rest are averaged. The simulated tracker's
    noise is a simulation setting (``[sim.tracker_noise]``, :class:`~tandemscan.sim_drivers.config.TrackerNoiseConfig`);
    a real tracker reports each reading's covariance itself."""

    ROLES = ("tracker",)
    range_max_mm: float = 30000.0
    fov_horizontal_deg: float = 70.0
    fov_vertical_deg: float = 55.0
    target_view_cone_deg: float = Field(80.0, description="target visible while its normal is this close to the camera")
    samples_per_reading: int = Field(1, ge=1, description="readings averaged at rest per pose")
    transfer_samples: int = Field(
        30, ge=1, description="readings averaged at rest on each side of a coordinate transfer (Eq. 2): its error "
                              "is carried to every later scan, and 30 frames are 0.5 s at the tracker's 60 Hz "
                              "while the target stands still anyway (the tracking AGV drives for tens of seconds)")
    transfer_arm_poses: int = Field(
        1, ge=1, description="arm poses the still target is read at on each side of a coordinate transfer (the same "
                             "joints replayed after the tracker moved): the new station follows from the target "
                             "positions over the arm's reach, not one target's orientation; 1 = the target where "
                             "the arm stands (docs/architecture.md, \"Coordinate transfers\")")
    transfer_arm_reach_mm: float = Field(
        300.0, gt=0, description="how far (mm) the extra arm poses of a transfer move the scanner across its view "
                                 "from the transfer's own pose (a square around it), besides the plan's scan poses "
                                 "there")
    still_noise_fraction: float = Field(
        0.5, ge=0, le=1, description="share of one reading's noise variance that every reading of one still period "
                                     "shares (air turbulence, refraction, the camera's calibration residual where "
                                     "the target sits in the image): averaging does not reduce it; the simulated "
                                     "tracker draws it so, the averaged reading's covariance counts it")
    timeout_s: float = 5.0
    scan_read_retries: int = Field(
        4, ge=0, description="a scan whose target the tracker cannot see is read again this many times, "
                             "scan_read_retry_s apart, before it is left out (a person or a cart passing through "
                             "the sight line); 0 = left out at once")
    scan_read_retry_s: float = Field(1.0, gt=0, description="seconds between the reads of a scan's hidden target")
    stream: TrackerStreamConfig = TrackerStreamConfig()


class JakaTcpConfig(_Strict):
    """Real JAKA controller (``driver = "real"``): command and status ports, motion speeds at the edge."""

    host: str = "10.5.5.100"
    command_port: int = Field(10001, ge=0, le=65535)
    status_port: int = Field(10000, ge=0, le=65535)
    reply_timeout_s: float = Field(3.0, gt=0)
    joint_accel_deg_s2: float = Field(180.0, gt=0, le=720.0)
    linear_speed_mm_s: float = Field(100.0, gt=0)
    linear_accel_mm_s2: float = Field(500.0, gt=0)
    inpos_tolerance_deg: float = Field(0.05, gt=0, description="joint target reached when all joints are this "
                                       "close; a linear target when the flange's orientation is this close too")
    inpos_tolerance_mm: float = Field(0.2, gt=0, description="linear target reached when this close")
    status_gap_timeout_s: float = Field(
        0.3, gt=0, description="no status message for this long while waiting on the stream = link lost; "
                               "4 push periods instead where the controller pushes slower (timed at connect)")
    power_on_timeout_s: float = Field(15.0, gt=0, description="power_on is asynchronous: wait this long for it")
    enable_timeout_s: float = Field(15.0, gt=0, description="enable_robot is asynchronous: wait this long for it")
    state_poll_period_s: float = Field(0.1, gt=0, description="get_robot_state polling period while waiting")


class ArmRepeatabilityConfig(_Strict):
    """How far the same joints land the flange from where they landed it before (an arm's pose repeatability,
    ISO 9283 RP, as the vendor states it: JAKA Zu 3/5/7 +-0.02 mm, Zu 12/18/20 +-0.03 mm), and its orientation
    share (no vendor figure). A coordinate transfer over several arm poses (``[tracker] transfer_arm_poses``)
    replays the same joints on both sides; this is the error of that replay (absolute accuracy cancels)."""

    pose_mm: float = Field(0.03, ge=0, description="ISO 9283 pose repeatability RP (+-mm): the distance from the "
                                                   "mean pose stays within it at 3 sigma")
    angle_deg: float = Field(0.003, ge=0, description="1-sigma per axis of the flange's orientation offset per "
                                                      "move (the wrist joints' share of RP 150 mm out)")

    def sigma(self) -> tuple[float, float]:
        """1-sigma per axis of one move's flange offset: (translation mm, rotation rad). For an isotropic normal
        offset of sigma s per axis, mean distance + 3 sigma of the distance is about 3.6 s (ISO 9283's RP)."""
        return self.pose_mm / 3.6, math.radians(self.angle_deg)


_ARM_MODEL_KEYS = ("dh_d_mm", "dh_a_mm", "joint_min_deg", "joint_max_deg")


@cache
def arm_models() -> dict[str, dict]:
    """The arm models of ``config/arm_models.toml`` by name: DH (mm), joint limits (deg), whether checked."""
    text = resources.files("tandemscan.config").joinpath("arm_models.toml").read_text(encoding="utf-8")
    return tomllib.loads(text)


class ArmConfig(DeviceSection):
    """The arm (JAKA Zu 7 by default): standard DH parameters (mm, rad) and joint limits (deg at this edge).

    ``model`` names an entry of ``config/arm_models.toml`` (zu7, zu12, zu18, zu20); its DH and limits fill the keys
    this section leaves out (docs/planning.md, "Arm models and the lifting column")."""

    ROLES = ("arm",)
    model: str = Field("zu7", description="arm model of config/arm_models.toml whose DH and limits are the defaults")
    # Standard DH of the Zu 7 (docs/planning.md, arm models: a public JAKA client cross-checked with
    # JAKA's ROS 2 URDF). Alpha signs differ between sources; this is the UR-style reading.
    dh_d_mm: tuple[float, ...] = (120.15, 0.0, 0.0, 115.01, 113.5, 107.0)
    dh_a_mm: tuple[float, ...] = (0.0, 360.0, 303.5, 0.0, 0.0, 0.0)
    dh_alpha_rad: tuple[float, ...] = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
    joint_min_deg: tuple[float, ...] = (-360.0, -85.0, -175.0, -85.0, -360.0, -360.0)
    joint_max_deg: tuple[float, ...] = (360.0, 265.0, 175.0, 265.0, 360.0, 360.0)
    joint_speed_deg_s: float = Field(60.0, gt=0)
    timeout_s: float = 60.0
    repeatability: ArmRepeatabilityConfig = Field(
        ArmRepeatabilityConfig(), description="what a coordinate transfer over several arm poses assumes of the "
                                              "arm's repeatability (its covariance)")
    jaka: JakaTcpConfig = JakaTcpConfig()

    @field_validator("dh_d_mm", "dh_a_mm", "dh_alpha_rad", "joint_min_deg", "joint_max_deg")
    @classmethod
    def _six(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) != 6:
            raise ValueError(f"needs 6 values, got {len(v)}")
        return v

    @model_validator(mode="before")
    @classmethod
    def _model_defaults(cls, data: object) -> object:
        """Fill the DH and limit keys left out from the named model's entry."""
        if not isinstance(data, dict):
            return data
        name = data.get("model", "zu7")
        models = arm_models()
        if name not in models:
            raise ValueError(f"unknown arm model {name!r} (known: {', '.join(sorted(models))})")
        return {**{k: tuple(models[name][k]) for k in _ARM_MODEL_KEYS}, **data}


class LiftConfig(DeviceSection):
    """An optional lifting column on the measurement AGV: a vertical axis that raises the arm base by
    ``height_mm`` above its mount ``T_V2_B`` (mm, mm/s). The planner sets its height per AGV station."""

    enabled: bool = False
    ROLES = ("lift",)
    min_mm: float = Field(0.0, ge=0, description="lowest column height above the mount, mm")
    max_mm: float = Field(0.0, ge=0, description="highest column height above the mount, mm")
    speed_mm_s: float = Field(50.0, gt=0)
    planning_step_mm: float = Field(250.0, gt=0, description="spacing of the heights the planner tries, mm")
    timeout_s: float = Field(60.0, gt=0)

    @model_validator(mode="after")
    def _range(self) -> LiftConfig:
        if self.max_mm < self.min_mm:
            raise ValueError(f"max_mm = {self.max_mm} is below min_mm = {self.min_mm}")
        return self

    def heights_mm(self) -> tuple[float, ...]:
        """The column heights the planner tries, lowest first (mm); the mount alone when there is no column."""
        if not self.enabled:
            return (0.0,)
        count = int(math.ceil((self.max_mm - self.min_mm) / self.planning_step_mm - 1e-9)) + 1
        return tuple(float(h) for h in np.linspace(self.min_mm, self.max_mm, max(count, 1)))


class ChassisCanConfig(_Strict):
    """Real chassis on CAN (``driver = "real"``): python-can bus, the DBC, and the closed-loop move gains."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = Field(500000, gt=0)
    dbc: Path | None = Field(None, description="CAN database; empty = the shipped AgileX-Scout-style v2 DBC")
    command_period_s: float = Field(0.02, gt=0, description="motion command period (protocol: 20 ms)")
    feedback_timeout_s: float = Field(0.5, gt=0, description="no status frame for this long = link lost")
    odometry_track_mm: float = Field(582.0, gt=0, description="effective skid-steer track for wheel odometry")
    odometry_mm_per_count: float = Field(
        1.0, gt=0, description="wheel travel per unit of the 0x311 odometry int32 (ugv_sdk passes the raw value; "
                               "mm on the chassis documented so far, unverified per model)")
    odometry_start_x_mm: float = Field(0.0, description="surveyed pose (floor frame F) the odometry starts from")
    odometry_start_y_mm: float = 0.0
    odometry_start_heading_deg: float = 0.0
    position_tolerance_mm: float = Field(5.0, gt=0, description="arrived when the odometry is this close, mm")
    approach_deadband_mm: float = Field(
        0.5, gt=0, description="final approach along the heading ends this close to the target (or when past it)")
    heading_tolerance_deg: float = Field(0.5, gt=0)
    standstill_mm_s: float = Field(
        1.0, ge=0, description="at rest when the motion state's linear speed is at most this, mm/s (its resolution: "
        "a chassis may report a count of encoder noise at standstill)")
    standstill_deg_s: float = Field(
        0.06, ge=0, description="and its angular speed at most this, deg/s (the 0.001 rad/s resolution)")
    gain_linear_per_s: float = Field(1.5, gt=0, description="linear speed = gain x distance error")
    gain_angular_per_s: float = Field(2.0, gt=0, description="angular speed = gain x heading error")


class ChassisConfig(DeviceSection):
    """An AGV chassis (skid steering): driver and speeds. How the simulated chassis slips is a simulation setting
    (``[sim.measure_chassis_slip]``, ``[sim.tracking_chassis_slip]``,
    :class:`~tandemscan.sim_drivers.config.ChassisSlipConfig`)."""

    ROLES = ("measure_chassis", "tracking_chassis")
    speed_mm_s: float = Field(300.0, gt=0)
    turn_rate_deg_s: float = Field(20.0, gt=0)
    timeout_s: float = 120.0
    can: ChassisCanConfig = ChassisCanConfig()


class SafetyModbusConfig(_Strict):
    """Real safety I/O on Modbus TCP (``driver = "real"``): addresses are wire addresses (0-based).

    Inputs are discrete inputs, true = tripped (``*_active_high = false`` inverts a normally-closed wiring).
    Outputs (target light, beacon) are coils of an I/O module, or holding registers of a stack light
    (PATLITE-style: one register per tier, ``*_on_value`` written for on, 0 for off).
    """

    host: str = "192.168.127.254"
    port: int = Field(502, ge=0, le=65535)
    device_id: int = Field(1, ge=0, le=255)
    estop_input: int = Field(0, ge=0)
    estop_active_high: bool = True
    light_curtain_input: int = Field(1, ge=0)
    light_curtain_active_high: bool = True
    target_light_coil: int = Field(0, ge=0, description="wire address of the target light's coil or register")
    target_light_output: OutputKind = "coil"
    target_light_on_value: int = Field(1, ge=1, le=0xFFFF, description="register value for on (registers only)")
    beacon_coil: int = Field(1, ge=0, description="wire address of the beacon's coil or register")
    beacon_output: OutputKind = "coil"
    beacon_on_value: int = Field(1, ge=1, le=0xFFFF, description="register value for on (registers only)")
    timeout_s: float = Field(1.0, gt=0)


class SafetyConfig(DeviceSection):
    """Cell safety I/O (e-stop, light curtain, target light)."""

    ROLES = ("safety",)
    poll_period_s: float = Field(0.02, gt=0)
    silent_after_periods: float = Field(2.0, ge=1, description="a Modbus poll unanswered this many poll periods "
                                        "is a safety stop (a silent module), long before the request's timeout")
    modbus: SafetyModbusConfig = SafetyModbusConfig()


class InstallationConfig(_Strict):
    """Nominal (CAD) installation transforms; the pipeline only ever uses calibrated estimates of them.

    Frames (docs/architecture.md, "Frames"): ``V1`` tracking chassis, ``C`` tracker camera (z along the optical axis,
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


class PlanningConfig(_Strict):
    """Motion planning (docs/planning.md, paper Eq. 13-18). Floor polygons are in the part frame F, mm.

    Measurement AGV: centre ``distance in (d3 + w/2, d4 + w/2)`` from the part's floor contour, ``step in
    (p, p + m)`` along it, with ``m`` the scan footprint width less the overlap. Tracker: candidate stations
    at ``d1`` from the contour; a measuring point is covered within ``d2`` and the field of view.
    """

    agv_width_mm: float = Field(800.0, gt=0, description="w: measurement AGV width, mm")
    arm_standoff_min_mm: float = Field(300.0, ge=0, description="d3: AGV side to part contour, least, mm")
    arm_standoff_max_mm: float = Field(500.0, gt=0, description="d4: AGV side to part contour, most, mm")
    station_step_mm: float = Field(600.0, gt=0, description="p: least step between AGV stations, mm")
    scan_overlap_fraction: float = Field(0.2, ge=0, lt=1, description="overlap of neighbouring scans")
    incidence_limit_deg: float = Field(45.0, ge=0, lt=90, description="most tilt of the view off the normal")
    agv_margin_mm: float = Field(
        60.0, ge=0, description="prefer scan poses still reachable with the AGV this far off its station (drift)"
    )
    agv_margin_deg: float = Field(1.0, ge=0, description="and turned this much off its heading")
    tracker_distance_mm: float = Field(3500.0, gt=0, description="d1: tracker candidates to part contour, mm")
    tracker_best_range_mm: float = Field(9000.0, gt=0, description="d2: best-accuracy tracker range, mm")
    tracker_min_range_mm: float = Field(1500.0, ge=0, description="nearest usable target distance, mm")
    tracker_candidate_step_mm: float = Field(700.0, gt=0, description="spacing of tracker candidates, mm")
    tracker_heading_offsets_deg: tuple[float, ...] = (-30.0, -15.0, 0.0, 15.0, 30.0)
    tracker_margin_deg: float = Field(3.0, ge=0, description="kept off the edges of the field of view and cone")
    exact_time_limit_s: float = Field(2.0, gt=0, description="integer-program time limit, s")
    exact_max_variables: int = Field(6000, gt=0, description="larger tracker instances go to the heuristic")
    floor_xy_mm: tuple[float, float, float, float] = Field(
        (-20000.0, -12000.0, 20000.0, 12000.0), description="cell floor rectangle: x min, y min, x max, y max"
    )
    keep_out_xy_mm: tuple[tuple[tuple[float, float], ...], ...] = Field(
        (), description="floor polygons no robot may stand in, each a list of (x, y) mm"
    )
    tracker_start: FloorPoseConfig = Field(
        FloorPoseConfig(x_mm=-1400.0, y_mm=4600.0, heading_deg=-90.0), description="where the tracking robot "
        "stands when a job begins (F): the tracker chain starts there where it sees a measuring point (the "
        "simulated robot starts at [sim] tracking_start)")
    arm_start_deg: tuple[float, ...] = Field(
        (0.0, 90.0, 0.0, 90.0, 0.0, 0.0), description="the arm's joints (deg) where a job starts: the first "
        "station's IK starts from them (the simulated arm rests at [sim] arm_home_deg)")

    @field_validator("arm_start_deg")
    @classmethod
    def _six_joints(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) != 6:
            raise ValueError(f"needs 6 values, got {len(v)}")
        return v


class JobConfig(_Strict):
    """Measurement job settings."""

    out_dir: Path = Path("out")
    voxel_mm: float = Field(1.0, gt=0, description="world map voxel edge, mm")
    installation_source: Literal["nominal", "calibration", "current"] = Field(
        "nominal", description="which mounts (T_T_S etc.) the stitch uses: the CAD nominal ones ([installation]), "
        "those of calibration_file (`tandemscan calibrate`, what `make measure` uses), or the cell's current "
        "calibration ([calibration] output_file, where it was made for this cell configuration and has not expired; "
        "else nominal)"
    )
    calibration_file: Path | None = None
    part_number: str | None = Field(
        None, min_length=1, max_length=200, description="the measured part's number (a job's request); empty: "
        "the inspection template's")
    serial: str | None = Field(None, min_length=1, max_length=200,
                               description="the measured part's serial number (a job's request, `--serial`)")
    resume_pose_tolerance_mm: float = Field(
        20.0, gt=0, description="a resumed job finds an AGV whose odometry is this far (mm) from where its journal "
        "left it moved or re-started: the tracker tells which and it is re-localised, or the operator decides")
    resume_pose_tolerance_deg: float = Field(1.0, gt=0, description="the same for the AGV's heading (deg)")
    resume_joint_tolerance_deg: float = Field(
        0.1, gt=0, description="a resumed job finds the arm off the joints its journal left it at when a joint is "
        "this far (deg) from them (a move cut short, a jogged arm): the arm moves back before the job goes on")
    max_scans_left_out: int | None = Field(
        3, ge=0, description="a daemon job that would leave out more scans than this (the tracker cannot see the "
        "target after its retries) pauses for the operator instead (paused_fault); resuming leaves that scan out "
        "and goes on; none = no limit. A job that left out scans ends succeeded_with_gaps")
    relocalise: bool = Field(
        True, description="place W in the plan's frame F from one target reading at the start (the inspection's "
        "registration to CAD) and, after each measurement-AGV drive, measure where it stands (tracker, Eq. 5) and "
        "re-solve the arm for the plan's scanner poses (T_F_S); off = the plan's joint targets as they are, no "
        "in-job inspection"
    )


class CorrectionConfig(_Strict):
    """Whole-job stitching correction (docs/registration.md): which pairs, the pair registration method, the
    fine ICP, the pose-graph edges and the shared scanner-mount unknown."""

    enabled: bool = True
    method: Literal["icp", "auto", "fpfh+icp", "deepmerge", "deepmerge+icp"] = Field(
        "icp", description="icp: the tracker stitch is finer than any global stage (docs/registration.md); auto: "
        "the fine stage and FPFH + RANSAC, the network too where they disagree, the best verified fit kept"
    )
    overlap_delta_mm: float | None = Field(
        None, gt=0, description="overlap = points whose nearest neighbour is closer; empty = from tracker covariance"
    )
    overlap_sigmas: float = Field(3.0, gt=0, description="delta = this many sigmas of the pair's pose uncertainty")
    overlap_min_delta_mm: float = Field(1.0, gt=0, description="lower bound of delta (point spacing and noise), mm")
    min_overlap_points: int = Field(200, ge=10, description="pairs with fewer overlap points get no edge")
    pair_cell_mm: float = Field(10.0, gt=0, description="grid cell (mm) by which scans are found to overlap")
    max_partners_per_scan: int = Field(
        6, ge=1, description="each scan is registered with at most this many scans of its own tracker station "
        "and as many of the others, those sharing the most grid cells with it, for the pose graph (joint off); "
        "the report's overlap RMS is taken on these pairs either way"
    )
    check_partners_per_scan: int = Field(
        1, ge=0, description="with joint (which starts from the tracker poses and takes no pose from the pairs): "
        "each scan is registered as a check (the report's correction.pairs, pairs_dropped, stages) with this many "
        "best-overlap scans of its own tracker station and as many of the others (the transfer links); 0 = none "
        "(docs/correction.md, Which pairs are registered)"
    )
    icp_max_points: int = Field(8000, ge=100, description="overlaps are thinned evenly to this many points per cloud")
    icp_max_distance_mm: float = Field(2.0, gt=0, description="point-to-plane ICP correspondence distance, mm")
    icp_iterations: int = Field(50, ge=1, description="ICP iterations per level of the coarse-to-fine schedule")
    job_pair_iterations: int = Field(
        5, ge=1, description="the same for the job's pairs (from the tracker stitch): later iterations only slid "
        "along smooth overlaps, the pose error no lower at 50 (docs/compute.md, benchmarks/pair_kernel.py)")
    global_voxel_fraction: float = Field(
        0.02, gt=0, lt=1, description="FPFH + RANSAC voxel edge, share of the target's bounding-box diagonal"
    )
    ransac_max_iterations: int = Field(100_000, ge=1, description="RANSAC draws of the FPFH global stage")
    ransac_confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC stops early at this confidence")
    global_fine_start_mm: float = Field(
        5.0, gt=0, description="correspondence distance at which the fine stage starts after a global stage, mm"
    )
    agreement_deg: float = Field(
        0.5, gt=0, description="auto: the fine stage and FPFH + RANSAC agree within this rotation, deg ..."
    )
    agreement_mm: float = Field(1.0, gt=0, description="... and this translation at the source's centroid, mm")
    max_cost_increase: float = Field(
        0.01, ge=0, lt=1, description="a result whose truncated point-to-plane cost exceeds the start's by more "
        "than this share of the final distance squared is refused: as if that share of the points had slid out "
        "of reach (a fit that slides along a smooth overlap moves a few boundary points that far)"
    )
    register_min_fitness: float = Field(
        0.1, ge=0, le=1, description="tandemscan register refuses a result with a smaller share of the source "
        "within the final correspondence distance"
    )
    register_max_rms_share: float = Field(
        0.25, gt=0, le=1, description="... or a point-to-plane RMS above this share of that distance (residuals "
        "spread evenly over the gate give 0.58; a fit gives the noise)"
    )
    edge_effective_points: float = Field(
        1000.0, gt=0, description="independent points an overlap is worth when weighting a pose-graph edge"
    )
    edge_min_eigen_ratio: float = Field(
        0.01, ge=0, lt=1, description="edge directions weaker than this share of the strongest are dropped"
    )
    joint: bool = Field(
        True, description="after the pairwise stage, refine all poses, transfers and the mount jointly on the overlap "
        "points (docs/correction.md, Joint refinement); off: the pose graph of the pairs gives the poses"
    )
    joint_voxel_mm: float = Field(2.0, gt=0,
                                  description="the joint refinement works on scans thinned to this voxel, mm")
    joint_max_distance_mm: float = Field(
        1.0, gt=0, description="joint refinement: a point's nearest neighbour in the other scan counts within this, mm"
    )
    joint_iterations: int = Field(
        2, ge=1, description="joint refinement: linearisations, the first on the correspondences found at the "
        "tracker poses, each later one at the poses so far (re-weighted there, and with joint_reassociate_mm "
        "associated anew); docs/correction.md, What the measurements showed")
    joint_reassociate_mm: float | None = Field(
        0.02, gt=0, description="joint refinement: before a linearisation after the first, a pair whose points moved "
        "more than this against its partner since its correspondences were found has them found anew, mm (the "
        "default, under half the scanner's noise, finds nearly every pair anew); empty = never "
        "(docs/correction.md, What the measurements showed)")
    joint_sigma_mm: float | None = Field(
        None, gt=0, description="joint refinement: 1-sigma of a point-to-plane residual between two single points "
        "seen head-on, mm (also the Huber cut's unit); empty = the robust scale of the residuals whitened by their "
        "relative variance, in each linearisation"
    )
    joint_max_partners_per_scan: int = Field(
        1000, ge=1, description="joint refinement: overlapping partners a scan keeps per station group (as "
        "max_partners_per_scan; the default keeps every pair sharing a grid cell)"
    )
    estimate_mount: bool = Field(
        True, description="the pose graph also estimates one shared correction of T_T_S (self-calibration)"
    )
    mount_nominal_sigma_mm: float = Field(
        2.0, gt=0, description="1-sigma per axis of the CAD nominal T_T_S (build tolerance), mm: the mount "
        "prior when the job stitches with nominal mounts"
    )
    mount_nominal_sigma_deg: float = Field(0.3, gt=0, description="the same for its rotation, deg per axis")
    mount_min_information_ratio: float = Field(
        1.0, ge=0, description="a direction of the T_T_S correction is estimated only where the overlaps give "
        "at least this times the prior's information; the others stay at the prior"
    )


class ComputeConfig(_Strict):
    """Where the end of a job's per-unit work runs (docs/compute.md): this PC's threads, or a Dask cluster whose
    workers read the job's scans by reference from ``scan_store``."""

    backend: Literal["local", "dask"] = Field(
        "local", description="local: threads of this PC; dask: the pair stage as Dask tasks (docs/compute.md)")
    scheduler: str = Field(
        "", description="dask: a scheduler address (tcp://host:8786); empty = a LocalCluster of dask_workers")
    dask_workers: int = Field(2, ge=1, description="dask with no scheduler: processes of the LocalCluster")
    scan_store: Path | None = Field(
        None, description="the folder the workers read the job's scans from (a shared filesystem); empty = the "
        "job folder")
    retries: int = Field(3, ge=0, description="dask: times a task lost with its worker is run again")
    tile_mm: float = Field(
        0.0, ge=0, description="the end of a job merges its cloud by slabs of W this wide (mm) on the backend, "
        "each unit reading only its scans (docs/compute.md, Tiles); 0 = in one process, as one map")
    report_points: int = Field(
        1_000_000, ge=1000, description="with tile_mm: the report's alignment, U and maps from every k-th "
        "voxel up to this many in the process that writes it; its deviation areas (and the verdict on them), "
        "figures, cloud_deviation.ply and (in their regions) characteristics and close-ups from every point, tile "
        "by tile on the backend (docs/compute.md, Tiles)")

    def store_of(self, job_dir: Path) -> Path:
        """The folder the end of the job in ``job_dir`` reads its scans from and keeps its scratch files in
        (``joint/``, ``tiles/``): ``scan_store``, or the job folder where it is empty."""
        return Path(self.scan_store or job_dir)

    @property
    def reads_scan_store(self) -> bool:
        """Whether the end of a job reads every scan from ``scan_store`` on the backend's workers (not ``local``):
        then the job's map process keeps no scan's thinned copy, only its stitch-view points (docs/compute.md)."""
        return self.backend != "local"


class DeepMergeConfig(_Strict):
    """The DeepMerge registration network (docs/deepmerge.md): its weights and inference size."""

    weights: Path | None = Field(None, description="trained weights (.pt); empty = the ones shipped in the package")
    num_points: int = Field(2048, ge=64, description="overlap points per cloud fed to the network")
    neighbours: int = Field(10, ge=4, description="k of the k x 14 point structure")
    rounds: int = Field(
        4, ge=1, description="re-embedding rounds: the source moved by the estimate so far and embedded afresh"
    )


class RegionConfig(_Strict):
    """A named inspection region: an axis-aligned box in the CAD/part frame F (mm), bounds inclusive."""

    name: str = Field(min_length=1)
    min_mm: tuple[float, float, float]
    max_mm: tuple[float, float, float]

    @field_validator("max_mm")
    @classmethod
    def _ordered(cls, v: tuple[float, float, float], info) -> tuple[float, float, float]:
        lo = info.data.get("min_mm")
        if lo is not None and any(b < a for a, b in zip(lo, v, strict=True)):
            raise ValueError(f"max_mm {v} must be >= min_mm {lo} on every axis")
        return v


class ReferenceSphereConfig(_Strict):
    """A reference sphere of the part or its fixture: a name and its calibrated centre in the CAD frame F, mm."""

    name: str = Field(min_length=1)
    centre_mm: tuple[float, float, float]


_DEFAULT_SPHERES = (  # 12 mm off the default part's +y side, inside the default band plan's scans
    ReferenceSphereConfig(name="RPS1", centre_mm=(-1010.0, 1002.7, 558.7)),
    ReferenceSphereConfig(name="RPS2", centre_mm=(-750.0, 1009.2, 960.6)),
    ReferenceSphereConfig(name="RPS3", centre_mm=(51.5, 969.0, 558.7)),
    ReferenceSphereConfig(name="RPS4", centre_mm=(312.8, 919.2, 961.7)),
    ReferenceSphereConfig(name="RPS5", centre_mm=(804.3, 786.7, 559.7)),
)


DEFAULT_PART_REGIONS = (  # of the parametric train nose (PartConfig without a mesh), frame F, mm
    RegionConfig(name="body", min_mm=(-1e5, -1e5, -1e5), max_mm=(-500.0, 1e5, 1e5)),
    RegionConfig(name="nose", min_mm=(-500.0, -1e5, -1e5), max_mm=(1e5, 1e5, 1e5)),
)


class InspectionConfig(_Strict):
    """Deviation-from-CAD inspection: tolerance band (mm, signed: + = material outside the CAD surface),
    named regions, optional best-fit alignment and the colour-map scale."""

    in_job: bool = Field(True, description="a measurement job writes report.html; off: E57 and pose log only")
    template: Path | None = Field(
        None, description="inspection template (characteristics) of the part, TOML; empty: PART.inspection.toml "
        "beside the part's mesh, or the shipped one of the parametric default part (docs/inspection.md)")
    tolerance_lower_mm: float = Field(-0.1, le=0)
    tolerance_upper_mm: float = Field(0.1, ge=0)
    decision_rule: Literal["iso14253-1", "simple"] = Field(
        "iso14253-1", description="ISO 14253-1: conformance proven only inside the tolerance shrunk by the "
        "expanded uncertainty U, nonconformance only outside it widened by U, else indeterminate; simple: "
        "in or out of the tolerance by the measured value alone (docs/inspection.md, \"Decision rule\")"
    )
    decision_k: float = Field(2.0, gt=0, description="coverage factor k of the expanded uncertainties U")
    regions: tuple[RegionConfig, ...] = Field(
        (), description="named regions reported apart; none configured: the parametric default part's body and "
        "nose where it is the part (CellConfig.part_inspection), none for a part mesh")
    mesh_group_regions: bool = Field(
        True, description="also one region per material group of the CAD mesh (OBJ usemtl), by closest triangle"
    )
    best_fit: bool = True
    best_fit_max_distance_mm: float = Field(
        1.0, gt=0, description="best-fit ICP uses only points deviating less than this, mm"
    )
    best_fit_iterations: int = Field(30, ge=1)
    alignment: Literal["best-fit", "rps", "none"] = Field(
        "best-fit", description="registration of the measured cloud to CAD: robust best fit to the surface, "
        "reference spheres (RPS), or none (the cloud is in the CAD frame already)"
    )
    alignment_distances_mm: tuple[float, ...] = Field(
        (400.0, 200.0, 100.0, 50.0, 16.0, 4.0), description="coarse-to-fine trim distances of the best-fit "
        "alignment before its final pass at best_fit_max_distance_mm, mm: the first bounds how far off CAD the "
        "cloud may start"
    )
    alignment_huber_sigmas: float = Field(
        2.0, gt=0, description="final best-fit pass: Huber weights beyond this many robust sigmas of the residual"
    )
    datum_regions: tuple[str, ...] = Field(
        (), description="names of regions whose points alone take part in the best-fit alignment; empty = all"
    )
    alignment_min_inlier_share: float = Field(
        0.5, gt=0, le=1, description="best-fit alignment: a fit leaving a smaller share of the points within "
        "best_fit_max_distance_mm of CAD tries the global stage, and failing there is a failed alignment"
    )
    reference_spheres: tuple[ReferenceSphereConfig, ...] = _DEFAULT_SPHERES
    reference_sphere_diameter_mm: float = Field(38.1, gt=0, description="calibrated diameter of the spheres, mm")
    reference_sphere_search_mm: float = Field(
        60.0, gt=0, description="RPS: points this close to a sphere's expected centre are fitted, mm"
    )
    area_smoothing_mm: float = Field(
        4.0, gt=0, description="deviation areas: each point's deviation is the mean over this radius, mm"
    )
    area_min_mm2: float = Field(50.0, ge=0, description="deviation areas smaller than this are not reported, mm^2")
    colour_limit_mm: float | None = Field(
        None, gt=0, description="colour-map saturates at +/- this, mm; default 3x the wider tolerance"
    )
    map_width_px: int = Field(800, ge=100, le=4000, description="width of each rendered colour-map view")
    map_max_points: int = Field(300_000, ge=1000, description="colour maps draw an even subsample of this size")
    max_points: int = Field(
        10_000_000, ge=1000, description="a job's inspection (deviations, areas, report, deviation PLY) takes at "
        "most this many points of its cloud, every k-th voxel beyond it: a whole part's 1 mm map holds about 8 M "
        "points at the coarse resolution and 18 M at the full one, whose inspection would otherwise need several "
        "GB more; cloud.ply and the E57 keep every point. With [compute] tile_mm it bounds only the report's sample, "
        "as report_points does (docs/compute.md, Tiles)"
    )
    views: tuple[Literal["isometric", "front", "left", "right", "top", "back"], ...] = (
        "isometric", "front", "left", "right", "top",
    )

    @field_validator("tolerance_upper_mm")
    @classmethod
    def _band_not_empty(cls, v: float, info) -> float:
        if v <= info.data.get("tolerance_lower_mm", -math.inf):
            raise ValueError("the tolerance band is empty: tolerance_upper_mm must be above tolerance_lower_mm")
        return v


class CalibrationConfig(_Strict):
    """Calibration plate (three reference spheres A, X, Y) and the hand-eye calibration job.

    Plate frame ``P`` (Eq. 7-8): x along A->X, origin at the foot of the perpendicular from Y onto the line
    A-X, y towards Y, z = x cross y. Sphere centres are given in ``P`` (mm), so A and X lie on the x axis and
    Y on the y axis.
    """

    sphere_diameter_mm: float = Field(38.1, gt=0, description="calibrated diameter of the three spheres, mm")
    centre_A_mm: tuple[float, float, float] = (-100.0, 0.0, 0.0)
    centre_X_mm: tuple[float, float, float] = (120.0, 0.0, 0.0)
    centre_Y_mm: tuple[float, float, float] = (0.0, 90.0, 0.0)
    stem_mm: float = Field(15.0, ge=0, description="sphere surface to plate top along -z, mm (sim mesh)")
    plate_size_mm: tuple[float, float] = (300.0, 210.0)
    radius_tolerance_mm: float = Field(0.3, gt=0, description="reject a sphere fit off the nominal radius by more")
    layout_tolerance_mm: float = Field(2.0, gt=0, description="max error of a centre-to-centre distance, mm")
    fit_fixed_radius: bool = Field(True, description="final centre fit with the calibrated radius fixed")
    min_pair_rotation_deg: float = Field(5.0, ge=0, description="hand-eye pose pairs rotating less are dropped")
    poses: int = Field(32, ge=3, description="arm poses of the calibration job")
    tracker_samples: int = Field(30, ge=1, description="tracker readings averaged at rest per calibration pose")
    scans_per_pose: int = Field(2, ge=1, description="plate scans whose sphere centres are averaged per pose")
    tilt_deg: float = Field(30.0, gt=0, lt=60, description="scanner tilt over the plate in the calibration job")
    roll_span_deg: float = Field(
        150.0, ge=0, le=360, description="the views' rolls about their view axes spread over +- half this, deg"
    )
    method: Literal["tsai", "park", "horaud", "daniilidis", "refine"] = "refine"
    T_V2_P: TransformConfig = Field(
        TransformConfig(xyz_mm=(550.0, 0.0, 250.0)),
        description="where the plate stands relative to the measurement chassis at its start (nominal for "
        "planning; the sim cell puts it exactly there)",
    )
    output_file: Path = Field(Path("out/calibration.json"), description="where `tandemscan calibrate` writes: the "
                              "cell's current calibration")
    max_age_h: float = Field(720.0, gt=0, description="the current calibration expires after this many hours")

    @field_validator("centre_A_mm", "centre_X_mm")
    @classmethod
    def _on_x_axis(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if abs(v[1]) > 1e-9 or abs(v[2]) > 1e-9:
            raise ValueError("A and X lie on the plate x axis: y = z = 0")
        return v

    @field_validator("centre_Y_mm")
    @classmethod
    def _on_y_axis(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if abs(v[0]) > 1e-9 or abs(v[2]) > 1e-9 or v[1] <= 0:
            raise ValueError("Y lies on the plate +y axis: x = z = 0, y > 0")
        return v

class VerificationConfig(_Strict):
    """Interim verification (VDI/VDE 2634-3 style, `tandemscan verify`): the calibration plate's spheres measured
    through the whole chain (tracker, target, mounts, scanner) from several views; maximum permissible errors
    (mm) and how long a verification holds."""

    views: int = Field(6, ge=2, description="plate views of a verification (each sphere seen from each)")
    mpe_sphere_spacing_mm: float = Field(0.15, gt=0, description="MPE of the sphere-spacing error across views")
    mpe_probing_form_mm: float = Field(0.1, gt=0, description="MPE of the probing form error (RMS of a sphere fit)")
    mpe_probing_size_mm: float = Field(0.1, gt=0, description="MPE of the probing size error (fitted diameter)")
    max_age_h: float = Field(24.0, gt=0, description="a job's verdict is indeterminate after a verification this "
                             "old (or one that failed); none on record: the report says so")
    output_file: Path = Field(Path("out/verification.json"), description="where `tandemscan verify` records "
                              "the last verification (the journal of verifications beside it, .jsonl)")


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
    worker_niceness: int = Field(5, ge=0, le=19, description="added niceness of worker processes (ray casting, "
                                 "stitching, exports): the event loop and its 50 Hz safety loop come first")
    fault_retry_attempts: int = Field(3, ge=0, description="automatic resumes of a job paused by a recoverable "
                                      "device fault, counted since its last committed step (0: the operator resumes)")
    fault_retry_initial_s: float = Field(2.0, gt=0, description="wait before the first automatic resume; doubles")
    fault_retry_max_s: float = Field(60.0, gt=0, description="cap of the wait between automatic resumes")
    max_body_bytes: int = Field(1_048_576, ge=1024, description="request bodies over this are refused (413) unread")
    scan_bytes_estimate: int = Field(8_000_000, ge=0, description="disk one raw scan and its share of the exports "
                                     "take (bytes), for the low-space guard of a new job")
    reserve_free_bytes: int = Field(50_000_000, ge=0, description="free space kept beyond a job's scans (bytes): "
                                    "the journal, reports and logs")


class OpcuaUserConfig(_Strict):
    """One OPC UA user: a viewer browses and subscribes, an operator may also call methods (docs/opcua.md)."""

    role: Literal["viewer", "operator"] = "viewer"
    password_hash: str = Field(min_length=1, description="scrypt hash of the password: `tandemscan opcua-user` "
                               "prints it")


class OpcuaConfig(_Strict):
    """The OPC UA server beside the REST API (docs/opcua.md): off unless ``enabled``; its certificate, key and
    trust list live in the state folder's ``opcua/`` unless ``trust_dir`` names another trust list."""

    enabled: bool = False
    host: str | None = Field(None, description="bind address; None: [daemon] host (loopback only while "
                             "anonymous access is allowed)")
    port: int = Field(4840, ge=0, le=65535)
    security_policies: list[Literal["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign",
                                    "Aes128Sha256RsaOaep_SignAndEncrypt", "Aes256Sha256RsaPss_SignAndEncrypt"]] = \
        Field(["Basic256Sha256_SignAndEncrypt"], min_length=1)
    allow_anonymous: bool = Field(False, description="an anonymous session is a viewer")
    users: dict[str, OpcuaUserConfig] = Field({}, description="user name: role and password hash")
    users_file: Path | None = Field(None, description="TOML file of further users ([users.NAME] tables)")
    trust_dir: Path | None = Field(None, description="folder of trusted client certificates (DER or PEM); None: "
                                   "opcua/trusted/ in the state folder")
    min_publishing_interval_ms: float = Field(200.0, gt=0, description="fastest publishing interval a "
                                              "subscription gets (ms): a faster request is revised up to it, so "
                                              "many fast subscribers cannot crowd the event loop")
    manufacturer: str = "tandemscan"
    model: str = "two-robot 3D measurement cell"
    serial_number: str = "SIM-0001"


def _simulator_section(section: str, what: str):
    """A field holding the simulator's own table ``[section]``: validated by the model the simulator registers for
    it (:func:`~tandemscan.config.device_registry.simulator_settings_model`, ``sim_drivers/config.py``), by default that
    model's defaults."""
    return Field(default_factory=lambda: simulator_settings_model(section)(),
                 description=f"{what}: the simulator's own table, validated by the model it registers")


class CellConfig(_Strict):
    """The whole cell."""

    name: str = "simulated cell"
    part: PartConfig = PartConfig()
    scanner: ScannerConfig = ScannerConfig()
    tracker: TrackerConfig = TrackerConfig()
    arm: ArmConfig = ArmConfig()
    lift: LiftConfig = LiftConfig()
    measure_chassis: ChassisConfig = ChassisConfig()
    tracking_chassis: ChassisConfig = ChassisConfig()
    safety: SafetyConfig = SafetyConfig()
    installation: InstallationConfig = InstallationConfig()
    sim: SerializeAsAny[BaseModel] = _simulator_section("sim", "the simulated cell's ground truth, noise and faults")
    job: JobConfig = JobConfig()
    inspection: InspectionConfig = InspectionConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    verification: VerificationConfig = VerificationConfig()
    planning: PlanningConfig = PlanningConfig()
    correction: CorrectionConfig = CorrectionConfig()
    deepmerge: DeepMergeConfig = DeepMergeConfig()
    compute: ComputeConfig = ComputeConfig()
    daemon: DaemonConfig = DaemonConfig()
    opcua: OpcuaConfig = OpcuaConfig()
    hil: SerializeAsAny[BaseModel] = _simulator_section("hil", "hardware-in-the-loop: the simulator's emulators")

    @field_validator("sim", "hil", mode="before")
    @classmethod
    def _validated_by_the_simulator(cls, table: object, info) -> object:
        """Hand the simulator its own table: validated by the model it registers for the section (errors at
        ``sim.key``, ``hil.key``)."""
        model = simulator_settings_model(info.field_name)
        return table if isinstance(table, model) else model.model_validate(table)

    def part_inspection(self) -> InspectionConfig:
        """``[inspection]`` for the configured part: without configured regions, the default part's body and nose
        (``DEFAULT_PART_REGIONS``) where the part is the parametric nose; a part mesh gets only the regions
        configured for it."""
        if self.part.mesh is None and "regions" not in self.inspection.model_fields_set:
            return self.inspection.model_copy(update={"regions": DEFAULT_PART_REGIONS})
        return self.inspection

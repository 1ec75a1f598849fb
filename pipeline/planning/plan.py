"""The plan format: the paper's unified command sequence, as data that can be dry-run or executed.

Chassis targets are in each chassis's odometry frame (which starts as the floor frame F), mm and rad.
A ``move_arm`` step may also carry the scanner pose it is meant to reach, ``T_F_S`` in the part frame F (mm):
the runner then re-solves the joints from the measurement AGV's pose as the tracker sees it, so the scan lands
where it was planned even when the chassis has drifted; without it the joint targets are used as they are.
A ``move_tracker`` step is a coordinate transfer: the measurement robot stands still while the tracking
robot moves, and the target is read before and after (Eq. 2). Stored as TOML or JSON by file suffix.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tomli_w
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from tandemscan.config.loader import format_validation_error


class PlanError(Exception):
    """A plan file is missing, unreadable or invalid."""


class _Step(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MoveTracker(_Step):
    """Move the tracking AGV (a coordinate transfer). ``alternatives``: labels of scans at the measurement AGV's
    station and column height whose target both tracker stations see past the part (the planner's cover: view,
    range, facing, sight line), nearest the transfer's own pose first; where the target is hidden at the
    transfer's own pose the runner reads it at these."""

    kind: Literal["move_tracker"] = "move_tracker"
    x_mm: float
    y_mm: float
    heading_rad: float
    alternatives: tuple[str, ...] = ()


class MoveMeasure(_Step):
    """Move the measurement AGV (the tracker stands still)."""

    kind: Literal["move_measure"] = "move_measure"
    x_mm: float
    y_mm: float
    heading_rad: float


class MoveLift(_Step):
    """Move the measurement AGV's lifting column to ``height_mm`` above the arm's mount (the arm folded)."""

    kind: Literal["move_lift"] = "move_lift"
    height_mm: float


Matrix4 = tuple[tuple[float, float, float, float], tuple[float, float, float, float],
                tuple[float, float, float, float], tuple[float, float, float, float]]


class MoveArm(_Step):
    """Joint move of the arm on the measurement AGV; ``T_F_S`` (optional): the planned scanner pose, part frame
    F, mm, row-major 4x4, which ``joints_rad`` reach when the AGV stands exactly at its planned pose."""

    kind: Literal["move_arm"] = "move_arm"
    joints_rad: tuple[float, float, float, float, float, float]
    T_F_S: Matrix4 | None = None

    @field_validator("T_F_S")
    @classmethod
    def _rigid(cls, T: Matrix4 | None) -> Matrix4 | None:
        if T is None:
            return T
        M = np.array(T, float)
        R = M[:3, :3]
        if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0]) or not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or (
                np.linalg.det(R) < 0):
            raise ValueError("T_F_S must be a rigid 4x4 transform (orthonormal rotation, last row 0 0 0 1)")
        return T


class Scan(_Step):
    """Capture a scan and read the tracker, both at rest."""

    kind: Literal["scan"] = "scan"
    label: str = ""


Step = Annotated[MoveTracker | MoveMeasure | MoveLift | MoveArm | Scan, Field(discriminator="kind")]


class PartIdentity(BaseModel):
    """The part a plan was made for: the SHA-256 of its mesh (vertices rounded to 1 um, then triangles) and its
    bounding box in the part frame F (mm)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    sha256: str
    bbox_min_mm: tuple[float, float, float]
    bbox_max_mm: tuple[float, float, float]
    triangles: int


class LeftOutArea(BaseModel):
    """Surface the plan does not measure, of one kind near one AGV station: why, its area (m^2), height range
    and centroid (part frame F, mm)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    reason: str
    station: int
    area_m2: float
    z_range_mm: tuple[float, float]
    centroid_mm: tuple[float, float, float]


class Plan(BaseModel):
    """A named sequence of steps for one part."""

    model_config = ConfigDict(extra="forbid")

    name: str
    part: str = Field("", description="the part the plan was made for (informative)")
    part_identity: PartIdentity | None = Field(None, description="the mesh the plan was made for; a job refuses "
                                               "a plan whose mesh differs")
    left_out: list[LeftOutArea] = Field(default_factory=list, description="surface the plan does not measure")
    coverage_pct: float | None = Field(None, description="share (%) of the part's surface where a scanner pose "
                                       "fits that the plan's scans see (the planner's dry run)")
    steps: list[Step]

    @field_validator("steps")
    @classmethod
    def _has_a_scan(cls, steps: list[Step]) -> list[Step]:
        if not any(isinstance(s, Scan) for s in steps):
            raise ValueError("a plan needs at least one scan step")
        return steps

    @property
    def scan_count(self) -> int:
        return sum(isinstance(s, Scan) for s in self.steps)

    @property
    def transfer_count(self) -> int:
        return sum(isinstance(s, MoveTracker) for s in self.steps)

    def save(self, path: Path) -> None:
        """Write as TOML (``.toml``) or JSON (anything else)."""
        data = self.model_dump(mode="json", exclude_none=True)  # TOML has no null: a missing T_F_S is absent
        path = Path(path)
        text = tomli_w.dumps(data) if path.suffix == ".toml" else json.dumps(data, indent=1)
        path.write_text(text, encoding="utf-8")

    @classmethod
    def load(cls, path: Path) -> Plan:
        """Read a TOML or JSON plan; raises :class:`PlanError` naming the file, key and reason."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
            raw = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
        except FileNotFoundError as e:
            raise PlanError(f"{path}: file not found") from e
        except OSError as e:
            raise PlanError(f"{path}: cannot read: {e.strerror}") from e
        except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as e:
            raise PlanError(f"{path}: not valid {'TOML' if path.suffix == '.toml' else 'JSON'}: {e}") from e
        try:
            return cls.model_validate(raw)
        except ValidationError as e:
            raise PlanError(f"{path}: {format_validation_error(e)}") from e

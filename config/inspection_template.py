"""Inspection templates: a part's characteristics, defined once (from its drawing or PMI) and evaluated on
every serial (docs/inspection.md, "Inspection templates"). A TOML file validated here like the cell
configuration; frame F (CAD), millimetres, directions as unit-free 3-vectors.

Where a job finds its template: the plan names it (``inspection_template``), else ``PART.inspection.toml``
beside the part's mesh, else ``[inspection] template``, else for the parametric default part the shipped
``config/templates/default-part.toml``. ``tandemscan inspect --template T.toml`` names it.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from tandemscan.config.loader import ConfigError, format_validation_error, read_toml
from tandemscan.config.models import InspectionConfig, RegionConfig

TEMPLATE_SUFFIX = ".inspection.toml"  # PART.inspection.toml beside PART.ply
DEFAULT_PART_TEMPLATE = "default-part.toml"

Vec3 = tuple[float, float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RegionSpec(_Strict):
    """Where on the CAD surface a characteristic applies: a named patch of the template, a box (frame F,
    bounds inclusive) or mesh face groups (material ids, by each point's closest triangle). One of them;
    a box and face groups together mean both."""

    patch: str | None = None
    min_mm: Vec3 | None = None
    max_mm: Vec3 | None = None
    face_groups: tuple[int, ...] = ()

    @model_validator(mode="after")
    def _one_selection(self) -> RegionSpec:
        if (self.min_mm is None) != (self.max_mm is None):
            raise ValueError("a box needs both min_mm and max_mm")
        if self.min_mm is not None and any(lo > hi for lo, hi in zip(self.min_mm, self.max_mm, strict=True)):
            raise ValueError("box min_mm is above max_mm")
        has_own = self.min_mm is not None or bool(self.face_groups)
        if (self.patch is not None) == has_own:
            raise ValueError("name a patch, or give a box (min_mm, max_mm) and/or face_groups")
        return self


class PatchSpec(_Strict):
    """A named patch of the CAD surface: a box (frame F) and/or mesh face groups."""

    min_mm: Vec3 | None = None
    max_mm: Vec3 | None = None
    face_groups: tuple[int, ...] = ()

    @model_validator(mode="after")
    def _selects(self) -> PatchSpec:
        RegionSpec(min_mm=self.min_mm, max_mm=self.max_mm, face_groups=self.face_groups)
        return self


class DatumFeatureSpec(_Strict):
    """One feature of a datum reference frame, fitted to a patch (a box) of the measured points and of the
    CAD: the primary ``plane``, the secondary ``line`` (its plane's intersection with the primary) and the
    tertiary ``point`` (where its plane meets that line)."""

    feature: Literal["plane", "line", "point"]
    patch: str


class AlignmentSpec(_Strict):
    """How the measured cloud is placed in the CAD frame before the characteristics are evaluated:
    ``best-fit`` over every point or over the points of ``datum_patches`` (boxes); ``rps`` over the reference
    spheres of ``[inspection]``; ``datums``, the datum reference frame of ``datums`` (a plane, a line and a
    point, in that order) after a best fit; ``none`` (the cloud is in the CAD frame already)."""

    method: Literal["best-fit", "rps", "datums", "none"] = "best-fit"
    datum_patches: tuple[str, ...] = ()
    datums: tuple[DatumFeatureSpec, ...] = ()

    @model_validator(mode="after")
    def _datums_complete(self) -> AlignmentSpec:
        if self.method == "datums" and [d.feature for d in self.datums] != ["plane", "line", "point"]:
            raise ValueError("a datum reference frame is a plane, a line and a point, in that order")
        return self


class _Characteristic(_Strict):
    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    name: str = Field(min_length=1, max_length=200)
    lower_mm: float = Field(description="lower limit of the actual value, mm")
    upper_mm: float = Field(description="upper limit of the actual value, mm")

    @model_validator(mode="after")
    def _band(self) -> _Characteristic:
        if (self.lower_mm is None) != (self.upper_mm is None):
            raise ValueError(f"{self.id}: give both lower_mm and upper_mm, or neither (the general tolerance)")
        if self.lower_mm is not None and not self.lower_mm < self.upper_mm:
            raise ValueError(f"{self.id}: lower_mm {self.lower_mm} must be below upper_mm {self.upper_mm}")
        return self


_GENERAL = ("none: the part's general surface profile tolerance, [inspection] tolerance_lower_mm/"
            "tolerance_upper_mm (ISO 22081)")


class _ProfileCharacteristic(_Characteristic):
    """A deviation from CAD, whose limits a drawing may leave to its general surface profile tolerance."""

    lower_mm: float | None = Field(None, description=f"lower limit of the deviation, mm; {_GENERAL}")
    upper_mm: float | None = Field(None, description=f"upper limit of the deviation, mm; {_GENERAL}")


class SurfaceProfileSpec(_ProfileCharacteristic):
    """ISO 1101 profile of a surface: the region's deviations from CAD; actual = the worst (largest |value|)
    of the deviations averaged over the template's ``smoothing_mm``, with the worst positive and negative."""

    kind: Literal["surface_profile"]
    region: RegionSpec


class FlatnessSpec(_Characteristic):
    """Flatness of a planar region: the range of the points' distances from their least-squares plane
    (after the template's smoothing); actual >= 0, so ``lower_mm`` is 0."""

    kind: Literal["flatness"]
    region: RegionSpec
    lower_mm: float = 0.0


class SectionSpec(_ProfileCharacteristic):
    """The deviation along the intersection of the CAD surface with a plane (``point_mm``, ``normal``):
    the points within ``half_width_mm`` of the plane (in ``region`` when given); actual = the worst."""

    kind: Literal["section"]
    point_mm: Vec3
    normal: Vec3
    half_width_mm: float = Field(1.0, gt=0)
    region: RegionSpec | None = None


class EdgeSpec(_Characteristic):
    """Position of a trimmed edge or an opening's edge: the CAD edge is the straight segment
    ``start_mm``-``end_mm`` (projected onto the CAD surface), ``into_opening`` points from the material into
    the opening (projected into the surface, normal to the edge). The edge is found in the cloud and on the
    CAD the same way (the surface outside it and the wall it drops along, within ``corridor_mm``); actual =
    the measured edge minus the CAD edge along ``-into_opening`` (+ = material beyond the CAD edge)."""

    kind: Literal["edge"]
    start_mm: Vec3
    end_mm: Vec3
    into_opening: Vec3
    corridor_mm: float = Field(15.0, gt=0)


Characteristic = Annotated[SurfaceProfileSpec | FlatnessSpec | SectionSpec | EdgeSpec, Field(discriminator="kind")]


class InspectionTemplate(_Strict):
    """A part's inspection template: identity, alignment, named patches and characteristics."""

    part: str = Field(min_length=1, description="what the part is, in words")
    part_number: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    smoothing_mm: float = Field(
        4.0, gt=0, description="per-point deviations are averaged over this radius before a worst is taken, mm")
    alignment: AlignmentSpec = AlignmentSpec()
    patches: dict[str, PatchSpec] = {}
    characteristics: tuple[Characteristic, ...] = Field(min_length=1)

    @field_validator("characteristics")
    @classmethod
    def _unique_ids(cls, v: tuple) -> tuple:
        ids = [c.id for c in v]
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if twice:
            raise ValueError(f"characteristic ids used twice: {twice}")
        return v

    @model_validator(mode="after")
    def _patches_known(self) -> InspectionTemplate:
        named = [*self.alignment.datum_patches, *(d.patch for d in self.alignment.datums)]
        for c in self.characteristics:
            region = getattr(c, "region", None)
            if region is not None and region.patch is not None:
                named.append(region.patch)
            if isinstance(c, SectionSpec | EdgeSpec):
                vec = c.normal if isinstance(c, SectionSpec) else c.into_opening
                if not math.hypot(*vec) > 0:
                    raise ValueError(f"{c.id}: a zero direction")
        unknown = sorted({n for n in named if n not in self.patches})
        if unknown:
            raise ValueError(f"patches {unknown} are not defined under [patches]")
        return self

    def inspection_config(self, cfg: InspectionConfig) -> InspectionConfig:
        """``cfg`` with the template's alignment: its method (a best fit before ``datums``) and, for a best fit
        over datum patches, those patches as ``[inspection]`` regions named ``datum:NAME`` (boxes only)."""
        datums = []
        for name in self.alignment.datum_patches:
            patch = self.patches[name]
            if patch.min_mm is None or patch.face_groups:
                raise ConfigError(f"datum patch {name!r}: a best fit's datum patch is a box (min_mm, max_mm) only")
            datums.append(RegionConfig(name=f"datum:{name}", min_mm=patch.min_mm, max_mm=patch.max_mm))
        method = "best-fit" if self.alignment.method == "datums" else self.alignment.method
        for d in self.alignment.datums:
            if self.patches[d.patch].min_mm is None:
                raise ConfigError(f"datum {d.feature} {d.patch!r}: a datum patch is a box (min_mm, max_mm)")
        return cfg.model_copy(update={"alignment": method,
                                      "regions": (*cfg.regions, *datums),
                                      "datum_regions": tuple(r.name for r in datums)})

    def with_general_tolerance(self, lower_mm: float, upper_mm: float) -> InspectionTemplate:
        """The template with the part's general surface profile tolerance ``[lower_mm, upper_mm]`` (ISO 22081: the
        drawing's title-block tolerance, ``[inspection] tolerance_*``) as the limits of each surface profile and
        section that states none of its own (docs/verdict.md, "Tolerances of the shipped parts")."""
        general = {"lower_mm": lower_mm, "upper_mm": upper_mm}
        return self.model_copy(update={"characteristics": tuple(
            c.model_copy(update=general) if c.lower_mm is None else c for c in self.characteristics)})

    @property
    def needs_general_tolerance(self) -> tuple[str, ...]:
        """Ids of the characteristics that take the general tolerance (no limits of their own)."""
        return tuple(c.id for c in self.characteristics if c.lower_mm is None)

    def region(self, spec: RegionSpec) -> PatchSpec:
        """The patch a region names, or the region's own box and face groups."""
        if spec.patch is not None:
            return self.patches[spec.patch]
        return PatchSpec(min_mm=spec.min_mm, max_mm=spec.max_mm, face_groups=spec.face_groups)


def load_template(path: Path | str) -> InspectionTemplate:
    """Read and validate an inspection template; :class:`ConfigError` names the file, key and reason."""
    path = Path(path)
    raw = read_toml(path, "inspection template")
    try:
        return InspectionTemplate.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(f"{path}: {format_validation_error(e)}") from e


def shipped_template(name: str = DEFAULT_PART_TEMPLATE) -> Path:
    """A template shipped in ``config/templates/`` (the default part's, the barrel panel's)."""
    return Path(str(resources.files("tandemscan.config").joinpath("templates", name)))


def find_template(mesh: Path | None, named: Path | None = None, configured: Path | None = None) -> Path | None:
    """The template of a job: ``named`` (by the plan), else ``MESH.inspection.toml`` beside the part's mesh,
    else ``configured`` (``[inspection] template``), else the shipped default part's when the part is the
    parametric one (``mesh`` None); None when there is none."""
    if named is not None:
        return named
    if mesh is not None:
        beside = mesh.with_name(mesh.stem + TEMPLATE_SUFFIX)
        if beside.is_file():
            return beside
    if configured is not None:
        return configured
    return shipped_template() if mesh is None else None

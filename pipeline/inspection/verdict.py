"""The verdict of an inspection, overall, per region and per deviation area, by the decision rule and the points'
expanded uncertainty (docs/verdict.md, "Verdict").

A deviation area is decided by its extreme (the deviation averaged over ``area_smoothing_mm``) against the band,
given the uncertainty of that average: the pose terms of its points (smooth over the surface, not averaged
away) and the noise divided by the points averaged (``PointUncertainty`` keeps the two apart). Under ISO
14253-1 the areas are sought beyond the band shrunk by the 95th percentile of that uncertainty over the cloud, and
each is then ``nonconforming`` (beyond the band widened by its own U), ``indeterminate`` (within U of a limit), or
dropped (inside the band shrunk by its U: conformance proven there). Where 2U is as wide as the band, no area of
the surface can prove conformance and the verdict is indeterminate, saying so; only areas beyond the band
widened by U are sought then. The simple rule keeps the areas beyond the band, each ``nonconforming``.

Whole and regions: ``fail`` where an area is nonconforming, ``pass`` where none is indeterminate and the band
holds 2U (test uncertainty ratio, band width / 2U of the median point, reported per region), else
``indeterminate``; reasons that hold the whole verdict back (``VerdictContext.holds``: an overdue or failed
verification) make a ``pass`` indeterminate, and reasons that leave the deviations themselves in doubt
(``VerdictContext.unsettled``: the cloud's pose on the CAD ambiguous between poses whose deviations differ) make any
verdict indeterminate.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from tandemscan.pipeline.inspection.decision import (
    DecisionRule,
    Tolerance,
    Verdict,
    combine,
    decide,
    uncertainty_ratio,
)
from tandemscan.pipeline.inspection.deviation_areas import NEIGHBOURS, DeviationArea, find_deviation_areas
from tandemscan.pipeline.inspection.inspect import InspectionCriteria, InspectionResult, region_mask
from tandemscan.pipeline.inspection.point_uncertainty import PointUncertainty


@dataclass(frozen=True)
class VerdictContext:
    """What the inspection knows of the instrument beside the points: the installation the cloud was measured with
    (``{"source", "file", "date", ...}``, None for a cloud from elsewhere), the last verification (``{"result",
    "age_h", ...}``, None: none known) and reasons that hold any proven conformance back (an overdue or failed
    verification: the verdict is indeterminate, with them)."""

    installation: dict | None = None
    verification: dict | None = None
    holds: tuple[str, ...] = ()
    unsettled: tuple[str, ...] = ()  # the deviations in doubt (an ambiguous pose): neither pass nor fail is proven


@dataclass(frozen=True)
class RegionVerdict:
    """One region's verdict, its test uncertainty ratio (band width over 2U of its median point) and the reason."""

    name: str
    verdict: Verdict
    uncertainty_median_mm: float
    test_uncertainty_ratio: float
    reason: str


@dataclass(frozen=True)
class Judgement:
    """The decision on a whole inspection: its verdict and reasons, the rule, the points' uncertainty, the regions'
    verdicts and the context it was made in."""

    verdict: Verdict
    reasons: tuple[str, ...]
    rule: DecisionRule
    uncertainty: PointUncertainty = field(repr=False)
    regions: tuple[RegionVerdict, ...]
    context: VerdictContext


def averaged_uncertainty(u: PointUncertainty, points_averaged: float) -> np.ndarray:
    """(N,) expanded uncertainty of each point's deviation averaged over ``points_averaged`` neighbours: the noise
    divided by them, the pose and alignment terms as they are (mm)."""
    systematic = np.clip((u.expanded_mm / u.k) ** 2 - u.noise_variance_mm2, 0.0, None)
    return u.k * np.sqrt(systematic + u.noise_variance_mm2 / max(points_averaged, 1.0))


def _points_averaged(points_mm: np.ndarray, radius_mm: float, cloud_points: int | None = None) -> float:
    """Median number of points within ``radius_mm`` of a point (at most ``NEIGHBOURS``), on a sample of 2000, of a
    cloud of ``cloud_points`` points that ``points_mm`` is an even thinning of (None: the points themselves)."""
    sample = points_mm[:: max(1, len(points_mm) // 2000)]
    tree = cKDTree(points_mm[:: max(1, len(points_mm) // 200_000)])
    thin = (len(points_mm) if cloud_points is None else cloud_points) / tree.n
    counts = np.array([len(h) for h in tree.query_ball_point(sample, radius_mm, workers=-1)]) * thin
    return float(min(NEIGHBOURS, np.median(counts)))


@dataclass(frozen=True)
class AreaSearch:
    """Where the verdict seeks the deviation areas (module doc): beyond ``[lower_mm, upper_mm]`` (mm: the band
    shrunk by ``guard_mm``, the 95th percentile of the averaged U; widened by it where 2U leaves no room, ``no_room``;
    the band itself under simple acceptance), and each inspected point's averaged U (``averaged_mm``, mm)."""

    lower_mm: float
    upper_mm: float
    guard_mm: float
    no_room: bool
    averaged_mm: np.ndarray = field(repr=False)


def area_search(points_mm: np.ndarray, u: PointUncertainty, criteria: InspectionCriteria,
                cloud_points: int | None = None) -> AreaSearch:
    """:class:`AreaSearch` of the inspected points ``points_mm`` (F, mm) with their uncertainty ``u``; the points
    averaged over ``area_smoothing_mm`` counted at the density of a cloud of ``cloud_points`` that they are an even
    sample of (None: they are the cloud)."""
    rule = criteria.rule
    band = Tolerance(criteria.tolerance_lower_mm, criteria.tolerance_upper_mm)
    area_u = averaged_uncertainty(u, _points_averaged(points_mm, criteria.area_smoothing_mm, cloud_points))
    guard = float(np.percentile(area_u, 95)) if len(area_u) else 0.0
    no_room = rule.name == "iso14253-1" and 2.0 * guard >= band.width
    if rule.name == "simple":
        lo, hi = band.lower, band.upper
    elif no_room:
        lo, hi = band.lower - guard, band.upper + guard
    else:
        lo, hi = band.lower + guard, band.upper - guard
    return AreaSearch(lo, hi, guard, no_room, area_u)


@dataclass(frozen=True)
class CloudAreas:
    """The deviation areas of a whole cloud that the inspected points are an even sample of, found at ``search``
    (the tiled inspection, every point: docs/compute.md "Tiles")."""

    search: AreaSearch
    areas: tuple[DeviationArea, ...]


def judge(result: InspectionResult, u: PointUncertainty, criteria: InspectionCriteria,
          context: VerdictContext | None = None, whole: CloudAreas | None = None) -> InspectionResult:
    """``result`` with its deviation areas decided (``decision``, ``uncertainty_mm``, ``reason``) and its
    :class:`Judgement` (module doc). ``whole``: the areas of the whole cloud ``result`` is a sample of, found at
    :func:`area_search` of the sample at the whole cloud's density (else the areas are the result's own)."""
    context = context or VerdictContext()
    rule = criteria.rule
    band = Tolerance(criteria.tolerance_lower_mm, criteria.tolerance_upper_mm)
    p = result.points_mm
    search = area_search(p, u, criteria) if whole is None else whole.search
    lo, hi, area_u, no_room = search.lower_mm, search.upper_mm, search.averaged_mm, search.no_room
    same = (lo, hi) == (criteria.tolerance_lower_mm, criteria.tolerance_upper_mm)  # the areas found already
    found = whole.areas if whole is not None else result.areas if same else find_deviation_areas(
        result.deviation_cloud, lo, hi, criteria.area_smoothing_mm, criteria.area_min_mm2)  # on its tree, screening
    step = max(1, len(p) // 500_000)
    tree = cKDTree(p[::step]) if found else None
    areas = []
    for a in found:
        at = int(tree.query(a.centroid_mm)[1]) * step
        decision = decide(a.extreme_mm, band, float(area_u[at]), rule, what=f"area #{a.id} ({a.side}) extreme")
        if decision.verdict == "pass":
            continue  # conformance proven there: no area
        label = "nonconforming" if decision.verdict == "fail" else "indeterminate"
        areas.append(dataclasses.replace(a, id=len(areas) + 1, decision=label,
                                         uncertainty_mm=round(decision.uncertainty, 5), reason=decision.reason))
    areas_t = tuple(areas)
    regions = tuple(_region(name, mask, areas_t, p, u, area_u, band, rule)
                    for name, mask in _region_masks(result, criteria))
    reasons = _reasons(areas_t, u, area_u, band, rule, no_room, context)
    verdict = combine([_area_verdict(a) for a in areas_t] + (["indeterminate"] if no_room or context.holds else [])
                      + ["pass"])
    if context.unsettled:  # the deviations themselves in doubt: nothing is proven, the whole nor any region
        verdict = "indeterminate"
        regions = tuple(dataclasses.replace(g, verdict="indeterminate",
                                            reason=f"region {g.name}: {context.unsettled[0]}") for g in regions)
    judgement = Judgement(verdict, tuple(reasons), rule, u, regions, context)
    return dataclasses.replace(result, areas=areas_t, judgement=judgement)


def _area_verdict(a: DeviationArea) -> Verdict:
    return "fail" if a.decision == "nonconforming" else "indeterminate"


def _region_masks(result: InspectionResult, criteria: InspectionCriteria) -> list[tuple[str, np.ndarray]]:
    """The configured regions' masks (the mesh groups' regions are reported with their statistics only)."""
    return [(r.name, region_mask(result.points_mm, r)) for r in criteria.regions]


def _region(name: str, mask: np.ndarray, areas: tuple[DeviationArea, ...], p: np.ndarray,
            u: PointUncertainty, area_u: np.ndarray, band: Tolerance, rule: DecisionRule) -> RegionVerdict:
    """A region's verdict: its areas (by centroid) and whether its band holds 2U of its averaged deviations.

    Eight parameters: the region (name, mask), the areas and points, their uncertainties, the band and the rule."""
    inside = [a for a in areas if _contains(p, mask, a)]
    if not mask.any():
        return RegionVerdict(name, "indeterminate", math.nan, math.nan, f"region {name}: no points measured")
    U, Ua = u.expanded_mm[mask], area_u[mask]
    tur = uncertainty_ratio(band, float(np.median(U)))
    room = rule.name == "simple" or 2.0 * float(np.percentile(Ua, 95)) < band.width
    verdict = combine([_area_verdict(a) for a in inside] + ([] if room else ["indeterminate"]) + ["pass"])
    if inside:
        why = ", ".join(f"#{a.id} {a.decision}" for a in inside)
        reason = f"region {name}: areas {why}"
    elif not room:
        reason = f"region {name}: 2U of its averaged deviations exceeds the tolerance width (TUR {tur:.2f})"
    else:
        reason = f"region {name}: every area within the tolerance shrunk by U (TUR {tur:.2f})"
    return RegionVerdict(name, verdict, float(np.median(U)), tur, reason)


def _contains(p: np.ndarray, mask: np.ndarray, a: DeviationArea) -> bool:
    """Whether the region's points hold the area's centroid (its nearest point is one of them)."""
    return bool(mask[int(np.argmin(np.sum((p - np.asarray(a.centroid_mm)) ** 2, axis=1)))])


def _reasons(areas: tuple[DeviationArea, ...], u: PointUncertainty, area_u: np.ndarray, band: Tolerance,
             rule: DecisionRule, no_room: bool, context: VerdictContext) -> list[str]:
    """The verdict's reasons in words, the decisive first."""
    median_u = float(np.median(u.expanded_mm)) if len(u.expanded_mm) else 0.0
    reasons = list(context.unsettled)
    reasons += [a.reason for a in areas if a.decision == "nonconforming"]
    reasons += [a.reason for a in areas if a.decision == "indeterminate"]
    if no_room:
        reasons.append(f"the expanded uncertainty of the averaged deviations ({float(np.percentile(area_u, 95)):.3f}"
                       f" mm, 95th percentile, k = {rule.k:g}) leaves no room in the tolerance "
                       f"{band.describe()}: conformance cannot be proven ({rule.label})")
    reasons += list(context.holds)
    inst = context.installation or {}
    if inst.get("source") == "nominal":
        reasons.append("the cell measured with nominal mounts (no calibration): its uncertainty is that of the "
                       "mounts' build tolerance")
    if not areas and not no_room:
        reasons.append(f"no area of the surface beyond the tolerance {band.describe()} shrunk by U "
                       f"({rule.label}; point U median {median_u:.3f} mm, TUR "
                       f"{uncertainty_ratio(band, median_u):.1f})")
    if rule.name == "simple":
        reasons.append("simple acceptance: decided by the measured values alone, the uncertainty not considered")
    return reasons

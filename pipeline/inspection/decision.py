"""Decision rules: conformance of a measured value to a tolerance interval given its expanded uncertainty
(docs/verdict.md, "Decision rule").

Two rules, named as ILAC-G8:09/2019 names them:

- ``"iso14253-1"`` (the default; ISO 14253-1:2017, guarded acceptance and guarded rejection by U): a value
  proves conformance only inside the tolerance interval shrunk by U on each side, and nonconformance only
  outside the interval widened by U; in between the result is indeterminate. When 2 U is as wide as the
  tolerance interval or wider, no value proves conformance (the zone is empty).
- ``"simple"`` (simple acceptance): inside the interval is a pass, outside a fail, whatever U is; the
  uncertainty is still reported, and every output names the rule.

Values, limits and U are in millimetres (or any one unit, the same for all); U is the expanded uncertainty
with the rule's coverage factor ``k`` (the GUM's U = k u). A missing limit of a one-sided tolerance is
``-inf`` / ``+inf``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

RuleName = Literal["iso14253-1", "simple"]
Verdict = Literal["pass", "fail", "indeterminate"]
RULE_NAMES: tuple[str, ...] = ("iso14253-1", "simple")

PASS, INDETERMINATE, FAIL = 1, 0, -1  # per-point codes of :func:`decide_points`
VERDICT_OF_CODE: dict[int, Verdict] = {PASS: "pass", INDETERMINATE: "indeterminate", FAIL: "fail"}


@dataclass(frozen=True)
class DecisionRule:
    """A decision rule by name and the coverage factor ``k`` of the expanded uncertainties it is given."""

    name: RuleName = "iso14253-1"
    k: float = 2.0

    def __post_init__(self) -> None:
        if self.name not in RULE_NAMES:
            raise ValueError(f"decision rule {self.name!r}: expected one of {', '.join(RULE_NAMES)}")
        if not (self.k > 0 and math.isfinite(self.k)):
            raise ValueError(f"decision rule coverage factor k = {self.k}: expected a finite k > 0")

    @property
    def label(self) -> str:
        """How every output names the rule, e.g. ``ISO 14253-1 (k = 2)`` or ``simple acceptance (k = 2)``."""
        what = "ISO 14253-1" if self.name == "iso14253-1" else "simple acceptance"
        return f"{what} (k = {self.k:g})"

    def as_dict(self) -> dict[str, object]:
        """``{"name", "k"}`` as report.json writes it."""
        return {"name": self.name, "k": float(self.k)}


@dataclass(frozen=True)
class Tolerance:
    """A tolerance interval ``[lower, upper]`` (inclusive; either limit may be infinite: one-sided)."""

    lower: float
    upper: float

    def __post_init__(self) -> None:
        if math.isnan(self.lower) or math.isnan(self.upper) or self.lower > self.upper:
            raise ValueError(f"tolerance [{self.lower}, {self.upper}]: expected lower <= upper")

    @property
    def width(self) -> float:
        """``upper - lower`` (inf for a one-sided tolerance)."""
        return self.upper - self.lower

    def describe(self, unit: str = "mm") -> str:
        """``[-0.100, +0.100] mm``, ``<= +0.300 mm`` or ``>= -0.200 mm``."""
        if math.isinf(self.lower) and math.isinf(self.upper):
            return "unbounded"
        if math.isinf(self.lower):
            return f"<= {self.upper:+.3f} {unit}"
        if math.isinf(self.upper):
            return f">= {self.lower:+.3f} {unit}"
        return f"[{self.lower:+.3f}, {self.upper:+.3f}] {unit}"


@dataclass(frozen=True)
class Decision:
    """The decision on one value: its verdict and why, in words."""

    verdict: Verdict
    value: float
    uncertainty: float  # expanded, with the rule's k
    tolerance: Tolerance
    rule: DecisionRule
    reason: str


def uncertainty_ratio(tolerance: Tolerance, uncertainty: float) -> float:
    """Test uncertainty ratio, the tolerance width over 2 U (inf when U is 0 or the tolerance one-sided)."""
    return math.inf if uncertainty <= 0.0 else tolerance.width / (2.0 * uncertainty)


def _check(uncertainty: float) -> None:
    if not (uncertainty >= 0.0 and math.isfinite(uncertainty)):
        raise ValueError(f"expanded uncertainty {uncertainty}: expected a finite value >= 0")


def decide(value: float, tolerance: Tolerance, uncertainty: float, rule: DecisionRule = DecisionRule(),
           what: str = "the value", unit: str = "mm") -> Decision:
    """Pass, fail or indeterminate for ``value`` against ``tolerance`` given its expanded uncertainty
    (``rule.k``), with the reason in one sentence naming ``what`` was decided."""
    _check(uncertainty)
    if not math.isfinite(value):
        raise ValueError(f"{what}: measured value {value} is not finite")
    code = int(decide_points(np.array([value]), tolerance, np.array([uncertainty]), rule)[0])
    verdict = VERDICT_OF_CODE[code]
    tol, u = tolerance.describe(unit), f"U = {uncertainty:.3f} {unit}"
    head = f"{what} {value:+.3f} {unit} ({u}, tolerance {tol})"
    inside = tolerance.lower <= value <= tolerance.upper
    if rule.name == "simple":
        where = "inside" if inside else "outside"
        reason = f"{head} lies {where} the tolerance: {verdict} by simple acceptance, uncertainty not considered"
    elif verdict == "pass":
        reason = f"{head} lies inside the tolerance shrunk by U: conformance proven ({rule.label})"
    elif verdict == "fail":
        reason = f"{head} lies outside the tolerance widened by U: nonconformance proven ({rule.label})"
    elif 2.0 * uncertainty >= tolerance.width:
        reason = (f"{head}: 2U is as wide as the tolerance (test uncertainty ratio "
                  f"{uncertainty_ratio(tolerance, uncertainty):.2f}), so neither conformance nor "
                  f"nonconformance can be proven ({rule.label})")
    else:
        side = "inside" if inside else "outside"
        reason = (f"{head} lies {side} the tolerance but within U of a limit: neither conformance nor "
                  f"nonconformance proven ({rule.label})")
    return Decision(verdict, float(value), float(uncertainty), tolerance, rule, reason)


def decide_points(values: np.ndarray, tolerance: Tolerance, uncertainty: np.ndarray | float,
                  rule: DecisionRule = DecisionRule()) -> np.ndarray:
    """(N,) int8 codes :data:`PASS`, :data:`INDETERMINATE`, :data:`FAIL` of ``values`` (N,) against
    ``tolerance`` given each value's expanded uncertainty (N,) or one for all (``rule.k``)."""
    v = np.asarray(values, dtype=np.float64)
    u = np.broadcast_to(np.asarray(uncertainty, dtype=np.float64), v.shape)
    if u.size and not (np.all(u >= 0.0) and np.all(np.isfinite(u))):
        raise ValueError("expanded uncertainties: expected finite values >= 0")
    guard = u if rule.name == "iso14253-1" else np.zeros_like(u)
    out = np.full(v.shape, INDETERMINATE, dtype=np.int8)
    room = 2.0 * guard < tolerance.width if rule.name == "iso14253-1" else True  # 2U >= width: no pass zone
    out[(v >= tolerance.lower + guard) & (v <= tolerance.upper - guard) & room] = PASS
    out[(v < tolerance.lower - guard) | (v > tolerance.upper + guard)] = FAIL
    return out


def combine(verdicts: list[Verdict] | tuple[Verdict, ...]) -> Verdict:
    """The verdict of a whole from its parts': fail when any part's nonconformance is proven, pass when every
    part's conformance is, else indeterminate (an empty whole is indeterminate: nothing was proven)."""
    if any(v == "fail" for v in verdicts):
        return "fail"
    if verdicts and all(v == "pass" for v in verdicts):
        return "pass"
    return "indeterminate"

"""Statistical process control of one characteristic over serials: an individuals chart with its moving
range, and the process capability against the tolerance (docs/quality.md, "Serials and trends").

As the textbooks give them (Montgomery, Introduction to Statistical Quality Control, individuals and
moving-range chart; capability ratios): with values x_1..x_n in measuring order, the moving ranges
MR_i = |x_i - x_{i-1}|, the within-process sigma MR-bar / d2 (d2 = 1.128 for ranges of two); the centre
line is the mean, the control limits mean +/- 3 sigma_within; Cp = (USL - LSL) / (6 sigma_within),
Cpk = min(USL - mean, mean - LSL) / (3 sigma_within); Pp, Ppk the same with the overall sample standard
deviation. Drift: a point beyond the control limits, or the last ``RUN`` points all on one side of the
centre line, or the last ``TREND`` points all rising or all falling (the Western Electric / Nelson rules).
Millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

D2_RANGE_OF_TWO = 1.128  # d2 of the moving range of two consecutive values
RUN = 7  # this many last values on one side of the centre line: a shift
TREND = 6  # this many last values steadily rising or falling: a trend


@dataclass(frozen=True)
class ControlChart:
    """An individuals chart of ``values`` (mm, measuring order) against the tolerance ``[lower, upper]``:
    mean, overall and within-process sigma, control limits, capability and what drifts. Ratios are None
    where a sigma is 0 or there are fewer than two values."""

    values: tuple[float, ...]
    lower_mm: float
    upper_mm: float
    mean_mm: float
    std_mm: float  # overall sample standard deviation
    sigma_within_mm: float  # moving range / d2
    ucl_mm: float
    lcl_mm: float
    cp: float | None
    cpk: float | None
    pp: float | None
    ppk: float | None
    beyond_limits: tuple[int, ...]  # indices of values beyond the control limits
    drift: str  # "" or why the process drifts, in words

    def summary(self) -> dict:
        """JSON-ready, every figure."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def _ratios(sigma: float, mean: float, lower: float, upper: float) -> tuple[float | None, float | None]:
    if not sigma > 0:
        return None, None
    return (upper - lower) / (6.0 * sigma), min(upper - mean, mean - lower) / (3.0 * sigma)


def _drift(x: np.ndarray, mean: float, beyond: np.ndarray) -> str:
    if len(beyond):
        return f"{len(beyond)} value(s) beyond the control limits"
    if len(x) >= RUN and (np.all(x[-RUN:] > mean) or np.all(x[-RUN:] < mean)):
        return f"the last {RUN} values on one side of the mean"
    steps = np.diff(x[-TREND:])
    if len(x) >= TREND and (np.all(steps > 0) or np.all(steps < 0)):
        return f"the last {TREND} values steadily {'rising' if steps[0] > 0 else 'falling'}"
    return ""


def individuals_chart(values, lower_mm: float, upper_mm: float) -> ControlChart:
    """The individuals chart and capability of ``values`` (at least one, measuring order) against the
    tolerance ``[lower_mm, upper_mm]`` (module docstring)."""
    x = np.asarray(values, float)
    if x.ndim != 1 or not len(x) or not np.all(np.isfinite(x)):
        raise ValueError("an individuals chart needs one or more finite values")
    mean = float(x.mean())
    std = float(x.std(ddof=1)) if len(x) > 1 else 0.0
    sigma = float(np.abs(np.diff(x)).mean() / D2_RANGE_OF_TWO) if len(x) > 1 else 0.0
    ucl, lcl = mean + 3.0 * sigma, mean - 3.0 * sigma
    beyond = np.flatnonzero((x > ucl) | (x < lcl)) if sigma > 0 else np.zeros(0, np.int64)
    cp, cpk = _ratios(sigma, mean, lower_mm, upper_mm)
    pp, ppk = _ratios(std, mean, lower_mm, upper_mm)
    return ControlChart(tuple(map(float, x)), lower_mm, upper_mm, mean, std, sigma, ucl, lcl, cp, cpk, pp, ppk,
                        tuple(int(i) for i in beyond), _drift(x, mean, beyond))

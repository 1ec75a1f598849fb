"""The ISO 14253-1 and simple decision rules (pipeline/inspection/decision.py)."""

import math

import numpy as np
import pytest
from tandemscan.config.models import CellConfig, InspectionConfig
from tandemscan.pipeline.inspection.decision import (
    FAIL,
    INDETERMINATE,
    PASS,
    DecisionRule,
    Tolerance,
    combine,
    decide,
    decide_points,
    uncertainty_ratio,
)
from tandemscan.pipeline.inspection.inspect import InspectionCriteria

BAND = Tolerance(-0.5, 0.5)
ISO = DecisionRule()
SIMPLE = DecisionRule("simple", 2.0)


@pytest.mark.parametrize(("value", "u", "iso", "simple"), [
    (0.0, 0.1, "pass", "pass"),
    (0.39, 0.1, "pass", "pass"),  # inside the band shrunk by U
    (0.45, 0.1, "indeterminate", "pass"),  # inside the band, within U of its limit
    (0.55, 0.1, "indeterminate", "fail"),  # outside the band, within U of its limit
    (0.61, 0.1, "fail", "fail"),  # outside the band widened by U
    (-0.61, 0.1, "fail", "fail"),
    (-0.45, 0.1, "indeterminate", "pass"),
    (0.0, 0.5, "indeterminate", "pass"),  # 2U = the tolerance width: nothing can be proven conforming
    (1.2, 0.5, "fail", "fail"),  # ... but a gross deviation is still proven out
])
def test_rules_decide_by_the_guard_bands(value, u, iso, simple):
    assert decide(value, BAND, u, ISO).verdict == iso
    assert decide(value, BAND, u, SIMPLE).verdict == simple


def test_reasons_name_the_rule_the_value_and_why():
    r = decide(0.45, BAND, 0.1, ISO, what="area #2 extreme")
    assert r.reason.startswith("area #2 extreme +0.450 mm")
    assert "within U of a limit" in r.reason and "ISO 14253-1 (k = 2)" in r.reason
    assert "conformance proven" in decide(0.0, BAND, 0.1, ISO).reason
    assert "nonconformance proven" in decide(0.7, BAND, 0.1, ISO).reason
    wide = decide(0.0, BAND, 0.6, ISO).reason
    assert "2U is as wide as the tolerance" in wide and "0.83" in wide  # the test uncertainty ratio
    assert "simple acceptance" in decide(0.45, BAND, 0.1, SIMPLE).reason


def test_points_agree_with_single_decisions_and_take_one_or_many_uncertainties():
    rng = np.random.default_rng(3)
    v = rng.uniform(-1.0, 1.0, 500)
    u = rng.uniform(0.0, 0.3, 500)
    codes = decide_points(v, BAND, u, ISO)
    names = {PASS: "pass", INDETERMINATE: "indeterminate", FAIL: "fail"}
    assert [names[c] for c in codes] == [decide(a, BAND, b, ISO).verdict for a, b in zip(v, u, strict=True)]
    assert set(codes) == {PASS, INDETERMINATE, FAIL}
    one = decide_points(v, BAND, 0.1, ISO)
    assert np.array_equal(one, decide_points(v, BAND, np.full(500, 0.1), ISO))
    assert np.array_equal(decide_points(v, BAND, u, SIMPLE), np.where(np.abs(v) <= 0.5, PASS, FAIL))


def test_one_sided_tolerance():
    upper_only = Tolerance(-math.inf, 0.3)
    assert upper_only.describe() == "<= +0.300 mm"
    assert decide(-5.0, upper_only, 0.1).verdict == "pass"
    assert decide(0.25, upper_only, 0.1).verdict == "indeterminate"
    assert decide(0.45, upper_only, 0.1).verdict == "fail"
    assert uncertainty_ratio(upper_only, 0.1) == math.inf
    assert uncertainty_ratio(BAND, 0.1) == pytest.approx(5.0)


def test_combine_parts_into_a_whole():
    assert combine(["pass", "pass"]) == "pass"
    assert combine(["pass", "indeterminate"]) == "indeterminate"
    assert combine(["indeterminate", "fail", "pass"]) == "fail"
    assert combine([]) == "indeterminate"


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="decision rule"):
        DecisionRule("guarded")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="k = 0"):
        DecisionRule("simple", 0.0)
    with pytest.raises(ValueError, match="lower <= upper"):
        Tolerance(0.2, 0.1)
    with pytest.raises(ValueError, match="finite value >= 0"):
        decide(0.0, BAND, -0.1)
    with pytest.raises(ValueError, match="finite values >= 0"):
        decide_points(np.zeros(2), BAND, np.array([0.1, np.nan]))


def test_config_names_the_rule_iso_by_default():
    assert InspectionCriteria.from_section(CellConfig().inspection).rule == DecisionRule("iso14253-1", 2.0)
    rule = InspectionCriteria.from_section(InspectionConfig(decision_rule="simple", decision_k=3.0)).rule
    assert rule.as_dict() == {"name": "simple", "k": 3.0}
    assert rule.label == "simple acceptance (k = 3)"
    with pytest.raises(ValueError):
        InspectionConfig(decision_rule="guarded")

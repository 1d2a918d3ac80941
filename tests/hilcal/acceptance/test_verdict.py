"""The verdict: the ISO 14253-1 decision rule and simple acceptance at their boundaries, limits over several
figures, and the overall verdict."""

from __future__ import annotations

import pytest

from hilcal.acceptance.uncertainty import Figure
from hilcal.acceptance.verdict import NO_LIMITS, LimitCheck, check_limit, check_limits, decide, overall


@pytest.mark.parametrize(("value", "expanded", "expected"), [
    (0.07, 0.02, "pass"),        # 0.09 <= 0.10: conformance proven
    (0.08, 0.02, "pass"),        # exactly on the limit with its band: still proven
    (0.09, 0.02, "not proven"),  # passes by its value, but the band reaches 0.11
    (0.11, 0.02, "not proven"),  # fails by its value, but the band reaches down to 0.09
    (0.12, 0.02, "not proven"),  # 0.12 - 0.02 = 0.10 is not above the limit
    (0.13, 0.02, "fail"),        # 0.11 > 0.10: non-conformance proven
])
def test_iso14253_decision_rule(value: float, expanded: float, expected: str) -> None:
    assert decide(value, expanded, 0.10, "iso14253-1") == expected


def test_simple_acceptance_ignores_the_uncertainty() -> None:
    assert decide(0.10, 0.5, 0.10, "simple") == "pass"
    assert decide(0.1001, 0.0, 0.10, "simple") == "fail"
    with pytest.raises(ValueError, match="decision rule"):
        decide(0.1, 0.0, 0.1, "guess")  # type: ignore[arg-type]


def test_a_limit_over_several_poses_is_decided_by_the_worst() -> None:
    mm = "mm"
    figures = [("P1", Figure(0.01, 0.001, mm)), ("P2", Figure(0.045, 0.005, mm)), ("P3", Figure(0.02, 0.001, mm))]
    check = check_limit("rp_position_mm", 0.05, figures, "iso14253-1")
    assert (check.decision, check.where, check.value) == ("not proven", "P2", 0.045)
    figures.append(("P4", Figure(0.08, 0.005, mm)))
    check = check_limit("rp_position_mm", 0.05, figures, "iso14253-1")
    assert (check.decision, check.where) == ("fail", "P4")
    passing = check_limit("rp_position_mm", 0.05, figures[:1], "iso14253-1")
    assert (passing.decision, passing.where, passing.expanded) == ("pass", "P1", pytest.approx(0.002))


def test_overall_verdict() -> None:
    def c(decision: str) -> LimitCheck:
        return LimitCheck("max_position_mm", 1.0, decision)  # type: ignore[arg-type]

    assert overall([]) == NO_LIMITS
    assert overall([c("pass"), c("pass")]) == "pass"
    assert overall([c("pass"), c("not proven")]) == "not proven"
    assert overall([c("pass"), c("not tested")]) == "not proven"
    assert overall([c("not proven"), c("fail")]) == "fail"


def test_limits_without_figures_are_not_tested_and_unknown_ones_refused() -> None:
    checks = check_limits({"ap_position_mm": 0.1, "max_position_mm": 0.1},
                          {"max_position_mm": [("verify", Figure(0.01, 0.001, "mm"))]})
    assert [(k.key, k.decision) for k in checks] == [("max_position_mm", "pass"), ("ap_position_mm", "not tested")]
    with pytest.raises(ValueError, match="unknown acceptance limits"):
        check_limits({"max_speed": 1.0}, {})

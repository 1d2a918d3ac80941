"""The adaptive plan's report section (hilcal.reports.adaptive): each stop said honestly, the verification against
the prediction and the target, and its part of the page."""

from __future__ import annotations

import pytest

from hilcal.reports.adaptive import adaptive_html, adaptive_section

RUN = {"options": {"target_mm": 0.03, "max_minutes": None},
       "budget": {"total_s": 5100.0, "measure_s": 2200.0, "after_measure_s": 2900.0, "fixed_total_s": 5100.0,
                  "fixed_measure_s": 2200.0, "fixed_measure_rows": 35, "source": "the fixed plan's estimated time"},
       "settings": {"confidence": 0.95}}
PREDICTION = {"n_rows": 18, "max_mm": 0.021, "low_mm": 0.015, "upper_mm": 0.029, "parameter_rms_mm": 0.005,
              "floor_upper_mm": 0.02, "confidence": 0.95, "noise_sigma_mm": [0.005] * 6, "noise_dof": [9.0] * 6,
              "noise_source": "2 repeated pose(s)"}
PLANS = {"reference_sha256": "a" * 64, "executed_sha256": "b" * 64}


def _decision(kind: str, prediction: dict | None = PREDICTION, **stop) -> dict:
    return {"distinct": 15, "minimum": None, "stop": {"kind": kind, "sentence": f"the {kind} rule said so",
                                                      "n_rows": 18, "elapsed_s": 1100.0, "prediction": prediction,
                                                      "unidentifiable": [], "screening": None, **stop}}


def test_a_target_reached_says_the_prediction_and_what_the_verification_measured():
    s = adaptive_section(_decision("target"), RUN, 0.0195, PLANS)
    assert s["verification"] == {"measured_max_mm": 0.0195, "within_prediction": True, "target_met": True}
    assert s["time_fraction_of_fixed"] == pytest.approx(0.5)
    assert s["summary"] == ("Target reached after 18 rows (18.3 min of machine time, 0.50 x the fixed plan's "
                            "measure phase): the verify maximum predicted below 29.0 µm with 95% confidence (median "
                            "21.0 µm), target 30.0 µm; the verification after the upload measured 19.5 µm: at or "
                            "below the predicted bound; the target is met.")


def test_a_verification_above_the_bound_or_the_target_is_said_so():
    s = adaptive_section(_decision("target"), RUN, 0.0312, PLANS)
    assert s["verification"]["within_prediction"] is False and s["verification"]["target_met"] is False
    assert "measured 31.2 µm: ABOVE the predicted bound; the target is NOT met." in s["summary"]


def test_budget_and_not_identifiable_stops_and_an_unverified_run():
    budget = adaptive_section(_decision("budget"), RUN, None, PLANS)
    assert budget["summary"].startswith("Budget reached after 18 rows") and "the accuracy proven by then" in (
        budget["summary"])
    assert budget["summary"].endswith("the verification after the upload was not measured.")
    names = ["leg1_dl0_mm", "leg2_dl0_mm"]
    lost = adaptive_section(_decision("not_identifiable", None, unidentifiable=names), RUN, None, PLANS)
    assert lost["unidentifiable"] == names and lost["prediction"] is None
    assert lost["summary"] == ("Not identifiable after 18 rows (18.3 min of machine time, 0.50 x the fixed plan's "
                               "measure phase): the not_identifiable rule said so. Nothing was identified or "
                               "uploaded.")


def test_suspected_physics_says_whose_bound_it_is_and_what_the_diagnosis_named():
    screening = {"n_rows": 17, "p_lack_of_fit": 1e-20, "p_load": 1e-9, "p_stroke": 1e-70, "alpha": 0.02,
                 "suspected": True}
    physics = {"effects": ["sensor_scale", "leg_compliance"], "predicted_max_mm": 0.0048}
    s = adaptive_section(_decision("budget", screening=screening), RUN, 0.0046, PLANS, physics)
    assert "this bound is the geometric model's" in s["summary"]
    assert "named sensor_scale, leg_compliance, and with them predicted 4.8 µm on the held-out" in s["summary"]


def test_the_page_part():
    page = adaptive_html(adaptive_section(_decision("converged"), RUN, 0.02, PLANS))
    assert "The prediction stopped improving after 18 rows" in page and "median 21.0 µm" in page
    assert "the fixed plan: 35" in page
    assert "Fixed plan" in adaptive_html(None)

"""The run report: JSON contract with indicators computed here by hand, and a page that really opens offline."""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import math
from html.parser import HTMLParser
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from drivers.controller.modbus import UploadRecord, WriteRecord
from hilcal.identification import IdentificationResult, identify
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.reports.run import RunReport, report_json, write_run_report
from hilcal.robot import Robot
from tests.poses import feasible_random_poses

# verification errors chosen so the paper's four indicators are easy by hand
POS_BEFORE_MM = np.array([3.0, 4.0, 5.0, 6.0, 2.0])
ORI_BEFORE_DEG = np.array([0.5, 0.4, 0.3, 0.6, 0.2])
SCALE_AFTER = 0.1
UPLOAD_SHA = "ab" * 32


def poses_with_errors(position_mm: np.ndarray, yaw_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Commanded poses with zero roll/pitch and measured ones offset along (0.6, 0, 0.8) and in yaw."""
    n = len(position_mm)
    commanded = np.zeros((n, 6))
    commanded[:, 0] = np.linspace(-20.0, 20.0, n)
    commanded[:, 2] = 1200.0
    commanded[:, 5] = np.linspace(-3.0, 3.0, n)
    measured = commanded.copy()
    measured[:, 0] += 0.6 * position_mm
    measured[:, 2] += 0.8 * position_mm
    measured[:, 5] += yaw_deg
    return measured, commanded


def summary(position_mm: np.ndarray, yaw_deg: np.ndarray) -> AccuracySummary:
    return AccuracySummary.of(*poses_with_errors(position_mm, yaw_deg))


@pytest.fixture(scope="module")
def identifications(robot: Robot) -> dict[str, IdentificationResult]:
    """LS and L-infinity on the same 20 noisy poses of a platform with known joint errors."""
    rng = np.random.default_rng(7)
    truth = np.zeros(42)
    truth[[0, 8, 20, 34, 41]] = [0.8, -0.5, 0.3, -1.2, 0.6]
    poses = feasible_random_poses(robot, 20, rng)
    legs = inverse_kinematics(Geometry.nominal(robot).perturbed(truth), poses)
    measured = poses.copy()
    measured[:, :3] += rng.normal(0.0, 0.005, (20, 3))
    return {est: identify(robot, legs, measured, estimator=est) for est in ("ls", "linf")}


def upload_dump() -> dict:
    return UploadRecord(
        operation="upload", endpoint="tcp://127.0.0.1:1502", device_id=1, started_at="2025-01-01T10:00:00+00:00",
        finished_at="2025-01-01T10:00:01+00:00", outcome="committed", params_sha256=UPLOAD_SHA,
        params_crc32="1234abcd", live_after_sha256=UPLOAD_SHA, staging_readback_match=True,
        live_readback_match=True, writes=[WriteRecord(function="write_registers", address=0x200, count=64,
                                                      at="2025-01-01T10:00:00.5+00:00", ok=True)],
    ).model_dump()


def make_report(identifications: dict[str, IdentificationResult], **changes: object) -> RunReport:
    after = summary(SCALE_AFTER * POS_BEFORE_MM, SCALE_AFTER * ORI_BEFORE_DEG)
    base = RunReport(
        status="complete", run_id="run-001", uploaded=True, estimator="linf", robot_name="paper-table1",
        plan_sha256="cd" * 32, started_at="2025-01-01T09:00:00+00:00", finished_at="2025-01-01T10:30:00+00:00",
        verify_before=summary(POS_BEFORE_MM, ORI_BEFORE_DEG), verify_after=after,
        per_pose_before=(POS_BEFORE_MM, ORI_BEFORE_DEG),
        per_pose_after=(SCALE_AFTER * POS_BEFORE_MM, SCALE_AFTER * ORI_BEFORE_DEG),
        identifications=identifications,
        predicted_after={"ls": summary(0.12 * POS_BEFORE_MM, 0.12 * ORI_BEFORE_DEG),
                         "linf": summary(0.11 * POS_BEFORE_MM, 0.11 * ORI_BEFORE_DEG)},
        chosen="linf",
        plausibility={"ok": True, "violations": [], "bounds_mm": 5.0},
        compensation={"mode": "full", "uploaded_parameters": {"l0_mm": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]},
                      "uncompensated": None},
        upload=upload_dump(),
        warnings=("CMM temperature drifted by 0.4 °C",),
    )
    return dataclasses.replace(base, **changes)


def test_json_contract_and_table7_by_hand(identifications: dict[str, IdentificationResult]) -> None:
    out = report_json(make_report(identifications))
    for key in ("status", "run_id", "uploaded", "estimator", "verification", "table7", "parameters", "ls_vs_linf",
                "plausibility", "compensation", "upload", "plan_sha256", "robot", "times", "warnings"):
        assert key in out
    assert (out["status"], out["run_id"], out["uploaded"], out["estimator"]) == ("complete", "run-001", True, "linf")
    before = out["verification"]["before"]
    assert set(before) == {"max_position_mm", "rms_position_mm", "max_orientation_deg", "rms_orientation_deg"}
    assert before["max_position_mm"] == pytest.approx(6.0, abs=1e-9)
    assert before["rms_position_mm"] == pytest.approx(math.sqrt((9 + 16 + 25 + 36 + 4) / 5), abs=1e-9)
    assert before["max_orientation_deg"] == pytest.approx(0.6, abs=1e-9)
    assert out["verification"]["after"]["max_position_mm"] == pytest.approx(0.6, abs=1e-9)
    assert set(out["verification"]) == {"before", "after"}
    t7 = out["table7"]
    assert t7["n_poses"] == len(POS_BEFORE_MM)
    assert t7["before"]["position_mm"] == pytest.approx({"max": 6.0, "range": 4.0, "mean": 4.0,
                                                         "rms": math.sqrt(18.0)}, abs=1e-9)
    assert t7["before"]["orientation_deg"] == pytest.approx({"max": 0.6, "range": 0.4, "mean": 0.4,
                                                            "rms": math.sqrt(0.9 / 5)}, abs=1e-9)
    for key in ("position_mm", "orientation_deg"):
        assert t7["reduction_percent"][key] == pytest.approx({i: 90.0 for i in ("max", "range", "mean", "rms")},
                                                             abs=1e-6)
    assert t7["predicted_after"]["linf"]["position_mm"]["max"] == pytest.approx(0.66, abs=1e-9)
    assert out["per_pose"]["before"]["position_mm"] == pytest.approx(POS_BEFORE_MM.tolist())
    assert out["upload"]["params_sha256"] == UPLOAD_SHA and out["robot"] == {"name": "paper-table1"}
    assert out["times"]["started_at"].startswith("2025-01-01T09")
    assert out["warnings"] == ["CMM temperature drifted by 0.4 °C"]


def test_parameters_of_the_chosen_estimator(identifications: dict[str, IdentificationResult]) -> None:
    linf = report_json(make_report(identifications))["parameters"]
    assert len(linf) == 42 and "leg1_da_x_mm" in linf and "leg6_dl0_mm" in linf
    assert all(p["std_mm"] is None for p in linf.values())
    assert [p["value_mm"] for p in linf.values()] == pytest.approx(identifications["linf"].x.tolist())
    ls = report_json(make_report(identifications, chosen="ls", estimator="ls"))["parameters"]
    assert all(p["std_mm"] is not None and p["std_mm"] > 0 for p in ls.values())
    assert list(ls) == list(identifications["ls"].names)
    assert [p["std_mm"] for p in ls.values()] == pytest.approx(identifications["ls"].std_errors.tolist())
    cmp = report_json(make_report(identifications))["ls_vs_linf"]
    assert set(cmp["estimators"]) == {"ls", "linf"}
    assert cmp["estimators"]["ls"]["fit"]["sigma_mm"] > 0 and cmp["estimators"]["linf"]["fit"]["sigma_mm"] is None
    assert cmp["comparison"]["lower_predicted_max_position"] == "linf"
    x_ls, x_linf = identifications["ls"].x, identifications["linf"].x
    assert cmp["comparison"]["max_abs_parameter_difference_mm"] == pytest.approx(np.max(np.abs(x_ls - x_linf)))


def test_nan_becomes_null_and_json_is_strict(identifications: dict[str, IdentificationResult], tmp_path: Path) -> None:
    ls = identifications["ls"]
    std = ls.std_errors.copy()
    std[3] = np.nan
    report = make_report({**identifications, "ls": dataclasses.replace(ls, std_errors=std)}, chosen="ls")
    json_path, _ = write_run_report(tmp_path, report)
    text = json_path.read_text()
    assert "NaN" not in text
    assert json.loads(text)["parameters"][ls.names[3]]["std_mm"] is None


class _Page(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[str] = []
        self.attrs: list[tuple[str, str, str]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        self.attrs += [(tag, k, v or "") for k, v in attrs]

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def parse(path: Path) -> _Page:
    page = _Page()
    page.feed(path.read_text(encoding="utf-8"))
    return page


def images(page: _Page) -> list[np.ndarray]:
    out = []
    for tag, key, value in page.attrs:
        if tag == "img" and key == "src":
            assert value.startswith("data:image/png;base64,")
            png = base64.b64decode(value.split(",", 1)[1])
            assert png[:8] == b"\x89PNG\r\n\x1a\n"
            out.append(matplotlib.image.imread(io.BytesIO(png), format="png"))
    return out


def assert_self_contained(page: _Page) -> None:
    assert not {"script", "link", "iframe", "object", "embed", "a"} & set(page.tags)
    for _tag, key, value in page.attrs:
        if key in ("src", "href"):
            assert value.startswith("data:"), value
        assert "http://" not in value and "https://" not in value


def test_html_is_self_contained_with_plots_and_table7(
    identifications: dict[str, IdentificationResult], tmp_path: Path
) -> None:
    json_path, html_path = write_run_report(tmp_path / "out", make_report(identifications))
    assert json.loads(json_path.read_text()) == report_json(make_report(identifications))
    page = parse(html_path)
    assert_self_contained(page)
    pictures = images(page)
    assert len(pictures) == 4
    assert all(p.shape[0] >= 300 and p.shape[1] >= 600 for p in pictures)
    text = " ".join(page.text)
    assert "6.0000" in text and "0.60000" in text  # before: max position (mm), max orientation (deg)
    assert "90.00" in text  # every indicator reduced by 90 %
    assert UPLOAD_SHA in text and "Committed to the controller" in text and "the live set read back matches" in text
    assert "position (mm)" in text and "orientation (deg)" in text
    assert all(row in text for row in ("maximum error", "range of error", "average error", "root-mean-square error"))
    assert "CMM temperature drifted" in text and "leg 6: leg length offset (mm)" in text


def test_aborted_run_without_upload(identifications: dict[str, IdentificationResult], tmp_path: Path) -> None:
    report = make_report(
        identifications, status="aborted", uploaded=False, verify_after=None, per_pose_after=None, upload=None,
        plausibility={"ok": False, "violations": ["leg3_dl0_mm = 7.2 mm exceeds 5 mm"], "bounds_mm": 5.0},
    )
    out = report_json(report)
    assert out["verification"]["after"] is None and out["table7"]["after"] is None
    assert out["table7"]["reduction_percent"] is None and out["upload"] is None
    assert out["plausibility"]["violations"] == ["leg3_dl0_mm = 7.2 mm exceeds 5 mm"]
    _, html_path = write_run_report(tmp_path, report)
    page = parse(html_path)
    assert_self_contained(page)
    assert len(images(page)) == 4
    text = " ".join(page.text)
    assert "NOT plausible" in text and "leg3_dl0_mm = 7.2 mm exceeds 5 mm" in text and "bounds_mm" not in text
    assert "nothing was uploaded" in text and "aborted" in text


def test_text_is_escaped(identifications: dict[str, IdentificationResult], tmp_path: Path) -> None:
    _, html_path = write_run_report(tmp_path, make_report(identifications, run_id="<script>alert(1)</script>"))
    page = parse(html_path)
    assert "script" not in page.tags
    assert "<script>alert(1)</script>" in " ".join(page.text)


def test_inconsistent_reports_are_refused(identifications: dict[str, IdentificationResult]) -> None:
    with pytest.raises(ValueError, match="chosen"):
        make_report(identifications, chosen="ridge")
    with pytest.raises(ValueError, match="per_pose_before"):
        make_report(identifications, per_pose_before=(POS_BEFORE_MM[:3], ORI_BEFORE_DEG[:3]))
    with pytest.raises(ValueError, match="both"):
        make_report(identifications, per_pose_after=None)

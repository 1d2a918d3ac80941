"""How `hilcal run` ends: the links' statistics, then a short summary of report.json (the verification poses before
and after with their uncertainty, an adaptive run's stop reason, what was uploaded, a laser tracker's stations, the
verdict, where the report and certificate are).

The same end for a plain run, a `--panel` run and a resumed one. report.json is read defensively: a key a run did
not reach (a refused upload, no sign-off) or one a later version adds is shown as such, never as a made-up number.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rich.console import Console, Group
from rich.rule import Rule
from rich.table import Table
from rich.text import Text

from hilcal.reports.upload import upload_facts

FIGURES = (("max_position_mm", "max position", "mm", 4), ("rms_position_mm", "RMS position", "mm", 4),
           ("max_orientation_deg", "max orientation", "deg", 5), ("rms_orientation_deg", "RMS orientation", "deg", 5))
"""The verification figures: report key, label, unit and decimals (as the accuracy tables print them)."""

MODES = {"full": "joint positions a, b and leg offsets l0", "offsets_only": "leg offsets l0 only"}
"""What each compensation mode of ``hilcal.compensation.compensate`` changes in the controller."""

RULE_NAMES = {"iso14253-1": "ISO 14253-1", "simple": "simple"}
"""The sign-off's decision rules by name (``hilcal.acceptance.verdict.RULES``)."""

VERDICT_STYLE = {"pass": "bold green", "fail": "bold red", "not proven": "bold yellow"}


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _figure(report: Mapping[str, Any], when: str, key: str, decimals: int) -> str:
    """'value ± U' from the sign-off's uncertainty, else the bare value from the verification, else 'not measured'."""
    uncertain = ((report.get("uncertainty") or {}).get(when) or {}).get(key) or {}
    value = _number(uncertain.get("value"))
    if value is None:
        value = _number(((report.get("verification") or {}).get(when) or {}).get(key))
    if value is None:
        return "not measured"
    spread = _number(uncertain.get("U"))
    return f"{value:.{decimals}f}" + ("" if spread is None else f" ± {spread:.{decimals}f}")


def accuracy_rows(report: Mapping[str, Any]) -> Table:
    """The verification poses before and after calibration: max and RMS, position and orientation, ± U (k = 2)."""
    n_verify = (report.get("method") or {}).get("n_verify_poses")
    after = ((report.get("per_pose") or {}).get("after") or {}).get("position_mm")
    n_after = sum(v is not None for v in after) if isinstance(after, list) else None
    table = Table(box=None, pad_edge=False, show_edge=False, padding=(0, 2, 0, 0))
    table.add_column(f"{n_verify} verification poses" if isinstance(n_verify, int) else "verification poses")
    table.add_column("before", justify="right")
    table.add_column("after" if n_after is None or n_after == n_verify else f"after ({n_after} poses)",
                     justify="right", style="bold")
    for key, label, unit, decimals in FIGURES:
        table.add_row(f"{label} ({unit})", _figure(report, "before", key, decimals),
                      _figure(report, "after", key, decimals))
    return table


def uploaded_lines(report: Mapping[str, Any]) -> list[str]:
    """What went into the controller: the compensation mode, the upload's outcome and hash, what physics it corrects."""
    if not report.get("uploaded"):
        return ["nothing uploaded" + ("" if report.get("status") in (None, "complete") else
                                      f" (run {report.get('status')})")]
    mode = (report.get("compensation") or {}).get("mode")
    upload = report.get("upload") or {}
    record = upload.get("record") or {}
    facts = upload_facts(upload)
    outcome = "outcome not recorded" if facts is None else facts.summary()
    sha = None if facts is None else facts.params_sha256
    lines = [MODES.get(mode, f"compensation mode {mode or 'not recorded'}"),
             outcome + (f" (sha256 {sha[:12]})" if isinstance(sha, str) else "")]
    physics = report.get("physics") if isinstance(report.get("physics"), Mapping) else {}
    block = (report.get("compensation") or {}).get("compensation_block")
    if block:
        lines.append("and the compensation block, one transaction with the geometry"
                     + {True: "; read back: matches", False: "; read back: DIFFERS"}.get(
                         record.get("compensation_readback_match"), ""))
    listed = False
    for key, label in (("corrected", "corrected"), ("not_corrected", "not corrected")):
        items = physics.get(key) if isinstance(physics.get(key), list) else []
        names = [_effect_name(c) for c in items]
        if names:
            lines.append(f"{label}: " + ", ".join(names))
            listed = True
    noise = _number(physics.get("noise_mm"))
    if physics.get("enabled") and not listed:
        lines.append("physics: nothing beyond the geometry" + ("" if noise is None else
                                                                 f" (noise yardstick {noise * 1000:.1f} µm)"))
    return lines


def _effect_name(c: Any) -> str:
    """An effect of the physics step as the summary names it."""
    if not isinstance(c, Mapping):
        return str(c)
    return str(c.get("title") or c.get("effect")) + (" (set-up fault)" if c.get("grade") == "fault" else "")


def verdict_text(report: Mapping[str, Any]) -> Text:
    """The sign-off's verdict, how many limits decided it, and each limit not passed with its figure ± U."""
    cert = report.get("certificate")
    if not isinstance(cert, Mapping) or not cert.get("verdict"):
        return Text("no sign-off in this report")
    verdict = str(cert["verdict"])
    limits = [c for c in cert.get("limits") or [] if isinstance(c, Mapping)]
    rule = (cert.get("decision_rule") or {}).get("key")
    text = Text(verdict, style=VERDICT_STYLE.get(verdict, ""))
    if limits:
        rule_words = f", {RULE_NAMES.get(rule, rule)} decision rule" if rule else ""
        text.append(f" ({len(limits)} limit{'s' if len(limits) != 1 else ''}{rule_words})")
    for c in limits:
        if c.get("decision") == "pass":
            continue
        value, spread = _number(c.get("value")), _number(c.get("U"))
        figure = "" if value is None else f": {value:.4g}" + ("" if spread is None else f" ± {spread:.2g}")
        text.append(f"; {c.get('label') or c.get('key')} {c.get('decision')}{figure} {c.get('unit', '')} against "
                    f"{c.get('limit')}")
    return text


def run_summary(report: Mapping[str, Any], report_path: Path, certificate_path: Path | None = None) -> Group:
    """The summary of one run's report.json, as a rich renderable (no markup is parsed: paths may hold brackets)."""
    from hilcal.reports.run import stations_lines  # here, not at start-up: plotting loads after the machine moved

    status = report.get("status") or "status not recorded"
    facts = Table.grid(padding=(0, 2))
    facts.add_column(style="bold")
    facts.add_column()
    adaptive = report.get("adaptive")
    if isinstance(adaptive, Mapping) and adaptive.get("summary"):
        facts.add_row("adaptive", Text(str(adaptive["summary"])))
    for n, line in enumerate(uploaded_lines(report)):
        facts.add_row("uploaded" if n == 0 else "", Text(line))
    for line in stations_lines(report.get("stations") if isinstance(report.get("stations"), Mapping) else None)[:1]:
        facts.add_row("instrument", Text(line))
    for n, line in enumerate(report.get("warnings") or []):
        facts.add_row("warning" if n == 0 else "", Text(str(line)))
    facts.add_row("verdict", verdict_text(report))
    facts.add_row("report", Text(f"{report_path.with_suffix('.html')} (and {report_path.name})"))
    if certificate_path is not None:
        facts.add_row("certificate", Text(str(certificate_path)))
    title = Text(f"run {report.get('run_id') or report_path.parent.name}: {status}")
    parts: list[Any] = [Rule(title, style="bold"), accuracy_rows(report)]
    if report.get("uncertainty"):
        parts.append(Text("± U: expanded uncertainty (k = 2) of each figure", style="dim"))
    return Group(*parts, facts)


def print_run_end(console: Console, report_path: Path | None, certificate_path: Path | None = None) -> None:
    """After the run's message: the links' statistics and the summary (nothing without a report)."""
    if report_path is None:
        return
    from hilcal.reports.run import links_lines  # here, not at start-up: plotting loads after the machine moved

    try:
        report = json.loads(report_path.read_text())
    except (OSError, ValueError) as e:
        console.print(f"report {report_path} unreadable: {e}", highlight=False, markup=False, soft_wrap=True)
        return
    for line in links_lines(report.get("links")):
        console.print(line, highlight=False, markup=False, soft_wrap=True)
    console.print(run_summary(report, report_path, certificate_path), highlight=False, markup=False)

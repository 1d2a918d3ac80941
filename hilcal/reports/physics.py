"""The run report's physics section: what the diagnosis of the run's own recording found, what the upload corrected
(with values and uncertainties), what it left and why, and the held-out accuracy it predicted against what the
verification then measured at the machine.
"""

from __future__ import annotations

import html
from typing import Any

from hilcal.reports.run_sections import FIGURES

BRIEF_KEYS = ("max_position_mm", "rms_position_mm", "max_orientation_deg", "rms_orientation_deg")


def _esc(value: object) -> str:
    return html.escape(str(value))


def _num(value: object, digits: int = 4) -> str:
    return "n/a" if value is None else f"{float(value):.{digits}f}"  # type: ignore[arg-type]


def _values(values: list[dict[str, Any]]) -> str:
    """Per parameter: leg, value ± standard error, unit."""
    cells = [f"leg {v['leg']}: {float(v['value']):+.4g} ± {float(v['std_error']):.2g} {_esc(v['unit'])}"
             if v.get("leg") else f"{float(v['value']):+.4g} ± {float(v['std_error']):.2g} {_esc(v['unit'])}"
             for v in values]
    return "; ".join(cells)


def prediction_rows(physics: dict[str, Any], measured_after: dict[str, float] | None,
                    offsets_only: bool = False) -> list[tuple[str, Any]]:
    """(label, brief) rows: predicted with the physics, predicted with the geometry alone, measured after; for a
    controller that holds the leg offsets only, the upload's prediction and what the joints would add."""
    if offsets_only:
        rows = [("predicted for the leg offsets uploaded (held-out verify poses)",
                 physics.get("predicted_with_physics")),
                ("with the joint positions too, which this controller does not hold (held-out verify poses)",
                 physics.get("predicted_geometry_only"))]
    else:
        rows = [("predicted with the physics (held-out verify poses)", physics.get("predicted_with_physics")),
                ("predicted with the geometry alone (held-out verify poses)", physics.get("predicted_geometry_only"))]
    rows.append(("measured at the machine after the upload", measured_after))
    return [(label, brief) for label, brief in rows if brief is not None]


def physics_lines(physics: dict[str, Any] | None) -> list[str]:
    """The section as plain sentences (the terminal's and the certificate's view): faults first."""
    if not physics:
        return []
    if not physics.get("enabled", True):
        return ["Physics: not diagnosed (--physics off): the geometry alone was uploaded."]
    lines = [*physics.get("corrects", []), *physics.get("leaves", [])]
    lines += [f"Set by hand: {text}" for text in physics.get("by_hand", [])]
    if physics.get("explained"):
        lines.append("The geometric fit alone needed " + "; ".join(physics["explained"]) + ": the physics above "
                     "explains it, so the geometry fitted together with it is the one uploaded.")
    if physics.get("noise_mm") is not None:
        source = physics.get("noise_source")
        lines.append(f"Noise yardstick: {float(physics['noise_mm']) * 1000:.1f} µm RMS pose position noise "
                     f"({NOISE_SOURCES.get(source, source)}).")
    return lines


NOISE_SOURCES = {"sphere_fit_rms_mm column": "from how closely each pose's spheres fitted the CMM's touch points",
                 "robot file cmm.sphere_sigma_mm": "the sphere-centre standard deviation the robot file gives",
                 "--cmm-sigma-mm": "as given with --cmm-sigma-mm"}
"""Where the diagnosis' noise yardstick came from, in words."""


def physics_html(physics: dict[str, Any] | None, measured_after: dict[str, float] | None,
                 offsets_only: bool = False) -> str:
    """The report page's section (offsets_only: the controller holds the leg offsets only)."""
    if not physics:
        return "<p>no diagnosis (the run stopped before identification)</p>"
    items = "".join(f"<li>{_esc(line)}</li>" for line in physics_lines(physics))
    corrected = "".join(
        f"<tr><td>{_esc(c['title'])}</td><td>{_esc(c['grade'])}</td><td>{_esc(_values(c.get('values') or []))}</td>"
        f"<td>{_esc(c.get('why_not') or 'corrected by the upload')}</td></tr>"
        for c in [*physics.get("corrected", []), *physics.get("not_corrected", [])])
    table = ("<table><tr><th>effect</th><th>grade</th><th>values ± standard error</th><th>in the upload</th></tr>"
             f"{corrected}</table>") if corrected else ""
    head = "".join(f"<th>{label} ({unit})</th>" for label, unit, _ in FIGURES.values())
    rows = "".join(f"<tr><th>{_esc(label)}</th>" + "".join(f"<td>{_num(brief.get(k), 5)}</td>" for k in BRIEF_KEYS)
                   + "</tr>" for label, brief in prediction_rows(physics, measured_after, offsets_only))
    accuracy = f'<table class="kv"><tr><th></th>{head}</tr>{rows}</table>' if rows else ""
    return (f"<p>geometry uploaded: {_esc(physics.get('geometry_source'))}; compensation block: "
            f"{'uploaded' if physics.get('block') else 'left as the controller held it'}</p>"
            f"<ul>{items}</ul>{table}{accuracy}")

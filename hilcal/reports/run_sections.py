"""The run report's sections in words: every figure named with its unit, the plausibility check explained, the
uploaded geometry and compensation block per leg, the simulated machine, the upload and the links.

Pure: each function turns a part of report.json into HTML (or lines for the terminal); report.json keeps its keys.
"""

from __future__ import annotations

import html
import math
import re
from collections.abc import Mapping
from typing import Any

from hilcal.reports.upload import upload_facts

FIGURES = {"max_position_mm": ("largest position error", "mm", 4), "rms_position_mm": ("RMS position error", "mm", 4),
           "max_orientation_deg": ("largest orientation error", "deg", 5),
           "rms_orientation_deg": ("RMS orientation error", "deg", 5)}
"""The four figures of a verification, in words, with their unit and digits."""

BLOCK_TERMS = {"scale_ppm": ("reading scale", "ppm"), "backlash_mm": ("backlash", "mm"),
               "compliance_mm_per_kn": ("leg compliance", "mm/kN"),
               "compliance_mm_per_kn_m": ("oil-column compliance", "mm/(kN m)"),
               "thermal_ppm_per_k": ("thermal growth", "ppm/K"), "table_start_mm": ("correction table from", "mm"),
               "table_end_mm": ("correction table to", "mm")}
"""The per-leg terms of a controller's compensation block, in words with their unit."""

_PARAMETER = re.compile(r"^leg(\d+)_(da|db|dl0|dl|du)(?:_([xyz]))?_(mm|rad)$")
_PARTS = {"da": "platform joint position", "db": "base joint position", "dl0": "leg length offset",
          "dl": "leg length error", "du": "leg direction"}
UPLOAD_IDENTIFIERS = (("params_sha256", "uploaded set, SHA-256"), ("params_crc32", "uploaded set, CRC-32 checksum"),
                      ("previous_live_sha256", "set it replaced, SHA-256"),
                      ("live_after_sha256", "live set read back after the commit, SHA-256"),
                      ("compensation_sha256", "compensation block, SHA-256"),
                      ("previous_compensation_sha256", "block it replaced, SHA-256"))
"""The identifiers of an upload shown in report.html, with what each is in words."""
REQUESTS = {"write_register": "write one register", "write_registers": "write registers",
            "read_holding_registers": "read registers"}
"""Modbus requests in words (the function codes 6, 16 and 3)."""


def _esc(value: object) -> str:
    return "–" if value is None else html.escape(str(value), quote=True)


def _num(value: Any, digits: int) -> str:
    return "n/a" if not isinstance(value, int | float) or not math.isfinite(value) else f"{value:.{digits}f}"


def parameter_words(name: str) -> str:
    """A parameter's name in words with its unit: leg1_da_x_mm -> "leg 1: platform joint position, x (mm)"."""
    m = _PARAMETER.match(name)
    if m is None:
        return name.replace("_", " ")
    leg, part, axis, unit = m.groups()
    return f"leg {leg}: {_PARTS[part]}" + (f", {axis}" if axis else "") + f" ({unit})"


def figures_sentence(before: Mapping[str, Any], after: Mapping[str, Any] | None) -> str:
    """The verification's four figures, before and after: "largest position error 1.9341 mm → 0.0046 mm, ..."."""
    parts = []
    for key, (label, unit, digits) in FIGURES.items():
        then = f"{_num(before.get(key), digits)} {unit}"
        parts.append(f"{label} {then} → " + (f"{_num(after.get(key), digits)} {unit}" if after else "not measured"))
    return ", ".join(parts)


def figures_table(rows: list[tuple[str, Mapping[str, Any] | None]]) -> str:
    """One row per labelled set of the four figures, each column named with its unit."""
    head = "".join(f"<th>{label} ({unit})</th>" for label, unit, _ in FIGURES.values())
    body = "".join(f"<tr><th>{_esc(label)}</th>" + "".join(
        f"<td>{_num((values or {}).get(key), digits)}</td>" for key, (_, _, digits) in FIGURES.items()) + "</tr>"
        for label, values in rows)
    return f'<table class="kv"><tr><th></th>{head}</tr>{body}</table>'


def plausibility_html(plausibility: Mapping[str, Any]) -> str:
    """The check that guards the upload, explained: its bounds and, for a set beyond them, why it was refused."""
    joint, offset = plausibility.get("joint_bound_mm"), plausibility.get("offset_bound_mm")
    bounds = "within the bounds a machine's assembly allows"
    if isinstance(joint, int | float) and isinstance(offset, int | float):
        bounds = (f"one a machine's assembly can have: each joint within {joint:g} mm of its nominal position and each "
                  f"leg's length offset within {offset:g} mm")
    rule = (f"An identified set is plausible when it converged, every parameter is determined and every correction "
            f"is {bounds}. A larger correction means a wrong robot file or a gross fault (a wrongly wired transducer, "
            "a loose joint), and the run does not upload it unless told to (--force).")
    if plausibility.get("ok"):
        return f"<p><b>Plausible</b>: the identified corrections are within these bounds. {rule}</p>"
    violations = "".join(f"<li>{_esc(v)}</li>" for v in plausibility.get("violations", []))
    return f"<p><b>NOT plausible</b>: nothing was uploaded. {rule}</p><ul>{violations}</ul>"


def _legs_table(columns: list[tuple[str, list[Any], int]]) -> str:
    """Legs as rows, one column per (heading, six values, digits); a value may be a vector."""
    head = "".join(f"<th>{_esc(h)}</th>" for h, _, _ in columns)
    rows = ""
    for leg in range(6):
        cells = ""
        for _, values, digits in columns:
            v = values[leg] if leg < len(values) else None
            cells += "<td>" + (", ".join(_num(x, digits) for x in v) if isinstance(v, list) else _num(v, digits)) + \
                "</td>"
        rows += f"<tr><th>leg {leg + 1}</th>{cells}</tr>"
    return f'<table class="kv"><tr><th></th>{head}</tr>{rows}</table>'


def compensation_html(compensation: Mapping[str, Any]) -> str:
    """What the run uploaded (or would have): the controller's geometry per leg, its compensation block in words,
    the accuracy the uploaded model predicts on the held-out poses, and what leg offsets alone leave."""
    if not compensation:
        return "<p>Nothing was identified, so nothing was prepared for the controller.</p>"
    mode = compensation.get("mode")
    what = {"full": "the joint positions of both platforms and the leg offsets",
            "offsets_only": "the leg offsets alone (the controller holds no joint positions)"}.get(mode, _esc(mode))
    p = compensation.get("uploaded_parameters") or {}
    out = [f"<p>The controller's geometry: {what}.</p>", _legs_table([
        ("platform joint a: x, y, z (mm)", p.get("a_mm") or [], 3),
        ("base joint b: x, y, z (mm)", p.get("b_mm") or [], 3),
        ("leg length at zero reading l0 (mm)", p.get("l0_mm") or [], 3)])]
    block = compensation.get("compensation_block")
    if not block:
        out.append("<p>The controller's compensation block: left as it was (nothing beyond the geometry to "
                   "compensate, or a controller without one).</p>")
    else:
        terms = [(f"{label} ({unit})", block.get(key) or [], 4) for key, (label, unit) in BLOCK_TERMS.items()
                 if any(block.get(key) or [])]
        points = len((block.get("table_mm") or [[]])[0])
        out.append("<p>The controller's compensation block" + (f", with a correction table of {points} points per "
                   "leg" if points else "") + f" (reference temperature {_num(block.get('reference_temperature_c'), 1)}"
                   " °C):</p>" + (_legs_table(terms) if terms else "<p>every term zero.</p>"))
    held_out = compensation.get("predicted_held_out")
    if held_out:
        out.append(f"<p>Predicted on the held-out verification poses (measured before the upload and not used in "
                   f"the fit; the verification after the upload measures it): {figures_sentence(held_out, None)}"
                   .replace(" → not measured", "") + ".</p>")
    left = compensation.get("uncompensated")
    if left:
        out.append("<p>What the leg offsets alone cannot correct of the identified geometry, over 64 workspace "
                   f"poses: {figures_sentence(left, None).replace(' → not measured', '')}.</p>")
    return "".join(out)


def simulation_lines(simulation: Mapping[str, Any] | None) -> list[str]:
    """What a simulated run simulated and the timing it ran with, in sentences (none for a real run)."""
    if not simulation:
        return []
    lines = [str(line).rstrip() for line in simulation.get("lines") or []]
    if simulation.get("timing"):
        lines.append(f"  timing: {simulation['timing']}")
    return lines


def simulation_html(simulation: Mapping[str, Any] | None) -> str:
    lines = simulation_lines(simulation)
    if not lines:
        return ""
    return ("<h2>The simulated machine</h2><p>This run measured simulated devices, not a machine.</p><ul>"
            + "".join(f"<li>{_esc(line.strip())}</li>" for line in lines) + "</ul>")


def links_lines(links: dict | None) -> list[str]:
    """One line per link: how often the run held or retried on it and for how long (s)."""
    if not links:
        return ["links: not recorded"]
    return [f"{name}: {v['holds']} holds/retries, {v['retakes']} poses re-taken, held {v['held_s']:.2f} s in all "
            f"(longest {v['longest_hold_s']:.2f} s){', LOST' if v['lost'] else ''}" for name, v in links.items()]


def stations_lines(stations: dict | None) -> list[str]:
    """How many stations the instrument measured from and after which poses it was set up again (none: no lines)."""
    if not stations:
        return []
    moves = stations.get("moves") or []
    after = ", ".join(str(mv.get("after_pose")) for mv in moves)
    count = stations.get("count")
    return [f"{count} station{'' if count == 1 else 's'}" + (f": set up again after {after}" if moves else
                                                               ": never moved"),
            *(f"station {mv.get('station')} from {mv.get('first_pose')}: moved {mv.get('moved_mm', 0):.1f} mm, "
              f"turned {mv.get('turned_deg', 0):.3f}° (its monuments {mv.get('monument_shift_mm', 0):.1f} mm off in "
              f"its view; a new station beyond {mv.get('threshold_mm', 0):.2f} mm)" for mv in moves)]


def links_html(links: dict | None) -> str:
    return "<ul>" + "".join(f"<li>{_esc(line)}</li>" for line in links_lines(links)) + "</ul>"


def upload_html(upload: Mapping[str, Any] | None) -> str:
    """The upload's story (``hilcal.reports.upload``), its identifiers in words and every write to the controller."""
    facts = upload_facts(upload)
    if facts is None or upload is None:
        return "<p>nothing was uploaded to the controller.</p>"
    record = upload.get("record") or upload
    ids = [(label, record.get(key)) for key, label in UPLOAD_IDENTIFIERS if record.get(key)]
    table = "".join(f"<tr><th>{_esc(label)}</th><td><code>{_esc(value)}</code></td></tr>" for label, value in ids)
    writes = record.get("writes") or []
    rows = "".join(
        f"<tr><td>{_esc(REQUESTS.get(str(w.get('function')), w.get('function')))}</td>"
        f"<td>0x{int(w.get('address', 0)):04X}</td><td>{_esc(w.get('count'))}</td>"
        f"<td>{_esc(str(w.get('at') or '')[:23].replace('T', ' '))}</td><td>{'yes' if w.get('ok') else 'NO'}</td>"
        f"<td>{_esc(w.get('error') or '')}</td></tr>" for w in writes)
    writes_html = (f"<details><summary>every write to the controller ({len(writes)})</summary><table><tr>"
                   "<th>request</th><th>first register</th><th>registers</th><th>time (UTC)</th><th>answered</th>"
                   f"<th>error</th></tr>{rows}</table></details>") if writes else ""
    story = "".join(f"<p>{_esc(line)}</p>" for line in facts.sentences())
    return f'{story}<table class="kv">{table}</table>{writes_html}'

"""docs/diagnosis.md's coverage figures, between its markers, from a run of the coverage study."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[3]


def fmt(v: float | None, digits: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def percent(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.1f} %"


METHOD_DOC = ROOT / "docs" / "diagnosis.md"
MARKERS = ("<!-- coverage:begin -->", "<!-- coverage:end -->")


def update_method_doc(summary: dict[str, Any], before: dict[str, Any] | None, command: str) -> None:
    """docs/diagnosis.md's coverage figures (between MARKERS), from this run; `before`: the same recordings on
    commit 92858cb."""
    text = METHOD_DOC.read_text()
    if MARKERS[0] not in text:
        return
    lines = [f"From `python {command}` on {time.strftime('%Y-%m-%d')} ([coverage_study.md](coverage_study.md); "
             "before: the same recordings on commit 92858cb, before the readings' noise, the repeats and the complete "
             "model's residual entered the errors):", ""]
    for g, s in summary.items():
        was = (before or {}).get(g)
        lines.append(f"- {g}: {percent(s['within_2'])} of {s['stated']} stated parameters within 2 standard errors, "
                     f"median abs(z) {fmt(s['median_abs_z'])}, {s['beyond_4']} beyond 4 (largest "
                     f"{fmt(s['max_abs_z'])}); said incomplete in {s['incomplete']} of {s['recordings']} recordings"
                     + (f"; before: {percent(was['within_2'])}, median {fmt(was['median_abs_z'])}, {was['beyond_4']} "
                        f"beyond 4 (largest {fmt(was['max_abs_z'])})." if was else "."))
    head, rest = text.split(MARKERS[0], 1)
    tail = rest.split(MARKERS[1], 1)[1]
    METHOD_DOC.write_text(head + MARKERS[0] + "\n" + "\n".join(lines) + "\n" + MARKERS[1] + tail)

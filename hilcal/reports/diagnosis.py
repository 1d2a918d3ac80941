"""`hilcal diagnose --report DIR`: plots, diagnosis.json, the compensation set (compensation.json with the refitted
geometry and every term, and one CSV table per generic term), proposed extra poses (CSV), the digital twin's
comparison (twin.json, twin.png; its sim_config.toml is written by the command) and a self-contained index.html
that opens with one sentence per finding and the parameter table.

The compensation set is consistent: geometric length = reported + the sum of its terms, with its geometry; every
table is the correction (mm) to ADD to the reported length of its leg against its variable, over the recorded
range only, with the 95 % band of the shape where there is one.
"""

from __future__ import annotations

import base64
import csv
import html
import json
from pathlib import Path

import numpy as np

from hilcal.discovery.corrections import CompensationSet, Term
from hilcal.discovery.explain import title_of
from hilcal.discovery.result import Diagnosis, Shape, Step
from hilcal.reports import diagnosis_plots as plots
from hilcal.reports.diagnosis_twin import TwinComparison, twin_html, twin_plot
from hilcal.robot import POSE_AXES


def _slug(key: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in key).strip("_")


def write_correction_table(term: Term, shape: Shape | None, path: Path) -> None:
    """One row per grid point of a table term: the variable, the correction and its 95 % band (mm)."""
    assert term.grid is not None and term.correction_mm is not None
    band = np.zeros(term.grid.size)
    if shape is not None and shape.grid.shape[1] == 1 and shape.band_mm.size:
        band = np.interp(term.grid, shape.grid[:, 0], shape.band_mm)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["leg", term.variable, "correction_mm", "band_low_mm", "band_high_mm"])
        for x, c, b in zip(term.grid, term.correction_mm, band, strict=True):
            w.writerow([term.leg + 1, f"{x:.9g}", f"{c:.7f}", f"{c - b:.7f}", f"{c + b:.7f}"])


def write_compensation(diag: Diagnosis, out_dir: Path) -> dict[tuple[str, int], str]:
    """compensation.json (geometry and terms; tables by file name) and one CSV per table term; {(group, leg): file}."""
    comp: CompensationSet | None = diag.compensation
    files: dict[tuple[str, int], str] = {}
    if comp is None:
        return files
    shapes = {(s.group.key, s.leg): s for s in diag.shapes}
    terms = []
    for term in comp.terms:
        entry = term.to_json()
        if term.grid is not None and term.variable != "session":
            name = f"correction_{_slug(term.group)}_leg{term.leg + 1}_{_slug(term.variable)}.csv"
            write_correction_table(term, shapes.get((term.group, term.leg)), out_dir / name)
            entry.pop("table", None)
            entry["file"] = name
            files[(term.group, term.leg)] = name
        terms.append(entry)
    data = {**comp.to_json(), "terms": terms}
    (out_dir / "compensation.json").write_text(json.dumps(data, indent=2))
    return files


def write_poses(poses: np.ndarray, path: Path) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(POSE_AXES)
        for pose in poses:
            w.writerow([f"{v:.4f}" for v in pose])


def _img(path: Path) -> str:
    if not path.exists():
        return ""
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img alt="{html.escape(path.name)}" src="data:image/png;base64,{data}">'


def _table(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _fmt(v: float | None, spec: str = ".3g") -> str:
    return "" if v is None or not np.isfinite(v) else format(v, spec)


def _verdict(step: Step) -> str:
    """'confirmed' or 'NOT confirmed' with the held-out figures (session shift removed when one is reported)."""
    if step.confirmed is None or step.judged_mm is None or step.judged_before_mm is None:
        return ""
    word = "confirmed" if step.confirmed else "NOT confirmed"
    return f"{word} ({step.judged_before_mm:.4f} -> {step.judged_mm:.4f} mm)"


def write_report(diag: Diagnosis, out_dir: Path, twin: TwinComparison | None = None,
                 twin_notes: tuple[str, ...] = ()) -> Path:
    """Write every file of the report into out_dir; return the page path. With `twin` (the recording replayed on the
    digital twin, see procedures/cli/twin.py) also twin.json, twin.png and the page's twin section."""
    out_dir.mkdir(parents=True, exist_ok=True)
    twin_section = ""
    if twin is not None:
        (out_dir / "twin.json").write_text(json.dumps({**twin.to_json(), "notes": list(twin_notes)}, indent=2))
        twin_plot(twin, out_dir / "twin.png")
        twin_section = twin_html(twin, _img(out_dir / "twin.png"), twin_notes)
    plots.leg_plot(diag, out_dir / "legs.png")
    plots.time_plot(diag, out_dir / "time.png")
    plots.waterfall_plot(diag, out_dir / "steps.png")
    plots.noise_plot(diag, out_dir / "noise.png")
    (out_dir / "diagnosis.json").write_text(json.dumps(diag.to_json(), indent=2))
    tables = write_compensation(diag, out_dir)
    shape_html = []
    for shape in diag.shapes:
        slug = _slug(shape.group.key if shape.group.leg is not None else f"{shape.group.key}_leg{shape.leg + 1}")
        plots.shape_plot(diag, shape, out_dir / f"shape_{slug}.png")
        table = tables.get((shape.group.key, shape.leg))
        extra = ""
        if shape.proposed_poses is not None and len(shape.proposed_poses):
            write_poses(shape.proposed_poses, out_dir / f"extra_poses_{slug}.csv")
            extra = f"<p>Proposed extra poses: <code>extra_poses_{slug}.csv</code> ({len(shape.proposed_poses)})</p>"
        name = shape.group.title if shape.group.leg is not None else f"leg {shape.leg + 1}: {shape.group.title}"
        shape_html.append(f"<h3>{html.escape(name)}</h3><p>{html.escape(shape.group.sentence)}. "
                          + (f"Correction table: <code>{html.escape(table)}</code>. " if table else "") +
                          f"{'' if shape.pinned else html.escape('Not pinned down: ' + shape.why_not_pinned)}</p>"
                          f"{extra}{_img(out_dir / f'shape_{slug}.png')}")
    steps = _table(
        ["step", "group", "kind", "params", "F", "p (family-wise)", "CV before µm", "CV after µm", "verify RMS mm",
         "held-out verdict", "removed"],
        [[str(s.index), s.key, s.kind, str(s.n_params), _fmt(s.f_statistic, ".1f"), _fmt(s.p_value),
          _fmt(s.cv_before_mm * 1000, ".2f"), _fmt(s.cv_rms_mm * 1000, ".2f"),
          "" if s.verify is None else f"{s.verify.position_mm.rms:.4f}", _verdict(s), ", ".join(s.removed)]
         for s in diag.steps],
    )
    candidates = _table(
        ["candidate", "testable", "F", "p (family-wise)", "CV µm", "chosen", "note"],
        [[c.name, "yes" if c.applicable else "no", _fmt(c.f_statistic, ".2f"), _fmt(c.p_value),
          _fmt(c.cv_rms_mm * 1000, ".2f"), "yes" if c.selected else "", c.rejected or c.reason or ""]
         for c in diag.candidates],
    )
    noise_rows = [[e.source, f"{e.position_mm * 1000:.2f}", _fmt(e.sphere_sigma_mm and e.sphere_sigma_mm * 1000, ".2f"),
                   _fmt(e.dof, ".0f")] for e in diag.noise.estimates]
    noise = _table(["source", "pose position noise µm RMS", "sphere-centre sigma µm", "dof"], noise_rows) \
        if noise_rows else "<p>noise level unknown: relative tests only</p>"
    params = _table(["effect", "leg", "value", "unit", "std error (cluster-robust)", "grade"],
                    [[r.effect, "" if r.leg is None else str(r.leg), f"{r.value:+.4g}", r.unit,
                      _fmt(r.std_error, ".2g"), r.grade] for r in diag.parameter_table])
    summary = "".join(f"<li>{html.escape(s)}</li>" for s in diag.summary) or "<li>nothing to report</li>"

    def acc(summary: object) -> str:
        return "n/a" if summary is None else ", ".join(f"{k} {v:.4f}" for k, v in summary.brief().items())

    findings = "".join(f"<li>{html.escape(f.text)}</li>" for f in diag.findings) or "<li>none stand out</li>"
    title = ", ".join(title_of(e) for e in diag.effects) or "none"
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>hilcal diagnosis: {html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}}img{{max-width:100%;display:block;margin:1em 0}}
table{{border-collapse:collapse;margin:.5em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}</style>
</head><body><h1>Missing physics: {html.escape(title)}</h1><ul>{summary}</ul>
<h2>Named effects: parameters</h2>{params}<p>The compensation set (geometry and every leg's terms):
<code>compensation.json</code>.</p>
<h2>Evidence</h2><p>{html.escape(diag.explanation)}</p>
<h2>Held-out verification poses</h2><p>geometry only: {acc(diag.before)}<br>final model: {acc(diag.after)}</p>
<h2>Selection steps</h2>{steps}{_img(out_dir / "steps.png")}
{twin_section}
<h2>Noise yardstick</h2>{noise}{_img(out_dir / "noise.png")}
<h2>Unexplained terms</h2>{''.join(shape_html) or '<p>none</p>'}
<h2>Library candidates (first step)</h2>{candidates}
<h2>Where the mismatch lives</h2><p>Each leg's residual under the geometry alone (before any effect is
fitted), against the pose and leg variables; the effects above may explain these.</p>
<ul>{findings}</ul>{_img(out_dir / "legs.png")}{_img(out_dir / "time.png")}
</body></html>"""
    path = out_dir / "index.html"
    path.write_text(page)
    return path

"""The calibration certificate: a printable A4 page (one or two sheets) made from report.json alone.

It carries what ISO/IEC 17025 section 7.8 asks of a calibration certificate: a unique number, the calibrated machine
and where, who and when, the instrument with its uncertainty and calibration status, the environment, the method,
the results before and after with their expanded uncertainty (k = 2), the ISO 9283 table, the verdict with its
decision rule, the uploaded parameter set with the controller's read-back, and signature lines. Pure: it only turns
the report's JSON into HTML; ``procedures.certificate`` writes the files and prints the PDF.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping
from typing import Any

from hilcal.reports.physics import NOISE_SOURCES
from hilcal.reports.upload import upload_facts

_CSS = """@page{size:A4;margin:13mm 13mm 15mm 13mm}
*{box-sizing:border-box}body{font-family:"DejaVu Sans",Arial,sans-serif;font-size:8.6pt;color:#111;margin:0 auto;
max-width:186mm;line-height:1.3;-webkit-print-color-adjust:exact}
h1{font-size:15pt;margin:0}h2{font-size:10pt;margin:3.2mm 0 1.2mm;border-bottom:.4pt solid #555}
header{display:flex;justify-content:space-between;align-items:flex-end;border-bottom:1.2pt solid #111;
padding-bottom:2mm}.number{font-size:11pt;font-weight:bold;text-align:right;white-space:nowrap}
.badge{display:inline-block;font-size:10pt;padding:.5mm 2.4mm;border:.8pt solid #111;margin-top:1mm}
table{border-collapse:collapse;width:100%;margin:.6mm 0}td,th{border:.4pt solid #999;padding:.5mm 1.4mm;
text-align:left;vertical-align:top}td.n{text-align:right;white-space:nowrap;font-variant-numeric:tabular-nums}
table.kv th{width:34%;background:#f2f2f2;font-weight:normal}th{background:#eaeaea}
section{break-inside:avoid}.verdict{font-size:12pt;font-weight:bold;padding:1.6mm 3mm;border:1pt solid #111;
margin:1mm 0}.pass{background:#dcefdc}.fail{background:#f6d5d5}.notproven{background:#fbefcc}
.none{background:#eeeeee}.warn{border:.6pt solid #b38600;background:#fff6d6;padding:1mm 2mm;margin:1mm 0}
.small{font-size:7.4pt;color:#333}.sig{display:flex;gap:12mm;margin-top:7mm}.sig div{flex:1;
border-top:.6pt solid #111;padding-top:1mm}code{font-size:7.4pt;word-break:break-all}
table.iso td,table.iso th{font-size:7.5pt;padding:.4mm .9mm}sub{line-height:0}
@media screen{body{margin:8mm auto;padding:0 6mm}}"""

ESTIMATORS = {"ls": "least-squares", "linf": "L-infinity (minimax)"}
DECISION_CLASS = {"pass": "pass", "fail": "fail", "not proven": "notproven", "not tested": "notproven"}


def _esc(value: object) -> str:
    return "–" if value is None else html.escape(str(value), quote=True)


def _yes(value: object) -> str:
    if value is None or isinstance(value, bool):
        return {True: "yes", False: "<b>NO</b>"}.get(value, "–")
    return _esc(value)


def _when(iso_time: object) -> str:
    """An ISO 8601 UTC time as 2026-11-23 19:06:36 UTC."""
    text = str(iso_time or "")
    return _esc(text[:19].replace("T", " ") + " UTC") if len(text) >= 19 else _esc(iso_time or None)


def _num(value: float | None, digits: int) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _fig(figure: Mapping[str, Any] | None, digits: int) -> str:
    """value ± U (k = 2)."""
    if not figure or figure.get("value") is None:
        return "–"
    u = figure.get("U")
    return _num(figure["value"], digits) + ("" if u is None else f" ± {_num(u, digits)}")


def _kv(rows: list[tuple[str, str]]) -> str:
    return '<table class="kv">' + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _results(report: Mapping[str, Any]) -> str:
    unc = report.get("uncertainty") or {}
    before, after = unc.get("before") or {}, unc.get("after") or {}
    rows = ""
    for key, label, digits in (("max_position_mm", "largest position error (mm)", 4),
                               ("rms_position_mm", "RMS position error (mm)", 4),
                               ("max_orientation_deg", "largest orientation error (deg)", 5),
                               ("rms_orientation_deg", "RMS orientation error (deg)", 5)):
        rows += (f"<tr><th>{label}</th><td class='n'>{_fig(before.get(key), digits)}</td>"
                 f"<td class='n'>{_fig(after.get(key), digits)}</td></tr>")
    n = (report.get("method") or {}).get("n_verify_poses")
    return (f"<table><tr><th>at the {_esc(n)} verification poses (measured against commanded)</th>"
            f"<th>before calibration</th><th>after calibration</th></tr>{rows}</table>")


def _iso_table(iso: Mapping[str, Any] | None) -> str:
    if not iso:
        return "<p>The ISO 9283 acceptance test was not part of this run.</p>"
    accuracy = repeatability = ""
    for p in iso["poses"]:
        c = p["commanded"]
        head = f"<tr><th>{_esc(p['pose'])}</th>"
        accuracy += (f"{head}<td class='n'>{_num(c[0], 1)}, {_num(c[1], 1)}, {_num(c[2], 1)}</td>"
                     f"<td class='n'>{_fig(p['ap_p_mm'], 4)}</td>"
                     + "".join(f"<td class='n'>{_fig(p[f'ap_{a}_deg'], 5)}</td>" for a in "abc") + "</tr>")
        repeatability += (f"{head}<td class='n'>{p['n_cycles']}</td><td class='n'>{_num(p['l_mean_mm'], 4)}</td>"
                          f"<td class='n'>{_num(p['s_l_mm'], 4)}</td><td class='n'>{_fig(p['rp_l_mm'], 4)}</td>"
                          + "".join(f"<td class='n'>{_fig(p[f'rp_{a}_deg'], 5)}</td>" for a in "abc") + "</tr>")
    cube = iso["cube"]
    notes = "".join(f"<li>{_esc(n)}</li>" for n in iso.get("notes", []))
    return (f"<table class='iso' id='iso-accuracy'><tr><th>pose</th><th>commanded x, y, z (mm)</th>"
            f"<th>AP<sub>P</sub> (mm)</th><th>AP<sub>a</sub> (deg)</th><th>AP<sub>b</sub> (deg)</th>"
            f"<th>AP<sub>c</sub> (deg)</th></tr>{accuracy}"
            f"</table><table class='iso' id='iso-repeatability'><tr><th>pose</th><th>cycles</th><th>l̄ (mm)</th>"
            f"<th>S<sub>l</sub> (mm)</th><th>RP<sub>l</sub> (mm)</th><th>RP<sub>a</sub> (±deg)</th>"
            f"<th>RP<sub>b</sub> (±deg)</th><th>RP<sub>c</sub> (±deg)</th></tr>{repeatability}</table>"
            f"<p class='small'>{_esc(iso['standard'])}: test cube of side {_num(cube['side_mm'], 1)} mm centred at "
            f"{_esc([round(v, 1) for v in cube['centre_mm']])} mm, orientation {_esc(cube['orientation_deg'])} deg; "
            f"{iso['cycles']} cycles of {', '.join(iso['order'])}, every pose approached from the same side. "
            "AP<sub>P</sub> = |barycentre − commanded position|; AP<sub>a,b,c</sub> = mean − commanded angle; "
            "RP<sub>l</sub> = l̄ + 3 S<sub>l</sub>; RP<sub>a,b,c</sub> = ±3 S<sub>a,b,c</sub>. Values ± U "
            "(k = 2).</p>" + (f"<ul class='small'>{notes}</ul>" if notes else ""))


def _verdict(cert: Mapping[str, Any]) -> str:
    verdict = cert.get("verdict") or "–"
    css = DECISION_CLASS.get(verdict, "none")
    rows = "".join(
        f"<tr><td>{_esc(c['label'])}</td><td>{_esc(c['where'])}</td>"
        f"<td class='n'>{_fig({'value': c['value'], 'U': c['U']}, 5)} {_esc(c['unit'])}</td>"
        f"<td class='n'>≤ {_num(c['limit'], 5)} {_esc(c['unit'])}</td>"
        f"<td class='{DECISION_CLASS.get(c['decision'], 'none')}'><b>{_esc(c['decision'])}</b></td></tr>"
        for c in cert.get("limits", []))
    table = (f"<table><tr><th>limit</th><th>deciding figure</th><th>value ± U</th><th>limit</th><th>decision</th>"
             f"</tr>{rows}</table>") if rows else ""
    rule = (cert.get("decision_rule") or {}).get("text", "")
    return (f"<div class='verdict {css}' id='verdict'>Verdict: {_esc(verdict)}</div>{table}"
            f"<p class='small'>Decision rule: {_esc(rule)}</p>")


def _upload(report: Mapping[str, Any]) -> str:
    upload = report.get("upload") or {}
    facts = upload_facts(upload)
    if facts is None or not upload.get("record"):
        return "<p>No parameter set was uploaded in this run.</p>"
    record = upload["record"]
    rows = [("uploaded parameter set, SHA-256", f"<code>{_esc(facts.params_sha256)}</code>")]
    if record.get("compensation_sha256"):
        rows.append(("compensation block, SHA-256", f"<code>{_esc(record.get('compensation_sha256'))}</code>"))
    rows.append(("controller", _esc(facts.endpoint)))
    return _kv(rows) + "".join(f"<p>{_esc(line)}</p>" for line in facts.sentences())


def _compensation(report: Mapping[str, Any]) -> str:
    """What the upload compensated beyond the geometry, each effect with its values ± standard error, and what it
    left (the run's physics step)."""
    physics = report.get("physics") or {}
    if not physics:
        return "<p>The geometry alone was identified.</p>"
    if not physics.get("enabled", True):
        return "<p>The geometry alone was uploaded (missing physics not diagnosed: --physics off).</p>"
    rows = []
    for c in [*physics.get("corrected", []), *physics.get("not_corrected", [])]:
        values = "; ".join(
            (f"leg {v['leg']}: " if v.get("leg") else "") + f"{float(v['value']):+.4g} ± {float(v['std_error']):.2g} "
            f"{_esc(v['unit'])}" for v in c.get("values") or []) or _esc(c.get("sentence"))
        status = "compensated" if not c.get("why_not") and physics.get("block") else (
            _esc(c.get("why_not")) or "not compensated: the controller has no compensation block")
        rows.append(f"<tr><td>{_esc(c.get('title'))}{' (set-up fault)' if c.get('grade') == 'fault' else ''}</td>"
                    f"<td>{values}</td><td>{status}</td></tr>")
    table = ("<table><tr><th>effect</th><th>values ± standard error</th><th>in the upload</th></tr>"
             + "".join(rows) + "</table>") if rows else "<p>Nothing beyond the geometry was found.</p>"
    by_hand = "".join(f"<div class='warn'>Set by hand: {_esc(t)}</div>" for t in physics.get("by_hand", []))
    noise, source = physics.get("noise_mm"), physics.get("noise_source")
    source = "" if noise is None else (f"<p class='small'>Noise yardstick: {float(noise) * 1000:.1f} µm RMS pose "
                                       f"position noise ({_esc(NOISE_SOURCES.get(source, source))}).</p>")
    return f"<p>Geometry: {_esc(physics.get('geometry_source'))}.</p>{table}{by_hand}{source}"


def _plan(method: Mapping[str, Any]) -> str:
    """Fixed, or adaptive with why its measurement stopped: the prediction then and what the verification measured."""
    stop = method.get("adaptive_stop")
    if method.get("plan") != "adaptive" or not stop:
        return f"fixed: {_esc(method.get('n_measure_rows'))} measurement rows"
    return (f"<span id='adaptive-stop'>adaptive, measured until the accuracy was proven; stop: "
            f"<b>{_esc(stop.get('title'))}</b>. {_esc(stop.get('summary'))}</span>")


def _software(sw: Mapping[str, Any]) -> str:
    modified = " (with local changes)" if sw.get("git_modified") else ""
    revision = f"<code>{_esc(sw.get('git_revision'))}</code>"
    return f"{_esc(sw.get('name'))} {_esc(sw.get('version'))}, git {revision}{modified}"


def _instrument_rows(inst: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The instrument and what its uncertainty is: a CMM's stated U per sphere-centre coordinate, a laser tracker's
    MPE read as U per coordinate of a point at its distance."""
    where = f" ({_esc(inst.get('url'))})" if inst.get("url") else ""
    if inst.get("kind") != "tracker":
        stated = inst.get("stated_uncertainty_mm")
        return [("coordinate measuring machine", f"{_esc(inst.get('cmm'))}{where}"),
                ("stated uncertainty", "not stated" if stated is None else
                 f"U = {_num(stated, 4)} mm (k = 2) per sphere-centre coordinate "
                 f"({_esc(inst.get('uncertainty_source'))})")]
    u, d, air = inst.get("point_uncertainty_mm") or {}, inst.get("target_distance_mm") or {}, inst.get("air") or {}
    return [("laser tracker", f"{_esc(inst.get('tracker'))}{where}"),
            ("maximum permissible error", f"MPE = ±({_esc(inst.get('mpe_constant_um'))} µm + "
             f"{_esc(inst.get('mpe_per_m_um'))} µm/m), read as the expanded uncertainty U (k = 2) of each "
             f"coordinate of a measured point at its distance from the tracker: U = {_num(u.get('min'), 4)} to "
             f"{_num(u.get('max'), 4)} mm over its {_esc(inst.get('n_platform_targets'))} platform targets and "
             f"{_esc(inst.get('n_base_monuments'))} base monuments, {_num((d.get('min') or 0) / 1000, 2)} to "
             f"{_num((d.get('max') or 0) / 1000, 2)} m away ({_esc(inst.get('uncertainty_source'))})"),
            ("air set on the tracker", "–" if not air else f"{_num(air.get('temperature_c'), 1)} °C, "
             f"{_num(air.get('pressure_hpa'), 1)} hPa, {_num(air.get('humidity_pct'), 0)} % relative humidity "
             "(its distances are corrected for the refraction of this air)")]


def certificate_html(report: Mapping[str, Any]) -> str:
    """The certificate page of one run's report.json (with its sign-off keys)."""
    cert = report.get("certificate") or {}
    machine, station = report.get("machine") or {}, report.get("station") or {}
    inst, env = report.get("instrument") or {}, report.get("environment") or {}
    method, times = report.get("method") or {}, report.get("times") or {}
    warnings = [w for w in cert.get("warnings", []) if w]
    temp = env.get("temperature_c")
    temperature = _esc(env.get("note")) if not temp else (
        f"{_num(temp['mean'], 2)} °C (from {_num(temp['min'], 2)} to {_num(temp['max'], 2)} °C, {temp['n']} readings)"
        + (f": {_esc(env['note'])}" if env.get("note") else ""))
    due = _esc(inst.get("calibration_due")) + (" – <b>OVERDUE</b>" if inst.get("overdue") else "")
    warn = "".join(f"<div class='warn'>{_esc(w)}</div>" for w in warnings)
    estimator = _esc(ESTIMATORS.get(str(method.get("estimator")), method.get("estimator")))
    return f"""<!doctype html><html lang="en"><head><meta charset="utf-8">
<title>Calibration certificate {_esc(cert.get('number'))}</title><style>{_CSS}</style></head><body>
<header><div><h1>Calibration certificate</h1><div class="small">Kinematic calibration of a 6-6 Gough/Stewart
platform, hardware in the loop (hilcal)</div></div>
<div class="number">No. <span id="certificate-number">{_esc(cert.get('number'))}</span><br>
<span class="small">issued {_when(cert.get('issued_at'))}</span><br>
<span class="badge {DECISION_CLASS.get(cert.get('verdict'), 'none')}" id="verdict-summary">Verdict: \
{_esc(cert.get('verdict') or None)}</span></div></header>
<section><h2>Calibrated machine, place and people</h2>{_kv([
    ("machine (robot file)", f"{_esc(machine.get('robot_name'))} – {_esc(machine.get('robot_file'))}"),
    ("serial number", _esc(machine.get("serial"))),
    ("station", f"{_esc(station.get('name'))}" + (f" ({_esc(station.get('file'))})" if station.get("file") else "")),
    ("operator", f"<span id='operator'>{_esc(report.get('operator'))}</span>"),
    ("run", f"{_esc(report.get('run_id'))}: {_when(times.get('started_at'))} to {_when(times.get('finished_at'))}"),
])}</section>
<section><h2>Instrument, environment and method</h2>{_kv([
    *_instrument_rows(inst),
    ("its calibration due", due),
    ("temperature", temperature),
    ("method", f"{_esc(method.get('model'))}-parameter rigid geometric model"
               + (f" with {_esc(', '.join(method['effects']))} compensated in the controller"
                  if method.get("effects") else "") + f", {estimator} estimator; "
               f"{_esc(method.get('n_measure_rows'))} measurement rows, "
               f"{_esc(method.get('n_verify_poses'))} held-out verification poses"),
    ("measurement plan", _plan(method)),
    ("pose plan SHA-256", f"<code>{_esc(method.get('plan_sha256'))}</code>"),
    ("software", _software(report.get("software") or {})),
])}</section>{warn}
<section><h2>Results: accuracy before and after calibration (value ± U, k = 2)</h2>{_results(report)}</section>
<section><h2>ISO 9283 pose accuracy and repeatability (after calibration)</h2>{_iso_table(report.get('iso9283'))}
</section>
<section><h2>Verdict</h2>{_verdict(cert)}</section>
<section><h2>Compensation beyond the geometry</h2>{_compensation(report)}</section>
<section><h2>Uploaded parameter set</h2>{_upload(report)}</section>
<section><p class="small">The expanded uncertainties U are the standard uncertainties multiplied by the coverage
factor k = 2 (GUM), from the {"laser tracker's MPE" if inst.get("kind") == "tracker" else "CMM's stated uncertainty"}
and the scatter of the poses measured more than once in this run,
propagated by seeded Monte Carlo (hilcal docs/certificate.md). The results hold for the machine as measured under
the conditions above. This certificate may only be copied in full.</p>
<div class="sig"><div>Calibrated by: {_esc(report.get('operator'))}<br>date and signature</div>
<div>Approved by: name, date and signature</div></div></section>
</body></html>"""


def signoff_html(signoff: Mapping[str, Any] | None) -> str:
    """The run report's sign-off box: the verdict and where the certificate is (empty without a sign-off)."""
    if not signoff or not signoff.get("certificate"):
        return ""
    cert = signoff["certificate"]
    css = DECISION_CLASS.get(cert.get("verdict"), "none")
    color = {"pass": "#dfd", "fail": "#fdd", "notproven": "#ffd"}.get(css, "#eee")
    return (f"<p style='background:{color};padding:.5em 1em'><b>Acceptance verdict: {_esc(cert.get('verdict'))}</b>"
            f" – certificate {_esc(cert.get('number'))}, operator {_esc(signoff.get('operator'))}: "
            "<a href='certificate.html'>certificate.html</a> · <a href='certificate.pdf'>certificate.pdf</a></p>")

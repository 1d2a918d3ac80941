"""Plots and a self-contained HTML page for a missing-physics diagnosis (`hilcal diagnose --report DIR`)."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hilcal.diagnosis import Diagnosis
from hilcal.physics import CANDIDATES_BY_NAME, EffectContext
from hilcal.recording import Recording

DRIVER_OF = {
    "leg_compliance": ("axial load (kN)", lambda c: c.force_kn),
    "oil_column_compliance": ("load x stroke (kN m)", lambda c: c.force_kn * c.stroke_mm / 1000.0),
    "sensor_scale": ("stroke (mm)", lambda c: c.stroke_mm),
    "joint_backlash": ("direction of last motion", lambda c: c.direction),
    "thermal_expansion": ("temperature (°C)", lambda c: np.broadcast_to(c.temp_c[:, None], c.legs_mm.shape)),
}


def _driver(diag: Diagnosis, ctx: EffectContext) -> tuple[str, np.ndarray]:
    if diag.effect in DRIVER_OF:
        label, fn = DRIVER_OF[diag.effect]
        return label, fn(ctx)
    return "time (s)", np.broadcast_to(ctx.time_s[:, None], ctx.legs_mm.shape)


def _leg_plot(diag: Diagnosis, rec: Recording, path: Path) -> None:
    """Leg-length residuals of the geometry-only fit against the driver of the named effect."""
    label, x = _driver(diag, diag.context)
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), sharey=True)
    measure = rec.phase == "measure"
    for i, ax in enumerate(axes.ravel()):
        r_um = diag.leg_residuals_mm[:, i] * 1000
        ax.scatter(x[measure, i], r_um[measure], s=14, label="measure rows")
        ax.scatter(x[~measure, i], r_um[~measure], s=14, marker="^", label="verify rows")
        ax.set_title(f"leg {i + 1}")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("leg residual, geometry only (µm)")
    axes[1, 0].set_ylabel("leg residual, geometry only (µm)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"Where the mismatch lives: per-leg residuals vs {label} (effect: {diag.effect})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _time_plot(diag: Diagnosis, path: Path) -> None:
    ctx = diag.context
    fig, ax = plt.subplots(figsize=(10, 3.8))
    for i in range(6):
        ax.plot(ctx.time_s, diag.leg_residuals_mm[:, i] * 1000, ".-", lw=0.7, label=f"leg {i + 1}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("leg residual (µm)")
    if ctx.temp_c is not None:
        twin = ax.twinx()
        twin.plot(ctx.time_s, ctx.temp_c, "k--", lw=1, label="temp_c")
        twin.set_ylabel("temperature (°C)")
    ax.legend(ncol=6, fontsize=8)
    ax.grid(alpha=0.3)
    ax.set_title("Residuals over time (execution order) and temperature")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _tests_plot(diag: Diagnosis, alpha: float, path: Path) -> None:
    tests = [t for t in diag.tests if t.applicable]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    values = [-np.log10(max(t.p_holm, 1e-6)) for t in tests]
    ax.barh([t.name for t in tests], values, color=["tab:red" if t.supported else "tab:gray" for t in tests])
    ax.axvline(-np.log10(alpha), color="k", ls="--", label=f"alpha = {alpha}")
    ax.set_xlabel("-log10(Holm-corrected p)")
    ax.legend()
    ax.set_title("Evidence per candidate (red: significant and better on held-out poses)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _verify_plot(diag: Diagnosis, path: Path) -> None:
    if diag.before is None or diag.after is None:
        return
    fig, ax = plt.subplots(figsize=(6, 3.5))
    labels = ["max position", "RMS position"]
    before = [diag.before.position_mm.max * 1000, diag.before.position_mm.rms * 1000]
    after = [diag.after.position_mm.max * 1000, diag.after.position_mm.rms * 1000]
    xs = np.arange(2)
    ax.bar(xs - 0.2, before, 0.4, label="geometry only")
    ax.bar(xs + 0.2, after, 0.4, label=f"geometry + {diag.effect}")
    ax.set_xticks(xs, labels)
    ax.set_ylabel("verify-pose error (µm)")
    ax.legend()
    ax.set_title("Held-out verification poses")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(diag: Diagnosis, rec: Recording, out_dir: Path, alpha: float = 0.05) -> Path:
    """Write the plots, diagnosis.json and a self-contained index.html into out_dir; return the page path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    plots = ("legs.png", "time.png", "tests.png", "verify.png")
    _leg_plot(diag, rec, out_dir / "legs.png")
    _time_plot(diag, out_dir / "time.png")
    _tests_plot(diag, alpha, out_dir / "tests.png")
    _verify_plot(diag, out_dir / "verify.png")
    (out_dir / "diagnosis.json").write_text(json.dumps(diag.to_json(), indent=2))
    images = "".join(
        f'<img alt="{name}" src="data:image/png;base64,{base64.b64encode((out_dir / name).read_bytes()).decode()}">'
        for name in plots if (out_dir / name).exists()
    )
    rows = "".join(
        f"<tr><td>{html.escape(t.name)}</td><td>{t.n_params}</td>"
        f"<td>{'' if not t.applicable else f'{t.f_statistic:.2f}'}</td>"
        f"<td>{'' if not t.applicable else f'{t.p_holm:.3g}'}</td>"
        f"<td>{'' if not t.applicable else f'{t.cv_rms_mm * 1000:.2f}'}</td>"
        f"<td>{'yes' if t.supported else ('' if t.applicable else html.escape(t.reason or ''))}</td></tr>"
        for t in diag.tests
    )
    params = "".join(
        f"<tr><td>{html.escape(k)}</td><td>{v:+.4g}</td><td>{diag.std_errors.get(k, float('nan')):.2g}</td></tr>"
        for k, v in diag.parameters.items()
    )
    findings = "".join(f"<li>{html.escape(f.text)}</li>" for f in diag.findings) or "<li>none stand out</li>"

    def acc(summary: object) -> str:
        return "n/a" if summary is None else ", ".join(f"{k} {v:.4f}" for k, v in summary.brief().items())

    axes = ", ".join(f"{k} {v:.4g}" for k, v in diag.residual_rms_by_axis().items())
    title = CANDIDATES_BY_NAME[diag.effect].title if diag.effect in CANDIDATES_BY_NAME else diag.effect
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>hilcal diagnosis: {html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}}img{{max-width:100%;display:block;margin:1em 0}}
table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}</style></head><body>
<h1>Missing physics: {html.escape(title)}</h1><p>{html.escape(diag.explanation)}</p>
<h2>Verification poses (held out)</h2><p>geometry only: {acc(diag.before)}<br>with the effect: {acc(diag.after)}</p>
<p>leave-one-pose-out residual: geometry only {diag.cv_rms_geometry_mm * 1000:.2f} µm{
'' if diag.cv_rms_effect_mm is None else f', with the effect {diag.cv_rms_effect_mm * 1000:.2f} µm'}</p>
<h2>Fitted parameters</h2><table><tr><th>parameter</th><th>value</th><th>std error (cluster-robust)</th></tr>
{params}</table><h2>Tests</h2><table><tr><th>candidate</th><th>params</th><th>F</th><th>Holm p</th>
<th>CV RMS µm</th><th>supported</th></tr>
{rows}</table><h2>Where the mismatch lives</h2><p>geometry-only residual RMS per pose axis: {html.escape(axes)}</p>
<ul>{findings}</ul>{images}</body></html>"""
    path = out_dir / "index.html"
    path.write_text(page)
    return path

"""Figures of a missing-physics diagnosis: where the residual lives, what each selection step bought on held-out
poses (waterfall), the fitted shape of every unexplained term with its band, and residual against noise per leg.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.discovery.physics import CANDIDATES_BY_NAME
from hilcal.discovery.result import Diagnosis, Shape
from hilcal.reports.figures import fixed_margins

DPI = 110


def _save(fig: plt.Figure, path: Path) -> None:
    """Write and close the figure; its margins are set in inches by the plot (hilcal.reports.figures)."""
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def driver_of(diag: Diagnosis) -> tuple[str, np.ndarray]:
    """The variable to plot leg residuals against: the first named effect's driver, else stroke."""
    ctx: EffectContext = diag.context
    first = diag.groups[0] if diag.groups else None
    if first is not None and first.effect in CANDIDATES_BY_NAME:
        cand = CANDIDATES_BY_NAME[first.effect]
        if first.effect == "thermal_expansion" and ctx.temp_c is not None:
            return cand.driver, ctx.per_leg(ctx.temp_c)
        if first.effect == "joint_backlash":
            return cand.driver, ctx.direction
        if first.effect == "leg_compliance":
            return cand.driver, ctx.force_kn
        if first.effect == "oil_column_compliance":
            return cand.driver, ctx.force_kn * ctx.stroke_mm / 1000.0
    if first is not None and first.variable in ("time",):
        return "time since session start (s)", ctx.per_leg(ctx.session_time_s)
    return "stroke (mm)", ctx.stroke_mm


def leg_plot(diag: Diagnosis, path: Path) -> None:
    """Leg-length residuals of the geometry-only fit against the driver of the first effect."""
    label, x = driver_of(diag)
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), sharey=True)
    measure = diag.measure
    for i, ax in enumerate(axes.ravel()):
        r_um = diag.leg_residuals_mm[:, i] * 1000
        ax.scatter(x[measure, i], r_um[measure], s=14, label="measure rows")
        ax.scatter(x[~measure, i], r_um[~measure], s=14, marker="^", label="verify rows")
        ax.set_title(f"leg {i + 1}")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("leg residual, geometry only (µm)")
    axes[0, 0].legend(fontsize=8)
    effects = ", ".join(diag.effects) or "none"
    fig.suptitle(f"Where the mismatch lives: per-leg residuals vs {label}\n(effects: {effects})")
    fixed_margins(fig, left_in=0.85, right_in=0.15, bottom_in=0.55, top_in=0.85, wspace_in=0.25, hspace_in=0.8)
    _save(fig, path)


def time_plot(diag: Diagnosis, path: Path) -> None:
    ctx = diag.context
    fig, ax = plt.subplots(figsize=(10, 3.8))
    order = np.arange(ctx.n)
    for i in range(6):
        ax.plot(order, diag.leg_residuals_mm[:, i] * 1000, ".-", lw=0.7, label=f"leg {i + 1}")
    ax.set_xlabel("row (execution order)")
    ax.set_ylabel("leg residual, geometry only (µm)")
    if ctx.temp_c is not None:
        twin = ax.twinx()
        twin.plot(order, ctx.temp_c, "k--", lw=1)
        twin.set_ylabel("temperature (°C, dashed)")
    for k in np.flatnonzero(np.diff(ctx.session)) + 0.5:
        ax.axvline(k, color="r", lw=1, ls=":")
    ax.legend(ncol=6, fontsize=8)
    ax.grid(alpha=0.3)
    ax.set_title("Residuals over the run (dotted red: a new session)")
    fixed_margins(fig, left_in=0.85, right_in=0.85 if ctx.temp_c is not None else 0.15, bottom_in=0.55, top_in=0.35)
    _save(fig, path)


def waterfall_plot(diag: Diagnosis, path: Path) -> None:
    """Held-out verify RMS after each selection step, against the noise floor."""
    if diag.before is None:
        return
    labels = ["geometry only"] + [f"{s.index}: +{s.key}" + (f"\n-{', '.join(s.removed)}" if s.removed else "")
                                  for s in diag.steps]
    values = [diag.before.position_mm.rms * 1000] + [
        np.nan if s.verify is None else s.verify.position_mm.rms * 1000 for s in diag.steps]
    fig, ax = plt.subplots(figsize=(max(7, 1.6 * len(values)), 4))
    colours = ["tab:gray"] + ["tab:red" if s.kind == "generic" else "tab:blue" for s in diag.steps]
    ax.bar(range(len(values)), values, color=colours)
    for k, v in enumerate(values):
        ax.text(k, v, f"{v:.1f}", ha="center", va="bottom", fontsize=8)
    if diag.noise.chosen is not None:
        floor = diag.noise.chosen.position_mm * 1000
        ax.axhline(floor, color="k", ls="--", lw=1, label=f"noise floor {floor:.1f} µm ({diag.noise.chosen.source})")
        ax.legend(fontsize=8)
    ax.set_xticks(range(len(values)), labels, fontsize=7, rotation=15)
    ax.set_ylabel("verify RMS position error (µm)")
    ax.set_title("What each step buys on held-out verify poses\n(blue: library physics, red: unexplained)", fontsize=10)
    fixed_margins(fig, left_in=0.85, right_in=0.15, bottom_in=0.95, top_in=0.55)
    _save(fig, path)


def shape_plot(diag: Diagnosis, shape: Shape, path: Path) -> None:
    """The fitted correction of one unexplained term with its 95 % band and the partial residuals."""
    g = shape.group
    fig, ax = plt.subplots(figsize=(7, 4))
    fixed_margins(fig, left_in=0.85, right_in=0.15, bottom_in=0.55, top_in=0.55)  # before a colorbar takes its share
    if shape.grid.shape[1] == 1:
        x = shape.grid[:, 0]
        ax.fill_between(x, (shape.correction_mm - shape.band_mm) * 1000, (shape.correction_mm + shape.band_mm) * 1000,
                        alpha=0.3, label="95 % band")
        ax.plot(x, shape.correction_mm * 1000, lw=2, label="fitted correction")
        values = _variable_at_rows(diag, shape)
        if values is not None:
            partial = _partial_residual(diag, shape)
            ax.scatter(values[diag.measure], partial[diag.measure] * 1000, s=12, c="k", label="measure rows")
            ax.scatter(values[~diag.measure], partial[~diag.measure] * 1000, s=12, marker="^", c="tab:orange",
                       label="verify rows (held out)")
        ax.set_xlabel(shape.columns[0])
        ax.legend(fontsize=8)
    elif shape.columns[0] == "direction":
        for d, style in ((-1.0, "--"), (1.0, "-")):
            rows = shape.grid[:, 0] == d
            ax.plot(shape.grid[rows, 1], shape.correction_mm[rows] * 1000, style, label=f"direction {d:+.0f}")
            ax.fill_between(shape.grid[rows, 1], (shape.correction_mm[rows] - shape.band_mm[rows]) * 1000,
                            (shape.correction_mm[rows] + shape.band_mm[rows]) * 1000, alpha=0.2)
        ax.set_xscale("log")
        ax.set_xlabel("size of the last move (mm)")
        ax.legend(fontsize=8)
    else:
        sc = ax.scatter(shape.grid[:, 0], shape.grid[:, 1], c=shape.correction_mm * 1000, cmap="RdBu_r", s=30)
        fig.colorbar(sc, ax=ax, label="correction at the recorded angles (µm)")
        ax.set_xlabel(shape.columns[0])
        ax.set_ylabel(shape.columns[1])
    ax.set_ylabel("leg length correction (µm)") if shape.grid.shape[1] == 1 or shape.columns[0] == "direction" else None
    ax.grid(alpha=0.3)
    pinned = "pinned down" if shape.pinned else "NOT pinned down"
    name = g.title if g.leg is not None else f"leg {shape.leg + 1}: {g.title}"
    ax.set_title(f"{name}\namplitude {shape.amplitude_mm * 1000:.1f} µm, {pinned}", fontsize=9)
    _save(fig, path)


def _variable_at_rows(diag: Diagnosis, shape: Shape) -> np.ndarray | None:
    ctx, leg = diag.context, shape.leg
    variable = shape.group.variable
    if variable in ("stroke", "stroke_cyclic"):
        return ctx.stroke_mm[:, leg]
    if variable == "axial_force":
        return ctx.force_kn[:, leg]
    if variable in ("time", "time_lag"):
        return ctx.session_time_s
    if variable == "temperature" and ctx.temp_c is not None:
        return ctx.temp_c
    return None


def _partial_residual(diag: Diagnosis, shape: Shape) -> np.ndarray:
    """Final-model leg residual of the shape's leg plus the shape's own fitted contribution, centred."""
    theta = diag.final_fit.x[shape.param_index]
    basis = shape.group.phi(diag.context)[:, shape.leg, shape.local_columns]
    contribution = (basis - basis[diag.measure].mean(axis=0)) @ theta
    return diag.leg_residuals_final_mm[:, shape.leg] + contribution


def noise_plot(diag: Diagnosis, path: Path) -> None:
    """Residual/noise ratio per leg, geometry only and final model."""
    ratio = diag.noise_ratio
    if ratio is None:
        return
    fig, ax = plt.subplots(figsize=(7, 3.5))
    xs = np.arange(6)
    ax.bar(xs - 0.2, ratio.per_leg_geometry, 0.4, label=f"geometry only (total {ratio.ratio_geometry:.2f})")
    ax.bar(xs + 0.2, ratio.per_leg_final, 0.4, label=f"final model (total {ratio.ratio_final:.2f})")
    ax.axhline(1.0, color="k", lw=1)
    ax.axhline(2.0, color="r", lw=1, ls="--", label="far above noise")
    ax.set_xticks(xs, [f"leg {i + 1}" for i in xs])
    ax.set_ylabel("residual / noise")
    ax.legend(fontsize=8)
    ax.set_title("Residual against the measurement noise (measure rows)")
    fixed_margins(fig, left_in=0.75, right_in=0.15, bottom_in=0.4, top_in=0.35)
    _save(fig, path)

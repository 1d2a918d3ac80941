"""The plots of the paper study (``paper_study.py``): identification error per pose set, reduction against noise,
verification error per pose, and L-infinity against LS per scenario (PNG files for docs/img/).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from paper_study_runs import (
    ERROR_SET_LABELS,
    EST_LABEL,
    POSE_SET_LABELS,
    SCENARIOS,
    GridResults,
    StudyPlan,
    T7Results,
    grid_median,
    indicator,
    reduction_pct,
)


def plot_ident_vs_pose_set(grid: GridResults, plan: StudyPlan, path: Path) -> None:
    """Identification error (RMS, log) vs pose set, one panel per error set, a line per noise level."""
    n = len(plan.error_sets)
    cols = 2 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 3.8 * rows), squeeze=False)
    x = np.arange(len(plan.pose_sets))
    colours = plt.cm.viridis(np.linspace(0, 0.85, len(plan.noises_mm)))
    for ax, err in zip(axes.flat, plan.error_sets, strict=False):
        for colour, noise in zip(colours, plan.noises_mm, strict=True):
            for est, style in (("ls", "-o"), ("linf", "--s")):
                y = [grid_median(grid.rows, "ident_rms", error_set=err, pose_set=p, noise_mm=noise, estimator=est)
                     for p in plan.pose_sets]
                ax.plot(x, y, style, color=colour, label=f"σ={noise:g} {EST_LABEL[est]}")
        ax.axhline(grid.true_rms[err], color="k", lw=0.8, ls=":", label="RMS of true errors")
        ax.set_yscale("log")
        ax.set_xticks(x, [POSE_SET_LABELS[p].split(":")[0] for p in plan.pose_sets])
        ax.set_xlabel("pose set")
        ax.set_ylabel("identification error RMS (mm)")
        ax.set_title(f"error set {ERROR_SET_LABELS[err]}")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=5, fontsize=7)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_reduction_vs_noise(grid: GridResults, plan: StudyPlan, pose_set: str, path: Path) -> None:
    """Max position / orientation error reduction (%) on the 100 evaluation poses vs noise, one line per set."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, (q, label) in zip(axes, (("pos", "position"), ("ori", "orientation")), strict=True):
        for err in plan.error_sets:
            for est, style in (("ls", "-o"), ("linf", "--s")):
                y = []
                for noise in plan.noises_mm:
                    sel = dict(error_set=err, pose_set=pose_set, noise_mm=noise, estimator=est)
                    y.append(reduction_pct(grid_median(grid.rows, f"before_{q}_max", **sel),
                                           grid_median(grid.rows, f"after_{q}_max", **sel)))
                ax.plot(plan.noises_mm, y, style, label=f"{ERROR_SET_LABELS[err]} {EST_LABEL[est]}")
        ax.set_xscale("log")
        ax.set_xlabel("CMM noise σ per sphere coordinate (mm)")
        ax.set_ylabel(f"max {label} error reduction (%)")
        ax.set_title(f"{label}: pose set {pose_set[3]}, true evaluation poses")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_per_pose(t7: T7Results, seed: int, path: Path) -> None:
    """Per-pose verification errors before and after LS / L∞ calibration (the paper's Figs. 13-14), log scale."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, (i, label, unit) in zip(axes, ((0, "position", "mm"), (1, "orientation", "deg")), strict=True):
        for key, style, name in (("before", "-o", "before"), ("ls", "-s", "after LS"), ("linf", "-^", "after L∞")):
            if key in t7.per_pose:
                e = t7.per_pose[key][i]
                ax.plot(np.arange(1, e.size + 1), e, style, ms=4, label=name)
        ax.set_yscale("log")
        ax.set_xlabel("verification pose")
        ax.set_ylabel(f"absolute {label} error ({unit})")
        ax.set_title(f"{label} error at verification poses (seed {seed})")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_scenarios(t7: T7Results, path: Path) -> None:
    """Per-seed relative difference of the max verification error, (L∞ - LS) / LS, per scenario."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, (q, label) in zip(axes, (("position_mm", "position"), ("orientation_deg", "orientation")), strict=True):
        data, names = [], []
        for scen in SCENARIOS:
            ls = t7.measured.get((scen, "42", "iterated", "ls"), [])
            li = t7.measured.get((scen, "42", "iterated", "linf"), [])
            if not ls or len(ls) != len(li):
                continue
            pairs = zip(ls, li, strict=True)
            data.append([100 * (indicator(b, q, "max") / indicator(a, q, "max") - 1) for a, b in pairs])
            names.append(scen)
        if data:
            ax.boxplot(data, tick_labels=names)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel(f"(L∞ − LS) / LS, max {label} error (%)")
        ax.set_title(f"max measured-verification {label} error; < 0: L∞ better")
        ax.tick_params(axis="x", labelrotation=20)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

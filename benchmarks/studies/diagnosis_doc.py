"""docs/diagnosis_study.md and its plots, from the summary of a diagnosis study run."""

from __future__ import annotations

import os
import platform
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from diagnosis_summary import (
    FALSE_ALARM_TARGET,
    GAIN_TARGET,
    PAIR_TARGET,
    RATIO_TARGET,
    UNLISTED_TARGET,
)


def _pct(x: float) -> str:
    return "–" if not np.isfinite(x) else f"{100 * x:.0f}%"


def _f(x: float | None, fmt: str = ".2f") -> str:
    return "–" if x is None or not np.isfinite(x) else format(x, fmt)


def _ci(d: dict[str, Any]) -> str:
    return f"{100 * d['ci'][0]:.1f}–{100 * d['ci'][1]:.1f}%"


def plot_singles(summary: dict[str, Any], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    cells = summary["singles"]
    for effect in sorted({k[0] for k in cells}):
        keys = sorted(k for k in cells if k[0] == effect and not k[2])
        ax.plot([k[1] for k in keys], [cells[k]["rate"] for k in keys], marker="o", label=effect)
    ax.axhline(0.8, color="grey", ls="--", lw=1)
    ax.set_xscale("log", base=2)
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("magnitude scale (1 = realistic concealed magnitude)")
    ax.set_ylabel("named first = truth")
    ax.set_title("One library effect: naming rate vs magnitude")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_unlisted(summary: dict[str, Any], path: Path) -> None:
    table = summary["unlisted"]["unlisted"]
    keys = [k for k in table if k[1] == max(s for _, s in table)]
    if not keys:
        return
    fig, ax = plt.subplots(figsize=(8, 4))
    xs = np.arange(len(keys))
    ax.bar(xs - 0.2, [table[k]["before_floor"] for k in keys], 0.4, label="geometry only")
    ax.bar(xs + 0.2, [table[k]["after_floor"] for k in keys], 0.4, label="geometry + generic model")
    ax.axhline(1.0, color="k", lw=1)
    ax.set_xticks(xs, [" + ".join(k[0]) for k in keys], fontsize=8, rotation=10)
    ax.set_ylabel("verify RMS / noise floor (median)")
    ax.set_title("Physics the library does not list: held-out error before and after the generic model")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _singles_section(summary: dict[str, Any]) -> list[str]:
    lines = ["## One library effect\n",
             "Named = the first effect named is the concealed one; alone = no other physics named besides it "
             "(the oil column's dead-volume part may add leg compliance, which is physically right). After/floor on "
             f"the named runs; requirement ≤ {RATIO_TARGET:g}.\n",
             "| effect | scale | columns | named | 95% CI | alone | before/floor | after/floor median | max | > 1.5× |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for (effect, scale, bare), d in summary["singles"].items():
        lines.append(f"| {effect} | {scale:g} | {'no cmd, no temp_c' if bare else 'all'} | {d['k']}/{d['n']} "
                     f"({_pct(d['rate'])}) | {_ci(d)} | {d['clean']} | {_f(d['before_floor'])} | "
                     f"{_f(d['ratio_median'])} | {_f(d['ratio_max'])} | {d['over']} |")
    return [*lines, ""]


def _pairs_section(summary: dict[str, Any]) -> list[str]:
    p = summary["pairs"]
    lines = ["## Two library effects at once\n",
             f"Both named (in any order); requirement ≥ {PAIR_TARGET:.0%} and after/floor ≤ {RATIO_TARGET:g}. "
             "*Extra* counts runs that also named physics that was not concealed.\n",
             "| pair | both named | 95% CI | extra | after/floor median | max | > 1.5× |",
             "|---|---|---|---|---|---|---|"]
    for key, d in p["table"].items():
        lines.append(f"| {' + '.join(key)} | {d['k']}/{d['n']} ({_pct(d['rate'])}) | {_ci(d)} | {d['extra']} | "
                     f"{_f(d['ratio_median'])} | {_f(d['ratio_max'])} | {d['over']} |")
    t = p["total"]
    lines.append(f"| **all pairs** | {t['k']}/{t['n']} ({_pct(t['rate'])}) | {_ci(t)} | {p['extra']} | "
                 f"{_f(p['ratio_median'])} | {_f(p['ratio_max'])} | {p['over']} |")
    return [*lines, ""]


def _unlisted_section(summary: dict[str, Any]) -> list[str]:
    lines = ["## Physics the library does not list\n",
             "Effects written in the simulator only (`sim_devices/rig/unlisted_physics.py`), never in `hilcal`. "
             "*Unexplained* = `unexplained` among the effects; *first* = the answer `effect` is `unexplained`; "
             "*library named* = physics named that was not concealed. Gain = verify RMS after / before "
             f"(requirement ≤ {GAIN_TARGET:g}, i.e. halved); *within* = explanations claiming "
             "'within its measurement noise' (must be 0).\n",
             "| concealed | scale | before/floor | unexplained | first | library named | library found | gain median "
             "| halved | within | shapes pinned |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for kind in ("unlisted", "combo"):
        for (effects, scale), d in summary["unlisted"][kind].items():
            found = f"{d['library_found']}/{d['n']}" if kind == "combo" else "–"
            lines.append(f"| {' + '.join(effects)} | {scale:g} | {_f(d['before_floor'])} | {d['k']}/{d['n']} "
                         f"({_pct(d['rate'])}) | {d['first']} | {d['library_named']} | {found} | "
                         f"{_f(d['gain_median'])} | {d['halved']}/{d['n']} | {d['within_claims']} | "
                         f"{d['pinned']}/{d['shapes']} |")
    return [*lines, ""]


def _nulls_section(summary: dict[str, Any]) -> list[str]:
    lines = ["## Null recordings (no missing physics)\n",
             f"A false alarm is any named effect or `unexplained`. Target ≤ {FALSE_ALARM_TARGET:.0%}; 95% "
             "Clopper–Pearson intervals. Residual/noise = the final model's residual against the noise yardstick.\n",
             "| recordings | runs | false alarms | rate | 95% CI | what | residual/noise median |",
             "|---|---|---|---|---|---|---|"]
    for name, d in summary["nulls"].items():
        lines.append(f"| {name} | {d['n']} | {d['k']} | {_pct(d['rate'])} | {_ci(d)} | {', '.join(d['which']) or '–'} "
                     f"| {_f(d['ratio_median'])} |")
    return [*lines, ""]


def verdict_lines(summary: dict[str, Any]) -> list[str]:
    p = summary["pairs"]
    lines = ["## Against the targets\n"]
    t = p["total"]
    over = "met" if p["over"] == 0 else f"**{p['over']} above {RATIO_TARGET:g}**"
    lines.append(f"- Pairs: both named in {t['k']}/{t['n']} = {_pct(t['rate'])} (target ≥ {PAIR_TARGET:.0%}: "
                 f"{'met' if t['rate'] >= PAIR_TARGET else '**missed**'}); after/floor max {_f(p['ratio_max'])} "
                 f"(≤ {RATIO_TARGET:g}: {over}).")
    table = summary["unlisted"]["unlisted"]
    top = max((s for _, s in table), default=None)
    cells = [d for (_, s), d in table.items() if s == top]
    if cells:
        n = sum(d["n"] for d in cells)
        said = sum(d["k"] for d in cells)
        halved = sum(d["halved"] for d in cells)
        within = sum(d["within_claims"] for d in cells)
        lines.append(f"- Out-of-library effects at scale {top:g} (before/floor "
                     f"{min(d['before_floor'] for d in cells):.1f}–{max(d['before_floor'] for d in cells):.1f}): "
                     f"unexplained in {said}/{n} = {_pct(said / n)} (target ≥ {UNLISTED_TARGET:.0%}: "
                     f"{'met' if said / n >= UNLISTED_TARGET else '**missed**'}); held-out RMS halved or better in "
                     f"{halved}/{n}; 'within noise' claims: {within} "
                     f"(target 0: {'met' if within == 0 else '**missed**'}).")
    pooled = summary["nulls"]["pooled"]
    lines.append(f"- Nulls: false alarms {pooled['k']}/{pooled['n']} = {_pct(pooled['rate'])} (95% CI {_ci(pooled)}; "
                 f"target ≤ {FALSE_ALARM_TARGET:.0%}: {'met' if pooled['rate'] <= FALSE_ALARM_TARGET else '**missed**'}"
                 f"{'' if pooled['ci'][1] <= FALSE_ALARM_TARGET else ', not demonstrated at 95% confidence'}).")
    o = summary["outliers"]
    if o["exact"]["n"]:
        lines.append(f"- Measurement outliers (two gross errors of 0.1-0.5 mm planted among the measure rows of one "
                     f"library effect): exactly the planted rows left out in {o['exact']['k']}/{o['exact']['n']}, the "
                     f"effect still named first in {o['named']['k']}/{o['named']['n']} (after/floor median "
                     f"{_f(o['ratio_median'])}); recordings without planted errors that lost a row to the screen: "
                     f"{o['false']['k']}/{o['false']['n']} ({o['false_nulls']['k']}/{o['false_nulls']['n']} nulls, "
                     "Student-t noise among them).")
    lines.append(f"- Named effects with a parameter outside its physical range: {summary['range_violations']} "
                 f"(target 0: {'met' if summary['range_violations'] == 0 else '**missed**'}).")
    lines.append(f"- `diagnose` on 56 rows (32 measure + 24 verify): median {_f(summary['seconds_median'], '.1f')} s, "
                 f"max {_f(summary['seconds_max'], '.1f')} s per recording, one worker per core on this machine "
                 "(target < 30 s).")
    return [*lines, ""]


def update_method_doc(path: Path, summary: dict[str, Any], command: str, extra: list[str] | None = None) -> None:
    """Replace the block between the study markers of docs/diagnosis.md with this run's verdicts."""
    text = path.read_text()
    begin, end = "<!-- study:begin -->", "<!-- study:end -->"
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    block = [f"From `{command}` on {datetime.now(UTC):%Y-%m-%d}:", "", *verdict_lines(summary)[1:],
             *[line for line in extra or [] if line]]
    path.write_text(head + begin + "\n" + "\n".join(block) + "\n" + end + tail)


def write_doc(summary: dict[str, Any], setup: list[str], command: str, elapsed_s: float, jobs: int,
              images: dict[str, str]) -> str:
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        "# Diagnosis study: several effects, physics the library does not list, nulls\n",
        f"Generated by `{command}` on {now} ({elapsed_s:.0f} s on {platform.machine()} with {jobs} worker "
        f"process(es), {os.cpu_count()} CPUs, Python {platform.python_version()}); {summary['n_runs']} recordings. "
        "Every number below comes from that run; rerun the command to regenerate this file and its plots.\n",
        "## Setup\n", *setup, "",
        *verdict_lines(summary), *_pairs_section(summary), *_unlisted_section(summary), *_nulls_section(summary),
        *_singles_section(summary), "## Plots\n",
    ]
    lines += [f"![{name}]({Path(path).relative_to('docs')})" for name, path in images.items()]
    return "\n".join(lines) + "\n"

"""The digital twin in the diagnosis report: the recording against the simulator that learned the machine, pose by
pose, with the geometry alone and with the physics.

The twins themselves are simulated elsewhere (`hilcal diagnose --report` replays the recording on the simulated rig
configured by the `sim_config.toml` it writes); this module holds the comparison as data, its figure and its page
section. A twin that holds the machine leaves what the measurement noise leaves: its position residual against the
recording is about the noise yardstick (ratio 1), the geometry-only twin's is larger by as much as the physics it
lacks.
"""

from __future__ import annotations

import html
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hilcal.error_models import pose_difference
from hilcal.reports.figures import fixed_margins, plain_log_scale

DPI = 110
TWINS = ("geometry", "physics")
TITLES = {"geometry": "twin with the geometry only", "physics": "twin with the physics"}


@dataclass(frozen=True)
class TwinComparison:
    """The recording's measured poses and the poses two twins reach at the same rows (mm, deg)."""

    seq: np.ndarray
    phase: np.ndarray
    measured: np.ndarray
    twins: dict[str, np.ndarray]
    """'geometry' and 'physics': [N, 6] true poses of each twin at the recording's rows."""
    noise_position_mm: float | None
    """RMS length of the measurement's 3-D position noise (the diagnosis' yardstick), None when unknown."""
    noise_source: str
    length_mm: float
    """Rotations as mm at this length (the platform's characteristic length) where a residual has one unit."""
    left_out: np.ndarray | None = None
    """[N] rows the diagnosis left out (measurement outliers: an error no twin reproduces; rows whose motion history
    is unknown): shown, but not in the figures."""

    @property
    def compared(self) -> np.ndarray:
        """[N] the rows in the figures."""
        return np.ones(self.seq.size, dtype=bool) if self.left_out is None else ~self.left_out

    def position_residual_mm(self, twin: str) -> np.ndarray:
        """Per row: the length (mm) of the measured position minus the twin's."""
        return np.linalg.norm(self.measured[:, :3] - self.twins[twin][:, :3], axis=1)

    def orientation_residual_deg(self, twin: str) -> np.ndarray:
        """Per row: the angle (deg) between the measured orientation and the twin's."""
        d = pose_difference(self.measured, self.twins[twin], self.length_mm)[:, 3:]
        return np.degrees(np.linalg.norm(d, axis=1) / self.length_mm)

    def rms_mm(self, twin: str, rows: np.ndarray | None = None) -> float:
        """RMS position residual (mm) over the compared rows (of `rows`)."""
        mask = self.compared if rows is None else self.compared & rows
        return float(np.sqrt(np.mean(self.position_residual_mm(twin)[mask] ** 2)))

    def ratio(self, twin: str, rows: np.ndarray | None = None) -> float | None:
        """RMS position residual over the noise yardstick (1: what the noise alone leaves)."""
        if self.noise_position_mm is None or self.noise_position_mm <= 0:
            return None
        return self.rms_mm(twin, rows) / self.noise_position_mm

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"noise_position_mm": self.noise_position_mm, "noise_source": self.noise_source,
                               "rows": int(self.compared.sum()),
                               "left_out_seq": [float(v) for v in self.seq[~self.compared]]}
        for twin in TWINS:
            per_phase = {str(ph): {"rms_position_mm": self.rms_mm(twin, self.phase == ph),
                                   "times_noise": self.ratio(twin, self.phase == ph)}
                         for ph in np.unique(self.phase)}
            angles = self.orientation_residual_deg(twin)[self.compared]
            out[twin] = {"rms_position_mm": self.rms_mm(twin), "times_noise": self.ratio(twin),
                         "rms_orientation_deg": float(np.sqrt(np.mean(angles**2))),
                         "by_phase": per_phase}
        return out

    def sentence(self) -> str:
        """The comparison in one sentence, with the noise level and its source."""
        parts = []
        for twin in TWINS:
            ratio = self.ratio(twin)
            times = "" if ratio is None else f", {ratio:.2f}x the noise"
            parts.append(f"{TITLES[twin]} {self.rms_mm(twin) * 1000:.1f} µm RMS{times}")
        noise = ("noise level unknown" if self.noise_position_mm is None else
                 f"noise {self.noise_position_mm * 1000:.1f} µm RMS ({self.noise_source})")
        skipped = int((~self.compared).sum())
        left = (f" ({skipped} row(s) the diagnosis left out, outliers or of unknown history, are not in the "
                "figures)" if skipped else "")
        return (f"The recording's {self.seq.size} poses replayed on the twin (its own leg readings, times and "
                f"sessions; the twins learned from these rows), measured minus simulated position: {'; '.join(parts)}; "
                f"{noise}{left}.")


def twin_plot(comparison: TwinComparison, path: Path) -> None:
    """Position residual per row (µm, in recorded order) of the recording against both twins, with the noise."""
    fig, ax = plt.subplots(figsize=(11, 4))
    x = np.arange(comparison.seq.size)
    kept = comparison.compared
    for twin, style in zip(TWINS, ("o", "s"), strict=True):
        r_um = comparison.position_residual_mm(twin) * 1000
        ax.plot(x[kept], r_um[kept], style, ms=3.5, label=TITLES[twin])
        if not kept.all():
            ax.plot(x[~kept], r_um[~kept], "x", ms=6, color="tab:red",
                    label="left out by the diagnosis" if twin == "physics" else None)
    if comparison.noise_position_mm is not None:
        ax.axhline(comparison.noise_position_mm * 1000, color="k", lw=1, ls="--",
                   label=f"noise yardstick ({comparison.noise_position_mm * 1000:.1f} µm RMS)")
    verify = np.flatnonzero(comparison.phase == "verify")
    if verify.size:
        ax.axvspan(verify[0] - 0.5, verify[-1] + 0.5, color="tab:orange", alpha=0.08, label="verify rows")
    plain_log_scale(ax)
    ax.set_xlabel("row of the recording")
    ax.set_ylabel("|measured - twin| position (µm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fixed_margins(fig, left_in=0.85, right_in=0.15, bottom_in=0.55, top_in=0.2)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def twin_html(comparison: TwinComparison, image: str, notes: tuple[str, ...] = ()) -> str:
    """The report's twin section: the sentence, a table per twin and phase, the figure, and what the twin leaves
    out."""
    rows = []
    for twin in TWINS:
        for ph in ["all", *[str(p) for p in np.unique(comparison.phase)]]:
            mask = None if ph == "all" else comparison.phase == ph
            ratio = comparison.ratio(twin, mask)
            rows.append(f"<tr><td>{html.escape(TITLES[twin])}</td><td>{html.escape(ph)}</td>"
                        f"<td>{comparison.rms_mm(twin, mask) * 1000:.2f}</td>"
                        f"<td>{'' if ratio is None else f'{ratio:.2f}'}</td></tr>")
    table = ("<table><tr><th>twin</th><th>rows</th><th>RMS position residual µm</th><th>times the noise</th></tr>"
             + "".join(rows) + "</table>")
    left_out = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    return (f"<h2>Digital twin</h2><p>{html.escape(comparison.sentence())} The simulator configuration is "
            "<code>sim_config.toml</code> (<code>hilcal sim --config</code>, <code>hilcal run --sim --sim-config"
            "</code>, <code>hilcal simulate --sim-config</code>).</p>" + table + image
            + (f"<p>What the twin does not hold:</p><ul>{left_out}</ul>" if left_out else ""))

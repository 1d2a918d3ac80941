"""The measure rows the final model cannot speak for: rows whose terms are unknown, and measurement outliers.

A row whose model terms are unknown is not an outlier. At the first row of a session (and until a leg has moved)
the direction from which a leg approached the pose is not in the recording, so a history term (joint backlash, the
last move's hysteresis) cannot apply there and the row's residual is larger: when the model holds such a term, these
rows are left out of the fit and the answer says what is unknown about them; the screen never calls them bad
measurements. Among the other measure rows, one whose left-out residual is beyond OUTLIER_FACTOR times the median is
a measurement outlier (a broken beam, a probing error, a knock). The search then runs again without the rows left
out, on the context computed on the whole recording, so leaving a row out changes no other row's history, session
or time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.discovery.term_groups import TermGroup

OUTLIER_FACTOR = 4.0
"""A measure row is a measurement outlier when the selected model's left-out residual there is beyond 4 times the
median (for Gaussian noise in six pose components the median is about 2.4 sigma, so this is about 9 sigma)."""
MAX_OUTLIER_SHARE = 0.05
MIN_OUTLIER_ALLOWANCE = 2
"""At most 5 % of the measure rows (and never fewer than 2) are left out as outliers; more is structure or noise."""
MIN_SCREENED_ROWS = 10


@dataclass(frozen=True)
class UnknownRows:
    """Measure rows (indices among the measure rows) where some chosen group's terms cannot be evaluated."""

    rows: np.ndarray
    legs: list[tuple[int, ...]]
    """Per row: the 1-based legs whose history is unknown there."""
    groups: list[tuple[str, ...]]
    """Per row: the chosen groups that cannot apply there."""


def unknown_rows(groups: tuple[TermGroup, ...] | list[TermGroup], ctx: EffectContext) -> UnknownRows:
    """The rows of ctx where a group of the model depends on a history the recording does not hold."""
    masks = {g.key: g.unknown_rows(ctx) for g in groups if g.history}
    if not masks:
        return UnknownRows(np.zeros(0, dtype=int), [], [])
    any_leg = np.any(np.stack(list(masks.values())), axis=0)
    rows = np.flatnonzero(any_leg.any(axis=1))
    return UnknownRows(rows, [tuple(int(i) + 1 for i in np.flatnonzero(any_leg[r])) for r in rows],
                       [tuple(k for k, m in masks.items() if m[r].any()) for r in rows])


@dataclass(frozen=True)
class Screened:
    """What the screen found among the measure rows under one model: rows with unknown terms and outliers."""

    found: UnknownRows
    left_out_mm: np.ndarray
    outliers: np.ndarray
    median_mm: float

    @property
    def any(self) -> bool:
        return bool(self.outliers.size or self.found.rows.size)


def screen_rows(groups: tuple[TermGroup, ...] | list[TermGroup], ctx: EffectContext,
                left_out_mm: np.ndarray) -> Screened:
    """The screen of the measure rows (context `ctx`, left-out residuals of a model with `groups`)."""
    found = unknown_rows(groups, ctx)
    return Screened(found, left_out_mm, outliers(left_out_mm, found.rows), known_median(left_out_mm, found.rows))


def outliers(left_out_mm: np.ndarray | None, unknown: np.ndarray | None = None) -> np.ndarray:
    """Measure rows (indices) whose left-out residual is beyond OUTLIER_FACTOR times the median of the rows whose
    terms are known; rows in `unknown` are never outliers. None are returned when more than the allowance would go
    (then it is structure or noise, not a few bad measurements)."""
    if left_out_mm is None or left_out_mm.size < MIN_SCREENED_ROWS:
        return np.zeros(0, dtype=int)
    known = np.isfinite(left_out_mm)
    if unknown is not None and unknown.size:
        known[unknown] = False
    if known.sum() < MIN_SCREENED_ROWS:
        return np.zeros(0, dtype=int)
    median = float(np.median(left_out_mm[known]))
    out = np.flatnonzero(known & (left_out_mm > OUTLIER_FACTOR * median))
    allowed = max(MIN_OUTLIER_ALLOWANCE, int(MAX_OUTLIER_SHARE * left_out_mm.size))
    return out if out.size <= allowed else np.zeros(0, dtype=int)


def known_median(left_out_mm: np.ndarray, unknown: np.ndarray) -> float:
    """Median left-out residual (mm) of the rows whose terms are known."""
    known = np.isfinite(left_out_mm)
    known[unknown] = False
    return float(np.median(left_out_mm[known] if known.any() else left_out_mm[np.isfinite(left_out_mm)]))


def _first_of_session(ctx: EffectContext, row: int) -> bool:
    return row == 0 or bool(ctx.session[row] != ctx.session[row - 1])


def unknown_json(found: UnknownRows, seq: np.ndarray, left_out_mm: np.ndarray | None,
                 median_mm: float) -> tuple[dict[str, Any], ...]:
    """Per row: seq, the legs and groups that cannot apply, and its left-out residual against the median."""
    out = []
    for r, legs, groups in zip(found.rows, found.legs, found.groups, strict=True):
        entry: dict[str, Any] = {"seq": float(seq[r]), "legs": list(legs), "groups": list(groups)}
        if left_out_mm is not None and np.isfinite(left_out_mm[r]) and median_mm > 0:
            entry["left_out_mm"] = float(left_out_mm[r])
            entry["times_median"] = float(left_out_mm[r] / median_mm)
        out.append(entry)
    return tuple(out)


def unknown_sentence(found: UnknownRows, entries: tuple[dict[str, Any], ...], ctx: EffectContext,
                     titles: dict[str, str]) -> str | None:
    """What is unknown about the rows whose history terms cannot apply (they are not measurement errors)."""
    if not found.rows.size:
        return None
    parts = []
    for r, legs, entry in zip(found.rows, found.legs, entries, strict=True):
        where = (f"first row of session {int(ctx.session[r]) + 1}" if _first_of_session(ctx, r)
                 else f"leg(s) {', '.join(map(str, legs))} not moved since session {int(ctx.session[r]) + 1} started")
        size = (f", left-out residual {entry['left_out_mm']:.4f} mm, {entry['times_median']:.1f}x the median"
                if "left_out_mm" in entry else "")
        parts.append(f"seq {entry['seq']:.0f} ({where}: direction of approach of leg(s) "
                     f"{', '.join(map(str, legs))} unknown{size})")
    names = sorted({titles.get(k, k) for groups in found.groups for k in groups})
    return (f"Rows whose history is unknown, left out of the fit (not measurement errors): {'; '.join(parts)}. The "
            f"recording does not say how these legs approached the pose, so {' and '.join(names)} cannot be applied "
            "there; the model is fitted on the other rows, whose history is computed on the whole recording (record "
            "the motion before a session's first pose, or start each session with a move towards it, to keep them).")


def outlier_sentence(rows: np.ndarray, excluded: tuple[dict[str, float], ...], median_mm: float,
                     at_stop: dict[int, str]) -> str:
    """The measurement outliers left out of the fit, with their left-out residual."""
    listed = ", ".join(f"seq {e['seq']:.0f} ({e['left_out_mm']:.4f} mm, {e['times_median']:.0f}x"
                       f"{at_stop.get(int(r), '')})" for r, e in zip(rows, excluded, strict=True))
    return (f"Measurement outlier(s) left out of the fit: {listed}: the left-out residual of the model is more than "
            f"{OUTLIER_FACTOR:g} times the median of the measure rows whose terms are known ({median_mm:.4f} mm); a "
            "bad measurement (a broken beam, a probing error, a knock) or a collision: re-measure these poses.")

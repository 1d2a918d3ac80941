"""Drift of a machine's geometry between calibrations: which identified parameters moved, by how much, and whether
that is beyond their standard errors (3σ) and physically meaningful (a stated threshold in mm).

A single calibration cannot show that a transducer mount is working loose; a machine's history can. Each
calibration contributes the estimated physical geometry (``machine_parameters``: joint positions, leg offsets and
the stroke each leg needs at the home pose, with standard errors from the identification's covariance). The
stroke at home is what the leg-length data determine well: a leg offset and a joint sliding along the leg look
alike to the data (their estimates correlate at 0.99), so each alone has a large standard error while their sum,
the leg's length at home, is pinned to a few µm.

``drift`` compares every parameter across the calibrations: a step (the best split into before and after,
weighted means) and a linear creep (weighted fit against time). The standard errors are widened when the
calibrations scatter more than they claim (Birge ratio), and the 3σ rule allows for having tried every split and
every parameter (Bonferroni), so a history without a change flags nothing. Pure math: no I/O.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from statistics import NormalDist
from typing import TYPE_CHECKING, Any

import numpy as np

from hilcal.kinematics import Geometry, leg_vectors, split_pose

if TYPE_CHECKING:  # the records import this module: keep scipy.optimize out of their start-up
    from hilcal.identification import IdentificationResult
    from hilcal.robot import Robot

SIGMA_LEVEL = 3.0
"""A change is flagged only beyond this many standard errors (family-wise, after Bonferroni)."""
THRESHOLD_MM = 0.05
"""...and only if it is at least this large: about what a calibrated machine's verification error is, so a
smaller change would not show in the machine's accuracy."""
DAYS_PER_MONTH = 30.0
_NAME = re.compile(r"^leg(\d)_(a|b)_([xyz])_mm$|^leg(\d)_(l0|stroke_at_home|reads_long_at_full_stroke)_mm$")


@dataclass(frozen=True)
class Calibration:
    """One calibration of a machine: when, which run, and each parameter's value and standard error (mm)."""

    run_id: str
    time: str
    """ISO 8601; calibrations are compared in this order."""
    values: Mapping[str, float]
    std: Mapping[str, float | None]


def machine_parameters(robot: Robot, ident: IdentificationResult, controller_l0_mm: Sequence[float]
                       ) -> dict[str, tuple[float, float | None]]:
    """The machine's physical geometry from one identification: name -> (value mm, standard error mm or None).

    ``leg{i}_a_{x,y,z}_mm`` (platform joints), ``leg{i}_b_{x,y,z}_mm`` (base joints), ``leg{i}_l0_mm`` (the true
    stroke-zero length: the controller's l0 during the run plus the identified offset, so an upload between two
    calibrations does not look like drift) and ``leg{i}_stroke_at_home_mm`` (the stroke the leg's transducer reads
    at the home pose). Standard errors come from the identification's covariance (None without one).
    """
    if ident.model != "42":
        raise ValueError(f"drift needs the 42-parameter geometric model, got model {ident.model!r}")
    d = np.asarray(ident.x[:42], dtype=float).reshape(6, 7)
    a, b = robot.a + d[:, 0:3], robot.b + d[:, 3:6]
    l0 = np.asarray(controller_l0_mm, dtype=float) + d[:, 6]
    R, t = split_pose(robot.home)
    _, length, u = leg_vectors(Geometry(a, b), R, t)
    stroke = length - l0
    cov = None if ident.covariance is None else np.asarray(ident.covariance, dtype=float)[:42, :42]
    out: dict[str, tuple[float, float | None]] = {}
    for i in range(6):
        block = slice(7 * i, 7 * i + 7)
        std = None if cov is None else np.sqrt(np.clip(np.diag(cov)[block], 0.0, None))
        for k, axis in enumerate("xyz"):
            out[f"leg{i + 1}_a_{axis}_mm"] = (float(a[i, k]), None if std is None else float(std[k]))
            out[f"leg{i + 1}_b_{axis}_mm"] = (float(b[i, k]), None if std is None else float(std[3 + k]))
        out[f"leg{i + 1}_l0_mm"] = (float(l0[i]), None if std is None else float(std[6]))
        # d(stroke) = u . (R da) - u . db - dl0: the leg's length at home, the sum the data pin down
        grad = np.concatenate([R.T @ u[i], -u[i], [-1.0]])
        stroke_std = None if cov is None else float(math.sqrt(max(grad @ cov[block, block] @ grad, 0.0)))
        out[f"leg{i + 1}_stroke_at_home_mm"] = (float(stroke[i]), stroke_std)
    return out


def describe(name: str) -> tuple[str, str]:
    """A parameter's name in words and what a change of it means physically."""
    m = _NAME.match(name)
    if m is None:
        return name, "the identified geometry changed"
    if m.group(1):
        leg, which, axis = m.group(1), m.group(2), m.group(3)
        joint = "platform" if which == "a" else "base"
        return f"leg {leg} {joint} joint {axis}", f"the {joint} joint of leg {leg} moved (loose mount, wear, a knock)"
    leg, which = m.group(4), m.group(5)
    if which == "l0":
        return f"leg {leg} offset", "a transducer or joint moved"
    if which == "reads_long_at_full_stroke":
        return (f"leg {leg} reading at full stroke", "its transducer's scale changed between calibrations: a failing "
                "transducer (or one reconfigured since)")
    return f"leg {leg} stroke at home", "a transducer or joint moved along the leg"


def reading_scale_parameters(reads_long_ppm: Sequence[float], std_ppm: Sequence[float], stroke_range_mm: float
                             ) -> dict[str, tuple[float, float | None]]:
    """Each leg's transducer scale error as how far it reads long at full stroke (mm, with its standard error):
    ``leg{i}_reads_long_at_full_stroke_mm``. In mm, so the same rule flags a scale that moved as a joint that did."""
    return {f"leg{i + 1}_reads_long_at_full_stroke_mm": (float(g) * 1e-6 * stroke_range_mm,
                                                         float(s) * 1e-6 * stroke_range_mm)
            for i, (g, s) in enumerate(zip(reads_long_ppm, std_ppm, strict=True))}


@dataclass(frozen=True)
class ParameterDrift:
    """One parameter across the calibrations, and the step or creep found in it."""

    name: str
    run_ids: tuple[str, ...]
    times: tuple[str, ...]
    values_mm: np.ndarray
    std_mm: np.ndarray
    since_last_mm: float | None
    """Newest minus the previous calibration."""
    since_last_sigma: float | None
    step_index: int | None
    """First calibration after the best split (None: fewer than two calibrations)."""
    step_mm: float | None
    step_sigma: float | None
    slope_mm_per_month: float | None
    slope_sigma: float | None
    birge_ratio: float
    """sqrt(chi^2 / dof) of the step model; the standard errors are widened by it when it exceeds 1."""
    flag: str | None = None
    """"step" or "creep" when flagged."""
    sentence: str | None = None
    since_last_flagged: bool = False

    def to_json(self) -> dict[str, Any]:
        def num(x: float | None) -> float | None:
            return None if x is None or not math.isfinite(x) else float(x)

        return {"name": self.name, "label": describe(self.name)[0], "run_ids": list(self.run_ids),
                "times": list(self.times), "values_mm": [num(v) for v in self.values_mm],
                "std_mm": [num(s) for s in self.std_mm], "since_last_mm": num(self.since_last_mm),
                "since_last_sigma": num(self.since_last_sigma), "since_last_flagged": self.since_last_flagged,
                "step_index": self.step_index, "step_mm": num(self.step_mm), "step_sigma": num(self.step_sigma),
                "slope_mm_per_month": num(self.slope_mm_per_month), "slope_sigma": num(self.slope_sigma),
                "birge_ratio": num(self.birge_ratio), "flag": self.flag, "sentence": self.sentence}


@dataclass(frozen=True)
class DriftResult:
    """Every parameter's drift over a machine's calibrations, and the flags in plain sentences."""

    machine: str
    n_calibrations: int
    threshold_mm: float
    sigma_level: float
    parameters: tuple[ParameterDrift, ...]
    skipped: tuple[str, ...] = field(default=())
    """Parameters left out (no finite standard error in at least two calibrations)."""

    @property
    def flagged(self) -> tuple[ParameterDrift, ...]:
        return tuple(p for p in self.parameters if p.flag is not None)

    @property
    def flagged_since_last(self) -> tuple[ParameterDrift, ...]:
        return tuple(p for p in self.parameters if p.since_last_flagged)

    def sentences(self) -> list[str]:
        return [p.sentence for p in self.flagged if p.sentence]

    def parameter(self, name: str) -> ParameterDrift:
        return next(p for p in self.parameters if p.name == name)

    def to_json(self) -> dict[str, Any]:
        return {"machine": self.machine, "n_calibrations": self.n_calibrations, "threshold_mm": self.threshold_mm,
                "sigma_level": self.sigma_level, "rule": rule_text(self.threshold_mm, self.sigma_level),
                "flags": self.sentences(), "since_last": [_since_last_sentence(p) for p in self.flagged_since_last],
                "parameters": [p.to_json() for p in self.parameters], "skipped": list(self.skipped)}


def rule_text(threshold_mm: float = THRESHOLD_MM, sigma_level: float = SIGMA_LEVEL) -> str:
    """The decision rule in one sentence (reports and docs quote it)."""
    return (f"a parameter is flagged when it changed by at least {threshold_mm:g} mm and by more than "
            f"{sigma_level:g} standard errors, after allowing for every split and every parameter tried")


def _days(times: Sequence[str]) -> np.ndarray:
    def parse(t: str) -> datetime:
        d = datetime.fromisoformat(t)
        return d if d.tzinfo else d.replace(tzinfo=UTC)

    t0 = parse(times[0])
    return np.array([(parse(t) - t0).total_seconds() / 86400.0 for t in times])


def _sigma_equivalent(z: float, trials: int) -> float:
    """|z| after a Bonferroni correction for `trials` tests, as the two-sided normal deviate of the same p."""
    p = min(1.0, math.erfc(abs(z) / math.sqrt(2.0)) * max(trials, 1))
    if p >= 1.0:
        return 0.0
    if p <= 0.0:  # beyond ~38σ the tail underflows: the correction no longer matters
        return abs(z)
    return -NormalDist().inv_cdf(p / 2.0)


def _best_step(x: np.ndarray, s: np.ndarray) -> tuple[int, float, float, float]:
    """Split with the largest |z|: (first index after, step mm, z, Birge ratio), z already widened.

    Every split at once from cumulative sums (O(n)), so a history of thousands of calibrations stays fast.
    """
    n = len(x)
    w = 1.0 / s**2
    cw, cwx, cwxx = np.cumsum(w), np.cumsum(w * x), np.cumsum(w * x * x)
    W1, S1, Q1 = cw[:-1], cwx[:-1], cwxx[:-1]
    W2, S2, Q2 = cw[-1] - W1, cwx[-1] - S1, cwxx[-1] - Q1
    m1, m2 = S1 / W1, S2 / W2
    chi2 = np.clip((Q1 - S1 * m1) + (Q2 - S2 * m2), 0.0, None)
    birge = np.sqrt(chi2 / (n - 2)) if n > 2 else np.ones(n - 1)
    z = (m2 - m1) / np.sqrt(1.0 / W1 + 1.0 / W2) / np.maximum(birge, 1.0)
    k = int(np.argmax(np.abs(z)))
    return k + 1, float(m2[k] - m1[k]), float(z[k]), float(birge[k])


def _trend(x: np.ndarray, s: np.ndarray, days: np.ndarray) -> tuple[float | None, float | None]:
    """Weighted straight line against time: (slope mm per month, z widened by the Birge ratio)."""
    if len(x) < 3 or float(np.ptp(days)) <= 0.0:
        return None, None
    w = 1.0 / s**2
    A = np.column_stack([np.ones_like(days), days / DAYS_PER_MONTH])
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    coef = cov @ (A.T @ (w * x))
    chi2 = float(w @ (x - A @ coef) ** 2)
    birge = max(math.sqrt(chi2 / (len(x) - 2)), 1.0)
    slope, se = float(coef[1]), math.sqrt(cov[1, 1]) * birge
    return slope, slope / se


def _since_last_sentence(p: ParameterDrift) -> str:
    label, meaning = describe(p.name)
    assert p.since_last_mm is not None and p.since_last_sigma is not None
    return (f"{label} {p.since_last_mm:+.3f} mm since the previous calibration ({p.times[-2][:10]}), "
            f"{abs(p.since_last_sigma):.0f}σ: {meaning}")


def _parameter(name: str, cals: Sequence[Calibration], days: np.ndarray, n_params: int, threshold_mm: float,
               sigma_level: float) -> ParameterDrift | None:
    keep = [j for j, c in enumerate(cals) if _finite(c.values.get(name)) and _positive(c.std.get(name))]
    if len(keep) < 2:
        return None
    x = np.array([cals[j].values[name] for j in keep], dtype=float)
    s = np.array([cals[j].std[name] for j in keep], dtype=float)
    times = tuple(cals[j].time for j in keep)
    last_mm = float(x[-1] - x[-2])
    last_z = last_mm / math.sqrt(s[-1] ** 2 + s[-2] ** 2)
    k, step_mm, step_z, birge = _best_step(x, s)
    slope, slope_z = _trend(x, s, days[keep])
    label, meaning = describe(name)
    flag = sentence = None
    step_ok = _sigma_equivalent(step_z, (len(x) - 1) * n_params) >= sigma_level and abs(step_mm) >= threshold_mm
    creep_ok = (slope is not None and slope_z is not None and abs(slope * (days[keep][-1] - days[keep][0])
                                                                  / DAYS_PER_MONTH) >= threshold_mm
                and _sigma_equivalent(slope_z, n_params) >= sigma_level)
    if step_ok and not (creep_ok and abs(slope_z or 0.0) > abs(step_z)):
        flag = "step"
        sentence = f"{label} {step_mm:+.2f} mm since {times[k][:10]}, {abs(step_z):.0f}σ: {meaning}"
    elif creep_ok:
        assert slope is not None and slope_z is not None
        flag = "creep"
        sentence = (f"{label} creeps {slope:+.3f} mm per month over {len(x)} calibrations since {times[0][:10]}, "
                    f"{abs(slope_z):.0f}σ: {meaning}, working loose?")
    since_last_flagged = (abs(last_mm) >= threshold_mm
                          and _sigma_equivalent(last_z, n_params) >= sigma_level)
    return ParameterDrift(name, tuple(cals[j].run_id for j in keep), times, x, s, last_mm, last_z, k, step_mm,
                          step_z, slope, slope_z, birge, flag, sentence, since_last_flagged)


def _finite(v: Any) -> bool:
    return v is not None and math.isfinite(float(v))


def _positive(v: Any) -> bool:
    return _finite(v) and float(v) > 0.0


def drift(calibrations: Sequence[Calibration], machine: str = "", *, threshold_mm: float = THRESHOLD_MM,
          sigma_level: float = SIGMA_LEVEL, names: Sequence[str] | None = None) -> DriftResult:
    """Every parameter's drift over a machine's calibrations (sorted by time); flags in plain sentences.

    `names` limits the parameters compared (default: every mm parameter of the newest calibration).
    """
    if threshold_mm < 0 or not math.isfinite(threshold_mm):
        raise ValueError(f"threshold_mm must be a finite number >= 0, got {threshold_mm}")
    cals = sorted(calibrations, key=lambda c: _timestamp(c.time))
    if len(cals) < 2:
        return DriftResult(machine, len(cals), threshold_mm, sigma_level, ())
    wanted = list(names) if names is not None else [n for n in cals[-1].values if n.endswith("_mm")]
    days = _days([c.time for c in cals])
    out, skipped = [], []
    for name in wanted:
        p = _parameter(name, cals, days, len(wanted), threshold_mm, sigma_level)
        if p is None:
            skipped.append(name)
        else:
            out.append(p)
    return DriftResult(machine, len(cals), threshold_mm, sigma_level, tuple(out), tuple(skipped))


def _timestamp(t: str) -> float:
    d = datetime.fromisoformat(t)
    return (d if d.tzinfo else d.replace(tzinfo=UTC)).timestamp()

"""Generic discrepancy terms: flexible shapes of a leg's length error in one variable that the leg sees.

When no library physics describes a mismatch, the diagnosis still locates and models it with these groups,
one per leg x variable x setting (and a few that act on every leg at once, with one set of coefficients per
leg, for a cause the legs share):
- stroke: cubic B-splines with 1-4 interior knots (smooth shapes of any form, e.g. a bent transducer);
- stroke_cyclic: sin/cos of 2 pi stroke / P for a scanned period P (screw lead, pinion or drum runout);
  per leg, and with one period for all legs (the same drive on every leg);
- base_joint_angle, platform_joint_angle: quadratic in the two joint angles (linear terms are what rigid
  joint-position errors produce, so a point-joint model absorbs them; curvature is joint geometry beyond
  point joints, e.g. offset axes of a universal joint); per leg and for all legs;
- axial_force: cubic B-splines in the leg's axial load (non-linear stiffness); linear for all legs;
- last_move: direction of the last move, alone and times the log of its size (friction hysteresis);
- time: cubic B-splines in the time since the session started (a drift of that leg); linear for all legs;
- temperature: cubic B-splines in the recorded temperature (that leg's own thermal behaviour).
- time_lag: a first-order approach 1 - exp(-t / tau) for a scanned time constant tau (a leg warming towards a
  new temperature, a seal settling), which predicts later rows sensibly.
Knots and ranges come from the rows the group is fitted on. Outside that range a spline is held constant.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.interpolate import BSpline
from scipy.optimize import minimize_scalar

from hilcal.discovery.context import EffectContext
from hilcal.discovery.term_groups import GENERIC, TermGroup

STROKE_KNOTS = (1, 2, 3, 4)
FORCE_KNOTS = (1, 2)
TIME_KNOTS = (1, 2, 3)
TEMPERATURE_KNOTS = (0, 1)
LAG_STEPS = 8
CYCLIC_OVERSAMPLING = 4
"""Periods are scanned at 1/4 of the Rayleigh frequency resolution (1 / stroke range)..."""
MAX_PERIODS = 120
"""...but at most this many (coarser steps on long recordings keep the search fast)."""
MIN_DISTINCT_VALUES = 6
MIN_CYCLES = 1.5
Basis = Callable[[EffectContext, int], np.ndarray]
Curve = Callable[[np.ndarray, int], np.ndarray]

READ: dict[str, Callable[[EffectContext, int], np.ndarray]] = {
    "stroke": lambda c, i: c.stroke_mm[:, i],
    "axial_force": lambda c, i: c.force_kn[:, i],
    "time": lambda c, i: c.session_time_s,
    "temperature": lambda c, i: np.zeros(c.n) if c.temp_c is None else c.temp_c,
}
LABEL = {"stroke": ("stroke", "mm"), "axial_force": ("axial load", "kN"), "time": ("time since session start", "s"),
         "temperature": ("temperature", "degC")}


def bspline_basis(x: np.ndarray, lo: float, hi: float, interior: np.ndarray, extend: bool = False) -> np.ndarray:
    """Cubic B-spline basis [len(x), len(interior) + 4] on [lo, hi].

    Outside the range the basis is clamped (held constant), or with `extend` continued linearly along its
    end slopes.
    """
    t = np.concatenate([[lo] * 4, interior, [hi] * 4])
    x = np.asarray(x, dtype=float)
    B = BSpline.design_matrix(np.clip(x, lo, hi), t, 3, extrapolate=False).toarray()
    if extend:
        h = 1e-6 * (hi - lo)
        ends = BSpline.design_matrix(np.array([lo, lo + h, hi - h, hi]), t, 3, extrapolate=False).toarray()
        slope_lo, slope_hi = (ends[1] - ends[0]) / h, (ends[3] - ends[2]) / h
        B = B + np.minimum(x - lo, 0.0)[:, None] * slope_lo + np.maximum(x - hi, 0.0)[:, None] * slope_hi
    return B


def _make(key: str, title: str, sentence: str, variable: str, setting: str, leg: int | None, q: int,
          basis: Basis, curve: Curve | None, names: list[str], **extra: object) -> TermGroup:
    """A group from a per-leg basis: one leg (leg given) or every leg with its own q coefficients (leg None)."""
    legs = [leg] if leg is not None else list(range(6))

    def phi(c: EffectContext) -> np.ndarray:
        out = np.zeros((c.n, 6, q * len(legs)))
        for k, i in enumerate(legs):
            out[:, i, k * q:(k + 1) * q] = basis(c, i)
        return out

    full_names = tuple(f"leg{i + 1}_{n}" for i in legs for n in names)
    return TermGroup(key=key, kind=GENERIC, effect="unexplained", title=title, names=full_names, phi=phi, leg=leg,
                     variable=variable, setting=setting, sentence=sentence, curve=curve, **extra)


def _spline_groups(variable: str, leg: int, fit: EffectContext, knot_counts: tuple[int, ...]) -> list[TermGroup]:
    read = READ[variable]
    label, unit = LABEL[variable]
    x = read(fit, leg)
    lo, hi = float(np.min(x)), float(np.max(x))
    distinct = np.unique(np.round(x, 9)).size
    groups = []
    for k in knot_counts:
        if hi <= lo or distinct < max(MIN_DISTINCT_VALUES, k + 4):
            continue
        interior = np.quantile(x, np.linspace(0, 1, k + 2)[1:-1]) if k else np.zeros(0)
        interior = np.unique(interior[(interior > lo) & (interior < hi)])

        def curve(values: np.ndarray, i: int, lo: float = lo, hi: float = hi, interior: np.ndarray = interior
                  ) -> np.ndarray:
            return bspline_basis(values, lo, hi, interior)

        def basis(c: EffectContext, i: int, curve: Curve = curve) -> np.ndarray:
            return curve(read(c, i), i)

        q = interior.size + 4
        groups.append(_make(
            f"leg{leg + 1}:{variable}:spline{k}", f"leg {leg + 1}: smooth function of its {label} ({k} interior knots)",
            f"leg {leg + 1}'s length error follows a smooth curve in its {label}", variable, f"{k} interior knots", leg,
            q, basis, curve, [f"{variable}_spline{k}_b{j}_mm" for j in range(q)], curve_range=(lo, hi), unit=unit,
        ))
    return groups


def _frequency_scan(fit: EffectContext) -> tuple[float, float, float] | None:
    """(lowest, highest frequency in 1/mm, step) of the period scan; None when the strokes are too few to scan."""
    span = float(np.min(np.ptp(fit.stroke_mm, axis=0)))
    distinct = min(np.unique(np.round(fit.stroke_mm[:, i], 6)).size for i in range(6))
    if span <= 0 or distinct < MIN_DISTINCT_VALUES:
        return None
    f_min, f_max = MIN_CYCLES / span, distinct / span
    return f_min, f_max, max(1.0 / (CYCLIC_OVERSAMPLING * span), (f_max - f_min) / MAX_PERIODS)


def period_step(fit: EffectContext) -> float:
    """The scan's step in frequency (1/mm): a quarter of the Rayleigh resolution, coarser on long recordings; 0
    when the strokes are too few to scan."""
    scan = _frequency_scan(fit)
    return 0.0 if scan is None else scan[2]


def _periods(fit: EffectContext) -> np.ndarray:
    """Scanned periods (mm): from 2/3 of the stroke range (1.5 cycles; a longer 'period' is a smooth bow, which
    the splines describe) down to the mean spacing of the recorded strokes."""
    scan = _frequency_scan(fit)
    if scan is None:
        return np.zeros(0)
    f_min, f_max, step = scan
    return 1.0 / np.arange(f_min, f_max + 1e-12, step)


def cyclic_group(period_mm: float, leg: int | None, stroke_range: tuple[float, float]) -> TermGroup:
    """sin/cos of 2 pi stroke / period on one leg (leg None: every leg, each with its own pair)."""
    def curve(values: np.ndarray, i: int) -> np.ndarray:
        arg = 2.0 * np.pi * np.asarray(values, dtype=float) / period_mm
        return np.stack([np.sin(arg), np.cos(arg)], axis=-1)

    def basis(c: EffectContext, i: int) -> np.ndarray:
        return curve(c.stroke_mm[:, i], i)

    who = "every leg" if leg is None else f"leg {leg + 1}"
    return _make(
        f"{'all' if leg is None else f'leg{leg + 1}'}:stroke_cyclic:{period_mm:.6g}mm",
        f"{who}: periodic error in its stroke (period {period_mm:.4g} mm)",
        f"{who}'s length error repeats every {period_mm:.4g} mm of stroke (a cyclic error, as a screw lead, "
        "a pinion or a drum with runout gives)", "stroke_cyclic", f"period {period_mm:.4g} mm", leg, 2, basis,
        curve, ["cyclic_sin_mm", "cyclic_cos_mm"], curve_range=stroke_range, unit="mm", period_mm=float(period_mm),
    )


def refine_period(group: TermGroup, fit: EffectContext, whitened_d: np.ndarray, Q: np.ndarray, r0: np.ndarray
                  ) -> TermGroup:
    """A chosen cyclic group at the period that explains most within one scan step of it: least squares in the
    frequency, with the current model's whitened residual r0, its columns' orthonormal basis Q and the whitened
    d(residual)/d(leg length) (N, 6, 6). The scan steps by a quarter of the frequency resolution; a period off by
    part of a step leaves a beat that grows along the stroke, which a scale or a bow then takes up."""
    step = period_step(fit)
    if group.period_mm is None or group.curve_range is None or step <= 0:
        return group
    width = 2 * (6 if group.leg is None else 1)

    def unexplained(f: float) -> float:
        cols = (whitened_d @ cyclic_group(1.0 / f, group.leg, group.curve_range).phi(fit)).reshape(-1, width)
        cols = cols - Q @ (Q.T @ cols)
        coef = np.linalg.lstsq(cols, r0, rcond=None)[0]
        return float(np.sum((r0 - cols @ coef) ** 2))

    f0 = 1.0 / group.period_mm
    best = minimize_scalar(unexplained, bounds=(f0 - step, f0 + step), method="bounded",
                           options={"xatol": step * 1e-3})
    if not best.success or best.fun >= unexplained(f0):
        return group
    return cyclic_group(1.0 / float(best.x), group.leg, group.curve_range)


def _cyclic_groups(fit: EffectContext) -> list[TermGroup]:
    stroke_range = (float(np.min(fit.stroke_mm)), float(np.max(fit.stroke_mm)))
    return [cyclic_group(float(period), leg, stroke_range) for period in _periods(fit) for leg in [None, *range(6)]]


def _angle_groups(fit: EffectContext, end: str) -> list[TermGroup]:
    angles = fit.base_angle_rad if end == "base" else fit.platform_angle_rad
    scales = np.max(np.abs(angles), axis=(0, 2))
    if np.any(scales <= 0):
        return []

    def curve(a: np.ndarray, i: int) -> np.ndarray:
        a1, a2 = a[..., 0] / scales[i], a[..., 1] / scales[i]
        return np.stack([a1 * a1, a1 * a2, a2 * a2], axis=-1)

    def basis(c: EffectContext, i: int) -> np.ndarray:
        return curve((c.base_angle_rad if end == "base" else c.platform_angle_rad)[:, i, :], i)

    groups = []
    for leg in [None, *range(6)]:
        who = "every leg" if leg is None else f"leg {leg + 1}"
        groups.append(_make(
            f"{'all' if leg is None else f'leg{leg + 1}'}:{end}_joint_angle:quadratic",
            f"{who}: curvature in its {end} joint angles",
            f"{who}'s length error depends non-linearly on the angle of its {end} joint (joint geometry beyond a "
            "point joint, e.g. offset axes of a universal joint)", f"{end}_joint_angle", "quadratic", leg, 3, basis,
            curve, [f"{end}_angle_{n}_mm" for n in ("a1a1", "a1a2", "a2a2")],
            angle_scale_rad=float(np.max(scales)),
        ))
    return groups


def _lag_groups(leg: int, fit: EffectContext) -> list[TermGroup]:
    """1 - exp(-t / tau) in the time since the session start, tau from a tenth to three times the session."""
    span = float(np.max(fit.session_time_s))
    if span <= 0 or np.unique(fit.session_time_s).size < MIN_DISTINCT_VALUES:
        return []
    groups = []
    for tau in span * np.geomspace(0.1, 3.0, LAG_STEPS):
        def curve(values: np.ndarray, i: int, tau: float = tau) -> np.ndarray:
            return (1.0 - np.exp(-np.asarray(values, dtype=float) / tau))[..., None]

        def basis(c: EffectContext, i: int, curve: Curve = curve) -> np.ndarray:
            return curve(c.session_time_s, i)

        groups.append(_make(
            f"leg{leg + 1}:time_lag:{tau:.4g}s", f"leg {leg + 1}: first-order drift in time (tau {tau:.4g} s)",
            f"leg {leg + 1}'s length drifts towards a new value with a time constant of {tau:.4g} s (a leg warming "
            "or cooling on its own, a seal or a mount settling)", "time_lag", f"tau {tau:.4g} s", leg, 1, basis, curve,
            [f"time_lag_{tau:.4g}s_mm"], curve_range=(0.0, span), unit="s",
        ))
    return groups


def _last_move_group(leg: int, fit: EffectContext) -> list[TermGroup]:
    known = fit.direction[:, leg] != 0
    size = fit.move_mm[known, leg]
    if known.sum() < MIN_DISTINCT_VALUES or np.all(fit.direction[known, leg] == fit.direction[known, leg][0]):
        return []
    ref = float(np.median(size)) or 1.0
    logs = np.log1p(size / ref)
    centre, spread = float(np.mean(logs)), float(np.std(logs)) or 1.0

    def curve(values: np.ndarray, i: int) -> np.ndarray:
        """Basis at [..., 2] = (direction, size of the last move in mm)."""
        d = values[..., 0]
        z = (np.log1p(np.nan_to_num(values[..., 1]) / ref) - centre) / spread
        return np.stack([0.5 * d, d * np.where(d != 0, z, 0.0)], axis=-1)

    def basis(c: EffectContext, i: int) -> np.ndarray:
        return curve(np.stack([c.direction[:, i], c.move_mm[:, i]], axis=-1), i)

    return [_make(
        f"leg{leg + 1}:last_move:direction_size", f"leg {leg + 1}: direction and size of its last move",
        f"leg {leg + 1}'s length error depends on the direction and the size of its last move (hysteresis beyond "
        "constant backlash)", "last_move", "direction, direction x log size", leg, 2, basis, curve,
        ["move_direction_mm", "move_direction_x_logsize_mm"], curve_range=(float(np.min(size)), float(np.max(size))),
        unit="mm", history=True,
    )]


ALL_LEG_SHAPES: tuple[tuple[str, str, Callable[[np.ndarray], np.ndarray]], ...] = (
    ("axial_force", "linear", lambda x: x),
    ("stroke", "quadratic", lambda x: (x / 1000.0) ** 2),
    ("time", "linear", lambda x: x / 3600.0),
)
"""One coefficient per leg in a shape every leg shares: the unsigned, unconstrained cousins of the library (legs
that lengthen under load, which no compliance can) and common non-linearities. A quadratic is taken about the middle
of each leg's stroke (`_all_leg_groups`): its curvature alone, without the slope that x² carries over a range from 0,
which is a reading-scale error's (a bent transducer, level at both ends of its stroke, would otherwise lend the scale
its slope: the coverage study's transducer bow read as 0.1 % scale errors, 7 standard errors off). The middle is the
one of the leg's stroke limits when the robot file gives them: a transducer's linearity error is stated against the
line through its two ends (end-point linearity), so a bow is symmetric about the stroke's middle, not the recorded
range's, whose offset from it would lend the scale a slope again (30 ppm per 15 mm on a 0.25 mm bow of a 1 m
stroke)."""


def _all_leg_groups(fit: EffectContext, stroke_limits_mm: tuple[np.ndarray, np.ndarray] | None = None
                    ) -> list[TermGroup]:
    groups = []
    for variable, setting, shape in ALL_LEG_SHAPES:
        read = READ[variable]
        label, unit = LABEL[variable]
        values = np.stack([read(fit, i) for i in range(6)], axis=1)
        if np.ptp(values) <= 0:
            continue
        middle = (values.min(axis=0) + values.max(axis=0)) / 2.0 if setting == "quadratic" else np.zeros(6)
        if setting == "quadratic" and variable == "stroke" and stroke_limits_mm is not None:
            middle = np.broadcast_to((np.asarray(stroke_limits_mm[0]) + np.asarray(stroke_limits_mm[1])) / 2.0,
                                     (6,)).astype(float)

        def curve(x: np.ndarray, i: int, shape: Callable = shape, middle: np.ndarray = middle) -> np.ndarray:
            return shape(np.asarray(x, dtype=float) - middle[i])[..., None]

        def basis(c: EffectContext, i: int, read: Callable = read, curve: Curve = curve) -> np.ndarray:
            return curve(read(c, i), i)

        groups.append(_make(
            f"all:{variable}:{setting}", f"every leg: {setting} in its {label}",
            f"every leg's length error follows its {label} ({setting}, one coefficient per leg)", variable,
            f"all legs, {setting}", None, 1, basis, curve, [f"{variable}_{setting}_mm"],
            curve_range=(float(np.min(values)), float(np.max(values))), unit=unit,
        ))
    return groups


def generic_groups(fit: EffectContext, stroke_limits_mm: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> list[TermGroup]:
    """Every generic group (per leg and for all legs), bound to the fitted rows; `stroke_limits_mm`: each leg's
    (lowest, highest) stroke from the robot file (leg limits minus the stroke-zero length), when known."""
    groups = (_all_leg_groups(fit, stroke_limits_mm) + _cyclic_groups(fit) + _angle_groups(fit, "base")
              + _angle_groups(fit, "platform"))
    for leg in range(6):
        groups += _spline_groups("stroke", leg, fit, STROKE_KNOTS)
        groups += _spline_groups("axial_force", leg, fit, FORCE_KNOTS)
        groups += _last_move_group(leg, fit)
        groups += _spline_groups("time", leg, fit, TIME_KNOTS)
        groups += _lag_groups(leg, fit)
        if fit.temp_c is not None:
            groups += _spline_groups("temperature", leg, fit, TEMPERATURE_KNOTS)
    return groups

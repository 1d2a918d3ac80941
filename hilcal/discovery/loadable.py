"""What of a diagnosis a controller can load: its compensation set as the controller's per-leg block, and what stays.

The diagnosis' compensation set (`hilcal.discovery.corrections`) adds terms to the recorded leg lengths, in the
recording's variables. A controller's block (`hilcal.leg_compensation`, docs/protocols.md) adds terms to its raw
stroke s with its own force, temperature and direction of motion. The recording's stroke is the reported length less
the robot file's l0: s + delta, delta = the controller's l0 at the recording less the robot file's (plus the block
that was live then, whose products with the new terms are second order and left out). So a term maps exactly:

- `stroke_mm` x k (a reading scale): scale += k 1e6 ppm, and k delta goes into l0;
- `axial_load_kN` x k: compliance -= k; `axial_load_kN*stroke_m` x k: compliance per metre -= k, compliance -= k
  delta / 1000;
- `direction` x k: backlash += 2 k; `leg_mm*(temp_c-20)` x k: thermal += k 1e6 ppm/K;
- a table over `stroke_mm`: the same table over s = x - delta, resampled with the live table onto at most
  ``max_points`` equally spaced points.

What depends on anything else (time, a session, the size of the last move, the joint angles, a shape of the force)
cannot be loaded: it is listed with the reason. So are unexplained shapes the poses did not pin down, and terms
needing a sensor reading the controller does not have.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.discovery.corrections import CompensationSet, Term
from hilcal.discovery.result import Diagnosis
from hilcal.error_models import GEOMETRIC_42
from hilcal.kinematics import Geometry, forward_kinematics
from hilcal.leg_compensation import N_LEGS, REFERENCE_TEMPERATURE_C, SCALAR_FIELDS, LegCompensation
from hilcal.metrics import AccuracySummary
from hilcal.recording import Recording
from hilcal.robot import Robot

MAX_TABLE_POINTS = 256
TABLE_TOLERANCE_MM = 1e-4
"""The controller's table reproduces the combined stroke tables to 0.1 µm where the points allow it."""
FINE_POINTS = 4001
NEEDS_FORCE = ("axial_load_kN", "axial_load_kN*stroke_m")
NEEDS_TEMPERATURE = ("leg_mm*(temp_c-20)",)
WHY_NOT = {
    "session": "a shift between sessions is a re-homing or a zero that moved, not a property of the machine: home "
               "the machine again and check the legs' zeros",
    "session_time_s": "it changes with time: a drift or warm-up that no length correction can follow",
    "last_move_mm_out": "it depends on the size of the last move (a hysteresis the block has no term for)",
    "last_move_mm_in": "it depends on the size of the last move (a hysteresis the block has no term for)",
    "base_joint_angle": "it depends on the joint angles (the pose), not on one leg's stroke",
    "platform_joint_angle": "it depends on the joint angles (the pose), not on one leg's stroke",
    "axial_load_kN": "a non-linear shape of the force that the block's linear compliance does not hold",
    "temp_c": "a non-linear shape of the temperature that the block's thermal coefficient does not hold",
}


@dataclass(frozen=True)
class Correction:
    """One effect the upload corrects (or would, where the controller could take it), in an engineer's words."""

    effect: str
    title: str
    legs: tuple[int, ...]
    sentence: str
    grade: str
    """'physics', 'fault' (a set-up fault: the upload corrects it, the cause should be fixed) or 'unexplained'."""
    values: tuple[dict[str, Any], ...] = ()
    """Per parameter: name, leg, value, unit, std_error."""
    why_not: str = ""
    """Empty when it is loaded; else why it stays uncorrected."""

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "title": self.title, "legs": list(self.legs), "sentence": self.sentence,
                "grade": self.grade, "values": list(self.values), "why_not": self.why_not or None}


@dataclass(frozen=True)
class Loadable:
    """The set to upload: the geometry fitted with the effects, the block and the l0 shift its terms imply."""

    geometry_x: np.ndarray
    """The 42 error parameters (da, db, dl0 per leg; hilcal.error_models.GEOMETRIC_42) of the joint fit."""
    block: LegCompensation
    """The block the controller should hold: the live one plus this diagnosis' loadable terms."""
    increment: LegCompensation
    """This diagnosis' loadable terms alone (on the same table grid as `block`)."""
    l0_shift_mm: np.ndarray
    """Constant parts of the terms (their stroke offset delta), to add to the leg offsets l0."""
    corrected: tuple[Correction, ...] = ()
    not_corrected: tuple[Correction, ...] = ()
    table_error_mm: float = 0.0
    """Largest difference between the controller's table and the combined stroke tables over their range."""
    loadable_keys: tuple[str, ...] = field(default_factory=tuple)
    """The diagnosis groups whose terms are in the block."""

    @property
    def corrects_anything(self) -> bool:
        return not self.increment.is_zero

    def to_json(self) -> dict[str, Any]:
        return {"block": self.block.to_json(), "increment": self.increment.to_json(),
                "l0_shift_mm": self.l0_shift_mm.tolist(), "table_error_mm": self.table_error_mm,
                "corrected": [c.to_json() for c in self.corrected],
                "not_corrected": [c.to_json() for c in self.not_corrected]}


def _add(values: dict[str, np.ndarray], name: str, leg: int, amount: float) -> None:
    values.setdefault(name, np.zeros(N_LEGS))[leg] += amount


def _library_term(term: Term, delta: float, values: dict[str, np.ndarray], l0_shift: np.ndarray) -> None:
    """Add one coefficient term to the block's scalars (see the module docstring for the mapping)."""
    k, leg = float(term.coefficient_mm or 0.0), term.leg
    if term.variable == "stroke_mm":
        _add(values, "scale_ppm", leg, k * 1e6)
        l0_shift[leg] += k * delta
    elif term.variable == "axial_load_kN":
        _add(values, "compliance_mm_per_kn", leg, -k)
    elif term.variable == "axial_load_kN*stroke_m":
        _add(values, "compliance_mm_per_kn_m", leg, -k)
        _add(values, "compliance_mm_per_kn", leg, -k * delta / 1000.0)
    elif term.variable == "direction":
        _add(values, "backlash_mm", leg, 2.0 * k)
    elif term.variable == "leg_mm*(temp_c-20)":
        _add(values, "thermal_ppm_per_k", leg, k * 1e6)
    else:
        raise ValueError(f"no block term for {term.variable}")


def _tables(terms: list[Term], delta: np.ndarray, live: LegCompensation, max_points: int
            ) -> tuple[LegCompensation, LegCompensation, float]:
    """The live block and the increment with one table grid, the increment holding the stroke tables of `terms`.

    Each leg's grid spans the live table and the new tables (in raw stroke); the point count is the smallest that
    reproduces the sum to TABLE_TOLERANCE_MM on every leg, at most max_points. Returns (live, increment, error)."""
    spans = [[] for _ in range(N_LEGS)]
    for t in terms:
        assert t.grid is not None
        spans[t.leg].append((float(t.grid[0]) - delta[t.leg], float(t.grid[-1]) - delta[t.leg]))
    if live.table_points:
        for leg in range(N_LEGS):
            spans[leg].append((float(live.table_start_mm[leg]), float(live.table_end_mm[leg])))
    if not any(spans):
        return live, replace(live, **_zero_scalars(), table_mm=np.zeros_like(live.table_mm)), 0.0
    start = np.array([min((a for a, _ in s), default=0.0) for s in spans])
    end = np.array([max((b for _, b in s), default=1.0) for s in spans])
    end = np.where(end > start, end, start + 1.0)

    def new_table(stroke: np.ndarray) -> np.ndarray:
        out = np.zeros_like(stroke)
        for t in terms:
            assert t.grid is not None and t.correction_mm is not None
            out[:, t.leg] += np.interp(stroke[:, t.leg] + delta[t.leg], t.grid, t.correction_mm)
        return out

    fine = np.linspace(start, end, FINE_POINTS)
    exact = new_table(fine) + live.table_at(fine)
    n = 2
    while True:
        grid = np.linspace(start, end, n)
        trial = LegCompensation(table_start_mm=start, table_end_mm=end,
                                table_mm=(new_table(grid) + live.table_at(grid)).T.copy())
        error = float(np.max(np.abs(trial.table_at(fine) - exact)))
        if error <= TABLE_TOLERANCE_MM or n >= max_points:
            break
        n = min(max_points, 2 * n)
    live_on_grid = replace(live, table_start_mm=start, table_end_mm=end, table_mm=live.table_at(grid).T.copy())
    return live_on_grid, LegCompensation(table_start_mm=start, table_end_mm=end, table_mm=new_table(grid).T.copy()), \
        error


def _zero_scalars() -> dict[str, np.ndarray]:
    return {name: np.zeros(N_LEGS) for name in SCALAR_FIELDS}


def _named(diag: Diagnosis, effect: str) -> Any:
    return next((n for n in diag.named if n.effect == effect), None)


def _correction(diag: Diagnosis, key: str, terms: list[Term], why_not: str = "") -> Correction:
    """The sentence and values of one group of the final model."""
    effect = terms[0].effect
    legs = tuple(sorted({t.leg + 1 for t in terms}))
    named = _named(diag, effect)
    if named is not None:
        values = tuple({"name": r.name, "leg": r.leg, "value": r.value, "unit": r.unit, "std_error": r.std_error}
                       for r in named.rows)
        return Correction(effect, named.title, named.legs or legs, named.sentence, named.grade, values, why_not)
    group = next((g for g in diag.groups if g.key == key), None)
    shapes = [s for s in diag.shapes if s.group.key == key]
    amplitude = max((s.amplitude_mm for s in shapes), default=max((t.size_mm for t in terms), default=0.0))
    title = group.title if group is not None else key
    sentence = (f"{title} on {'leg' if len(legs) == 1 else 'legs'} {', '.join(map(str, legs))}: a shape no library "
                f"effect names, up to ±{amplitude * 1000:.1f} µm")
    return Correction(effect, title, legs, sentence, "unexplained", (), why_not)


def loadable_compensation(diag: Diagnosis, robot: Robot, l0_before_mm: np.ndarray, *,
                          live: LegCompensation | None = None, force_reading: bool = True,
                          temperature_reading: bool = True, max_points: int = MAX_TABLE_POINTS) -> Loadable:
    """The block a controller can hold for this diagnosis' compensation set, composed with the live block.

    `l0_before_mm` are the controller's leg offsets when the recording was made (its stroke reference), `live` the
    block it held then (None: none). Terms needing a force or temperature reading the controller lacks are not
    loaded, and say so."""
    comp = diag.compensation
    live = live or LegCompensation()
    if live.reference_temperature_c != REFERENCE_TEMPERATURE_C:
        raise ValueError("the live block's reference temperature is not 20 °C: compose it by hand")
    geometry = np.array([comp.geometry_mm[n] for n in GEOMETRIC_42.names]) if comp is not None else \
        diag.final_fit.x[:42].copy()
    delta = np.asarray(l0_before_mm, dtype=float) - robot.l0
    by_group: dict[str, list[Term]] = {}
    for t in () if comp is None else comp.terms:
        by_group.setdefault(t.group, []).append(t)
    unpinned = {(s.group.key, s.leg) for s in diag.shapes if not s.pinned}
    values: dict[str, np.ndarray] = {}
    l0_shift = np.zeros(N_LEGS)
    tables: list[Term] = []
    corrected, not_corrected, loaded = [], [], []
    for key, terms in by_group.items():
        why = _why_not(terms, unpinned, force_reading, temperature_reading)
        if why:
            not_corrected.append(_correction(diag, key, terms, why))
            continue
        for t in terms:
            if t.coefficient_mm is not None:
                _library_term(t, float(delta[t.leg]), values, l0_shift)
            else:
                tables.append(t)
        loaded.append(key)
        corrected.append(_correction(diag, key, terms))
    live_grid, increment, error = _tables(tables, delta, live, max_points)
    increment = replace(increment, **{**_zero_scalars(), **values})
    block = replace(live_grid, **{name: getattr(live_grid, name) + getattr(increment, name)
                                  for name in _zero_scalars()},
                    table_mm=live_grid.table_mm + increment.table_mm)
    corrected.sort(key=lambda c: c.grade != "fault")
    return Loadable(geometry, block, increment, l0_shift, tuple(corrected), tuple(not_corrected), error,
                    tuple(loaded))


def _why_not(terms: list[Term], unpinned: set[tuple[str, int]], force: bool, temperature: bool) -> str:
    """Why a group's terms cannot go into the block ('' when they can)."""
    for t in terms:
        if t.angle_terms or t.variable in ("base_joint_angle", "platform_joint_angle"):
            return WHY_NOT["base_joint_angle"]
        if t.coefficient_mm is None and t.variable != "stroke_mm":
            return WHY_NOT.get(t.variable, f"it depends on {t.variable}, which the block has no term for")
        if t.coefficient_mm is not None and t.variable in ("session", "session_time_s"):
            return WHY_NOT[t.variable]
        if t.variable in NEEDS_FORCE and not force:
            return "the controller reads no axial force, so it cannot apply a compliance"
        if t.variable in NEEDS_TEMPERATURE and not temperature:
            return "the controller reads no leg temperature, so it cannot apply a thermal coefficient"
        if t.coefficient_mm is None and (t.group, t.leg) in unpinned:
            return "the recorded poses do not pin its shape down (its 95 % band is wide): measure more poses first"
    return ""


def held_out_prediction(diag: Diagnosis, loadable: Loadable, rec: Recording, robot: Robot) -> AccuracySummary | None:
    """The verify rows' pose error that the uploaded set predicts: the joint geometry with only the loaded terms
    applied (what stays uncorrected stays in the error), against the measured poses, which no choice used."""
    verify = rec.phase == "verify"
    if diag.compensation is None or not verify.any():
        return None
    loaded = CompensationSet(diag.compensation.geometry_mm,
                             tuple(t for t in diag.compensation.terms if t.group in loadable.loadable_keys))
    legs = rec.legs_mm + loaded.leg_corrections(EffectContext.from_recording(rec, robot))
    geometry = Geometry.nominal(robot).perturbed(loadable.geometry_x)
    predicted = forward_kinematics(geometry, legs[verify], rec.meas[verify])
    return AccuracySummary.of(rec.meas[verify], predicted)

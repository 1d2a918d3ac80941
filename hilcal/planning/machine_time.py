"""Machine time of a calibration: how long the legs take to move between poses, and the whole route's time.

A move of a Stewart platform is commanded as six leg-length setpoints that the servo reaches together, so a
move lasts as long as its slowest leg. Each leg follows a trapezoidal velocity profile (accelerate at
``leg_accel_mm_s2``, cruise at ``leg_speed_mm_s``, decelerate), or a triangular one when the distance is too
short to reach the cruise speed. Every move ends at a standstill (the procedure waits for IN_POSITION), so
a long move split into waypoints costs one profile per step. A measured pose adds a settle wait and the CMM
probing time. The motion rules are those of the plan: steps of at most ``max_step_mm`` on any leg,
interpolated in pose space, then an approach point with every leg ``approach_mm`` shorter, then the target;
a repeated measurement of the same pose first retreats every leg by ``retreat_mm``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hilcal.kinematics import Geometry, inverse_kinematics


@dataclass(frozen=True)
class MotionTiming:
    """The machine's timing (from the real devices): leg speed and acceleration, waits and probing per pose."""

    leg_speed_mm_s: float
    leg_accel_mm_s2: float
    settle_s: float
    cmm_s_per_pose: float
    move_overhead_s: float = 0.0
    """Per move: command round trip and the controller's in-position check."""

    def __post_init__(self) -> None:
        if not (self.leg_speed_mm_s > 0 and self.leg_accel_mm_s2 > 0):
            raise ValueError(f"leg speed and acceleration must be positive, got {self.leg_speed_mm_s} mm/s, "
                             f"{self.leg_accel_mm_s2} mm/s²")
        if min(self.settle_s, self.cmm_s_per_pose, self.move_overhead_s) < 0:
            raise ValueError("settle, CMM and per-move times must be >= 0")


@dataclass(frozen=True)
class MotionRules:
    """How the plan moves between poses (mm): step bound, approach distance, retreat before a repeat."""

    max_step_mm: float = 50.0
    approach_mm: float = 2.0
    retreat_mm: float = 10.0

    def __post_init__(self) -> None:
        if self.max_step_mm <= 0 or self.approach_mm < 0 or self.retreat_mm < self.approach_mm:
            raise ValueError(f"need max_step_mm > 0, approach_mm >= 0 and retreat_mm >= approach_mm, got {self}")


def trapezoid_time(distance_mm: np.ndarray | float, speed_mm_s: float, accel_mm_s2: float) -> np.ndarray:
    """Time (s) of a rest-to-rest move over |distance|: trapezoidal profile, triangular below v²/a."""
    d = np.abs(np.asarray(distance_mm, dtype=float))
    v, a = speed_mm_s, accel_mm_s2
    return np.where(d >= v * v / a, d / v + v / a, 2.0 * np.sqrt(d / a))


def move_time(legs_from: np.ndarray, legs_to: np.ndarray, timing: MotionTiming) -> np.ndarray:
    """Time (s) of moves [...] between leg-length setpoints [..., 6]: the slowest leg, plus the per-move overhead."""
    per_leg = trapezoid_time(np.asarray(legs_to) - np.asarray(legs_from), timing.leg_speed_mm_s, timing.leg_accel_mm_s2)
    return per_leg.max(axis=-1) + timing.move_overhead_s


def interpolated_poses(geom: Geometry, start_pose: np.ndarray, target_pose: np.ndarray, max_step_mm: float
                       ) -> np.ndarray:
    """Poses (n, 6) from start (excluded) to target (the last row) with no leg changing more than max_step_mm.

    Poses are interpolated in pose space (the workspace box is convex); legs are not linear in the pose, so
    the number of steps grows from ceil(largest leg change / bound) until every leg step is within the bound.
    """
    start = np.asarray(start_pose, dtype=float)
    target = np.asarray(target_pose, dtype=float)
    start_legs = inverse_kinematics(geom, start)
    n = max(1, int(np.ceil(np.max(np.abs(inverse_kinematics(geom, target) - start_legs)) / max_step_mm)))
    while True:
        poses = start + (target - start) * (np.arange(1, n + 1)[:, None] / n)
        legs = inverse_kinematics(geom, np.vstack([start, poses]))
        if np.max(np.abs(np.diff(legs, axis=0))) <= max_step_mm:
            return poses
        n += 1


def visit_setpoints(geom: Geometry, start_pose: np.ndarray, target_pose: np.ndarray, rules: MotionRules,
                    *, approach: bool = True) -> list[tuple[str, np.ndarray]]:
    """The leg setpoints (kind, legs (6,)) that take the platform from start to target under the rules.

    Kinds: "transit" (bounded steps), "retreat" (a repeat of the same pose: every leg retreat_mm shorter),
    "approach" (every leg approach_mm shorter than at the target) and "target". Without `approach` (a move
    that measures nothing, e.g. back home) the target is reached directly.
    """
    start = np.asarray(start_pose, dtype=float)
    target = np.asarray(target_pose, dtype=float)
    target_legs = inverse_kinematics(geom, target)
    if approach and np.array_equal(start, target):
        return [("retreat", target_legs - rules.retreat_mm), ("approach", target_legs - rules.approach_mm),
                ("target", target_legs)]
    poses = interpolated_poses(geom, start, target, rules.max_step_mm)
    steps = [("transit", legs) for legs in inverse_kinematics(geom, poses[:-1])]
    if approach:
        steps.append(("approach", target_legs - rules.approach_mm))
    return [*steps, ("target", target_legs)]


def _waypoint_legs(geom: Geometry, starts: np.ndarray, targets: np.ndarray, max_step_mm: float) -> list[
        tuple[np.ndarray, np.ndarray]]:
    """``interpolated_poses`` for many start/target pairs: (pair indices, legs [P, n + 1, 6]) per step count n."""
    l_start = inverse_kinematics(geom, starts)
    span = np.max(np.abs(inverse_kinematics(geom, targets) - l_start), axis=-1)
    n = np.maximum(1, np.ceil(span / max_step_mm)).astype(int)
    todo = np.arange(len(starts))
    done = []
    while todo.size:
        retry = []
        for k in np.unique(n[todo]):
            idx = todo[n[todo] == k]
            frac = np.arange(0, k + 1) / k
            poses = starts[idx, None, :] + (targets[idx] - starts[idx])[:, None, :] * frac[None, :, None]
            legs = inverse_kinematics(geom, poses)
            over = np.max(np.abs(np.diff(legs, axis=1)), axis=(1, 2)) > max_step_mm
            done.append((idx[~over], legs[~over]))
            retry.append(idx[over])
        todo = np.concatenate(retry)
        n[todo] += 1
    return done


@dataclass(frozen=True)
class MoveCosts:
    """Time (s), setpoint count and leg travel (sum over setpoints of the largest leg change, mm) per move.

    min_leg_mm and max_leg_mm are the extreme leg setpoints of the move (transit, retreat, approach, target):
    legs are not linear in the pose, so a straight line between two reachable poses can leave the leg limits.
    """

    time_s: np.ndarray
    n_moves: np.ndarray
    travel_mm: np.ndarray
    min_leg_mm: np.ndarray
    max_leg_mm: np.ndarray

    def within(self, leg_limits: tuple[float, float]) -> np.ndarray:
        """Which moves keep every setpoint within [low, high] mm."""
        return (self.min_leg_mm >= leg_limits[0]) & (self.max_leg_mm <= leg_limits[1])


def move_costs(geom: Geometry, starts: np.ndarray, targets: np.ndarray, rules: MotionRules, timing: MotionTiming,
               *, approach: bool = True) -> MoveCosts:
    """Costs [P] of visiting targets [P, 6] from starts [P, 6], exactly as ``visit_setpoints`` moves, batched."""
    starts = np.atleast_2d(np.asarray(starts, dtype=float))
    targets = np.atleast_2d(np.asarray(targets, dtype=float))
    time_s = np.zeros(len(starts))
    travel = np.zeros(len(starts))
    count = np.zeros(len(starts), dtype=int)
    low, high = np.zeros(len(starts)), np.zeros(len(starts))
    for idx, legs in _waypoint_legs(geom, starts, targets, rules.max_step_mm):
        if approach:
            legs = np.concatenate([legs[:, :-1], legs[:, -1:] - rules.approach_mm, legs[:, -1:]], axis=1)
        steps = np.diff(legs, axis=1)
        time_s[idx] = move_time(0.0, steps, timing).sum(axis=1)
        travel[idx] = np.abs(steps).max(axis=-1).sum(axis=1)
        count[idx] = steps.shape[1]
        low[idx], high[idx] = legs[:, 1:].min(axis=(1, 2)), legs[:, 1:].max(axis=(1, 2))
    if approach:
        same = np.all(starts == targets, axis=1)
        if same.any():
            r, a = rules.retreat_mm, rules.approach_mm
            steps = np.array([-r, r - a, a])[:, None] * np.ones(6)
            time_s[same] = move_time(0.0, steps, timing).sum()
            travel[same] = r + (r - a) + a
            count[same] = 3
            low[same] = inverse_kinematics(geom, targets[same]).min(axis=-1) - r
    return MoveCosts(time_s, count, travel, low, high)


@dataclass(frozen=True)
class PhaseTime:
    """Estimated machine time of one phase of the route (s) and its leg travel (mm)."""

    phase: str
    n_poses: int
    n_moves: int
    leg_travel_mm: float
    motion_s: float
    settle_s: float
    probing_s: float

    @property
    def total_s(self) -> float:
        return self.motion_s + self.settle_s + self.probing_s


@dataclass(frozen=True)
class TimeEstimate:
    """Estimated machine time of a route, per phase; the parts are motion, settle and probing (s)."""

    phases: tuple[PhaseTime, ...]

    @property
    def motion_s(self) -> float:
        return sum(p.motion_s for p in self.phases)

    @property
    def settle_s(self) -> float:
        return sum(p.settle_s for p in self.phases)

    @property
    def probing_s(self) -> float:
        return sum(p.probing_s for p in self.phases)

    @property
    def total_s(self) -> float:
        return self.motion_s + self.settle_s + self.probing_s

    @property
    def leg_travel_mm(self) -> float:
        return sum(p.leg_travel_mm for p in self.phases)

    def phase(self, name: str) -> PhaseTime:
        for p in self.phases:
            if p.phase == name:
                return p
        raise KeyError(name)

    def as_dict(self) -> dict:
        """Plain JSON: totals and per phase, seconds and mm."""
        keys = ("motion_s", "settle_s", "probing_s", "total_s", "leg_travel_mm")
        return {**{k: getattr(self, k) for k in keys},
                "phases": {p.phase: {"n_poses": p.n_poses, "n_moves": p.n_moves,
                                     **{k: getattr(p, k) for k in keys}} for p in self.phases}}


def estimate_route(geom: Geometry, start_pose: np.ndarray, phases: Sequence[tuple[str, np.ndarray]],
                   rules: MotionRules, timing: MotionTiming, end_pose: np.ndarray | None = None) -> TimeEstimate:
    """Time of visiting each phase's poses in order from start_pose (then back to end_pose, if given).

    Every pose is approached under the rules, settled and probed once; a pose equal to the previous one is
    a repeat (retreat, approach, target). The final move to end_pose (phase "return_home") measures nothing.
    """
    out = []
    pose = np.asarray(start_pose, dtype=float)
    for name, poses in phases:
        q = np.atleast_2d(np.asarray(poses, dtype=float)).reshape(-1, 6)
        if len(q) == 0:
            out.append(PhaseTime(name, 0, 0, 0.0, 0.0, 0.0, 0.0))
            continue
        c = move_costs(geom, np.vstack([pose, q[:-1]]), q, rules, timing)
        out.append(PhaseTime(name, len(q), int(c.n_moves.sum()), float(c.travel_mm.sum()), float(c.time_s.sum()),
                             len(q) * timing.settle_s, len(q) * timing.cmm_s_per_pose))
        pose = q[-1]
    if end_pose is not None:
        c = move_costs(geom, pose, np.asarray(end_pose, dtype=float), rules, timing, approach=False)
        out.append(PhaseTime("return_home", 0, int(c.n_moves[0]), float(c.travel_mm[0]), float(c.time_s[0]), 0.0, 0.0))
    return TimeEstimate(tuple(out))


def calibration_phases(measure_poses: np.ndarray, verify_poses: np.ndarray,
                       acceptance_poses: np.ndarray | None = None) -> list[tuple[str, np.ndarray]]:
    """The calibration procedure's route: measure, verify, then the verify poses again after the upload, then the
    acceptance test's poses in visiting order (phase "acceptance"), if any."""
    phases = [("measure", measure_poses), ("verify", verify_poses), ("verify_after", verify_poses)]
    return phases if acceptance_poses is None else [*phases, ("acceptance", acceptance_poses)]


def format_minutes(seconds: float) -> str:
    """"1 h 02 min", "12.5 min" or "40 s": a duration for people."""
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 3600:
        return f"{seconds / 60:.1f} min"
    hours, minutes = divmod(round(seconds / 60), 60)
    return f"{hours} h {minutes:02d} min"


def repeatable_pose(geom: Geometry, poses: np.ndarray, lower_leg_limit_mm: float, rules: MotionRules) -> int:
    """Index of the pose to measure repeatedly: the one whose shortest leg is furthest above the limit.

    A repeat retreats every leg by rules.retreat_mm, so that pose needs the room; ValueError if none has it.
    """
    margin = inverse_kinematics(geom, np.atleast_2d(poses)).min(axis=-1) - lower_leg_limit_mm
    k = int(np.argmax(margin))
    if margin[k] < rules.retreat_mm:
        raise ValueError(f"no pose leaves {rules.retreat_mm} mm above the lower leg limit for a repeat's retreat "
                         f"(best: {margin[k]:.1f} mm)")
    return k

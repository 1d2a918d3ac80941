"""The computing of the paper study (``paper_study.py``): the truth rig, the identification runs over the grid of
section 5.2 and the Table 7 block, and the paired statistics that compare LS with L-infinity.

The rig's noise-free truth (its own forward kinematics and sphere layout) is solved once per error set and pose
set; measurement noise is then added to the sphere centres here, so one truth solve serves every noise level and
noise shape. A self-check compares this path with ``simulate_recording`` at zero noise.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.progress import Progress
from scipy.spatial.transform import Rotation
from scipy.stats import binomtest

from hilcal.identifiability import identifiability, leg_axis_modes
from hilcal.identification import IdentificationError, IdentificationResult, identify, predict_poses
from hilcal.kinematics import Geometry, KinematicsError, forward_kinematics, gravity_wrench, leg_forces, split_pose
from hilcal.metrics import AccuracySummary, pose_errors
from hilcal.planning.design import factorial_exchange, paper_pose_sets, random_poses, verification_poses
from hilcal.pose_measurement import pose_from_spheres
from hilcal.robot import Robot
from procedures.cli.simulated_recording import simulate_recording
from sim_devices.rig.config import GeometryErrors, RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

ROOT = Path(__file__).resolve().parents[2]
DOC_PATH = ROOT / "docs" / "paper_study.md"
IMG_DIR = ROOT / "docs" / "img"

ERROR_SET_LABELS = {
    "table3": "I (Table 3)",
    "table4": "II (Table 4)",
    "table5": "III (Table 5)",
    "table2": "Table 2",
}
POSE_SET_LABELS = {
    "set1_random32": "1: random 32",
    "set2_doptimal32": "2: D-opt 32",
    "set3_factorial_exchange32": "3: factorial+exchange 32",
    "set4_doptimal64": "4: D-opt 64",
}
ESTIMATORS = ("ls", "linf")
EST_LABEL = {"ls": "LS", "linf": "L∞"}

GAIN_ERROR = 1e-4
"""Unmodelled transducer gain error: the controller reports (1 + GAIN_ERROR) times the length that drove the rig."""

LEG_COMPLIANCE_MM_PER_N = 1e-5
"""Unmodelled axial leg compliance (stiffness 100 N/µm): the reported length exceeds the loaded length by c·f."""

PAPER_TABLE7 = {
    "before": {"position_mm": (6.9595, 14.2670, 6.1194, 6.1455), "orientation_deg": (0.6977, 1.4721, 0.5952, 0.5971)},
    "linf": {"position_mm": (0.9408, 1.8534, 0.9001, 0.9005), "orientation_deg": (0.0848, 0.1620, 0.0805, 0.0806)},
    "ls": {"position_mm": (1.0980, 2.0313, 1.0174, 1.0189), "orientation_deg": (0.1037, 0.1815, 0.0964, 0.0965)},
}
"""The paper's Table 7 (max, range, mean, RMS), quoted for reference only; never used in a computation."""

INDICATORS = ("max", "range", "mean", "rms")


@dataclass(frozen=True)
class StudyPlan:
    """What to run: the section 5.2 grid and the Table 7 block (seeds, noise levels, sets)."""

    quick: bool
    seeds: tuple[int, ...]
    error_sets: tuple[str, ...]
    noises_mm: tuple[float, ...]
    pose_sets: tuple[str, ...]
    n_eval: int
    t7_seeds: tuple[int, ...]
    t7_noise_mm: float = 0.005
    n_verify: int = 24


FULL_PLAN = StudyPlan(
    quick=False,
    seeds=(0, 1, 2, 3, 4),
    error_sets=("table3", "table4", "table5", "table2"),
    noises_mm=(1e-4, 1e-3, 1e-2, 1e-1),
    pose_sets=tuple(POSE_SET_LABELS),
    n_eval=100,
    t7_seeds=tuple(range(20)),
)
QUICK_PLAN = StudyPlan(
    quick=True,
    seeds=(0,),
    error_sets=("table3", "table2"),
    noises_mm=(1e-3, 1e-1),
    pose_sets=("set1_random32", "set3_factorial_exchange32"),
    n_eval=30,
    t7_seeds=(0, 1, 2),
)


# ---------------------------------------------------------------------------------------------- simulation


@dataclass(frozen=True)
class Truth:
    """Commanded poses, the leg lengths the controller reported for them, and the poses the rig really took."""

    cmd: np.ndarray
    legs_mm: np.ndarray
    poses: np.ndarray


class TruthRig:
    """Noise-free truth from the independent rig physics; measurement noise is added by ``measure``."""

    def __init__(self, robot: Robot, errors: GeometryErrors, seed: int) -> None:
        self.robot = robot
        self.rig = SimulatedRig(robot, RigConfig(seed=seed, errors=errors, cmm_noise_mm=0.0))

    def run(self, cmd: np.ndarray) -> Truth:
        """Command each pose with the uncalibrated controller and solve the rig's true forward kinematics."""
        legs = self.rig.controller_ik(cmd)
        return Truth(cmd=np.asarray(cmd, dtype=float), legs_mm=legs, poses=self.rig.true_poses_for_lengths(legs))

    def measure(self, poses: np.ndarray, noise_mm: float, kind: str, rng: np.random.Generator) -> np.ndarray:
        """CMM-measured poses: sphere centres in the CMM frame plus noise, registered by hilcal.

        kind: ``gaussian`` N(0, σ²) per sphere coordinate; ``uniform`` U(±√3σ) per sphere coordinate (same std,
        bounded); ``uniform_pose`` noise-free spheres, then U(±√3σ) on each pose residual component (rotations
        as mm at the characteristic length), the case where L∞ is the maximum-likelihood estimator.
        """
        R, t = split_pose(poses)
        spheres = self.robot.platform_spheres
        platform_base = np.einsum("nij,kj->nki", R, spheres) + t[:, None, :]
        platform_cmm = self.rig.to_cmm(platform_base)
        base_cmm = np.repeat(self.rig.to_cmm(self.robot.base_spheres)[None], len(poses), axis=0)
        half = np.sqrt(3.0) * noise_mm
        if kind == "gaussian":
            platform_cmm = platform_cmm + rng.normal(0.0, noise_mm, platform_cmm.shape)
            base_cmm = base_cmm + rng.normal(0.0, noise_mm, base_cmm.shape)
        elif kind == "uniform":
            platform_cmm = platform_cmm + rng.uniform(-half, half, platform_cmm.shape)
            base_cmm = base_cmm + rng.uniform(-half, half, base_cmm.shape)
        elif kind != "uniform_pose":
            raise ValueError(f"unknown noise kind {kind!r}")
        measured = pose_from_spheres(platform_cmm, base_cmm, self.robot).pose
        if kind == "uniform_pose":
            measured = _perturb_pose(measured, rng.uniform(-half, half, measured.shape), self.robot)
        return measured


def _perturb_pose(poses: np.ndarray, delta: np.ndarray, robot: Robot) -> np.ndarray:
    """Apply [dt (mm), length·dw (mm)] in the base frame to poses (mm, deg)."""
    R, t = split_pose(poses)
    dR = Rotation.from_rotvec(delta[:, 3:] / robot.characteristic_length_mm).as_matrix()
    ypr = Rotation.from_matrix(dR @ R).as_euler("ZYX", degrees=True)
    return np.column_stack([t + delta[:, :3], ypr[:, ::-1]])


def self_check(robot: Robot) -> float:
    """Max |difference| (mm or deg) between this script's measurement path and simulate_recording at zero noise."""
    errors = load_errors("table2", robot)
    rng = np.random.default_rng(99)
    measure_cmd, verify_cmd = random_poses(robot, 8, rng), random_poses(robot, 4, rng)
    rec = simulate_recording(robot, RigConfig(seed=5, errors=errors, cmm_noise_mm=0.0), measure_cmd, verify_cmd)
    rig = TruthRig(robot, errors, seed=5)
    truth = rig.run(np.concatenate([measure_cmd, verify_cmd]))
    meas = rig.measure(truth.poses, 0.0, "gaussian", rng)
    return float(max(np.max(np.abs(rec.legs_mm - truth.legs_mm)), np.max(np.abs(rec.meas - meas))))


def perturb_legs(robot: Robot, truth: Truth, effect: str) -> np.ndarray:
    """Leg lengths the controller reports under an unmodelled effect (the rig moved with truth.legs_mm)."""
    if effect == "none":
        return truth.legs_mm
    if effect == "gain":
        return truth.legs_mm * (1.0 + GAIN_ERROR)
    if effect == "compliance":
        force = leg_forces(Geometry.nominal(robot), truth.poses, gravity_wrench(robot, truth.poses))
        return truth.legs_mm + LEG_COMPLIANCE_MM_PER_N * force
    raise ValueError(f"unknown effect {effect!r}")


# ---------------------------------------------------------------------------------------------- evaluation


def predicted_poses(
    robot: Robot, result: IdentificationResult | None, legs_mm: np.ndarray, cmd: np.ndarray
) -> np.ndarray:
    """Poses the controller model believes for these legs: nominal FK (before) or the calibrated model (after)."""
    if result is None:
        return forward_kinematics(Geometry.nominal(robot), legs_mm, cmd)
    return predict_poses(result, robot, legs_mm, cmd)


def ident_errors(robot: Robot, x: np.ndarray, truth_vector: np.ndarray) -> tuple[float, float]:
    """RMS of identified minus true errors (mm), in full and with the 12 leg-axis modes projected out."""
    d = x - truth_vector
    modes = np.array([m for _, m in leg_axis_modes(robot, robot.home[None, :])])
    q, _ = np.linalg.qr(modes.T)
    d_rest = d - q @ (q.T @ d)
    return float(np.sqrt(np.mean(d**2))), float(np.sqrt(np.mean(d_rest**2)))


def run_identify(
    robot: Robot, legs_mm: np.ndarray, meas: np.ndarray, estimator: str, model: str = "42", method: str = "iterated"
) -> tuple[IdentificationResult | None, float]:
    """Identify and time it; None when the identification fails (counted and reported, never hidden)."""
    t0 = time.perf_counter()
    try:
        result = identify(robot, legs_mm, meas, estimator=estimator, model=model, method=method)
    except (IdentificationError, KinematicsError):
        return None, time.perf_counter() - t0
    return result, time.perf_counter() - t0


def reduction_pct(before: float, after: float) -> float:
    return 100.0 * (1.0 - after / before)


# ---------------------------------------------------------------------------------------------- the grid


@dataclass
class GridResults:
    """Rows of the section 5.2 grid (one per seed, error set, pose set, noise level and estimator)."""

    rows: list[dict] = field(default_factory=list)
    d_efficiency: dict[str, list[float]] = field(default_factory=dict)
    weakest_sv: dict[str, list[float]] = field(default_factory=dict)
    true_rms: dict[str, float] = field(default_factory=dict)
    failures: int = 0


def run_grid(robot: Robot, plan: StudyPlan, progress: Progress) -> GridResults:
    """The identification simulations of section 5.2 over error sets, noise levels, pose sets and seeds."""
    out = GridResults()
    total = len(plan.seeds) * len(plan.error_sets) * len(plan.pose_sets) * len(plan.noises_mm) * len(ESTIMATORS)
    task = progress.add_task("§5.2 grid", total=total)
    errors = {name: load_errors(name, robot) for name in plan.error_sets}
    for name, e in errors.items():
        out.true_rms[name] = float(np.sqrt(np.mean(e.to_vector() ** 2)))
    for seed in plan.seeds:
        progress.update(task, description=f"§5.2 grid: pose sets (seed {seed})")
        designs = paper_pose_sets(robot, seed)
        for key in plan.pose_sets:
            out.d_efficiency.setdefault(key, []).append(float(designs[key].metrics.d_efficiency))
            rep = identifiability(robot, designs[key].poses, "42")
            out.weakest_sv.setdefault(key, []).append(float(rep.singular_values[-1]))
        eval_cmd = random_poses(robot, plan.n_eval, np.random.default_rng([seed, 100]))
        for ie, err_name in enumerate(plan.error_sets):
            truth_vec = errors[err_name].to_vector()
            rig = TruthRig(robot, errors[err_name], seed)
            progress.update(task, description=f"§5.2 grid: truth {ERROR_SET_LABELS[err_name]} (seed {seed})")
            ev = rig.run(eval_cmd)
            ev_before = predicted_poses(robot, None, ev.legs_mm, ev.cmd)
            before_true = AccuracySummary.of(ev_before, ev.poses)
            truths = {key: rig.run(designs[key].poses) for key in plan.pose_sets}
            for ip, key in enumerate(plan.pose_sets):
                for inoise, noise in enumerate(plan.noises_mm):
                    rng = np.random.default_rng([seed, ie, ip, inoise, 1])
                    meas = rig.measure(truths[key].poses, noise, "gaussian", rng)
                    ev_meas = rig.measure(ev.poses, noise, "gaussian", rng)
                    before_meas = AccuracySummary.of(ev_before, ev_meas)
                    for est in ESTIMATORS:
                        progress.update(
                            task,
                            description=f"§5.2 {ERROR_SET_LABELS[err_name]} set {key[3]} σ={noise:g} {EST_LABEL[est]}",
                        )
                        result, dt = run_identify(robot, truths[key].legs_mm, meas, est)
                        row = {
                            "seed": seed, "error_set": err_name, "pose_set": key, "noise_mm": noise, "estimator": est,
                            "time_s": dt, "ok": result is not None,
                            "before_pos_max": before_true.position_mm.max,
                            "before_ori_max": before_true.orientation_deg.max,
                            "before_meas_pos_max": before_meas.position_mm.max,
                            "before_meas_ori_max": before_meas.orientation_deg.max,
                        }
                        if result is None:
                            out.failures += 1
                        else:
                            pred = predicted_poses(robot, result, ev.legs_mm, ev.cmd)
                            after_true = AccuracySummary.of(pred, ev.poses)
                            after_meas = AccuracySummary.of(pred, ev_meas)
                            rms_all, rms_rest = ident_errors(robot, result.x, truth_vec)
                            row.update(
                                ident_rms=rms_all, ident_rms_rest=rms_rest,
                                ident_red=reduction_pct(out.true_rms[err_name], rms_all),
                                after_pos_max=after_true.position_mm.max,
                                after_ori_max=after_true.orientation_deg.max,
                                after_meas_pos_max=after_meas.position_mm.max,
                                after_meas_ori_max=after_meas.orientation_deg.max,
                                converged=result.converged,
                            )
                        out.rows.append(row)
                        progress.advance(task)
    return out


# ---------------------------------------------------------------------------------------------- Table 7 block

SCENARIOS: dict[str, tuple[str, str, str]] = {
    "gaussian": ("gaussian", "none", "Gaussian sphere noise (the Table 7 analogue)"),
    "uniform": ("uniform", "none", "bounded noise: uniform per sphere coordinate, same std"),
    "uniform_pose": ("uniform_pose", "none", "bounded noise: uniform per measured pose component"),
    "gain": ("gaussian", "gain", f"unmodelled transducer gain error {GAIN_ERROR:g} (Gaussian noise)"),
    "compliance": (
        "gaussian",
        "compliance",
        f"unmodelled leg compliance {LEG_COMPLIANCE_MM_PER_N:g} mm/N under gravity (Gaussian noise)",
    ),
}
"""Scenario key -> (noise kind, unmodelled effect, description)."""

MODEL_VARIANTS: tuple[tuple[str, str], ...] = (("42", "iterated"), ("42", "one_step"), ("60", "one_step"))


@dataclass
class T7Results:
    """Per-seed indicators of the Table 7 block; keys (scenario, model, method, estimator)."""

    measured: dict[tuple[str, str, str, str], list[AccuracySummary]] = field(default_factory=dict)
    true: dict[tuple[str, str, str, str], list[AccuracySummary]] = field(default_factory=dict)
    fit_max: dict[tuple[str, str, str, str], list[float]] = field(default_factory=dict)
    times: dict[tuple[str, str, str, str], list[float]] = field(default_factory=dict)
    per_pose: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    failures: int = 0
    rank60: int = 0


def run_table7(robot: Robot, plan: StudyPlan, progress: Progress) -> T7Results:
    """Table 2 errors, pose set 3, 24 verification poses, σ = 0.005 mm, many seeds; plus the extra scenarios."""
    out = T7Results()
    n_fits = len(SCENARIOS) * len(ESTIMATORS) + (len(MODEL_VARIANTS) - 1) * len(ESTIMATORS)
    task = progress.add_task("Table 7 block", total=len(plan.t7_seeds) * n_fits)
    progress.update(task, description="Table 7 block: pose set 3")
    set3 = factorial_exchange(robot, 32, np.random.default_rng(0)).poses
    out.rank60 = identifiability(robot, set3, "60").rank
    errors = load_errors("table2", robot)
    for seed in plan.t7_seeds:
        rig = TruthRig(robot, errors, seed)
        progress.update(task, description=f"Table 7 block: truth (seed {seed})")
        tm = rig.run(set3)
        tv = rig.run(verification_poses(robot, plan.n_verify, seed))
        for isc, (scen, (kind, effect, _)) in enumerate(SCENARIOS.items()):
            rng = np.random.default_rng([seed, isc, 7])
            meas_m = rig.measure(tm.poses, plan.t7_noise_mm, kind, rng)
            meas_v = rig.measure(tv.poses, plan.t7_noise_mm, kind, rng)
            legs_m, legs_v = perturb_legs(robot, tm, effect), perturb_legs(robot, tv, effect)
            variants = MODEL_VARIANTS if scen == "gaussian" else MODEL_VARIANTS[:1]
            before = predicted_poses(robot, None, legs_v, tv.cmd)
            out.measured.setdefault((scen, "-", "-", "before"), []).append(AccuracySummary.of(before, meas_v))
            out.true.setdefault((scen, "-", "-", "before"), []).append(AccuracySummary.of(before, tv.poses))
            if scen == "gaussian" and seed == plan.t7_seeds[0]:
                out.per_pose["before"] = pose_errors(before, meas_v)
            for model, method in variants:
                for est in ESTIMATORS:
                    progress.update(task, description=f"Table 7 block: {scen} {model}/{method} {EST_LABEL[est]}")
                    result, dt = run_identify(robot, legs_m, meas_m, est, model, method)
                    key = (scen, model, method, est)
                    progress.advance(task)
                    if result is None:
                        out.failures += 1
                        continue
                    pred = predicted_poses(robot, result, legs_v, tv.cmd)
                    out.measured.setdefault(key, []).append(AccuracySummary.of(pred, meas_v))
                    out.true.setdefault(key, []).append(AccuracySummary.of(pred, tv.poses))
                    out.fit_max.setdefault(key, []).append(result.max_abs_residual)
                    out.times.setdefault(key, []).append(dt)
                    if scen == "gaussian" and model == "42" and method == "iterated" and seed == plan.t7_seeds[0]:
                        out.per_pose[est] = pose_errors(pred, meas_v)
    return out


# ---------------------------------------------------------------------------------------------- aggregation


def median(values: Iterable[float]) -> float:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return statistics.median(v) if v else float("nan")


def grid_median(rows: Sequence[dict], column: str, **where: object) -> float:
    return median(r.get(column, float("nan")) for r in rows if all(r[k] == v for k, v in where.items()))


def indicator(summary: AccuracySummary, quantity: str, name: str) -> float:
    return float(getattr(getattr(summary, quantity), name))


@dataclass(frozen=True)
class Comparison:
    """Paired (by seed) comparison of L∞ against LS on the maximum verification error of one quantity."""

    linf_wins: int
    n: int
    p_value: float
    ls_median: float
    linf_median: float
    rel_diff_median_pct: float

    def verdict(self) -> str:
        """Plain statement: who is better in how many seeds, and whether a sign test can tell."""
        if self.n == 0:
            return "no data"
        sig = f"sign test p = {self.p_value:.2g}" + ("" if self.p_value < 0.05 else ", not significant")
        if 2 * self.linf_wins > self.n:
            return f"L∞ is better in {self.linf_wins} of {self.n} seeds ({sig})"
        if 2 * self.linf_wins == self.n:
            return f"L∞ and LS split {self.linf_wins} to {self.n - self.linf_wins} ({sig})"
        return f"LS is better in {self.n - self.linf_wins} of {self.n} seeds ({sig})"

    def agrees(self) -> str:
        """Agreement with the paper's claim that L∞ gives the smaller maximum error."""
        if 2 * self.linf_wins > self.n and self.p_value < 0.05:
            return "**agrees** with the paper"
        if 2 * self.linf_wins > self.n:
            return "leans towards the paper, **not significantly**"
        if 2 * self.linf_wins < self.n and self.p_value < 0.05:
            return "**disagrees** with the paper"
        return "**does not confirm** the paper"


def compare(data: dict, scen: str, quantity: str) -> Comparison:
    """L∞ vs LS (42-parameter, iterated) on the maximum error of one quantity over the seeds of a scenario."""
    ls = [indicator(a, quantity, "max") for a in data.get((scen, "42", "iterated", "ls"), [])]
    li = [indicator(a, quantity, "max") for a in data.get((scen, "42", "iterated", "linf"), [])]
    if not ls or len(ls) != len(li):
        return Comparison(0, 0, float("nan"), float("nan"), float("nan"), float("nan"))
    k = sum(b < a for a, b in zip(ls, li, strict=True))
    ties = sum(b == a for a, b in zip(ls, li, strict=True))
    n = len(ls) - ties
    p_value = float(binomtest(k, n).pvalue) if n else 1.0
    rel = median(100.0 * (b / a - 1.0) for a, b in zip(ls, li, strict=True))
    return Comparison(k, n, p_value, median(ls), median(li), rel)

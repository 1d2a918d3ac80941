"""One case of the adaptive-plan study: the fixed plan and the adaptive plan walked on the same in-process rig.

The rig (`sim_devices.rig`) is driven as `hilcal run` drives it through the controller: an uncalibrated controller
commands each pose by the nominal inverse kinematics, the CMM measures the spheres and `hilcal` turns them into a
pose. After identification (least squares, the run's default), the "upload" is in-process: the controller holds the
compensated geometry (`hilcal.compensation.compensate`), commands the verify poses by its inverse kinematics, and the
rig moves to those lengths. Moves go straight to the target (no approach point): the effects studied here do not
depend on the motion history. The rig's clock advances by each row's estimated machine time.

Common random numbers: the verify-after measurements of one case use a second rig with the same truth and a seed
derived from the case's, so the fixed plan, the adaptive plans and the true geometry (the floor) meet the same CMM
noise there and differ only by the geometry the controller holds.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import structlog

from hilcal.compensation import ControllerGeometry, compensate
from hilcal.discovery.search import diagnose
from hilcal.identification import identify
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.planning.forecast import forecast, time_range
from hilcal.planning.machine_time import estimate_route
from hilcal.planning.sequential import AdaptiveProblem, AdaptiveSettings, adaptive_problem, decide, start, update
from hilcal.pose_measurement import pose_from_spheres
from hilcal.recording import Recording, recording_from_arrays
from hilcal.robot import Robot, default_robot
from procedures.plan import CalibrationPlan, make_plan, motion_rules, timing_for
from procedures.timing import TimingSection
from sim_devices.rig.config import (
    EffectsConfig,
    RigConfig,
    SensorScaleConfig,
    concealed_effect_config,
    load_errors,
    random_errors,
)
from sim_devices.rig.rig import SimulatedRig

TABLES = ("table2", "table3", "table4", "table5")
RANDOM_SIGMA_MM = 0.5
"""Random geometric errors: all 42 drawn from N(0, 0.5 mm²), the size of the paper's tables (RMS 0.13-1.1 mm)."""
AFTER_SEED_OFFSET = 7_000_000
REPLICATE_SEED_OFFSET = 3_000_000
"""The fixed plan measured again on the same truth with other CMM noise: how far two equally good calibrations'
verify-after maxima lie apart."""
FLOOR_SEED_OFFSET = 20_000
SCALE_FAULT_PPM = 3000.0
"""The concealed scale fault: 0.3 % of the stroke on one leg."""
TARGET_FACTOR = 2.0
PLAN_SEED = 0


@dataclass(frozen=True)
class Case:
    """One rig: its geometric errors (a paper table or random), its seed, and concealed physics or not."""

    errors: str
    seed: int
    physics: bool = False


_WORKER: dict[str, Any] = {}


def init_worker(target_mm: float | None = None, improvements: tuple[float, ...] = ()) -> None:
    """Per process: quiet logs, the robot, the fixed plan, the default timing and the adaptive problems: the default
    settings ("adaptive"), with a target ("target") and with other improvement fractions ("improvement_<f>")."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    robot = default_robot()
    station = TimingSection()
    plan = make_plan(robot, PLAN_SEED, timing=station.timing())
    timing = timing_for(plan, station.timing())
    rules = motion_rules(plan)
    budget = measure_time(robot, plan.poses("measure"), plan, timing)
    variants: dict[str, dict[str, Any]] = {"adaptive": {}}
    if target_mm is not None:
        variants["target"] = {"target_mm": target_mm}
    variants.update({f"improvement_{f:g}": {"min_improvement": f} for f in improvements})
    problems = {key: adaptive_problem(robot, plan.poses("verify"),
                                      AdaptiveSettings(max_measure_s=budget, seed=PLAN_SEED, **options), rules, timing,
                                      reference_measure=plan.poses("measure"))
                for key, options in variants.items()}
    _WORKER.update(robot=robot, plan=plan, timing=timing, budget=budget, problems=problems, target_mm=target_mm)


def measure_time(robot: Robot, rows: np.ndarray, plan: CalibrationPlan, timing: Any) -> float:
    """The measure phase's estimated machine time (s): home, then the rows, under the plan's rules and timing."""
    return estimate_route(Geometry.nominal(robot), robot.home, [("measure", rows)], motion_rules(plan),
                          timing).phase("measure").total_s


def rig_config(case: Case, robot: Robot) -> RigConfig:
    """The case's rig: table or random errors; with physics, a leg compliance and a 0.3 % scale fault on one leg."""
    if case.errors == "random":
        errors = random_errors(case.seed, RANDOM_SIGMA_MM)
    else:
        errors = load_errors(case.errors, robot)
    effects = EffectsConfig()
    if case.physics:
        gain = [0.0] * 6
        gain[case.seed % 6] = SCALE_FAULT_PPM
        effects = EffectsConfig(leg_compliance=concealed_effect_config("leg_compliance", 1.0, case.seed).leg_compliance,
                                sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=gain))
    return RigConfig(seed=case.seed, errors=errors, effects=effects)


class Walker:
    """The rig with an uncalibrated controller: command a pose, wait, measure it; keeps the rows."""

    def __init__(self, robot: Robot, config: RigConfig) -> None:
        self.robot = robot
        self.rig = SimulatedRig(robot, config)
        self.rows: dict[str, list] = {k: [] for k in ("cmd", "legs", "meas", "rms", "time", "temp", "phase")}

    def measure(self, pose: np.ndarray, wait_s: float, phase: str) -> tuple[np.ndarray, np.ndarray]:
        self.rig.advance_time(wait_s)
        self.rig.move_to_lengths(self.rig.controller_ik(pose))
        platform, base = self.rig.measure_spheres()
        fit = pose_from_spheres(platform, base, self.robot)
        legs = self.rig.reported_lengths()
        for key, value in (("cmd", pose), ("legs", legs), ("meas", fit.pose), ("rms", np.max(fit.rms_residual_mm)),
                           ("time", self.rig.time_s), ("temp", self.rig.temperature_c()), ("phase", phase)):
            self.rows[key].append(value)
        return legs, fit.pose

    def recording(self) -> Recording:
        r = self.rows
        return recording_from_arrays(np.arange(1, len(r["cmd"]) + 1), r["phase"], r["time"], np.array(r["cmd"]),
                                     np.array(r["legs"]), np.array(r["meas"]),
                                     {"sphere_fit_rms_mm": np.array(r["rms"]), "temp_c": np.array(r["temp"])},
                                     robot=self.robot, source="<adaptive study>")


def verify_after(robot: Robot, config: RigConfig, params: ControllerGeometry, verify: np.ndarray
                 ) -> tuple[AccuracySummary, AccuracySummary]:
    """Verify poses commanded by a controller holding `params`, on the case's verify-after rig (common noise): the
    same truth as `config`, its own seed. Measured against commanded, and (for the study only) true against
    commanded: the calibration's own error, without the CMM's noise."""
    rig = SimulatedRig(robot, config.model_copy(update={"seed": config.seed + AFTER_SEED_OFFSET}))
    measured, true = [], []
    for pose in verify:
        rig.move_to_lengths(inverse_kinematics(params.ik_geometry(), pose) - params.l0 + robot.l0)
        true.append(rig.true_pose())
        measured.append(pose_from_spheres(*rig.measure_spheres(), robot).pose)
    return AccuracySummary.of(np.array(measured), verify), AccuracySummary.of(np.array(true), verify)


def true_geometry(robot: Robot, config: RigConfig) -> ControllerGeometry:
    """What a perfect calibration uploads: the rig's true joints and stroke-zero lengths."""
    da, db, dl0 = config.errors.as_arrays()
    return ControllerGeometry(robot.a + da, robot.b + db, robot.l0 + dl0)


def calibrated(robot: Robot, legs: np.ndarray, meas: np.ndarray, verify: np.ndarray) -> ControllerGeometry:
    ident = identify(robot, legs, meas)
    before = ControllerGeometry(robot.a, robot.b, robot.l0)
    return compensate(robot, before, ident, offsets_only=False, sample_poses=verify).parameters


def _fixed(config: RigConfig, measure_config: RigConfig | None = None) -> tuple[dict[str, Any], Walker]:
    """The fixed plan measured on `measure_config` (default `config`; a replicate: the same truth, other noise) and
    verified on the verify-after rig of `config`."""
    robot, plan, timing = _WORKER["robot"], _WORKER["plan"], _WORKER["timing"]
    rows, verify = plan.poses("measure"), plan.poses("verify")
    walker = Walker(robot, measure_config or config)
    geom, rules = Geometry.nominal(robot), motion_rules(plan)
    previous = robot.home
    for pose in rows:
        step = estimate_route(geom, previous, [("measure", pose[None])], rules, timing).total_s
        walker.measure(pose, step, "measure")
        previous = pose
    legs, meas = np.array(walker.rows["legs"]), np.array(walker.rows["meas"])
    after, own = verify_after(robot, config, calibrated(robot, legs, meas, verify), verify)
    return {"rows": len(rows), "time_s": measure_time(robot, rows, plan, timing), "max_mm": after.position_mm.max,
            "rms_mm": after.position_mm.rms, "noiseless_rms_mm": own.position_mm.rms,
            "noiseless_max_mm": own.position_mm.max}, walker


def _adaptive(config: RigConfig, problem: AdaptiveProblem, with_forecast: bool = False
              ) -> tuple[dict[str, Any], Walker]:
    robot, plan, timing = _WORKER["robot"], _WORKER["plan"], _WORKER["timing"]
    verify = plan.poses("verify")
    walker = Walker(robot, config)
    state = start(problem)
    wall = 0.0
    forecasts: dict[str, float] = {}
    while True:
        t0 = time.perf_counter()
        decision = decide(problem, state)
        wall += time.perf_counter() - t0
        if decision.stop is not None:
            break
        choice = decision.next
        legs, meas = walker.measure(choice.pose, choice.time_s, "measure")
        t0 = time.perf_counter()
        state = update(problem, state, choice.pose, legs, meas)
        wall += time.perf_counter() - t0
        if with_forecast and state.n_rows == 1 + problem.settings.repeats:
            forecasts["after_repeats_s"] = state.elapsed_s + forecast(problem, state).remaining_s
    stop = decision.stop
    rows = state.commanded()
    time_s = measure_time(robot, rows, plan, timing)
    if abs(time_s - state.elapsed_s) > 1e-6:
        raise RuntimeError(f"the adaptive state's machine time {state.elapsed_s} s differs from the route estimate "
                           f"{time_s} s")
    legs, meas = np.array(walker.rows["legs"]), np.array(walker.rows["meas"])
    after, own = verify_after(robot, config, calibrated(robot, legs, meas, verify), verify)
    pred = stop.prediction
    scr = state.screening
    return {"rows": state.n_rows, "distinct": len(np.unique(rows, axis=0)), "time_s": time_s,
            "max_mm": after.position_mm.max, "rms_mm": after.position_mm.rms, "noiseless_rms_mm": own.position_mm.rms,
            "noiseless_max_mm": own.position_mm.max, "stop": stop.kind,
            "sentence": stop.sentence, "predicted_max_mm": None if pred is None else pred.max_mm,
            "predicted_upper_mm": None if pred is None else pred.upper_mm,
            "predicted_low_mm": None if pred is None else pred.low_mm,
            "predicted_parameter_rms_mm": None if pred is None else pred.parameter_rms_mm, "decision_wall_s": wall,
            "suspected": None if scr is None else scr.suspected, "screening": None if scr is None else scr.to_json(),
            "library_efficiency": state.library_efficiency, "poses": rows.tolist(), **forecasts}, walker


def run_case(case: Case) -> dict[str, Any]:
    """The fixed plan, the adaptive plan without a target (and with the target, if set), on the same rig seed."""
    robot = _WORKER["robot"]
    config = rig_config(case, robot)
    verify = _WORKER["plan"].poses("verify")
    t0 = time.perf_counter()
    fixed, fixed_walker = _fixed(config)
    adaptive, walker = _adaptive(config, _WORKER["problems"]["adaptive"], with_forecast=True)
    floor = verify_after(robot, config, true_geometry(robot, config), verify)[0].position_mm.max
    out: dict[str, Any] = {"errors": case.errors, "seed": case.seed, "physics": case.physics, "fixed": fixed,
                           "adaptive": adaptive, "floor_mm": floor}
    if not case.physics:
        replicate = config.model_copy(update={"seed": config.seed + REPLICATE_SEED_OFFSET})
        out["fixed_replicate"] = _fixed(config, replicate)[0]
        for key, problem in _WORKER["problems"].items():
            if key != "adaptive":
                out[key] = _adaptive(config, problem)[0]
    if case.physics:
        out["diagnosis"] = {}
        for key, w in (("fixed", fixed_walker), ("adaptive", walker)):
            for pose in verify:
                w.measure(pose, _WORKER["timing"].settle_s + _WORKER["timing"].cmm_s_per_pose, "verify")
            diag = diagnose(w.recording(), robot, alpha=0.02, n_boot=999, seed=case.seed)
            out["diagnosis"][key] = {"effects": list(diag.effects), "effect": diag.effect}
    out["seconds"] = time.perf_counter() - t0
    return out


def fixed_plan_rows() -> np.ndarray:
    """The fixed plan's measure rows (repeats included), in visiting order."""
    return _WORKER["plan"].poses("measure")


def pre_motion_range() -> dict[str, Any]:
    """The adaptive problem's time range before motion (no noise known yet)."""
    return time_range(_WORKER["problems"]["adaptive"]).to_json()


def floor_samples(n: int) -> np.ndarray:
    """Verify-after maxima (mm) with the true geometry on n seeded rigs (Table 2 errors): noise and resolution only."""
    robot, verify = _WORKER["robot"], _WORKER["plan"].poses("verify")
    out = []
    for k in range(n):
        config = rig_config(Case("table2", FLOOR_SEED_OFFSET + k), robot)
        out.append(verify_after(robot, config, true_geometry(robot, config), verify)[0].position_mm.max)
    return np.array(out)


def screening_power(rows: np.ndarray, compliance_mm_per_kn: float = 0.005, alpha: float = 0.02) -> dict[str, float]:
    """How well the screening's load test sees a realistic leg compliance on these measure rows (no rig: the linear
    model, the CMM's noise propagated through the sphere registration, every leg c mm/kN).

    Non-centrality of the added-variable F-test of the six load terms after the 42 geometric parameters, with each
    row whitened by its pose noise, and the test's power at the screening's level (Bonferroni over its three tests).
    """
    from scipy.stats import f as f_dist
    from scipy.stats import ncf

    from hilcal.discovery.noise import sphere_noise_covariance
    from hilcal.planning.candidates import library_columns, library_variables
    from hilcal.planning.design import pose_jacobians

    robot = _WORKER["robot"]
    J = pose_jacobians(robot, rows)
    sigma = np.sqrt(np.diagonal(sphere_noise_covariance(robot, rows, RigConfig.model_fields["cmm_noise_mm"].default,
                                                        robot.characteristic_length_mm), axis1=1, axis2=2))
    load = library_columns(J, *library_variables(robot, rows))[..., :6]
    A = (J / sigma[..., None]).reshape(-1, 42)
    X = (load / sigma[..., None]).reshape(-1, 6) @ np.full(6, compliance_mm_per_kn)
    residual = X - A @ np.linalg.lstsq(A, X, rcond=None)[0]
    lam = float(residual @ residual)
    dfd = 6 * len(rows) - 48
    critical = f_dist.isf(alpha / 3, 6, dfd)
    return {"noncentrality": lam, "power": float(ncf.sf(critical, 6, dfd, lam)), "rows": len(rows)}

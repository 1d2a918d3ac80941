"""One case of the diagnosis study: simulate a recording on the independent rig, diagnose it, score the answer.

The rig (`sim_devices`) conceals library physics (`concealed_effect_config`), physics that the library does
not list (`concealed_unlisted_config`, written in the simulator only), several at once, or nothing. Its true
poses are used for scoring only (the noise floor), never by the diagnosis. The set-up faults and aliases part
(`fault_alias_cases`, `build_fault_case`) conceals a scale fault of a few per cent on a light hexapod with a
hydraulic or an electric robot file, with or without a compliance that is a near-alias of it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import structlog

from hilcal.discovery.search import diagnose
from hilcal.kinematics import Geometry, gravity_wrench, leg_forces
from hilcal.metrics import AccuracySummary
from hilcal.planning.design import factorial_exchange, verification_poses
from hilcal.recording import Recording
from hilcal.robot import ActuatorSpec, Robot, default_robot, load_robot
from hilcal.workspace import random_poses
from procedures.cli.simulated_recording import RecordingOptions, simulate_with_truth
from sim_devices.rig.config import (
    EFFECT_NAMES,
    CmmPose,
    EffectsConfig,
    OilColumnComplianceConfig,
    RigConfig,
    SensorScaleConfig,
    concealed_effect_config,
    load_errors,
    random_errors,
)
from sim_devices.rig.electric_config import DriveComplianceConfig, MotorEncoderConfig, drive_compliance_for_signature
from sim_devices.rig.unlisted_concealed import concealed_unlisted_config

N_MEASURE = 32
N_VERIFY = 24
VERIFY_SEED = 0
NULL_GEOMETRY_SIGMA_MM = 0.5
ALPHA = 0.02
WITHIN_NOISE_TEXT = "within its measurement noise"
COMPANIONS = {"oil_column_compliance": {"leg_compliance"}}
"""The rig's oil column has a dead volume, a load term independent of the stroke: a structural compliance."""


@dataclass(frozen=True)
class Case:
    """One simulated recording: what the rig conceals and how the recording is written."""

    kind: str
    """single, pair, unlisted, combo (unlisted + library) or null."""
    effects: tuple[str, ...]
    scale: float
    seed: int
    noise_model: str = "gaussian"
    bare: bool = False
    """No cmd_* and no temp_c columns (as many real recordings)."""
    outliers: int = 0
    """Measure rows given a gross measurement error (a broken beam, a probing error)."""


def effects_config(case: Case) -> EffectsConfig:
    """All concealed effects of a case merged into one rig configuration."""
    merged: dict[str, Any] = {}
    for name in case.effects:
        if name in EFFECT_NAMES:
            cfg = concealed_effect_config(name, case.scale, case.seed)
        else:
            cfg = concealed_unlisted_config(name, case.scale, case.seed)
        merged.update({k: v for k, v in cfg.model_dump().items() if v.get("enabled")})
    return EffectsConfig.model_validate(merged)


_WORKER: dict[str, Any] = {}


def init_worker() -> None:
    """Per process: quiet logs, the robot, the plan and the Table 2 errors."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    robot = default_robot()
    _WORKER.update(robot=robot, measure=factorial_exchange(robot, N_MEASURE, np.random.default_rng(0)).poses,
                   verify=verification_poses(robot, N_VERIFY, VERIFY_SEED), table2=load_errors("table2", robot))


def strip(rec: Recording) -> Recording:
    """The recording without commanded poses and temperatures."""
    extra = {k: v for k, v in rec.extra.items() if k != "temp_c"}
    return dataclasses.replace(rec, cmd=np.full_like(rec.cmd, np.nan), extra=extra)


OUTLIER_SIZE_MM = (0.1, 0.5)
"""A gross measurement error: a position jump of this size (the floor is a few µm) in a random direction."""


def plant_outliers(rec: Recording, n: int, seed: int) -> tuple[Recording, list[int]]:
    """`n` measure rows with a gross position error; their seq numbers."""
    rng = np.random.default_rng([seed, 0x0D7])
    rows = np.sort(rng.choice(np.flatnonzero(rec.phase == "measure"), size=n, replace=False))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    meas = rec.meas.copy()
    meas[rows, :3] += direction * rng.uniform(*OUTLIER_SIZE_MM, size=(n, 1))
    return dataclasses.replace(rec, meas=meas), [int(rec.seq[r]) for r in rows]


def _in_range(diag: Any) -> bool:
    for g in diag.groups:
        if g.physical_range is None:
            continue
        values = np.array([diag.parameters[n] for n in g.names])
        if np.any(values < g.physical_range.low - 1e-9) or np.any(values > g.physical_range.high + 1e-9):
            return False
    return True


def run_case(case: Case, n_boot: int) -> dict[str, Any]:
    """Simulate, diagnose and score one recording."""
    if not _WORKER:
        init_worker()
    robot: Robot = _WORKER["robot"]
    errors = random_errors(case.seed, NULL_GEOMETRY_SIGMA_MM) if case.kind == "null" else _WORKER["table2"]
    config = RigConfig(seed=case.seed, errors=errors, effects=effects_config(case), cmm_noise_model=case.noise_model)
    rec, truth = simulate_with_truth(robot, config, _WORKER["measure"], _WORKER["verify"])
    if case.bare:
        rec = strip(rec)
    planted: list[int] = []
    if case.outliers:
        rec, planted = plant_outliers(rec, case.outliers, case.seed)
    t0 = time.perf_counter()
    diag = diagnose(rec, robot, alpha=ALPHA, n_boot=n_boot, seed=case.seed)
    elapsed = time.perf_counter() - t0
    verify = rec.phase == "verify"
    library = [e for e in diag.effects if e != "unexplained"]
    truth_library = {e for e in case.effects if e in EFFECT_NAMES}
    allowed = truth_library.union(*(COMPANIONS.get(e, set()) for e in truth_library))
    return {
        "kind": case.kind, "effects": list(case.effects), "scale": case.scale, "seed": case.seed,
        "noise_model": case.noise_model, "bare": case.bare,
        "effect": diag.effect, "named": list(diag.effects), "library_named": library,
        "false_library": [e for e in library if e not in allowed],
        "unexplained": "unexplained" in diag.effects,
        "before_mm": diag.before.position_mm.rms, "after_mm": diag.after.position_mm.rms,
        "floor_mm": AccuracySummary.of(rec.meas[verify], truth[verify]).position_mm.rms,
        "ratio_geometry": None if diag.noise_ratio is None else diag.noise_ratio.ratio_geometry,
        "ratio_final": None if diag.noise_ratio is None else diag.noise_ratio.ratio_final,
        "within_claim": WITHIN_NOISE_TEXT in diag.explanation,
        "in_range": _in_range(diag), "n_steps": len(diag.steps),
        "shapes": [{"group": s.group.key, "leg": s.leg + 1, "pinned": s.pinned} for s in diag.shapes],
        "seconds": elapsed, "outliers_planted": planted,
        "outliers_excluded": sorted(int(e["seq"]) for e in diag.excluded),
    }


# ---------------------------------------------------------------- set-up faults and aliases

FAULT_ROBOT_FILE = Path(__file__).resolve().parents[2] / "examples" / "electric_hexapod" / "robot.toml"
"""A light electric hexapod (4 kg, 50 mm strokes); the hydraulic cases use the same machine declared hydraulic."""
FAULT_PCT = (2.0, 10.0)
"""Size of a scale fault, % of the reported stroke (random sign)."""
TYPICAL_SCALE_PPM = 60.0
"""The other legs: ± a ground screw's lead tolerance, or a transducer's calibrated gain error."""
ALIAS_SIGNATURE_MM = (0.03, 0.05)
"""The near-alias compliance: its sag changes by this over the stroke range at the leg's load at home. On the 4 kg
hexapod (about 7 N per leg) that takes 85-145 mm/(kN m), far softer than a healthy drive (a screw 0.07, a steel-cord
belt 4-11) or oil column (about 2): by design, as a healthy one would not show above the CMM noise at all."""
FAULT_DEAD_LENGTH_MM = 10.0
"""Free screw length at zero stroke (electric) or dead oil column (hydraulic)."""
FAULT_HOMING_MM = 0.003
"""Electric legs home at every power-on with this repeatability (1σ)."""
FAULT_SESSIONS = (54, 54)
"""Measure rows per session (two sessions), then one session of FAULT_N_VERIFY verify rows."""
FAULT_N_VERIFY = 60
FAULT_SECONDS_PER_POSE = 60.0
FAULT_SESSION_GAP_S = 20.0 * 3600.0
FAULT_GEOMETRY_SIGMA_MM = 0.03
FAULT_CMM_NOISE_MM = 0.0015
FAULT_LEG_RESOLUTION_MM = 0.0001
FAULT_CMM_POSE = CmmPose(x_mm=380.0, y_mm=-260.0, z_mm=-120.0, roll_deg=-0.2, pitch_deg=0.4, yaw_deg=-52.0)
HYDRAULIC_EFFECTS = frozenset({"oil_column_compliance"})
"""Library effects that cannot be physical on electric legs."""


@dataclass(frozen=True)
class FaultCase:
    """A scale fault on some legs of the light hexapod, declared hydraulic or electric, with or without an alias."""

    actuators: Literal["hydraulic", "electric"]
    n_fault_legs: int
    alias: bool
    seed: int
    """Same seed and actuators: same geometry, faulty legs, fault sizes and poses with and without the alias."""
    fault_pct: tuple[float, float] = FAULT_PCT
    """Range of the fault's size, % of the reported stroke (e.g. (4, 8) for one leg's mm/rev 4-8 % off)."""


@dataclass(frozen=True)
class FaultTruth:
    """What the rig conceals, in the diagnosis' units (legs 1-based).

    sensor_scale_ppm: per leg g with the convention of docs/diagnosis.md, geometric length = reported + dl0 -
    g · stroke, stroke = reported - l0. Electric (motor encoder, lead_ratio r = true / configured mm per
    revolution): true stroke = s_home + e + r (reported stroke - s_home), so g = 1 - r exactly (s_home and the
    homing offset e are constants for dl0). Hydraulic (a linear transducer with a mis-set gradient; the rig's
    SensorScaleConfig reports true stroke × (1 + g_rig)): g = g_rig / (1 + g_rig), i.e. g_rig = g / (1 - g).
    alias_um_per_kn_m: per leg, the near-alias compliance per metre of TRUE stroke (drive: c_per_length;
    hydraulic: the oil column's κ), with a constant part alias_dead_length_mm of free screw or dead oil on top
    (a load-only compliance); on the reported stroke the slope is κ (1 - g).
    """

    fault_legs: tuple[int, ...]
    fault_ppm: tuple[float, ...]
    sensor_scale_ppm: tuple[float, ...]
    alias_effect: str | None
    alias_um_per_kn_m: tuple[float, ...] | None
    alias_dead_length_mm: float
    homing_repeatability_mm: float
    not_physical: tuple[str, ...]
    """Library effects that must not be named with this robot file (hydraulic ones on electric legs)."""


@dataclass(frozen=True)
class FaultRecording:
    """One built case: the recording and the robot file given to the diagnosis, the truth and the true poses."""

    case: FaultCase
    robot: Robot
    recording: Recording
    truth: FaultTruth
    true_poses: np.ndarray
    """The rig's true pose per row (for the noise floor; never given to the diagnosis)."""
    rig: RigConfig


def fault_alias_cases(seeds: range | list[int] = range(5)) -> list[FaultCase]:
    """Both robot files × one or two faulty legs × without and with the near-alias compliance × the seeds."""
    return [
        FaultCase(actuators, n, alias, seed)
        for actuators in ("electric", "hydraulic")
        for n in (1, 2)
        for alias in (False, True)
        for seed in seeds
    ]


def fault_robot(actuators: Literal["hydraulic", "electric"]) -> Robot:
    """The light hexapod's robot file, as it is (electric, motor encoders) or declared hydraulic with linear sensors."""
    robot = load_robot(FAULT_ROBOT_FILE)
    if actuators == "electric":
        return robot
    spec = robot.spec.model_copy(
        update={"name": f"{robot.name}-hydraulic", "actuators": ActuatorSpec(kind="hydraulic", transducer="linear")}
    )
    return Robot(spec)


def home_loads_kn(robot: Robot) -> np.ndarray:
    """(6,) axial leg loads (kN, compression positive) at home with the robot file's geometry and mass."""
    home = robot.home
    return leg_forces(Geometry.nominal(robot), home, gravity_wrench(robot, home)) / 1000.0


def _fault_effects(case: FaultCase, robot: Robot) -> tuple[EffectsConfig, FaultTruth]:
    """The rig's effects and the truth: the draws depend on (seed, actuators, n_fault_legs), not on alias."""
    rng = np.random.default_rng([case.seed, 0xFA17, case.n_fault_legs, case.actuators == "electric"])
    g = rng.uniform(-TYPICAL_SCALE_PPM, TYPICAL_SCALE_PPM, 6) * 1e-6
    legs = np.sort(rng.choice(6, case.n_fault_legs, replace=False))
    g[legs] = rng.choice([-1.0, 1.0], case.n_fault_legs) * rng.uniform(*case.fault_pct, case.n_fault_legs) / 100.0
    stroke_range_mm = robot.leg_limits[1] - robot.leg_limits[0]
    signature = rng.uniform(*ALIAS_SIGNATURE_MM, 6)
    loads = home_loads_kn(robot)
    per_length = np.array([drive_compliance_for_signature(signature[i], loads[i], stroke_range_mm) for i in range(6)])
    fx: dict[str, Any] = {}
    if case.actuators == "electric":
        fx["motor_encoder"] = MotorEncoderConfig(
            enabled=True, lead_ratio=(1.0 - g).tolist(), homing_repeatability_mm=FAULT_HOMING_MM
        )
        if case.alias:
            fx["drive_compliance"] = DriveComplianceConfig(
                enabled=True, c_fixed_mm_per_kn=0.0, c_per_length_mm_per_kn_m=per_length.tolist(),
                free_length_at_zero_stroke_mm=FAULT_DEAD_LENGTH_MM,
            )
    else:
        fx["sensor_scale"] = SensorScaleConfig(enabled=True, gain_error_ppm=(g / (1.0 - g) * 1e6).tolist())
        if case.alias:
            fx["oil_column_compliance"] = OilColumnComplianceConfig(
                enabled=True, kappa_mm_per_kn_m=per_length.tolist(), dead_length_m=FAULT_DEAD_LENGTH_MM / 1000.0
            )
    alias_effect = None
    if case.alias:
        alias_effect = "drive_compliance" if case.actuators == "electric" else "oil_column_compliance"
    truth = FaultTruth(
        fault_legs=tuple(int(i) + 1 for i in legs),
        fault_ppm=tuple(float(g[i] * 1e6) for i in legs),
        sensor_scale_ppm=tuple(float(v * 1e6) for v in g),
        alias_effect=alias_effect,
        alias_um_per_kn_m=tuple(float(v * 1000.0) for v in per_length) if case.alias else None,
        alias_dead_length_mm=FAULT_DEAD_LENGTH_MM if case.alias else 0.0,
        homing_repeatability_mm=FAULT_HOMING_MM if case.actuators == "electric" else 0.0,
        not_physical=tuple(sorted(HYDRAULIC_EFFECTS)) if case.actuators == "electric" else (),
    )
    return EffectsConfig.model_validate(fx), truth


def build_fault_case(case: FaultCase) -> FaultRecording:
    """Simulate one case as a real machine's logger writes it: 2 × 54 measure rows in two sessions, 60 verify rows
    in a third (three power-ons), random poses without repeats, no commanded pose, no temperature."""
    if case.n_fault_legs not in (1, 2) or case.actuators not in ("hydraulic", "electric"):
        raise ValueError(f"n_fault_legs must be 1 or 2 and actuators hydraulic or electric, got {case!r}")
    if not 0.0 < case.fault_pct[0] <= case.fault_pct[1] < 50.0:
        raise ValueError(f"fault_pct must be a range inside (0, 50) %, got {case.fault_pct}")
    robot = fault_robot(case.actuators)
    effects, truth = _fault_effects(case, robot)
    rng = np.random.default_rng([case.seed, 0xFA18])
    measure = random_poses(robot, sum(FAULT_SESSIONS), rng)
    verify = random_poses(robot, FAULT_N_VERIFY, rng)
    geometry_seed = int(np.random.default_rng([case.seed, 0xFA19]).integers(2**31))
    config = RigConfig(
        seed=case.seed,
        errors=random_errors(geometry_seed, FAULT_GEOMETRY_SIGMA_MM),
        cmm_noise_mm=FAULT_CMM_NOISE_MM,
        leg_resolution_mm=FAULT_LEG_RESOLUTION_MM,
        cmm_pose=FAULT_CMM_POSE,
        effects=effects,
    )
    options = RecordingOptions(
        session_gap_s=FAULT_SESSION_GAP_S, unknown_start=True, excursion_end="random", include_cmd=False,
        include_temp=False, include_sphere_fit_rms=True,
        measure_session_starts=tuple(np.cumsum(FAULT_SESSIONS)[:-1].tolist()),
    )
    rec, truth_poses = simulate_with_truth(
        robot, config, measure, verify, seconds_per_pose=FAULT_SECONDS_PER_POSE, options=options
    )
    return FaultRecording(case=case, robot=robot, recording=rec, truth=truth, true_poses=truth_poses, rig=config)

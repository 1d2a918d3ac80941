"""One case of the diagnosis study: simulate a recording on the independent rig, diagnose it, score the answer.

The rig (`sim_devices`) conceals library physics (`concealed_effect_config`), physics that the library does
not list (`concealed_unlisted_config`, written in the simulator only), several at once, or nothing. Its true
poses are used for scoring only (the noise floor), never by the diagnosis.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import structlog

from hilcal.discovery.search import diagnose
from hilcal.metrics import AccuracySummary
from hilcal.planning.design import factorial_exchange, verification_poses
from hilcal.recording import Recording
from hilcal.robot import Robot, default_robot
from procedures.cli.simulated_recording import simulate_with_truth
from sim_devices.rig.config import (
    EFFECT_NAMES,
    EffectsConfig,
    RigConfig,
    concealed_effect_config,
    load_errors,
    random_errors,
)
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
        "seconds": elapsed,
    }

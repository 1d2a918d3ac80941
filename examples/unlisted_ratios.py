"""Measure how far each concealed out-of-library effect pushes a geometry-only calibration above the noise floor.

For each effect of sim_devices.rig.unlisted_concealed and each seed: simulate the study's recording (paper robot,
Table 2 errors, 5 µm CMM noise, 32 D-optimal measure poses + 24 verification poses, 45 s per pose), calibrate
the 42 geometric parameters by least squares on the measure rows (hilcal.identification.identify), predict the
verify rows by forward kinematics, and compare with the floor:

- before = verify RMS position error, predicted vs measured pose (what a user can compute);
- floor = verify RMS position error, measured vs the rig's true pose (measurement noise only).

``--hooke-fraction`` instead reports, per leg, the fraction of the variance of the Hooke-joint Δl (d = 1.5 mm)
over the run's true poses that a per-leg least-squares fit on [1, u, Rᵀu] leaves unexplained: rigid
dl0/db/da errors change a leg length by exactly such linear terms (to first order), so this is the part of
the effect that no geometric calibration can absorb. ``--overlap`` reports that fraction for every concealed
effect, and the fraction left when the direction of the last move (the library's joint_backlash) is added.

Run: ``python examples/unlisted_ratios.py [--seeds 8] [--scale 1]``, ``... --hooke-fraction [--axis-angle-deg A]``
or ``... --overlap --seeds 3``.
The functions are importable (``verify_ratio``, ``hooke_unabsorbed_fraction``) for studies.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import structlog
from rich.console import Console
from rich.progress import Progress

from hilcal.identification import identify, predict_poses
from hilcal.metrics import AccuracySummary
from hilcal.planning.design import factorial_exchange, verification_poses
from hilcal.robot import Robot, default_robot, rotation_matrix
from procedures.cli.simulated_recording import simulate_with_truth
from sim_devices.rig.config import EffectsConfig, GeometryErrors, RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from sim_devices.rig.unlisted_concealed import concealed_unlisted_config
from sim_devices.rig.unlisted_config import PARTLY_LISTED_EFFECT_NAMES, UNLISTED_EFFECT_NAMES, HookeJointOffsetConfig

N_MEASURE = 32
N_VERIFY = 24
HOOKE_CHECK_OFFSET_MM = 1.5
CONCEALED_NAMES = (*UNLISTED_EFFECT_NAMES, *PARTLY_LISTED_EFFECT_NAMES)


@dataclass(frozen=True)
class RatioResult:
    """Verify RMS position errors (mm) of a geometry-only calibration and of the measurement itself."""

    before_mm: float
    floor_mm: float
    truth_error_mm: float
    """Verify RMS position error of the prediction against the true pose."""

    @property
    def ratio(self) -> float:
        return self.before_mm / self.floor_mm


def study_poses(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The diagnosis study's 32 D-optimal measure poses and 24 verification poses."""
    measure = factorial_exchange(robot, N_MEASURE, np.random.default_rng(0)).poses
    return measure, verification_poses(robot, N_VERIFY, 0)


def verify_ratio(robot: Robot, config: RigConfig, measure: np.ndarray, verify: np.ndarray) -> RatioResult:
    """Simulate, calibrate the geometry on the measure rows, predict the verify rows (truth: for the floor only)."""
    rec, truth = simulate_with_truth(robot, config, measure, verify)
    m, v = rec.phase == "measure", rec.phase == "verify"
    fit = identify(robot, rec.legs_mm[m], rec.meas[m])
    predicted = predict_poses(fit, robot, rec.legs_mm[v], rec.meas[v])
    return RatioResult(
        before_mm=AccuracySummary.of(rec.meas[v], predicted).position_mm.rms,
        floor_mm=AccuracySummary.of(rec.meas[v], truth[v]).position_mm.rms,
        truth_error_mm=AccuracySummary.of(truth[v], predicted).position_mm.rms,
    )


def unabsorbed_fraction(
    robot: Robot,
    config: RigConfig,
    name: str,
    poses: np.ndarray,
    *,
    with_direction: bool = False,
    seconds_per_pose: float = 45.0,
) -> np.ndarray:
    """(6,) fraction of the variance of effect `name`'s Δl over the visited poses left by a per-leg LS fit.

    Regressors per leg: [1, u, Rᵀu] (what rigid dl0/db/da errors produce), plus the direction of the last move
    (what the library's joint_backlash produces) when with_direction. NaN for legs the effect leaves constant.
    """
    rig = SimulatedRig(robot, config)
    da, db, _ = config.errors.as_arrays()
    a, b = robot.a + da, robot.b + db
    dl, u, rtu, direction = [], [], [], []
    for pose in poses:
        rig.advance_time(seconds_per_pose)
        rig.move_to_lengths(rig.controller_ik(pose))
        true = rig.true_pose()
        R = rotation_matrix(np.radians(true[3:]))
        legs = a @ R.T + true[:3] - b
        unit = legs / np.linalg.norm(legs, axis=1, keepdims=True)
        dl.append(rig.length_corrections_mm()[name])
        u.append(unit)
        rtu.append(unit @ R)
        direction.append(rig.motion_direction())
    dl_arr, u_arr, rtu_arr, dir_arr = (np.array(x) for x in (dl, u, rtu, direction))
    out = np.full(6, np.nan)
    for i in range(6):
        y = dl_arr[:, i] - dl_arr[:, i].mean()
        if y @ y < 1e-18:
            continue
        columns = [np.ones(len(poses)), *u_arr[:, i].T, *rtu_arr[:, i].T]
        if with_direction:
            columns.append(dir_arr[:, i])
        X = np.column_stack(columns)
        resid = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
        out[i] = resid @ resid / (y @ y)
    return out


def hooke_unabsorbed_fraction(
    robot: Robot,
    errors: GeometryErrors,
    poses: np.ndarray,
    offset_mm: float = HOOKE_CHECK_OFFSET_MM,
    axis_angle_deg: float = 0.0,
) -> np.ndarray:
    """(6,) fraction of the variance of the Hooke-joint Δl over the poses left by a per-leg fit on [1, u, Rᵀu]."""
    hooke = HookeJointOffsetConfig(enabled=True, offset_mm=offset_mm, axis_angle_deg=axis_angle_deg)
    config = RigConfig(errors=errors, effects=EffectsConfig(hooke_joint_offset=hooke), cmm_noise_mm=0.0)
    return unabsorbed_fraction(robot, config, "hooke_joint_offset", poses)


def _ratios(seeds: int, scale: float, console: Console) -> None:
    robot = default_robot()
    errors = load_errors("table2", robot)
    measure, verify = study_poses(robot)
    rows: dict[str, list[RatioResult]] = {}
    with Progress(console=console, transient=True) as bar:
        task = bar.add_task("simulate + calibrate", total=len(CONCEALED_NAMES) * seeds + seeds)
        for name in ("none", *CONCEALED_NAMES):
            for seed in range(seeds):
                effects = concealed_unlisted_config(name, scale, seed)
                config = RigConfig(seed=seed, errors=errors, effects=effects)
                rows.setdefault(name, []).append(verify_ratio(robot, config, measure, verify))
                bar.advance(task)
    print(f"| effect (scale {scale:g}) | before/floor median | min | max | before (µm, median) | floor (µm, median) |")
    print("|---|---|---|---|---|---|")
    for name, results in rows.items():
        ratios = [r.ratio for r in results]
        print(
            f"| {name} | {statistics.median(ratios):.1f} | {min(ratios):.1f} | {max(ratios):.1f} | "
            f"{1000 * statistics.median(r.before_mm for r in results):.0f} | "
            f"{1000 * statistics.median(r.floor_mm for r in results):.1f} |"
        )


def _overlap(seeds: int) -> None:
    robot = default_robot()
    errors = load_errors("table2", robot)
    poses = np.vstack(study_poses(robot))
    print("| effect (scale 1) | seed | left after rigid, per leg | left after rigid + direction, per leg |")
    print("|---|---|---|---|")
    for name in CONCEALED_NAMES:
        for seed in range(seeds):
            config = RigConfig(seed=seed, errors=errors, effects=concealed_unlisted_config(name, 1.0, seed))
            rigid, both = (unabsorbed_fraction(robot, config, name, poses, with_direction=w) for w in (False, True))
            text = [" ".join("-" if np.isnan(x) else f"{x:.2f}" for x in f) for f in (rigid, both)]
            print(f"| {name} | {seed} | {text[0]} | {text[1]} |")


def _hooke(console: Console, axis_angle_deg: float) -> None:
    robot = default_robot()
    errors = load_errors("table2", robot)
    measure, verify = study_poses(robot)
    for label, poses in (
        ("32 D-optimal + 24 verification poses", np.vstack([measure, verify])),
        ("verification_poses(robot, 56, 0)", verification_poses(robot, 56, 0)),
    ):
        f = hooke_unabsorbed_fraction(robot, errors, poses, axis_angle_deg=axis_angle_deg)
        console.print(
            f"Hooke offset {HOOKE_CHECK_OFFSET_MM} mm, first axes at {axis_angle_deg:g}° from horizontal, {label}: "
            "unabsorbed variance fraction per leg "
            f"{np.array2string(f, precision=3)}, median {np.median(f):.3f}"
        )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8, help="seeds per effect (default 8)")
    parser.add_argument("--scale", type=float, default=1.0, help="magnitude scale (default 1)")
    parser.add_argument("--hooke-fraction", action="store_true", help="report the Hooke joint check instead")
    parser.add_argument("--axis-angle-deg", type=float, default=0.0, help="Hooke first axes from horizontal")
    parser.add_argument(
        "--overlap", action="store_true", help="report the variance left by rigid and rigid + backlash terms instead"
    )
    args = parser.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    console = Console(stderr=True)
    if args.hooke_fraction:
        _hooke(console, args.axis_angle_deg)
    elif args.overlap:
        _overlap(args.seeds)
    else:
        _ratios(args.seeds, args.scale, console)
    return 0


if __name__ == "__main__":
    sys.exit(main())

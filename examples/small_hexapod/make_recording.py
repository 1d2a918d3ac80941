"""Generate examples/small_hexapod/recording.csv: a simulated calibration recording of a small electric hexapod.

The data is made by this project's simulated rig (sim_devices) with a concealed truth that is printed by
``--print-truth`` and listed in the README. It imitates a third-party recording: poses in a random order
(motion directions vary), measure rows on one day and verify rows on the next (the machine was switched off,
re-homed and moved in between: a per-leg zero shift on two legs), each session starting after motion that is
not recorded (where the machine was before the first row, and how it got there, is unknown), three repeats of
one pose, no commanded pose (empty cmd_* columns), no temperature column, and the CMM's sphere-fit RMS per row.

Run ``python examples/small_hexapod/make_recording.py [--out PATH] [--print-truth]``; every draw is seeded, so
the output is the committed recording.csv.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import structlog

from hilcal.identification import identify, predict_poses
from hilcal.metrics import AccuracySummary
from hilcal.recording import Recording, write_recording
from hilcal.robot import Robot, load_robot
from hilcal.workspace import random_poses
from procedures.cli.simulated_recording import RecordingOptions, second_session_start_s, simulate_with_truth
from sim_devices.rig.config import (
    CmmPose,
    EffectsConfig,
    JointBacklashConfig,
    RigConfig,
    SensorScaleConfig,
    random_errors,
)
from sim_devices.rig.unlisted_config import ZeroShiftConfig

HERE = Path(__file__).resolve().parent
ROBOT_FILE = HERE / "robot.toml"
RECORDING_FILE = HERE / "recording.csv"

SEED = 7
N_MEASURE_RANDOM = 48
REPEATS = 3
"""Repeats of one pose (home) among the measure rows: a direct look at the repeatability."""
N_VERIFY = 24
SECONDS_PER_POSE = 75.0
"""Move, settle and probe six spheres on a CMM."""
SESSION_GAP_S = 20.5 * 3600.0
"""Next morning."""
GEOMETRY_SIGMA_MM = 0.03
CMM_NOISE_MM = 0.001
LEG_RESOLUTION_MM = 0.0001
GAIN_ERROR_PPM = (30.0, 100.0)
"""Lead (scale) error of the ball screws on three legs, random sign."""
BACKLASH_MM = (0.002, 0.006)
ZERO_SHIFT_MM = (0.003, 0.008)
"""Re-homing shift on two legs, random sign."""
CMM_POSE = CmmPose(x_mm=-420.0, y_mm=310.0, z_mm=-95.0, roll_deg=0.3, pitch_deg=-0.2, yaw_deg=37.0)
"""Where the CMM's frame sits in the hexapod's base frame (the hexapod stands on the CMM table)."""
EXPORT_DECIMALS = {"time_s": 1, "legs_mm": 4, "position_mm": 5, "angle_deg": 6, "sphere_fit_rms_mm": 6}
"""Digits as a controller and a CMM would export them: 0.1 µm legs, 10 nm positions, 1e-6° angles."""


def poses(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Measure poses (random, with REPEATS copies of home shuffled in) and random verify poses, in visit order."""
    rng = np.random.default_rng([SEED, 1])
    measure = np.vstack([random_poses(robot, N_MEASURE_RANDOM, rng), np.tile(robot.home, (REPEATS, 1))])
    measure = measure[rng.permutation(len(measure))]
    return measure, random_poses(robot, N_VERIFY, rng)


def rig_config(robot: Robot, n_measure: int) -> RigConfig:
    """The concealed truth: geometric errors, ball-screw physics, the re-homing shift and the CMM."""
    rng = np.random.default_rng([SEED, 2])
    gain = np.zeros(6)
    gain_legs = rng.choice(6, 3, replace=False)
    gain[gain_legs] = rng.choice([-1.0, 1.0], 3) * rng.uniform(*GAIN_ERROR_PPM, 3)
    shift = np.zeros(6)
    shift_legs = rng.choice(6, 2, replace=False)
    shift[shift_legs] = rng.choice([-1.0, 1.0], 2) * rng.uniform(*ZERO_SHIFT_MM, 2)
    options = recording_options()
    backlash = np.round(rng.uniform(*BACKLASH_MM, 6), 4)
    effects = EffectsConfig(
        sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=np.round(gain, 1).tolist()),
        joint_backlash=JointBacklashConfig(enabled=True, backlash_mm=backlash.tolist()),
        zero_shift=ZeroShiftConfig(
            enabled=True,
            shift_mm=np.round(shift, 4).tolist(),
            from_time_s=second_session_start_s(n_measure, seconds_per_pose=SECONDS_PER_POSE, options=options),
        ),
    )
    return RigConfig(
        seed=SEED,
        errors=random_errors(SEED, GEOMETRY_SIGMA_MM),
        cmm_noise_mm=CMM_NOISE_MM,
        leg_resolution_mm=LEG_RESOLUTION_MM,
        cmm_pose=CMM_POSE,
        effects=effects,
    )


def recording_options() -> RecordingOptions:
    """Two sessions, each after unrecorded motion to an unknown pose; no cmd_*, no temp_c; with sphere_fit_rms_mm."""
    return RecordingOptions(
        session_gap_s=SESSION_GAP_S,
        unknown_start=True,
        excursion_end="random",
        include_cmd=False,
        include_temp=False,
        include_sphere_fit_rms=True,
    )


def exported(rec: Recording) -> Recording:
    """The recording rounded to EXPORT_DECIMALS (far below the noise: at most 0.05 µm on a leg)."""
    meas = rec.meas.copy()
    meas[:, :3] = np.round(meas[:, :3], EXPORT_DECIMALS["position_mm"])
    meas[:, 3:] = np.round(meas[:, 3:], EXPORT_DECIMALS["angle_deg"])
    extra = {k: np.round(v, EXPORT_DECIMALS[k]) for k, v in rec.extra.items()}
    return replace(
        rec,
        time_s=np.round(rec.time_s, EXPORT_DECIMALS["time_s"]),
        legs_mm=np.round(rec.legs_mm, EXPORT_DECIMALS["legs_mm"]),
        meas=meas,
        extra=extra,
    )


def simulate() -> tuple[Robot, RigConfig, Recording, np.ndarray]:
    """The robot, the concealed rig configuration, the exported recording and the rig's true poses."""
    robot = load_robot(ROBOT_FILE)
    measure, verify = poses(robot)
    config = rig_config(robot, len(measure))
    rec, truth = simulate_with_truth(
        robot, config, measure, verify, seconds_per_pose=SECONDS_PER_POSE, options=recording_options()
    )
    return robot, config, exported(rec), truth


def make(out: Path = RECORDING_FILE) -> Recording:
    """Simulate and write the recording."""
    rec = simulate()[2]
    write_recording(out, rec)
    return rec


def truth_markdown(simulated: tuple[Robot, RigConfig, Recording, np.ndarray] | None = None) -> str:
    """The concealed truth and the accuracy yardsticks as markdown (units in every name), as quoted in the README.

    simulated: the result of simulate(), to avoid simulating again.
    """
    robot, config, rec, truth = simulated or simulate()
    da, db, dl0 = config.errors.as_arrays()
    fx = config.effects
    gain, backlash, shift = (
        np.ravel(np.broadcast_to(v, 6))
        for v in (fx.sensor_scale.gain_error_ppm, fx.joint_backlash.backlash_mm, fx.zero_shift.shift_mm)
    )

    def um(values: np.ndarray) -> str:
        return ", ".join(f"{1000 * v:+.1f}" for v in np.ravel(values))

    lines = [
        "| leg | da_um (x, y, z) | db_um (x, y, z) | dl0_um | gain_error_ppm | backlash_um | zero_shift_um |",
        "|---|---|---|---|---|---|---|",
    ]
    for i in range(6):
        lines.append(
            f"| {i + 1} | {um(da[i])} | {um(db[i])} | {um(dl0[i])} | {gain[i]:+.1f} | {1000 * backlash[i]:.1f} "
            f"| {um(shift[i])} |"
        )
    m, v = rec.phase == "measure", rec.phase == "verify"
    fit = identify(robot, rec.legs_mm[m], rec.meas[m])
    before = AccuracySummary.of(rec.meas[v], predict_poses(fit, robot, rec.legs_mm[v], rec.meas[v])).position_mm.rms
    floor = AccuracySummary.of(rec.meas[v], truth[v]).position_mm.rms
    lines += [
        "",
        f"- The zero shift applies from rig time {fx.zero_shift.from_time_s:.0f} s (the second session's power-on), "
        "i.e. to every verify row.",
        f"- CMM noise: Gaussian, {1000 * config.cmm_noise_mm:.1f} µm per sphere-centre coordinate; leg readings in "
        f"{1000 * config.leg_resolution_mm:.1f} µm steps.",
        f"- Verify RMS position error, measured vs true pose (the noise floor): {1000 * floor:.2f} µm; "
        f"geometry-only least-squares calibration on the measure rows, predicted vs measured: {1000 * before:.2f} µm "
        f"({before / floor:.1f}x the floor).",
        f"- Seed: SEED = {SEED} in make_recording.py (rig, geometric errors, poses, effect draws).",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RECORDING_FILE, help="CSV to write (default: the committed one)")
    parser.add_argument("--print-truth", action="store_true", help="print the concealed truth instead")
    args = parser.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    if args.print_truth:
        print(truth_markdown())
        return 0
    rec = make(args.out)
    print(f"wrote {args.out}: {rec.n} rows ({int(np.sum(rec.phase == 'measure'))} measure)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Generate examples/electric_hexapod/recording.csv: a simulated small electric hexapod with a set-up fault.

The data is made by this project's simulated rig (sim_devices) with a concealed truth that ``--print-truth`` prints
and the README lists. The legs are motor-encoder legs: one leg's configured mm per revolution is wrong by 1/16 (a
15-tooth motor pulley fitted where the controller assumes 16), every homing moves each leg's zero by the home
switch's repeatability, and the drive is soft enough that its compliance, load × stroke on a light platform, is a
near-alias of a scale error. It imitates a real machine's logger: 108 measure poses from two sessions and 60 verify
poses from a third (three power-ons and homings, on three days), poses in a random order without repeats, no
commanded pose (empty cmd_*), no temperature column, and the CMM's sphere-fit RMS per row.

Run ``python examples/electric_hexapod/make_recording.py [--out PATH] [--print-truth]``; every draw is seeded, so
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
from hilcal.kinematics import Geometry, leg_vectors, split_pose
from hilcal.metrics import AccuracySummary
from hilcal.recording import Recording, write_recording
from hilcal.robot import Robot, load_robot
from hilcal.workspace import random_poses
from procedures.cli.simulated_recording import RecordingOptions, simulate_with_truth
from sim_devices.rig.config import CmmPose, EffectsConfig, RigConfig, random_errors
from sim_devices.rig.electric_config import DriveComplianceConfig, MotorEncoderConfig
from sim_devices.rig.electric_physics import homing_offsets_mm
from sim_devices.rig.rig import SimulatedRig

HERE = Path(__file__).resolve().parent
ROBOT_FILE = HERE / "robot.toml"
RECORDING_FILE = HERE / "recording.csv"

SEED = 18
N_MEASURE_PER_SESSION = 54
MEASURE_SESSIONS = 2
N_VERIFY = 60
SECONDS_PER_POSE = 60.0
"""Move, settle and probe six spheres on a CMM."""
SESSION_GAP_S = 20.0 * 3600.0
"""Each session on the next day."""
GEOMETRY_SIGMA_MM = 0.03
CMM_NOISE_MM = 0.0015
"""A bridge CMM probing 10 mm spheres: 1-2 µm per sphere-centre coordinate."""
LEG_RESOLUTION_MM = 0.0001
"""A 2 mm lead over 16384 encoder counts per screw revolution: 0.12 µm; the controller exports 0.1 µm."""
FAULT_LEAD_RATIO = 15.0 / 16.0
"""True / configured mm per revolution on the faulty leg: a 15-tooth motor pulley configured as 16 teeth."""
SCREW_LEAD_PPM = 60.0
"""Lead tolerance of the other legs' ground screws, ± (ISO 3408 class 5: 23 µm over 315 mm, about 70 ppm)."""
SCREW_LEAD_MM = 2.0
PITCH_ERROR_MM = (0.001, 0.002)
"""Periodic lead error within one revolution (a ground screw: a few µm peak to peak)."""
DRIVE_C_PER_LENGTH_MM_PER_KN_M = (100.0, 150.0)
"""Drives far softer than healthy ones (a Ø12 steel screw is 0.067, a 10 mm steel-cord belt 4-11): big enough to
show on a light platform, and then a near-alias of a scale error."""
DRIVE_FREE_LENGTH_MM = 10.0
"""Screw between the fixed bearing and the nut with the leg retracted (a compact leg)."""
HOMING_REPEATABILITY_MM = 0.003
CMM_POSE = CmmPose(x_mm=380.0, y_mm=-260.0, z_mm=-120.0, roll_deg=-0.2, pitch_deg=0.4, yaw_deg=-52.0)
"""Where the CMM's frame sits in the hexapod's base frame (the hexapod stands on the CMM table)."""
EXPORT_DECIMALS = {"time_s": 1, "legs_mm": 4, "position_mm": 5, "angle_deg": 6, "sphere_fit_rms_mm": 6}
"""Digits as a controller and a CMM would export them: 0.1 µm legs, 10 nm positions, 1e-6° angles."""


def poses(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Measure poses (both sessions, in visit order) and verify poses: random over the workspace, no repeats."""
    rng = np.random.default_rng([SEED, 1])
    return random_poses(robot, MEASURE_SESSIONS * N_MEASURE_PER_SESSION, rng), random_poses(robot, N_VERIFY, rng)


def fault_leg() -> int:
    """The leg (0-based) with the wrong mm per revolution."""
    return int(np.random.default_rng([SEED, 2]).integers(6))


def rig_config() -> RigConfig:
    """The concealed truth: geometric errors, motor encoders with one mis-set leg, soft drives, the CMM."""
    rng = np.random.default_rng([SEED, 3])
    ratio = 1.0 + np.round(rng.uniform(-SCREW_LEAD_PPM, SCREW_LEAD_PPM, 6), 1) * 1e-6
    ratio[fault_leg()] = FAULT_LEAD_RATIO
    encoder = MotorEncoderConfig(
        enabled=True,
        lead_ratio=ratio.tolist(),
        lead_mm=SCREW_LEAD_MM,
        homing_repeatability_mm=HOMING_REPEATABILITY_MM,
        pitch_error_mm=np.round(rng.uniform(*PITCH_ERROR_MM, 6), 4).tolist(),
        pitch_phase_deg=np.round(rng.uniform(0.0, 360.0, 6), 1).tolist(),
    )
    drive = DriveComplianceConfig(
        enabled=True,
        c_per_length_mm_per_kn_m=np.round(rng.uniform(*DRIVE_C_PER_LENGTH_MM_PER_KN_M, 6), 1).tolist(),
        free_length_at_zero_stroke_mm=DRIVE_FREE_LENGTH_MM,
    )
    return RigConfig(
        seed=SEED,
        errors=random_errors(SEED, GEOMETRY_SIGMA_MM),
        cmm_noise_mm=CMM_NOISE_MM,
        leg_resolution_mm=LEG_RESOLUTION_MM,
        cmm_pose=CMM_POSE,
        effects=EffectsConfig(motor_encoder=encoder, drive_compliance=drive),
    )


def recording_options() -> RecordingOptions:
    """Three sessions (two of measure rows, one of verify rows), each after unrecorded motion; no cmd_*, no temp_c."""
    return RecordingOptions(
        session_gap_s=SESSION_GAP_S,
        unknown_start=True,
        excursion_end="random",
        include_cmd=False,
        include_temp=False,
        include_sphere_fit_rms=True,
        measure_session_starts=tuple(N_MEASURE_PER_SESSION * k for k in range(1, MEASURE_SESSIONS)),
    )


def session_of_rows() -> np.ndarray:
    """Session number (0-based: the rig's homing count) of every row."""
    measure = np.repeat(np.arange(MEASURE_SESSIONS), N_MEASURE_PER_SESSION)
    return np.concatenate([measure, np.full(N_VERIFY, MEASURE_SESSIONS)])


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
    config = rig_config()
    rec, truth = simulate_with_truth(
        robot, config, measure, verify, seconds_per_pose=SECONDS_PER_POSE, options=recording_options()
    )
    return robot, config, exported(rec), truth


def make(out: Path = RECORDING_FILE) -> Recording:
    """Simulate and write the recording."""
    rec = simulate()[2]
    write_recording(out, rec)
    return rec


def drive_signature(robot: Robot, config: RigConfig, rec: Recording) -> dict[str, np.ndarray]:
    """Per leg over the recorded rows, the drive compliance replayed on the rig session by session: its spread (mm),
    the mean axial load (kN), and how much it looks like a scale error once rigid geometry has absorbed its share.

    The rigid errors of leg i change its length, to first order, by dl0 + u·(-db) + (Rᵀu)·da (u the leg direction,
    R the platform rotation at the measured pose): both the drive's Δl and the stroke are projected off the span of
    [1, u, Rᵀu]; alias_cos is the cosine between what is left of them, apparent_scale_ppm the g (correction
    -g · stroke) that the drive alone would be taken for.
    """
    rig = SimulatedRig(robot, config)
    sessions = session_of_rows()
    drive, loads = np.empty((rec.n, 6)), np.empty((rec.n, 6))
    for k, lengths in enumerate(rec.legs_mm):
        while rig.session < sessions[k]:
            rig.start_session()
        rig.move_to_lengths(lengths)
        drive[k] = rig.length_corrections_mm()["drive_compliance"]
        loads[k] = rig.leg_forces_kn()
    rotation, translation = split_pose(rec.meas)
    _, _, u = leg_vectors(Geometry.nominal(robot), rotation, translation)
    stroke = rec.legs_mm - robot.l0
    cos, scale = np.empty(6), np.empty(6)
    for i in range(6):
        rigid = np.column_stack([np.ones(rec.n), u[:, i], np.einsum("nji,nj->ni", rotation, u[:, i])])
        q, _ = np.linalg.qr(rigid)
        s_left, d_left = (v - q @ (q.T @ v) for v in (stroke[:, i], drive[:, i]))
        cos[i] = s_left @ d_left / (np.linalg.norm(s_left) * np.linalg.norm(d_left))
        scale[i] = -(s_left @ d_left) / (s_left @ s_left) * 1e6
    return {"spread_mm": np.ptp(drive, axis=0), "load_kn": loads.mean(axis=0), "alias_cos": cos,
            "apparent_scale_ppm": scale}


def truth_markdown(
    simulated: tuple[Robot, RigConfig, Recording, np.ndarray] | None = None,
    signature: dict[str, np.ndarray] | None = None,
) -> str:
    """The concealed truth and the accuracy yardsticks as markdown (units in every name), as quoted in the README.

    simulated: the result of simulate(), signature: drive_signature of it, to avoid computing them again.
    """
    robot, config, rec, truth = simulated or simulate()
    da, db, dl0 = config.errors.as_arrays()
    enc, drive = config.effects.motor_encoder, config.effects.drive_compliance
    ratio, pitch = np.asarray(enc.lead_ratio), np.asarray(enc.pitch_error_mm)
    c_length = np.asarray(drive.c_per_length_mm_per_kn_m)
    homing = np.array([homing_offsets_mm(config.seed, s, enc.homing_repeatability_mm) for s in range(3)])
    sig = signature if signature is not None else drive_signature(robot, config, rec)

    def um(values: np.ndarray) -> str:
        return ", ".join(f"{1000 * v:+.1f}" for v in np.ravel(values))

    lines = [
        "| leg | da_um (x, y, z) | db_um (x, y, z) | dl0_um | lead_ratio (true/configured) | sensor_scale_ppm "
        "| pitch_error_um | drive_c_per_length_mm_per_kn_m | mean_load_n | drive_spread_um | drive_alias_cos "
        "| drive_apparent_scale_ppm | homing_um (session 1, 2, 3) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i in range(6):
        lines.append(
            f"| {i + 1} | {um(da[i])} | {um(db[i])} | {um(dl0[i])} | {ratio[i]:.7f} | {(1 - ratio[i]) * 1e6:+.1f} "
            f"| {1000 * pitch[i]:.1f} | {c_length[i]:.1f} | {1000 * sig['load_kn'][i]:.2f} "
            f"| {1000 * sig['spread_mm'][i]:.1f} | {sig['alias_cos'][i]:+.2f} | {sig['apparent_scale_ppm'][i]:+.0f} "
            f"| {um(homing[:, i])} |"
        )
    m, v = rec.phase == "measure", rec.phase == "verify"
    fit = identify(robot, rec.legs_mm[m], rec.meas[m])
    before = AccuracySummary.of(rec.meas[v], predict_poses(fit, robot, rec.legs_mm[v], rec.meas[v])).position_mm.rms
    floor = AccuracySummary.of(rec.meas[v], truth[v]).position_mm.rms
    lines += [
        "",
        f"- The faulty leg is leg {fault_leg() + 1}: lead_ratio {FAULT_LEAD_RATIO:.4f} (15/16), so it reads "
        f"{100 * (1 / FAULT_LEAD_RATIO - 1):.2f} % long and the diagnosis' `sensor_scale` (correction -g · stroke) "
        f"is g = 1 - lead_ratio = {(1 - FAULT_LEAD_RATIO) * 1e6:+.0f} ppm.",
        f"- Drive compliance: Δl = -c F, c = {drive.c_fixed_mm_per_kn:g} mm/kN + c_per_length × "
        f"({drive.free_length_at_zero_stroke_mm:g} mm + true stroke), fixed bearing at the base end, F the axial "
        "load from the platform's statics. drive_alias_cos: cosine between its Δl and the stroke after the rigid "
        "errors of the leg absorbed their share (first order, at the measured poses); drive_apparent_scale_ppm: the "
        "scale error g it alone would be taken for.",
        f"- Homing: the switch's trip point moves by N(0, ({1000 * enc.homing_repeatability_mm:.0f} µm)²) per leg at "
        f"each of the three power-ons (rows 1-{N_MEASURE_PER_SESSION}, {N_MEASURE_PER_SESSION + 1}-"
        f"{MEASURE_SESSIONS * N_MEASURE_PER_SESSION}, verify rows); pitch error period = the {enc.lead_mm:g} mm "
        "screw lead.",
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

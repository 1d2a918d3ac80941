"""Recordings shaped like real ones, for the diagnose benchmark and the tests: what makes a real diagnosis slow.

A real two-session recording of a medium electric hexapod (168 rows: 108 measure rows on one day, 60 verify rows the
next) took `hilcal diagnose` 9.8-12.7 s on 2 cores where the benchmark's own 168-row recording took 3.9 s: it had a
re-homing shift between the sessions, generic terms (a cyclic error over the stroke, a base-joint-angle shape),
near-aliases and an outlier, so the search runs twice and goes through more steps. These recordings have each of
those, simulated on the independent rig (`sim_devices`) for the medium electric hexapod of examples/import/logger
(150 mm strokes, 45 kg):

- 108 measure rows in one session and 60 verify rows in a second one 20 h later, each after unrecorded motion;
  motor-encoder legs re-homed at the second power-on (a zero shift of tens of µm on the verify rows);
- a mis-set mm per revolution on one leg (a scale fault) and drives soft enough to be a near-alias of it;
- out-of-library physics: a cyclic error over the stroke (a drum or pinion with runout, period 70-110 mm) and a
  base universal joint whose axes do not meet by 3-5 mm (a shape in the base joint angle; its constant part makes
  every leg read a few mm long, which the diagnosis reports as a leg-zero set-up fault);
- one measure row with a gross position error (a probing error), no commanded poses, no temperature column.

``python benchmarks/studies/diagnosis_real_shaped.py --out DIR`` writes ``real_shaped_<seed>.csv`` and the robot file
there.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilcal.recording import Recording, write_recording
from hilcal.robot import Robot, load_robot
from hilcal.workspace import random_poses
from procedures.cli.simulated_recording import RecordingOptions, simulate_with_truth
from sim_devices.rig.config import CmmPose, EffectsConfig, RigConfig, random_errors
from sim_devices.rig.electric_config import DriveComplianceConfig, MotorEncoderConfig, drive_compliance_for_signature
from sim_devices.rig.unlisted_config import CyclicStrokeErrorConfig, HookeJointOffsetConfig

ROOT = Path(__file__).resolve().parents[2]
ROBOT_FILE = ROOT / "examples" / "import" / "logger" / "robot.toml"
SEEDS = (0, 1, 2)
N_MEASURE = 108
N_VERIFY = 60
SECONDS_PER_POSE = 60.0
SESSION_GAP_S = 20.0 * 3600.0
GEOMETRY_SIGMA_MM = 0.05
CMM_NOISE_MM = 0.0015
LEG_RESOLUTION_MM = 0.0001
HOMING_REPEATABILITY_MM = 0.02
"""A home switch without an index pulse: the legs' zeros move by tens of µm at the second power-on."""
SCREW_LEAD_PPM = 60.0
FAULT_LEAD_RATIO = (0.985, 0.995)
"""One leg's true/configured mm per revolution: a gear ratio or lead set 0.5-1.5 % off."""
DRIVE_SIGNATURE_MM = (0.015, 0.03)
"""The soft drives' sag changes by this over the stroke range at the home load: a near-alias of a scale error."""
CYCLIC_AMPLITUDE_MM = (0.004, 0.008)
CYCLIC_PERIOD_MM = (70.0, 110.0)
HOOKE_OFFSET_MM = (3.0, 5.0)
OUTLIER_MM = 0.2
CMM_POSE = CmmPose(x_mm=900.0, y_mm=-600.0, z_mm=-300.0, roll_deg=0.1, pitch_deg=-0.3, yaw_deg=35.0)


@dataclass(frozen=True)
class RealShaped:
    """One recording, the robot file it was made for, the rig's truth and its true poses (for scoring only)."""

    seed: int
    robot: Robot
    recording: Recording
    rig: RigConfig
    true_poses: np.ndarray
    outlier_seq: int


def rig_config(robot: Robot, seed: int) -> RigConfig:
    """The concealed truth of one seed (see the module docstring)."""
    rng = np.random.default_rng([seed, 0x5EA1])
    ratio = 1.0 + rng.uniform(-SCREW_LEAD_PPM, SCREW_LEAD_PPM, 6) * 1e-6
    ratio[rng.integers(6)] = rng.uniform(*FAULT_LEAD_RATIO)
    stroke_range = robot.leg_limits[1] - robot.leg_limits[0]
    load_kn = robot.moving_mass_kg * robot.gravity_mps2 / 6000.0
    per_length = [drive_compliance_for_signature(s, load_kn, stroke_range) for s in rng.uniform(*DRIVE_SIGNATURE_MM, 6)]
    effects = EffectsConfig(
        motor_encoder=MotorEncoderConfig(enabled=True, lead_ratio=ratio.tolist(), lead_mm=5.0,
                                         homing_repeatability_mm=HOMING_REPEATABILITY_MM),
        drive_compliance=DriveComplianceConfig(enabled=True, c_per_length_mm_per_kn_m=per_length,
                                               free_length_at_zero_stroke_mm=20.0),
        cyclic_stroke_error=CyclicStrokeErrorConfig(
            enabled=True, amplitude_mm=rng.uniform(*CYCLIC_AMPLITUDE_MM, 6).tolist(),
            period_mm=float(rng.uniform(*CYCLIC_PERIOD_MM)), phase_deg=rng.uniform(0.0, 360.0, 6).tolist()),
        hooke_joint_offset=HookeJointOffsetConfig(enabled=True, offset_mm=float(rng.uniform(*HOOKE_OFFSET_MM)),
                                                  axis_angle_deg=rng.uniform(-10.0, 10.0, 6).tolist()),
    )
    return RigConfig(seed=seed, errors=random_errors(seed, GEOMETRY_SIGMA_MM), cmm_noise_mm=CMM_NOISE_MM,
                     leg_resolution_mm=LEG_RESOLUTION_MM, cmm_pose=CMM_POSE, effects=effects)


def real_shaped(seed: int) -> RealShaped:
    """Simulate one real-shaped recording (about 10 s)."""
    robot = load_robot(ROBOT_FILE)
    rng = np.random.default_rng([seed, 0x5EA2])
    measure, verify = random_poses(robot, N_MEASURE, rng), random_poses(robot, N_VERIFY, rng)
    config = rig_config(robot, seed)
    options = RecordingOptions(session_gap_s=SESSION_GAP_S, unknown_start=True, excursion_end="random",
                               include_cmd=False, include_temp=False, include_sphere_fit_rms=True)
    rec, truth = simulate_with_truth(robot, config, measure, verify, seconds_per_pose=SECONDS_PER_POSE,
                                     options=options)
    row = int(rng.integers(10, N_MEASURE - 10))
    direction = rng.normal(size=3)
    meas = rec.meas.copy()
    meas[row, :3] += OUTLIER_MM * direction / np.linalg.norm(direction)
    return RealShaped(seed, robot, dataclasses.replace(rec, meas=meas), config, truth, int(rec.seq[row]))


def write(out_dir: Path, seeds: Sequence[int] = SEEDS) -> list[Path]:
    """Write the recordings (and a copy of the robot file) into out_dir; their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "robot.toml").write_text(ROBOT_FILE.read_text())
    paths = []
    for seed in seeds:
        path = out_dir / f"real_shaped_{seed}.csv"
        write_recording(path, real_shaped(seed).recording)
        paths.append(path)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="*", default=list(SEEDS))
    args = parser.parse_args(argv)
    for path in write(args.out, args.seeds):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

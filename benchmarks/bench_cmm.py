"""Timing and accuracy benchmark of CMM measurement through the real driver and the simulated CMM on a pty.

Why: a calibration measures dozens of poses, each needing six spheres; the protocol and fitting overhead
per sphere (with the machine's own motion time scaled to zero) should be known and tracked, as should the
accuracy the probing strategy reaches at the simulator's noise. Prints a Markdown table.
Run ``python benchmarks/bench_cmm.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from collections.abc import Sequence

import numpy as np
import structlog
from _docs import write_doc
from scipy.spatial.transform import Rotation

from drivers.cmm.probing import REGISTERED_DEG, REGISTERED_MM
from drivers.cmm.serial import SerialCmm
from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.server import start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

NOISE_MM = 0.002
COMMANDED = np.array([150.0, -100.0, 3200.0, 3.0, -2.0, 6.0])


def _alignment(rig: SimulatedRig) -> np.ndarray:
    """T_cmm<-base from the simulated CMM placement, spoiled by ~1 mm as a station survey would be."""
    c = rig.config.cmm_pose.as_array()
    R = Rotation.from_euler("xyz", c[3:], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ c[:3] + np.array([0.8, -0.6, 0.5])
    return T


def run(repeats: int = 10, seed: int = 0) -> dict:
    """Median wall times (s) of one sphere and of a 6-sphere pose over a pty, and the errors against the truth."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    robot = default_robot()
    rig = SimulatedRig(robot, RigConfig(seed=seed, errors=load_errors("table2")))
    rig.move_to_lengths(rig.controller_ik(COMMANDED))
    truth = rig.true_pose()
    base_true = rig.to_cmm(robot.base_spheres)
    config = CmmServerConfig(seed=seed, time_scale=0.0, noise_sigma_mm=NOISE_MM)
    sphere_s, pose_s, sphere_err, pos_err, ori_err = [], [], [], [], []
    n_commands = 0
    with start_cmm_server(robot, rig, config) as server, SerialCmm(server.path) as cmm:
        cmm.start_session()
        cmm.home()
        for k in range(repeats):
            t0 = time.perf_counter()
            m = cmm.measure_sphere(base_true[k % 3], robot.sphere_radius_mm)
            sphere_s.append(time.perf_counter() - t0)
            sphere_err.append(float(np.linalg.norm(m.centre_mm - base_true[k % 3])))
        before = server.commands_handled
        for _ in range(repeats):
            t0 = time.perf_counter()
            # the exact alignment, known as a registered one is (every pose of a run after its first)
            pm = cmm.measure_pose(robot, _alignment(rig), COMMANDED,
                                  alignment_tolerance=(REGISTERED_MM, REGISTERED_DEG), registered=True)
            pose_s.append(time.perf_counter() - t0)
            pos_err.append(float(np.max(np.abs(pm.pose[:3] - truth[:3]))))
            ori_err.append(float(np.max(np.abs(pm.pose[3:] - truth[3:]))))
        n_commands = (server.commands_handled - before) // repeats
        cmm.end_session()
    return {
        "repeats": repeats,
        "noise_sigma_mm": NOISE_MM,
        "sphere_touches": len(m.probes),
        "sphere_time_s": statistics.median(sphere_s),
        "sphere_centre_error_max_mm": max(sphere_err),
        "pose_time_s": statistics.median(pose_s),
        "pose_commands": n_commands,
        "pose_position_error_max_mm": max(pos_err),
        "pose_orientation_error_max_deg": max(ori_err),
    }


def markdown(result: dict) -> str:
    """The result as a small Markdown table."""
    return "\n".join(
        [
            f"CMM over a pty, simulator noise {result['noise_sigma_mm']} mm per coordinate, instant machine "
            f"motion, median of {result['repeats']}:",
            "",
            "| measurement | wall time | commands | max error vs truth |",
            "| --- | ---: | ---: | ---: |",
            f"| one sphere ({result['sphere_touches']} touches + fit) | {1e3 * result['sphere_time_s']:.1f} ms | "
            f"{result['sphere_touches'] + 1} | centre {1e3 * result['sphere_centre_error_max_mm']:.2f} um |",
            f"| pose (6 spheres + registration) | {1e3 * result['pose_time_s']:.1f} ms | {result['pose_commands']} | "
            f"position {1e3 * result['pose_position_error_max_mm']:.2f} um, "
            f"orientation {result['pose_orientation_error_max_deg']:.1e} deg |",
        ]
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="5 repeats")
    args = parser.parse_args(argv)
    repeats = 5 if args.quick else args.repeats
    table = markdown(run(repeats))
    print(table)
    write_doc("benchmarks_cmm.md", "CMM measurement timings", "benchmarks/bench_cmm.py",
              f"{repeats} repeats; wall-clock, no assertions on speed.", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Timing and accuracy benchmark of CMM measurement through the I++ DME driver and the simulated CMM, over a pty and
over TCP on 127.0.0.1.

Why: a calibration measures dozens of poses, each needing six spheres; the protocol and fitting overhead per sphere
and per pose (with the machine's own motion time scaled to zero), the I++ DME lines a pose costs, and the accuracy the
probing strategy reaches with a ball stylus at the simulator's noise should be known and tracked. Prints a Markdown
table. Run ``python benchmarks/bench_cmm.py [--repeats N]``.
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

from drivers.cmm.ippdme import IppDmeCmm
from drivers.cmm.probing import REGISTERED_DEG, REGISTERED_MM
from drivers.cmm.transcript import TranscriptMemory
from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig, ToolConfig
from sim_devices.cmm.server import start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

NOISE_MM = 0.002
BALL_MM = 1.5
COMMANDED = np.array([150.0, -100.0, 3200.0, 3.0, -2.0, 6.0])


def _alignment(rig: SimulatedRig) -> np.ndarray:
    """T_cmm<-base from the simulated CMM placement."""
    c = rig.config.cmm_pose.as_array()
    R = Rotation.from_euler("xyz", c[3:], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ c[:3]
    return T


def run(repeats: int = 10, seed: int = 0, transport: str = "pty") -> dict:
    """Median wall times (s) of one sphere and of a 6-sphere pose, the lines a pose costs, the errors against the
    truth and the first pose's (station alignment spoiled by about 1 mm, so its base spheres are searched for)."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    robot = default_robot()
    rig = SimulatedRig(robot, RigConfig(seed=seed, errors=load_errors("table2")))
    rig.move_to_lengths(rig.controller_ik(COMMANDED))
    truth = rig.true_pose()
    base_true = rig.to_cmm(robot.base_spheres)
    config = CmmServerConfig(seed=seed, time_scale=0.0, noise_sigma_mm=NOISE_MM, tcp_port=0,
                             tools=(ToolConfig(name="Probe1", ball_radius_mm=BALL_MM),))
    sphere_s, pose_s, sphere_err, pos_err, ori_err, lines = [], [], [], [], [], []
    transcript = TranscriptMemory()
    with start_cmm_server(robot, rig, config) as server:
        url = server.path if transport == "pty" else server.socket_url
        with IppDmeCmm(url, transcript=transcript) as cmm:
            cmm.start_session()
            cmm.home()
            spoiled = _alignment(rig)
            spoiled[:3, 3] += np.array([0.8, -0.6, 0.5])
            t0 = time.perf_counter()
            first = cmm.measure_pose(robot, spoiled, COMMANDED)
            first_s = time.perf_counter() - t0
            for k in range(repeats):
                t0 = time.perf_counter()
                m = cmm.measure_sphere(base_true[k % 3], robot.sphere_radius_mm)
                sphere_s.append(time.perf_counter() - t0)
                sphere_err.append(float(np.linalg.norm(m.centre_mm - base_true[k % 3])))
            for _ in range(repeats):
                before = len(transcript.lines)
                t0 = time.perf_counter()
                # the exact alignment, known as a registered one is (every pose of a run after its first)
                pm = cmm.measure_pose(robot, _alignment(rig), COMMANDED,
                                      alignment_tolerance=(REGISTERED_MM, REGISTERED_DEG), registered=True)
                pose_s.append(time.perf_counter() - t0)
                lines.append(len(transcript.lines) - before)
                pos_err.append(float(np.max(np.abs(pm.pose[:3] - truth[:3]))))
                ori_err.append(float(np.max(np.abs(pm.pose[3:] - truth[3:]))))
            cmm.end_session()
        collisions = server.collisions
    return {
        "transport": transport,
        "repeats": repeats,
        "noise_sigma_mm": NOISE_MM,
        "ball_mm": BALL_MM,
        "sphere_touches": len(m.probes),
        "sphere_time_s": statistics.median(sphere_s),
        "sphere_centre_error_max_mm": max(sphere_err),
        "pose_time_s": statistics.median(pose_s),
        "pose_lines": int(statistics.median(lines)),
        "pose_position_error_max_mm": max(pos_err),
        "pose_orientation_error_max_deg": max(ori_err),
        "first_pose_time_s": first_s,
        "first_pose_touches": first.extra["touches"],
        "collisions": collisions,
    }


def markdown(results: list[dict]) -> str:
    """The results as a small Markdown table."""
    r0 = results[0]
    out = [f"I++ DME driver on the simulated CMM, {r0['ball_mm']} mm stylus ball, noise {r0['noise_sigma_mm']} mm per "
           f"coordinate, instant machine motion, median of {r0['repeats']}:", "",
           "| transport | measurement | wall time | I++ lines (sent + received) | max error vs truth |",
           "| --- | --- | ---: | ---: | ---: |"]
    for r in results:
        out += [
            f"| {r['transport']} | one sphere ({r['sphere_touches']} touches + fit) | "
            f"{1e3 * r['sphere_time_s']:.1f} ms | | centre {1e3 * r['sphere_centre_error_max_mm']:.2f} um |",
            f"| {r['transport']} | pose (6 spheres + registration) | {1e3 * r['pose_time_s']:.1f} ms | "
            f"{r['pose_lines']} | position {1e3 * r['pose_position_error_max_mm']:.2f} um, orientation "
            f"{r['pose_orientation_error_max_deg']:.1e} deg |",
            f"| {r['transport']} | first pose (base spheres searched for, {r['first_pose_touches']} touches) | "
            f"{1e3 * r['first_pose_time_s']:.1f} ms | | |"]
    out += ["", f"Collisions of the stylus ball: {sum(r['collisions'] for r in results)}."]
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="5 repeats")
    args = parser.parse_args(argv)
    repeats = 5 if args.quick else args.repeats
    table = markdown([run(repeats, transport="pty"), run(repeats, transport="tcp")])
    print(table)
    write_doc("benchmarks_cmm.md", "CMM measurement timings", "benchmarks/bench_cmm.py",
              f"{repeats} repeats; wall-clock, no assertions on speed.", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())

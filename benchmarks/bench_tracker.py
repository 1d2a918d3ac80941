"""Machine time per pose and pose noise of the laser tracker, through the run's own code path: the simulated station
(``hilcal sim --instrument tracker``'s defaults: the tracker 5 to 9 m from the paper robot's four platform nests and
four base monuments, MPE ±(15 µm + 6 µm/m)), its channels made a station file, the real drivers opened on it
(emScon over TCP) and the poses measured as the engine measures them (``drivers.instrument.TrackerPoseInstrument``).

Why: a run with a tracker spends its measuring time turning the beam, letting the ATR search and measuring each
target; the simulated tracker's machine clock (before its time scale, ``TrackerServerHandle.machine_time_s``) says how
long that takes per pose, for a first pose searched as the station's tolerance says and for the poses after it. The
pose noise, from repeated measurements of a still platform, is compared with what the MPE implies through the target
registrations (``hilcal.acceptance.tracker_mpe.tracker_pose_covariance``, the certificate's figure at that pose).
Run ``python benchmarks/bench_tracker.py [--repeats N] [--quick]``.
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

from hilcal.acceptance.tracker_mpe import tracker_origin_mm, tracker_pose_covariance
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.pose_measurement import pose_from_matrix
from hilcal.robot import default_robot, rotation_matrix
from hilcal.workspace import random_poses
from procedures.station import open_devices, station_from_channels
from sim_devices.sim_config import SimConfig, SimTrackerConfig
from sim_devices.simulator import start_sim

N_POSES = 8
"""Poses the platform visits (seeded draws from the paper robot's reachable workspace, after its home); the last one
is also held for the repeats."""


def _pose_error(measured: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """[dx, dy, dz mm, small rotation about x, y, z deg] of the measured pose against the truth (base axes)."""
    R = rotation_matrix(np.radians(measured[3:])) @ rotation_matrix(np.radians(truth[3:])).T
    return np.concatenate([measured[:3] - truth[:3], pose_from_matrix(R, np.zeros(3))[3:]])


def run(repeats: int = 200, seed: int = 0) -> dict:
    """Machine time per pose (first, later, still) and the pose scatter of `repeats` measurements of a still
    platform against the MPE's prediction."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    config = SimConfig(instrument="tracker", tracker=SimTrackerConfig(time_scale=0.0))
    poses = np.vstack([default_robot().home, random_poses(default_robot(), N_POSES - 1, np.random.default_rng(seed))])
    with start_sim(config) as sim:
        station = station_from_channels(sim.channels())
        server = sim.tracker_server
        with open_devices(station) as devices:
            robot, instrument = devices.robot, devices.instrument
            t0 = server.machine_time_s
            instrument.prepare()
            setup_s = server.machine_time_s - t0
            devices.controller.enable()
            moving: list[dict] = []
            for k, pose in enumerate(poses):
                legs = inverse_kinematics(Geometry.nominal(robot), pose)  # the controller's geometry
                devices.controller.move_legs(legs, 60.0)
                t0, w0 = server.machine_time_s, time.perf_counter()
                measured = instrument.measure_pose(robot, pose, None)
                moving.append({"first": k == 0, "machine_s": server.machine_time_s - t0,
                               "wall_s": time.perf_counter() - w0, "searches": measured.extra["searches"],
                               "widened": measured.extra["widened_searches"]})
            errors, still_s = [], []
            for _ in range(repeats):
                t0 = server.machine_time_s
                measured = instrument.measure_pose(robot, poses[-1], None)
                still_s.append(server.machine_time_s - t0)
                errors.append(_pose_error(measured.pose, sim.controller.true_pose()))
            devices.controller.disable()
            t = station.tracker
            predicted = np.sqrt(np.diag(tracker_pose_covariance(*t.layouts(), poses[-1], tracker_origin_mm(
                t.alignment_matrix()), t.mpe_constant_um, t.mpe_per_m_um)))
            distances = np.linalg.norm(server.machine.targets(), axis=1)
    errors = np.array(errors)
    later = [m for m in moving if not m["first"]]
    return {"repeats": repeats, "setup_s": setup_s, "first": moving[0],
            "later_machine_s": [m["machine_s"] for m in later], "later_wall_s": [m["wall_s"] for m in later],
            "later_widened": sum(m["widened"] for m in later), "still_machine_s": statistics.median(still_s),
            "scatter": errors.std(axis=0, ddof=1).tolist(), "bias": errors.mean(axis=0).tolist(),
            "predicted": predicted.tolist(), "distance_m": [float(distances.min() / 1e3), float(distances.max() / 1e3)],
            "n_targets": len(distances)}


def markdown(r: dict) -> str:
    """The result as Markdown tables."""
    later = r["later_machine_s"]
    names = ("x (mm)", "y (mm)", "z (mm)", "roll (deg)", "pitch (deg)", "yaw (deg)")
    lines = [
        f"The simulated station of `hilcal sim --instrument tracker`: {r['n_targets']} targets (4 platform nests, 4 "
        f"base monuments) {r['distance_m'][0]:.1f} to {r['distance_m'][1]:.1f} m from the tracker, MPE ±(15 µm + 6 "
        "µm/m); "
        "the tracker's machine time as its simulator counts it (turning at 180°/s, an ATR search of 1 s, a "
        "stationary measurement of 1 s per target), motion at the simulator's time scale 0.",
        "",
        "| | machine time | searches | wall time (instant tracker) |",
        "| --- | ---: | ---: | ---: |",
        f"| initialise and set up | {r['setup_s']:.1f} s | – | – |",
        f"| first pose (the station's 10 mm, 0.2° tolerance) | {r['first']['machine_s']:.1f} s | "
        f"{r['first']['searches']} ({r['first']['widened']} widened) | {1e3 * r['first']['wall_s']:.0f} ms |",
        f"| each later pose ({len(later)} poses over the workspace) | {statistics.mean(later):.1f} s "
        f"({min(later):.1f} to {max(later):.1f}) | {8 * len(later) + r['later_widened']} ({r['later_widened']} "
        f"widened) | {1e3 * statistics.median(r['later_wall_s']):.0f} ms |",
        f"| a still platform, measured again | {r['still_machine_s']:.1f} s | 8 | – |",
        "",
        f"Pose noise: {r['repeats']} measurements of the still platform against its true pose, the standard deviation "
        "of each coordinate against the MPE's prediction (each target's coordinates with u = U(d)/2 at its distance, "
        "through the registrations of both layouts; the certificate's figure):",
        "",
        "| coordinate | measured scatter | predicted by the MPE | ratio | mean error |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for k, name in enumerate(names):
        scale, unit = (1e3, "µm") if k < 3 else (1.0, "°")
        s, p, b = r["scatter"][k] * scale, r["predicted"][k] * scale, r["bias"][k] * scale
        fmt = ".1f" if k < 3 else ".5f"
        lines.append(f"| {name} | {s:{fmt}} {unit} | {p:{fmt}} {unit} | {s / p:.2f} | {b:+{fmt}} {unit} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--quick", action="store_true", help="40 repeats")
    args = parser.parse_args(argv)
    repeats = 40 if args.quick else args.repeats
    table = markdown(run(repeats))
    print(table)
    write_doc("benchmarks_tracker.md", "Laser tracker: machine time per pose and pose noise",
              "benchmarks/bench_tracker.py", f"{repeats} repeats of the still pose; the ratio of a standard deviation "
              f"from {repeats} draws is good to about ±{100 / np.sqrt(2 * (repeats - 1)):.0f} %.", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())

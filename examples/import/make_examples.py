"""Generate the three worked examples of docs/import.md from the simulated rig, seeded, in the formats machines write.

**The data is simulated** (sim_devices), not measured. Each example folder gets the files as the machine or the
tracker would export them, and ``simulated.csv``: the same run as the simulator writes it directly in hilcal's
recording format, to compare an import with.

- ``logger/``: a medium electric hexapod (robot.toml made from geometry.toml by `hilcal robot-from-geometry`); its
  logger writes leg positions in motor revolutions and the pose as a quaternion; day1.csv holds the measure
  session, day2.csv the verify session 20 h later, after a power cycle and re-homing.
- ``tracker/``: the paper robot measured by a laser tracker: three reflectors on the platform and three reference
  nests on the base, in the tracker's own frame, with the controller's leg lengths in m; one file with
  semicolons, decimal commas and a preamble.
- ``paper/``: the paper robot's own log: leg strokes in mm, poses in m and rad, commanded poses, ISO time stamps,
  cal/check rows, the CMM's fit RMS and the oil temperature.

Run ``python examples/import/make_examples.py [--out DIR] [--truth]``; every draw is seeded, so the output is
the committed files. ``--diagnose`` prints the comparison table of docs/import.md from the committed files.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType

import numpy as np
import structlog

from hilcal.importing import geometry_robot_toml, load_geometry, load_map
from hilcal.planning.design import factorial_exchange, verification_poses
from hilcal.recording import Recording, write_recording
from hilcal.robot import Robot, default_robot, load_robot
from hilcal.workspace import random_poses
from procedures.cli.simulated_recording import RecordingOptions, second_session_start_s, simulate_with_truth
from sim_devices.rig.config import (
    EffectsConfig,
    JointBacklashConfig,
    RigConfig,
    SensorScaleConfig,
    TemperatureConfig,
    concealed_effect_config,
    load_errors,
    random_errors,
)
from sim_devices.rig.unlisted_config import ZeroShiftConfig

HERE = Path(__file__).resolve().parent
SEED = 19
EXAMPLES = ("logger", "tracker", "paper")
IMPORTS: dict[str, tuple[tuple[str, ...], str | None]] = {
    "logger": (("day1.csv", "day2.csv"), "file:day2.csv"),
    "tracker": (("tracker_export.csv",), "every:3"),
    "paper": (("docking_sim_log.csv",), None),
}
"""Per example, the files and the --hold-out of its `hilcal import` command (docs/import.md)."""


def _exporters() -> ModuleType:
    """examples/ is not a package: load the exporters next to this file."""
    name = "hilcal_example_exporters"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, HERE / "exporters.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


@dataclass(frozen=True)
class Example:
    """One generated example: the robot, the simulator's own recording, the exported files and how to import them."""

    name: str
    robot: Robot
    robot_file: Path | None
    direct: Recording
    files: tuple[Path, ...]
    hold_out: str | None
    truth: str


# ------------------------------------------------------------------ logger: electric hexapod, two sessions

LOGGER_GAP_S = 20.0 * 3600.0
LOGGER_SECONDS_PER_POSE = 60.0


def logger(folder: Path) -> Example:
    """Electric hexapod: ball-screw lead errors, a little backlash, re-homing shifts two legs' zeros on day 2."""
    src = HERE / "logger"
    _, text, _ = geometry_robot_toml(load_geometry(src / "geometry.toml"), "geometry.toml")
    (folder / "robot.toml").write_text(text, encoding="utf-8")
    robot = load_robot(folder / "robot.toml")
    rng = np.random.default_rng([SEED, 1])
    measure = np.vstack([random_poses(robot, 42, rng), np.tile(robot.home, (3, 1))])
    measure = measure[rng.permutation(len(measure))]
    verify = random_poses(robot, 21, rng)
    options = RecordingOptions(session_gap_s=LOGGER_GAP_S, include_cmd=False, include_temp=False,
                               include_sphere_fit_rms=False)
    day2 = second_session_start_s(len(measure), seconds_per_pose=LOGGER_SECONDS_PER_POSE, options=options)
    gain = np.array([60.0, 0.0, -80.0, 0.0, 45.0, 0.0])
    shift = np.array([0.0, 0.012, 0.0, -0.009, 0.0, 0.0])
    effects = EffectsConfig(
        sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=gain.tolist()),
        joint_backlash=JointBacklashConfig(enabled=True, backlash_mm=0.002),
        zero_shift=ZeroShiftConfig(enabled=True, shift_mm=shift.tolist(), from_time_s=day2),
    )
    config = RigConfig(seed=SEED, errors=random_errors(SEED, 0.04), cmm_noise_mm=0.002, leg_resolution_mm=0.0005,
                       effects=effects)
    direct, _ = simulate_with_truth(robot, config, measure, verify, seconds_per_pose=LOGGER_SECONDS_PER_POSE,
                                    options=options)
    exp = _exporters()
    files = exp.export_recording(direct, load_map(src / "map.toml"), folder, list(IMPORTS["logger"][0]),
                                 exp.ExportOptions(decimals={"legs": 7, "position": 5, "orientation": 10, "time": 1},
                                                   clock_origin_s=[0.0, day2],
                                                   extra_columns={"status": np.full(direct.n, "ready")}))
    truth = (f"42-parameter geometry errors N(0, (40 µm)^2) (seed {SEED}); ball-screw lead error "
             f"{', '.join(f'{g:+.0f}' for g in gain)} ppm (legs 1-6); joint backlash 2 µm; re-homing on day 2: "
             f"zero shift {', '.join(f'{1000 * s:+.0f}' for s in shift)} µm; pose noise from 2 µm sphere noise; "
             "legs in 0.5 µm steps")
    return Example("logger", robot, folder / "robot.toml", direct, tuple(files), IMPORTS["logger"][1], truth)


# ------------------------------------------------------------------ tracker: paper robot, raw reflector points

TRACKER_POSES = 48


def tracker(folder: Path) -> Example:
    """Paper robot with Table 2 errors and leg compliance, measured by a laser tracker in its own frame."""
    robot = default_robot()
    poses = random_poses(robot, TRACKER_POSES, np.random.default_rng([SEED, 2]))
    effects = concealed_effect_config("leg_compliance", 1.0, SEED)
    config = RigConfig(seed=SEED, errors=load_errors("table2", robot), effects=effects)
    centres: list[tuple[np.ndarray, np.ndarray]] = []
    rec, _ = simulate_with_truth(robot, config, poses, np.empty((0, 6)), options=RecordingOptions(
        include_cmd=False, include_temp=False), sphere_centres=centres)
    phase = np.array(["measure"] * rec.n, dtype="<U7")
    phase[2::3] = "verify"
    direct = replace(rec, phase=phase)
    points = np.array([np.vstack(pair) for pair in centres])
    exp = _exporters()
    preamble = ["Tracker export;Job 0419 docking simulator;", "Units;mm;", ";;"]
    files = exp.export_recording(direct, load_map(HERE / "tracker" / "map.toml"), folder, list(IMPORTS["tracker"][0]),
                                 exp.ExportOptions(decimals={"legs": 7, "targets": 5, "time": 0}, preamble=preamble,
                                                   clock_origin_s=[-12.0], measured_targets=points,
                                                   extra_columns={"Pose": np.arange(1, direct.n + 1)}))
    c = np.ravel(np.broadcast_to(effects.leg_compliance.c_mm_per_kn, 6))
    truth = (f"Table 2 geometry errors; leg compliance {', '.join(f'{v:.4f}' for v in c)} mm/kN (legs 1-6); "
             f"tracker noise {1000 * config.cmm_noise_mm:.0f} µm per coordinate; every third pose held out")
    return Example("tracker", robot, None, direct, tuple(files), IMPORTS["tracker"][1], truth)


# ------------------------------------------------------------------ paper: the docking simulator's own log


def paper(folder: Path) -> Example:
    """Paper robot with Table 2 errors and thermal growth of the legs, in its controller's own log format."""
    robot = default_robot()
    measure = factorial_exchange(robot, 32, np.random.default_rng([SEED, 3])).poses
    verify = verification_poses(robot, 24, SEED)
    effects = concealed_effect_config("thermal_expansion", 1.0, SEED)
    temperature = TemperatureConfig(t0_c=19.5, drift_k_per_h=1.5, amplitude_k=0.3, period_s=5400.0)
    config = RigConfig(seed=SEED, errors=load_errors("table2", robot), effects=effects, temperature=temperature)
    direct, _ = simulate_with_truth(robot, config, measure, verify)
    exp = _exporters()
    files = exp.export_recording(direct, load_map(HERE / "paper" / "map.toml"), folder, list(IMPORTS["paper"][0]),
                                 exp.ExportOptions(decimals={"legs": 4, "position": 9, "orientation": 12,
                                                             "temperature": 3, "fit_rms": 6}))
    truth = (f"Table 2 geometry errors; thermal growth {effects.thermal_expansion.alpha_ppm_per_k:.2f} ppm/K "
             f"(T_ref 20 °C) with the oil temperature drifting {temperature.drift_k_per_h:g} K/h; CMM noise "
             f"{1000 * config.cmm_noise_mm:.0f} µm per coordinate")
    return Example("paper", robot, None, direct, tuple(files), IMPORTS["paper"][1], truth)


BUILDERS: dict[str, Callable[[Path], Example]] = {"logger": logger, "tracker": tracker, "paper": paper}


def make(name: str, out: Path | None = None) -> Example:
    """Simulate one example and write its files (and simulated.csv) into out (default: its committed folder)."""
    folder = out or HERE / name
    folder.mkdir(parents=True, exist_ok=True)
    example = BUILDERS[name](folder)
    write_recording(folder / "simulated.csv", example.direct)
    return example


def diagnose_table() -> str:
    """Markdown: `diagnose` on each committed example as imported and on its simulated.csv (docs/import.md)."""
    from hilcal.discovery.search import diagnose
    from hilcal.importing import import_recording, parse_hold_out
    from hilcal.recording import read_recording

    rows = ["| example | effects, imported | effects, simulated.csv | largest parameter difference | noise yardstick "
            "| verify RMS after, imported / simulated.csv |", "|---|---|---|---|---|---|"]
    for name in EXAMPLES:
        folder = HERE / name
        files, hold_out = IMPORTS[name]
        robot = load_robot(folder / "robot.toml") if (folder / "robot.toml").exists() else default_robot()
        imported = import_recording([folder / f for f in files], load_map(folder / "map.toml"), robot=robot,
                                    hold_out=None if hold_out is None else parse_hold_out(hold_out)).recording
        a, b = diagnose(imported, robot), diagnose(read_recording(folder / "simulated.csv", robot), robot)
        worst = max(abs(a.parameters[k] - v) / b.std_errors[k] for k, v in b.parameters.items())
        noise = "none" if b.noise.chosen is None else b.noise.chosen.source
        after = " / ".join("n/a" if d.after is None else f"{1000 * d.after.position_mm.rms:.2f} µm" for d in (a, b))
        rows.append(f"| {name} | {', '.join(a.effects) or 'none'} | {', '.join(b.effects) or 'none'} | "
                    f"{worst:.4f} standard errors | {noise} | {after} |")
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="write the examples under this folder instead")
    parser.add_argument("--truth", action="store_true", help="print what each simulation holds")
    parser.add_argument("--diagnose", action="store_true", help="diagnose the committed examples, imported and "
                        "as simulated.csv, and print the comparison (writes nothing)")
    args = parser.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    if args.diagnose:
        print(diagnose_table())
        return 0
    for name in EXAMPLES:
        example = make(name, None if args.out is None else args.out / name)
        if args.truth:
            print(f"- {name}: {example.truth}")
        else:
            print(f"{name}: {example.direct.n} rows -> {', '.join(p.name for p in example.files)}, simulated.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())

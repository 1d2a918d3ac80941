"""Walk the in-process simulated rig through measurement and verification poses and record a CSV-ready Recording.

This is the simulated counterpart of a shop-floor run: for each pose the rig's clock advances by the time
per pose, an uncalibrated controller commands the pose, the CMM measures the six spheres (hilcal turns them
into a measured pose) and the leg temperature sensor is read into the ``temp_c`` column. ``time_s`` is the
rig's clock at the measurement.

Options reproduce the conditions of recordings made elsewhere (see ``RecordingOptions``): measure and verify
rows in two sessions on different days, and measure rows from several sessions (the clock jumps, the machine is
powered on again and reaches home by a motion that is not recorded), a start from an unknown motion history, and
files without the commanded pose (empty ``cmd_*``), without ``temp_c`` or without ``sphere_fit_rms_mm``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import structlog

from hilcal.pose_measurement import pose_from_spheres
from hilcal.recording import Recording, recording_from_arrays
from hilcal.robot import Robot
from sim_devices.rig.config import RigConfig
from sim_devices.rig.rig import SimulatedRig

log = structlog.get_logger(__name__)

EXCURSION_WORKSPACE_FRACTION = 0.5
"""Unrecorded excursions go to a seeded pose in this central fraction of each workspace range."""
MAX_EXCURSION_DRAWS = 1000
SECONDS_PER_HOUR = 3600.0


@dataclass(frozen=True)
class RecordingOptions:
    """How a simulated recording is made and what it writes (defaults: one session, all columns).

    session_gap_s: None for one session; otherwise the verify rows are a second session that starts this many
    seconds after the last measure row (e.g. 86400 for the next day): the rig is powered on again
    (SimulatedRig.start_session) and makes an unrecorded excursion, so its motion history is unknown.
    unknown_start: the first session, too, starts with such an unrecorded excursion.
    excursion_end: where an excursion leaves the machine: "home", or "random" (at the excursion's random pose,
    so the recording says neither where the machine was before a session's first row nor how it got there).
    measure_session_starts: indices of measure rows (> 0) that start a further session, each like the verify
    session (after session_gap_s, powered on again, an unrecorded excursion): measure rows from several sessions.
    """

    session_gap_s: float | None = None
    unknown_start: bool = False
    excursion_end: Literal["home", "random"] = "home"
    include_cmd: bool = True
    include_temp: bool = True
    include_sphere_fit_rms: bool = True
    measure_session_starts: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.session_gap_s is not None and not (np.isfinite(self.session_gap_s) and self.session_gap_s >= 0):
            raise ValueError(f"session_gap_s must be finite and >= 0, got {self.session_gap_s}")
        starts = self.measure_session_starts
        if starts and (self.session_gap_s is None or list(starts) != sorted(set(starts)) or starts[0] <= 0):
            raise ValueError(
                f"measure_session_starts must be increasing row indices > 0 with a session_gap_s, got {starts}"
            )
        if self.excursion_end not in ("home", "random"):
            raise ValueError(f"excursion_end must be 'home' or 'random', got {self.excursion_end!r}")

    @property
    def excursion_moves(self) -> int:
        """Moves of one unrecorded excursion (each takes seconds_per_pose): out, and back home unless it ends there."""
        return 2 if self.excursion_end == "home" else 1


def second_session_start_s(n_measure: int, *, seconds_per_pose: float, options: RecordingOptions) -> float:
    """Rig clock (s) at which the verify session starts (power-on), e.g. for a re-homing ZeroShiftConfig.from_time_s."""
    if options.session_gap_s is None:
        raise ValueError("the recording has one session: set RecordingOptions.session_gap_s")
    first = options.excursion_moves * seconds_per_pose if options.unknown_start else 0.0
    earlier = len(options.measure_session_starts) * (options.session_gap_s + options.excursion_moves * seconds_per_pose)
    return first + n_measure * seconds_per_pose + options.session_gap_s + earlier


def simulate_recording(
    robot: Robot,
    config: RigConfig,
    measure_poses: np.ndarray,
    verify_poses: np.ndarray,
    *,
    seconds_per_pose: float = 45.0,
    options: RecordingOptions | None = None,
) -> Recording:
    """Command every pose (measure rows first, then verify rows), measure it, and return the recording."""
    return simulate_with_truth(
        robot, config, measure_poses, verify_poses, seconds_per_pose=seconds_per_pose, options=options
    )[0]


def _check_temperature(config: RigConfig, options: RecordingOptions) -> None:
    """The rig's temperature drifts linearly; over a day's gap that is tens of kelvin, so refuse where it matters."""
    drift = config.temperature.drift_k_per_h
    if not options.session_gap_s or drift == 0.0:
        return
    if options.include_temp or config.effects.thermal_expansion.enabled:
        change = drift * options.session_gap_s / SECONDS_PER_HOUR
        raise ValueError(
            f"a session gap of {options.session_gap_s:g} s with a temperature drift of {drift:g} K/h moves the "
            f"temperature by {change:.3g} K (the rig's model has no daily cycle): set temperature.drift_k_per_h = 0, "
            "or record without temp_c and without thermal_expansion"
        )


def _excursion(
    rig: SimulatedRig, robot: Robot, rng: np.random.Generator, seconds_per_pose: float, end: str
) -> None:
    """Unrecorded motion to a seeded random reachable pose, and back home if end == "home"."""
    ws = robot.workspace
    mid, half = ws.mean(axis=1), (ws[:, 1] - ws[:, 0]) / 2 * EXCURSION_WORKSPACE_FRACTION
    lo, hi = robot.leg_limits
    for _ in range(MAX_EXCURSION_DRAWS):
        lengths = rig.controller_ik(rng.uniform(mid - half, mid + half))
        if np.all((lengths >= lo) & (lengths <= hi)):
            break
    else:
        raise ValueError(f"no reachable excursion pose in {MAX_EXCURSION_DRAWS} draws: check the robot's workspace")
    for target in (lengths, rig.controller_ik(robot.home))[: 2 if end == "home" else 1]:
        rig.advance_time(seconds_per_pose)
        rig.move_to_lengths(target)


def simulate_with_truth(
    robot: Robot,
    config: RigConfig,
    measure_poses: np.ndarray,
    verify_poses: np.ndarray,
    *,
    seconds_per_pose: float = 45.0,
    options: RecordingOptions | None = None,
    sphere_centres: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[Recording, np.ndarray]:
    """The recording and, for studies only, the rig's true pose at every row (never written to the file).

    sphere_centres: when given, the CMM's raw (platform, base) sphere centres of every row are appended to it,
    in the CMM's frame (what a CMM or laser tracker exports).
    """
    options = options or RecordingOptions()
    _check_temperature(config, options)
    if any(k >= len(measure_poses) for k in options.measure_session_starts):
        raise ValueError(f"measure_session_starts {options.measure_session_starts} must be below {len(measure_poses)}")
    rig = SimulatedRig(robot, config)
    excursions = np.random.default_rng([config.seed, 0xE4C])
    commanded = np.concatenate([measure_poses, verify_poses])
    phases = ["measure"] * len(measure_poses) + ["verify"] * len(verify_poses)
    legs = np.empty_like(commanded)
    measured = np.empty_like(commanded)
    fit_rms = np.empty(len(commanded))
    time_s = np.empty(len(commanded))
    temp_c = np.empty(len(commanded))
    truth = np.empty_like(commanded)
    if options.unknown_start:
        _excursion(rig, robot, excursions, seconds_per_pose, options.excursion_end)
    for k, pose in enumerate(commanded):
        new_session = k == len(measure_poses) or k in options.measure_session_starts
        if new_session and options.session_gap_s is not None:
            rig.advance_time(options.session_gap_s)
            rig.start_session()
            _excursion(rig, robot, excursions, seconds_per_pose, options.excursion_end)
        rig.advance_time(seconds_per_pose)
        rig.move_to_lengths(rig.controller_ik(pose))
        legs[k] = rig.reported_lengths()
        truth[k] = rig.true_pose()
        platform, base = rig.measure_spheres()
        if sphere_centres is not None:
            sphere_centres.append((platform, base))
        fit = pose_from_spheres(platform, base, robot)
        measured[k] = fit.pose
        fit_rms[k] = np.max(fit.rms_residual_mm)
        time_s[k] = rig.time_s
        temp_c[k] = rig.temperature_c()
    log.info("simulated_recording", n_measure=len(measure_poses), n_verify=len(verify_poses),
             seed=config.seed, cmm_noise_mm=config.cmm_noise_mm, cmm_noise_model=config.cmm_noise_model,
             effects=list(config.effects.active()), session_gap_s=options.session_gap_s)
    extra = {}
    if options.include_sphere_fit_rms:
        extra["sphere_fit_rms_mm"] = fit_rms
    if options.include_temp:
        extra["temp_c"] = temp_c
    rec = recording_from_arrays(
        seq=np.arange(1, len(commanded) + 1),
        phase=phases,
        time_s=time_s,
        cmd=commanded if options.include_cmd else None,
        legs_mm=legs,
        meas=measured,
        extra=extra,
        robot=robot,
        source="<simulated rig>",
    )
    return rec, truth

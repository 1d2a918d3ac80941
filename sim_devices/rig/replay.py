"""Replay a recording on the simulated rig: the rig's true pose at every row, for a twin to be compared with what was
measured there.

The rig is driven through the recording's reported leg lengths in their order, its clock at each row's time (from
the earliest row's: `rig_clock_s`), powered on again (SimulatedRig.start_session) wherever the recording starts a
new session, so the motion history, the time in the session and the session number are those of the recording. The
motion before the first row is not in the recording: the rig starts as after a long outward move of every leg.
"""

from __future__ import annotations

import numpy as np

from hilcal.recording import session_numbers
from hilcal.robot import Robot
from sim_devices.rig.config import RigConfig
from sim_devices.rig.rig import SimulatedRig


def replay_poses(robot: Robot, config: RigConfig, time_s: np.ndarray, legs_mm: np.ndarray) -> np.ndarray:
    """(N, 6) true poses (mm, deg) of the rig at the rows of a recording (times in s, reported legs in mm).

    Readings beyond the robot file's leg limits (a recording may hold a few) are held at the limit."""
    time_s = np.asarray(time_s, dtype=float)
    legs = np.clip(np.asarray(legs_mm, dtype=float), *robot.leg_limits)
    if time_s.ndim != 1 or legs.shape != (time_s.size, 6):
        raise ValueError(f"expected times (N,) and legs (N, 6), got {time_s.shape} and {legs.shape}")
    session = session_numbers(time_s)
    clock = rig_clock_s(time_s)
    rig = SimulatedRig(robot, config)
    out = np.empty((time_s.size, 6))
    for k in range(time_s.size):
        rig.set_time(float(clock[k]))
        if k and session[k] != session[k - 1]:
            rig.start_session()
        rig.move_to_lengths(legs[k])
        out[k] = rig.true_pose()
    return out


def rig_clock_s(time_s: np.ndarray) -> np.ndarray:
    """The rig's clock (s) at a recording's rows: their time from the earliest row's (the rig's clock starts at 0)."""
    time_s = np.asarray(time_s, dtype=float)
    return time_s - np.min(time_s) if time_s.size else time_s

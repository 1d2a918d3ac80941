"""Walk the in-process simulated rig through measurement and verification poses and record a CSV-ready Recording.

This is the simulated counterpart of a shop-floor run: an uncalibrated controller commands each pose,
the CMM measures the six spheres, and hilcal turns the sphere centres into a measured pose.
"""

from __future__ import annotations

import numpy as np
import structlog

from hilcal.pose_measurement import pose_from_spheres
from hilcal.recording import Recording, recording_from_arrays
from hilcal.robot import Robot
from sim_devices.config import RigConfig
from sim_devices.rig import SimulatedRig

log = structlog.get_logger(__name__)


def simulate_recording(
    robot: Robot,
    config: RigConfig,
    measure_poses: np.ndarray,
    verify_poses: np.ndarray,
    *,
    seconds_per_pose: float = 45.0,
) -> Recording:
    """Command every pose (measure rows first, then verify rows), measure it, and return the recording."""
    rig = SimulatedRig(robot, config)
    commanded = np.concatenate([measure_poses, verify_poses])
    phases = ["measure"] * len(measure_poses) + ["verify"] * len(verify_poses)
    legs = np.empty_like(commanded)
    measured = np.empty_like(commanded)
    fit_rms = np.empty(len(commanded))
    for k, pose in enumerate(commanded):
        rig.move_to_lengths(rig.controller_ik(pose))
        legs[k] = rig.reported_lengths()
        platform, base = rig.measure_spheres()
        fit = pose_from_spheres(platform, base, robot)
        measured[k] = fit.pose
        fit_rms[k] = np.max(fit.rms_residual_mm)
    log.info("simulated_recording", n_measure=len(measure_poses), n_verify=len(verify_poses),
             seed=config.seed, cmm_noise_mm=config.cmm_noise_mm)
    return recording_from_arrays(
        seq=np.arange(1, len(commanded) + 1),
        phase=phases,
        time_s=np.arange(len(commanded)) * seconds_per_pose,
        cmd=commanded,
        legs_mm=legs,
        meas=measured,
        extra={"sphere_fit_rms_mm": fit_rms},
        robot=robot,
        source="<simulated rig>",
    )

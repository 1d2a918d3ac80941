"""Walk the in-process simulated rig through measurement and verification poses and record a CSV-ready Recording.

This is the simulated counterpart of a shop-floor run: for each pose the rig's clock advances by the time
per pose, an uncalibrated controller commands the pose, the CMM measures the six spheres (hilcal turns them
into a measured pose) and the leg temperature sensor is read into the ``temp_c`` column. ``time_s`` is the
rig's clock at the measurement.
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
    return simulate_with_truth(robot, config, measure_poses, verify_poses, seconds_per_pose=seconds_per_pose)[0]


def simulate_with_truth(
    robot: Robot,
    config: RigConfig,
    measure_poses: np.ndarray,
    verify_poses: np.ndarray,
    *,
    seconds_per_pose: float = 45.0,
) -> tuple[Recording, np.ndarray]:
    """The recording and, for studies only, the rig's true pose at every row (never written to the file)."""
    rig = SimulatedRig(robot, config)
    commanded = np.concatenate([measure_poses, verify_poses])
    phases = ["measure"] * len(measure_poses) + ["verify"] * len(verify_poses)
    legs = np.empty_like(commanded)
    measured = np.empty_like(commanded)
    fit_rms = np.empty(len(commanded))
    time_s = np.empty(len(commanded))
    temp_c = np.empty(len(commanded))
    truth = np.empty_like(commanded)
    for k, pose in enumerate(commanded):
        rig.advance_time(seconds_per_pose)
        rig.move_to_lengths(rig.controller_ik(pose))
        legs[k] = rig.reported_lengths()
        truth[k] = rig.true_pose()
        platform, base = rig.measure_spheres()
        fit = pose_from_spheres(platform, base, robot)
        measured[k] = fit.pose
        fit_rms[k] = np.max(fit.rms_residual_mm)
        time_s[k] = rig.time_s
        temp_c[k] = rig.temperature_c()
    log.info("simulated_recording", n_measure=len(measure_poses), n_verify=len(verify_poses),
             seed=config.seed, cmm_noise_mm=config.cmm_noise_mm, cmm_noise_model=config.cmm_noise_model,
             effects=list(config.effects.active()))
    rec = recording_from_arrays(
        seq=np.arange(1, len(commanded) + 1),
        phase=phases,
        time_s=time_s,
        cmd=commanded,
        legs_mm=legs,
        meas=measured,
        extra={"sphere_fit_rms_mm": fit_rms, "temp_c": temp_c},
        robot=robot,
        source="<simulated rig>",
    )
    return rec, truth

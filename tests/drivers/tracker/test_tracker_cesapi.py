"""Interoperability with code we did not write: CESAPI's own emScon client (``CESAPI.connection.Connection`` and
``CESAPI.command.CommandSync``, unmodified) initialises the simulated tracker, sets its units and measures a point
that matches the truth within the tracker's noise.

CESAPI's modules call ``logging.basicConfig()`` at import, so they are imported inside the test (pytest's log
capture then holds the root logger and the call changes nothing). Its client reads each packet's header, then
sleeps 0.2 s: the test takes a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.robot import default_robot
from sim_devices.tracker.config import Station, TrackerServerConfig
from sim_devices.tracker.server import start_tracker_server
from sim_devices.tracker.targets import rig_reflectors

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
STATION = [-4800.0, 3100.0, 1200.0, 0.0, 0.0, -40.0]
POSE = ROBOT.home + np.array([-20.0, 30.0, -25.0, -1.0, 0.5, -3.0])


class Platform:
    def true_pose(self) -> np.ndarray:
        return POSE.copy()


def truth_in_tracker() -> np.ndarray:
    """(6, 3) reflector centres in the tracker's frame (platform spheres at POSE, then base spheres)."""
    R_platform = Rotation.from_euler("xyz", POSE[3:], degrees=True).as_matrix()
    points = np.vstack([ROBOT.platform_spheres @ R_platform.T + POSE[:3], ROBOT.base_spheres])
    R = Rotation.from_euler("xyz", STATION[3:], degrees=True).as_matrix()
    return (points - np.array(STATION[:3])) @ R


def test_cesapi_client_initialises_sets_units_and_measures() -> None:
    from CESAPI import packet as es
    from CESAPI.command import CommandSync
    from CESAPI.connection import Connection

    station = Station(**dict(zip(("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), STATION, strict=True)))
    config = TrackerServerConfig(seed=9, time_scale=0.0, station=station)
    with start_tracker_server(rig_reflectors(ROBOT, Platform()), config) as server:
        connection = Connection()
        connection.connect(host="127.0.0.1", port=server.port)
        try:
            command = CommandSync(connection)
            command.Initialize()
            units = es.SystemUnitsDataT()
            units.lenUnitType, units.angUnitType = es.ES_LU_Millimeter, es.ES_AU_Degree
            units.tempUnitType, units.pressUnitType, units.humUnitType = es.ES_TU_Celsius, es.ES_PU_Mbar, es.ES_HU_RH
            command.SetUnits(units)
            answer = command.GetUnits()
            assert (answer.unitsSettings.lenUnitType, answer.unitsSettings.angUnitType) == (
                es.ES_LU_Millimeter, es.ES_AU_Degree)
            q = truth_in_tracker()[4]  # a base sphere
            command.GoPosition(0, *(q + np.array([8.0, 5.0, -6.0])))
            command.FindReflector(float(np.linalg.norm(q)))
            result = command.StartMeasurement()
        finally:
            connection.disconnect()
    assert isinstance(result, es.SingleMeasResultT)
    xyz = np.array([result.dVal1, result.dVal2, result.dVal3])
    sigma = (15.0 + 6.0 * np.linalg.norm(q) / 1000.0) / 2000.0  # half the MPE, mm
    assert np.all(np.abs(xyz - q) < 4.5 * sigma), (xyz - q, sigma)
    assert result.dStd1 == pytest.approx(sigma, rel=1e-9)
    assert result.packetInfo.status == es.ES_RS_AllOK

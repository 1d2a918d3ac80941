"""Settings of the simulated laser tracker: where it stands, the true air, its accuracy (MPE), the ATR search, timing,
obstacles to the line of sight, the TCP endpoint, and the fault kinds with their per-command rates.

Lengths are mm and angles degrees unless a field name says otherwise. The station is the tracker's frame in the base
frame: p_base = R p_tracker + t, R = Rz(yaw) Ry(pitch) Rx(roll) (a levelled tracker: roll = pitch = 0, its z axis
up). ``move_every_poses`` moves it during a session, as an operator sets a tracker up again near its place.
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np
from pydantic import Field

from sim_devices.config_base import Strict


class Station(Strict):
    """Where the tracker stands: its frame in the base frame."""

    x_mm: float
    y_mm: float
    z_mm: float
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0

    def as_array(self) -> np.ndarray:
        """[x, y, z mm, roll, pitch, yaw deg]."""
        return np.array([self.x_mm, self.y_mm, self.z_mm, self.roll_deg, self.pitch_deg, self.yaw_deg])


DEFAULT_STATION = Station(x_mm=6000.0, y_mm=-1500.0, z_mm=1800.0, yaw_deg=165.0)
"""Six metres beside the paper robot, looking at it: every sphere of the rig 4 to 9 m away."""


class Air(Strict):
    """The air the beam travels through (the truth; the client tells the tracker what it thinks it is)."""

    temperature_c: float = Field(default=20.0, ge=-20.0, le=60.0)
    pressure_hpa: float = Field(default=1013.25, ge=500.0, le=1200.0)
    humidity_pct: float = Field(default=50.0, ge=0.0, le=100.0)


class Obstacle(Strict):
    """A sphere in the base frame that no beam passes (a column, a cabinet, the operator)."""

    centre_mm: tuple[float, float, float]
    radius_mm: float = Field(gt=0)


class Fault(StrEnum):
    """Injectable faults. BEAM_BREAK applies to StartMeasurement only, the others to any command."""

    GARBAGE = "garbage"
    """Packets of a data type the AT4xx definitions lack (as a newer server sends) before the answer."""
    PARTIAL = "partial"
    """The answer is cut in the middle and never finished; nothing follows (the connection stays open)."""
    SILENCE = "silence"
    """The command is dropped: no answer at all, nothing executed."""
    DELAY = "delay"
    """The answer comes ``delay_s`` late."""
    BEAM_BREAK = "beam_break"
    """The beam breaks during the measurement: its answer is AllOK, then an ErrorResponseT (NoStationaryResult)
    instead of the result; the lock is lost (a new search finds the reflector again)."""


class FaultRates(Strict):
    """Probability per command of each fault."""

    garbage: float = Field(default=0.0, ge=0, le=1)
    partial: float = Field(default=0.0, ge=0, le=1)
    silence: float = Field(default=0.0, ge=0, le=1)
    delay: float = Field(default=0.0, ge=0, le=1)
    beam_break: float = Field(default=0.0, ge=0, le=1)


class TrackerServerConfig(Strict):
    """The simulated tracker: station, air, accuracy, search, timing, obstacles, endpoint and faults."""

    seed: int = 0
    station: Station = DEFAULT_STATION
    air: Air = Field(default_factory=Air, description="the true air; the tracker starts believing 20 °C, "
                     "1013.25 hPa, 50 % until the client sets its environment")
    mpe_constant_um: float = Field(default=15.0, ge=0, description="MPE U = ±(constant + per_m · distance)")
    mpe_per_m_um: float = Field(default=6.0, ge=0)
    noise_scale: float = Field(default=1.0, ge=0, description="multiplies the noise drawn (0: noiseless); the "
                               "standard deviations the tracker states stay the MPE's")
    search_radius_mm: float = Field(default=50.0, gt=0, description="the ATR search radius at power-up")
    search_timeout_s: float = Field(default=5.0, gt=0, description="the ATR search's timeout at power-up")
    min_range_mm: float = Field(default=800.0, ge=0)
    max_range_mm: float = Field(default=40000.0, gt=0)
    slew_speed_deg_s: float = Field(default=180.0, gt=0, description="GoPosition's turn rate")
    search_time_s: float = Field(default=1.0, ge=0, description="an ATR search that finds a reflector")
    measure_time_s: float = Field(default=1.0, gt=0, description="a stationary measurement at power-up (lMeasTime)")
    initialize_time_s: float = Field(default=20.0, ge=0)
    time_scale: float = Field(default=1.0, ge=0, description="multiplies every duration; 0 = instant")
    obstacles: list[Obstacle] = Field(default_factory=list)
    port: int = Field(default=0, ge=0, le=65535, description="TCP port on 127.0.0.1; 0: ephemeral")
    delay_s: float = Field(default=0.5, gt=0, description="how late a DELAY fault's answer is (real seconds)")
    garbage_packets: int = Field(default=2, ge=1, le=20, description="packets per GARBAGE fault")
    faults: FaultRates = Field(default_factory=FaultRates)
    hang_after_commands: int | None = Field(default=None, ge=0, description="the tracker answers nothing from its "
                                            "command number N + 1 on, over every connection (a tracker that hangs "
                                            "until it is restarted); None: never")
    move_every_poses: int = Field(default=0, ge=0, description="the operator sets the tracker up again near its "
                                  "place after every K poses it measured (a pose: a round in which every platform "
                                  "target was measured); 0: never")
    move_mm: float = Field(default=40.0, ge=0, description="how far each such move shifts the tracker's origin (a "
                           "seeded direction)")
    move_deg: float = Field(default=0.5, ge=0, le=180, description="how far each such move turns the tracker about "
                            "its origin (a seeded axis)")

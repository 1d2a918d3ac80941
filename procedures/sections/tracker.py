"""The station file's measuring instrument: ``[instrument] kind`` and a laser tracker's ``[tracker]`` section.

A station measures with a CMM (``kind = "cmm"``, the default: ``procedures.station.CmmSection``) or with a laser
tracker (``kind = "tracker"``)::

    [instrument]
    kind = "tracker"

    [tracker]
    host = "192.168.0.1"               # the tracker controller (emScon over TCP)
    port = 700
    alignment = [6184.0, 104.0, -1800.0, 0.0, 0.0, -165.0]  # approximate T_tracker<-base, or a 4x4
    alignment_tolerance_mm = 10.0      # how far off it may be: the first pose's monuments are searched that far
    alignment_tolerance_deg = 0.2
    identity = "Leica AT960-MR, serial 750123"   # for the certificate
    calibration_due = 2027-06-30       # the tracker's own calibration
    mpe_constant_um = 15.0             # MPE U = ±(15 µm + 6 µm/m), read as U (k = 2) per coordinate of a point
    mpe_per_m_um = 6.0
    reflector = "RRR 1.5in"            # a name the tracker lists (GetReflectors), or its id
    environment = { temperature_c = 20.5, pressure_hpa = 1002.0, humidity_pct = 45.0 }   # as measured at the station
    platform_targets_mm = [[950.0, 0.0, 80.0], [0.0, 950.0, 80.0], [-950.0, 0.0, 80.0], [0.0, -950.0, 80.0]]
    base_monuments_mm = [[2800.0, 1600.0, 0.0], [-2800.0, 1600.0, 0.0], [0.0, -3200.0, 0.0]]
    [tracker.driver]                   # drivers.tracker.emscon.EmsconConfig's timeouts and retries
    move_timeout_s = 30.0
    [tracker.search]                   # drivers.tracker.pose.TrackerPoseConfig: ATR search radius, registrations
    max_radius_mm = 100.0

``platform_targets_mm`` are the SMR nests' reflector centres in the platform frame (at least 3, 4 recommended: one
more than the registration needs shows a reflector set wrong), ``base_monuments_mm`` the fixed nests' reflector
centres as surveyed in the base frame (at least 3). Neither may lie on a line, and no two targets may be closer than
``MIN_SPACING_MM``. The robot file's CMM spheres are the CMM's; a tracker station names its own targets.
"""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from drivers.cmm.types import as_transform
from drivers.tracker.base import Environment
from drivers.tracker.emscon import EmsconConfig
from drivers.tracker.pose import TrackerPoseConfig
from hilcal.acceptance.tracker_mpe import pose_sigma, tracker_origin_mm, tracker_pose_covariance
from hilcal.protocols.emscon import DEFAULT_PORT
from hilcal.robot import Robot

MIN_SPACING_MM = 20.0
"""Two targets closer than this could be taken for each other by the ATR."""
MIN_SPREAD_MM = 10.0
"""A layout whose points all lie within this of one line cannot fix the turn about it."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def alignment_list(v: Any) -> list[Any]:
    """An approximate alignment as written in a station file: [x, y, z mm, roll, pitch, yaw deg] or a 4x4 (ValueError
    saying what is expected otherwise)."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape not in ((6,), (4, 4)) or not np.all(np.isfinite(a)):
        raise ValueError(f"must be [x, y, z, roll, pitch, yaw] (mm, deg) or a 4x4 matrix of numbers, got {v!r}"[:200])
    if a.shape == (4, 4) and not np.array_equal(a[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError("the last row of a 4x4 alignment must be [0, 0, 0, 1]")
    as_transform(a)
    return a.tolist()


class InstrumentSection(_Strict):
    """``[instrument]``: what measures the platform's pose."""

    kind: Literal["cmm", "tracker"] = Field(default="cmm", description="cmm: the [cmm] section; tracker: [tracker]")


class TrackerEnvironment(_Strict):
    """The air at the station as the operator measured it: the tracker corrects its distances for it."""

    temperature_c: float = Field(ge=-20.0, le=60.0)
    pressure_hpa: float = Field(ge=500.0, le=1200.0)
    humidity_pct: float = Field(ge=0.0, le=100.0)


def _layout(v: Any, what: str) -> list[tuple[float, float, float]]:
    """At least 3 points of 3 finite numbers, not on a line, none closer to another than MIN_SPACING_MM."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.ndim != 2 or a.shape[1] != 3 or not np.all(np.isfinite(a)):
        raise ValueError(f"must be a list of [x, y, z] points (mm), got {v!r}"[:200])
    if len(a) < 3:
        raise ValueError(f"at least 3 {what} are needed to register a frame, got {len(a)}")
    gaps = np.linalg.norm(a[:, None] - a[None], axis=2) + np.diag(np.full(len(a), np.inf))
    i, j = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
    if gaps[i, j] < MIN_SPACING_MM:
        raise ValueError(f"{what} {min(i, j) + 1} and {max(i, j) + 1} are {gaps[i, j]:.1f} mm apart, closer than "
                         f"{MIN_SPACING_MM:g} mm: the tracker's search could take one for the other")
    spread = np.linalg.svd(a - a.mean(axis=0), compute_uv=False)
    if spread[1] / np.sqrt(len(a)) < MIN_SPREAD_MM:
        raise ValueError(f"the {what} lie on a line: a registration on them cannot fix the turn about it")
    return [tuple(p) for p in a.tolist()]


class TrackerDriver(EmsconConfig):
    """``[tracker.driver]``: the driver's timeouts and retries (``drivers.tracker.emscon.EmsconConfig``); the address
    is the section's own ``host`` and ``port``."""

    host: str = Field(default="", exclude=True)
    port: int = Field(default=DEFAULT_PORT, exclude=True)


class TrackerSection(_Strict):
    """A laser tracker on Leica's emScon (see the module docstring for the TOML)."""

    host: str = Field(min_length=1, description="the tracker controller's address")
    port: int = Field(default=DEFAULT_PORT, ge=1, le=65535)
    alignment: list[Any] = Field(description="T_tracker<-base, good to a few mm: a 4x4 matrix or [x, y, z mm, roll, "
                                 "pitch, yaw deg] of the base frame in the tracker's frame")
    alignment_tolerance_mm: float = Field(default=10.0, gt=0, le=100.0, description="how far the base frame's origin "
                                          "may be from where `alignment` puts it")
    alignment_tolerance_deg: float = Field(default=0.2, ge=0, le=5.0, description="how far `alignment` may be turned")
    identity: str | None = Field(default=None, min_length=1, max_length=200, description="make, model and serial")
    calibration_due: dt.date | None = Field(default=None, description="the tracker's own calibration is due then")
    mpe_constant_um: float = Field(default=15.0, gt=0, le=1000.0, description="MPE U = ±(constant + per_m · d)")
    mpe_per_m_um: float = Field(default=6.0, ge=0, le=1000.0)
    reflector: str | int = Field(default="RRR 1.5in", description="the reflector: a name the tracker lists, or its id")
    environment: TrackerEnvironment = Field(description="temperature, pressure and humidity at the station")
    platform_targets_mm: list[tuple[float, float, float]] = Field(
        description="SMR nests on the platform (platform frame, reflector centres): at least 3, 4 recommended")
    base_monuments_mm: list[tuple[float, float, float]] = Field(description="fixed nests surveyed in the base frame "
                                                                "(reflector centres): at least 3")
    driver: TrackerDriver = Field(default_factory=TrackerDriver, description="timeouts and retries (not host or port)")
    search: TrackerPoseConfig = Field(default_factory=TrackerPoseConfig)

    @field_validator("alignment")
    @classmethod
    def _alignment(cls, v: list[Any]) -> list[Any]:
        return alignment_list(v)

    @field_validator("platform_targets_mm", mode="before")
    @classmethod
    def _platform(cls, v: Any) -> Any:
        return _layout(v, "platform targets")

    @field_validator("base_monuments_mm", mode="before")
    @classmethod
    def _base(cls, v: Any) -> Any:
        return _layout(v, "base monuments")

    @model_validator(mode="after")
    def _endpoint_here(self) -> TrackerSection:
        if {"host", "port"} & self.driver.model_fields_set:
            raise ValueError("give host and port in [tracker] itself, not in [tracker.driver]")
        return self

    def alignment_matrix(self) -> np.ndarray:
        """(4, 4) T_tracker<-base."""
        return as_transform(np.asarray(self.alignment, dtype=float))

    def emscon_config(self) -> EmsconConfig:
        """The driver's settings with this tracker's address."""
        return EmsconConfig(**self.driver.model_dump(), host=self.host, port=self.port)

    def environment_setting(self) -> Environment:
        e = self.environment
        return Environment(e.temperature_c, e.pressure_hpa, e.humidity_pct)

    def layouts(self) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) platform targets (platform frame) and (K, 3) base monuments (base frame), mm."""
        return np.array(self.platform_targets_mm, dtype=float), np.array(self.base_monuments_mm, dtype=float)

    def pose_covariance(self, robot: Robot) -> np.ndarray:
        """(6, 6) covariance (mm, deg) of one pose at the robot's home, from the MPE at each target's distance."""
        platform, base = self.layouts()
        return tracker_pose_covariance(platform, base, robot.home, tracker_origin_mm(self.alignment_matrix()),
                                       self.mpe_constant_um, self.mpe_per_m_um)

    def setup_prompt(self) -> str:
        """What the operator confirms before the first pose."""
        return (f"Set the reflector ({self.reflector}) in the {len(self.platform_targets_mm)} platform nests and on "
                f"the {len(self.base_monuments_mm)} base monuments; laser tracker warmed up, in sight of every target "
                "and standing where the station file's alignment says?")


def tracker_from_channels(channels: dict[str, Any]) -> dict[str, Any]:
    """The ``[tracker]`` settings of a running simulator (its channels): endpoint, identity, MPE, the true air as
    the station's weather sensors give it, the published alignment and the target layouts."""
    t, targets = channels["tracker"], channels["tracker_targets"]
    return {"host": t["host"], "port": t["port"], "alignment": channels["tracker_alignment"],
            "identity": t.get("identity"), "mpe_constant_um": t["mpe_constant_um"], "mpe_per_m_um": t["mpe_per_m_um"],
            "environment": t["air"], "platform_targets_mm": targets["platform_targets_mm"],
            "base_monuments_mm": targets["base_monuments_mm"]}


def instrument_options(station: Any, robot: Robot) -> dict[str, Any]:
    """What the procedure needs to know of the station's instrument: the set-up question and, for a tracker, the
    pose noise its MPE implies (the diagnosis' noise yardstick); a CMM station's are the defaults."""
    if station.instrument.kind != "tracker":
        return {}
    return {"setup_prompt": station.tracker.setup_prompt(), "pose_sigma": pose_sigma(station.tracker.pose_covariance(
        robot))}

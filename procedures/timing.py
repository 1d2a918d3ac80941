"""The station's ``[timing]`` section: how fast the machine moves and measures, for time estimates and ordering.

The values describe the real devices (measure them on the machine: a timed leg move, a settled pose, one
CMM pose measurement). The defaults are placeholders for a large hydraulic platform with a CMM probing six
spheres. The simulated devices have their own timing in their own configuration; the tool never reads it.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilcal.planning.machine_time import MotionTiming


class TimingSection(BaseModel):
    """Leg speed (mm/s) and acceleration (mm/s²), settle wait and CMM time per pose (s), overhead per move (s)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    leg_speed_mm_s: float = Field(default=50.0, gt=0, description="leg speed of a calibration move")
    leg_accel_mm_s2: float = Field(default=100.0, gt=0, description="leg acceleration and deceleration")
    settle_s: float = Field(default=2.0, ge=0, description="wait after arriving before measuring")
    cmm_s_per_pose: float = Field(default=45.0, ge=0, description="CMM time to measure one pose")
    move_overhead_s: float = Field(default=0.5, ge=0, description="per move: command and in-position check")

    def timing(self, settle_s: float | None = None) -> MotionTiming:
        """The timing for ``hilcal.planning.machine_time`` (settle_s: a plan's own settle wait, not the station's)."""
        return MotionTiming(self.leg_speed_mm_s, self.leg_accel_mm_s2, self.settle_s if settle_s is None else settle_s,
                            self.cmm_s_per_pose, self.move_overhead_s)

    def describe(self) -> str:
        return (f"legs {self.leg_speed_mm_s:g} mm/s, {self.leg_accel_mm_s2:g} mm/s², settle {self.settle_s:g} s, "
                f"CMM {self.cmm_s_per_pose:g} s per pose, {self.move_overhead_s:g} s per move")


class TimingFileError(ValueError):
    """A station file whose [timing] section cannot be read."""


def load_timing(path: str | Path) -> TimingSection:
    """Only the ``[timing]`` section of a station TOML (defaults if absent): for runs on the simulated devices."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as err:
        raise TimingFileError(f"station file {p}: cannot read: {err.strerror}") from None
    except tomllib.TOMLDecodeError as err:
        raise TimingFileError(f"station file {p}: not valid TOML: {err}") from None
    try:
        return TimingSection.model_validate(data.get("timing", {}))
    except ValidationError as err:
        problems = "; ".join(f"timing.{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors())
        raise TimingFileError(f"station file {p}: {problems}") from None

"""Settings of the simulated CMM: noise, timing, transports, and the fault kinds with their per-command rates."""

from __future__ import annotations

from enum import StrEnum
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class Fault(StrEnum):
    """Injectable faults. GARBAGE/PARTIAL/SILENCE apply to any command, MISS/OUTLIER to PtMeas only."""

    GARBAGE = "garbage"
    """Random non-protocol lines before the final response line."""
    PARTIAL = "partial"
    """The data (or final) line is cut in the middle, never finished; nothing follows."""
    SILENCE = "silence"
    """The command is dropped: no response at all, nothing executed."""
    MISS = "miss"
    """PtMeas reports "Surface not found" although the surface is there."""
    OUTLIER = "outlier"
    """PtMeas returns a point displaced outwards along the approach direction by ``outlier_mm``."""


class FaultRates(BaseModel):
    """Probability per command of each fault."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    garbage: float = Field(default=0.0, ge=0, le=1)
    partial: float = Field(default=0.0, ge=0, le=1)
    silence: float = Field(default=0.0, ge=0, le=1)
    miss: float = Field(default=0.0, ge=0, le=1)
    outlier: float = Field(default=0.0, ge=0, le=1)


class CmmServerConfig(BaseModel):
    """The simulated CMM: noise, timing, transports and faults."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    seed: int = 0
    noise_sigma_mm: float = Field(default=0.002, ge=0, description="touch-point noise per coordinate")
    time_scale: float = Field(default=1.0, ge=0, description="multiplies every duration; 0 = instant")
    probe_time_s: float = Field(default=0.05, ge=0, description="fixed overhead of one touch (trigger, retract), "
                                "beyond the positioning travel and the probing stroke")
    travel_speed_mm_s: float = Field(default=250.0, gt=0, description="positioning moves (GoTo, PtMeas approach)")
    probing_speed_mm_s: float = Field(default=10.0, gt=0, description="the probing stroke, from the PtMeas start "
                                      "point to the touch (or the whole 2 x search distance on a miss)")
    home_time_s: float = Field(default=10.0, ge=0)
    on_collision: Literal["stop", "count"] = Field(
        default="stop", description="a positioning move (GoTo, PtMeas approach) into a tooling sphere, or a platform "
        "sphere that strikes the parked probe: 'stop' as a real CMM (error 2504 Collision, latched, the probe stopped "
        "at the surface); 'count': only a GoTo target or PtMeas start inside a sphere stops it, a path through one "
        "and a strike are counted and logged and the probe passes (for drivers that do not route around the spheres)")
    pty: bool = True
    tcp_port: int | None = Field(default=None, ge=0, le=65535, description="None: no TCP; 0: ephemeral port")
    outlier_mm: float = Field(default=0.5, gt=0)
    garbage_lines: int = Field(default=2, ge=1, le=20, description="lines per GARBAGE fault")
    faults: FaultRates = FaultRates()

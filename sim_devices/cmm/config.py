"""Settings of the simulated CMM: its tools, noise, timing, transports, and the fault kinds with per-command rates."""

from __future__ import annotations

from enum import StrEnum
from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from hilcal.protocols.ippdme import NO_TOOL, RESERVED_TOOLS, UNDEF_TOOL


class Fault(StrEnum):
    """Injectable faults. GARBAGE/PARTIAL/SILENCE apply to any command, MISS/OUTLIER to PtMeas only."""

    GARBAGE = "garbage"
    """Random non-protocol lines before the transaction's last line."""
    PARTIAL = "partial"
    """The first response line after the acknowledgement is cut in the middle, never finished; nothing follows."""
    SILENCE = "silence"
    """The command is dropped: no response at all (not even ``&``), nothing executed."""
    MISS = "miss"
    """PtMeas reports 1006 "Surface not found" although the surface is there."""
    OUTLIER = "outlier"
    """PtMeas reports a ball centre displaced outwards along the probing direction by ``outlier_mm``."""


class FaultRates(BaseModel):
    """Probability per command of each fault."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    garbage: float = Field(default=0.0, ge=0, le=1)
    partial: float = Field(default=0.0, ge=0, le=1)
    silence: float = Field(default=0.0, ge=0, le=1)
    miss: float = Field(default=0.0, ge=0, le=1)
    outlier: float = Field(default=0.0, ge=0, le=1)


class ParameterConfig(BaseModel):
    """One parameter of a GoToPar or PtMeasPar block (6.3.6, 6.3.7): its Min, Max and Def (Act starts at Def)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    min: float
    max: float
    default: float

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if not self.min <= self.default <= self.max:
            raise ValueError(f"need min <= default <= max, got {self.min}, {self.default}, {self.max}")
        return self


def _par(low: float, high: float, default: float) -> ParameterConfig:
    return ParameterConfig(min=low, max=high, default=default)


class ToolConfig(BaseModel):
    """A stylus of the tool table: its name and ball radius and its PtMeasPar distances (mm; 6.3.7).

    Speeds are the server's (``travel_speed_mm_s`` for GoToPar.Speed, ``probing_speed_mm_s`` for PtMeasPar.Speed)
    unless a tool sets its own. Every tool's ball centre is the machine's position (no offsets between styli).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(min_length=1, max_length=64, pattern=r'^[ !#-~]+$')
    ball_radius_mm: float = Field(default=1.5, ge=0, le=50)
    approach_mm: ParameterConfig = _par(0.5, 50.0, 10.0)
    search_mm: ParameterConfig = _par(0.5, 50.0, 10.0)
    retract_mm: ParameterConfig = _par(-1.0, 50.0, 10.0)
    """Retract < 0 means back to the approach position (6.3.2.13)."""
    probing_speed_mm_s: ParameterConfig | None = None
    travel_speed_mm_s: ParameterConfig | None = None

    @model_validator(mode="after")
    def _not_reserved(self) -> Self:
        if self.name in RESERVED_TOOLS:
            raise ValueError(f"{self.name!r} is a reserved tool name (6.3.2.14)")
        return self


class CmmServerConfig(BaseModel):
    """The simulated CMM: tools, noise, timing, transports and faults."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    seed: int = 0
    tools: tuple[ToolConfig, ...] = (ToolConfig(name="Probe1"),)
    active_tool: str = Field(default="Probe1", description="the tool active at power-up: a tool's name, 'RefTool', "
                             "'NoTool' or 'UnDefTool' (a server that does not know which tool is loaded, 6.3.2.14)")
    noise_sigma_mm: float = Field(default=0.002, ge=0, description="noise of a latched ball centre per coordinate")
    time_scale: float = Field(default=1.0, ge=0, description="multiplies every duration; 0 = instant")
    probe_time_s: float = Field(default=0.05, ge=0, description="fixed overhead of one touch (trigger, settle), "
                                "beyond the positioning travel, the probing stroke and the retract")
    travel_speed_mm_s: float = Field(default=250.0, gt=0, description="GoToPar.Speed's default: positioning moves "
                                     "(GoTo, the PtMeas approach and retract)")
    probing_speed_mm_s: float = Field(default=10.0, gt=0, description="PtMeasPar.Speed's default: the probing "
                                      "stroke, from the approach position to the touch or the end of search")
    home_time_s: float = Field(default=10.0, ge=0)
    tool_change_time_s: float = Field(default=2.0, ge=0)
    volume_limit_mm: float = Field(default=100_000.0, gt=0, description="|X|, |Y|, |Z| of a target beyond this: "
                                   "1008 Target position out of machine volume")
    home_position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    on_collision: Literal["stop", "count"] = Field(
        default="stop", description="the ball entering a tooling sphere on a positioning move (GoTo, the PtMeas "
        "approach or retract), or a platform sphere that strikes the parked ball: 'stop' as a real CMM (2504 "
        "Collision, the machine stopped where the ball met the surface); 'count': only a target inside a sphere "
        "stops it, a path through one and a strike are counted and logged and the ball passes")
    pty: bool = True
    tcp_port: int | None = Field(default=None, ge=0, le=65535, description="None: no TCP; 0: ephemeral port "
                                 "(a real server listens on 1294, 6.1)")
    outlier_mm: float = Field(default=0.5, gt=0)
    garbage_lines: int = Field(default=2, ge=1, le=20, description="lines per GARBAGE fault")
    faults: FaultRates = FaultRates()

    @model_validator(mode="after")
    def _tools(self) -> Self:
        names = [tool.name for tool in self.tools]
        if len(set(names)) != len(names):
            raise ValueError(f"tool names must be unique: {names}")
        if self.active_tool not in (*names, "RefTool", NO_TOOL, UNDEF_TOOL):
            raise ValueError(f"active_tool {self.active_tool!r} is no tool of the table")
        return self

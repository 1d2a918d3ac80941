"""The simulated CMM's tool table (6.3.2.14-6.3.2.23): styli, the reserved tools, and their parameter blocks.

Each tool has a GoToPar block (Speed, Accel; 6.3.6) and a PtMeasPar block (Speed, Accel, Approach, Search,
Retract; 6.3.7), each parameter with Min, Max, Def and Act; only Act can be set, clamped to [Min, Max] (the caller
answers warning 0504), and a tool that becomes active gets its Act values set to Def again. ``RefTool`` (a ball of
radius 0: the machine's reference point) and ``NoTool`` (moves, never measures) are listed by EnumTools;
``BaseTool`` (the defaults, not an instance to use) and ``UnDefTool`` (what the server reports when it does not know
which tool is loaded) are not.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hilcal.protocols.ippdme import GO_TO_PARAMETERS, NO_TOOL, PT_MEAS_PARAMETERS, UNDEF_TOOL
from sim_devices.cmm.config import CmmServerConfig, ParameterConfig, ToolConfig

REF_TOOL = "RefTool"
BASE_TOOL = "BaseTool"
BLOCKS = {"GoToPar": GO_TO_PARAMETERS, "PtMeasPar": PT_MEAS_PARAMETERS}
"""The parameter blocks of a tool and their parameters, in the order EnumProp lists them."""


@dataclass
class Parameter:
    """Min, Max, Def and the settable Act of one parameter."""

    min: float
    max: float
    default: float
    act: float = 0.0

    def __post_init__(self) -> None:
        self.act = self.default

    def part(self, name: str) -> float:
        """``Act``, ``Def``, ``Max`` or ``Min``."""
        return {"Act": self.act, "Def": self.default, "Max": self.max, "Min": self.min}[name]

    def set(self, value: float) -> bool:
        """Set Act, clamped to [Min, Max] (6.3.6); True when the value had to be clamped."""
        self.act = min(max(value, self.min), self.max)
        return self.act != value


@dataclass
class Tool:
    """One tool: its name, ball radius and parameter blocks; ``kind`` tells the reserved tools apart."""

    name: str
    ball_radius_mm: float
    blocks: dict[str, dict[str, Parameter]] = field(default_factory=dict)
    kind: str = "stylus"
    """``stylus``, ``ref`` (RefTool), ``none`` (NoTool), ``base`` (BaseTool) or ``undefined`` (UnDefTool)."""

    @property
    def can_measure(self) -> bool:
        return self.kind in ("stylus", "ref", "base")

    @property
    def defined(self) -> bool:
        return self.kind != "undefined"

    def reset(self) -> None:
        """Act back to Def in every block (the tool became active, 6.3.6 and 6.3.7)."""
        for block in self.blocks.values():
            for parameter in block.values():
                parameter.act = parameter.default

    def parameter(self, block: str, name: str) -> Parameter:
        return self.blocks[block][name]

    @property
    def approach_mm(self) -> float:
        return self.blocks["PtMeasPar"]["Approach"].act

    @property
    def search_mm(self) -> float:
        return self.blocks["PtMeasPar"]["Search"].act

    @property
    def retract_mm(self) -> float:
        return self.blocks["PtMeasPar"]["Retract"].act

    @property
    def travel_speed_mm_s(self) -> float:
        return self.blocks["GoToPar"]["Speed"].act

    @property
    def probing_speed_mm_s(self) -> float:
        return self.blocks["PtMeasPar"]["Speed"].act


def _parameter(config: ParameterConfig) -> Parameter:
    return Parameter(config.min, config.max, config.default)


def _speed(override: ParameterConfig | None, default: float, low: float, high: float) -> Parameter:
    if override is not None:
        return _parameter(override)
    return Parameter(min(low, default), max(high, default), default)


def make_tool(config: ToolConfig, server: CmmServerConfig, kind: str = "stylus") -> Tool:
    """A tool of the table with its blocks at their defaults."""
    goto = {"Speed": _speed(config.travel_speed_mm_s, server.travel_speed_mm_s, 1.0, 500.0),
            "Accel": Parameter(10.0, 5000.0, 1000.0)}
    ptmeas = {"Speed": _speed(config.probing_speed_mm_s, server.probing_speed_mm_s, 0.1, 50.0),
              "Accel": Parameter(10.0, 2000.0, 100.0), "Approach": _parameter(config.approach_mm),
              "Search": _parameter(config.search_mm), "Retract": _parameter(config.retract_mm)}
    return Tool(config.name, config.ball_radius_mm, {"GoToPar": goto, "PtMeasPar": ptmeas}, kind)


class ToolTable:
    """The tools the server knows, the active one and the one FindTool found last (6.3.2.16, 6.3.2.17)."""

    def __init__(self, config: CmmServerConfig) -> None:
        self.tools: dict[str, Tool] = {tool.name: make_tool(tool, config) for tool in config.tools}
        reserved = ToolConfig(name="Reserved", ball_radius_mm=0.0)
        for name, kind in ((REF_TOOL, "ref"), (NO_TOOL, "none"), (BASE_TOOL, "base")):
            tool = make_tool(reserved, config, kind)
            tool.name = name
            self.tools[name] = tool
        self.undefined = Tool(UNDEF_TOOL, 0.0, {}, "undefined")
        self.active: Tool = self.undefined if config.active_tool == UNDEF_TOOL else self.tools[config.active_tool]
        self.found: Tool = self.undefined

    def enumerate(self) -> list[str]:
        """EnumTools' names: RefTool and NoTool first, then the styli (6.3.2.23, 6.3.2.14)."""
        return [REF_TOOL, NO_TOOL, *(n for n, t in self.tools.items() if t.kind == "stylus")]

    def find(self, name: str) -> Tool | None:
        """The tool of that name (BaseTool included, 6.3.2.14), None if there is none."""
        return self.tools.get(name)

    def activate(self, tool: Tool) -> None:
        """Make ``tool`` the active tool with its Act values at their defaults."""
        tool.reset()
        self.active = tool

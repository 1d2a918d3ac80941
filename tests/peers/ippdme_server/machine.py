"""Simulated Cartesian CMM: tools, parameter blocks, coordinate systems and contact geometry.

Pure model code without sockets or threads.  Positions are the centre of the active tool's
probing ball in the machine coordinate system (MachineCsy), in millimetres (section 6.1.2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

Vec = np.ndarray
Limits = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]

#: Sub-properties of a parameter (sections 6.3.6 / 6.3.7), in the order of example 7.8.
PARAM_FIELDS = ("Max", "Min", "Act", "Def")
GOTO_PARAMS = ("Speed", "Accel")
PTMEAS_PARAMS = ("Speed", "Accel", "Approach", "Search", "Retract")


# --------------------------------------------------------------------------- parameters

@dataclass
class Param:
    """One parameter with Min/Max/Act/Def (A.6.7 param.h); only Act is settable."""

    minimum: float
    maximum: float
    default: float
    actual: float = math.nan

    def __post_init__(self) -> None:
        if math.isnan(self.actual):
            self.actual = self.default

    def value(self, sub: str) -> float:
        """Value of sub-property ``Max``/``Min``/``Act``/``Def``."""
        return {"Max": self.maximum, "Min": self.minimum,
                "Act": self.actual, "Def": self.default}[sub]

    def set_actual(self, value: float) -> bool:
        """Set Act, clamping into [Min, Max]; return True if clamped (warning 0504, 6.3.6)."""
        clamped = min(max(value, self.minimum), self.maximum)
        self.actual = clamped
        return clamped != value


def _goto_block() -> dict[str, Param]:
    return {"Speed": Param(0.1, 500.0, 100.0), "Accel": Param(1.0, 2000.0, 500.0)}


def _ptmeas_block() -> dict[str, Param]:
    return {
        "Speed": Param(0.1, 50.0, 5.0),
        "Accel": Param(1.0, 2000.0, 100.0),
        "Approach": Param(0.0, 100.0, 2.0),
        "Search": Param(0.0, 100.0, 4.0),
        "Retract": Param(-100.0, 100.0, 2.0),
    }


# --------------------------------------------------------------------------- tools

@dataclass
class ToolModel:
    """A tool of the tool changer (section 6.3.2.14 and A.6.2 tool.h).

    ``radius`` is the probing ball radius (AvrRadius, 6.3.13).  The predefined tools differ
    in the flags, per the table of section 6.3.2.14.
    """

    name: str
    radius: float
    goto_par: dict[str, Param] | None
    ptmeas_par: dict[str, Param] | None
    can_measure: bool
    enumerable: bool
    changeable: bool
    defined: bool = True

    def block(self, name: str) -> dict[str, Param] | None:
        """Parameter block ``GoToPar`` or ``PtMeasPar`` (None if the tool has none)."""
        return {"GoToPar": self.goto_par, "PtMeasPar": self.ptmeas_par}.get(name)

    def reset_actuals(self) -> None:
        """Act := Def for every parameter (done whenever this tool becomes active, 6.3.6)."""
        for block in (self.goto_par, self.ptmeas_par):
            for param in (block or {}).values():
                param.actual = param.default


def make_tools(probe_name: str, stylus_radius: float) -> dict[str, ToolModel]:
    """The predefined tools of section 6.3.2.14 plus one real probe.

    * BaseTool: default capabilities, not visible, not usable for ChangeTool.
    * RefTool: supports all standard tool properties (a ball like the probe).
    * NoTool: can only move, not measure; no PtMeasPar block.
    * UnDefTool: the error result of tool handling, every use generates an error.
    """
    return {
        "BaseTool": ToolModel("BaseTool", 0.0, _goto_block(), _ptmeas_block(),
                              can_measure=False, enumerable=False, changeable=False),
        "RefTool": ToolModel("RefTool", stylus_radius, _goto_block(), _ptmeas_block(),
                             can_measure=True, enumerable=True, changeable=True),
        "NoTool": ToolModel("NoTool", 0.0, _goto_block(), None,
                            can_measure=False, enumerable=True, changeable=True),
        probe_name: ToolModel(probe_name, stylus_radius, _goto_block(), _ptmeas_block(),
                              can_measure=True, enumerable=True, changeable=True),
        "UnDefTool": ToolModel("UnDefTool", 0.0, None, None, can_measure=False,
                               enumerable=False, changeable=False, defined=False),
    }


# --------------------------------------------------------------------------- coordinate systems

#: SetCoordSystem enumeration (6.3.3.1) in transformation-chain order (6.3.3, picture 21).
CSY_CHAIN = ("MachineCsy", "MoveableMachineCsy", "MultipleArmCsy", "PartCsy")
#: Enumerators of Get/SetCsyTransformation (6.3.3.3 / 6.3.3.4).
TRANSFORM_NAMES = ("PartCsy", "JogDisplayCsy", "JogMoveCsy", "SensorCsy",
                   "MoveableMachineCsy", "MultipleArmCsy")


def euler_matrix(theta: float, psi: float, phi: float) -> np.ndarray:
    """Rotation matrix from Euler angles in degrees, exactly as R33::Create in A.4.2."""
    c1, s1 = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    c2, s2 = math.cos(math.radians(psi)), math.sin(math.radians(psi))
    c3, s3 = math.cos(math.radians(phi)), math.sin(math.radians(phi))
    return np.array([
        [c2 * c3 - c1 * s2 * s3, s2 * c3 + c1 * c2 * s3, s1 * s3],
        [-c2 * s3 - c1 * s2 * c3, -s2 * s3 + c1 * c2 * c3, s1 * c3],
        [s1 * s2, -s1 * c2, c1],
    ])


@dataclass
class CsyTransform:
    """One SetCsyTransformation record (X0, Y0, Z0, Theta, Psi, Phi), section 6.3.3.4.

    Applied as ``x' = M x + X0``: X0..Z0 is "the zero point of the machine coordinate system
    in part coordinates" (6.3.3.4), M the matrix of A.4.2.
    """

    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angles: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def matrix(self) -> np.ndarray:
        return euler_matrix(*self.angles)


@dataclass
class CoordinateSystems:
    """Active coordinate system and the stored transformations (section 6.3.3)."""

    active: str = "MachineCsy"
    transforms: dict[str, CsyTransform] = field(
        default_factory=lambda: {name: CsyTransform() for name in TRANSFORM_NAMES})

    def _chain(self) -> list[CsyTransform]:
        level = CSY_CHAIN.index(self.active)
        return [self.transforms[name] for name in CSY_CHAIN[1:level + 1]]

    def point_from_machine(self, point: Vec) -> Vec:
        for tr in self._chain():
            point = tr.matrix @ point + np.array(tr.origin)
        return point

    def point_to_machine(self, point: Vec) -> Vec:
        for tr in reversed(self._chain()):
            point = tr.matrix.T @ (point - np.array(tr.origin))
        return point

    def vector_from_machine(self, vector: Vec) -> Vec:
        for tr in self._chain():
            vector = tr.matrix @ vector
        return vector

    def vector_to_machine(self, vector: Vec) -> Vec:
        for tr in reversed(self._chain()):
            vector = tr.matrix.T @ vector
        return vector


# --------------------------------------------------------------------------- geometry

@dataclass(frozen=True)
class Sphere:
    """A spherical artefact in machine coordinates."""

    centre: Vec
    radius: float


def first_contact(start: Vec, end: Vec, spheres: list[Sphere], ball_radius: float
                  ) -> tuple[float, Sphere] | None:
    """First fraction t in [0, 1] where the ball moving start->end touches a sphere.

    The ball touches a sphere when its centre is at distance ``sphere.radius + ball_radius``
    from the sphere centre.  A ball already touching (or inside) and moving away is free.
    """
    direction = end - start
    a = float(direction @ direction)
    if a == 0.0:
        return None
    best: tuple[float, Sphere] | None = None
    for sphere in spheres:
        reach = sphere.radius + ball_radius
        rel = start - sphere.centre
        b = 2.0 * float(rel @ direction)
        c = float(rel @ rel) - reach * reach
        if b >= -1e-9 * 2.0 * reach * math.sqrt(a):
            continue
        if c <= 0.0:
            t = 0.0
        else:
            disc = b * b - 4.0 * a * c
            if disc < 0.0:
                continue
            t = (-b - math.sqrt(disc)) / (2.0 * a)
            if t > 1.0:
                continue
        if best is None or t < best[0]:
            best = (t, sphere)
    return best


def inside_limits(point: Vec, limits: Limits) -> bool:
    """True if the point lies inside the axis travel limits."""
    return all(lo - 1e-9 <= point[i] <= hi + 1e-9 for i, (lo, hi) in enumerate(limits))


def exit_fraction(start: Vec, end: Vec, limits: Limits) -> float:
    """Largest t in [0, 1] such that start + t (end - start) stays inside the limits."""
    t_max = 1.0
    for i, (lo, hi) in enumerate(limits):
        delta = end[i] - start[i]
        if delta > 0.0 and end[i] > hi:
            t_max = min(t_max, (hi - start[i]) / delta)
        elif delta < 0.0 and end[i] < lo:
            t_max = min(t_max, (lo - start[i]) / delta)
    return max(t_max, 0.0)

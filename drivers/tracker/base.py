"""The laser tracker interface: one small abstract API, what it measures, and how it fails.

A transport module (``drivers.tracker.emscon``: Leica's emScon over TCP) implements the primitives: initialise, the
units, the environment and refraction, the reflector, the ATR search parameters, positioning (``go_position``,
``find_reflector``) and one single-point measurement. This class adds ``setup`` and ``measure_point`` (go to an
approximate position, let the ATR find the reflector, measure; a measurement the beam broke is made again).

Units at this interface are mm, degrees, °C, hPa and % relative humidity, whatever the tracker's own; points are in
the tracker's frame (x, y, z mm; a tracker without a transformation set reports in its own frame).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from types import TracebackType

import numpy as np
import structlog

from hilcal.protocols.emscon import Command, ResultStatus, name_of

log = structlog.get_logger(__name__)


class TrackerDriverError(Exception):
    """Base class of every tracker driver error."""


class TrackerConnectionError(TrackerDriverError):
    """The tracker cannot be reached, or the connection was lost and could not be opened again."""


class TrackerTimeout(TrackerDriverError):
    """No answer within the command's timeout, after the bounded retries."""

    def __init__(self, message: str, command: str, timeout_s: float, attempts: int) -> None:
        super().__init__(message)
        self.command = command
        self.timeout_s = timeout_s
        self.attempts = attempts


class TrackerProtocolError(TrackerDriverError):
    """A stream that cannot be read on (a header no packet has, a packet that does not unpack, too many packets
    that answer nothing), after the bounded retries."""


class TrackerError(TrackerDriverError):
    """An error status the tracker reported: in a command's answer, in a result, or in an error packet
    (``unsolicited``: an ``ErrorResponseT``, sent when the error happened rather than as the answer)."""

    def __init__(self, command: int, status: int, unsolicited: bool = False, detail: str = "") -> None:
        where = "error packet" if unsolicited else "answer"
        super().__init__(f"tracker {where} to {name_of(Command, command)}: status {name_of(ResultStatus, status)}"
                         + (f": {detail}" if detail else ""))
        self.command = command
        self.status = status
        self.unsolicited = unsolicited


class TrackerNotInitialized(TrackerError):
    """The tracker must be initialised (``initialize()``) before it moves or measures."""


class NoReflectorLocked(TrackerError):
    """A measurement with no reflector locked on (the beam was broken, or no search found one)."""


class ReflectorNotFound(TrackerError):
    """The ATR search found no reflector where it was sent: none within the search radius, out of range, or out of
    the line of sight."""


class MeasurementFailed(TrackerError):
    """The measurement started but gave no result (the beam broke during it)."""


class TrackerParameterError(TrackerError):
    """The tracker refused a parameter (out of range, unknown reflector, meteo data out of range)."""


class TrackerNotSupported(TrackerError):
    """The tracker does not implement the command."""


_PARAMETER_STATUSES = {name for name in ResultStatus.__members__ if name.startswith(("WrongParameter", "Parameter"))}
_PARAMETER_STATUSES |= {"MeteoDataOutOfRange", "InvalidInputData"}


def tracker_error(command: int, status: int, unsolicited: bool = False, detail: str = "") -> TrackerError:
    """The typed error of a status the tracker reported for a command."""
    try:
        name = ResultStatus(status).name
    except ValueError:
        name = ""
    cls: type[TrackerError] = TrackerError
    if name == "TrackerNotInitialized":
        cls = TrackerNotInitialized
    elif name == "MeasurementStatusNotReady":
        cls = ReflectorNotFound if command == Command.FindReflector else NoReflectorLocked
    elif name == "NoStationaryResult":
        cls = MeasurementFailed
    elif name == "NotImplemented":
        cls = TrackerNotSupported
    elif name in _PARAMETER_STATUSES:
        cls = TrackerParameterError
    if cls is ReflectorNotFound and not detail:
        detail = "no reflector where the beam was sent (out of the line of sight, out of range, or beyond the search " \
                 "radius)"
    return cls(command, status, unsolicited, detail)


@dataclass(frozen=True)
class Environment:
    """The air the distance meter's wavelength is corrected for."""

    temperature_c: float
    pressure_hpa: float
    humidity_pct: float


@dataclass(frozen=True)
class Refraction:
    """Refractive indices of the air the tracker applies: interferometer and absolute distance meter."""

    ifm_index: float
    adm_index: float


@dataclass(frozen=True)
class Reflector:
    """A reflector the tracker knows (its id is what ``set_reflector`` takes)."""

    reflector_id: int
    name: str
    target_type: str
    surface_offset_mm: float
    """Distance from the reflector's centre to the surface it sits on (the SMR's radius)."""


@dataclass(frozen=True)
class SearchParams:
    """The ATR search: how far from where it is sent it looks, and for how long."""

    radius_mm: float
    timeout_s: float


@dataclass(frozen=True)
class TrackerUnits:
    """The units the tracker speaks in, by emScon's names."""

    length: str
    angle: str
    temperature: str
    pressure: str
    humidity: str


@dataclass(frozen=True)
class TrackerPoint:
    """One single-point measurement of a reflector's centre in the tracker's frame."""

    xyz_mm: np.ndarray
    """(3,) x, y, z, mm."""
    std_mm: np.ndarray
    """(3,) standard deviations of x, y, z the tracker states, mm."""
    std_total_mm: float
    apriori_std_mm: np.ndarray
    """(3,) standard deviations of x, y, z from the tracker's accuracy model, mm."""
    environment: Environment
    """The air the measurement was corrected for."""


def finite3(value: np.ndarray | tuple[float, ...], name: str) -> np.ndarray:
    """Three finite numbers as an array, else ValueError naming the argument."""
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return v


class TrackerInterface(abc.ABC):
    """A laser tracker. Subclasses implement the primitives; not thread-safe."""

    measure_retries: int = 2
    """``measure_point``: acquisitions made again after a measurement the beam broke (or a lost lock)."""
    remeasures: int = 0
    """How many measurements ``measure_point`` made again so far (beam breaks, locks lost)."""

    @abc.abstractmethod
    def initialize(self) -> None:
        """Initialise the tracker (its angles and distance meter referenced); needed before it moves or measures."""

    @abc.abstractmethod
    def set_units(self) -> None:
        """Make the tracker speak mm, degrees, °C, hPa and % relative humidity."""

    @abc.abstractmethod
    def units(self) -> TrackerUnits:
        """The units the tracker speaks in now."""

    @abc.abstractmethod
    def set_single_point_mode(self) -> None:
        """Cartesian coordinates in the tracker's frame, one stationary measurement per ``measure``."""

    @abc.abstractmethod
    def set_environment(self, environment: Environment) -> None:
        """The air temperature, pressure and humidity the distance meter is corrected for (its refraction)."""

    @abc.abstractmethod
    def environment(self) -> Environment:
        """The environment the tracker corrects for now."""

    @abc.abstractmethod
    def refraction(self) -> Refraction:
        """The refractive indices the tracker applies now (computed by the tracker from its environment)."""

    @abc.abstractmethod
    def set_refraction(self, refraction: Refraction) -> None:
        """Set the refractive indices directly (until the environment is set again)."""

    @abc.abstractmethod
    def reflectors(self) -> tuple[Reflector, ...]:
        """Every reflector the tracker knows."""

    @abc.abstractmethod
    def reflector(self) -> int:
        """The id of the reflector the tracker measures with."""

    @abc.abstractmethod
    def set_reflector(self, reflector_id: int) -> None:
        """Measure with this reflector (one of ``reflectors()``)."""

    @abc.abstractmethod
    def search_params(self) -> SearchParams:
        """The ATR search's radius and timeout."""

    @abc.abstractmethod
    def set_search_params(self, radius_mm: float, timeout_s: float) -> None:
        """Set the ATR search's radius and timeout."""

    @abc.abstractmethod
    def go_position(self, point_mm: np.ndarray, use_adm: bool = False) -> None:
        """Point the beam at a point (tracker frame, mm); with ``use_adm`` lock on a reflector found there."""

    @abc.abstractmethod
    def find_reflector(self, approx_distance_mm: float) -> None:
        """Search for a reflector around the beam's direction at about this distance and lock on it;
        ReflectorNotFound if there is none."""

    @abc.abstractmethod
    def direction_deg(self) -> tuple[float, float]:
        """The beam's (horizontal, vertical) angles, degrees."""

    @abc.abstractmethod
    def measure(self) -> TrackerPoint:
        """One single-point measurement of the reflector locked on."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the transport."""

    def __enter__(self) -> TrackerInterface:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def setup(self, environment: Environment | None = None, reflector_id: int | None = None) -> None:
        """Units, single-point mode, and (when given) the environment and the reflector."""
        self.set_units()
        self.set_single_point_mode()
        if environment is not None:
            self.set_environment(environment)
        if reflector_id is not None:
            self.set_reflector(reflector_id)

    def measure_point(self, approx_mm: np.ndarray | tuple[float, float, float]) -> TrackerPoint:
        """Measure the reflector near ``approx_mm`` (tracker frame): point the beam there, let the ATR search for it
        at that distance, measure. A measurement the beam broke (or a lock lost before it) is made again from the
        positioning on, ``measure_retries`` times at most; ReflectorNotFound at once when the search finds nothing
        (a reflector out of the line of sight, or not within the search radius)."""
        approx = finite3(approx_mm, "approx_mm")
        distance = float(np.linalg.norm(approx))
        if distance <= 0:
            raise ValueError("approx_mm must not be the tracker's origin")
        for attempt in range(1 + self.measure_retries):
            try:
                self.go_position(approx)
                self.find_reflector(distance)
                return self.measure()
            except ReflectorNotFound as err:
                near = ", ".join(f"{v:.1f}" for v in approx)
                raise ReflectorNotFound(err.command, err.status, err.unsolicited,
                                        f"no reflector found near ({near}) mm in the tracker's frame (out of the line "
                                        "of sight, out of range, or beyond the search radius)") from err
            except (MeasurementFailed, NoReflectorLocked) as err:
                if attempt == self.measure_retries:
                    raise
                self.remeasures += 1
                log.warning("tracker.measure_again", approx_mm=approx.round(3).tolist(), attempt=attempt + 1,
                            error=str(err))
        raise AssertionError("unreachable")

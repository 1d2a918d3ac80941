"""The CMM interface: one small abstract transport API, the stylus ball's tracked position, and the measurements.

Like python-can's ``BusABC``: a protocol module (``drivers.cmm.ippdme``) implements the primitive commands (session,
homing, GoTo, one touch, the touch settings, the position); this class tracks where the stylus ball is and counts its
touches, and measures spheres and poses with the transport-independent strategy of ``drivers.cmm.probing``. The
errors, results and settings live in ``drivers.cmm.types`` and are importable from here. All coordinates are in the
CMM frame, mm; poses are [x, y, z mm, roll, pitch, yaw deg], R = Rz(yaw) Ry(pitch) Rx(roll).

A touching probe's stylus ends in a ball of radius r (the CMM states it: Tool.AvrRadius(), 6.3.13), and PtMeas
reports the ball's centre (6.3.2.13). So everything here is in ball-centre space: ``position_mm`` is the ball's
centre, a touch starts with the ball's centre at ``start`` and reports the ball's centre at contact; a tooling sphere of
radius R is touched when the ball's centre is R + r from its centre. The nominal point a touch sends is the surface
point the ball would touch, start - (Approach + r)·IJK, so the approach position the specification defines, nominal +
(Approach + r)·IJK, is exactly ``start``.
"""

from __future__ import annotations

import abc
from types import TracebackType

import numpy as np
import structlog

from drivers.cmm.probing import Prober
from drivers.cmm.types import (
    BaseMeasurement,
    CmmConnectionError,
    CmmDriverError,
    CmmError,
    CmmMotionTimeout,
    CmmProtocolError,
    CmmTimeout,
    PoseMeasurement,
    PoseMeasurementError,
    ProbeLost,
    ProbeMiss,
    ProbeRecord,
    ProbeStatus,
    ProbingConfig,
    SphereMeasurement,
    SphereMeasurementError,
    SphereSearch,
    Touch,
    TouchSettings,
    as_transform,
    transform_from_pose,
)
from hilcal.acquisition.spheres import SpherePrediction
from hilcal.robot import Robot

log = structlog.get_logger(__name__)

__all__ = ["CmmConnectionError", "CmmDriverError", "CmmError", "CmmInterface", "CmmMotionTimeout",
           "CmmProtocolError", "CmmTimeout", "PoseMeasurement", "PoseMeasurementError", "ProbeLost", "ProbeMiss",
           "ProbeRecord", "ProbeStatus", "ProbingConfig", "SphereMeasurement", "SphereMeasurementError",
           "SphereSearch", "Touch", "TouchSettings", "as_transform", "transform_from_pose"]


class CmmInterface(abc.ABC):
    """A coordinate measuring machine with a ball stylus. Subclasses implement the primitives; not thread-safe."""

    probing: ProbingConfig = ProbingConfig()
    position_mm: np.ndarray | None = None
    """Where the stylus ball's centre is (CMM frame), as far as this driver knows; None: unknown (asked next time)."""
    stylus_radius_mm: float | None = None
    """The active tool's ball radius as the CMM states it (None: not read yet, or the tool changed)."""
    touch: TouchSettings | None = None
    """The touch settings the CMM has now, as read back (None: unknown)."""
    touches: int = 0
    """Touches made since the driver was opened (misses included)."""
    _touch_request: tuple[float, float] | None = None

    # ------------------------------------------------------------------ primitives

    @abc.abstractmethod
    def _start_session(self) -> None:
        """Open a measurement session and learn the CMM (its version, class, tools)."""

    @abc.abstractmethod
    def end_session(self) -> None:
        """Close the measurement session."""

    @abc.abstractmethod
    def _home(self, force: bool) -> np.ndarray:
        """Home the machine when it is not homed (or ``force``), activate the station's tool, read the stylus; where
        the ball's centre is afterwards."""

    @abc.abstractmethod
    def _refresh_stylus(self) -> float:
        """Read the active tool's ball radius (and what a touch reports) again; the radius."""

    @abc.abstractmethod
    def clear_errors(self) -> None:
        """Leave the error state entered after an error (a probe miss, a collision, an emergency stop released)."""

    @abc.abstractmethod
    def _goto(self, point_mm: np.ndarray) -> None:
        """Move the ball's centre in a straight line to a point without touching."""

    @abc.abstractmethod
    def _probe(self, nominal_mm: np.ndarray, ijk: np.ndarray) -> Touch:
        """PtMeas at this nominal surface point approaching along -ijk (unit); ProbeMiss if nothing was touched."""

    @abc.abstractmethod
    def _set_touch(self, approach_mm: float, search_mm: float, retract_mm: float) -> TouchSettings:
        """Set the touch settings; what the CMM has afterwards (it may clamp)."""

    @abc.abstractmethod
    def _where(self) -> np.ndarray:
        """Ask the CMM where the ball's centre is."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the transport."""

    def __enter__(self) -> CmmInterface:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ tracked primitives

    def start_session(self) -> None:
        """Open a measurement session (the CMM's touch settings are read again before the next touch)."""
        self.touch, self._touch_request = None, None
        self._start_session()

    def home(self, force: bool = False) -> None:
        """Get ready to move: home the machine if it is not homed (or ``force``); the station's tool, the stylus."""
        self.position_mm = None
        self.position_mm = np.asarray(self._home(force), dtype=float)

    def stylus(self) -> float:
        """The ball radius (read again after the CMM changed its tool)."""
        if self.stylus_radius_mm is None:
            self.stylus_radius_mm = float(self._refresh_stylus())
        return self.stylus_radius_mm

    def where(self) -> np.ndarray:
        """Where the ball's centre is (asked when unknown)."""
        if self.position_mm is None:
            self.position_mm = np.asarray(self._where(), dtype=float)
        return self.position_mm

    def set_touch(self, approach_mm: float, search_mm: float) -> TouchSettings:
        """Ask for these touch settings (the retract as long as the approach), sent only when they change; what the
        CMM has: the caller plans with that."""
        request = self._within_limits(round(float(approach_mm), 6), round(float(search_mm), 6))
        if self.touch is None or request != self._touch_request:
            self.touch = self._set_touch(request[0], request[1], request[0])
            self._touch_request = request
        return self.touch

    def _within_limits(self, approach_mm: float, search_mm: float) -> tuple[float, float]:
        """The request as the CMM would clamp it, where it states its limits (not sent just to be clamped)."""
        return approach_mm, search_mm

    def goto(self, point_mm: np.ndarray) -> None:
        """Move the ball's centre in a straight line to a point (the caller keeps the line clear:
        ``drivers.cmm.probing``)."""
        self.position_mm = None
        self._goto(point_mm)
        self.position_mm = np.asarray(point_mm, dtype=float).copy()

    def probe(self, start_mm: np.ndarray, ijk: np.ndarray) -> Touch:
        """Touch from ``start`` (the approach position: the ball's centre) along -ijk with the current settings.

        The ball then searches down to start - (Approach + Search)·ijk (a server may read the end of search as the
        ball's centre there or as its surface, r shorter: the caller plans for the longer). Returns the touch with
        ``reported_mm`` the ball's centre at contact. Afterwards the ball is where the specification puts it:
        contact + Retract·ijk (Retract >= 0) or back at ``start`` (Retract < 0); after a miss (ProbeMiss) or a lost
        report (ProbeLost) the errors are cleared and the CMM is asked.
        """
        r = self.stylus()
        settings = self.touch or self.set_touch(*(self._touch_request or (self.probing.min_search_mm,) * 2))
        n = np.asarray(ijk, dtype=float)
        n = n / np.linalg.norm(n)
        start = np.asarray(start_mm, dtype=float)
        nominal = start - (settings.approach_mm + r) * n
        self.position_mm = None
        self.touches += 1
        try:
            touch = self._probe(nominal, n)
        except ProbeMiss:
            self.clear_errors()
            self.where()
            raise
        except ProbeLost:
            self.where()
            raise
        self.position_mm = (touch.reported_mm + settings.retract_mm * n if settings.retract_mm >= 0
                            else start.copy())
        return touch

    def ball_centre(self, touch: Touch, ijk: np.ndarray) -> tuple[np.ndarray, float | None]:
        """The centre of a ball of the stated radius touching the surface point of ``touch``: its reported centre,
        moved by the difference of its effective radius ER() (6.3.2.25) along the surface normal (the reported IJK()
        where it points to the approach side, else the approach direction)."""
        r = self.stylus()
        if touch.effective_radius_mm is None:
            return touch.reported_mm, None
        n = np.asarray(ijk, dtype=float) / np.linalg.norm(ijk)
        m = n
        if touch.ijk is not None and np.linalg.norm(touch.ijk) > 0 and touch.ijk @ n > 0:
            m = touch.ijk / np.linalg.norm(touch.ijk)
        return touch.reported_mm - (touch.effective_radius_mm - r) * m, touch.effective_radius_mm

    # ------------------------------------------------------------------ measurements

    def measure_sphere(self, nominal_centre_mm: np.ndarray, radius_mm: float, up: np.ndarray = (0.0, 0.0, 1.0),
                       bound_mm: float | None = None) -> SphereMeasurement:
        """Find and probe a sphere predicted at ``nominal_centre_mm`` to within ``bound_mm`` (default: the probing
        settings' ``default_bound_mm``), approaching from the ``up`` side (``drivers.cmm.probing``).

        Misses and outliers are recorded, never used, and touched again within ``max_reprobes``; a sphere not where
        predicted is searched for. SphereMeasurementError when too few good points remain, the free-fit radius less
        the stylus radius is off the nominal by more than ``radius_tol_mm``, or no search finds the sphere. A centre
        more than ``prediction_tol_mm`` from where its probe pattern was laid out is measured once more around the
        fit (the first pass is kept as ``superseded``). The ball ends above the sphere, clear of it for whatever move
        comes next.
        """
        up_v = np.asarray(up, dtype=float)
        bound = self.probing.default_bound_mm if bound_mm is None else bound_mm
        pred = SpherePrediction(np.asarray(nominal_centre_mm, dtype=float), bound, up_v / np.linalg.norm(up_v))
        prober = Prober(self)
        measured = prober.measure_sphere(pred, radius_mm)
        prober.leave(measured, pred.up)
        return measured

    def measure_base(self, robot: Robot, alignment: np.ndarray, alignment_tolerance: tuple[float, float] | None,
                     platform_pose: np.ndarray, platform_cov: np.ndarray) -> BaseMeasurement:
        """Measure the base spheres alone, searching from ``alignment`` within ``alignment_tolerance`` as the run's
        first pose does, and register them on the robot's base layout, without moving the platform: its spheres'
        regions (``platform_pose`` within ``platform_cov``, as in ``measure_pose``) are kept clear."""
        return Prober(self).measure_base(robot, alignment, alignment_tolerance, platform_pose, platform_cov)

    def measure_pose(self, robot: Robot, alignment: np.ndarray, expected_pose: np.ndarray | None = None,
                     pose_cov: np.ndarray | None = None, alignment_tolerance: tuple[float, float] | None = None,
                     registered: bool = False) -> PoseMeasurement:
        """Measure the base spheres, then the platform spheres, and register both layouts to get the pose.

        ``alignment`` is an approximate T_cmm<-base (4x4, or the (6,) pose of the base frame in the CMM frame) known
        to ``alignment_tolerance`` (mm, deg; default: 10 mm and 0.2 deg,
        ``drivers.cmm.types.DEFAULT_ALIGNMENT_MM/DEG``); ``expected_pose`` (default: the robot's home) predicts the
        platform spheres with ``pose_cov``, the (6, 6) covariance of its [dt (mm); dw (rad)] in base axes
        (``hilcal.acquisition.model.PosePrediction``; default: ``default_bound_mm`` in translation). Each measured
        sphere conditions its body's frame, so the next is predicted better; ``extra`` counts the touches and
        searches. An alignment not ``registered`` on measured base spheres yet (the station's; the default) may be
        off beyond its tolerance: base-sphere searches then descend from ``max_search_mm`` above the prediction.
        Pass a previous pose's ``refined_alignment`` with ``registered=True`` and a tight tolerance
        (``drivers.cmm.probing.REGISTERED_MM/DEG``) to skip that. The ball ends parked above every place a platform
        sphere can reach.
        """
        return Prober(self).measure_pose(robot, alignment, expected_pose, pose_cov, alignment_tolerance, registered)

"""The CMM interface: one small abstract transport API, the probe's tracked position, and the measurements.

Like python-can's ``BusABC``: a transport module (``drivers.cmm.serial``) implements the primitive commands (session,
homing, GoTo, one touch, the search distance); this class tracks where the probe is and counts its touches, and
measures spheres and poses with the transport-independent strategy of ``drivers.cmm.probing``. The errors, results
and settings live in ``drivers.cmm.types`` and are importable from here. All coordinates are in the CMM frame, mm;
poses are [x, y, z mm, roll, pitch, yaw deg], R = Rz(yaw) Ry(pitch) Rx(roll).
"""

from __future__ import annotations

import abc
from types import TracebackType

import numpy as np

from drivers.cmm.probing import Prober
from drivers.cmm.types import (
    CmmConnectionError,
    CmmDriverError,
    CmmError,
    CmmProtocolError,
    CmmTimeout,
    PoseMeasurement,
    PoseMeasurementError,
    ProbeMiss,
    ProbeRecord,
    ProbeStatus,
    ProbingConfig,
    SphereMeasurement,
    SphereMeasurementError,
    SphereSearch,
    as_transform,
    transform_from_pose,
)
from hilcal.acquisition.spheres import SpherePrediction
from hilcal.robot import Robot

__all__ = ["CmmConnectionError", "CmmDriverError", "CmmError", "CmmInterface", "CmmProtocolError", "CmmTimeout",
           "PoseMeasurement", "PoseMeasurementError", "ProbeMiss", "ProbeRecord", "ProbeStatus", "ProbingConfig",
           "SphereMeasurement", "SphereMeasurementError", "SphereSearch", "as_transform", "transform_from_pose"]


class CmmInterface(abc.ABC):
    """A coordinate measuring machine. Subclasses implement the transport primitives; not thread-safe."""

    probing: ProbingConfig = ProbingConfig()
    position_mm: np.ndarray | None = None
    """Where the probe is (CMM frame), as far as this driver moved it; None until homed."""
    search_mm: float | None = None
    """The search distance the CMM has now (None: unknown)."""
    touches: int = 0
    """Touches made since the driver was opened (misses included)."""

    # ------------------------------------------------------------------ transport primitives

    @abc.abstractmethod
    def _start_session(self) -> None:
        """Open a measurement session (the CMM's session settings, e.g. its search distance, are reset)."""

    @abc.abstractmethod
    def end_session(self) -> None:
        """Close the measurement session."""

    @abc.abstractmethod
    def _home(self) -> np.ndarray:
        """Reference the machine axes; where the probe is afterwards (CMM frame)."""

    @abc.abstractmethod
    def clear_errors(self) -> None:
        """Leave the error state entered after a failed motion (a probe miss, a collision)."""

    @abc.abstractmethod
    def _goto(self, point_mm: np.ndarray) -> None:
        """Move the probe in a straight line to a point without touching."""

    @abc.abstractmethod
    def _probe(self, point_mm: np.ndarray, ijk: np.ndarray) -> np.ndarray:
        """Touch the surface near ``point_mm``: move straight to point + search * ijk, then approach along -ijk for up
        to twice the search distance; the touched point (3,). ProbeMiss if none."""

    @abc.abstractmethod
    def _set_search_distance(self, mm: float) -> None:
        """Set the search distance of the touches that follow."""

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
        """Open a measurement session with the probing settings' search distance."""
        self._start_session()
        self.search_mm = None
        self.set_search_distance(self.probing.min_search_mm)

    def home(self) -> None:
        """Reference the machine axes; the probe is then at the machine's home position."""
        self.position_mm = None
        self.position_mm = np.asarray(self._home(), dtype=float)

    def set_search_distance(self, mm: float) -> None:
        """Set the touches' search distance (sent only when it changes)."""
        if self.search_mm is None or abs(mm - self.search_mm) > 1e-9:
            self._set_search_distance(mm)
            self.search_mm = float(mm)

    def goto(self, point_mm: np.ndarray) -> None:
        """Move the probe in a straight line to a point (the caller keeps the line clear: ``drivers.cmm.probing``)."""
        self.position_mm = None
        self._goto(point_mm)
        self.position_mm = np.asarray(point_mm, dtype=float).copy()

    def probe(self, point_mm: np.ndarray, ijk: np.ndarray, search_mm: float | None = None) -> np.ndarray:
        """Touch near ``point_mm`` approaching along -ijk (with this search distance, else the current one); the
        touched point. The probe is left at the touch's start point, point + search * ijk."""
        if search_mm is not None:
            self.set_search_distance(search_mm)
        n = np.asarray(ijk, dtype=float)
        start = np.asarray(point_mm, dtype=float) + (self.search_mm or 0.0) * n / np.linalg.norm(n)
        self.position_mm = None
        self.touches += 1
        try:
            return self._probe(point_mm, ijk)
        finally:
            self.position_mm = start

    # ------------------------------------------------------------------ measurements

    def measure_sphere(self, nominal_centre_mm: np.ndarray, radius_mm: float, up: np.ndarray = (0.0, 0.0, 1.0),
                       bound_mm: float | None = None) -> SphereMeasurement:
        """Find and probe a sphere predicted at ``nominal_centre_mm`` to within ``bound_mm`` (default: the probing
        settings' ``default_bound_mm``), approaching from the ``up`` side (``drivers.cmm.probing``).

        Misses and outliers are recorded, never used, and touched again within ``max_reprobes``; a sphere not where
        predicted is searched for. SphereMeasurementError when too few good points remain, the free-fit radius is
        off by more than ``radius_tol_mm``, or no search finds the sphere. A centre more than ``prediction_tol_mm``
        from where its probe pattern was laid out is measured once more around the fit (the first pass is kept as
        ``superseded``). The probe ends above the sphere, clear of it for whatever move comes next.
        """
        up_v = np.asarray(up, dtype=float)
        bound = self.probing.default_bound_mm if bound_mm is None else bound_mm
        pred = SpherePrediction(np.asarray(nominal_centre_mm, dtype=float), bound, up_v / np.linalg.norm(up_v))
        prober = Prober(self)
        measured = prober.measure_sphere(pred, radius_mm)
        prober.leave(measured, pred.up)
        return measured

    def measure_pose(self, robot: Robot, alignment: np.ndarray, expected_pose: np.ndarray | None = None,
                     pose_cov: np.ndarray | None = None, alignment_tolerance: tuple[float, float] | None = None,
                     registered: bool = False) -> PoseMeasurement:
        """Measure the base spheres, then the platform spheres, and register both layouts to get the pose.

        ``alignment`` is an approximate T_cmm<-base (4x4, or the (6,) pose of the base frame in the CMM frame) known
        to ``alignment_tolerance`` (mm, deg; default: 10 mm and 0.2 deg,
        ``drivers.cmm.types.DEFAULT_ALIGNMENT_MM/DEG``);
        ``expected_pose``
        (default: the robot's home) predicts the platform spheres with ``pose_cov``, the (6, 6) covariance of its
        [dt (mm); dw (rad)] in base axes (``hilcal.acquisition.model.PosePrediction``; default: ``default_bound_mm``
        in translation). Each measured sphere conditions its body's frame, so the next is predicted better;
        ``extra`` counts the touches and searches. An alignment not ``registered`` on measured base spheres yet (the
        station's; the default) may be off beyond its tolerance: base-sphere searches then descend from
        ``max_search_mm`` above the prediction. Pass a previous pose's ``refined_alignment`` with ``registered=True``
        and a tight tolerance (``drivers.cmm.probing.REGISTERED_MM/DEG``) to skip that. The probe ends parked above
        every place a platform sphere can reach.
        """
        return Prober(self).measure_pose(robot, alignment, expected_pose, pose_cov, alignment_tolerance, registered)

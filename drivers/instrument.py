"""The measuring instrument of a run behind one small interface: a CMM or a laser tracker measures the platform pose.

The engine asks the instrument to get ready (``prepare``) and to measure the pose where the run's model expects it
(``measure_pose(robot, expected_pose, pose_cov)``), and journals what comes back (``MeasuredPose``). Each instrument
keeps its own alignment to the base frame: the station's approximate one, known to its tolerance, until a pose has
registered the base; then each pose's registration (only a prediction: every pose measures the base again). ``link``
names the instrument's link for the link guard and the report (``"cmm"``, ``"tracker"``).

A laser tracker is set up again during a run (for the line of sight, or knocked): its searches find the monuments
(``drivers.tracker.pose``), its ``StationLog`` counts the stations (``drivers.tracker.station``), and every row's
``extra`` says the station and where the tracker stood (``station``, ``station_pose``), with ``station_change`` on the
first pose of a new station. A monument not found where the previous pose's registration puts it is ``TrackerMoved``:
the tracker moved farther than the searches reach.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog

from drivers.cmm.base import CmmInterface
from drivers.cmm.probing import REGISTERED_DEG, REGISTERED_MM
from drivers.tracker.base import Environment, TrackerDriverError, TrackerInterface
from drivers.tracker.pose import TargetNotFound, TrackerPoseConfig, TrackerPoser
from drivers.tracker.station import StationLog, station_pose
from hilcal.robot import Robot

log = structlog.get_logger(__name__)


class InstrumentSetupError(TrackerDriverError):
    """The instrument cannot be set up as the station says (a reflector the tracker does not know)."""


class TrackerMoved(TargetNotFound):
    """A base monument not found where the previous pose's registration puts it: the tracker was set up again farther
    than the widest search reaches (or the monument's reflector is gone or hidden)."""


@dataclass(frozen=True)
class MeasuredPose:
    """One measured platform pose, as the engine journals it."""

    pose: np.ndarray
    """(6,) [x, y, z mm, roll, pitch, yaw deg] of the platform in the base frame."""
    registration_rms_mm: float
    """The larger RMS residual of the platform and base registrations (journaled as ``sphere_fit_rms_mm``)."""
    refined_alignment: np.ndarray
    """(4, 4) T_instrument<-base registered on this pose's base points."""
    extra: dict[str, Any] = field(default_factory=dict)
    """What the measurement met (touches and searches; a tracker's searches, re-measures, stated deviations)."""


class PoseInstrument(abc.ABC):
    """An instrument that measures platform poses; subclasses wrap a CMM or a laser tracker."""

    kind: str
    link: str
    address: str
    """Where it is (a serial URL, host:port), for the panel and the certificate."""

    @abc.abstractmethod
    def prepare(self) -> None:
        """Get ready to measure (start, home or initialise, settings); safe to repeat."""

    @abc.abstractmethod
    def measure_pose(self, robot: Robot, expected_pose: np.ndarray, pose_cov: np.ndarray | None) -> MeasuredPose:
        """Measure the platform where the run's model expects it (its pose and the covariance of [dt mm; dw rad])."""

    def continue_from(self, detail: dict[str, Any]) -> None:
        """A resumed run: the journal's last row (its detail) says what the instrument had measured from (a tracker's
        station); nothing for a CMM."""
        return None

    def expect_move(self) -> None:
        """The operator set the instrument up again near its place: search its base as for a moved one."""
        return None


class CmmPoseInstrument(PoseInstrument):
    """A CMM: the robot file's tooling spheres, probed by ``drivers.cmm.probing`` with the CMM's stylus.

    ``prepare`` opens the session (a second one: EndSession first, 6.3.1), homes only when the CMM is not homed, and
    activates the station's tool; an error state left from before (an emergency stop since released) is cleared
    there, where an operator has set the machine going again, never in the middle of a pose."""

    kind = link = "cmm"

    def __init__(self, cmm: CmmInterface, address: str, alignment: np.ndarray,
                 tolerance: tuple[float, float] | None) -> None:
        self.cmm = cmm
        self.address = address
        self.alignment = np.asarray(alignment, dtype=float)
        self.tolerance = tolerance
        """How well ``alignment`` is known (mm, deg): the station's tolerance until a pose registered the base."""

    def prepare(self) -> None:
        self.cmm.start_session()
        self.cmm.home()
        log.info("cmm.ready", address=self.address, stylus_radius_mm=self.cmm.stylus_radius_mm)

    def measure_pose(self, robot: Robot, expected_pose: np.ndarray, pose_cov: np.ndarray | None) -> MeasuredPose:
        registered = self.tolerance == (REGISTERED_MM, REGISTERED_DEG)
        pm = self.cmm.measure_pose(robot, self.alignment, expected_pose=expected_pose, pose_cov=pose_cov,
                                   alignment_tolerance=self.tolerance, registered=registered)
        self.alignment, self.tolerance = pm.refined_alignment, (REGISTERED_MM, REGISTERED_DEG)
        return MeasuredPose(np.asarray(pm.pose, dtype=float), float(np.max(pm.pose_fit.rms_residual_mm)),
                            pm.refined_alignment, dict(pm.extra))


class TrackerPoseInstrument(PoseInstrument):
    """A laser tracker: the station's platform targets and base monuments, found by ``drivers.tracker.pose``."""

    kind = link = "tracker"

    def __init__(self, tracker: TrackerInterface, address: str, alignment: np.ndarray,
                 tolerance: tuple[float, float], platform_targets_mm: np.ndarray, base_monuments_mm: np.ndarray,
                 environment: Environment, reflector: str | int, config: TrackerPoseConfig | None = None,
                 mpe_um: tuple[float, float] = (15.0, 6.0)) -> None:
        self.tracker = tracker
        self.address = address
        self.alignment = np.asarray(alignment, dtype=float)
        self.tolerance = tolerance
        self.alignment_cov: np.ndarray | None = None
        """The registration's covariance once a pose registered the base (then the tolerance no longer applies)."""
        self.platform_targets = np.asarray(platform_targets_mm, dtype=float)
        self.base_monuments = np.asarray(base_monuments_mm, dtype=float)
        self.environment = environment
        self.reflector = reflector
        self.poser = TrackerPoser(tracker, config)
        self.stations = StationLog(self.base_monuments, *mpe_um)
        self.registered = False
        """Whether a pose of this session registered the base (then a monument not found means the tracker moved)."""
        """The stations so far; ``mpe_um`` (constant µm, µm/m) sets what a move is (``drivers.tracker.station``)."""

    def _reflector_id(self) -> int:
        known = self.tracker.reflectors()
        for r in known:
            if self.reflector == r.reflector_id or (isinstance(self.reflector, str)
                                                    and self.reflector.strip().lower() == r.name.strip().lower()):
                return r.reflector_id
        listed = ", ".join(f"{r.reflector_id} {r.name!r}" for r in known) or "none"
        raise InstrumentSetupError(f"the tracker knows no reflector {self.reflector!r} (it lists: {listed}): set "
                                   "[tracker] reflector to one of them")

    def prepare(self) -> None:
        self.tracker.initialize()
        self.tracker.setup(self.environment, self._reflector_id())
        self.poser.forget_settings()
        log.info("tracker.ready", address=self.address, reflector=self.reflector,
                 environment=vars(self.environment))

    def continue_from(self, detail: dict[str, Any]) -> None:
        if "station" in detail and "station_pose" in detail:
            self.stations.resume(detail["station"], np.asarray(detail["station_pose"], dtype=float))

    def expect_move(self) -> None:
        cfg = self.poser.cfg
        self.alignment_cov, self.tolerance = None, (cfg.moved_tolerance_mm, cfg.moved_tolerance_deg)

    def measure_pose(self, robot: Robot, expected_pose: np.ndarray, pose_cov: np.ndarray | None) -> MeasuredPose:
        try:
            pm = self.poser.measure_pose(self.platform_targets, self.base_monuments, self.alignment, expected_pose,
                                         pose_cov, alignment_tolerance=self.tolerance, alignment_cov=self.alignment_cov)
        except TargetNotFound as err:
            if not self.registered or not err.target.startswith("base monument"):
                raise
            raise TrackerMoved(self._moved(err), err.target, err.radius_mm) from err
        self.alignment, self.alignment_cov, self.registered = pm.refined_alignment, pm.refined_cov, True
        change = self.stations.observe(pm.refined_alignment)
        extra = {**pm.extra, "station": self.stations.number,
                 "station_pose": [round(float(v), 6) for v in station_pose(pm.refined_alignment)]}
        if change is not None:
            extra["station_change"] = change.to_json()
            log.info("tracker.station_change", **change.to_json())
        return MeasuredPose(np.asarray(pm.pose, dtype=float), float(np.max(pm.pose_fit.rms_residual_mm)),
                            pm.refined_alignment, extra)

    def _moved(self, err: TargetNotFound) -> str:
        where = ", ".join(f"{v:.0f}" for v in station_pose(self.alignment)[:3])
        return (f"the tracker was moved: {err.target} is not within {err.radius_mm:g} mm (the widest search) of where "
                f"the last pose's registration (station {self.stations.number}, the tracker at ({where}) mm in the "
                "base frame) puts it. Set the tracker up again nearer that place, or give its new approximate "
                "alignment in the station file's [tracker] alignment (T_tracker<-base, within alignment_tolerance_mm), "
                "then resume the run: it finds the monuments again from there and counts a new station (also check "
                "that the monument's reflector sits in its nest, in the line of sight)")

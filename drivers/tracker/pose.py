"""How a laser tracker measures a platform pose, on any transport (``drivers.tracker.base``): the base monuments, then
the platform targets, each aimed at its prediction and found by the tracker's ATR search.

Every target comes with a prediction and a bound (``hilcal.acquisition.spheres.BodyBelief``: the station's
alignment known to its tolerance until the base is registered, then the registration; the platform from the pose
prediction and covariance the run's model gives). The ATR search radius is the bound (at least ``least_radius_mm``);
a target not found within it is searched for again with the radius widened (``widen_factor``) up to
``max_radius_mm``, and never farther than ``neighbour_fraction`` of the way to the nearest other target's prediction
(the ATR locks on the nearest reflector it sees): still not found, ``TargetNotFound`` names the target. A measurement
the beam broke is made again by ``TrackerInterface.measure_point``. Each measured point conditions its body's frame
with the standard deviation the tracker states, so the next target of that body is predicted better. The monument
predicted nearest the tracker is measured first (a tracker set up again, turned, moves it least); a monument found
beyond its bound means the alignment is not what it was (the tracker was set up again near its place): the base is
predicted again from the alignment known only to ``moved_tolerance_mm`` and ``moved_tolerance_deg``, conditioned on
the monuments found so far. The base monuments registered on their surveyed layout give the refined alignment; the
pose comes from both registrations (``hilcal.pose_measurement.pose_from_points``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from drivers.cmm.types import as_transform, transform_from_pose
from drivers.tracker.base import ReflectorNotFound, TrackerDriverError, TrackerInterface, TrackerPoint
from hilcal.acquisition.spheres import BodyBelief
from hilcal.pose_measurement import PoseFit, pose_from_points, rigid_fit

log = structlog.get_logger(__name__)

UP = np.array([0.0, 0.0, 1.0])
"""A reflector has no approach side; the predictions' pole is unused."""
LEAST_SIGMA_MM = 0.001
"""A measured point conditions its body's frame with at least this standard deviation per axis."""


class TrackerPoseConfig(BaseModel):
    """How the targets are searched for and the registrations judged (transport-independent)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    least_radius_mm: float = Field(default=5.0, gt=0, description="the ATR search radius at least, however well a "
                                   "target is predicted")
    max_radius_mm: float = Field(default=100.0, gt=0, description="a target not found is searched for on wider "
                                 "radii up to this")
    widen_factor: float = Field(default=2.0, gt=1.0, description="each search after a miss is this much wider")
    neighbour_fraction: float = Field(default=0.45, gt=0, lt=0.5, description="a search reaches at most this "
                                      "fraction of the way to the nearest other target's prediction")
    search_timeout_s: float = Field(default=5.0, gt=0, description="the ATR search's own timeout, sent with its radius")
    registration_tol_mm: float = Field(default=0.2, gt=0, description="largest RMS of a registration of the measured "
                                       "targets on their layout")
    default_bound_mm: float = Field(default=2.0, gt=0, description="the platform's uncertainty when the caller gives "
                                    "no covariance")
    moved_tolerance_mm: float = Field(default=100.0, gt=0, description="a base monument found beyond its bound: the "
                                      "tracker was set up again, its alignment known only to this (at the base's "
                                      "origin) and moved_tolerance_deg, and the monuments are predicted again from it")
    moved_tolerance_deg: float = Field(default=1.0, gt=0)


class TargetNotFound(TrackerDriverError):
    """A target the ATR did not find within the widest search allowed; names the target and where it was sought."""

    def __init__(self, message: str, target: str = "", radius_mm: float = 0.0) -> None:
        super().__init__(message)
        self.target = target
        """The target's name: "base monument 2", "platform target 1"."""
        self.radius_mm = radius_mm
        """The widest search made for it."""


class TrackerPoseError(TrackerDriverError):
    """The measured targets do not match their layout (a registration RMS beyond the tolerance)."""


@dataclass(frozen=True)
class TargetMeasurement:
    """One target as measured: what it is, where it was predicted (tracker frame) and within what, the point."""

    name: str
    predicted_mm: np.ndarray
    bound_mm: float
    point: TrackerPoint
    search_radius_mm: float
    """The ATR search radius it was found with."""
    searches: int
    """ATR searches for it (1: found at once; more: widened)."""

    @property
    def offset_mm(self) -> float:
        """How far from its prediction it was found."""
        return float(np.linalg.norm(self.point.xyz_mm - self.predicted_mm))


@dataclass(frozen=True)
class TrackerPoseMeasurement:
    """A platform pose measured from the base monuments and the platform targets, with everything behind it."""

    pose: np.ndarray
    """(6,) platform pose in the base frame [x, y, z mm, roll, pitch, yaw deg]."""
    pose_fit: PoseFit
    platform: tuple[TargetMeasurement, ...]
    base: tuple[TargetMeasurement, ...]
    alignment: np.ndarray
    """(4, 4) approximate T_tracker<-base given to the measurement."""
    refined_alignment: np.ndarray
    """(4, 4) T_tracker<-base registered on the measured base monuments."""
    refined_cov: np.ndarray
    """(6, 6) covariance of the refined alignment's [dt (mm); dw (rad)], for the next pose's predictions."""
    expected_pose: np.ndarray
    extra: dict = field(default_factory=dict)

    @property
    def point_std_mm(self) -> np.ndarray:
        """(M + K, 3) the standard deviations the tracker stated, platform targets first."""
        return np.array([t.point.std_mm for t in (*self.platform, *self.base)])


class TrackerPoser:
    """One tracker's pose strategy; remembers the search radius it set last (sent again only when it changes)."""

    def __init__(self, tracker: TrackerInterface, config: TrackerPoseConfig | None = None) -> None:
        self.tracker = tracker
        self.cfg = config or TrackerPoseConfig()
        self._radius_mm: float | None = None

    def forget_settings(self) -> None:
        """The tracker may have lost our settings (a new connection to a restarted tracker): set them again."""
        self._radius_mm = None

    def _set_radius(self, radius_mm: float) -> None:
        if self._radius_mm is None or not np.isclose(radius_mm, self._radius_mm, rtol=1e-6):
            self.tracker.set_search_params(radius_mm, self.cfg.search_timeout_s)
            self._radius_mm = radius_mm

    def measure_pose(self, platform_layout: np.ndarray, base_layout: np.ndarray, alignment: np.ndarray,
                     expected_pose: np.ndarray, pose_cov: np.ndarray | None = None,
                     alignment_tolerance: tuple[float, float] | None = None,
                     alignment_cov: np.ndarray | None = None) -> TrackerPoseMeasurement:
        """The base monuments, then the platform targets (see the module docstring).

        ``alignment`` is T_tracker<-base (4x4, or the (6,) pose of the base frame in the tracker's frame), known to
        ``alignment_cov`` (6x6 of [dt mm; dw rad], a registration's) or else to ``alignment_tolerance`` (mm, deg: a
        bound); ``expected_pose`` and ``pose_cov`` the run's prediction of the platform in the base frame.
        """
        cfg = self.cfg
        platform_layout = np.asarray(platform_layout, dtype=float)
        base_layout = np.asarray(base_layout, dtype=float)
        T0 = as_transform(alignment)
        if alignment_cov is not None:
            base_belief = BodyBelief(T0, np.asarray(alignment_cov, dtype=float))
        else:
            mm, deg = alignment_tolerance or (cfg.default_bound_mm, 0.0)
            base_belief = BodyBelief.within(T0, mm, deg)
        expected = np.asarray(expected_pose, dtype=float)
        cov = (BodyBelief.within(np.eye(4), cfg.default_bound_mm, 0.0).cov if pose_cov is None
               else np.asarray(pose_cov, dtype=float))
        T_bp = transform_from_pose(expected)
        remeasures0 = getattr(self.tracker, "remeasures", 0)
        base, T_tb, rms_b, base_belief = self._base(base_layout, base_belief, T0, platform_layout, T_bp, cov)
        base_pts = np.array([t.point.xyz_mm for t in base])
        if rms_b > cfg.registration_tol_mm:
            raise TrackerPoseError(
                f"the base monuments do not match their surveyed layout: registration RMS {rms_b:.4f} mm > "
                f"{cfg.registration_tol_mm} mm (a monument moved, a reflector in the wrong nest, or a survey wrong)")
        registered = BodyBelief(T_tb, base_belief.cov)
        platform_belief = registered.composed(T_bp, cov)
        platform: list[TargetMeasurement] = []
        for k, s in enumerate(platform_layout):
            others = [platform_belief.point(p) for j, p in enumerate(platform_layout) if j != k]
            others += [registered.point(p) for p in base_layout]
            found = self._find(f"platform target {k + 1}", platform_belief, s, np.array(others))
            platform.append(found)
            platform_belief = platform_belief.condition(s, found.point.xyz_mm, _sigma(found.point))
        fit = pose_from_points(np.array([t.point.xyz_mm for t in platform]), platform_layout, base_pts, base_layout,
                               "the station's target layouts")
        if fit.platform_rms_mm > cfg.registration_tol_mm:
            raise TrackerPoseError(
                f"the platform targets do not match their layout: registration RMS {float(fit.platform_rms_mm):.4f} "
                f"mm > {cfg.registration_tol_mm} mm (a reflector in the wrong nest, or a nest not where the station "
                "file says)")
        targets = (*base, *platform)
        extra = {"targets": len(targets), "searches": sum(t.searches for t in targets),
                 "widened_searches": sum(t.searches - 1 for t in targets),
                 "remeasures": getattr(self.tracker, "remeasures", 0) - remeasures0,
                 "largest_search_radius_mm": max(t.search_radius_mm for t in targets),
                 "largest_search_offset_mm": max(t.offset_mm for t in targets),
                 "point_std_mm": float(max(np.max(t.point.std_mm) for t in targets)),
                 "registration_rms_mm": [float(v) for v in fit.rms_residual_mm]}
        log.info("tracker.pose_measured", pose=fit.pose.tolist(), rms_mm=fit.rms_residual_mm.tolist(), **extra)
        return TrackerPoseMeasurement(pose=fit.pose, pose_fit=fit, platform=tuple(platform), base=tuple(base),
                                      alignment=T0, refined_alignment=T_tb, refined_cov=registered.cov,
                                      expected_pose=expected, extra=extra)

    def measure_monuments(self, base_layout: np.ndarray, alignment: np.ndarray,
                          alignment_tolerance: tuple[float, float], platform_layout: np.ndarray,
                          platform_pose: np.ndarray, platform_cov: np.ndarray
                          ) -> tuple[tuple[TargetMeasurement, ...], np.ndarray, float]:
        """The base monuments alone, searched from the station's alignment within its tolerance as a run's first
        pose does, the platform's targets (``platform_pose`` within ``platform_cov``) kept out of the searches
        (``hilcal check``); the monuments, T_tracker<-base registered on them and the registration's RMS (mm)."""
        T0 = as_transform(alignment)
        base_belief = BodyBelief.within(T0, *alignment_tolerance)
        base, T_tb, rms, _ = self._base(np.asarray(base_layout, dtype=float), base_belief, T0,
                                        np.asarray(platform_layout, dtype=float),
                                        transform_from_pose(np.asarray(platform_pose, dtype=float)),
                                        np.asarray(platform_cov, dtype=float))
        return base, T_tb, rms

    def _base(self, base_layout: np.ndarray, base_belief: BodyBelief, T0: np.ndarray, platform_layout: np.ndarray,
              T_bp: np.ndarray, cov: np.ndarray) -> tuple[tuple[TargetMeasurement, ...], np.ndarray, float,
                                                          BodyBelief]:
        """The monuments nearest first, each conditioning the base's frame (a monument beyond its bound: the tracker
        was set up again, so the alignment is known only to the moved tolerance); their registration."""
        cfg = self.cfg
        found_at: dict[int, TargetMeasurement] = {}
        for k in _nearest_first(base_belief, base_layout):
            s = base_layout[k]
            others = [base_belief.point(p) for j, p in enumerate(base_layout) if j != k]
            others += [base_belief.composed(T_bp, cov).point(p) for p in platform_layout]
            found = self._find(f"base monument {k + 1}", base_belief, s, np.array(others))
            found_at[k] = found
            if found.offset_mm > found.bound_mm:  # not where the alignment put it: the tracker was set up again
                log.info("tracker.alignment_reset", target=found.name, offset_mm=found.offset_mm,
                         bound_mm=found.bound_mm)
                base_belief = BodyBelief.within(T0, cfg.moved_tolerance_mm, cfg.moved_tolerance_deg)
                for j, t in found_at.items():
                    base_belief = base_belief.condition(base_layout[j], t.point.xyz_mm, _sigma(t.point))
            else:
                base_belief = base_belief.condition(s, found.point.xyz_mm, _sigma(found.point))
        base = [found_at[k] for k in range(len(base_layout))]
        base_pts = np.array([t.point.xyz_mm for t in base])
        R_tb, t_tb, rms_b = rigid_fit(base_layout, base_pts)
        T_tb = np.eye(4)
        T_tb[:3, :3], T_tb[:3, 3] = R_tb, t_tb
        return tuple(base), T_tb, float(rms_b), base_belief

    def _find(self, name: str, belief: BodyBelief, body_point: np.ndarray, others: np.ndarray) -> TargetMeasurement:
        """Aim at the target's prediction with the search radius its bound asks for; widen after a miss."""
        cfg = self.cfg
        pred = belief.predict(body_point, UP, 0.0)
        nearest = float(np.min(np.linalg.norm(others - pred.centre_mm, axis=1))) if len(others) else np.inf
        limit = min(cfg.max_radius_mm, cfg.neighbour_fraction * nearest)
        radius = min(max(cfg.least_radius_mm, pred.bound_mm), limit)
        searches = 0
        while True:
            self._set_radius(radius)
            searches += 1
            try:
                point = self.tracker.measure_point(pred.centre_mm)
            except ReflectorNotFound as err:
                if radius >= limit * (1.0 - 1e-9):
                    where = ", ".join(f"{v:.1f}" for v in pred.centre_mm)
                    why = (f"the widest search allowed ({cfg.max_radius_mm:g} mm)" if limit == cfg.max_radius_mm else
                           f"nearly half-way ({cfg.neighbour_fraction:g}) to the nearest other target")
                    raise TargetNotFound(
                        f"{name}: no reflector within {radius:.1f} mm of its prediction ({where}) mm in the tracker's "
                        f"frame after {searches} ATR search(es), {why}: check that its reflector sits in its nest, "
                        "in the tracker's line of sight, and the station's alignment and target layout",
                        name, radius) from err
                log.info("tracker.search_widened", target=name, radius_mm=radius, bound_mm=pred.bound_mm)
                radius = min(radius * cfg.widen_factor, limit)
                continue
            return TargetMeasurement(name, pred.centre_mm, pred.bound_mm, point, radius, searches)


def _nearest_first(belief: BodyBelief, layout: np.ndarray) -> list[int]:
    """The order the monuments are measured in: the one predicted nearest the tracker first (a tracker set up again
    turned by an angle moves it least), then the others in the layout's order."""
    nearest = int(np.argmin([np.linalg.norm(belief.point(p)) for p in layout]))
    return [nearest, *(k for k in range(len(layout)) if k != nearest)]


def _sigma(point: TrackerPoint) -> float:
    """The standard deviation a measured point conditions its frame with: the largest the tracker states."""
    std = np.asarray(point.std_mm, dtype=float)
    return max(float(np.max(std)) if std.size and np.all(np.isfinite(std)) else 0.0, LEAST_SIGMA_MM)

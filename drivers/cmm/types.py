"""What the CMM driver measures and how it fails: errors, probe records, sphere and pose results, the probing
settings, and the frame helpers; shared by the interface (``drivers.cmm.base``) and the probing strategy
(``drivers.cmm.probing``). All coordinates are in the CMM frame, mm; poses are [x, y, z mm, roll, pitch, yaw deg],
R = Rz(yaw) Ry(pitch) Rx(roll).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from hilcal.pose_measurement import PoseFit
from hilcal.robot import rotation_matrix
from hilcal.sphere_fit import MIN_POINTS_FREE_RADIUS, SphereFit, outlier_threshold_mm


class CmmDriverError(Exception):
    """Base class of every CMM driver error."""


class CmmConnectionError(CmmDriverError):
    """The port cannot be opened, or the connection was lost (or the CMM answers neither a motion nor AbortE)."""


class CmmTimeout(CmmDriverError):
    """No complete response within its bounded wait (a query: after its bounded re-asks)."""


class CmmMotionTimeout(CmmTimeout):
    """A motion (GoTo, PtMeas, Home, ChangeTool) did not complete in time: it was aborted with AbortE (6.3.1.5), never
    sent again; the errors were cleared and the probe's position read back (``position_mm``)."""

    def __init__(self, message: str, command: str, position_mm: np.ndarray | None, error_status: bool | None) -> None:
        super().__init__(message)
        self.command = command
        self.position_mm = position_mm
        self.error_status = error_status
        """GetErrStatusE's answer after the recovery (None: not asked)."""


class CmmProtocolError(CmmDriverError):
    """A response that breaks the protocol (a malformed line for our tag, an answer that is not the requested data)."""


class ProbeLost(CmmProtocolError):
    """A touch was made but its report was garbled: the point is lost (the probe's position was read back)."""


class CmmToolChanged(CmmProtocolError):
    """The CMM changed its tool on its own (an E0000 ChangeTool event, 9.5.4) during a measurement: the stylus is
    read again before the next one."""


class CmmError(CmmDriverError):
    """An error reported by the CMM, ``! Error(severity, code, "method", "text")`` (8), of severity 2 or more.

    ``errors`` holds every error of the transaction (8: a transaction can carry several); ``tag`` is the tag it came
    with (E0000: unsolicited, 6.2.4)."""

    def __init__(self, code: int, text: str, severity: int = 3, method: str = "", tag: str = "",
                 errors: tuple[ErrorReport, ...] = ()) -> None:
        super().__init__(f"CMM error {code:04d} (severity {severity}) in {method or '?'}: {text}")
        self.code = code
        self.text = text
        self.severity = severity
        self.method = method
        self.tag = tag
        self.errors = errors


class ProbeMiss(CmmError):
    """PtMeas touched no surface within the search (1006 Surface not found; 1003 No touch)."""


class CmmEmergencyStop(CmmError):
    """0500 Emergency stop, with any tag: motion stops, nothing moves until it is released and cleared."""


class CmmCollision(CmmError):
    """2504 Collision: the machine stopped where it struck something."""


class CmmTransactionAborted(CmmError):
    """0006 Transaction aborted: an AbortE or an error of severity 2 or more ended the transaction (6.2.5, 6.3.1.5)."""


class CmmInErrorState(CmmDriverError):
    """The CMM is in an error state (severity 2 or more, or after AbortE) not cleared yet: the driver sends nothing but
    GetErrStatusE, GetXtdErrStatus and ClearAllErrors (6.2.5) until ``clear_errors()``; ``cause`` is the error."""

    def __init__(self, message: str, cause: CmmError | None) -> None:
        super().__init__(message)
        self.cause = cause


@dataclass(frozen=True)
class ErrorReport:
    """One ``! Error(F1, F2, F3, Text)`` as received (a warning of severity 0 or 1 is returned, not raised)."""

    severity: int
    code: int
    method: str
    text: str
    tag: str = ""


@dataclass(frozen=True)
class Touch:
    """One PtMeas as the CMM reported it (6.3.2.13): the stylus ball's centre at contact, and where the CMM gives
    them, the surface direction IJK() and the effective radius ER() (6.3.2.25)."""

    reported_mm: np.ndarray
    ijk: np.ndarray | None = None
    effective_radius_mm: float | None = None


@dataclass(frozen=True)
class TouchSettings:
    """The active tool's PtMeasPar as the CMM has them (6.3.7, read back after SetProp: a server clamps)."""

    approach_mm: float
    search_mm: float
    retract_mm: float


class SphereMeasurementError(CmmDriverError):
    """Too few good points, or the fitted sphere fails its checks; carries every probe made."""

    def __init__(self, message: str, probes: tuple[ProbeRecord, ...] = ()) -> None:
        super().__init__(message)
        self.probes = probes


class PoseMeasurementError(CmmDriverError):
    """The measured sphere centres do not match the robot's sphere layout."""


class ProbeStatus(StrEnum):
    USED = "used"
    OUTLIER = "outlier"
    MISS = "miss"


@dataclass(frozen=True)
class ProbeRecord:
    """One touch as made: where the stylus ball's centre was expected to touch, the approach direction, the ball
    centre the CMM reported (PtMeas reports the ball centre, 6.3.2.13; None on a miss) and its fate."""

    target_mm: np.ndarray
    ijk: np.ndarray
    point_mm: np.ndarray | None
    status: ProbeStatus
    residual_mm: float | None = None
    """Radial residual against the final fit (None for a miss)."""
    detail: str = ""
    effective_radius_mm: float | None = None
    """ER() of the touch where the CMM reports it (6.3.2.25): ``point_mm`` is then the centre of a ball of the
    tool's AvrRadius touching the same surface point."""


@dataclass(frozen=True)
class SphereSearch:
    """A search for a sphere that was not where predicted closely enough to probe: its region and touches."""

    predicted_mm: np.ndarray
    """The predicted centre the search started around."""
    bound_mm: float
    """How far from the prediction the sphere could be (the widest stage searched)."""
    touches: int
    """Descents made (touches and misses)."""
    found_mm: np.ndarray
    """The centre the search found, from the touched cap."""

    @property
    def offset_mm(self) -> float:
        """How far from its prediction the sphere was found."""
        return float(np.linalg.norm(self.found_mm - self.predicted_mm))


@dataclass(frozen=True)
class SphereMeasurement:
    """A measured tooling sphere: fixed-radius centre, its residuals, the free-radius check and every probe.

    The points are stylus-ball centres: they lie on a sphere of radius ``radius_mm + stylus_radius_mm`` around the
    tooling sphere's centre, the radius both fits work with."""

    centre_mm: np.ndarray
    radius_mm: float
    """The tooling sphere's nominal radius."""
    fit: SphereFit
    """Fixed-radius fit (radius_mm + stylus_radius_mm) over the used ball centres."""
    free_fit: SphereFit
    """Free-radius fit over the same points (a check on the radius and on the probing)."""
    probes: tuple[ProbeRecord, ...]
    """Every touch in order, including rejected outliers and misses."""
    nominal_centre_mm: np.ndarray
    """The predicted centre the probe pattern was laid out around."""
    superseded: SphereMeasurement | None = None
    """A first pass that was far from its prediction and was measured again around its fitted centre."""
    search: SphereSearch | None = None
    """How the sphere was found when it was not looked for where predicted (None: probed where predicted)."""
    stylus_radius_mm: float = 0.0
    """The stylus ball's radius the CMM stated (Tool.AvrRadius(), 6.3.13)."""

    @property
    def points_mm(self) -> np.ndarray:
        """(N, 3) points used in the fit."""
        return np.array([p.point_mm for p in self.probes if p.status is ProbeStatus.USED])

    @property
    def residuals_mm(self) -> np.ndarray:
        """(N,) radial residuals of the used points."""
        return self.fit.residuals_mm

    @property
    def rms_mm(self) -> float:
        return self.fit.rms_mm

    @property
    def radius_free_mm(self) -> float:
        """The tooling sphere's radius by the free fit: the ball centres' radius less the stylus radius."""
        return self.free_fit.radius_mm - self.stylus_radius_mm

    @property
    def rejected(self) -> tuple[ProbeRecord, ...]:
        """Outliers and misses: made, recorded, never used."""
        return tuple(p for p in self.probes if p.status is not ProbeStatus.USED)

    @property
    def offset_from_nominal_mm(self) -> float:
        return float(np.linalg.norm(self.centre_mm - self.nominal_centre_mm))


@dataclass(frozen=True)
class BaseMeasurement:
    """The base spheres measured alone and registered on the robot's base layout (``hilcal check``)."""

    spheres: tuple[SphereMeasurement, ...]
    refined_alignment: np.ndarray
    """(4, 4) T_cmm<-base registered on the measured spheres."""
    registration_rms_mm: float
    """RMS of the registration's residuals: how well the measured centres match the robot file's layout."""


@dataclass(frozen=True)
class PoseMeasurement:
    """A platform pose measured from the base and platform spheres, with everything behind it."""

    pose: np.ndarray
    """(6,) platform pose in the base frame [x, y, z mm, roll, pitch, yaw deg]."""
    pose_fit: PoseFit
    platform: tuple[SphereMeasurement, ...]
    base: tuple[SphereMeasurement, ...]
    alignment: np.ndarray
    """(4, 4) approximate T_cmm<-base given to the measurement."""
    refined_alignment: np.ndarray
    """(4, 4) T_cmm<-base registered on the measured base spheres."""
    expected_pose: np.ndarray
    """(6,) pose used to predict where the platform spheres are."""
    extra: dict = field(default_factory=dict)


DEFAULT_ALIGNMENT_MM, DEFAULT_ALIGNMENT_DEG = 10.0, 0.2
"""How far a station's approximate alignment may be off when nothing says better (a bound): the first pose's base
spheres are searched for within it."""


class ProbingConfig(BaseModel):
    """How spheres are probed and judged (transport-independent)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    n_ring: int = Field(default=6, ge=3, le=16, description="touches around the sphere, besides the pole")
    elevations_deg: tuple[float, ...] = Field(default=(30.0,), min_length=1)
    clearance_mm: float = Field(default=20.0, gt=0, description="GoTo this far above the pole before probing")
    probe_sigma_mm: float = Field(default=0.002, ge=0, description="expected probing noise per coordinate")
    outlier_k_sigma: float = Field(default=5.0, gt=0)
    outlier_floor_mm: float = Field(default=0.005, ge=0)
    max_reprobes: int = Field(default=4, ge=0, description="extra touches per sphere for misses and outliers")
    min_points: int = Field(default=MIN_POINTS_FREE_RADIUS, ge=MIN_POINTS_FREE_RADIUS)
    radius_tol_mm: float = Field(default=0.05, gt=0, description="max |free-fit radius - nominal radius|")
    prediction_tol_mm: float = Field(default=2.0, gt=0, description="re-measure a sphere this far from prediction")
    registration_tol_mm: float = Field(default=0.05, gt=0, description="max RMS of the sphere-layout registrations")
    min_search_mm: float = Field(default=5.0, gt=0, description="least search distance of a touch: the stylus ball "
                                 "starts this far out from where it would touch the predicted sphere and searches as "
                                 "far beyond it")
    search_margin_mm: float = Field(default=1.0, gt=0, description="a touch starts this far beyond where the sphere's "
                                    "surface could be")
    route_margin_mm: float = Field(default=0.5, gt=0, description="positioning moves keep this far outside the region "
                                   "a sphere could be in")
    search_fraction: float = Field(default=0.4, gt=0, le=1.0, description="a sphere whose prediction is uncertain by "
                                   "more than this fraction of its radius is searched for before it is probed")
    max_search_mm: float = Field(default=90.0, gt=0, le=90.0, description="the widest search around a prediction: "
                                 "a sphere not found within it stops the measurement")
    default_bound_mm: float = Field(default=2.0, gt=0, description="how far a sphere may be from where it is asked for "
                                    "when the caller gives no uncertainty")
    least_bound_mm: float = Field(default=0.3, gt=0, description="the least bound of a prediction from a model")

    @property
    def outlier_threshold_mm(self) -> float:
        return outlier_threshold_mm(self.probe_sigma_mm, self.outlier_k_sigma, self.outlier_floor_mm)


def transform_from_pose(pose: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform of a pose [x, y, z mm, roll, pitch, yaw deg]."""
    p = np.asarray(pose, dtype=float)
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(np.radians(p[3:6]))
    T[:3, 3] = p[:3]
    return T


def as_transform(alignment: np.ndarray) -> np.ndarray:
    """A 4x4 T_cmm<-base from a 4x4 matrix or a (6,) pose of the base frame in the CMM frame."""
    a = np.asarray(alignment, dtype=float)
    if a.shape == (6,):
        return transform_from_pose(a)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise ValueError(f"alignment must be a finite 4x4 transform or a (6,) pose, got shape {a.shape}")
    R = a[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("alignment rotation is not a proper rotation matrix")
    return a.copy()


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., 3) through a 4x4 transform."""
    return np.asarray(points, dtype=float) @ T[:3, :3].T + T[:3, 3]

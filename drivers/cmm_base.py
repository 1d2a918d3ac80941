"""The CMM interface: one small abstract transport API plus the transport-independent probing strategy.

Like python-can's ``BusABC``: a transport module (``drivers.cmm_serial``) implements the primitive
commands (session, homing, GoTo, one touch); the sphere and pose measurements built on them live here.
All coordinates are in the CMM frame, mm; poses are [x, y, z mm, roll, pitch, yaw deg],
R = Rz(yaw) Ry(pitch) Rx(roll).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from enum import StrEnum
from types import TracebackType

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from hilcal.pose_measurement import PoseFit, pose_from_spheres, rigid_fit
from hilcal.robot import Robot, rotation_matrix
from hilcal.sphere_fit import (
    MIN_POINTS_FREE_RADIUS,
    SphereFit,
    SphereFitError,
    fit_sphere,
    fit_sphere_robust,
    outlier_threshold_mm,
    sphere_probe_pattern,
)

log = structlog.get_logger(__name__)


class CmmDriverError(Exception):
    """Base class of every CMM driver error."""


class CmmConnectionError(CmmDriverError):
    """The port cannot be opened, or the connection was lost."""


class CmmTimeout(CmmDriverError):
    """No complete response within the timeout, after the bounded retries."""


class CmmProtocolError(CmmDriverError):
    """A response that breaks the protocol (malformed line for our tag, a response with a wrong tag...)."""


class CmmError(CmmDriverError):
    """An error reported by the CMM: ``! Error(severity, code, "method", "text")``."""

    def __init__(self, code: int, text: str, severity: int = 3, method: str = "") -> None:
        super().__init__(f"CMM error {code:04d} (severity {severity}) in {method or '?'}: {text}")
        self.code = code
        self.text = text
        self.severity = severity
        self.method = method


class ProbeMiss(CmmError):
    """PtMeas touched no surface within the search distance."""


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
    """One touch as made: target, approach direction, the returned point (None on a miss) and its fate."""

    target_mm: np.ndarray
    ijk: np.ndarray
    point_mm: np.ndarray | None
    status: ProbeStatus
    residual_mm: float | None = None
    """Radial residual against the final fit (None for a miss)."""
    detail: str = ""


@dataclass(frozen=True)
class SphereMeasurement:
    """A measured tooling sphere: fixed-radius centre, its residuals, the free-radius check and every probe."""

    centre_mm: np.ndarray
    radius_mm: float
    """Nominal radius the centre was fitted with."""
    fit: SphereFit
    """Fixed-radius fit over the used points."""
    free_fit: SphereFit
    """Free-radius fit over the same points (a check on the radius and on the probing)."""
    probes: tuple[ProbeRecord, ...]
    """Every touch in order, including rejected outliers and misses."""
    nominal_centre_mm: np.ndarray
    """The predicted centre the probe pattern was laid out around."""
    superseded: SphereMeasurement | None = None
    """A first pass that was far from its prediction and was measured again around its fitted centre."""

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
        return self.free_fit.radius_mm

    @property
    def rejected(self) -> tuple[ProbeRecord, ...]:
        """Outliers and misses: made, recorded, never used."""
        return tuple(p for p in self.probes if p.status is not ProbeStatus.USED)

    @property
    def offset_from_nominal_mm(self) -> float:
        return float(np.linalg.norm(self.centre_mm - self.nominal_centre_mm))


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


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=float) @ T[:3, :3].T + T[:3, 3]


class CmmInterface(abc.ABC):
    """A coordinate measuring machine. Subclasses implement the transport primitives; not thread-safe."""

    probing: ProbingConfig = ProbingConfig()

    # ------------------------------------------------------------------ transport primitives

    @abc.abstractmethod
    def start_session(self) -> None:
        """Open a measurement session (and apply the session settings, e.g. the search distance)."""

    @abc.abstractmethod
    def end_session(self) -> None:
        """Close the measurement session."""

    @abc.abstractmethod
    def home(self) -> None:
        """Reference the machine axes."""

    @abc.abstractmethod
    def clear_errors(self) -> None:
        """Leave the error state entered after a failed motion (a probe miss, a collision)."""

    @abc.abstractmethod
    def goto(self, point_mm: np.ndarray) -> None:
        """Move the probe to a point without touching."""

    @abc.abstractmethod
    def probe(self, point_mm: np.ndarray, ijk: np.ndarray) -> np.ndarray:
        """Touch the surface near ``point_mm`` approaching along -ijk; the touched point (3,). ProbeMiss if none."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the transport."""

    def __enter__(self) -> CmmInterface:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ measurements

    def _touch(self, target: np.ndarray, ijk: np.ndarray, records: list[ProbeRecord]) -> int | None:
        """One touch, recorded; returns its record index, or None on a miss (recorded, error state cleared)."""
        try:
            point = self.probe(target, ijk)
        except ProbeMiss as miss:
            log.warning("cmm.probe_miss", target_mm=target.tolist(), ijk=ijk.tolist(), code=miss.code)
            records.append(ProbeRecord(target, ijk, None, ProbeStatus.MISS, None, miss.text))
            self.clear_errors()
            return None
        records.append(ProbeRecord(target, ijk, point, ProbeStatus.USED))
        return len(records) - 1

    def measure_sphere(
        self,
        nominal_centre_mm: np.ndarray,
        radius_mm: float,
        up: np.ndarray = (0.0, 0.0, 1.0),
        prediction_tol_mm: float | None = None,
    ) -> SphereMeasurement:
        """Probe a sphere (pole + ring, approaching along the normals of the nominal sphere) and fit its centre.

        Misses and outliers (|residual| > the probing config's threshold) are recorded, never used, and their
        targets touched again within ``max_reprobes``. With fewer than ``min_points`` good points, or a
        free-fit radius off by more than ``radius_tol_mm``, raises SphereMeasurementError. A centre more than
        ``prediction_tol_mm`` (default: the probing config's) from the nominal one is measured once more
        around the fitted centre; the first pass is kept as ``superseded``.
        """
        first = self._measure_sphere_once(np.asarray(nominal_centre_mm, dtype=float), radius_mm, up)
        tol = self.probing.prediction_tol_mm if prediction_tol_mm is None else prediction_tol_mm
        if first.offset_from_nominal_mm <= tol:
            return first
        log.info(
            "cmm.sphere_remeasure",
            nominal_mm=first.nominal_centre_mm.tolist(),
            fitted_mm=first.centre_mm.tolist(),
            offset_mm=first.offset_from_nominal_mm,
        )
        second = self._measure_sphere_once(first.centre_mm, radius_mm, up)
        return SphereMeasurement(
            centre_mm=second.centre_mm,
            radius_mm=second.radius_mm,
            fit=second.fit,
            free_fit=second.free_fit,
            probes=second.probes,
            nominal_centre_mm=second.nominal_centre_mm,
            superseded=first,
        )

    def _reprobe(self, indices: list[int], targets: np.ndarray, normals: np.ndarray, records: list,
                 good: list[tuple[int, int]], budget: int) -> int:
        """Touch the pattern points `indices` again while the re-probe budget lasts; returns what is left."""
        for k in indices:
            if budget == 0:
                break
            budget -= 1
            idx = self._touch(targets[k], normals[k], records)
            if idx is not None:
                good.append((k, idx))
        return budget

    def _measure_sphere_once(self, centre: np.ndarray, radius_mm: float, up: np.ndarray) -> SphereMeasurement:
        """One pass of the probe pattern around ``centre`` with miss and outlier handling."""
        cfg = self.probing
        targets, normals = sphere_probe_pattern(centre, radius_mm, up, cfg.n_ring, cfg.elevations_deg)
        self.goto(centre + (radius_mm + cfg.clearance_mm) * normals[0])
        records: list[ProbeRecord] = []
        good: list[tuple[int, int]] = []  # (pattern index, record index) of the touches in use, in touch order
        missed: list[int] = []
        for k in range(len(targets)):
            idx = self._touch(targets[k], normals[k], records)
            if idx is None:
                missed.append(k)
            else:
                good.append((k, idx))
        budget = self._reprobe(missed, targets, normals, records, good, cfg.max_reprobes)
        threshold = cfg.outlier_threshold_mm
        while True:
            if len(good) < cfg.min_points:
                raise SphereMeasurementError(
                    f"sphere near {np.round(centre, 3).tolist()} mm: only {len(good)} good points "
                    f"(need {cfg.min_points}) after {len(records)} touches",
                    tuple(records),
                )
            pts = np.array([records[i].point_mm for _, i in good])
            try:
                robust = fit_sphere_robust(pts, radius_mm, threshold, centre)
            except SphereFitError as err:
                raise SphereMeasurementError(f"sphere near {centre.tolist()} mm: {err}", tuple(records)) from err
            for j in robust.outliers:
                self._mark_outlier(records, good[j][1], float(robust.residuals_mm[j]))
            if robust.inliers.all():
                break
            retry = [good[j][0] for j in robust.outliers]
            good = [good[j] for j in np.flatnonzero(robust.inliers)]
            if budget == 0:
                break
            budget = self._reprobe(retry, targets, normals, records, good, budget)
        used = np.array([records[i].point_mm for _, i in good])
        if len(used) < cfg.min_points:
            raise SphereMeasurementError(
                f"sphere near {np.round(centre, 3).tolist()} mm: only {len(used)} consistent points "
                f"(need {cfg.min_points}; outlier threshold {threshold:.4f} mm) after {len(records)} touches",
                self._finalise_records(records, robust.fit.centre_mm, radius_mm),
            )
        fit = robust.fit  # the fixed-radius fit over exactly the used points, in the same order
        final = self._finalise_records(records, fit.centre_mm, radius_mm)
        try:
            free = fit_sphere(used, None, fit.centre_mm)
        except SphereFitError as err:
            raise SphereMeasurementError(f"sphere near {centre.tolist()} mm: radius check: {err}", final) from err
        radius_sd_mm = free.radius_sd_unit * max(cfg.probe_sigma_mm, fit.sigma_hat_mm)
        if not radius_sd_mm <= cfg.radius_tol_mm / 3.0:
            raise SphereMeasurementError(
                f"sphere near {np.round(centre, 3).tolist()} mm: the used points determine the radius only to "
                f"{radius_sd_mm:.4f} mm, too poorly for the {cfg.radius_tol_mm} mm radius check",
                final,
            )
        if np.any(np.abs(fit.residuals_mm) > threshold):
            raise SphereMeasurementError(
                f"sphere near {np.round(centre, 3).tolist()} mm: residuals up to "
                f"{np.max(np.abs(fit.residuals_mm)):.4f} mm exceed the outlier threshold {threshold:.4f} mm "
                "with no touches left to reject",
                final,
            )
        if abs(free.radius_mm - radius_mm) > cfg.radius_tol_mm:
            raise SphereMeasurementError(
                f"sphere near {np.round(centre, 3).tolist()} mm: free-fit radius {free.radius_mm:.4f} mm differs "
                f"from the nominal {radius_mm} mm by more than {cfg.radius_tol_mm} mm",
                final,
            )
        log.debug(
            "cmm.sphere_measured",
            centre_mm=fit.centre_mm.tolist(),
            rms_mm=fit.rms_mm,
            radius_free_mm=free.radius_mm,
            touches=len(records),
            rejected=len(records) - len(used),
        )
        return SphereMeasurement(
            centre_mm=fit.centre_mm,
            radius_mm=radius_mm,
            fit=fit,
            free_fit=free,
            probes=final,
            nominal_centre_mm=centre,
        )

    @staticmethod
    def _mark_outlier(records: list[ProbeRecord], index: int, residual_mm: float) -> None:
        rec = records[index]
        log.warning("cmm.probe_outlier", point_mm=rec.point_mm.tolist(), residual_mm=residual_mm)
        records[index] = ProbeRecord(
            rec.target_mm, rec.ijk, rec.point_mm, ProbeStatus.OUTLIER, residual_mm, "residual over threshold"
        )

    @staticmethod
    def _finalise_records(records: list[ProbeRecord], centre: np.ndarray, radius_mm: float) -> tuple[ProbeRecord, ...]:
        """Every record with its residual against the final centre."""
        out = []
        for rec in records:
            if rec.point_mm is None:
                out.append(rec)
                continue
            residual = float(np.linalg.norm(rec.point_mm - centre) - radius_mm)
            out.append(ProbeRecord(rec.target_mm, rec.ijk, rec.point_mm, rec.status, residual, rec.detail))
        return tuple(out)

    def _measure_group(self, predicted: np.ndarray, radius_mm: float, up: np.ndarray) -> tuple[SphereMeasurement, ...]:
        """Measure spheres in turn, shifting each prediction by the mean offset found on the ones before."""
        out: list[SphereMeasurement] = []
        offsets: list[np.ndarray] = []
        for raw in predicted:
            correction = np.mean(offsets, axis=0) if offsets else np.zeros(3)
            m = self.measure_sphere(raw + correction, radius_mm, up)
            out.append(m)
            offsets.append(m.centre_mm - raw)
        return tuple(out)

    def measure_pose(
        self, robot: Robot, alignment: np.ndarray, expected_pose: np.ndarray | None = None
    ) -> PoseMeasurement:
        """Measure the base spheres, then the platform spheres, and register both layouts to get the pose.

        ``alignment`` is an approximate T_cmm<-base (4x4, or the (6,) pose of the base frame in the CMM frame),
        good to a few mm; ``expected_pose`` (default: the robot's home) predicts the platform spheres. Each
        measured base sphere corrects the prediction of the next by the mean offset so far; the full base
        registration then refines the alignment before the platform spheres are predicted (and corrected the
        same way, sphere by sphere).
        """
        T0 = as_transform(alignment)
        expected = robot.home if expected_pose is None else np.asarray(expected_pose, dtype=float)
        r = robot.sphere_radius_mm
        base_up = T0[:3, 2]
        base = self._measure_group(_apply(T0, robot.base_spheres), r, base_up)
        base_centres = np.array([m.centre_mm for m in base])
        R_cb, t_cb, rms_b = rigid_fit(robot.base_spheres, base_centres)
        if rms_b > self.probing.registration_tol_mm:
            raise PoseMeasurementError(
                f"base spheres do not match the robot's base sphere layout: registration RMS {rms_b:.4f} mm "
                f"> {self.probing.registration_tol_mm} mm"
            )
        T_cb = np.eye(4)
        T_cb[:3, :3], T_cb[:3, 3] = R_cb, t_cb
        T_bp = transform_from_pose(expected)
        T_cp = T_cb @ T_bp
        platform = self._measure_group(_apply(T_cp, robot.platform_spheres), r, T_cp[:3, 2])
        fit = pose_from_spheres(np.array([m.centre_mm for m in platform]), base_centres, robot)
        if fit.platform_rms_mm > self.probing.registration_tol_mm:
            raise PoseMeasurementError(
                f"platform spheres do not match the robot's platform sphere layout: registration RMS "
                f"{float(fit.platform_rms_mm):.4f} mm > {self.probing.registration_tol_mm} mm"
            )
        log.info("cmm.pose_measured", pose=fit.pose.tolist(), rms_mm=fit.rms_residual_mm.tolist())
        return PoseMeasurement(
            pose=fit.pose,
            pose_fit=fit,
            platform=platform,
            base=base,
            alignment=T0,
            refined_alignment=T_cb,
            expected_pose=expected,
        )

"""Identification of geometric errors by least squares and by L-infinity (minimax) estimation.

Every estimator takes recorded leg lengths and measured poses and returns an IdentificationResult.
- Least squares: iterated = Levenberg–Marquardt (damped Gauss–Newton, MINPACK via scipy) on the
  nonlinear model with Jacobian-based column scaling; one_step = the paper's single linearized solve.
- L-infinity: the linear programme of the paper's eqs. 28–31 solved by HiGHS; one_step linearizes at
  the nominal geometry as the paper does, iterated runs sequential LPs with a trust region (step bound)
  on the nonlinear model until the maximum residual stops falling.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import structlog
from scipy.optimize import least_squares, linprog
from scipy.spatial.transform import Rotation

from hilcal.error_models import (
    GEOMETRIC_42,
    MODELS,
    forward_jacobian,
    implicit_jacobian,
    implicit_residuals,
    paper60_jacobian,
    pose_difference,
)
from hilcal.kinematics import Geometry, forward_kinematics, split_pose
from hilcal.misfit import Misfit, honest_covariance
from hilcal.robot import Robot
from hilcal.stations import StationFrames

log = structlog.get_logger(__name__)

Estimator = Literal["ls", "linf"]
Formulation = Literal["forward", "implicit"]
Method = Literal["iterated", "one_step"]


class IdentificationError(ValueError):
    """The data cannot support the requested identification (too few poses, bad shapes)."""


@dataclass(frozen=True)
class IdentificationResult:
    """Outcome of one identification; parameters in the model's units (mm, rad for the paper's du)."""

    x: np.ndarray
    names: tuple[str, ...]
    model: str
    estimator: str
    formulation: str
    method: str
    residuals: np.ndarray
    max_abs_residual: float
    rms_residual: float
    sigma: float | None
    std_errors: np.ndarray | None
    covariance: np.ndarray | None
    rank: int
    n_iterations: int
    converged: bool
    message: str
    length_mm: float
    station_frames: dict[int, np.ndarray] | None = None
    """Each fitted instrument station's rigid error [dt (mm); dw (rad)] about the workspace centre (None: one
    station, or none given); the first station's is zero by definition (``hilcal.stations``)."""
    misfit: Misfit | None = None
    """With the recording's noise (``identify(noise_covariance=...)``): whether the model is incomplete and what its
    misfit adds to the covariance (``hilcal.misfit``); None: the covariance is sigma^2 (J^T J)^+."""

    def parameters(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, self.x, strict=True)}

    def geometry(self, robot: Robot) -> Geometry:
        """The calibrated rigid geometry (42-parameter model only)."""
        if self.model != GEOMETRIC_42.key:
            raise IdentificationError("only the rigid 42-parameter model defines a calibrated geometry")
        return Geometry.nominal(robot).perturbed(self.x[: GEOMETRIC_42.size])


def _check_data(legs_mm: np.ndarray, poses: np.ndarray, n_params: int) -> tuple[np.ndarray, np.ndarray]:
    L = np.asarray(legs_mm, dtype=float)
    q = np.asarray(poses, dtype=float)
    if L.ndim != 2 or L.shape[1] != 6 or q.shape != L.shape:
        raise IdentificationError(f"expected legs and poses of shape (N, 6), got {L.shape} and {q.shape}")
    if not (np.isfinite(L).all() and np.isfinite(q).all()):
        raise IdentificationError("leg lengths and measured poses must be finite")
    if 6 * L.shape[0] <= n_params:
        raise IdentificationError(
            f"{L.shape[0]} poses give {6 * L.shape[0]} equations for {n_params} parameters: "
            f"need at least {n_params // 6 + 1} poses (more for a useful fit)"
        )
    return L, q


def residual_function(
    robot: Robot,
    legs_mm: np.ndarray,
    poses: np.ndarray,
    formulation: Formulation,
    length_mm: float,
    extra: np.ndarray | None = None,
    stations: np.ndarray | None = None,
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """r(x), dr/dx for the 42-parameter model, optionally with extra leg-length terms and instrument stations.

    `extra` [N, 6, q] holds regressors phi of effects that are linear in their parameters theta: the
    geometric leg length becomes reported + dl0 + phi @ theta, and x = [42 geometric errors, theta].
    `stations` (N,) labels each row's instrument station: every station but the first gets a rigid frame error,
    eliminated from r and J by projection (``hilcal.stations``), so the fit is the joint one (forward only).
    """
    nominal = Geometry.nominal(robot)
    n_geo = GEOMETRIC_42.size
    phi = np.zeros((*np.shape(legs_mm), 0)) if extra is None else np.asarray(extra, dtype=float)
    dl0_cols = [7 * i + 6 for i in range(6)]

    def corrected(x: np.ndarray) -> tuple[Geometry, np.ndarray]:
        return nominal.perturbed(x[:n_geo]), legs_mm + phi @ x[n_geo:]

    def forward(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        geom, lengths = corrected(x)
        predicted = forward_kinematics(geom, lengths, poses)
        r = pose_difference(poses, predicted, length_mm).reshape(-1)
        J = forward_jacobian(geom, predicted, length_mm)
        J_extra = J[..., dl0_cols] @ phi
        return r, -np.concatenate([J, J_extra], axis=-1).reshape(r.size, -1)

    def implicit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        geom, lengths = corrected(x)
        r = implicit_residuals(geom, lengths, poses).reshape(-1)
        return r, np.concatenate([implicit_jacobian(geom, poses), -phi], axis=-1).reshape(r.size, -1)

    frames = None if stations is None else StationFrames.of(stations, poses, length_mm, robot.home[:3])
    if formulation == "forward":
        if frames is None:
            return forward
        return lambda x: frames.project(*forward(x))  # type: ignore[return-value]
    if formulation == "implicit":
        if frames is not None:
            raise IdentificationError("instrument stations are fitted in the forward formulation only")
        return implicit
    raise IdentificationError(f"unknown formulation {formulation!r}: use 'forward' or 'implicit'")


def _paper60_linear(
    robot: Robot, legs_mm: np.ndarray, poses: np.ndarray, length_mm: float
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The paper's linear model: r(dp) = measured - nominal FK pose - J dp, J from eq. 23."""
    nominal = Geometry.nominal(robot)
    predicted = forward_kinematics(nominal, legs_mm, poses)
    r0 = pose_difference(poses, predicted, length_mm).reshape(-1)
    J = paper60_jacobian(nominal, predicted, length_mm).reshape(-1, 60)

    def linear(dp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return r0 - J @ dp, -J

    return linear


def _column_scale(J: np.ndarray) -> np.ndarray:
    """RMS effect of each parameter on the residuals; zero columns get scale 1."""
    c = np.sqrt(np.mean(J**2, axis=0))
    return np.where(c > 0, c, 1.0)


def _ls_statistics(
    r: np.ndarray, J: np.ndarray, eliminated: int = 0
) -> tuple[float, np.ndarray | None, np.ndarray | None, int]:
    """sigma^2 = sum r^2 / (m - rank - eliminated) and covariance sigma^2 (J^T J)^+ with column scaling;
    `eliminated`: parameters projected out of r and J beforehand (instrument stations)."""
    m = r.size - eliminated
    c = _column_scale(J)
    _U, s, Vt = np.linalg.svd(J / c, full_matrices=False)
    rank = int(np.sum(s > s[0] * 1e-10))
    dof = m - rank
    if dof <= 0:
        return float("nan"), None, None, rank
    sigma2 = float(r @ r) / dof
    inv = (Vt[:rank].T / s[:rank] ** 2) @ Vt[:rank]
    cov = sigma2 * inv / np.outer(c, c)
    std = np.sqrt(np.diag(cov))
    if rank < J.shape[1]:
        null = Vt[rank:]
        std = np.where(np.abs(null).max(axis=0) > 1e-6, np.nan, std)
    return float(np.sqrt(sigma2)), std, cov, rank


def _solve_minimax_lp(r0: np.ndarray, J: np.ndarray, bound: float | None) -> tuple[np.ndarray, float]:
    """min y s.t. |r0 + J d| <= y elementwise (eqs. 28–31), with optional |d_j * c_j| <= bound."""
    m, p = J.shape
    c = _column_scale(J)
    Js = J / c
    ones = np.ones((m, 1))
    A_ub = np.block([[Js, -ones], [-Js, -ones]])
    b_ub = np.concatenate([-r0, r0])
    cost = np.zeros(p + 1)
    cost[-1] = 1.0
    var_bounds = [(None, None) if bound is None else (-bound, bound)] * p + [(0, None)]
    res = linprog(cost, A_ub=A_ub, b_ub=b_ub, bounds=var_bounds, method="highs")
    if res.status != 0:
        raise IdentificationError(f"L-infinity linear programme failed: {res.message}")
    return res.x[:p] / c, float(res.x[-1])


def _identify_ls(fun: Callable, p: int, method: Method, max_nfev: int, x0: np.ndarray | None = None
                 ) -> tuple[np.ndarray, int, bool, str]:
    x0 = np.zeros(p) if x0 is None else np.asarray(x0, dtype=float)
    if method == "one_step":
        r0, J = fun(x0)
        c = _column_scale(J)
        d = np.linalg.lstsq(J / c, -r0, rcond=1e-10)[0] / c
        return d, 1, True, "single linearized least-squares step at the nominal geometry"
    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = fun(x)
        return cache[key]

    sol = least_squares(
        lambda x: evaluate(x)[0], x0, jac=lambda x: evaluate(x)[1], method="lm", x_scale="jac",
        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=max_nfev,
    )
    return sol.x, int(sol.nfev), bool(sol.status > 0), str(sol.message)


def _identify_linf(
    fun: Callable, p: int, method: Method, max_iter: int, tol: float
) -> tuple[np.ndarray, int, bool, str]:
    x = np.zeros(p)
    r, J = fun(x)
    if method == "one_step":
        d, _ = _solve_minimax_lp(r, J, None)
        return d, 1, True, "single linearized L-infinity LP at the nominal geometry"
    f = float(np.max(np.abs(r)))
    radius = max(f, 1e-3)
    for it in range(1, max_iter + 1):
        d, predicted = _solve_minimax_lp(r, J, radius)
        predicted_gain = f - predicted
        if predicted_gain <= tol * max(f, 1e-9):
            return x, it, True, f"sequential LP converged: predicted gain {predicted_gain:.3g} mm"
        r_new, J_new = fun(x + d)
        f_new = float(np.max(np.abs(r_new)))
        ratio = (f - f_new) / predicted_gain
        if ratio > 0.1:
            x, r, J, f = x + d, r_new, J_new, f_new
            if ratio > 0.75:
                radius *= 2.0
        else:
            radius *= 0.25
        log.debug("slp_step", iteration=it, max_residual_mm=f, ratio=ratio, radius=radius)
        if radius < 1e-12:
            return x, it, True, "sequential LP converged: trust region collapsed at a minimax point"
    return x, max_iter, False, f"sequential LP stopped after {max_iter} iterations"


def identify(
    robot: Robot,
    legs_mm: np.ndarray,
    poses: np.ndarray,
    *,
    estimator: Estimator = "ls",
    model: str = "42",
    formulation: Formulation = "forward",
    method: Method = "iterated",
    length_mm: float | None = None,
    max_iter: int = 100,
    tol: float = 1e-9,
    extra_regressors: np.ndarray | None = None,
    extra_names: tuple[str, ...] = (),
    x0: np.ndarray | None = None,
    stations: np.ndarray | None = None,
    noise_covariance: np.ndarray | None = None,
    noise_dof: float | None = None,
    sessions: np.ndarray | None = None,
) -> IdentificationResult:
    """Identify geometric errors from reported leg lengths and measured poses (mm, deg).

    `length_mm` converts rotation residuals (rad) to mm; default: the platform's characteristic
    length. The paper's 60-parameter model is linear, so it supports the forward one-step method only.
    `extra_regressors` [N, 6, q] adds effects linear in their parameters (named by `extra_names`) to the
    rigid model: geometric length = reported + dl0 + phi @ theta. `x0` starts the iterated least squares there
    (e.g. a previous fit) instead of at the nominal geometry. `stations` (N,) labels each pose's instrument station:
    every station but the first gets its rigid frame error fitted with the rest (``hilcal.stations``; least squares,
    forward formulation). `noise_covariance` (N, 6, 6): the measured pose noise of every row (residual metric, with
    `noise_dof` its degrees of freedom, None when stated; `sessions` (N,) the rows' sessions): the least-squares
    covariance is then the noise's and, when the residual exceeds it, the model's misfit's (``hilcal.misfit``; forward
    42-parameter model).
    """
    if model not in MODELS:
        raise IdentificationError(f"unknown model {model!r}: use one of {sorted(MODELS)}")
    if estimator not in ("ls", "linf"):
        raise IdentificationError(f"unknown estimator {estimator!r}: use 'ls' or 'linf'")
    if method not in ("iterated", "one_step"):
        raise IdentificationError(f"unknown method {method!r}: use 'iterated' or 'one_step'")
    spec = MODELS[model]
    names = spec.names
    if extra_regressors is not None:
        if model != GEOMETRIC_42.key:
            raise IdentificationError("extra effects can only be added to the rigid 42-parameter model")
        if np.shape(extra_regressors)[:2] != np.shape(legs_mm) or len(extra_names) != np.shape(extra_regressors)[2]:
            raise IdentificationError("extra_regressors must be [N, 6, q] with q names")
        names = names + tuple(extra_names)
    frames = None if stations is None else StationFrames.of(stations, np.asarray(poses, dtype=float), 1.0,
                                                              robot.home[:3])
    if frames is not None and (estimator != "ls" or model != GEOMETRIC_42.key):
        raise IdentificationError("instrument stations are fitted by least squares on the 42-parameter model only")
    L, q = _check_data(legs_mm, poses, len(names) + (0 if frames is None else frames.n_params))
    lc = robot.characteristic_length_mm if length_mm is None else float(length_mm)
    if model == "60":
        if formulation != "forward" or method != "one_step":
            raise IdentificationError("the paper's 60-parameter model is linear: use formulation=forward, "
                                      "method=one_step")
        fun = _paper60_linear(robot, L, q, lc)
    else:
        fun = residual_function(robot, L, q, formulation, lc, extra_regressors, stations)
    if estimator == "ls":
        if x0 is not None and np.shape(x0) != (len(names),):
            raise IdentificationError(f"x0 must have {len(names)} values, got {np.shape(x0)}")
        x, nit, converged, message = _identify_ls(fun, len(names), method, max_nfev=max_iter, x0=x0)
    else:
        x, nit, converged, message = _identify_linf(fun, len(names), method, max_iter, tol)
    r, J = fun(x)
    sigma, std, cov, rank = _ls_statistics(r, J, 0 if frames is None else frames.n_params)
    misfit = None
    if noise_covariance is not None and estimator == "ls" and model == GEOMETRIC_42.key and formulation == "forward" \
            and cov is not None:
        raw = J if frames is None else residual_function(robot, L, q, formulation, lc, extra_regressors)(x)[1]
        honest, misfit = honest_covariance(
            J, r, noise_covariance, raw.reshape(len(L), 6, -1)[:, :, [7 * i + 6 for i in range(6)]], L, sessions,
            frames=None if frames is None else StationFrames.of(stations, q, lc, robot.home[:3]), noise_dof=noise_dof)
        std = np.where(np.isnan(std), np.nan, np.sqrt(np.clip(np.diag(honest), 0.0, None)))
        cov = honest
    station_frames = None
    if frames is not None:
        raw = residual_function(robot, L, q, formulation, lc, extra_regressors)(x)[0]
        station_frames = frames.estimate(raw)
    if estimator != "ls":
        sigma, std, cov = None, None, None
    result = IdentificationResult(
        x=x, names=names, model=model, estimator=estimator, formulation=formulation, method=method,
        residuals=r.reshape(-1, 6), max_abs_residual=float(np.max(np.abs(r))),
        rms_residual=float(np.sqrt(np.mean(r**2))), sigma=sigma, std_errors=std, covariance=cov,
        rank=rank, n_iterations=nit, converged=converged, message=message, length_mm=lc,
        station_frames=station_frames, misfit=misfit,
    )
    log.info("identified", model=model, estimator=estimator, formulation=formulation, method=method,
             n_poses=L.shape[0], max_residual_mm=result.max_abs_residual, rms_residual_mm=result.rms_residual,
             iterations=nit, converged=converged)
    return result


def predict_poses(result: IdentificationResult, robot: Robot, legs_mm: np.ndarray, guess: np.ndarray) -> np.ndarray:
    """Poses (mm, deg) that the calibrated model predicts from reported leg lengths."""
    if result.model == GEOMETRIC_42.key:
        return forward_kinematics(result.geometry(robot), legs_mm, guess)
    nominal = Geometry.nominal(robot)
    base = forward_kinematics(nominal, legs_mm, guess)
    delta = paper60_jacobian(nominal, base, result.length_mm) @ result.x
    return _compose_small(base, delta, result.length_mm)


def _compose_small(poses: np.ndarray, delta: np.ndarray, length_mm: float) -> np.ndarray:
    """Apply a small pose error [dt (mm), length*dw] in the base frame to poses (mm, deg)."""
    R, t = split_pose(poses)
    dR = Rotation.from_rotvec(delta[..., 3:] / length_mm).as_matrix()
    out = np.empty_like(poses)
    out[..., :3] = t + delta[..., :3]
    ypr = Rotation.from_matrix(dR @ R).as_euler("ZYX", degrees=True)
    out[..., 3], out[..., 4], out[..., 5] = ypr[..., 2], ypr[..., 1], ypr[..., 0]
    return out

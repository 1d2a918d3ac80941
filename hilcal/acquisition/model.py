"""What the run believes about the machine while it measures it: a refit after every pose, held to priors.

The controller commands leg readings through its own geometry (a, b, l0). The machine as it is differs by joint
errors, leg-offset errors and gross reading-scale faults (a transducer gradient set wrong). Per leg the model has
eight parameters relative to the controller's geometry, [da (3, platform frame), db (3, base frame), dl0, k], and the
true joint-to-joint length is

    L_i = reading_i + dl0_i + k_i (reading_i - l0_i)

(k_i: physical mm per read mm, minus one; a transducer whose gradient reads g too long has k = 1/(1 + g) - 1).
A Gaussian prior (the robot file's ``[tolerances]``) holds the 48 parameters. Every measured pose refits the maximum
a posteriori estimate on the leg-length residuals at all measured poses (Gauss-Newton on data and prior together, so
no direction the poses cannot see is left unbounded) with its covariance; the prediction of the next pose carries
that covariance and the misfit the model shows (physics it leaves out) into a pose covariance.

The bound must hold from the first poses on, while 48 parameters can still fit every measured pose exactly: the
residuals then show nothing, whatever the model lacks (a drive's compliance) or however far beyond the priors the
machine is (a gradient set 6 % wrong). So the misfit is also what makes each measured pose, left out, predicted as
well as the fit says (``predictive_misfit_mm``), and every prediction is widened by how the measured poses fell
against the predictions made before them (``MachineBelief.calibration``): a bound that grows with the evidence
that the model does not explain the machine.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import gammaincinv

from hilcal.kinematics import Geometry, forward_kinematics, inverse_jacobian, leg_vectors, split_pose
from hilcal.robot import Robot

N_LEGS = 6
PER_LEG = 8
N_PARAMS = N_LEGS * PER_LEG
MAX_ITERATIONS = 12
STEP_TOL = 1e-9
MAX_REWEIGHTS = 8
"""Refits with the misfit estimated again (until it changes by less than 5 %), at most."""
PREDICTED_BY_DATA = 0.25
"""A pose left out counts for the predictive misfit when the others predict it this much better than the priors alone
(variance: twice as well in standard deviation); one the priors mostly predict says how far the machine is from
them, which the calibration takes up, not what the model leaves out."""


@dataclass(frozen=True)
class Priors:
    """Standard deviations of the machine's errors before anything is measured, and the misfit floor."""

    joint_mm: float = 2.0
    leg_offset_mm: float = 3.0
    reading_scale: float = 0.02
    """k, the reading's gradient error as a fraction (0.02 = 2 %)."""
    misfit_mm: float = 0.02
    """The least leg-length misfit assumed: transducer resolution, the physics a rigid model leaves out."""

    @classmethod
    def of(cls, robot: Robot) -> Priors:
        """The robot file's ``[tolerances]`` (its defaults when the file has none)."""
        t = robot.tolerances
        return cls(t.joint_mm, t.leg_offset_mm, t.reading_scale_pct / 100.0, t.misfit_mm)

    def sigmas(self) -> np.ndarray:
        """(48,) prior standard deviation per parameter, in the model's order."""
        leg = [self.joint_mm] * 6 + [self.leg_offset_mm, self.reading_scale]
        return np.tile(np.asarray(leg, dtype=float), N_LEGS)

    def tightened(self, factor: float) -> Priors:
        """The priors divided by `factor` (a machine just calibrated is known far better than a new one)."""
        return Priors(self.joint_mm / factor, self.leg_offset_mm / factor, self.reading_scale / factor,
                      self.misfit_mm)


@dataclass(frozen=True)
class PosePrediction:
    """The pose the model expects for some leg readings and its covariance."""

    pose: np.ndarray
    """(6,) [x, y, z mm, roll, pitch, yaw deg] of the platform in the base frame."""
    cov: np.ndarray
    """(6, 6) covariance of [dt (mm); dw (rad)], dw the small rotation about the platform origin in base axes."""

    @property
    def position_sd_mm(self) -> float:
        """The largest standard deviation of the platform origin's position, mm."""
        return float(np.sqrt(np.max(np.linalg.eigvalsh(self.cov[:3, :3]))))


@dataclass(frozen=True)
class MachineBelief:
    """The acquisition model after some measured poses (see the module docstring); build with `prior_belief`."""

    a: np.ndarray
    b: np.ndarray
    l0: np.ndarray
    """The controller's geometry the readings are commanded through: (6, 3), (6, 3), (6,) mm."""
    priors: Priors
    x: np.ndarray
    """(48,) the estimate, per leg [da_x, da_y, da_z, db_x, db_y, db_z (mm), dl0 (mm), k]."""
    cov: np.ndarray
    """(48, 48) its covariance."""
    legs_mm: np.ndarray
    """(N, 6) readings of the measured poses."""
    poses: np.ndarray
    """(N, 6) measured poses."""
    misfit_mm: float
    """Leg-length misfit per residual: the floor, or what the fit's residuals, or the poses left out of it
    (``predictive_misfit_mm``), show beyond it."""
    residual_rms_mm: float
    """RMS of the leg-length residuals at the measured poses (0 before any pose)."""
    surprises: tuple[float, ...] = ()
    """Per measured pose, how far it lay from the prediction of the belief before it: its leg-length residual
    normalised by that prediction's covariance (chi-square with six degrees of freedom when the predictions are
    honest)."""

    def calibration(self) -> float:
        """The factor on the predictions' standard deviations that makes the surprises so far what honest predictions
        give: on average 6, and the largest of N no larger than the median of the largest of N chi-square(6) draws
        (at least 1)."""
        if not self.surprises:
            return 1.0
        q = np.asarray(self.surprises)
        return float(np.sqrt(max(1.0, float(np.mean(q)) / N_LEGS, float(np.max(q)) / _largest_of(q.size))))

    @property
    def n_poses(self) -> int:
        return len(self.poses)

    def per_leg(self) -> np.ndarray:
        """(6, 8) the estimate per leg."""
        return self.x.reshape(N_LEGS, PER_LEG)

    def geometry(self, legs_mm: np.ndarray) -> Geometry:
        """The kinematic geometry of the estimate for these readings (the reading scale folded into dl0)."""
        p = self.per_leg()
        stroke = np.asarray(legs_mm, dtype=float) - self.l0
        return Geometry(self.a + p[:, 0:3], self.b + p[:, 3:6], p[:, 6] + p[:, 7] * stroke)

    def reading_gain(self) -> np.ndarray:
        """(6,) how much too long each transducer reads its stroke (g = 1/(1 + k) - 1; 0.06 = 6 % long)."""
        return 1.0 / (1.0 + self.per_leg()[:, 7]) - 1.0

    def physical_lengths_mm(self, legs_mm: np.ndarray) -> np.ndarray:
        """(..., 6) the legs' lengths on the controller's scale (l0 + stroke) once the reading scale is undone: what
        the travel limits apply to."""
        legs = np.asarray(legs_mm, dtype=float)
        return self.l0 + (legs - self.l0) * (1.0 + self.per_leg()[:, 7])


def prior_belief(a_mm: np.ndarray, b_mm: np.ndarray, l0_mm: np.ndarray, priors: Priors) -> MachineBelief:
    """The belief before any pose: the controller's geometry with the priors' covariance."""
    sig = priors.sigmas()
    return MachineBelief(np.asarray(a_mm, dtype=float), np.asarray(b_mm, dtype=float),
                         np.asarray(l0_mm, dtype=float), priors, np.zeros(N_PARAMS), np.diag(sig**2),
                         np.zeros((0, N_LEGS)), np.zeros((0, 6)), priors.misfit_mm, 0.0)


def _residuals(belief: MachineBelief, x: np.ndarray, legs: np.ndarray, poses: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Leg-length residuals (N*6,) at the measured poses and their Jacobian (N*6, 48)."""
    p = x.reshape(N_LEGS, PER_LEG)
    stroke = legs - belief.l0
    geom = Geometry(belief.a + p[:, 0:3], belief.b + p[:, 3:6], np.zeros(N_LEGS))
    R, t = split_pose(poses)
    _, length, u = leg_vectors(geom, R, t)
    r = length - (legs + p[:, 6] + p[:, 7] * stroke)
    return r.reshape(-1), _constraint_rows(u, R, stroke).reshape(-1, N_PARAMS)


def _constraint_rows(u: np.ndarray, R: np.ndarray, stroke: np.ndarray) -> np.ndarray:
    """d(geometric minus true length)/d(parameters) [..., 6, 48]: per leg [u^T R, -u^T, -1, -stroke]."""
    G = np.zeros((*u.shape[:-2], N_LEGS, N_PARAMS))
    uR = np.einsum("...ij,...jk->...ik", u, R)
    for i in range(N_LEGS):
        c = PER_LEG * i
        G[..., i, c:c + 3] = uR[..., i, :]
        G[..., i, c + 3:c + 6] = -u[..., i, :]
        G[..., i, c + 6] = -1.0
        G[..., i, c + 7] = -stroke[..., i]
    return G


def update(belief: MachineBelief, legs_mm: np.ndarray, pose: np.ndarray) -> MachineBelief:
    """The belief with one more measured pose (its readings and the pose the instrument measured)."""
    legs = np.vstack([belief.legs_mm, np.asarray(legs_mm, dtype=float).reshape(1, N_LEGS)])
    poses = np.vstack([belief.poses, np.asarray(pose, dtype=float).reshape(1, 6)])
    return refit(belief, legs, poses)


def refit(belief: MachineBelief, legs_mm: np.ndarray, poses: np.ndarray) -> MachineBelief:
    """The MAP estimate and covariance on these measured poses (replacing the belief's), started from the belief's
    estimate and misfit. Poses added after the belief's own add their surprises (``MachineBelief.surprises``); a
    refit on other poses starts that record again."""
    legs = np.asarray(legs_mm, dtype=float).reshape(-1, N_LEGS)
    poses = np.asarray(poses, dtype=float).reshape(-1, 6)
    if len(poses) == 0:
        return prior_belief(belief.a, belief.b, belief.l0, belief.priors)
    sig_p = belief.priors.sigmas()
    x = belief.x.copy()  # the last estimate: a pose more moves it little, so Gauss-Newton starts next to the answer
    misfit = belief.misfit_mm
    for _ in range(MAX_REWEIGHTS):  # the misfit scales the data's weight: estimate, weigh again
        for _ in range(MAX_ITERATIONS):
            r, J = _residuals(belief, x, legs, poses)
            normal, gradient = _normal(J, r, x, misfit, sig_p)
            step = -np.linalg.solve(normal, gradient)
            x = x + step
            if np.max(np.abs(step) / sig_p) < STEP_TOL:
                break
        r, J = _residuals(belief, x, legs, poses)
        cov = np.linalg.inv(_normal(J, r, x, misfit, sig_p)[0])
        cov = 0.5 * (cov + cov.T)
        determined = float(np.sum(1.0 - np.diag(cov) / sig_p**2))
        dof = r.size - determined
        seen = float(np.sqrt(np.sum(r**2) / dof)) if dof >= 3 else 0.0
        new_misfit = max(belief.priors.misfit_mm, seen, predictive_misfit_mm(r, J, cov, misfit, sig_p))
        if np.isclose(new_misfit, misfit, rtol=0.05):
            break
        misfit = new_misfit
    rms = float(np.sqrt(np.mean(r**2)))
    return MachineBelief(belief.a, belief.b, belief.l0, belief.priors, x, cov, legs, poses, misfit, rms,
                         _surprises(belief, legs, poses))


def _normal(J: np.ndarray, r: np.ndarray, x: np.ndarray, misfit_mm: float, sig_p: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """The normal matrix (48, 48) and gradient (48,) of data (weighed by the misfit) and prior together."""
    W = J / misfit_mm
    return W.T @ W + np.diag(sig_p**-2), W.T @ (r / misfit_mm) + x / sig_p**2


def _largest_of(n: int) -> float:
    """The median of the largest of n chi-square(6) draws: its quantile 0.5^(1/n)."""
    return float(2.0 * gammaincinv(N_LEGS / 2.0, 0.5 ** (1.0 / n)))


def predictive_misfit_mm(r: np.ndarray, J: np.ndarray, cov: np.ndarray, misfit_mm: float, sig_p: np.ndarray
                         ) -> float:
    """The least leg-length misfit at which the fit predicts each measured pose from the others as well as it says.

    Each pose left out in turn (closed form, linearised: its residual through (I - H)^-1, H its block of the hat
    matrix) is a prediction of a pose the fit did not see, with its covariance: the parameters' part and the misfit
    per leg. With the right misfit their normalised squares are chi-square(6): on average 6, and the largest of N no
    larger than the median of the largest of N draws (what a model error that is large at a few poses only breaks
    first). Only the poses the others predict (``PREDICTED_BY_DATA``) count; 0 when they already are within it, or
    when there are none.
    """
    n = r.size // N_LEGS
    Jb = J.reshape(n, N_LEGS, N_PARAMS)
    keep = np.eye(N_LEGS) - (Jb @ cov @ np.swapaxes(Jb, 1, 2)) / misfit_mm**2
    left_out = np.linalg.solve(keep, r.reshape(n, N_LEGS, 1))[..., 0]
    part = misfit_mm**2 * (np.linalg.inv(keep) - np.eye(N_LEGS))  # the parameters' part of its covariance
    by_prior = np.einsum("nik,k,nik->n", Jb, sig_p**2, Jb)  # the trace of that part from the priors alone
    counted = np.trace(part, axis1=1, axis2=2) <= PREDICTED_BY_DATA * by_prior
    if not counted.any():
        return 0.0
    lam, V = np.linalg.eigh(0.5 * (part[counted] + np.swapaxes(part[counted], 1, 2)))
    lam = np.maximum(lam, 0.0)
    proj = np.einsum("nij,ni->nj", V, left_out[counted]) ** 2
    largest = _largest_of(int(counted.sum()))

    def least(excess: Callable[[np.ndarray], float]) -> float:
        """The least misfit^2 at which excess(normalised squares) <= 0, to 1 % (bisection: they fall as it grows)."""
        lo, hi = misfit_mm**2 * 1e-6, float(np.max(np.sum(proj, axis=1)))
        if excess(np.sum(proj / (lam + lo), axis=1)) <= 0.0:
            return 0.0
        while hi / lo > 1.01:
            mid = np.sqrt(lo * hi)
            lo, hi = (mid, hi) if excess(np.sum(proj / (lam + mid), axis=1)) > 0.0 else (lo, mid)
        return hi

    return float(np.sqrt(max(least(lambda q: float(np.mean(q)) - N_LEGS),
                             least(lambda q: float(np.max(q)) - largest))))


def _surprises(belief: MachineBelief, legs: np.ndarray, poses: np.ndarray) -> tuple[float, ...]:
    """The belief's surprises and those of the poses after its own, each against the belief's prediction: its
    leg-length residual under the belief's estimate, normalised by the model's covariance of it (before the
    calibration, which these then set)."""
    n = belief.n_poses
    same = len(poses) >= n and np.array_equal(poses[:n], belief.poses) and np.array_equal(legs[:n], belief.legs_mm)
    kept, new = (belief.surprises, slice(n, None)) if same else ((), slice(0, None))
    if len(poses[new]) == 0:
        return kept
    r, G = _residuals(belief, belief.x, legs[new], poses[new])
    r, G = r.reshape(-1, N_LEGS), G.reshape(-1, N_LEGS, N_PARAMS)
    S = G @ belief.cov @ np.swapaxes(G, 1, 2) + belief.misfit_mm**2 * np.eye(N_LEGS)
    return (*kept, *(float(q) for q in np.einsum("ni,ni->n", r, np.linalg.solve(S, r[..., None])[..., 0])))


def predict(belief: MachineBelief, legs_mm: np.ndarray, guess: np.ndarray) -> PosePrediction:
    """The pose these readings put the platform at under the belief, with its covariance (``PosePrediction``).

    ForwardKinematicsError when the readings reach no pose near `guess` under the belief.
    """
    legs = np.asarray(legs_mm, dtype=float)
    geom = belief.geometry(legs)
    pose = forward_kinematics(geom, legs, np.asarray(guess, dtype=float))[0]
    R, t = split_pose(pose)
    Jx = inverse_jacobian(geom, R, t)
    _, _, u = leg_vectors(geom, R, t)
    G = _constraint_rows(u, R, legs - belief.l0)
    Jinv = np.linalg.inv(Jx)
    D = -Jinv @ G
    cov = (D @ belief.cov @ D.T + belief.misfit_mm**2 * (Jinv @ Jinv.T)) * belief.calibration() ** 2
    return PosePrediction(pose, 0.5 * (cov + cov.T))


def leg_discrepancy_mm(a_mm: np.ndarray, b_mm: np.ndarray, legs_mm: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(6,) the length each leg has at a measured pose by the controller's geometry, minus what it reads: how much
    longer than its reading each leg is (a model-free first look at a gross fault)."""
    R, t = split_pose(np.asarray(pose, dtype=float))
    _, length, _ = leg_vectors(Geometry(np.asarray(a_mm, dtype=float), np.asarray(b_mm, dtype=float)), R, t)
    return length - np.asarray(legs_mm, dtype=float)

"""Measurement-pose selection: D-optimal designs for identifying the 42 rigid-model errors.

The information of a pose set is M = sum_k J_k^T J_k, J_k the (6, 42) pose-error Jacobian of pose k at the
nominal geometry (rotation rows in mm at the robot's characteristic length). Maximizing det M minimizes the
volume of the least-squares confidence ellipsoid of the identified errors. The paper (Yu 2022, section 5.2)
compares four sets: 32 random poses, 32 and 64 coordinate-exchange poses, and 32 poses from "the union of a
full factorial exploration and a coordinate exchange algorithm"; ``paper_pose_sets`` builds all four.

Poses are arrays [..., 6] = [x, y, z (mm), roll, pitch, yaw (deg)].
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from rich.progress import Progress

from hilcal.error_models import forward_jacobian
from hilcal.kinematics import Geometry
from hilcal.robot import Robot
from hilcal.workspace import MAX_CONDITION, feasible, random_poses

if TYPE_CHECKING:
    from scipy.stats import qmc

N_PARAMETERS = 42
"""Columns of the pose-error Jacobian (rigid model: per leg da 3, db 3, dl0 1)."""

_MIN_POSES = -(-N_PARAMETERS // 6)
"""Fewest poses whose 6 equations each can make M nonsingular (7)."""


@dataclass(frozen=True)
class DesignMetrics:
    """Quality of a pose set for identifying the 42 errors; larger log_det and O1 are better.

    log_det is ln det(M / n), the information per pose, so sets of different size compare. d_efficiency is
    exp((log_det - reference) / 42) against a reference per-pose log det (None without one). The condition
    number is of the stacked (6n, 42) Jacobian with unit-norm columns; the singular values are unscaled.
    """

    n_poses: int
    log_det: float
    d_efficiency: float | None
    condition_number: float
    min_singular_value: float
    observability_index: float


@dataclass(frozen=True)
class Design:
    """A named pose set (mm, deg) and its metrics; n_passes and converged describe the exchange run."""

    name: str
    poses: np.ndarray
    metrics: DesignMetrics
    n_passes: int = 0
    converged: bool = True


def pose_jacobians(robot: Robot, poses: np.ndarray) -> np.ndarray:
    """Pose-error Jacobians [..., 6, 42] at the nominal geometry, rotation rows in mm."""
    return forward_jacobian(
        Geometry.nominal(robot), np.asarray(poses, dtype=float), robot.characteristic_length_mm
    )


def information_matrix(robot: Robot, poses: np.ndarray) -> np.ndarray:
    """Fisher information (42, 42) of a pose set under unit white noise: M = sum_k J_k^T J_k."""
    J = pose_jacobians(robot, np.atleast_2d(poses))
    return np.einsum("kij,kil->jl", J, J)


def _log_det(M: np.ndarray) -> np.ndarray:
    """ln det of symmetric matrices [..., 42, 42]; -inf where not positive definite."""
    sign, logabs = np.linalg.slogdet(M)
    return np.where(sign > 0, logabs, -np.inf)


def candidate_log_dets(
    info: np.ndarray, jac_old: np.ndarray | None, jac_candidates: np.ndarray
) -> np.ndarray:
    """ln det(M - J_old^T J_old + J_c^T J_c) [C] for candidate Jacobians [C, 6, 42]: a rank-6 exchange.

    Replaces one pose's information by each candidate's without rebuilding M from all poses (jac_old None
    adds the candidate instead). Non-positive-definite results give -inf.
    """
    base = info if jac_old is None else info - jac_old.T @ jac_old
    return _log_det(base + np.swapaxes(jac_candidates, -1, -2) @ jac_candidates)


def design_metrics(
    robot: Robot, poses: np.ndarray, reference_log_det_per_pose: float | None = None
) -> DesignMetrics:
    """Metrics of a pose set: per-pose log det, D-efficiency, scaled condition number, Borm–Menq O1."""
    q = np.atleast_2d(np.asarray(poses, dtype=float))
    n = len(q)
    if n == 0:
        raise ValueError("design_metrics needs at least one pose")
    A = pose_jacobians(robot, q).reshape(6 * n, N_PARAMETERS)
    log_det = float(_log_det(A.T @ A / n))
    s = np.linalg.svd(A, compute_uv=False)
    if len(s) < N_PARAMETERS:
        s = np.concatenate([s, np.zeros(N_PARAMETERS - len(s))])
    norms = np.linalg.norm(A, axis=0)
    s_scaled = np.linalg.svd(A / np.where(norms > 0, norms, 1.0), compute_uv=False)
    with np.errstate(divide="ignore"):
        condition = float(s_scaled[0] / s_scaled[-1]) if len(s_scaled) == N_PARAMETERS else float("inf")
        o1 = float(np.exp(np.mean(np.log(s))) / np.sqrt(n))
    d_eff = None
    if reference_log_det_per_pose is not None:
        d_eff = float(np.exp((log_det - reference_log_det_per_pose) / N_PARAMETERS))
    return DesignMetrics(
        n_poses=n,
        log_det=log_det,
        d_efficiency=d_eff,
        condition_number=condition,
        min_singular_value=float(s[-1]),
        observability_index=o1,
    )


def _check_n(n: int) -> None:
    if n < _MIN_POSES:
        raise ValueError(f"need at least {_MIN_POSES} poses to identify {N_PARAMETERS} parameters, got {n}")


def coordinate_exchange(
    robot: Robot,
    n: int,
    rng: np.random.Generator,
    start: np.ndarray | None = None,
    levels: int = 11,
    max_passes: int = 20,
    *,
    tol: float = 1e-6,
    distinct: bool = True,
    progress: bool = False,
    name: str | None = None,
) -> Design:
    """D-optimal n-pose design by Meyer–Nachtsheim coordinate exchange over a `levels`-point grid per axis.

    For each pose and each of its 6 coordinates, every equally spaced level of that coordinate's workspace
    range is tried (infeasible candidates skipped) and the one maximizing ln det M is kept, M updated by a
    rank-6 exchange. Passes repeat until one raises ln det M by less than `tol` (det by a factor < 1 + tol)
    or `max_passes` is reached. Starts from `start` (n, 6) or from feasible random poses drawn from `rng`.
    With `distinct` a candidate equal to another design pose is skipped: D-optimal exact designs like to
    replicate extreme poses, which on a rig only re-measures a pose instead of adding a new one.
    """
    _check_n(n)
    if levels < 2:
        raise ValueError(f"levels must be at least 2, got {levels}")
    if start is None:
        poses = random_poses(robot, n, rng)
    else:
        poses = np.array(start, dtype=float)
        if poses.shape != (n, 6):
            raise ValueError(f"start must have shape ({n}, 6), got {poses.shape}")
        bad = np.flatnonzero(~feasible(robot, poses))
        if bad.size:
            raise ValueError(f"start poses {bad[:10].tolist()} are not feasible")
    grid = np.linspace(robot.workspace[:, 0], robot.workspace[:, 1], levels, axis=1)
    J = pose_jacobians(robot, poses)
    M = np.einsum("kij,kil->jl", J, J)
    current = float(_log_det(M))
    passes, converged = 0, False
    bar = _progress_bar(progress)
    task = bar.add_task("coordinate exchange", total=max_passes * n) if bar is not None else None
    try:
        for passes in range(1, max_passes + 1):
            at_start = current
            for k in range(n):
                for axis in range(6):
                    cands = np.repeat(poses[k][None, :], levels, axis=0)
                    cands[:, axis] = grid[axis]
                    ok = feasible(robot, cands)
                    if distinct:
                        others = np.delete(poses, k, axis=0)
                        ok &= ~np.any(np.all(cands[:, None, :] == others[None], axis=-1), axis=1)
                    if not ok.any():
                        continue
                    Jc = pose_jacobians(robot, cands[ok])
                    ld = candidate_log_dets(M, J[k], Jc)
                    best = int(np.argmax(ld))
                    if ld[best] > current + 1e-12 and cands[ok][best, axis] != poses[k, axis]:
                        M = M - J[k].T @ J[k] + Jc[best].T @ Jc[best]
                        poses[k] = cands[ok][best]
                        J[k] = Jc[best]
                        current = float(ld[best])
                if bar is not None:
                    bar.update(task, advance=1, description=f"pass {passes}: ln det M {current:.4f}")
            M = np.einsum("kij,kil->jl", J, J)
            current = float(_log_det(M))
            if current - at_start < tol:
                converged = True
                if bar is not None:
                    bar.update(
                        task, completed=max_passes * n, description=f"converged: ln det M {current:.4f}"
                    )
                break
    finally:
        if bar is not None:
            bar.stop()
    return Design(
        name=name or f"coordinate_exchange{n}",
        poses=poses,
        metrics=design_metrics(robot, poses),
        n_passes=passes,
        converged=converged,
    )


def _progress_bar(enabled: bool) -> Progress | None:
    """A started rich Progress, or None when disabled."""
    if not enabled:
        return None
    bar = Progress()
    bar.start()
    return bar


def factorial_candidates(robot: Robot, levels: int = 3) -> np.ndarray:
    """The feasible points of the full-factorial grid (levels^6) over the workspace box, (N, 6)."""
    ws = robot.workspace
    axes = [np.linspace(lo, hi, levels) for lo, hi in ws]
    grid = np.array(list(itertools.product(*axes)))
    return grid[feasible(robot, grid)]


def point_exchange(
    robot: Robot, candidates: np.ndarray, n: int, *, max_passes: int = 20, tol: float = 1e-6
) -> np.ndarray:
    """Indices of an n-subset of `candidates` (distinct points) of high det M: greedy then modified Fedorov.

    Greedy forward selection from a tiny ridge gives a nonsingular start; then each design point in turn is
    swapped for the unused candidate that most increases ln det M, until a pass gains less than `tol`.
    """
    _check_n(n)
    N = len(candidates)
    if N < n:
        raise ValueError(f"only {N} feasible candidates for an {n}-point subset")
    Jc = pose_jacobians(robot, candidates)
    G = np.swapaxes(Jc, -1, -2) @ Jc
    ridge = 1e-6 * np.trace(G.sum(axis=0)) / (N * N_PARAMETERS)
    M = ridge * np.eye(N_PARAMETERS)
    chosen = np.zeros(N, dtype=bool)
    order: list[int] = []
    for _ in range(n):
        ld = _log_det(M + G)
        ld[chosen] = -np.inf
        c = int(np.argmax(ld))
        chosen[c] = True
        order.append(c)
        M = M + G[c]
    idx = np.array(order)
    M = G[idx].sum(axis=0)
    current = float(_log_det(M))
    for _ in range(max_passes):
        at_start = current
        for k in range(n):
            ld = _log_det((M - G[idx[k]]) + G)
            ld[chosen] = -np.inf
            c = int(np.argmax(ld))
            if ld[c] > current + 1e-12:
                M = M - G[idx[k]] + G[c]
                chosen[idx[k]], chosen[c] = False, True
                idx[k] = c
                current = float(ld[c])
        M = G[idx].sum(axis=0)
        current = float(_log_det(M))
        if current - at_start < tol:
            break
    return idx


def factorial_exchange(
    robot: Robot,
    n: int,
    rng: np.random.Generator,
    *,
    factorial_levels: int = 3,
    levels: int = 11,
    max_passes: int = 20,
    progress: bool = False,
) -> Design:
    """The paper's pose set 3: "the union of a full factorial exploration and a coordinate exchange".

    Interpretation: the full-factorial grid (``factorial_levels`` per axis; 3^6 = 729 points, of which the
    feasible ones are candidates) is explored for the n-point D-optimal subset by point exchange (greedy +
    modified Fedorov, distinct points); that subset then starts a coordinate exchange on the finer
    ``levels`` grid, which may move any coordinate off the factorial levels. ``rng`` is unused by the
    deterministic search and kept for a uniform signature.
    """
    del rng
    cands = factorial_candidates(robot, factorial_levels)
    idx = point_exchange(robot, cands, n, max_passes=max_passes)
    refined = coordinate_exchange(
        robot,
        n,
        np.random.default_rng(0),
        start=cands[idx],
        levels=levels,
        max_passes=max_passes,
        progress=progress,
    )
    return replace(refined, name=f"factorial_exchange{n}")


def verification_poses(robot: Robot, n: int, seed: int, *, n_scrambles: int = 16) -> np.ndarray:
    """n feasible poses (n, 6) spread evenly over the workspace: scrambled Sobol, best of several scrambles.

    Each scramble's Sobol sequence is scaled to the workspace box and filtered for feasibility; of
    `n_scrambles` seeded scrambles the one with the largest minimum pairwise distance (box scaled to a unit
    cube) is returned, so the set is both low-discrepancy and free of near-duplicates.
    """
    if n < 1:
        raise ValueError(f"n must be positive, got {n}")
    ws = robot.workspace
    span = ws[:, 1] - ws[:, 0]
    best, best_dist = None, -np.inf
    for child in np.random.SeedSequence(seed).spawn(n_scrambles):
        m = max(1, int(np.ceil(np.log2(n))))
        while True:
            unit = _sobol(np.random.default_rng(child)).random_base2(m)
            q = ws[:, 0] + unit * span
            q = q[feasible(robot, q)]
            if len(q) >= n:
                break
            if m >= 20:
                raise ValueError(f"fewer than {n} feasible poses among 2^20 Sobol points of the workspace")
            m += 1
        q = q[:n]
        d = _min_pairwise_distance((q - ws[:, 0]) / span)
        if d > best_dist:
            best, best_dist = q, d
    return best


def _sobol(rng: np.random.Generator) -> qmc.Sobol:
    """A scrambled 6-D Sobol engine seeded by rng (scipy >= 1.15 names the argument rng, older ones seed)."""
    from scipy.stats import qmc  # scipy.stats costs half a second: only runs that design a plan pay for it

    try:
        return qmc.Sobol(d=6, scramble=True, rng=rng)
    except TypeError:
        return qmc.Sobol(d=6, scramble=True, seed=rng)


def _min_pairwise_distance(x: np.ndarray) -> float:
    if len(x) < 2:
        return float("inf")
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)
    return float(d[np.triu_indices(len(x), 1)].min())


PAPER_POSE_SETS = ("set1_random32", "set2_doptimal32", "set3_factorial_exchange32", "set4_doptimal64")


def paper_pose_sets(robot: Robot, seed: int, names: Iterable[str] | None = None) -> dict[str, Design]:
    """The four pose sets of the paper's section 5.2 (or only those named), D-efficiencies relative to set 1 (32
    random poses).

    Set 2 is the coordinate exchange started from set 1, so its gain over set 1 is the exchange's alone;
    set 3 is deterministic (factorial grid) and set 4 starts from an independent stream of the same seed. A set is
    the same whether or not the others are made (set 1, the reference, is always drawn).
    """
    wanted = list(PAPER_POSE_SETS if names is None else names)
    unknown = sorted(set(wanted) - set(PAPER_POSE_SETS))
    if unknown:
        raise ValueError(f"unknown pose set(s) {unknown}: choose from {', '.join(PAPER_POSE_SETS)}")
    s1, s4 = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    set1 = random_poses(robot, 32, s1)
    makers = {  # in this order: set 2 draws from s1 after set 1
        "set2_doptimal32": lambda: coordinate_exchange(robot, 32, s1, start=set1),
        "set3_factorial_exchange32": lambda: factorial_exchange(robot, 32, s1),
        "set4_doptimal64": lambda: coordinate_exchange(robot, 64, s4),
    }
    designs = {"set1_random32": Design("set1_random32", set1, design_metrics(robot, set1))}
    designs.update({key: make() for key, make in makers.items() if key in wanted})
    ref = designs["set1_random32"].metrics.log_det
    return {
        key: replace(design, name=key, metrics=design_metrics(robot, design.poses, ref))
        for key, design in designs.items() if key in wanted
    }


def design_report(designs: Iterable[Design] | Mapping[str, Design]) -> str:
    """Plain-text table of designs: name, n, ln det per pose, D-efficiency, condition number, O1."""
    items = list(designs.values()) if isinstance(designs, Mapping) else list(designs)
    header = ("design", "n", "ln det(M/n)", "D-eff vs random", "cond (scaled)", "O1")
    rows = [header]
    for d in items:
        m = d.metrics
        rows.append(
            (
                d.name,
                str(m.n_poses),
                f"{m.log_det:.3f}",
                "-" if m.d_efficiency is None else f"{m.d_efficiency:.3f}",
                f"{m.condition_number:.4g}",
                f"{m.observability_index:.4g}",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = [
        "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


__all__ = [
    "MAX_CONDITION",
    "N_PARAMETERS",
    "PAPER_POSE_SETS",
    "Design",
    "DesignMetrics",
    "candidate_log_dets",
    "coordinate_exchange",
    "design_metrics",
    "design_report",
    "factorial_candidates",
    "factorial_exchange",
    "feasible",
    "information_matrix",
    "paper_pose_sets",
    "point_exchange",
    "pose_jacobians",
    "random_poses",
    "verification_poses",
]

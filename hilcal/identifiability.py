"""Identifiability: SVD of the column-scaled identification Jacobian over a pose set, explained in words.

Columns are scaled to unit norm so that the singular values compare parameter *combinations*, not units.
A direction with a (numerically) zero singular value is unidentifiable: no measurement on these poses
can tell it from zero. A tiny but nonzero one is identifiable in principle and poorly in practice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.error_models import MODELS, forward_jacobian, paper60_jacobian
from hilcal.kinematics import N_LEGS, Geometry, leg_vectors, split_pose
from hilcal.robot import Robot
from hilcal.stations import StationFrames

RANK_TOL = 1e-9
WEAK_TOL = 1e-2


@dataclass(frozen=True)
class Direction:
    """A right singular vector of the scaled Jacobian, with its relative singular value."""

    relative_singular_value: float
    coefficients: dict[str, float]
    description: str


@dataclass(frozen=True)
class IdentifiabilityReport:
    model: str
    n_poses: int
    n_params: int
    rank: int
    condition_number: float
    singular_values: np.ndarray
    unidentifiable: tuple[Direction, ...]
    weak: tuple[Direction, ...]
    weak_explained: tuple[str, ...]
    group_ranks: dict[str, int]
    n_stations: int = 1
    """Instrument stations; every one but the first has its frame fitted too (projected out here)."""


def _jacobian(robot: Robot, poses: np.ndarray, model: str, length_mm: float) -> np.ndarray:
    geom = Geometry.nominal(robot)
    if model == "42":
        return forward_jacobian(geom, poses, length_mm).reshape(-1, 42)
    return paper60_jacobian(geom, poses, length_mm).reshape(-1, 60)


def _group(name: str) -> str:
    """Parameter group of a name such as leg3_db_z_mm -> 'db'."""
    return name.split("_")[1]


def _describe(v: np.ndarray, names: tuple[str, ...]) -> tuple[dict[str, float], str]:
    """Largest coefficients of a direction, listed as a sentence."""
    v = v / np.abs(v).max()
    order = np.argsort(-np.abs(v))
    coeffs = {names[j]: round(float(v[j]), 3) for j in order if abs(v[j]) >= 0.2}
    legs = sorted({int(n[3]) for n in coeffs})
    groups = "/".join(sorted({_group(n) for n in coeffs}))
    parts = ", ".join(f"{k} {c:+.2f}" for k, c in list(coeffs.items())[:6])
    more = "" if len(coeffs) <= 6 else f" and {len(coeffs) - 6} more"
    return coeffs, f"legs {legs} ({groups}): {parts}{more}"


def leg_axis_modes(robot: Robot, poses: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Per-leg 42-parameter modes that change no leg length while the leg keeps its mean direction.

    Sliding base joint b_i along the leg axis by e (db_i = e u_i) shortens the leg by e, which dl0_i = -e
    undoes; likewise sliding the platform joint a_i towards the base. Only the variation of the leg
    direction over the poses separates these from zero.
    """
    R, t = split_pose(poses)
    _, _, u = leg_vectors(Geometry.nominal(robot), R, t)
    modes = []
    for i in range(N_LEGS):
        axis = u[:, i].mean(axis=0)
        axis /= np.linalg.norm(axis)
        axis_platform = np.einsum("nji,nj->i", R, u[:, i]) / len(poses)
        axis_platform /= np.linalg.norm(axis_platform)
        slides = (("base joint b", axis, slice(3, 6)), ("platform joint a", -axis_platform, slice(0, 3)))
        for joint, vec, cols in slides:
            m = np.zeros(42)
            m[7 * i + cols.start : 7 * i + cols.stop] = vec
            m[7 * i + 6] = -1.0
            modes.append((f"leg {i + 1}: {joint} along the leg axis vs leg offset dl0", m))
    return modes


def _explain_weak(
    robot: Robot, poses: np.ndarray, Vt: np.ndarray, c: np.ndarray, n_weak: int, rank: int
) -> tuple[str, ...]:
    """Which physical per-leg modes lie in the weak subspace, and how much of each."""
    if n_weak == 0:
        return ()
    basis = Vt[rank - n_weak : rank]
    R, t = split_pose(poses)
    _, _, u = leg_vectors(Geometry.nominal(robot), R, t)
    shares: dict[int, list[str]] = {}
    for label, m in leg_axis_modes(robot, poses):
        ms = m * c
        inside = float(np.linalg.norm(basis @ ms) / np.linalg.norm(ms))
        if inside > 0.7:
            i = int(label.split()[1].rstrip(":")) - 1
            joint = label.split(": ")[1].split(" along")[0]
            shares.setdefault(i, []).append(f"{joint} {100 * inside:.0f}%")
    out = []
    for i, parts in shares.items():
        axis = u[:, i].mean(axis=0)
        spread = np.degrees(np.max(np.arccos(np.clip(u[:, i] @ axis / np.linalg.norm(axis), -1, 1))))
        out.append(f"leg {i + 1}: sliding a joint along the leg axis while changing dl0 by the same amount "
                   f"({', '.join(parts)} inside the weak subspace); the leg direction varies only {spread:.1f} deg "
                   "over these poses, so leg lengths barely tell the two apart")
    return tuple(out)


def identifiability(
    robot: Robot, poses: np.ndarray, model: str = "42", length_mm: float | None = None, max_listed: int = 8,
    stations: np.ndarray | None = None,
) -> IdentifiabilityReport:
    """Rank, condition and the unidentifiable and weak directions of an error model over a pose set; with each
    pose's instrument station, of the model once every station's frame but the first is fitted too."""
    spec = MODELS[model]
    lc = robot.characteristic_length_mm if length_mm is None else length_mm
    J = _jacobian(robot, np.atleast_2d(poses), model, lc)
    frames = None if stations is None else StationFrames.of(stations, np.atleast_2d(poses), lc, robot.home[:3])
    if frames is not None:
        J = frames.project(np.zeros(J.shape[0]), J)[1]
    c = np.linalg.norm(J, axis=0)
    c = np.where(c > 0, c, 1.0)
    _, s, Vt = np.linalg.svd(J / c, full_matrices=True)
    rel = s / s[0]
    rank = int(np.sum(rel > RANK_TOL))
    null = [(float(rel[k]) if k < rel.size else 0.0, Vt[k] / c) for k in range(rank, spec.size)]
    weak = [(float(rel[k]), Vt[k] / c) for k in range(rank) if rel[k] < WEAK_TOL][::-1]

    def directions(items: list) -> tuple[Direction, ...]:
        out = []
        for value, v in items[:max_listed]:
            coeffs, text = _describe(v, spec.names)
            out.append(Direction(value, coeffs, text))
        return tuple(out)

    group_ranks = {}
    for g in dict.fromkeys(_group(n) for n in spec.names):
        cols = [j for j, n in enumerate(spec.names) if _group(n) == g]
        sg = np.linalg.svd(J[:, cols] / c[cols], compute_uv=False)
        group_ranks[g] = int(np.sum(sg > sg[0] * RANK_TOL))
    cond = float(s[0] / s[rank - 1])
    return IdentifiabilityReport(
        model=model, n_poses=int(np.atleast_2d(poses).shape[0]), n_params=spec.size, rank=rank,
        condition_number=cond, singular_values=rel, unidentifiable=directions(null), weak=directions(weak),
        weak_explained=_explain_weak(robot, poses, Vt, c, len(weak), rank) if model == "42" else (),
        group_ranks=group_ranks, n_stations=1 if frames is None else len(frames.free) + 1,
    )


def format_report(rep: IdentifiabilityReport) -> str:
    """Plain-text report for the CLI."""
    lines = [
        f"Identifiability of the {rep.n_params}-parameter model over {rep.n_poses} poses "
        "(column-scaled identification Jacobian, forward pose-error formulation)"
        + ("" if rep.n_stations == 1 else f", {rep.n_stations} instrument stations: every one's frame but the "
           "first's fitted too"),
        f"  rank: {rep.rank} of {rep.n_params}"
        + ("  (all parameters identifiable)" if rep.rank == rep.n_params
           else f"  ({rep.n_params - rep.rank} unidentifiable directions)"),
        f"  condition number (identifiable part): {rep.condition_number:.4g}",
        "  smallest relative singular values: "
        + ", ".join(f"{x:.3g}" for x in rep.singular_values[-min(8, rep.singular_values.size):]),
        "  rank of each parameter group alone: "
        + ", ".join(f"{g}: {r} of {N_LEGS * (1 if g in ('dl0', 'dl') else 3)}" for g, r in rep.group_ranks.items()),
    ]
    if rep.unidentifiable:
        lines.append(f"  unidentifiable directions (first {len(rep.unidentifiable)} of {rep.n_params - rep.rank}):")
        lines += [f"    - {d.description}" for d in rep.unidentifiable]
    if rep.weak:
        lines.append(f"  weakly identifiable directions (relative singular value < {WEAK_TOL:g}):")
        lines += [f"    - [{d.relative_singular_value:.2e}] {d.description}" for d in rep.weak]
    if rep.weak_explained:
        lines.append("  physical meaning of the weak directions:")
        lines += [f"    - {text}" for text in rep.weak_explained]
    if rep.model == "60":
        lines += [
            "  why: eq. 23 solves the 18 vector-chain equations for 6 pose errors in the least-squares sense, so the",
            "  joint errors act only through the net force and moment of the six chain errors; a rigid platform",
            "  fixes du_i from the joint and length errors (only the leg-axis projection of each chain is a",
            "  constraint), which is the 42-parameter model. The 60 parameters are not independent.",
        ]
    return "\n".join(lines)

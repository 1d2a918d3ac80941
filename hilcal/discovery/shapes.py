"""The fitted shape of every generic (unexplained) term: correction vs variable with a 95 % band, whether the
recorded poses pin it down, and, when they do not, extra poses that would (`hilcal.discovery.augmentation`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from hilcal.discovery.augmentation import augment, candidate_jacobians, candidate_pool
from hilcal.discovery.context import EffectContext
from hilcal.discovery.result import Shape, Step
from hilcal.discovery.term_groups import GENERIC, TermGroup, stack_phi
from hilcal.error_models import implicit_jacobian
from hilcal.identification import IdentificationResult
from hilcal.metrics import AccuracySummary
from hilcal.robot import Robot

N_GEO = 42
Z95 = 1.96
PIN_FRACTION = 0.5
"""A shape is pinned down when its 95 % band is at most half its amplitude at every recorded pose."""
COLUMN_OF = {
    "stroke": "stroke_mm", "stroke_cyclic": "stroke_mm", "axial_force": "axial_force_kN",
    "time": "session_time_s", "time_lag": "session_time_s", "temperature": "temp_c",
}
POSE_VARIABLES = ("stroke", "stroke_cyclic", "axial_force", "base_joint_angle", "platform_joint_angle")


def shape_grid(group: TermGroup, leg: int, ctx: EffectContext) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """(column names, grid in user units, basis at the grid [n, q]) of one leg of a generic group.

    One-variable shapes are tabulated over the recorded range; joint-angle shapes at the recorded angles (a
    quadratic in two angles is only known where the joint has been).
    """
    assert group.curve is not None
    if group.variable in COLUMN_OF:
        assert group.curve_range is not None
        x = np.linspace(*group.curve_range, 201)
        return (COLUMN_OF[group.variable],), x[:, None], group.curve(x, leg)
    if group.variable in ("base_joint_angle", "platform_joint_angle"):
        angles = (ctx.base_angle_rad if group.variable.startswith("base") else ctx.platform_angle_rad)[:, leg, :]
        return ("joint_angle1_deg", "joint_angle2_deg"), np.degrees(angles), group.curve(angles, leg)
    assert group.curve_range is not None
    sizes = np.geomspace(max(group.curve_range[0], 1e-3), max(group.curve_range[1], 2e-3), 25)
    pts = np.array([(d, s) for d in (-1.0, 1.0) for s in sizes])
    return ("direction", "last_move_mm"), pts, group.curve(pts, leg)


def _alias_note(group: TermGroup, alternatives: tuple[str, ...]) -> str:
    if not alternatives:
        return ""
    return (f"other settings fit the held-out rows almost as well ({', '.join(alternatives)}): with the poses "
            "recorded, the shape's scale (period or knots) is ambiguous")


def visible_basis(robot: Robot, final: IdentificationResult, ctx: EffectContext, leg: int, basis: np.ndarray
                  ) -> np.ndarray:
    """The part of a leg's correction basis at the recorded rows that the leg's seven geometric parameters
    cannot absorb (what the data actually shows of the shape)."""
    G = implicit_jacobian(final.geometry(robot), ctx.pose)[:, leg, 7 * leg:7 * leg + 7]
    return basis - G @ np.linalg.lstsq(G, basis, rcond=None)[0]


def _shape(robot: Robot, ctx: EffectContext, final: IdentificationResult, cov: np.ndarray, J: np.ndarray,
           sigma2: float, chosen: list[TermGroup], g: TermGroup, leg: int, block: np.ndarray, local: np.ndarray,
           verify: list[AccuracySummary | None], step_of: dict[str, int],
           alternatives: dict[str, tuple[TermGroup, ...]], seed: int,
           candidates: Callable[[], tuple[np.ndarray, np.ndarray]]) -> Shape:
    """One leg's correction of a generic group, its band, and extra poses when it is not pinned down.

    Amplitude and band that decide "pinned down" are those of the visible part at the recorded rows. The
    tabulated curve is the correction to apply together with the geometry of the same fit; its band holds
    that geometry fixed.
    """
    theta = final.x[block]
    rows = visible_basis(robot, final, ctx, leg, g.phi(ctx)[:, leg, local])

    def band_of(c: np.ndarray) -> float:
        return float(Z95 * np.sqrt(max(np.max(np.einsum("ni,ij,nj->n", rows, c, rows)), 0.0)))

    amplitude = float(np.ptp(rows @ theta) / 2.0)
    band_rows = band_of(cov[np.ix_(block, block)])
    alts = tuple(a.setting for a in alternatives.get(g.key, ()))
    pinned = band_rows <= PIN_FRACTION * amplitude and not alts
    why = ""
    if not pinned:
        why = _alias_note(g, alts) or (f"the 95 % band reaches {band_rows * 1000:.1f} µm against an amplitude of "
                                       f"{amplitude * 1000:.1f} µm at the recorded poses")
    columns, grid, B = shape_grid(g, leg, ctx)
    Bc = B - g.phi(ctx)[:, leg, local].mean(axis=0)
    conditional = sigma2 * np.linalg.pinv((J.T @ J)[np.ix_(block, block)])
    band = Z95 * np.sqrt(np.clip(np.einsum("ni,ij,nj->n", Bc, conditional, Bc), 0.0, None))
    poses, proposed_band = None, None
    if not pinned and g.variable in POSE_VARIABLES:
        aug = augment(robot, final.geometry(robot), final.length_mm, J.T @ J, sigma2,
                      lambda c: stack_phi(chosen, c.at_recorded_state(ctx)), block, band_of,
                      PIN_FRACTION * amplitude, seed, candidates=candidates())
        poses = aug.poses
        proposed_band = float(aug.predicted_band_mm[-1]) if aug.predicted_band_mm.size else None
    elif not pinned:
        why += "; more poses do not help here: spread the measurements over time (or temperature) instead"
    k = step_of.get(g.key)
    return Shape(
        g, leg, block, local, columns, grid, Bc @ theta, band, amplitude,
        None if k is None or verify[k - 1] is None else verify[k - 1].position_mm.rms,
        None if k is None or verify[k] is None else verify[k].position_mm.rms,
        pinned, why, alts, poses, proposed_band,
    )


def shapes_for(
    robot: Robot, ctx: EffectContext, final: IdentificationResult, cov: np.ndarray, J: np.ndarray,
    chosen: list[TermGroup], steps: list[Step], before: AccuracySummary | None,
    alternatives: dict[str, tuple[TermGroup, ...]], seed: int = 0,
) -> list[Shape]:
    """A Shape for every generic group of the final model, with extra poses where it is not pinned down. An all-leg
    group keeps the legs where it is larger than twice the residual sigma (at least its largest leg, so that every
    chosen group is described)."""
    shapes = []
    offset = N_GEO
    verify = [before, *[s.verify for s in steps]]
    step_of = {s.key: s.index for s in steps}
    m, p = J.shape
    sigma2 = float(final.residuals.ravel() @ final.residuals.ravel()) / max(m - p, 1)

    @functools.cache
    def candidates() -> tuple[np.ndarray, np.ndarray]:
        """The augmentation's pool and its Jacobians for this model: the same for every shape (made once)."""
        pool = candidate_pool(robot, seed)
        return pool, candidate_jacobians(robot, final.geometry(robot), pool, final.length_mm,
                                         lambda c: stack_phi(chosen, c.at_recorded_state(ctx)))

    for g in chosen:
        start = offset
        offset += g.n_params
        if g.kind != GENERIC or g.curve is None:
            continue
        legs = [g.leg] if g.leg is not None else list(range(6))
        group_shapes = [_shape(robot, ctx, final, cov, J, sigma2, chosen, g, leg, start + g.leg_columns(leg),
                               g.leg_columns(leg), verify, step_of, alternatives, seed, candidates) for leg in legs]
        large = [s for s in group_shapes if s.amplitude_mm > 2.0 * np.sqrt(sigma2)]
        if g.leg is None:
            group_shapes = large or [max(group_shapes, key=lambda s: s.amplitude_mm)]
        shapes.extend(group_shapes)
    return shapes

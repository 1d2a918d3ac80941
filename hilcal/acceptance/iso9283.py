"""ISO 9283 pose accuracy (AP) and pose repeatability (RP): the test cube, the poses P1-P5, the cycle, the figures.

The definitions are those of ISO 9283:1998 (pose accuracy and pose repeatability). The test cube is the largest
cube, edges parallel to the base axes, that fits the robot's workspace; here it is centred on the middle of the
workspace box, at the home orientation, and every point of a 5 x 5 x 5 grid over it must be reachable (workspace
box, leg limits with the approach margin, far from singular). P1 is the cube's centre; P2-P5 lie on the diagonals
of the diagonal plane C1-C2-C7-C8 (the plane y = z through the centre) at 10 % of the diagonal from the corners
C1, C2, C7, C8. Each cycle visits P1, P5, P4, P3, P2; every pose is approached from the same side. Poses are
[x, y, z mm, roll, pitch, yaw deg]; roll, pitch and yaw are ISO's a, b, c (rotations about x, y and z).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.robot import LegLimitSpec, Robot
from hilcal.workspace import feasible

POSE_NAMES = ("P1", "P2", "P3", "P4", "P5")
CYCLE_ORDER = (0, 4, 3, 2, 1)
"""One cycle visits P1, P5, P4, P3, P2 (indices into POSE_NAMES); the next cycle starts again at P1."""
DEFAULT_CYCLES = 30
CORNER_FRACTION = 0.1
"""P2-P5 lie this fraction of the diagonal's length from their corners (the standard allows 0.08-0.12)."""
_CORNERS = {"C1": (-1.0, -1.0, -1.0), "C2": (1.0, -1.0, -1.0), "C7": (1.0, 1.0, 1.0), "C8": (-1.0, 1.0, 1.0)}
_DIAGONALS = (("C1", "C7"), ("C2", "C8"), ("C7", "C1"), ("C8", "C2"))
"""P2..P5: (the corner it lies near, the opposite corner of the same diagonal)."""


@dataclass(frozen=True)
class IsoCube:
    """The ISO 9283 test cube: centre (mm), side (mm) and the orientation (deg) of every test pose."""

    centre_mm: np.ndarray
    side_mm: float
    orientation_deg: np.ndarray

    @property
    def diagonal_mm(self) -> float:
        return float(self.side_mm * np.sqrt(3.0))

    def corner(self, name: str) -> np.ndarray:
        """A corner of the diagonal plane C1-C2-C7-C8 (mm)."""
        return self.centre_mm + 0.5 * self.side_mm * np.array(_CORNERS[name])


def _margin_robot(robot: Robot, lower_margin_mm: float) -> Robot:
    lo, hi = robot.leg_limits
    return Robot(robot.spec.model_copy(update={"leg_limits": LegLimitSpec(min_mm=lo + lower_margin_mm, max_mm=hi)}))


def _grid(cube_centre: np.ndarray, side_mm: float, orientation: np.ndarray, n: int) -> np.ndarray:
    steps = np.linspace(-0.5, 0.5, n) * side_mm
    xyz = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3) + cube_centre
    return np.hstack([xyz, np.broadcast_to(orientation, (len(xyz), 3))])


def largest_cube(robot: Robot, *, lower_margin_mm: float = 0.0, tolerance_mm: float = 0.5, grid: int = 5) -> IsoCube:
    """The largest cube (by bisection on its side, to tolerance_mm) centred on the workspace box whose grid fits.

    `lower_margin_mm` raises the lower leg limit (the approach point of every pose is that much shorter).
    ValueError if not even the centre is reachable.
    """
    ws = robot.workspace
    centre = ws[:3].mean(axis=1)
    orientation = np.clip(robot.home[3:], ws[3:, 0], ws[3:, 1])
    checked = _margin_robot(robot, lower_margin_mm)

    def fits(side: float) -> bool:
        return bool(np.all(feasible(checked, _grid(centre, side, orientation, grid))))

    if not fits(0.0):
        raise ValueError(f"the centre of the workspace box {centre.round(1).tolist()} mm is not reachable at the "
                         f"home orientation: no ISO 9283 test cube fits")
    lo, hi = 0.0, float(np.min(ws[:3, 1] - ws[:3, 0]))
    if fits(hi):
        return IsoCube(centre, hi, orientation)
    while hi - lo > tolerance_mm:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return IsoCube(centre, lo, orientation)


def iso_poses(cube: IsoCube, fraction: float = CORNER_FRACTION) -> np.ndarray:
    """P1-P5 (5, 6): P1 the cube's centre, P2-P5 on the plane's diagonals at `fraction` of them from C1, C2, C7, C8."""
    if not 0.08 <= fraction <= 0.12:
        raise ValueError(f"ISO 9283 puts P2-P5 at (10 ± 2) % of the diagonal from the corners, not {fraction:.0%}")
    points = [cube.centre_mm]
    for near, far in _DIAGONALS:
        start = cube.corner(near)
        points.append(start + fraction * (cube.corner(far) - start))
    return np.hstack([np.array(points), np.broadcast_to(cube.orientation_deg, (5, 3))])


def cycle_route(poses: np.ndarray, cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """The poses in visiting order over `cycles` cycles (cycles * 5, 6) and which test pose each row is (0 = P1)."""
    if cycles < 1:
        raise ValueError(f"need at least one cycle, got {cycles}")
    which = np.tile(np.array(CYCLE_ORDER), cycles)
    return np.asarray(poses, dtype=float)[which], which


def _wrap_deg(angle: np.ndarray) -> np.ndarray:
    return (np.asarray(angle, dtype=float) + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class PoseCharacteristics:
    """AP and RP of one test pose from its n attained poses (mm and deg), with the standard's intermediate values.

    ap_xyz_mm = (x̄ - x_c, ȳ - y_c, z̄ - z_c); ap_p_mm = |ap_xyz_mm|; ap_abc_deg = (ā - a_c, b̄ - b_c, c̄ - c_c).
    l_mm[j] = |attained position j - barycentre|; rp_l_mm = l̄ + 3 S_l; rp_abc_deg = 3 (S_a, S_b, S_c) (the
    standard writes RP_a = ±3 S_a). S are sample standard deviations (n - 1).
    """

    commanded: np.ndarray
    barycentre: np.ndarray
    ap_xyz_mm: np.ndarray
    ap_p_mm: float
    ap_abc_deg: np.ndarray
    l_mm: np.ndarray
    l_mean_mm: float
    s_l_mm: float
    rp_l_mm: float
    s_abc_deg: np.ndarray
    rp_abc_deg: np.ndarray

    @property
    def n_cycles(self) -> int:
        return int(self.l_mm.size)


def pose_characteristics(attained: np.ndarray, commanded: np.ndarray) -> PoseCharacteristics:
    """ISO 9283 AP and RP of one pose: `attained` (n, 6) measured over n >= 2 cycles, `commanded` (6,)."""
    q = np.atleast_2d(np.asarray(attained, dtype=float))
    c = np.asarray(commanded, dtype=float)
    if q.ndim != 2 or q.shape[1] != 6 or c.shape != (6,):
        raise ValueError(f"attained must be (n, 6) and commanded (6,), got {q.shape} and {c.shape}")
    if len(q) < 2:
        raise ValueError("pose repeatability needs at least two cycles")
    angles = c[3:] + _wrap_deg(q[:, 3:] - c[3:])
    barycentre = np.concatenate([q[:, :3].mean(axis=0), angles.mean(axis=0)])
    ap_xyz = barycentre[:3] - c[:3]
    l_mm = np.linalg.norm(q[:, :3] - barycentre[:3], axis=1)
    s_l = float(np.std(l_mm, ddof=1))
    s_abc = np.std(angles, axis=0, ddof=1)
    return PoseCharacteristics(
        commanded=c, barycentre=barycentre, ap_xyz_mm=ap_xyz, ap_p_mm=float(np.linalg.norm(ap_xyz)),
        ap_abc_deg=barycentre[3:] - c[3:], l_mm=l_mm, l_mean_mm=float(l_mm.mean()), s_l_mm=s_l,
        rp_l_mm=float(l_mm.mean() + 3.0 * s_l), s_abc_deg=s_abc, rp_abc_deg=3.0 * s_abc)

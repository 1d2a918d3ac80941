"""Probe routes keep out of every ball; a search lattice leaves no sphere unfound; a touched cap gives the centre; a
body's frame, conditioned on measured spheres, predicts the next within its bound."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.acquisition.routes import Ball, RouteError, plan_route
from hilcal.acquisition.search import cap_centre, descent_offsets
from hilcal.acquisition.spheres import BodyBelief, park_height_mm
from hilcal.robot import default_robot

UP = np.array([0.0, 0.0, 1.0])


def _clearance(points: list[np.ndarray], balls: list[Ball]) -> float:
    """The least distance of any segment of the polyline to a ball's surface (negative: it enters one)."""
    worst = np.inf
    for a, b in itertools.pairwise(points):
        for ball in balls:
            t = np.linspace(0.0, 1.0, 2001)[:, None]
            d = np.min(np.linalg.norm(a + t * (b - a) - ball.centre_mm, axis=1))
            worst = min(worst, d - ball.radius_mm)
    return worst


def test_a_straight_route_is_kept_when_clear() -> None:
    assert len(plan_route(np.zeros(3), np.array([100.0, 0.0, 0.0]), [Ball(np.array([50.0, 30.0, 0.0]), 10.0)],
                          UP)) == 1


@pytest.mark.parametrize("seed", range(20))
def test_routes_go_around_balls(seed: int) -> None:
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-50, 50, 3)
    ball = Ball(centre, rng.uniform(5.0, 30.0))
    other = Ball(centre + rng.normal(0, 1, 3) * 150.0, 10.0)
    direction = rng.normal(0, 1, 3)
    direction /= np.linalg.norm(direction)
    start = centre + direction * ball.radius_mm * rng.uniform(1.05, 3.0)
    goal = centre - direction * ball.radius_mm * rng.uniform(1.05, 3.0) + rng.normal(0, 2, 3)
    if np.linalg.norm(goal - centre) <= ball.radius_mm or any(
            np.linalg.norm(p - other.centre_mm) <= other.radius_mm for p in (start, goal)):
        pytest.skip("drawn inside a ball")
    route = plan_route(start, goal, [ball, other], UP)
    assert np.allclose(route[-1], goal)
    assert _clearance([start, *route], [ball, other]) > 0


def test_a_goal_inside_a_ball_is_refused_and_a_start_inside_one_leaves_outwards() -> None:
    ball = Ball(np.zeros(3), 20.0)
    with pytest.raises(RouteError, match="lies where a sphere could be"):
        plan_route(np.array([100.0, 0.0, 0.0]), np.array([5.0, 0.0, 0.0]), [ball], UP)
    start = np.array([0.0, 0.0, 15.0])
    route = plan_route(start, np.array([0.0, 0.0, -60.0]), [ball], UP)
    assert route[0][2] > 15.0  # first out along the ray from the centre (upwards here)
    assert _clearance(route, [ball]) > 0


@pytest.mark.parametrize("reach", [5.0, 30.0, 90.0])
def test_the_search_lattice_covers_its_disk(reach: float) -> None:
    r = 12.7
    lattice = descent_offsets(r, reach)
    rng = np.random.default_rng(1)
    angle, radius = rng.uniform(0, 2 * np.pi, 5000), reach * np.sqrt(rng.uniform(0, 1, 5000))
    centres = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
    nearest = np.min(np.linalg.norm(centres[:, None, :] - lattice[None], axis=2), axis=1)
    assert np.all(nearest < r)  # some descent passes within r of every centre in the disk: it touches
    d = np.linalg.norm(lattice, axis=1)
    assert np.all(np.diff(d) >= -1e-9), "nearest first"


def test_a_cap_of_three_touches_gives_the_centre() -> None:
    rng = np.random.default_rng(2)
    r, centre = 12.7, np.array([100.0, -20.0, 30.0])
    normals = np.array([[0.1, 0.2, 1.0], [0.6, -0.1, 0.8], [-0.3, 0.5, 0.7]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    touches = centre + r * normals + rng.normal(0, 0.002, (3, 3))
    found, rms = cap_centre(touches, r, UP)
    assert np.linalg.norm(found - centre) < 0.05 and rms < 0.01


@pytest.mark.parametrize(("degrees", "most_shrink"), [(0.2, 1.0), (0.02, 0.5)])
def test_conditioning_on_spheres_predicts_the_next_within_its_bound(degrees: float, most_shrink: float) -> None:
    """Monte Carlo: frames drawn from the stated tolerance; each measured sphere shrinks the next ones' bounds and the
    bounds still hold the truth. With a turn of 0.2 deg over 5 m the turn dominates, and two spheres on a line leave the
    turn about it; with 0.02 deg the translation dominates and one sphere halves the bounds."""
    rng = np.random.default_rng(4)
    layout = np.array([[2500.0, 1443.38, 100.0], [-2500.0, 1443.38, 100.0], [0.0, -2886.75, 100.0]])
    nominal = np.eye(4)
    prior = BodyBelief.within(nominal, 10.0, degrees)
    misses, shrink = 0, []
    for _ in range(300):
        sd = np.sqrt(np.diag(prior.cov))
        xi = rng.normal(0.0, sd)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(xi[3:]).as_matrix()
        T[:3, 3] = xi[:3]
        truth = layout @ T[:3, :3].T + T[:3, 3]
        first = prior.predict(layout[0], UP, 0.1)
        misses += np.linalg.norm(truth[0] - first.centre_mm) > first.bound_mm
        belief = prior
        for k in (1, 2):
            belief = belief.condition(layout[k - 1], truth[k - 1] + rng.normal(0, 0.005, 3), 0.005)
            pred = belief.predict(layout[k], UP, 0.1)
            misses += np.linalg.norm(truth[k] - pred.centre_mm) > pred.bound_mm
            shrink.append(pred.bound_mm / prior.predict(layout[k], UP, 0.1).bound_mm)
    assert misses <= 2  # about 1e-3 of 900 predictions may fall outside a 4-sigma bound
    assert max(shrink) < most_shrink


def test_the_park_height_is_above_every_platform_sphere_in_the_workspace() -> None:
    robot = default_robot()
    height = park_height_mm(robot, 20.0)
    rng = np.random.default_rng(0)
    lo, hi = robot.workspace[:, 0], robot.workspace[:, 1]
    poses = rng.uniform(lo, hi, (2000, 6))
    R = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]], degrees=True).as_matrix()
    tops = np.einsum("nij,kj->nki", R, robot.platform_spheres)[..., 2] + poses[:, None, 2] + robot.sphere_radius_mm
    assert height - tops.max() > 15.0

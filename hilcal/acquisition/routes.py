"""Probe routes that keep out of every place a tooling sphere could be.

A positioning move is a straight segment; an obstacle is a ball (a sphere's predicted centre, its radius plus its
bound and a margin). A blocked segment goes around the first ball it meets on an arc in the plane of the segment and
the ball's centre, with chords that clear the ball; a route that still meets a ball is refused (``RouteError``), never
driven.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ARC_RADIUS_FACTOR = 1.15
"""Arcs run at this many times the ball's radius (chords of about 60 degrees then clear it)."""
MAX_DETOURS = 4


class RouteError(RuntimeError):
    """No route between two points keeps out of the obstacles."""


@dataclass(frozen=True)
class Ball:
    """A region the probe must not enter: centre (3,) mm and radius mm."""

    centre_mm: np.ndarray
    radius_mm: float


def segment_distance(a: np.ndarray, b: np.ndarray, point: np.ndarray) -> float:
    """The least distance between the segment a-b and a point (mm)."""
    d = b - a
    length2 = float(d @ d)
    s = 0.0 if length2 == 0.0 else float(np.clip((point - a) @ d / length2, 0.0, 1.0))
    return float(np.linalg.norm(a + s * d - point))


def first_blocking(a: np.ndarray, b: np.ndarray, balls: list[Ball]) -> Ball | None:
    """The ball the segment a-b meets first (nearest to a along the segment), or None."""
    if not balls:
        return None
    centres = np.array([ball.centre_mm for ball in balls])
    radii = np.array([ball.radius_mm for ball in balls])
    d = b - a
    length2 = float(d @ d) or 1.0
    s = np.clip((centres - a) @ d / length2, 0.0, 1.0)
    hit = np.linalg.norm(a + s[:, None] * d - centres, axis=1) < radii
    if not hit.any():
        return None
    return balls[int(np.flatnonzero(hit)[np.argmin(s[hit])])]


def _arc(a: np.ndarray, b: np.ndarray, ball: Ball, up: np.ndarray) -> list[np.ndarray]:
    """Waypoints from a to b around one ball: out along a's ray, along the arc, in along b's ray."""
    c = ball.centre_mm
    da, db = a - c, b - c
    radius = max(ARC_RADIUS_FACTOR * ball.radius_mm, min(np.linalg.norm(da), np.linalg.norm(db)))
    ua, ub = da / np.linalg.norm(da), db / np.linalg.norm(db)
    normal = np.cross(ua, ub)
    if np.linalg.norm(normal) < 1e-9:  # a and b on one line through the centre: go over the top (the up side)
        side = up - (up @ ua) * ua
        if np.linalg.norm(side) < 1e-9:
            side = np.cross(ua, [1.0, 0.0, 0.0] if abs(ua[0]) < 0.9 else [0.0, 1.0, 0.0])
        normal = np.cross(ua, side / np.linalg.norm(side))
    normal = normal / np.linalg.norm(normal)
    angle = float(np.arctan2(np.linalg.norm(np.cross(ua, ub)), ua @ ub))
    if angle < 1e-9:
        angle = np.pi
    max_step = 2.0 * np.arccos(min(ball.radius_mm / radius, 1.0)) * 0.9
    n = max(1, int(np.ceil(angle / max_step)))
    tangent = np.cross(normal, ua)
    points = [c + radius * (np.cos(k * angle / n) * ua + np.sin(k * angle / n) * tangent) for k in range(n + 1)]
    return points


def plan_route(start: np.ndarray, goal: np.ndarray, balls: list[Ball], up: np.ndarray) -> list[np.ndarray]:
    """Waypoints after `start` up to and including `goal`, every segment clear of every ball.

    A start inside a ball (a region that grew after the probe got there, where it stands clear of the sphere) is left
    first along the ray from the ball's centre: the sphere, if it is within the ball, lies behind the probe. RouteError
    when the goal lies inside a ball, or no detour clears them all.
    """
    start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
    inside = [b for b in balls if np.linalg.norm(goal - b.centre_mm) < b.radius_mm]
    if inside:
        raise RouteError(f"the target {np.round(goal, 3).tolist()} mm lies where a sphere could be (within "
                         f"{inside[0].radius_mm:.1f} mm of {np.round(inside[0].centre_mm, 3).tolist()})")
    for ball in balls:
        out = start - ball.centre_mm
        if np.linalg.norm(out) < ball.radius_mm:
            ray = out / max(float(np.linalg.norm(out)), 1e-9)
            exit_point = ball.centre_mm + ARC_RADIUS_FACTOR * ball.radius_mm * ray
            others = [b for b in balls if b is not ball]
            if first_blocking(start, exit_point, others) is not None:
                break
            return [exit_point, *plan_route(exit_point, goal, balls, up)]
    route = [start, goal]
    for _ in range(MAX_DETOURS):
        for k in range(len(route) - 1):
            ball = first_blocking(route[k], route[k + 1], balls)
            if ball is not None:
                route[k + 1:k + 1] = _arc(route[k], route[k + 1], ball, np.asarray(up, dtype=float))
                break
        else:
            return route[1:]
    raise RouteError(f"no route from {np.round(start, 3).tolist()} to {np.round(goal, 3).tolist()} mm keeps out of "
                     "the spheres' regions")

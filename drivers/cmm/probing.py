"""How a CMM finds and measures tooling spheres and a platform pose, on any transport (``drivers.cmm.base``).

All of it happens in ball-centre space: the stylus ball (radius r, stated by the CMM) touches a sphere of radius R
when its centre is R + r from the sphere's centre, so the ball's centre moves on and around spheres of radius R + r,
the fits use R + r, and every region the ball keeps out of is a sphere's possible region grown by r. Every sphere
comes with a prediction and a bound (how far off it may be, ``hilcal.acquisition.spheres``). A sphere
predicted to within a fraction of its radius is probed at once: the touches start beyond where its surface could be
and search as far past it. A less certain one is searched for first, as a CMM operator would: descents from above on
a widening pattern until a touch, touches around that point, the centre from that cap; a sphere not found where a
probe pattern expected it is searched for too, on a wider pattern each time, up to ``max_search_mm``. Every
positioning move keeps out of the regions where any sphere could be (``hilcal.acquisition.routes``), and so does
each touch's start (the approach position); a descent's search reaches r further than planned where a server reads
the end of search as the ball's centre, and is kept clear of the other spheres for that longer stroke too. Each
measured sphere conditions its body's frame, so the next sphere of that body is predicted better.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog

from drivers.cmm.types import (
    DEFAULT_ALIGNMENT_DEG,
    DEFAULT_ALIGNMENT_MM,
    BaseMeasurement,
    PoseMeasurement,
    PoseMeasurementError,
    ProbeLost,
    ProbeMiss,
    ProbeRecord,
    ProbeStatus,
    SphereMeasurement,
    SphereMeasurementError,
    SphereSearch,
    as_transform,
    transform_from_pose,
)
from hilcal.acquisition.routes import Ball, plan_route, segment_distance
from hilcal.acquisition.search import basis, cap_centre, cap_offsets, descent_offsets
from hilcal.acquisition.spheres import BodyBelief, SpherePrediction, park_height_mm
from hilcal.pose_measurement import pose_from_spheres, rigid_fit
from hilcal.robot import Robot
from hilcal.sphere_fit import SphereFitError, fit_sphere, fit_sphere_robust, sphere_probe_pattern

log = structlog.get_logger(__name__)

MEASURED_SIGMA_MM = 0.005
"""A measured sphere centre's uncertainty per axis when it conditions its body's frame."""
REGISTERED_MM, REGISTERED_DEG = 0.05, 0.002
"""How well a frame registered on measured spheres is known (a bound), for the next pose's predictions."""


@dataclass
class Regions:
    """Where each sphere of a measurement could be: the balls every positioning move keeps out of."""

    balls: dict[str, Ball] = field(default_factory=dict)

    def others(self, key: str) -> list[Ball]:
        return [b for k, b in self.balls.items() if k != key]


def _up() -> np.ndarray:
    return np.array([0.0, 0.0, 1.0])


class Prober:
    """One CMM's probing strategy (the CMM gives the tracked primitives ``where``, ``goto``, ``set_touch``, ``probe``
    and the stylus radius)."""

    def __init__(self, cmm: Any) -> None:
        self.cmm = cmm
        self.cfg = cmm.probing
        self.r = float(cmm.stylus())
        """The stylus ball's radius."""

    # ------------------------------------------------------------------ moves

    def _go(self, point: np.ndarray, avoid: list[Ball], *, last: bool = True) -> None:
        """Move the ball to `point` along a route clear of `avoid` (straight when nothing is in the way); without
        `last`, only to the last waypoint before it (a touch's own positioning move goes the rest of the way)."""
        route = plan_route(self.cmm.where(), point, avoid, _up())
        for waypoint in route if last else route[:-1]:
            self.cmm.goto(waypoint)

    def _touch(self, target: np.ndarray, ijk: np.ndarray, approach_mm: float, search_mm: float, avoid: list[Ball],
               records: list[ProbeRecord]) -> int | None:
        """One touch expecting the ball's centre at `target`: it starts `approach_mm` out along `ijk` (routed there
        clear of `avoid`) and searches `search_mm` past the target; recorded; its record index, or None on a miss."""
        settings = self.cmm.set_touch(approach_mm, search_mm)
        if settings.approach_mm + settings.search_mm < approach_mm + search_mm - 1e-6:
            log.warning("cmm.touch_reach_short", asked_mm=approach_mm + search_mm,
                        reach_mm=settings.approach_mm + settings.search_mm)
        start = target + approach_mm * ijk
        self._go(start, avoid, last=False)
        return self._record(start, target, ijk, records)

    def _record(self, start: np.ndarray, target: np.ndarray, ijk: np.ndarray, records: list[ProbeRecord]
                ) -> int | None:
        """Touch from `start` and record it (a miss as a miss); its record index, or None on a miss."""
        try:
            touch = self.cmm.probe(start, ijk)
        except (ProbeMiss, ProbeLost) as miss:
            log.info("cmm.probe_miss", target_mm=target.tolist(), ijk=ijk.tolist(), error=str(miss))
            records.append(ProbeRecord(target, ijk, None, ProbeStatus.MISS, None, str(miss)))
            return None
        point, er = self.cmm.ball_centre(touch, ijk)
        records.append(ProbeRecord(target, ijk, point, ProbeStatus.USED, effective_radius_mm=er))
        return len(records) - 1

    def _descend(self, line: np.ndarray, up: np.ndarray, top: float, bottom: float, avoid: list[Ball],
                 records: list[ProbeRecord]) -> int | None:
        """A descent of the ball's centre along `up` through `line` from height `top` to `bottom`, in as many
        touches as the CMM's stroke (Approach + Search, as it clamps them) needs: each continues where the last one's
        search ended, down the corridor it swept clear. The touching record's index, or None."""
        height, first = top, True
        while height > bottom + 1e-6:
            half = 0.5 * (height - bottom)
            settings = self.cmm.set_touch(half, half)
            start = line + height * up
            if first:
                self._go(start, avoid, last=False)
            elif np.linalg.norm(np.cross(self.cmm.where() - line, up)) > 0.01:
                log.warning("cmm.descent_stopped", at_mm=line.tolist(), where_mm=self.cmm.where().tolist(),
                            reason="after the miss the CMM left the ball off the swept line")
                return None
            idx = self._record(start, start - settings.approach_mm * up, up, records)
            if idx is not None:
                return idx
            height, first = height - (settings.approach_mm + settings.search_mm), False
        return None

    # ------------------------------------------------------------------ one sphere

    def measure_sphere(self, pred: SpherePrediction, radius_mm: float, others: list[Ball] | None = None
                       ) -> SphereMeasurement:
        """Find and measure one sphere of radius `radius_mm` (see the module docstring); SphereMeasurementError
        when it cannot be."""
        others = others or []
        centre, bound, search = pred.centre_mm, pred.bound_mm, None
        if bound > self.cfg.search_fraction * radius_mm:
            search = self._locate(pred, radius_mm, bound, others)
            centre, bound = search.found_mm, self.cfg.least_bound_mm
        try:
            first = self._pattern(centre, radius_mm, bound, pred.up, others)
        except SphereMeasurementError as err:
            log.info("cmm.sphere_not_where_predicted", predicted_mm=centre.tolist(), bound_mm=bound, error=str(err))
            search = self._locate(SpherePrediction(centre, bound, pred.up), radius_mm, max(2.0 * bound, radius_mm),
                                  others)
            first = self._pattern(search.found_mm, radius_mm, self.cfg.least_bound_mm, pred.up, others)
        if first.offset_from_nominal_mm <= self.cfg.prediction_tol_mm:
            return _with(first, search=search, nominal=pred.centre_mm)
        log.info("cmm.sphere_remeasure", nominal_mm=first.nominal_centre_mm.tolist(),
                 fitted_mm=first.centre_mm.tolist(), offset_mm=first.offset_from_nominal_mm)
        second = self._pattern(first.centre_mm, radius_mm, self.cfg.least_bound_mm, pred.up, others)
        return _with(second, search=search, nominal=pred.centre_mm, superseded=first)

    def leave(self, m: SphereMeasurement, up: np.ndarray) -> None:
        """Back to clearance above a sphere just measured: the next move, which knows nothing of it, starts clear."""
        reach = m.radius_mm + self.r
        region = Ball(m.centre_mm, reach + self.cfg.route_margin_mm)
        self._go(m.centre_mm + (reach + self.cfg.clearance_mm) * up, [region])

    def _locate(self, pred: SpherePrediction, radius_mm: float, bound: float, others: list[Ball]) -> SphereSearch:
        """Descend from above on widening lattices until a touch, then touch the cap around it (module docstring).

        Each descent starts above the highest the ball could meet the sphere (R + r above the highest possible
        centre, and a margin) and searches to below the lowest; each touch's nominal point is derived from the CMM's
        actual Approach, so it starts where planned whatever the CMM clamps (``_descend``). The whole stroke, r
        longer where a server reads the end of search as the ball's centre, keeps out of the other spheres'
        regions (a descent that would not is skipped)."""
        cfg = self.cfg
        reach = radius_mm + self.r
        x, y, up = basis(pred.up)
        m = cfg.search_margin_mm
        touches = 0
        stage = min(bound, cfg.max_search_mm)
        while True:
            top, bottom = reach + max(stage, pred.ceiling_mm) + m, -(stage + m)
            region = Ball(pred.centre_mm, reach + stage + cfg.route_margin_mm)
            log.info("cmm.sphere_search", predicted_mm=pred.centre_mm.tolist(), bound_mm=stage)
            for offset in descent_offsets(reach, stage):
                line = pred.centre_mm + offset[0] * x + offset[1] * y
                if any(segment_distance(line + top * up, line + (bottom - self.r) * up, b.centre_mm) < b.radius_mm
                       for b in others):
                    log.warning("cmm.descent_skipped", at_mm=line.tolist(), reason="another sphere's region")
                    continue
                records: list[ProbeRecord] = []
                touches += 1
                if self._descend(line, up, top, bottom, [*others, region], records) is not None:
                    found = self._cap(records[-1].point_mm, reach, up, others)
                    touches += found[1]
                    return SphereSearch(pred.centre_mm, stage, touches, found[0])
            if stage >= cfg.max_search_mm:
                raise SphereMeasurementError(
                    f"sphere near {np.round(pred.centre_mm, 3).tolist()} mm: not found within {stage:.1f} mm of its "
                    f"prediction ({touches} descents): check the station's alignment and the sphere's mounting")
            stage = min(2.0 * stage, cfg.max_search_mm)

    def _cap(self, first: np.ndarray, reach: float, up: np.ndarray, others: list[Ball]) -> tuple[np.ndarray, int]:
        """The centre from descents around a first touch on the cap (the first touch alone: the pole below it);
        `reach` is R + r, the ball centre's distance from the sphere's centre at a touch."""
        x, y, _ = basis(up)
        m = self.cfg.search_margin_mm
        # The centre lies within `reach` of the touch and not above it: nothing the ball can meet is higher than
        # touch + reach, and all of it lies within this ball.
        region = Ball(first - 2.0 * reach * up, 3.0 * reach + self.cfg.route_margin_mm)
        points, touches = [first], 0
        for offset in cap_offsets(reach):
            target = first + offset[0] * x + offset[1] * y
            records: list[ProbeRecord] = []
            touches += 1
            if self._touch(target, up, reach + m, reach + m, [*others, region], records) is not None:
                points.append(records[-1].point_mm)
            if len(points) >= 4:
                break
        try:
            centre, _ = cap_centre(np.array(points), reach, up)
        except ValueError:
            centre = first - reach * up
        return centre, touches

    def _pattern(self, centre: np.ndarray, radius_mm: float, bound: float, up: np.ndarray, others: list[Ball]
                 ) -> SphereMeasurement:
        """One pass of the probe pattern around `centre` (the sphere within `bound` of it): misses and outliers
        touched again within the re-probe budget; SphereMeasurementError when too few good points remain."""
        cfg = self.cfg
        reach = radius_mm + self.r
        search = max(cfg.min_search_mm, bound + cfg.search_margin_mm)
        avoid = [*others, Ball(centre, reach + bound + cfg.route_margin_mm)]
        targets, normals = sphere_probe_pattern(centre, reach, up, cfg.n_ring, cfg.elevations_deg)
        self._go(centre + (reach + max(cfg.clearance_mm, search + cfg.search_margin_mm)) * normals[0], avoid)
        # The pole last: the ball then leaves the sphere from above it, clear of it on the way to the next one.
        targets, normals = np.roll(targets, -1, axis=0), np.roll(normals, -1, axis=0)
        records: list[ProbeRecord] = []
        good: list[tuple[int, int]] = []
        missed: list[int] = []
        for k in range(len(targets)):
            idx = self._touch(targets[k], normals[k], search, search, avoid, records)
            (missed.append(k) if idx is None else good.append((k, idx)))
        budget = self._reprobe(missed, targets, normals, search, avoid, records, good, cfg.max_reprobes)
        threshold = cfg.outlier_threshold_mm
        while True:
            if len(good) < cfg.min_points:
                raise SphereMeasurementError(
                    f"sphere near {np.round(centre, 3).tolist()} mm: only {len(good)} good points "
                    f"(need {cfg.min_points}) after {len(records)} touches", tuple(records))
            pts = np.array([records[i].point_mm for _, i in good])
            try:
                robust = fit_sphere_robust(pts, reach, threshold, centre)
            except SphereFitError as err:
                raise SphereMeasurementError(f"sphere near {centre.tolist()} mm: {err}", tuple(records)) from err
            for j in robust.outliers:
                rec, residual = records[good[j][1]], float(robust.residuals_mm[j])
                log.warning("cmm.probe_outlier", point_mm=rec.point_mm.tolist(), residual_mm=residual)
                records[good[j][1]] = dataclasses.replace(rec, status=ProbeStatus.OUTLIER, residual_mm=residual,
                                                          detail="residual over threshold")
            if robust.inliers.all():
                break
            retry = [good[j][0] for j in robust.outliers]
            good = [good[j] for j in np.flatnonzero(robust.inliers)]
            if budget == 0:
                break
            budget = self._reprobe(retry, targets, normals, search, avoid, records, good, budget)
        return self._judge(centre, radius_mm, robust.fit, good, records, threshold)

    def _reprobe(self, indices: list[int], targets: np.ndarray, normals: np.ndarray, search: float,
                 avoid: list[Ball], records: list, good: list[tuple[int, int]], budget: int) -> int:
        """Touch the pattern points `indices` again while the re-probe budget lasts; returns what is left."""
        for k in indices:
            if budget == 0:
                break
            budget -= 1
            idx = self._touch(targets[k], normals[k], search, search, avoid, records)
            if idx is not None:
                good.append((k, idx))
        return budget

    def _judge(self, centre: np.ndarray, radius_mm: float, fit: Any, good: list[tuple[int, int]], records: list,
               threshold: float) -> SphereMeasurement:
        """The fitted sphere with its checks: enough consistent points, the radius determined and right (the free
        fit's radius, less the stylus radius, against the sphere's)."""
        cfg = self.cfg
        reach = radius_mm + self.r
        used = np.array([records[i].point_mm for _, i in good])
        final = _finalise(records, fit.centre_mm, reach)
        where = f"sphere near {np.round(centre, 3).tolist()} mm"
        if len(used) < cfg.min_points:
            raise SphereMeasurementError(
                f"{where}: only {len(used)} consistent points (need {cfg.min_points}; outlier threshold "
                f"{threshold:.4f} mm) after {len(records)} touches", final)
        try:
            free = fit_sphere(used, None, fit.centre_mm)
        except SphereFitError as err:
            raise SphereMeasurementError(f"{where}: radius check: {err}", final) from err
        radius_sd_mm = free.radius_sd_unit * max(cfg.probe_sigma_mm, fit.sigma_hat_mm)
        if not radius_sd_mm <= cfg.radius_tol_mm / 3.0:
            raise SphereMeasurementError(
                f"{where}: the used points determine the radius only to {radius_sd_mm:.4f} mm, too poorly for the "
                f"{cfg.radius_tol_mm} mm radius check", final)
        if np.any(np.abs(fit.residuals_mm) > threshold):
            raise SphereMeasurementError(
                f"{where}: residuals up to {np.max(np.abs(fit.residuals_mm)):.4f} mm exceed the outlier threshold "
                f"{threshold:.4f} mm with no touches left to reject", final)
        if abs(free.radius_mm - reach) > cfg.radius_tol_mm:
            raise SphereMeasurementError(
                f"{where}: the ball centres lie on a sphere of radius {free.radius_mm:.4f} mm; less the stylus's "
                f"{self.r} mm that is {free.radius_mm - self.r:.4f} mm, not the nominal {radius_mm} mm within "
                f"{cfg.radius_tol_mm} mm", final)
        log.debug("cmm.sphere_measured", centre_mm=fit.centre_mm.tolist(), rms_mm=fit.rms_mm,
                  radius_free_mm=free.radius_mm - self.r, touches=len(records), rejected=len(records) - len(used))
        return SphereMeasurement(centre_mm=fit.centre_mm, radius_mm=radius_mm, fit=fit, free_fit=free, probes=final,
                                 nominal_centre_mm=centre, stylus_radius_mm=self.r)

    # ------------------------------------------------------------------ a pose

    def _start(self, robot: Robot, alignment: np.ndarray, expected: np.ndarray, pose_cov: np.ndarray | None,
               alignment_tolerance: tuple[float, float] | None) -> tuple[BodyBelief, np.ndarray, np.ndarray,
                                                                         Regions]:
        """The base's belief, the platform's transform and covariance, and every sphere's region before a touch."""
        cfg = self.cfg
        reach = robot.sphere_radius_mm + self.r
        mm, deg = alignment_tolerance or (DEFAULT_ALIGNMENT_MM, DEFAULT_ALIGNMENT_DEG)
        base_belief = BodyBelief.within(as_transform(alignment), mm, deg)
        cov = BodyBelief.within(np.eye(4), cfg.default_bound_mm, 0.0).cov if pose_cov is None else pose_cov
        T_bp = transform_from_pose(expected)
        platform_belief = base_belief.composed(T_bp, np.asarray(cov, dtype=float))
        regions = Regions()
        for key, belief, points in (("base", base_belief, robot.base_spheres),
                                    ("platform", platform_belief, robot.platform_spheres)):
            for k, s in enumerate(points):
                pred = belief.predict(s, _up(), cfg.least_bound_mm)
                regions.balls[f"{key}{k}"] = Ball(pred.centre_mm, reach + pred.bound_mm + cfg.route_margin_mm)
        return base_belief, T_bp, np.asarray(cov, dtype=float), regions

    def _base(self, robot: Robot, base_belief: BodyBelief, regions: Regions, registered: bool) -> BaseMeasurement:
        """The base spheres, each predicted from the frame the ones before it conditioned, and their registration."""
        ceiling = 0.0 if registered else self.cfg.max_search_mm
        base, _ = self._measure_body("base", base_belief, robot.base_spheres, robot.sphere_radius_mm,
                                     self.cfg.least_bound_mm, regions, ceiling)
        R_cb, t_cb, rms_b = rigid_fit(robot.base_spheres, np.array([m.centre_mm for m in base]))
        T_cb = np.eye(4)
        T_cb[:3, :3], T_cb[:3, 3] = R_cb, t_cb
        return BaseMeasurement(spheres=base, refined_alignment=T_cb, registration_rms_mm=float(rms_b))

    def measure_base(self, robot: Robot, alignment: np.ndarray, alignment_tolerance: tuple[float, float] | None,
                     platform_pose: np.ndarray, platform_cov: np.ndarray) -> BaseMeasurement:
        """The base spheres alone, the platform not moved (``hilcal check``): its spheres' regions, wherever
        ``platform_pose`` within ``platform_cov`` can put them, are kept clear; the ball ends parked above every place
        a platform sphere can reach."""
        base_belief, _, _, regions = self._start(robot, alignment, np.asarray(platform_pose, dtype=float),
                                                 platform_cov, alignment_tolerance)
        measured = self._base(robot, base_belief, regions, registered=False)
        T_cb = measured.refined_alignment
        above = T_cb[:3, :3].T @ (measured.spheres[-1].centre_mm - T_cb[:3, 3])  # the last sphere, in the base frame
        above[2] = park_height_mm(robot, self.cfg.clearance_mm + self.r)
        self._go(T_cb[:3, :3] @ above + T_cb[:3, 3], list(regions.balls.values()))
        return measured

    def measure_pose(self, robot: Robot, alignment: np.ndarray, expected_pose: np.ndarray | None = None,
                     pose_cov: np.ndarray | None = None, alignment_tolerance: tuple[float, float] | None = None,
                     registered: bool = False) -> PoseMeasurement:
        """The base spheres, then the platform spheres, each predicted from its body's frame as conditioned by the
        spheres before it; the pose from both registrations (see ``CmmInterface.measure_pose``)."""
        cfg = self.cfg
        T0 = as_transform(alignment)
        expected = robot.home if expected_pose is None else np.asarray(expected_pose, dtype=float)
        base_belief, T_bp, cov, regions = self._start(robot, T0, expected, pose_cov, alignment_tolerance)
        touches0 = self.cmm.touches
        measured = self._base(robot, base_belief, regions, registered)
        base, T_cb = measured.spheres, measured.refined_alignment
        if measured.registration_rms_mm > cfg.registration_tol_mm:
            raise PoseMeasurementError(f"base spheres do not match the robot's base sphere layout: registration RMS "
                                       f"{measured.registration_rms_mm:.4f} mm > {cfg.registration_tol_mm} mm")
        platform_belief = BodyBelief.within(T_cb, REGISTERED_MM, REGISTERED_DEG).composed(T_bp, cov)
        platform, _ = self._measure_body("platform", platform_belief, robot.platform_spheres, robot.sphere_radius_mm,
                                         cfg.least_bound_mm, regions)
        base_centres = np.array([m.centre_mm for m in base])
        fit = pose_from_spheres(np.array([m.centre_mm for m in platform]), base_centres, robot)
        if fit.platform_rms_mm > cfg.registration_tol_mm:
            raise PoseMeasurementError(f"platform spheres do not match the robot's platform sphere layout: "
                                       f"registration RMS {float(fit.platform_rms_mm):.4f} mm > "
                                       f"{cfg.registration_tol_mm} mm")
        self._park(robot, T_cb, fit.pose, regions)
        searched = [m.search for m in (*base, *platform) if m.search is not None]
        extra = {"touches": self.cmm.touches - touches0, "searched_spheres": len(searched),
                 "search_touches": sum(s.touches for s in searched),
                 "largest_search_offset_mm": max((s.offset_mm for s in searched), default=0.0)}
        log.info("cmm.pose_measured", pose=fit.pose.tolist(), rms_mm=fit.rms_residual_mm.tolist(), **extra)
        return PoseMeasurement(pose=fit.pose, pose_fit=fit, platform=platform, base=base, alignment=T0,
                               refined_alignment=T_cb, expected_pose=expected, extra=extra)

    def _park(self, robot: Robot, T_cb: np.ndarray, pose: np.ndarray, regions: Regions) -> None:
        """Leave the ball above every place a platform sphere can reach (by the clearance and its own radius), over
        the last one measured: the platform moves next."""
        T = transform_from_pose(pose)
        above = T[:3, :3] @ robot.platform_spheres[-1] + T[:3, 3]
        above[2] = park_height_mm(robot, self.cfg.clearance_mm + self.r)
        self._go(T_cb[:3, :3] @ above + T_cb[:3, 3], list(regions.balls.values()))

    def _measure_body(self, key: str, belief: BodyBelief, points: np.ndarray, r: float, floor: float,
                      regions: Regions, ceiling_mm: float = 0.0) -> tuple[tuple[SphereMeasurement, ...], BodyBelief]:
        """Each sphere of one body in turn, predicted from the frame the spheres before it conditioned."""
        out = []
        reach, margin = r + self.r, self.cfg.route_margin_mm
        for k, s in enumerate(points):
            name = f"{key}{k}"
            pred = dataclasses.replace(belief.predict(s, _up(), floor), ceiling_mm=ceiling_mm)
            regions.balls[name] = Ball(pred.centre_mm, reach + pred.bound_mm + margin)
            m = self.measure_sphere(pred, r, regions.others(name))
            regions.balls[name] = Ball(m.centre_mm, reach + margin)
            belief = belief.condition(s, m.centre_mm, MEASURED_SIGMA_MM)
            for j in range(k + 1, len(points)):
                nxt = belief.predict(points[j], _up(), floor)
                regions.balls[f"{key}{j}"] = Ball(nxt.centre_mm, reach + nxt.bound_mm + margin)
            out.append(m)
        return tuple(out), belief


def _with(m: SphereMeasurement, *, search: SphereSearch | None, nominal: np.ndarray,
          superseded: SphereMeasurement | None = None) -> SphereMeasurement:
    """The measurement as reported: against the original prediction, with its search and first pass."""
    return dataclasses.replace(m, nominal_centre_mm=nominal if superseded is None else m.nominal_centre_mm,
                               superseded=superseded, search=search)


def _finalise(records: list[ProbeRecord], centre: np.ndarray, reach_mm: float) -> tuple[ProbeRecord, ...]:
    """Every record with its residual against the final centre (the ball centres' radius `reach_mm`, R + r)."""
    return tuple(rec if rec.point_mm is None else
                 dataclasses.replace(rec, residual_mm=float(np.linalg.norm(rec.point_mm - centre) - reach_mm))
                 for rec in records)

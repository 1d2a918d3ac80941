"""A recording from several instrument stations: their rigid errors fitted with the diagnosis' model.

Every station but the first (``hilcal.stations``) has a rigid error of its own. The stations' errors come from a
joint least-squares fit (``hilcal.identification`` with the stations projected out) of the geometry, the stations and
the library effects the diagnosis has chosen (none at first); the measured poses are taken back into the first
station's frame and the whole diagnosis runs on them; its choice of library effects gives the next joint fit, until
the stations' errors move by less than a micrometre. The generic shapes stay out of the joint fit: they could take up
any station's error. The diagnosis' final covariance is taken with the stations projected out, so every stated
standard error carries the stations' uncertainty.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import structlog

from hilcal.discovery.context import EffectContext
from hilcal.discovery.screen import unknown_rows
from hilcal.discovery.term_groups import LIBRARY
from hilcal.identification import identify
from hilcal.recording import Recording
from hilcal.robot import Robot
from hilcal.stations import StationFrames, remove_frames

log = structlog.get_logger(__name__)

MAX_PASSES = 4
TOLERANCE_MM = 1e-3
"""The passes stop once no station's error moves by more than this (translation, and rotation at the platform's
length)."""


def _frames(rec: Recording, robot: Robot) -> StationFrames | None:
    mea = rec.select("measure")
    if mea.stations is None:
        return None
    return StationFrames.of(mea.stations, mea.meas, robot.characteristic_length_mm, robot.home[:3])


def _joint(rec: Recording, robot: Robot, groups: list[Any]) -> dict[int, np.ndarray]:
    """The stations' errors of the joint least-squares fit of the geometry, these groups' parameters and the
    stations (projected out, ``hilcal.identification``), on the measure rows where every group's terms are known:
    a row whose motion history is unknown (a session's first) is left out when a group depends on it, as the
    diagnosis leaves it out (`hilcal.discovery.screen`); kept, its unmodelled backlash would move the station of
    that session, and with it the zero shifts that nearly alias the station."""
    mea = rec.select("measure")
    phi, names, known = None, (), np.ones(mea.n, dtype=bool)
    if groups:
        ctx = EffectContext.from_recording(rec, robot).rows(rec.phase == "measure")
        phi = np.concatenate([g.phi(ctx) for g in groups], axis=2)
        names = tuple(n for g in groups for n in g.names)
        known[unknown_rows(groups, ctx).rows] = False
        phi = phi[known]
    return identify(robot, mea.legs_mm[known], mea.meas[known], extra_regressors=phi, extra_names=names,
                    stations=mea.stations[known]).station_frames or {}


def _moved_mm(a: dict[int, np.ndarray], b: dict[int, np.ndarray], length_mm: float) -> float:
    return max((float(np.max(np.abs(np.concatenate([a[s][:3] - b[s][:3], length_mm * (a[s][3:] - b[s][3:])]))))
                for s in a), default=0.0)


def in_base_frame(rec: Recording, robot: Robot, frames: dict[int, np.ndarray]) -> Recording:
    """The recording with every row's station error taken out of its measured pose."""
    meas = remove_frames(rec.meas, rec.stations, frames, robot.characteristic_length_mm, robot.home[:3])
    return dataclasses.replace(rec, meas=meas)


def with_stations(rec: Recording, robot: Robot, run: Callable[[Recording], Any]) -> Any:
    """`run` (a diagnosis of a recording) with the stations' errors fitted alongside (see the module docstring);
    the result gains ``station_frames`` (per station [dt (mm); dw (rad)]). One station, or none: `run(rec)`."""
    if _frames(rec, robot) is None:
        return run(rec)
    estimate = _joint(rec, robot, [])
    diag = run(in_base_frame(rec, robot, estimate))
    for k in range(MAX_PASSES):
        library = [g for g in diag.groups if g.kind == LIBRARY]
        new = _joint(rec, robot, library)
        moved = _moved_mm(new, estimate, robot.characteristic_length_mm)
        log.info("station_pass", n=k + 1, groups=[g.key for g in library], moved_mm=moved)
        if moved < TOLERANCE_MM:
            break
        estimate = new
        diag = run(in_base_frame(rec, robot, estimate))
    return dataclasses.replace(diag, station_frames=estimate)

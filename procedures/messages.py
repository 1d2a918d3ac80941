"""The small messages a procedure yields; the engine executes each and sends back its result.

A procedure is a plain generator (as in Bluesky's plans): it decides *what* to do, the engine decides
*how* (devices, journal, prompts, progress). That split makes journaling, resume and simulation natural.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Prompt:
    """Ask the operator to confirm something; the result is True to go on (always True with --yes)."""

    key: str
    text: str
    detail: dict | None = None
    """What the operator should read before answering (e.g. the upload's parameter diff); shown, not asked."""


@dataclass(frozen=True)
class ReadParams:
    """The controller's live parameter set, its capabilities and (register map 1.1) its live compensation block;
    journaled under `key`, so a resumed run gets the same answer."""

    key: str


@dataclass(frozen=True)
class ReadLegs:
    """The leg lengths the controller reports now (mm)."""


@dataclass(frozen=True)
class PrepareCmm:
    """Get the measuring instrument ready before the first pose: start the CMM session and home it, or initialise the
    laser tracker and set its units, environment and reflector (``drivers.instrument.PoseInstrument.prepare``)."""


@dataclass(frozen=True)
class Enable:
    """Servo on."""


@dataclass(frozen=True)
class Disable:
    """Servo off (required before a parameter upload)."""


@dataclass(frozen=True)
class MoveLegs:
    """Move to leg lengths (mm, controller units); result: the lengths reached."""

    lengths_mm: tuple[float, ...]
    label: str


@dataclass(frozen=True)
class Settle:
    seconds: float


@dataclass(frozen=True)
class Measure:
    """Measure the platform pose with the instrument and journal it before anything else moves; result: the row."""

    phase: str
    index: int
    cmd_pose: tuple[float, ...]
    expected_pose: tuple[float, ...] | None = None
    """Where the run's model of the machine expects the platform (None: at the commanded pose)."""
    pose_cov: tuple[float, ...] | None = None
    """The 36 entries of the expectation's covariance of [dt (mm); dw (rad)] (``hilcal.acquisition.PosePrediction``);
    None: the CMM driver's default uncertainty."""


@dataclass(frozen=True)
class Recall:
    """All journaled measurement rows of these phases, in execution order."""

    phases: tuple[str, ...]


@dataclass(frozen=True)
class Upload:
    """Transactional parameter upload (staging, CRC, read-back, commit, read-back, save), journaled; with a
    compensation block (drivers.controller.parameter_sets.CompensationBlock) the block goes in the same transaction."""

    params: object
    save: bool
    compensation: object | None = None


@dataclass(frozen=True)
class Checkpoint:
    label: str
    data: dict | None = None


def as_tuple(values: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(values).ravel())

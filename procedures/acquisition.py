"""Measuring the machine as it is, during a run: the model that predicts each pose, and the checks that stop a run
before it moves a machine it cannot measure safely.

Before motion the leg readings must lie within the legs' travel and reach a pose. Each measured pose refits the
acquisition model (``hilcal.acquisition.model``: the geometry with gross reading scales, held to the robot file's
``[tolerances]``, its bound widened by what it fails to predict; logged as ``acquisition.widened``); the next pose's
prediction and covariance go with its ``Measure`` message, so the CMM searches only where the platform can be. The
first measured pose is compared with the readings leg by leg: a gross set-up fault is said in a note and measured as
it is, a leg off by more than a quarter of its travel stops the run. A planned pose whose legs the model says would
leave their travel (a transducer that reads short drives its leg beyond it) is skipped with a note. After the upload
the model starts again from the uploaded geometry, with the priors tightened.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import structlog

from hilcal.acquisition.model import MachineBelief, PosePrediction, Priors, predict, prior_belief, refit
from hilcal.kinematics import Geometry, KinematicsError, forward_kinematics, inverse_kinematics
from hilcal.robot import Robot
from procedures.engine import RunInterrupted

log = structlog.get_logger(__name__)

GROSS_FRACTION = 0.25
"""A leg whose reading is off by more than this fraction of its travel at the first pose stops the run."""
NOTE_SIGMAS = 5.0
"""A leg's discrepancy beyond this many of the priors' standard deviations is a gross set-up fault, said in a note."""
REACH_SIGMAS = 2.0
"""A pose is not driven to when the model puts a leg beyond its travel by more than this many standard deviations
(the plan already keeps every setpoint within the travel: only a reading scale can take a leg beyond it)."""
AFTER_UPLOAD_TIGHTENING = 10.0
"""The priors after the upload: the uploaded geometry is known this many times better than the robot file's."""


class MachineNotMeasurable(RunInterrupted):
    """A fault beyond safe acquisition (a dead transducer, a leg far off): the run stops and says what it saw."""


@dataclass
class Acquisition:
    """The run's current model of the machine and what it noted (one per controller geometry: before and after the
    upload)."""

    robot: Robot
    belief: MachineBelief
    notes: list[str] = field(default_factory=list)

    @classmethod
    def start(cls, robot: Robot, a_mm: np.ndarray, b_mm: np.ndarray, l0_mm: np.ndarray, rows: list[dict],
              tightening: float = 1.0) -> Acquisition:
        """The model from the priors, taught the rows measured already one by one, as the run learned them (a resumed
        run's journal: the same model, its record of how each pose fell against its prediction included, and its
        first row checked again: the same notes, or the same stop)."""
        acq = cls(robot, prior_belief(a_mm, b_mm, l0_mm, Priors.of(robot).tightened(tightening)))
        for row in rows:
            acq.learn(row)
        return acq

    @property
    def geometry(self) -> Geometry:
        """The controller's geometry, as its setpoints are computed."""
        b = self.belief
        return Geometry(b.a, b.b, np.zeros(6))

    def check_readings(self, legs_mm: np.ndarray) -> None:
        """Before motion: every reading within its leg's travel and all of them reaching a pose, else stop."""
        legs = np.asarray(legs_mm, dtype=float)
        lo, hi = self.robot.leg_limits
        slack = 0.02 * (hi - lo)
        for i, value in enumerate(legs):
            if not np.isfinite(value) or not lo - slack <= value <= hi + slack:
                raise MachineNotMeasurable(
                    f"leg {i + 1} reads {value:.3f} mm, outside its travel {lo:.1f}-{hi:.1f} mm: its transducer is "
                    "dead or disconnected (check its wiring and the controller's leg order); nothing moved")
        try:
            forward_kinematics(self.geometry_for(legs), legs, self.robot.home)
        except KinematicsError as err:
            raise MachineNotMeasurable(f"the leg readings {np.round(legs, 3).tolist()} mm put the platform at no pose "
                                       f"of the robot file ({err}): check the robot file and the transducers; "
                                       "nothing moved") from None

    def geometry_for(self, legs_mm: np.ndarray) -> Geometry:
        """The model's kinematic geometry for these readings."""
        return self.belief.geometry(legs_mm)

    def expect(self, legs_mm: np.ndarray, guess: np.ndarray) -> PosePrediction | None:
        """Where these readings put the platform under the model (None when the model reaches no pose there)."""
        if self.belief.n_poses:
            guess = self.belief.poses[-1]
        try:
            return predict(self.belief, legs_mm, guess)
        except KinematicsError:
            log.warning("acquisition.no_prediction", legs_mm=np.asarray(legs_mm).tolist())
            return None

    def learn(self, row: dict) -> None:
        """Refit with one more measured pose; at the first pose of the model, the gross-fault check."""
        first = self.belief.n_poses == 0
        legs, meas = np.asarray(row["legs"], dtype=float), np.asarray(row["meas"], dtype=float)
        self.belief = refit(self.belief, np.vstack([self.belief.legs_mm, legs]),
                            np.vstack([self.belief.poses, meas]))
        b = self.belief
        if b.misfit_mm > b.priors.misfit_mm or b.calibration() > 1.0:
            log.info("acquisition.widened", poses=b.n_poses, surprise=b.surprises[-1], misfit_mm=b.misfit_mm,
                     calibration=b.calibration())
        if first:
            self._first_pose(legs, meas)

    def _first_pose(self, legs: np.ndarray, meas: np.ndarray) -> None:
        """Each leg's length by the measured pose against its reading: a note, or a stop beyond safe acquisition."""
        geom = self.geometry
        implied = inverse_kinematics(geom, meas)
        off = implied - legs
        lo, hi = self.robot.leg_limits
        travel = hi - lo
        t = self.robot.tolerances
        stroke = legs - self.belief.l0
        typical = np.sqrt(2.0 * t.joint_mm**2 + t.leg_offset_mm**2 + (t.reading_scale_pct / 100.0 * stroke) ** 2)
        worst = int(np.argmax(np.abs(off)))
        if abs(off[worst]) > GROSS_FRACTION * travel:
            raise MachineNotMeasurable(
                f"leg {worst + 1} reads {abs(off[worst]):.1f} mm {'short' if off[worst] > 0 else 'long'} at the first "
                f"pose (the measured pose makes it {implied[worst]:.3f} mm, it reads {legs[worst]:.3f} mm), more than "
                f"a quarter of its {travel:.0f} mm travel: beyond what a run can measure safely; check its "
                "transducer's zero and gradient and the robot file")
        for i in np.flatnonzero(np.abs(off) > NOTE_SIGMAS * typical):
            self.notes.append(
                f"leg {i + 1} reads {abs(off[i]):.2f} mm {'short' if off[i] > 0 else 'long'} at the first pose (the "
                f"robot file's tolerances allow about {typical[i]:.2f} mm): a gross set-up fault, measured as it is")
        for note in self.notes:
            log.warning("acquisition.gross_fault", note=note)

    def unreachable(self, legs_mm: np.ndarray, what: str) -> str | None:
        """Why these setpoints (rows of six: the approach point and the target) would drive a leg beyond its travel
        under the model (None: they would not)."""
        legs = np.atleast_2d(np.asarray(legs_mm, dtype=float))
        lo, hi = self.robot.leg_limits
        physical = self.belief.physical_lengths_mm(legs)
        sd_k = np.sqrt(np.diag(self.belief.cov)[7::8])
        margin = REACH_SIGMAS * sd_k * np.abs(legs - self.belief.l0)
        over = np.maximum(physical - hi, lo - physical) - margin
        if not (over > 0).any():
            return None
        row, leg = np.unravel_index(int(np.argmax(over)), over.shape)
        gain = 100.0 * self.belief.reading_gain()[leg]
        return (f"{what} is out of reach: under the model measured so far leg {leg + 1} would be at "
                f"{physical[row, leg]:.1f} mm for a setpoint of {legs[row, leg]:.1f} mm (its transducer reads "
                f"{gain:+.2f} % of its stroke), beyond its travel {lo:.1f}-{hi:.1f} mm; not measured")

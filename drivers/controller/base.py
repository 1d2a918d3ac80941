"""Abstract servo-controller interface and its typed errors, in the style of python-can's ``can/bus.py``.

Two roles, each a small interface: ``ControllerInterface`` moves the legs (``hilcal_can.py``: hilcal's own CAN message
set through any python-can interface) and ``ParameterInterface`` reads and writes the geometry and compensation the
controller holds, as a transaction (``modbus.py``). One device may play both roles. Lengths are *controller lengths*
in mm: stroke + the controller's leg offset l0.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from types import TracebackType
from typing import Any, NamedTuple

import numpy as np

from drivers.controller.parameter_sets import CompensationBlock, Identity, ParameterSet, UploadRecord
from hilcal.protocols.controller_states import ControllerState, FaultCode, RefusalReason
from hilcal.robot import Robot

N_LEGS = 6
FOLLOWED_MM = 0.01
"""A leg's reading that changes by less than this during a move that asks more of it did not follow the leg."""


class ControllerError(Exception):
    """Base class of every controller driver error."""


class ControllerLost(ControllerError):
    """No heartbeat from the controller within the timeout: it is not commanded until heartbeats resume."""


class ControllerFault(ControllerError):
    """The controller is in FAULT (or ESTOP, see EStopActive); motion stopped, FAULT_RESET needed. ``legs``: the
    legs (1-based) whose reading did not follow during the move, when the driver could tell."""

    def __init__(self, message: str, state: ControllerState, fault: FaultCode, legs: Sequence[int] = ()) -> None:
        super().__init__(message)
        self.state = state
        self.fault = fault
        self.legs = tuple(legs)


class EStopActive(ControllerFault):
    """The controller is in ESTOP (latched): release the e-stop, then FAULT_RESET."""


class CommandRefused(ControllerError):
    """A command not allowed in the current state, refused by the driver (nothing sent) or by the controller."""

    def __init__(self, message: str, reason: RefusalReason, state: ControllerState | None, by: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.state = state
        self.by = by


class CommandTimeout(ControllerError):
    """The controller did not acknowledge a command in time: it may or may not have executed it."""


class LimitViolation(ControllerError, ValueError):
    """A setpoint outside the robot's leg limits (or not finite): refused before anything is sent."""


class FrameError(ControllerError):
    """A frame that is not a valid controller frame (unknown ID, wrong length, bad checksum)."""


class MotionTimeout(ControllerError):
    """The legs did not reach IN_POSITION within the timeout."""


class MotionAborted(ControllerError):
    """The move ended without IN_POSITION (stopped or disabled by someone else)."""


class PositionMismatch(ControllerError):
    """The controller reported IN_POSITION but its feedback differs from the setpoint beyond the tolerance."""


class Feedback(NamedTuple):
    """Measured controller lengths (mm) with the state and fault code of the same heartbeat."""

    lengths_mm: np.ndarray
    state: ControllerState
    fault: FaultCode


def check_leg_limits(robot: Robot, lengths_mm: Sequence[float] | np.ndarray) -> np.ndarray:
    """The lengths as a (6,) float array; LimitViolation naming every leg outside robot.leg_limits."""
    lengths = np.asarray(lengths_mm, dtype=float)
    if lengths.shape != (N_LEGS,):
        raise LimitViolation(f"expected {N_LEGS} leg lengths, got shape {lengths.shape}")
    lo, hi = robot.leg_limits
    bad = [
        f"leg {i + 1}: {v} mm"
        for i, v in enumerate(lengths)
        if not (np.isfinite(v) and lo <= v <= hi)
    ]
    if bad:
        raise LimitViolation(f"setpoint outside the leg limits [{lo}, {hi}] mm: {', '.join(bad)}; nothing sent")
    return lengths


def legs_not_following(before_mm: np.ndarray, lowest_mm: np.ndarray, highest_mm: np.ndarray,
                       target_mm: np.ndarray) -> list[int]:
    """Legs (1-based) whose reading stayed within FOLLOWED_MM (lowest to highest seen, the reading before the move
    included) although the setpoint was further away, while the reading of another leg asked to move did move."""
    lo = np.minimum(lowest_mm, before_mm)
    hi = np.maximum(highest_mm, before_mm)
    asked = np.abs(np.asarray(target_mm) - before_mm) > FOLLOWED_MM
    still = asked & (hi - lo < FOLLOWED_MM)
    if not (asked & ~still).any():
        return []
    return [int(i) + 1 for i in np.flatnonzero(still)]


def not_following_text(legs: Sequence[int], reading_mm: np.ndarray, target_mm: np.ndarray,
                       leg_limits_mm: tuple[float, float]) -> str:
    """What the driver saw of legs whose reading did not follow, in words (see ``legs_not_following``)."""
    lo, hi = leg_limits_mm

    def values(arr: np.ndarray) -> str:
        return " and ".join(", ".join(f"{arr[k - 1]:.3f}" for k in legs).rsplit(", ", 1)) + " mm"

    def names(ks: Sequence[int]) -> str:
        return " and ".join(", ".join(str(k) for k in ks).rsplit(", ", 1))

    outside = [k for k in legs if not lo <= reading_mm[k - 1] <= hi]
    beyond = "" if not outside else f", outside the leg limits [{lo:g}, {hi:g}] mm," if outside == list(legs) else \
        f" (leg{'s' if len(outside) > 1 else ''} {names(outside)} outside the leg limits [{lo:g}, {hi:g}] mm)"
    if len(legs) == 1:
        return (f"leg {names(legs)} read {values(reading_mm)} throughout{beyond} while its setpoint was "
                f"{values(target_mm)} (the other legs followed): its transducer does not follow the leg "
                "(dead or disconnected)")
    return (f"legs {names(legs)} read {values(reading_mm)} throughout{beyond} while their setpoints were "
            f"{values(target_mm)} (the other legs followed): their transducers do not follow the legs "
            "(dead or disconnected)")


class ControllerInterface(ABC):
    """A servo controller of a 6-leg platform; a context manager that closes the link on exit."""

    @abstractmethod
    def enable(self) -> None:
        """DISABLED -> ENABLED (servo on, holding position)."""

    @abstractmethod
    def disable(self) -> None:
        """ENABLED / MOVING / IN_POSITION -> DISABLED."""

    @abstractmethod
    def stop(self) -> None:
        """Halt motion where the legs are: MOVING -> ENABLED."""

    @abstractmethod
    def fault_reset(self) -> None:
        """FAULT -> DISABLED; ESTOP -> DISABLED once the e-stop is released."""

    @abstractmethod
    def estop(self) -> None:
        """Software e-stop: always sent, whatever the state; latches ESTOP."""

    @abstractmethod
    def move_legs(self, lengths_mm: Sequence[float] | np.ndarray, timeout_s: float) -> np.ndarray:
        """Check the setpoint against the leg limits, send it, wait for IN_POSITION; measured lengths (mm)."""

    @abstractmethod
    def feedback(self) -> Feedback:
        """Latest measured lengths, state and fault code."""

    @property
    @abstractmethod
    def state(self) -> ControllerState:
        """Latest controller state (ControllerLost if the heartbeat is lost)."""

    @abstractmethod
    def close(self) -> None:
        """Release the transport (idempotent)."""

    def __enter__(self) -> ControllerInterface:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class ParameterInterface(ABC):
    """A controller's parameter interface: the geometry and compensation it holds, changed only as a transaction.

    Every operation returns an ``UploadRecord`` (``drivers.controller.parameter_sets``) of each write, the hashes of
    the sets involved, timestamps and read-back results, or raises a ``ParamsError`` carrying it as ``err.record``;
    a failed write puts the old values back. ``endpoint`` and ``device_id`` name the device in records and messages.
    """

    endpoint: str
    device_id: int
    has_backup: bool = True
    """The device keeps the set before the last commit (``rollback`` needs nothing); False: ``rollback`` needs the
    record of the last upload, whose ``previous_params`` it writes back."""

    @abstractmethod
    def read_identity(self) -> Identity:
        """Who the device is and what it can take (IdentityError if it is not a compatible controller)."""

    @abstractmethod
    def read_state(self) -> ControllerState:
        """The controller's state (parameters change only while DISABLED)."""

    @abstractmethod
    def read_live(self) -> ParameterSet:
        """The geometry in use."""

    @abstractmethod
    def read_live_compensation(self) -> CompensationBlock:
        """The compensation block in use (CapabilityError where the device has none)."""

    @abstractmethod
    def read_leg_forces_kn(self) -> np.ndarray:
        """Each leg's axial compression as the controller reads it (kN)."""

    @abstractmethod
    def read_temperature_c(self) -> float:
        """The leg temperature as the controller reads it (°C)."""

    @abstractmethod
    def upload(self, params: ParameterSet | Sequence[float] | np.ndarray, *, save: bool = False,
               compensation: CompensationBlock | None = None) -> UploadRecord:
        """Write, read back and commit a geometry (and a compensation block when given); save=True also saves."""

    @abstractmethod
    def save(self) -> UploadRecord:
        """Copy the live set to non-volatile memory and verify it."""

    @abstractmethod
    def rollback(self, last_upload: UploadRecord | None = None) -> UploadRecord:
        """Put the set in use before the last commit back. A device with a backup uses its own and needs nothing; one
        without writes ``last_upload``'s ``previous_params`` (the caller finds that record in the records) or refuses
        without it."""

    def describe(self) -> dict[str, Any]:
        """Identity, state, live geometry and checksum as plain data (``hilcal check``); a checksum is None where
        the device has none. Raises the driver's ParamsError where a read fails."""
        identity = self.read_identity()
        return {"endpoint": self.endpoint, "identity": identity.as_dict(), "state": self.read_state().name,
                "geometry": self.read_live().model_dump(), "checksum": None}

    @abstractmethod
    def close(self) -> None:
        """Release the transport (idempotent)."""

    def __enter__(self) -> ParameterInterface:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""The controller model as a CANopen device keeps its parameters: no staging, live values changed one at a time, a
stored set in non-volatile memory that power-up and NMT reset node load, and factory values 1011h brings back.

``CanopenController`` is the simulator's ``PersistentController`` (servo, rig, compensation arithmetic, state file)
with the parameter memory of a device without staging banks: a write of one geometry value or compensation term
changes the live set at once, allowed only while the machine is not enabled; 1010h copies the live set into the
stored one (written to the state file before the write is answered); the state file's live set is the stored one,
so a simulator killed in the middle of an upload restarts holding the last stored set. Writes are checked against
the sanity bounds of ``hilcal.protocols.registers`` and ``hilcal.protocols.compensation``; a refusal raises
``ParameterRefused`` with a reason the CANopen adapters turn into an SDO abort code.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from hilcal.protocols.compensation import (
    LIMITS,
    MAX_TABLE_POINTS,
    MIN_TABLE_POINTS,
    NEEDS_FORCE,
    NEEDS_TEMPERATURE,
    TEMPERATURE_RANGE_C,
    block_from_words,
    block_words,
    zero_block,
)
from hilcal.protocols.controller_states import MOTION_STATES
from hilcal.protocols.registers import A_B_LIMIT_MM, L0_INDEX, L0_MAX_MM, L0_MIN_MM
from hilcal.robot import Robot
from sim_devices.controller.state_machine import ControllerSimConfig
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_state import BankState, PersistentController, StateStore

N_LEGS = 6
Reason = Literal["state", "read_only", "range", "unsupported"]


class ParameterRefused(Exception):
    """A parameter write the device refuses: ``reason`` is state (the machine is enabled), read_only (the device
    cannot change it), range (beyond the bounds) or unsupported (a term it cannot apply)."""

    def __init__(self, reason: Reason, message: str) -> None:
        super().__init__(message)
        self.reason: Reason = reason


def _finite_within(value: float, bound: float, what: str) -> None:
    if not (math.isfinite(value) and abs(value) <= bound):
        raise ParameterRefused("range", f"{what} = {value} is not finite or beyond ±{bound:g}")


class CanopenController(PersistentController):
    """The simulated controller with a CANopen device's parameter memory (see the module docstring)."""

    def __init__(self, robot: Robot, rig: SimulatedRig, config: ControllerSimConfig,
                 store: StateStore | None = None, banks: BankState | None = None) -> None:
        super().__init__(robot, rig, config, store, None)
        self._factory = np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0]).astype(np.float32)
        if banks is not None:
            comp = banks.compensation_words()["saved"]
            self.restore_banks(banks.saved, banks.saved, None, banks.commit_counter, banks.save_counter,
                               {"live": comp, "saved": comp, "backup": None})

    def _banks_state(self) -> BankState:
        """The state file holds the stored set only (a device's RAM does not survive a power cut)."""
        if self._bank_state is None or self._bank_state[0] != self.banks_version:
            saved = self.saved_parameters().tolist()
            comp = self.comp_words("saved")
            self._bank_state = (self.banks_version, BankState(
                live=saved, backup=None, saved=saved, commit_counter=self._banks.commit_counter,
                save_counter=self._banks.save_counter, comp_live=comp_hex(comp), comp_backup=None,
                comp_saved=comp_hex(comp)))
        return self._bank_state[1]

    # ------------------------------------------------------------------ checks

    def _check_disabled(self) -> None:
        self._update()
        if self._state in MOTION_STATES:
            raise ParameterRefused("state", f"the controller is {self._state.name}: parameters change only while "
                                            "it is disabled")

    def _changed(self) -> None:
        self._banks.version += 1

    # ------------------------------------------------------------------ geometry

    def write_geometry(self, index: int, value: float) -> None:
        """Set one of the 42 live values (a1x..a6z, b1x..b6z, l0 1..6; mm) at once."""
        with self._lock:
            self._check_disabled()
            if self._banks.capabilities.offsets_only and index < L0_INDEX:
                raise ParameterRefused("read_only", "this controller holds only the leg offsets: a and b are fixed")
            if index >= L0_INDEX:
                if not (math.isfinite(value) and L0_MIN_MM <= value <= L0_MAX_MM):
                    raise ParameterRefused("range", f"l0 = {value} mm is outside [{L0_MIN_MM}, {L0_MAX_MM}] mm")
            else:
                _finite_within(value, A_B_LIMIT_MM, "a joint coordinate")
            self._banks.live[index] = np.float32(value)
            self._changed()

    def geometry(self, which: Literal["live", "saved"] = "live") -> np.ndarray:
        """The 42 float32 values (mm) of the live or the stored set."""
        with self._lock:
            return (self._banks.live if which == "live" else self._banks.saved).astype(np.float32).copy()

    # ------------------------------------------------------------------ compensation

    def block(self, which: Literal["live", "saved"] = "live") -> dict[str, Any]:
        """The live or stored compensation block, decoded."""
        with self._lock:
            return block_from_words(self._banks.comp_live if which == "live" else self._banks.comp_saved)

    def _set_block(self, block: dict[str, Any]) -> None:
        self._banks.comp_live = block_words(block)
        self._changed()

    def _check_comp(self) -> dict[str, Any]:
        self._check_disabled()
        if not self._banks.capabilities.compensation:
            raise ParameterRefused("unsupported", "this controller has no compensation block")
        return block_from_words(self._banks.comp_live)

    def write_term(self, name: str, leg: int, value: float) -> None:
        """Set one leg's (0-based) compensation term of ``LEG_FIELDS`` at once."""
        with self._lock:
            block = self._check_comp()
            _finite_within(value, LIMITS[name], name)
            caps = self._banks.capabilities
            if value != 0.0 and ((name in NEEDS_FORCE and not caps.force_reading)
                                 or (name in NEEDS_TEMPERATURE and not caps.temperature_reading)):
                raise ParameterRefused("unsupported", f"{name} needs a sensor reading this controller does not have")
            block[name][leg] = float(np.float32(value))
            self._set_block(block)

    def write_reference_temperature(self, value: float) -> None:
        with self._lock:
            block = self._check_comp()
            lo, hi = TEMPERATURE_RANGE_C
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ParameterRefused("range", f"reference temperature {value} °C is outside {TEMPERATURE_RANGE_C}")
            block["reference_temperature_c"] = float(np.float32(value))
            self._set_block(block)

    def write_table_points(self, points: int) -> None:
        """Set the number of stroke-table points: every leg's table is cut or padded with zeros to it."""
        with self._lock:
            block = self._check_comp()
            if not (points == 0 or MIN_TABLE_POINTS <= points <= MAX_TABLE_POINTS):
                raise ParameterRefused("range", f"table points must be 0 or {MIN_TABLE_POINTS}..{MAX_TABLE_POINTS}")
            block["table_points"] = points
            block["table_mm"] = [(list(row) + [0.0] * points)[:points] for row in block["table_mm"]]
            self._set_block(block)

    def write_table(self, leg: int, values: Sequence[float]) -> None:
        """Set one leg's (0-based) stroke table (as many values as there are table points)."""
        with self._lock:
            block = self._check_comp()
            if len(values) != block["table_points"]:
                raise ParameterRefused("range", f"the table has {block['table_points']} points, got {len(values)}")
            for v in values:
                _finite_within(float(v), LIMITS["table_mm"], "a table value")
            block["table_mm"][leg] = [float(np.float32(v)) for v in values]
            self._set_block(block)

    # ------------------------------------------------------------------ non-volatile memory

    def store(self, indices: Sequence[int] | None = None) -> None:
        """1010h: the live set (or only these of the 42 values) becomes the stored one, in the state file before
        this returns."""
        with self._lock:
            self._check_disabled()
            if indices is None:
                self._banks.saved = self._banks.live.copy()
                self._banks.comp_saved = list(self._banks.comp_live)
            else:
                for i in indices:
                    self._banks.saved[i] = self._banks.live[i]
            self._banks.save_counter += 1
            self._changed()
            self.save_state()

    def restore_factory(self, indices: Sequence[int] | None = None) -> None:
        """1011h: the stored set (or these of the 42 values) becomes the factory one (the robot file's geometry, no
        compensation); it is loaded at the next reset."""
        with self._lock:
            if indices is None:
                self._banks.saved = self._factory.copy()
                self._banks.comp_saved = block_words(zero_block())
            else:
                for i in indices:
                    self._banks.saved[i] = self._factory[i]
            self._changed()
            self.save_state()

    def load_stored(self, indices: Sequence[int] | None = None) -> None:
        """Power-up or NMT reset node: the live set (or these of the 42 values) is loaded from the stored one."""
        with self._lock:
            if indices is None:
                self._banks.live = self._banks.saved.copy()
                self._banks.comp_live = list(self._banks.comp_saved)
            else:
                for i in indices:
                    self._banks.live[i] = self._banks.saved[i]
            self._changed()

    @property
    def store_count(self) -> int:
        return self._banks.save_counter

    def leg_limits_mm(self) -> tuple[float, float]:
        return self.robot.leg_limits

    def is_enabled(self) -> bool:
        """True in a motion state (ENABLED, MOVING, IN_POSITION)."""
        return self.snapshot().state in MOTION_STATES


def comp_hex(words: Sequence[int]) -> str:
    """Registers as the state file keeps them (hex of big-endian 16-bit words)."""
    return b"".join(int(w).to_bytes(2, "big") for w in words).hex()


"""The simulated controller's parameter memory: the geometry set and the compensation block, each in four banks.

Live, staging, backup and saved (non-volatile) banks of the 42-value geometry (``hilcal.protocols.registers``) and,
with the COMPENSATION capability, of the compensation block (``hilcal.protocols.compensation``). One transaction
covers both: OPEN_STAGING copies both live banks into staging; COMMIT checks every written register and both CRCs
and swaps both at once (the previous live pair becomes the backup); ROLLBACK swaps both back; SAVE copies both. A
host that writes only the geometry (register map 1.0) leaves the block as it is. Not thread-safe on its own: the
controller calls it under its lock and checks that it is DISABLED first.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import structlog

from hilcal.protocols.compensation import (
    BLOCK_REGISTERS,
    block_from_words,
    block_violations,
    block_words,
    zero_block,
)
from hilcal.protocols.registers import (
    L0_INDEX,
    L0_REGISTERS,
    PARAMETER_COUNT,
    PARAMETER_REGISTERS,
    REGISTERS_PER_FLOAT,
    ParamCommand,
    ParamStatus,
    crc32_of_words,
    floats_from_words,
    parameter_limit_violations,
    words_from_floats,
)

log = structlog.get_logger(__name__)

Bank = Literal["live", "backup", "saved", "staging"]
ZERO_BLOCK_WORDS = tuple(block_words(zero_block()))


class StagingWriteRefused(Exception):
    """A staging write the controller's capabilities do not allow (mapped to a Modbus exception)."""


@dataclass(frozen=True)
class BankCapabilities:
    """What the parameter memory accepts: the whole geometry or the leg offsets only, a compensation block, and
    which sensor readings its terms may use."""

    offsets_only: bool = False
    compensation: bool = True
    force_reading: bool = True
    temperature_reading: bool = True


@dataclass
class ParameterBanks:
    """Geometry (float32 values) and compensation block (registers) banks, staging and the transaction's state."""

    live: np.ndarray
    saved: np.ndarray
    capabilities: BankCapabilities = field(default_factory=BankCapabilities)
    backup: np.ndarray | None = None
    comp_live: list[int] = field(default_factory=lambda: list(ZERO_BLOCK_WORDS))
    comp_saved: list[int] = field(default_factory=lambda: list(ZERO_BLOCK_WORDS))
    comp_backup: list[int] | None = None
    staging: list[int] = field(default_factory=list)
    comp_staging: list[int] = field(default_factory=lambda: list(ZERO_BLOCK_WORDS))
    written: set[int] = field(default_factory=set)
    comp_written: set[int] = field(default_factory=set)
    staged_length: int = 0
    staged_crc_words: list[int] = field(default_factory=lambda: [0, 0])
    staged_comp_crc_words: list[int] = field(default_factory=lambda: [0, 0])
    status: ParamStatus = ParamStatus.NO_COMMAND
    commit_counter: int = 0
    save_counter: int = 0
    version: int = 0
    """+1 on every change of a live, backup or saved bank (callers cache what they derive from them)."""

    def __post_init__(self) -> None:
        if not self.staging:
            self.staging = words_from_floats(self.live.tolist())

    # ------------------------------------------------------------------ reads

    def words(self, bank: Bank) -> list[int]:
        """A geometry bank as 84 registers (ABCD float32); a missing backup reads as zeros."""
        if bank == "staging":
            return list(self.staging)
        values = getattr(self, bank)
        return [0] * PARAMETER_REGISTERS if values is None else words_from_floats(values.tolist())

    def crc32(self, bank: Literal["live", "backup", "saved"]) -> int:
        if bank == "backup" and self.backup is None:
            return 0
        return crc32_of_words(self.words(bank))

    def comp_words(self, bank: Bank) -> list[int]:
        """A compensation bank as registers; a missing backup reads as zeros."""
        words = getattr(self, f"comp_{bank}")
        return [0] * BLOCK_REGISTERS if words is None else list(words)

    def comp_crc32(self, bank: Literal["live", "backup", "saved"]) -> int:
        words = getattr(self, f"comp_{bank}")
        return 0 if words is None else crc32_of_words(words)

    def live_block(self) -> dict[str, Any]:
        """The live compensation block, decoded."""
        return block_from_words(self.comp_live)

    # ------------------------------------------------------------------ staging

    def write_staging(self, offset: int, words: Sequence[int]) -> None:
        """Registers into the geometry staging bank; an offsets-only memory takes the l0 part only."""
        if offset < 0 or offset + len(words) > PARAMETER_REGISTERS:
            raise StagingWriteRefused(f"staging offset {offset}+{len(words)} is outside 0..{PARAMETER_REGISTERS}")
        if self.capabilities.offsets_only and offset < L0_INDEX * REGISTERS_PER_FLOAT:
            raise StagingWriteRefused("offsets-only controller: a/b staging registers are read-only")
        for k, w in enumerate(words):
            self.staging[offset + k] = int(w) & 0xFFFF
            self.written.add(offset + k)

    def write_comp_staging(self, offset: int, words: Sequence[int]) -> None:
        """Registers into the compensation staging bank."""
        if not self.capabilities.compensation:
            raise StagingWriteRefused("this controller has no compensation block")
        if offset < 0 or offset + len(words) > BLOCK_REGISTERS:
            raise StagingWriteRefused(f"compensation staging offset {offset}+{len(words)} is outside "
                                      f"0..{BLOCK_REGISTERS}")
        for k, w in enumerate(words):
            self.comp_staging[offset + k] = int(w) & 0xFFFF
            self.comp_written.add(offset + k)

    def write_header(self, length: int | None, crc_words: Sequence[int | None],
                     comp_crc_words: Sequence[int | None] = (None, None)) -> None:
        """STAGED_LENGTH, STAGED_CRC32 and STAGED_COMP_CRC32 (None leaves a value unchanged)."""
        if length is not None:
            self.staged_length = int(length) & 0xFFFF
        for target, values in ((self.staged_crc_words, crc_words), (self.staged_comp_crc_words, comp_crc_words)):
            for k, w in enumerate(values):
                if w is not None:
                    target[k] = int(w) & 0xFFFF

    # ------------------------------------------------------------------ commands

    def command(self, command: ParamCommand) -> ParamStatus:
        """Execute a parameter command (the caller has checked that the controller is DISABLED)."""
        if command is ParamCommand.OPEN_STAGING:
            self.staging = words_from_floats(self.live.tolist())
            self.comp_staging = list(self.comp_live)
            self.written.clear()
            self.comp_written.clear()
            self.staged_length = 0
            self.staged_crc_words = [0, 0]
            self.staged_comp_crc_words = [0, 0]
            return ParamStatus.OK
        if command is ParamCommand.SAVE:
            self.saved = self.live.copy()
            self.comp_saved = list(self.comp_live)
            self.save_counter += 1
            self.version += 1
            return ParamStatus.OK
        if command is ParamCommand.ROLLBACK:
            if self.backup is None:
                return ParamStatus.NO_BACKUP
            self.live, self.backup = self.backup, self.live
            self.comp_live, self.comp_backup = self.comp_backup or list(ZERO_BLOCK_WORDS), self.comp_live
            self.commit_counter += 1
            self.version += 1
            return ParamStatus.OK
        return self._commit()

    def _commit(self) -> ParamStatus:
        l0_start = L0_INDEX * REGISTERS_PER_FLOAT
        offsets_only = self.capabilities.offsets_only
        required = set(range(l0_start, l0_start + L0_REGISTERS)) if offsets_only else set(range(PARAMETER_REGISTERS))
        if not required <= self.written:
            return ParamStatus.INCOMPLETE_STAGING
        if self.staged_length != len(self.written) + len(self.comp_written):
            return ParamStatus.LENGTH_MISMATCH
        if crc32_of_words(self.staging) != (self.staged_crc_words[0] << 16 | self.staged_crc_words[1]):
            return ParamStatus.CRC_MISMATCH
        if self.comp_written and crc32_of_words(self.comp_staging) != (
                self.staged_comp_crc_words[0] << 16 | self.staged_comp_crc_words[1]):
            return ParamStatus.CRC_MISMATCH
        values = np.asarray(floats_from_words(self.staging), dtype=np.float32)
        if not np.isfinite(values).all():
            return ParamStatus.NOT_FINITE
        if parameter_limit_violations(values.tolist()):
            return ParamStatus.LIMIT_VIOLATION
        if offsets_only and not np.array_equal(values[:L0_INDEX], self.live[:L0_INDEX]):
            return ParamStatus.CAPABILITY_VIOLATION
        status = self._check_block()
        if status is not ParamStatus.OK:
            return status
        self.backup, self.live = self.live, values
        self.comp_backup, self.comp_live = self.comp_live, list(self.comp_staging)
        self.commit_counter += 1
        self.version += 1
        self.written.clear()
        self.comp_written.clear()
        self.staged_length = 0
        self.staged_crc_words = [0, 0]
        self.staged_comp_crc_words = [0, 0]
        log.info("parameters_committed", crc32=hex(crc32_of_words(words_from_floats(values.tolist()))),
                 compensation_crc32=hex(crc32_of_words(self.comp_live)))
        return ParamStatus.OK

    def _check_block(self) -> ParamStatus:
        """The staged block's layout, values and the sensor readings its terms need."""
        if not self.comp_written:
            return ParamStatus.OK
        try:
            block = block_from_words(self.comp_staging)
        except ValueError as err:
            log.info("compensation_refused", reason=str(err))
            return ParamStatus.LIMIT_VIOLATION
        values = [v for name, value in block.items() if name != "table_points"
                  for v in (value if isinstance(value, list) else [value])]
        if not np.isfinite(np.concatenate([np.ravel(np.asarray(v, dtype=float)) for v in values])).all():
            return ParamStatus.NOT_FINITE
        problems = block_violations(block, force_reading=self.capabilities.force_reading,
                                    temperature_reading=self.capabilities.temperature_reading)
        if problems:
            log.info("compensation_refused", reasons=problems)
            unsupported = block_violations(block)
            return ParamStatus.LIMIT_VIOLATION if unsupported else ParamStatus.NOT_SUPPORTED
        return ParamStatus.OK

    # ------------------------------------------------------------------ set-up

    def install(self, values: Sequence[float]) -> None:
        """Service-tool path: replace live and saved geometry without a transaction (the block is kept)."""
        v = np.asarray(values, dtype=np.float32)
        if v.shape != (PARAMETER_COUNT,) or parameter_limit_violations(v.tolist()):
            raise ValueError(f"not a valid {PARAMETER_COUNT}-value parameter set")
        self.live = v.copy()
        self.saved = v.copy()
        self.backup = None
        self.comp_backup = None
        self.version += 1

    def restore(self, live: Sequence[float], saved: Sequence[float], backup: Sequence[float] | None,
                commit_counter: int, save_counter: int, comp: dict[str, list[int] | None] | None = None) -> None:
        """Put back banks kept outside the process (non-volatile state across a restart)."""
        self.live = np.asarray(live, dtype=np.float32)
        self.saved = np.asarray(saved, dtype=np.float32)
        self.backup = None if backup is None else np.asarray(backup, dtype=np.float32)
        self.staging = words_from_floats(self.live.tolist())
        self.commit_counter = commit_counter
        self.save_counter = save_counter
        comp = comp or {}
        self.comp_live = list(comp.get("live") or ZERO_BLOCK_WORDS)
        self.comp_saved = list(comp.get("saved") or ZERO_BLOCK_WORDS)
        self.comp_backup = None if self.backup is None else list(comp.get("backup") or ZERO_BLOCK_WORDS)
        self.comp_staging = list(self.comp_live)
        self.version += 1

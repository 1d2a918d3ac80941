"""The parameter transaction of a device without staging (register map ``transaction = "direct"``), as far as such a
device allows one: ``ControllerParams`` has already refused unless the device is disabled (where the map has a state
register) and recorded the old set; here the new values are written to the live registers, read back (with the
checksum register where the map has one) and, on any failure, the old set is written back and read back; the record
and the error say which writes happened and what the device holds afterwards.

Rollback writes the set before the last upload back, from the first of: the device's backup registers (where the map
has them), the set the caller passes (``hilcal rollback`` takes it from the records: the upload record's
``previous_live_sha256`` names it), the set this driver replaced in its last upload. A device that keeps no backup
cannot swap atomically: the same write, read back, restore-on-failure sequence carries the rollback.
"""

from __future__ import annotations

from drivers.controller.modbus_codec import Block, bank_blocks, geometry_words, sha_of_vector
from drivers.controller.parameter_sets import ParameterSet, ParamsError, UploadRecord, UploadRefused
from hilcal.protocols.registers import ParamStatus, crc32_of_words

Words = dict[str, list[int]]


def _differing(old: list[int], now: list[int], per: int) -> list[tuple[int, list[int]]]:
    """(offset, old registers) of every run of whole values whose registers differ between ``old`` and ``now``."""
    runs: list[tuple[int, list[int]]] = []
    for k in range(0, len(old), per):
        if old[k:k + per] == now[k:k + per]:
            continue
        if runs and runs[-1][0] + len(runs[-1][1]) == k:
            runs[-1][1].extend(old[k:k + per])
        else:
            runs.append((k, list(old[k:k + per])))
    return runs


def _writes_text(record: UploadRecord, first: int) -> str:
    done = record.writes[first:]
    if not done:
        return "no write was sent"
    return "writes: " + ", ".join(f"0x{w.address:04X}+{w.count} {'ok' if w.ok else 'failed'}" for w in done)


class DirectTransaction:
    """Mixin of ``ControllerParams`` (whose requests, banks and records it uses): upload and rollback for a map with
    ``transaction = "direct"``."""

    def __init__(self) -> None:
        self._replaced: tuple[Words, list[int] | None] | None = None
        """(live registers, live block) this driver replaced in its last direct upload."""

    def _direct_upload(self, record: UploadRecord, old: Words, words: Words,
                       parts: list[str] | None, comp_words: list[int] | None) -> None:
        m = self.map
        old_comp = None if comp_words is None else self._comp_read("live")
        blocks: list[Block] = bank_blocks(m, "live", words, parts)
        if comp_words is not None:
            blocks.append((m.compensation.live, comp_words))  # type: ignore[union-attr]
        first = len(record.writes)
        try:
            self._write_blocks(record, blocks)
            self._check_live(record, self._flat(words), comp_words,
                             "live set read back after writing differs from the uploaded set")
        except ParamsError as err:
            sent = _writes_text(record, first)
            restored = self._restore(record, old, old_comp)
            err.args = (f"{err}; {sent}; {restored}",)
            raise
        self._replaced = (old, old_comp)

    def _restore(self, record: UploadRecord, old: Words, old_comp: list[int] | None) -> str:
        """Write back every whole value that differs from the old set, read back; what the device holds, in words."""
        m = self.map
        first = len(record.writes)
        try:
            now = self._bank_parts("live")
            blocks: list[Block] = []
            for p in m.parts():
                per = p.registers // p.values
                blocks += [(p.banks["live"] + k, w) for k, w in _differing(old[p.name], now[p.name], per)]
            if old_comp is not None:
                blocks += [(m.compensation.live + k, w)  # type: ignore[union-attr]
                           for k, w in _differing(old_comp, self._comp_read("live"), 2)]
            self._write_blocks(record, blocks)
            after = self._bank_parts("live")
            record.live_after_sha256 = self._sha(after)
            same = self._flat(after) == self._flat(old) and (old_comp is None or self._comp_read("live") == old_comp)
        except ParamsError as err:
            return (f"writing the old set back failed ({type(err).__name__}: {err}; {_writes_text(record, first)}): "
                    "the device may hold a mix of the old and new sets; upload again or roll back")
        if not same:
            return ("the old set was written back but reads back different: the device may hold a mix of the old and "
                    "new sets; upload again or roll back")
        return (f"the old set was written back ({_writes_text(record, first)}) and read back: the device holds the old "
                "set")

    def _sha(self, words: Words) -> str:
        return sha_of_vector(self._vector(words))

    def _direct_rollback(self, previous: ParameterSet | None) -> UploadRecord:
        record, identity, live = self._begin("rollback")
        m = self.map
        try:
            comp = None
            if m.geometry.l0.backup is not None:
                target = self._bank_parts("backup")
                if identity.compensation and m.compensation is not None and m.compensation.backup is not None:
                    comp = self._comp_read("backup")
            elif previous is not None:
                target = geometry_words(m, self.device_set(previous).to_vector())
            elif self._replaced is not None:
                target, comp = self._replaced
            else:
                raise UploadRefused(f"register map {m.device.name} keeps no backup registers and no set to put back "
                                    "was given: pass the set before the last upload (hilcal rollback takes it from "
                                    "the records); nothing written", ParamStatus.NO_BACKUP)
            record.params_sha256 = self._sha(target)
            record.params_crc32 = f"{crc32_of_words(self._flat(target)):08x}"
            parts = self._geometry_parts(identity, self._vector(live), self._vector(target))
            self._direct_upload(record, live, target, parts, comp)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "rolled_back")
        return record

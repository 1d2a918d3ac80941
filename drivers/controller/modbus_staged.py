"""The parameter transaction of a device with staging banks (register map ``transaction = "staged"``, hilcal's own
map among them; docs/protocols.md): OPEN_STAGING, write the staging banks (geometry and compensation block), write the
staged length and checksums, read staging back, COMMIT, read live back. The device swaps the staged set in atomically
and keeps the previous one as backup, so the live set is always the old or the new one; ROLLBACK swaps them back.
"""

from __future__ import annotations

from drivers.controller.modbus_codec import Block, bank_blocks, merge, sha_of_vector, sha_of_words, u32_words
from drivers.controller.parameter_sets import ParamsError, ReadbackMismatch, UploadRecord
from hilcal.protocols.registers import crc32_of_words


class StagedTransaction:
    """Mixin of ``ControllerParams`` (whose requests, banks and records it uses): upload and rollback for a map with
    ``transaction = "staged"``."""

    def _staged_upload(self, record: UploadRecord, words: dict[str, list[int]], parts: list[str] | None,
                       comp_words: list[int] | None) -> None:
        m = self.map
        blocks = bank_blocks(m, "staging", words, parts)
        comp_blocks = [] if comp_words is None else [(m.compensation.staging, comp_words)]  # type: ignore[union-attr]
        record.staged_registers = sum(len(w) for _, w in blocks) + (0 if comp_words is None else len(comp_words))
        self._command(record, "open_staging")
        self._write_blocks(record, blocks)
        self._write_blocks(record, comp_blocks)
        flat = self._flat(words)
        header: list[Block] = []
        if m.staging is not None and m.staging.length is not None:
            header.append((m.staging.length, [record.staged_registers]))
        if m.checksum is not None and m.checksum.staged is not None:
            header.append((m.checksum.staged, u32_words(m, crc32_of_words(flat))))
        comp_sums = m.compensation.checksum if m.compensation else None
        if comp_words is not None and comp_sums is not None and comp_sums.staged is not None:
            header.append((comp_sums.staged, u32_words(m, crc32_of_words(comp_words))))
        for address, values in merge(header):
            self._write(record, address, values)
        self._compare(record, "staging", self._flat(self._bank_parts("staging")), flat)
        if comp_words is not None:
            self._compare(record, "compensation staging", self._comp_read("staging"), comp_words)
        self._command(record, "commit")
        self._check_live(record, flat, comp_words, "live set read back after COMMIT differs from the uploaded set")

    @staticmethod
    def _compare(record: UploadRecord, what: str, read: list[int], written: list[int]) -> None:
        match = read == written
        if what == "staging":
            record.staging_readback_match = match
        else:
            record.staging_readback_match = bool(record.staging_readback_match) and match
        if not match:
            bad = [k for k, (a, b) in enumerate(zip(read, written, strict=True)) if a != b]
            raise ReadbackMismatch(f"{what} read-back differs at registers {bad[:8]}; not committed")

    def _staged_rollback(self) -> UploadRecord:
        record, identity, _ = self._begin("rollback")
        try:
            backup_parts = self._bank_parts("backup")
            backup = self._flat(backup_parts)
            record.params_sha256 = sha_of_vector(self._vector(backup_parts))
            record.params_crc32 = f"{crc32_of_words(backup):08x}"
            comp_backup = self._comp_read("backup") if identity.compensation else None
            if comp_backup is not None:
                record.compensation_sha256 = sha_of_words(comp_backup)
            self._command(record, "rollback")
            self._check_live(record, backup, comp_backup, "live set after ROLLBACK is not the former backup")
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "rolled_back")
        return record

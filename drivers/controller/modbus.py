"""Modbus driver of the controller's parameter interface (pymodbus client; Modbus TCP or RTU), by a register map.

The register map (``hilcal.protocols.modbus_map``; default: hilcal's own ``hilcal-1.1``) says where everything is and
which transaction the device takes. ``transaction = "staged"`` (see docs/protocols.md): refuse unless DISABLED;
OPEN_STAGING; write the staging banks in chunks (the geometry and, where the map has one, the compensation block);
write the staged length and checksums; read staging back and compare; COMMIT (the device swaps the set in atomically,
keeping the previous one as backup); read live back and compare. ``save`` and ``rollback`` are commands of their own.
``transaction = "direct"`` (a device without staging: ``modbus_direct.py``): refuse unless disabled, record the old
set, write live, read back, on any failure write the old set back. Requests are never retried (retries=0): a write
whose answer was lost may have been executed, so the caller starts a new upload. Every operation returns (or attaches
to its exception) an ``UploadRecord``; ``records`` keeps them all. ``describe()`` is what ``hilcal check`` shows.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import structlog

from drivers.controller.base import ParameterInterface
from drivers.controller.modbus_codec import (
    Block,
    chunks,
    field_value,
    geometry_vector,
    geometry_words,
    sha_of_vector,
    sha_of_words,
    spans,
    u32_value,
)
from drivers.controller.modbus_direct import DirectTransaction
from drivers.controller.modbus_staged import StagedTransaction
from drivers.controller.parameter_sets import (
    CapabilityError,
    CompensationBlock,
    Identity,
    IdentityError,
    ModbusExceptionResponse,
    ModbusTransportError,
    NotDisabled,
    ParameterSet,
    ParameterValidationError,
    ParamsError,
    ReadbackMismatch,
    UploadRecord,
    UploadRefused,
    WriteRecord,
    now_utc,
)
from hilcal.protocols.compensation import BLOCK_REGISTERS
from hilcal.protocols.controller_states import ControllerState
from hilcal.protocols.modbus_map import RegisterMap, default_register_map, load_register_map
from hilcal.protocols.registers import (
    MAX_WRITE_REGISTERS,
    PARAMETER_COUNT,
    Capability,
    ParamStatus,
    crc32_of_words,
)

if TYPE_CHECKING:
    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

__all__ = [
    "CapabilityError", "CompensationBlock", "ControllerParams", "Identity", "IdentityError", "ModbusExceptionResponse",
    "ModbusTransportError", "NotDisabled", "ParameterSet", "ParameterValidationError", "ParamsError",
    "ReadbackMismatch", "UploadRecord", "UploadRefused", "WriteRecord",
]

log = structlog.get_logger(__name__)

DEFAULT_CHUNK_REGISTERS = 64
EXCEPTION_MEANING = {
    1: "ILLEGAL FUNCTION: the device does not take this function code",
    2: "ILLEGAL DATA ADDRESS: no such register, or not writable, on this device (check the map's address)",
    3: "ILLEGAL DATA VALUE: the device refused the value or the quantity",
    4: "SERVER DEVICE FAILURE: the device failed while carrying out the request",
    5: "ACKNOWLEDGE: accepted, still being processed",
    6: "SERVER DEVICE BUSY: try again later",
    8: "MEMORY PARITY ERROR",
    10: "GATEWAY PATH UNAVAILABLE",
    11: "GATEWAY TARGET DEVICE FAILED TO RESPOND: no device answers at this device id",
}
"""Modbus exception codes (MODBUS Application Protocol v1.1b3, 7)."""


class ControllerParams(StagedTransaction, DirectTransaction, ParameterInterface):
    """The controller's Modbus parameter interface; TCP (``host``/``port``) or RTU (``serial_port``).

    ``register_map``: a ``RegisterMap``, a built-in map's name or a map file's path (None: ``hilcal-1.1``); an invalid
    map raises ``RegisterMapError`` here, before anything is sent. ``nominal``: the values of the geometry parts the
    device does not hold (the robot file's nominal set), required when the map holds the leg offsets alone.
    """

    def __init__(
        self,
        host: str | None = None,
        port: int = 502,
        *,
        serial_port: str | None = None,
        baudrate: int = 115200,
        device_id: int = 1,
        timeout_s: float = 1.0,
        chunk_registers: int = DEFAULT_CHUNK_REGISTERS,
        register_map: RegisterMap | str | Path | None = None,
        nominal: ParameterSet | None = None,
    ) -> None:
        if (host is None) == (serial_port is None):
            raise ValueError("give either host (Modbus TCP) or serial_port (Modbus RTU)")
        if not 1 <= chunk_registers <= MAX_WRITE_REGISTERS:
            raise ValueError(f"chunk_registers must be 1..{MAX_WRITE_REGISTERS}")
        self.map = (default_register_map() if register_map is None else register_map
                    if isinstance(register_map, RegisterMap) else load_register_map(register_map))
        if self.map.held_values() < PARAMETER_COUNT and nominal is None:
            raise ValueError(f"register map {self.map.device.name} holds the leg offsets alone: give nominal= (the "
                             "robot's nominal set) for the joint coordinates a and b")
        self.fill = np.zeros(PARAMETER_COUNT) if nominal is None else nominal.to_vector()
        from pymodbus import FramerType  # here, not at the top: the records and the engine use only the models
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        self.device_id = device_id
        self.chunk_registers = min(chunk_registers, self.map.device.max_write_registers)
        self.records: list[UploadRecord] = []
        self._client: ModbusTcpClient | ModbusSerialClient
        if host is not None:
            self.endpoint = f"tcp://{host}:{port}"
            self._client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)
        else:
            assert serial_port is not None
            self.endpoint = f"rtu://{serial_port}@{baudrate}"
            self._client = ModbusSerialClient(
                serial_port, framer=FramerType.RTU, baudrate=baudrate, timeout=timeout_s, retries=0
            )
        super().__init__()

    def close(self) -> None:
        self._client.close()

    # ------------------------------------------------------------------ requests

    def _request(self, what: str, call: Callable[..., Any], address: int, **kwargs: Any) -> Any:
        from pymodbus.exceptions import ModbusException

        try:
            response = call(address, device_id=self.device_id, **kwargs)
        except ModbusException as err:
            self._client.close()
            raise ModbusTransportError(f"{what} at 0x{address:04X} ({address}): {err}") from err
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            meaning = EXCEPTION_MEANING.get(code, "not a code of the Modbus specification")
            raise ModbusExceptionResponse(f"{what} at 0x{address:04X} ({address}): Modbus exception {code} ({meaning})",
                                          response.function_code & 0x7F, address, code)
        return response

    def _read(self, address: int, count: int, what: str = "read") -> list[int]:
        out: list[int] = []
        step = self.map.device.max_read_registers
        for start in range(address, address + count, step):
            n = min(step, address + count - start)
            response = self._request(what, self._client.read_holding_registers, start, count=n)
            registers = list(response.registers)
            if len(registers) != n:
                self._client.close()
                raise ModbusTransportError(f"{what} at 0x{start:04X}: {len(registers)} registers instead of {n}")
            out.extend(registers)
        return out

    def _read_many(self, wanted: Sequence[tuple[int, int]], what: str) -> dict[int, int]:
        """Registers of several spans (adjacent ones in one request) by address."""
        out: dict[int, int] = {}
        for address, count in spans(wanted):
            out.update(zip(range(address, address + count), self._read(address, count, what), strict=True))
        return out

    def _write(self, record: UploadRecord | None, address: int, values: Sequence[int]) -> None:
        single = len(values) == 1
        entry = WriteRecord(
            function="write_register" if single else "write_registers", address=address, count=len(values), at=now_utc()
        )
        if record is not None:
            record.writes.append(entry)
        try:
            if single:
                self._request("write", self._client.write_register, address, value=int(values[0]))
            else:
                self._request("write", self._client.write_registers, address, values=[int(v) for v in values])
        except ParamsError as err:
            entry.error = str(err)
            raise
        entry.ok = True

    def _write_blocks(self, record: UploadRecord | None, blocks: Sequence[Block]) -> None:
        for address, words in chunks(blocks, self.chunk_registers):
            self._write(record, address, words)

    # ------------------------------------------------------------------ the map's banks

    def _bank_parts(self, bank: str, parts: Sequence[str] | None = None) -> dict[str, list[int]]:
        """The held geometry parts' registers in one bank (CapabilityError if the map has no such bank)."""
        layout = [p for p in self.map.parts() if parts is None or p.name in parts]
        missing = [p.name for p in layout if p.banks[bank] is None]
        if missing:
            raise CapabilityError(f"register map {self.map.device.name} has no {bank} bank for {', '.join(missing)}")
        regs = self._read_many([(p.banks[bank], p.registers) for p in layout], f"read geometry {bank}")
        return {p.name: [regs[p.banks[bank] + k] for k in range(p.registers)] for p in layout}

    def _flat(self, words: dict[str, list[int]]) -> list[int]:
        """Held parts' registers in set order: what the device's checksum covers."""
        return [w for p in self.map.parts() if p.name in words for w in words[p.name]]

    def _vector(self, words: dict[str, list[int]]) -> np.ndarray:
        try:
            return geometry_vector(self.map, words, self.fill)
        except ValueError as err:
            raise ParameterValidationError(str(err)) from None

    def _bank_set(self, bank: str) -> ParameterSet:
        return ParameterSet.from_vector(self._vector(self._bank_parts(bank)))

    def _comp_read(self, bank: str) -> list[int]:
        comp = self.map.compensation
        address = None if comp is None else getattr(comp, bank)
        if address is None:
            raise CapabilityError(f"register map {self.map.device.name} has no compensation {bank} bank")
        return self._read(address, BLOCK_REGISTERS, f"read compensation {bank}")

    def _checksum(self, bank: str, compensation: bool = False) -> int | None:
        """A checksum register's value (None where the map has none)."""
        section = self.map.compensation.checksum if compensation and self.map.compensation else self.map.checksum
        address = None if section is None else getattr(section, bank)
        return None if address is None else u32_value(self.map, self._read(address, 2, f"read {bank} checksum"))

    @property
    def has_backup(self) -> bool:
        """Staged maps and maps with backup registers keep the set before the last commit; others need the record."""
        return self.map.staged or self.map.geometry.l0.backup is not None

    def device_key(self, identity: Identity) -> str:
        """Who the device is across restarts, for the records (its map and serial number, else its address)."""
        if identity.serial_number:
            return f"modbus:{self.map.device.name}:{identity.serial_number}"
        return f"modbus:{self.map.device.name}:{self.endpoint}@{self.device_id}"

    def device_set(self, params: ParameterSet | Sequence[float] | np.ndarray) -> ParameterSet:
        """The set as the device will hold it: validated, the held parts rounded through the map's types and scales
        (float32 for hilcal's map). ParameterValidationError (nothing sent) for a value the map cannot hold."""
        target = params if isinstance(params, ParameterSet) else ParameterSet.from_vector(params)
        vector = target.to_vector()
        try:
            return ParameterSet.from_vector(geometry_vector(self.map, geometry_words(self.map, vector), vector))
        except ValueError as err:
            raise ParameterValidationError(f"register map {self.map.device.name}: {err}; nothing written") from None

    # ------------------------------------------------------------------ reads

    def read_identity(self) -> Identity:
        ident = self.map.identity.fields() if self.map.identity else {}
        regs = self._read_many([(f.address, f.count) for f in ident.values()], "read identity")
        values = {k: int(field_value(self.map, f, [regs[f.address + j] for j in range(f.count)]))
                  for k, f in ident.items()}
        declared = self.map.capabilities()
        if "capabilities" in values:
            caps = Capability(values["capabilities"] & int(declared))
        else:
            caps = declared & ~Capability.OFFSETS_ONLY if Capability.FULL_GEOMETRY in declared else declared
        identity = Identity(
            magic=values.get("magic", 0), protocol_version=values.get("protocol_version", 0),
            firmware_version=values.get("firmware_version", 0), serial_number=values.get("serial_number", 0),
            capabilities=caps, parameter_count=values.get("parameter_count", self.map.held_values()))
        wrong = [f"{k} 0x{values[k]:04X} (expected 0x{f.expect:04X})" if k == "magic" else
                 f"{k} {values[k]} (expected {f.expect})" for k, f in ident.items()
                 if f.expect is not None and values[k] != f.expect]
        if wrong:
            raise IdentityError(f"not a compatible controller for register map {self.map.device.name}: "
                                f"{', '.join(wrong)}")
        return identity

    def read_state(self) -> ControllerState:
        s = self.map.state
        if s is None:
            raise CapabilityError(f"register map {self.map.device.name} has no state register")
        value = int(field_value(self.map, s, self._read(s.address, s.count, "read state"))) & s.mask  # type: ignore[arg-type]
        for state, raw in s.values().items():
            if value in raw:
                return state
        raise IdentityError(f"controller state register holds unknown value {value} (0x{value:X}): not in the map "
                            f"{self.map.device.name}'s [state] values")

    def read_status(self) -> ParamStatus:
        s = self.map.status
        if s is None:
            raise CapabilityError(f"register map {self.map.device.name} has no status register")
        value = self._read(s.address, 1, "read status")[0]
        for status, raw in s.codes().items():
            if raw == value:
                return status
        raise IdentityError(f"PARAM_STATUS holds unknown value {value}")

    def read_live(self) -> ParameterSet:
        return self._bank_set("live")

    def read_backup(self) -> ParameterSet:
        return self._bank_set("backup")

    def read_saved(self) -> ParameterSet:
        return self._bank_set("saved")

    def read_live_compensation(self) -> CompensationBlock:
        """The compensation block in use (register map 1.1 only)."""
        return CompensationBlock.from_words(self._comp_read("live"))

    def read_saved_compensation(self) -> CompensationBlock:
        return CompensationBlock.from_words(self._comp_read("saved"))

    def _sensor(self, name: str, n: int) -> list[float]:
        f = getattr(self.map.sensors, name, None) if self.map.sensors else None
        if f is None:
            raise CapabilityError(f"register map {self.map.device.name} has no {name} reading")
        words = self._read(f.address, n * f.count, f"read {name}")
        return [float(field_value(self.map, f, words[k:k + f.count])) for k in range(0, len(words), f.count)]

    def read_leg_forces_kn(self) -> np.ndarray:
        """Each leg's axial compression as the controller reads it (kN; FORCE_READING only)."""
        return np.asarray(self._sensor("leg_forces_kn", 6), dtype=float)

    def read_temperature_c(self) -> float:
        """The leg temperature as the controller reads it (°C; TEMPERATURE_READING only)."""
        return self._sensor("temperature_c", 1)[0]

    def describe(self) -> dict[str, Any]:
        """What ``hilcal check`` shows, as plain data: the map, identity, state, live geometry and its checksum (the
        device's checksum register, where the map has one, against the CRC-32 of the registers read), the fault code
        and diagnostics registers. Each part that
        cannot be read carries its error instead ("…_error": "IdentityError: …"; after a transport error the rest is
        not tried); nothing is written."""
        out: dict[str, Any] = {"endpoint": self.endpoint, "device_id": self.device_id, "map": self.map.device.name,
                               "transaction": self.map.device.transaction}
        steps: list[tuple[str, Callable[[], Any]]] = [
            ("identity", lambda: self.read_identity().as_dict()),
            ("state", lambda: None if self.map.state is None else self.read_state().name),
            ("geometry", self._describe_geometry),
            ("registers", self._describe_registers),
        ]
        link_down: str | None = None
        for key, step in steps:
            try:
                if link_down is not None:
                    raise ModbusTransportError(f"not read: {link_down}")
                out[key] = step()
            except ParamsError as err:
                out[key] = None
                out[f"{key}_error"] = f"{type(err).__name__}: {err}"
                if isinstance(err, ModbusTransportError) and link_down is None:
                    link_down = f"the link failed reading {key}"
        return out

    def _describe_registers(self) -> dict[str, int | float]:
        """The fault code and the map's diagnostics registers."""
        fields = dict(self.map.diagnostics)
        if self.map.fault_code is not None:
            fields["fault_code"] = self.map.fault_code
        regs = self._read_many([(f.address, f.count) for f in fields.values()], "read diagnostics")
        return {k: field_value(self.map, f, [regs[f.address + j] for j in range(f.count)]) for k, f in fields.items()}

    def _describe_geometry(self) -> dict[str, Any]:
        words = self._bank_parts("live")
        crc = crc32_of_words(self._flat(words))
        device = self._checksum("live")
        out: dict[str, Any] = {"held": [p.name for p in self.map.parts()], "crc32": f"{crc:08x}",
                               "checksum_register": None if device is None else f"{device:08x}",
                               "checksum_match": None if device is None else device == crc}
        out["set"] = ParameterSet.from_vector(self._vector(words)).model_dump()
        return out

    # ------------------------------------------------------------------ transactions

    def _begin(self, operation: Literal["upload", "rollback", "save"]
               ) -> tuple[UploadRecord, Identity, dict[str, list[int]]]:
        """Record, identity, DISABLED (where the map has a state register) and the live set before anything."""
        record = UploadRecord(operation=operation, endpoint=self.endpoint, device_id=self.device_id,
                              started_at=now_utc())
        self.records.append(record)
        try:
            identity = self.read_identity()
            record.identity = identity.as_dict()
            record.offsets_only = identity.offsets_only
            record.device = self.device_key(identity)
            if self.map.state is not None:
                state = self.read_state()
                if state is not ControllerState.DISABLED:
                    raise NotDisabled(f"controller is {state.name}: parameters change only while DISABLED; "
                                      "nothing written")
            live = self._bank_parts("live")
            record.previous_live_crc32 = f"{crc32_of_words(self._flat(live)):08x}"
            record.previous_live_sha256 = sha_of_vector(self._vector(live))
            record.previous_params = ParameterSet.from_vector(self._vector(live)).model_dump()
            if identity.compensation:
                comp = self._comp_read("live")
                record.previous_compensation_sha256 = sha_of_words(comp)
                record.previous_compensation_crc32 = f"{crc32_of_words(comp):08x}"
        except ParamsError as err:
            self._finish(record, err)
            raise
        return record, identity, live

    def _finish(
        self,
        record: UploadRecord,
        err: ParamsError | None,
        outcome: Literal["committed", "rolled_back", "saved"] = "committed",
    ) -> None:
        record.finished_at = now_utc()
        if err is None:
            record.outcome = outcome
            log.info("controller_params", operation=record.operation, outcome=record.outcome,
                     crc32=record.params_crc32, writes=len(record.writes))
            return
        record.outcome = "refused" if isinstance(err, NotDisabled | CapabilityError | UploadRefused |
                                                 ParameterValidationError | IdentityError) else "failed"
        record.error = f"{type(err).__name__}: {err}"
        err.record = record
        log.warning("controller_params", operation=record.operation, outcome=record.outcome, error=record.error)

    def _command(self, record: UploadRecord, name: str) -> None:
        codes = self.map.commands.codes() if self.map.commands else {}
        if name not in codes:
            raise CapabilityError(f"register map {self.map.device.name} has no {name} command")
        self._write(record, self.map.commands.address, [codes[name]])  # type: ignore[union-attr]
        if self.map.status is None:
            return
        status = self.read_status()
        record.controller_status = status.name
        if status is not ParamStatus.OK:
            raise UploadRefused(f"controller refused {name.upper()}: {status.name}", status)

    def _geometry_parts(self, identity: Identity, live: np.ndarray, target: np.ndarray) -> list[str] | None:
        """The parts this device takes (None: all it holds); CapabilityError if the set changes one it does not."""
        if identity.offsets_only:
            if not np.array_equal(live[:36], target[:36]):
                raise CapabilityError("offsets-only controller: this set changes a/b joint coordinates; only "
                                      "the six leg offsets l0 can be written; nothing written")
            return ["l0"]
        if Capability.FULL_GEOMETRY in identity.capabilities:
            return None
        raise CapabilityError(f"controller capabilities {identity.capabilities!r} allow no parameter writes")

    @staticmethod
    def _check_compensation(identity: Identity, block: CompensationBlock) -> None:
        if not identity.compensation:
            raise CapabilityError("this controller (register map 1.0) has no compensation block: upload the "
                                  "geometry alone; nothing written")
        missing = block.needs() & ~identity.capabilities
        if missing:
            raise CapabilityError(f"the compensation block needs {missing.name}, which this controller does not "
                                  "have; nothing written")

    def upload(self, params: ParameterSet | Sequence[float] | np.ndarray, *, save: bool = False,
               compensation: CompensationBlock | None = None) -> UploadRecord:
        """Write, verify and commit a parameter set, and with it a compensation block when one is given (see the
        module docstring); save=True also saves them. Without a block the controller keeps its own."""
        target = self.device_set(params)
        vector = target.to_vector()
        words = geometry_words(self.map, vector)
        comp_words = None if compensation is None else compensation.as_float32().to_words()
        record, identity, live = self._begin("upload")
        record.params_sha256 = target.sha256()
        record.params_crc32 = f"{crc32_of_words(self._flat(words)):08x}"
        try:
            if save and "save" not in (self.map.commands.codes() if self.map.commands else {}):
                raise CapabilityError(f"register map {self.map.device.name} has no save command: upload without "
                                      "save; nothing written")
            parts = self._geometry_parts(identity, self._vector(live), vector)
            if compensation is not None and comp_words is not None:
                self._check_compensation(identity, compensation)
                record.compensation_sha256 = sha_of_words(comp_words)
                record.compensation_crc32 = f"{crc32_of_words(comp_words):08x}"
            if self.map.staged:
                self._staged_upload(record, words, parts, comp_words)
            else:
                self._direct_upload(record, live, words, parts, comp_words)
            if save:
                self._save_steps(record, identity)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "committed")
        return record

    def _check_live(self, record: UploadRecord, flat: list[int], comp_words: list[int] | None, message: str) -> None:
        """Read live (and its checksum register) back: it must be ``flat`` (and the block ``comp_words``)."""
        live_parts = self._bank_parts("live")
        live_crc = self._checksum("live")
        record.live_after_sha256 = sha_of_vector(self._vector(live_parts))
        record.live_readback_match = self._flat(live_parts) == flat and live_crc in (None, crc32_of_words(flat))
        if comp_words is not None:
            comp_crc = self._checksum("live", compensation=True)
            record.compensation_readback_match = self._comp_read("live") == comp_words and comp_crc in (
                None, crc32_of_words(comp_words))
            record.live_readback_match = record.live_readback_match and record.compensation_readback_match
        if not record.live_readback_match:
            raise ReadbackMismatch(message)

    def _save_steps(self, record: UploadRecord, identity: Identity) -> None:
        self._command(record, "save")
        m = self.map
        checks = []
        if all(p.banks["saved"] is not None for p in m.parts()):
            checks.append(self._flat(self._bank_parts("saved")) == self._flat(self._bank_parts("live")))
        elif m.checksum is not None and m.checksum.saved is not None:
            checks.append(self._checksum("saved") == crc32_of_words(self._flat(self._bank_parts("live"))))
        if identity.compensation and m.compensation is not None and m.compensation.saved is not None:
            checks.append(self._comp_read("saved") == self._comp_read("live"))
        record.saved_readback_match = all(checks) if checks else None
        if checks and not all(checks):
            raise ReadbackMismatch("non-volatile set read back after SAVE differs from the live set")
        record.saved = True

    def save(self) -> UploadRecord:
        """Copy the live set (and block) to non-volatile memory (controller DISABLED) and verify it."""
        record, identity, _ = self._begin("save")
        try:
            self._save_steps(record, identity)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "saved")
        return record

    def rollback(self, last_upload: UploadRecord | None = None) -> UploadRecord:
        """Put the set in use before the last upload back (controller DISABLED). Staged maps: the ROLLBACK command
        swaps live and backup, geometry and block together. Direct maps: ``modbus_direct.py`` (the device's backup
        registers, else ``last_upload``'s ``previous_params``, else the set this driver replaced in its last
        upload)."""
        if not self.map.staged:
            previous = None
            if last_upload is not None and last_upload.previous_params is not None:
                previous = ParameterSet.model_validate(last_upload.previous_params)
            return self._direct_rollback(previous)
        return self._staged_rollback()

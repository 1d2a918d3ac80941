"""Zentrix HX-6 hexapod controller: simulated CANopen slave.

The protocol work (SDO server, NMT slave, heartbeat and EMCY producers) is done
by ``canopen.LocalNode`` fed with the vendor EDS ``zentrix_hx6.eds``. This
module implements what sits behind the object dictionary in the real firmware:
leg motion, status reporting, the kinematic geometry and the non-volatile
parameter memory (CiA 301 objects 1010h/1011h).

Units on the bus: leg lengths are INTEGER32 in nm, geometry is REAL32 in mm.
See MANUAL.md for the customer-facing description.
"""

from __future__ import annotations

import json
import logging
import math
import os
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, Self

import can
import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError

log = logging.getLogger(__name__)

EDS_PATH = Path(__file__).with_name("zentrix_hx6.eds")

NUM_LEGS = 6
NM_PER_MM = 1_000_000
STROKE_MIN_NM = 0
STROKE_MAX_NM = 50_000_000
MID_STROKE_MM = 25.0
MOVE_TIME_MAX_MS = 50
DEFAULT_SERIAL_NUMBER = 0x0006D3A1
NOTIFIER_CYCLE_S = 0.1  # receive-thread wake-up period; bounds the time close() takes

# Object dictionary indices used by the application.
OD_ERROR_REGISTER = 0x1001
OD_STORE_PARAMETERS = 0x1010
OD_RESTORE_DEFAULTS = 0x1011
OD_HEARTBEAT_TIME = 0x1017
OD_IDENTITY = 0x1018
OD_TARGET_LENGTH = 0x2000
OD_ACTUAL_LENGTH = 0x2001
OD_ENCODER_POSITION = 0x2002
OD_CONTROL_WORD = 0x2010
OD_STATUS_WORD = 0x2011
OD_MOVE_COUNTER = 0x2012
OD_FAULT_CODE = 0x2013
OD_MOVE_TIME = 0x2020
OD_LEG_GEOMETRY = tuple(0x2101 + leg for leg in range(NUM_LEGS))
IDENTITY_SERIAL_NUMBER = 4

# Motion control word 2010h (bits act on a 0 -> 1 transition).
CW_START_MOVE = 0x0001
CW_FAULT_RESET = 0x0080

# Motion status word 2011h.
SW_IN_MOTION = 0x0001
SW_IN_POSITION = 0x0002
SW_FAULT = 0x0004
SW_GEOMETRY_MODIFIED = 0x0010

# Fault code 2013h and the EMCY message sent with it.
FAULT_NONE = 0x0000
FAULT_LEG_DRIVE = 0x0001
EMCY_DEVICE_HARDWARE = 0x5000
ERROR_REGISTER_GENERIC = 0x01

# Geometry record sub-indices 1..7 and their accepted ranges in mm.
GEOMETRY_FIELDS = ("base_x", "base_y", "base_z", "platform_x", "platform_y", "platform_z",
                   "zero_length")
GEOMETRY_LIMITS_MM = ((-1000.0, 1000.0), (-1000.0, 1000.0), (-500.0, 500.0),
                      (-1000.0, 1000.0), (-1000.0, 1000.0), (-500.0, 500.0),
                      (100.0, 1000.0))
ZERO_LENGTH = GEOMETRY_FIELDS.index("zero_length")

SAVE_SIGNATURE = 0x65766173  # "save", CiA 301 object 1010h
LOAD_SIGNATURE = 0x64616F6C  # "load", CiA 301 object 1011h

# SDO abort codes raised by the application (CiA 301).
ABORT_HARDWARE_ERROR = 0x06060000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_CANNOT_STORE = 0x08000020
ABORT_DEVICE_STATE = 0x08000022

# NMT command specifiers (CiA 301).
NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

# Parameter groups of the non-volatile memory and the 1010h/1011h sub-index
# selecting them. Sub-index 3 (application parameters, 6000h-9FFFh) selects
# nothing: the HX-6 has no objects in that range.
GROUP_COMMUNICATION = "communication"
GROUP_MANUFACTURER = "manufacturer"
STORAGE_GROUPS = {
    1: (GROUP_COMMUNICATION, GROUP_MANUFACTURER),
    2: (GROUP_COMMUNICATION,),
    4: (GROUP_MANUFACTURER,),
}

Geometry = list[list[float]]


def _float32(value: float) -> float:
    """Round a Python float to the nearest IEEE-754 single, as the firmware stores REAL32."""
    return struct.unpack("<f", struct.pack("<f", value))[0]


class Plant(Protocol):
    """The mechanics behind the controller: six legs with length encoders."""

    def move_to(self, encoder_mm: list[float]) -> None:
        """Drive the six legs to these encoder positions (mm)."""

    def read(self) -> list[float]:
        """Return the six encoder positions (mm)."""


class PerfectPlant:
    """Ideal legs that reach exactly the commanded encoder positions.

    They power up at mid-stroke, 25.000 mm on every encoder, unless told otherwise.
    """

    def __init__(self, initial_mm: Sequence[float] | None = None) -> None:
        start = [MID_STROKE_MM] * NUM_LEGS if initial_mm is None else initial_mm
        self._position = [float(value) for value in start]

    def move_to(self, encoder_mm: list[float]) -> None:
        self._position = [float(value) for value in encoder_mm]

    def read(self) -> list[float]:
        return list(self._position)


class NonVolatileMemory:
    """The controller's parameter flash, one JSON document holding the stored groups.

    Without a path the memory lives in RAM only: it survives NMT resets but not
    a new device instance (power cycle).
    """

    FORMAT = "zentrix-hx6-nvm"
    VERSION = 1

    def __init__(self, path: Path | None) -> None:
        self._path = path
        self._groups: dict[str, dict[str, Any]] = self._read_file() if path else {}

    def get(self, group: str) -> dict[str, Any] | None:
        """The stored parameter set of a group, or None if nothing is stored."""
        return self._groups.get(group)

    def save(self, groups: dict[str, dict[str, Any]]) -> None:
        """Store parameter sets; raises OSError if the file cannot be written."""
        self._commit({**self._groups, **groups})

    def erase(self, names: Sequence[str]) -> None:
        """Forget stored sets so that factory defaults apply at the next reset."""
        self._commit({name: data for name, data in self._groups.items() if name not in names})

    def _commit(self, groups: dict[str, dict[str, Any]]) -> None:
        if self._path is not None:
            document = {"format": self.FORMAT, "version": self.VERSION, "groups": groups}
            self._path.parent.mkdir(parents=True, exist_ok=True)
            scratch = self._path.with_name(self._path.name + ".tmp")
            scratch.write_text(json.dumps(document, indent=2))
            os.replace(scratch, self._path)
        self._groups = groups

    def _read_file(self) -> dict[str, dict[str, Any]]:
        assert self._path is not None
        if not self._path.exists():
            return {}
        try:
            document = json.loads(self._path.read_text())
            if document.get("format") != self.FORMAT or document.get("version") != self.VERSION:
                raise ValueError("unknown format")
            groups = document["groups"]
            if not isinstance(groups, dict):
                raise TypeError("groups is not an object")
            return {name: data for name, data in groups.items() if isinstance(data, dict)}
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
            log.warning("Ignoring unreadable parameter memory %s: %s", self._path, exc)
            return {}


@dataclass
class _Move:
    """A synchronised move in progress: all legs start and arrive together."""

    start_mm: list[float]
    target_mm: list[float]
    started: float
    duration_s: float

    def position_mm(self, now: float) -> list[float]:
        """Leg encoder positions along the linear set-point profile."""
        if self.duration_s <= 0:
            return list(self.target_mm)
        fraction = min(1.0, max(0.0, (now - self.started) / self.duration_s))
        return [s + (t - s) * fraction for s, t in zip(self.start_mm, self.target_mm, strict=True)]


class _StrictLocalNode(canopen.LocalNode):
    """LocalNode that answers 0609 0011h for sub-indices the EDS does not define.

    canopen's ODArray synthesises an entry for any sub-index 1..255 and a VAR
    is found under any sub-index; the real firmware only knows the listed ones.
    """

    def _find_object(self, index: int, subindex: int) -> ODVariable:
        obj = super()._find_object(index, subindex)
        parent = obj.parent
        if isinstance(parent, ODArray):
            defined = subindex in parent.subindices
        else:
            defined = isinstance(parent, ODRecord) or subindex == 0
        if not defined:
            raise SdoAbortedError(ABORT_NO_SUBINDEX)
        return obj


Reader = Callable[[int, ODVariable], int | float | None]
Writer = Callable[[int, Any], None]


class ZentrixHX6:
    """A Zentrix HX-6 controller attached to a python-can bus.

    The constructor powers the device up: it sends the boot-up message, enters
    PRE-OPERATIONAL and produces heartbeats per 1017h until :meth:`close`.
    ``moves`` counts the moves handed to the plant since construction.
    """

    def __init__(
        self,
        channel: str,
        node_id: int = 5,
        plant: Plant | None = None,
        interface: str = "virtual",
        storage_path: str | Path | None = None,
        serial_number: int = DEFAULT_SERIAL_NUMBER,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CANopen node-ID must be 1..127, got {node_id}")
        if not 0 <= serial_number <= 0xFFFFFFFF:
            raise ValueError(f"Serial number must fit UNSIGNED32, got {serial_number}")
        self.node_id = node_id
        self.plant: Plant = plant if plant is not None else PerfectPlant()
        self.moves = 0
        self._serial_number = serial_number
        self._lock = threading.RLock()
        self._closed = False
        self._memory = NonVolatileMemory(Path(storage_path) if storage_path else None)

        self.node = _StrictLocalNode(node_id, str(EDS_PATH))
        od = self.node.object_dictionary
        self._factory_geometry: Geometry = [
            [_float32(od[index][sub].default) for sub in range(1, len(GEOMETRY_FIELDS) + 1)]
            for index in OD_LEG_GEOMETRY
        ]
        self._factory_move_time_ms = int(od[OD_MOVE_TIME].default)
        self._factory_heartbeat_ms = int(od[OD_HEARTBEAT_TIME].default)

        self._heartbeat_ms = self._factory_heartbeat_ms
        self._geometry: Geometry = [list(leg) for leg in self._factory_geometry]
        self._move_time_ms = self._factory_move_time_ms
        self._targets_nm = [0] * NUM_LEGS
        self._control_word = 0
        self._fault_code = FAULT_NONE
        self._error_register = 0
        self._completed_moves = 0
        self._geometry_modified = False
        self._move: _Move | None = None
        self._move_timer: threading.Timer | None = None

        self._readers: dict[int, Reader] = {
            OD_ERROR_REGISTER: lambda sub, var: self._error_register,
            OD_STORE_PARAMETERS: lambda sub, var: var.default,
            OD_RESTORE_DEFAULTS: lambda sub, var: var.default,
            OD_HEARTBEAT_TIME: lambda sub, var: self._heartbeat_ms,
            OD_IDENTITY: lambda sub, var: (
                self._serial_number if sub == IDENTITY_SERIAL_NUMBER else None),
            OD_TARGET_LENGTH: lambda sub, var: self._targets_nm[sub - 1],
            OD_ACTUAL_LENGTH: lambda sub, var: self._actual_lengths_nm()[sub - 1],
            OD_ENCODER_POSITION: lambda sub, var: self._encoder_positions_nm()[sub - 1],
            OD_CONTROL_WORD: lambda sub, var: self._control_word,
            OD_STATUS_WORD: lambda sub, var: self._status_word(),
            OD_MOVE_COUNTER: lambda sub, var: self._completed_moves,
            OD_FAULT_CODE: lambda sub, var: self._fault_code,
            OD_MOVE_TIME: lambda sub, var: self._move_time_ms,
        }
        self._writers: dict[int, Writer] = {
            OD_STORE_PARAMETERS: self._write_store_parameters,
            OD_RESTORE_DEFAULTS: self._write_restore_defaults,
            OD_HEARTBEAT_TIME: self._write_heartbeat_time,
            OD_TARGET_LENGTH: self._write_target_length,
            OD_CONTROL_WORD: self._write_control_word,
            OD_MOVE_TIME: self._write_move_time,
        }
        for leg, index in enumerate(OD_LEG_GEOMETRY):
            self._readers[index] = lambda sub, var, leg=leg: self._geometry[leg][sub - 1]
            self._writers[index] = lambda sub, value, leg=leg: self._write_geometry(
                leg, sub, value)
        self.node.add_read_callback(self._on_sdo_read)
        self.node.add_write_callback(self._on_sdo_write)

        self.network = canopen.Network(can.Bus(interface=interface, channel=channel))
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        try:
            self._attach_to_network()
            self._reset_application()
            self._reset_communication()
        except BaseException:
            self.network.disconnect()
            raise

    @property
    def nmt_state(self) -> str:
        """Current NMT state name, e.g. 'PRE-OPERATIONAL'."""
        return self.node.nmt.state

    def close(self) -> None:
        """Power the device off: stop motion, heartbeat and the bus connection."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._move_timer is not None:
                self._move_timer.cancel()
        self.node.nmt.stop_heartbeat()
        self.network.disconnect()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- bus attachment, NMT -------------------------------------------------

    def _attach_to_network(self) -> None:
        """Register the node, routing SDO and NMT through this device's gates."""
        self.network.add_node(self.node)
        sdo_rx = self.node.sdo.rx_cobid
        self.network.unsubscribe(sdo_rx, self.node.sdo.on_request)
        self.network.subscribe(sdo_rx, self._on_sdo_request)
        self.network.unsubscribe(0, self.node.nmt.on_command)
        self.network.subscribe(0, self._on_nmt_command)
        self.network.connect()

    def _on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """SDO requests are served in PRE-OPERATIONAL and OPERATIONAL only."""
        if self.node.nmt.state != "STOPPED":
            self.node.sdo.on_request(can_id, data, timestamp)

    def _on_nmt_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        command = data[0]
        if command == NMT_RESET_NODE:
            self._reset_application()
            self._reset_communication()
        elif command == NMT_RESET_COMMUNICATION:
            self._reset_communication()
        elif command in (NMT_START, NMT_STOP, NMT_ENTER_PRE_OPERATIONAL):
            self.node.nmt.on_command(can_id, data, timestamp)

    def _reset_communication(self) -> None:
        """Reload communication parameters, send boot-up, enter PRE-OPERATIONAL."""
        stored = self._memory.get(GROUP_COMMUNICATION)
        heartbeat_ms = self._factory_heartbeat_ms
        if stored is not None:
            value = stored.get("heartbeat_ms")
            if isinstance(value, int) and 0 <= value <= 0xFFFF:
                heartbeat_ms = value
            else:
                log.warning("Stored heartbeat time %r invalid, using factory value", value)
        with self._lock:
            self._heartbeat_ms = heartbeat_ms
        nmt = self.node.nmt
        nmt.stop_heartbeat()
        nmt.state = "INITIALISING"
        nmt.state = "PRE-OPERATIONAL"

    def _reset_application(self) -> None:
        """Power-on state of the application: stored (or factory) parameters, legs at rest."""
        with self._lock:
            if self._move is not None:
                self._halt_move()
            geometry, move_time_ms = self._stored_manufacturer_parameters()
            self._geometry = geometry
            self._move_time_ms = move_time_ms
            self._geometry_modified = False
            self._fault_code = FAULT_NONE
            self._error_register = 0
            self._control_word = 0
            self._completed_moves = 0
            self._targets_nm = self._actual_lengths_nm()

    def _stored_manufacturer_parameters(self) -> tuple[Geometry, int]:
        """Geometry and move time from the parameter memory, else factory defaults."""
        factory = ([list(leg) for leg in self._factory_geometry], self._factory_move_time_ms)
        stored = self._memory.get(GROUP_MANUFACTURER)
        if stored is None:
            return factory
        try:
            geometry = [[_float32(float(value)) for value in leg] for leg in stored["geometry_mm"]]
            move_time_ms = int(stored["move_time_ms"])
            shape_ok = len(geometry) == NUM_LEGS and all(
                len(leg) == len(GEOMETRY_FIELDS) for leg in geometry)
            if not shape_ok:
                raise ValueError("wrong shape")
            values_ok = all(
                low <= value <= high
                for leg in geometry
                for value, (low, high) in zip(leg, GEOMETRY_LIMITS_MM, strict=True))
            if not (values_ok and 0 <= move_time_ms <= MOVE_TIME_MAX_MS):
                raise ValueError("out of range")
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("Stored manufacturer parameters invalid (%s), using factory values", exc)
            return factory
        return geometry, move_time_ms

    # -- object dictionary access --------------------------------------------

    def _on_sdo_read(self, index: int, subindex: int, od: ODVariable) -> int | float | None:
        reader = self._readers.get(index)
        is_entry_count = subindex == 0 and isinstance(od.parent, (ODArray, ODRecord))
        if reader is None or is_entry_count:
            return None
        with self._lock:
            return reader(subindex, od)

    def _on_sdo_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        writer = self._writers.get(index)
        if writer is None:
            return
        with self._lock:
            writer(subindex, od.decode_raw(data))

    def _write_store_parameters(self, subindex: int, value: int) -> None:
        groups = STORAGE_GROUPS.get(subindex)
        if value != SAVE_SIGNATURE or groups is None:
            raise SdoAbortedError(ABORT_CANNOT_STORE)
        snapshot = {
            GROUP_COMMUNICATION: {"heartbeat_ms": self._heartbeat_ms},
            GROUP_MANUFACTURER: {"geometry_mm": [list(leg) for leg in self._geometry],
                                 "move_time_ms": self._move_time_ms},
        }
        try:
            self._memory.save({group: snapshot[group] for group in groups})
        except OSError as exc:
            log.error("Parameter memory write failed: %s", exc)
            raise SdoAbortedError(ABORT_HARDWARE_ERROR) from exc
        if GROUP_MANUFACTURER in groups:
            self._geometry_modified = False

    def _write_restore_defaults(self, subindex: int, value: int) -> None:
        groups = STORAGE_GROUPS.get(subindex)
        if value != LOAD_SIGNATURE or groups is None:
            raise SdoAbortedError(ABORT_CANNOT_STORE)
        try:
            self._memory.erase(groups)
        except OSError as exc:
            log.error("Parameter memory write failed: %s", exc)
            raise SdoAbortedError(ABORT_HARDWARE_ERROR) from exc

    def _write_heartbeat_time(self, subindex: int, value: int) -> None:
        # canopen's NmtSlave has already (re)started the heartbeat producer.
        self._heartbeat_ms = value

    def _write_target_length(self, subindex: int, value: int) -> None:
        leg = subindex - 1
        encoder_nm = value - self._zero_length_nm(leg)
        if encoder_nm < STROKE_MIN_NM:
            raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
        if encoder_nm > STROKE_MAX_NM:
            raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        self._targets_nm[leg] = value

    def _write_control_word(self, subindex: int, value: int) -> None:
        if value & ~(CW_START_MOVE | CW_FAULT_RESET):
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        rising = value & ~self._control_word
        if rising & CW_FAULT_RESET:
            self._reset_fault()
        if rising & CW_START_MOVE:
            self._start_move()
        self._control_word = value

    def _write_move_time(self, subindex: int, value: int) -> None:
        if value > MOVE_TIME_MAX_MS:
            raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        self._move_time_ms = value

    def _write_geometry(self, leg: int, subindex: int, value: float) -> None:
        if self._move is not None:
            raise SdoAbortedError(ABORT_DEVICE_STATE)
        if not math.isfinite(value):
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        low, high = GEOMETRY_LIMITS_MM[subindex - 1]
        if value < low:
            raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
        if value > high:
            raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        self._geometry[leg][subindex - 1] = value
        self._geometry_modified = True

    # -- motion --------------------------------------------------------------

    def _start_move(self) -> None:
        """Begin a synchronised move of all six legs to the target lengths (2000h)."""
        if self._move is not None or self._fault_code != FAULT_NONE:
            raise SdoAbortedError(ABORT_DEVICE_STATE)
        target_nm = [self._targets_nm[leg] - self._zero_length_nm(leg) for leg in range(NUM_LEGS)]
        if any(not STROKE_MIN_NM <= value <= STROKE_MAX_NM for value in target_nm):
            raise SdoAbortedError(ABORT_CANNOT_STORE)
        move = _Move(start_mm=self._read_plant(),
                     target_mm=[value / NM_PER_MM for value in target_nm],
                     started=time.monotonic(),
                     duration_s=self._move_time_ms / 1000.0)
        self._move = move
        if move.duration_s == 0:
            if not self._finish_move(move):
                raise SdoAbortedError(ABORT_HARDWARE_ERROR)
            return
        self._move_timer = threading.Timer(move.duration_s, self._on_move_timer, args=(move,))
        self._move_timer.daemon = True
        self._move_timer.start()

    def _on_move_timer(self, move: _Move) -> None:
        with self._lock:
            if not self._closed:
                self._finish_move(move)

    def _finish_move(self, move: _Move) -> bool:
        """Hand the end point to the plant; False (and a fault) if the legs fail."""
        if self._move is not move:
            return False
        self._move = None
        self._move_timer = None
        try:
            self.plant.move_to(list(move.target_mm))
        except Exception:
            log.exception("Leg drive failure")
            self._raise_fault(FAULT_LEG_DRIVE)
            return False
        self.moves += 1
        self._completed_moves = (self._completed_moves + 1) & 0xFFFFFFFF
        return True

    def _halt_move(self) -> None:
        """Stop the legs where they are now (used by NMT reset during a move)."""
        assert self._move is not None
        if self._move_timer is not None:
            self._move_timer.cancel()
        position = self._move.position_mm(time.monotonic())
        self._move = None
        self._move_timer = None
        try:
            self.plant.move_to(position)
        except Exception:
            log.exception("Leg drive failure while halting")

    def _raise_fault(self, code: int) -> None:
        self._fault_code = code
        self._error_register |= ERROR_REGISTER_GENERIC
        if self.node.nmt.state in ("PRE-OPERATIONAL", "OPERATIONAL"):
            self.node.emcy.send(EMCY_DEVICE_HARDWARE, self._error_register,
                                struct.pack("<H", code))

    def _reset_fault(self) -> None:
        if self._fault_code == FAULT_NONE:
            return
        self._fault_code = FAULT_NONE
        self._error_register = 0
        if self.node.nmt.state in ("PRE-OPERATIONAL", "OPERATIONAL"):
            self.node.emcy.reset(self._error_register)

    # -- derived values --------------------------------------------------------

    def _status_word(self) -> int:
        status = 0
        if self._move is not None:
            status |= SW_IN_MOTION
        elif self._fault_code == FAULT_NONE:
            status |= SW_IN_POSITION
        if self._fault_code != FAULT_NONE:
            status |= SW_FAULT
        if self._geometry_modified:
            status |= SW_GEOMETRY_MODIFIED
        return status

    def _zero_length_nm(self, leg: int) -> int:
        return round(self._geometry[leg][ZERO_LENGTH] * NM_PER_MM)

    def _read_plant(self) -> list[float]:
        try:
            values = [float(value) for value in self.plant.read()]
        except Exception as exc:
            log.exception("Leg encoder read failure")
            raise SdoAbortedError(ABORT_HARDWARE_ERROR) from exc
        if len(values) != NUM_LEGS:
            raise SdoAbortedError(ABORT_HARDWARE_ERROR)
        return values

    def _encoder_positions_nm(self) -> list[int]:
        if self._move is not None:
            position = self._move.position_mm(time.monotonic())
        else:
            position = self._read_plant()
        return [round(value * NM_PER_MM) for value in position]

    def _actual_lengths_nm(self) -> list[int]:
        return [encoder + self._zero_length_nm(leg)
                for leg, encoder in enumerate(self._encoder_positions_nm())]

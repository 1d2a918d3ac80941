"""Laser tracker driver on Leica's emScon: binary packets over a TCP socket of our own.

The packets are ``hilcal.protocols.emscon``'s (CESAPI's layouts from Leica's ``ES_C_API_Def.h``); CESAPI's own
``Connection`` is not used (it polls with sleeps and configures logging at import). One command at a time:

* Before a command is sent, whatever the tracker sent since is read and dropped (logged).
* The answer is the command packet with the same command code; a status other than ``AllOK`` is a typed
  ``TrackerError`` (``drivers.tracker.base.tracker_error``). ``StartMeasurement`` also waits for its
  ``SingleMeasResultT``. An ``ErrorResponseT`` for the pending command is a typed error too (``unsolicited``); one for
  another command is logged. Status-change notices and reflector positions are logged and passed over; packets of
  data types or command codes the AT4xx definitions lack (a newer server's) are skipped and logged, at most
  ``max_skipped_packets`` per command.
* Every wait is bounded: connecting by ``connect_timeout_s``, sending by ``write_timeout_s``, an answer by the
  command's timeout (``command_timeout_s``; ``initialize_timeout_s``; ``move_timeout_s`` for GoPosition and
  FindReflector; ``measure_timeout_s``). emScon answers carry no tag, so a late answer cannot be told from the
  answer to a command sent again: after a timeout, a stream out of step or a lost connection the driver closes the
  connection (whatever the tracker still sends for the abandoned command dies with it), connects again and sends the
  command again, ``max_retries`` times at most; then ``TrackerTimeout`` (naming the command),
  ``TrackerProtocolError`` or ``TrackerConnectionError``. A tracker that refuses the connection fails at once.

The driver makes the tracker speak mm, degrees, °C and hPa (``set_units``, sent by itself before the first command
that carries a unit); the tracker keeps its units across connections.
"""

from __future__ import annotations

import contextlib
import socket
import time
from collections.abc import Callable

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from drivers.tracker.base import (
    Environment,
    Reflector,
    Refraction,
    SearchParams,
    TrackerConnectionError,
    TrackerInterface,
    TrackerPoint,
    TrackerProtocolError,
    TrackerTimeout,
    TrackerUnits,
    finite3,
    tracker_error,
)
from hilcal.protocols.emscon import (
    DEFAULT_PORT,
    HEADER,
    AngleUnit,
    Command,
    CoordinateSystemType,
    DataType,
    HumidityUnit,
    LengthUnit,
    MeasMode,
    Packet,
    PacketError,
    PressureUnit,
    ResultStatus,
    SystemStatusChange,
    TargetType,
    TemperatureUnit,
    UnknownPacket,
    decode,
    decode_name,
    encode,
    name_of,
    new_command,
    packet_type,
    take_packets,
)

log = structlog.get_logger(__name__)

RECV_BYTES = 65536
MAX_DISCARD_BYTES = 1 << 20
"""Bound on one drain, so a tracker that never stops sending cannot hold the driver."""
UNITS = (LengthUnit.Millimeter, AngleUnit.Degree, TemperatureUnit.Celsius, PressureUnit.HPascal, HumidityUnit.RH)
"""What the driver makes the tracker speak (hPa is mbar)."""
MOVE_COMMANDS = (Command.GoPosition, Command.FindReflector)
RESULT_TYPES = (DataType.SingleMeasResult, DataType.SingleMeasResult2)


class EmsconConfig(BaseModel):
    """Where the tracker is, and the bound on every wait."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    host: str = Field(default="192.168.0.1", description="the tracker controller's address")
    port: int = Field(default=DEFAULT_PORT, gt=0, le=65535)
    connect_timeout_s: float = Field(default=5.0, gt=0)
    write_timeout_s: float = Field(default=2.0, gt=0)
    command_timeout_s: float = Field(default=5.0, gt=0, description="an answer to a setting or a query")
    initialize_timeout_s: float = Field(default=120.0, gt=0, description="an answer to Initialize")
    move_timeout_s: float = Field(default=30.0, gt=0, description="an answer to GoPosition or FindReflector (longer "
                                  "than the ATR search's own timeout)")
    measure_timeout_s: float = Field(default=30.0, gt=0, description="StartMeasurement's answer and result")
    max_retries: int = Field(default=2, ge=0, description="connections opened again and the command sent again after "
                             "a timeout, a stream out of step or a lost connection")
    measure_retries: int = Field(default=2, ge=0, description="measure_point: acquisitions made again after the beam "
                                 "broke during a measurement")
    max_skipped_packets: int = Field(default=64, ge=0, description="unknown or stale packets passed over per command")


class _Stalled(Exception):
    """A transaction that a new connection and a resend may cure."""


class _NoAnswer(_Stalled):
    pass


class _OutOfStep(_Stalled):
    pass


class _Lost(_Stalled):
    pass


def _only_notices(data: bytearray) -> bool:
    """Whether the bytes are whole status-change notices and nothing else (consumes ``data``)."""
    try:
        packets = take_packets(data)
    except PacketError:
        return False
    return not data and all(_type_of(p) == DataType.SystemStatusChange for p in packets)


def _type_of(raw: bytes) -> int:
    """The data type in a packet's header."""
    return int(HEADER.unpack_from(raw)[1])


class EmsconTracker(TrackerInterface):
    """A Leica tracker on emScon over TCP. Connects at construction; ``initialize()`` before it moves or measures."""

    def __init__(self, config: EmsconConfig | None = None, **settings: object) -> None:
        """Connect with ``config``, or with ``EmsconConfig`` fields given as keywords (not both)."""
        if config is not None and settings:
            raise TypeError("give an EmsconConfig or its fields as keywords, not both")
        self.config = config or EmsconConfig.model_validate(settings)
        self.measure_retries = self.config.measure_retries
        self._sock: socket.socket | None = None
        self._rx = bytearray()
        self._units_set = False
        self.reconnects = 0
        """Connections opened again after a failed transaction."""
        self._connect()

    # ------------------------------------------------------------------ transport

    @property
    def address(self) -> str:
        return f"{self.config.host}:{self.config.port}"

    def _connect(self) -> None:
        try:
            sock = socket.create_connection((self.config.host, self.config.port), self.config.connect_timeout_s)
        except OSError as err:
            raise TrackerConnectionError(f"cannot connect to the tracker at {self.address}: {err}") from err
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._rx.clear()
        log.info("tracker.connected", address=self.address)

    def _disconnect(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None
        self._rx.clear()

    def close(self) -> None:
        """Close the connection (the tracker keeps its state)."""
        if self._sock is not None:
            self._disconnect()
            log.info("tracker.closed", address=self.address)

    def _send(self, data: bytes) -> None:
        assert self._sock is not None
        try:
            self._sock.settimeout(self.config.write_timeout_s)
            self._sock.sendall(data)
        except TimeoutError:
            raise _Lost(f"sending took longer than {self.config.write_timeout_s} s") from None
        except OSError as err:
            raise _Lost(f"sending failed: {err}") from None

    def _fill(self, deadline: float) -> bool:
        """Read what arrives before the deadline into the buffer; False at the deadline."""
        assert self._sock is not None
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        try:
            self._sock.settimeout(remaining)
            chunk = self._sock.recv(RECV_BYTES)
        except TimeoutError:
            return False
        except OSError as err:
            raise _Lost(f"reading failed: {err}") from None
        if not chunk:
            raise _Lost("the tracker closed the connection")
        self._rx += chunk
        return True

    def _discard_input(self, before: str) -> None:
        """Drop what the tracker sent since the last command: logged, at debug level when it is only the notices that
        follow a setting's answer."""
        assert self._sock is not None
        pending = bytearray(self._rx)
        self._rx.clear()
        try:
            self._sock.settimeout(0.0)
            while len(pending) < MAX_DISCARD_BYTES:
                chunk = self._sock.recv(RECV_BYTES)
                if not chunk:
                    raise _Lost("the tracker closed the connection")
                pending += chunk
        except (BlockingIOError, TimeoutError, InterruptedError):
            pass
        except OSError as err:
            raise _Lost(f"reading failed: {err}") from None
        if pending:
            head = bytes(pending[:64]).hex()
            log_at = log.debug if _only_notices(bytearray(pending)) else log.info
            log_at("tracker.input_discarded", before=before, n_bytes=len(pending), head=head)

    # ------------------------------------------------------------------ transactions

    def _timeout_for(self, command: int) -> float:
        if command == Command.Initialize:
            return self.config.initialize_timeout_s
        if command in MOVE_COMMANDS:
            return self.config.move_timeout_s
        if command == Command.StartMeasurement:
            return self.config.measure_timeout_s
        return self.config.command_timeout_s

    def transact(self, packet: Packet, *, result: bool = False,
                 n_answers: Callable[[Packet], int] | None = None) -> tuple[list[Packet], Packet | None]:
        """Send a command packet; its answers (one, or as many as ``n_answers(first answer)`` says) and, with
        ``result``, the measurement result. Typed TrackerError on an error status; bounded as the module says."""
        command = int(packet.packetInfo.command)
        name = name_of(Command, command)
        data = encode(packet)
        timeout = self._timeout_for(command)
        attempts = 1 + self.config.max_retries
        last: _Stalled | None = None
        for attempt in range(1, attempts + 1):
            if self._sock is None:
                self._connect()
                self.reconnects += 1
            try:
                self._discard_input(name)
                log.debug("tracker.send", command=name, attempt=attempt)
                self._send(data)
                return self._await(command, time.monotonic() + timeout, result, n_answers)
            except _Stalled as err:
                log.warning("tracker.transaction_failed", command=name, attempt=attempt, error=str(err))
                self._disconnect()
                last = err
        if isinstance(last, _NoAnswer):
            raise TrackerTimeout(f"{name}: {last} ({attempts} attempts, a new connection each)", name, timeout,
                                 attempts) from last
        kind = TrackerProtocolError if isinstance(last, _OutOfStep) else TrackerConnectionError
        raise kind(f"{name}: {last} ({attempts} attempts, a new connection each)") from last

    def _await(self, command: int, deadline: float, want_result: bool,
               n_answers: Callable[[Packet], int] | None) -> tuple[list[Packet], Packet | None]:
        name = name_of(Command, command)
        answers: list[Packet] = []
        result: Packet | None = None
        expected = 1
        skipped = 0

        def skip(event: str, **kw: object) -> None:
            nonlocal skipped
            skipped += 1
            log.warning(event, waiting_for=name, **kw)
            if skipped > self.config.max_skipped_packets:
                raise _OutOfStep(f"more than {self.config.max_skipped_packets} packets answered nothing")

        while True:
            try:
                raws = take_packets(self._rx)
            except PacketError as err:
                raise _OutOfStep(str(err)) from None
            for raw in raws:
                try:
                    p = decode(raw, answer=True)
                except UnknownPacket as err:
                    skip("tracker.unknown_packet_skipped", reason=str(err), head=raw[:32].hex())
                    continue
                except PacketError as err:
                    raise _OutOfStep(str(err)) from None
                kind = packet_type(p)
                if kind == DataType.Command:
                    if p.packetInfo.command != command:
                        skip("tracker.stale_answer_skipped", command=name_of(Command, p.packetInfo.command))
                        continue
                    if p.packetInfo.status != ResultStatus.AllOK:
                        raise tracker_error(command, p.packetInfo.status)
                    answers.append(p)
                    if len(answers) == 1 and n_answers is not None:
                        expected = n_answers(p)
                elif kind == DataType.Error:
                    if p.command == command:
                        raise tracker_error(command, p.status, unsolicited=True)
                    log.warning("tracker.error_packet", waiting_for=name, command=name_of(Command, p.command),
                                status=name_of(ResultStatus, p.status))
                elif kind in RESULT_TYPES:
                    if not want_result:
                        skip("tracker.stale_result_skipped")
                        continue
                    if p.packetInfo.status != ResultStatus.AllOK:
                        raise tracker_error(command, p.packetInfo.status, detail="in the measurement result")
                    result = p
                elif kind == DataType.SystemStatusChange:
                    log.debug("tracker.status_change", change=name_of(SystemStatusChange, p.systemStatusChange))
                else:
                    log.debug("tracker.packet_passed_over", data_type=name_of(DataType, kind))
            if len(answers) >= expected and (result is not None or not want_result):
                return answers, result
            if not self._fill(deadline):
                partial = f" ({len(self._rx)} bytes of a packet never finished)" if self._rx else ""
                what = "result" if answers else "answer"
                raise _NoAnswer(f"no {what} within {self._timeout_for(command)} s{partial}")

    def _command(self, command: int, **fields: object) -> Packet:
        """Send a command with top-level fields set; its answer."""
        packet = new_command(command)
        for key, value in fields.items():
            setattr(packet, key, value)
        return self.transact(packet)[0][0]

    def _ensure_units(self) -> None:
        if not self._units_set:
            self.set_units()

    # ------------------------------------------------------------------ commands

    def initialize(self) -> None:
        self._command(Command.Initialize)

    def set_units(self) -> None:
        packet = new_command(Command.SetUnits)
        u = packet.unitsSettings
        u.lenUnitType, u.angUnitType, u.tempUnitType, u.pressUnitType, u.humUnitType = (int(x) for x in UNITS)
        self.transact(packet)
        self._units_set = True

    def units(self) -> TrackerUnits:
        u = self._command(Command.GetUnits).unitsSettings
        return TrackerUnits(name_of(LengthUnit, u.lenUnitType), name_of(AngleUnit, u.angUnitType),
                            name_of(TemperatureUnit, u.tempUnitType), name_of(PressureUnit, u.pressUnitType),
                            name_of(HumidityUnit, u.humUnitType))

    def set_single_point_mode(self) -> None:
        self._command(Command.SetCoordinateSystemType, coordSysType=int(CoordinateSystemType.RHR))
        self._command(Command.SetMeasurementMode, measMode=int(MeasMode.Stationary))

    def set_environment(self, environment: Environment) -> None:
        self._ensure_units()
        packet = new_command(Command.SetEnvironmentParams)
        e = packet.environmentData
        e.dTemperature, e.dPressure, e.dHumidity = (
            float(environment.temperature_c), float(environment.pressure_hpa), float(environment.humidity_pct))
        self.transact(packet)

    def environment(self) -> Environment:
        self._ensure_units()
        e = self._command(Command.GetEnvironmentParams).environmentData
        return Environment(e.dTemperature, e.dPressure, e.dHumidity)

    def refraction(self) -> Refraction:
        r = self._command(Command.GetRefractionParams).refractionData
        return Refraction(r.dIfmRefractionIndex, r.dAdmRefractionIndex)

    def set_refraction(self, refraction: Refraction) -> None:
        packet = new_command(Command.SetRefractionParams)
        packet.refractionData.dIfmRefractionIndex = float(refraction.ifm_index)
        packet.refractionData.dAdmRefractionIndex = float(refraction.adm_index)
        self.transact(packet)

    def reflectors(self) -> tuple[Reflector, ...]:
        """Every reflector the tracker knows (emScon answers GetReflectors with one packet per reflector)."""
        self._ensure_units()
        answers, _ = self.transact(new_command(Command.GetReflectors), n_answers=lambda a: max(1, a.iTotalReflectors))
        if answers[0].iTotalReflectors == 0:
            return ()
        return tuple(Reflector(a.iInternalReflectorId, decode_name(a.cReflectorName), name_of(TargetType, a.targetType),
                               a.dSurfaceOffset) for a in answers)

    def reflector(self) -> int:
        return int(self._command(Command.GetReflector).iInternalReflectorId)

    def set_reflector(self, reflector_id: int) -> None:
        self._command(Command.SetReflector, iInternalReflectorId=int(reflector_id))

    def search_params(self) -> SearchParams:
        self._ensure_units()
        s = self._command(Command.GetSearchParams).searchParams
        return SearchParams(s.dSearchRadius, s.lTimeOut / 1000.0)

    def set_search_params(self, radius_mm: float, timeout_s: float) -> None:
        self._ensure_units()
        packet = new_command(Command.SetSearchParams)
        packet.searchParams.dSearchRadius = float(radius_mm)
        packet.searchParams.lTimeOut = round(timeout_s * 1000.0)
        self.transact(packet)

    def go_position(self, point_mm: np.ndarray, use_adm: bool = False) -> None:
        p = finite3(point_mm, "point_mm")
        self._ensure_units()
        self._command(Command.GoPosition, dVal1=float(p[0]), dVal2=float(p[1]), dVal3=float(p[2]),
                      bUseADM=int(bool(use_adm)))

    def find_reflector(self, approx_distance_mm: float) -> None:
        if not np.isfinite(approx_distance_mm) or approx_distance_mm <= 0:
            raise ValueError(f"approx_distance_mm must be a positive number, got {approx_distance_mm!r}")
        self._ensure_units()
        self._command(Command.FindReflector, dAproxDistance=float(approx_distance_mm))

    def direction_deg(self) -> tuple[float, float]:
        self._ensure_units()
        a = self._command(Command.GetDirection)
        return float(a.dHzAngle), float(a.dVtAngle)

    def measure(self) -> TrackerPoint:
        self._ensure_units()
        _, r = self.transact(new_command(Command.StartMeasurement), result=True)
        assert r is not None
        point = TrackerPoint(
            xyz_mm=np.array([r.dVal1, r.dVal2, r.dVal3]),
            std_mm=np.array([r.dStd1, r.dStd2, r.dStd3]),
            std_total_mm=float(r.dStdTotal),
            apriori_std_mm=np.array([r.dAprioriStd1, r.dAprioriStd2, r.dAprioriStd3]),
            environment=Environment(r.dTemperature, r.dPressure, r.dHumidity),
        )
        log.debug("tracker.measured", xyz_mm=point.xyz_mm.round(4).tolist(), std_mm=point.std_mm.round(5).tolist())
        return point

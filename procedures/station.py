"""Station configuration and device factory: the same code drives the simulator and the shop floor.

A station file (TOML) says where the devices are; relative ``robot`` and ``records`` paths are relative to
the file. ``open_devices(station)`` opens the controller (CAN), its parameter interface (Modbus) and the measuring
instrument (the CMM, or with ``[instrument] kind = "tracker"`` the laser tracker of ``[tracker]``:
``procedures.sections.tracker``), checks that the controller answers, and closes everything again on exit or if any of
them fails to open.

Example::

    robot = "robots/plant3.toml"       # omit for the built-in paper Table 1 robot
    name = "bay 2 station"             # this calibration station (optional)
    records = "records"                # where runs are recorded (optional): a folder (its records.sqlite) or file
    operator = "J. Smith"              # optional

    [machine]                          # the machine on the station (optional)
    serial = "DMS-0042"                # its serial number: with the robot file name, the machine's identity

    [can]                              # passed unchanged to can.Bus(**can)
    interface = "socketcan"
    channel = "can0"
    bitrate = 500000

    [controller]                       # procedures.sections.controller: kind = "hilcal" (the default: [can] with
    kind = "hilcal"                    # hilcal's message set and [modbus]) or "canopen" (EDS, node ids, mapping)

    [modbus]                           # TCP: host/port; RTU: serial_port/baudrate (kind = "hilcal" only)
    host = "192.168.10.20"
    port = 502
    device_id = 1
    timeout_s = 1.0
    map = "maps/hexapod.toml"          # its register map (docs/modbus_maps.md); omit for hilcal's own hilcal-1.1

    [instrument]
    kind = "cmm"                  # the default; "tracker": a laser tracker ([tracker], procedures.sections.tracker)

    [cmm]                              # an I++ DME 1.4.3 server (drivers.cmm.ippdme)
    url = "socket://10.0.0.5:1294"     # its TCP port (6.1; 1294 when omitted), or a serial line: /dev/ttyUSB0
    tool = "Probe1"                    # the stylus to activate (ChangeTool); omit: the CMM's active tool
    alignment = [1250.0, -3400.0, -820.0, 0.0, 0.0, 90.0]   # T_cmm<-base: [x, y, z, roll, pitch, yaw] or 4x4
    alignment_tolerance_mm = 10.0      # how far off the alignment may be (the first pose searches the base spheres)
    alignment_tolerance_deg = 0.2
    identity = "Leitz PMM-C, serial 4711"   # for the certificate (procedures.signoff.CmmIdentity)
    stated_uncertainty_mm = 0.004      # expanded U (k = 2) of one measured sphere-centre coordinate
    calibration_due = 2027-03-31       # the CMM's own calibration
    [cmm.ippdme]                       # drivers.cmm.ippdme.IppDmeConfig: waits, homing
    motion_timeout_s = 60.0
    [cmm.probing]                      # drivers.cmm.base.ProbingConfig
    probe_sigma_mm = 0.002

    [motion]
    move_timeout_s = 120.0
    heartbeat_timeout_s = 0.1          # a later heartbeat: link down, nothing is sent, the run holds

    [links]                            # procedures.link_guard.LinksSection: riding through drop-outs
    heartbeat_grace_s = 1.0            # the run ends only after this long without a heartbeat
    cmm_retries = 2                    # tracker_retries for a laser tracker
    modbus_retries = 3

    [timing]                           # procedures.timing.TimingSection: the machine's speed, for estimates
    leg_speed_mm_s = 50.0
    leg_accel_mm_s2 = 100.0
    settle_s = 2.0
    cmm_s_per_pose = 45.0
    move_overhead_s = 0.5

    [records]                          # instead of the top-level records path: a database for the whole plant
    url = "postgresql+psycopg://hilcal@db.plant/hilcal"   # or a SQLite file path (relative to this file)

    [acceptance]                       # procedures.signoff.AcceptanceSection: limits of the sign-off
    max_position_mm = 0.05
    rp_position_mm = 0.02
"""

from __future__ import annotations

import tomllib
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import structlog
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from drivers.cmm.base import ProbingConfig, as_transform
from drivers.cmm.ippdme import IppDmeCmm, IppDmeConfig
from drivers.cmm.transcript import TRANSCRIPT_NAME, TranscriptFile
from drivers.cmm.types import DEFAULT_ALIGNMENT_DEG, DEFAULT_ALIGNMENT_MM
from drivers.controller.base import ControllerInterface, ParameterInterface
from drivers.controller.hilcal_can import ControllerCan
from drivers.controller.modbus import ControllerParams
from drivers.controller.parameter_sets import ParameterSet
from drivers.instrument import CmmPoseInstrument, PoseInstrument, TrackerPoseInstrument
from drivers.tracker.emscon import EmsconTracker
from hilcal.protocols.modbus_map import RegisterMap, RegisterMapError, default_register_map, load_register_map
from hilcal.protocols.toml_text import toml_lines
from hilcal.robot import Robot, RobotFileError, load_robot
from procedures.link_guard import LinksSection
from procedures.sections.controller import ControllerSection, HilcalControllerSection, open_canopen, resolve_paths
from procedures.sections.tracker import InstrumentSection, TrackerSection, alignment_list, tracker_from_channels
from procedures.signoff import AcceptanceSection, CmmIdentity
from procedures.timing import TimingSection

log = structlog.get_logger(__name__)

class StationConfigError(ValueError):
    """A station file that cannot be read or does not describe a usable station."""


class DeviceOpenError(RuntimeError):
    """A device of the station could not be opened (the others were closed again)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CanSection(BaseModel):
    """python-can bus settings, passed unchanged to ``can.Bus(**...)`` (interface-specific keys allowed)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    interface: str = Field(description="python-can interface: socketcan, pcan, kvaser, slcan, virtual, ...")
    channel: str | int = Field(description="e.g. can0, PCAN_USBBUS1, /dev/ttyACM0")

    def bus_config(self) -> dict[str, Any]:
        """The keyword arguments of ``can.Bus``."""
        return self.model_dump()


class ModbusSection(_Strict):
    """The controller's parameter interface: Modbus TCP (host, port) or RTU (serial_port, baudrate), and its register
    map (``map``: a built-in map's name or a map file, relative to the station file; default hilcal's own
    ``hilcal-1.1``), read and validated with the station (docs/modbus_maps.md)."""

    host: str | None = None
    port: int = Field(default=502, ge=1, le=65535)
    serial_port: str | None = None
    baudrate: int = Field(default=115200, gt=0)
    device_id: int = Field(default=1, ge=1, le=247)
    timeout_s: float = Field(default=1.0, gt=0)
    map: str | None = Field(default=None, min_length=1, description="register map: a built-in map's name or a map "
                            "file (None: hilcal-1.1)")
    _register_map: RegisterMap = PrivateAttr(default_factory=default_register_map)

    @field_validator("map")
    @classmethod
    def _map_is_valid(cls, v: str | None) -> str | None:
        if v is not None:
            try:
                load_register_map(v)
            except RegisterMapError as err:
                raise ValueError(str(err)) from None
        return v

    @model_validator(mode="after")
    def _one_transport(self) -> ModbusSection:
        if (self.host is None) == (self.serial_port is None):
            raise ValueError("give either host (Modbus TCP) or serial_port (Modbus RTU), not both or neither")
        if self.map is not None:
            self._register_map = load_register_map(self.map)
        return self

    def register_map(self) -> RegisterMap:
        """The validated register map."""
        return self._register_map

    def open_params(self, nominal: ParameterSet | None = None) -> ControllerParams:
        """The parameter interface's driver (nothing is sent yet); ``nominal``: the robot's nominal set, for the parts
        of the geometry a map without them does not hold."""
        return ControllerParams(self.host, self.port, serial_port=self.serial_port, baudrate=self.baudrate,
                                device_id=self.device_id, timeout_s=self.timeout_s,
                                register_map=self._register_map, nominal=nominal)


class CmmSection(CmmIdentity):
    """The CMM, an I++ DME server: its URL, the stylus to use, the approximate T_cmm<-base, protocol and probing
    options; for the certificate its identity, stated uncertainty and calibration due date
    (``procedures.signoff.CmmIdentity``)."""

    url: str = Field(min_length=1, description="socket://HOST:1294 (I++ DME's TCP port, 6.1; the port may be "
                     "omitted), or a pyserial URL of a serial line: /dev/ttyUSB0, ...")
    tool: str | None = Field(default=None, min_length=1, max_length=64, pattern=r'^[ !#-~]+$',
                             description="the stylus to activate (ChangeTool, 6.3.2.18); None: the CMM's active tool")
    alignment: list[Any] = Field(
        description="T_cmm<-base, good to a few mm: a 4x4 matrix or [x, y, z mm, roll, pitch, yaw deg]"
    )
    alignment_tolerance_mm: float = Field(default=DEFAULT_ALIGNMENT_MM, gt=0, le=90.0,
                                          description="how far the base frame's origin may be from where `alignment` "
                                          "puts it (the first pose searches that far)")
    alignment_tolerance_deg: float = Field(default=DEFAULT_ALIGNMENT_DEG, ge=0, le=5.0,
                                           description="how far `alignment` may be turned")
    ippdme: IppDmeConfig = Field(default_factory=IppDmeConfig)
    probing: ProbingConfig = Field(default_factory=ProbingConfig)

    @field_validator("alignment")
    @classmethod
    def _transform(cls, v: list[Any]) -> list[Any]:
        return alignment_list(v)

    def alignment_matrix(self) -> np.ndarray:
        """(4, 4) T_cmm<-base."""
        return as_transform(np.asarray(self.alignment, dtype=float))


class MotionSection(_Strict):
    """Timeouts and tolerances of the controller link and of moves."""

    move_timeout_s: float = Field(default=120.0, gt=0, description="one move_legs call")
    heartbeat_timeout_s: float = Field(default=0.1, gt=0, description="link down (no command sent) after this "
                                       "silence; the run holds and ends only after [links] heartbeat_grace_s")
    ack_timeout_s: float = Field(default=0.5, gt=0, description="command acknowledgement")
    connect_timeout_s: float = Field(default=5.0, gt=0, description="first heartbeat after opening CAN")
    position_tolerance_mm: float = Field(default=0.01, gt=0, description="feedback vs setpoint at IN_POSITION")


class MachineSection(_Strict):
    """The machine under calibration: its serial number (with the robot file's name, its identity in records)."""

    serial: str | None = Field(default=None, min_length=1, max_length=100, description="the machine's serial")


class RecordsSection(_Strict):
    """Where the calibration records go: a database URL (``postgresql+psycopg://user@host/db``) or a SQLite file."""

    url: str = Field(min_length=1, description="database URL or SQLite file path")


class StationConfig(_Strict):
    """Where the devices of one calibration station are (see the module docstring for a TOML example)."""

    robot: Path | None = Field(default=None, description="robot TOML file; None: the built-in paper Table 1 robot")
    name: str | None = Field(default=None, min_length=1, max_length=100, description="this calibration station")
    machine: MachineSection = Field(default_factory=MachineSection)
    can: CanSection | None = None
    """The controller's CAN bus (a station to run with needs it; ``hilcal check`` checks only what a file names)."""
    controller: ControllerSection = Field(default_factory=HilcalControllerSection)
    modbus: ModbusSection | None = None
    instrument: InstrumentSection = Field(default_factory=InstrumentSection)
    cmm: CmmSection | None = None
    tracker: TrackerSection | None = None
    motion: MotionSection = Field(default_factory=MotionSection)
    timing: TimingSection = Field(default_factory=TimingSection)
    links: LinksSection = Field(default_factory=LinksSection)
    acceptance: AcceptanceSection = Field(default_factory=AcceptanceSection)
    records: Path | RecordsSection | None = Field(default=None, description="folder or file of the run records, "
                                                  "or a [records] table with a database url")
    operator: str | None = None

    @model_validator(mode="after")
    def _its_instrument(self, info: ValidationInfo) -> StationConfig:
        if (info.context or {}).get("partial"):
            return self
        if self.can is None:
            raise ValueError("a station needs a [can] section: the controller's CAN bus (interface, channel; "
                             "python-can's settings)")
        if self.controller.kind == "hilcal" and self.modbus is None:
            raise ValueError("a station with hilcal's own controller ([controller] kind = \"hilcal\", the default) "
                             "needs a [modbus] section (its parameter interface); a CANopen controller says "
                             "[controller] kind = \"canopen\"")
        if self.instrument.kind == "cmm" and self.cmm is None:
            raise ValueError("a station measured with a CMM ([instrument] kind = \"cmm\", the default) needs a [cmm] "
                             "section (url, alignment); one with a laser tracker says [instrument] kind = \"tracker\"")
        if self.instrument.kind == "tracker" and self.tracker is None:
            raise ValueError("[instrument] kind = \"tracker\" needs a [tracker] section (host, alignment, "
                             "environment, platform_targets_mm, base_monuments_mm)")
        return self

    def has_controller(self) -> bool:
        """The file names the controller: its CAN bus and, for hilcal's own controller, its [modbus] too."""
        return self.can is not None and (self.controller.kind != "hilcal" or self.modbus is not None)

    def instrument_address(self) -> str:
        """Where the station's measuring instrument is: the CMM's URL, or the tracker's host:port."""
        return f"{self.tracker.host}:{self.tracker.port}" if self.measuring_tracker() else self.cmm.url

    def measuring_tracker(self) -> TrackerSection | None:
        """The laser tracker's section when the station measures with one (else None)."""
        return self.tracker if self.instrument.kind == "tracker" else None

    def records_target(self) -> str | None:
        """The records database this station names: a URL, a SQLite file, or a folder's records.sqlite."""
        if isinstance(self.records, RecordsSection):
            return self.records.url
        if self.records is None:
            return None
        return str(self.records if self.records.suffix in (".sqlite", ".sqlite3", ".db") else
                   self.records / "records.sqlite")


def _format_errors(err: ValidationError, source: str) -> str:
    lines = [f"{source}: {err.error_count()} problem(s)"]
    for e in err.errors():
        where = ".".join(str(p) for p in e["loc"]) or "<top>"
        lines.append(f"  {where}: {e['msg'].removeprefix('Value error, ')}")
    return "\n".join(lines)


def station_from_dict(data: dict[str, Any], source: str = "<station>", *, partial: bool = False) -> StationConfig:
    """Validate parsed station settings; StationConfigError naming every bad field. ``partial``: a file may name only
    some of the station's devices (``hilcal check``); every section it has is checked as usual."""
    try:
        return StationConfig.model_validate(data, context={"partial": partial})
    except ValidationError as err:
        raise StationConfigError(_format_errors(err, source)) from None


def load_station(path: str | Path, *, partial: bool = False) -> StationConfig:
    """Read a station TOML file; relative ``robot``/``records`` paths are taken relative to the file. ``partial``:
    see ``station_from_dict``."""
    p = Path(path)
    source = f"station file {p}"
    try:
        text = p.read_text()
    except OSError as err:
        raise StationConfigError(f"{source}: cannot read: {err.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise StationConfigError(f"{source}: not valid TOML: {err}") from None
    base = p.resolve().parent
    for key in ("robot", "records"):
        value = data.get(key)
        if isinstance(value, str) and value and not Path(value).is_absolute():
            data[key] = str(base / value)
    resolve_paths(data, base)
    url = data["records"].get("url") if isinstance(data.get("records"), dict) else None
    if isinstance(url, str) and url and "://" not in url and not Path(url).is_absolute():
        data["records"]["url"] = str(base / url)
    return station_from_dict(data, source, partial=partial)


def station_to_toml(station: StationConfig) -> str:
    """The station as TOML text (``load_station`` reads it back to an equal StationConfig)."""
    return "\n".join(toml_lines(station.model_dump(mode="json", exclude_none=True), "")).lstrip("\n") + "\n"


def save_station(station: StationConfig, path: str | Path) -> None:
    """Write the station as a TOML file (paths are written as they are, absolute or relative to the cwd)."""
    Path(path).write_text(station_to_toml(station))


def station_from_channels(channels: dict[str, Any], robot_path: str | Path | None = None,
                          controller: dict[str, Any] | None = None) -> StationConfig:
    """The station of a running simulator (``SimHandle.channels()`` / the JSON line of ``hilcal sim --json``).

    The robot is ``robot_path``, else the simulator's robot file, else the built-in robot; its name must be
    the simulator's robot (StationConfigError otherwise). The CMM's identity and stated uncertainty are the
    simulator's, where it states them (a real station's come from its file); a simulated tracker's identity, MPE,
    air, published alignment and target layouts likewise.
    """
    path = robot_path if robot_path is not None else channels.get("robot_path")
    try:
        robot = load_robot(path)
    except RobotFileError as err:
        raise StationConfigError(str(err)) from None
    if "robot" in channels and robot.name != channels["robot"]:
        raise StationConfigError(
            f"the simulator runs robot {channels['robot']!r} but the robot file "
            f"{path or '<built-in>'} is {robot.name!r}"
        )
    try:
        data = {"robot": path, "can": channels["can"], "modbus": channels.get("modbus"), "controller": controller}
        if channels.get("instrument") == "tracker":
            data.update(instrument={"kind": "tracker"}, tracker=tracker_from_channels(channels))
        else:
            data["cmm"] = {"url": channels["cmm"]["url"], "alignment": channels["cmm_alignment"],
                           **{k: channels["cmm"][k] for k in ("identity", "stated_uncertainty_mm")
                              if channels["cmm"].get(k)}}
    except (KeyError, TypeError) as err:
        raise StationConfigError(f"simulator channels: missing {err}") from None
    return station_from_dict({k: v for k, v in data.items() if v is not None}, "simulator channels")


@dataclass(eq=False)
class Devices:
    """The open devices of a station; ``close()`` (or ``with``) closes all of them."""

    station: StationConfig
    robot: Robot
    controller: ControllerInterface
    """``ControllerCan`` (hilcal's message set) or ``CanopenController``."""
    params: ParameterInterface
    """``ControllerParams`` (Modbus) or ``CanopenParams`` (the same CANopen link as the controller)."""
    cmm: IppDmeCmm | None
    cmm_alignment: np.ndarray | None
    """(4, 4) T_cmm<-base from the station file (None: the station measures with a laser tracker)."""
    instrument: PoseInstrument
    """What measures the poses: the CMM or the laser tracker (``drivers.instrument``)."""
    tracker: EmsconTracker | None = None
    _stack: ExitStack = field(default_factory=ExitStack, repr=False)

    def close(self) -> None:
        """Close the instrument, the parameter interface and the CAN link (idempotent); device states are left as
        they are."""
        self._stack.close()

    def __enter__(self) -> Devices:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def open_devices(station: StationConfig, *, check: bool = True, run_folder: str | Path | None = None) -> Devices:
    """Open the controller (hilcal's CAN message set, or CANopen), its parameter interface (Modbus, or the CANopen
    controller's own) and the measuring instrument of a station.

    With ``check`` the controller must send a heartbeat within ``motion.connect_timeout_s`` and the parameter
    interface must identify as a compatible controller. With a ``run_folder`` the CMM's conversation is kept there,
    every line as on the wire (``instrument_transcript.txt``, appended to on a resumed run: ``drivers.cmm.transcript``).
    DeviceOpenError (naming the device) if anything fails; whatever was opened before is closed again.
    """
    try:
        robot = load_robot(station.robot)
    except RobotFileError as err:
        raise DeviceOpenError(f"the robot file: {err}") from None
    with ExitStack() as stack:
        controller, params = open_controller(station, robot, stack, check)
        tracker, cmm, alignment = None, None, None
        t = station.measuring_tracker()
        try:
            if t is not None:
                tracker = EmsconTracker(t.emscon_config())
                stack.callback(tracker.close)
                platform, base = t.layouts()
                instrument: PoseInstrument = TrackerPoseInstrument(
                    tracker, station.instrument_address(), t.alignment_matrix(),
                    (t.alignment_tolerance_mm, t.alignment_tolerance_deg), platform, base, t.environment_setting(),
                    t.reflector, t.search, (t.mpe_constant_um, t.mpe_per_m_um))
            else:
                transcript = None
                if run_folder is not None:
                    transcript = TranscriptFile(Path(run_folder) / TRANSCRIPT_NAME)
                    stack.callback(transcript.close)
                cmm = IppDmeCmm(station.cmm.url, station.cmm.ippdme, station.cmm.probing, transcript,
                                station.cmm.tool)
                stack.callback(cmm.close)
                alignment = station.cmm.alignment_matrix()
                instrument = CmmPoseInstrument(cmm, station.cmm.url, alignment, (station.cmm.alignment_tolerance_mm,
                                                                                  station.cmm.alignment_tolerance_deg))
        except Exception as err:
            what = "the laser tracker" if t is not None else "the CMM"
            raise DeviceOpenError(f"{what} at {station.instrument_address()}: {_reason(err)}") from err
        devices = Devices(station, robot, controller, params, cmm, alignment, instrument, tracker, stack.pop_all())
    log.info("station_devices_opened", robot=robot.name, can=station.can.bus_config().get("channel"),
             controller=station.controller.kind,
             modbus=params.endpoint, instrument=station.instrument.kind, address=station.instrument_address())
    return devices


def can_words(bus: dict[str, Any]) -> str:
    """A station's CAN interface in words: "CAN interface socketcan, channel can0, 500000 bit/s"."""
    said = f"CAN interface {bus.get('interface')}, channel {bus.get('channel')}"
    return said + (f", {bus['bitrate']} bit/s" if bus.get("bitrate") else "")


def _reason(err: BaseException) -> str:
    """What went wrong in words: the error's message, or where a driver restates the settings as a Python dict (the
    CAN driver does), the cause it wraps (the operating system's or the bus library's words)."""
    text, cause = str(err), err.__cause__
    if "{'" in text and cause is not None and str(cause):
        text = str(cause)
    return text or type(err).__name__


def open_controller(station: StationConfig, robot: Robot, stack: ExitStack, check: bool, *, writes: bool = True
                     ) -> tuple[ControllerInterface, ParameterInterface]:
    """The controller and its parameter interface of the station's [controller] kind (closed by ``stack``); check:
    wait for its heartbeat and read its identity; writes=False: open it without writing anything (`hilcal check`)."""
    motion = station.motion
    if station.controller.kind == "canopen":
        try:
            controller, params = open_canopen(station.controller, station.can.bus_config(), robot,
                                              heartbeat_timeout_s=motion.heartbeat_timeout_s,
                                              ack_timeout_s=motion.ack_timeout_s,
                                              position_tolerance_mm=motion.position_tolerance_mm, writes=writes)
            stack.callback(controller.close)
            if check:
                controller.wait_for_heartbeat(motion.connect_timeout_s)
                params.read_identity()
        except Exception as err:
            nodes = ", ".join(str(n) for n in station.controller.nodes())
            raise DeviceOpenError(f"the CANopen controller ({station.controller.eds_path().name}, node {nodes}) on "
                                  f"{can_words(station.can.bus_config())}: {_reason(err)}") from err
        return controller, params
    try:
        controller = ControllerCan(station.can.bus_config(), robot, heartbeat_timeout_s=motion.heartbeat_timeout_s,
                                   ack_timeout_s=motion.ack_timeout_s,
                                   position_tolerance_mm=motion.position_tolerance_mm)
        stack.callback(controller.close)
        if check:
            controller.wait_for_heartbeat(motion.connect_timeout_s)
    except Exception as err:
        raise DeviceOpenError(f"the controller's {can_words(station.can.bus_config())}: {_reason(err)}") from err
    mb = station.modbus
    assert mb is not None  # the station's validator
    try:
        params = mb.open_params(ParameterSet.from_robot(robot))
        stack.callback(params.close)
        if check:
            params.read_identity()
    except Exception as err:
        where = f"Modbus TCP {mb.host}:{mb.port}" if mb.host else f"Modbus RTU on {mb.serial_port}"
        raise DeviceOpenError(f"the controller's parameter interface, {where}: {_reason(err)}") from err
    return controller, params

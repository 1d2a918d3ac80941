"""The ``hilcal sim`` configuration: robot, rig truth, controller, CMM or laser tracker, and state file, read from TOML
and validated.

Example configuration (every key optional; relative paths are relative to the file)::

    robot = "robots/plant3.toml"    # default: `hilcal run --robot FILE`'s, else the built-in paper Table 1 robot
    state_file = "sim_state.json"   # default: no persistence
    instrument = "cmm"              # or "tracker" (hilcal sim --instrument tracker): the laser tracker instead

    [rig]                           # SimulatedRig truth: seed and errors, plus any RigConfig field
    seed = 0
    errors = "table2"               # table2..table5, zero, or an errors TOML file
    errors_scale = 1.0              # multiplies the errors (the paper's tables are for its 3.7 m machine)
    leg_resolution_mm = 0.001
    [rig.effects.thermal_expansion]
    enabled = true

    [controller]                    # ControllerSimConfig; time_scale defaults to 100 here
    time_scale = 100.0
    protocol = "hilcal"             # or "canopen" (the HX-6, one CANopen node) or "canopen-cia402" (six LD-1 drives)
                                    # (hilcal sim --controller ...)
    canopen = { node_id = 1, drive_node_ids = [1, 2, 3, 4, 5, 6] }   # CANopen node ids
    following_error_mm = 5.0        # a moving leg whose reading is this far from its ramp: FAULT FOLLOWING_ERROR
    dead_transducer_legs = [4]      # a fault to find: legs whose transducer is dead (default: none)
    dead_reading_mm = 0.0           # what a dead one reads (controller length; default: its power-up reading)
    [controller.can_faults]
    drop_rate = 0.001

    [cmm]                           # CmmServerConfig, I++ DME 1.4.3 (time_scale defaults to 0.0005, tcp_port to 0)
    noise_sigma_mm = 0.002          # noise of a latched ball centre per coordinate
    stated_uncertainty_mm = 0.004   # U (k = 2) per sphere-centre coordinate it states (default 2 x noise_sigma_mm)
    alignment_error_mm = 2.0        # error of the published T_cmm<-base (a station's rough CMM set-up)
    alignment_error_deg = 0.02
    on_collision = "stop"           # a crash is 2504 Collision (the default; "count": logged, the ball passes)
    probing_speed_mm_s = 10.0       # PtMeasPar.Speed's default; probe_time_s (0.05) per touch, travel_speed_mm_s 250
    active_tool = "Probe1"          # at power-up ("UnDefTool": a server that does not know which tool is loaded)
    [[cmm.tools]]                   # the tool table (default: Probe1, a 1.5 mm ball, Approach/Search/Retract 10)
    name = "Probe1"
    ball_radius_mm = 1.5
    [cmm.faults]
    garbage = 0.01

    [tracker]                       # TrackerServerConfig (time_scale defaults to 0.0005 here)
    station = { x_mm = 6000.0, y_mm = -1500.0, z_mm = 1800.0, yaw_deg = 165.0 }  # its frame in the base frame
    mpe_constant_um = 15.0          # MPE U = ±(15 µm + 6 µm/m): the noise is U/2 along and across the beam
    mpe_per_m_um = 6.0
    search_radius_mm = 50.0         # the ATR search radius at power-up
    alignment_error_mm = 2.0        # error of the published T_tracker<-base (a station's rough set-up)
    alignment_error_deg = 0.02
    platform_targets_mm = [[1000.0, 0.0, 100.0], [-500.0, 866.03, 100.0], [-500.0, -866.03, 100.0]]  # the nests
    base_monuments_mm = [[2500.0, 1443.38, 100.0], [-2500.0, 1443.38, 100.0], [0.0, -2886.75, 100.0]]
                                    # default: four of each around the robot file's spheres (published as the truth)
    hang_after_commands = 400       # a fault: it answers nothing from its 401st command on (default: never)
    move_every_poses = 20           # set up again near its place after every 20 poses it measured (default 0: never)
    move_mm = 40.0                  # each move: its origin this far along a seeded direction (default 40)
    move_deg = 0.5                  # and its frame turned this much about a seeded axis (default 0.5)
    [tracker.air]                   # the true air (the tracker corrects for what the client sets)
    temperature_c = 20.0
    pressure_hpa = 1013.25
    humidity_pct = 50.0
    [[tracker.obstacles]]           # spheres no beam passes (base frame)
    centre_mm = [3000.0, -800.0, 1500.0]
    radius_mm = 300.0
    [tracker.faults]
    beam_break = 0.01
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hilcal.protocols.toml_text import toml_lines
from hilcal.robot import Robot
from sim_devices.canopen.config import CanopenSimConfig, Variant
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.controller.state_machine import ControllerSimConfig
from sim_devices.rig.config import BUILTIN_ERROR_SETS, GeometryErrors, RigConfig, load_errors
from sim_devices.tracker.config import TrackerServerConfig

log = structlog.get_logger(__name__)


ControllerProtocol = Literal["hilcal", "canopen", "canopen-cia402"]
CONTROLLER_PROTOCOLS: tuple[str, ...] = ("hilcal", "canopen", "canopen-cia402")
CANOPEN_VARIANTS: dict[str, Variant] = {"canopen": "hexapod", "canopen-cia402": "cia402"}


class SimConfigError(ValueError):
    """A simulator configuration that cannot be read or is not valid."""


class SimRigSettings(BaseModel):
    """The rig: ``seed``, ``errors`` (built-in name or TOML file) and any further ``RigConfig`` field."""

    model_config = ConfigDict(extra="allow", frozen=True)

    seed: int = 0
    errors: str = Field(default="table2", description=f"one of {', '.join(BUILTIN_ERROR_SETS)} or an errors TOML file")
    errors_scale: float = Field(default=1.0, gt=0, le=100.0, description="multiplies every geometric error (the "
                                "paper's tables are a 3.7 m machine's: 0.03 brings them to a 100 mm hexapod's size)")

    @model_validator(mode="after")
    def _valid_rig_fields(self) -> SimRigSettings:
        try:
            RigConfig.model_validate({**(self.model_extra or {}), "seed": self.seed, "errors": GeometryErrors.zero()})
        except ValidationError as err:
            raise ValueError("; ".join(
                f"{'.'.join(str(p) for p in e['loc'])}: {e['msg'].removeprefix('Value error, ')}" for e in err.errors()
            )) from None
        return self

    def rig_config(self, robot: Robot) -> RigConfig:
        """The RigConfig with the errors loaded (ValueError naming the errors source if they cannot be)."""
        errors = load_errors(self.errors, robot)
        if self.errors_scale != 1.0:
            errors = GeometryErrors.from_vector(errors.to_vector() * self.errors_scale)
        return RigConfig.model_validate({**(self.model_extra or {}), "seed": self.seed, "errors": errors})


class SimControllerConfig(ControllerSimConfig):
    """ControllerSimConfig with the launcher's default time scale: servo and rig clock × 100.

    A 56-pose plan (~870 moves of at most 50 mm) then takes ~30 s: each move is bounded by the 20 ms heartbeat,
    and the rig clock covers about the duration of a real run (~50 min).
    """

    time_scale: float = Field(default=100.0, gt=0, description="simulated seconds per real second")
    protocol: ControllerProtocol = Field(
        default="hilcal", description="what the controller speaks: hilcal (hilcal's own CAN message set on SLCAN and "
        "Modbus TCP), canopen (the HX-6 hexapod controller, one CANopen node) or canopen-cia402 (six CiA 402 LD-1 "
        "leg drives), the CANopen ones on SLCAN only")
    canopen: CanopenSimConfig = Field(default_factory=CanopenSimConfig, description="CANopen node ids")

    @property
    def canopen_variant(self) -> Variant | None:
        """The CANopen variant served (None: hilcal's own protocol)."""
        return CANOPEN_VARIANTS.get(self.protocol)


class SimCmmConfig(CmmServerConfig):
    """CmmServerConfig with fast defaults, a TCP endpoint, the error of the published CMM alignment, and the
    uncertainty the simulated CMM states (as a real CMM's calibration certificate does, for the station file)."""

    time_scale: float = Field(default=0.0005, ge=0, description="multiplies every CMM duration; 0 = instant")
    tcp_port: int | None = Field(default=0, ge=0, le=65535, description="None: pty only; 0: ephemeral port")
    alignment_error_mm: float = Field(default=2.0, ge=0, description="offset of the published T_cmm<-base")
    alignment_error_deg: float = Field(default=0.02, ge=0, description="rotation error of the published T_cmm<-base")
    stated_uncertainty_mm: float | None = Field(
        default=None, gt=0, le=1.0, description="expanded uncertainty U (k = 2) of one sphere-centre coordinate "
        "that the simulated CMM states; None: 2 x noise_sigma_mm, one touch point's (a centre fitted from several "
        "touches scatters less, so this errs on the safe side)")

    def stated_uncertainty(self) -> float | None:
        """U (k = 2) per sphere-centre coordinate: as set, else 2 x noise_sigma_mm (None for a noiseless CMM)."""
        if self.stated_uncertainty_mm is not None:
            return self.stated_uncertainty_mm
        return 2.0 * self.noise_sigma_mm if self.noise_sigma_mm > 0 else None

    def identity(self) -> str:
        """The CMM as a certificate names it: what it is and the noise it was configured with."""
        return f"simulated CMM (hilcal sim), touch-point noise {self.noise_sigma_mm:g} mm per coordinate"

    def server_config(self, default_seed: int) -> CmmServerConfig:
        """The CmmServerConfig to start the server with (seed: the rig seed unless set here)."""
        data = self.model_dump(exclude={"alignment_error_mm", "alignment_error_deg", "stated_uncertainty_mm"})
        if "seed" not in self.model_fields_set:
            data["seed"] = default_seed
        return CmmServerConfig.model_validate(data)


class SimTrackerConfig(TrackerServerConfig):
    """TrackerServerConfig with fast defaults, the error of the published tracker alignment (a station's rough
    set-up, as for the CMM), and the targets: reflectors in the platform's nests and on the base monuments, whose
    layouts the simulator publishes as a survey gives them (the truth)."""

    time_scale: float = Field(default=0.0005, ge=0, description="multiplies every tracker duration; 0 = instant")
    alignment_error_mm: float = Field(default=2.0, ge=0, description="offset of the published T_tracker<-base")
    alignment_error_deg: float = Field(default=0.02, ge=0, description="rotation error of the published alignment")
    platform_targets_mm: list[tuple[float, float, float]] | None = Field(
        default=None, min_length=3, description="nests on the platform (platform frame); None: four around the robot "
        "file's platform spheres (sim_devices.tracker.targets.default_targets)")
    base_monuments_mm: list[tuple[float, float, float]] | None = Field(
        default=None, min_length=3, description="monuments on the floor (base frame); None: four around the robot "
        "file's base spheres")

    def identity(self) -> str:
        """The tracker as a certificate names it: what it is and its MPE."""
        return (f"simulated laser tracker (hilcal sim, emScon), MPE ±({self.mpe_constant_um:g} µm + "
                f"{self.mpe_per_m_um:g} µm/m)")

    def server_config(self, default_seed: int) -> TrackerServerConfig:
        """The TrackerServerConfig to start the server with (seed: the rig seed unless set here)."""
        data = self.model_dump(exclude={"alignment_error_mm", "alignment_error_deg", "platform_targets_mm",
                                        "base_monuments_mm"})
        if "seed" not in self.model_fields_set:
            data["seed"] = default_seed
        return TrackerServerConfig.model_validate(data)


class SimConfig(BaseModel):
    """Everything ``hilcal sim`` runs (see the module docstring for a TOML example)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot: Path | None = Field(default=None, description="robot TOML file; None: the built-in paper Table 1 robot")
    rig: SimRigSettings = Field(default_factory=SimRigSettings)
    controller: SimControllerConfig = Field(default_factory=SimControllerConfig)
    cmm: SimCmmConfig = Field(default_factory=SimCmmConfig)
    instrument: Literal["cmm", "tracker"] = Field(default="cmm", description="the measuring instrument served")
    tracker: SimTrackerConfig = Field(default_factory=SimTrackerConfig)
    state_file: Path | None = Field(default=None, description="controller and rig state, kept across restarts")


def format_validation_errors(err: ValidationError, source: str) -> str:
    lines = [f"{source}: {err.error_count()} problem(s)"]
    for e in err.errors():
        where = ".".join(str(p) for p in e["loc"]) or "<top>"
        lines.append(f"  {where}: {e['msg'].removeprefix('Value error, ')}")
    return "\n".join(lines)


def _resolve(base: Path, value: Any) -> Any:
    """A relative path string resolved against base (other values unchanged)."""
    if isinstance(value, str) and value and not Path(value).is_absolute():
        return str(base / value)
    return value


def load_sim_config(
    path: str | Path | None = None, *, state_file: str | Path | None = None, seed: int | None = None,
    instrument: str | None = None, controller: str | None = None, robot: str | Path | None = None,
) -> SimConfig:
    """The configuration from a TOML file (None: defaults), with ``--state-file``/``--seed``/``--instrument``/
    ``--controller`` (the controller's protocol) and ``--robot`` (the robot file to simulate) overrides.

    Relative ``robot``, ``state_file`` and errors-file paths are relative to the file. SimConfigError otherwise.
    """
    data: dict[str, Any] = {}
    source = "simulator defaults"
    if path is not None:
        p = Path(path)
        source = f"simulator config {p}"
        try:
            data = tomllib.loads(p.read_text())
        except OSError as err:
            raise SimConfigError(f"{source}: cannot read: {err.strerror}") from None
        except tomllib.TOMLDecodeError as err:
            raise SimConfigError(f"{source}: not valid TOML: {err}") from None
        base = p.resolve().parent
        for key in ("robot", "state_file"):
            data[key] = _resolve(base, data.get(key))
        rig = data.get("rig")
        if isinstance(rig, dict) and isinstance(rig.get("errors"), str) and rig["errors"] not in BUILTIN_ERROR_SETS:
            data["rig"] = {**rig, "errors": _resolve(base, rig["errors"])}
    if state_file is not None:
        data["state_file"] = str(state_file)
    if robot is not None:
        data["robot"] = str(robot)
    if seed is not None:
        rig = data.get("rig")
        data["rig"] = {**(rig if isinstance(rig, dict) else {}), "seed": seed}
    if instrument is not None:
        data["instrument"] = instrument
    if controller is not None:
        table = data.get("controller")
        data["controller"] = {**(table if isinstance(table, dict) else {}), "protocol": controller}
    data = {k: v for k, v in data.items() if v is not None}
    try:
        return SimConfig.model_validate(data)
    except ValidationError as err:
        raise SimConfigError(format_validation_errors(err, source)) from None


def sim_config_toml(data: dict[str, Any], header: str = "") -> str:
    """A simulator configuration (the dict `load_sim_config` reads: robot, rig, controller, cmm) as TOML text, with
    an optional comment header; tables, arrays of tables and arrays of numbers."""
    comment = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    return comment + "\n".join(toml_lines(data, "")).lstrip("\n") + "\n"


def simulation_summary(config: SimConfig, robot: Robot) -> dict[str, Any]:
    """What a simulator with this configuration simulates, in figures and in sentences (``lines``): the robot, its
    geometric errors and their size, the effects beyond the geometry, the instrument and its noise, the clock."""
    rig = config.rig.rig_config(robot)
    vector = rig.errors.to_vector().reshape(6, 7)
    joints_mm = float(np.max(np.abs(vector[:, :6]))) if vector.size else 0.0
    lengths_mm = float(np.max(np.abs(vector[:, 6])))
    source = config.rig.errors
    scale = config.rig.errors_scale
    scaled = "" if scale == 1.0 else f", times {scale:g}"
    if source == "zero":
        errors = "none: the machine is built exactly as its robot file says"
    elif source in BUILTIN_ERROR_SETS:
        errors = (f"the paper's Table {source.removeprefix('table')} (Yu 2022, in mm for its 3.7 m robot)"
                  + (scaled or ", not scaled to this robot") + ", each leg's length error taken along this robot's leg")
    else:
        errors = f"the errors file {source}{scaled}"
    if source != "zero":
        errors += f": joint errors up to {joints_mm:.3g} mm, leg length errors up to {lengths_mm:.3g} mm"
    effects = [{"name": name, "title": _title(getattr(rig.effects, name))} for name in rig.effects.active()]
    if config.instrument == "tracker":
        t = config.tracker
        instrument = (f"the simulated laser tracker (Leica emScon over TCP), MPE ±({t.mpe_constant_um:g} µm + "
                      f"{t.mpe_per_m_um:g} µm/m), its station set up {t.alignment_error_mm:g} mm and "
                      f"{t.alignment_error_deg:g}° away from where it is published")
    else:
        c = config.cmm
        stated = c.stated_uncertainty()
        instrument = (f"the simulated CMM (I++ DME), noise {c.noise_sigma_mm:g} mm per touch-point coordinate"
                      + ("" if stated is None else f", stated uncertainty U = {stated:g} mm (k = 2)")
                      + f", set up {c.alignment_error_mm:g} mm and {c.alignment_error_deg:g}° away from where it "
                      "is published")
    temperature = rig.temperature
    scale_s = config.controller.time_scale
    if temperature.table_c is not None:
        air = "the legs' temperature follows a recorded history"
    else:
        air = (f"the legs' temperature starts at {temperature.t0_c:.1f} °C and drifts {temperature.drift_k_per_h:.2f} "
               f"K/h with a {temperature.amplitude_k:g} K swing")
    clock = (f"the simulated controller ({config.controller.protocol}) runs {scale_s:g} times faster than real time "
             f"(its clock: {air})")
    robot_file = None if config.robot is None else str(config.robot)
    lines = [f"simulated machine: robot {robot.name} ({robot_file or 'the built-in paper Table 1 robot'}), "
             f"seed {config.rig.seed}",
             f"  geometric errors: {errors}",
             "  beyond the geometry: " + (", ".join(e["title"] for e in effects) or "nothing (the geometry alone)"),
             f"  instrument: {instrument}",
             f"  clock: {clock}"]
    return {"robot": {"name": robot.name, "file": robot_file},
            "errors": {"source": source, "scale": scale, "max_joint_error_mm": joints_mm,
                       "max_length_error_mm": lengths_mm, "words": errors},
            "effects": effects, "instrument": {"kind": config.instrument, "words": instrument},
            "time_scale": scale_s, "seed": config.rig.seed, "lines": lines}


def _title(effect: BaseModel) -> str:
    """An effect in words: the first part of its configuration's docstring ("Structural leg compliance")."""
    first = (type(effect).__doc__ or type(effect).__name__).strip().split("\n\n")[0]
    return " ".join(first.split(":")[0].removesuffix(".").split())

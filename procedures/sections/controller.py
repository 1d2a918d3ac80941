"""The station's ``[controller]`` section: which protocol the motion controller speaks and, for CANopen, its EDS, node
ids and mapping, checked against the EDS when the station is read (docs/controllers.md).

``kind = "hilcal"`` (the default): hilcal's own CAN message set on ``[can]`` and the Modbus parameter interface of
``[modbus]``. ``kind = "canopen"``: a CANopen controller on the bus of ``[can]`` (python-can settings as for the
default), ``eds`` (a path relative to the station file, or ``builtin:hexapod_controller`` /
``builtin:cia402_leg_drive``), ``node_id`` (one node for the machine) or ``node_ids`` (one per leg, leg order) and the
mapping (``drivers.controller.canopen_mapping``); ``profile = "cia402-hexapod"`` fills the mapping for six CiA 402
drives from ``position_unit_mm`` alone. ``open_canopen`` opens the link and returns the motion and parameter
interfaces sharing it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers.controller.canopen_mapping import (
    Actual,
    CanopenMapping,
    Checksum,
    Command,
    Compensation,
    DeviceControl,
    Geometry,
    IdentityCheck,
    MappingError,
    Readings,
    Setpoints,
)
from hilcal.protocols.canopen import CIA402_LEG_DRIVE_EDS, HEXAPOD_CONTROLLER_EDS

BUILTIN_EDS = {"builtin:hexapod_controller": HEXAPOD_CONTROLLER_EDS, "builtin:cia402_leg_drive": CIA402_LEG_DRIVE_EDS}
MAPPING_KEYS = ("device_control", "setpoints", "actual", "geometry", "compensation", "readings", "checksum", "store",
                "restore", "identity", "emcy_codes")


class HilcalControllerSection(BaseModel):
    """hilcal's own CAN message set ([can]) with the Modbus parameter interface ([modbus])."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["hilcal"] = "hilcal"


class CanopenControllerSection(BaseModel):
    """A CANopen controller (see the module docstring); the mapping's sections are ``[controller.setpoints]`` and so
    on, as in ``drivers.controller.canopen_mapping.CanopenMapping``."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    kind: Literal["canopen"]
    eds: str = Field(min_length=1, description="EDS or DCF file (relative to the station file) or builtin:NAME")
    node_id: int | None = Field(default=None, ge=1, le=127, description="the controller's node (one node)")
    node_ids: list[int] | None = Field(default=None, description="one node per leg, in leg order (six drives)")
    profile: Literal["custom", "cia402-hexapod"] = "custom"
    position_unit_mm: float | None = Field(default=None, gt=0, description="cia402-hexapod: one position unit in "
                                           "mm (1 µm: 0.001)")
    leg_offsets: bool = Field(default=True, description="cia402-hexapod: the leg offsets are 607Ch home offset")
    sdo_timeout_s: float = Field(default=0.5, gt=0, le=10, description="one SDO request")
    heartbeat_ms: int | None = Field(default=None, ge=1, le=65535, description="producer heartbeat time written to "
                                     "1017h on opening (default: the device's own)")
    device_control: DeviceControl | None = None
    setpoints: Setpoints | None = None
    actual: Actual | None = None
    geometry: Geometry | None = None
    compensation: Compensation | None = None
    readings: Readings | None = None
    checksum: Checksum | None = None
    store: Command | None = None
    restore: Command | None = None
    identity: IdentityCheck | None = None
    emcy_codes: dict[str, str] | None = None

    @model_validator(mode="after")
    def _fits(self) -> CanopenControllerSection:
        if (self.node_id is None) == (self.node_ids is None):
            raise ValueError("give node_id (one node) or node_ids (one per leg), not both or neither")
        ids = self.nodes()
        if any(not 1 <= n <= 127 for n in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"node_ids {ids}: each 1-127, each once")
        if self.profile == "cia402-hexapod":
            if len(ids) != 6:
                raise ValueError("profile cia402-hexapod: node_ids holds the six drives' nodes, leg 1 first")
            if self.position_unit_mm is None:
                raise ValueError("profile cia402-hexapod needs position_unit_mm (one position unit in mm; 1 µm: "
                                 "0.001)")
        elif self.setpoints is None or self.actual is None:
            raise ValueError("a custom CANopen mapping needs [controller.setpoints] and [controller.actual] (or "
                             "profile = \"cia402-hexapod\")")
        try:
            self.resolve()
        except MappingError as err:
            raise ValueError(str(err)) from None
        return self

    def nodes(self) -> list[int]:
        return list(self.node_ids) if self.node_ids is not None else [int(self.node_id or 0)]

    def eds_path(self) -> Path:
        return BUILTIN_EDS.get(self.eds, Path(self.eds))

    def mapping(self) -> CanopenMapping:
        """The mapping: the profile's, with the station's own sections in place of the profile's same sections."""
        given = {k: getattr(self, k) for k in MAPPING_KEYS if getattr(self, k) is not None}
        if self.profile == "cia402-hexapod":
            from drivers.controller.canopen_resolved import cia402_hexapod

            base = cia402_hexapod(position_unit_mm=float(self.position_unit_mm or 0), offsets=self.leg_offsets)
            return base.model_copy(update=given)
        return CanopenMapping.model_validate({k: v if not isinstance(v, BaseModel) else v.model_dump()
                                              for k, v in given.items()})

    def resolve(self) -> Any:
        """The mapping resolved against the EDS (``drivers.controller.canopen_resolved.Resolved``); MappingError."""
        from drivers.controller.canopen_link import load_dictionaries
        from drivers.controller.canopen_resolved import resolve

        path = self.eds_path()
        try:
            dictionaries = load_dictionaries(path, self.nodes())
        except ValueError as err:
            raise MappingError(f"controller.eds: {err}") from None
        return resolve(self.mapping(), dictionaries, self.nodes(), path.name)


ControllerSection = Annotated[HilcalControllerSection | CanopenControllerSection, Field(discriminator="kind")]


def resolve_paths(data: dict[str, Any], base: Path) -> None:
    """A station file's relative ``controller.eds`` and ``modbus.map`` taken relative to the file (in place)."""
    from hilcal.protocols.modbus_map import built_in_maps

    for key, name, built_in in (("controller", "eds", BUILTIN_EDS), ("modbus", "map", built_in_maps())):
        section = data.get(key)
        value = section.get(name) if isinstance(section, dict) else None
        if isinstance(value, str) and value and value not in built_in and not Path(value).is_absolute():
            section[name] = str(base / value)


def open_canopen(section: CanopenControllerSection, bus_config: dict[str, Any], robot: Any, *,
                 heartbeat_timeout_s: float, ack_timeout_s: float, position_tolerance_mm: float,
                 bus: Any = None, writes: bool = True) -> tuple[Any, Any]:
    """Open the controller's CANopen link: (CanopenController, CanopenParams) sharing it; closing either closes it.
    writes=False (`hilcal check`): the producer heartbeat time is read, not set to the section's heartbeat_ms."""
    from drivers.controller.canopen_link import CanopenLink, load_dictionaries
    from drivers.controller.canopen_motion import CanopenController
    from drivers.controller.canopen_params import CanopenParams

    resolved = section.resolve()
    link = CanopenLink(bus_config, load_dictionaries(section.eds_path(), section.nodes()),
                       sdo_timeout_s=section.sdo_timeout_s, heartbeat_timeout_s=heartbeat_timeout_s,
                       heartbeat_ms=section.heartbeat_ms, bus=bus, writes=writes)
    return (CanopenController(link, resolved, robot, ack_timeout_s=ack_timeout_s,
                              position_tolerance_mm=position_tolerance_mm),
            CanopenParams(link, resolved, robot))


def open_parameters(station: Any) -> Any:
    """The station's parameter interface alone (``hilcal upload``, ``hilcal rollback``): Modbus, or the CANopen
    controller's (its link opened; the robot file's geometry stands for what the device does not hold)."""
    from drivers.controller.parameter_sets import ParameterSet
    from hilcal.robot import load_robot

    if station.controller.kind == "canopen":
        robot = load_robot(station.robot)
        return open_canopen(station.controller, station.can.bus_config(), robot,
                            heartbeat_timeout_s=station.motion.heartbeat_timeout_s,
                            ack_timeout_s=station.motion.ack_timeout_s,
                            position_tolerance_mm=station.motion.position_tolerance_mm)[1]
    mb = station.modbus
    assert mb is not None
    return mb.open_params(ParameterSet.from_robot(load_robot(station.robot)))

"""The pre-flight check of a station (``hilcal check``), as a technician runs it at the start of a shift.

Every device the station file names is connected and asked who it is and what state it is in: the controller (its
heartbeat and state, the parameter interface's identity, the geometry it holds and its checksum), the CMM (its I++ DME
version and class, tools, active stylus and its radius, whether it is homed; then the robot's base spheres, searched
for from the station's alignment and its tolerance as a run's first pose does) or the laser tracker (its monuments).
Nothing is written to a controller and the platform does not move: the probe keeps clear of wherever the platform's
spheres can be in its workspace. Each device's result is plain data (``DeviceCheck.as_json``); a device that fails
says why in ``problems`` and the others are still checked.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog

from hilcal.robot import Robot

log = structlog.get_logger(__name__)


@dataclass
class DeviceCheck:
    """One device's check: who it is, what was found, and what is wrong (empty: nothing)."""

    kind: str
    """"controller", "cmm" or "tracker"."""
    address: str
    identity: Any = None
    details: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def as_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "address": self.address, "identity": self.identity, **self.details,
                "ok": self.ok, "problems": list(self.problems)}


@dataclass
class StationCheck:
    """Every device's check; the station is fit for a run when all of them are."""

    devices: list[DeviceCheck]

    @property
    def ok(self) -> bool:
        return bool(self.devices) and all(d.ok for d in self.devices)

    def as_json(self) -> dict[str, Any]:
        return {"ok": self.ok, "devices": [d.as_json() for d in self.devices]}


def workspace_belief(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Where the platform can be when nothing says where it is: the workspace's centre and a covariance whose bound
    covers the workspace box ([dt mm; dw rad], as ``hilcal.acquisition`` bounds a prediction)."""
    from hilcal.acquisition.spheres import BodyBelief

    lo, hi = robot.workspace[:, 0], robot.workspace[:, 1]
    centre = (lo + hi) / 2
    half_mm = float(np.linalg.norm((hi - lo)[:3] / 2))
    half_deg = float(np.max((hi - lo)[3:] / 2))
    return centre, BodyBelief.within(np.eye(4), half_mm, half_deg).cov


def check_cmm(station: Any, robot: Robot, home: Callable[[], bool]) -> DeviceCheck:
    """Connect the CMM, read who it is and its stylus, home it if asked (``home()`` says whether the operator agrees),
    and measure the robot's base spheres in the CMM's frame."""
    from drivers.cmm.ippdme import IppDmeCmm
    from drivers.cmm.types import CmmDriverError

    section = station.cmm
    check = DeviceCheck("cmm", section.url)
    try:
        with IppDmeCmm(section.url, section.ippdme, section.probing, tool=section.tool) as cmm:
            cmm.start_session()
            check.identity = {"dme_version": cmm.version, "machine_class": cmm.machine_class,
                              "stated": section.identity}
            check.details.update(tools=cmm.tools, active_tool=cmm.active_tool)
            homed = cmm.is_homed()
            check.details["homed"] = homed
            if not homed and not home():
                check.problems.append("the CMM is not homed: home it (hilcal check --home, or at the CMM) before a "
                                      "run; its spheres were not measured")
                return check
            cmm.home()
            check.details.update(homed=True, active_tool=cmm.active_tool,
                                 stylus_radius_mm=round(float(cmm.stylus_radius_mm), 6))
            pose, cov = workspace_belief(robot)
            base = cmm.measure_base(robot, section.alignment_matrix(),
                                    (section.alignment_tolerance_mm, section.alignment_tolerance_deg), pose, cov)
    except (CmmDriverError, OSError, ValueError) as err:
        check.problems.append(f"{type(err).__name__}: {err}")
        return check
    spheres = [{"name": f"base {k + 1}", "centre_mm": [round(float(v), 4) for v in m.centre_mm],
                "radius_mm": round(float(m.radius_free_mm), 4), "rms_mm": round(float(m.rms_mm), 5),
                "touches": len(m.probes), "searched": m.search is not None}
               for k, m in enumerate(base.spheres)]
    check.details["spheres"] = spheres
    check.details["registration_rms_mm"] = round(base.registration_rms_mm, 5)
    check.details["alignment"] = [[round(float(v), 6) for v in row] for row in base.refined_alignment]
    tol = section.probing.registration_tol_mm
    if base.registration_rms_mm > tol:
        check.problems.append(f"the base spheres do not match the robot file's base layout: registration RMS "
                              f"{base.registration_rms_mm:.4f} mm > {tol} mm (a sphere moved, or the layout is wrong)")
    return check


def check_tracker(station: Any, robot: Robot) -> DeviceCheck:
    """Connect the laser tracker, initialise it with the station's air and reflector, and find its monuments."""
    from drivers.instrument import TrackerPoseInstrument
    from drivers.tracker.base import TrackerDriverError
    from drivers.tracker.emscon import EmsconTracker
    from drivers.tracker.pose import TrackerPoseError

    t = station.tracker
    check = DeviceCheck("tracker", f"{t.host}:{t.port}", identity=t.identity)
    try:
        with EmsconTracker(t.emscon_config()) as tracker:
            platform, base = t.layouts()
            instrument = TrackerPoseInstrument(tracker, check.address, t.alignment_matrix(),
                                               (t.alignment_tolerance_mm, t.alignment_tolerance_deg), platform, base,
                                               t.environment_setting(), t.reflector, t.search,
                                               (t.mpe_constant_um, t.mpe_per_m_um))
            instrument.prepare()
            pose, cov = workspace_belief(robot)
            monuments, _, rms = instrument.poser.measure_monuments(
                base, t.alignment_matrix(), (t.alignment_tolerance_mm, t.alignment_tolerance_deg), platform, pose,
                cov)
    except (TrackerDriverError, TrackerPoseError, OSError, ValueError) as err:
        check.problems.append(f"{type(err).__name__}: {err}")
        return check
    check.details["monuments"] = [{"name": m.name, "point_mm": [round(float(v), 4) for v in m.point.xyz_mm],
                                   "offset_mm": round(m.offset_mm, 4)} for m in monuments]
    check.details["registration_rms_mm"] = round(rms, 5)
    return check


def _canopen_stops(control: Any) -> dict[str, str]:
    """How hilcal can stop the device over the bus, in words: a mapping without a halt or a quick stop is said before
    a run, not found when the operator pauses."""
    return {"stop": "none: a move in progress runs to its end" if control.halt_bit is None
            else f"halt, controlword bit {control.halt_bit}",
            "estop": "none over the bus: the machine's hardware e-stop only" if control.quick_stop is None
            else f"quick stop, controlword {control.quick_stop:04X}h"}


def check_controller(station: Any, robot: Robot) -> DeviceCheck:
    """Connect the controller: its heartbeat and state, and the parameter interface's identity, state, geometry and
    checksum (nothing written)."""
    from procedures.station import DeviceOpenError, open_controller

    bus = station.can.bus_config()
    check = DeviceCheck("controller", f"CAN {bus.get('interface')} {bus.get('channel')}")
    check.details.update(protocol=station.controller.kind, can=f"{bus.get('interface')} {bus.get('channel')}")
    if station.controller.kind == "canopen":
        check.details["stops"] = _canopen_stops(station.controller.mapping().device_control)
    with ExitStack() as stack:
        try:
            controller, params = open_controller(station, robot, stack, check=False, writes=False)
            feedback = controller.wait_for_heartbeat(station.motion.connect_timeout_s)
            check.details["state"] = feedback.state.name
            check.details["lengths_mm"] = [round(float(v), 4) for v in feedback.lengths_mm]
        except DeviceOpenError as err:
            check.problems.append(str(err))
            return check
        except Exception as err:  # the controller's own errors: whatever its protocol raises is the answer here
            check.problems.append(f"no heartbeat: {type(err).__name__}: {err}")
        try:
            described = params.describe()
        except Exception as err:
            check.problems.append(f"parameter interface {params.endpoint}: {type(err).__name__}: {err}")
            return check
    check.identity = described.pop("identity", None)
    check.details["parameters"] = described
    check.problems += [f"{key.removesuffix('_error')}: {value}" for key, value in described.items()
                       if key.endswith("_error") and value]
    geometry = described.get("geometry") or {}
    if isinstance(geometry, dict) and geometry.get("checksum_match") is False:
        check.problems.append(f"the geometry's checksum register {geometry.get('checksum_register')} is not the "
                              f"CRC-32 of the registers read ({geometry.get('crc32')})")
    if described.get("checksum") is not None and described.get("checksum") != described.get("checksum_expected"):
        check.problems.append(f"the device's checksum {described['checksum']} is not that of the geometry read "
                              f"({described['checksum_expected']})")
    return check


def check_station(station: Any, robot: Robot, *, home: Callable[[], bool]) -> StationCheck:
    """Check every device the station file names (see the module docstring)."""
    devices: list[DeviceCheck] = []
    if station.has_controller():
        devices.append(check_controller(station, robot))
    if station.measuring_tracker() is not None:
        devices.append(check_tracker(station, robot))
    elif station.cmm is not None:
        devices.append(check_cmm(station, robot, home))
    for d in devices:
        log.info("check.device", kind=d.kind, address=d.address, ok=d.ok, problems=d.problems)
    return StationCheck(devices)

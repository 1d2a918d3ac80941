"""All simulated devices in one process: the servo controller (SLCAN + Modbus TCP; or, with ``[controller] protocol =
"canopen"`` or ``"canopen-cia402"``, CANopen on SLCAN) and the measuring instrument, the CMM (pty + TCP) or, with
``instrument = "tracker"``, the laser tracker (emScon on TCP).

``start_sim(config)`` composes the rig, the persistent controller, its servers and the instrument's server in-process
(a context manager). The instrument reads the platform pose through the controller (``SimulatedController.true_pose``,
under its lock), so it never sees a half-updated rig. Everything binds to 127.0.0.1.
"""

from __future__ import annotations

import os
import time
from types import TracebackType
from typing import Any, cast

import numpy as np
import structlog

from hilcal.robot import Robot, load_robot
from sim_devices.canopen.model import CanopenController
from sim_devices.canopen.servers import CanopenServers, serve_canopen
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.controller.servers import ControllerServers, serve_controller
from sim_devices.controller.state_machine import SimulatedController
from sim_devices.rig.rig import SimulatedRig
from sim_devices.rotation import matrix_from_rotvec, matrix_from_rpy_deg
from sim_devices.sim_config import SimConfig
from sim_devices.sim_state import DEFAULT_LOCK_TIMEOUT_S, PersistentController, StateStore, restore_rig
from sim_devices.tracker.config import Station
from sim_devices.tracker.server import TrackerServerHandle, start_tracker_server
from sim_devices.tracker.targets import default_targets, layout_reflectors

log = structlog.get_logger(__name__)


HOST = "127.0.0.1"


class LockedRigView:
    """The rig as the CMM sees it: the pose is read through the controller, under its lock."""

    def __init__(self, rig: SimulatedRig, controller: SimulatedController) -> None:
        self._rig = rig
        self._controller = controller

    def true_pose(self) -> np.ndarray:
        return self._controller.true_pose()

    def to_cmm(self, points_base_mm: np.ndarray) -> np.ndarray:
        return self._rig.to_cmm(points_base_mm)


def published_alignment(rig: SimulatedRig, error_mm: float, error_deg: float, seed: int) -> np.ndarray:
    """T_cmm<-base (4x4) of the rig's CMM placement, spoiled by error_mm and error_deg (seeded, in the base frame)."""
    origin = rig.to_cmm(np.zeros(3))
    T = np.eye(4)
    T[:3, :3] = (rig.to_cmm(np.eye(3)) - origin).T
    T[:3, 3] = origin
    return _spoiled(T, error_mm, error_deg, [seed, 0xA11])


def published_tracker_alignment(station: Station, error_mm: float, error_deg: float, seed: int) -> np.ndarray:
    """T_tracker<-base (4x4) of the tracker's station (p_base = R p_tracker + t), spoiled like the CMM's."""
    R = matrix_from_rpy_deg(station.as_array()[3:])
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ station.as_array()[:3]
    return _spoiled(T, error_mm, error_deg, [seed, 0x7A11])


def _spoiled(T: np.ndarray, error_mm: float, error_deg: float, seed: list[int]) -> np.ndarray:
    """T composed with a seeded error of error_mm and error_deg in the base frame."""
    rng = np.random.default_rng(seed)
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    spoil = np.eye(4)
    spoil[:3, :3] = matrix_from_rotvec(np.radians(error_deg) * axis / np.linalg.norm(axis))
    spoil[:3, 3] = error_mm * shift / np.linalg.norm(shift)
    return T @ spoil


def tracker_targets(config: SimConfig, robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """(platform nests (M, 3) in the platform frame, base monuments (K, 3) in the base frame), mm: the configuration's,
    else four of each around the robot file's spheres."""
    platform, base = default_targets(robot)
    t = config.tracker
    return (platform if t.platform_targets_mm is None else np.array(t.platform_targets_mm, dtype=float),
            base if t.base_monuments_mm is None else np.array(t.base_monuments_mm, dtype=float))


class SimHandle:
    """The running simulator: ``controller``, ``controller_servers``, ``rig``, and the instrument's server:
    ``cmm_server`` and its ``alignment``, or ``tracker_server`` and its ``tracker_alignment`` (the other is None)."""

    def __init__(
        self,
        config: SimConfig,
        robot: Robot,
        rig: SimulatedRig,
        controller: PersistentController,
        controller_servers: ControllerServers | CanopenServers,
        cmm_server: CmmServerHandle | None,
        store: StateStore | None,
        restored: bool = False,
        tracker_server: TrackerServerHandle | None = None,
    ) -> None:
        self.config = config
        self.robot = robot
        self.rig = rig
        self.controller = controller
        self.controller_servers = controller_servers
        self.cmm_server = cmm_server
        self.tracker_server = tracker_server
        self.store = store
        self.restored = restored
        """True when the controller and rig state came from an existing state file."""
        cmm, tracker = config.cmm, config.tracker
        self.tracker_targets = tracker_targets(config, robot)
        """(platform nests, base monuments) mm: where the simulated tracker's reflectors sit (the truth)."""
        self.alignment = published_alignment(rig, cmm.alignment_error_mm, cmm.alignment_error_deg, config.rig.seed)
        self.tracker_alignment = published_tracker_alignment(
            tracker.station, tracker.alignment_error_mm, tracker.alignment_error_deg, config.rig.seed)
        self._closed = False

    def channels(self) -> dict[str, Any]:
        """Where to connect the real drivers (JSON-serialisable)."""
        servers, cmm, tracker = self.controller_servers, self.cmm_server, self.tracker_server
        out: dict[str, Any] = {
            "can": {"interface": "slcan", "channel": servers.slcan_path, "sleep_after_open": 0},
            "controller": {"protocol": self.config.controller.protocol},
            "instrument": self.config.instrument,
            "robot": self.robot.name,
            "robot_path": None if self.config.robot is None else str(self.config.robot),
            "state_file": None if self.store is None else str(self.store.path),
            "pid": os.getpid(),
        }
        if isinstance(servers, CanopenServers):
            out["canopen"] = servers.channels()
        else:
            out["modbus"] = {"host": HOST, "port": servers.modbus_port, "device_id": self.config.controller.device_id}
        if cmm is not None:
            out["cmm"] = {"url": cmm.path or cmm.socket_url, "socket_url": cmm.socket_url,
                          "identity": self.config.cmm.identity(),
                          "stated_uncertainty_mm": self.config.cmm.stated_uncertainty()}
            out["cmm_alignment"] = self.alignment.tolist()
        if tracker is not None:
            t = self.config.tracker
            out["tracker"] = {"protocol": "emscon", "host": tracker.host, "port": tracker.port,
                              "address": tracker.address, "identity": t.identity(),
                              "mpe_constant_um": t.mpe_constant_um, "mpe_per_m_um": t.mpe_per_m_um,
                              "air": t.air.model_dump()}
            out["tracker_alignment"] = self.tracker_alignment.tolist()
            out["tracker_targets"] = {"platform_targets_mm": self.tracker_targets[0].tolist(),
                                      "base_monuments_mm": self.tracker_targets[1].tolist()}
        if isinstance(servers, ControllerServers) and servers.modbus_rtu_path is not None:
            out["modbus_rtu"] = {"serial_port": servers.modbus_rtu_path, "baudrate": 115200,
                                 "device_id": self.config.controller.device_id}
        return out

    def close(self) -> None:
        """Stop the CMM and the controller servers, save the final state, release the state file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.cmm_server is not None:
                self.cmm_server.close()
            if self.tracker_server is not None:
                self.tracker_server.close()
            self.controller_servers.close()
            self.controller.save_state(force=True)
        finally:
            if self.store is not None:
                self.store.close()
        log.info("sim_stopped")

    def __enter__(self) -> SimHandle:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def start_sim(config: SimConfig | None = None, *, lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> SimHandle:
    """Start the simulated controller and the instrument (CMM or tracker) in this process; ``close()`` (or ``with``)
    stops them.

    Raises RobotFileError / ValueError (bad robot or errors), SimStateError (state file), OSError (transports).
    """
    cfg = config or SimConfig()
    t0 = time.perf_counter()
    robot = load_robot(cfg.robot)
    rig = SimulatedRig(robot, cfg.rig.rig_config(robot))
    store = StateStore(cfg.state_file, robot.name, lock_timeout_s) if cfg.state_file is not None else None
    servers: ControllerServers | CanopenServers | None = None
    cmm: CmmServerHandle | None = None
    tracker: TrackerServerHandle | None = None
    try:
        saved = store.load() if store is not None else None
        if saved is not None:
            restore_rig(rig, saved.rig)
        banks = saved.banks if saved else None
        variant = cfg.controller.canopen_variant
        if variant is None:
            controller = PersistentController(robot, rig, cfg.controller, store, banks)
            controller.save_state(force=True)
            servers = serve_controller(controller)
        else:
            controller = CanopenController(robot, rig, cfg.controller, store, banks)
            controller.save_state(force=True)
            nvram = None if cfg.state_file is None else cfg.state_file.with_name(cfg.state_file.name + ".canopen.json")
            servers = serve_canopen(controller, variant, cfg.controller.canopen, nvram_path=nvram)
        view = LockedRigView(rig, controller)
        if cfg.instrument == "tracker":
            platform, base = tracker_targets(cfg, robot)
            tracker = start_tracker_server(layout_reflectors(platform, base, view),
                                           cfg.tracker.server_config(cfg.rig.seed), platform_reflectors=len(platform))
        else:
            cmm = start_cmm_server(robot, cast(SimulatedRig, view), cfg.cmm.server_config(cfg.rig.seed))
    except BaseException:
        if servers is not None:
            servers.close()
        if store is not None:
            store.close()
        raise
    handle = SimHandle(cfg, robot, rig, controller, servers, cmm, store, restored=saved is not None,
                       tracker_server=tracker)
    log.info("sim_started", robot=robot.name, restored=handle.restored, start_s=round(time.perf_counter() - t0, 3),
             can=servers.slcan_path, controller=cfg.controller.protocol, instrument=cfg.instrument,
             cmm=cmm.path if cmm else None, cmm_socket=cmm.socket_url if cmm else None,
             tracker=tracker.address if tracker else None)
    return handle

"""All simulated devices in one process: the servo controller (SLCAN + Modbus TCP) and the CMM (pty + TCP).

``start_sim(config)`` composes the rig, the persistent controller, its servers and the CMM server in-process
(a context manager). The CMM reads the platform pose through the controller (``SimulatedController.true_pose``,
under its lock), so it never sees a half-updated rig. Everything binds to 127.0.0.1.
"""

from __future__ import annotations

import os
import time
from types import TracebackType
from typing import Any, cast

import numpy as np
import structlog
from scipy.spatial.transform import Rotation

from hilcal.robot import Robot, load_robot
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.controller.servers import ControllerServers, serve_controller
from sim_devices.controller.state_machine import SimulatedController
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import SimConfig
from sim_devices.sim_state import DEFAULT_LOCK_TIMEOUT_S, PersistentController, StateStore, restore_rig

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
    rng = np.random.default_rng([seed, 0xA11])
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    spoil = np.eye(4)
    spoil[:3, :3] = Rotation.from_rotvec(np.radians(error_deg) * axis / np.linalg.norm(axis)).as_matrix()
    spoil[:3, 3] = error_mm * shift / np.linalg.norm(shift)
    return T @ spoil


class SimHandle:
    """The running simulator: ``controller``, ``controller_servers``, ``cmm_server``, ``rig``, ``alignment``."""

    def __init__(
        self,
        config: SimConfig,
        robot: Robot,
        rig: SimulatedRig,
        controller: PersistentController,
        controller_servers: ControllerServers,
        cmm_server: CmmServerHandle,
        store: StateStore | None,
        restored: bool = False,
    ) -> None:
        self.config = config
        self.robot = robot
        self.rig = rig
        self.controller = controller
        self.controller_servers = controller_servers
        self.cmm_server = cmm_server
        self.store = store
        self.restored = restored
        """True when the controller and rig state came from an existing state file."""
        cmm = config.cmm
        self.alignment = published_alignment(rig, cmm.alignment_error_mm, cmm.alignment_error_deg, config.rig.seed)
        self._closed = False

    def channels(self) -> dict[str, Any]:
        """Where to connect the real drivers (JSON-serialisable)."""
        servers, cmm = self.controller_servers, self.cmm_server
        out: dict[str, Any] = {
            "can": {"interface": "slcan", "channel": servers.slcan_path, "sleep_after_open": 0},
            "modbus": {"host": HOST, "port": servers.modbus_port, "device_id": self.config.controller.device_id},
            "cmm": {"url": cmm.path or cmm.socket_url, "socket_url": cmm.socket_url,
                    "identity": self.config.cmm.identity(),
                    "stated_uncertainty_mm": self.config.cmm.stated_uncertainty()},
            "cmm_alignment": self.alignment.tolist(),
            "robot": self.robot.name,
            "robot_path": None if self.config.robot is None else str(self.config.robot),
            "state_file": None if self.store is None else str(self.store.path),
            "pid": os.getpid(),
        }
        if servers.modbus_rtu_path is not None:
            out["modbus_rtu"] = {"serial_port": servers.modbus_rtu_path, "baudrate": 115200,
                                 "device_id": self.config.controller.device_id}
        return out

    def close(self) -> None:
        """Stop the CMM and the controller servers, save the final state, release the state file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.cmm_server.close()
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
    """Start the simulated controller and CMM in this process; ``close()`` (or ``with``) stops them.

    Raises RobotFileError / ValueError (bad robot or errors), SimStateError (state file), OSError (transports).
    """
    cfg = config or SimConfig()
    t0 = time.perf_counter()
    robot = load_robot(cfg.robot)
    rig = SimulatedRig(robot, cfg.rig.rig_config(robot))
    store = StateStore(cfg.state_file, robot.name, lock_timeout_s) if cfg.state_file is not None else None
    servers: ControllerServers | None = None
    try:
        saved = store.load() if store is not None else None
        if saved is not None:
            restore_rig(rig, saved.rig)
        controller = PersistentController(robot, rig, cfg.controller, store, saved.banks if saved else None)
        controller.save_state(force=True)
        servers = serve_controller(controller)
        cmm = start_cmm_server(robot, cast(SimulatedRig, LockedRigView(rig, controller)),
                               cfg.cmm.server_config(cfg.rig.seed))
    except BaseException:
        if servers is not None:
            servers.close()
        if store is not None:
            store.close()
        raise
    handle = SimHandle(cfg, robot, rig, controller, servers, cmm, store, restored=saved is not None)
    log.info("sim_started", robot=robot.name, restored=handle.restored, start_s=round(time.perf_counter() - t0, 3),
             can=servers.slcan_path, modbus_port=servers.modbus_port, cmm=cmm.path, cmm_socket=cmm.socket_url)
    return handle

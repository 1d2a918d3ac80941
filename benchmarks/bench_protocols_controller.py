"""Latency benchmark of the controller links through the real drivers and the simulated controller.

Why: every calibration pose needs a leg move and the end of a calibration an upload, so the protocol
overhead (with the servo's own motion time scaled to ~zero) should be known and tracked. Measures the CAN
round trip setpoint -> IN_POSITION feedback over SLCAN on a pty (and python-can's virtual bus for
comparison), the command -> acknowledgement round trip, and a 42-parameter Modbus TCP upload with read-back
and commit. Prints a small Markdown table; makes no assertions on speed.
Run ``python benchmarks/bench_protocols_controller.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np
import structlog
from _docs import write_doc

from drivers.controller.hilcal_can import ControllerCan
from drivers.controller.modbus import ControllerParams
from hilcal.robot import Robot, default_robot
from sim_devices.controller.can_bus_server import CanBusServer
from sim_devices.controller.can_peer import ControllerCanPeer
from sim_devices.controller.servers import start_controller_servers
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

TIME_SCALE = 1e6


def _stats(samples_s: list[float]) -> dict[str, float]:
    ordered = sorted(samples_s)
    return {
        "median_ms": 1e3 * statistics.median(ordered),
        "p95_ms": 1e3 * ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))],
        "max_ms": 1e3 * ordered[-1],
    }


def _timed(fn: Callable[[], object], repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def _can_round_trips(driver: ControllerCan, repeats: int) -> tuple[list[float], list[float]]:
    """(setpoint -> IN_POSITION times, ENABLE/DISABLE acknowledgement times)."""
    driver.wait_for_heartbeat(2.0)
    acks = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        driver.enable()
        acks.append(time.perf_counter() - t0)
        driver.disable()
    driver.enable()
    start = driver.feedback().lengths_mm
    moves = []
    for k in range(repeats):
        target = start + (0.1 if k % 2 == 0 else -0.1)
        t0 = time.perf_counter()
        driver.move_legs(target, timeout_s=2.0)
        moves.append(time.perf_counter() - t0)
    driver.disable()
    return moves, acks


def _virtual_bus(robot: Robot, rig: SimulatedRig, repeats: int) -> list[float]:
    controller = SimulatedController(robot, rig, ControllerSimConfig(time_scale=TIME_SCALE))
    channel = f"bench-{os.getpid()}"
    with CanBusServer(ControllerCanPeer(controller), {"interface": "virtual", "channel": channel}).start():
        with ControllerCan({"interface": "virtual", "channel": channel}, robot, heartbeat_timeout_s=0.5) as driver:
            moves, _ = _can_round_trips(driver, repeats)
    return moves


def run(repeats: int = 20, seed: int = 0) -> dict:
    """Latency statistics (ms) of the CAN and Modbus round trips; see the module docstring."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    robot = default_robot()
    rig = SimulatedRig(robot, RigConfig(seed=seed, errors=load_errors("table2")))
    config = ControllerSimConfig(time_scale=TIME_SCALE)
    with start_controller_servers(robot, rig, config) as servers:
        bus_config = {"interface": "slcan", "channel": servers.slcan_path, "sleep_after_open": 0}
        with ControllerCan(bus_config, robot, heartbeat_timeout_s=0.5) as driver:
            slcan_moves, slcan_acks = _can_round_trips(driver, repeats)
        nominal = np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0])
        with ControllerParams("127.0.0.1", servers.modbus_port, timeout_s=2.0) as params:
            sets = [nominal + 0.01 * (k % 2) for k in range(repeats)]
            uploads = []
            for values in sets:
                t0 = time.perf_counter()
                params.upload(values)
                uploads.append(time.perf_counter() - t0)
            writes = len(params.records[-1].writes)
            reads = _timed(params.read_live, repeats)
    virtual_moves = _virtual_bus(robot, SimulatedRig(robot, RigConfig(seed=seed, errors=load_errors("table2"))),
                                 repeats)
    return {
        "repeats": repeats,
        "heartbeat_period_ms": 1e3 * config.heartbeat_period_s,
        "can_slcan_pty_move": _stats(slcan_moves),
        "can_slcan_pty_command_ack": _stats(slcan_acks),
        "can_virtual_move": _stats(virtual_moves),
        "modbus_tcp_upload": _stats(uploads),
        "modbus_tcp_upload_writes": writes,
        "modbus_tcp_read_live": _stats(reads),
    }


def markdown(result: dict) -> str:
    """The result as a small Markdown table."""
    rows = [
        ("CAN over SLCAN/pty: setpoint -> IN_POSITION feedback", result["can_slcan_pty_move"]),
        ("CAN over SLCAN/pty: command -> acknowledgement", result["can_slcan_pty_command_ack"]),
        ("CAN over virtual bus: setpoint -> IN_POSITION feedback", result["can_virtual_move"]),
        (f"Modbus TCP: 42-parameter upload ({result['modbus_tcp_upload_writes']} writes, read-back, commit)",
         result["modbus_tcp_upload"]),
        ("Modbus TCP: read live set (84 registers)", result["modbus_tcp_read_live"]),
    ]
    lines = [
        f"Controller links, instant servo motion (time_scale {TIME_SCALE:g}), heartbeat "
        f"{result['heartbeat_period_ms']:.0f} ms, {result['repeats']} repeats:",
        "",
        "| round trip | median | p95 | max |",
        "| --- | ---: | ---: | ---: |",
    ]
    for label, s in rows:
        lines.append(f"| {label} | {s['median_ms']:.1f} ms | {s['p95_ms']:.1f} ms | {s['max_ms']:.1f} ms |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--quick", action="store_true", help="5 repeats")
    args = parser.parse_args(argv)
    repeats = 5 if args.quick else args.repeats
    table = markdown(run(repeats))
    print(table)
    write_doc("benchmarks_controller.md", "Controller protocol latencies", "benchmarks/bench_protocols_controller.py",
              f"{repeats} repeats; wall-clock, no assertions on speed.", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The simulator as a process: ``hilcal sim`` / ``python -m sim_devices.launcher``, and spawning it for ``hilcal run``.

``run_sim_process`` starts the simulator in this process (``simulator.start_sim``), prints the channels and serves
until SIGINT/SIGTERM; ``spawn_sim_subprocess`` starts ``python -m sim_devices.launcher --json`` as a separate
process and returns its channels (``hilcal run --sim``); ``stop_sim_subprocess`` stops it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any, cast

import numpy as np
import structlog

from hilcal.robot import RobotFileError
from sim_devices.sim_config import (
    CONTROLLER_PROTOCOLS,
    SimConfig,
    SimConfigError,
    load_sim_config,
    simulation_summary,
)
from sim_devices.sim_state import SimStateError
from sim_devices.simulator import SimHandle, start_sim

log = structlog.get_logger(__name__)


DEFAULT_SPAWN_TIMEOUT_S = 30.0
STOP_POLL_S = 0.1
PROJECT_ROOT = Path(__file__).resolve().parents[1]


class SimStartError(RuntimeError):
    """The simulator subprocess did not start (it died or printed no channels in time)."""


def _describe(channels: dict[str, Any], handle: SimHandle) -> str:
    rig = handle.config.rig
    simulation = channels.get("simulation") or simulation_summary(handle.config, handle.robot)
    lines = [
        f"hilcal simulator: robot {channels['robot']}, errors {rig.errors}, seed {rig.seed}, "
        f"controller protocol {channels['controller']['protocol']}",
        f"  CAN (SLCAN)   {channels['can']['channel']}   "
        f"(can.Bus(interface='slcan', channel='{channels['can']['channel']}', sleep_after_open=0))",
    ]
    if "modbus" in channels:
        lines.append(f"  Modbus TCP    {channels['modbus']['host']}:{channels['modbus']['port']} "
                     f"(device id {channels['modbus']['device_id']})")
    if "canopen" in channels:
        co = channels["canopen"]
        what = "HX-6 hexapod controller" if co["variant"] == "hexapod" else "LD-1 CiA 402 leg drives (legs 1-6)"
        lines += [f"  CANopen       {what}, node id(s) {', '.join(str(n) for n in co['node_ids'])} ({co['profile']})",
                  f"  EDS           {co['eds']}"]
    if "cmm" in channels:
        cmm = channels["cmm"]
        lines += [f"  CMM           {cmm['url']}" + (f"   or {cmm['socket_url']}" if cmm["socket_url"] else "")
                  + "   (I++ DME 1.4.3)",
                  "  CMM alignment T_cmm<-base (approximate, as a station's CMM set-up gives it):",
                  _rows(channels["cmm_alignment"])]
    if "tracker" in channels:
        tracker = channels["tracker"]
        mpe = f"±({tracker['mpe_constant_um']:g} µm + {tracker['mpe_per_m_um']:g} µm/m)"
        targets = channels.get("tracker_targets") or {}
        lines += [f"  tracker       {tracker['address']}   (Leica emScon over TCP; MPE {mpe})",
                  f"  targets       {len(targets.get('platform_targets_mm', []))} platform nests, "
                  f"{len(targets.get('base_monuments_mm', []))} base monuments (layouts: --json's tracker_targets)",
                  "  tracker alignment T_tracker<-base (approximate, as a station's tracker set-up gives it):",
                  _rows(channels["tracker_alignment"])]
    if channels["state_file"]:
        restored = "restored" if handle.restored else "new"
        lines.append(f"  state file    {channels['state_file']} ({restored})")
    lines += [*simulation["lines"], "Ctrl-C (SIGINT) or SIGTERM stops the simulator."]
    return "\n".join(lines)


def _rows(matrix: list[list[float]]) -> str:
    return "\n".join("    [" + ", ".join(f"{v:12.4f}" for v in row) + "]" for row in np.asarray(matrix))


def run_sim_process(config: SimConfig, as_json: bool, *, stdin_watch: bool = False,
                    on_channels: Callable[[dict[str, Any]], None] | None = None) -> int:
    """``hilcal sim``: start everything, print the channels (text or one JSON line), serve until SIGINT/SIGTERM.

    With ``stdin_watch`` it also stops when stdin reaches end of file (the spawning process has gone);
    ``on_channels`` is called with the channels once they are printed (``hilcal sim --station-out`` writes the
    station file). Returns the exit code: 0 after a clean stop, 2 if the simulator could not start.
    """
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("sim_signal", signal=signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            handle = start_sim(config)
        except (RobotFileError, SimStateError, ValueError, OSError) as err:
            print(f"error: the simulator did not start: {err}", file=sys.stderr, flush=True)
            return 2
        with handle:
            channels = {**handle.channels(), "simulation": simulation_summary(handle.config, handle.robot)}
            print(json.dumps(channels) if as_json else _describe(channels, handle), flush=True)
            if on_channels is not None:
                on_channels(channels)
            watch_fd = sys.stdin.fileno() if stdin_watch else None
            while not stop.is_set():
                if watch_fd is None:
                    stop.wait(STOP_POLL_S)
                    continue
                readable, _, _ = select.select([watch_fd], [], [], STOP_POLL_S)
                if readable and not os.read(watch_fd, 4096):
                    log.info("sim_parent_gone")
                    stop.set()
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _configure_logging(verbose: bool) -> None:
    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.INFO if verbose else logging.WARNING),
        logger_factory=lambda *_: structlog.PrintLogger(sys.stderr),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sim_devices.launcher [--config FILE] [--json] [--state-file PATH] [--seed N]
    [--instrument cmm|tracker] [--controller hilcal|canopen|canopen-cia402] [--robot FILE]``."""
    parser = argparse.ArgumentParser(prog="python -m sim_devices.launcher", description=__doc__.split("\n")[0])
    parser.add_argument("--config", type=Path, help="simulator TOML file (default: built-in settings)")
    parser.add_argument("--json", action="store_true", help="print the channels as one JSON line")
    parser.add_argument("--state-file", type=Path, help="keep the controller and rig state in this file")
    parser.add_argument("--seed", type=int, help="rig seed (overrides the file)")
    parser.add_argument("--instrument", choices=("cmm", "tracker"), help="the measuring instrument (overrides the "
                        "file; default: cmm)")
    parser.add_argument("--controller", choices=CONTROLLER_PROTOCOLS, help="the controller's protocol (overrides "
                        "the file; default: hilcal)")
    parser.add_argument("--robot", type=Path, help="simulate this robot file (overrides the file's robot)")
    parser.add_argument("--stdin-watch", action="store_true", help="stop when stdin closes (spawning process gone)")
    parser.add_argument("--verbose", "-v", action="store_true", help="structured logs on stderr")
    args = parser.parse_args(argv)
    _configure_logging(args.verbose)
    try:
        config = load_sim_config(args.config, state_file=args.state_file, seed=args.seed,
                                 instrument=args.instrument, controller=args.controller, robot=args.robot)
    except SimConfigError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 2
    return run_sim_process(config, args.json, stdin_watch=args.stdin_watch)


def _read_first_line(proc: subprocess.Popen[bytes], deadline: float) -> bytes | None:
    """The first stdout line of proc (without the newline), None if it exits or the deadline passes first."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    buf = b""
    while b"\n" not in buf:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        readable, _, _ = select.select([fd], [], [], min(remaining, STOP_POLL_S))
        if readable:
            chunk = os.read(fd, 65536)
            if not chunk:
                return None
            buf += chunk
    return buf.split(b"\n", 1)[0]


def _tail(fh: IO[bytes], limit: int = 4000) -> str:
    fh.flush()
    fh.seek(0)
    text = fh.read().decode(errors="replace").strip()
    return text[-limit:] or "(no output on stderr)"


def spawn_sim_subprocess(
    config_path: str | Path | None,
    extra_args: Sequence[str] = (),
    *,
    timeout_s: float = DEFAULT_SPAWN_TIMEOUT_S,
    log_path: str | Path | None = None,
) -> tuple[subprocess.Popen[bytes], dict[str, Any]]:
    """Start ``python -m sim_devices.launcher --json --stdin-watch`` and return (process, channels).

    The simulator runs in its own session (a terminal Ctrl-C reaches only the caller, which stops it with
    ``stop_sim_subprocess``) and exits by itself if the caller dies (its stdin closes). Its stderr goes to
    ``log_path`` (with ``--verbose``) or a temporary file. SimStartError, with the simulator's stderr, if it
    exits or prints no channels within ``timeout_s``.
    """
    cmd = [sys.executable, "-m", "sim_devices.launcher", "--json", "--stdin-watch"]
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    if log_path is not None:
        cmd.append("--verbose")
    cmd += list(extra_args)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(PROJECT_ROOT), env.get("PYTHONPATH")) if p)
    err_file: IO[bytes] = open(log_path, "w+b") if log_path is not None else tempfile.TemporaryFile()
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err_file, env=env,
                                start_new_session=True)
        line = _read_first_line(proc, time.monotonic() + timeout_s)
        channels: dict[str, Any] | None = None
        if line is not None:
            with contextlib.suppress(ValueError):
                parsed = json.loads(line)
                channels = parsed if isinstance(parsed, dict) and "can" in parsed else None
        if channels is None:
            code = proc.poll()
            stop_sim_subprocess(proc)
            what = f"exited with code {code}" if code is not None else f"printed no channels within {timeout_s} s"
            raise SimStartError(f"the simulator ({' '.join(cmd[2:])}) {what}:\n{_tail(err_file)}")
    finally:
        err_file.close()
    log.info("sim_subprocess_started", pid=proc.pid, can=channels["can"]["channel"])
    return proc, channels


def stop_sim_subprocess(proc: subprocess.Popen[Any], timeout_s: float = 5.0) -> int:
    """SIGTERM, wait up to timeout_s (then SIGKILL), close the pipes; the exit code (negative: killed)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("sim_subprocess_killed", pid=proc.pid)
            proc.kill()
            proc.wait()
    for pipe in (proc.stdin, proc.stdout):
        if pipe is not None:
            with contextlib.suppress(OSError):
                pipe.close()
    return cast(int, proc.returncode)


if __name__ == "__main__":
    sys.exit(main())

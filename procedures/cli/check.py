"""`hilcal check --station FILE [--json] [--home]`: the pre-flight check of a station's devices (procedures.check).

Exit codes: 0 every device is well, 3 a device failed its check, 2 a bad station file. The platform does not move and
nothing is written to a controller; the CMM homes only when the operator agrees or with ``--home``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from procedures.cli.common import err, fail, out

DEVICE_FAILED = 3


def check(
    station: Annotated[Path, typer.Option("--station", help="the station file: every device it names is checked "
                                          "(a file with only \\[cmm] checks only the CMM)")],
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object: ok and each device's findings")]
    = False,
    home: Annotated[bool, typer.Option("--home", help="home the CMM if it is not homed, without asking")] = False,
) -> None:
    """Check a station before a shift: connect each device, read who it is and its state, and measure the base
    (the CMM's base spheres, or the laser tracker's monuments) without moving the platform."""
    from hilcal.robot import RobotFileError, load_robot
    from procedures.check import check_station
    from procedures.station import StationConfigError, load_station

    try:
        config = load_station(station, partial=True)
        robot = load_robot(config.robot)
    except (StationConfigError, RobotFileError) as e:
        fail(str(e))
    if not (config.has_controller() or config.cmm is not None or config.measuring_tracker() is not None):
        fail(f"station file {station}: it names no device to check ([can] with [modbus] or a CANopen [controller], "
             "[cmm], or [instrument] kind = \"tracker\" with [tracker])")

    def agree_to_home() -> bool:
        if home:
            return True
        if as_json or not sys.stdin.isatty():
            return False
        return typer.confirm("The CMM is not homed. Home it now (its axes move to their reference marks)?",
                             default=False)

    result = check_station(config, robot, home=agree_to_home)
    if as_json:
        print(json.dumps(result.as_json(), indent=2))
    else:
        for device in result.devices:
            _print_device(device.as_json())
        out.print("station ready" if result.ok else "station NOT ready: see the problems above")
    if not result.ok:
        raise typer.Exit(DEVICE_FAILED)


def _print_device(d: dict) -> None:
    """One device's findings as a technician reads them."""
    out.print(f"{d['kind']} at {d['address']}: {'ok' if d['ok'] else 'FAILED'}")
    identity = d.get("identity")
    if isinstance(identity, dict):
        out.print("  identity: " + ", ".join(f"{k} {v}" for k, v in identity.items() if v is not None))
    elif identity:
        out.print(f"  identity: {identity}")
    if d["kind"] == "cmm":
        if d.get("tools") is not None:
            out.print(f"  tools: {', '.join(d['tools']) or 'none'}; active: {d.get('active_tool')}; "
                      f"homed: {'yes' if d.get('homed') else 'no'}")
        if d.get("stylus_radius_mm") is not None:
            out.print(f"  stylus ball radius: {d['stylus_radius_mm']:.4f} mm (from the CMM)")
        for s in d.get("spheres", []):
            x, y, z = s["centre_mm"]
            out.print(f"  {s['name']}: centre [{x:.4f}, {y:.4f}, {z:.4f}] mm in the CMM's frame, radius "
                      f"{s['radius_mm']:.4f} mm, fit RMS {s['rms_mm'] * 1000:.1f} µm")
        if d.get("registration_rms_mm") is not None:
            out.print(f"  against the robot file's base layout: RMS {d['registration_rms_mm'] * 1000:.1f} µm")
    elif d["kind"] == "tracker":
        for m in d.get("monuments", []):
            x, y, z = m["point_mm"]
            out.print(f"  {m['name']}: [{x:.4f}, {y:.4f}, {z:.4f}] mm, {m['offset_mm']:.3f} mm from the alignment's "
                      "prediction")
    else:
        _print_controller(d)
    for problem in d["problems"]:
        err.print(f"  problem: {problem}", highlight=False, soft_wrap=True)


def _print_controller(d: dict) -> None:
    if d.get("state"):
        out.print(f"  state: {d['state']}; leg lengths {', '.join(f'{v:.3f}' for v in d.get('lengths_mm', []))} mm")
    stops = d.get("stops")
    if stops:
        out.print(f"  stop: {stops['stop']}; e-stop: {stops['estop']}")
    params = d.get("parameters") or {}
    if params.get("state"):
        out.print(f"  parameter interface {params.get('endpoint')}: {params['state']}")
    geometry = params.get("geometry") or {}
    held = geometry.get("set") if isinstance(geometry, dict) and "set" in geometry else geometry
    if isinstance(held, dict) and held.get("l0_mm"):
        out.print(f"  leg offsets l0: {', '.join(f'{v:.4f}' for v in held['l0_mm'])} mm")
    checksum = params.get("checksum") or (geometry.get("crc32") if isinstance(geometry, dict) else None)
    if checksum:
        out.print(f"  geometry checksum: {checksum}")

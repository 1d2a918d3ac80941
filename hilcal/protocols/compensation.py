"""The controller's compensation block as data: its register layout, its sanity bounds and its word encoding.

A controller with the COMPENSATION capability (register-map version 1.1) corrects every leg length it reports and
every setpoint it receives, the way CNC controllers apply pitch-error and backlash tables. Per leg i, with s the
leg's raw stroke (the transducer's reading less the leg offset l0 of the geometry set), F its axial compression in
kN as the controller reads it, T its leg temperature in °C and d = +1 after the leg last extended, -1 after it
last retracted (moves under 1 µm keep the direction)::

    length = l0 + s + scale_ppm 1e-6 s + table(s) + d backlash_mm / 2
             - compliance_mm_per_kn F - compliance_mm_per_kn_m F s / 1000
             + thermal_ppm_per_k 1e-6 (l0 + s) (T - reference_temperature_c)

table(s) interpolates linearly between ``table_points`` equally spaced points from ``table_start_mm`` to
``table_end_mm`` of s and holds its end values outside. A setpoint is a length: the controller servos the raw
stroke until the corrected length equals it. Layout (16-bit registers; float32 in ABCD order as the geometry):
FORMAT (u16), TABLE_POINTS (u16), REFERENCE_TEMPERATURE_C (f32), then per leg 1..6 the seven scalars of
``LEG_FIELDS`` and ``MAX_TABLE_POINTS`` table values (unused ones 0). Where the block's four banks (live, staging,
backup, saved) are is the register map's ``[compensation]`` section (``hilcal.protocols.modbus_map``). See
docs/protocols.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from hilcal.protocols.registers import N_LEGS, crc32_of_words, floats_from_words, words_from_floats

FORMAT = 1
"""Layout version of the block (register FORMAT)."""
MAX_TABLE_POINTS = 256
MIN_TABLE_POINTS = 2
LEG_FIELDS = ("scale_ppm", "backlash_mm", "compliance_mm_per_kn", "compliance_mm_per_kn_m", "thermal_ppm_per_k",
              "table_start_mm", "table_end_mm")
LEG_FLOATS = len(LEG_FIELDS) + MAX_TABLE_POINTS
HEADER_REGISTERS = 4
BLOCK_REGISTERS = HEADER_REGISTERS + N_LEGS * LEG_FLOATS * 2
DEFAULT_REFERENCE_TEMPERATURE_C = 20.0
"""ISO 1: lengths are stated at 20 °C."""

LIMITS: dict[str, float] = {
    "scale_ppm": 100_000.0, "backlash_mm": 10.0, "compliance_mm_per_kn": 10.0, "compliance_mm_per_kn_m": 10.0,
    "thermal_ppm_per_k": 100.0, "table_start_mm": 20_000.0, "table_end_mm": 20_000.0, "table_mm": 10.0,
}
"""Sanity bounds the controller checks at COMMIT (|value| <= bound): a reading scale within 10 %, play and table
values within 10 mm, compliances within 10 mm/kN, a thermal coefficient within 100 ppm/K. The calibration tool keeps
to far tighter, physical bounds of its own."""
TEMPERATURE_RANGE_C = (-50.0, 100.0)
NEEDS_FORCE = ("compliance_mm_per_kn", "compliance_mm_per_kn_m")
NEEDS_TEMPERATURE = ("thermal_ppm_per_k",)

Block = dict[str, Any]
"""{"table_points": int, "reference_temperature_c": float, each of LEG_FIELDS: 6 floats, "table_mm": 6 lists of
table_points floats}."""


def zero_block() -> Block:
    """The block that corrects nothing (a controller's factory state)."""
    out: Block = {"table_points": 0, "reference_temperature_c": DEFAULT_REFERENCE_TEMPERATURE_C}
    out.update({name: [0.0] * N_LEGS for name in LEG_FIELDS})
    out["table_mm"] = [[] for _ in range(N_LEGS)]
    return out


def block_words(block: Mapping[str, Any]) -> list[int]:
    """The block's BLOCK_REGISTERS registers (floats rounded to float32); ValueError for a malformed block."""
    points = int(block["table_points"])
    if not (points == 0 or MIN_TABLE_POINTS <= points <= MAX_TABLE_POINTS):
        raise ValueError(f"table_points must be 0 or {MIN_TABLE_POINTS}..{MAX_TABLE_POINTS}, got {points}")
    words = [FORMAT, points, *words_from_floats([float(block["reference_temperature_c"])])]
    for leg in range(N_LEGS):
        table = [float(v) for v in block["table_mm"][leg]]
        if len(table) != points:
            raise ValueError(f"leg {leg + 1}: table has {len(table)} values, table_points is {points}")
        values = [float(block[name][leg]) for name in LEG_FIELDS] + table + [0.0] * (MAX_TABLE_POINTS - points)
        words += words_from_floats(values)
    return words


def block_crc32(block: Mapping[str, Any]) -> int:
    """CRC-32 of the block's registers (STAGED_COMP_CRC32, LIVE_COMP_CRC32 ...)."""
    return crc32_of_words(block_words(block))


def block_from_words(words: Sequence[int]) -> Block:
    """Decode BLOCK_REGISTERS registers; ValueError when the layout is not this one (format, point count, unused
    table values not zero)."""
    if len(words) != BLOCK_REGISTERS:
        raise ValueError(f"a compensation block has {BLOCK_REGISTERS} registers, got {len(words)}")
    if words[0] != FORMAT:
        raise ValueError(f"compensation block format {words[0]} (this host knows format {FORMAT})")
    points = int(words[1])
    if not (points == 0 or MIN_TABLE_POINTS <= points <= MAX_TABLE_POINTS):
        raise ValueError(f"TABLE_POINTS {points} is neither 0 nor {MIN_TABLE_POINTS}..{MAX_TABLE_POINTS}")
    block: Block = {"table_points": points, "reference_temperature_c": floats_from_words(words[2:4])[0]}
    values = floats_from_words(words[HEADER_REGISTERS:])
    n = len(LEG_FIELDS)
    for k, name in enumerate(LEG_FIELDS):
        block[name] = [values[leg * LEG_FLOATS + k] for leg in range(N_LEGS)]
    block["table_mm"] = []
    for leg in range(N_LEGS):
        table = values[leg * LEG_FLOATS + n:(leg + 1) * LEG_FLOATS]
        if any(v != 0.0 for v in table[points:]):
            raise ValueError(f"leg {leg + 1}: table values beyond TABLE_POINTS = {points} are not zero")
        block["table_mm"].append(table[:points])
    return block


def block_violations(block: Mapping[str, Any], *, force_reading: bool = True, temperature_reading: bool = True
                     ) -> list[str]:
    """Why the controller would refuse this block at COMMIT (empty: it is fine). A block that needs a force or a
    temperature reading the controller does not have is refused too (terms it cannot apply)."""
    problems = []
    t_ref = float(block["reference_temperature_c"])
    if not (math.isfinite(t_ref) and TEMPERATURE_RANGE_C[0] <= t_ref <= TEMPERATURE_RANGE_C[1]):
        problems.append(f"reference_temperature_c = {t_ref} is outside {TEMPERATURE_RANGE_C} °C")
    for name in (*LEG_FIELDS, "table_mm"):
        values = [v for row in block[name] for v in row] if name == "table_mm" else list(block[name])
        for v in values:
            if not (math.isfinite(float(v)) and abs(float(v)) <= LIMITS[name]):
                problems.append(f"{name} value {v} is not finite or beyond ±{LIMITS[name]:g}")
                break
    if int(block["table_points"]):
        for leg in range(N_LEGS):
            if not float(block["table_end_mm"][leg]) > float(block["table_start_mm"][leg]):
                problems.append(f"leg {leg + 1}: table_end_mm must be above table_start_mm")
    needs = [(NEEDS_FORCE, force_reading, "an axial-force reading"),
             (NEEDS_TEMPERATURE, temperature_reading, "a leg-temperature reading")]
    for names, available, what in needs:
        if not available and any(float(v) != 0.0 for name in names for v in block[name]):
            problems.append(f"{', '.join(names)} need {what}, which this controller does not have")
    return problems

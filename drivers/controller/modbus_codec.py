"""The driver's encoding of a register map's values (``hilcal.protocols.modbus_map``): integers and floats in the
map's data types and word order, mm through the map's scale and offset, the geometry laid out per bank, and register
runs merged and cut into requests. Written from the word orders' definitions in docs/modbus_maps.md.

Modbus itself only says that a register is big-endian (MODBUS Application Protocol v1.1b3, 4.2); how a 32- or 64-bit
value spreads over registers is the device's choice. Named after the bytes of a 32-bit value A B C D (A the most
significant): ABCD high word first, CDAB low word first, BADC and DCBA the same with the bytes of each register
swapped. A 64-bit value follows the same two switches: CDAB and DCBA reverse its four registers. 16-bit values are
plain registers.
"""

from __future__ import annotations

import hashlib
import math
import struct
from collections.abc import Sequence

import numpy as np

from hilcal.protocols.modbus_map import INTEGER_RANGE, TYPE_REGISTERS, PartLayout, RegisterField, RegisterMap
from hilcal.protocols.registers import PARAMETER_COUNT, words_from_floats, words_to_bytes

STRUCT = {"u16": "H", "i16": "h", "u32": "I", "i32": "i", "f32": "f", "f64": "d"}
Block = tuple[int, list[int]]
"""(first address, registers)."""


def _arrange(words: list[int], word_order: str) -> list[int]:
    """One value's registers, big-endian (ABCD) <-> the wire; its own inverse."""
    if len(words) == 1:
        return words
    if word_order in ("CDAB", "DCBA"):
        words = words[::-1]
    if word_order in ("BADC", "DCBA"):
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    return words


def encode(values: Sequence[int | float], type_: str, word_order: str) -> list[int]:
    """Raw values (counts) -> registers; ValueError for a value the type cannot hold."""
    out: list[int] = []
    for k, v in enumerate(values):
        if type_ in INTEGER_RANGE:
            lo, hi = INTEGER_RANGE[type_]
            if not (isinstance(v, int | np.integer) and lo <= v <= hi):
                raise ValueError(f"value {k} = {v} does not fit a {type_} ({lo}..{hi})")
        elif not math.isfinite(v) or (type_ == "f32" and abs(v) > 3.4028234663852886e38):
            raise ValueError(f"value {k} = {v} does not fit a {type_}")
        raw = struct.pack(f">{STRUCT[type_]}", v)
        out += _arrange([int.from_bytes(raw[j:j + 2], "big") for j in range(0, len(raw), 2)], word_order)
    return out


def decode(words: Sequence[int], type_: str, word_order: str) -> list[int | float]:
    """Registers -> raw values; ValueError for a count that is not whole values or a word outside 0..65535."""
    per = TYPE_REGISTERS[type_]
    if len(words) % per:
        raise ValueError(f"{len(words)} registers are not whole {type_} values")
    for w in words:
        if not (isinstance(w, int) and 0 <= w <= 0xFFFF):
            raise ValueError(f"register value {w!r} is not a 16-bit word")
    out: list[int | float] = []
    for k in range(0, len(words), per):
        raw = b"".join(w.to_bytes(2, "big") for w in _arrange(list(words[k:k + per]), word_order))
        out.append(struct.unpack(f">{STRUCT[type_]}", raw)[0])
    return out


def field_words(m: RegisterMap, f: RegisterField, value: int) -> list[int]:
    return encode([value], f.type, m.word_order(f.word_order))


def field_value(m: RegisterMap, f: RegisterField, words: Sequence[int]) -> int | float:
    return decode(words, f.type, m.word_order(f.word_order))[0]


def u32_words(m: RegisterMap, value: int) -> list[int]:
    """A checksum register's two words in the device's word order."""
    return encode([value], "u32", m.device.word_order)


def u32_value(m: RegisterMap, words: Sequence[int]) -> int:
    return int(decode(words, "u32", m.device.word_order)[0])


def part_words(part: PartLayout, values_mm: Sequence[float]) -> list[int]:
    """A geometry part's registers for its values in mm; ValueError naming the value that does not fit."""
    counts: list[int | float] = []
    for k, v in enumerate(values_mm):
        c = (float(v) - part.offset) / part.scale
        if part.type in INTEGER_RANGE:
            if not math.isfinite(c):
                raise ValueError(f"{part.name} value {k + 1} = {v} mm is not finite")
            c = round(c)
        counts.append(c)
    try:
        return encode(counts, part.type, part.word_order)
    except ValueError as err:
        raise ValueError(f"{part.name}: {err} (scale {part.scale:g} mm, offset {part.offset:g} mm)") from None


def part_values(part: PartLayout, words: Sequence[int]) -> list[float]:
    """A geometry part's values in mm from its registers."""
    return [float(c) * part.scale + part.offset for c in decode(words, part.type, part.word_order)]


def geometry_words(m: RegisterMap, vector: np.ndarray) -> dict[str, list[int]]:
    """Each held part's registers for a 42-value set (ValueError if a value does not fit)."""
    return {p.name: part_words(p, vector[p.start:p.start + p.values]) for p in m.parts()}


def geometry_vector(m: RegisterMap, words: dict[str, list[int]], fill: np.ndarray) -> np.ndarray:
    """The 42-value set: the held parts decoded over ``fill`` (the values of the parts the device does not hold)."""
    vector = np.array(fill, dtype=float, copy=True)
    if vector.shape != (PARAMETER_COUNT,):
        raise ValueError(f"the fill set has shape {vector.shape}")
    for p in m.parts():
        vector[p.start:p.start + p.values] = part_values(p, words[p.name])
    return vector


def bank_blocks(m: RegisterMap, bank: str, words: dict[str, list[int]], parts: Sequence[str] | None = None
                ) -> list[Block]:
    """(address, registers) of the held parts (or those named) in one bank."""
    return [(p.banks[bank], words[p.name]) for p in m.parts() if parts is None or p.name in parts
            if p.banks[bank] is not None]


def merge(blocks: Sequence[Block]) -> list[Block]:
    """Blocks sorted by address, adjacent ones merged (one request where the device has one run)."""
    out: list[Block] = []
    for address, words in sorted(blocks, key=lambda b: b[0]):
        if out and out[-1][0] + len(out[-1][1]) == address:
            out[-1] = (out[-1][0], out[-1][1] + list(words))
        else:
            out.append((address, list(words)))
    return out


def chunks(blocks: Sequence[Block], size: int) -> list[Block]:
    """Merged blocks cut into requests of at most ``size`` registers."""
    return [(address + k, words[k:k + size]) for address, words in merge(blocks) for k in range(0, len(words), size)]


def spans(blocks: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """(address, count) spans sorted, adjacent ones merged."""
    return [(a, len(w)) for a, w in merge([(a, [0] * n) for a, n in blocks])]


def sha_of_words(words: Sequence[int]) -> str:
    return hashlib.sha256(words_to_bytes(words)).hexdigest()


def sha_of_vector(vector: np.ndarray) -> str:
    """``ParameterSet.sha256`` of a 42-value set without validating it (the hash records key parameter sets by)."""
    return sha_of_words(words_from_floats(np.asarray(vector, dtype=float).tolist()))

"""Rows a logger wrote without a measurement, left out on request (`hilcal import --skip-incomplete`), each one named.

Trackers lose their target and loggers write a sample twice. By default either is an error that names its file,
line and column, because a recording must not lose a measurement silently. With the option the importer leaves such
rows out instead and lists every one (file, line, why) in its notes: a row with an empty or NaN cell in a column the
measurement needs (legs, measured pose or targets, time, phase, temperature, fit RMS), and a row that repeats an
earlier one in every mapped column. The command columns are not needed: a row whose command is empty has an unknown
command, as without the option.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

from hilcal.importing.mapping import ImportMap
from hilcal.importing.table import Table


def needed_columns(mapping: ImportMap) -> list[str]:
    """The mapped columns a row cannot do without (every mapped column but the commanded pose's)."""
    command = set() if mapping.command is None else {*mapping.command.position.columns,
                                                     *mapping.command.orientation.columns}
    return [c for c in mapping.columns() if c not in command]


def _missing(text: str, decimal: str) -> bool:
    if text == "":
        return True
    try:
        return math.isnan(float(text.replace(",", ".") if decimal == "," else text))
    except ValueError:
        return False  # not a number at all: a format error, which the import reports as one


def leave_out_incomplete(tables: Sequence[Table], mapping: ImportMap) -> tuple[list[Table], list[str]]:
    """The tables without their incomplete and duplicated rows, and one sentence per row left out (file order)."""
    needed = needed_columns(mapping)
    every = mapping.columns()
    seen: dict[tuple[str, ...], str] = {}
    kept_tables, left_out = [], []
    for table in tables:
        need = [(c, table.index(c)) for c in needed]
        key_at = [table.index(c) for c in every]
        rows, lines = [], []
        for row, line in zip(table.rows, table.lines, strict=True):
            empty = [c for c, k in need if _missing(row[k].strip(), table.decimal)]
            key = tuple(row[k].strip() for k in key_at)
            if empty:
                left_out.append(f"{table.name} line {line}: no value in {', '.join(empty)}")
                continue
            if key in seen:
                left_out.append(f"{table.name} line {line}: the same values as {seen[key]} in every mapped column")
                continue
            seen[key] = f"{table.name} line {line}"
            rows.append(row)
            lines.append(line)
        kept_tables.append(dataclasses.replace(table, rows=tuple(rows), lines=tuple(lines)))
    return kept_tables, left_out

"""TOML text of the configuration files the tools exchange (station files, simulator configurations): values,
tables and arrays of tables, written by hand because tomllib only reads."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def toml_value(value: Any) -> str:
    """One value: booleans, integers, finite floats (exact repr), strings and paths, arrays of them."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"TOML cannot hold {value}")
        return repr(value)
    if isinstance(value, str | Path):
        return json.dumps(str(value))
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {type(value).__name__}")


def _is_tables(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def toml_lines(data: dict[str, Any], prefix: str = "") -> list[str]:
    """A table's lines: its keys (None left out), then its sub-tables and arrays of tables under `prefix`."""
    lines = [f"{k} = {toml_value(v)}" for k, v in data.items()
             if v is not None and not isinstance(v, dict) and not _is_tables(v)]
    for k, v in data.items():
        name = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict):
            lines += ["", f"[{name}]", *toml_lines(v, name)]
        elif _is_tables(v):
            for item in v:
                lines += ["", f"[[{name}]]", *toml_lines(item, name)]
    return lines

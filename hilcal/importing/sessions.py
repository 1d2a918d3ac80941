"""Clocks, sessions and phases of an import: every file its own session unless a shared clock says otherwise.

The recording format starts a new session where ``time_s`` goes back or jumps by more than 4 h. A file with its
own clock (no time column, or seconds/milliseconds since its logger started) gets ``time_s`` from 0 at its
earliest row, so the clock goes back at the next file: a new session. A shared clock (ISO stamps, or epoch
seconds with ``clock = "shared"``) puts all files on one time line, and the format's rule decides.
Phases come from the mapping's phase column, else from ``--hold-out``, else every row is a measure row.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

import numpy as np

from hilcal.importing.errors import ValueProblem

EPOCH = datetime(1970, 1, 1)
_HOLD_OUT = re.compile(r"^(every):(\d+)$|^(file):(.+)$")


@dataclass(frozen=True)
class HoldOut:
    """Which rows become verify rows: every N-th row of every file, or the rows of one named file."""

    every: int | None = None
    file: str | None = None

    def __post_init__(self) -> None:
        if (self.every is None) == (self.file is None):
            raise ValueError("a hold-out is either every:N or file:NAME")
        if self.every is not None and self.every < 2:
            raise ValueError(f"every:N needs N >= 2 (every:{self.every} would leave no measure rows)")

    def describe(self) -> str:
        return f"every:{self.every}" if self.every is not None else f"file:{self.file}"


def parse_hold_out(text: str) -> HoldOut:
    """'every:N' or 'file:NAME' as a HoldOut; ValueError with the accepted forms otherwise."""
    m = _HOLD_OUT.match(text.strip())
    if m is None:
        raise ValueError(f"--hold-out {text!r}: expected every:N (every N-th row of every file) or file:NAME")
    return HoldOut(every=int(m.group(2))) if m.group(1) else HoldOut(file=m.group(4))


def iso_seconds(text: str) -> tuple[float, bool]:
    """Seconds since 1970-01-01 of an ISO 8601 stamp, and whether it carried a time zone."""
    stamp = datetime.fromisoformat(text.strip())
    if stamp.tzinfo is not None:
        return stamp.timestamp(), True
    return (stamp - EPOCH) / timedelta(seconds=1), False


def stamps_seconds(texts: Sequence[str], unit: str, numbers: np.ndarray | None = None) -> np.ndarray:
    """(n,) seconds of a time column: numbers in s or ms, or ISO text (all with a zone, or none)."""
    if unit == "s":
        return np.asarray(numbers, dtype=float).copy()
    if unit == "ms":
        return np.asarray(numbers, dtype=float) / 1000.0
    out = np.empty(len(texts))
    zoned: bool | None = None
    for i, text in enumerate(texts):
        try:
            out[i], has_zone = iso_seconds(text)
        except ValueError:
            raise ValueProblem(i, 0, f"{text!r} is not an ISO 8601 time stamp (e.g. 2025-03-04T08:15:30.250)") from None
        if zoned is not None and has_zone != zoned:
            raise ValueProblem(i, 0, f"{text!r}: time stamps with and without a time zone are mixed")
        zoned = has_zone
    return out


def clocks(per_file_s: Sequence[np.ndarray], mode: str) -> list[np.ndarray]:
    """``time_s`` per file: own clocks from 0 at each file's earliest row ('per_file'), or one from 0 ('shared')."""
    if mode == "shared":
        start = min(float(np.min(t)) for t in per_file_s)
        return [np.asarray(t, dtype=float) - start for t in per_file_s]
    return [np.asarray(t, dtype=float) - float(np.min(t)) for t in per_file_s]


def row_clock(n_rows: int) -> np.ndarray:
    """The clock of a file without time stamps: its row numbers, 1 s apart from 0 (the order is known, not the time)."""
    return np.arange(n_rows, dtype=float)


def missing_session_start(per_file_time_s: Sequence[np.ndarray], session: np.ndarray) -> int | None:
    """Index of the first file (after the first) whose first row does not start a new session, else None."""
    start = 0
    for k, t in enumerate(per_file_time_s):
        if k > 0 and session[start] == session[start - 1]:
            return k
        start += len(t)
    return None


def phases_from_column(values: Sequence[str], measure: Sequence[str], verify: Sequence[str]) -> np.ndarray:
    """'measure'/'verify' from a phase column; a value that is neither is a ValueProblem at its row."""
    out = np.empty(len(values), dtype=object)
    for i, v in enumerate(values):
        if v in measure:
            out[i] = "measure"
        elif v in verify:
            out[i] = "verify"
        else:
            raise ValueProblem(i, 0, f"{v!r} is neither a measure value ({', '.join(measure)}) nor a verify value "
                               f"({', '.join(verify)}) of [phase]")
    return out.astype(str)


def phases_from_hold_out(n_rows: int, file_name: str, hold_out: HoldOut | None) -> np.ndarray:
    """One file's phases: every N-th row (N, 2N, ... counted from 1) or all rows of the named file are verify rows."""
    phase = np.full(n_rows, "measure", dtype=object)
    if hold_out is not None and hold_out.every is not None:
        phase[hold_out.every - 1 :: hold_out.every] = "verify"
    elif hold_out is not None and file_name == hold_out.file:
        phase[:] = "verify"
    return phase.astype(str)

"""Hold-out rules, clocks and ISO stamps."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.importing import HoldOut, parse_hold_out
from hilcal.importing.errors import ValueProblem
from hilcal.importing.sessions import clocks, phases_from_column, phases_from_hold_out, stamps_seconds
from hilcal.recording import session_numbers


def test_hold_out_forms():
    assert parse_hold_out("every:3") == HoldOut(every=3)
    assert parse_hold_out("file:day 2.csv") == HoldOut(file="day 2.csv")
    for bad in ("every:1", "every:x", "third", "file:"):
        with pytest.raises(ValueError):
            parse_hold_out(bad)


def test_every_third_row_of_a_file_counts_from_its_first_row():
    phase = phases_from_hold_out(7, "a.csv", HoldOut(every=3))
    assert list(phase) == ["measure", "measure", "verify", "measure", "measure", "verify", "measure"]
    assert set(phases_from_hold_out(3, "b.csv", HoldOut(file="b.csv"))) == {"verify"}
    assert set(phases_from_hold_out(3, "a.csv", HoldOut(file="b.csv"))) == {"measure"}


def test_phase_values_of_the_map_and_an_unknown_one():
    assert list(phases_from_column(["cal", "check"], ("cal",), ("check",))) == ["measure", "verify"]
    with pytest.raises(ValueProblem) as info:
        phases_from_column(["cal", "Cal"], ("cal",), ("check",))
    assert info.value.row == 1


def test_own_clocks_restart_so_every_file_is_a_session_and_a_shared_one_decides_by_the_gap():
    first, second = np.array([100.0, 160.0, 220.0]), np.array([90.0, 150.0])
    time_s = np.concatenate(clocks([first, second], "per_file"))
    assert list(time_s) == [0.0, 60.0, 120.0, 0.0, 60.0]
    assert list(session_numbers(time_s)) == [0, 0, 0, 1, 1]
    later = second + 220.0 + 3600.0
    assert list(session_numbers(np.concatenate(clocks([first, later], "shared")))) == [0] * 5
    next_day = second + 220.0 + 5 * 3600.0
    assert list(session_numbers(np.concatenate(clocks([first, next_day], "shared")))) == [0, 0, 0, 1, 1]


def test_iso_stamps_with_and_without_zone():
    naive = stamps_seconds(["2025-03-04T08:00:00", "2025-03-04T08:00:01.250"], "iso")
    assert naive[1] - naive[0] == pytest.approx(1.25, abs=1e-6)
    zoned = stamps_seconds(["2025-03-04T08:00:00+01:00", "2025-03-04T07:30:00Z"], "iso")
    assert zoned[1] - zoned[0] == pytest.approx(1800.0)
    with pytest.raises(ValueProblem) as info:
        stamps_seconds(["2025-03-04T08:00:00", "2025-03-04T08:00:00Z"], "iso")
    assert info.value.row == 1
    with pytest.raises(ValueProblem, match="not an ISO 8601"):
        stamps_seconds(["yesterday"], "iso")
    assert list(stamps_seconds([], "ms", np.array([1500.0, 2500.0]))) == [1.5, 2.5]

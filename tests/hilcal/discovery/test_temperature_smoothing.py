"""The temperature smoothing is scipy's Savitzky-Golay filter of order 1 (written out to spare every run the import
of scipy.signal): the same numbers on windows shorter than, equal to and longer than the recording."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.discovery.context import TEMPERATURE_WINDOW, smooth_temperature


@pytest.mark.parametrize("n", [5, 6, 7, 8, 9, 24, 101])
def test_smoothing_is_savitzky_golay_of_order_one(n: int) -> None:
    from scipy.signal import savgol_filter  # imported here: at the top, every worker's collection would pay 0.4 s

    temp_c = 20.0 + np.random.default_rng(n).normal(0.0, 0.05, n).cumsum()
    width = min(TEMPERATURE_WINDOW, n - (1 - n % 2))
    expected = savgol_filter(temp_c, width, 1, mode="interp")
    assert np.allclose(smooth_temperature(temp_c), expected, rtol=0.0, atol=1e-12)


def test_a_linear_warm_up_is_kept_and_short_recordings_are_left_alone() -> None:
    ramp = 20.0 + 0.01 * np.arange(30)
    assert np.allclose(smooth_temperature(ramp), ramp, rtol=0.0, atol=1e-12)
    short = np.array([20.0, 21.0, 20.5, 20.2])
    assert np.array_equal(smooth_temperature(short), short)

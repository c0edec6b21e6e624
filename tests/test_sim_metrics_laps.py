"""Laps held in the steady windows, from the arc length."""
import math

import numpy as np
import pytest

from drift_sim.metrics import laps


def test_laps_count_the_arc_length_inside_the_windows():
    t = np.arange(0.0, 60.0, 0.01)
    s = 9.0 * t                               # 9 m/s along a 94.25 m lap
    lap = 2 * math.pi * 15.0
    assert laps(t, s, [[15.0, 50.0]], lap) == pytest.approx(9.0 * 35.0 / lap, rel=1e-3)
    assert laps(t, s, [[0.0, 10.0], [20.0, 30.0]], lap) == pytest.approx(180.0 / lap, rel=1e-3)
    assert laps(t, s, [], lap) == 0.0


def test_transition_time_and_windowed_maximum():
    from drift_sim.metrics import max_abs_in_windows, transition_time
    t = np.arange(0.0, 10.0, 0.01)
    beta = np.radians(np.where(t < 4.0, -30.0, np.where(t < 5.5, -30.0 + 40.0 * (t - 4.0), 30.0)))
    # |beta| > 20 deg: left until 4.25 s, right from 5.25 s
    assert transition_time(t, beta, math.radians(20.0)) == pytest.approx(1.0, abs=0.02)
    assert math.isnan(transition_time(t, -np.abs(beta), math.radians(20.0)))
    e_y = np.where((t > 4.0) & (t < 6.0), 3.0, 0.5)
    assert max_abs_in_windows(t, e_y, [[0.0, 4.0], [6.0, 10.0]]) == 0.5

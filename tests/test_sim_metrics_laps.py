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

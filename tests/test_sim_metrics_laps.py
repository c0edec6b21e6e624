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


def test_settled_windows_lie_between_the_flips_wherever_they_fall_in_time():
    from drift_sim.metrics import settled_windows
    t = np.arange(0.0, 30.0, 0.01)
    # grip until 2 s, ramp to -30 deg by 5 s, flip to +30 deg over 12-14 s, back over 22-24 s;
    # a window opens 3 s after the reference came within 1 deg of its value
    ramp = np.clip((t - 2.0) / 3.0, 0.0, 1.0) * -30.0
    flip1 = np.clip((t - 12.0) / 2.0, 0.0, 1.0) * 60.0
    flip2 = np.clip((t - 22.0) / 2.0, 0.0, 1.0) * -60.0
    beta_ref = np.radians(ramp + flip1 + flip2)
    beta_ref[:50] = np.nan   # no reference yet
    windows = settled_windows(t, beta_ref, 3.0, math.radians(10.0))
    assert len(windows) == 3
    for (a, b), (a_want, b_want) in zip(windows, [(8.0, 12.0), (17.0, 22.0), (27.0, 30.0)]):
        assert a == pytest.approx(a_want, abs=0.1) and b == pytest.approx(b_want, abs=0.1)
    # a reference that never holds one value long enough: no window (the run is judged lost)
    assert settled_windows(t, np.radians(20.0 * np.sin(t)), 3.0, math.radians(10.0)) == []


def test_a_scenario_gives_steady_windows_or_settle_not_both(tmp_path):
    from drift_control.params import ParamError
    from drift_control.scenario import load_scenario_spec
    text = ('duration: 10.0\ncontrol_mode: full\nsurface: {name: dry}\npath: circle_left_15\n'
            'initial: {V: 11.0, s: 0.0}\nmetrics: {steady: [[1.0, 5.0]], settle: 3.0}\n')
    (tmp_path / 'both.yaml').write_text(text)
    with pytest.raises(ParamError, match='settle, not both'):
        load_scenario_spec(str(tmp_path / 'both.yaml'))


def test_exit_time_runs_from_the_references_last_drift_moment_to_grip_for_good():
    from drift_sim.metrics import exit_time
    t = np.arange(0.0, 20.0, 0.01)
    beta_ref = np.radians(np.clip((14.0 - t) / 2.0, 0.0, 1.0) * -30.0)   # drift until 12 s
    beta = np.radians(np.clip((15.0 - t) / 2.0, 0.0, 1.0) * -30.0)       # the car 1 s later
    beta[t > 15.5] += np.radians(np.where(t[t > 15.5] < 15.8, -4.0, 0.0))  # a last twitch
    # the reference within 1 deg of 30 until 12.07 s; |beta| < 3 deg for good from 15.8 s
    assert exit_time(t, beta, beta_ref) == pytest.approx(15.8 - (14.0 - 2.0 * 29.0 / 30.0),
                                                         abs=0.02)
    assert math.isnan(exit_time(t, beta, np.full_like(t, math.radians(-30.0))))   # no exit asked
    assert math.isnan(exit_time(t, np.full_like(t, math.radians(-30.0)), beta_ref))  # not left

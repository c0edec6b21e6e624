"""Integral action of the path-following correction: only once settled, never in the entry."""
import math
from dataclasses import replace

import pytest

from drift_control import path as P
from drift_control.signals import Direction
from test_reference_selector import drift_circle, params, state_on, steady_circle_lookup

from drift_control.reference import ReferenceSelector


def run(selector, path, e_y, beta, seconds, t0=0.0):
    """Hold the car ``e_y`` left of the path at sideslip ``beta`` while it drives on."""
    ref, dt, V = None, 0.02, 10.0
    for k in range(int(seconds / dt)):
        t = t0 + k * dt
        ref = selector.select(state_on(path, 30.0 + V * t, e_y, t=t, V=V, beta=beta))
    return ref


def test_integral_builds_only_while_the_car_is_settled_in_its_drift():
    path = drift_circle(Direction.LEFT)
    sel = ReferenceSelector(steady_circle_lookup, path,
                            params(k_p=0.0, k_d=0.0, k_i=0.01, integral_limit=10.0,
                                   integral_band=1.5, integral_beta_band=0.05,
                                   horizon_steps=0))
    K = 1.0 / 15.0
    # 1 m inside the path but sideslip 10 deg off its reference: the entry, no integration
    ref = run(sel, path, 1.0, math.radians(-20.0), 2.0)
    assert ref.curvature_cmd == pytest.approx(K, abs=1e-12)
    # 3 m off the path, on the sideslip reference: a transient, no integration either
    ref = run(sel, path, 3.0, math.radians(-30.0), 2.0, t0=2.0)
    assert ref.curvature_cmd == pytest.approx(K, abs=1e-12)
    # settled 1 m inside: the integral widens the curvature command (a car inside a left circle
    # is steered out), by k_i * 1 m * 2 s
    ref = run(sel, path, 1.0, math.radians(-30.0), 2.0, t0=4.0)
    assert K - ref.curvature_cmd == pytest.approx(0.01 * 1.0 * 2.0, rel=0.05)


def test_integral_learnt_in_the_left_drift_is_mirrored_for_the_right_drift():
    """The integral holds a steady curvature offset of the drift (the car turns less tightly
    than its equilibrium): after the flip the right drift needs the mirror image. Carried over
    unmirrored it steered the car 1 m to the inside of the right circle."""
    prof = P.SideslipProfile(math.radians(30.0))
    path = P.alternating(15.0, 30.0, laps_first=1.0, sideslip=prof)
    sel = ReferenceSelector(steady_circle_lookup, path,
                            params(k_p=0.0, k_d=0.0, k_i=0.01, integral_limit=10.0,
                                   integral_band=1.5, side_band=0.045, radius_max=40.0,
                                   horizon_steps=0))
    left = run(sel, path, 1.0, math.radians(-30.0), 2.0)          # s 30 -> 50 m, left circle
    offset = left.curvature_cmd - left.curvature
    assert offset == pytest.approx(-0.01 * 1.0 * 2.0, rel=0.05)
    # on through the flip on the path (nothing more to integrate), into the right circle
    dt, V = 0.02, 10.0
    for k in range(int(9.0 / dt)):
        t = 2.0 + k * dt
        right = sel.select(state_on(path, 50.0 + V * (t - 2.0), 0.0, t=t, V=V))
    assert right.direction == Direction.RIGHT
    assert right.curvature_cmd - right.curvature == pytest.approx(-offset, rel=0.02)


def drive(selector, path, s0, seconds, t0=0.0, tighter=0.006, V=10.0):
    """The car on the path at its sideslip reference, turning ``tighter`` [1/m] more tightly
    than the curvature the last reference asked (the path's on the first call)."""
    ref, dt = None, 0.02
    for k in range(int(seconds / dt)):
        t = t0 + k * dt
        st = state_on(path, s0 + V * (t - t0), 0.0, t=t, V=V)
        if ref is not None:
            K = ref.curvature_cmd
            st = replace(st, r=V * (K + math.copysign(tighter, K)),
                         beta=-math.copysign(math.radians(30.0), K))
        ref = selector.select(st)
    return ref


def bias_params(**over):
    base = dict(k_p=0.0, k_d=0.0, k_i=0.0, curvature_bias_time=1.0, horizon_steps=10,
                side_band=0.045, radius_max=40.0)
    base.update(over)
    return params(**base)


def test_a_car_that_turns_tighter_than_asked_is_asked_less_once_it_drifts_steadily():
    """The bias is learnt on the curvature the car drives (r / V) against the one asked, and
    the command then asks so much less that the car drives the path's."""
    K = 1.0 / 15.0
    prof = P.SideslipProfile(math.radians(30.0), ramp_length=20.0)
    path = P.circle(15.0, Direction.LEFT, sideslip=prof)
    sel = ReferenceSelector(steady_circle_lookup, path, bias_params())
    ref = drive(sel, path, 0.5, 1.5)                # in the entry ramp: nothing learnt
    assert ref.curvature_cmd == pytest.approx(K, abs=1e-12)
    ref = drive(sel, path, 30.0, 10.0, t0=2.0)       # 10 time constants of steady drift
    assert ref.curvature_cmd == pytest.approx(K - 0.006, rel=1e-3)


def test_the_bias_learnt_in_the_left_drift_is_mirrored_and_held_through_the_flip():
    K = 1.0 / 15.0
    prof = P.SideslipProfile(math.radians(30.0))
    path = P.alternating(15.0, 30.0, laps_first=1.0, sideslip=prof)
    sel = ReferenceSelector(steady_circle_lookup, path, bias_params())
    left = drive(sel, path, 20.0, 6.0)               # s 20 -> 80 m of the 94 m left circle
    assert left.curvature_cmd == pytest.approx(K - 0.006, rel=1e-3)
    # on through the flip (nothing learnt there) to the right circle: the bias is the left
    # drift's mirrored (unmirrored, it would ask 0.012 1/m too tight a curvature there)
    right = drive(sel, path, 80.0, 4.5, t0=6.0)
    assert right.direction == Direction.RIGHT and right.curvature == pytest.approx(-K)
    assert right.curvature_cmd == pytest.approx(-(K - 0.006), rel=1e-3)
    # a right drift that turns as asked unlearns it
    right = drive(sel, path, 125.0, 6.0, t0=10.5, tighter=0.0)
    assert right.curvature_cmd == pytest.approx(-K, rel=1e-3)


def test_a_yaw_rate_stuck_at_zero_takes_no_more_than_the_bias_bound(caplog):
    """A yaw-rate signal stuck at 0 reads as a car that does not turn: unbounded, ``b`` would
    follow it to ``-K`` and ask the whole correction limit; the bound keeps it, and says so."""
    K, limit = 1.0 / 15.0, 0.015
    prof = P.SideslipProfile(math.radians(30.0), ramp_length=20.0)
    path = P.circle(15.0, Direction.LEFT, sideslip=prof)
    sel = ReferenceSelector(steady_circle_lookup, path,
                            bias_params(correction_limit=0.05, curvature_bias_limit=limit))
    dt, V = 0.02, 10.0
    with caplog.at_level('WARNING', logger='drift_control.reference'):
        for k in range(int(10.0 / dt)):
            t = 2.0 + k * dt
            st = replace(state_on(path, 30.0 + V * (t - 2.0), 0.0, t=t, V=V),
                         r=0.0, beta=-math.radians(30.0))
            ref = sel.select(st)
    assert ref.curvature_cmd == pytest.approx(K + limit, rel=1e-9)
    assert 'curvature bias' in caplog.text and 'bound' in caplog.text

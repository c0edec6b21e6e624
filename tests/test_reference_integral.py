"""Integral action of the path-following correction: only once settled, never in the entry."""
import math

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

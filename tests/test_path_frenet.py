"""Frenet projection: exact on circles and lines, continuous across seams, O(1) per call."""
import math

import numpy as np
import pytest

from drift_control import path as P
from drift_control.frenet import Frenet, project_on_arc
from drift_control.signals import Direction

R = 15.0


@pytest.mark.parametrize('offset', [-3.0, -0.5, 0.0, 0.7, 4.0])
def test_left_circle_projection_is_exact(offset):
    """Centre (0, R); e_y = R - distance to centre (left of a CCW circle is inside)."""
    path, frenet = P.circle(R, Direction.LEFT), None
    frenet = Frenet(path)
    for theta in np.linspace(0.0, 2.5 * math.pi, 60):          # angle travelled from the start
        rho = R - offset
        x, y = rho * math.sin(theta), R - rho * math.cos(theta)
        fp = frenet.project(x, y, theta + 0.2)
        assert fp.s == pytest.approx(R * theta, abs=1e-9), 'arc length must be unwrapped'
        assert fp.e_y == pytest.approx(offset, abs=1e-9)
        assert fp.heading_error == pytest.approx(0.2, abs=1e-9)
        assert fp.K == pytest.approx(1.0 / R)


def test_right_circle_inside_is_right_of_path():
    path = P.circle(R, Direction.RIGHT)                          # centre (0, -R)
    fp = Frenet(path).project(0.0, -2.0, 0.0)
    assert fp.e_y == pytest.approx(-2.0, abs=1e-12)
    assert fp.K == pytest.approx(-1.0 / R)
    fp = Frenet(path).project(R * math.sin(1.0) * 1.1, -R + R * math.cos(1.0) * 1.1, -1.0)
    assert fp.s == pytest.approx(R * 1.0, abs=1e-9)
    assert fp.e_y == pytest.approx(0.1 * R, abs=1e-9)           # outside a CW circle: left
    assert fp.heading_error == pytest.approx(0.0, abs=1e-9)


def test_straight_line_projection_is_exact_beyond_both_ends():
    yaw0 = 0.3
    path = P.from_segments([(50.0, 0.0, 0.0)], start=(1.0, 2.0, yaw0))
    t, n = np.array([math.cos(yaw0), math.sin(yaw0)]), np.array([-math.sin(yaw0), math.cos(yaw0)])
    for along, across in [(-2.0, 1.0), (0.0, -3.0), (17.3, 0.4), (49.99, -1.0), (53.0, 2.0)]:
        x, y = np.array([1.0, 2.0]) + along * t + across * n
        fp = Frenet(path).project(x, y, yaw0 - 0.5)
        assert fp.s == pytest.approx(along, abs=1e-9)
        assert fp.e_y == pytest.approx(across, abs=1e-9)
        assert fp.heading_error == pytest.approx(-0.5, abs=1e-12)


def test_arc_projection_matches_line_for_vanishing_curvature():
    for k in (1e-13, 1e-9, 1e-6):
        ds, e_y = project_on_arc(3.0, 2.0, 0.0, 0.0, 0.0, k)
        assert ds == pytest.approx(3.0, rel=1e-5) and e_y == pytest.approx(2.0, rel=1e-5)


@pytest.mark.parametrize('builder', [lambda: P.circle(R), lambda: P.figure8(R, 10.0),
                                     lambda: P.polyline(
                                         [[30 * math.cos(a), 20 * math.sin(a)] for a in
                                          np.linspace(0, 2 * math.pi, 24, endpoint=False)],
                                         closed=True),
                                     lambda: P.circle(2.0)])   # a lap shorter than the window
def test_s_is_continuous_across_the_seam_for_three_laps(builder):
    """Drive 3 laps 0.5 m off the path in 0.3 m steps: s grows by ~0.3 m each step, no jump."""
    path = builder()
    frenet = Frenet(path)
    s_true = np.arange(0.0, 3.0 * path.length, 0.3)
    s_meas = []
    for s in s_true:
        i = s / path.ds
        x, y = path.x[int(i) % path.n], path.y[int(i) % path.n]
        psi = path.psi[int(i) % path.n]
        fp = frenet.project(x - 0.5 * math.sin(psi), y + 0.5 * math.cos(psi), psi)
        assert fp.e_y == pytest.approx(0.5, abs=2e-3)
        s_meas.append(fp.s)
    steps = np.diff(s_meas)
    assert steps.min() > 0.2 and steps.max() < 0.4, 'no jump of s, also not at the seam'
    assert s_meas[-1] == pytest.approx(3.0 * path.length - 0.3, abs=0.5)
    assert frenet.global_searches == 1


def test_figure8_crossing_keeps_the_branch():
    """At the crossing both branches are near; the window keeps the one being driven."""
    path = P.figure8(R, 10.0)
    frenet = Frenet(path)
    for s in np.arange(0.0, 2 * path.length, 0.5):
        i = int(round(s / path.ds)) % path.n
        fp = frenet.project(path.x[i], path.y[i], path.psi[i])
        assert fp.s == pytest.approx(s, abs=0.06)
        assert fp.K == pytest.approx(path.K[i], abs=1e-3)


def _long_path(length):
    """A winding open path of ``length`` [m]: alternating arcs and straights."""
    unit = [(20.0, 0.0, 0.0), (10.0, 0.0, 0.05), (30.0, 0.05, 0.05), (10.0, 0.05, -0.05),
            (30.0, -0.05, -0.05), (10.0, -0.05, 0.0)]
    n = int(length // 110.0)
    return P.from_segments(unit * n, ds=0.1)


def test_projection_work_is_constant_on_a_10_km_path():
    """Count samples examined per call: the same on 1 km and 10 km, far below the path size."""
    work = {}
    for length in (1_000.0, 10_000.0):
        path = _long_path(length)
        frenet = Frenet(path, window_back=5.0, window_forward=15.0)
        frenet.project(path.x[0], path.y[0], path.psi[0])      # first call: global
        assert frenet.points_examined == path.n
        per_call = []
        for i in range(10, path.n - 10, 7):                     # 0.7 m per call (35 m/s, 50 Hz)
            fp = frenet.project(path.x[i] + 0.3, path.y[i] - 0.2, path.psi[i])
            assert fp.s == pytest.approx(i * path.ds, abs=0.5)
            per_call.append(frenet.points_examined)
        work[length] = max(per_call)
        assert frenet.global_searches == 1
    assert work[10_000.0] == work[1_000.0] <= 201
    assert work[10_000.0] < _long_path(10_000.0).n / 400


def test_lost_car_triggers_a_global_search():
    path = _long_path(2_000.0)
    frenet = Frenet(path, lost_distance=5.0)
    frenet.project(path.x[100], path.y[100], 0.0)
    far = 12_000
    fp = frenet.project(path.x[far] + 1.0, path.y[far], path.psi[far])
    assert frenet.global_searches == 2
    assert fp.s == pytest.approx(far * path.ds, abs=2.0)


def test_mirrored_path_mirrors_the_projection():
    path = P.alternating(R, 10.0)
    mirror = path.mirrored()
    f, fm = Frenet(path), Frenet(mirror)
    rng = np.random.default_rng(0)
    for i in range(0, path.n, 97):
        dx, dy, dyaw = rng.normal(0.0, 1.0, 3)
        x, y, yaw = path.x[i] + dx, path.y[i] + dy, path.psi[i] + 0.3 * dyaw
        a, b = f.project(x, y, yaw), fm.project(x, -y, -yaw)
        assert b.s == pytest.approx(a.s, abs=1e-9)
        assert b.e_y == pytest.approx(-a.e_y, abs=1e-9)
        assert b.heading_error == pytest.approx(-a.heading_error, abs=1e-9)
        assert b.K == pytest.approx(-a.K, abs=1e-12)


def test_a_car_lost_on_an_open_path_is_not_handed_back_to_a_stretch_it_passed():
    """Off the exit straight by 14 m near its start, the car is nearer the drift circle it left:
    the global search keeps it on the straight (progress), not on the circle 150 m back."""
    from drift_control.params import config_dir
    path = P.load_path_file(config_dir() / 'paths' / 'circle_exit_15.yaml')
    frenet = Frenet(path, lost_distance=5.0)
    j = int(round(260.0 / path.ds))   # on the straight, 20 m after the clothoid
    frenet.reset(s_hint=j * path.ds)
    frenet.project(path.x[j], path.y[j], path.psi[j])
    nx, ny = -math.sin(path.psi[j]), math.cos(path.psi[j])   # left normal
    fp = frenet.project(path.x[j] + 16.0 * nx, path.y[j] + 16.0 * ny, path.psi[j] + 1.0)
    assert frenet.global_searches == 1
    assert fp.s > 250.0, fp.s

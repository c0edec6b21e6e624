"""Path builders and the YAML format: geometry consistent, curvature continuous, errors named."""
import glob
import math
import os

import numpy as np
import pytest

from drift_control import path as P
from drift_control.params import ParamError, config_dir, load_yaml
from drift_control.signals import Direction

R = 15.0


def _check_geometry(path, tol_K=2e-3):
    """Heading is the integral of K, positions the integral of the heading (sample to sample)."""
    dpsi = np.diff(path.psi)
    assert np.abs(dpsi - 0.5 * (path.K[1:] + path.K[:-1]) * path.ds).max() < tol_K * path.ds
    chord = np.hypot(np.diff(path.x), np.diff(path.y))
    assert np.abs(chord - path.ds).max() < 1e-3 * path.ds
    direction = np.arctan2(np.diff(path.y), np.diff(path.x))
    mid = 0.5 * (path.psi[1:] + path.psi[:-1])
    assert np.abs(np.angle(np.exp(1j * (direction - mid)))).max() < 1e-3
    if path.closed:   # the seam is an ordinary step
        assert math.hypot(path.x[0] - path.x[-1], path.y[0] - path.y[-1]) == pytest.approx(
            path.ds, rel=1e-3)


def test_circle_is_a_circle():
    path = P.circle(R, Direction.LEFT, start=(2.0, 1.0, math.pi / 2))   # centre at (2 - R, 1)
    assert path.closed and path.length == pytest.approx(2 * math.pi * R)
    assert np.hypot(path.x - (2.0 - R), path.y - 1.0) == pytest.approx(np.full(path.n, R))
    assert np.all(path.K == pytest.approx(1.0 / R))
    _check_geometry(path)


def test_interpolation_between_samples_is_exact_on_a_circle():
    path = P.circle(R, Direction.RIGHT)                       # clockwise, yaw 0 at s = 0
    s = np.linspace(-10.0, 3 * path.length, 1001)             # across the seam, several laps
    assert path.heading_at(s) == pytest.approx(P.wrap_angle(-s / R), abs=1e-12)
    assert path.curvature_at(s) == pytest.approx(np.full(s.shape, -1 / R))


def test_alternating_is_left_then_right_with_a_continuous_curvature():
    path = P.alternating(R, transition=10.0, laps_first=1.0, laps_second=1.0)
    assert not path.closed
    assert path.length == pytest.approx(4 * math.pi * R + 10.0)
    assert path.K[0] == pytest.approx(1 / R) and path.K[-1] == pytest.approx(-1 / R)
    assert np.abs(np.diff(path.K)).max() <= 2 / R / 10.0 * path.ds * 1.01
    assert path.direction_at(10.0) == Direction.LEFT
    assert path.direction_at(path.length - 10.0) == Direction.RIGHT
    _check_geometry(path)


def test_alternating_without_transition_is_two_tangent_circles():
    path = P.alternating(R, transition=0.0)
    half = path.n // 2
    assert (path.x[half], path.y[half]) == pytest.approx((0.0, 0.0), abs=0.06)
    assert math.hypot(path.x[-1], path.y[-1]) == pytest.approx(0.0, abs=1e-3)  # step mid-sample
    _check_geometry(path, tol_K=1.0)   # the curvature step itself is allowed here


@pytest.mark.parametrize('transition', [0.0, 5.0, 10.0, 20.0])
def test_figure8_closes_and_turns_both_ways(transition):
    path = P.figure8(R, transition)
    assert path.closed                                   # from_segments checked the closure
    total_turn = path.psi[-1] - path.psi[0] + path.ds * path.K[-1]
    assert total_turn == pytest.approx(0.0, abs=1e-3)   # winding number 0 (a circle: 2 pi)
    assert path.K.max() == pytest.approx(1 / R) and path.K.min() == pytest.approx(-1 / R)
    if transition > 0:
        assert np.abs(np.diff(np.append(path.K, path.K[0]))).max() < 2 / R / transition * 0.11
    _check_geometry(path, tol_K=1.0 if transition == 0 else 2e-3)


def test_polyline_through_circle_points_has_the_circle_curvature():
    pts = [[R * math.cos(a), R * math.sin(a)] for a in np.linspace(0, 2 * math.pi, 36,
                                                                      endpoint=False)]
    path = P.polyline(pts, closed=True)
    assert path.length == pytest.approx(2 * math.pi * R, rel=1e-4)
    assert path.K == pytest.approx(np.full(path.n, 1 / R), rel=5e-3)
    _check_geometry(path)


def test_polyline_smoothing_bounds_the_curvature_of_a_corner():
    pts = [[0, 0], [10, 0], [20, 0], [30, 0], [30, 10], [30, 20], [30, 30]]
    sharp = P.polyline(pts, smoothing=0.0)
    smooth = P.polyline(pts, smoothing=1.0)
    assert np.abs(smooth.K).max() < np.abs(sharp.K).max()
    assert np.abs(np.diff(smooth.K)).max() < 0.01


def test_mirrored_path_turns_the_other_way():
    path = P.alternating(R, 10.0)
    m = path.mirrored()
    assert np.all(m.K == -path.K) and np.all(m.y == -path.y)
    assert m.direction_at(5.0) == Direction.RIGHT
    assert m.beta_at(100.0) == path.beta_at(100.0)


def test_sideslip_entry_ramp_is_continuous():
    prof = P.SideslipProfile(math.radians(30), math.radians(2), grip_until=20.0, ramp_length=15.0)
    path = P.circle(R, sideslip=prof)
    s = np.arange(0.0, 3 * path.length, 0.05)
    beta = path.beta_at(s)
    assert beta[s < 20.0] == pytest.approx(math.radians(2))
    assert beta[s > 35.0] == pytest.approx(math.radians(30))      # on every later lap too
    assert np.abs(np.diff(beta)).max() < 1.5 * math.radians(28) / 15.0 * 0.05 * 1.01


def test_sideslip_knots_are_periodic_on_a_closed_path():
    prof = P.SideslipProfile(0.0, knots=((0.0, 0.4), (50.0, 0.6)))
    path = P.circle(R, sideslip=prof)
    assert path.beta_at(25.0) == pytest.approx(0.5)
    assert path.beta_at(25.0 + path.length) == pytest.approx(0.5)


def test_every_shipped_path_file_loads():
    files = sorted(glob.glob(os.path.join(config_dir(), 'paths', '*.yaml')))
    assert len(files) >= 4
    for f in files:
        path = P.load_path(load_yaml(f)['path'], os.path.basename(f))
        assert np.all(np.isfinite(path.K)) and path.length > 50.0
        # a drift somewhere after the entry (an exit path ends in grip)
        assert np.max(path.beta_at(np.arange(0.0, path.length + 200.0, 1.0))) > math.radians(20)


def test_segments_yaml():
    raw = {'type': 'segments', 'segments': [{'length': 20.0}, {'length': 10.0,
                                                             'curvature_end': 1 / R},
                                            {'radius': R, 'angle_deg': 90, 'direction': 'left'}],
           'sideslip': {'beta_deg': 25}}
    path = P.load_path(raw)
    assert path.length == pytest.approx(30.0 + R * math.pi / 2)
    assert path.psi[-1] - path.psi[0] == pytest.approx(math.pi / 2 + 10.0 / R / 2)


@pytest.mark.parametrize('raw, key', [
    ({'type': 'circle', 'radius': 15.0, 'radiuss': 3}, 'radiuss'),
    ({'type': 'circle', 'radius': -1.0}, 'path.radius'),
    ({'type': 'circle', 'radius': 15.0, 'direction': 'up'}, 'path.direction'),
    ({'type': 'spiral'}, 'path.type'),
    ({'type': 'circle', 'radius': 15.0, 'transition': 3.0}, 'transition'),
    ({'type': 'circle', 'radius': 15.0, 'sideslip': {'beta': 30}}, 'path.sideslip'),
    ({'type': 'segments', 'closed': True, 'segments': [{'length': 10.0}]}, 'does not close'),
    ({'type': 'segments', 'segments': [{'length': 10.0, 'curvatur': 0.1}]}, 'segments[0]'),
])
def test_bad_yaml_is_a_param_error_naming_the_key(raw, key):
    with pytest.raises(ParamError, match=key.replace('[', r'\[').replace(']', r'\]')):
        P.load_path(raw)


def test_scenario_path_is_inline_or_a_paths_file(tmp_path):
    from drift_control.scenario import resolve_path
    (tmp_path / 'paths').mkdir()
    (tmp_path / 'paths' / 'ring.yaml').write_text('path: {type: circle, radius: 20.0}\n')
    assert resolve_path('ring', tmp_path, 'by_name').K[0] == pytest.approx(1 / 20.0)
    assert resolve_path('ring', tmp_path, 'by_name').name == 'ring', 'named after its file'
    inline = {'type': 'circle', 'radius': 10.0, 'direction': 'right'}
    assert resolve_path(inline, tmp_path, 'inline').K[0] == pytest.approx(-1 / 10.0)
    assert P.load_path_file(tmp_path / 'paths' / 'ring.yaml').K[0] == pytest.approx(1 / 20.0)
    with pytest.raises(ParamError, match='none.path: expected a mapping'):
        resolve_path(None, tmp_path, 'none')
    with pytest.raises(ParamError, match='not found'):
        resolve_path('nosuch', tmp_path, 'nosuch')


def test_scenario_path_file_with_keys_laid_over_it(tmp_path):
    """``{file: name, ...}``: the file's path with the given keys changed, mappings key by key
    (a longer entry ramp keeps the file's drift sideslip and grip phase)."""
    from drift_control.scenario import resolve_path
    (tmp_path / 'paths').mkdir()
    (tmp_path / 'paths' / 'ring.yaml').write_text(
        'path:\n  type: circle\n  radius: 20.0\n'
        '  sideslip: {beta_deg: 30.0, grip_until: 20.0, ramp_length: 45.0}\n')
    base = resolve_path('ring', tmp_path, 'base')
    long = resolve_path({'file': 'ring', 'sideslip': {'ramp_length': 80.0}}, tmp_path, 'long')
    assert long.sideslip.ramp_length == 80.0 and base.sideslip.ramp_length == 45.0
    assert long.sideslip.grip_until == base.sideslip.grip_until == 20.0
    assert long.beta_at(200.0) == pytest.approx(base.beta_at(200.0)) == pytest.approx(
        math.radians(30.0))
    assert long.beta_at(70.0) < base.beta_at(70.0), 'still ramping at 70 m'
    assert np.array_equal(long.K, base.K) and long.name == 'ring'
    with pytest.raises(ParamError,
                       match=r'bad.path \(ring.yaml\).sideslip.ramp_length: must not be negative'):
        resolve_path({'file': 'ring', 'sideslip': {'ramp_length': -1.0}}, tmp_path, 'bad')
    with pytest.raises(ParamError, match='not found'):
        resolve_path({'file': 'nosuch'}, tmp_path, 'nosuch')


def test_planned_sides_flip_where_the_curves_reverse_as_the_curvature_blend_does():
    """On the alternating clothoid the planned flip (20.25 m, centred at the inflection) is the
    selector's curvature blend (|K| < 0.045 over the linear clothoid) to within half a percent."""
    path = P.alternating(15.0, 30.0, 1.0, 1.0)
    band = 0.045
    u = np.clip(0.5 * (1.0 + path.K / band), 0.0, 1.0)
    blend = u * u * (3.0 - 2.0 * u)
    planned = path.with_planned_sides(20.25, 0.01).side
    assert np.max(np.abs(planned - blend)) < 0.005


def test_planned_sides_keep_a_wide_curve_on_its_own_side_and_flip_mid_straight():
    k = 1.0 / 15.0
    segs = [(40.0, k, k),              # left R 15
            (20.0, 0.0, 0.0),          # straight between two left curves: stays left
            (40.0, k, k),
            (10.0, k, -1.0 / 35.0),    # into a wide right curve (R 35)
            (60.0, -1.0 / 35.0, -1.0 / 35.0),
            (40.0, 0.0, 0.0),          # straight between right and left: flips at its middle
            (40.0, k, k)]
    path = P.from_segments(segs).with_planned_sides(20.0, 0.01)
    side = path.side_at
    assert side(20.0) == 1.0 and side(50.0) == 1.0             # no flip on the first straight
    assert side(140.0) == 0.0                                   # the wide right curve is right
    mid = 40.0 + 20.0 + 40.0 + 10.0 + 60.0 + 20.0               # the second straight's middle
    assert side(mid) == pytest.approx(0.5, abs=0.01)
    assert side(mid - 10.5) == 0.0 and side(mid + 10.5) == 1.0
    mirrored = path.mirrored()
    assert mirrored.side_at(140.0) == 1.0
    with pytest.raises(ParamError, match='closer than flip_length'):
        P.from_segments(segs).with_planned_sides(120.0, 0.01)


def test_a_closed_figure8_flips_once_at_each_crossing_even_across_the_seam():
    path = P.figure8(R, 30.0).with_planned_sides(20.0, 0.01)
    half = path.length / 2.0
    assert path.side_at(0.0) == pytest.approx(0.5, abs=0.01)      # the crossing at the seam
    assert path.side_at(half) == pytest.approx(0.5, abs=0.01)
    assert path.side_at(0.5 * half) == 1.0 and path.side_at(1.5 * half) == 0.0


def test_flip_length_is_read_from_the_path_file():
    raw = {'type': 'alternating', 'radius': 15.0, 'transition': 30.0, 'flip_length': 20.0}
    assert P.load_path(raw).side is not None
    assert P.load_path({k: v for k, v in raw.items() if k != 'flip_length'}).side is None
    with pytest.raises(ParamError, match='flip_length'):
        P.load_path({**raw, 'flip_length': -1.0})

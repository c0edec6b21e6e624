"""ReferenceSelector: curvature correction sign, mirroring, clamping, continuity, never NaN."""
import logging
import math
import os
from dataclasses import replace

import numpy as np
import pytest

from drift_control import path as P
from drift_control.params import ParamError, config_dir, from_dict
from drift_control.reference import (ReferenceParams, ReferenceSelector, check_horizon_spacing,
                                     flip_samples, load_reference_params, mirrored_reference)
from drift_control.signals import Direction, Equilibrium, Validity, VehicleState

R = 15.0
A_LAT = 7.0                     # lateral acceleration of the stand-in map [m/s^2]
BETA_RANGE = (0.0, math.radians(45.0))
RADIUS_RANGE = (8.0, 50.0)


def steady_circle_lookup(beta_abs, radius, direction):
    """Analytic stand-in for EquilibriumMap.lookup: a steady circle V = sqrt(a_lat R), r = V/R."""
    assert direction in (Direction.LEFT, Direction.RIGHT), 'the selector picks a side'
    clamped = not (BETA_RANGE[0] <= beta_abs <= BETA_RANGE[1]
                   and RADIUS_RANGE[0] <= radius <= RADIUS_RANGE[1])
    beta_abs = min(max(beta_abs, BETA_RANGE[0]), BETA_RANGE[1])
    radius = min(max(radius, RADIUS_RANGE[0]), RADIUS_RANGE[1])
    d = int(direction)
    V = math.sqrt(A_LAT * radius)
    omega = V / 0.32
    eq = Equilibrium(V=V, beta=-d * beta_abs, r=d * V / radius, omega_F=omega,
                     omega_R=omega * (1.0 + 0.5 * beta_abs), delta=d * (2.7 / radius - beta_abs),
                     T_R=400.0 + 2000.0 * beta_abs)
    return eq, clamped


def params(**over):
    base = dict(k_p=0.01, k_d=0.012, radius_min=RADIUS_RANGE[0], radius_max=RADIUS_RANGE[1],
                horizon_steps=10, horizon_dt=0.02)
    base.update(over)
    return ReferenceParams(**base)


def drift_circle(direction=Direction.LEFT):
    prof = P.SideslipProfile(math.radians(30.0))
    return P.circle(R, direction, sideslip=prof)


def state_on(path, s, e_y=0.0, t=0.0, V=10.0, beta=None, course_error=0.0, **kw):
    """A car at arc length ``s`` [m], ``e_y`` [m] left of the path, velocity along the path."""
    i = int(round(s / path.ds)) % path.n
    psi = path.psi[i]
    if beta is None:
        beta = -math.copysign(math.radians(30.0), path.K[i]) if path.K[i] else 0.0
    x, y = path.x[i] - e_y * math.sin(psi), path.y[i] + e_y * math.cos(psi)
    yaw = psi + course_error - beta
    return VehicleState(stamp=t, V=V, beta=beta, r=V * path.K[i], x=x, y=y, yaw=yaw, **kw)


def mirror_state(st):
    return VehicleState(stamp=st.stamp, V=st.V, beta=-st.beta, r=-st.r, x=st.x, y=-st.y,
                        yaw=-st.yaw)


@pytest.mark.parametrize('direction', [Direction.LEFT, Direction.RIGHT])
def test_car_outside_the_circle_gets_a_tighter_curvature(direction):
    path = drift_circle(direction)
    outside = -int(direction) * 2.0            # left of a CCW circle is inside
    refs = {}
    for name, e_y in (('on', 0.0), ('outside', outside), ('inside', -outside)):
        sel = ReferenceSelector(steady_circle_lookup, path, params())
        refs[name] = sel.select(state_on(path, 30.0, e_y))
    on, out, inn = refs['on'], refs['outside'], refs['inside']
    assert on.curvature_cmd == pytest.approx(int(direction) / R)
    assert abs(out.curvature_cmd) > abs(on.curvature_cmd) > abs(inn.curvature_cmd)
    assert np.sign(out.curvature_cmd) == int(direction)
    radius = lambda ref: ref.target.V / abs(ref.target.r)                       # noqa: E731
    assert radius(out) < R < radius(inn)
    assert out.direction == direction and out.target.r * int(direction) > 0


def test_course_towards_the_path_damps_the_correction():
    """de_y/dt = V sin(psi + beta) (Eq. 1): heading back to the path reduces the correction."""
    path = drift_circle()
    static = ReferenceSelector(steady_circle_lookup, path, params()).select(
        state_on(path, 30.0, -2.0))
    returning = ReferenceSelector(steady_circle_lookup, path, params()).select(
        state_on(path, 30.0, -2.0, course_error=0.1))   # course turned left: towards the path
    assert returning.curvature_cmd < static.curvature_cmd
    assert returning.heading_error == pytest.approx(0.1 + math.radians(30.0), abs=1e-6)


def test_kinematic_car_following_the_commanded_curvature_converges_to_the_path():
    """A point mass whose course curvature is K_cmd starts 3 m outside: e_y decays, no NaN."""
    path = drift_circle()
    sel = ReferenceSelector(steady_circle_lookup, path, params())
    st = state_on(path, 0.0, -3.0)
    x, y, course, V, dt = st.x, st.y, st.yaw + st.beta, 10.0, 0.02
    e_hist = []
    for k in range(1500):                       # 30 s
        beta = -math.radians(30.0)
        ref = sel.select(VehicleState(stamp=k * dt, V=V, beta=beta, r=V / R, x=x, y=y,
                                      yaw=course - beta))
        assert ref.is_finite()
        e_hist.append(ref.e_y)
        turn = V * ref.curvature_cmd * dt          # exact arc: move along the chord
        x += V * dt * math.cos(course + 0.5 * turn)
        y += V * dt * math.sin(course + 0.5 * turn)
        course += turn
    e = np.abs(e_hist)
    assert e[-250:].max() < 0.05, 'settles on the path'
    assert max(e_hist) < 1.0, 'little overshoot to the inside'
    assert ref.s == pytest.approx(30 * V, rel=0.05) and ref.s > path.length * 3


def test_mirroring_the_path_mirrors_the_reference():
    path = P.alternating(R, 10.0, sideslip=P.SideslipProfile(math.radians(30.0),
                                                            math.radians(2.0), 20.0, 15.0))
    a = ReferenceSelector(steady_circle_lookup, path, params())
    b = ReferenceSelector(steady_circle_lookup, path.mirrored(), params())
    rng = np.random.default_rng(1)
    for k, s in enumerate(np.arange(0.0, path.length, 0.25)):
        st = state_on(path, s, e_y=rng.normal(0, 0.5), t=0.02 * k)
        ra, rb = a.select(st), b.select(mirror_state(st))
        expect = mirrored_reference(ra)
        assert rb.direction == expect.direction
        assert rb.s == pytest.approx(expect.s, abs=1e-9)
        for field in ('curvature', 'curvature_cmd', 'e_y', 'heading_error'):
            assert getattr(rb, field) == pytest.approx(getattr(expect, field), abs=1e-9)
        for eb, ee in zip((rb.target,) + rb.horizon, (expect.target,) + expect.horizon):
            assert np.array(list(vars(eb).values())) == pytest.approx(
                np.array(list(vars(ee).values())), abs=1e-9)


def test_out_of_map_references_clamp_with_a_rate_limited_warning(caplog):
    tight = P.circle(5.0, sideslip=P.SideslipProfile(math.radians(60.0)))   # both off the map
    sel = ReferenceSelector(steady_circle_lookup, tight, params(warn_interval=60.0))
    with caplog.at_level(logging.WARNING, logger='drift_control.reference'):
        refs = [sel.select(state_on(tight, 0.1 * k, t=0.02 * k)) for k in range(100)]
    assert all(r.clamped and r.is_finite() for r in refs)
    assert abs(refs[-1].curvature_cmd) <= 1.0 / RADIUS_RANGE[0] + 1e-12
    assert abs(refs[-1].target.beta) <= BETA_RANGE[1]
    warnings = [r for r in caplog.records if 'clamped' in r.getMessage()]
    assert len(warnings) == 1, 'warned once per interval, not once per call'


def test_non_finite_or_poseless_state_keeps_the_last_reference(caplog):
    path = drift_circle()
    sel = ReferenceSelector(steady_circle_lookup, path, params())
    assert sel.select(VehicleState(stamp=0.0, V=math.nan, beta=0.0, r=0.0)) is None
    good = sel.select(state_on(path, 10.0, t=0.02))
    bad = state_on(path, 10.5, t=0.04)
    for broken in (VehicleState(**{**vars(bad), 'x': math.nan}),
                   VehicleState(**{**vars(bad), 'beta': math.inf}),
                   VehicleState(**{**vars(bad), 'validity': int(Validity.ALL & ~Validity.POSE)})):
        assert sel.select(broken) is good
    assert sel.rejected == 4
    assert sel.select(bad).s == pytest.approx(10.5, abs=0.06)


def test_lookup_returning_nan_never_reaches_the_reference():
    path = drift_circle()
    calls = {'n': 0}

    def flaky(beta_abs, radius, direction):
        calls['n'] += 1
        eq, c = steady_circle_lookup(beta_abs, radius, direction)
        return (Equilibrium(*(math.nan,) * 7), c) if calls['n'] > 10 else (eq, c)

    sel = ReferenceSelector(flaky, path, params(horizon_steps=0))
    refs = [sel.select(state_on(path, s, t=0.02 * k)) for k, s in enumerate(range(20))]
    assert all(r.is_finite() for r in refs)
    assert refs[-1] is refs[9]


@pytest.mark.parametrize('transition', [10.0, 0.0])
def test_left_right_transition_is_continuous(transition):
    """Along the alternating manoeuvre at 50 Hz the reference moves a bounded amount per step."""
    prof = P.SideslipProfile(math.radians(30.0), math.radians(2.0), 20.0, 15.0)
    path = P.alternating(R, transition, sideslip=prof)
    p = params(course_yaw=False)     # the equilibria themselves; course_yaw: its own test
    sel = ReferenceSelector(steady_circle_lookup, path, p)
    V, dt = 10.0, 0.02
    refs = [sel.select(state_on(path, s, t=k * dt)) for k, s in
            enumerate(np.arange(0.0, path.length - 1.0, V * dt))]
    K = np.array([r.curvature_cmd for r in refs])
    beta = np.array([r.target.beta for r in refs])
    yaw_rate = np.array([r.target.r for r in refs])
    assert np.abs(np.diff(K)).max() <= p.curvature_rate_max * dt + 1e-12
    # beta = (2 w - 1) beta_abs: w and beta_abs are both rate-limited
    dbeta_max = 2 * math.radians(30.0) * p.side_rate_max * dt + p.beta_rate_max * dt
    assert np.abs(np.diff(beta)).max() <= dbeta_max * 1.001
    # r = (2 w - 1) r_eq(K): the weight's rate plus the map's slope times the curvature rate
    Ks = np.linspace(1 / p.radius_max, 1 / p.radius_min, 200)
    r_eq = [steady_circle_lookup(0.5, 1 / k, Direction.LEFT)[0].r for k in Ks]
    slope = np.abs(np.diff(r_eq) / np.diff(Ks)).max()
    dr_max = 2 * max(r_eq) * p.side_rate_max * dt + slope * p.curvature_rate_max * dt
    assert np.abs(np.diff(yaw_rate)).max() <= dr_max * 1.001
    dirs = [int(r.direction) for r in refs]
    assert dirs[0] == 1 and dirs[-1] == -1, 'left to right'
    assert dirs.count(0) >= 1.0 / p.side_rate_max / dt - 1, 'the flip takes 1/side_rate_max'
    assert all(np.diff([d for d in dirs if d]) <= 0), 'one flip, no chatter'
    assert beta[0] == pytest.approx(-math.radians(2.0)) and beta[-1] == pytest.approx(
        math.radians(30.0))


def test_horizon_sees_the_transition_coming():
    prof = P.SideslipProfile(math.radians(30.0))
    path = P.alternating(R, 10.0, laps_first=1.0, sideslip=prof)
    sel = ReferenceSelector(steady_circle_lookup, path, params(horizon_steps=25,
                                                               horizon_dt=0.04,
                                                               course_yaw=False))
    s_flip = 2 * math.pi * R + 5.0
    ref = sel.select(state_on(path, s_flip - 6.0, V=10.0))
    assert len(ref.horizon) == 25 and ref.horizon[0] == ref.target
    assert ref.target.r > 0 and ref.horizon[-1].r < 0, 'the last stages already drift right'
    assert np.all(np.diff([e.r for e in ref.horizon]) <= 1e-12), 'monotone towards the right'
    # the path's own curvature at the same stages: the circle's, then the straight's
    s_k = ref.s + 10.0 * 0.04 * np.arange(25)
    assert ref.horizon_curvature == pytest.approx(path.curvature_at(s_k).tolist())
    assert ref.horizon_curvature[0] == pytest.approx(1.0 / R) and ref.horizon_curvature[-1] < 0


def test_horizon_spacing_must_match_the_nmpc_stages():
    """A horizon spaced unlike the NMPC's stages is a ParamError naming the key."""
    check_horizon_spacing(params(horizon_steps=25, horizon_dt=0.03), 0.03)
    check_horizon_spacing(params(horizon_steps=0, horizon_dt=0.02), 0.03)   # no horizon
    with pytest.raises(ParamError, match='reference.horizon_dt'):
        check_horizon_spacing(params(horizon_steps=25, horizon_dt=0.02), 0.03)


def constant_speed_lookup(beta_abs, radius, direction):
    """Equilibria all at 10 m/s: yaw rate V / R, sideslip -direction * beta_abs."""
    eq, clamped = steady_circle_lookup(beta_abs, radius, direction)
    radius = min(max(radius, RADIUS_RANGE[0]), RADIUS_RANGE[1])
    return replace(eq, V=10.0, r=int(direction) * 10.0 / radius), clamped


def _course_error_deg(refs, V, dt):
    """How far the course (psi + beta) of a car that follows ``refs`` exactly has turned away
    from the path's heading, per sample [deg]."""
    yaw = np.cumsum([0.0] + [r.target.r * dt for r in refs[:-1]])
    course = yaw + np.array([r.target.beta for r in refs])
    path_heading = np.cumsum([0.0] + [r.curvature * V * dt for r in refs[:-1]])
    return np.degrees(np.abs((course - course[0]) - path_heading))


@pytest.mark.parametrize('course_yaw, course_error_max_deg', [(True, 3.0), (False, None)])
def test_course_yaw_keeps_the_velocity_direction_turning_with_the_path(course_yaw,
                                                                     course_error_max_deg):
    """A car that follows the references exactly (yaw rate r_ref, sideslip beta_ref) through
    the left -> right flip at 10 m/s: its course psi + beta must turn as the path does.

    Without the correction the course turns by the whole sideslip change (60 deg) too far.
    """
    prof = P.SideslipProfile(math.radians(30.0))
    path = P.alternating(R, 30.0, laps_first=1.0, sideslip=prof)
    p = params(horizon_steps=25, course_yaw=course_yaw, side_band=0.045, radius_max=40.0)
    sel = ReferenceSelector(constant_speed_lookup, path, p)
    V, dt = 10.0, 0.02
    s0 = 2 * math.pi * R - 20.0          # settled left drift, before the clothoid
    refs = [sel.select(state_on(path, s, t=k * dt)) for k, s in
            enumerate(np.arange(s0, s0 + 60.0, V * dt))]
    assert refs[0].direction == Direction.LEFT and refs[-1].direction == Direction.RIGHT
    error = _course_error_deg(refs, V, dt)
    if course_error_max_deg is not None:
        assert error.max() < course_error_max_deg
    else:
        assert error[-1] == pytest.approx(60.0, abs=3.0)


@pytest.mark.parametrize('entry, course_error_max_deg', [(True, 3.0), (False, None)])
def test_course_yaw_in_the_entry_is_an_option(entry, course_error_max_deg):
    """The entry ramp (0 -> 30 deg over 30 m of the R = 15 m circle at 10 m/s), the references
    followed exactly: with ``course_yaw_entry`` the course turns with the path; without it the
    course falls behind by the whole sideslip ramp."""
    prof = P.SideslipProfile(math.radians(30.0), grip_until=10.0, ramp_length=30.0)
    path = P.circle(R, sideslip=prof)
    p = params(horizon_steps=25, course_yaw=True, course_yaw_entry=entry, radius_max=40.0)
    sel = ReferenceSelector(constant_speed_lookup, path, p)
    V, dt = 10.0, 0.02
    refs = [sel.select(state_on(path, s, t=k * dt)) for k, s in
            enumerate(np.arange(0.0, 50.0, V * dt))]
    assert refs[-1].target.beta == pytest.approx(-math.radians(30.0))
    error = _course_error_deg(refs, V, dt)
    if course_error_max_deg is not None:
        assert error.max() < course_error_max_deg
    else:
        assert error[-1] == pytest.approx(30.0, abs=3.0)


def test_lateral_correction_does_not_flip_the_drift_side():
    """Mid-clothoid, where the path still curves left, a car 3 m right of the path (a large
    correction to the left) and one 3 m left (to the right) both keep the path's side."""
    prof = P.SideslipProfile(math.radians(30.0))
    path = P.alternating(R, 30.0, laps_first=1.0, sideslip=prof)
    p = params(horizon_steps=0, side_band=0.045, radius_max=40.0, correction_limit=0.05)
    s = 2 * math.pi * R + 10.0            # K(s) = +1/45: left, inside the blend band
    sides = []
    for e_y in (-3.0, 0.0, 3.0):
        sel = ReferenceSelector(steady_circle_lookup, path, p)
        sel.reset(s_hint=s)          # the path passes near itself: project locally
        ref = sel.select(state_on(path, s, e_y))
        assert (ref.curvature_cmd - ref.curvature) * e_y <= -0.01 * abs(e_y), 'towards the path'
        sides.append(ref.target.beta)
    assert sides[0] == pytest.approx(sides[1]) and sides[2] == pytest.approx(sides[1])
    assert sides[1] < 0.0, 'still (mostly) the left drift'


def test_params_file_loads_and_bad_keys_are_named():
    p = load_reference_params(os.path.join(config_dir(), 'reference.yaml'))
    assert p.k_p > 0 and p.radius_min < p.radius_max
    with pytest.raises(ParamError, match='k_pp'):
        from_dict(ReferenceParams, {'k_pp': 1.0, 'k_d': 0.0, 'radius_min': 8.0,
                                    'radius_max': 50.0}, 'reference')
    with pytest.raises(ParamError, match='radius_min'):
        params(radius_min=60.0)
    with pytest.raises(ParamError, match='k_d'):
        params(k_d=-1.0)
    with pytest.raises(ParamError, match='flip_radius_max'):
        params(flip_radius_max=4.0)     # narrower than the map's tightest curve


def _drive(sel, path, s0, e0, V, seconds, dt=0.02):
    """Kinematic car whose course curvature is K_cmd (exact arcs); returns the e_y history."""
    st = state_on(path, s0, e0)
    x, y, course = st.x, st.y, st.yaw + st.beta
    e_hist = []
    for k in range(int(seconds / dt)):
        beta = -math.copysign(0.5, path.curvature_at(s0 + V * k * dt) or 1.0)
        ref = sel.select(VehicleState(stamp=k * dt, V=V, beta=beta, r=0.0, x=x, y=y,
                                      yaw=course - beta))
        assert ref is not None and ref.is_finite()
        e_hist.append(ref.e_y)
        turn = V * ref.curvature_cmd * dt
        x += V * dt * math.cos(course + 0.5 * turn)
        y += V * dt * math.sin(course + 0.5 * turn)
        course += turn
    return np.array(e_hist)


@pytest.mark.parametrize('V', [8.0, 12.0])
def test_kinematic_car_keeps_the_figure8_through_its_transitions(V):
    path = P.figure8(R, 10.0, sideslip=P.SideslipProfile(math.radians(30.0)))
    sel = ReferenceSelector(steady_circle_lookup, path, params())
    e = _drive(sel, path, 20.0, -2.0, V, 40.0)
    assert np.abs(e[500:]).max() < 0.15, 'left<->right transitions cost < 15 cm'
    assert sel.frenet.global_searches == 1


def test_integral_action_does_not_wind_up_while_saturated():
    path = drift_circle()
    p = params(k_i=0.01, integral_limit=100.0, correction_limit=0.01)
    sel = ReferenceSelector(steady_circle_lookup, path, p)
    for k in range(500):                                   # 10 s held 4 m outside: saturated
        ref = sel.select(state_on(path, 0.2 * k, -4.0, t=0.02 * k))
        assert ref.curvature_cmd == pytest.approx(1 / R + p.correction_limit)
    back = [sel.select(state_on(path, 100.0 + 0.2 * k, 0.0, t=10.0 + 0.02 * k))
            for k in range(10)]
    # without anti-windup int e_y dt = -40 m s and k_i * 40 = 0.4 1/m would hold the limit
    assert back[-1].curvature_cmd == pytest.approx(1 / R, abs=2e-3)


def test_start_hint_resolves_an_overlapping_open_path():
    """The alternating path's second circle passes by its start: a hint picks the first pass."""
    path = P.alternating(R, 10.0, laps_second=3.0)
    st = state_on(path, 1.0, -3.0)
    sel = ReferenceSelector(steady_circle_lookup, path, params())
    assert sel.select(st).s > 100.0, 'globally the right circle is nearer'
    sel.reset(s_hint=0.0)
    assert sel.select(st).s == pytest.approx(1.0, abs=0.06)


@pytest.mark.parametrize('side', [1.0, -1.0])
def test_a_car_beside_a_straight_in_grip_is_steered_back(side):
    """On a straight the left and right references are blended; in grip the side follows the
    corrected curvature, so a car left of the path gets a right-turning yaw rate (and the
    mirror image), where the path's own side (zero curvature) would cancel to r = 0."""
    straight = P.from_segments([(200.0, 0.0, 0.0)], sideslip=P.SideslipProfile(0.0))
    sel = ReferenceSelector(steady_circle_lookup, straight, params())
    ref = sel.select(state_on(straight, 50.0, e_y=side * 2.0, beta=0.0))
    assert ref.curvature_cmd * side < 0.0
    assert ref.target.r * side < 0.0 and all(e.r * side < 0.0 for e in ref.horizon)
    on_path = ReferenceSelector(steady_circle_lookup, straight, params()).select(
        state_on(straight, 50.0, beta=0.0))
    assert on_path.target.r == pytest.approx(0.0, abs=1e-12)
    # drifting, the side stays the path's: the correction cannot flip the drift
    drifting = P.from_segments([(200.0, 0.0, 0.0)],
                               sideslip=P.SideslipProfile(math.radians(30.0)))
    ref = ReferenceSelector(steady_circle_lookup, drifting, params()).select(
        state_on(drifting, 50.0, e_y=side * 2.0, beta=0.0))
    assert ref.target.r == pytest.approx(0.0, abs=1e-12)


def test_a_drift_on_a_wide_curve_is_on_its_planned_side():
    """A 35 m right curve is inside the curvature blend (|K| < 0.045): without a plan its
    reference is a blend of left and right, with planned sides (flip_length) a right drift."""
    k = 1.0 / 15.0
    segs = [(60.0, k, k), (20.0, k, -1.0 / 35.0), (120.0, -1.0 / 35.0, -1.0 / 35.0)]
    prof = P.SideslipProfile(math.radians(30.0))
    for planned, direction in ((False, Direction.NONE), (True, Direction.RIGHT)):
        path = P.from_segments(segs, sideslip=prof)
        path = path.with_planned_sides(20.0, 0.01) if planned else path
        sel = ReferenceSelector(steady_circle_lookup, path, params(side_band=0.045))
        sel.reset(s_hint=140.0)
        ref = sel.select(state_on(path, 140.0))
        assert ref.direction == direction
    assert ref.target.beta > 0.0 and ref.target.r < 0.0   # right: beta > 0, turning clockwise


@pytest.mark.parametrize('direction', [Direction.LEFT, Direction.RIGHT])
def test_a_slide_in_the_entry_is_caught_latched_capped_and_lapses_after_it(direction):
    """A car that slides before the entry ramp asks for it gets a reference that continues from
    its slide (not a pull back to grip); the floor holds while the slide eases, never exceeds the
    drift sideslip and ends with the entry."""
    prof = P.SideslipProfile(math.radians(30.0), grip_until=20.0, ramp_length=40.0)
    path = P.circle(R, direction, sideslip=prof)
    d = int(direction)
    sel = ReferenceSelector(steady_circle_lookup, path, params(catch_beta=math.radians(8.0)))
    beta_ref = []
    for k, (s, slide_deg) in enumerate([(2.0, 1.0), (4.0, 5.0), (6.0, 15.0), (8.0, 12.0),
                                        (10.0, 45.0), (12.0, 20.0), (70.0, 20.0)]):
        st = state_on(path, s, t=0.5 * k, beta=-d * math.radians(slide_deg))
        beta_ref.append(math.degrees(-d * sel.select(st).target.beta))
    assert beta_ref[:2] == pytest.approx([0.0, 0.0])         # grip, and slides within grip
    assert beta_ref[2] == pytest.approx(15.0)                  # caught
    assert beta_ref[3] == pytest.approx(15.0)                  # latched while the slide eases
    assert beta_ref[4] == pytest.approx(30.0)                  # at most the drift sideslip
    assert beta_ref[5] == pytest.approx(30.0)
    assert beta_ref[6] == pytest.approx(30.0)                  # after the entry: the profile
    ref = sel.select(state_on(path, 10.0, t=10.0, beta=-d * math.radians(20.0)))
    assert all(abs(eq.beta) >= abs(ref.target.beta) - 1e-9 for eq in ref.horizon)


def test_a_slide_to_the_other_side_or_with_the_catch_off_is_not_caught():
    prof = P.SideslipProfile(math.radians(30.0), grip_until=20.0, ramp_length=40.0)
    path = P.circle(R, Direction.LEFT, sideslip=prof)
    for over, beta_deg in (({'catch_beta': math.radians(8.0)}, 15.0), ({}, -15.0)):
        sel = ReferenceSelector(steady_circle_lookup, path, params(**over))
        for k in range(3):
            ref = sel.select(state_on(path, 2.0 + k, t=0.5 * k, beta=math.radians(beta_deg)))
        assert ref.target.beta == pytest.approx(0.0)


def test_a_caught_slide_follows_a_profile_that_falls_within_the_entry():
    """The caught floor is at most the drift sideslip at each ``s``: a profile falling from 35
    to 20 deg inside the entry lowers it, and the entry ends without a step (it held 24.5 deg to
    the entry's end and then fell 4.5 deg at the rate limit: a wet run braked and lost the path)."""
    knots = tuple((s, math.radians(b)) for s, b in ((0.0, 35.0), (30.0, 35.0), (45.0, 20.0),
                                                   (80.0, 20.0)))
    prof = P.SideslipProfile(0.0, grip_until=5.0, ramp_length=60.0, knots=knots)
    path = P.circle(R, Direction.LEFT, sideslip=prof)
    sel = ReferenceSelector(steady_circle_lookup, path, params(catch_beta=math.radians(8.0),
                                                               beta_rate_max=100.0))
    beta_ref, drift = [], []
    sel.select(state_on(path, 15.0, t=-0.5))   # the side is known from the first cycle on
    for k, (s, slide_deg) in enumerate([(20.0, 26.0), (40.0, 26.0), (50.0, 21.0), (60.0, 20.0),
                                        (70.0, 20.0)]):
        ref = sel.select(state_on(path, s, t=0.5 * k, beta=-math.radians(slide_deg)))
        beta_ref.append(math.degrees(-ref.target.beta))
        drift.append(math.degrees(float(path.drift_beta_at(s))))
    assert beta_ref[0] == pytest.approx(26.0)                   # caught below the 35 deg ahead
    assert beta_ref[1] == pytest.approx(drift[1], abs=0.05)     # capped by the falling profile
    assert all(b <= d + 0.05 for b, d in zip(beta_ref, drift)), (beta_ref, drift)
    assert beta_ref[-1] == pytest.approx(20.0)                  # after the entry: the profile


@pytest.mark.parametrize('direction', [Direction.LEFT, Direction.RIGHT])
def test_the_entry_reference_leads_the_cars_own_sideslip_by_at_most_entry_lead(direction):
    """A car that does not slide as the ramp asks: the entry's sideslip reference stays within
    ``entry_lead`` of its sideslip to the drift side; after the entry, the path's again."""
    prof = P.SideslipProfile(math.radians(30.0), grip_until=0.0, ramp_length=40.0)
    path = P.circle(R, direction, sideslip=prof)
    d = int(direction)
    sel = ReferenceSelector(steady_circle_lookup, path, params(entry_lead=math.radians(10.0),
                                                               beta_rate_max=100.0))
    beta_ref = []
    for k, (s, slide_deg) in enumerate([(1.0, 0.0), (30.0, 0.0), (32.0, 12.0), (34.0, -5.0),
                                        (70.0, 0.0)]):
        st = state_on(path, s, t=0.5 * k, beta=-d * math.radians(slide_deg))
        beta_ref.append(math.degrees(-d * sel.select(st).target.beta))
    path_deg = [math.degrees(float(path.beta_at(s))) for s in (1.0, 30.0, 32.0, 34.0, 70.0)]
    assert beta_ref[0] == pytest.approx(path_deg[0], abs=0.01)   # the ramp starts below the lead
    assert beta_ref[1] == pytest.approx(10.0)               # the ramp asks 25 deg, the car 0
    assert beta_ref[2] == pytest.approx(22.0)               # the car slides: the lead follows
    assert beta_ref[3] == pytest.approx(10.0)               # sliding the other way counts as 0
    assert beta_ref[4] == pytest.approx(30.0)               # after the entry: the profile
    off = ReferenceSelector(steady_circle_lookup, path, params(beta_rate_max=100.0))
    ref = off.select(state_on(path, 30.0, t=0.0))
    assert math.degrees(abs(ref.target.beta)) == pytest.approx(path_deg[1], abs=0.05), 'off'


def exit_path():
    """A left drift circle leaving through a clothoid onto a straight, the sideslip falling
    from 30 to 0 deg along the clothoid (no entry ramp: the drift is established)."""
    k = 1.0 / R
    prof = P.SideslipProfile(0.0, knots=((0.0, math.radians(30.0)), (90.0, math.radians(30.0)),
                                         (110.0, 0.0), (300.0, 0.0)))
    return P.from_segments([(90.0, k, k), (20.0, k, 0.0), (190.0, 0.0, 0.0)], sideslip=prof)


def test_leaving_a_drift_the_yaw_rate_unwinds_the_sideslip_and_the_speed_rises_gently():
    """While the sideslip reference falls the yaw rate carries -d(beta_ref)/dt, as in a flip
    (else the course turns by the whole 30 deg); the speed reference rises at most
    speed_rise_max toward the straight's grip speed (the stand-in map: 10.2 -> 18.7 m/s)."""
    path = exit_path()
    for rise in (0.0, 2.0):
        sel = ReferenceSelector(steady_circle_lookup, path, params(speed_rise_max=rise))
        V_prev, t = None, 0.0
        for s in np.arange(80.0, 115.0, 0.2):
            beta_ref = float(path.beta_at(s))
            ref = sel.select(state_on(path, s, t=t, beta=-beta_ref))
            if s == pytest.approx(100.0):   # mid-unwinding: 30 deg in 20 m at 10 m/s, 0.26 rad/s
                assert ref.target.r < float(path.curvature_at(s)) * ref.target.V - 0.2
            if rise:
                V_stages = [e.V for e in ref.horizon]
                assert np.all(np.diff(V_stages) <= rise * 0.02 + 1e-9)
                if V_prev is not None:
                    assert ref.target.V <= V_prev + rise * 0.02 + 1e-9
            V_prev, t = ref.target.V, t + 0.02
        assert (ref.target.V < math.sqrt(A_LAT * RADIUS_RANGE[1]) - 3.0) == (rise > 0.0)


def test_a_steady_drift_is_not_touched_by_the_speed_rise_limit():
    path = drift_circle()
    plain = ReferenceSelector(steady_circle_lookup, path, params())
    limited = ReferenceSelector(steady_circle_lookup, path, params(speed_rise_max=2.0))
    for k in range(50):
        st = state_on(path, 30.0 + 0.2 * k, e_y=0.3 * math.sin(k), t=0.02 * k)
        assert limited.select(st) == plain.select(st)


def curve_change(R_from, R_to, length=150.0):
    """A 30 deg left drift (established, no entry ramp) on an R_from arc, a 10 m clothoid, then
    an R_to arc."""
    prof = P.SideslipProfile(math.radians(30.0))
    k0, k1 = 1.0 / R_from, 1.0 / R_to
    return P.from_segments([(length, k0, k0), (10.0, k0, k1), (150.0, k1, k1)], sideslip=prof)


def test_ahead_of_a_tighter_curve_the_speed_falls_at_drift_speed_fall_along_the_path():
    """The stand-in map drifts R 40 m at 16.7 m/s and R 10 m at 8.4 m/s: the plan asks for
    the tighter curve's speed from as far back as ``drift_speed_fall`` needs (v^2 = v_1^2 +
    2 a d), the same turn driven slower (radius and sideslip kept); far before it and on it
    the map's own speed."""
    path, fall = curve_change(40.0, 10.0), 1.5
    plain = ReferenceSelector(steady_circle_lookup, path, params())
    planned = ReferenceSelector(steady_circle_lookup, path, params(drift_speed_fall=fall))
    V_tight = math.sqrt(A_LAT * 10.0)
    for k, s in enumerate(np.arange(0.0, 200.2, 0.2)):
        st = state_on(path, s, t=0.02 * k)
        a, b = plain.select(st), planned.select(st)
        if not any(s == pytest.approx(x) for x in (20.0, 120.0, 140.0, 148.0, 200.0)):
            continue
        for e, f in zip(a.horizon, b.horizon):
            assert f.V <= e.V + 1e-9
            assert f.r / f.V == pytest.approx(e.r / e.V) and f.beta == e.beta
        to_tight = 160.0 - s   # where the clothoid reaches R 10 m (within its 10 m)
        if s < 50.0 or s > 170.0:
            assert b.target == a.target
        else:
            assert b.target.V < a.target.V
            assert b.target.V ** 2 - V_tight ** 2 == pytest.approx(2 * fall * to_tight, abs=25.0)
            assert np.all(np.diff([e.V for e in b.horizon]) <= 1e-9)


def test_in_a_drift_the_speed_reference_rises_at_most_drift_speed_rise():
    """Onto a wider curve the map asks for its speed at once (8.4 -> 16.7 m/s); the car cannot
    gain it while it holds the sideslip, and at the map's yaw rate it would turn the tight
    radius. The reference rises at most ``drift_speed_rise`` per second and per stage, the same
    turn driven slower."""
    path, rise = curve_change(10.0, 40.0, length=40.0), 1.0
    sel = ReferenceSelector(steady_circle_lookup, path, params(drift_speed_rise=rise))
    V_prev = None
    for k, s in enumerate(np.arange(30.0, 110.0, 0.2)):
        ref = sel.select(state_on(path, s, t=0.02 * k, V=8.4))
        stages = ref.horizon
        assert np.all(np.diff([e.V for e in stages]) <= rise * 0.02 + 1e-9)
        assert all(e.r / e.V == pytest.approx(float(path.curvature_at(s)), abs=0.02)
                   for e in stages[:1])
        if V_prev is not None:
            assert ref.target.V <= V_prev + rise * 0.02 + 1e-9
        V_prev = ref.target.V
    assert V_prev < math.sqrt(A_LAT * 10.0) + rise * 0.02 * k + 1e-6 < math.sqrt(A_LAT * 40.0)


def test_a_reference_seen_later_moves_its_horizon_on():
    """Reference.at: a reference selected for an older state, seen ``age`` later, starts its
    stages that much further on (linear between stages, the last held); at its own time it is
    itself."""
    from drift_control.signals import Reference
    stages = tuple(Equilibrium(V=10.0 + k, beta=-0.1 * k, r=0.5, omega_F=30.0, omega_R=40.0 + k,
                               delta=0.01 * k, T_R=1000.0 + 100.0 * k) for k in range(4))
    ref = Reference(stamp=2.0, target=stages[0], direction=Direction.LEFT, horizon=stages, s=7.0,
                    horizon_curvature=(0.01, 0.02, 0.04, 0.04))
    assert ref.at(2.0, 0.03) is ref and ref.at(1.99, 0.03) is ref
    assert replace(ref, horizon=()).at(2.5, 0.03).target == stages[0]
    whole = ref.at(2.03, 0.03)   # one stage later: stages 1, 2, 3, 3
    assert [e.V for e in whole.horizon] == pytest.approx([11.0, 12.0, 13.0, 13.0])
    assert whole.horizon_curvature == pytest.approx([0.02, 0.04, 0.04, 0.04])
    assert whole.target == whole.horizon[0] and whole.stamp == 2.0 and whole.s == 7.0
    part = ref.at(2.02, 0.03)    # two thirds of a stage: every field between its neighbours
    first = part.horizon[0]
    for name in ('V', 'beta', 'omega_R', 'delta', 'T_R'):
        a, b = getattr(stages[0], name), getattr(stages[1], name)
        assert getattr(first, name) == pytest.approx(a + 2.0 / 3.0 * (b - a)), name
    assert part.horizon[-1] == stages[-1]
    assert part.horizon_curvature[0] == pytest.approx(0.01 + 2.0 / 3.0 * 0.01)
    assert ref.at(2.5, 0.03).horizon == (stages[-1],) * 4   # past its end: the last held


def test_a_blended_lookup_stays_within_the_flip_radius():
    """A map that reaches wide curves: a steady drift there is looked up at its radius, but
    left and right blended (a flip, where the path straightens) at most at ``flip_radius_max``,
    so the flip asks for no faster drift than before the map reached that far."""
    sel = ReferenceSelector(steady_circle_lookup, drift_circle(), params(flip_radius_max=20.0))
    wide, _, _ = sel.equilibrium(0.5, 1.0 / 45.0, 1.0)
    assert wide.V == pytest.approx(math.sqrt(A_LAT * 45.0))
    mid, direction, _ = sel.equilibrium(0.5, 0.0, 0.5)
    assert direction == Direction.NONE
    assert mid.V == pytest.approx(math.sqrt(A_LAT * 20.0))
    many = ReferenceSelector(steady_circle_lookup, drift_circle(), params(flip_radius_max=20.0),
                             lookup_many=lambda asks: [steady_circle_lookup(*a) for a in asks])
    assert many._equilibria([(0.5, 0.0, 0.5)])[0][0] == mid   # the horizon's lookups too
    off = ReferenceSelector(steady_circle_lookup, drift_circle(), params())
    assert off.equilibrium(0.5, 0.0, 0.5)[0].V == pytest.approx(math.sqrt(A_LAT * 50.0))


def test_only_a_flip_is_looked_up_within_the_flip_radius():
    """The cap is the flip's, between curves of opposite sides: an exit's straight (a curve on
    one side only) blends left and right at the map's largest radius as without the cap."""
    prof = P.SideslipProfile(math.radians(30.0))
    flip, figure8 = P.alternating(R, 30.0, sideslip=prof), P.figure8(R, 30.0, sideslip=prof)
    band = 1.0 / RADIUS_RANGE[1]
    assert flip_samples(flip.K, band, False).any()
    assert not flip_samples(exit_path().K, band, False).any()
    crossings = flip_samples(figure8.K, band, True)   # a closed lap: around the seam too
    assert np.count_nonzero(crossings & ~np.roll(crossings, 1)) == 2, 'both crossings'
    speeds = {}
    for name, path, s in (('flip', flip, 2 * math.pi * R + 10.0), ('exit', exit_path(), 150.0)):
        for cap in (0.0, 20.0):
            sel = ReferenceSelector(steady_circle_lookup, path, params(flip_radius_max=cap),
                                    lookup_many=lambda asks: [steady_circle_lookup(*a)
                                                              for a in asks])
            ref = sel.select(state_on(path, s, beta=0.0))
            speeds[name, cap] = [e.V for e in ref.horizon]
    assert speeds['exit', 20.0] == speeds['exit', 0.0]
    assert min(np.subtract(speeds['flip', 20.0], speeds['flip', 0.0])) < -1.0

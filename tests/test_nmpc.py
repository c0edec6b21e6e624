"""NMPC: closed loop to a drift equilibrium, bounds, failure handling, torque-only mode, solvers."""
import dataclasses
import math
import shutil

import casadi as ca
import numpy as np
import pytest

from drift_control.equilibrium import solve_equilibrium
from drift_control.nmpc import Nmpc, NmpcStatus, _shift_rows, reference_rows
from drift_control.ocp import (NPATH, NS, NXO, S_E_Y, S_K, NmpcParams, Ocp, SolverParams,
                               load_nmpc_params)
from drift_control.params import ParamError, load_surface, load_vehicle
from drift_control.signals import Direction, Equilibrium, Mode, Reference, Validity, VehicleState
from drift_control.tyre import simple_peak_slip
from drift_control.vehicle import NU, X, VehicleModel, front_axle_course

TS = 0.02


@pytest.fixture(scope='module')
def params():
    return load_nmpc_params()


@pytest.fixture(scope='module')
def plant(vp):
    """The full model (dynamic front wheel) at 1 ms RK4 steps as the plant, 10 ms per call."""
    return VehicleModel(vp).discrete(TS / 2, 10)


def measure(x, now, rng=None, noise=0.0, **kw):
    """The state as measured; without noise still never bit-identical twice (a sensor that is
    would be frozen: drift_control.plausibility)."""
    n = (lambda: rng.normal(0.0, noise)) if rng is not None else (lambda: 0.0)
    V = x[0] + 1e-9 * math.sin(1e3 * now)
    return VehicleState(stamp=now, V=V + n(), beta=x[1] + n(), r=x[2] + n(),
                        wheel_speeds=(x[3], x[3], x[4], x[4]), delta=x[5], **kw)


def perturbed_start(eq: Equilibrium) -> np.ndarray:
    x = np.zeros(9)
    x[:6] = [0.95 * eq.V, eq.beta + 0.1, 0.8 * eq.r, eq.omega_F, 0.95 * eq.omega_R,
             eq.delta + 0.05]
    return x


def run_loop(ctrl: Nmpc, plant, eq, x, seconds, mu_plant, seed=0, driver=None,
             powertrain=False):
    """Closed loop; returns states (n, 9) and results. ``driver(x)`` steers in TORQUE_ONLY.

    ``powertrain``: the torque reaches the wheels 30 ms late and through an 80 ms lag.
    """
    rng = np.random.default_rng(seed)
    ctrl.reset()
    xs, results = [], []
    pipe, torque = [eq.T_R] * (3 if powertrain else 0), eq.T_R
    for k in range(int(round(seconds / TS))):
        now = k * TS
        res = ctrl.step(measure(x, now, rng, 0.003), Reference(now, eq, Direction.LEFT), now)
        rate = driver(x) if driver else res.command.delta_rate
        for _ in range(2):
            pipe.append(res.command.drive_torque)
            torque = torque + (1 - math.exp(-0.01 / 0.08)) * (pipe.pop(0) - torque) \
                if powertrain else pipe.pop(0)
            x = np.asarray(plant(x, [rate, torque], [0.0, mu_plant])).ravel()
        xs.append(x)
        results.append(res)
    return np.array(xs), results


def assert_within_bounds(ctrl: Nmpc, commands):
    b = ctrl.bounds
    for c in commands:
        values = (c.delta, c.delta_rate, c.drive_torque)
        assert all(math.isfinite(v) for v in values), c
        assert abs(c.delta) <= b.delta_max + 1e-9, c
        assert abs(c.delta_rate) <= b.delta_dot_max + 1e-9, c
        assert b.T_R_min - 1e-6 <= c.drive_torque <= b.T_R_max + 1e-6, c


# --- parameters --------------------------------------------------------------------------------

def test_yaml_bad_key_is_named(tmp_path):
    bad = tmp_path / 'nmpc.yaml'
    bad.write_text('N: 25\ncost: {beta: 0.01, betta: 0.02}\n')
    with pytest.raises(ParamError, match='betta'):
        load_nmpc_params(bad)
    bad.write_text('solver: {method: acado}\n')
    with pytest.raises(ParamError, match='solver.method'):
        load_nmpc_params(bad)


def test_tighter_yaml_limits_win(vp):
    p = NmpcParams(limits=dataclasses.replace(NmpcParams().limits, delta_dot_max=0.4))
    ocp = Ocp(vp, p)
    assert ocp.bounds.delta_dot_max == 0.4
    assert ocp.bounds.delta_max == vp.limits.delta_max


# --- closed loop ---------------------------------------------------------------------------------

def test_torque_costs_scale_with_the_cars_torque_range_where_asked(vp):
    """Scales set for the M3's range: a car with a third of it is charged the same per share of
    its range, not a third as much; off (0), every car has the scales in Nm."""
    base = load_nmpc_params()
    assert base.cost.torque_range == 0.0
    gr86 = load_vehicle('gr86')
    b = Ocp(gr86, base).bounds
    assert base.cost.torque(b) == (base.cost.T_R, base.cost.T_R_rate)
    params = dataclasses.replace(base, cost=dataclasses.replace(base.cost, torque_range=7500.0))
    m3 = Ocp(vp, params).bounds
    assert m3.T_R_max - m3.T_R_min == 7500.0
    assert params.cost.torque(m3) == (base.cost.T_R, base.cost.T_R_rate)
    share = (b.T_R_max - b.T_R_min) / 7500.0
    assert share == pytest.approx(2500.0 / 7500.0)
    assert params.cost.torque(b) == pytest.approx((base.cost.T_R * share,
                                                   base.cost.T_R_rate * share))
    with pytest.raises(ParamError, match='torque_range'):
        dataclasses.replace(base.cost, torque_range=-1.0)


def test_closed_loop_converges_to_30deg_drift(nmpc, plant, eq30):
    """Plant: full model, friction 5 % below the NMPC's, measurement noise."""
    xs, results = run_loop(nmpc, plant, eq30, perturbed_start(eq30), 5.0, mu_plant=0.95)
    beta_err = np.degrees(xs[int(3.0 / TS):, 1] - eq30.beta)
    assert np.max(np.abs(beta_err)) < 1.0, f'beta error after 3 s up to {beta_err.max():.2f} deg'
    r_err = xs[int(3.0 / TS):, 2] - eq30.r
    assert np.max(np.abs(r_err)) < 0.03
    assert all(r.status == NmpcStatus.OK for r in results)
    assert_within_bounds(nmpc, [r.command for r in results])
    assert abs(np.mean(beta_err)) < 0.2, 'offset-free: no steady beta offset from the mu error'


def test_model_error_is_learnt_only_in_a_steady_drift(nmpc, plant, eq30):
    """Learnt while holding the drift on a friction error; decays once the reference moves
    (a flip: no side), since a constant error fitted to a transient spoils the prediction."""
    xs, _ = run_loop(nmpc, plant, eq30, perturbed_start(eq30), 3.0, mu_plant=0.95)
    learnt = np.abs(nmpc.model_error).max()
    assert learnt > 1e-4
    x = xs[-1]
    for k in range(25):
        now = 3.0 + k * TS
        res = nmpc.step(measure(x, now), Reference(now, eq30, Direction.NONE), now)
        for _ in range(2):
            x = np.asarray(plant(x, [res.command.delta_rate, res.command.drive_torque],
                                 [0.0, 0.95])).ravel()
    assert np.abs(nmpc.model_error).max() < 0.2 * learnt


def test_a_slow_car_is_not_braked_further_in_a_drift(vp, params, eq30):
    """Below brake_speed_ratio[0] of the reference speed the plan has no braking torque (with a
    driver steering too); at the reference speed or while blending left and right, the full
    bound."""
    ctrl = Nmpc(vp, dataclasses.replace(params, brake_speed_ratio=(0.6, 0.75)))
    slow = np.array(perturbed_start(eq30))
    slow[0], slow[3], slow[4] = 0.5 * eq30.V, 0.5 * eq30.omega_F, 0.5 * eq30.omega_R
    # a reference asking for braking torque: the guard, not the cost, keeps the plan >= 0
    drift = Reference(0.0, dataclasses.replace(eq30, T_R=ctrl.bounds.T_R_min), Direction.LEFT)
    assert ctrl._braking_bound(slow[0], drift) == 0.0
    assert ctrl._braking_bound(0.675 * eq30.V, drift) == pytest.approx(0.5 * ctrl.bounds.T_R_min)
    assert ctrl._braking_bound(eq30.V, drift) == ctrl.bounds.T_R_min
    assert ctrl._braking_bound(slow[0], Reference(0.0, drift.target, Direction.NONE)) is None
    res = ctrl.step(measure(slow, 0.0), drift, 0.0)
    assert res.status == NmpcStatus.OK
    assert res.predicted_inputs[:, 1].min() >= -1e-6
    off = Nmpc(vp, dataclasses.replace(params, brake_speed_ratio=(0.0, 0.0)))
    assert off._braking_bound(slow[0], drift) is None
    torque_only = Nmpc(vp, dataclasses.replace(params, brake_speed_ratio=(0.6, 0.75)),
                       mode=Mode.TORQUE_ONLY)
    assert torque_only._braking_bound(slow[0], drift) == 0.0, 'a driver steering: guarded too'
    assert off.step(measure(slow, 0.0), drift, 0.0).predicted_inputs[:, 1].min() < -100.0


def test_front_slip_band_keeps_the_plans_front_tyre_near_its_peak(vp, params, eq30, plant):
    """front_slip_max: from the warm start's front axle course, stages 1 .. N may steer at most
    the band off it; from a measured steering outside the band the bounds close in at the
    steering rate (each stage reachable from the last, so the QP stays feasible). The drift is
    held as without the band."""
    ctrl = Nmpc(vp, dataclasses.replace(params, front_slip_max=1.5))
    band = 1.5 * simple_peak_slip(vp.front_tyre.lateral)
    assert math.radians(8.0) < band / 1.5 < math.radians(9.0)   # B 14, C 1.4: ~8.5 deg
    x = np.array(perturbed_start(eq30))[:6].tolist() + [eq30.T_R, eq30.T_R]
    ref = Reference(0.0, eq30, Direction.LEFT)
    w0 = ctrl._cold_guess(ctrl.ocp, np.array(x), ref)
    lock, step = ctrl.bounds.delta_max, ctrl.bounds.delta_dot_max * params.dt
    V, beta, r = x[0], x[1], x[2]
    course = front_axle_course(V, beta, r, vp.a)
    delta_0 = course + band + 5 * step   # steered 5 stages' rate beyond the band, into the turn
    lbw, ubw = ctrl.ocp.bounds_for(np.array(x))
    nz, N = NS + NU, params.N
    ctrl._front_slip_band(lbw, ubw, ctrl._front_courses(w0), delta_0, nz)
    lo, hi = lbw[X.DELTA + nz::nz], ubw[X.DELTA + nz::nz]
    assert len(lo) == N
    assert lo[0] == hi[0] == pytest.approx(delta_0 - step, rel=1e-5)
    assert hi[4] == pytest.approx(course + band, abs=1e-6), 'the band reached in 5 stages'
    edges = np.concatenate([[delta_0], lo])
    assert np.all(np.diff(edges) >= -step * (1 + 1e-9)), 'closing in no faster than the rate'
    assert lo[-1] == pytest.approx(max(course - band, -lock))
    assert hi[-1] == pytest.approx(course + band)
    assert np.all(lo <= hi) and np.all(lo >= -lock) and np.all(hi <= lock)
    xs, results = run_loop(ctrl, plant, eq30, perturbed_start(eq30), 3.0, mu_plant=1.0)
    assert all(res.status == NmpcStatus.OK for res in results)
    assert abs(np.degrees(xs[-1, 1] - eq30.beta)) < 1.0
    torque_only = Nmpc(vp, dataclasses.replace(params, front_slip_max=1.5),
                       mode=Mode.TORQUE_ONLY)
    assert torque_only._front_slip == 0.0, 'the driver steers: no band on his steering'


def test_paper_formulation_converges_too(vp, params, plant, eq30):
    """No model-error estimate, ideal actuator (the paper's NMPC): converges, with an offset."""
    paper = dataclasses.replace(params, disturbance_gain=0.0, torque_lag=0.0,
                                solver=dataclasses.replace(params.solver, codegen=False))
    xs, _ = run_loop(Nmpc(vp, paper), plant, eq30, perturbed_start(eq30), 5.0, mu_plant=0.95)
    beta_err = np.degrees(xs[int(3.0 / TS):, 1] - eq30.beta)
    assert np.max(np.abs(beta_err)) < 1.0


def test_lagging_powertrain_gives_no_torque_limit_cycle(nmpc, plant, eq30):
    """30 ms delay + 80 ms lag in the plant: with the OCP's lag ~280 Nm std, without ~2100."""
    xs, results = run_loop(nmpc, plant, eq30, perturbed_start(eq30), 5.0, mu_plant=0.95,
                           powertrain=True)
    torques = np.array([r.command.drive_torque for r in results[int(3.0 / TS):]])
    assert np.std(torques) < 600.0, f'torque std {np.std(torques):.0f} Nm'
    assert np.max(np.abs(np.degrees(xs[int(3.0 / TS):, 1] - eq30.beta))) < 1.0


def test_commands_within_bounds_far_from_the_reference(nmpc, plant, eq30):
    """From straight driving at 12 m/s toward the drift: the bounds are active and held."""
    x = np.zeros(9)
    x[:6] = [12.0, 0.0, 0.0, 12.0 / 0.327, 12.0 / 0.329, 0.3]
    xs, results = run_loop(nmpc, plant, eq30, x, 2.0, mu_plant=1.0)
    commands = [r.command for r in results]
    assert_within_bounds(nmpc, commands)
    assert max(abs(c.delta_rate) for c in commands) == pytest.approx(
        nmpc.bounds.delta_dot_max, rel=1e-3), 'the steering-rate bound should be active'


def test_mu_is_a_runtime_parameter(vp, params, plant):
    """The same compiled solver drifts on the wet surface when told mu."""
    mu = load_surface('wet').mu
    sol = solve_equilibrium(math.radians(-30.0), 15.0, vp, mu=mu)
    assert sol.converged
    ctrl = Nmpc(vp, params, mu=mu)
    xs, _ = run_loop(ctrl, plant, sol.eq, perturbed_start(sol.eq), 4.0, mu_plant=mu)
    assert abs(math.degrees(xs[-1, 1] - sol.eq.beta)) < 1.0


def test_reference_horizon_per_stage(eq30):
    """A per-stage horizon is used stage by stage; a short one is held at its last entry."""
    other = dataclasses.replace(eq30, beta=-0.3)
    ref = Reference(0.0, eq30, horizon=(eq30, other))
    rows = reference_rows(ref, 25)
    assert rows[0, 1] == eq30.beta and np.all(rows[1:, 1] == -0.3)
    assert np.all(reference_rows(Reference(0.0, eq30), 25)[:, 1] == eq30.beta)


# --- stages longer than the control period -------------------------------------------------------

def test_stage_length_is_validated():
    with pytest.raises(ParamError, match='nmpc.stage_dt'):
        NmpcParams(Ts=0.02, stage_dt=0.01)
    assert NmpcParams(Ts=0.02).dt == 0.02 and NmpcParams(Ts=0.02, stage_dt=0.03).dt == 0.03


def test_one_stage_is_two_control_periods_of_the_same_model(vp, eq30):
    """F (a stage) and F_period (a control period) integrate the same model with the same step."""
    ocp = Ocp(vp, NmpcParams(Ts=0.02, stage_dt=0.04, substeps=4, torque_lag=0.0))
    x = np.array([*perturbed_start(eq30)[:NXO], eq30.T_R, eq30.T_R])
    u = np.array([0.3, eq30.T_R + 500.0])
    stage = np.asarray(ocp.F(x, u, 1.0, 0.0)).ravel()[:NXO]
    half = np.asarray(ocp.F_period(x, u, 1.0, 0.0)).ravel()
    twice = np.asarray(ocp.F_period(np.concatenate([half, x[NXO:]]), u, 1.0, 0.0)).ravel()
    assert np.allclose(stage, twice, rtol=1e-9, atol=1e-9)
    assert not np.allclose(half, stage, atol=1e-3), 'a period is shorter than a stage'


def test_plan_stepped_on_by_a_fraction_of_a_stage():
    rows = np.arange(8.0).reshape(4, 2)
    assert np.array_equal(_shift_rows(rows, 0.0), rows)
    assert np.allclose(_shift_rows(rows, 0.5), [[1, 2], [3, 4], [5, 6], [6, 7]])
    assert np.allclose(_shift_rows(rows, 1.0), [[2, 3], [4, 5], [6, 7], [6, 7]])
    assert np.array_equal(_shift_rows(rows, 2 / 3, hold=True), rows[[0, 1, 2, 3]])
    assert np.array_equal(_shift_rows(rows, 4 / 3, hold=True), rows[[1, 2, 3, 3]])


def test_command_is_one_control_period_along_a_longer_stage(nmpc, eq30, params):
    """With 30 ms stages and a 20 ms period the steering command is where the plan's rate takes
    the wheel in one period, not at the end of the first stage."""
    assert params.dt > params.Ts, 'config/nmpc.yaml: stages longer than the period'
    x, now = warm(nmpc, eq30)
    res = nmpc.step(measure(x, now), Reference(now, eq30, Direction.LEFT), now)
    assert res.stage_dt == params.dt
    c = res.command
    assert c.delta_rate == pytest.approx(res.predicted_inputs[0, 0])
    # from the plan's start: the measured steering moved on by its age (state_age)
    start = res.predicted_states[0, 5]
    assert c.delta == pytest.approx(start + c.delta_rate * params.Ts, abs=1e-9)


@pytest.mark.parametrize('stage_dt', [0.02, 0.04])
def test_model_error_is_learnt_per_control_period(vp, params, eq30, stage_dt):
    """A plant that is the OCP's own model plus a yaw-rate offset per 20 ms period: the learnt
    error is that offset, whatever the stage length (the OCP adds it per stage, scaled)."""
    p = dataclasses.replace(params, stage_dt=stage_dt, substeps=round(stage_dt / 0.01),
                            disturbance_gain=0.1,
                            solver=dataclasses.replace(params.solver, codegen=False))
    ctrl = Nmpc(vp, p)
    offset = np.zeros(NXO)
    offset[2] = 0.002   # [rad/s] per period, under disturbance_max
    x = np.array([eq30.V, eq30.beta, eq30.r, eq30.omega_F, eq30.omega_R, eq30.delta])
    T_act = eq30.T_R
    for k in range(150):
        now = k * p.Ts
        state = measure(np.concatenate([x, [0.0] * 3]), now, drive_torque=T_act)
        res = ctrl.step(state, Reference(now, eq30, Direction.LEFT), now)
        assert res.status == NmpcStatus.OK
        u = [res.command.delta_rate, res.command.drive_torque]
        x = np.asarray(ctrl.ocp.F_period([*x, T_act, T_act], u, 1.0, p.torque_lag)).ravel() + offset
        T_act += (1.0 - math.exp(-p.Ts / p.torque_lag)) * (res.command.drive_torque - T_act)
    assert ctrl.model_error[2] == pytest.approx(0.002, rel=0.1)
    seen = []
    solve = ctrl._solver.solve
    ctrl._solver.solve = lambda w0, p_, *a: seen.append(p_) or solve(w0, p_, *a)
    now += p.Ts
    ctrl.step(measure(np.concatenate([x, [0.0] * 3]), now, drive_torque=T_act),
              Reference(now, eq30, Direction.LEFT), now)
    d = ctrl.ocp.unpack_params(seen[0]).d
    assert np.allclose(d, ctrl.model_error * stage_dt / p.Ts), 'added per stage'


def test_model_error_decays_at_its_own_rate_off_a_steady_drift(vp, params, eq30):
    """Learning and forgetting are separate rates: off a steady drift (a reference without a
    drift side) the learnt error shrinks by ``disturbance_decay`` per period, whatever the gain."""
    p = dataclasses.replace(params, disturbance_gain=0.02, disturbance_decay=0.25,
                            solver=dataclasses.replace(params.solver, codegen=False))
    ctrl = Nmpc(vp, p)
    x, now = warm(ctrl, eq30)
    ctrl._d = 0.5 * np.asarray(p.disturbance_max)   # as if learnt
    for _ in range(3):
        before = ctrl.model_error
        now += TS
        assert ctrl.step(measure(x, now), Reference(now, eq30), now).status == NmpcStatus.OK
        assert np.allclose(ctrl.model_error, 0.75 * before, rtol=1e-12, atol=0.0)


def test_warm_start_previous_or_shifted(vp, params, eq30, monkeypatch):
    """'previous' starts each step from the last solution as it was, 'shifted' from it moved on
    by one control period (Ts / stage_dt of a stage)."""
    for mode in ('previous', 'shifted'):
        ctrl = Nmpc(vp, dataclasses.replace(
            params, solver=dataclasses.replace(params.solver, warm_start=mode, codegen=False)))
        x, now = warm(ctrl, eq30)
        last = ctrl._w.copy()
        seen = []
        solve = ctrl._solver.solve
        monkeypatch.setattr(ctrl._solver, 'solve', lambda w0, *a: seen.append(w0) or solve(w0, *a))
        ctrl.step(measure(x, now), Reference(now, eq30), now)
        X0, U0 = ctrl.ocp.split(seen[0])
        X, U = ctrl.ocp.split(last)
        shift = 0.0 if mode == 'previous' else params.Ts / params.dt
        assert np.allclose(X0[1:], _shift_rows(X, shift)[1:]) and np.allclose(
            U0, _shift_rows(U, shift, hold=True)), mode


def test_unknown_warm_start_is_named(tmp_path):
    bad = tmp_path / 'nmpc.yaml'
    bad.write_text('solver: {warm_start: none}\n')
    with pytest.raises(ParamError, match='solver.warm_start'):
        load_nmpc_params(bad)


# --- failures ------------------------------------------------------------------------------------

def warm(ctrl, eq, steps=3):
    ctrl.reset()
    x = perturbed_start(eq)
    for k in range(steps):
        assert ctrl.step(measure(x, k * TS), Reference(k * TS, eq), k * TS).status == NmpcStatus.OK
    return x, steps * TS


def test_solver_failure_shifts_then_falls_back(nmpc, eq30, monkeypatch):
    x, now = warm(nmpc, eq30)
    last = nmpc.step(measure(x, now), Reference(now, eq30), now).command

    def broken(*args, **kwargs):
        raise RuntimeError('injected')
    monkeypatch.setattr(nmpc._solver, 'solve', broken)
    statuses, commands = [], [last]
    for k in range(1, nmpc.params.max_failures + 4):
        t = now + k * TS
        res = nmpc.step(measure(x, t), Reference(t, eq30), t)
        statuses.append(res.status)
        commands.append(res.command)
        assert 'injected' in res.message
    n = nmpc.params.max_failures
    assert statuses[:n] == [NmpcStatus.SHIFTED] * n
    assert all(s == NmpcStatus.FALLBACK for s in statuses[n:])
    assert_within_bounds(nmpc, commands)
    fallback = commands[n + 1:]
    assert all(c.mode == Mode.FALLBACK for c in fallback)
    torques = [c.drive_torque for c in commands[n:]]
    assert all(abs(b) < abs(a) or a == 0 for a, b in zip(torques, torques[1:])), 'torque ramps down'
    for a, b in zip(commands[n:], fallback):
        assert abs(b.delta - a.delta) <= nmpc.params.fallback_delta_rate * TS + 1e-12
    monkeypatch.undo()
    t = now + 10 * TS
    assert nmpc.step(measure(x, t), Reference(t, eq30), t).status == NmpcStatus.OK, 'recovers'


def test_failed_cycle_serves_the_plan_one_control_period_on(nmpc, eq30, params, monkeypatch):
    """With stages longer than the period the shifted plan is read at the time of the cycle:
    the torque of the stage that time falls in, the steering where the plan has it then."""
    x, now = warm(nmpc, eq30)
    plan = nmpc.step(measure(x, now), Reference(now, eq30), now)
    X, U = plan.predicted_states, plan.predicted_inputs
    monkeypatch.setattr(nmpc._solver, 'solve',
                        lambda *a, **k: (_ for _ in ()).throw(RuntimeError('injected')))
    for k in (1, 2):
        t = now + k * TS
        res = nmpc.step(measure(x, t), Reference(t, eq30), t)
        assert res.status == NmpcStatus.SHIFTED
        at = k * TS / params.dt   # stages since the plan
        j = int(at + 1e-9)
        assert res.command.drive_torque == pytest.approx(U[j, 1])
        delta = X[j, 5] + (at - j) * (X[j + 1, 5] - X[j, 5])
        assert res.command.delta == pytest.approx(delta + U[j, 0] * TS, abs=1e-9)


def test_failure_falls_back_within_one_cycle(vp, params, eq30, monkeypatch):
    ctrl = Nmpc(vp, dataclasses.replace(params, max_failures=0))
    x, now = warm(ctrl, eq30)
    monkeypatch.setattr(ctrl._solver, 'solve',
                        lambda *a, **k: (_ for _ in ()).throw(RuntimeError('injected')))
    res = ctrl.step(measure(x, now), Reference(now, eq30), now)
    assert res.status == NmpcStatus.FALLBACK and res.command.mode == Mode.FALLBACK
    assert_within_bounds(ctrl, [res.command])


@pytest.mark.parametrize('bad', ['nan', 'stale', 'future', 'invalid', 'none', 'ref_nan',
                                 'ref_stale'])
def test_bad_input_never_reaches_the_solver(nmpc, eq30, bad, monkeypatch):
    x, now = warm(nmpc, eq30)
    calls = []
    monkeypatch.setattr(nmpc._solver, 'solve', lambda *a, **k: calls.append(1))
    state, ref = measure(x, now), Reference(now, eq30)
    if bad == 'nan':
        state = dataclasses.replace(state, beta=float('nan'))
    elif bad == 'stale':
        state = dataclasses.replace(state, stamp=now - 0.06)
    elif bad == 'future':
        state = dataclasses.replace(state, stamp=now + 0.06)
    elif bad == 'invalid':
        state = dataclasses.replace(state, validity=int(Validity.ALL & ~Validity.BETA))
    elif bad == 'none':
        state = None
    elif bad == 'ref_nan':
        ref = Reference(now, dataclasses.replace(eq30, r=float('inf')))
    elif bad == 'ref_stale':
        ref = Reference(now - 0.2, eq30)
    res = nmpc.step(state, ref, now)
    assert not calls
    assert res.status in (NmpcStatus.SHIFTED, NmpcStatus.FALLBACK) and not res.solved
    assert_within_bounds(nmpc, [res.command])


def test_nan_state_falls_back_within_one_cycle(vp, params, eq30):
    ctrl = Nmpc(vp, dataclasses.replace(params, max_failures=0))
    x, now = warm(ctrl, eq30)
    res = ctrl.step(dataclasses.replace(measure(x, now), r=float('nan')), Reference(now, eq30), now)
    assert res.status == NmpcStatus.FALLBACK
    assert_within_bounds(ctrl, [res.command])


def test_no_input_at_start_releases_the_actuators(nmpc, eq30):
    nmpc.reset()
    for k in range(3):
        res = nmpc.step(None, Reference(k * TS, eq30), k * TS)
        assert res.status == NmpcStatus.NO_INPUT and res.command.mode == Mode.OFF
        assert res.command.drive_torque == 0.0


# --- torque-only mode --------------------------------------------------------------------------

def test_torque_only_keeps_the_measured_steering(vp, params, plant, eq30):
    """The driver steers (a slow P controller on beta); the NMPC's own delta is a proposal."""
    ctrl = Nmpc(vp, params, mode=Mode.TORQUE_ONLY)
    x, now = warm(ctrl, eq30)
    x[5] = eq30.delta + 0.1   # the driver steers 0.1 rad away from the equilibrium
    res = ctrl.step(measure(x, now), Reference(now, eq30), now)
    assert res.command.mode == Mode.TORQUE_ONLY
    hold = params.torque_only_hold_stages
    assert np.allclose(res.predicted_states[:hold + 1, 5], x[5]), 'first stages keep the measured'
    assert res.predicted_inputs[0, 0] == pytest.approx(0.0, abs=1e-9)
    assert res.command.delta != pytest.approx(x[5], abs=1e-3), 'proposal is the NMPC own delta'

    def driver(state):
        return float(np.clip(-2.0 * (state[1] - eq30.beta) + 2.0 * (eq30.delta - state[5]),
                             -0.5, 0.5))
    xs, results = run_loop(ctrl, plant, eq30, perturbed_start(eq30), 3.0, 1.0, driver=driver)
    assert all(r.command.mode == Mode.TORQUE_ONLY for r in results)
    assert_within_bounds(ctrl, [r.command for r in results])
    assert np.all(np.abs(xs[:, 1]) > math.radians(15.0)), 'the torque keeps the car drifting'


def test_rear_lock_slip_keeps_the_plans_rear_wheel_rolling(vp, params):
    """An entry that over-rotates (M3 steady_dry seed 4 through the EKF at 3.5 s): the plan
    brakes the rear through standstill into reverse, which engine braking cannot do; with
    ``rear_lock_slip`` its wheel keeps within that slip of the axle's speed."""
    eq = solve_equilibrium(math.radians(-16.3), 15.0, vp).eq
    x = [10.3, math.radians(-16.3), 1.22, 31.0, 36.7, math.radians(5.8)]
    for lock, rolling in ((0.0, False), (0.15, True)):
        ctrl = Nmpc(vp, dataclasses.replace(params, rear_lock_slip=lock))
        for k in range(6):
            now = k * TS
            state = VehicleState(stamp=now, V=x[0] + 1e-9 * k, beta=x[1], r=x[2],
                                 wheel_speeds=(x[3], x[3], x[4], x[4]), delta=x[5])
            res = ctrl.step(state, Reference(now, eq), now)
        assert res.status == NmpcStatus.OK
        P = res.predicted_states[1:]
        floor = 0.85 * P[:, X.V] * np.cos(P[:, X.BETA]) / vp.R_R
        assert bool(np.all(P[:, X.OMEGA_R] > floor - 0.5)) == rolling, P[:, X.OMEGA_R]
    assert P[:, X.OMEGA_R].min() > 0.0
    with pytest.raises(ParamError, match='nmpc.rear_lock_slip'):
        dataclasses.replace(params, rear_lock_slip=1.0)


def test_rear_lock_slip_never_asks_a_braked_wheel_to_spin_up_before_it_can(vp, params):
    """The rear wheel measured well below its floor while the braking torque is still on its
    way (a wet entry that braked): the floors bind from the stage a request reaches the wheel,
    so the plan is found and spins the wheel up to them."""
    eq = solve_equilibrium(math.radians(-21.0), 15.0, vp).eq
    ctrl = Nmpc(vp, dataclasses.replace(params, rear_lock_slip=0.15))
    V, beta = 7.8, math.radians(-20.9)
    floor = 0.85 * V * math.cos(beta) / vp.R_R
    for k in range(6):
        now = k * TS
        state = VehicleState(stamp=now, V=V + 1e-9 * k, beta=beta, r=0.64,
                             wheel_speeds=(23.0, 23.0, 0.6 * floor, 0.6 * floor),
                             delta=math.radians(-11.7), drive_torque=-1400.0)
        res = ctrl.step(state, Reference(now, eq), now)
        assert res.status == NmpcStatus.OK, res
    P = res.predicted_states
    assert P[-1, X.OMEGA_R] > 0.84 * P[-1, X.V] * math.cos(P[-1, X.BETA]) / vp.R_R


# --- solver backends ---------------------------------------------------------------------------

def test_gcc_missing_falls_back_to_interpreted(vp, params, eq30, monkeypatch):
    import drift_control.compiled as compiled
    monkeypatch.setattr(compiled.shutil, 'which', lambda name: None)
    ctrl = Nmpc(vp, params)
    assert ctrl._solver.qp_data.class_name() == 'MXFunction'
    assert ctrl._solver.iteration is None
    warm(ctrl, eq30)


def test_configured_solver_is_compiled(nmpc):
    if nmpc.params.solver.codegen and shutil.which('gcc'):
        assert nmpc._solver.iteration is not None, 'one compiled call per RTI iteration'


class Counted:
    """A compiled function that counts its calls."""

    def __init__(self, fn):
        self.fn, self.calls = fn, 0

    def __getattr__(self, name):
        return getattr(self.fn, name)

    def __call__(self):
        self.calls += 1
        return self.fn()


def test_prepared_steps_give_the_same_commands_bit_for_bit(vp, params, plant, eq30):
    """``prepare`` (the linearisation ahead of the state) changes when the work is done, not
    its result: a loop with it and one without give identical commands, through a friction
    change (the prepared linearisation is then not used) and a fallback's cold restart."""
    if not shutil.which('gcc'):
        pytest.skip('no gcc')
    loops = []
    for prepared in (False, True):
        ctrl = Nmpc(vp, params, mu=1.0)
        prep, feedback = ctrl._solver.iteration
        ctrl._solver.iteration = counted = Counted(prep), feedback
        x, commands, in_step = perturbed_start(eq30), [], []
        for k in range(60):
            now = k * TS
            if k == 30:
                ctrl.mu = 0.9
            state = measure(x, now) if k != 45 else None   # one missing state: fallback
            before = counted[0].calls
            res = ctrl.step(state, Reference(now, eq30, Direction.LEFT), now)
            in_step.append(counted[0].calls - before)
            if prepared:
                ctrl.prepare()
            commands.append(res.command)
            for _ in range(2):
                x = np.asarray(plant(x, [res.command.delta_rate, res.command.drive_torque],
                                     [0.0, 0.95])).ravel()
        loops.append(commands)
    assert loops[0] == loops[1]
    assert sum(in_step[1:30]) == 0, 'a prepared step only does the feedback'
    assert in_step[30] == 1, 'prepared for another friction: linearised again'


@pytest.mark.parametrize('qp', ['hpipm', 'qrqp'])
def test_compiled_iteration_matches_interpreted(vp, params, eq30, qp):
    """The one-call compiled iteration solves the same QP as the interpreted functions (its
    gap Jacobian is summed in another order: equal to rounding)."""
    if not shutil.which('gcc'):
        pytest.skip('no gcc')
    sp = dataclasses.replace(params.solver, qp_solver=qp)
    # the paper's OCP alone: a variant with the path states would be compiled for nothing
    ctrl = Nmpc(vp, dataclasses.replace(params, solver=sp,
                                        cost=dataclasses.replace(params.cost, e_y=0.0)))
    solver, ocp = ctrl._solver, ctrl.ocp
    x0 = np.r_[perturbed_start(eq30)[:6], eq30.T_R, eq30.T_R]
    w0 = ocp.join(np.tile(x0, (ocp.N + 1, 1)), np.tile([0.0, eq30.T_R], (ocp.N, 1)))
    p = ocp.pack_params(reference_rows(Reference(0.0, eq30), ocp.N), 1.0)
    lb, ub = ocp.bounds_for(x0)
    args = (w0 / solver.D, p, lb / solver.D, ub / solver.D)
    compiled = solver._iterate(*args)
    solver.iteration = None
    interpreted = solver._iterate(*args)
    assert compiled[3] == interpreted[3], 'same success status'
    assert np.allclose(compiled[0], interpreted[0], rtol=0, atol=1e-9)
    assert compiled[1] == interpreted[1] and compiled[2] == pytest.approx(interpreted[2], abs=1e-9)


def assert_flag_weighs(ctrl, rows, flag: str, state: int, ratio: float):
    """Raised, the OCP parameter ``flag`` weighs ``state`` in every stage after the first
    ``ratio`` times as much (the squared ratio in the Gauss-Newton Hessian), nothing else."""
    ocp = ctrl.ocp
    H = [np.diag(ctrl._solver._hessian(ocp.pack_params(rows, 1.0, **{flag: f})).full())
         for f in (False, True)]
    weighed = [ocp.x(np.arange(ocp.nw), k)[state] for k in range(1, ocp.N + 1)]
    assert np.allclose(H[1][weighed] / H[0][weighed], ratio ** 2)
    others = np.setdiff1d(np.arange(ocp.nw), weighed)
    assert np.array_equal(H[1][others], H[0][others])


def test_a_flip_weighs_the_rear_wheel_speed_until_the_drift_is_steady(vp, params, eq30):
    """With ``cost.omega_R_flip`` the rear wheel speed weighs as that scale from the first
    horizon with sideslip references on both sides until they are a steady drift again (the
    catch after the crossing included); the compiled iteration solves the QP the interpreted
    one does with that weight. Off, the Hessian stays the constant it was."""
    assert Nmpc(vp, params)._solver.H is not None, 'off: a constant Hessian'
    assert not Nmpc(vp, params)._flip(Reference(0.0, eq30, Direction.LEFT))
    cost = dataclasses.replace(params.cost, omega_R_flip=5.0, e_y=0.0)   # the paper's OCP only
    ctrl = Nmpc(vp, dataclasses.replace(params, cost=cost))
    ocp, solver = ctrl.ocp, ctrl._solver
    rows = reference_rows(Reference(0.0, eq30), ocp.N)
    assert_flag_weighs(ctrl, rows, 'flip', X.OMEGA_R, cost.omega_R / cost.omega_R_flip)

    right = dataclasses.replace(eq30, beta=-eq30.beta, r=-eq30.r, delta=-eq30.delta)
    n = ocp.N + 1
    horizons = {'left': (eq30,) * n, 'both sides': (eq30,) * 10 + (right,) * (n - 10),
                'catch': tuple(dataclasses.replace(right, beta=right.beta * (1 + 0.01 * k))
                               for k in range(n)),
                'steady right': (right,) * n}
    seen = [ctrl._flip(Reference(0.0, h[0], Direction.LEFT, h)) for h in horizons.values()]
    assert seen == [False, True, True, False]

    if not shutil.which('gcc'):
        return
    x0 = np.r_[perturbed_start(eq30)[:6], eq30.T_R, eq30.T_R]
    w0 = ocp.join(np.tile(x0, (ocp.N + 1, 1)), np.tile([0.0, eq30.T_R], (ocp.N, 1)))
    lb, ub = ocp.bounds_for(x0)
    args = (w0 / solver.D, ocp.pack_params(rows, 1.0, flip=True), lb / solver.D, ub / solver.D)
    compiled = solver._iterate(*args)
    solver.iteration = None
    interpreted = solver._iterate(*args)
    assert np.allclose(compiled[0], interpreted[0], rtol=0, atol=1e-9)
    unweighted = solver._iterate(args[0], ocp.pack_params(rows, 1.0), *args[2:])
    assert not np.allclose(unweighted[0], interpreted[0], rtol=0, atol=1e-6), 'the weight acts'


def test_a_steady_drift_slowing_down_weighs_the_speed_as_v_slow(vp, params, eq30):
    """With ``cost.V_slow`` the speed weighs as that scale while a steady drift's reference
    slows down along the horizon (one side, one sideslip): not in a flip, not in an entry ramp,
    not at a constant speed. Off, the Hessian stays the constant it was."""
    n = params.N + 1
    slower = tuple(dataclasses.replace(eq30, V=eq30.V - 0.05 * k) for k in range(n))
    assert not Nmpc(vp, params)._slow(Reference(0.0, slower[0], Direction.LEFT, slower)), 'off'
    cost = dataclasses.replace(params.cost, V_slow=0.5, e_y=0.0)   # the paper's OCP only
    ctrl = Nmpc(vp, dataclasses.replace(params, cost=cost))
    rows = reference_rows(Reference(0.0, eq30), ctrl.ocp.N)
    assert_flag_weighs(ctrl, rows, 'slow', X.V, cost.V / cost.V_slow)

    right = dataclasses.replace(eq30, beta=-eq30.beta, r=-eq30.r, delta=-eq30.delta)
    horizons = {'steady': (eq30,) * n, 'slowing': slower,
                'slowing into a flip': slower[:10] + (right,) * (n - 10),
                'slowing in a ramp': tuple(dataclasses.replace(e, beta=e.beta * (1 - 0.01 * k))
                                           for k, e in enumerate(slower))}
    seen = [ctrl._slow(Reference(0.0, h[0], Direction.LEFT, h)) for h in horizons.values()]
    assert seen == [False, True, False, False]

    passed = []   # and the step hands it to the solver
    solve = ctrl._solver.solve
    ctrl._solver.solve = lambda w0, p_, *a: passed.append(p_) or solve(w0, p_, *a)
    x = [eq30.V, eq30.beta, eq30.r, eq30.omega_F, eq30.omega_R, eq30.delta, 0.0, 0.0, 0.0]
    for h in (slower, (eq30,) * n):
        ctrl.step(measure(np.array(x), 0.0, drive_torque=eq30.T_R),
                  Reference(0.0, h[0], Direction.LEFT, h), 0.0)
    assert [ctrl.ocp.unpack_params(p_).slow for p_ in passed] == [1.0, 0.0]


def path_loop(ctrl: Nmpc, plant, eq, x, seconds: float, K: float) -> np.ndarray:
    """Closed loop on a circle of curvature ``K`` (the plant's path states), the reference
    saying where the car is; the lateral error after each period [m]."""
    ctrl.reset()
    e_y = []
    for k in range(int(round(seconds / TS))):
        now = k * TS
        ref = Reference(now, eq, Direction.LEFT, curvature=K, e_y=float(x[X.E_Y]),
                        heading_error=float(x[X.PSI]))
        res = ctrl.step(measure(x, now), ref, now)
        for _ in range(2):
            x = np.asarray(plant(x, [res.command.delta_rate, res.command.drive_torque],
                                 [K, 1.0])).ravel()
        e_y.append(float(x[X.E_Y]))
    return np.array(e_y)


def test_the_lateral_error_is_weighed_with_the_path_states(vp, params, plant, eq30):
    """A car in its drift 1 m left of the circle: the NMPC that tracks the equilibrium alone
    (the paper's) drives the offset circle, 1 m right of the path half a lap later; with
    ``cost.e_y`` it drives back onto the path."""
    on = Nmpc(vp, dataclasses.replace(params, cost=dataclasses.replace(
        params.cost, e_y=0.1, e_y_after_flip=0.0)))
    off = Nmpc(vp, dataclasses.replace(params, cost=dataclasses.replace(params.cost, e_y=0.0)))
    assert (off.path_ocp, on.ocp.ns, on.path_ocp.ns) == (None, NS, NS + NPATH)
    K = eq30.r / eq30.V
    x = np.zeros(9)
    x[:6] = [eq30.V, eq30.beta, eq30.r, eq30.omega_F, eq30.omega_R, eq30.delta]
    x[X.PSI], x[X.E_Y] = -eq30.beta, 1.0   # moving along the tangent, 1 m left
    half_lap = math.pi / eq30.r
    offset = path_loop(off, plant, eq30, x, half_lap, K)
    back = path_loop(on, plant, eq30, x, half_lap, K)
    assert offset[-1] < -0.9, offset[::10]
    assert np.max(np.abs(back[-int(1.5 / TS):])) < 0.2, back[::10]


def test_the_lateral_error_weighs_once_the_car_drifts_in_full_mode(vp, params, eq30):
    """The grip phase and the entry ramp are left to the reference selector: the lateral error
    weighs from the first horizon of one steady drift since the reset (latched), and never in
    TORQUE_ONLY, where the driver follows the path."""
    on = dataclasses.replace(params, cost=dataclasses.replace(params.cost, e_y=0.2,
                                                              e_y_after_flip=0.0))
    ctrl, n = Nmpc(vp, on), on.N + 1
    grip = dataclasses.replace(eq30, beta=0.0, r=0.3)
    ramp = tuple(dataclasses.replace(eq30, beta=eq30.beta * k / n) for k in range(n))
    horizons = ((grip,) * n, ramp, (eq30,) * n, ramp)
    seen = [ctrl._drifting(Reference(0.0, h[0], Direction.LEFT, h), 0.0) for h in horizons]
    assert seen == [False, False, True, True]
    ctrl.reset()
    assert not ctrl._drifting(Reference(0.0, grip, Direction.LEFT, (grip,) * n), 0.0)
    semi = Nmpc(vp, on, mode=Mode.TORQUE_ONLY)
    assert not semi._drifting(Reference(0.0, eq30, Direction.LEFT, (eq30,) * n), 0.0)

    # the OCP solved while it weighs is the other one with the lateral error's cost added
    base, path = ctrl.ocp, ctrl.path_ocp
    rows = reference_rows(Reference(0.0, eq30), base.N)
    H = [np.diag(solver._hessian(ocp.pack_params(rows, 1.0)).full())
         for solver, ocp in ((ctrl._solver, base), (ctrl._path_solver, path))]
    states, inputs = base.split(np.arange(base.nw))   # where each base entry sits in the other
    at = path.join(np.hstack([states, np.full((base.N + 1, NPATH), -1)]), inputs).astype(int)
    weighed = [path.x(np.arange(path.nw), k)[S_E_Y] for k in range(1, path.N + 1)]
    assert np.all(H[1][weighed] > 0.0)
    assert H[1][at >= 0] == pytest.approx(H[0][at[at >= 0]], rel=1e-12)


def test_the_lateral_error_weighs_only_around_a_flip_with_e_y_after_flip(vp, params, eq30):
    """With ``cost.e_y_after_flip`` the lateral error weighs from a flip's first horizon (both
    sides, or between them) until that long after its last, once the car has drifted."""
    cost = dataclasses.replace(params.cost, e_y=0.2, e_y_after_flip=3.0)
    ctrl, n = Nmpc(vp, dataclasses.replace(params, cost=cost)), params.N + 1
    left, right = (eq30,) * n, (eq30.mirrored(),) * n
    flip = tuple(eq30 if k < n // 2 else eq30.mirrored() for k in range(n))
    seen = [ctrl._drifting(Reference(t, h[0], Direction.LEFT, h), t)
            for t, h in ((0.0, left), (5.0, left), (6.0, flip), (6.5, right), (8.9, right),
                         (9.1, right), (20.0, right))]
    assert seen == [False, False, True, True, True, False, False]
    ctrl.reset()   # a flip before the first steady drift is the entry's: not weighed
    assert not ctrl._drifting(Reference(0.0, flip[0], Direction.NONE, flip), 0.0)
    with pytest.raises(ParamError, match='nmpc.cost.e_y_after_flip'):
        dataclasses.replace(params.cost, e_y_after_flip=-1.0)


def test_the_path_states_are_solved_only_while_the_lateral_error_weighs(vp, params, eq30):
    """With ``cost.e_y_after_flip`` the NMPC solves the smaller OCP in the steady drift and the
    one with the path states from the flip on, that long after it; the guess carries over
    both ways, the path states rolled out along it (no gaps past the measured stage 0)."""
    cost = dataclasses.replace(params.cost, e_y=0.2, e_y_after_flip=0.2)
    ctrl, n = Nmpc(vp, dataclasses.replace(params, cost=cost)), params.N + 1
    left, right = (eq30,) * n, (eq30.mirrored(),) * n
    flip = tuple(eq30 if k < n // 2 else eq30.mirrored() for k in range(n))
    solved = []
    for name in ('_solver', '_path_solver'):
        solver = getattr(ctrl, name)
        solver.solve = (lambda run, name: lambda w0, p_, *a: (solved.append((name, w0, p_))
                                                               or run(w0, p_, *a)))(
            solver.solve, name)
    for k in range(40):
        now = k * TS
        h = left if k < 10 else flip if k < 15 else right
        eq = h[0]
        x = [eq.V, eq.beta, eq.r, eq.omega_F, eq.omega_R, eq.delta]
        res = ctrl.step(measure(x, now, drive_torque=eq.T_R),
                        Reference(now, eq, Direction.LEFT if k < 15 else Direction.RIGHT, h,
                                  curvature=1 / 15, e_y=0.3), now)
        assert res.status == NmpcStatus.OK, (k, res.message)
    names = [name for name, _, _ in solved]
    last_flip, after = 14, int(round(0.2 / TS))
    assert names == ['_solver'] * 10 + ['_path_solver'] * (last_flip - 9 + after) \
        + ['_solver'] * (40 - last_flip - 1 - after)
    _, w0, p_ = solved[10]   # the first path solve: the guess from the smaller OCP's plan
    path = ctrl.path_ocp
    gaps = np.asarray(path.gaps(w0, p_)).ravel().reshape(path.N, path.ns)
    assert np.max(np.abs(gaps[1:, NS:])) < 1e-9


def test_the_paths_curvature_reaches_each_stage_through_the_parameters(vp, params, eq30):
    """With the path states, stage k's curvature state is the path's at stage k: the gaps
    vanish for a plan that carries it, whatever the stages' curvatures."""
    ocp = Ocp(vp, dataclasses.replace(params, cost=dataclasses.replace(params.cost, e_y=0.5)))
    N = ocp.N
    K = np.linspace(1 / 15, -1 / 15, N + 1)
    p = ocp.pack_params(reference_rows(Reference(0.0, eq30), N), 1.0, curvature=K)
    x0 = [eq30.V, eq30.beta, eq30.r, eq30.omega_F, eq30.omega_R, eq30.delta, eq30.T_R, eq30.T_R,
          -eq30.beta, 0.0, K[0]]
    states, inputs = [np.array(x0)], np.tile([0.0, eq30.T_R], (N, 1))
    for k in range(N):
        nxt = np.asarray(ocp.F(states[-1], inputs[k], 1.0, ocp.params.torque_lag)).ravel()
        nxt[S_K] += K[k + 1] - K[k]
        states.append(nxt)
    gaps = np.asarray(ocp.gaps(ocp.join(np.array(states), inputs), p)).ravel()
    assert np.max(np.abs(gaps)) < 1e-9
    assert [s[S_K] for s in states] == pytest.approx(K.tolist())
    with pytest.raises(ParamError, match='nmpc.cost.e_y'):
        dataclasses.replace(params.cost, e_y=-1.0)


def test_the_lateral_error_asked_decays_from_the_cars_at_e_y_time(vp, params, eq30):
    """With ``cost.e_y_time`` stage k is asked the car's lateral error times exp(-t_k / tau):
    a plan along that costs nothing for it, one straight onto the path does."""
    cost = dataclasses.replace(params.cost, e_y=0.2, e_y_time=1.0)
    ocp = Ocp(vp, dataclasses.replace(params, cost=cost))
    base = Ocp(vp, dataclasses.replace(params, cost=cost), path=False)
    J = ca.Function('J', [ocp.w, ocp.p], [ocp.J])
    J_base = ca.Function('J', [base.w, base.p], [base.J])
    rows = reference_rows(Reference(0.0, eq30), ocp.N)
    states = np.zeros((ocp.N + 1, ocp.ns))
    inputs = np.zeros((ocp.N, 2))
    t = np.arange(ocp.N + 1) * params.dt
    without = float(J_base(base.join(states[:, :NS], inputs), base.pack_params(rows, 1.0)))

    def e_y_cost(e_y):   # the OCP's cost beyond the one without the path states
        states[:, S_E_Y] = e_y
        return float(J(ocp.join(states, inputs), ocp.pack_params(rows, 1.0, e_y=1.5))) - without

    assert e_y_cost(1.5 * np.exp(-t / cost.e_y_time)) == pytest.approx(0.0, abs=1e-9)
    assert e_y_cost(np.zeros_like(t)) > 1.0


def test_failed_compiled_qp_names_its_status(vp, params, eq30):
    """A QP the compiled iteration cannot solve fails with the status the interpreted one
    reports (it is solved again, interpreted, on the same data)."""
    if not shutil.which('gcc'):
        pytest.skip('no gcc')
    ctrl = Nmpc(vp, params)
    solver, ocp = ctrl._solver, ctrl.ocp
    x0 = np.r_[eq30.V, eq30.beta, eq30.r, eq30.omega_F, eq30.omega_R, eq30.delta, eq30.T_R,
               eq30.T_R]
    w0 = ocp.join(np.tile(x0, (ocp.N + 1, 1)), np.tile([0.0, eq30.T_R], (ocp.N, 1)))
    p = ocp.pack_params(reference_rows(Reference(0.0, eq30), ocp.N), 1.0)
    lb, ub = ocp.bounds_for(x0)
    i = ocp.x(np.arange(ocp.nw), 1)[X.DELTA]   # the steering of state 1: out of reach
    lb[i] = ub[i] = eq30.delta + 0.3
    args = (w0 / solver.D, p, lb / solver.D, ub / solver.D)
    compiled = solver._iterate(*args)
    solver.iteration = None
    interpreted = solver._iterate(*args)
    assert compiled[0] is None and interpreted[0] is None
    assert compiled[3] == interpreted[3]


@pytest.mark.slow
@pytest.mark.parametrize('method,qp', [('rti', 'qrqp'), ('rti', 'osqp'), ('sqp', 'qrqp'),
                                       ('ipopt', 'qrqp'), ('fatrop', 'qrqp')])
def test_solvers_agree(vp, eq30, method, qp):
    """Converged from the same start, every backend finds the same optimum."""
    ref_sp = SolverParams(method='rti', qp_solver='hpipm', codegen=False, max_iter=30, tol=1e-9)
    sp = SolverParams(method=method, qp_solver=qp, codegen=False, max_iter=50, tol=1e-9)
    costs = []
    for s in (ref_sp, sp):
        ocp = Ocp(vp, NmpcParams(solver=s))
        from drift_control.ocp_solvers import make_solver
        x0 = np.r_[perturbed_start(eq30)[:6], eq30.T_R, eq30.T_R]
        rows = reference_rows(Reference(0.0, eq30), ocp.N)
        lb, ub = ocp.bounds_for(x0)
        w0 = ocp.join(np.tile(x0, (ocp.N + 1, 1)), np.tile([0.0, eq30.T_R], (ocp.N, 1)))
        out = make_solver(ocp, s).solve(w0, ocp.pack_params(rows, 1.0), lb, ub, 50)
        assert out.success, (method, qp, out.status)
        costs.append(out.cost)
    assert costs[1] == pytest.approx(costs[0], rel=1e-4)


def test_drift_entry_from_grip_on_a_ramped_reference(nmpc, plant, vp):
    """From a 9 m/s grip turn, a reference ramped at 1 rad/s (as the selector limits it)."""
    from drift_control.eqmap import load_map
    from drift_control.assembly import map_file
    from drift_control.params import default_vehicle
    eqmap = load_map(map_file(default_vehicle(), 'dry'))
    nmpc.reset()
    x = np.zeros(9)
    x[:6] = [9.0, -0.02, 0.6, 9.0 / vp.R_F, 9.0 / vp.R_R, 0.05]
    for k in range(int(3.0 / TS)):
        now = k * TS
        beta_abs = min(float(eqmap.beta_abs[0]) + 1.0 * now, math.radians(30.0))
        eq, _ = eqmap.lookup(beta_abs, 15.0, Direction.LEFT)
        res = nmpc.step(measure(x, now), Reference(now, eq, Direction.LEFT), now)
        assert res.status == NmpcStatus.OK, res.message
        x = np.asarray(plant(x, [res.command.delta_rate, res.command.drive_torque],
                             [0.0, 1.0])).ravel()
    assert abs(math.degrees(x[1]) + 30.0) < 1.0 and x[5] < 0.0, 'a counter-steered 30 deg drift'


def test_lockstep_trigger_once_per_period_with_the_matching_reference():
    from drift_control.nmpc import LockstepTrigger
    trig = LockstepTrigger(0.02, reference_wait=0.005)
    assert not trig.on_state(0.0, wall=100.0), 'waits for the reference of this state'
    assert trig.on_reference(0.0)
    assert trig.fired() == 0.0
    assert not trig.on_state(0.01, wall=100.01) and not trig.poll(100.05), 'not due yet'
    assert not trig.on_state(0.02, wall=100.02)
    assert not trig.poll(100.022)
    assert trig.poll(100.026), 'no reference: solve anyway after reference_wait'
    assert trig.fired() == 0.02
    assert not trig.on_reference(0.02), 'nothing pending'


def test_a_failing_preparation_costs_time_not_the_cycle(vp, params, eq30, monkeypatch):
    ctrl = Nmpc(vp, params)
    x = perturbed_start(eq30)
    ctrl.step(measure(x, 0.0), Reference(0.0, eq30, Direction.LEFT), 0.0)

    def broken(*args):
        raise RuntimeError('no memory')
    monkeypatch.setattr(ctrl._solver, 'prepare', broken)
    ctrl.prepare()   # logged, not raised
    res = ctrl.step(measure(x, TS), Reference(TS, eq30, Direction.LEFT), TS)
    assert res.status == NmpcStatus.OK


def test_a_reference_selected_a_period_ago_is_solved_from_now_on(nmpc, eq30, monkeypatch):
    """The selector may run after the command (the NMPC node's in-process stages): the NMPC
    then tracks the older reference's stages from now on (Reference.at), not from its stamp."""
    seen = []
    solve = Nmpc._solve
    monkeypatch.setattr(Nmpc, '_solve', lambda self, state, ref, now: (
        seen.append(ref), solve(self, state, ref, now))[1])
    stages = tuple(dataclasses.replace(eq30, V=eq30.V + 0.01 * k) for k in range(nmpc.params.N))
    ref = Reference(1.0, stages[0], Direction.LEFT, stages)
    nmpc.reset()
    x = perturbed_start(eq30)
    assert nmpc.step(measure(x, 1.0), ref, 1.0).status == NmpcStatus.OK
    assert seen[-1] is ref   # as old as the state: as it is
    assert nmpc.step(measure(x, 1.0 + TS), ref, 1.0 + TS).status == NmpcStatus.OK
    shift = TS / nmpc.params.dt
    assert seen[-1].target.V == pytest.approx(eq30.V + 0.01 * shift)
    assert seen[-1].horizon[-1] == stages[-1]


def test_the_state_predicted_one_period_on_carries_the_pose(nmpc, eq30):
    """What the selector after the command selects on: the model's state one control period
    after a solve, the pose moved along the course; nothing without a solve."""
    nmpc.reset()
    x = perturbed_start(eq30)
    state = dataclasses.replace(measure(x, 1.0), x=0.0, y=0.0, yaw=0.3)
    assert nmpc.next_state(state) is None
    assert nmpc.step(state, Reference(1.0, eq30, Direction.LEFT), 1.0).status == NmpcStatus.OK
    nxt = nmpc.next_state(state)
    assert nxt.stamp == pytest.approx(1.0 + TS)
    assert nxt.V == pytest.approx(state.V, abs=0.5)
    assert nxt.beta == pytest.approx(state.beta, abs=0.05)
    course = state.yaw + state.beta
    assert math.hypot(nxt.x, nxt.y) == pytest.approx(TS * state.V, rel=0.05)
    assert math.atan2(nxt.y, nxt.x) == pytest.approx(course, abs=0.05)


@pytest.mark.parametrize('turned', [0.0, 0.004])
def test_a_measured_states_age_is_predicted_on(vp, params, eq30, turned):
    """With ``state_age`` each measured state starts the plan moved on by its age: speed and
    sideslip at the rates the measured accelerations give, the yaw rate and wheels by the model
    under the torque requested, the steering at the rate asked, whatever the wheels were
    measured to do (no derivative of the measured angle in the command); a stamped state (an
    estimator's) as is."""
    from drift_control.signals import Reference, VehicleState
    from drift_control.vehicle import NU, U, velocity_rates
    age = np.array([0.01, 0.02, 0.01, 0.01, 0.01, 0.01])
    x = np.array([eq30.V, eq30.beta + 0.05, eq30.r, eq30.omega_F, eq30.omega_R,
                  eq30.delta + 0.02])   # off the equilibrium: the states move
    ax, ay = 0.4, 7.5
    starts, first = {}, {}
    for stamped in (False, True):
        ctrl = Nmpc(vp, dataclasses.replace(params, state_age=tuple(age)), stamped=stamped)
        seen = []
        run = ctrl._solver.solve
        ctrl._solver.solve = lambda w0, p, *a, run=run, seen=seen: \
            seen.append(np.array(w0[:NXO + 1])) or run(w0, p, *a)
        for k in range(2):
            state = VehicleState(stamp=k * 0.02, V=x[0], beta=x[1], r=x[2], ax=ax, ay=ay,
                                 wheel_speeds=(x[3], x[3], x[4], x[4]), delta=x[5] + k * turned,
                                 drive_torque=eq30.T_R)
            result = ctrl.step(state, Reference(k * 0.02, eq30), k * 0.02)
            first.setdefault(stamped, result.command)
        assert np.allclose(seen[0][:NXO], x), 'no request applied yet: as measured'
        starts[stamped] = seen[1]
    x1 = x + np.eye(NXO)[5] * turned
    assert np.allclose(starts[True][:NXO], x1)
    assert abs(first[False].delta_rate) > 0.05, 'a steering rate asked'
    u = np.zeros(NU)
    u[U.DELTA_DOT], u[U.T_R] = first[False].delta_rate, first[False].drive_torque
    x_dot = np.asarray(ctrl.ocp.f_state(np.r_[x1, starts[False][NXO]], u, ctrl.mu,
                                        ctrl.lag)).ravel()[:NXO]
    x_dot[:2] = velocity_rates(x1[0], x1[1], x1[2], ax, ay)
    assert np.allclose(starts[False][:NXO], x1 + age * x_dot)
    assert starts[False][5] == pytest.approx(x1[5] + 0.01 * first[False].delta_rate)
    assert not np.allclose(starts[False][:NXO], x1)


def test_an_impossible_acceleration_is_not_used_to_age_the_state(vp, params, eq30):
    """A finite but impossible accelerometer reading (a sensor fault) leaves the speed and
    sideslip to the model: the plan starts where a plausible reading would have put it."""
    from drift_control.signals import Reference, VehicleState
    age = (0.01, 0.02, 0.01, 0.01, 0.01, 0.01)
    starts = []
    for ay in (7.5, 1e4):
        ctrl = Nmpc(vp, dataclasses.replace(params, state_age=age))
        seen = []
        run = ctrl._solver.solve
        ctrl._solver.solve = lambda w0, p, *a, run=run, seen=seen: \
            seen.append(np.array(w0[:NXO])) or run(w0, p, *a)
        for k in range(2):
            state = VehicleState(stamp=k * 0.02, V=eq30.V, beta=eq30.beta, r=eq30.r, ay=ay,
                                 wheel_speeds=(eq30.omega_F,) * 2 + (eq30.omega_R,) * 2,
                                 delta=eq30.delta, drive_torque=eq30.T_R)
            ctrl.step(state, Reference(k * 0.02, eq30), k * 0.02)
        starts.append(seen[1])
    assert abs(starts[1][1] - eq30.beta) < 0.01, 'the sideslip moved by the model, not 1e4'
    assert not np.allclose(starts[0], starts[1])


def test_the_state_age_names_its_key():
    with pytest.raises(ParamError, match='state_age'):
        NmpcParams(state_age=(0.01,) * 5)
    with pytest.raises(ParamError, match='state_age'):
        NmpcParams(state_age=(0.0, 0.2, 0.0, 0.0, 0.0, 0.0))   # beyond max_input_age

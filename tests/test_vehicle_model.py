"""Single-track model: Newton's law, symmetry, float/symbol agreement, Jacobians, singular corners."""
import math

import casadi as ca
import numpy as np
import pytest

from drift_control.params import load_vehicle
from drift_control.vehicle import (NX, THETA, U, X, VehicleModel, axle_torque,
                                   front_axle_course, mirror_input, mirror_state, rhs, slips,
                                   velocity_rates)


@pytest.fixture(scope='module')
def vp():
    return load_vehicle()


@pytest.fixture(scope='module')
def model(vp):
    return VehicleModel(vp)


def random_states(vp, n, seed=0):
    """Random but physical states: moving forward, moderate slips."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, NX))
    x[:, X.V] = rng.uniform(3.0, 30.0, n)
    x[:, X.BETA] = rng.uniform(-0.8, 0.8, n)
    x[:, X.R] = rng.uniform(-1.5, 1.5, n)
    x[:, X.OMEGA_F] = x[:, X.V] / vp.R_F * rng.uniform(0.9, 1.1, n)
    x[:, X.OMEGA_R] = x[:, X.V] / vp.R_R * rng.uniform(0.8, 1.8, n)
    x[:, X.DELTA] = rng.uniform(-0.5, 0.5, n)
    x[:, X.PSI] = rng.uniform(-0.5, 0.5, n)
    x[:, X.E_Y] = rng.uniform(-2.0, 2.0, n)
    x[:, X.S] = rng.uniform(0.0, 100.0, n)
    u = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1500, 6000, n)])
    theta = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(0.5, 1.1, n)])
    return x, u, theta


def test_velocity_frame_equations_agree_with_newton_in_the_body_frame(vp, model):
    """Resolve the tyre forces in the body frame and derive V_dot, beta_dot from vx_dot, vy_dot.

    This is the check that catches the sign of F_xF sin(delta - beta) in beta_dot (the paper's
    Eq. 2 prints a minus).
    """
    x, u, theta = random_states(vp, 200, seed=3)
    for xi, ui, ti in zip(x, u, theta):
        f = model.forces(xi, mu=ti[THETA.MU])
        V, beta, r, delta = xi[X.V], xi[X.BETA], xi[X.R], xi[X.DELTA]
        vx, vy = V * math.cos(beta), V * math.sin(beta)
        Fx = f.F_xF * math.cos(delta) - f.F_yF * math.sin(delta) + f.F_xR - vp.c_drag * V * vx
        Fy = f.F_xF * math.sin(delta) + f.F_yF * math.cos(delta) + f.F_yR - vp.c_drag * V * vy
        vx_dot = Fx / vp.m + r * vy
        vy_dot = Fy / vp.m - r * vx
        V_dot = (vx * vx_dot + vy * vy_dot) / V
        beta_dot = (vx * vy_dot - vy * vx_dot) / V ** 2
        Mz = vp.a * (f.F_xF * math.sin(delta) + f.F_yF * math.cos(delta)) - vp.b * f.F_yR
        x_dot = model.rhs(xi, ui, *ti)
        assert x_dot[X.V] == pytest.approx(V_dot, rel=1e-9, abs=1e-9)
        assert x_dot[X.BETA] == pytest.approx(beta_dot, rel=1e-9, abs=1e-9)
        assert x_dot[X.R] == pytest.approx(Mz / vp.I_z, rel=1e-12)


def test_front_slip_is_the_steering_off_the_front_axles_course(vp):
    """The numeric course the NMPC bounds its steering by and the slip the model computes
    (apart from the model's smooth floor under the slip denominator)."""
    x, _, _ = random_states(vp, 200)
    for xi in x:
        alpha_F = float(slips(xi, vp)[0])
        course = front_axle_course(xi[X.V], xi[X.BETA], xi[X.R], vp.a)
        assert alpha_F == pytest.approx(xi[X.DELTA] - course, abs=1e-6)


def test_mirroring_left_right_mirrors_the_derivative(model, vp):
    x, u, theta = random_states(vp, 100, seed=4)
    for xi, ui, ti in zip(x, u, theta):
        mirrored = model.rhs(mirror_state(xi), mirror_input(ui), -ti[THETA.K], ti[THETA.MU])
        expected = mirror_state(model.rhs(xi, ui, *ti))
        np.testing.assert_allclose(mirrored, expected, rtol=1e-10, atol=1e-9)


def test_rates_from_measured_accelerations_are_the_models_on_its_own(vp, model):
    """``velocity_rates`` fed the body accelerations the model's forces give (what an ideal
    accelerometer at the centre of gravity reads) returns the model's V_dot and beta_dot."""
    x, u, theta = random_states(vp, 200, seed=4)
    for xi, ui, ti in zip(x, u, theta):
        f = model.forces(xi, mu=ti[THETA.MU])
        V, beta, delta = xi[X.V], xi[X.BETA], xi[X.DELTA]
        ax = (f.F_xF * math.cos(delta) - f.F_yF * math.sin(delta) + f.F_xR
              - vp.c_drag * V * V * math.cos(beta)) / vp.m
        ay = (f.F_xF * math.sin(delta) + f.F_yF * math.cos(delta) + f.F_yR
              - vp.c_drag * V * V * math.sin(beta)) / vp.m
        x_dot = model.rhs(xi, ui, *ti)
        V_dot, beta_dot = velocity_rates(V, beta, xi[X.R], ax, ay)
        assert V_dot == pytest.approx(x_dot[X.V], rel=1e-9, abs=1e-9)
        assert beta_dot == pytest.approx(x_dot[X.BETA], rel=1e-6, abs=1e-6)


def test_float_and_casadi_evaluations_agree(model, vp):
    x, u, theta = random_states(vp, 100, seed=5)
    for xi, ui, ti in zip(x, u, theta):
        floats = np.asarray(rhs([float(v) for v in xi], [float(v) for v in ui],
                                [float(v) for v in ti], vp), dtype=float).ravel()
        symbolic = model.rhs(xi, ui, *ti)
        np.testing.assert_allclose(floats, symbolic, rtol=1e-10, atol=1e-10)


def test_jacobians_match_finite_differences(model, vp):
    xs, us, ths = ca.SX.sym('x', NX), ca.SX.sym('u', 2), ca.SX.sym('t', 2)
    out = model.f(xs, us, ths)
    jac = ca.Function('jacobians', [xs, us, ths], [ca.jacobian(out, xs), ca.jacobian(out, us)])
    x, u, theta = random_states(vp, 20, seed=6)
    for xi, ui, ti in zip(x, u, theta):
        J_x, J_u = (np.asarray(m) for m in jac(xi, ui, ti))
        h = 1e-6
        for i in range(NX):
            e = np.zeros(NX)
            e[i] = h * max(1.0, abs(xi[i]))
            fd = (model.rhs(xi + e, ui, *ti) - model.rhs(xi - e, ui, *ti)) / (2 * e[i])
            np.testing.assert_allclose(J_x[:, i], fd, rtol=1e-4, atol=1e-3 * (1 + np.abs(fd).max()))
        e = np.array([0.0, 1e-3])
        fd = (model.rhs(xi, ui + e, *ti) - model.rhs(xi, ui - e, *ti)) / 2e-3
        np.testing.assert_allclose(J_u[:, U.T_R], fd, rtol=1e-6, atol=1e-9)


def test_no_nan_or_inf_in_the_singular_corners(model, vp):
    """Standstill, huge sideslip, locked and spinning wheels, a car at the centre of curvature."""
    grid = []
    for V in (0.0, 0.05, 0.5, 5.0, 40.0):
        for beta in np.radians([-90.0, -60.0, 0.0, 60.0, 90.0]):
            for wheel in (0.0, 1.0, 300.0):          # locked, crawling, spinning [rad/s]
                for e_y, K in ((0.0, 0.0), (15.0, 1 / 15.0), (40.0, 1 / 15.0)):
                    grid.append([V, beta, 1.0, wheel, wheel, 0.4, 0.3, e_y, 0.0, K])
    grid = np.array(grid)
    out = model.f.map(len(grid))(grid[:, :NX].T, np.tile([[0.5], [6000.0]], len(grid)),
                                 np.vstack([grid[:, NX], np.ones(len(grid))]))
    assert np.all(np.isfinite(np.asarray(out)))
    xs, us, ths = ca.SX.sym('x', NX), ca.SX.sym('u', 2), ca.SX.sym('t', 2)
    jac = ca.Function('jacobians', [xs, us, ths], [ca.jacobian(model.f(xs, us, ths), xs)])
    J = jac.map(len(grid))(grid[:, :NX].T, np.tile([[0.5], [6000.0]], len(grid)),
                          np.vstack([grid[:, NX], np.ones(len(grid))]))
    assert np.all(np.isfinite(np.asarray(J)))


def test_a_car_on_the_path_stays_on_the_path(model, vp):
    """Paper Eq. (1): yaw rate V K, no sideslip, on the path -> e_y and heading error constant."""
    R, V = 50.0, 10.0
    x = np.zeros(NX)
    x[[X.V, X.R, X.OMEGA_F, X.OMEGA_R]] = V, V / R, V / vp.R_F, V / vp.R_R
    x_dot = model.rhs(x, [0.0, 0.0], 1 / R, 1.0)
    assert x_dot[X.PSI] == pytest.approx(0.0, abs=1e-12)
    assert x_dot[X.E_Y] == pytest.approx(0.0, abs=1e-12)
    assert x_dot[X.S] == pytest.approx(V, rel=1e-12)
    x[X.E_Y] = 2.0   # 2 m inside a left curve: the path point moves slower than the car
    assert model.rhs(x, [0.0, 0.0], 1 / R, 1.0)[X.S] == pytest.approx(V / (1 - 2.0 / R), rel=1e-9)


def test_coasting_decelerates_and_drive_torque_accelerates(model, vp):
    x = np.zeros(NX)
    x[[X.V, X.OMEGA_F, X.OMEGA_R]] = 20.0, 20.0 / vp.R_F, 20.0 / vp.R_R
    assert model.rhs(x, [0.0, 0.0])[X.V] == pytest.approx(-vp.c_drag * 400 / vp.m, rel=1e-9)
    traj = model.simulate(x, np.tile([0.0, 2000.0], (100, 1)), 0.01, substeps=4)
    # after the wheel spins up, the torque accelerates the car and both axles' spin inertia
    accel = (traj[-1, X.V] - traj[50, X.V]) / 0.5
    V_mid = traj[75, X.V]
    m_eff = vp.m + vp.I_wR / vp.R_R ** 2 + vp.I_wF / vp.R_F ** 2
    assert accel == pytest.approx((2000.0 / vp.R_R - vp.c_drag * V_mid ** 2) / m_eff, rel=0.02)


def test_engine_braking_resists_the_rear_wheel_and_never_turns_it_backwards(model, vp):
    # a turning wheel gets the torque exactly: the model's numbers are those without the fade
    for T in (-1500.0, -0.3, 0.0, 2000.0):
        assert float(axle_torque(T, 10.5)) == T and float(axle_torque(T, 60.0)) == T
    assert float(axle_torque(3000.0, 0.0)) == 3000.0, 'drive torque spins up a stopped wheel'
    assert float(axle_torque(-1500.0, -0.5)) > -5.0, 'no engine braking on a wheel turning back'
    # a car sliding slowly with its rear locked by engine braking: the wheel stays at ~0
    x = np.zeros(NX)
    x[[X.V, X.OMEGA_F, X.OMEGA_R]] = 3.0, 3.0 / vp.R_F, 3.0 / vp.R_R
    traj = model.simulate(x, np.tile([0.0, vp.limits.T_R_min], (150, 1)), 0.01, substeps=4)
    assert traj[:, X.OMEGA_R].min() > -0.5, 'engine braking reversed the rear wheel'
    assert traj[-1, X.V] < 2.0, 'the braked car slows down'


def test_free_rolling_front_wheel_keeps_the_vehicle_dynamics(vp):
    """'free_rolling' only changes the front wheel: same forces at free rolling, same V, beta, r."""
    dyn, free = VehicleModel(vp), VehicleModel(vp, front_wheel='free_rolling')
    x, u, theta = random_states(vp, 30, seed=8)
    for xi, ui, ti in zip(x, u, theta):
        # put the front wheel exactly at its free-rolling speed
        V, beta, r, delta = xi[X.V], xi[X.BETA], xi[X.R], xi[X.DELTA]
        v_xw = V * math.cos(beta) * math.cos(delta) + (V * math.sin(beta) + vp.a * r) * math.sin(delta)
        xi[X.OMEGA_F] = v_xw / vp.R_F
        a, b = dyn.rhs(xi, ui, *ti), free.rhs(xi, ui, *ti)
        np.testing.assert_allclose(a[[X.V, X.BETA, X.R, X.OMEGA_R]], b[[X.V, X.BETA, X.R, X.OMEGA_R]],
                                   rtol=1e-9, atol=1e-9)
        assert b[X.OMEGA_F] == pytest.approx(0.0, abs=1e-9)


def test_rk4_converges_at_fourth_order(model, vp):
    x0 = np.zeros(NX)
    x0[[X.V, X.BETA, X.R, X.OMEGA_F, X.OMEGA_R]] = 12.0, -0.3, 0.6, 12 / vp.R_F, 16 / vp.R_R
    u = np.tile([0.2, 1500.0], (10, 1))
    ref = model.simulate(x0, u, 0.02, substeps=64)[-1]
    err = [np.abs(model.simulate(x0, u, 0.02, substeps=n)[-1] - ref)[:6].max() for n in (8, 16)]
    assert err[1] < err[0] / 10   # 2^4 = 16 in theory

"""Steady-state drift equilibria (paper section III): physics of single solves."""
import numpy as np
import pytest

from drift_control.equilibrium import (derivative_scale, input_vector, scaled_derivative,
                                       solve_equilibrium, solve_row, state_vector)
from drift_control.params import load_surface, load_vehicle
from drift_control.tyre import longitudinal_peak_slip
from drift_control.vehicle import X, VehicleModel


@pytest.fixture(scope='module')
def vehicle():
    return load_vehicle()


@pytest.fixture(scope='module')
def model(vehicle):
    return VehicleModel(vehicle)


@pytest.fixture(scope='module')
def drift_30_15(vehicle, model):
    return solve_equilibrium(np.radians(-30.0), 15.0, vehicle, model=model)


def test_drift_equilibrium_is_a_steady_circle(drift_30_15, model):
    sol = drift_30_15
    eq = sol.eq
    assert sol.converged, sol
    assert np.max(np.abs(sol.residual)) <= 1e-8
    # re-inserted in the model (not the solver's own residual): nothing moves
    assert np.max(np.abs(scaled_derivative(eq, model))) <= 1e-8
    assert eq.V / eq.r == pytest.approx(15.0, rel=1e-9), 'R = V / r'
    assert eq.r > 0 and eq.beta < 0, 'left drift: r > 0, beta < 0'
    assert np.sign(eq.delta) == -np.sign(eq.r), 'a full drift counter-steers'
    assert sol.kind == 'drift'


def test_drift_rear_is_past_its_longitudinal_peak(drift_30_15, vehicle, model):
    f = model.forces(state_vector(drift_30_15.eq))
    assert drift_30_15.kappa_R == pytest.approx(f.kappa_R)
    assert f.kappa_R > longitudinal_peak_slip(f.F_zR, vehicle.rear_tyre)
    # the rear wheel spins faster than the ground under it, the front rolls freely
    v_x = drift_30_15.eq.V * np.cos(drift_30_15.eq.beta)
    assert drift_30_15.eq.omega_R * vehicle.R_R > 1.2 * v_x
    assert f.F_xF == pytest.approx(0.0, abs=1e-6)
    # torque balances the rear longitudinal force at the wheel
    assert drift_30_15.eq.T_R == pytest.approx(f.F_xR * vehicle.R_R, rel=1e-9)


def test_mirrored_equilibrium_is_an_equilibrium(drift_30_15, model):
    right = drift_30_15.eq.mirrored()
    assert right.r < 0 and right.beta > 0 and right.delta > 0
    assert np.max(np.abs(scaled_derivative(right, model))) <= 1e-8


def test_open_loop_equilibrium_holds_briefly_then_diverges(drift_30_15, model):
    """The drift equilibrium is unstable: held open loop it stays put, a nudge grows."""
    eq = drift_30_15.eq
    x0 = state_vector(eq)
    dt, n = 0.001, 3000
    inputs = np.tile(input_vector(eq), (n, 1))
    exact = model.simulate(x0, inputs[:500], dt)
    assert np.max(np.abs(exact[:, X.BETA] - eq.beta)) < 1e-4, 'exact start: stays for 0.5 s'
    x_pert = x0.copy()
    x_pert[X.BETA] += np.radians(0.5)
    traj = model.simulate(x_pert, inputs, dt)
    dev = np.abs(traj[:, X.BETA] - eq.beta)
    assert dev[100] < np.radians(1.0), 'near the equilibrium for a short time'
    assert dev.max() > np.radians(5.0), 'then it diverges (unstable drift equilibrium)'


def test_drift_equilibrium_has_an_unstable_mode(drift_30_15, model):
    """Linearised about the drift (inputs held), one eigenvalue has a positive real part."""
    import casadi as ca
    x = ca.SX.sym('x', 9)
    A = ca.Function('A', [x], [ca.jacobian(model.f(x, input_vector(drift_30_15.eq), [0, 1])[:5],
                                           x)[:, :5]])
    eig = np.linalg.eigvals(np.asarray(A(state_vector(drift_30_15.eq))))
    assert eig.real.max() > 0.1, eig


def test_speed_grows_with_radius_at_constant_sideslip(vehicle, model):
    Vs = [solve_equilibrium(np.radians(-25.0), R, vehicle, model=model).eq.V
          for R in (10.0, 20.0, 30.0)]
    assert Vs[0] < Vs[1] < Vs[2]


def test_wet_surface_drifts_slower(vehicle, model):
    mu_wet = load_surface('wet').mu
    dry = solve_equilibrium(np.radians(-25.0), 15.0, vehicle, model=model)
    wet = solve_equilibrium(np.radians(-25.0), 15.0, vehicle, mu=mu_wet, model=model)
    assert dry.converged and wet.converged
    assert wet.eq.V < dry.eq.V
    assert np.max(np.abs(scaled_derivative(wet.eq, model, mu_wet))) <= 1e-8


def test_row_continuation_stays_on_one_branch(vehicle, model):
    betas = np.radians(-np.arange(15.0, 36.0, 1.0))
    row = solve_row(betas, 15.0, vehicle, model=model)
    assert all(s.converged for s in row)
    delta = np.array([s.eq.delta for s in row])
    V = np.array([s.eq.V for s in row])
    # one branch: deeper sideslip, more counter-steer and less speed, smoothly
    assert np.all(np.diff(delta) < 0) and np.all(np.diff(V) < 0)
    assert np.max(np.abs(np.diff(delta))) < np.radians(2.0)
    assert derivative_scale(vehicle).shape == (5,)

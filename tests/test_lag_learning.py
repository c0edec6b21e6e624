"""The powertrain lag learnt online (drift_control.lag_learning) and its use by the NMPC."""
import dataclasses
import math

import numpy as np
import pytest

from drift_control.lag_learning import LagLearner, LagLearningParams
from drift_control.ocp import load_nmpc_params
from drift_control.params import ParamError

TS = 0.02


@pytest.fixture(scope='module')
def params():
    return load_nmpc_params()


def powertrain(requests, delay: float, tau: float, signal_delay: float, noise: float, seed=0):
    """The torque measured at the end of each period of ``requests`` (one per period ``TS``):
    a transport delay and a first-order lag, integrated in 1 ms steps, measured ``signal_delay``
    late with white noise."""
    h, sub = 0.001, round(TS / 0.001)
    n = len(requests) * sub
    u = np.repeat(requests, sub)
    lagged = np.concatenate([np.full(round(delay / h), requests[0]), u])[:n]
    T, out = float(requests[0]), np.empty(n)
    for i, v in enumerate(lagged):
        T += (1.0 - math.exp(-h / tau)) * (v - T)
        out[i] = T
    seen = np.concatenate([np.full(round(signal_delay / h), requests[0]), out])[:n]
    rng = np.random.default_rng(seed)
    return seen[sub - 1::sub] + rng.normal(0.0, noise, len(requests))


def steps(seconds: float, seed=0):
    """Torque requests that step every 0.3 s within +-1500 Nm, one per period."""
    rng = np.random.default_rng(seed)
    levels = rng.uniform(-1500.0, 1500.0, int(seconds / 0.3) + 1)
    return np.repeat(levels, round(0.3 / TS))[:round(seconds / TS)]


@pytest.mark.parametrize('delay, tau', [(0.03, 0.08), (0.07, 0.12), (0.0, 0.06)])
def test_the_learnt_lag_is_the_powertrains_delay_plus_lag(delay, tau):
    params = LagLearningParams(enabled=True)
    u = steps(6.0)
    m = powertrain(u, delay, tau, params.signal_delay, noise=10.0)
    learner = LagLearner(params, TS, initial=0.11)
    for request, measured in zip(u, m):
        learner.add(request, measured)
        learner.update()
    assert learner.fits > 10
    assert learner.lag == pytest.approx(delay + tau, abs=0.012)


def test_without_excitation_or_measurement_the_lag_stays():
    params = LagLearningParams(enabled=True)
    learner = LagLearner(params, TS, initial=0.11)
    u = np.full(300, 800.0)
    for request, measured in zip(u, powertrain(u, 0.07, 0.12, 0.02, noise=10.0)):
        learner.add(request, measured)
        learner.update()
    assert (learner.lag, learner.fits) == (0.11, 0)
    u = steps(6.0)
    for request in u:   # no torque measured: nothing to fit
        learner.add(request, None)
        learner.update()
    assert (learner.lag, learner.fits) == (0.11, 0)


def test_a_gap_in_the_measurement_starts_the_window_again():
    params = LagLearningParams(enabled=True)
    learner = LagLearner(params, TS, initial=0.11)
    u = steps(6.0)
    m = powertrain(u, 0.07, 0.12, 0.02, noise=10.0)
    window = round(params.window / TS)
    for k, (request, measured) in enumerate(zip(u, m)):
        learner.add(request, None if k % (window - 1) == window - 2 else measured)
        learner.update()
    assert learner.fits == 0, 'no window is ever full'
    learner.reset()
    assert learner.lag == 0.11


def test_the_learning_params_name_the_bad_key():
    with pytest.raises(ParamError, match='lag_min/lag_max'):
        LagLearningParams(lag_min=0.3)
    with pytest.raises(ParamError, match='delay_max'):
        LagLearningParams(delay_max=0.3)
    with pytest.raises(ParamError, match='gain'):
        LagLearningParams(gain=0.0)


def test_the_nmpc_plans_with_the_learnt_lag(vp, params, eq30):
    """With learning on, every solve's parameters carry the learner's lag (the OCP's lag is a
    runtime parameter) and the plan's torque follows it; off, the configured lag."""
    from drift_control.nmpc import Nmpc, NmpcStatus
    from drift_control.signals import Reference, VehicleState
    x = [eq30.V, eq30.beta, eq30.r, eq30.omega_F, eq30.omega_R, eq30.delta]
    plans = {}
    for lag in (None, 0.11, 0.19):
        learning = dataclasses.replace(params.torque_lag_learning, enabled=bool(lag))
        ctrl = Nmpc(vp, dataclasses.replace(params, torque_lag_learning=learning))
        assert (ctrl.lag_learner is None) == (lag is None)
        if lag:
            ctrl.lag_learner.lag = lag
        seen = []
        run = ctrl._solver.solve
        ctrl._solver.solve = lambda w0, p, *a, run=run, ctrl=ctrl, seen=seen: \
            seen.append(float(ctrl.ocp.unpack_params(p).lag)) or run(w0, p, *a)
        for k in range(3):
            now = k * TS
            state = VehicleState(stamp=now, V=x[0] + 1e-9 * k, beta=x[1], r=x[2],
                                 wheel_speeds=(x[3], x[3], x[4], x[4]), delta=x[5],
                                 drive_torque=eq30.T_R + 300.0)
            res = ctrl.step(state, Reference(now, eq30), now)
            assert res.status == NmpcStatus.OK
        assert seen == [lag or params.torque_lag] * 3 and ctrl.lag == seen[0]
        plans[lag] = res.predicted_states
    assert np.array_equal(plans[None], plans[0.11])
    assert not np.allclose(plans[0.11], plans[0.19], atol=1e-3)

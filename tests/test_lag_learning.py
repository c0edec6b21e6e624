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


def powertrain(requests, delay: float, tau: float, noise: float, every: float = 0.01, seed=0):
    """The wheel torque at instants ``every`` apart of ``requests`` (one per period ``TS``,
    sent at ``k TS``): a transport delay and a first-order lag, integrated in 1 ms steps, with
    white noise. Returns (instants, torques)."""
    h, sub = 0.001, round(TS / 0.001)
    n = len(requests) * sub
    u = np.repeat(requests, sub)
    lagged = np.concatenate([np.full(round(delay / h), requests[0]), u])[:n]
    T, out = float(requests[0]), np.empty(n)
    for i, v in enumerate(lagged):
        T += (1.0 - math.exp(-h / tau)) * (v - T)
        out[i] = T
    pick = np.arange(round(every / h) - 1, n, round(every / h))
    rng = np.random.default_rng(seed)
    return (pick + 1) * h, out[pick] + rng.normal(0.0, noise, len(pick))


def steps(seconds: float, seed=0):
    """Torque requests that step every 0.3 s within +-1500 Nm, one per period."""
    rng = np.random.default_rng(seed)
    levels = rng.uniform(-1500.0, 1500.0, int(seconds / 0.3) + 1)
    return np.repeat(levels, round(0.3 / TS))[:round(seconds / TS)]


def drive(learner, requests, samples, latency=0.02, update=lambda k: True, skip=()):
    """Each period: the samples that have arrived (``latency`` after their instant), a fit if
    one is due (when ``update(k)``), then the period's request; the lag after each period."""
    t_m, m = samples
    seen, lags = 0, []
    for k, request in enumerate(requests):
        now = k * TS
        while seen < len(t_m) and t_m[seen] + latency <= now + 1e-9:
            learner.measure(t_m[seen], m[seen])
            seen += 1
        if update(k):
            learner.update()
        if k not in skip:
            learner.request(now, request)
        lags.append(learner.lag)
    return lags


@pytest.mark.parametrize('delay, tau', [(0.03, 0.08), (0.07, 0.12), (0.0, 0.06)])
@pytest.mark.parametrize('every', [0.01, 0.02])
def test_the_learnt_lag_is_the_powertrains_delay_plus_lag(delay, tau, every):
    """Torque samples at 100 Hz (a torque unit's) or one a period (the state's), each with
    its instant."""
    u = steps(6.0)
    learner = LagLearner(LagLearningParams(enabled=True), TS, initial=0.11)
    drive(learner, u, powertrain(u, delay, tau, noise=10.0, every=every))
    assert learner.fits > 10
    assert learner.lag == pytest.approx(delay + tau, abs=0.012)


def test_a_fit_sees_the_same_data_whenever_it_runs():
    """A fit is taken with a request; fitted then or at the next period's start (``update``
    from ``Nmpc.prepare`` or from ``Nmpc.step``): the same lags."""
    u = steps(6.0)
    samples = powertrain(u, 0.05, 0.09, noise=10.0)
    params = LagLearningParams(enabled=True)
    every = drive(LagLearner(params, TS, 0.11), u, samples)
    late = LagLearner(params, TS, 0.11)
    lags = drive(late, u, samples, update=lambda k: k % 2 == 0)
    assert late.fits > 10
    assert lags[::2] == every[::2]


def test_without_excitation_or_measurement_the_lag_stays():
    params = LagLearningParams(enabled=True)
    learner = LagLearner(params, TS, initial=0.11)
    u = np.full(300, 800.0)
    drive(learner, u, powertrain(u, 0.07, 0.12, noise=10.0))
    assert (learner.lag, learner.fits) == (0.11, 0)
    drive(learner, steps(6.0), (np.zeros(0), np.zeros(0)))   # nothing measured
    assert (learner.lag, learner.fits) == (0.11, 0)


def test_missed_periods_or_an_interruption_start_the_window_again():
    params = LagLearningParams(enabled=True)
    u = steps(6.0)
    samples = powertrain(u, 0.07, 0.12, noise=10.0)
    window = round(params.window / TS)
    learner = LagLearner(params, TS, initial=0.11)
    missed = {k + i for k in range(window - 4, len(u), window - 3) for i in range(3)}
    drive(learner, u, samples, skip=missed)
    assert learner.fits == 0, 'no window is ever full'
    learner = LagLearner(params, TS, initial=0.11)

    def interrupted(k):   # a fallback now and then (the learner told before the update)
        if k % (window - 1) == window - 2:
            learner.interrupt()
        return True

    drive(learner, u, samples, update=interrupted)
    assert learner.fits == 0
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


def test_the_nmpc_learns_from_its_own_requests_and_the_torque_samples(vp, params, eq30):
    """Every solved step hands the learner its request and the state's drive torque (at the
    state's instant less ``signal_delay``); torque samples, once fed, replace the state's; a
    step below ``speed_min`` or in fallback starts the window again."""
    from drift_control.nmpc import Nmpc, NmpcStatus
    from drift_control.signals import Reference, VehicleState
    learning = dataclasses.replace(params.torque_lag_learning, enabled=True)
    ctrl = Nmpc(vp, dataclasses.replace(params, torque_lag_learning=learning))
    x = [eq30.V, eq30.beta, eq30.r, eq30.omega_F, eq30.omega_R, eq30.delta]

    def step(k, V=x[0]):
        now = k * TS
        state = VehicleState(stamp=now, V=V, beta=x[1], r=x[2],
                             wheel_speeds=(x[3], x[3], x[4], x[4]), delta=x[5],
                             drive_torque=eq30.T_R)
        return ctrl.step(state, Reference(now, eq30), now)

    for k in range(3):
        assert step(k).status == NmpcStatus.OK
    assert ctrl.lag_learner.window == (3, 3)
    assert ctrl.lag_learner._measured[-1] == (2 * TS - learning.signal_delay, eq30.T_R)
    ctrl.observe_torque(2 * TS, 1234.0)
    step(3)
    assert ctrl.lag_learner.window == (4, 4)   # the sample, not the state's torque
    assert ctrl.lag_learner._measured[-1] == (2 * TS, 1234.0)
    step(4, V=learning.speed_min - 0.1)
    assert ctrl.lag_learner.window == (0, 0)
    assert step(5, V=math.nan).status != NmpcStatus.OK
    assert ctrl.lag_learner.window == (0, 0)


def test_a_future_stamped_measurement_does_not_stop_the_learning():
    """Measurements older than the newest are ignored: one stamped in the future goes with the
    next request instead of shutting every later one out."""
    u = steps(6.0)
    learner = LagLearner(LagLearningParams(enabled=True), TS, initial=0.11)
    learner.measure(1e6, 500.0)
    drive(learner, u, powertrain(u, 0.07, 0.12, noise=10.0))
    assert learner.fits > 10
    assert learner.lag == pytest.approx(0.19, abs=0.012)

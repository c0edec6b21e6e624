"""Simulator session, lock-step gate, driver and metrics without ROS."""
import dataclasses
import math

import numpy as np
import pytest

from drift_control.signals import Command, Mode
from drift_sim import metrics
from drift_sim.driver import Driver, load_driver_params
from drift_sim.lockstep import LockstepGate
from drift_sim.scenario import load_scenario, scenario_names
from drift_sim.simulator import Simulator

SCENARIOS = ('alternating_dry', 'steady_dry', 'steady_wet', 'semi_auto_dry', 'semi_auto_wet',
             'eps_limited_dry')


def test_every_required_scenario_loads_with_its_path_and_plant():
    assert set(SCENARIOS) <= set(scenario_names())
    for name in SCENARIOS:
        loaded = load_scenario(name)
        assert loaded.path.length > 50.0
        assert loaded.mu > 0.0
    eps = load_scenario('eps_limited_dry')
    assert eps.plant.steering.torque_max == 30.0 and eps.scenario.expect_spin


def test_overrides_reach_surface_and_plant():
    loaded = load_scenario('steady_dry', ['surface.mu=0.55', 'plant.lsd.locking=1.0'])
    assert loaded.mu == 0.55 and loaded.plant.lsd.locking == 1.0
    from drift_control.params import ParamError
    with pytest.raises(ParamError, match='surfce'):
        load_scenario('steady_dry', ['surfce.mu=0.5'])


def test_gate_waits_for_the_command_of_the_step_and_reports_timeouts():
    gate = LockstepGate(dt=0.01, command_period=0.02, timeout=0.5, startup_timeout=5.0)
    assert not gate.ready(0.0, 0.0) and not gate.ready(0.0, 4.9), 'the first state waits too'
    assert gate.ready(0.0, 5.1) and gate.timeouts == 1, 'startup timeout, counted'
    assert gate.ready(0.01, 5.1), 'between command periods nothing is due'
    assert not gate.ready(0.02, 5.2)
    gate.offer(Command(0.02, 0.0, 0.0, 0.0))
    assert gate.ready(0.02, 6.0) and gate.ready(0.03, 6.0) and not gate.ready(0.04, 6.0)
    gate.offer(Command(0.04, 0.0, 0.0, 0.0))
    assert gate.ready(0.04, 6.1) and gate.timeouts == 1
    assert not gate.ready(0.06, 7.0) and gate.ready(0.06, 7.6) and gate.timeouts == 2


def test_gate_first_command_releases_the_initial_state():
    gate = LockstepGate(0.01, 0.02, 0.5, 5.0)
    assert not gate.ready(0.0, 0.0)
    gate.offer(Command(0.0, 0.0, 0.0, 0.0))
    assert gate.ready(0.0, 0.1) and gate.ready(0.01, 0.1) and not gate.ready(0.02, 0.1)
    assert gate.timeouts == 0


def test_gate_can_wait_for_the_reference_of_the_state_too():
    gate = LockstepGate(0.01, 0.02, 0.5, 5.0, wait_reference=True)
    gate.offer(Command(0.02, 0.0, 0.0, 0.0))
    gate.offer_reference(0.0)
    assert not gate.ready(0.02, 0.0), 'command without a reference of this period'
    gate.offer_reference(0.01)
    assert gate.ready(0.02, 0.1) and gate.timeouts == 0


def test_driver_steers_through_its_reaction_delay():
    drift_circle = 'path={type: circle, radius: 15.0, sideslip: {beta_deg: 30.0}}'
    loaded = load_scenario('semi_auto_dry', [drift_circle])
    p = load_driver_params(loaded.driver_raw)
    sim = Simulator(loaded)
    driver = Driver(p, loaded.path, sim.dt)
    state = sim.reset()
    driver.reset(0.0, s=0.0)
    driver.reset(driver.intent(state), s=0.0)
    base = driver.delta
    n = int(round(p.reaction_delay / sim.dt))
    skidding = dataclasses.replace(state, beta=-0.8)   # beyond the desired -30 deg
    outs = [driver.steer(skidding)[0] for _ in range(n + 10)]
    assert max(abs(o - base) for o in outs[:n]) < 1e-9, 'no reaction before the delay'
    assert outs[-1] < base - 0.02, 'then it counter-steers more against too much left sideslip'


def test_torque_only_scenario_steers_by_the_driver_and_stays_on_a_grip_circle():
    grip_circle = 'path={type: circle, radius: 15.0, sideslip: {beta_deg: 0.0}}'
    loaded = load_scenario('semi_auto_dry', ['duration=5.0', grip_circle])
    sim = Simulator(loaded)
    sim.reset()
    e_y = []
    while not sim.done:    # the NMPC's steering proposal is ignored; moderate torque
        sim.step(Command(sim.t, -0.3, 0.0, 600.0, Mode.TORQUE_ONLY))
        e_y.append(sim.sample().e_y)
    assert sim.truth.state.delta > 0.05, 'the driver steers into the left circle'
    assert max(abs(e) for e in e_y) < 1.0, 'path feedback keeps the driver on the circle'


def test_metrics_on_synthetic_series():
    t = np.arange(0.0, 10.0, 0.01)
    beta_ref = np.full_like(t, -0.5)
    beta = beta_ref + 0.02 * np.sin(2.0 * np.pi * t)
    assert metrics.beta_rms_error(t, beta, beta_ref, [(0, 10)]) == pytest.approx(
        0.02 / math.sqrt(2), rel=0.02)
    assert metrics.time_in_drift(t, beta, math.radians(10)) == pytest.approx(10.0, abs=0.02)
    assert math.isnan(metrics.spin_time(t, beta))
    spun = np.where(t > 6.0, -1.6, beta)
    assert metrics.spin_time(t, spun) == pytest.approx(6.01, abs=0.011)
    # a car that stopped at 8 s: its sideslip beyond 75 deg from then on is no spin
    stopped = np.where(t > 8.0, -1.6, beta)
    V = np.where(t > 8.0, 0.05, 9.0)
    assert math.isnan(metrics.spin_time(t, stopped, V=V))
    assert metrics.spin_time(t, spun, V=V) == pytest.approx(6.01, abs=0.011)
    out = metrics.summary(t, spun, beta_ref, 0.1 * t, [(0, 5)], 5.0, math.radians(10),
                          [0.001, 0.002, 0.010], wall_time=1.0)
    assert out['spun'] and out['max_abs_e_y_m'] == pytest.approx(0.999)
    assert out['real_time_factor'] == pytest.approx(9.99)

"""The plant simulator: energy and consistency checks of the double-track model (drift_sim)."""
import math

import numpy as np
import pytest

from drift_control.params import ParamError
from drift_control.signals import Command, Mode
from drift_sim.model import S, Y, PlantModel
from drift_sim.params import load_plant_params
from drift_sim.plant import Plant

NO_FIELD = ('road.variation=0.0',)


@pytest.fixture(scope='module')
def params():
    return load_plant_params(overrides=NO_FIELD)


@pytest.fixture(scope='module')
def model(params):
    return PlantModel(params)


def run(plant, command, seconds, steer=None, brake=0.0):
    """Step ``plant`` for ``seconds``; return the ground-truth states (n, NS)."""
    states = []
    for _ in range(int(round(seconds / plant.p.step))):
        plant.step(command, steer=steer, brake=brake)
        states.append(plant.truth.x)
    return np.array(states)


def effective_mass(p):
    """Body mass plus the wheels' and driveline's rotating inertia seen in translation [kg]."""
    w = p.wheels
    return p.body.m + 2 * w.I_wF / w.R_F ** 2 + (2 * w.I_wR + w.I_drive) / w.R_R ** 2


def test_coasting_decelerates_by_drag_and_rolling_resistance(params, model):
    plant = Plant(params, mu=1.0, model=model)
    plant.reset(V=25.0)
    x = run(plant, Command(0.0, 0.0, 0.0, 0.0), 2.0)
    V = np.hypot(x[:, S.VX], x[:, S.VY])
    assert np.all(np.diff(V) < 0.0), 'a coasting car never speeds up'
    V_mid = V[len(V) // 2]
    expected = (params.body.c_drag * V_mid ** 2 + params.body.c_roll * params.body.m
                * params.body.g) / effective_mass(params)
    measured = (V[0] - V[-1]) / (len(V) - 1) / params.step
    assert measured == pytest.approx(expected, rel=0.1)
    assert abs(x[-1, S.Y]) < 1e-6 and abs(x[-1, S.R]) < 1e-9, 'no yaw without steering'


def test_straight_line_acceleration_matches_the_drive_torque(params, model):
    plant = Plant(params, mu=1.0, model=model)
    T = 2000.0
    plant.reset(V=10.0, drive_torque=T)
    x = run(plant, Command(0.0, 0.0, 0.0, T), 1.5)
    V = np.hypot(x[:, S.VX], x[:, S.VY])
    i, j = 50, 149     # after the transport delay and the torque lag
    V_mid = V[(i + j) // 2]
    p = params
    force = T / p.wheels.R_R - p.body.c_drag * V_mid ** 2 - p.body.c_roll * p.body.m * p.body.g
    expected = force / effective_mass(p)
    measured = (V[j] - V[i]) / ((j - i) * p.step)
    assert measured == pytest.approx(expected, rel=0.05)
    assert x[-1, S.OMEGA_RL] * p.wheels.R_R > V[-1], 'a driven wheel turns faster than it rolls'


def test_engine_braking_stops_the_rear_wheels_but_never_reverses_them(params, model):
    plant = Plant(params, mu=1.0, model=model)
    plant.reset(V=3.0)
    T = params.powertrain.T_min
    x = run(plant, Command(0.0, 0.0, 0.0, T), 2.0)
    rear = x[:, [S.OMEGA_RL, S.OMEGA_RR]]
    assert rear.min() > -0.5, 'engine braking turned a rear wheel backwards'
    assert np.hypot(x[-1, S.VX], x[-1, S.VY]) < 2.0, 'the braked car slows down'


def test_left_and_right_turns_are_mirror_images(params, model):
    runs = []
    for sign in (1.0, -1.0):
        plant = Plant(params, mu=1.0, model=model, seed=3)
        plant.reset(V=15.0)
        runs.append(run(plant, Command(0.0, sign * 0.08, 0.0, 800.0), 3.0))
    left, right = runs
    assert left[-1, S.R] > 0.3, 'a positive steering angle turns left'
    for name in ('VX', 'X', 'T_DRIVE'):
        np.testing.assert_allclose(left[:, S[name]], right[:, S[name]], rtol=1e-7, atol=1e-7)
    for name in ('VY', 'R', 'Y', 'YAW', 'DELTA'):
        np.testing.assert_allclose(left[:, S[name]], -right[:, S[name]], rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(left[:, S.OMEGA_RL], right[:, S.OMEGA_RR], rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize('locking', [0.0, 1.0])
def test_differential_open_spins_the_inner_wheel_locked_does_not(locking, model):
    p = load_plant_params(overrides=NO_FIELD + (f'lsd.locking={locking}', 'lsd.preload=0'))
    plant = Plant(p, mu=1.0, model=PlantModel(p))
    plant.reset(V=12.0)
    x = run(plant, Command(0.0, 0.12, 0.0, 2500.0), 2.0)
    inner, outer = x[-50:, S.OMEGA_RL], x[-50:, S.OMEGA_RR]     # left turn: left is inner
    slip = np.mean(inner - outer)
    if locking == 0.0:
        assert slip > 5.0, f'open differential: unloaded inner wheel should spin up, got {slip}'
    else:
        assert abs(slip) < 1.5, f'locked differential keeps both speeds close, got {slip}'


def test_eps_torque_limit_keeps_the_wheels_from_the_requested_angle(model):
    reached = {}
    for torque_max in (30.0, 150.0):
        p = load_plant_params(overrides=NO_FIELD + (f'steering.torque_max={torque_max}',))
        plant = Plant(p, mu=1.0, model=PlantModel(p))
        plant.reset(V=20.0)
        request = Command(0.0, 0.10, 0.0, 1200.0, Mode.FULL)
        states, torques = [], []
        for _ in range(150):
            hands_off = plant.step(request).steering_torque
            states.append(plant.truth.state)
            torques.append(plant.truth.y[Y.STEER_TORQUE])
        reached[torque_max] = states[-1].delta
        assert max(abs(t) for t in torques) <= torque_max + 1e-3
        assert abs(hands_off) < 1.0, 'the driver applies no torque when the actuator steers'
    assert reached[150.0] == pytest.approx(0.10, abs=0.005), 'a strong actuator tracks'
    assert reached[30.0] < 0.10 - 0.02, 'the 30 Nm EPS loses against the aligning moment'


def test_same_seed_gives_the_same_trajectory_and_measurements(model):
    p = load_plant_params()
    out = []
    for seed in (7, 7, 8):
        plant = Plant(p, mu=1.0, seed=seed, model=PlantModel(p))
        plant.reset(V=12.0)
        meas = [plant.step(Command(0.0, 0.05, 0.0, 1500.0)) for _ in range(100)]
        out.append((plant.truth.x, np.array([[m.V, m.beta, m.r, m.x] for m in meas])))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    assert not np.array_equal(out[0][1], out[2][1]), 'another seed, other noise'


def test_friction_field_stays_within_its_band_and_varies():
    p = load_plant_params()
    plant = Plant(p, mu=0.6, seed=11)
    gx, gy = np.meshgrid(np.linspace(-100, 100, 201), np.linspace(-100, 100, 201))
    mu = plant.friction_at(gx, gy)
    assert np.max(np.abs(mu - 0.6)) <= p.road.variation + 1e-12
    assert np.ptp(mu) > p.road.variation, 'the field actually varies over a skid pad'
    other = Plant(p, mu=0.6, seed=12).friction_at(gx, gy)
    assert not np.allclose(mu, other)


def test_drive_torque_waits_for_the_transport_delay(params, model):
    plant = Plant(params, mu=1.0, model=model)
    plant.reset(V=10.0)
    applied = []
    for _ in range(10):
        plant.step(Command(0.0, 0.0, 0.0, 3000.0))
        applied.append(plant.truth.x[S.T_DRIVE])
    k = int(round(params.powertrain.delay / params.step))
    assert max(applied[:k - 1]) < 1e-9
    assert applied[-1] > 0.3 * 3000.0 * (1 - math.exp(-(10 - k) * params.step
                                                       / params.powertrain.tau))


def test_measurement_is_delayed_per_signal(model):
    p = load_plant_params(overrides=('measurement.r.delay=0.05', 'measurement.r.std=0.0'))
    plant = Plant(p, mu=1.0, model=PlantModel(p))
    plant.reset(V=15.0)
    truth, meas = [], []
    for _ in range(60):
        meas.append(plant.step(Command(0.0, 0.1, 0.0, 500.0)).r)
        truth.append(plant.truth.state.r)
    np.testing.assert_allclose(meas[5:], truth[:-5], atol=1e-12)


def test_a_wrong_override_is_named():
    with pytest.raises(ParamError, match='lsd'):
        load_plant_params(overrides=('lsd.lockng=0.5',))
    with pytest.raises(ParamError, match='measurement'):
        load_plant_params(overrides=('measurement.speed={std: 1, delay: 0}',))

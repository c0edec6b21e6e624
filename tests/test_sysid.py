"""Identification of the controller's model from recorded driving (issue 23).

The logs are made in-process in about a second: the controller's own single-track model
(``ModelPlant``, with measurement noise) under the scripted manoeuvre driver, with tyre
coefficients the fit does not start from, so the truth is known.
"""
import dataclasses
import math

import numpy as np
import pytest

from drift_control import sysid
from drift_control.model_plant import ModelPlant
from drift_control.params import ParamError, load_vehicle
from drift_control.powertrain_fit import fit_powertrain
from drift_control.prediction import predict
from drift_control.vehicle import NX, VehicleModel, X
from drift_sim.manoeuvre import Manoeuvre, ScriptedDriver, Segment, load_manoeuvre

TRUE = {'front_tyre.lateral.B': 12.0, 'front_tyre.lateral.D': 0.93, 'rear_tyre.pKy1': 20.0,
        'rear_tyre.pDy1': 0.92, 'rear_tyre.pKx1': 18.0, 'rear_tyre.rBx1': 16.0}
NOISE = {'V': 0.05, 'beta': 0.005, 'r': 0.005, 'omega': 0.1, 'delta': 0.001}
SETTINGS = sysid.SysIdSettings(block_s=4.0)
GRIP = (Segment('circle', 14.0, 8.0, (8.0, 18.0)),
        Segment('steps', 8.0, 3.0, (12.0,), period=1.0),
        Segment('sweep', 8.0, 3.0, (12.0,), f0=0.3, f1=2.0))
BURSTS = (Segment('circle', 4.0, 9.0, (9.0,)),
          Segment('burst', 13.66, 9.0, (9.0,), period=6.83, power_s=2.0, drive_g=0.52,
                  beta_peak_deg=30.0))


@pytest.fixture(scope='module')
def prior():
    return load_vehicle('m3_competition')


def _drive(prior, segments, seed=1, truth=TRUE):
    """The manoeuvre on the single-track model whose tyres are ``truth``: a ``Log``."""
    true = sysid.with_values(prior, truth)
    plant = ModelPlant(true, noise=NOISE, seed=seed, substep=0.0025)
    x0 = np.zeros(NX)
    x0[X.V], x0[X.OMEGA_F], x0[X.OMEGA_R] = 8.0, 8.0 / true.R_F, 8.0 / true.R_R
    state = plant.reset(x0)
    prog = Manoeuvre(segments=segments)
    driver = ScriptedDriver(prog, prior, 1.0, 0.01)
    rows = []
    for _ in range(int(round(prog.duration / 0.01))):
        cmd = driver.command(state, plant.t)
        state = plant.step(cmd, 0.01)
        rows.append((state.stamp, state.V, state.beta, state.r, state.omega_F, state.omega_R,
                     state.delta, state.drive_torque, cmd.drive_torque))
    a = np.array(rows).T
    return sysid.Log(*a)


@pytest.fixture(scope='module')
def full_log(prior):
    return _drive(prior, GRIP + BURSTS)


@pytest.fixture(scope='module')
def grip_log(prior):
    return _drive(prior, GRIP)


@pytest.fixture(scope='module')
def fit(full_log, prior):
    return sysid.identify(full_log, prior, 1.0, settings=SETTINGS)


def test_the_fit_finds_the_tyres_of_the_car_that_drove(fit, full_log):
    assert np.degrees(np.abs(full_log.beta)).max() > 15.0, 'the bursts must drift'
    for p in fit.params:
        truth = TRUE.get(p.name, p.prior)   # C coefficients: the prior is the truth
        assert p.value == pytest.approx(truth, rel=0.05), p
        assert 0.0 < p.ci95 < 0.15 * p.value, p
    # the prior was off by 7-20 %: the fit moved every perturbed value most of the way
    for name, truth in TRUE.items():
        p = next(q for q in fit.params if q.name == name)
        assert abs(p.value - truth) < 0.35 * abs(p.prior - truth), p


def test_identified_model_predicts_held_out_driving_better_than_the_data_sheet(fit, full_log,
                                                                                  prior):
    _, held = sysid.split(full_log, SETTINGS)
    ident = predict(fit.vehicle, full_log, held, 1.0, SETTINGS)
    sheet = predict(prior, full_log, held, 1.0, SETTINGS)
    assert len(ident.t0) >= 10
    assert ident.rms_r < 0.5 * sheet.rms_r
    assert ident.rms_beta < 0.5 * sheet.rms_beta
    assert ident.rms_beta < math.radians(0.5)


def test_the_symbolic_fit_model_is_the_controllers_model(prior, full_log):
    """The fit evaluates vehicle.rhs itself: at the prior's values it is the NMPC's model."""
    data = sysid.smooth(full_log, SETTINGS.window_s)
    mask = np.zeros(len(full_log.t), bool)
    mask[500:520] = True
    names = sysid.DEFAULT_FIT + ('I_z',)
    problem = sysid.EquationError(prior, names, 1.0, data, mask)
    got = problem.predicted([sysid.value_of(prior, n) for n in names])
    model = VehicleModel(prior, 1, 'free_rolling')
    for k, row in zip(np.nonzero(mask)[0], got):
        want = model.rhs(data.x[k], data.u[k], 0.0, 1.0)[[X.V, X.BETA, X.R, X.OMEGA_R]]
        assert row == pytest.approx(want, rel=1e-9, abs=1e-9)


def test_a_log_without_drift_cannot_identify_the_rear_peak(prior, grip_log):
    log = grip_log
    with pytest.raises(sysid.IdentificationError,
                       match=r'^rear_tyre\.pCy1, rear_tyre\.pDy1: no sideslip beyond the grip '
                             r'limit') as err:
        sysid.identify(log, prior, 1.0, settings=SETTINGS)
    assert '\n' not in str(err.value)
    # what grip driving does identify, it still fits
    fit = sysid.identify(log, prior, 1.0, names=('front_tyre.lateral.B', 'rear_tyre.pKy1'),
                         settings=SETTINGS)
    values = {p.name: p.value for p in fit.params}
    assert values['front_tyre.lateral.B'] == pytest.approx(12.0, rel=0.1)
    assert values['rear_tyre.pKy1'] == pytest.approx(20.0, rel=0.1)


def test_the_yaw_inertia_is_fitted_when_asked(prior, full_log):
    wrong = sysid.with_values(prior, {'I_z': 2400.0})     # the car that drove has 3000
    fit = sysid.identify(full_log, wrong, 1.0, names=sysid.DEFAULT_FIT + ('I_z',),
                         settings=SETTINGS)
    p = next(q for q in fit.params if q.name == 'I_z')
    assert p.ci95 < 0.05 * p.value
    assert abs(p.value - prior.I_z) < max(p.ci95, 0.03 * prior.I_z)


def test_a_parameter_the_log_does_not_excite_is_refused_by_its_confidence(prior):
    """Without wheelspin the peak of the driving force is free to trade against its stiffness
    (the wheelspin check waived, so that the confidence interval is what refuses it)."""
    truth = {**TRUE, 'rear_tyre.rBx1': prior.rear_tyre.rBx1, 'rear_tyre.pDx1': 1.05}
    with pytest.raises(sysid.IdentificationError,
                       match=r'^rear_tyre\.pDx1: not identified by this log .*95 % CI'):
        sysid.identify(_drive(prior, GRIP, truth=truth), prior, 1.0,
                       names=('rear_tyre.pKx1', 'rear_tyre.pDx1'),
                       settings=dataclasses.replace(SETTINGS, min_spin_s=0.0))


def test_the_pure_driving_peak_needs_wheelspin_at_small_slip_angles(prior, full_log):
    """The drift spins the rear wheel at 15-35 deg of slip angle only: the log gives the
    combined-slip weight times the peak, not the peak."""
    with pytest.raises(sysid.IdentificationError,
                       match=r'^rear_tyre\.pDx1: no wheelspin at small slip angles') as err:
        sysid.identify(full_log, prior, 1.0, names=sysid.DEFAULT_FIT + ('rear_tyre.pDx1',),
                       settings=SETTINGS)
    assert '\n' not in str(err.value)
    # power-on on the straight spins the rear at a slip angle near zero: the peak is fitted
    truth = {'rear_tyre.pKx1': 18.0, 'rear_tyre.pDx1': 1.05}
    launches = (Segment('burst', 12.0, 0.0, (8.0,), period=4.0, power_s=1.0, drive_g=0.8,
                        beta_peak_deg=6.0),)
    log = _drive(prior, GRIP + launches, truth=truth)
    fit = sysid.identify(log, prior, 1.0, names=('rear_tyre.pKx1', 'rear_tyre.pDx1'),
                         settings=SETTINGS)
    assert fit.evidence['prior']['spin_straight_s'] >= SETTINGS.min_spin_s
    for p in fit.params:
        assert p.value == pytest.approx(truth[p.name], rel=0.05), p


def test_powertrain_delay_and_lag_are_recovered():
    rng = np.random.default_rng(0)
    dt, n = 0.01, 3000
    t = dt * np.arange(n)
    T_cmd = np.repeat(rng.uniform(-500.0, 4000.0, n // 50), 50)
    T, state = np.empty(n), 0.0
    a = math.exp(-dt / 0.08)
    for i in range(n):                       # 30 ms delay, 80 ms lag
        T[i] = state
        state = a * state + (1 - a) * T_cmd[max(i - 3, 0)]
    z = np.zeros(n)
    log = sysid.Log(t, z + 10, z, z, z, z, z, T + rng.normal(0, 10.0, n), T_cmd)
    lag = fit_powertrain(log)
    assert lag.delay == pytest.approx(0.03, abs=1e-9)
    assert lag.tau == pytest.approx(0.08, abs=max(lag.tau_ci95, 0.002))
    assert lag.torque_lag == pytest.approx(0.11, abs=0.005)
    assert fit_powertrain(sysid.Log(t, *[z] * 7, np.full(n, np.nan))) is None


def test_the_manoeuvre_files_load_and_a_bad_key_is_named(tmp_path):
    for name in ('sysid', 'sysid_wet'):
        prog = load_manoeuvre(name)
        assert 170.0 <= prog.duration <= 185.0
        assert {'circle', 'steps', 'sweep', 'burst'} <= {s.kind for s in prog.segments}
    assert 'drift' in {s.kind for s in load_manoeuvre('sysid').segments}
    bad = tmp_path / 'bad.yaml'
    bad.write_text('segments:\n  - {kind: circle, duration: 5.0, steer_deg: 8.0, speed: [6.0], '
                   'on: 1.0}\n')
    with pytest.raises(ParamError, match=r'bad\.yaml\.segments\[0\]: unknown key'):
        load_manoeuvre(str(bad))


def test_a_burst_slides_past_the_grip_limit_and_regrips(prior):
    """The scripted driver on the simulator's double-track car: into a drift and back out."""
    from drift_sim.scenario import load_scenario
    from drift_sim.simulator import Simulator
    sim = Simulator(load_scenario('sysid_dry'))
    driver = ScriptedDriver(Manoeuvre(segments=BURSTS[:1] + (BURSTS[1],)), prior, 1.0, sim.dt)
    state, beta = sim.reset(), []
    for _ in range(int(round(17.66 / sim.dt))):
        state = sim.step(driver.command(state, sim.t))
        beta.append(abs(sim.plant.truth.state.beta))
    beta = np.degrees(beta)
    assert beta.max() > 12.0            # well past the rear's ~7 deg peak slip
    assert beta.max() < 60.0            # caught, not spun
    assert beta[-100:].max() < 6.0      # regripped at the end of each cycle


def test_a_drift_segment_holds_its_sideslip_and_regrips(prior):
    """Power on to 30 deg, held there 6 s by the throttle loop, then out to grip again."""
    from drift_sim.scenario import load_scenario
    from drift_sim.simulator import Simulator
    sim = Simulator(load_scenario('sysid_dry'))
    seg = Segment('drift', 18.0, 9.0, (9.0,), period=18.0, power_s=2.0, drive_g=0.52,
                  beta_peak_deg=30.0, hold_s=6.0)
    driver = ScriptedDriver(Manoeuvre(segments=(BURSTS[0], seg)), prior, 1.0, sim.dt)
    state, t, beta = sim.reset(), [], []
    for _ in range(int(round((BURSTS[0].duration + seg.duration) / sim.dt))):
        state = sim.step(driver.command(state, sim.t))
        t.append(sim.t)
        beta.append(abs(sim.plant.truth.state.beta))
    t, beta = np.array(t), np.degrees(beta)
    start = t[np.argmax(beta > 29.0)]          # the hold starts as the sideslip nears 30 deg
    assert beta.max() < 40.0                    # the entry's overshoot caught
    held = beta[(t > start + 2.5) & (t < start + 5.5)]   # settled after the entry's swing
    assert 26.0 < held.min() and held.max() < 34.0
    assert abs(held.mean() - 30.0) < 2.0
    assert beta[-50:].max() < 6.0               # regripped at the end


def _write_bag(path, log, with_state=True):
    ser = pytest.importorskip('rclpy.serialization')
    msgs = pytest.importorskip('drift_msgs.msg')
    from drift_tools.bag_writer import BagWriter
    with BagWriter(path) as bag:
        if with_state:
            bag.add_topic('/vehicle/state', 'drift_msgs/msg/VehicleState')
        bag.add_topic('/drift/command', 'drift_msgs/msg/DriftCommand')
        for k, t in enumerate(log.t):
            stamp = dict(sec=int(t), nanosec=int(round((t % 1) * 1e9)))
            ns = int(round(t * 1e9))
            if with_state:
                st = msgs.VehicleState(v=log.V[k], beta=log.beta[k], r=log.r[k],
                                       delta=log.delta[k], drive_torque=log.T[k])
                st.wheel_speeds = [log.omega_F[k]] * 2 + [log.omega_R[k]] * 2
                st.header.stamp.sec, st.header.stamp.nanosec = stamp['sec'], stamp['nanosec']
                bag.write('/vehicle/state', ser.serialize_message(st), ns)
            cmd = msgs.DriftCommand(mode=1, delta=log.delta[k], drive_torque=log.T_cmd[k])
            cmd.header.stamp.sec, cmd.header.stamp.nanosec = stamp['sec'], stamp['nanosec']
            bag.write('/drift/command', ser.serialize_message(cmd), ns + 1)
    return path


def test_identify_script_writes_a_vehicle_that_loads_and_a_report(tmp_path, full_log, prior,
                                                                  capsys):
    from conftest import load_script
    bag = _write_bag(tmp_path / 'bag', full_log)
    out = tmp_path / 'cfg' / 'm3_identified.yaml'
    rc = load_script('identify').main([str(bag), '--vehicle', 'm3_competition', '--out',
                                       str(out), '--report', str(tmp_path / 'rep')])
    assert rc == 0, capsys.readouterr().err
    car = load_vehicle(out)
    assert car.rear_tyre.pDy1 == pytest.approx(TRUE['rear_tyre.pDy1'], rel=0.05)
    assert car.m == prior.m and car.front_tyre.longitudinal == prior.front_tyre.longitudinal
    import yaml
    record = yaml.safe_load(out.read_text())['_identified']
    assert record['bag'].endswith('bag') and 'rear_tyre.pDy1' in record['parameters']
    assert car.torque_lag == record['powertrain']['nmpc_torque_lag_s']   # the NMPC's, this car
    assert record['held_out']['identified']['rms_beta_deg'] < \
        record['held_out']['data_sheet']['rms_beta_deg']
    for name in ('report.md', 'fit.json', 'predictions.png', 'tyres.png'):
        assert (tmp_path / 'rep' / name).stat().st_size > 0


@pytest.mark.parametrize('case, code, words', [
    ('no_state', 2, '/vehicle/state'),
    ('no_bag', 2, 'not a bag directory'),
    ('unknown_vehicle', 2, "vehicle 'no_such_car'"),
    ('grip_only', 1, 'no sideslip beyond the grip limit'),
])
def test_identify_script_refuses_bad_input_in_one_line(tmp_path, prior, capsys, case, code,
                                                       words):
    from conftest import load_script
    vehicle = 'no_such_car' if case == 'unknown_vehicle' else 'm3_competition'
    bag = tmp_path / 'bag'
    if case == 'grip_only':
        _write_bag(bag, _drive(prior, GRIP + GRIP))
    elif case != 'no_bag':
        short = sysid.Log(*(np.asarray(c)[:300] for c in _short_log()))
        _write_bag(bag, short, with_state=case != 'no_state')
    rc = load_script('identify').main([str(bag), '--vehicle', vehicle, '--no-figures'])
    err = capsys.readouterr().err
    assert rc == code
    assert err.startswith('identify: ') and words in err
    assert err.count('\n') == 1 and 'Traceback' not in err


def _short_log():
    t = 0.01 * np.arange(300)
    z = np.zeros(300)
    return (t, z + 10.0, z, z, z + 30.0, z + 30.0, z, z, z)

"""drift_sim.sensors: seeded and reproducible, each unit's rate and latency, quantisation, the
IMU's bias and roll, faults, and parameters that name the bad key."""
import math
from dataclasses import replace

import numpy as np
import pytest

from drift_control.params import ParamError
from drift_control.signals import VehicleState
from drift_sim.sensors import Sensors, load_sensor_params, parse_fault

DT = 0.01
PARAMS = load_sensor_params('realistic')


def truth(t):
    """A car speeding up in a left turn: every signal moves."""
    V = 10.0 + t
    return VehicleState(stamp=round(t, 9), V=V, beta=-0.3, r=0.5, ax=1.0, ay=5.0,
                        wheel_speeds=(30.0 + t, 30.0 + t, 35.0 + t, 35.0 + t), delta=-0.05,
                        drive_torque=1500.0, x=t, y=2.0 * t, yaw=0.5 * t)


def run(seconds=1.0, seed=0, faults=(), params=PARAMS):
    sensors = Sensors(params, DT, seed, [parse_fault(f) for f in faults])
    out = list(sensors.reset(truth(0.0)))
    arrivals = [(0.0, s) for s in out]
    for k in range(1, int(round(seconds / DT)) + 1):
        t = round(k * DT, 9)
        arrivals += [(t, s) for s in sensors.step(truth(t))]
    return sensors, arrivals


def of(arrivals, unit):
    return [(t, s) for t, s in arrivals if s.unit == unit]


def test_same_seed_same_samples_other_seed_other_samples():
    _, a = run(seed=4)
    _, b = run(seed=4)
    _, c = run(seed=5)
    assert a == b
    assert [s.values for _, s in a] != [s.values for _, s in c]


@pytest.mark.parametrize('unit', ['ins', 'imu', 'wheels', 'steering', 'torque'])
def test_each_unit_arrives_at_its_rate_after_its_latency(unit):
    p = getattr(PARAMS, unit)
    _, arrivals = run(2.0)
    got = of(arrivals, unit)[1:]                      # after the start's sample
    assert all(t - s.stamp == pytest.approx(p.latency, abs=1e-9) for t, s in got)
    assert all(s.stamp >= 0.0 for _, s in got)
    gaps = np.diff([s.stamp for _, s in got])
    assert np.allclose(gaps, 1.0 / p.rate)


def test_values_sit_on_the_frames_resolution():
    _, arrivals = run()
    for unit in ('ins', 'wheels', 'steering'):
        channels = getattr(PARAMS, unit).channels
        for _, s in of(arrivals, unit):
            for name, v in zip(channels, s.values):
                res = channels[name].resolution
                assert v / res == pytest.approx(round(v / res), abs=1e-6), (unit, name, v)


def test_imu_reads_its_offsets_and_gravity_through_the_roll():
    imu = replace(PARAMS.imu, channels={k: replace(c, std=0.0, bias_walk=0.0, resolution=0.0)
                                        for k, c in PARAMS.imu.channels.items()})
    sensors, arrivals = run(params=replace(PARAMS, imu=imu))
    bias = sensors.units[1].bias
    assert np.any(np.abs(bias) > 0)
    roll = 9.81 * math.sin(imu.roll_gradient * 5.0)
    for _, s in of(arrivals, 'imu'):
        assert s.values == pytest.approx((1.0 + bias[0], 5.0 + roll + bias[1], 0.5 + bias[2]))


def test_faults_act_only_in_their_window():
    _, arrivals = run(2.0, faults=['ins:dropout:0.5:1.0', 'steering.delta:freeze:1.0:1.5',
                                   'wheels.RL:stuck:0.4:0.8:0', 'imu.r:bias_step:1.2:2:0.1'])
    ins = [s.stamp for _, s in of(arrivals, 'ins')]
    assert not [t for t in ins if 0.5 <= t < 1.0] and [t for t in ins if t >= 1.0]
    frozen = {s.values[0] for _, s in of(arrivals, 'steering') if 1.0 <= s.stamp < 1.5}
    assert len(frozen) == 1
    rl = [(s.stamp, s.values[2]) for _, s in of(arrivals, 'wheels')]
    assert all(v == 0.0 for t, v in rl if 0.4 <= t < 0.8)
    assert all(v > 30.0 for t, v in rl if t >= 0.8)
    r = [(s.stamp, s.values[2]) for _, s in of(arrivals, 'imu')]
    assert np.mean([v for t, v in r if t >= 1.2]) - np.mean([v for t, v in r if t < 1.2]) \
        == pytest.approx(0.1, abs=0.01)


@pytest.mark.parametrize('override, where', [
    ('ins.channels.beta.std=-1', 'sensors.ins.channels.beta'),
    ('imu.latency=-0.01', 'sensors.imu'),
    ('wheels.channels.XX={std: 0.1}', 'sensors.wheels.channels'),
    ('torque.rte=100', 'sensors.torque'),
])
def test_bad_sensor_parameters_name_the_key(override, where):
    with pytest.raises(ParamError, match=where.replace('.', r'\.')):
        load_sensor_params('realistic', overrides=[override])


def test_a_rate_that_does_not_divide_the_plant_rate_is_refused():
    with pytest.raises(ParamError, match=r'sensors\.wheels\.rate'):
        Sensors(load_sensor_params('realistic', overrides=['wheels.rate=30']), DT)


@pytest.mark.parametrize('text, message', [
    ('gps:dropout:1:2', 'unknown unit'),
    ('ins.vz:freeze:1:2', 'no channel'),
    ('ins.beta:melt:1:2', 'unknown kind'),
    ('imu:bias_step:1:2:0.1', 'needs a channel'),
    ('ins:dropout:a:2', 'numbers'),
])
def test_a_bad_fault_is_named(text, message):
    with pytest.raises(ParamError, match=message):
        parse_fault(text)


def test_closed_loop_through_sensors_and_estimator_reports_the_estimator():
    pytest.importorskip('drift_control.nmpc')
    from drift_sim.closed_loop import run_closed_loop
    out, data = run_closed_loop('steady_dry', ['duration=3.0'], sensors='realistic',
                                estimator='ekf')
    assert not out['spun'] and out['commands_lost'] == 0
    summary = out['estimator_summary']
    assert summary['nis']['ins.beta']['n'] > 250 and 0 < summary['step_ms_p50'] < 5.0
    seen_err = np.degrees(np.abs(data['beta_seen'] - data['beta']))[100:]
    assert seen_err.max() < 1.0           # what the controller saw, against the truth

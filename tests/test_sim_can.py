"""CAN vehicle mode: the simulator behind the car's end of the DBC, the bridge's gateway in front."""
import contextlib

import can
import pytest

from drift_control.signals import Command, Mode

pytest.importorskip('drift_vehicle_bridge.vehicle_side')

from drift_sim.can_vehicle import CanVehicle  # noqa: E402
from drift_sim.scenario import load_scenario  # noqa: E402
from drift_sim.simulator import Simulator  # noqa: E402
from drift_vehicle_bridge.description import SENSOR_SIGNALS  # noqa: E402
from drift_vehicle_bridge.gateway import Gateway  # noqa: E402
from drift_vehicle_bridge.params import load_bridge_params  # noqa: E402
from drift_vehicle_bridge.vehicle_side import CarSide  # noqa: E402

STRAIGHT = ('path={type: segments, segments: [{length: 300.0, curvature: 0.0}]}',
            'initial.yaw_rate_from_path=false', 'duration=5.0')


def test_bridge_gateway_drives_the_simulated_car_over_a_virtual_bus():
    with can.Bus('sim_can_test', interface='virtual') as car_bus, \
            can.Bus('sim_can_test', interface='virtual') as our_bus:
        car = CarSide(car_bus)
        gateway = Gateway(our_bus, car.codec, load_bridge_params())
        sim = Simulator(load_scenario('steady_dry', STRAIGHT))
        vehicle = CanVehicle(sim, car)
        torque_when_armed = None
        for k in range(150):
            now = 0.01 * k
            vehicle.step(now)
            seen = gateway.step(now)
            if k == 20:
                assert gateway.request_arm(now)[0], 'a straight, hands-off car can be armed'
                torque_when_armed = sim.truth.state.drive_torque
            if k > 20:
                gateway.set_command(Command(now, 0.0, 0.0, 1500.0, Mode.FULL), now)
        assert torque_when_armed == pytest.approx(0.0, abs=1e-6), 'released: no drive torque'
        assert gateway.mode.name == 'ACTIVE_FULL'
        assert vehicle.command.drive_torque == pytest.approx(1500.0, abs=1.0)
        assert sim.truth.state.drive_torque > 1400.0, 'the request reached the powertrain'
        assert seen.V == pytest.approx(sim.truth.state.V, abs=0.3), 'state frames reach the bridge'
        assert vehicle.released > 20


class _RecordingCar(CarSide):
    """The car's end, keeping each step's sensor samples as they went out."""

    sent_samples: list = []

    def send_samples(self, samples, brake_pedal=False, skip=()):
        self.sent_samples.append(list(samples))
        return super().send_samples(samples, brake_pedal, skip)


@pytest.mark.parametrize('description', ['can/drift_vehicle.dbc', 'can/drift_vehicle_fd.dbc'])
def test_sensor_samples_cross_the_bus_to_the_bridge(description):
    """Sensor mode: each unit's sample leaves the car in its frames and arrives at the bridge
    as the same sample (to the frame's resolution), at the unit's rate, aged by its latency."""
    from drift_sim.sensors import Sensors, load_sensor_params
    from drift_vehicle_bridge.codec import Codec
    from drift_vehicle_bridge.params import description_path

    fd = description.endswith('_fd.dbc')
    params = load_bridge_params(None, {'description': description, 'bus': {'fd': fd},
                                       'sensors': {'enabled': True}})
    codec = Codec.load(description_path(params))
    scale = {s.name: s.scale for name in codec.gateway_pdus for s in codec.payload_signals(name)}
    with can.Bus('sim_can_sensors', interface='virtual', fd=fd) as car_bus, \
            can.Bus('sim_can_sensors', interface='virtual', fd=fd) as our_bus:
        car = _RecordingCar(car_bus, codec)
        car.sent_samples = []
        gateway = Gateway(our_bus, codec, params)
        sim = Simulator(load_scenario('steady_dry', ['duration=2.0']))
        vehicle = CanVehicle(sim, car, sensors=Sensors(load_sensor_params('realistic'), sim.dt))
        received, compared = {}, 0
        for k in range(100):
            now = 0.01 * k
            vehicle.step(now)
            gateway.step(now)
            got = {s.unit: s for s in gateway.take_samples(now)}
            for unit, s in got.items():
                received[unit] = received.get(unit, 0) + 1
                assert s.age == pytest.approx(params.sensors.latency[unit])
            for sample in car.sent_samples[-1]:
                if sample.unit not in got:
                    continue
                sigs = SENSOR_SIGNALS[sample.unit]
                for sig, sent, back in zip(sigs, sample.values, got[sample.unit].values):
                    assert back == pytest.approx(sent, abs=0.5 * scale[sig] + 1e-9), sig
                    compared += 1
    assert compared > 1000
    # wheels at 50 Hz; on CAN FD steering and torque share the wheels' frame, and its rate
    slow = {'wheels', 'steering', 'torque'} if fd else {'wheels'}
    for unit in SENSOR_SIGNALS:
        expected = 50 if unit in slow else 100
        assert expected - 3 <= received.get(unit, 0) <= expected, unit
    assert gateway.stats()['sensor_samples'] == received
    assert gateway.state.validity == 0x7ff, 'the 50 Hz frames within their own timeout'
    timeout = gateway.monitor.timeout
    assert timeout('DS_CHASSIS' if fd else 'DS_WHEELS_FRONT') == pytest.approx(0.06)
    assert timeout('DS_POSE' if fd else 'DS_POSE_XY') == pytest.approx(0.03)


@contextlib.contextmanager
def sensor_link(channel: str, overrides=('duration=1.0',)):
    """The car's end and the bridge in sensor mode on a virtual bus, a scenario's simulator and
    the realistic sensor units on it: (car, gateway, sim, sensors)."""
    from drift_sim.sensors import Sensors, load_sensor_params

    params = load_bridge_params(None, {'sensors': {'enabled': True}})
    with can.Bus(channel, interface='virtual') as car_bus, \
            can.Bus(channel, interface='virtual') as our_bus:
        car = CarSide(car_bus)
        sim = Simulator(load_scenario('steady_dry', list(overrides)))
        sensors = Sensors(load_sensor_params('realistic'), sim.dt)
        sensors.reset(sim.truth.state)
        yield car, Gateway(our_bus, car.codec, params), sim, sensors


def test_a_unit_with_a_lost_frame_waits_for_its_next_complete_sample():
    with sensor_link('sim_can_lost') as (car, gateway, sim, sensors):
        units = []
        for k in range(10):
            sim.step(Command(0.01 * k, sim.state.delta, 0.0, 0.0, Mode.OFF))
            car.send_samples(sensors.step(sim.truth.state),
                             skip=('DS_POSE_XY',) if k == 6 else ())
            gateway.step(0.01 * k)
            units.append({s.unit for s in gateway.take_samples(0.01 * k)})
    assert 'ins' in units[5] and 'ins' in units[7]
    assert 'ins' not in units[6] and 'imu' in units[6], 'the INS of step 6 lacked its position'


def test_parts_of_a_sample_more_than_max_spread_apart_are_not_joined():
    from drift_vehicle_bridge.codec import Codec, Frame
    from drift_vehicle_bridge.sensors import SensorAssembler
    from drift_vehicle_bridge.vehicle_side import default_dbc

    codec = Codec.load(default_dbc())
    latency = dict.fromkeys(SENSOR_SIGNALS, 0.0)
    sensors = SensorAssembler(codec, latency, max_spread=0.015)
    ins = codec.sensor_frames['ins']
    values = {name: {s.name: 1.0 for s in codec.payload_signals(name)} for name in ins}
    sensors.receive(Frame(ins[0], 0, values[ins[0]]), 0.0)    # the rest of this one lost
    assert sensors.take(0.0) == [] and sensors.take(0.01) == []
    for name in ins[1:]:
        sensors.receive(Frame(name, 1, values[name]), 0.02)
    assert sensors.take(0.02) == [], 'the first part is 20 ms older: not the same sample'
    sensors.receive(Frame(ins[0], 2, values[ins[0]]), 0.025)   # a burst split by a cycle edge
    (sample,) = sensors.take(0.03)
    assert sample.unit == 'ins' and sample.age == pytest.approx(0.005)


def _drive_armed(link, steps: int, skip, estimate_until: int):
    """Sensor mode with the truth as the estimator's state until ``estimate_until``, armed at
    step 20 and commanded after; ``skip(k)``: the PDUs left out at step k. Per step: the mode,
    and whether the frames alone had a speed."""
    from dataclasses import replace

    from drift_control.signals import Validity

    car, gateway, sim, sensors = link
    modes, own_speed = [], []
    for k in range(steps):
        now = 0.01 * k
        command = car.poll_command(now) or Command(now, sim.state.delta, 0.0, 0.0, Mode.OFF)
        sim.step(command)
        car.send_samples(sensors.step(sim.truth.state), skip=skip(k))
        if k < estimate_until:
            gateway.set_estimate(replace(sim.truth.state, validity=int(Validity.ALL)), now)
        if k == 20:
            assert gateway.request_arm(now)[0]
        if k > 20:
            gateway.set_command(Command(now, 0.0, 0.0, 800.0, Mode.FULL), now)
        gateway.step(now)
        modes.append(gateway.mode.name)
        own_speed.append(gateway.state.has(Validity.V))
    return modes, own_speed, gateway


def test_sensor_mode_judges_the_estimate_so_a_gnss_dropout_does_not_release_the_car():
    """In sensor mode the modes judge the estimator's state: its INS frames gone for 1 s, the
    bridge stays ACTIVE on the estimate; the estimate itself gone, it drops to OFF."""
    with sensor_link('sim_can_est', STRAIGHT) as link:
        ins_pdus = link[0].codec.sensor_frames['ins']
        modes, own_speed, gateway = _drive_armed(
            link, 300, lambda k: ins_pdus if 100 <= k < 200 else (), estimate_until=250)
    assert not any(own_speed[110:200]), 'the frames alone: no speed during the dropout'
    assert set(modes[25:250]) == {'ACTIVE_FULL'}, 'held on the estimate through the dropout'
    assert modes[-1] == 'OFF' and gateway.modes.reason.name == 'STATE_INVALID'
    assert modes.index('OFF', 250) <= 250 + 7, 'within the heartbeat timeout of the last one'


def test_sensor_mode_still_drops_when_a_unit_the_estimator_cannot_carry_goes_silent():
    """The steering angle's frames gone: no estimate stands in for them, the bridge drops."""
    with sensor_link('sim_can_steer', STRAIGHT) as link:
        modes, _, gateway = _drive_armed(
            link, 120, lambda k: ('DS_STEERING',) if k >= 80 else (), estimate_until=120)
    assert set(modes[25:80]) == {'ACTIVE_FULL'}
    assert modes[-1] == 'OFF' and gateway.modes.reason.name == 'STATE_INVALID'
    assert modes.index('OFF', 80) <= 80 + 4, 'within the frame timeout'


def test_sensor_mode_does_not_arm_without_an_estimate():
    with sensor_link('sim_can_noest', STRAIGHT) as (car, gateway, sim, _):
        for k in range(10):
            car.send_state(sim.plant.measure())
            gateway.step(0.01 * k)
        assert gateway.state.has(0x7ff), 'the frames are all there'
        assert gateway.request_arm(0.1) == (False, 'arm refused: STATE_INVALID')


def test_the_bridges_sensor_timing_is_the_simulated_cars():
    """config/bridge.yaml's latencies and rates describe the car the link graphs simulate with
    config/sim/sensors/realistic.yaml: if one is changed alone, the bridge stamps the simulated
    samples wrongly and times their frames out at the wrong rate."""
    from drift_sim.sensors import load_sensor_params

    sim, bridge = load_sensor_params('realistic'), load_bridge_params().sensors
    for unit in SENSOR_SIGNALS:
        assert bridge.latency[unit] == pytest.approx(getattr(sim, unit).latency), unit
        assert bridge.rate[unit] == pytest.approx(getattr(sim, unit).rate), unit

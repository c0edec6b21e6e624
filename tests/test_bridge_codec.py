"""Vehicle bridge codec: every bus description (classic CAN, CAN FD, FlexRay ARXML), its E2E
protection, signal round trips at their resolution, the same state through each, parameters."""
import ast
import math
import random
import shutil
from pathlib import Path

import pytest
import yaml

from drift_control.params import ParamError, config_dir, load_vehicle, vehicle_names
from drift_control.signals import Validity, VehicleState
from drift_vehicle_bridge.codec import (COMMAND_FRAMES, STATE_SIGNALS, Codec, Fault, FrameError)
from drift_vehicle_bridge.codec import load_description
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.monitor import StateMonitor
from drift_vehicle_bridge.params import MonitorParams, SensorLinkParams, load_bridge_params
from drift_vehicle_bridge.pdu import Pdu

PKG = Path(__file__).resolve().parents[1] / 'src' / 'drift_vehicle_bridge' / 'drift_vehicle_bridge'
DESCRIPTIONS = ('can/drift_vehicle.dbc', 'can/drift_vehicle_fd.dbc',
                'flexray/drift_vehicle.arxml')
PROFILES = {'can/drift_vehicle.dbc': {'P01'}, 'can/drift_vehicle_fd.dbc': {'P04', 'P05'},
            'flexray/drift_vehicle.arxml': {'P02'}}


@pytest.fixture(scope='module', params=DESCRIPTIONS)
def codec(request):
    return Codec.load(config_dir() / request.param)


@pytest.fixture(scope='module')
def classic():
    return Codec.load(config_dir() / DESCRIPTIONS[0])


def test_every_pdu_is_10ms_with_a_unique_e2e_data_id_and_the_profiles_named(codec):
    source = str(Path(codec.description.source).relative_to(config_dir()))
    pdus = codec.description.pdus
    ids = [(p.e2e.data_id, p.e2e.data_id_list) for p in pdus]
    assert len(set(ids)) == len(ids)
    assert {p.e2e.profile for p in pdus} == PROFILES[source]
    assert all(p.cycle == 0.01 for p in pdus), 'every PDU is a 10 ms PDU'
    assert set(COMMAND_FRAMES) <= {p.name for p in pdus}
    if codec.description.kind == 'can':
        assert all(p.length == 8 and not p.fd for p in pdus)
    if codec.description.kind == 'canfd':
        assert all(p.fd for p in pdus)


def test_the_e2e_header_covers_data_id_and_payload(codec):
    name = next(iter(codec.state_frames))
    values = {s.name: 0.0 for s in codec.payload_signals(name)}
    pdu = codec.encode(name, values, counter=5)
    assert codec.decode(pdu).counter == 5
    # The same payload under another PDU's id must not pass: masquerading is caught.
    other = next(n for n in codec.state_frames if n != name
                 and codec.spec(n).length == codec.spec(name).length)
    forged = Pdu(codec.spec(other).id, pdu.data, fd=pdu.fd)
    with pytest.raises(FrameError) as err:
        codec.decode(forged)
    assert err.value.fault in (Fault.CRC, Fault.DATA_ID)
    flipped = bytearray(pdu.data)
    flipped[-1] ^= 0x01
    with pytest.raises(FrameError) as err:
        codec.decode(Pdu(pdu.id, bytes(flipped), fd=pdu.fd))
    assert err.value.fault == Fault.CRC


def test_every_signal_round_trips_at_its_resolution(codec):
    for name in codec.names:
        rng = random.Random(name)
        sigs = codec.payload_signals(name)
        modulo = codec.protection(name).counter_modulo
        for counter in range(40):
            values = {s.name: rng.uniform(s.minimum, s.maximum) for s in sigs}
            frame = codec.decode(codec.encode(name, values, counter))
            codec.check_range(frame)
            assert frame.counter == counter % modulo
            for s in sigs:
                # Rounding to the nearest step: at most half a step off (+ float noise).
                assert abs(frame.values[s.name] - values[s.name]) <= 0.5 * s.scale + 1e-9, s.name
            # A value on the grid comes back exactly.
            grid = {s.name: round(values[s.name] / s.scale) * s.scale for s in sigs}
            back = codec.decode(codec.encode(name, grid, counter)).values
            assert all(back[k] == pytest.approx(v, abs=1e-12) for k, v in grid.items())
        for s in sigs:   # both range ends are representable and accepted
            for end in (s.minimum, s.maximum):
                zero = {t.name: 0 for t in sigs}
                frame = codec.decode(codec.encode(name, {**zero, s.name: end}, 0))
                codec.check_range(frame)
                assert frame.values[s.name] == pytest.approx(end, abs=0.5 * s.scale)


def test_resolutions_fit_drifting(codec):
    sig = {s.name: s for n in codec.names for s in codec.payload_signals(n)}
    assert set(STATE_SIGNALS) <= set(sig)
    assert sig['beta'].scale <= 0.001 and sig['r'].scale <= 0.001
    assert sig['omega_RR'].scale <= 0.01 and sig['omega_RR'].maximum >= 300.0
    assert sig['drive_torque'].scale <= 1.0 and sig['drive_torque'].maximum >= 8000.0
    assert sig['torque_req'].minimum <= -8000.0
    assert sig['x'].scale <= 0.01 and sig['delta'].scale <= 0.0005


STATE = VehicleState(stamp=0.0, V=9.3456, beta=-0.5234, r=0.8123, vx=8.1, vy=-4.6, ax=-0.51,
                     ay=7.77, wheel_speeds=(27.11, 27.65, 41.02, 42.981), delta=-0.1234,
                     steering_torque=-2.3, drive_torque=2345.4, brake_pedal=True, x=-123.456,
                     y=7890.12, yaw=2 * math.pi + 0.5)


def _received(codec, state, cycles=3):
    """The monitor's state after ``cycles`` 10 ms cycles of the state's PDUs."""
    monitor = StateMonitor(codec, MonitorParams())
    for k in range(cycles):
        now = 1.0 + 0.01 * k
        for name, values in codec.state_signals(state).items():
            assert monitor.receive(codec.encode(name, values, k), now)
        monitor.tick(now)
    return monitor, now


def test_vehicle_state_survives_the_state_pdus(codec):
    monitor, now = _received(codec, STATE)
    out = monitor.state(now)
    assert out.validity == int(Validity.ALL)
    assert out.brake_pedal is True
    assert out.yaw == pytest.approx(0.5, abs=1e-4)       # wrapped to [-pi, pi]
    for field, tol in (('V', 0.005), ('beta', 0.0005), ('r', 0.00025), ('vx', 0.005),
                       ('vy', 0.005), ('ax', 0.005), ('ay', 0.005), ('delta', 0.00005),
                       ('steering_torque', 0.005), ('drive_torque', 0.5), ('x', 0.005),
                       ('y', 0.005)):
        assert getattr(out, field) == pytest.approx(getattr(STATE, field), abs=tol), field
    assert out.wheel_speeds == pytest.approx(STATE.wheel_speeds, abs=0.005)
    assert monitor.state(now + 0.031).validity == 0, 'every PDU is stale 31 ms later'


def test_every_description_decodes_the_same_state_to_the_same_signals(classic):
    """Classic DBC, CAN FD DBC and FlexRay ARXML: one interface, the same values bit for bit."""
    states = []
    for source in DESCRIPTIONS:
        codec = Codec.load(config_dir() / source)
        monitor, now = _received(codec, STATE)
        states.append(monitor.state(now))
    assert states[0].validity == int(Validity.ALL)
    assert all(s == states[0] for s in states[1:]), states


def test_a_description_the_codec_cannot_serve_is_one_line(tmp_path):
    text = (config_dir() / DESCRIPTIONS[0]).read_text()
    for broken, match in (
            (text.replace(' SG_ beta : 32|16@1- (0.001,0) [-3.141|3.141] "rad" DRIFT_STACK\n', ''),
             r'state signal.*beta'),
            (text.replace(' SG_ beta : 32|16@1- (0.001,0)',
                          ' SG_ r_imu : 48|16@1- (0.0005,0) [-10|10] "rad/s" DRIFT_STACK\n'
                          ' SG_ beta : 32|16@1- (0.001,0)'),
             r'sensor signal r_imu in both DS_YAW and DS_ACCEL'),
            (text.replace('BA_ "E2E_DataID" BO_ 273 2577;', 'BA_ "E2E_DataID" BO_ 273 2576;'),
             r'data ID 2576 not unique'),
            (text.replace('BA_DEF_DEF_ "E2E_Profile" "P01";', 'BA_DEF_DEF_ "E2E_Profile" "P99";'),
             r'P99'),
            (text.replace(' SG_ vx : 16|16@1- (0.01,0)', ' SG_ vx : 4|16@1- (0.01,0)'),
             r'vx|overlap'),
            ('BO_ oops', r'cannot read the DBC')):
        path = tmp_path / 'broken.dbc'
        path.write_text(broken)
        with pytest.raises(ParamError, match=match) as err:
            Codec.load(path)
        assert '\n' not in str(err.value), err.value
    with pytest.raises(ParamError, match='unknown bus description'):
        load_description(tmp_path / 'bus.kcd')


def test_bridge_yaml_loads_and_bad_keys_name_themselves(tmp_path):
    params = load_bridge_params()
    assert params.cycle_time == 0.01 and params.bus.interface and params.transport == 'can'
    shutil.copytree(config_dir(), tmp_path / 'config')
    raw = yaml.safe_load((config_dir() / 'bridge.yaml').read_text())
    raw['mode']['arm_envelope']['beta_maxx'] = 0.3
    (tmp_path / 'config' / 'bridge.yaml').write_text(yaml.safe_dump(raw))
    with pytest.raises(ParamError, match=r'bridge\.mode\.arm_envelope.*beta_maxx'):
        load_bridge_params(tmp_path / 'config')
    with pytest.raises(ParamError, match=r'bridge\.limits\.torque_rate_max'):
        load_bridge_params(None, {'limits': {'torque_rate_max': 'fast'}})
    with pytest.raises(ParamError, match=r'bridge\.monitor\.max_counter_delta'):
        load_bridge_params(None, {'monitor': {'max_counter_delta': 0}})
    with pytest.raises(ParamError, match=r'bridge\.transport'):
        load_bridge_params(None, {'transport': 'flexray'})
    with pytest.raises(ParamError, match=r'bridge\.udp\.remote'):
        load_bridge_params(None, {'transport': 'udp', 'udp': {'remote': 'gateway'}})
    with pytest.raises(ParamError, match=r'auto_arm'):   # a gateway off this machine
        load_bridge_params(None, {'transport': 'udp', 'auto_arm': True,
                                  'udp': {'remote': '192.168.10.2:30502'}})
    assert load_bridge_params(None, {'transport': 'udp', 'auto_arm': True}).simulated()


def test_tx_allow_only_names_our_own_pdus_and_limits_fit_their_signals(classic):
    with pytest.raises(ParamError, match=r'bridge\.tx_allow.*DS_YAW'):
        Gateway(None, classic, load_bridge_params(None, {'tx_allow': ['DS_YAW']}))
    with pytest.raises(ParamError, match=r'bridge\.tx_allow.*NOPE'):
        Gateway(None, classic, load_bridge_params(None, {'tx_allow': ['NOPE']}))
    with pytest.raises(ParamError, match=r'bridge\.limits\.torque_max'):
        Gateway(None, classic, load_bridge_params(None, {'limits': {'torque_max': 9000.0}}))


@pytest.mark.parametrize('vehicle', vehicle_names())
def test_command_limits_derive_from_the_vehicle_and_may_only_tighten(vehicle):
    bridge = load_bridge_params(vehicle=vehicle).limits
    lim = load_vehicle(vehicle).limits
    assert (bridge.delta_max, bridge.delta_rate_max, bridge.torque_min, bridge.torque_max) == \
        (lim.delta_max, lim.delta_dot_max, lim.T_R_min, lim.T_R_max)
    tight = load_bridge_params(None, {'limits': {'torque_max': 0.5 * lim.T_R_max}}, vehicle)
    assert tight.limits.torque_max == 0.5 * lim.T_R_max
    with pytest.raises(ParamError, match=r'bridge\.limits\.delta_max.*only tighten'):
        load_bridge_params(None, {'limits': {'delta_max': lim.delta_max + 0.1}}, vehicle)


def test_core_modules_do_not_import_rclpy():
    for path in PKG.glob('*.py'):
        tree = ast.parse(path.read_text())
        names = {a.name.split('.')[0] for node in ast.walk(tree)
                 if isinstance(node, ast.Import) for a in node.names}
        names |= {node.module.split('.')[0] for node in ast.walk(tree)
                  if isinstance(node, ast.ImportFrom) and node.module}
        assert not names & {'rclpy', 'drift_msgs', 'std_msgs', 'diagnostic_msgs'}, path.name


def test_every_description_carries_each_sensor_unit_in_estimator_order(codec):
    from drift_control.estimator import FIELDS
    from drift_vehicle_bridge.description import SENSOR_SIGNALS

    assert list(SENSOR_SIGNALS) == list(FIELDS)
    assert all(len(SENSOR_SIGNALS[u]) == len(FIELDS[u]) for u in FIELDS)
    assert codec.sensor_missing == {}
    assert set(codec.sensor_frames) == set(SENSOR_SIGNALS)
    carried = {s.name for n in codec.gateway_pdus for s in codec.payload_signals(n)}
    assert {s for sigs in SENSOR_SIGNALS.values() for s in sigs} <= carried


def test_sensor_mode_refuses_a_description_without_a_unit_and_a_missing_latency(tmp_path):
    dbc = (config_dir() / DESCRIPTIONS[0]).read_text()
    lean = tmp_path / 'lean.dbc'
    lean.write_text('\n'.join(line for line in dbc.splitlines() if 'r_imu' not in line))
    codec = Codec.load(lean)
    assert codec.sensor_missing == {'imu': ('r_imu',)}
    load_bridge_params()   # without sensor mode the description serves as before
    params = load_bridge_params(None, {'sensors': {'enabled': True}})
    with pytest.raises(ParamError, match=r"lean.dbc: sensor mode needs the imu signal\(s\) "
                                         r"\['r_imu'\]"):
        Gateway(None, codec, params)
    with pytest.raises(ParamError, match=r'bridge.sensors.latency.gps: unknown sensor unit'):
        load_bridge_params(None, {'sensors': {'latency': {'gps': 0.1}}})
    with pytest.raises(ParamError, match=r"bridge.sensors.latency: .*\(missing \['ins', "):
        SensorLinkParams(enabled=True, latency={'torque': 0.02})

"""Vehicle bridge: DBC layout, E2E CRC, signal round trips at their resolution, parameters."""
import ast
import math
import random
import shutil
from pathlib import Path

import pytest
import yaml
from crccheck.crc import Crc8SaeJ1850

from drift_control.params import ParamError, config_dir, load_vehicle, vehicle_names
from drift_control.signals import Validity, VehicleState
from drift_vehicle_bridge.codec import (COMMAND_FRAMES, STATE_FRAMES, Codec, Fault, FrameError,
                                        state_signals)
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.params import load_bridge_params
from drift_vehicle_bridge.vehicle_side import default_dbc

E2E = ('CRC', 'AliveCounter')
PKG = Path(__file__).resolve().parents[1] / 'src' / 'drift_vehicle_bridge' / 'drift_vehicle_bridge'


@pytest.fixture(scope='module')
def codec():
    return Codec.load(default_dbc())


def test_every_frame_is_classic_8_bytes_10ms_with_unique_e2e_data_id(codec):
    ids = [m.dbc.attributes['E2E_DataID'].value for m in codec.db.messages]
    assert len(set(ids)) == len(ids) == len(STATE_FRAMES) + len(COMMAND_FRAMES)
    for m in codec.db.messages:
        assert m.length == 8 and not m.is_extended_frame, m.name
        assert m.cycle_time == 10, f'{m.name}: every frame is a 10 ms frame'


def test_crc_is_the_autosar_crc8_sae_j1850():
    # AUTOSAR SWS_CRCLibrary check value of Crc_CalculateCRC8 for "123456789".
    assert Crc8SaeJ1850.calc(b'123456789') == 0x4B


def test_crc_covers_data_id_and_payload(codec):
    msg = codec.encode('DS_VELOCITY', {'vx': 8.0, 'vy': -1.0, 'V': 8.06}, counter=5)
    data_id = codec.message('DS_VELOCITY').dbc.attributes['E2E_DataID'].value
    assert msg.data[0] == Crc8SaeJ1850.calc(data_id.to_bytes(2, 'little') + bytes(msg.data[1:]))
    other = codec.encode('DS_ACCEL', {'ax': 8.0, 'ay': -1.0}, counter=5)
    # The same payload under another data ID must not pass: masquerading is caught by the CRC.
    forged = other.__class__(arbitration_id=msg.arbitration_id, data=bytes(other.data),
                             is_extended_id=False)
    with pytest.raises(FrameError) as err:
        codec.decode(forged)
    assert err.value.fault == Fault.CRC


@pytest.mark.parametrize('name', [m for m in (*STATE_FRAMES, *COMMAND_FRAMES)])
def test_every_signal_round_trips_at_its_resolution(codec, name):
    rng = random.Random(name)
    m = codec.message(name)
    sigs = [s for s in m.signals if s.name not in E2E]
    for counter in range(40):
        values = {s.name: rng.uniform(s.minimum, s.maximum) for s in sigs}
        frame = codec.decode(codec.encode(name, values, counter))
        codec.check_range(frame)
        assert frame.counter == counter % 16
        for s in sigs:
            # Rounding to the nearest step: at most half a step off (+ float noise).
            assert abs(frame.values[s.name] - values[s.name]) <= 0.5 * s.scale + 1e-9, s.name
        # A value on the grid comes back exactly.
        grid = {s.name: round(values[s.name] / s.scale) * s.scale for s in sigs}
        back = codec.decode(codec.encode(name, grid, counter)).values
        assert all(back[k] == pytest.approx(v, abs=1e-12) for k, v in grid.items())
    for s in sigs:   # both range ends are representable and accepted
        for end in (s.minimum, s.maximum):
            frame = codec.decode(codec.encode(name, {**{t.name: 0 for t in sigs}, s.name: end}, 0))
            codec.check_range(frame)
            assert frame.values[s.name] == pytest.approx(end, abs=0.5 * s.scale)


def test_resolutions_fit_drifting(codec):
    sig = {s.name: s for m in codec.db.messages for s in m.signals}
    assert sig['beta'].scale <= 0.001 and sig['r'].scale <= 0.001
    assert sig['omega_RR'].scale <= 0.01 and sig['omega_RR'].maximum >= 300.0
    assert sig['drive_torque'].scale <= 1.0 and sig['drive_torque'].maximum >= 8000.0
    assert sig['torque_req'].minimum <= -8000.0
    assert sig['x'].scale <= 0.01 and sig['delta'].scale <= 0.0005


def test_vehicle_state_survives_the_state_frames(codec):
    from drift_vehicle_bridge.monitor import StateMonitor
    from drift_vehicle_bridge.params import MonitorParams
    state = VehicleState(stamp=0.0, V=9.3456, beta=-0.5234, r=0.8123, vx=8.1, vy=-4.6, ax=-0.51,
                         ay=7.77, wheel_speeds=(27.11, 27.65, 41.02, 42.981), delta=-0.1234,
                         steering_torque=-2.3, drive_torque=2345.4, brake_pedal=True, x=-123.456,
                         y=7890.12, yaw=2 * math.pi + 0.5)
    monitor = StateMonitor(codec, MonitorParams())
    for name, values in state_signals(state).items():
        assert monitor.receive(codec.encode(name, values, 0), now=1.0)
    out = monitor.state(1.0)
    assert out.validity == int(Validity.ALL)
    assert out.brake_pedal is True
    assert out.yaw == pytest.approx(0.5, abs=1e-4)       # wrapped to [-pi, pi]
    for field, tol in (('V', 0.005), ('beta', 0.0005), ('r', 0.00025), ('vx', 0.005),
                       ('vy', 0.005), ('ax', 0.005), ('ay', 0.005), ('delta', 0.00005),
                       ('steering_torque', 0.005), ('drive_torque', 0.5), ('x', 0.005),
                       ('y', 0.005)):
        assert getattr(out, field) == pytest.approx(getattr(state, field), abs=tol), field
    assert out.wheel_speeds == pytest.approx(state.wheel_speeds, abs=0.005)
    assert monitor.state(1.031).validity == 0, 'every frame is stale 31 ms later'


def test_bridge_yaml_loads_and_bad_keys_name_themselves(tmp_path):
    params = load_bridge_params()
    assert params.cycle_time == 0.01 and params.bus.interface
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


def test_tx_allow_only_names_our_own_frames_and_limits_fit_the_dbc(codec):
    with pytest.raises(ParamError, match=r'bridge\.tx_allow.*DS_YAW'):
        Gateway(None, codec, load_bridge_params(None, {'tx_allow': ['DS_YAW']}))
    with pytest.raises(ParamError, match=r'bridge\.tx_allow.*NOPE'):
        Gateway(None, codec, load_bridge_params(None, {'tx_allow': ['NOPE']}))
    with pytest.raises(ParamError, match=r'bridge\.limits\.torque_max'):
        Gateway(None, codec, load_bridge_params(None, {'limits': {'torque_max': 9000.0}}))


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

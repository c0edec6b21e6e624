"""State -> command latency from a bag's log times: known answers, refusals."""
import json

import numpy as np
import pytest

from conftest import load_script
from drift_tools.bag_writer import BagWriter
from drift_tools.latency import state_to_command

ser = pytest.importorskip('rclpy.serialization')
msgs = pytest.importorskip('drift_msgs.msg')


def test_each_command_is_matched_to_the_newest_state_before_it():
    states = np.arange(10) * 0.01
    commands = np.array([-0.001, 0.004, 0.0135, 0.02, 0.0999])
    # before the first state: left out; a command logged with a state counts it as used
    assert state_to_command(states, commands) == pytest.approx([0.004, 0.0035, 0.0, 0.0099])


def _bag(path, delay, clock='realtime'):
    with BagWriter(path) as bag:
        bag.add_topic('/vehicle/state', 'drift_msgs/msg/VehicleState')
        bag.add_topic('/drift/command', 'drift_msgs/msg/DriftCommand')
        bag.add_metadata('drift_run', {'clock': clock, 'scenario': 'steady_dry'})
        for k in range(500):
            t = 1000.0 + 0.01 * k
            bag.write('/vehicle/state', ser.serialize_message(msgs.VehicleState(v=9.0)),
                      int(round(t * 1e9)))
            if k % 2 == 0:
                late = 0.015 if k == 300 else delay      # one late command: the max
                bag.write('/drift/command', ser.serialize_message(msgs.DriftCommand(mode=1)),
                          int(round((t + late) * 1e9)))
    return path


def test_the_script_prints_percentiles_and_refuses_a_lockstep_bag(tmp_path, capsys):
    latency = load_script('latency')
    assert latency.main([str(_bag(tmp_path / 'rt', 0.004)), '--json']) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['p50_ms'] == pytest.approx(4.0, abs=1e-3)
    assert out['max_ms'] == pytest.approx(5.0, abs=1e-3)    # 15 ms late: 5 ms after a state
    assert out['commands'] == 200                            # the first second left out
    assert latency.main([str(_bag(tmp_path / 'ls', 0.0, clock='lockstep'))]) == 2
    err = capsys.readouterr().err
    assert 'lock-step' in err and len(err.strip().splitlines()) == 1
    assert latency.main([str(tmp_path / 'nothing')]) == 2


def test_with_the_estimator_the_path_starts_at_the_sensors_and_splits_hop_by_hop(tmp_path,
                                                                                   capsys):
    from builtin_interfaces.msg import Time
    path = tmp_path / 'est'
    hops = [('/vehicle/sensors', 'SensorSamples', 0.0), ('/vehicle/state', 'VehicleState', 0.001),
            ('/drift/reference', 'DriftReference', 0.003), ('/drift/command', 'DriftCommand',
                                                             0.0045)]
    with BagWriter(path) as bag:
        for topic, name, _ in hops:
            bag.add_topic(topic, f'drift_msgs/msg/{name}')
        bag.add_metadata('drift_run', {'clock': 'realtime'})
        for k in range(300):
            t = 1000.0 + 0.01 * k
            for topic, name, delay in hops:
                if topic != '/vehicle/sensors' and k % 2:
                    continue   # states, references and commands of every other frame only
                m = getattr(msgs, name)()
                m.header.stamp = Time(sec=int(t), nanosec=int(round((t % 1) * 1e9)))
                bag.write(topic, ser.serialize_message(m), int(round((t + delay) * 1e9)))
    latency = load_script('latency')
    assert latency.main([str(path), '--json']) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['from'] == '/vehicle/sensors' and out['p50_ms'] == pytest.approx(4.5, abs=1e-3)
    stages = out['stages']
    assert stages['/vehicle/sensors -> /vehicle/state']['p50_ms'] == pytest.approx(1.0, abs=1e-3)
    assert stages['/vehicle/state -> /drift/reference']['max_ms'] == pytest.approx(2.0, abs=1e-3)
    assert stages['/drift/reference -> /drift/command']['p99_ms'] == pytest.approx(1.5, abs=1e-3)
    assert stages['/vehicle/sensors -> /drift/command']['commands'] == 100

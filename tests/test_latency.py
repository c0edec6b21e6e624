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

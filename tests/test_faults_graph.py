"""Faults on the node graph: runs that would pass with nothing run now fail, with the reason."""
import os
import subprocess
import sys

import pytest

pytest.importorskip('drift_msgs.msg')
pytestmark = pytest.mark.ros


def test_a_lockstep_simulator_whose_controller_never_commands_ends_the_run_non_zero():
    """Without an NMPC the lock-step loop would wait forever and the run 'pass' with nothing."""
    env = {**os.environ, 'ROS_DOMAIN_ID': '124', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    proc = subprocess.run(
        [sys.executable, '-m', 'drift_sim.nodes.sim_node', '--ros-args', '-p',
         'clock_mode:=lockstep', '-p', 'scenario:=steady_dry', '-p', 'startup_timeout:=1.0'],
        env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert 'the controller never commanded' in proc.stdout + proc.stderr


def test_lockstep_on_a_graph_without_its_clock_owner_is_refused_at_launch(capsys):
    from conftest import load_script
    rc = load_script('run_stack').main(['--graph', 'vehicle', '--clock', 'lockstep',
                                        '--duration', '1'])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "has no clock owner 'sim'" in err and len(err.splitlines()) == 1, err

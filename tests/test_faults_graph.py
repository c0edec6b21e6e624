"""Faults on the node graph: runs that would pass with nothing run now fail, with the reason."""
import os
import subprocess
import sys

import pytest

from conftest import REPO

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


def test_a_stop_during_start_up_is_honoured_without_sigkill():
    """--duration 1 stops the graph while the simulator still builds its plant (CasADi clears a
    pending SIGINT there; the launcher's SIGTERM is remembered from the first import on)."""
    env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    for _ in range(2):
        proc = subprocess.run([sys.executable, str(REPO / 'scripts' / 'run_stack.py'),
                               '--duration', '1', '--domain-id', '125'], env=env,
                              capture_output=True, text=True, timeout=60)
        out = proc.stdout + proc.stderr
        assert proc.returncode == 0 and 'SIGKILL' not in out, out[-2000:]
        assert 'exit codes: sim=0, reference=0, nmpc=0' in out, out[-2000:]

"""Replay over DDS: a lock-step bag drives live reference and NMPC nodes, which answer with the
recorded commands; and a replay ends cleanly on SIGTERM."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from conftest import REPO

pytest.importorskip('drift_msgs.msg')
pytestmark = [pytest.mark.ros, pytest.mark.slow]


def _env(domain):
    return {**os.environ, 'ROS_DOMAIN_ID': str(domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
            'PYTHONUNBUFFERED': '1'}


@pytest.fixture(scope='module')
def lockstep_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp('replay') / 'bag'
    proc = subprocess.run(
        [sys.executable, str(REPO / 'scripts' / 'run_stack.py'), '--scenario', 'steady_dry',
         '--clock', 'lockstep', '--sim-duration', '4', '--bag', str(bag), '--domain-id', '129',
         '--no-summary'], env=_env(129), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:]
    return bag


def test_a_lockstep_bag_replayed_into_live_nodes_gives_the_recorded_commands(lockstep_bag,
                                                                            tmp_path):
    from drift_tools.stack import (NodeSpec, RunOptions, load_stack, node_command,
                                   write_params_file)
    stack = load_stack(REPO / 'config' / 'stack.yaml')
    opts = RunOptions(params_file=write_params_file(stack, tmp_path / 'p.yaml'),
                      config_dir=REPO / 'config', scenario='steady_dry', clock='lockstep')
    nodes = [subprocess.Popen(node_command(NodeSpec(name, module), opts, 'sim', stack.node_params),
                              env=_env(130), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
             for name, module in (('reference', 'drift_control.nodes.reference_node'),
                                  ('nmpc', 'drift_control.nodes.nmpc_node'))]
    try:
        time.sleep(0.5)
        proc = subprocess.run(
            [sys.executable, str(REPO / 'scripts' / 'replay.py'), str(lockstep_bag), '--lockstep',
             '--discovery-timeout', '30', '--step-timeout', '5', '--json',
             str(tmp_path / 'cmp.json')],
            env=_env(130), capture_output=True, text=True, timeout=300)
    finally:
        for p in nodes:
            p.send_signal(signal.SIGTERM)
        logs = [p.communicate(timeout=30)[0] for p in nodes]
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((tmp_path / 'cmp.json').read_text())
    assert report['matched'] >= report['recorded'] - 1, (report, proc.stdout)
    assert report['delta_max_abs_diff'] < 1e-6 and report['torque_max_abs_diff'] < 1e-3, \
        (report, proc.stdout)
    assert report['mode_mismatches'] == 0, report
    assert 'stale' not in logs[1], logs[1][-2000:]


def test_replay_ends_cleanly_on_sigterm(lockstep_bag):
    proc = subprocess.Popen([sys.executable, str(REPO / 'scripts' / 'replay.py'),
                             str(lockstep_bag), '--clock', '--loop', '0',
                             '--discovery-timeout', '0.1'],
                            env=_env(131), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    time.sleep(4.0)
    proc.send_signal(signal.SIGTERM)
    out = proc.communicate(timeout=20)[0]
    assert proc.returncode == 0 and 'Traceback' not in out, out
    assert 'replay: published' in out, out

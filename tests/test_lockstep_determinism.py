"""Lock-step sim time: the full node graph gives the same run twice for the same seed.

Each node is its own process (scripts/run_stack.py); the simulator steps only when the NMPC's
command for the step has come, and the reference and NMPC nodes act on states, not timers.
Each run lasts SIM_S of sim time (the simulator ends it), however fast the machine.
"""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('drift_msgs.msg')
pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
SIM_S = 6.0     # simulated seconds per run


def record(bag: Path, domain_id: int) -> None:
    proc = subprocess.run(
        [sys.executable, str(REPO / 'scripts' / 'run_stack.py'), '--scenario', 'steady_dry',
         '--clock', 'lockstep', '--sim-duration', str(SIM_S), '--duration', '80', '--bag',
         str(bag), '--domain-id', str(domain_id), '--no-summary'],
        env={**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'},
        capture_output=True, text=True, timeout=90)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert '[launch] stopped (node-exit)' in proc.stdout, 'the simulator ended the run: ' + \
        proc.stdout[-3000:]


def test_same_seed_same_bag_contents(tmp_path):
    from drift_control.nmpc import Nmpc
    from drift_control.ocp import load_nmpc_params
    from drift_control.params import load_vehicle
    from drift_tools.bag import read_bag
    Nmpc(load_vehicle(), load_nmpc_params())   # compiled once here, not in the first run's node
    from drift_tools.timeseries import series_from_bag
    runs = []
    for i, domain_id in enumerate((120, 121)):
        record(tmp_path / f'run{i}', domain_id)
        runs.append(series_from_bag(read_bag(tmp_path / f'run{i}')))
    a, b = runs
    # every step and every command of both runs is in its bag (the loop's publishers keep a
    # history for a recorder they match late; the simulator ends after the last answer)
    n, m = round(SIM_S / 0.01) + 1, round(SIM_S / 0.02) + 1
    for run in runs:
        assert len(run.truth['t']) == n and run.truth['t'][0] == 0.0, run.truth['t'][:3]
        assert len(run.command['t']) == m and run.command['t'][0] == 0.0, run.command['t'][:3]
    for key in ('t', 'V', 'beta', 'r', 'delta', 'x', 'y'):
        np.testing.assert_array_equal(a.truth[key], b.truth[key], err_msg=key)
    for key in ('t', 'delta', 'drive_torque', 'mode'):
        np.testing.assert_array_equal(a.command[key], b.command[key], err_msg=key)
    assert np.abs(np.degrees(a.truth['beta'][:n])).max() > 5.0, 'the car did something'

    # the bag's log times are sim time: its span is the sim span, the rates are the nodes' rates
    from drift_tools.run_info import read_run_info
    from drift_tools.summary import summarize_bag
    summary = summarize_bag(tmp_path / 'run0')
    assert abs(summary.duration_s - SIM_S) <= 0.021, summary.duration_s
    assert summary.topics['/sim/state'].rate_hz == pytest.approx(100.0, rel=0.01)
    assert summary.topics['/drift/command'].rate_hz == pytest.approx(50.0, rel=0.02)
    info = read_run_info(tmp_path / 'run0')
    assert info['scenario'] == 'steady_dry' and info['clock'] == 'lockstep'
    assert len(info['commit']) == 40 and 'nmpc.yaml' in info['config']

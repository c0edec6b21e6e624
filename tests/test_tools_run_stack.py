"""scripts/run_stack.py on graphs of test nodes: duration, a crashing node, SIGINT, the bag."""
import re
import signal
import subprocess
import time

import pytest

from conftest import PYTHON, REPO, TESTS
from drift_tools.bag import read_bag

pytestmark = pytest.mark.ros

STACK = TESTS / 'nodes_for_tests' / 'stack.yaml'


def run_stack(env, *args):
    return subprocess.Popen([PYTHON, str(REPO / 'scripts' / 'run_stack.py'), '--stack', str(STACK),
                             '--kill-timeout', '5', *args],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_duration_bag_and_summary(node_env, tmp_path):
    t0 = time.monotonic()
    proc = run_stack(node_env, '--graph', 'rec', '--duration', '6', '--bag', str(tmp_path / 'b'))
    out, _ = proc.communicate(timeout=60)
    elapsed = time.monotonic() - t0
    assert proc.returncode == 0, out
    assert 6.0 <= elapsed < 20.0, f'took {elapsed:.1f} s for --duration 6'
    assert 'stopped (duration)' in out and '[talker]   published 200' in out, out
    # count=200 reached the talker through the generated parameter file
    commands = read_bag(tmp_path / 'b', ['/drift/command'])['/drift/command']
    assert len(commands) == 200
    summary = [line.split() for line in out.splitlines() if line.strip().startswith('/drift/command')]
    assert summary and summary[-1][1] == '200', out


def test_a_crashing_node_fails_the_run(node_env):
    t0 = time.monotonic()
    proc = run_stack(node_env, '--graph', 'crash', '--duration', '60')
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 3, out
    assert time.monotonic() - t0 < 20.0
    assert 'crasher exited with code 3' in out, out
    # the talker was stopped, cleanly, whether or not it had got to publishing (a loaded
    # machine may still be starting it when the crasher leaves)
    assert re.search(r'stopped \(node-crash\); exit codes: talker=(0|-15|143), crasher=3', out), out


def test_sigint_is_forwarded_and_the_bag_closed(node_env, tmp_path):
    proc = run_stack(node_env, '--graph', 'rec', '--bag', str(tmp_path / 'b'), '--no-summary')
    lines = []
    for line in proc.stdout:             # wait until the recorder has the talker's topics
        lines.append(line)
        if 'recording /vehicle/state' in line:
            break
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    out = ''.join(lines) + out
    assert proc.returncode == 0, out
    assert 'stopped (signal); exit codes: recorder=0, talker=0' in out, out
    got = read_bag(tmp_path / 'b', backend='rosbags')   # needs the footer a clean stop writes
    assert len(got['/drift/command']) > 0


def test_a_real_time_run_is_recorded_from_its_first_step(node_env, tmp_path):
    """The simulator in real time starts once the recorder hears every publisher, as in lock
    step: a writer matched late keeps only 1 s for it (a bag once lacked a run's first 2 s)."""
    bag = tmp_path / 'b'
    proc = subprocess.run([PYTHON, str(REPO / 'scripts' / 'run_stack.py'), '--scenario',
                           'steady_dry', '--clock', 'realtime', '--sim-duration', '1.5', '--bag',
                           str(bag), '--no-summary', '--kill-timeout', '5'],
                          env=node_env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    got = read_bag(bag, ['/sim/state', '/vehicle/state', '/drift/command'])
    truth = got['/sim/state']
    assert len(truth) == 151, len(truth)              # t = 0 and every 10 ms step to 1.5 s
    first = truth[0].msg.header.stamp
    assert got['/vehicle/state'][0].msg.header.stamp == first

    def seconds(stamp):
        return stamp.sec + 1e-9 * stamp.nanosec
    # the controller was up at t = 0 (the simulator used to start before it: 0.8-1.7 s)
    assert got.get('/drift/command'), 'no command recorded'
    lag = seconds(got['/drift/command'][0].msg.header.stamp) - seconds(first)
    assert 0.0 <= lag < 0.5, f'the first command {lag:.2f} s after the first state'

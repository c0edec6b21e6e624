"""The recorder node on live publishers, stopped with SIGINT and killed with SIGKILL.

Both bags are read back with rosbags and with mcap + mcap_ros2 and the messages counted.
"""
import signal
import subprocess
import time

import pytest

from conftest import PYTHON
from drift_tools.bag import bag_info, read_bag
from drift_tools.bag_salvage import recover_bag

pytestmark = pytest.mark.ros

N = 150   # messages per topic the talker sends


def start(env, module, *params):
    argv = [PYTHON, '-m', module, '--ros-args']
    for p in params:
        argv += ['-p', p]
    return subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def wait_for_flushed(bag, topic, count, timeout=30.0):
    """Poll metadata.yaml, which the recorder rewrites on every flush."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            topics = bag_info(bag).topics
            if topic in topics and topics[topic].count >= count:
                return
        except (OSError, KeyError, TypeError):
            pass
        time.sleep(0.1)
    raise AssertionError(f'{topic}: {count} messages not flushed to {bag} within {timeout} s')


@pytest.fixture
def recording(tmp_path, node_env):
    """A recorder and a talker sending N numbered messages per topic once it is recorded."""
    bag = tmp_path / 'bag'
    procs = []

    def run():
        procs.append(start(node_env, 'drift_tools.nodes.recorder_node', f'bag_dir:={bag}',
                           'flush_period:=0.2', 'discovery_period:=0.2', 'chunk_size:=2048'))
        procs.append(start(node_env, 'nodes_for_tests.talker', f'count:={N}', 'wait_for:=1',
                           'rate:=100.0'))
        wait_for_flushed(bag, '/drift/command', N)
        wait_for_flushed(bag, '/sim/debug', N)
        return bag, procs[0]

    yield run
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.communicate(timeout=10)


def check_bag(bag):
    for backend in ('rosbags', 'mcap'):
        out = read_bag(bag, backend=backend)
        # and the nodes' logs and the recorder's own health reports
        assert set(out) - {'/diagnostics', '/rosout'} == {'/vehicle/state', '/drift/command',
                                                           '/sim/debug'}, backend
        commands = [m.msg.drive_torque for m in out['/drift/command']]
        assert commands == [float(i) for i in range(N)], f'{backend}: reliable topic incomplete'
        assert [m.msg.data for m in out['/sim/debug']] == [float(i) for i in range(N)]
        states = out['/vehicle/state']            # best effort: allow a few drops, no duplicates
        speeds = [m.msg.v for m in states]
        assert len(states) >= 0.9 * N and speeds == sorted(set(speeds)), backend
        assert list(states[0].msg.wheel_speeds) == [1.0, 2.0, 3.0, 4.0]
        times = [m.t for m in out['/drift/command']]
        assert times == sorted(times) and 0.5 < times[-1] - times[0] < 30.0


def test_sigint_closes_a_complete_bag(recording):
    bag, recorder = recording()
    recorder.send_signal(signal.SIGINT)
    assert recorder.wait(15) == 0
    with open(next(bag.glob('*.mcap')), 'rb') as fh:
        assert fh.read()[-8:] == b'\x89MCAP0\r\n', 'no MCAP footer after SIGINT'
    assert bag_info(bag).topics['/drift/command'].count == N
    check_bag(bag)


def test_sigkill_keeps_every_flushed_message(recording, tmp_path):
    bag, recorder = recording()
    recorder.kill()
    recorder.wait(15)
    with open(next(bag.glob('*.mcap')), 'rb') as fh:
        assert fh.read()[-8:] != b'\x89MCAP0\r\n', 'a killed recorder cannot have closed the file'
    assert bag_info(bag).topics['/drift/command'].count == N    # metadata.yaml from a flush
    before = next(bag.glob('*.mcap')).read_bytes()
    check_bag(bag)                                        # read as it is, by the salvage scanner
    recovery = recover_bag(bag, tmp_path / 'recovered')
    assert next(bag.glob('*.mcap')).read_bytes() == before, 'reading or recovering changed it'
    assert sum(recovery.kept.values()) >= 3 * 0.9 * N
    check_bag(tmp_path / 'recovered')

"""scripts/topic.py against a live talker: echo prints the messages, hz measures the rate."""
import subprocess

import pytest

from conftest import PYTHON, REPO

pytestmark = pytest.mark.ros

TOPIC_PY = str(REPO / 'scripts' / 'topic.py')


@pytest.fixture
def talker(node_env):
    proc = subprocess.Popen([PYTHON, '-m', 'nodes_for_tests.talker', '--ros-args', '-p',
                             'rate:=20.0'], env=node_env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    yield node_env
    proc.terminate()
    proc.wait(10)


def tool(env, *args, timeout=30):
    return subprocess.run([PYTHON, TOPIC_PY, *args], env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_echo_shows_live_messages(talker):
    res = tool(talker, 'echo', 'vehicle/state', '-n', '2')
    assert res.returncode == 0, res.stderr
    assert res.stdout.count('---') == 2
    assert 'wheel_speeds: [1.0, 2.0, 3.0, 4.0]' in res.stdout and 'frame_id:' in res.stdout


def test_list_and_hz(talker):
    listed = tool(talker, 'list', '-t', '--wait', '1.5')
    assert '/vehicle/state [drift_msgs/msg/VehicleState]' in listed.stdout.splitlines()
    res = tool(talker, 'hz', '/drift/command', '--duration', '3')
    rates = [float(line.split('rate ')[1].split()[0]) for line in res.stdout.splitlines()
             if ' rate ' in line]
    assert rates and rates[-1] == pytest.approx(20.0, rel=0.3), res.stdout


def test_echo_of_a_missing_topic_fails(talker):
    res = tool(talker, 'echo', '/nothing/here', '--timeout', '1')
    assert res.returncode != 0 and 'no publisher on /nothing/here' in res.stderr

"""The operator CLI (``drift``): bag commands in process; bridge, parameters, services and topics
against live nodes."""
import math
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace

import pytest

from conftest import PYTHON, REPO
from drift_tools.operator import main

pytest.importorskip('drift_msgs.msg')
ser = pytest.importorskip('rclpy.serialization')


def drift(env, *args, timeout=60):
    return subprocess.run([PYTHON, '-m', 'drift_tools.operator', *args], env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def bag(tmp_path):
    from drift_msgs.msg import DriftCommand, VehicleState
    from drift_tools.bag_writer import BagWriter
    with BagWriter(tmp_path / 'bag') as w:
        w.add_topic('/vehicle/state', 'drift_msgs/msg/VehicleState')
        w.add_topic('/drift/command', 'drift_msgs/msg/DriftCommand')
        for i in range(100):                     # 1 s at 100 Hz, commands at 50 Hz
            t = 10**9 + i * 10**7
            s = VehicleState(v=float(i), wheel_speeds=[1.0, 2.0, 3.0, float(i)])
            s.header.stamp.sec, s.header.stamp.nanosec = divmod(t, 10**9)
            w.write('/vehicle/state', ser.serialize_message(s), t)
            if i % 2 == 0:
                w.write('/drift/command', ser.serialize_message(DriftCommand(drive_torque=float(i))), t)
    return tmp_path / 'bag'


def test_bag_info_slice_and_export(bag, tmp_path, capsys):
    assert main(['bag', 'info', str(bag)]) == 0
    out = capsys.readouterr().out
    assert '150 messages over 0.99 s' in out and 'from the index' in out
    assert main(['bag', 'slice', str(bag), str(tmp_path / 'cut'), '--start', '0.5', '--end',
                 '0.59', '--topics', '/vehicle/state']) == 0
    from drift_tools.bag import read_bag
    cut = read_bag(tmp_path / 'cut')
    assert list(cut) == ['/vehicle/state'] and [m.msg.v for m in cut['/vehicle/state']] == \
        [float(i) for i in range(50, 60)]
    assert main(['bag', 'export', str(bag), str(tmp_path / 'csv')]) == 0
    lines = (tmp_path / 'csv' / 'vehicle__state.csv').read_text().splitlines()
    header = lines[0].split(',')
    assert len(lines) == 101 and header[0] == 'log_time_s' and 'wheel_speeds.3' in header
    assert lines[8].split(',')[header.index('v')] == '7.0'


@pytest.mark.parametrize('argv, says', [
    (['bag', 'info', '/no/such/bag'], 'no such bag directory'),
    (['bag', 'slice', '{bag}', '{tmp}/x', '--start', '5'], 'outside the bag (0..0.990 s)'),
    (['bag', 'export', '{bag}', '{tmp}/y', '--topics', '/nope'], "no messages on ['/nope']"),
])
def test_bag_bad_input_is_one_line_and_exit_2(bag, tmp_path, capsys, argv, says):
    argv = [a.format(bag=bag, tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and len(err.splitlines()) == 1, err


@pytest.fixture
def env():
    return {**os.environ, 'ROS_DOMAIN_ID': '133', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}


@pytest.mark.ros
def test_recorder_parameters_runtime_one_applies_others_refused(env, tmp_path):
    rec = subprocess.Popen([PYTHON, '-m', 'drift_tools.nodes.recorder_node', '--ros-args', '-p',
                            f'bag_dir:={tmp_path / "bag"}', '-p', 'health_period:=0.2'],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        res = drift(env, 'param', 'list', '/recorder')
        assert res.returncode == 0 and 'disk_warn_free_mb' in res.stdout.split(), res.stderr
        res = drift(env, 'param', 'get', '/recorder', 'chunk_size')
        assert res.stdout.strip() == '262144', res.stderr
        res = drift(env, 'status', '--name', 'recorder')
        assert res.returncode == 0 and 'recorder: OK recording' in res.stdout, res.stdout
        # a runtime parameter: the warning threshold above any disk's free space -> WARN
        res = drift(env, 'param', 'set', '/recorder', 'disk_warn_free_mb', '1.0e12')
        assert res.returncode == 0, res.stderr
        deadline = time.monotonic() + 10
        while 'WARN' not in (res := drift(env, 'status', '--name', 'recorder')).stdout:
            assert time.monotonic() < deadline, res.stdout
        assert 'disk space low' in res.stdout
        # refused: read at start; a bad value of a runtime one; an unknown node
        res = drift(env, 'param', 'set', '/recorder', 'chunk_size', '5')
        assert res.returncode == 1 and 'chunk_size is read at start only' in res.stderr
        res = drift(env, 'param', 'set', '/recorder', 'disk_stop_free_mb', '1.0e13')
        assert res.returncode == 1 and 'out of range' in res.stderr, res.stderr   # descriptor
        assert drift(env, 'param', 'set', '/recorder', 'disk_warn_free_mb', '100').returncode == 0
        res = drift(env, 'param', 'set', '/recorder', 'disk_stop_free_mb', '200')
        assert res.returncode == 1 and 'stop_free <= warn_free' in res.stderr, res.stderr
        res = drift(env, 'param', 'get', '/planner', 'x', '--timeout', '3')
        assert res.returncode == 2 and 'no node /planner' in res.stderr
        res = drift(env, 'param', 'get', '/recorder', 'no_such')
        assert res.returncode == 2 and "no parameter 'no_such'" in res.stderr
    finally:
        rec.terminate()
        rec.communicate(timeout=20)


@pytest.mark.ros
def test_arm_refused_without_a_state_then_accepted_in_a_hand_over(env):
    """The bridge node in this process on a virtual bus; a car side feeds calm driving."""
    import can
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from drift_control.signals import VehicleState
    from drift_vehicle_bridge.nodes.bridge_node import BridgeNode
    from drift_vehicle_bridge.vehicle_side import CarSide

    os.environ.update(env)
    channel = f'operator-{os.getpid()}'
    rclpy.init()
    car_bus = can.Bus(channel, interface='virtual')
    bridge = BridgeNode(parameter_overrides=[Parameter('interface', value='virtual'),
                                             Parameter('channel', value=channel)])
    executor = SingleThreadedExecutor()
    executor.add_node(bridge)
    stop, feeding = threading.Event(), threading.Event()
    calm = VehicleState(stamp=0.0, V=8.0, beta=-0.05, r=0.4, vx=8.0, vy=-0.4,
                        wheel_speeds=(24.0, 24.0, 24.5, 24.5), delta=0.03, drive_torque=400.0)

    def spin():
        car, last = CarSide(car_bus), 0.0
        while not stop.is_set():
            now = time.monotonic()
            if feeding.is_set() and now - last >= 0.01:
                car.send_state(replace(calm, stamp=now, V=8.0 + 0.02 * math.sin(300 * now)))
                last = now
            car.poll_command(now)
            executor.spin_once(timeout_sec=0.002)
    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        res = drift(env, 'arm')
        assert res.returncode == 1 and 'arm refused' in res.stderr, res.stdout + res.stderr
        feeding.set()
        deadline = time.monotonic() + 10
        while 'validity: 0x7ff' not in (res := drift(env, 'status')).stdout:
            assert time.monotonic() < deadline, res.stdout
        res = drift(env, 'arm')
        assert res.returncode == 0 and 'arm: armed' in res.stdout.lower(), res.stdout + res.stderr
        assert drift(env, 'disarm').returncode == 0
        res = drift(env, 'service', 'call', '/bridge/arm', 'std_srvs/srv/SetBool', '{data: maybe}')
        assert res.returncode == 2 and 'data' in res.stderr, res.stderr
    finally:
        stop.set()
        thread.join(5)
        executor.shutdown()
        bridge.close()
        bridge.destroy_node()
        car_bus.shutdown()
        rclpy.try_shutdown()


@pytest.mark.ros
def test_topic_pub_reaches_echo_and_bad_fields_are_refused(env):
    echo = subprocess.Popen([PYTHON, '-m', 'drift_tools.operator', 'topic', 'echo',
                             '/drift/command', '-n', '1', '--timeout', '30'], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    # publish until the echo has its message (count 0 = until stopped)
    proc = subprocess.Popen([PYTHON, '-m', 'drift_tools.operator', 'topic', 'pub',
                             '/drift/command', 'drift_msgs/msg/DriftCommand',
                             '{drive_torque: 123.5, mode: 2}', '-n', '0', '-r', '20'], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out = echo.communicate(timeout=60)[0]
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert echo.returncode == 0 and 'drive_torque: 123.5' in out, out
    res = drift(env, 'topic', 'pub', '/x', 'drift_msgs/msg/DriftCommand', '{torque: 1}')
    assert res.returncode == 2 and 'torque: no such field' in res.stderr
    res = drift(env, 'topic', 'echo', '/no/such/topic', '--timeout', '2')
    assert res.returncode == 1 and 'no publisher on /no/such/topic' in res.stderr

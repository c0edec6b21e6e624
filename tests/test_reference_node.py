"""reference_node in its own process: refuses to start without a map, publishes with one."""
import math
import shutil
import os
import subprocess
import sys
import textwrap
import time

import pytest

from drift_control.params import config_dir

pytestmark = pytest.mark.ros

CIRCLE = os.path.join(str(config_dir()), 'paths', 'circle_left_15.yaml')

# Runs the real node with drift_control.eqmap replaced by an analytic steady-circle map, so the
# node's plumbing is tested without the map engineer's file (the node itself never invents one).
_WITH_FAKE_MAP = textwrap.dedent('''
    import math, sys, types
    from drift_control.signals import Equilibrium
    class FakeMap:
        radius, meta = [8.0, 40.0], {}
        def lookup(self, beta_abs, radius, direction):
            V = math.sqrt(7.0 * radius); d = int(direction)
            return Equilibrium(V, -d * beta_abs, d * V / radius, V / 0.3, V / 0.3, -d * 0.1,
                               800.0), False
    fake = types.ModuleType('drift_control.eqmap')
    fake.MapError = ValueError
    fake.load_map = lambda *args, **kwargs: FakeMap()
    sys.modules['drift_control.eqmap'] = fake
    from drift_control.nodes.reference_node import main
    sys.exit(main())
''')


@pytest.fixture
def env(monkeypatch):
    domain = 60 + os.getpid() % 5          # 60..64: the reference selector's tests
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return dict(os.environ, PYTHONUNBUFFERED='1')


def test_node_exits_non_zero_without_a_map(env, tmp_path):
    shutil.copytree(config_dir(), tmp_path / 'config')    # its maps dir, ../maps, is empty
    cmd = [sys.executable, '-m', 'drift_control.nodes.reference_node', '--ros-args',
           '-p', f'path_file:={CIRCLE}', '-p', f'config_dir:={tmp_path / "config"}']
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode != 0
    assert 'map' in out.stderr.lower(), out.stderr


def _drive_node(cmd, env, beta=-0.5):
    """Start the node, feed it 2 s of a car 1 m outside the 15 m circle at sideslip ``beta``
    [rad], collect its output."""
    import rclpy
    from drift_msgs.msg import DriftReference, VehicleState
    from nav_msgs.msg import Path as PathMsg
    from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data

    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    rclpy.init()
    node = rclpy.create_node('reference_test')
    refs, paths = [], []
    try:
        pub = node.create_publisher(VehicleState, 'vehicle/state', qos_profile_sensor_data)
        node.create_subscription(DriftReference, 'drift/reference', refs.append, 10)
        node.create_subscription(PathMsg, 'drift/path', paths.append,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        deadline = time.monotonic() + 30.0
        while pub.get_subscription_count() == 0 or not paths:
            assert time.monotonic() < deadline and proc.poll() is None, 'node did not come up'
            rclpy.spin_once(node, timeout_sec=0.1)
        R, V = 15.0, 10.0
        for k in range(100):
            theta = V * 0.02 * k / R
            m = VehicleState(v=V, beta=beta, r=V / R, x=16 * math.sin(theta),
                             y=R - 16 * math.cos(theta), yaw=theta - beta, validity=2047)
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(20_000_000 * k, 1_000_000_000)
            pub.publish(m)
            end = time.monotonic() + 0.02
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.005)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.shutdown()
        proc.terminate()
        out = proc.communicate(timeout=20)[0]
    assert len(refs) > 30, out
    assert len(paths[0].poses) > 150
    last = refs[-1]
    assert last.direction == last.DIRECTION_LEFT and last.target.r > 0
    assert last.e_y == pytest.approx(-1.0, abs=1e-6)
    assert last.curvature == pytest.approx(1 / R) and last.curvature_cmd > 1 / R
    assert last.s == pytest.approx(V * 0.02 * (last.header.stamp.sec * 50
                                               + last.header.stamp.nanosec // 20_000_000), abs=0.05)
    return refs


def test_node_publishes_references_and_the_path(env):
    _drive_node([sys.executable, '-c', _WITH_FAKE_MAP, '--ros-args', '-p',
                 f'path_file:={CIRCLE}'], env)


def test_node_with_the_real_map(env):
    # a car in grip (a slide beyond catch_beta would be caught: test_reference_selector)
    refs = _drive_node([sys.executable, '-m', 'drift_control.nodes.reference_node', '--ros-args',
                        '-p', f'path_file:={CIRCLE}'], env, beta=-0.03)
    last = refs[-1]
    assert len(last.horizon) > 1
    assert last.s < 20.0, 'still in the grip entry of circle_left_15 (grip_until 20 m)'
    assert last.target.beta == 0.0 and last.target.delta > 0.0, 'grip steers into the turn'
    assert last.horizon[-1].beta < 0.0, 'the horizon sees the drift entry coming'

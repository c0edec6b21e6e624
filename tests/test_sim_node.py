"""sim_node in its own process: in lock-step it advances only when the controller's command came."""
import os
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.ros


@pytest.fixture
def env(monkeypatch):
    domain = 70 + os.getpid() % 10          # 70..79: the simulator's tests
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return dict(os.environ, PYTHONUNBUFFERED='1')


def test_lockstep_advances_only_on_commands(env):
    import rclpy
    from drift_msgs.msg import DriftCommand, VehicleState
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    proc = subprocess.Popen([sys.executable, '-m', 'drift_sim.nodes.sim_node', '--ros-args',
                             '-p', 'scenario:=steady_dry', '-p', 'clock_mode:=lockstep',
                             '-p', 'startup_timeout:=60.0', '-p', 'lockstep_timeout:=60.0',
                             '-p', 'wait_reference:=false'],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node('sim_test')
    clocks, states = [], []
    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    try:
        node.create_subscription(Clock, '/clock', lambda m: clocks.append(
            m.clock.sec + 1e-9 * m.clock.nanosec), reliable)
        node.create_subscription(VehicleState, 'vehicle/state', states.append, reliable)
        pub = node.create_publisher(DriftCommand, 'drift/command', reliable)

        def spin_for(seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.02)

        deadline = time.monotonic() + 60.0
        while pub.get_subscription_count() == 0 or not states:   # the first state is re-offered
            assert time.monotonic() < deadline and proc.poll() is None, 'sim did not come up'
            rclpy.spin_once(node, timeout_sec=0.1)
        spin_for(1.0)
        assert max(clocks, default=0.0) == 0.0, 'without a command the sim waits at 0 s'
        assert all(st.header.stamp.nanosec == 0 for st in states)
        for k in range(4):
            t = 0.02 * k
            cmd = DriftCommand(mode=DriftCommand.MODE_FULL, delta=0.05, drive_torque=500.0)
            cmd.header.stamp.sec, cmd.header.stamp.nanosec = 0, int(round(t * 1e9))
            pub.publish(cmd)
            spin_for(0.8)
            assert max(clocks) == pytest.approx(t + 0.02), f'one command at {t} s, one period'
        assert states[-1].header.stamp.nanosec == int(round(0.08 * 1e9))
        assert proc.poll() is None
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        proc.terminate()
        out, _ = proc.communicate(timeout=20)
    assert 'lockstep' in out, out

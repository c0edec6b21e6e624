"""nmpc_node in its own process: a finite command and a status for a given state and reference."""
import math
import os
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.ros


@pytest.fixture
def env(monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(50 + os.getpid() % 10))   # 50..59: the NMPC's tests
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return dict(os.environ, PYTHONUNBUFFERED='1')


@pytest.mark.parametrize('trigger', ['timer', 'state'])
def test_node_publishes_a_finite_command(env, trigger):
    import rclpy
    from drift_msgs.msg import DriftCommand, DriftReference, Equilibrium, NmpcStatus, VehicleState
    from rclpy.qos import qos_profile_sensor_data

    cmd = [sys.executable, '-m', 'drift_control.nodes.nmpc_node', '--ros-args',
           '-p', 'control_mode:=full', '-p', f'trigger:={trigger}']
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    rclpy.init()
    node = rclpy.create_node('nmpc_test')
    commands, statuses = [], []
    try:
        state_pub = node.create_publisher(VehicleState, 'vehicle/state', qos_profile_sensor_data)
        ref_pub = node.create_publisher(DriftReference, 'drift/reference', 10)
        node.create_subscription(DriftCommand, 'drift/command', commands.append, 10)
        node.create_subscription(NmpcStatus, 'drift/nmpc/status', statuses.append, 10)
        deadline = time.monotonic() + 60.0
        while state_pub.get_subscription_count() == 0 or ref_pub.get_subscription_count() == 0:
            assert proc.poll() is None, proc.stdout.read()
            assert time.monotonic() < deadline, 'node did not come up'
            rclpy.spin_once(node, timeout_sec=0.1)
        # a 30 deg left drift on R = 15 m, slightly off its equilibrium
        eq = Equilibrium(v=10.67, beta=-0.5236, r=0.7113, omega_f=31.22, omega_r=41.76,
                         delta=-0.3833, drive_torque=1434.0)
        while not any(s.status == NmpcStatus.STATUS_OK for s in statuses):
            assert proc.poll() is None, proc.stdout.read()
            assert time.monotonic() < deadline, [s.message for s in statuses[-3:]]
            stamp = node.get_clock().now().to_msg()
            state = VehicleState(v=10.2, beta=-0.45, r=0.65, wheel_speeds=[31.0, 31.0, 40.0, 40.0],
                                 delta=-0.35, validity=VehicleState.VALID_ALL)
            state.header.stamp = stamp
            ref = DriftReference(direction=DriftReference.DIRECTION_LEFT, target=eq)
            ref.header.stamp = stamp
            ref_pub.publish(ref)
            state_pub.publish(state)
            end = time.monotonic() + 0.02
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.005)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        proc.terminate()
        proc.wait(timeout=10)
    ok = [s for s in statuses if s.status == NmpcStatus.STATUS_OK][0]
    assert len(ok.predicted_states) == 26 * len(ok.state_names)
    assert ok.solve_time > 0.0 and math.isfinite(ok.cost)
    assert commands
    for c in commands:
        assert all(math.isfinite(v) for v in (c.delta, c.delta_rate, c.drive_torque))
        assert abs(c.delta) <= 0.5 and -1500.0 <= c.drive_torque <= 6000.0
    assert any(c.mode == DriftCommand.MODE_FULL for c in commands)

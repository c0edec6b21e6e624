"""drift_msgs between two OS processes over DDS: every field survives, and the round trip is fast."""
import math
import statistics
import subprocess
import time

import pytest

from conftest import PYTHON

pytestmark = pytest.mark.ros


@pytest.fixture
def ros_node(tools_domain_id):
    """An rclpy node of this test process in its own context (nothing global left behind)."""
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=tools_domain_id)
    node = rclpy.create_node('roundtrip_test', context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)


def _spin_until(executor, cond, timeout, what):
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        executor.spin_once(timeout_sec=0.02)


def test_drift_reference_round_trip_between_processes(ros_node, node_env):
    from drift_msgs.msg import DriftReference, Equilibrium
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    node, executor = ros_node
    echo = subprocess.Popen([PYTHON, '-m', 'nodes_for_tests.echo'], env=node_env)
    try:
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        received = []
        pub = node.create_publisher(DriftReference, 'ping', qos)
        node.create_subscription(DriftReference, 'pong', received.append, qos)
        _spin_until(executor, lambda: pub.get_subscription_count() > 0
                    and node.count_publishers('pong') > 0, 20.0, 'discovery of the echo node')

        eq = Equilibrium(v=8.0, beta=-0.5, r=0.53, omega_f=26.0, omega_r=40.0, delta=-0.2,
                         drive_torque=900.0)
        sent = DriftReference(direction=DriftReference.DIRECTION_LEFT, target=eq,
                              horizon=[eq, Equilibrium(v=1.0)], curvature=1 / 15.0, e_y=-0.3,
                              clamped=True)
        sent.header.frame_id = 'map'
        # Reliable, but the echo's subscription may still be settling: resend until one returns.
        _spin_until(executor, lambda: received or pub.publish(sent), 10.0, 'the first echo')
        got = received[0]
        assert got.header.frame_id == 'map' and got.direction == DriftReference.DIRECTION_LEFT
        assert got.target == eq and list(got.horizon) == [eq, Equilibrium(v=1.0)]
        assert got.curvature == pytest.approx(1 / 15.0) and got.e_y == -0.3 and got.clamped

        rtt = []
        for i in range(1, 41):     # the warm-up resends carried s = 0 and may still arrive
            received.clear()
            sent.s = float(i)
            t0 = time.perf_counter()
            pub.publish(sent)
            _spin_until(executor, lambda: any(m.s == float(i) for m in received), 5.0, f'echo {i}')
            rtt.append(time.perf_counter() - t0)
        median, p95 = statistics.median(rtt), sorted(rtt)[int(0.95 * len(rtt)) - 1]
        print(f'\nDriftReference round trip over 2 processes: median {1e3 * median:.2f} ms, '
              f'p95 {1e3 * p95:.2f} ms, max {1e3 * max(rtt):.2f} ms (n={len(rtt)})')
        assert math.isfinite(median) and median < 0.1, f'round trip median {median:.3f} s'
    finally:
        echo.terminate()
        try:
            echo.wait(10)
        except subprocess.TimeoutExpired:   # once (1 of ~6 CI runs) its DDS teardown hung
            echo.kill()                     # past 10 s; the round trip was already judged
            echo.wait(5)

"""The loop's QoS: a subscription matched late (the recorder's) still gets the first messages."""
import time
from types import SimpleNamespace

import pytest

from drift_tools.recording import KEPT_TOPICS, STACK_TOPICS

TIMEOUT = 10.0


def test_kept_topics_are_stack_topics_and_not_latched_values():
    assert KEPT_TOPICS <= set(STACK_TOPICS)
    assert {'drift/command', 'drift/nmpc/status', 'sim/state', '/clock'} <= KEPT_TOPICS
    assert not any(STACK_TOPICS[t][1] for t in KEPT_TOPICS), 'a history, not a latched value'


@pytest.mark.ros
def test_a_transient_local_subscription_gets_what_was_published_before_it_matched(
        tools_domain_id):
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Int32

    from drift_control.nodes.qos import KEPT_DEPTH, kept_qos
    from drift_tools.nodes.recorder_node import make_qos

    context = Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node('kept_qos_test', context=context)
        pub = node.create_publisher(Int32, 'drift/command', kept_qos())
        for i in range(3):          # nobody listens yet: the recorder has not matched us
            pub.publish(Int32(data=i))
        late, live = [], []
        node.create_subscription(Int32, 'drift/command', lambda m: late.append(m.data),
                                 make_qos(True, True))
        live_sub = node.create_subscription(Int32, 'drift/command', lambda m: live.append(m.data),
                                            make_qos(True, False))
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + TIMEOUT
        while pub.get_subscription_count() < 2 or live_sub.get_publisher_count() < 1 \
                or len(late) < 3:
            assert time.monotonic() < deadline, f'got {late}'
            executor.spin_once(timeout_sec=0.05)
        pub.publish(Int32(data=3))
        while len(late) < 4 or not live:
            assert time.monotonic() < deadline, f'got {late}, {live}'
            executor.spin_once(timeout_sec=0.05)
        assert late == [0, 1, 2, 3], 'the kept messages, then the new one, each once'
        assert live == [3], 'a volatile subscription gets only what is sent after it matched'
        assert KEPT_DEPTH >= 50
        executor.shutdown()
    finally:
        rclpy.shutdown(context=context)


def test_echo_and_hz_take_only_new_messages_of_a_kept_topic():
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from drift_tools.nodes.cli_ros import matching_qos
    latched = [SimpleNamespace(qos_profile=SimpleNamespace(
        reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))]
    assert matching_qos(latched, '/drift/command').durability == DurabilityPolicy.VOLATILE
    assert matching_qos(latched, '/clock').durability == DurabilityPolicy.VOLATILE
    assert matching_qos(latched, '/drift/path').durability == DurabilityPolicy.TRANSIENT_LOCAL

"""nodes.matching: a publisher counts as matched once its side sees every listed subscription."""
import threading

from drift_control.nodes.matching import publishers_matched, wait_publishers_matched


class FakePub:
    def __init__(self, topic, matched):
        self.topic_name, self.matched = topic, matched

    def get_subscription_count(self):
        return self.matched


class FakeNode:
    def __init__(self, listed):
        self.listed = listed

    def count_subscribers(self, topic):
        return self.listed[topic]


def test_a_subscription_the_graph_lists_but_the_publisher_has_not_matched_is_waited_for():
    node = FakeNode({'/drift/command': 2, '/drift/nmpc/status': 1})
    cmd, status = FakePub('/drift/command', 1), FakePub('/drift/nmpc/status', 1)
    assert not publishers_matched(node, [cmd, status])   # the recorder's: listed, not matched
    threading.Timer(0.05, lambda: setattr(cmd, 'matched', 2)).start()   # the middleware's thread
    assert wait_publishers_matched(node, [cmd, status], timeout=5.0)
    assert publishers_matched(node, [cmd, status])


def test_the_wait_gives_up_after_its_timeout():
    node = FakeNode({'/drift/command': 1})
    assert not wait_publishers_matched(node, [FakePub('/drift/command', 0)], timeout=0.05)

"""Whether a node's publishers are matched, writer side, with every subscription of the graph.

Discovery is not symmetric: a subscription (the recorder's) can be matched with a publisher, and
the graph can list it, while that publisher has not matched the subscription yet. What a
reliable, volatile publisher sends in that gap never reaches it (a bag without the run's first
commands), so lock-step nodes wait for their publishers' side too.
"""
from __future__ import annotations

import time

MATCH_POLL_S = 0.002   # how often a wait looks again [s]
MATCH_TIMEOUT_S = 1.0  # a lock-step node waits this long at most, once [s]


def publishers_matched(node, publishers) -> bool:
    """Every publisher matched with as many subscriptions as the graph lists on its topic."""
    return all(pub.get_subscription_count() >= node.count_subscribers(pub.topic_name)
               for pub in publishers)


def wait_publishers_matched(node, publishers, timeout: float) -> bool:
    """Block until ``publishers_matched`` (the middleware matches in its own threads, not in
    the executor), at most ``timeout`` [s]; False if it timed out."""
    deadline = time.monotonic() + timeout
    while not publishers_matched(node, publishers):
        if time.monotonic() >= deadline:
            return False
        time.sleep(MATCH_POLL_S)
    return True

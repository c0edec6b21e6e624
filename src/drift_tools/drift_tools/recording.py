"""Which topics the recorder records: the stack's fixed list plus anything under its namespaces."""
from __future__ import annotations

from dataclasses import dataclass

# The stack's topics (relative names, as the nodes publish them: a namespace or remap moves them
# all together) -> (type, latched). Known in advance, so the recorder subscribes to them before
# their publishers exist and misses none of the first messages; latched = transient-local.
STACK_TOPICS = {
    'vehicle/state': ('drift_msgs/msg/VehicleState', False),
    'vehicle/sensors': ('drift_msgs/msg/SensorSamples', False),   # with the estimator stage
    'drift/reference': ('drift_msgs/msg/DriftReference', False),
    'drift/command': ('drift_msgs/msg/DriftCommand', False),
    'drift/nmpc/status': ('drift_msgs/msg/NmpcStatus', False),
    'drift/path': ('nav_msgs/msg/Path', True),
    'diagnostics': ('diagnostic_msgs/msg/DiagnosticArray', False),
    '/clock': ('rosgraph_msgs/msg/Clock', False),
    'sim/state': ('drift_msgs/msg/VehicleState', False),
    '/rosout': ('rcl_interfaces/msg/Log', True),   # every node's log lines (transient local)
}
# The loop's topics, published with a short transient-local history (drift_control.nodes.qos):
# subscribed transient local from the start, a publisher that matches the recorder late still
# delivers the run's first messages.
KEPT_TOPICS = frozenset({'vehicle/state', 'vehicle/sensors', 'drift/reference', 'drift/command',
                         'drift/nmpc/status', '/clock', 'sim/state'})
STACK_NAMESPACES = ('vehicle', 'drift', 'sim')
NEVER = ('/parameter_events',)


@dataclass(frozen=True)
class TopicSelector:
    """Decide from a resolved (absolute) topic name whether to record it.

    Parameters
    ----------
    topics : tuple of str
        Absolute names always recorded once a publisher appears.
    namespaces : tuple of str
        Absolute namespaces (``/sim``); every topic below one is recorded too.
    """

    topics: tuple
    namespaces: tuple

    def wants(self, topic: str) -> bool:
        """True for a listed topic or one under a recorded namespace."""
        if topic in NEVER or topic.endswith(('/_action/status', '/_action/feedback')):
            return False
        if topic in self.topics:
            return True
        return any(topic.startswith(ns.rstrip('/') + '/') for ns in self.namespaces)

    def select(self, names_and_types) -> list[tuple[str, str]]:
        """From ``get_topic_names_and_types()`` output, the (topic, type) pairs to record.

        A topic published with several types is skipped (it cannot go into one channel).
        """
        out = []
        for name, types in names_and_types:
            if self.wants(name) and len(types) == 1:
                out.append((name, types[0]))
        return out

"""Which topics the recorder records: the stack's fixed list plus anything under its namespaces."""
from __future__ import annotations

from dataclasses import dataclass

# Relative names, as the nodes publish them (a namespace or remap moves them all together).
STACK_TOPICS = (
    'vehicle/state', 'drift/reference', 'drift/command', 'drift/nmpc/status', 'drift/path',
    'diagnostics', '/clock',
)
STACK_NAMESPACES = ('vehicle', 'drift', 'sim')
NEVER = ('/rosout', '/parameter_events')


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

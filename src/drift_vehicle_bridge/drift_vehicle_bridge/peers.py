"""Whether a node the drive does not depend on, but the operator should know about, is alive.

On the car the recorder is not critical: the drive goes on without it (``stack.yaml``), so its
death must be visible where the operator looks, in the bridge's diagnostics. The recorder reports
on ``/diagnostics`` every second; :class:`HeartbeatWatch` turns its reports, or their absence,
into one status. No ROS here.
"""
from __future__ import annotations

from dataclasses import dataclass

OK, WARN, ERROR = 0, 1, 2     # as diagnostic_msgs/DiagnosticStatus levels


@dataclass
class HeartbeatWatch:
    """The last report of the diagnostics status named ``name``, and when it came.

    Parameters
    ----------
    name : str
        ``DiagnosticStatus.name`` to follow (``'recorder'``).
    timeout : float
        Silence after which the peer counts as gone [s].
    """

    name: str
    timeout: float = 3.0
    _level: int = OK
    _message: str = ''
    _seen: float | None = None

    def report(self, level: int, message: str, now: float) -> None:
        """The peer's status as it published it, received at ``now`` [s]."""
        self._level, self._message, self._seen = int(level), message, now

    def status(self, now: float) -> tuple[int, str] | None:
        """(level, message); None while the peer was never heard of (not in this graph)."""
        if self._seen is None:
            return None
        silent = now - self._seen
        if silent > self.timeout:
            return ERROR, f'{self.name} silent for {silent:.1f} s: presumed dead'
        return self._level, f'{self.name}: {self._message}'

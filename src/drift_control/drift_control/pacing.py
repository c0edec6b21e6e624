"""Real-time pacing: how many fixed-period cycles are due, so a late timer never loses a cycle.

A ROS timer that fires late skips the periods it missed (rcl keeps the phase, not the count): a
10 ms loop on a loaded machine then runs at 93 Hz instead of 100. ``Pacer`` counts cycles on the
monotonic clock instead; the caller runs every due cycle, so the rate holds on average and only
a stall longer than ``max_burst`` periods is dropped (and counted).
"""
from __future__ import annotations

import math


class Pacer:
    """Cycles of ``period`` due at ``now``, counted from the first call.

    Parameters
    ----------
    period : float
        Cycle period [s].
    max_burst : int
        Most cycles run back to back to catch up; a longer stall is skipped, not replayed.
    """

    def __init__(self, period: float, max_burst: int = 5):
        if not period > 0.0 or max_burst < 1:
            raise ValueError(f'Pacer: period must be > 0 and max_burst >= 1, got {period}, '
                             f'{max_burst}')
        self.period, self.max_burst = period, max_burst
        self.cycles = 0        # cycles run
        self.skipped = 0       # cycles dropped after stalls longer than max_burst periods
        self.late = 0          # calls that ran more than one cycle
        self._next: float | None = None

    def due(self, now: float) -> int:
        """Cycles to run now (``now`` a monotonic clock [s]); each counts as run."""
        if self._next is None:
            self._next = now
        # a cycle is due from half a period before its time: a timer firing a little early or
        # late must not alternate between 0 and 2 cycles
        n = max(0, math.floor((now - self._next) / self.period + 0.5) + 1)
        if n > self.max_burst:
            self.skipped += n - self.max_burst
            self._next += (n - self.max_burst) * self.period
            n = self.max_burst
        self._next += n * self.period
        self.cycles += n
        self.late += int(n > 1)
        return n

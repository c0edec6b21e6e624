"""Pacing: cycles due on a clock (``Pacer``), periods due in stamp time (``PeriodGate``).

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


class PeriodGate:
    """Once per ``period`` of stamp time: is a stamp due? Never wedged by one bad stamp.

    A stamp opens a new period from ``TOLERANCE`` of a period before the last served one plus
    ``period``: stamps taken in real time jitter by milliseconds, and a state 0.5 ms early must
    not hold the solve over to the next state (a 30 ms gap in a 20 ms loop, 4 % of the cycles
    at 100 Hz states). A source faster than twice the rate is served every 3/4 period at most.
    A stamp more than ``FUTURE_MAX`` ahead of the node's own clock is refused (one state stamped
    1e6 s would otherwise push the next due time out of reach for good); a stamp more than a
    period before the last one that fired means the clock stepped back (a restarted simulator,
    a corrected clock): the gate starts over on the new timeline instead of waiting out the step.
    """

    EPS = 1e-3          # stamp tolerance of a backward step [s]
    TOLERANCE = 0.25    # how early a stamp may open its period [periods]
    FUTURE_MAX = 1.0    # largest believable lead of a stamp over the node's clock [s]

    def __init__(self, period: float):
        self.period = period
        self.last = -math.inf      # stamp that fired last
        self.refused_future = 0    # stamps refused as from the future
        self.restarts = 0          # backward clock steps followed

    def due(self, stamp: float, clock: float | None = None) -> bool:
        """Whether ``stamp`` opens a new period (``clock``: the node's time, None: unknown)."""
        if clock is not None and stamp > clock + self.FUTURE_MAX:
            self.refused_future += 1
            return False
        if stamp < self.last - self.period - self.EPS:
            self.last = -math.inf
            self.restarts += 1
        return stamp >= self.last + (1.0 - self.TOLERANCE) * self.period

    def fired(self, stamp: float) -> None:
        """The period of ``stamp`` was served."""
        self.last = stamp

"""Where a periodic cycle's late start went: its own running, waiting for a CPU, or the machine.

The link cycles (the bridge, a simulated car) run against 30 ms frame timeouts; on a shared
virtual machine a cycle can start late because the hypervisor took the CPUs or other tasks had
them, not because of the cycle's own work. Read from Linux's per-thread scheduler statistics
and per-CPU steal time; zeros where there is no /proc. No ROS import.
"""
from __future__ import annotations

import os


class CycleWatch:
    """The longest gap between two runs of a periodic cycle, and where its time went.

    Call ``tick`` at the start of each cycle, in the thread that runs it. Of the longest gap
    since the last ``take``: ``ran`` is this thread's own CPU time, ``waited`` its time runnable
    on a run queue while other tasks (or the kernel's share for normal tasks) had the CPUs, and
    ``stolen`` the CPU time the machine's hypervisor took from the busiest CPU; the rest it
    slept or was blocked. A cycle late by what it waited and what was stolen was delayed by the
    machine; one late by its own running or sleeping, by itself.
    """

    def __init__(self):
        self._last: tuple[float, int, int, tuple[int, ...]] | None = None
        self._tick = 1.0 / os.sysconf('SC_CLK_TCK') if hasattr(os, 'sysconf') else 0.01   # [s]
        self.reset()

    def reset(self) -> None:
        self.gap = self.ran = self.waited = self.stolen = 0.0

    def tick(self, now: float) -> None:
        """At the start of a cycle, ``now`` [s] on a monotonic clock."""
        ran, waited = _thread_schedstat()
        stolen = _steal_ticks()
        if self._last is not None:
            gap = now - self._last[0]
            if gap > self.gap:
                self.gap = gap
                self.ran = 1e-9 * (ran - self._last[1])
                self.waited = 1e-9 * (waited - self._last[2])
                self.stolen = min(gap, self._tick * max(
                    (b - a for a, b in zip(self._last[3], stolen)), default=0))
        self._last = (now, ran, waited, stolen)

    def take(self) -> dict[str, float]:
        """The longest gap since the last call and its parts [s]; starts over."""
        out = {'gap': self.gap, 'ran': self.ran, 'waited': self.waited, 'stolen': self.stolen}
        self.reset()
        return out


def _thread_schedstat() -> tuple[int, int]:
    """This thread's time on a CPU and runnable waiting for one [ns] (0, 0 where unknown)."""
    try:
        with open('/proc/thread-self/schedstat') as f:
            ran, waited, _ = f.read().split()
        return int(ran), int(waited)
    except (OSError, ValueError):
        return 0, 0


def _steal_ticks() -> tuple[int, ...]:
    """Steal time of each CPU [clock ticks] (() where unknown)."""
    try:
        with open('/proc/stat') as f:
            f.readline()   # all CPUs together
            out = []
            for line in f:
                if not line.startswith('cpu'):
                    break
                out.append(int(line.split()[8]))
        return tuple(out)
    except (OSError, ValueError, IndexError):
        return ()

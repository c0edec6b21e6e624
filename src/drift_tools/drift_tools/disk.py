"""Disk space for a recording: a warning well before the disk is full, a clean stop just before.

A recorder that runs the disk full loses the bag's summary and, on a car, whatever else needs the
disk. :class:`DiskWatch` looks at the free space and the recording's write rate: it warns when the
space left is below a floor or would last less than a set time at the current rate, and asks for
a stop while there is still room to close the bag properly. No ROS here; the recorder node calls it.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from enum import IntEnum

MIB = 1024 * 1024


class DiskLevel(IntEnum):
    OK = 0
    WARN = 1      # record on, tell the operator
    STOP = 2      # close the bag now, while its summary still fits


@dataclass(frozen=True)
class DiskLimits:
    """When to warn and when to stop [bytes, s]."""

    warn_free: float = 2048 * MIB       # warn below this much free space
    warn_time_left: float = 600.0       # or when the free space lasts less at the current rate
    stop_free: float = 64 * MIB         # stop recording below this (the summary needs some room)
    rate_tau: float = 10.0              # time constant of the write-rate average [s]

    def __post_init__(self):
        if not 0 <= self.stop_free <= self.warn_free:
            raise ValueError('disk limits: need 0 <= stop_free <= warn_free')
        if self.warn_time_left < 0 or self.rate_tau <= 0:
            raise ValueError('disk limits: warn_time_left >= 0 and rate_tau > 0 needed')


@dataclass(frozen=True)
class DiskStatus:
    level: DiskLevel
    free: int                  # [bytes]
    rate: float                # recording's write rate [bytes/s]
    time_left: float           # free / rate [s]; inf while nothing is written
    message: str


class DiskWatch:
    """Free space of the file system holding ``path`` against :class:`DiskLimits`.

    Parameters
    ----------
    path : path
        Any path on the file system to watch (the bag directory).
    usage : callable
        ``usage(path).free`` in bytes; ``shutil.disk_usage`` (a test passes its own).
    """

    def __init__(self, path, limits: DiskLimits = DiskLimits(), usage=shutil.disk_usage):
        self.path, self.limits, self._usage = path, limits, usage
        self._last = None          # (time, bytes written)
        self.rate = 0.0

    def check(self, written: int, now: float) -> DiskStatus:
        """The status now, given the bytes the recording has written so far and the time [s]."""
        if self._last is not None and now > self._last[0]:
            dt = now - self._last[0]
            sample = max(written - self._last[1], 0) / dt
            weight = min(dt / self.limits.rate_tau, 1.0)
            self.rate += weight * (sample - self.rate)
        self._last = (now, written)
        free = int(self._usage(self.path).free)
        left = free / self.rate if self.rate > 0 else float('inf')
        lim = self.limits
        text = f'{free / MIB:.0f} MiB free'
        if left < float('inf'):
            text += f', {_duration(left)} at {self.rate / MIB:.2f} MiB/s'
        if free < lim.stop_free:
            return DiskStatus(DiskLevel.STOP, free, self.rate, left,
                              f'disk nearly full ({text}): recording stopped')
        if free < lim.warn_free or left < lim.warn_time_left:
            return DiskStatus(DiskLevel.WARN, free, self.rate, left, f'disk space low: {text}')
        return DiskStatus(DiskLevel.OK, free, self.rate, left, text)


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f'{seconds / 3600:.1f} h'
    if seconds >= 60:
        return f'{seconds / 60:.0f} min'
    return f'{seconds:.0f} s'

"""Log replay: frames of a recorded drive (candump .log, .asc, .blf, ...) paced in real time."""
from __future__ import annotations

import os
from collections.abc import Iterator

import can

from drift_vehicle_bridge.pdu import Pdu
from drift_vehicle_bridge.transport import pdu_of


class LogReplay:
    """Hands out the frames of a python-can log as their recorded time comes due.

    Parameters
    ----------
    path : str or os.PathLike
        Any log ``can.LogReader`` reads; the format follows the suffix.
    speed : float
        Replay speed factor (1 = as recorded).
    """

    def __init__(self, path: str | os.PathLike, speed: float = 1.0):
        self._reader = can.LogReader(path)
        self._frames: Iterator[can.Message] = iter(self._reader)
        self._speed = speed
        self._pending: can.Message | None = next(self._frames, None)
        self._t0_log = self._pending.timestamp if self._pending else 0.0
        self._t0: float | None = None
        self.finished = self._pending is None

    def due(self, now: float) -> list[Pdu]:
        """Every frame recorded up to ``now`` [s] since the first call (replay clock)."""
        if self._t0 is None:
            self._t0 = now
        horizon = self._t0_log + (now - self._t0) * self._speed
        out = []
        while self._pending is not None and self._pending.timestamp <= horizon:
            out.append(pdu_of(self._pending))
            self._pending = next(self._frames, None)
        if self._pending is None and not self.finished:
            self.finished = True
            self._reader.stop()
        return out


__all__ = ['LogReplay']

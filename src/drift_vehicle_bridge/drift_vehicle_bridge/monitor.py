"""The state monitor: checked state frames in, a VehicleState with per-signal validity bits out."""
from __future__ import annotations

import can

from drift_control.params import ParamError
from drift_control.signals import VehicleState
from drift_vehicle_bridge.checks import FrameChecker
from drift_vehicle_bridge.codec import (STATE_FRAMES, VALIDITY_FRAMES, Codec, frame_fields,
                                        state_from_fields)
from drift_vehicle_bridge.params import MonitorParams


class StateMonitor:
    """Keeps the latest accepted value of every state signal and when its frame last arrived.

    A validity bit is set while every frame it needs (``codec.VALIDITY_FRAMES``) passed its checks
    within its timeout; a stale signal keeps its last value with the bit cleared.
    """

    def __init__(self, codec: Codec, params: MonitorParams):
        unknown = sorted(set(params.timeouts) - set(STATE_FRAMES))
        if unknown:
            raise ParamError(f'bridge.monitor.timeouts: unknown frame(s) {unknown}')
        self.checker = FrameChecker(codec, STATE_FRAMES, params.max_counter_delta,
                                    params.frame_timeout)
        self._timeout = {n: params.timeouts.get(n, params.frame_timeout) for n in STATE_FRAMES}
        self._fields: dict[str, float] = {}
        self._seen: dict[str, float] = {}     # frame name -> time it was last accepted [s]

    def receive(self, msg: can.Message, now: float) -> bool:
        """Check one received frame at time ``now`` [s]; True if it was accepted."""
        frame = self.checker.check(msg, now)
        if frame is None or frame.name not in STATE_FRAMES:
            return False
        self._fields.update(frame_fields(frame))
        self._seen[frame.name] = now
        return True

    def fresh(self, name: str, now: float) -> bool:
        seen = self._seen.get(name)
        return seen is not None and now - seen <= self._timeout[name]

    def validity(self, now: float) -> int:
        """Validity bits of the state at time ``now`` [s]."""
        bits = 0
        for bit, frames in VALIDITY_FRAMES.items():
            if all(self.fresh(n, now) for n in frames):
                bits |= int(bit)
        return bits

    def state(self, now: float) -> VehicleState | None:
        """The current state, or None before the first accepted frame."""
        if not self._seen:
            return None
        return state_from_fields(self._fields, now, self.validity(now))


__all__ = ['StateMonitor']

"""The state monitor: checked state PDUs in, a VehicleState with per-signal validity bits out."""
from __future__ import annotations

from drift_control.params import ParamError
from drift_control.signals import VehicleState
from drift_vehicle_bridge.checks import FrameChecker
from drift_vehicle_bridge.codec import Codec, state_from_fields
from drift_vehicle_bridge.params import MonitorParams
from drift_vehicle_bridge.pdu import Pdu


class StateMonitor:
    """Keeps the latest accepted value of every state signal and when its PDU last arrived.

    A validity bit is set while every PDU carrying one of its signals (``codec.validity_frames``)
    is valid (E2E) and arrived within its timeout; an invalid signal keeps its last value with
    the bit cleared. With ``sensors`` (a ``SensorAssembler``) each accepted PDU whose E2E state
    is valid also goes there.
    """

    def __init__(self, codec: Codec, params: MonitorParams, sensors=None):
        self.codec, self.sensors = codec, sensors
        names = codec.gateway_pdus
        unknown = sorted(set(params.timeouts) - set(names))
        if unknown:
            raise ParamError(f'bridge.monitor.timeouts: unknown PDU(s) {unknown} '
                             f'(the description has {sorted(names)})')
        self.checker = FrameChecker(codec, names, params.max_counter_delta, params.e2e)
        self._timeout = {n: params.timeouts.get(n, params.frame_timeout) for n in names}
        self._fields: dict[str, float] = {}
        self._seen: dict[str, float] = {}     # PDU name -> time it was last accepted [s]

    def receive(self, pdu: Pdu, now: float) -> bool:
        """Check one received PDU at time ``now`` [s]; True if it was accepted."""
        frame = self.checker.check(pdu, now)
        if frame is None or frame.name not in self._timeout:
            return False
        self._fields.update(self.codec.frame_fields(frame))
        self._seen[frame.name] = now
        if self.sensors is not None and self.checker.valid(frame.name):
            self.sensors.receive(frame, now)
        return True

    def tick(self, now: float) -> None:
        """End of a receive cycle: each PDU overdue at ``now`` counts as no new data."""
        for name, timeout in self._timeout.items():
            seen = self._seen.get(name)
            if seen is None or now - seen > timeout:
                self.checker.no_new_data(name)

    def timeout(self, name: str) -> float:
        """How long PDU ``name`` may be missing before its signals go invalid [s]."""
        return self._timeout[name]

    def fresh(self, name: str, now: float) -> bool:
        seen = self._seen.get(name)
        return seen is not None and now - seen <= self._timeout[name] \
            and self.checker.valid(name)

    def validity(self, now: float) -> int:
        """Validity bits of the state at time ``now`` [s]."""
        bits = 0
        for bit, frames in self.codec.validity_frames.items():
            if all(self.fresh(n, now) for n in frames):
                bits |= int(bit)
        return bits

    def state(self, now: float) -> VehicleState | None:
        """The current state, or None before the first accepted PDU."""
        if not self._seen:
            return None
        return state_from_fields(self._fields, now, self.validity(now))


__all__ = ['StateMonitor']

"""Receive-side checks: id, format, AUTOSAR E2E (profile check + state machine per PDU), range."""
from __future__ import annotations

import logging
from collections import Counter

from drift_vehicle_bridge.codec import Codec, Fault, Frame, FrameError
from drift_vehicle_bridge.e2e import ProfileStatus, Receiver, SMConfig
from drift_vehicle_bridge.pdu import Pdu

log = logging.getLogger(__name__)

ACCEPTED = (ProfileStatus.OK, ProfileStatus.OK_SOME_LOST)
STATUS_FAULT = {ProfileStatus.REPEATED: Fault.COUNTER_REPEAT,
                ProfileStatus.WRONG_SEQUENCE: Fault.COUNTER_JUMP}


class FrameChecker:
    """Accepts or rejects each received PDU and counts both; never raises.

    One E2E receiver per PDU this side consumes. A PDU's signals are valid while its E2E state
    machine is VALID and the last PDU received passed every check: a rejected PDU (bad CRC,
    repeated or jumping counter, wrong data ID or length, a value out of range) invalidates them
    at once, not only when the good one before it times out.

    Parameters
    ----------
    codec : Codec
        The description's codec.
    rx_names : iterable of str
        PDUs this side consumes; any other known PDU is counted as ``foreign`` (our own
        transmissions echoed by the bus, or a PDU for the other side) and ignored.
    max_counter_delta : int
        Largest accepted counter step (1 = no PDU may be lost).
    sm : SMConfig
        The AUTOSAR E2E state machine's window and thresholds.
    """

    def __init__(self, codec: Codec, rx_names, max_counter_delta: int = 2,
                 sm: SMConfig | None = None):
        self.codec = codec
        sm = sm or SMConfig()
        names = tuple(rx_names)
        self.receivers = {n: Receiver(codec.protection(n), max_counter_delta, sm,
                                      _other_data_ids(codec, n)) for n in names}
        self.accepted: Counter = Counter()     # PDU name -> accepted
        self.faults: Counter = Counter()       # Fault value -> rejected
        self.foreign = 0                       # known PDUs not meant for this side
        self._intact: dict[str, bool] = {}     # the last PDU received passed every check
        self._stamps: dict[str, list[float]] = {}   # name -> [first, last] accepted stamp [s]

    def check(self, pdu: Pdu, now: float) -> Frame | None:
        """The decoded PDU if it passes every check, else None (and the fault is counted)."""
        try:
            spec = self.codec.spec_of(pdu.id)
            if spec is not None and spec.name not in self.receivers:
                self.foreign += 1
                return None
            spec = self.codec.lookup(pdu)
            name, rx = spec.name, self.receivers[spec.name]
            self._intact[name] = False
            status = rx.check(pdu.data)
            if status not in ACCEPTED:
                fault = STATUS_FAULT.get(status) or Fault(rx.error)
                raise FrameError(fault, f'{name}: {rx.reason()}')
            frame = Frame(name, rx.protection.counter(pdu.data),
                          self.codec.unpack(name, pdu.data))
            self.codec.check_range(frame)
        except FrameError as err:
            self.faults[err.fault.value] += 1
            log.debug('PDU rejected: %s', err)
            return None
        except Exception as err:   # noqa: BLE001 -- a PDU must never take the bridge down
            self.faults['decode'] += 1
            log.warning('PDU 0x%x undecodable: %r', getattr(pdu, 'id', -1), err)
            return None
        self._intact[name] = True
        self.accepted[name] += 1
        stamp = pdu.timestamp or now
        self._stamps.setdefault(name, [stamp, stamp])[1] = stamp
        return frame

    def no_new_data(self, name: str) -> None:
        """A cycle in which ``name`` did not arrive in time: the state machine counts it."""
        self.receivers[name].check(None)

    def valid(self, name: str) -> bool:
        """The PDU's signals may be used: E2E state VALID and the last PDU intact."""
        return self._intact.get(name, False) and self.receivers[name].valid

    def states(self) -> dict[str, str]:
        """E2E status and state of each PDU that is not valid (diagnostics)."""
        return {n: rx.reason() for n, rx in self.receivers.items() if not self.valid(n)}

    def rates(self) -> dict[str, float]:
        """Accepted PDUs per second of each PDU since the first, from their reception stamps."""
        return {n: (self.accepted[n] - 1) / (last - first)
                for n, (first, last) in self._stamps.items() if last > first}

    def last_stamps(self) -> dict[str, float]:
        """Reception stamp of each PDU's latest accepted one [s]: with ``accepted`` two
        snapshots give the rate between them, start-up left out."""
        return {n: last for n, (_, last) in self._stamps.items()}

    @property
    def rejected(self) -> int:
        return sum(self.faults.values())


def _other_data_ids(codec: Codec, name: str) -> list:
    """Data IDs of the description's other PDUs of the same profile (to name a misrouted PDU)."""
    profile = codec.spec(name).e2e.profile
    return [spec.e2e.data_id_list or spec.e2e.data_id for spec in codec.description.pdus
            if spec.name != name and spec.e2e.profile == profile]


__all__ = ['FrameChecker']

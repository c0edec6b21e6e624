"""Receive-side E2E checks: DLC, CRC, range (via the codec) and the alive counter, with counts."""
from __future__ import annotations

import logging
from collections import Counter

import can

from drift_vehicle_bridge.codec import COUNTER_MODULO, Codec, Fault, Frame, FrameError

log = logging.getLogger(__name__)


class FrameChecker:
    """Accepts or rejects each received frame and counts both; never raises.

    Parameters
    ----------
    codec : Codec
        DBC codec (DLC, CRC and range checks).
    rx_names : iterable of str
        Messages this side consumes; any other known message is counted as ``foreign`` (one of our
        own transmissions echoed by the bus, or a frame for the other side) and ignored.
    max_counter_delta : int
        Largest accepted alive-counter step (1 = no frame may be lost).
    resync_after : float
        After this long without an accepted frame [s], the next counter is taken as a new start
        (AUTOSAR E2E resynchronisation); a repeated counter is never accepted.
    """

    def __init__(self, codec: Codec, rx_names, max_counter_delta: int = 2,
                 resync_after: float = 0.03):
        self.codec = codec
        self.rx_ids = {codec.frame_id(n) for n in rx_names}
        self.max_counter_delta = max_counter_delta
        self.resync_after = resync_after
        self.accepted: Counter = Counter()     # message name -> frames accepted
        self.faults: Counter = Counter()       # Fault value -> frames rejected
        self.foreign = 0                       # known frames not meant for this side
        self._last: dict[str, tuple[int, float]] = {}   # name -> (counter, time accepted)

    def check(self, msg: can.Message, now: float) -> Frame | None:
        """The decoded frame if it passes every check, else None (and the fault is counted)."""
        try:
            if msg.arbitration_id not in self.rx_ids and not msg.is_extended_id \
                    and self.codec.name_of(msg.arbitration_id) is not None:
                self.foreign += 1
                return None
            frame = self.codec.decode(msg)
            self._check_counter(frame, now)    # before range: an authentic frame still counts
            self.codec.check_range(frame)
        except FrameError as err:
            self.faults[err.fault.value] += 1
            log.debug('frame rejected: %s', err)
            return None
        except Exception as err:   # noqa: BLE001 -- a frame must never take the bridge down
            self.faults['decode'] += 1
            log.warning('frame 0x%x undecodable: %r', getattr(msg, 'arbitration_id', -1), err)
            return None
        self.accepted[frame.name] += 1
        return frame

    def _check_counter(self, frame: Frame, now: float) -> None:
        last = self._last.get(frame.name)
        step = 1 if last is None else (frame.counter - last[0]) % COUNTER_MODULO
        if step == 0:
            raise FrameError(Fault.COUNTER_REPEAT, f'{frame.name}: counter {frame.counter}')
        self._last[frame.name] = (frame.counter, now)   # a jump resynchronises on the new counter
        if step > self.max_counter_delta and now - last[1] <= self.resync_after:
            raise FrameError(Fault.COUNTER_JUMP,
                             f'{frame.name}: counter {last[0]} -> {frame.counter}')

    @property
    def rejected(self) -> int:
        return sum(self.faults.values())


__all__ = ['FrameChecker']

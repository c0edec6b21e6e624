"""The car's end of the DBC: state frames out, checked command frames in (simulator, tests)."""
from __future__ import annotations

import math
import os
import time
from collections import Counter

import can

from drift_control.params import config_dir
from drift_control.signals import Command, VehicleState
from drift_vehicle_bridge.checks import FrameChecker
from drift_vehicle_bridge.codec import (CMD_STATUS, CMD_STEER, CMD_TORQUE, COMMAND_FRAMES,
                                        VALIDITY_FRAMES, Codec, command_from_signals,
                                        state_signals)
from drift_vehicle_bridge.mode import BridgeMode


def default_dbc() -> str:
    """The project's DBC, ``config/can/drift_vehicle.dbc``."""
    return str(config_dir() / 'can' / 'drift_vehicle.dbc')


class CarSide:
    """What the car's gateway does on the bus, as the simulator's CAN vehicle mode needs it.

    ``send_state(state)`` writes the state frames with alive counters and CRCs;
    ``poll_command(now)`` reads every pending frame, checks it as the real gateway must (DLC, CRC,
    counter, range, timeout) and returns the request to apply, or None: released.

    Parameters
    ----------
    bus : can.BusABC
        Any python-can bus; the caller owns it (and closes it).
    codec : Codec, optional
        DBC codec; default: the project's DBC.
    command_timeout : float
        A command frame older than this no longer counts [s]; 3 bridge cycles by default.
    max_counter_delta : int
        Accepted alive-counter step of the command frames.
    """

    def __init__(self, bus: can.BusABC, codec: Codec | None = None,
                 command_timeout: float = 0.03, max_counter_delta: int = 2):
        self.bus = bus
        self.codec = codec or Codec.load(default_dbc())
        self.command_timeout = command_timeout
        self.checker = FrameChecker(self.codec, COMMAND_FRAMES, max_counter_delta, command_timeout)
        self.bridge_mode: BridgeMode | None = None    # from the last accepted DS_CMD_STATUS
        self.frames_sent = 0
        self._counters: Counter = Counter()
        self._latest: dict[str, tuple[dict, float]] = {}   # name -> (signals, time accepted [s])

    @classmethod
    def open(cls, dbc: str | os.PathLike | None = None, **bus_kwargs) -> 'CarSide':
        """A CarSide on ``can.Bus(**bus_kwargs)`` (close with ``car.bus.shutdown()``)."""
        return cls(can.Bus(**bus_kwargs), Codec.load(dbc or default_dbc()))

    def send_state(self, state: VehicleState, skip: tuple[str, ...] = ()) -> int:
        """Write the state frames for ``state``; returns how many were sent.

        Values outside a signal's DBC range are saturated. A frame is left out (and so times out at
        the bridge) when a validity bit it carries is clear in ``state.validity``, one of its
        values is not finite, or its name is in ``skip`` (fault injection).
        """
        leave_out = set(skip)
        for bit, frames in VALIDITY_FRAMES.items():
            if not state.has(bit):
                leave_out.update(frames)
        sent = 0
        for name, values in state_signals(state).items():
            if name in leave_out or not all(math.isfinite(v) for v in values.values()):
                continue
            msg = self.codec.encode(name, self.codec.saturate(name, values), self._counters[name])
            self.bus.send(msg)
            self._counters[name] += 1
            sent += 1
        self.frames_sent += sent
        return sent

    def poll_command(self, now: float | None = None) -> Command | None:
        """Read pending frames; the request to apply at ``now`` [s] (default: monotonic clock).

        None means released: no fresh DS_CMD_STATUS, or the bridge is OFF/ARMED, or the request
        frame(s) of its mode are missing, stale or failed a check. ``Command.mode`` is FULL or
        TORQUE_ONLY; in TORQUE_ONLY the steering stays with the driver (delta reads 0).
        """
        now = time.monotonic() if now is None else now
        while True:
            try:
                msg = self.bus.recv(timeout=0.0)
            except (can.CanError, OSError, ValueError):   # a bad datagram, a bus-off
                self.checker.faults['bus_error'] += 1
                break
            if msg is None:
                break
            frame = self.checker.check(msg, now)
            if frame is not None:
                self._latest[frame.name] = (frame.values, now)
                if frame.name == CMD_STATUS:
                    self.bridge_mode = BridgeMode(int(frame.values['bridge_mode']))
        status = self._fresh(CMD_STATUS, now)
        if status is None:
            return None
        return command_from_signals(status, self._fresh(CMD_STEER, now),
                                    self._fresh(CMD_TORQUE, now), now)

    def _fresh(self, name: str, now: float) -> dict | None:
        values, seen = self._latest.get(name, (None, -math.inf))
        return values if now - seen <= self.command_timeout else None


__all__ = ['CarSide', 'default_dbc']

"""The car's end of the interface: state PDUs out, checked command PDUs in (simulator, tests)."""
from __future__ import annotations

import math
import os
import time
from collections import Counter

import can

from drift_control.params import config_dir
from drift_control.signals import Command, VehicleState
from drift_vehicle_bridge.checks import FrameChecker
from drift_vehicle_bridge.codec import (CMD_STATUS, CMD_STEER, CMD_TORQUE, COMMAND_FRAMES, Codec,
                                        command_from_signals)
from drift_vehicle_bridge.e2e import SMConfig
from drift_vehicle_bridge.mode import BridgeMode
from drift_vehicle_bridge.params import BridgeParams, description_path
from drift_vehicle_bridge.transport import as_transport, discard_pending, open_transport


def default_dbc() -> str:
    """The project's classic CAN DBC, ``config/can/drift_vehicle.dbc``."""
    return str(config_dir() / 'can' / 'drift_vehicle.dbc')


class CarSide:
    """What the car's gateway does on the link, as the simulator's vehicle mode needs it.

    ``send_state(state)`` writes the state PDUs, E2E protected; ``poll_command(now)`` reads
    every pending PDU, checks it as the real gateway must (length, E2E, range, timeout) and
    returns the request to apply, or None: released.

    Parameters
    ----------
    link : transport or can.BusABC
        A transport or any python-can bus; the caller owns it (and shuts it down).
    codec : Codec, optional
        The bus description's codec; default: the project's classic CAN DBC.
    command_timeout : float
        A command PDU older than this no longer counts [s]; 3 bridge cycles by default.
    max_counter_delta : int
        Accepted E2E counter step of the command PDUs.
    sm : SMConfig, optional
        E2E state machine of each command PDU.
    """

    def __init__(self, link, codec: Codec | None = None, command_timeout: float = 0.03,
                 max_counter_delta: int = 3, sm: SMConfig | None = None):
        self.transport = as_transport(link)
        self.codec = codec or Codec.load(default_dbc())
        self.command_timeout = command_timeout
        self.checker = FrameChecker(self.codec, COMMAND_FRAMES, max_counter_delta, sm)
        self.bridge_mode: BridgeMode | None = None    # from the last accepted DS_CMD_STATUS
        self.frames_sent = 0
        self._counters: Counter = Counter()
        self._latest: dict[str, tuple[dict, float]] = {}   # name -> (signals, time accepted [s])

    @classmethod
    def open(cls, params: BridgeParams, cfg_dir: str | os.PathLike | None = None) -> 'CarSide':
        """The gateway's end of the link and description the bridge's ``params`` name (shut
        down with ``car.transport.shutdown()``)."""
        return cls(open_transport(params, car_side=True),
                   Codec.load(description_path(params, cfg_dir)),
                   max_counter_delta=params.monitor.max_counter_delta, sm=params.monitor.e2e)

    def send_state(self, state: VehicleState, skip: tuple[str, ...] = ()) -> int:
        """Write the state PDUs for ``state``; returns how many were sent.

        Values outside a signal's range are saturated. A PDU is left out (and so times out at
        the bridge) when a validity bit it carries is clear in ``state.validity``, one of its
        values is not finite, or its name is in ``skip`` (fault injection).
        """
        leave_out = set(skip)
        for bit, frames in self.codec.validity_frames.items():
            if not state.has(bit):
                leave_out.update(frames)
        return self._send(self.codec.state_signals(state), leave_out)

    def send_samples(self, samples, brake_pedal: bool = False, skip: tuple[str, ...] = ()) -> int:
        """Write the PDUs that carry one step's sensor samples (``estimator.SensorSample``s; a
        PDU of several units once all of them have a sample); returns how many were sent.

        A unit without a sample this step (its rate, a dropout) leaves its PDUs out; so do a
        non-finite value and ``skip``, as in ``send_state``.
        """
        by_unit = {s.unit: tuple(s.values) for s in samples}
        return self._send(self.codec.sensor_signals(by_unit, brake_pedal), set(skip))

    def _send(self, pdus: dict[str, dict], leave_out: set) -> int:
        sent = 0
        for name, values in pdus.items():
            if name in leave_out or not all(math.isfinite(v) for v in values.values()):
                continue
            pdu = self.codec.encode(name, self.codec.saturate(name, values), self._counters[name])
            self.transport.send(pdu)
            self._counters[name] += 1
            sent += 1
        self.transport.flush()
        self.frames_sent += sent
        return sent

    def discard_backlog(self, limit: int = 100_000) -> int:
        """Drop what the link queued while the car was not stepping (it waited to start): those
        requests are history, and a receive queue that overflowed meanwhile would read as
        counter jumps. Returns how many PDUs."""
        return discard_pending(self.transport, limit)

    def poll_command(self, now: float | None = None) -> Command | None:
        """Read pending frames; the request to apply at ``now`` [s] (default: monotonic clock).

        None means released: no fresh DS_CMD_STATUS, or the bridge is OFF/ARMED, or the request
        PDU(s) of its mode are missing, stale or failed a check. ``Command.mode`` is FULL or
        TORQUE_ONLY; in TORQUE_ONLY the steering stays with the driver (delta reads 0).
        """
        now = time.monotonic() if now is None else now
        while True:
            try:
                pdu = self.transport.recv(timeout=0.0)
            except (can.CanError, OSError, ValueError):   # a bad datagram, a bus-off
                self.checker.faults['bus_error'] += 1
                break
            if pdu is None:
                break
            frame = self.checker.check(pdu, now)
            if frame is not None:
                self._latest[frame.name] = (frame.values, now)
                if frame.name == CMD_STATUS:
                    self.bridge_mode = BridgeMode(int(frame.values['bridge_mode']))
        for name in COMMAND_FRAMES:
            if now - self._latest.get(name, (None, -math.inf))[1] > self.command_timeout:
                self.checker.no_new_data(name)
        status = self._fresh(CMD_STATUS, now)
        if status is None:
            return None
        return command_from_signals(status, self._fresh(CMD_STEER, now),
                                    self._fresh(CMD_TORQUE, now), now)

    def stats(self) -> dict:
        """Counters of the car's end for diagnostics (totals since start)."""
        checker = self.checker
        return {'rx': dict(checker.accepted), 'rx_rate': checker.rates(),
                'rx_stamp': checker.last_stamps(),
                'faults': dict(checker.faults), 'e2e': checker.states(),
                'foreign': checker.foreign, 'sent': self.frames_sent,
                'errors': dict(getattr(self.transport, 'errors', {}))}

    def _fresh(self, name: str, now: float) -> dict | None:
        values, seen = self._latest.get(name, (None, -math.inf))
        return values if now - seen <= self.command_timeout and self.checker.valid(name) \
            else None


__all__ = ['CarSide', 'default_dbc']

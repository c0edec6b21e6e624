"""The gateway: owns the python-can bus and runs the 10 ms cycle (receive, decide, write)."""
from __future__ import annotations

import logging
import math
import os
from collections import Counter

import can

from drift_control.params import ParamError
from drift_control.signals import Command, VehicleState
from drift_vehicle_bridge.codec import (CMD_STATUS, CMD_STEER, CMD_TORQUE, Codec, steer_signals,
                                        torque_signals)
from drift_vehicle_bridge.limits import CommandLimiter
from drift_vehicle_bridge.mode import BridgeMode, ModeManager
from drift_vehicle_bridge.monitor import StateMonitor
from drift_vehicle_bridge.params import BridgeParams, dbc_path

log = logging.getLogger(__name__)

MAX_FRAMES_PER_CYCLE = 1000    # a babbling bus must not starve the cycle


class Gateway:
    """One bridge cycle per ``step(now)``; what is written depends on the mode.

    Every cycle writes DS_CMD_STATUS (heartbeat, mode, drop reason): in OFF and ARMED that is the
    explicit "no request". DS_CMD_TORQUE is written only in ACTIVE_*, DS_CMD_STEER only in
    ACTIVE_FULL, both after the limiter. Only messages in ``params.tx_allow`` are ever written.
    With ``bus=None`` (log replay) nothing is written and arming is refused. With
    ``params.auto_arm`` (simulated buses only) the gateway requests arming itself each cycle
    while OFF until it has once been ACTIVE; after that a drop to OFF is latched as usual.

    Parameters
    ----------
    bus : can.BusABC or None
        Any python-can bus; the gateway never closes a bus it was given.
    codec : Codec
        The DBC codec.
    params : BridgeParams
        Validated bridge parameters.
    checker : drift_control.plausibility.InputChecker, optional
        The vehicle's physical bounds on a measured state (wheel speeds against the speed, the
        steering lock) and the frozen-sensor check: an implausible state is an invalid one.
    """

    def __init__(self, bus: can.BusABC | None, codec: Codec, params: BridgeParams,
                 checker=None):
        self.bus, self.codec, self.params = bus, codec, params
        self._allow = _check_tx_allow(codec, params)
        self.monitor = StateMonitor(codec, params.monitor)
        self.modes = ModeManager(params.mode, checker)
        self.limiter = CommandLimiter(params.limits, params.cycle_time)
        self.state: VehicleState | None = None
        self.sent: Counter = Counter()
        self.errors: Counter = Counter()   # tx_blocked, tx_error, bus_error, command_rejected
        self._counters = Counter()
        self._command: Command | None = None
        self._command_time: float | None = None
        self.been_active = False

    @classmethod
    def open(cls, params: BridgeParams, cfg_dir: str | os.PathLike | None = None) -> 'Gateway':
        """Open ``can.Bus(**params.bus)`` and load the DBC named in ``params``."""
        codec = Codec.load(dbc_path(params, cfg_dir))
        return cls(can.Bus(**params.bus.kwargs()), codec, params)

    @property
    def mode(self) -> BridgeMode:
        return self.modes.mode

    def receive(self, msg: can.Message, now: float) -> bool:
        """Feed one frame (from the bus or a log) received at ``now`` [s]."""
        return self.monitor.receive(msg, now)

    def set_command(self, cmd: Command, now: float) -> bool:
        """The controller's latest command, arrived at ``now`` [s]; a non-finite one is dropped."""
        if not all(math.isfinite(v) for v in (cmd.delta, cmd.delta_rate, cmd.drive_torque)):
            self.errors['command_rejected'] += 1
            return False
        self._command, self._command_time = cmd, now
        return True

    def request_arm(self, now: float) -> tuple[bool, str]:
        """Explicit arm request (operator); returns (armed, why)."""
        if self.bus is None:
            return False, 'arm refused: replay (no bus)'
        return self.modes.request_arm(self.monitor.state(now), now)

    def disarm(self) -> None:
        self.modes.disarm()

    def step(self, now: float) -> VehicleState | None:
        """One cycle at ``now`` [s]: drain the bus, update state and mode, write the frames."""
        self._drain(now)
        self.state = self.monitor.state(now)
        if self.params.auto_arm and self.mode == BridgeMode.OFF and not self.been_active:
            self.request_arm(now)    # retried while refused: arms once the state allows it
        was_active = self.mode.active
        mode = self.modes.update(now, self.state, self._command, self._command_time)
        if mode.active and not was_active:
            self.limiter.reset(self.state.delta, self.state.drive_torque)
            self.been_active = True
        self._transmit(mode)
        return self.state

    def shutdown(self) -> None:
        """Drop to OFF and say so on the bus once more (the caller closes the bus)."""
        if self.mode != BridgeMode.OFF:
            self.modes.disarm()
            self._transmit(self.mode)

    def stats(self) -> dict:
        """Counters for diagnostics (totals since start)."""
        checker = self.monitor.checker
        return {'mode': self.mode.name, 'drop_reason': self.modes.reason.name,
                'implausible': self.modes.implausible or '',
                'validity': self.state.validity if self.state else 0,
                'rx': dict(checker.accepted), 'faults': dict(checker.faults),
                'foreign': checker.foreign, 'tx': dict(self.sent), 'errors': dict(self.errors)}

    def _drain(self, now: float) -> None:
        if self.bus is None:
            return
        for _ in range(MAX_FRAMES_PER_CYCLE):
            try:
                msg = self.bus.recv(timeout=0.0)
            except (can.CanError, OSError, ValueError) as err:   # a bad datagram, a bus-off
                self.errors['bus_error'] += 1
                log.warning('receive failed: %s', err)
                return
            if msg is None:
                return
            self.monitor.receive(msg, now)

    def _transmit(self, mode: BridgeMode) -> None:
        if self.bus is None:
            return
        if mode.active:
            cmd = self.limiter.apply(self._command)
            if mode == BridgeMode.ACTIVE_FULL:
                self._write(CMD_STEER, steer_signals(cmd))
            else:   # steering stays with the driver: track it for a smooth switch to FULL
                self.limiter.delta = self.state.delta
            self._write(CMD_TORQUE, torque_signals(cmd))
        self._write(CMD_STATUS, {'bridge_mode': int(mode), 'drop_reason': int(self.modes.reason)})

    def _write(self, name: str, values: dict) -> None:
        if name not in self._allow:
            self.errors['tx_blocked'] += 1
            log.error('refusing to write %s: not in tx_allow', name)
            return
        try:
            self.bus.send(self.codec.encode(name, values, self._counters[name]), timeout=0.005)
        except (can.CanError, OSError) as err:
            self.errors['tx_error'] += 1
            log.warning('send %s failed: %s', name, err)
            return
        self._counters[name] += 1
        self.sent[name] += 1


def _check_tx_allow(codec: Codec, params: BridgeParams) -> frozenset[str]:
    """The allow-list must name our own messages; the limits must fit their DBC ranges."""
    for name in params.tx_allow:
        try:
            senders = codec.message(name).senders
        except ParamError:
            raise ParamError(f'bridge.tx_allow: {name!r} is not a message of the DBC') from None
        if 'DRIFT_STACK' not in senders:
            raise ParamError(f'bridge.tx_allow: {name!r} is sent by {senders}, not DRIFT_STACK')
    lim = params.limits
    sig = {s.name: s for m in (CMD_STEER, CMD_TORQUE) for s in codec.message(m).signals}
    checks = (('delta_max', (lim.delta_max, -lim.delta_max), 'delta_req'),
              ('delta_rate_max', (lim.delta_rate_max, -lim.delta_rate_max), 'delta_rate_req'),
              ('torque_min', (lim.torque_min,), 'torque_req'),
              ('torque_max', (lim.torque_max,), 'torque_req'))
    for key, values, signal in checks:
        s = sig[signal]
        if not all(s.minimum <= v <= s.maximum for v in values):
            raise ParamError(f'bridge.limits.{key}: {values[0]} outside the DBC range of '
                             f'{signal} [{s.minimum}, {s.maximum}]')
    return frozenset(params.tx_allow)


__all__ = ['Gateway']

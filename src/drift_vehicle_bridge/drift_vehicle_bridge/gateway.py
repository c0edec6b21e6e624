"""The gateway: runs the 10 ms cycle on a transport (receive, decide, write)."""
from __future__ import annotations

import logging
import math
import os
from collections import Counter
from dataclasses import replace

import can

from drift_control.params import ParamError
from drift_control.signals import Command, Validity, VehicleState
from drift_vehicle_bridge.codec import (CMD_STATUS, CMD_STEER, CMD_TORQUE, Codec, steer_signals,
                                        torque_signals)
from drift_vehicle_bridge.limits import CommandLimiter
from drift_vehicle_bridge.mode import BridgeMode, ModeManager
from drift_vehicle_bridge.monitor import StateMonitor
from drift_vehicle_bridge.params import BridgeParams, description_path
from drift_vehicle_bridge.pdu import Pdu
from drift_vehicle_bridge.sensors import SensorAssembler, UnitSample, sensor_timeouts
from drift_vehicle_bridge.transport import as_transport, discard_pending, open_transport

log = logging.getLogger(__name__)

MAX_FRAMES_PER_CYCLE = 1000    # a babbling bus must not starve the cycle [PDUs]
NO_STEER = {'steer_request': 0, 'delta_req': 0.0, 'delta_rate_req': 0.0}
# what the estimator carries through a GNSS/INS dropout (the IMU and the wheels go on)
INS_BRIDGED = Validity.V | Validity.BETA | Validity.VX_VY | Validity.R | Validity.POSE
NO_TORQUE = {'torque_request': 0, 'torque_req': 0.0}


class Gateway:
    """One bridge cycle per ``step(now)``; what is written depends on the mode.

    Every cycle writes DS_CMD_STATUS (heartbeat, mode, drop reason) and both request PDUs, so
    that the car's E2E state machines stay VALID and a request applies in the cycle it starts:
    ``torque_request`` is set only in ACTIVE_*, ``steer_request`` only in ACTIVE_FULL, their
    values after the limiter; in OFF and ARMED nothing is requested. Only PDUs in
    ``params.tx_allow`` are ever written (a blocked one is tried, and counted, only to request).
    With ``link=None`` (log replay) nothing is written and arming is refused. With
    ``params.auto_arm`` (simulated buses only) the gateway requests arming itself each cycle
    while OFF until it has once been ACTIVE; after that a drop to OFF is latched as usual.

    Parameters
    ----------
    link : transport, can.BusABC or None
        A transport (``transport.py``, ``soad.py``) or any python-can bus; the gateway never
        shuts down a link it was given.
    codec : Codec
        The bus description's codec.
    params : BridgeParams
        Validated bridge parameters.
    checker : drift_control.plausibility.InputChecker, optional
        The vehicle's physical bounds on a measured state (wheel speeds against the speed, the
        steering lock) and the frozen-sensor check: an implausible state is an invalid one.

    With ``params.sensors.enabled`` the received PDUs are also reassembled into the sensor
    units' samples (``take_samples``), and the modes judge the state estimator's state
    (``set_estimate``) instead of the frames' own: a GNSS dropout the estimator bridges is no
    reason to release the car, a stale estimate (the controller's process stalled) is.
    """

    def __init__(self, link, codec: Codec, params: BridgeParams, checker=None):
        self.transport = None if link is None else as_transport(link)
        self.codec, self.params = codec, params
        self._allow = _check_tx_allow(codec, params)
        self.sensors, monitor = None, params.monitor
        if params.sensors.enabled:
            self.sensors = SensorAssembler(codec, params.sensors.latency, 1.5 * params.cycle_time)
            monitor = replace(monitor, timeouts={
                **sensor_timeouts(codec, params.sensors.rate, monitor.frame_timeout),
                **monitor.timeouts})
        self.monitor = StateMonitor(codec, monitor, self.sensors)
        self.modes = ModeManager(params.mode, checker)
        self.limiter = CommandLimiter(params.limits, params.cycle_time)
        self.state: VehicleState | None = None
        self.sent: Counter = Counter()
        self.errors: Counter = Counter()   # tx_blocked, tx_error, bus_error, command_rejected
        self._counters = Counter()
        self._command: Command | None = None
        self._command_time: float | None = None
        self._estimate: VehicleState | None = None
        self._estimate_time = -math.inf
        self.been_active = False
        self.discarded_at_start = 0   # PDUs queued before the first cycle, dropped

    @classmethod
    def open(cls, params: BridgeParams, cfg_dir: str | os.PathLike | None = None) -> 'Gateway':
        """Open the transport of ``params`` and load the bus description it names."""
        codec = Codec.load(description_path(params, cfg_dir))
        return cls(open_transport(params), codec, params)

    @property
    def mode(self) -> BridgeMode:
        return self.modes.mode

    def receive(self, pdu: Pdu, now: float) -> bool:
        """Feed one PDU (from the link or a log) received at ``now`` [s]."""
        return self.monitor.receive(pdu, now)

    def set_command(self, cmd: Command, now: float) -> bool:
        """The controller's latest command, arrived at ``now`` [s]; a non-finite one is dropped."""
        if not all(math.isfinite(v) for v in (cmd.delta, cmd.delta_rate, cmd.drive_torque)):
            self.errors['command_rejected'] += 1
            return False
        self._command, self._command_time = cmd, now
        return True

    def take_samples(self, now: float) -> list[UnitSample]:
        """The sensor units' samples completed since the last call (sensor mode, else none)."""
        return self.sensors.take(now) if self.sensors is not None else []

    def set_estimate(self, state: VehicleState, now: float) -> None:
        """Sensor mode: the estimator's newest state, arrived at ``now`` [s]."""
        self._estimate, self._estimate_time = state, now

    def judged_state(self, now: float) -> VehicleState | None:
        """The state the modes judge at ``now`` [s]: the frames' own, or in sensor mode the
        estimator's (None once older than the command heartbeat's timeout) with the driver's
        steering torque and brake pedal from the frames. Valid where the estimate is and, but
        for what the estimator carries through a GNSS/INS dropout, the frames are too."""
        own = self.monitor.state(now)
        if self.sensors is None:
            return own
        est = self._estimate
        if est is None or own is None \
                or now - self._estimate_time > self.params.mode.heartbeat_timeout:
            return None
        return replace(est, stamp=now, steering_torque=own.steering_torque,
                       brake_pedal=own.brake_pedal,
                       validity=est.validity & (own.validity | INS_BRIDGED))

    def request_arm(self, now: float) -> tuple[bool, str]:
        """Explicit arm request (operator); returns (armed, why)."""
        if self.transport is None:
            return False, 'arm refused: replay (no link)'
        return self.modes.request_arm(self.judged_state(now), now)

    def disarm(self, now: float | None = None) -> None:
        self.modes.disarm(now)

    def discard_backlog(self) -> int:
        """Drop what the link queued before the first cycle; returns how many PDUs.

        A node opens its link before its first tick: what arrives meanwhile is the car before
        the bridge ran, and a receive queue that overflowed in that time would read as counter
        jumps of every PDU.
        """
        n = 0 if self.transport is None else \
            discard_pending(self.transport, 100 * MAX_FRAMES_PER_CYCLE)
        self.discarded_at_start += n
        return n

    def step(self, now: float) -> VehicleState | None:
        """One cycle at ``now`` [s]: drain the link, update state and mode, write the PDUs."""
        self._drain(now)
        self.monitor.tick(now)
        self.state = self.monitor.state(now)
        if self.params.auto_arm and self.mode == BridgeMode.OFF and not self.been_active:
            self.request_arm(now)    # retried while refused: arms once the state allows it
        was_active = self.mode.active
        judged = self.judged_state(now)
        mode = self.modes.update(now, judged, self._command, self._command_time)
        if mode.active and not was_active:
            self.limiter.reset(judged.delta, judged.drive_torque)
            self.been_active = True
        self._transmit(mode)
        return self.state

    def shutdown(self) -> None:
        """Drop to OFF and say so on the link once more (the caller shuts the link down)."""
        if self.mode != BridgeMode.OFF:
            self.modes.disarm()
            self._transmit(self.mode)

    def stats(self) -> dict:
        """Counters for diagnostics (totals since start)."""
        checker = self.monitor.checker
        return {'mode': self.mode.name, 'drop_reason': self.modes.reason.name,
                'drops': dict(self.modes.drops), 'dropped_at': self.modes.dropped_at,
                'implausible': self.modes.implausible or '',
                'validity': self.state.validity if self.state else 0,
                'rx': dict(checker.accepted), 'rx_rate': checker.rates(),
                'rx_stamp': checker.last_stamps(),
                'faults': dict(checker.faults),
                'e2e': checker.states(), 'foreign': checker.foreign,
                'discarded_at_start': self.discarded_at_start, 'tx': dict(self.sent),
                **({'sensor_samples': dict(self.sensors.samples)} if self.sensors else {}),
                'errors': {**self.errors, **{f'link_{k}': v for k, v in
                                             getattr(self.transport, 'errors', {}).items()}}}

    def _drain(self, now: float) -> None:
        if self.transport is None:
            return
        for _ in range(MAX_FRAMES_PER_CYCLE):
            try:
                pdu = self.transport.recv(timeout=0.0)
            except (can.CanError, OSError, ValueError) as err:   # a bad datagram, a bus-off
                self.errors['bus_error'] += 1
                log.warning('receive failed: %s', err)
                return
            if pdu is None:
                return
            self.monitor.receive(pdu, now)

    def _transmit(self, mode: BridgeMode) -> None:
        if self.transport is None:
            return
        cmd = self.limiter.apply(self._command) if mode.active else None
        if mode == BridgeMode.ACTIVE_FULL:
            self._write(CMD_STEER, steer_signals(cmd))
        else:
            if mode.active:   # steering stays with the driver: track it for a smooth switch
                self.limiter.delta = self.state.delta
            if CMD_STEER in self._allow:
                self._write(CMD_STEER, NO_STEER)
        self._write(CMD_TORQUE, torque_signals(cmd) if mode.active else NO_TORQUE)
        self._write(CMD_STATUS, {'bridge_mode': int(mode), 'drop_reason': int(self.modes.reason)})
        try:
            self.transport.flush()
        except (can.CanError, OSError) as err:
            self.errors['tx_error'] += 1
            log.warning('flush failed: %s', err)

    def _write(self, name: str, values: dict) -> None:
        if name not in self._allow:
            self.errors['tx_blocked'] += 1
            log.error('refusing to write %s: not in tx_allow', name)
            return
        try:
            self.transport.send(self.codec.encode(name, values, self._counters[name]))
        except (can.CanError, OSError) as err:
            self.errors['tx_error'] += 1
            log.warning('send %s failed: %s', name, err)
            return
        self._counters[name] += 1
        self.sent[name] += 1


def _check_tx_allow(codec: Codec, params: BridgeParams) -> frozenset[str]:
    """The allow-list must name our own PDUs; the limits must fit their signals' ranges."""
    for name in params.tx_allow:
        try:
            senders = codec.spec(name).senders
        except ParamError:
            raise ParamError(f'bridge.tx_allow: {name!r} is not a PDU of '
                             f'{codec.description.source}') from None
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
            raise ParamError(f'bridge.limits.{key}: {values[0]} outside the range of '
                             f'{signal} [{s.minimum}, {s.maximum}]')
    return frozenset(params.tx_allow)


__all__ = ['Gateway']

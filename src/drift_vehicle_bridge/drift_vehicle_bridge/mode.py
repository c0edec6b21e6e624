"""The mode manager: OFF -> ARMED -> ACTIVE (full | torque-only), and every way back to OFF."""
from __future__ import annotations

import logging
from collections import Counter
from enum import IntEnum

from drift_control.signals import Command, Mode, Validity, VehicleState
from drift_vehicle_bridge.params import Envelope, ModeParams

log = logging.getLogger(__name__)

# Without these the bridge can neither control nor see a driver takeover.
REQUIRED = Validity.CONTROL | Validity.STEERING_TORQUE | Validity.BRAKE_PEDAL


class BridgeMode(IntEnum):
    """Bridge mode; same values as ``bridge_mode`` of DS_CMD_STATUS in the DBC."""

    OFF = 0                 # nothing requested; actuators with the driver
    ARMED = 1               # ready; still nothing requested
    ACTIVE_FULL = 2         # steering and drive torque requested
    ACTIVE_TORQUE_ONLY = 3  # drive torque requested; steering with the driver

    @property
    def active(self) -> bool:
        return self in (BridgeMode.ACTIVE_FULL, BridgeMode.ACTIVE_TORQUE_ONLY)


class DropReason(IntEnum):
    """Why the bridge left ARMED/ACTIVE; same values as ``drop_reason`` in the DBC."""

    NONE = 0
    DISARM = 1
    DRIVER_TORQUE = 2
    BRAKE_PEDAL = 3
    STATE_INVALID = 4
    ENVELOPE = 5
    HEARTBEAT = 6
    ARM_TIMEOUT = 7
    COMMAND_OFF = 8       # the controller asked for OFF: back to ARMED, not a drop to OFF


class ModeManager:
    """Decides each cycle what the bridge may request from the car.

    ARMED is entered only by ``request_arm`` with a fresh, valid state inside the arm envelope.
    ACTIVE follows once a fresh command asks for it. A driver takeover (steering torque, brake
    pedal), an invalid or stale state, leaving the active envelope, a stale command stream
    (heartbeat) or ``disarm`` drops to OFF in the same ``update`` call; only a new ``request_arm``
    leaves OFF again.
    """

    def __init__(self, params: ModeParams, checker=None):
        self.p = params
        self.checker = checker     # drift_control.plausibility.InputChecker: bounds, frozen
        self.mode = BridgeMode.OFF
        self.reason = DropReason.NONE
        self.implausible: str | None = None   # why the last state was not believed
        self.drops: Counter = Counter()       # 'FROM_MODE/REASON' -> drops to OFF since start
        self.dropped_at: float | None = None  # when the last drop came (the caller's clock) [s]
        self._armed_at = 0.0

    def hazard(self, state: VehicleState | None, envelope: Envelope,
               stack_steers: bool = True) -> DropReason | None:
        """The first reason not to request anything from the car in ``state``, or None.

        Driver steering torque is a takeover only while the stack steers (or may start to): in
        the torque-only (semi-automated) mode the driver's hands on the wheel are the point.
        """
        if state is None or not state.is_finite() or not state.has(REQUIRED):
            return DropReason.STATE_INVALID
        self.implausible = self.checker.check(state) if self.checker is not None else None
        if self.implausible is not None:   # impossible (a wheel speed, the steering) or frozen
            return DropReason.STATE_INVALID
        if stack_steers and abs(state.steering_torque) > self.p.steering_torque_takeover:
            return DropReason.DRIVER_TORQUE
        if state.brake_pedal:
            return DropReason.BRAKE_PEDAL
        if not envelope.holds(state.V, state.beta, state.r):
            return DropReason.ENVELOPE
        return None

    def request_arm(self, state: VehicleState | None, now: float) -> tuple[bool, str]:
        """Arm now if ``state`` allows it; returns (armed, why)."""
        if self.mode != BridgeMode.OFF:
            return True, f'already {self.mode.name}'
        hazard = self.hazard(state, self.p.arm_envelope)
        if hazard is not None:
            return False, f'arm refused: {hazard.name}'
        self.mode, self._armed_at = BridgeMode.ARMED, now
        log.info('armed')
        return True, 'armed'

    def disarm(self, now: float | None = None) -> None:
        if self.mode != BridgeMode.OFF:
            self._drop(DropReason.DISARM, now)

    def update(self, now: float, state: VehicleState | None, command: Command | None,
               command_time: float | None) -> BridgeMode:
        """The mode for this cycle at time ``now`` [s]; ``command_time`` is when it arrived."""
        if self.mode == BridgeMode.OFF:
            return self.mode
        fresh = command is not None and command_time is not None \
            and now - command_time <= self.p.heartbeat_timeout
        driver_steers = (self.mode == BridgeMode.ACTIVE_TORQUE_ONLY and not fresh) or (
            fresh and self._active_mode(command.mode) == BridgeMode.ACTIVE_TORQUE_ONLY)
        hazard = self.hazard(state, self.p.active_envelope, stack_steers=not driver_steers)
        if hazard is not None:
            return self._drop(hazard, now)
        if self.mode == BridgeMode.ARMED:
            if fresh and command.mode != Mode.OFF:
                self.mode = self._active_mode(command.mode)
            elif now - self._armed_at > self.p.arm_timeout:
                return self._drop(DropReason.ARM_TIMEOUT, now)
        elif not fresh:
            return self._drop(DropReason.HEARTBEAT, now)
        elif command.mode == Mode.OFF:
            self.mode, self.reason, self._armed_at = BridgeMode.ARMED, DropReason.COMMAND_OFF, now
        else:
            self.mode = self._active_mode(command.mode)
        return self.mode

    def _active_mode(self, mode: Mode) -> BridgeMode:
        # FALLBACK is the controller's own safe command: executed like FULL, through the limits.
        if mode == Mode.TORQUE_ONLY or not self.p.allow_full:
            return BridgeMode.ACTIVE_TORQUE_ONLY
        return BridgeMode.ACTIVE_FULL

    def _drop(self, reason: DropReason, now: float | None) -> BridgeMode:
        log.warning('%s -> OFF: %s%s', self.mode.name, reason.name,
                    f' ({self.implausible})' if self.implausible else '')
        self.drops[f'{self.mode.name}/{reason.name}'] += 1
        self.mode, self.reason, self.dropped_at = BridgeMode.OFF, reason, now
        return self.mode


__all__ = ['BridgeMode', 'DropReason', 'ModeManager', 'REQUIRED']

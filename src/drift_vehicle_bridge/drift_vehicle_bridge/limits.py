"""The command limiter: clamps and rate-limits every request before it is encoded."""
from __future__ import annotations

from dataclasses import replace

from drift_control.signals import Command
from drift_vehicle_bridge.params import LimitParams


def _clip(value: float, lo: float, hi: float) -> float:
    return min(max(value, lo), hi)


class CommandLimiter:
    """Keeps requested steering angle and drive torque within limits and rate limits.

    Parameters
    ----------
    params : LimitParams
        Angle [rad], rate [rad/s], torque [Nm] and torque-rate [Nm/s] limits.
    dt : float
        Bridge cycle [s]: one call of ``apply`` moves at most ``rate_max * dt``.
    """

    def __init__(self, params: LimitParams, dt: float):
        self.p = params
        self.dt = dt
        self.delta = 0.0     # last requested (or, torque-only, measured) road-wheel angle [rad]
        self.torque = 0.0    # last requested drive torque [Nm]

    def reset(self, delta: float, torque: float) -> None:
        """Start the rate limits from the measured angle [rad] and torque [Nm] (on activation)."""
        self.delta, self.torque = delta, torque

    def apply(self, cmd: Command) -> Command:
        """The command to write this cycle: rate-limited towards ``cmd``, then clamped."""
        p = self.p
        step = p.delta_rate_max * self.dt
        self.delta = _clip(_clip(cmd.delta, self.delta - step, self.delta + step),
                           -p.delta_max, p.delta_max)
        step = p.torque_rate_max * self.dt
        self.torque = _clip(_clip(cmd.drive_torque, self.torque - step, self.torque + step),
                            p.torque_min, p.torque_max)
        return replace(cmd, delta=self.delta, drive_torque=self.torque,
                       delta_rate=_clip(cmd.delta_rate, -p.delta_rate_max, p.delta_rate_max))


__all__ = ['CommandLimiter']

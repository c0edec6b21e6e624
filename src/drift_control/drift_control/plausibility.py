"""Input plausibility: a measured state the controller must not act on, even though it is finite.

A wheel turning backwards at 100 rad/s under a car going forwards, 1000 m/s, a yaw rate of
50 rad/s, a steering angle past the end stop: each is finite, each would drive the NMPC to its
limits. So would a frozen sensor (the same values, stamp after stamp, while the car moves).
``InputChecker`` names the first such reason; the NMPC then drops to its fallback in the same
cycle and solves again from the first plausible state (a frozen signal counts as plausible again
once it moves); the vehicle bridge drops to OFF.
Bounds derive from the vehicle where it has them (the steering lock) and are physical otherwise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

from drift_control.params import VehicleParams, require
from drift_control.signals import VehicleState


@dataclass(frozen=True)
class InputLimits:
    """What a measured state may be (``inputs:`` of ``config/nmpc.yaml``)."""

    V_max: float = 45.0             # speed [m/s]: beyond the maps (40 m/s) and any drift
    r_max: float = 5.0              # |yaw rate| [rad/s]: a spinning car stays below ~3
    wheel_reverse_max: float = 3.0  # rim speed a wheel may turn backwards [m/s] (sensor noise)
    front_overspeed: float = 3.0    # front rim speed above 1.3 x V [m/s]: an unpowered wheel
    rear_overspeed: float = 30.0    # rear rim speed above V [m/s]: a spinning drive wheel
    delta_margin: float = 0.15      # |delta| beyond the vehicle's delta_max [rad] (end stop)
    freeze_cycles: int = 10         # consecutive identical states that mean a frozen sensor [-]
    freeze_min_speed: float = 1.0   # judged only above this speed [m/s]: a parked car is still

    def __post_init__(self):
        for name in ('V_max', 'r_max', 'wheel_reverse_max', 'front_overspeed', 'rear_overspeed',
                     'delta_margin'):
            require(getattr(self, name) > 0, f'nmpc.inputs.{name}', 'must be positive')
        require(self.freeze_cycles >= 2, 'nmpc.inputs.freeze_cycles', 'must be >= 2')
        require(self.freeze_min_speed >= 0, 'nmpc.inputs.freeze_min_speed', 'must be >= 0')

    def for_period(self, period: float, own_period: float) -> 'InputLimits':
        """The same limits for a checker fed every ``period`` [s] instead of ``own_period``:
        the frozen-sensor window keeps its length in time (the bridge runs at 100 Hz)."""
        cycles = max(2, round(self.freeze_cycles * own_period / period))
        return replace(self, freeze_cycles=cycles)


class InputChecker:
    """Judges each new measured state; ``check`` returns a reason or None.

    Parameters
    ----------
    vehicle : VehicleParams
        Rolling radii and the steering lock.
    limits : InputLimits
    """

    def __init__(self, vehicle: VehicleParams, limits: InputLimits = InputLimits()):
        self.vehicle, self.limits = vehicle, limits
        self.reset()

    def reset(self) -> None:
        self._last: tuple | None = None     # (stamp, values) of the previous state
        self._same = 0                      # states in a row with the previous one's values

    def check(self, state: VehicleState) -> str | None:
        """The reason ``state`` (finite, valid) is implausible, or None."""
        frozen = self.frozen(state)
        return self.bounds(state) or frozen

    def bounds(self, s: VehicleState) -> str | None:
        """Physical bounds, no history."""
        lim, v = self.limits, self.vehicle
        if not -1.0 <= s.V <= lim.V_max:
            return f'speed {s.V:.1f} m/s outside [-1, {lim.V_max:g}]'
        if not abs(s.beta) <= math.pi:
            return f'sideslip {s.beta:.2f} rad outside [-pi, pi]'
        if not abs(s.r) <= lim.r_max:
            return f'yaw rate {s.r:.2f} rad/s beyond {lim.r_max:g}'
        delta_max = v.limits.delta_max + lim.delta_margin
        if not abs(s.delta) <= delta_max:
            return f'steering angle {s.delta:.3f} rad beyond the lock ({delta_max:.3f})'
        speed = abs(s.V)
        for i, w in enumerate(s.wheel_speeds):
            front = i < 2
            rim = w * (v.R_F if front else v.R_R)
            high = (1.3 * speed + lim.front_overspeed) if front else (speed + lim.rear_overspeed)
            if not -lim.wheel_reverse_max <= rim <= high:
                name = ('FL', 'FR', 'RL', 'RR')[i]
                return (f'wheel speed {name} {w:.1f} rad/s ({rim:.1f} m/s at the rim) outside '
                        f'[{-lim.wheel_reverse_max:g}, {high:.1f}] m/s at {speed:.1f} m/s')
        return None

    def frozen(self, s: VehicleState) -> str | None:
        """The reason if ``freeze_cycles`` samples in a row (advancing stamps) were identical
        while the car moved; feed it every sample."""
        values = (s.V, s.beta, s.r, s.delta, *s.wheel_speeds)
        if self._last is None or s.stamp > self._last[0]:   # a new sample (not one seen again)
            moving = abs(s.V) >= self.limits.freeze_min_speed
            if self._last is not None and moving:
                self._same = self._same + 1 if values == self._last[1] else 0
            elif not moving:
                self._same = 0
            self._last = (s.stamp, values)
        if self._same + 1 >= self.limits.freeze_cycles:
            return (f'measurements frozen ({self._same + 1} identical samples with advancing '
                    'stamps)')
        return None


__all__ = ['InputChecker', 'InputLimits']

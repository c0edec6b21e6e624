"""Sensors: the car's measuring units, each with its rate, latency, noise, bias and faults.

``Sensors.step(truth)`` takes the plant's ground truth once per plant call and returns the
``SensorSample`` messages that arrive at that instant: an INS/GNSS unit (speed, sideslip, yaw
rate, pose), an IMU (ax, ay, yaw rate with bias, bias drift and the body roll in ay), ABS wheel
speeds, the steering angle sensor and the powertrain's torque estimate, each quantised to its
frame's resolution (``config/can/drift_vehicle.dbc``). Figures and their provenance live in
``config/sim/sensors/<name>.yaml``. Same seed, same samples.
"""
from __future__ import annotations

import copy
import math
import os
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drift_control.estimator import FIELDS, SensorSample
from drift_control.params import (ParamError, config_dir, from_dict, load_yaml, set_key,
                                  split_override)
from drift_control.signals import VehicleState

FAULT_KINDS = ('dropout', 'freeze', 'bias_step', 'stuck', 'jump')


@dataclass(frozen=True)
class ChannelNoise:
    """Errors of one measured signal [its unit]."""

    std: float = 0.0            # white noise per sample
    resolution: float = 0.0     # quantisation step (0: none)
    bias_std: float = 0.0       # constant offset drawn per run
    bias_walk: float = 0.0      # random-walk drift of the offset [unit / sqrt(s)]
    gm_std: float = 0.0         # slow first-order Gauss-Markov error, stationary std
    gm_tau: float = 1.0         # its correlation time [s]
    scale_std: float = 0.0      # scale factor error drawn per run [-]

    def __post_init__(self):   # ValueError: from_dict names the channel
        for name in ('std', 'resolution', 'bias_std', 'bias_walk', 'gm_std', 'scale_std'):
            if not getattr(self, name) >= 0:
                raise ValueError(f'{name} must be >= 0')
        if not self.gm_tau > 0:
            raise ValueError('gm_tau must be positive')


@dataclass(frozen=True)
class UnitParams:
    """One sensor unit: output rate, latency to the estimator and its channels."""

    rate: float                          # [Hz]
    latency: float                       # sample instant to arrival [s]
    channels: dict[str, ChannelNoise]
    roll_gradient: float = 0.0           # IMU only: body roll per lateral acceleration [rad s^2/m]

    def __post_init__(self):   # ValueError: from_dict names the unit
        for name, ok in (('rate', self.rate > 0), ('latency', self.latency >= 0),
                         ('roll_gradient', self.roll_gradient >= 0)):
            if not ok:
                raise ValueError(f'{name} must be {"positive" if name == "rate" else ">= 0"}')


@dataclass(frozen=True)
class SensorParams:
    """All units (``config/sim/sensors/<name>.yaml``)."""

    ins: UnitParams
    imu: UnitParams
    wheels: UnitParams
    steering: UnitParams
    torque: UnitParams


@dataclass(frozen=True)
class Fault:
    """A sensor fault over ``[start, end)`` of the time the samples describe [s].

    ``dropout``: the unit sends nothing; ``freeze``: the channel repeats its last value;
    ``bias_step``: ``value`` is added; ``stuck``: the channel reads ``value``; ``jump``: like
    ``bias_step``, meant for a short window.
    """

    unit: str
    channel: str | None
    kind: str
    start: float
    end: float
    value: float = 0.0

    def active(self, t: float) -> bool:
        return self.start <= t < self.end


def parse_fault(text: str) -> Fault:
    """``unit[.channel]:kind:start:end[:value]``, e.g. ``ins:dropout:30:31``,
    ``ins.beta:freeze:30:40``, ``imu.r:bias_step:30:55:0.0175``, ``wheels.FL:stuck:30:55:0``."""
    parts = text.split(':')
    if len(parts) not in (4, 5):
        raise ParamError(f'sensor fault {text!r}: expected unit[.channel]:kind:start:end[:value]')
    unit, _, channel = parts[0].partition('.')
    if unit not in FIELDS:
        raise ParamError(f'sensor fault {text!r}: unknown unit {unit!r}; known {list(FIELDS)}')
    if channel and channel not in FIELDS[unit]:
        raise ParamError(f'sensor fault {text!r}: {unit} has no channel {channel!r}; '
                         f'known {list(FIELDS[unit])}')
    if parts[1] not in FAULT_KINDS:
        raise ParamError(f'sensor fault {text!r}: unknown kind {parts[1]!r}; known {FAULT_KINDS}')
    if parts[1] != 'dropout' and not channel:
        raise ParamError(f'sensor fault {text!r}: {parts[1]} needs a channel (unit.channel)')
    try:
        numbers = [float(v) for v in parts[2:]]
    except ValueError:
        raise ParamError(f'sensor fault {text!r}: start, end and value must be numbers') from None
    return Fault(unit, channel or None, parts[1], *numbers)


def sensors_file(name: str, config: str | os.PathLike | None = None) -> Path:
    """``config/sim/sensors/<name>.yaml``, or ``name`` itself when it is a file."""
    path = Path(name)
    if path.suffix in ('.yaml', '.yml') and path.is_file():
        return path
    path = Path(config or config_dir()) / 'sim' / 'sensors' / f'{name}.yaml'
    if not path.is_file():
        raise ParamError(f'sensors {name!r}: no file {path}')
    return path


def load_sensor_params(name: str = 'realistic', config=None, overrides=()) -> SensorParams:
    """Validate a sensor set after ``key=value`` overrides; every error names the key."""
    raw = copy.deepcopy(load_yaml(sensors_file(name, config)))
    for item in overrides:
        set_key(raw, *split_override(item), where='sensors')
    params = from_dict(SensorParams, raw, 'sensors')
    for unit in FIELDS:
        got = set(getattr(params, unit).channels)
        missing, unknown = sorted(set(FIELDS[unit]) - got), sorted(got - set(FIELDS[unit]))
        if missing or unknown:
            raise ParamError(f'sensors.{unit}.channels: needs {list(FIELDS[unit])} '
                             f'(missing {missing}, unknown {unknown})')
    return params


def _truth_value(state: VehicleState, unit: str, name: str) -> float:
    if unit == 'wheels':
        return state.wheel_speeds[FIELDS['wheels'].index(name)]
    return getattr(state, name)


class _Unit:
    """One unit's timing and error state."""

    def __init__(self, name: str, p: UnitParams, dt: float, rng: np.random.Generator):
        self.name, self.p, self.rng = name, p, rng
        self.period = int(round(1.0 / (p.rate * dt)))
        self.lag = int(round(p.latency / dt))
        if self.period < 1 or abs(self.period * dt * p.rate - 1.0) > 1e-6:
            raise ParamError(f'sensors.{name}.rate: {p.rate:g} Hz is not the plant rate '
                             f'{1 / dt:g} Hz divided by a whole number')
        if abs(self.lag * dt - p.latency) > 1e-9:
            raise ParamError(f'sensors.{name}.latency: {p.latency:g} s is not a multiple of the '
                             f'plant step {dt:g} s')
        self.noise = [p.channels[c] for c in FIELDS[name]]
        self.h = self.period * dt
        n = len(self.noise)
        self.bias = np.array([c.bias_std for c in self.noise]) * rng.standard_normal(n)
        self.scale = 1.0 + np.array([c.scale_std for c in self.noise]) * rng.standard_normal(n)
        self.gm = np.array([c.gm_std for c in self.noise]) * rng.standard_normal(n)
        self.last: list[float | None] = [None] * n

    def sample(self, state: VehicleState, faults) -> tuple[float, ...]:
        h, rng, n = self.h, self.rng, len(self.noise)
        white = rng.standard_normal(n)
        walk = rng.standard_normal(n)
        slow = rng.standard_normal(n)
        out = []
        for i, (name, c) in enumerate(zip(FIELDS[self.name], self.noise)):
            true = _truth_value(state, self.name, name)
            if self.name == 'imu' and name == 'ay':   # gravity seen through the body roll
                true = true + 9.81 * math.sin(self.p.roll_gradient * true)
            self.bias[i] += c.bias_walk * math.sqrt(h) * walk[i]
            phi = math.exp(-h / c.gm_tau)
            self.gm[i] = phi * self.gm[i] + c.gm_std * math.sqrt(1.0 - phi * phi) * slow[i]
            value = self.scale[i] * true + self.bias[i] + self.gm[i] + c.std * white[i]
            for f in faults:
                if f.channel == name:
                    if f.kind in ('bias_step', 'jump'):
                        value += f.value
                    elif f.kind == 'stuck':
                        value = f.value
                    elif f.kind == 'freeze' and self.last[i] is not None:
                        value = self.last[i]
            if name == 'yaw':
                value = math.remainder(value, 2.0 * math.pi)
            if c.resolution > 0.0:
                value = round(value / c.resolution) * c.resolution
            self.last[i] = value
            out.append(value)
        return tuple(out)


class Sensors:
    """The car's sensor units on the plant's ground truth.

    Parameters
    ----------
    params : SensorParams
    dt : float
        Plant step [s]: rates divide it, latencies are multiples of it.
    seed : int
        Seeds every unit's noise and biases (one stream per unit).
    faults : iterable of Fault
    """

    def __init__(self, params: SensorParams, dt: float, seed: int = 0, faults=()):
        self.p, self.dt, self.seed = params, dt, int(seed)
        self.faults = tuple(faults)
        self.units = self._build()   # checks rates and latencies against dt now, not at reset

    def reset(self, truth_state: VehicleState) -> list[SensorSample]:
        """Start a run at ``truth_state``; returns one sample of each unit, all of that instant."""
        self.units = self._build()
        depth = max(u.lag for u in self.units) + 1
        self._hist = deque([truth_state] * depth, maxlen=depth)
        self.k = 0
        return [SensorSample(u.name, truth_state.stamp, u.sample(truth_state, ()))
                for u in self.units]

    def _build(self) -> list[_Unit]:
        """Every unit with fresh noise: one random stream per unit, from the seed."""
        return [_Unit(name, getattr(self.p, name), self.dt,
                      np.random.default_rng(np.random.SeedSequence([self.seed, 0x5E25, i])))
                for i, name in enumerate(FIELDS)]

    def step(self, truth_state: VehicleState) -> list[SensorSample]:
        """The samples arriving at ``truth_state.stamp``, after one plant step."""
        self._hist.append(truth_state)
        self.k += 1
        out = []
        for u in self.units:
            if self.k < u.lag or (self.k - u.lag) % u.period:
                continue   # nothing sampled since the start has arrived yet
            past = self._hist[-1 - u.lag]
            stamp = round(truth_state.stamp - u.lag * self.dt, 9)
            faults = [f for f in self.faults if f.unit == u.name and f.active(stamp)]
            if any(f.kind == 'dropout' for f in faults):
                continue
            out.append(SensorSample(u.name, stamp, u.sample(past, faults)))
        return out


__all__ = ['ChannelNoise', 'FAULT_KINDS', 'Fault', 'SensorParams', 'Sensors', 'UnitParams',
           'load_sensor_params', 'parse_fault', 'sensors_file']

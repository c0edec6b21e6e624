"""Scripted identification manoeuvre: a test driver's program of steering and throttle, no NMPC.

A manoeuvre (``config/sim/manoeuvres/<name>.yaml``) is a list of segments a driver on a skid pad
can follow, each at a speed held with the throttle:

- ``circle``: constant steering angle, speed ramped from ``speed[0]`` to ``speed[1]`` (ISO 4138
  constant-steer method) up to the grip limit;
- ``steps``: steering steps of +-``steer_deg`` around straight ahead every ``period`` seconds;
- ``sweep``: a steering sine whose frequency rises from ``f0`` to ``f1`` (a chirp);
- ``burst``: turn in at ``steer_deg``, then full power for ``power_s`` s (power-on oversteer),
  power off and counter-steer along the front axle's direction of travel until the car regrips;
- ``drift``: as a burst, but the slide is held at ``beta_peak_deg`` for ``hold_s`` s with the
  throttle (more power, more sideslip) before the power rolls off: the steady drift the
  controller will be asked for, so the fit sees the tyres where the drift works them.

Speeds are for a mu = 1 surface and scale with sqrt(mu), drive forces (a share of the car's
weight, so one file fits cars of any mass) with mu. Safety: beyond ``beta_abort_deg`` of sideslip the power goes
off whatever the segment asks. ``run_manoeuvre`` plays a scenario on the plant with this driver
as the only source of commands; ``scripts/sysid_drive.py`` records it to a bag.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Iterator, Literal, NamedTuple

from drift_control.params import (ParamError, VehicleParams, config_dir, from_dict,
                                  load_vehicle, load_yaml, require)
from drift_control.signals import Command, Mode, VehicleState
from drift_sim.scenario import load_scenario
from drift_sim.simulator import Simulator


@dataclass(frozen=True)
class Segment:
    """One part of the programme; speeds [m/s] and drive forces are for mu = 1."""

    kind: Literal['circle', 'steps', 'sweep', 'burst', 'drift']
    duration: float                  # [s]
    steer_deg: float                 # turn-in angle (circle, burst) or amplitude, + left [deg]
    speed: tuple[float, ...]         # held speed, or [start, end] of a ramp [m/s]
    period: float = 2.0              # steps: time per step; burst: time per burst cycle [s]
    f0: float = 0.2                  # sweep: start frequency [Hz]
    f1: float = 2.0                  # sweep: end frequency [Hz]
    drive_g: float = 0.0             # burst: drive force while the power is on, per weight [-]
    power_s: float = 1.5             # burst: seconds of power per cycle, at most [s]
    beta_peak_deg: float = 20.0      # burst: power off once the sideslip reaches this [deg]
    lift_beta_deg: float = 8.0       # circle: power off beyond this sideslip (limit found) [deg]
    hold_s: float = 0.0              # drift: seconds the sideslip is held at beta_peak_deg [s]
    hold_g: float = 0.25             # drift: drive force holding it, per weight, before the
                                     # sideslip feedback [-]
    hold_gain: float = 0.6           # drift: drive force per weight per radian of sideslip error

    def __post_init__(self):
        require(self.duration > 0, 'segment.duration', 'must be positive')
        require(1 <= len(self.speed) <= 2 and min(self.speed) > 0, 'segment.speed',
                'one speed or [start, end], each positive')
        require(self.period > 0, 'segment.period', 'must be positive')
        require(self.kind not in ('burst', 'drift') or 0 < self.power_s < self.period,
                'segment.power_s', 'must lie between 0 and the period')
        require(self.kind != 'drift' or self.power_s + self.hold_s < self.period,
                'segment.hold_s', 'power and hold must fit in the period')
        require(0 < self.f0 <= self.f1, 'segment.f0', 'need 0 < f0 <= f1')


@dataclass(frozen=True)
class Manoeuvre:
    """The whole programme and the driver's throttle loop."""

    segments: tuple[Segment, ...]
    speed_gain: float = 0.6          # throttle per speed error, as an acceleration [1/s]
    speed_integral: float = 0.15     # integral of the speed error [1/s^2]
    beta_abort_deg: float = 40.0     # power off beyond this sideslip in any segment [deg]
    regrip_beta_deg: float = 4.0     # after a burst: throttle again once below this [deg]
    rate_max: float = 1.0            # the hands: road-wheel angle rate [rad/s]
    lift_torque: float = -800.0      # the throttle loop's least torque (lifting) [Nm]
    k_r: float = 0.15                # counter-steer per yaw-rate excess in a slide [rad s/rad]
    anticipation: float = 0.3        # the driver judges the sideslip this far ahead [s]
    description: str = ''

    def __post_init__(self):
        require(len(self.segments) > 0, 'manoeuvre.segments', 'needs at least one segment')
        require(self.speed_gain > 0 and self.speed_integral >= 0, 'manoeuvre.speed_gain',
                'gains must be positive')

    @property
    def duration(self) -> float:
        return sum(s.duration for s in self.segments)


def manoeuvre_file(name: str, config: str | os.PathLike | None = None) -> FsPath:
    """``config/sim/manoeuvres/<name>.yaml``, or ``name`` itself when it is a file."""
    if os.path.isfile(name):
        return FsPath(name)
    return FsPath(config or config_dir()) / 'sim' / 'manoeuvres' / f'{name}.yaml'


def load_manoeuvre(name: str, config: str | os.PathLike | None = None) -> Manoeuvre:
    """Load and validate a manoeuvre; a bad key is a ParamError naming it."""
    path = manoeuvre_file(name, config)
    return from_dict(Manoeuvre, load_yaml(path), path.name)


class ScriptedDriver:
    """Turns the programme into commands (FULL mode: a steering and a throttle robot).

    Parameters
    ----------
    manoeuvre : Manoeuvre
    vehicle : VehicleParams
        The driver's feel for the car: mass, CoG, rear radius, torque limits.
    mu : float
        Surface friction the programme is scaled to [-].
    dt : float
        Call period [s].
    """

    def __init__(self, manoeuvre: Manoeuvre, vehicle: VehicleParams, mu: float, dt: float):
        self.m, self.p, self.mu, self.dt = manoeuvre, vehicle, mu, dt
        self._starts = []
        t = 0.0
        for seg in manoeuvre.segments:
            self._starts.append(t)
            t += seg.duration
        self._integral, self._index, self._delta = 0.0, -1, 0.0
        self._lifted, self._power_off, self._hold_from = False, False, None
        self._beta_prev, self._beta_rate = 0.0, 0.0

    def segment_at(self, t: float) -> tuple[int, float]:
        """Index of the segment running at ``t`` and the time into it [s]."""
        i = max(k for k, t0 in enumerate(self._starts) if t0 <= t + 1e-9)
        return i, t - self._starts[i]

    def command(self, state: VehicleState, t: float) -> Command:
        """The steering angle and drive torque for the measured ``state`` at time ``t``."""
        i, tau = self.segment_at(t)
        seg = self.m.segments[i]
        # the driver feels where the slide is going: |beta| rate through a 50 ms lag
        rate = (abs(state.beta) - self._beta_prev) / self.dt
        self._beta_prev = abs(state.beta)
        self._beta_rate += (rate - self._beta_rate) * min(1.0, self.dt / 0.05)
        if i != self._index:       # a new segment: the throttle loop starts afresh
            self._index, self._integral, self._lifted = i, 0.0, False
            self._cycle = -1
        scale_v = math.sqrt(self.mu)
        speeds = seg.speed if len(seg.speed) == 2 else (seg.speed[0], seg.speed[0])
        v_target = scale_v * (speeds[0] + (speeds[1] - speeds[0]) * tau / seg.duration)
        steer = math.radians(seg.steer_deg)
        beta = abs(state.beta)
        torque = None                # None: the throttle loop holds v_target
        if seg.kind == 'circle':
            delta = steer
            if beta > math.radians(seg.lift_beta_deg):
                self._lifted = True  # the grip limit: lift, let it regrip, ramp on from there
            elif self._lifted and beta < math.radians(self.m.regrip_beta_deg):
                self._lifted = False
                self._integral = 0.0
            torque = 0.0 if self._lifted else None
        elif seg.kind == 'steps':
            n = int(tau // seg.period)
            delta = steer * (0.0 if n % 2 == 0 else (1.0 if n % 4 == 1 else -1.0))
        elif seg.kind == 'sweep':
            rate = (seg.f1 - seg.f0) / seg.duration
            delta = steer * math.sin(2.0 * math.pi * (seg.f0 * tau + 0.5 * rate * tau * tau))
        else:                        # burst, drift
            cycle = int(tau // seg.period)
            if cycle != self._cycle:
                self._cycle, self._power_off, self._hold_from = cycle, None, None
            delta = steer
            torque = self._burst(seg, tau % seg.period, state)
        delta = self._catch(state, delta)
        sliding = -math.copysign(1.0, state.r) * state.beta > math.radians(self.m.regrip_beta_deg)
        if beta > math.radians(self.m.beta_abort_deg):
            torque = 0.0
        if torque is None:
            # a sliding car is not lifted hard: that snaps the rear round
            floor = 0.0 if sliding else self.m.lift_torque
            torque = max(self._hold_speed(v_target, state.V), floor)
        else:
            self._integral = 0.0
        lo, hi = self.p.limits.T_R_min, self.p.limits.T_R_max
        torque = min(max(torque, lo), hi)
        delta = min(max(delta, -self.p.limits.delta_max), self.p.limits.delta_max)
        step = self.m.rate_max * self.dt    # the hands are only so fast
        delta = min(max(delta, self._delta - step), self._delta + step)
        rate = (delta - self._delta) / self.dt
        self._delta = delta
        return Command(t, delta, rate, torque, Mode.FULL)

    def _catch(self, state: VehicleState, delta: float) -> float:
        """Steering with a slide caught: once the rear steps out, the front wheels follow
        where the front axle travels (front slip ~0) less a yaw-rate damping."""
        V = max(state.V, 1.0)
        slide = -math.copysign(1.0, state.r) * state.beta   # > 0: the rear steps out
        w = min(1.0, max(0.0, (slide - math.radians(2.0)) / math.radians(6.0)))
        if w == 0.0:
            return delta
        follow = math.atan2(V * math.sin(state.beta) + self.p.a * state.r,
                            V * math.cos(state.beta))
        r_turn = V * math.tan(delta) / self.p.L
        return w * (follow - self.m.k_r * (state.r - r_turn)) + (1.0 - w) * delta

    def _burst(self, seg: Segment, tau: float, state: VehicleState):
        """Drive torque of a burst cycle: grip, power on until the sideslip peaks, feather off
        over half a second (a sudden lift snaps the rear round), regrip; None: hold the speed."""
        power_from = 0.4 * (seg.period - seg.power_s)
        if tau < power_from:
            return None
        # the sideslip the driver expects a moment ahead: a fast-growing slide is caught early
        ahead = abs(state.beta) + self.m.anticipation * max(self._beta_rate, 0.0)
        weight = self.mu * self.p.m * self.p.g * self.p.R_R    # drive torque per g of force
        if seg.kind == 'drift' and self._power_off is None:
            if self._hold_from is None and ahead > math.radians(seg.beta_peak_deg):
                self._hold_from = tau
            if self._hold_from is not None:
                if tau - self._hold_from < seg.hold_s:    # hold: more power, more sideslip
                    error = math.radians(seg.beta_peak_deg) - ahead
                    self._power = max(0.0, weight * (seg.hold_g + seg.hold_gain * error))
                    return self._power
                self._power_off = tau
        if self._power_off is None and (ahead > math.radians(seg.beta_peak_deg)
                                        or tau >= power_from + seg.power_s):
            self._power_off = tau
        if self._power_off is None:   # full power, eased off as the sideslip nears its peak
            ease = (ahead / math.radians(seg.beta_peak_deg) - 0.3) / 0.5
            self._power = seg.drive_g * weight * (1.0 - 0.8 * min(1.0, max(0.0, ease)))
            return self._power
        fade = 1.0 - (tau - self._power_off) / 0.5
        if fade > 0.0:
            return fade * self._power
        if abs(state.beta) > math.radians(self.m.regrip_beta_deg):
            return 0.0
        return None

    def _hold_speed(self, v_target: float, V: float) -> float:
        """PI throttle on the speed error, with the drag as feed-forward [Nm]."""
        error = v_target - V
        self._integral += self.m.speed_integral * error * self.dt
        self._integral = min(max(self._integral, -2.0), 2.0)   # [m/s^2]
        accel = self.m.speed_gain * error + self._integral
        return self.p.R_R * (self.p.m * accel + self.p.c_drag * V * V)


class Sample(NamedTuple):
    """One 10 ms step of a manoeuvre run."""

    t: float
    command: Command
    measured: VehicleState
    truth: VehicleState


def run_manoeuvre(scenario: str, manoeuvre: str | None = None, seed: int | None = None,
                  config: str | os.PathLike | None = None, vehicle: str | None = None,
                  overrides=()) -> Iterator[Sample]:
    """Play ``scenario`` on the plant with the scripted driver: an iterator over every step.

    Loads and validates everything before it returns (a bad key raises here, not mid-run).

    The manoeuvre defaults to the scenario's ``driver.manoeuvre`` key, else ``sysid``; the run
    lasts the scenario's duration or the manoeuvre's, whichever is shorter.
    """
    cfg = FsPath(config or config_dir())
    loaded = load_scenario(scenario, overrides, cfg, seed=seed, vehicle=vehicle)
    sc = loaded.scenario
    if sc.control_mode != 'full':
        raise ParamError(f'scenario {sc.name}: a scripted manoeuvre needs control_mode: full')
    name = manoeuvre or str(sc.driver.get('manoeuvre', 'sysid'))
    prog = load_manoeuvre(name, cfg)
    car = load_vehicle(sc.vehicle, cfg)
    sim = Simulator(loaded)
    driver = ScriptedDriver(prog, car, loaded.mu, sim.dt)
    return _drive(sim, driver, int(round(min(sc.duration, prog.duration) / sim.dt)))


def _drive(sim: Simulator, driver: ScriptedDriver, n: int) -> Iterator[Sample]:
    state = sim.reset()
    for _ in range(n):
        cmd = driver.command(state, sim.t)
        state = sim.step(cmd)
        yield Sample(sim.t, cmd, state, sim.plant.truth.state)

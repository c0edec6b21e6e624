"""Supervisor: notices when the car is no longer doing what the controller asks, and latches.

The paper's full-automation test on a production car failed this way: the electric power steering
(~30 Nm) could not hold the counter-steer the NMPC asked for, the front wheels aligned with the
direction of travel and the car spun. An MPC that keeps optimising on a steering angle it does
not get presses on into the spin. The supervisor watches the outcome instead of the solver:

- steering authority: over a leaky window of ``steer_window`` seconds, the controller asked for
  more than ``steer_demand_min`` of net steering motion in one direction and the road wheels
  moved less than ``steer_ratio_min`` of it that way (the NMPC re-plans from the measured angle
  every cycle, so its command is never far from the measurement: the shortfall shows in the
  motion, not in the angle). Both sums are signed: a command dithering around a held angle asks
  for no net motion, and a slow actuator's phase lag on that dither is not a loss of authority;
- sideslip envelope: ``|beta|`` exceeds the reference's by more than ``beta_excess_max``, or
  ``beta_abs_max`` outright (a spin starts);

and then trips, latched: the caller goes to its safe fallback (torque ramped down, steering
toward the reference) until ``reset()`` (a new arming).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

from drift_control.params import config_dir, from_dict, load_yaml, require
from drift_control.signals import Command, Mode, Reference, VehicleState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SupervisorParams:
    """Thresholds of the supervisor (``config/supervisor.yaml``)."""

    enabled: bool = True
    steer_demand_min: float = 0.10     # steering motion asked for within the window [rad] ...
    steer_ratio_min: float = 0.3       # ... of which less than this share happened trips [-]
    steer_window: float = 0.5          # time constant of the leaky window [s]
    steer_judge_beta: float = 0.17     # steering judged only with |beta_ref| above this [rad]
    beta_excess_max: float = 0.35      # |beta| - |beta_ref| beyond this [rad] ...
    beta_excess_time: float = 0.3      # ... for longer than this [s]
    beta_abs_max: float = 1.05         # |beta| beyond this trips at once [rad] (~60 deg)

    def __post_init__(self):
        for name in ('steer_demand_min', 'steer_ratio_min', 'steer_window', 'beta_excess_max',
                     'beta_excess_time', 'beta_abs_max'):
            require(getattr(self, name) > 0, f'supervisor.{name}', 'must be positive')


def load_supervisor_params(path=None) -> SupervisorParams:
    """Load ``config/supervisor.yaml`` (section ``supervisor``)."""
    path = Path(path) if path else config_dir() / 'supervisor.yaml'
    raw = load_yaml(path)
    return from_dict(SupervisorParams, raw.get('supervisor', {}), f'{path.name}.supervisor')


class Supervisor:
    """Latching monitor of steering authority and sideslip; see the module docstring."""

    def __init__(self, params: SupervisorParams):
        self.p = params
        self.reason: str | None = None
        self._beta_since: float | None = None
        self._asked = self._moved = 0.0      # signed leaky sums of steering motion [rad]
        self._prev: tuple[float, float, float] | None = None   # (t, delta measured, commanded)

    @property
    def tripped(self) -> bool:
        return self.reason is not None

    def reset(self) -> None:
        """Clear the latch (a new arming) and the timers."""
        self.reason = None
        self._beta_since = self._prev = None
        self._asked = self._moved = 0.0

    def check(self, state: VehicleState | None, ref: Reference | None,
              last_command: Command | None, now: float) -> str | None:
        """Update with the newest state; returns the trip reason once tripped, else None."""
        if self.reason is not None or not self.p.enabled or state is None \
                or not state.is_finite():
            return self.reason
        p = self.p
        beta_abs = abs(state.beta)
        if beta_abs > p.beta_abs_max:
            return self._trip(f'sideslip {math.degrees(state.beta):.0f} deg beyond '
                              f'{math.degrees(p.beta_abs_max):.0f} deg: spinning')
        if ref is not None and ref.is_finite():
            excess = beta_abs - abs(ref.target.beta)
            self._beta_since = _since(self._beta_since, excess > p.beta_excess_max, now)
            if self._beta_since is not None and now - self._beta_since > p.beta_excess_time:
                return self._trip(f'sideslip {math.degrees(excess):.0f} deg beyond its '
                                  f'reference for {now - self._beta_since:.2f} s')
        # judged in a drift only: in grip the wheels' self-centring is the driver's business
        drifting = ref is not None and abs(ref.target.beta) > p.steer_judge_beta
        steering = last_command is not None and last_command.mode == Mode.FULL and drifting
        if steering and self._prev is not None and now > self._prev[0]:
            t0, measured0, commanded0 = self._prev
            asked = commanded0 - measured0                 # motion the last command asked for
            moved = state.delta - measured0
            keep = math.exp(-(now - t0) / p.steer_window)
            self._asked = keep * self._asked + asked
            self._moved = keep * self._moved + moved
            demand = abs(self._asked)
            delivered = self._moved * math.copysign(1.0, self._asked)
            if demand > p.steer_demand_min and delivered < p.steer_ratio_min * demand:
                return self._trip(f'steering authority lost: the wheels moved '
                                  f'{math.degrees(delivered):.1f} deg of '
                                  f'{math.degrees(demand):.1f} deg asked')
        elif not steering:
            self._asked = self._moved = 0.0
        self._prev = (now, state.delta, last_command.delta) if steering else None
        return None

    def _trip(self, reason: str) -> str:
        self.reason = reason
        log.error('supervisor tripped: %s', reason)
        return reason


def _since(t0: float | None, condition: bool, now: float) -> float | None:
    """When ``condition`` started to hold continuously (None while it does not)."""
    if not condition:
        return None
    return now if t0 is None else t0

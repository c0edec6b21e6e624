"""Driver model of the semi-automated mode: a human who steers while the NMPC sets the torque.

Drifters point the front wheels roughly where the front axle is going and correct with a front
slip angle; this model does the same, with feedback on sideslip, yaw rate and path errors,
a reaction delay (the driver acts on what happened ``reaction_delay`` ago) and a first-order
neuromuscular lag with a rate limit (limited bandwidth)::

    delta = atan((v_y + a r) / v_x) + alpha_F
    alpha_F = alpha_ff + w k_beta (beta - beta_des) - k_r (r - r_des) - k_e e_y - k_psi psi_err

with ``w = min(1, |beta_des| / beta_drift)`` (sideslip is a target only in a drift),
``alpha_ff`` the linear front slip angle that carries the axle's share of ``m V^2 K``, and
``beta_des``, ``r_des = V K`` from the path (``Path.beta_at``, its curvature). The law is odd in
(beta, r, e_y, K), so left and right drifts are mirror images.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from drift_control.frenet import Frenet
from drift_control.params import from_dict, require
from drift_control.path import Path
from drift_control.signals import VehicleState


@dataclass(frozen=True)
class DriverParams:
    """Gains and limits of the driver (``config/sim/driver.yaml``)."""

    reaction_delay: float   # [s]
    bandwidth: float        # [Hz]
    rate_max: float         # [rad/s]
    k_beta: float           # [rad/rad]
    k_r: float              # [rad s/rad]
    k_e: float              # [rad/m]
    k_psi: float            # [rad/rad]
    alpha_max: float        # [rad]
    beta_drift: float       # desired |beta| from which the sideslip feedback is at full gain [rad]
    m: float                # [kg]
    a: float                # [m]
    L: float                # [m]
    C_F: float              # [N/rad]

    def __post_init__(self):
        require(self.reaction_delay >= 0, 'driver.reaction_delay', 'must be >= 0')
        for name in ('bandwidth', 'rate_max', 'alpha_max', 'beta_drift', 'm', 'a', 'L', 'C_F'):
            require(getattr(self, name) > 0, f'driver.{name}', 'must be positive')


def load_driver_params(raw: dict) -> DriverParams:
    """Validate the driver mapping (``LoadedScenario.driver_raw``)."""
    return from_dict(DriverParams, raw, 'driver')


class Driver:
    """Steers the car along ``path`` at the path's desired sideslip.

    Parameters
    ----------
    params : DriverParams
        Gains and limits.
    path : Path
        Path and desired sideslip profile.
    dt : float
        Call period of ``steer`` [s].
    """

    def __init__(self, params: DriverParams, path: Path, dt: float):
        self.p, self.path, self.dt = params, path, dt
        self.frenet = Frenet(path)
        self.reset()

    def reset(self, delta: float = 0.0, s: float | None = None) -> None:
        """Forget the past; hands at ``delta`` [rad], car near arc length ``s`` [m]."""
        self.frenet.reset(s)
        n = max(int(round(self.p.reaction_delay / self.dt)), 0)
        self._seen = deque([delta] * n, maxlen=n + 1)   # intents not yet acted on
        self.delta = delta

    def intent(self, state: VehicleState) -> float:
        """The road-wheel angle the driver wants for ``state``, before delay and lag [rad]."""
        p = self.p
        fp = self.frenet.project(state.x, state.y, state.yaw, state.beta)
        K = float(fp.K)
        V = max(state.V, 1.0)
        beta_des = -math.copysign(float(self.path.beta_at(fp.s)), K) if K != 0.0 else 0.0
        alpha_ff = p.m * (p.L - p.a) / p.L * V * V * K / p.C_F
        # sideslip is a target only in a drift; in grip it follows from speed and radius
        w_drift = min(1.0, abs(beta_des) / p.beta_drift)
        alpha = (alpha_ff + w_drift * p.k_beta * (state.beta - beta_des)
                 - p.k_r * (state.r - V * K)
                 - p.k_e * fp.e_y - p.k_psi * fp.heading_error)
        alpha = float(np.clip(alpha, -p.alpha_max, p.alpha_max))
        vx = max(state.vx, 1.0)
        return math.atan((state.vy + p.a * state.r) / vx) + alpha

    def steer(self, state: VehicleState) -> tuple[float, float]:
        """One call: the steering angle [rad] and rate [rad/s] the driver applies now."""
        self._seen.append(self.intent(state))
        target = self._seen[0]    # what the driver decided reaction_delay ago
        tau = 1.0 / (2.0 * math.pi * self.p.bandwidth)
        rate = (target - self.delta) / tau
        rate = float(np.clip(rate, -self.p.rate_max, self.p.rate_max))
        self.delta += rate * self.dt
        return self.delta, rate

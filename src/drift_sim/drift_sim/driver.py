"""Driver model of the semi-automated mode: a skilled human who steers while the NMPC sets torque.

A drifter points the front wheels where the front axle should be going in the drift he intends
(his feel for the equilibrium steering) and corrects around it: counter-steers more when the car
over-rotates (sideslip or yaw rate beyond the intended ones) and less when it straightens, and
steers toward a point on the path ``preview`` seconds ahead::

    delta_int = atan((V sin beta_k + a r_k) / (V cos beta_k)) + alpha_F
    alpha_F   = clip(alpha_ff - k_e e_prev, +-alpha_max)
                + w k_beta (beta - beta_des) - k_w (r - r_des)
    e_prev    = e_y + V T_p sin(psi - psi_path + beta)              (lateral error ahead)

with ``beta_des`` the path's desired sideslip (signed by the curvature ``K``), ``r_des = V K``,
``alpha_ff`` the linear front slip angle that carries the front axle's share of ``m V^2 K``,
``w = min(1, |beta_des| / beta_drift)`` and ``k_w = w k_r + (1 - w) k_r_grip``. In a drift
(``w = 1``) the kinematic term is taken at the intended ``(beta_des, r_des)``, the driver's
intent; in grip (``w = 0``) at the perceived ``(beta, r)``, so it reduces to following the front
axle's direction of travel. The path asks for a bounded slip angle; the counter-steer is bounded
only by the end stop. The law is odd in (beta, r, e_y, K): left and right drifts are mirror
images.

The driver perceives what a human perceives -- speed, sideslip, yaw rate, pose on the path --
from the measured state, with Gaussian perception noise; acts on what it perceived
``reaction_delay`` ago; the hands follow through a first-order lag (``bandwidth``) with a rate
limit.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from drift_control.frenet import Frenet
from drift_control.params import from_dict, require
from drift_control.path import Path
from drift_control.signals import VehicleState


@dataclass(frozen=True)
class DriverParams:
    """Gains and limits of the driver (``config/sim/driver.yaml``)."""

    reaction_delay: float   # perception-to-action delay [s]
    bandwidth: float        # first-order lag of the hands [Hz]
    rate_max: float         # road-wheel angle rate [rad/s]
    k_beta: float           # counter-steer per sideslip error [rad/rad]
    k_r: float              # counter-steer per yaw-rate error in a drift [rad s/rad]
    k_r_grip: float         # steering per yaw-rate error in grip [rad s/rad]
    k_e: float              # steering per preview lateral error [rad/m]
    preview: float          # look-ahead time of the lateral error [s]
    alpha_max: float        # largest front slip angle the path asks for [rad]
    beta_drift: float       # desired |beta| from which the drift intent is at full weight [rad]
    noise_beta: float       # perception noise of the sideslip, standard deviation [rad]
    noise_r: float          # perception noise of the yaw rate, standard deviation [rad/s]
    seed: int               # seed of the perception noise [-]
    m: float                # the driver's feel for the car: mass [kg]
    a: float                # CoG to front axle [m]
    L: float                # wheelbase [m]
    C_F: float              # front axle cornering stiffness [N/rad]

    def __post_init__(self):
        for name in ('reaction_delay', 'k_beta', 'k_r', 'k_r_grip', 'k_e', 'preview', 'noise_beta',
                     'noise_r'):
            require(getattr(self, name) >= 0, f'driver.{name}', 'must be >= 0')
        for name in ('bandwidth', 'rate_max', 'alpha_max', 'beta_drift', 'm', 'a', 'L', 'C_F'):
            require(getattr(self, name) > 0, f'driver.{name}', 'must be positive')
        require(self.a < self.L, 'driver.a', 'must be shorter than the wheelbase L')


def load_driver_params(raw: dict) -> DriverParams:
    """Validate the driver mapping (``LoadedScenario.driver_raw``); a bad key is a ParamError."""
    return from_dict(DriverParams, raw, 'driver')


class Driver:
    """Steers the car along ``path`` at the path's desired sideslip.

    Parameters
    ----------
    params : DriverParams
        Gains and limits.
    path : Path
        Path and desired sideslip profile (what the driver was told to drive).
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
        self._rng = np.random.default_rng(self.p.seed)
        n = max(int(round(self.p.reaction_delay / self.dt)), 0)
        self._seen = deque([delta] * n, maxlen=n + 1)   # intents not yet acted on
        self.delta = delta

    def intent(self, state: VehicleState) -> float:
        """The road-wheel angle [rad] the driver wants for ``state``, before delay and lag.

        Deterministic: perception noise is added by ``steer``.
        """
        p = self.p
        fp = self.frenet.project(state.x, state.y, state.yaw, state.beta)
        K = float(fp.K)
        V = max(state.V, 1.0)
        beta_des = -math.copysign(float(self.path.beta_at(fp.s)), K) if K != 0.0 else 0.0
        r_des = V * K
        # intent in a drift, perception in grip (sideslip follows from speed and radius there)
        w = min(1.0, abs(beta_des) / p.beta_drift)
        beta_k = w * beta_des + (1.0 - w) * state.beta
        r_k = w * r_des + (1.0 - w) * state.r
        kinematic = math.atan2(V * math.sin(beta_k) + p.a * r_k, V * math.cos(beta_k))
        alpha_ff = p.m * (p.L - p.a) / p.L * V * V * K / p.C_F
        course_error = math.remainder(fp.heading_error + state.beta, 2.0 * math.pi)
        e_prev = fp.e_y + V * p.preview * math.sin(course_error)
        k_w = w * p.k_r + (1.0 - w) * p.k_r_grip
        # the path asks for a bounded front slip angle; counter-steer is bounded by the end stop
        alpha_path = float(np.clip(alpha_ff - p.k_e * e_prev, -p.alpha_max, p.alpha_max))
        return (kinematic + alpha_path + w * p.k_beta * (state.beta - beta_des)
                - k_w * (state.r - r_des))

    def steer(self, state: VehicleState) -> tuple[float, float]:
        """One call: the steering angle [rad] and rate [rad/s] the driver applies now."""
        p = self.p
        if p.noise_beta > 0.0 or p.noise_r > 0.0:
            n_beta, n_r = self._rng.standard_normal(2)
            state = replace(state, beta=state.beta + p.noise_beta * n_beta,
                            r=state.r + p.noise_r * n_r)
        self._seen.append(self.intent(state))
        target = self._seen[0]    # what the driver decided reaction_delay ago
        tau = 1.0 / (2.0 * math.pi * p.bandwidth)
        rate = float(np.clip((target - self.delta) / tau, -p.rate_max, p.rate_max))
        self.delta += rate * self.dt
        return self.delta, rate

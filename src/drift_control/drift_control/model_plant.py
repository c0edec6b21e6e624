"""The controller's own single-track model used as a plant, with a pose in the map frame.

For controller tests and benchmarks that must not depend on the richer simulator (``drift_sim``):
the same ``reset`` / ``step(command, dt)`` shape as ``drift_sim``'s plant, perturbed friction,
Gaussian measurement noise, and the commanded steering angle followed through the steering-rate
input (the model has delta as a state).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from drift_control.params import VehicleParams
from drift_control.signals import Command, Mode, VehicleState
from drift_control.vehicle import NX, X, rhs, rk4_step


class ModelPlant:
    """Single-track model plus global pose (x, y, yaw), stepped with RK4.

    Parameters
    ----------
    p : VehicleParams
        Vehicle parameters.
    mu : float
        Surface friction of the plant (perturb it against the controller's) [-].
    noise : dict, optional
        Standard deviation per measured signal: keys ``V``, ``beta``, ``r``, ``omega``,
        ``delta`` [SI units].
    seed : int
        Seed of the measurement noise.
    substep : float
        Integration step [s]; the front wheel-speed mode needs <= ~2 ms.
    """

    def __init__(self, p: VehicleParams, mu: float = 1.0, noise: dict | None = None,
                 seed: int = 0, substep: float = 0.002):
        self.p = p
        self.mu = mu
        self.noise = dict(noise or {})
        self.substep = substep
        self._rng = np.random.default_rng(seed)
        x = ca.SX.sym('x', NX + 3)      # model state, then global x, y, yaw
        u = ca.SX.sym('u', 2)
        x_dot = rhs(x[:NX], u, ca.vertcat(0.0, mu), p)
        course = x[NX + 2] + x[X.BETA]
        pose_dot = ca.vertcat(x[X.V] * ca.cos(course), x[X.V] * ca.sin(course), x[X.R])
        self._f = ca.Function('plant_f', [x, u], [ca.vertcat(x_dot, pose_dot)])
        self._steps: dict[int, ca.Function] = {}
        self.x = np.zeros(NX + 3)
        self.t = 0.0
        self._torque = 0.0

    def reset(self, x0, pose=(0.0, 0.0, 0.0), t: float = 0.0) -> VehicleState:
        """Start from the model state ``x0`` (length NX, path states ignored) at ``pose``."""
        self.x = np.concatenate([np.asarray(x0, dtype=float)[:NX], pose])
        self.t = t
        return self.measure()

    def step(self, command: Command, dt: float) -> VehicleState:
        """Apply ``command`` for ``dt`` seconds; returns the measured state at the end."""
        lim = self.p.limits
        delta_dot = (command.delta - self.x[X.DELTA]) / dt   # reach the commanded angle ...
        delta_dot = float(np.clip(delta_dot, -lim.delta_dot_max, lim.delta_dot_max))
        if command.mode in (Mode.OFF, Mode.TORQUE_ONLY):     # ... unless nobody steers by wire
            delta_dot = 0.0
        torque = float(np.clip(command.drive_torque, lim.T_R_min, lim.T_R_max))
        n = max(1, int(math.ceil(dt / self.substep - 1e-9)))
        self.x = np.asarray(self._stepper(n, dt)(self.x, [delta_dot, torque])).ravel()
        self._torque = torque
        self.t += dt
        return self.measure()

    def measure(self) -> VehicleState:
        """The state as a sensor would report it, with the configured noise."""
        x = self.x

        def noisy(value, key):
            sd = self.noise.get(key, 0.0)
            return float(value + (self._rng.normal(0.0, sd) if sd > 0 else 0.0))

        V, beta = noisy(x[X.V], 'V'), noisy(x[X.BETA], 'beta')
        wf, wr = x[X.OMEGA_F], x[X.OMEGA_R]
        return VehicleState(
            stamp=self.t, V=V, beta=beta, r=noisy(x[X.R], 'r'),
            vx=V * math.cos(beta), vy=V * math.sin(beta),
            wheel_speeds=tuple(noisy(w, 'omega') for w in (wf, wf, wr, wr)),
            delta=noisy(x[X.DELTA], 'delta'), x=float(x[NX]), y=float(x[NX + 1]),
            yaw=float(x[NX + 2]), drive_torque=self._torque)

    def _stepper(self, n: int, dt: float) -> ca.Function:
        if n not in self._steps:
            xs, us = ca.SX.sym('x', NX + 3), ca.SX.sym('u', 2)
            x_next = rk4_step(lambda x, u, _: self._f(x, u), xs, us, None, dt, n)
            self._steps[n] = ca.Function('plant_step', [xs, us], [x_next])
        return self._steps[n]

"""Nonlinear single-track model in Frenet path coordinates (paper section II), written once.

The body ``rhs(x, u, theta, p)`` uses only casadi operations, so it evaluates on floats and on
symbols alike; ``VehicleModel`` wraps it in ``casadi.Function`` objects: ``f`` for the NMPC and the
equilibrium solver (symbolic, differentiable), and numeric calls for analysis and quick simulation.

States (``X``): speed V, sideslip beta, yaw rate r, front and rear wheel speeds omega_F, omega_R,
road-wheel angle delta, and the path states heading error psi, lateral error e_y, arc length s.
Inputs (``U``): steering rate delta_dot, rear axle drive torque T_R (a negative one is engine
braking, which fades as the rear wheel stops: ``axle_torque``). Runtime parameters
(``THETA``): path curvature K and surface friction mu.

The equations of motion are resolved from the tyre forces, not copied: the paper's Eq. (2) prints
``-F_xF sin(delta - beta)`` in beta_dot, but projecting the front force onto the normal of the
velocity gives ``+F_xF sin(delta - beta)`` (``tests/test_vehicle_model.py`` checks the model
against Newton's law in the body frame).
"""
from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple

import casadi as ca
import numpy as np

from drift_control.params import VehicleParams
from drift_control.tyre import combined_forces, front_forces

X = IntEnum('X', 'V BETA R OMEGA_F OMEGA_R DELTA PSI E_Y S', start=0)
U = IntEnum('U', 'DELTA_DOT T_R', start=0)
THETA = IntEnum('THETA', 'K MU', start=0)
NX, NU, NTHETA = len(X), len(U), len(THETA)
N_VEHICLE = X.DELTA + 1   # V .. delta: the states the path does not influence

# Regularisation widths. Each blend differs from the hard corner by w exp(-distance / w), so it is
# exact to machine precision a few widths away, and keeps the model finite and differentiable at
# V = 0, at a locked wheel and with the car at the centre of the path's curvature.
_SMOOTH_W = 0.01         # width of the smooth max in speed [m/s]
_LOAD_FLOOR = 100.0      # a lifted wheel keeps this much vertical load [N]
_FRENET_FLOOR = 0.1      # 1 - e_y K never goes below this (car far inside a tight curve) [-]
FREE_ROLLING_TAU = 0.05  # time constant of the front wheel speed in 'free_rolling' mode [s]
COAST_OMEGA = 0.5        # engine braking fades over this rear wheel speed around standstill [rad/s]


class AxleForces(NamedTuple):
    """Tyre forces and slips of both axles, in each wheel's own frame [N, rad, -]."""

    F_xF: object
    F_yF: object
    F_xR: object
    F_yR: object
    F_zF: object
    F_zR: object
    alpha_F: object
    alpha_R: object
    kappa_F: object
    kappa_R: object


def axle_torque(T, omega, width=COAST_OMEGA):
    """The drive torque ``T`` [Nm] at a wheel turning at ``omega`` [rad/s]: a negative one is
    engine braking, which resists the rotation and fades out before the wheel stops (2 % left
    at standstill); it never turns the wheel backwards. Exactly ``T`` above 21 ``width``
    (``tanh`` rounds to 1 there)."""
    return ca.fmax(T, 0.0) + ca.fmin(T, 0.0) * 0.5 * (1.0 + ca.tanh(omega / width - 2.0))


def smooth_max(a, b, w=_SMOOTH_W):
    """max(a, b) smoothed over a band of width ``w``: ``b + w softplus((a - b) / w)``.

    Not a Python ``if``: the OCP needs a right-hand side with continuous derivatives. The softplus
    is written in its overflow-free form ``max(z, 0) + log1p(exp(-|z|))``.
    """
    z = (a - b) / w
    return b + w * (ca.fmax(z, 0.0) + ca.log1p(ca.exp(-ca.fabs(z))))


def front_axle_course(V: float, beta: float, r: float, a: float) -> float:
    """Direction of the front axle's velocity from the body's x axis [rad], numeric: the front
    slip angle of ``slips`` is ``delta`` minus this while the axle moves forward."""
    return math.atan2(V * math.sin(beta) + a * r, max(V * math.cos(beta), 0.1))


def velocity_rates(V: float, beta: float, r: float, ax: float, ay: float) -> tuple:
    """``(V_dot, beta_dot)`` from the body's measured accelerations at the centre of gravity
    (x forward, y left) [m/s^2], numeric: ``rhs``'s Newton in the velocity frame with the
    accelerations measured instead of modelled."""
    cos_b, sin_b = math.cos(beta), math.sin(beta)
    return ax * cos_b + ay * sin_b, (ay * cos_b - ax * sin_b) / max(V, 1.0) - r


def slips(x, p: VehicleParams):
    """Slip angles and longitudinal slips (alpha_F, kappa_F, alpha_R, kappa_R).

    The velocity of each axle is rotated into its wheel frame; slip denominators are held above
    ``p.v_eps`` so that standstill and a locked or spinning wheel stay finite.
    """
    V, beta, r, delta = x[X.V], x[X.BETA], x[X.R], x[X.DELTA]
    v_x = V * ca.cos(beta)
    v_yF = V * ca.sin(beta) + p.a * r
    v_yR = V * ca.sin(beta) - p.b * r
    v_xwF = v_x * ca.cos(delta) + v_yF * ca.sin(delta)
    v_ywF = -v_x * ca.sin(delta) + v_yF * ca.cos(delta)
    den_F = smooth_max(v_xwF, p.v_eps)
    den_R = smooth_max(v_x, p.v_eps)
    alpha_F = -ca.atan(v_ywF / den_F)
    alpha_R = -ca.atan(v_yR / den_R)
    kappa_F = (x[X.OMEGA_F] * p.R_F - v_xwF) / den_F
    kappa_R = (x[X.OMEGA_R] * p.R_R - v_x) / den_R
    return alpha_F, kappa_F, alpha_R, kappa_R


def axle_forces(x, p: VehicleParams, mu, load_passes: int = 1,
                front_wheel: str = 'dynamic') -> AxleForces:
    """Tyre forces with quasi-static longitudinal load transfer.

    The load transfer ``h / L * sum(F_x, body)`` depends on forces that depend on the loads; the
    loop is closed by ``load_passes`` fixed-point passes from the static loads (each pass shrinks
    the error by about ``h mu / L`` ~ 0.2). With ``front_wheel='free_rolling'`` the front tyre
    transmits no longitudinal force.
    """
    alpha_F, kappa_F, alpha_R, kappa_R = slips(x, p)
    delta = x[X.DELTA]
    F_zF = p.m * p.g * p.b / p.L
    F_zR = p.m * p.g * p.a / p.L
    static_F, static_R = F_zF, F_zR
    for i in range(load_passes + 1):
        F_xF, F_yF = front_forces(alpha_F, kappa_F, F_zF, p.front_tyre, mu)
        if front_wheel == 'free_rolling':
            F_xF = 0.0 * F_xF
        F_xR, F_yR = combined_forces(alpha_R, kappa_R, F_zR, p.rear_tyre, mu)
        if i == load_passes:
            break
        transfer = p.h / p.L * (F_xF * ca.cos(delta) - F_yF * ca.sin(delta) + F_xR)
        F_zF = smooth_max(static_F - transfer, _LOAD_FLOOR, _LOAD_FLOOR)
        F_zR = smooth_max(static_R + transfer, _LOAD_FLOOR, _LOAD_FLOOR)
    return AxleForces(F_xF, F_yF, F_xR, F_yR, F_zF, F_zR, alpha_F, alpha_R, kappa_F, kappa_R)


def rhs(x, u, theta, p: VehicleParams, load_passes: int = 1, front_wheel: str = 'dynamic'):
    """Time derivative of the state, paper Eq. (1) and (2) plus wheel and steering dynamics.

    Parameters
    ----------
    x : casadi.SX or array of length NX
        State, laid out as ``X``.
    u : casadi.SX or array of length NU
        Input: steering rate [rad/s], rear axle drive torque [Nm].
    theta : casadi.SX or array of length NTHETA
        Path curvature K [1/m] and surface friction mu [-].
    p : VehicleParams
        Vehicle parameters.
    load_passes : int
        Fixed-point passes of the quasi-static load transfer.
    front_wheel : {'dynamic', 'free_rolling'}
        'dynamic': I_wF omega_F' = -F_xF R_F. 'free_rolling': F_xF = 0 and omega_F follows the
        free-rolling speed with time constant ``FREE_ROLLING_TAU`` (removes the stiffest mode,
        ~1.5 ms, for coarse integrators; identical equilibria).
    """
    V, beta, r, delta = x[X.V], x[X.BETA], x[X.R], x[X.DELTA]
    f = axle_forces(x, p, theta[THETA.MU], load_passes, front_wheel)

    # Newton in the velocity frame: tangential (V_dot) and normal (beta_dot + r) components
    V_dot = (f.F_xF * ca.cos(delta - beta) - f.F_yF * ca.sin(delta - beta)
             + f.F_xR * ca.cos(beta) + f.F_yR * ca.sin(beta) - p.c_drag * V * V) / p.m
    V_reg = smooth_max(V, p.v_eps)   # beta is undefined at standstill; keep 1/V bounded
    beta_dot = (f.F_yF * ca.cos(delta - beta) + f.F_xF * ca.sin(delta - beta)
                - f.F_xR * ca.sin(beta) + f.F_yR * ca.cos(beta)) / (p.m * V_reg) - r
    r_dot = (p.a * (f.F_xF * ca.sin(delta) + f.F_yF * ca.cos(delta)) - p.b * f.F_yR) / p.I_z

    if front_wheel == 'free_rolling':
        v_xwF = V * ca.cos(beta) * ca.cos(delta) + (V * ca.sin(beta) + p.a * r) * ca.sin(delta)
        omega_F_dot = (v_xwF / p.R_F - x[X.OMEGA_F]) / FREE_ROLLING_TAU
    else:
        omega_F_dot = -f.F_xF * p.R_F / p.I_wF
    omega_R_dot = (axle_torque(u[U.T_R], x[X.OMEGA_R]) - f.F_xR * p.R_R) / p.I_wR

    # Frenet kinematics, paper Eq. (1); psi is the heading error to the path tangent
    K = theta[THETA.K]
    course = x[X.PSI] + beta
    s_dot = V * ca.cos(course) / smooth_max(1.0 - x[X.E_Y] * K, _FRENET_FLOOR, 0.01)
    psi_dot = r - K * s_dot
    e_y_dot = V * ca.sin(course)
    return ca.vertcat(V_dot, beta_dot, r_dot, omega_F_dot, omega_R_dot, u[U.DELTA_DOT],
                      psi_dot, e_y_dot, s_dot)


def rk4_step(f, x, u, theta, dt: float, substeps: int = 1):
    """One step of length ``dt`` of classic Runge-Kutta 4 with ``substeps`` equal substeps."""
    h = dt / substeps
    for _ in range(substeps):
        k1 = f(x, u, theta)
        k2 = f(x + h / 2 * k1, u, theta)
        k3 = f(x + h / 2 * k2, u, theta)
        k4 = f(x + h * k3, u, theta)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


class VehicleModel:
    """The single-track model as casadi Functions, plus numeric helpers.

    Attributes
    ----------
    f : casadi.Function
        ``f(x, u, theta) -> x_dot``.
    forces_fn : casadi.Function
        ``forces_fn(x, theta) -> [F_xF, F_yF, F_xR, F_yR, F_zF, F_zR, alpha_F, alpha_R,
        kappa_F, kappa_R]``.
    """

    def __init__(self, p: VehicleParams, load_passes: int = 1, front_wheel: str = 'dynamic'):
        if front_wheel not in ('dynamic', 'free_rolling'):
            raise ValueError(f"front_wheel must be 'dynamic' or 'free_rolling', got {front_wheel!r}")
        self.p = p
        self.load_passes = load_passes
        self.front_wheel = front_wheel
        x = ca.SX.sym('x', NX)
        u = ca.SX.sym('u', NU)
        theta = ca.SX.sym('theta', NTHETA)
        self.f = ca.Function('f', [x, u, theta], [rhs(x, u, theta, p, load_passes, front_wheel)],
                             ['x', 'u', 'theta'], ['x_dot'])
        forces = axle_forces(x, p, theta[THETA.MU], load_passes, front_wheel)
        self.forces_fn = ca.Function('forces', [x, theta], [ca.vertcat(*forces)],
                                     ['x', 'theta'], ['forces'])

    def rhs(self, x, u, K: float = 0.0, mu: float = 1.0) -> np.ndarray:
        """Numeric state derivative, shape (NX,)."""
        return np.asarray(self.f(x, u, [K, mu])).ravel()

    def forces(self, x, mu: float = 1.0, K: float = 0.0) -> AxleForces:
        """Numeric tyre forces and slips at state ``x``."""
        return AxleForces(*np.asarray(self.forces_fn(x, [K, mu])).ravel().tolist())

    def discrete(self, dt: float, substeps: int = 1) -> ca.Function:
        """``F(x, u, theta) -> x_next``: RK4 over ``dt`` with ``substeps`` substeps."""
        x = ca.SX.sym('x', NX)
        u = ca.SX.sym('u', NU)
        theta = ca.SX.sym('theta', NTHETA)
        return ca.Function('F', [x, u, theta], [rk4_step(self.f, x, u, theta, dt, substeps)],
                           ['x', 'u', 'theta'], ['x_next'])

    def simulate(self, x0, inputs, dt: float, K: float = 0.0, mu: float = 1.0,
                 substeps: int = 1) -> np.ndarray:
        """Integrate from ``x0`` under the input sequence ``inputs`` (n, NU); returns (n+1, NX)."""
        inputs = np.atleast_2d(np.asarray(inputs, dtype=float))
        step = self.discrete(dt, substeps).mapaccum(len(inputs))
        theta = np.tile([[K], [mu]], (1, len(inputs)))
        traj = np.asarray(step(np.asarray(x0, dtype=float), inputs.T, theta))
        return np.vstack([np.asarray(x0, dtype=float), traj.T])


def mirror_state(x):
    """Mirror a state left <-> right: beta, r, delta, psi, e_y change sign."""
    x = np.array(x, dtype=float)
    for i in (X.BETA, X.R, X.DELTA, X.PSI, X.E_Y):
        x[..., i] = -x[..., i]
    return x


def mirror_input(u):
    """Mirror an input left <-> right: the steering rate changes sign."""
    u = np.array(u, dtype=float)
    u[..., U.DELTA_DOT] = -u[..., U.DELTA_DOT]
    return u

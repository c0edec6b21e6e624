"""The plant's equations of motion: a double-track car, written once in casadi operations.

Body: planar rigid body (vx, vy, r, yaw, x, y) with roll and pitch as lagged quasi-static load
transfer on all four wheels. Four wheel-spin DOF; rear wheels driven through a limited-slip
differential; per-wheel MF 5.2-style combined-slip tyres (``drift_control.tyre.combined_forces``,
the shared tyre code, with the plant's own coefficients) behind first-order slip relaxation;
drive torque lag (a negative drive torque is engine braking: it resists the rear wheels'
rotation and never turns them backwards); a steering system with a rate-limited reference and a
torque-limited position loop working against the self-aligning moment of the front tyres;
aerodynamic drag, rolling resistance, brakes; friction from the road field at each contact
patch.

``PlantModel.step`` is ONE casadi Function that integrates ``substeps`` RK4 steps (``mapaccum``),
so Python runs once per plant call (10 ms), not once per 1 ms step; ``PlantModel.compiled`` is
the same Function compiled with gcc and called through ctypes.
"""
from __future__ import annotations

import logging
import os
import tempfile
from enum import IntEnum
from pathlib import Path

import casadi as ca
import numpy as np

from drift_control.compiled import CompiledFunction, build_cached
from drift_control.params import cache_dir
from drift_control.tyre import combined_forces
from drift_control.vehicle import axle_torque, smooth_max
from drift_sim.params import PlantParams
from drift_sim.road import N_FIELD, friction

_log = logging.getLogger(__name__)

S = IntEnum('S', 'VX VY R YAW X Y OMEGA_FL OMEGA_FR OMEGA_RL OMEGA_RR '
                 'KAPPA_FL KAPPA_FR KAPPA_RL KAPPA_RR ALPHA_FL ALPHA_FR ALPHA_RL ALPHA_RR '
                 'DELTA DELTA_DOT DELTA_REF DELTA_INT T_DRIVE AX_F AY_F', start=0)
UP = IntEnum('UP', 'DELTA_CMD DELTA_RATE_CMD T_REQ BRAKE STEER_TORQUE_MAX', start=0)
PP = IntEnum('PP', 'MU VARIATION LOCKING', start=0)      # followed by the friction field modes
Y = IntEnum('Y', 'AX AY STEER_TORQUE M_ALIGN MU FZ_FL FZ_FR FZ_RL FZ_RR FX_FL FX_FR FX_RL FX_RR '
                 'FY_FL FY_FR FY_RL FY_RR', start=0)
NS, NUP, NY = len(S), len(UP), len(Y)
WHEELS = ('FL', 'FR', 'RL', 'RR')
_LOAD_FLOOR = 100.0     # a lifted wheel keeps this much vertical load [N]


def n_params(p: PlantParams) -> int:
    """Length of the runtime parameter vector: mu, variation, locking, field modes."""
    return len(PP) + N_FIELD * p.road.modes


def _sat(value, limit):
    """Smooth saturation ``limit * tanh(value / limit)``."""
    return limit * ca.tanh(value / limit)


def rhs(x, u, q, p: PlantParams):
    """State derivative and output signals of the plant, ``(x_dot, y)``.

    Parameters
    ----------
    x : casadi.SX, length NS
        State, laid out as ``S``.
    u : casadi.SX, length NUP
        Steering angle request [rad] and rate [rad/s], drive torque request after the transport
        delay [Nm], total brake torque [Nm], steering actuator torque limit at the wheel [Nm].
    q : casadi.SX, length n_params(p)
        Surface mu [-], field amplitude [-], LSD locking fraction [-], field modes.
    p : PlantParams
        Plant parameters (baked into the expression).
    """
    bo, wh, st = p.body, p.wheels, p.steering
    vx, vy, r, yaw = x[S.VX], x[S.VY], x[S.R], x[S.YAW]
    delta = x[S.DELTA]
    b = bo.b
    pos = ((bo.a, 0.5 * bo.track_F), (bo.a, -0.5 * bo.track_F),
           (-b, 0.5 * bo.track_R), (-b, -0.5 * bo.track_R))
    radius = (wh.R_F, wh.R_F, wh.R_R, wh.R_R)
    tyres = (p.front_tyre, p.front_tyre, p.rear_tyre, p.rear_tyre)
    steer = (delta, delta, 0.0, 0.0)

    # quasi-static load transfer from the lagged body accelerations (roll and pitch)
    m, g, h = bo.m, bo.g, bo.h
    ax_f, ay_f = x[S.AX_F], x[S.AY_F]
    pitch = m * h * ax_f / (2.0 * bo.L)
    roll_F = bo.roll_share_F * m * h * ay_f / bo.track_F
    roll_R = (1.0 - bo.roll_share_F) * m * h * ay_f / bo.track_R
    static_F, static_R = 0.5 * m * g * b / bo.L, 0.5 * m * g * bo.a / bo.L
    loads = (static_F - pitch - roll_F, static_F - pitch + roll_F,
             static_R + pitch - roll_R, static_R + pitch + roll_R)

    c_yaw, s_yaw = ca.cos(yaw), ca.sin(yaw)
    modes = q[len(PP):]
    F_x = F_y = M_z = 0.0
    out = {}
    x_dot = [0.0] * NS
    M_align = 0.0
    for i, name in enumerate(WHEELS):
        px, py = pos[i]
        F_z = smooth_max(loads[i], _LOAD_FLOOR, _LOAD_FLOOR)
        # contact-patch velocity in the wheel frame
        v_x = vx - r * py
        v_y = vy + r * px
        cs, sn = ca.cos(steer[i]), ca.sin(steer[i])
        v_cx = v_x * cs + v_y * sn
        v_cy = -v_x * sn + v_y * cs
        den = ca.sqrt(v_cx * v_cx + wh.v_eps * wh.v_eps)
        omega = x[S[f'OMEGA_{name}']]
        kappa, alpha = x[S[f'KAPPA_{name}']], x[S[f'ALPHA_{name}']]
        # first-order relaxation: the slips lag their kinematic values by sigma / |v|
        x_dot[S[f'KAPPA_{name}']] = (omega * radius[i] - v_cx - den * kappa) / wh.sigma_x
        x_dot[S[f'ALPHA_{name}']] = (-ca.atan(v_cy / den) - alpha) * den / wh.sigma_y
        mu = friction(x[S.X] + px * c_yaw - py * s_yaw, x[S.Y] + px * s_yaw + py * c_yaw,
                      q[PP.MU], q[PP.VARIATION], modes)
        f = combined_forces(alpha, kappa, F_z, tyres[i], mu)
        fx_b = f.Fx * cs - f.Fy * sn
        fy_b = f.Fx * sn + f.Fy * cs
        F_x, F_y = F_x + fx_b, F_y + fy_b
        M_z = M_z + px * fy_b - py * fx_b
        out[f'FZ_{name}'], out[f'FX_{name}'], out[f'FY_{name}'] = F_z, f.Fx, f.Fy
        if i < 2:
            trail = st.trail_mech + st.trail_pneu / ca.sqrt(1.0 + (st.trail_B * alpha) ** 2)
            M_align = M_align + trail * f.Fy
        out[f'_wheel_{name}'] = (omega, f.Fx, F_z)

    V = ca.sqrt(vx * vx + vy * vy + 1e-6)
    F_x = F_x - bo.c_drag * V * vx
    F_y = F_y - bo.c_drag * V * vy
    ax, ay = F_x / m, F_y / m          # what an IMU at the CoG measures
    x_dot[S.VX] = ax + r * vy
    x_dot[S.VY] = ay - r * vx
    x_dot[S.R] = M_z / bo.I_z
    x_dot[S.YAW] = r
    x_dot[S.X] = vx * c_yaw - vy * s_yaw
    x_dot[S.Y] = vx * s_yaw + vy * c_yaw
    x_dot[S.AX_F] = (ax - ax_f) / bo.load_tau
    x_dot[S.AY_F] = (ay - ay_f) / bo.load_tau

    # wheels: brakes and rolling resistance oppose the rotation (smooth sign)
    pt = p.powertrain
    brake = ca.fmax(u[UP.BRAKE], 0.0)
    brake_w = (0.5 * pt.brake_balance * brake,) * 2 + (0.5 * (1.0 - pt.brake_balance) * brake,) * 2
    resist = []
    for i, name in enumerate(WHEELS):
        omega, fx, F_z = out.pop(f'_wheel_{name}')
        sign = ca.tanh(omega / wh.omega_eps)
        resist.append(fx * radius[i] + (brake_w[i] + bo.c_roll * F_z * radius[i]) * sign)
    x_dot[S.OMEGA_FL] = -resist[0] / wh.I_wF
    x_dot[S.OMEGA_FR] = -resist[1] / wh.I_wF
    # rear: the carrier (mean speed) carries the driveline inertia; the LSD acts on the difference
    w_L, w_R = x[S.OMEGA_RL], x[S.OMEGA_RR]
    # engine braking (a negative drive torque) resists the carrier's rotation, never reverses it
    T = axle_torque(x[S.T_DRIVE], 0.5 * (w_L + w_R), wh.omega_eps)
    cap = q[PP.LOCKING] * ca.sqrt(T * T + 1.0) + p.lsd.preload + 1.0
    T_lock = _sat(p.lsd.viscous * (w_L - w_R), cap)
    mean_dot = (T - resist[2] - resist[3]) / (2.0 * wh.I_wR + wh.I_drive)
    diff_dot = (-T_lock - resist[2] + resist[3]) / wh.I_wR
    x_dot[S.OMEGA_RL] = mean_dot + 0.5 * diff_dot
    x_dot[S.OMEGA_RR] = mean_dot - 0.5 * diff_dot
    x_dot[S.T_DRIVE] = (ca.fmin(ca.fmax(u[UP.T_REQ], pt.T_min), pt.T_max) - x[S.T_DRIVE]) / pt.tau

    # steering: rate-limited reference, PD position loop saturated at the actuator torque
    delta_cmd = ca.fmin(ca.fmax(u[UP.DELTA_CMD], -st.delta_max), st.delta_max)
    ref_rate = u[UP.DELTA_RATE_CMD] + 4.0 * st.bandwidth * (delta_cmd - x[S.DELTA_REF])
    x_dot[S.DELTA_REF] = _sat(ref_rate, st.rate_max)
    # PID position loop (poles near -w_n), integral with back-calculation anti-windup
    w_n = 2.0 * np.pi * st.bandwidth
    error = x[S.DELTA_REF] - delta
    T_pid = st.J * (2.0 * w_n * w_n * error + 2.0 * w_n * (x_dot[S.DELTA_REF] - x[S.DELTA_DOT])
                    + w_n ** 3 * x[S.DELTA_INT])
    T_act = _sat(T_pid, u[UP.STEER_TORQUE_MAX] + 1e-3)
    x_dot[S.DELTA_INT] = error - (T_pid - T_act) / (st.J * w_n ** 3 * 0.05)
    # end stop: a stiff spring beyond delta_max
    stop = 2e5 * (ca.fmax(delta - st.delta_max - 0.02, 0.0) + ca.fmin(delta + st.delta_max + 0.02,
                                                                     0.0))
    x_dot[S.DELTA] = x[S.DELTA_DOT]
    x_dot[S.DELTA_DOT] = (T_act - M_align - st.c * x[S.DELTA_DOT] - stop) / st.J

    out.update(AX=ax, AY=ay, STEER_TORQUE=T_act / st.ratio, M_ALIGN=M_align,
               MU=friction(x[S.X], x[S.Y], q[PP.MU], q[PP.VARIATION], modes))
    return ca.vertcat(*x_dot), ca.vertcat(*(out[k.name] for k in Y))


class PlantModel:
    """The plant's casadi Functions.

    Attributes
    ----------
    f : casadi.Function
        ``f(x, u, q) -> (x_dot, y)``.
    step : casadi.Function
        ``step(x0, U, q) -> (X, Ys)``: ``substeps`` RK4 steps of ``dt``; ``U`` is (NUP, substeps),
        one input column per step; ``X`` and ``Ys`` hold the state and outputs after each step.
    """

    def __init__(self, p: PlantParams, jit: bool | None = None):
        self.p = p
        x = ca.SX.sym('x', NS)
        u = ca.SX.sym('u', NUP)
        q = ca.SX.sym('q', n_params(p))
        x_dot, y = rhs(x, u, q, p)
        self.f = ca.Function('plant_f', [x, u, q], [x_dot, y], ['x', 'u', 'q'], ['x_dot', 'y'])
        h = p.dt
        k1 = x_dot
        k2 = self.f(x + h / 2 * k1, u, q)[0]
        k3 = self.f(x + h / 2 * k2, u, q)[0]
        k4 = self.f(x + h * k3, u, q)[0]
        x_next = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        rk4 = ca.Function('plant_rk4', [x, u, q], [x_next, self.f(x_next, u, q)[1]])
        self.step = rk4.mapaccum('plant_step', p.substeps, [0], [0])
        if jit is None:
            jit = os.environ.get('DRIFT_SIM_JIT', '1') != '0'
        #: the same ``step`` compiled, called on its own buffers (``Plant`` uses it); None:
        #: interpreted (no gcc, or ``DRIFT_SIM_JIT=0``)
        self.compiled = _compile(self.step) if jit else None
        self.jit = self.compiled is not None


def _compile(fun: ca.Function) -> CompiledFunction | None:
    """``fun`` as C built by gcc, cached by the hash of its source beside the NMPC's (``.codegen``
    under ``cache_dir()``, else the temporary directory); None (interpreted) when that fails."""
    for cache in (cache_dir() / '.codegen', Path(tempfile.gettempdir()) / 'drift_codegen'):
        so = build_cached(fun, fun.name(), cache)
        if so is not None:
            return CompiledFunction(so, fun)
    _log.warning('plant: compilation failed; using the interpreted function')
    return None

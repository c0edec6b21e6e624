"""The NMPC's optimal control problem (paper section IV, Eq. 5): parameters, NLP and bounds.

Multiple shooting on the vehicle states of the single-track model (``vehicle.rhs``, RK4 with
substeps per stage). Path following is the reference selector's job (the paper's); with
``cost.e_y`` a second OCP's state also carries the path states (heading error, lateral error and
the path's curvature, whose change to each next stage is a parameter) and weighs the lateral
error: the NMPC solves that one while the lateral error weighs (``Nmpc``).
The OCP state adds two torques: ``T_act``, the drive torque at the wheels, which follows the
request ``T_R`` with the powertrain lag ``torque_lag`` (the car's engine lag and request delay;
with 0 it is the request itself), and ``T_last``, the request of the previous stage
(``T_last+ = T_R``), so the torque-rate penalty stays stage-wise and the QP keeps the OCP block
structure HPIPM needs. Decision vector, stage-interleaved for the structure-exploiting solvers::

    w = [x_0, u_0, x_1, u_1, ..., x_{N-1}, u_{N-1}, x_N]
    x = (V, beta, r, omega_F, omega_R, delta, T_act, T_last[, psi, e_y, K]),  u = (delta_dot, T_R)

``x_0`` is fixed through its bounds (``lbw = ubw``). Runtime parameters ``p = [ref_0 .. ref_N,
mu, d, flip, slow[, dK_0 .. dK_N-1, e_y_0], lag]`` (``d``: model error added per stage, for
offset-free tracking; ``flip``: 1 while the reference flips sides, weighing the rear wheel speed
as ``cost.omega_R_flip``; ``slow``: 1 while a drift's reference slows down, weighing the speed
as ``cost.V_slow``; with the path states ``dK``, the path's change of curvature to each next
stage, and ``e_y_0``, the car's lateral error; ``lag``, the powertrain's lag), so one
compiled solver serves every reference, surface, mode and powertrain. Every cost term is a
squared residual ``(error / scale)^2``: the Gauss-Newton RTI solver uses the residual vector.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, NamedTuple

import casadi as ca
import numpy as np

from drift_control.params import (ParamError, VehicleParams, config_dir, from_dict, load_yaml,
                                   require)
from drift_control.lag_learning import LagLearningParams
from drift_control.plausibility import InputLimits
from drift_control.vehicle import N_VEHICLE, NTHETA, NU, U, X, VehicleModel, rk4_step

NXO = N_VEHICLE            # vehicle states in the OCP: V, beta, r, omega_F, omega_R, delta
S_T_ACT = NXO              # index of T_act (torque at the wheels) in an OCP state
S_T_LAST = NXO + 1         # index of T_last (previous torque request)
NS = NXO + 2               # OCP state size without the path states
S_PSI, S_E_Y, S_K = NS, NS + 1, NS + 2   # path states, with ``cost.e_y``: heading error, lateral
                                         # error and the path's curvature at the car
NPATH = 3                  # path states
NREF = 7                   # one Equilibrium: V, beta, r, omega_F, omega_R, delta, T_R
REF_T_R = 6                # index of T_R in one reference row


@dataclass(frozen=True)
class CostScales:
    """Error of unit cost for each term; each stage cost term is ``(error / scale)^2``.

    A smaller scale weighs a term more. State errors are to the equilibrium reference. With a
    ``torque_range``, the torque scales are for a car of that torque range and another car's
    scale with its own (``torque``): a car with less torque is then charged the same per share
    of its range. 0: the torque scales in Nm for every car.
    """

    V: float = 3.0              # speed [m/s]
    beta: float = 0.01          # sideslip [rad]
    r: float = 0.02             # yaw rate [rad/s]
    omega_F: float = 20.0       # front wheel speed [rad/s]
    omega_R: float = 10.0       # rear wheel speed [rad/s]
    delta: float = 0.3          # steering angle [rad] (weak pull to the equilibrium steering)
    T_R: float = 3000.0         # drive torque to the equilibrium torque [Nm] (regularisation)
    delta_dot: float = 0.5      # steering rate [rad/s]
    T_R_rate: float = 20000.0   # drive torque rate [Nm/s]
    omega_R_flip: float = 0.0   # rear wheel speed while the reference flips sides [rad/s];
                                # 0: omega_R throughout
    V_slow: float = 0.0         # speed while a drift's reference slows down [m/s]; 0: V throughout
    e_y: float = 0.0            # lateral error to the path [m]; 0: no path states in the OCP
    e_y_time: float = 0.0       # ... asked to decay from the car's with this time constant [s];
                                # 0: to vanish at once
    e_y_after_flip: float = 0.0  # ... weighed only in a flip and this long after it [s]; 0:
                                # throughout the drift
    terminal_factor: float = 5.0   # terminal state cost = factor x stage state cost [-]
    torque_range: float = 0.0   # T_R_max - T_R_min the torque scales are set for [Nm]; 0: none

    def __post_init__(self):
        for name, value in self.__dict__.items():
            if name not in ('torque_range', 'omega_R_flip', 'V_slow', 'e_y', 'e_y_time',
                            'e_y_after_flip'):
                require(value > 0, f'nmpc.cost.{name}', f'must be positive, got {value}')
        require(self.torque_range >= 0, 'nmpc.cost.torque_range', 'must be >= 0 (0: off)')
        require(self.e_y >= 0, 'nmpc.cost.e_y', 'must be >= 0 (0: off)')
        require(self.e_y_time >= 0, 'nmpc.cost.e_y_time', 'must be >= 0 (0: at once)')
        require(self.e_y_after_flip >= 0, 'nmpc.cost.e_y_after_flip',
                'must be >= 0 (0: throughout the drift)')
        require(self.omega_R_flip == 0 or 0 < self.omega_R_flip < self.omega_R,
                'nmpc.cost.omega_R_flip', 'must be 0 (off) or in (0, omega_R): a heavier weight')
        require(self.V_slow == 0 or 0 < self.V_slow < self.V,
                'nmpc.cost.V_slow', 'must be 0 (off) or in (0, V): a heavier weight')

    def flip_extra(self) -> float:
        """Weight of the extra rear-wheel residual that makes ``omega_R`` weigh as
        ``omega_R_flip`` in a flip (0: off): ``1/omega_R_flip^2 = 1/omega_R^2 + extra^2``."""
        if self.omega_R_flip == 0:
            return 0.0
        return math.sqrt(self.omega_R_flip ** -2 - self.omega_R ** -2)

    def slow_extra(self) -> float:
        """Weight of the extra speed residual that makes ``V`` weigh as ``V_slow`` while the
        reference slows down (0: off), as ``flip_extra``."""
        if self.V_slow == 0:
            return 0.0
        return math.sqrt(self.V_slow ** -2 - self.V ** -2)

    def torque(self, bounds: 'Bounds') -> tuple[float, float]:
        """The scales (T_R [Nm], T_R_rate [Nm/s]) for a car with the torque ``bounds``."""
        if self.torque_range == 0.0:
            return self.T_R, self.T_R_rate
        share = (bounds.T_R_max - bounds.T_R_min) / self.torque_range
        return self.T_R * share, self.T_R_rate * share


@dataclass(frozen=True)
class NmpcLimits:
    """Optional tighter bounds than ``VehicleParams.limits``; the tighter of the two is used."""

    delta_max: float = math.inf       # [rad]
    delta_dot_max: float = math.inf   # [rad/s]
    T_R_min: float = -math.inf        # [Nm]
    T_R_max: float = math.inf         # [Nm]


@dataclass(frozen=True)
class SolverParams:
    """Which solver runs the OCP, and how.

    ``method``: 'rti' = Gauss-Newton SQP with ``max_iter`` QPs per step (1 = real-time
    iteration), QP solver ``qp_solver``; 'sqp' = casadi sqpmethod (exact Hessian) with
    ``qp_solver``; 'ipopt'; 'fatrop'. ``codegen``: compile the problem's functions with gcc,
    cached under ``codegen_dir`` (relative to the repository), interpreted when gcc is missing.
    ``hpipm_mode``: HPIPM's option preset (its interior-point formulation and safeguards).
    ``warm_start``: each step starts from the last solution 'shifted' by one control period
    (states linear between stages, inputs held, when a stage is longer) or from it as it was
    ('previous'), the real-time iteration continuing on a slowly moving problem.
    """

    method: Literal['rti', 'sqp', 'ipopt', 'fatrop'] = 'rti'
    qp_solver: Literal['qrqp', 'osqp', 'hpipm', 'qpoases'] = 'hpipm'
    hpipm_mode: Literal['speed_abs', 'speed', 'balance', 'robust'] = 'balance'   # HPIPM's preset
    max_iter: int = 1              # SQP / GN iterations per control step
    cold_start_iter: int = 10      # iterations of the first solve (no warm start yet)
    warm_start: Literal['shifted', 'previous'] = 'shifted'   # the last solution moved on by one
                                   # control period, or as it was
    tol: float = 1e-6              # NLP tolerance (sqp, ipopt, fatrop) / GN step norm (rti)
    codegen: bool = True
    codegen_dir: str = '.codegen'
    gcc_flags: tuple[str, ...] = ('-O2',)

    def __post_init__(self):
        require(self.max_iter >= 1, 'nmpc.solver.max_iter', 'must be >= 1')
        require(self.cold_start_iter >= 1, 'nmpc.solver.cold_start_iter', 'must be >= 1')


@dataclass(frozen=True)
class NmpcParams:
    """Everything the NMPC reads from ``config/nmpc.yaml``."""

    N: int = 25                     # stages [-]
    Ts: float = 0.02                # control period [s]
    stage_dt: float = 0.0           # stage length [s]; 0: the control period
    substeps: int = 2               # RK4 substeps per stage [-]
    front_wheel: Literal['dynamic', 'free_rolling'] = 'free_rolling'
    load_passes: int = 1            # quasi-static load transfer passes of the model [-]
    cost: CostScales = field(default_factory=CostScales)
    limits: NmpcLimits = field(default_factory=NmpcLimits)
    solver: SolverParams = field(default_factory=SolverParams)
    max_input_age: float = 0.05     # state / reference older than this are stale [s]
    max_failures: int = 3           # consecutive failures served by the shifted plan [-]
    fallback_torque_rate: float = 3000.0   # torque ramp-down rate in fallback [Nm/s]
    fallback_delta_rate: float = 0.3       # steering rate toward the reference delta [rad/s]
    fallback_trip_slip: float = 0.1        # after a trip: engine braking while the rear wheels
                                           # spin this much faster than the ground [-]
    torque_only_hold_stages: int = 1       # TORQUE_ONLY: stages the driver is assumed to hold
    torque_lag: float = 0.0         # powertrain: first-order lag of the drive torque [s]; 0: none
    disturbance_gain: float = 0.0   # offset-free: share of the prediction error taken per step
    disturbance_decay: float = 0.1  # share of d dropped per step where it is not learnt
    disturbance_max: tuple[float, ...] = (0.05, 0.01, 0.01, 1.0, 1.0, 0.0)   # |d| per period
    disturbance_beta_band: float = 0.05   # learn d only within this of the beta reference [rad]
    disturbance_min_beta: float = 0.2     # ... of a drift reference (|beta_ref| above) [rad]
    inputs: InputLimits = field(default_factory=InputLimits)   # plausible measured states
    brake_speed_ratio: tuple[float, float] = (0.0, 0.0)   # V / V_ref: no braking torque below
                                    # the first, the full braking bound above the second (off: 0)
    front_slip_max: float = 0.0     # the plan's steering keeps the front slip angle within
                                    # this many times the model's front peak slip (0: off)
    rear_lock_slip: float = 0.0     # the plan brakes the rear wheel to at most this
                                    # longitudinal slip, kappa >= -this (0: off)
    torque_lag_learning: LagLearningParams = field(default_factory=LagLearningParams)
    state_age: tuple[float, ...] = (0.0,) * NXO   # how old each measured state is at its
                                    # stamp, V .. delta [s]: predicted on before the plan

    def __post_init__(self):
        require(self.N >= 2, 'nmpc.N', 'must be >= 2')
        require(self.Ts > 0, 'nmpc.Ts', 'must be positive')
        require(self.stage_dt == 0 or self.stage_dt >= self.Ts, 'nmpc.stage_dt',
                'must be 0 (the control period) or at least the control period Ts')
        require(self.substeps >= 1, 'nmpc.substeps', 'must be >= 1')
        require(self.max_input_age > 0, 'nmpc.max_input_age', 'must be positive')
        require(self.max_failures >= 0, 'nmpc.max_failures', 'must be >= 0')
        require(self.fallback_torque_rate > 0 and self.fallback_delta_rate > 0, 'nmpc.fallback_*',
                'rates must be positive')
        require(self.fallback_trip_slip > 0, 'nmpc.fallback_trip_slip', 'must be positive')
        require(0 <= self.torque_only_hold_stages < self.N, 'nmpc.torque_only_hold_stages',
                'must be in [0, N)')
        require(self.torque_lag >= 0, 'nmpc.torque_lag', 'must be >= 0')
        require(self.front_slip_max >= 0, 'nmpc.front_slip_max', 'must be >= 0 (0: off)')
        require(0 <= self.rear_lock_slip < 1, 'nmpc.rear_lock_slip', 'must be in [0, 1) (0: off)')
        low, high = self.brake_speed_ratio if len(self.brake_speed_ratio) == 2 else (-1, -1)
        require(0 <= low <= high, 'nmpc.brake_speed_ratio',
                'must be [low, high] with 0 <= low <= high ([0, 0]: off)')
        require(0 <= self.disturbance_gain <= 1, 'nmpc.disturbance_gain', 'must be in [0, 1]')
        require(0 <= self.disturbance_decay <= 1, 'nmpc.disturbance_decay', 'must be in [0, 1]')
        require(len(self.disturbance_max) == NXO and min(self.disturbance_max) >= 0,
                'nmpc.disturbance_max', f'must be {NXO} values >= 0 (V .. delta)')
        require(len(self.state_age) == NXO
                and all(0 <= a < self.max_input_age for a in self.state_age), 'nmpc.state_age',
                f'must be {NXO} values in [0, max_input_age) (V .. delta)')

    @property
    def dt(self) -> float:
        """Length of one predicted stage [s]."""
        return self.stage_dt or self.Ts


def load_nmpc_params(path=None) -> NmpcParams:
    """Load ``config/nmpc.yaml`` (or ``path``); a wrong key is a ParamError naming it."""
    path = Path(path) if path else config_dir() / 'nmpc.yaml'
    return from_dict(NmpcParams, load_yaml(path), path.stem)


def for_vehicle(params: NmpcParams, vehicle: VehicleParams) -> NmpcParams:
    """``params`` with the car's own powertrain lag where its file gives one (an identified
    car's ``torque_lag``); else ``nmpc.torque_lag`` stands."""
    if vehicle.torque_lag is None or vehicle.torque_lag == params.torque_lag:
        return params
    return replace(params, torque_lag=vehicle.torque_lag)


class Bounds(NamedTuple):
    """Effective actuator bounds: the tighter of vehicle and NMPC limits."""

    delta_max: float
    delta_dot_max: float
    T_R_min: float
    T_R_max: float


def effective_bounds(vehicle: VehicleParams, params: NmpcParams) -> Bounds:
    """Tighter of ``vehicle.limits`` and ``params.limits``."""
    v, n = vehicle.limits, params.limits
    b = Bounds(min(v.delta_max, n.delta_max), min(v.delta_dot_max, n.delta_dot_max),
               max(v.T_R_min, n.T_R_min), min(v.T_R_max, n.T_R_max))
    if not b.T_R_min < b.T_R_max:
        raise ParamError(f'nmpc.limits: empty torque range [{b.T_R_min}, {b.T_R_max}]')
    return b


class OcpParams(NamedTuple):
    """The runtime parameters ``p`` of an ``Ocp``, unpacked (symbolic or numeric)."""

    refs: list          # reference row of each stage 0 .. N
    mu: object          # surface friction
    d: object           # model error per stage (V .. delta)
    flip: object        # 1 while the reference flips sides
    slow: object        # 1 while a drift's reference slows down
    dK: object          # the path's change of curvature per stage (N; empty without path states)
    e_y_0: object       # the car's lateral error, from which the one asked decays [m] (0 without)
    lag: object         # the powertrain's lag [s] (with ``torque_lag``; else unused)


class Ocp:
    """The multiple-shooting NLP as casadi SX expressions, plus packing and bounds helpers.

    Attributes
    ----------
    w, p : casadi.SX
        Decision and parameter vectors.
    residual : casadi.SX
        Cost residuals; the objective is ``J = sum(residual**2)``.
    J : casadi.SX
        Objective. The equality constraints are ``gaps(w, p) = 0``.
    F : casadi.Function
        One shooting stage (``stage_dt``), RK4 with ``substeps`` on ``vehicle.rhs``.
    F_period : casadi.Function
        One control period (``Ts``) in RK4 steps no longer than the stage's: where the next
        measured state should be (the model-error estimate compares against it).
    """

    def __init__(self, vehicle: VehicleParams, params: NmpcParams, path: bool | None = None):
        params = for_vehicle(params, vehicle)
        self.vehicle, self.params = vehicle, params
        self.bounds = effective_bounds(vehicle, params)
        #: the path states (heading error, lateral error, curvature) are in the OCP; ``path``
        #: None: with ``cost.e_y``
        self.path = params.cost.e_y > 0 if path is None else bool(path)
        if self.path and params.cost.e_y == 0:
            raise ValueError('path states need nmpc.cost.e_y > 0 (the lateral error scale)')
        #: OCP state size
        self.ns = ns = NS + NPATH if self.path else NS
        N, nz = params.N, ns + NU
        self.N, self.nw = N, N * nz + ns
        self.np = (N + 1) * NREF + 1 + NXO + 2 + (N + 1 if self.path else 0) + 1
        model = VehicleModel(vehicle, params.load_passes, params.front_wheel)
        self.model = model
        xs, us, mu_s = ca.SX.sym('x', ns), ca.SX.sym('u', NU), ca.SX.sym('mu')
        # the OCP integrates the first N_VEHICLE model states (path states do not feed back: they
        # are held at zero) and, with a powertrain lag, the torque at the wheels. The lag is a
        # runtime parameter (``lag_s``, the model's theta plus one): a lag learnt on the car
        # (``Nmpc``, ``torque_lag_learning``) needs no new solver
        lag, lag_s = params.torque_lag, ca.SX.sym('lag')
        x7, u_req = ca.SX.sym('x7', NXO + 1), ca.SX.sym('u', NU)
        th = ca.SX.sym('theta', NTHETA + 1)
        x9 = ca.vertcat(x7[:NXO], ca.SX.zeros(len(X) - NXO))
        T_act = x7[NXO]
        u_wheel = ca.vertcat(u_req[U.DELTA_DOT], T_act if lag > 0 else u_req[U.T_R])
        T_dot = (u_req[U.T_R] - T_act) / th[NTHETA] if lag > 0 else 0.0
        f7 = ca.Function('f7', [x7, u_req, th],
                         [ca.vertcat(model.f(x9, u_wheel, th[:NTHETA])[:NXO], T_dot)])
        theta = ca.vertcat(0.0, mu_s, lag_s)   # curvature unused: no path states in the OCP
        #: the model's time derivative, ``f_state(x, u, mu, lag)``: x the vehicle states V ..
        #: delta and the torque at the wheels, u the requests (steering rate, torque)
        self.f_state = ca.Function('f_state', [x7, u_req, mu_s, lag_s], [f7(x7, u_req, theta)],
                                   ['x', 'u', 'mu', 'lag'], ['x_dot'])
        x_end = rk4_step(f7, xs[:NXO + 1], us, theta, params.dt, params.substeps)
        T_act_end = x_end[NXO] if lag > 0 else us[U.T_R]
        x_next = ca.vertcat(x_end[:NXO], T_act_end, us[U.T_R])
        if self.path:   # the same stage with the heading and lateral errors on a path whose
            # curvature is the state K (held over the stage; the next stage's comes from p)
            x10 = ca.SX.sym('x10', NXO + 3)
            x9p = ca.vertcat(x10[:NXO], x10[NXO + 1:], 0.0)
            dx = model.f(x9p, ca.vertcat(u_req[U.DELTA_DOT], x10[NXO] if lag > 0
                                         else u_req[U.T_R]), th[:NTHETA])
            T_dot10 = (u_req[U.T_R] - x10[NXO]) / th[NTHETA] if lag > 0 else 0.0
            f10 = ca.Function('f10', [x10, u_req, th],
                              [ca.vertcat(dx[:NXO], T_dot10, dx[X.PSI], dx[X.E_Y])])
            start = ca.vertcat(xs[:NXO + 1], xs[S_PSI], xs[S_E_Y])
            x_end = rk4_step(f10, start, us, ca.vertcat(xs[S_K], mu_s, lag_s), params.dt,
                             params.substeps)
            x_next = ca.vertcat(x_end[:NXO], x_end[NXO] if lag > 0 else us[U.T_R], us[U.T_R],
                                x_end[NXO + 1:], xs[S_K])
        #: one stage, ``F(x, u, mu, lag) -> x_next`` on the OCP state (T_last+ = T_R), ``lag``
        #: the powertrain's [s] (unused without ``torque_lag``)
        self.F = ca.Function('F', [xs, us, mu_s, lag_s], [x_next], ['x', 'u', 'mu', 'lag'],
                             ['x_next'])
        #: with the path states, ``path_rollout(X, U, path_0, K, mu, lag) -> (NPATH, N+1)``: the
        #: path states along a plan's vehicle states and inputs (X (NS, N), U (NU, N)) from
        #: ``path_0``, the curvature of stage k from ``K`` (N+1), as the gaps have them
        self.path_rollout = self._path_rollout() if self.path else None
        # one control period, RK4 steps no longer than the stage's: where the next state should be
        period_steps = max(1, math.ceil(params.substeps * params.Ts / params.dt - 1e-9))
        x_period = rk4_step(f7, xs[:NXO + 1], us, theta, params.Ts, period_steps)
        #: one control period, ``F_period(x, u, mu, lag) -> x`` (vehicle states V .. delta)
        self.F_period = ca.Function('F_period', [xs, us, mu_s, lag_s], [x_period[:NXO]],
                                    ['x', 'u', 'mu', 'lag'], ['x_next'])

        self.w, self.p = ca.SX.sym('w', self.nw), ca.SX.sym('p', self.np)
        refs, _, _, flip, slow, _, e_y_0, _ = self.unpack_params(self.p)
        c = params.cost
        flip_extra, slow_extra = c.flip_extra(), c.slow_extra()
        state_scale = np.array([c.V, c.beta, c.r, c.omega_F, c.omega_R, c.delta])
        T_R_scale, T_R_rate_scale = c.torque(self.bounds)
        # the lateral error asked of stage k: the car's, decayed over k stages
        decay = [math.exp(-k * params.dt / c.e_y_time) if c.e_y_time > 0 else 0.0
                 for k in range(N + 1)]
        res = []
        for k in range(N):   # every residual is linear in w: the GN Hessian depends on p at most
            xk, uk = self.x(self.w, k), self.u(self.w, k)
            res.append(uk[U.DELTA_DOT] / c.delta_dot)
            # stage 0's change comes one control period after T_last, but is scaled by the stage
            # as the others (scaled by the period, wet entries spun more: docs/tuning_log.md)
            res.append((uk[U.T_R] - xk[S_T_LAST]) / (T_R_rate_scale * params.dt))
            res.append((uk[U.T_R] - refs[k][REF_T_R]) / T_R_scale)
            if k > 0:   # x_0 is fixed: its cost is a constant
                res.append((xk[:NXO] - refs[k][:NXO]) / state_scale)
                if flip_extra:
                    res.append(flip * flip_extra * (xk[X.OMEGA_R] - refs[k][X.OMEGA_R]))
                if slow_extra:
                    res.append(slow * slow_extra * (xk[X.V] - refs[k][X.V]))
                if self.path:
                    res.append((xk[S_E_Y] - decay[k] * e_y_0) / c.e_y)
        term = math.sqrt(c.terminal_factor)
        x_N = self.x(self.w, N)
        res.append(term * (x_N[:NXO] - refs[N][:NXO]) / state_scale)
        if flip_extra:
            res.append(term * flip * flip_extra * (x_N[X.OMEGA_R] - refs[N][X.OMEGA_R]))
        if slow_extra:
            res.append(term * slow * slow_extra * (x_N[X.V] - refs[N][X.V]))
        if self.path:
            res.append(term * (x_N[S_E_Y] - decay[N] * e_y_0) / c.e_y)
        self.residual = ca.vertcat(*res)
        self.J = ca.sumsqr(self.residual)

    def _path_rollout(self) -> ca.Function:
        N = self.params.N
        X_v, U_s = ca.SX.sym('X', NS, N), ca.SX.sym('U', NU, N)
        path_0, K, mu = ca.SX.sym('path_0', NPATH), ca.SX.sym('K', N + 1), ca.SX.sym('mu')
        lag = ca.SX.sym('lag')
        rows = [path_0]
        for k in range(N):
            x_next = self.F(ca.vertcat(X_v[:, k], rows[-1]), U_s[:, k], mu, lag)
            rows.append(ca.vertcat(x_next[S_PSI], x_next[S_E_Y], K[k + 1]))
        return ca.Function('path_rollout', [X_v, U_s, path_0, K, mu, lag], [ca.horzcat(*rows)])

    def gaps(self, w, p):
        """Shooting gaps ``F(x_k, u_k, mu) + o_k - x_{k+1}``, k = 0..N-1 (HPIPM's ``A x + B u -
        x+``), ``o_k`` the ``offsets``.

        ``w`` and ``p`` may be SX (the stage is inlined) or MX (one mapped stage function: small
        code).
        """
        ns, nz = self.ns, self.ns + NU
        par = self.unpack_params(p)
        body = ca.reshape(w[:self.N * nz], nz, self.N)
        x_next = self.F.map(self.N)(body[:ns, :], body[ns:, :], par.mu, par.lag) \
            + self.offsets(p)
        x_after = ca.horzcat(body[:ns, 1:], w[self.N * nz:])
        return ca.vec(x_next - x_after)

    def offsets(self, p):
        """(ns, N) what each stage adds to the model's next state: ``d``, the estimated model
        error of one stage (offset-free tracking, ``Nmpc``), and with the path states the path's
        change of curvature to the next stage."""
        _, _, d, _, _, dK, _, _ = self.unpack_params(p)
        if not self.path:
            return ca.repmat(ca.vertcat(d, ca.DM.zeros(NS - NXO)), 1, self.N)
        return ca.vertcat(ca.repmat(ca.vertcat(d, ca.DM.zeros(NS - NXO + NPATH - 1)), 1, self.N),
                          ca.reshape(dK, 1, self.N))

    # --- layout -------------------------------------------------------------------------------
    def state_scale(self) -> np.ndarray:
        """Typical magnitudes of one OCP state (V, beta, r, omega_F, omega_R, delta, T_act, T_last
        and the path states)."""
        scale = np.array([10.0, 0.5, 0.5, 30.0, 30.0, 0.3, 1000.0, 1000.0])
        return np.concatenate([scale, [0.5, 1.0, 0.05]]) if self.path else scale

    def variable_scale(self) -> np.ndarray:
        """Typical magnitudes of every entry of ``w``, for solver scaling."""
        stage = np.concatenate([self.state_scale(), [1.0, 1000.0]])
        return np.concatenate([np.tile(stage, self.N), self.state_scale()])

    def x(self, w, k: int):
        """State of stage ``k`` in ``w`` (symbolic or numeric)."""
        i = k * (self.ns + NU)
        return w[i:i + self.ns]

    def u(self, w, k: int):
        """Input of stage ``k`` in ``w``."""
        i = k * (self.ns + NU) + self.ns
        return w[i:i + NU]

    def split(self, w) -> tuple[np.ndarray, np.ndarray]:
        """Numeric ``w`` -> OCP states (N+1, ns) and inputs (N, 2)."""
        w = np.asarray(w, dtype=float).ravel()
        ns = self.ns
        body = w[:-ns].reshape(self.N, ns + NU)
        return np.vstack([body[:, :ns], w[-ns:]]), body[:, ns:].copy()

    def join(self, states, inputs) -> np.ndarray:
        """OCP states (N+1, ns) and inputs (N, 2) -> ``w``."""
        body = np.hstack([np.asarray(states)[:-1], np.asarray(inputs)])
        return np.concatenate([body.ravel(), np.asarray(states)[-1]])

    def unpack_params(self, p) -> 'OcpParams':
        """``p`` -> ([ref_0 .. ref_N], mu, d, flip, slow, dK, e_y_0, lag); without the path
        states ``dK`` is empty and ``e_y_0`` 0."""
        n = (self.N + 1) * NREF
        refs = [p[k * NREF:(k + 1) * NREF] for k in range(self.N + 1)]
        i = n + 3 + NXO
        dK, e_y_0 = (p[i:i + self.N], p[i + self.N]) if self.path else (p[0:0], 0.0)
        return OcpParams(refs, p[n], p[n + 1:n + 1 + NXO], p[n + 1 + NXO], p[n + 2 + NXO], dK,
                         e_y_0, p[self.np - 1])

    def pack_params(self, refs, mu: float, d=None, flip: bool = False, slow: bool = False,
                    curvature=None, e_y: float = 0.0, lag: float | None = None) -> np.ndarray:
        """Numeric parameter vector.

        Parameters
        ----------
        refs : array (N+1, 7)
            Reference per stage in Equilibrium field order.
        mu : float
            Surface friction [-].
        d : array (6,), optional
            Model error added to each stage's vehicle states (V .. delta); default zero.
        flip : bool
            The reference flips sides: the rear wheel speed weighs as ``cost.omega_R_flip``.
        slow : bool
            A drift's reference slows down: the speed weighs as ``cost.V_slow``.
        curvature : array (N+1,), optional
            The path's curvature at each stage [1/m] (with the path states; default straight).
        e_y : float
            The car's lateral error [m], from which stage k's decays (``cost.e_y_time``).
        lag : float, optional
            The powertrain's lag [s]; default ``torque_lag``.
        """
        refs = np.asarray(refs, dtype=float)
        if refs.shape != (self.N + 1, NREF):
            raise ValueError(f'refs must be ({self.N + 1}, {NREF}), got {refs.shape}')
        d = np.zeros(NXO) if d is None else np.asarray(d, dtype=float)
        parts = [refs.ravel(), [mu], d, [1.0 if flip else 0.0], [1.0 if slow else 0.0]]
        if self.path:
            K = np.zeros(self.N + 1) if curvature is None else np.asarray(curvature, dtype=float)
            parts += [np.diff(K), [e_y]]
        parts.append([self.params.torque_lag if lag is None else lag])
        return np.concatenate(parts)

    def bounds_for(self, x_init, hold_stages: int = 0,
                   T_R_min: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Bounds (lbw, ubw): x_0 fixed to ``x_init`` (all ``ns``); delta, delta_dot, T_R limited.

        ``hold_stages`` first stages get ``delta_dot = 0`` (a driver who holds the wheel);
        ``T_R_min`` raises the lower torque bound of every stage (never above ``T_R_max``).
        """
        b = self.bounds
        if T_R_min is not None:
            b = b._replace(T_R_min=min(max(b.T_R_min, T_R_min), b.T_R_max))
        lb, ub = np.full(self.nw, -np.inf), np.full(self.nw, np.inf)
        ns = self.ns
        nz = ns + NU
        # strided slices: every stage's entry (N + 1 states, N inputs fit in nw = N nz + NS)
        lb[X.DELTA::nz], ub[X.DELTA::nz] = -b.delta_max, b.delta_max
        rate = ns + U.DELTA_DOT
        lb[rate::nz], ub[rate::nz] = -b.delta_dot_max, b.delta_dot_max
        lb[rate:rate + hold_stages * nz:nz] = ub[rate:rate + hold_stages * nz:nz] = 0.0
        lb[ns + U.T_R::nz], ub[ns + U.T_R::nz] = b.T_R_min, b.T_R_max
        lb[:ns] = ub[:ns] = x_init
        return lb, ub

    def clip_initial_state(self, x_init) -> np.ndarray:
        """Measured steering beyond the limit is taken at the limit (keeps the QP feasible)."""
        x = np.array(x_init, dtype=float)
        b = self.bounds
        for i, low, high in ((X.DELTA, -b.delta_max, b.delta_max), (S_T_ACT, b.T_R_min, b.T_R_max),
                             (S_T_LAST, b.T_R_min, b.T_R_max)):
            x[i] = min(max(x[i], low), high)   # np.clip's order, without its call overhead
        return x


__all__ = ['Bounds', 'CostScales', 'NmpcLimits', 'NmpcParams', 'Ocp', 'SolverParams',
           'effective_bounds', 'for_vehicle', 'load_nmpc_params', 'NPATH', 'NREF', 'NS', 'NXO',
           'OcpParams', 'S_E_Y', 'S_K', 'S_PSI', 'S_T_ACT', 'S_T_LAST']

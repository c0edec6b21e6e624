"""The drift NMPC (paper section IV): one OCP solve per control period, safe output always.

``Nmpc.step(state, ref, now)`` turns the latest vehicle state and equilibrium reference into an
actuator command. The OCP and its solvers live in ``ocp.py`` and ``ocp_solvers.py``; this module
owns what happens around a solve: input checks (missing, stale, non-finite, invalid), warm start
by shifting the previous solution, the wheel-torque estimate through the powertrain lag, the
model-error estimate for offset-free tracking (``disturbance_gain``; 0 gives the paper's NMPC),
the shifted plan after a failed solve, and the safe fallback (torque ramped down, steering
rate-limited toward the reference) after repeated failures.
"""
from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass, replace
from enum import IntEnum

import numpy as np

from drift_control.feasibility import equilibrium_problem
from drift_control.lag_learning import LagLearner
from drift_control.ocp import (NREF, NS, NXO, S_T_ACT, S_T_LAST, NmpcParams, Ocp,
                              for_vehicle)
from drift_control.ocp_solvers import make_solver, period_function
from drift_control.pacing import PeriodGate
from drift_control.params import VehicleParams
from drift_control.plausibility import InputChecker
from drift_control.signals import Command, Direction, Mode, Reference, Validity, VehicleState
from drift_control.supervisor import Supervisor, SupervisorParams
from drift_control.tyre import simple_peak_slip
from drift_control.vehicle import NU, U, X, front_axle_course, velocity_rates

log = logging.getLogger(__name__)

STATE_NAMES = ('V', 'beta', 'r', 'omega_F', 'omega_R', 'delta')
INPUT_NAMES = ('delta_dot', 'T_R')
_MIRROR = np.array([1.0, -1.0, -1.0, 1.0, 1.0, -1.0])   # left <-> right: beta, r, delta change sign


def _side_sign(ref: Reference) -> np.ndarray:
    """Per-state factor from a right drift's frame to a left drift's (its own inverse)."""
    return _MIRROR if ref.direction == Direction.RIGHT else np.ones(NXO)


class NmpcStatus(IntEnum):
    """Outcome of one cycle; same values as NmpcStatus.msg ``STATUS_*``."""

    OK = 0          # solved; command from this solution
    SHIFTED = 1     # solve failed or input bad; command from the shifted previous solution
    FALLBACK = 2    # safe fallback active
    NO_INPUT = 3    # nothing to act on yet (no valid state since start): actuators released


@dataclass(frozen=True)
class NmpcResult:
    """What one ``Nmpc.step`` returns; the node publishes status from this, not the solver.

    ``predicted_states`` is (N+1, 6) in ``STATE_NAMES`` order, ``predicted_inputs`` (N, 2) in
    ``INPUT_NAMES`` order; both are empty in fallback.
    """

    command: Command
    solved: bool
    status: NmpcStatus
    solve_time_s: float
    iterations: int
    cost: float
    predicted_states: np.ndarray
    predicted_inputs: np.ndarray
    message: str
    consecutive_failures: int = 0
    stage_dt: float = 0.0   # length of one predicted stage [s]


class Nmpc:
    """Nonlinear MPC that tracks drift equilibria with steering rate and rear drive torque.

    Parameters
    ----------
    vehicle_params : VehicleParams
        The controller's model of the car.
    nmpc_params : NmpcParams
        Horizon, cost, bounds, solver and safety settings (``config/nmpc.yaml``).
    mode : Mode
        ``Mode.FULL`` (steering and torque) or ``Mode.TORQUE_ONLY`` (the driver steers; the
        measured steering is the applied one, ``command.delta`` is the NMPC's proposal).
    mu : float
        Surface friction coefficient [-], a runtime parameter (see ``mu`` attribute).
    supervisor : SupervisorParams, optional
        Watch steering authority and the sideslip envelope; a trip latches the fallback until
        ``reset()`` (see ``drift_control.supervisor``). None: no supervisor.
    stamped : bool
        Each state is what its stamp says (a state estimator's, an exact model's):
        ``nmpc.state_age``, the ages of a measured state (the simulator's, a car gateway's),
        is not predicted on.
    """

    def __init__(self, vehicle_params: VehicleParams, nmpc_params: NmpcParams,
                 mode: Mode = Mode.FULL, mu: float = 1.0,
                 supervisor: SupervisorParams | None = None, stamped: bool = False):
        if mode not in (Mode.FULL, Mode.TORQUE_ONLY):
            raise ValueError(f'mode must be FULL or TORQUE_ONLY, got {mode!r}')
        nmpc_params = for_vehicle(nmpc_params, vehicle_params)
        self.params, self.mode, self.mu = nmpc_params, Mode(mode), float(mu)
        self.ocp = Ocp(vehicle_params, nmpc_params, path=False)
        self.bounds = self.ocp.bounds
        self._solver = make_solver(self.ocp, nmpc_params.solver)
        self._period = period_function(self.ocp, nmpc_params.solver)
        #: with ``cost.e_y`` in FULL mode, the OCP with the path states, solved while the lateral
        #: error weighs (``_drifting``): elsewhere the smaller OCP costs no more than without
        self.path_ocp = Ocp(vehicle_params, nmpc_params, path=True) \
            if nmpc_params.cost.e_y > 0 and mode == Mode.FULL else None
        self._path_solver = make_solver(self.path_ocp, nmpc_params.solver) \
            if self.path_ocp is not None else None
        self._hold = nmpc_params.torque_only_hold_stages if mode == Mode.TORQUE_ONLY else 0
        # the plan's front slip band [rad] and the front axle's distance from the CoG [m]
        self._front_slip = (nmpc_params.front_slip_max
                            * simple_peak_slip(vehicle_params.front_tyre.lateral)
                            if mode == Mode.FULL and nmpc_params.front_slip_max > 0 else 0.0)
        self._a = vehicle_params.a
        self._rear_lock, self._R_R = nmpc_params.rear_lock_slip, vehicle_params.R_R
        # the first stage a torque requested now has reached the wheel (``_rear_floors``)
        self._rear_first = math.ceil(nmpc_params.torque_lag / nmpc_params.dt - 1e-9) + 1
        self.supervisor = Supervisor(supervisor) if supervisor is not None else None
        self.inputs = InputChecker(vehicle_params, nmpc_params.inputs)
        #: the powertrain lag learnt from the requests and the measured torque (with
        #: ``torque_lag_learning.enabled`` and a lag in the OCP); kept over ``reset`` (same car)
        learning = nmpc_params.torque_lag_learning
        self.lag_learner = LagLearner(learning, nmpc_params.Ts, nmpc_params.torque_lag) \
            if learning.enabled and nmpc_params.torque_lag > 0 else None
        self._torque_samples = False   # observe_torque has been fed
        # how old each measured state is (the driver's steering in TORQUE_ONLY: not ours to
        # predict)
        age = np.zeros(NXO) if stamped else np.array(nmpc_params.state_age, dtype=float)
        if mode == Mode.TORQUE_ONLY:
            age[X.DELTA] = 0.0
        self._state_age = age if age.any() else None
        self.reset()

    @property
    def lag(self) -> float:
        """The powertrain lag the plans use [s]: learnt, or ``torque_lag``."""
        return self.lag_learner.lag if self.lag_learner is not None else self.params.torque_lag

    def reset(self) -> None:
        """Forget the previous solution, failures and commands (e.g. on re-engagement)."""
        self._w: np.ndarray | None = None   # last accepted solution
        self._w_ocp = self.ocp               # ... of this OCP (its layout)
        self._age = 0                        # cycles since that solution
        self._failures = 0
        self._last: Command | None = None
        self._engaged = False                # a solve has succeeded since the reset
        self._drifted = False                # a steady drift's horizon seen since the reset
        self._T_act = 0.0                    # modelled torque at the wheels [Nm]
        self._d = np.zeros(NXO)              # model error per control period (offset-free)
        self._x1_pred: np.ndarray | None = None   # the last solve's prediction of this state
        self._to_predict: tuple | None = None   # ... before it is worked out: (x, u, mu, lag, d)
        self._guess: tuple | None = None           # (solution, age, the warm start from it,
                                                   # its front axle courses, rear wheel floors)
        self._flipping = False                     # the reference flips sides (latched)
        self._flip_seen = -math.inf                # a horizon not on one side: when last [s]
        if getattr(self, 'supervisor', None) is not None:
            self.supervisor.reset()
        if getattr(self, 'lag_learner', None) is not None:
            self.lag_learner.interrupt()
        self.inputs.reset()

    @property
    def model_error(self) -> np.ndarray:
        """The learnt model error per control period, in a left drift's frame (V .. delta)."""
        return self._d.copy()

    # --- one cycle -----------------------------------------------------------------------------
    def step(self, state: VehicleState | None, ref: Reference | None, now: float) -> NmpcResult:
        """One control cycle at time ``now`` [s] (the clock of the state and reference stamps).

        A state that is missing, non-finite, invalid, stale, from the future or implausible gives
        the fallback in this cycle (no plan is served without a measurement to confirm it); a
        reference problem or a solver failure serves the shifted plan for up to
        ``max_failures`` cycles first. The next good state is solved from a cold start.
        """
        state_problem = self._state_problem(state, now)
        learner = self.lag_learner
        if learner is not None:   # a fit not prepared, then the state's torque if measured
            learner.update()
            if state_problem is None and not self._torque_samples \
                    and state.has(Validity.DRIVE_TORQUE):
                learner.measure(state.stamp - learner.params.signal_delay, state.drive_torque)
        ref_problem = self._reference_problem(ref, now) if state_problem is None else None
        tripped = self.supervisor.check(state, ref, self._last, now) \
            if self.supervisor is not None and self._engaged else None
        if tripped is not None:   # latched: no more solving into a car that does not follow
            result = self._fallback(state, ref, now, f'supervisor: {tripped}', 0.0, 0,
                                    tripped=True)
        elif state_problem is not None:
            result = self._failed(state, ref, now, state_problem, solve_time=0.0, iterations=0,
                                  shift=False)
        elif ref_problem is not None:
            result = self._failed(state, ref, now, ref_problem, solve_time=0.0, iterations=0)
        else:   # a reference selected for an older state: its stages from now on
            result = self._solve(state, ref.at(now, self.params.dt), now)
        self._last = result.command
        self._T_act = self._propagate_torque(result.command.drive_torque, state)
        if learner is not None:   # the NMPC's own requests at speed, nothing else
            if result.status in (NmpcStatus.OK, NmpcStatus.SHIFTED) and state_problem is None \
                    and state.V >= learner.params.speed_min:
                learner.request(now, result.command.drive_torque)
            else:
                learner.interrupt()
        return replace(result, stage_dt=self.params.dt)

    def observe_torque(self, stamp: float, torque: float) -> None:
        """A drive torque sample at the wheels [Nm] of instant ``stamp`` [s] (the torque
        unit's, as the estimator took it): from the first on, the lag is learnt from these
        instead of the state's drive torque. Nothing without lag learning."""
        if self.lag_learner is not None:
            self._torque_samples = True
            self.lag_learner.measure(stamp, torque)

    def prepare(self) -> None:
        """Do the next cycle's work that needs no measurement now, once the command is out:
        the one-period prediction and the model's linearisation along the warm start (the
        real-time iteration's preparation phase). Optional: ``step`` does whatever was not
        prepared, and its command is the same bit for bit either way."""
        self._predict()
        if self.lag_learner is not None:
            self.lag_learner.update()
        if self._w is None:
            return
        solver = self._path_solver if self._w_ocp is self.path_ocp else self._solver
        try:   # the OCP solved last (the next cycle's, unless the lateral error starts or stops)
            solver.prepare(self._warm_guess(), self.mu, self.lag)
        except Exception as err:   # never the node's end: the next step linearises itself
            log.warning('NMPC preparation failed (%s: %s); the next step does all its work',
                        type(err).__name__, err)

    def _propagate_torque(self, request: float, state) -> float:
        """Wheel torque after one period of ``request`` through the powertrain lag (exact)."""
        lag = self.lag
        if lag <= 0.0:
            return request
        start = self._T_act if self._engaged else (
            state.drive_torque if state is not None and state.has(Validity.DRIVE_TORQUE)
            and math.isfinite(state.drive_torque) else request)
        return start + (1.0 - math.exp(-self.params.Ts / lag)) * (request - start)

    def _state_problem(self, state, now) -> str | None:
        """Why the measured state cannot be used, or None."""
        age = self.params.max_input_age
        if state is None:
            return 'no vehicle state'
        if not state.is_finite():
            return 'vehicle state not finite'
        if not state.has(Validity.CONTROL):
            return f'vehicle state invalid (validity {state.validity:#x})'
        if now - state.stamp > age:
            return f'vehicle state stale ({now - state.stamp:.3f} s old)'
        if state.stamp - now > age:
            return f'vehicle state from the future ({state.stamp - now:.3f} s ahead)'
        implausible = self.inputs.check(state)
        if implausible is not None:
            return f'implausible vehicle state: {implausible}'
        return None

    def _reference_problem(self, ref, now) -> str | None:
        """Why the reference cannot be used, or None."""
        age = self.params.max_input_age
        if ref is None:
            return 'no reference'
        if not ref.is_finite():
            return 'reference not finite'
        if 0 < len(ref.horizon) < self.params.N:
            return (f'reference horizon of {len(ref.horizon)} stages, the NMPC needs '
                    f'>= {self.params.N}')
        if not abs(now - ref.stamp) <= age:
            return f'reference stale ({now - ref.stamp:.3f} s old)'
        return self._infeasible(ref)

    def _infeasible(self, ref: Reference) -> str | None:
        """Why the reference asks what the car cannot do (steering past lock, torque past its
        limits, no forward speed), or None."""
        for k, eq in enumerate((ref.target, *ref.horizon)):
            problem = equilibrium_problem(eq, self.bounds)
            if problem is not None:
                where = 'target' if k == 0 else f'stage {k - 1}'
                return f'reference infeasible: {where} {problem}'
        return None

    def _solve(self, state: VehicleState, ref: Reference, now: float) -> NmpcResult:
        N = self.params.N
        ocp, solver = self.ocp, self._solver
        if self.path_ocp is not None and self._drifting(ref, now):
            ocp, solver = self.path_ocp, self._path_solver
        measured = state.drive_torque if state.has(Validity.DRIVE_TORQUE) else ref.target.T_R
        T_last = self._last.drive_torque if self._last is not None else measured
        # torque at the wheels: our own lag model of the requests while engaged (it knows the
        # requests still on their way), the measured torque when starting (cold)
        T_act = self._T_act if self._w is not None else measured
        x = [state.V, state.beta, state.r, state.omega_F, state.omega_R, state.delta, T_act,
             T_last]
        if self._state_age is not None and self._last is not None:
            x[:NXO] = self._aged(x[:NXO + 1], state)
        curvature = None
        if ocp.path:   # where the car is on the path, and the path's curvature over the horizon
            curvature = path_curvature(ref, N)
            x += [ref.heading_error, ref.e_y, curvature[0]]
        x_init = ocp.clip_initial_state(x)
        self._T_act = x_init[S_T_ACT]
        self._update_disturbance(x_init, ref)
        d = self._d * _side_sign(ref)   # learnt per control period; a stage may span several
        p = ocp.pack_params(reference_rows(ref, N), self.mu, d * self.params.dt / self.params.Ts,
                            self._flip(ref), self._slow(ref), curvature, ref.e_y, self.lag)
        lbw, ubw = ocp.bounds_for(x_init, self._hold, self._braking_bound(state.V, ref))
        if self._w is None:
            w0, iterations = self._cold_guess(ocp, x_init, ref), self.params.solver.cold_start_iter
        else:
            w0, iterations = self._warm_guess(), self.params.solver.max_iter
            if self._w_ocp is not ocp:
                w0 = self._relayout(w0, ocp, x_init, curvature)
            if self._front_slip > 0.0:
                self._front_slip_band(lbw, ubw, self._guess[3], x_init[X.DELTA], ocp.ns + NU)
            i = X.OMEGA_R
            for floor in self._guess[4]:   # the rear wheel's floors (none when off)
                i += ocp.ns + NU
                lbw[i] = max(lbw[i], floor)
        w0[:ocp.ns] = x_init
        t0 = time.perf_counter()
        try:
            out = solver.solve(w0, p, lbw, ubw, iterations)
            error = None if out.success else f'solver: {out.status}'
        except Exception as err:   # a solver exception is a failed cycle, never a crash
            out, error = None, f'solver raised {type(err).__name__}: {err}'
        solve_time = time.perf_counter() - t0
        if error is None and not np.all(np.isfinite(out.w)):
            error = 'solver returned non-finite values'
        if error is not None:
            return self._failed(state, ref, now, error, solve_time, out.iterations if out else 0)
        self._w, self._w_ocp, self._age, self._failures, self._engaged = out.w, ocp, 0, 0, True
        X_pred, U_pred = ocp.split(out.w)
        # where the next state should be: one control period of the model from this one
        self._to_predict = X_pred[0, :NS].copy(), U_pred[0].copy(), self.mu, self.lag, d
        command = self._command_from_plan(X_pred, U_pred, now)
        return NmpcResult(command, True, NmpcStatus.OK, solve_time, out.iterations, out.cost,
                          X_pred[:, :NXO], U_pred, str(out.status))

    def _aged(self, x, state: VehicleState) -> list[float]:
        """The measured vehicle states V .. delta moved on by their ages (``x``: those states
        and the torque at the wheels): one Euler step each, speed and sideslip at the rates the
        measured accelerations give (the car's own, not the model's tyres), the yaw rate and
        wheels by the model under the torque asked since the last cycle, the steering at the
        rate asked (not at the measured one: fed back into the next command, that derivative
        of a noisy angle around a slow steering actuator sets the torque chattering; a
        steering that does not deliver the asked rate is the supervisor's to catch)."""
        last, u = self._last, np.zeros(NU)
        if math.isfinite(last.delta_rate) and math.isfinite(last.drive_torque):
            u[U.DELTA_DOT], u[U.T_R] = last.delta_rate, last.drive_torque
        else:
            u[U.T_R] = x[NXO]
        x_dot = np.asarray(self.ocp.f_state(x, u, self.mu, self.lag)).ravel()[:NXO]
        if state.has(Validity.AX_AY) and math.hypot(state.ax, state.ay) <= self.ACCEL_MAX:
            x_dot[X.V], x_dot[X.BETA] = velocity_rates(x[X.V], x[X.BETA], x[X.R], state.ax,
                                                       state.ay)
        return list(np.asarray(x[:NXO]) + self._state_age * x_dot)

    ACCEL_MAX = 20.0     # a measured acceleration beyond any tyre's grip [m/s^2]: not used

    FLIP_SIDE = 0.05     # a sideslip reference beyond this [rad] is on one side
    FLIP_STEADY = 0.01   # a flip ends when the horizon's sideslip references are this close [rad]

    def _flip(self, ref: Reference) -> bool:
        """Whether the reference flips sides: from the first horizon with sideslip references
        on both sides until one whose references are a steady drift again. The catch after the
        crossing, when the horizon already holds one side, is part of the flip."""
        if self.params.cost.omega_R_flip == 0.0:
            return False
        betas = [e.beta for e in (ref.horizon or (ref.target,))]
        if max(betas) > self.FLIP_SIDE and min(betas) < -self.FLIP_SIDE:
            self._flipping = True
        elif self._flipping and max(betas) - min(betas) < self.FLIP_STEADY:
            self._flipping = False
        return self._flipping

    def _drifting(self, ref: Reference, now: float) -> bool:
        """Whether the lateral error is weighed: in FULL mode once a horizon of one steady drift
        (one side, one sideslip) has been seen since the reset; with ``cost.e_y_after_flip``
        only while a horizon is not on one side (a flip, or leaving the drift) and that long
        after the last such horizon. The grip phase and the entry ramp are left to the reference
        selector's path following, the path in TORQUE_ONLY to the driver."""
        if self.mode != Mode.FULL:
            return False
        betas = [e.beta for e in ref.horizon or (ref.target,)]
        one_side = min(betas) > self.FLIP_SIDE or max(betas) < -self.FLIP_SIDE
        if not self._drifted:
            self._drifted = one_side and max(betas) - min(betas) < self.FLIP_STEADY
        window = self.params.cost.e_y_after_flip
        if not self._drifted or window == 0.0:
            return self._drifted
        if not one_side:
            self._flip_seen = now
        return now - self._flip_seen <= window

    SLOW_DROP = 0.2   # a drift's reference slows down when its speed falls this much [m/s]

    def _slow(self, ref: Reference) -> bool:
        """Whether a steady drift's reference slows down: one side and one sideslip over the
        whole horizon (not an entry ramp, not a flip) and its speed falling along it (a tighter
        curve ahead). The speed is weighed lightly for the friction the map does not know;
        slowing for a curve it must be followed."""
        if self.params.cost.V_slow == 0.0 or not ref.horizon:
            return False
        betas = [e.beta for e in ref.horizon]
        steady = (min(betas) > self.FLIP_SIDE or max(betas) < -self.FLIP_SIDE) \
            and max(betas) - min(betas) < self.FLIP_STEADY
        return steady and ref.horizon[-1].V < ref.horizon[0].V - self.SLOW_DROP

    def _braking_bound(self, V: float, ref: Reference) -> float | None:
        """Lower torque bound that keeps a slow car from braking itself to a stop.

        In the grip-to-drift entry the OCP can hold the sideslip ramp with engine braking (the
        braked rear axle loses lateral grip) instead of power: within its horizon that
        tracks beta and r, but the car loses speed the whole time, reaches walking pace and
        spins (the entry's most common failure over seeds). Below ``brake_speed_ratio[0]`` of
        the reference speed no braking torque is allowed, above ``[1]`` the full bound, linear
        in between. Not while blending left and right: the blended speed is no equilibrium's.
        In TORQUE_ONLY too: there the NMPC braked in the grip phase, chasing a sideslip it
        cannot reach without the steering (measurements: docs/tuning_log.md).
        """
        low, high = self.params.brake_speed_ratio
        if high <= 0.0 or ref.direction == Direction.NONE or not ref.target.V > 0.0:
            return None
        share = (V / ref.target.V - low) / max(high - low, 1e-9)
        return min(1.0, max(0.0, share)) * self.bounds.T_R_min

    def _front_slip_band(self, lbw, ubw, courses, delta_0: float, nz: int) -> None:
        """Steering bounds of stages 1 .. N that keep the front slip angle within the band.

        Past its peak slip the front tyre's force hardly grows with the steering, and that is
        where its model is least certain: plans that steer on to the lock there (to rotate the
        car or scrub speed) lean on what a plant with another front does not share. The front
        axle's ``courses`` come from the warm start, the real-time iteration's linearisation
        point (``_front_courses``, worked out with it in ``prepare``); each stage's bound is cut
        to what the steering rate can reach from the last, so the QP stays feasible. ``nz``:
        the OCP's stage size.
        """
        lock, band = self.bounds.delta_max, self._front_slip
        step = self.bounds.delta_dot_max * self.params.dt * (1.0 - 1e-6)
        lo = hi = delta_0
        i = X.DELTA
        for course in courses:
            i += nz
            reach_lo, reach_hi = max(lo - step, -lock), min(hi + step, lock)
            lo = max(reach_lo, min(course - band, reach_hi))
            hi = min(reach_hi, max(course + band, reach_lo))
            lbw[i], ubw[i] = lo, hi

    def _front_courses(self, w0) -> tuple[float, ...]:
        """The front axle's course (``vehicle.front_axle_course``) at stages 1 .. N of ``w0``;
        none without the front slip band."""
        if self._front_slip <= 0.0:
            return ()
        nz, a = self._w_ocp.ns + NU, self._a
        return tuple(front_axle_course(w0[i + X.V], w0[i + X.BETA], w0[i + X.R], a)
                     for i in range(nz, (self.params.N + 1) * nz, nz))

    def _rear_floors(self, w0) -> tuple[float, ...]:
        """The rear wheel speed's lower bounds at stages 1 .. N of ``w0`` (its braking slip at
        most ``rear_lock_slip`` of the axle's speed); none when off.

        Engine braking that locks the rear is where the combined-slip tyre model is least like
        a real tyre: a plan that stops an over-rotating entry by locking the rear (the model's
        lateral force holds) meets a plant whose rear slides further. The floors bind from the
        stage a torque requested now has reached the wheel (``torque_lag``): a wheel measured
        below its floor, with braking torque still on its way, could not reach it sooner, and
        the QP would be infeasible.
        """
        if self._rear_lock <= 0.0:
            return ()
        nz, scale = self._w_ocp.ns + NU, (1.0 - self._rear_lock) / self._R_R
        return tuple(scale * w0[k * nz + X.V] * math.cos(w0[k * nz + X.BETA])
                     if k >= self._rear_first else -math.inf for k in range(1, self.params.N + 1))

    # --- warm start and failures -----------------------------------------------------------
    def _cold_guess(self, ocp: Ocp, x_init, ref: Reference) -> np.ndarray:
        """Hold the initial state over the horizon, inputs at the reference torque."""
        N = self.params.N
        T = np.clip(ref.target.T_R, self.bounds.T_R_min, self.bounds.T_R_max)
        states = np.tile(x_init, (N + 1, 1))
        states[1:, S_T_LAST] = states[1:, S_T_ACT] = T
        return ocp.join(states, np.tile([0.0, T], (N, 1)))

    def _relayout(self, w, ocp: Ocp, x_init, curvature) -> np.ndarray:
        """The guess ``w`` (in ``_w_ocp``'s layout) for ``ocp``: without the path states, or
        with them rolled out from the car's along the guess's stages and the path's
        ``curvature`` at each stage (as the gaps would have them)."""
        states, inputs = self._w_ocp.split(w)
        if not ocp.path:
            return ocp.join(states[:, :NS], inputs)
        path = ocp.path_rollout(states[:-1, :NS].T, inputs.T, x_init[NS:], curvature, self.mu,
                                self.lag)
        return ocp.join(np.hstack([states[:, :NS], np.asarray(path).T]), inputs)

    def _warm_guess(self) -> np.ndarray:
        """The next solve's start: the last solution, ``_age`` + 1 periods old (more after
        failed cycles), shifted by that time or as it was (``warm_start``); a new array."""
        w, age = self._w, self._age
        if self._guess is None or self._guess[0] is not w or self._guess[1] != age:
            shift = self._periods_in_stages(age + 1) \
                if self.params.solver.warm_start == 'shifted' else 0.0
            guess = self._shifted(w, shift)
            self._guess = w, age, guess, self._front_courses(guess), self._rear_floors(guess)
        return self._guess[2].copy()

    def _predict(self) -> None:
        """The last solve's prediction of the next measured state, if not yet worked out."""
        if self._to_predict is not None:
            x, u, mu, lag, d = self._to_predict
            self._x1_pred, self._to_predict = self._period(x, u, mu, lag) + d, None

    def next_state(self, state: VehicleState) -> VehicleState | None:
        """The last solve's prediction of ``state`` one control period on (the model's states,
        the pose carried along with the mean yaw rate and course); None without a solve."""
        self._predict()
        x1 = self._x1_pred
        if x1 is None or self._age != 0 or not state.has(Validity.POSE):
            return None
        Ts = self.params.Ts
        V, beta, r = float(x1[X.V]), float(x1[X.BETA]), float(x1[X.R])
        yaw = state.yaw + 0.5 * Ts * (state.r + r)
        course = 0.5 * (state.yaw + state.beta + yaw + beta)
        step = 0.5 * Ts * (state.V + V)
        return replace(state, stamp=state.stamp + Ts, V=V, beta=beta, r=r,
                       x=state.x + step * math.cos(course), y=state.y + step * math.sin(course),
                       yaw=yaw, delta=float(x1[X.DELTA]))

    def _periods_in_stages(self, periods: int) -> float:
        return periods * self.params.Ts / self.params.dt

    def _shifted(self, w, shift: float) -> np.ndarray:
        """The solution ``shift`` stages later, the last stage repeated: states linear between
        stages, inputs held over their stage (as the plan applies them)."""
        ocp = self._w_ocp
        states, inputs = ocp.split(w)
        return ocp.join(_shift_rows(states, shift), _shift_rows(inputs, shift, hold=True))

    def _update_disturbance(self, x_init, ref: Reference) -> None:
        """Offset-free tracking: move ``d`` by a share of the last one-step prediction error.

        ``d`` is learnt only while the reference is a steady drift: one side, sideslip above
        ``disturbance_min_beta`` and the same over the horizon. In grip, along the entry ramp
        and in a flip the model error is large and changes with the state, and a constant
        ``d`` fitted to it spoils the whole horizon's prediction (it stalled the grip-to-drift
        entry): there ``d`` decays by ``disturbance_decay`` per period. It is held while the
        car is further than ``disturbance_beta_band`` from its sideslip reference (no learning
        from a slide). ``d`` is kept for a left drift and mirrored for a right one, so the error
        learnt before a flip serves after it. The gain sets how much of the measurement noise
        reaches ``d``, which the OCP adds at every stage of the horizon. In TORQUE_ONLY it is
        learnt throughout: the driver steers and closes the yaw loop, and the NMPC's torque
        needs the learnt error through the entry (semi_auto_wet stalled with the gate). The
        steering (the driver's in TORQUE_ONLY) is measured, never a model error. Only after a
        cycle whose command came from a fresh solve (the prediction then matches what ran).
        """
        gain, p = self.params.disturbance_gain, self.params
        self._predict()
        if gain <= 0.0 or self._x1_pred is None:
            return
        beta_ref = ref.target.beta
        stages = ref.horizon or (ref.target,)
        always = self.mode == Mode.TORQUE_ONLY
        steady = always or (ref.direction != Direction.NONE
                            and abs(beta_ref) >= p.disturbance_min_beta
                            and max(abs(e.beta - beta_ref) for e in stages) < 1e-3)
        if not steady:
            self._d = (1.0 - p.disturbance_decay) * self._d
        elif always or abs(x_init[X.BETA] - beta_ref) < p.disturbance_beta_band:
            error = (np.asarray(x_init[:NXO]) - self._x1_pred) * _side_sign(ref)
            limit = np.asarray(p.disturbance_max)
            self._d = np.clip(self._d + gain * error, -limit, limit)
        self._x1_pred = None

    def _failed(self, state, ref, now, reason: str, solve_time: float,
                iterations: int, shift: bool = True) -> NmpcResult:
        """A cycle without a usable solution: the shifted plan while it lasts (``shift``), then
        fallback."""
        self._failures += 1
        self._x1_pred = self._to_predict = None
        N = self.params.N
        if shift and self._w is not None and self._failures <= self.params.max_failures \
                and self._periods_in_stages(self._age + 1) < N - self._hold:
            self._age += 1
            X_pred, U_pred = self._w_ocp.split(
                self._shifted(self._w, self._periods_in_stages(self._age)))
            command = self._command_from_plan(X_pred, U_pred, now)
            return NmpcResult(command, False, NmpcStatus.SHIFTED, solve_time, iterations,
                              math.nan, X_pred[:, :NXO], U_pred,
                              f'{reason}; shifted plan ({self._age})', self._failures)
        if not self._engaged:   # never acted: keep the actuators released
            delta = state.delta if state is not None and math.isfinite(state.delta) else 0.0
            command = Command(now, self._clip_delta(delta), 0.0, 0.0, Mode.OFF)
            return NmpcResult(command, False, NmpcStatus.NO_INPUT, solve_time, iterations,
                              math.nan, np.zeros((0, NXO)), np.zeros((0, 2)), reason,
                              self._failures)
        return self._fallback(state, ref, now, reason, solve_time, iterations)

    def _fallback(self, state, ref, now, reason: str, solve_time: float,
                  iterations: int, tripped: bool = False) -> NmpcResult:
        """The safe fallback: torque ramped down, steering rate-limited toward the reference
        (after a supervisor's trip: the drift abandoned, ``_trip_command``)."""
        if self._w is not None:
            log.warning('NMPC fallback: %s', reason)
        self._w = None   # the old plan is no longer a warm start; the next solve starts cold
        if tripped:
            command = self._trip_command(state, now)
        else:
            command = self._fallback_command(ref, now)
        return NmpcResult(command, False, NmpcStatus.FALLBACK, solve_time, iterations, math.nan,
                          np.zeros((0, NXO)), np.zeros((0, 2)), f'fallback: {reason}',
                          self._failures)

    def _fallback_command(self, ref: Reference | None, now: float) -> Command:
        """Torque ramped toward zero, steering rate-limited toward the reference steering.

        The ramp starts from the last command or from the torque the powertrain has delivered
        of it (the modelled lag), whichever is nearer zero: a fallback in the middle of a
        6000 Nm request the wheels have not yet seen must not deliver it. In TORQUE_ONLY mode
        the driver steers: the fallback only ramps the torque down and keeps the mode, so no
        actuator takes the steering from the driver.
        """
        last = self._last
        target = ref.target.delta if ref is not None and ref.is_finite() else last.delta
        T_step = self.params.fallback_torque_rate * self.params.Ts
        start = last.drive_torque
        if math.isfinite(self._T_act) and abs(self._T_act) < abs(start):
            start = self._T_act
        return self._steered_toward(target, start - _clip(start, -T_step, T_step), now)

    def _trip_command(self, state: VehicleState | None, now: float) -> Command:
        """After a supervisor's trip the drift is given up, not continued: the torque off at
        once, engine braking while the rear wheels spin more than ``fallback_trip_slip`` over
        the ground (a spinning wheel has no side grip to give), and the steering rate-limited
        toward the front axle's course (no front slip: the front tyres' aligning moment, which
        a weak steering could not hold, is gone), not toward the drift's counter-steer."""
        torque, target = 0.0, self._last.delta
        if state is not None and state.is_finite():
            target = front_axle_course(state.V, state.beta, state.r, self._a)
            ground = state.V * math.cos(state.beta)
            if state.omega_R * self._R_R - ground > self.params.fallback_trip_slip * max(ground,
                                                                                          1.0):
                torque = self.bounds.T_R_min
        return self._steered_toward(target, torque, now)

    def _steered_toward(self, target: float, torque: float, now: float) -> Command:
        """A fallback command: ``torque``, the steering rate-limited toward ``target`` [rad]
        (``fallback_delta_rate``); in TORQUE_ONLY the driver's steering is left alone."""
        last, Ts = self._last, self.params.Ts
        if self.mode == Mode.TORQUE_ONLY:
            return self._safe(Command(now, last.delta, 0.0, torque, Mode.TORQUE_ONLY))
        limit = self.params.fallback_delta_rate * Ts
        step = _clip(self._clip_delta(target) - last.delta, -limit, limit)
        return self._safe(Command(now, last.delta + step, step / Ts, torque, Mode.FALLBACK))

    # --- output ---------------------------------------------------------------------------------
    def _command_from_plan(self, X_pred, U_pred, now: float) -> Command:
        """Torque of the first stage; steering one control period on (in TORQUE_ONLY the
        proposal, after the stages the driver holds)."""
        k = min(self._hold, self.params.N - 1)
        rate = float(U_pred[k, U.DELTA_DOT])
        return self._safe(Command(now, float(X_pred[k, X.DELTA]) + rate * self.params.Ts, rate,
                                  float(U_pred[0, U.T_R]), self.mode))

    def _clip_delta(self, delta: float) -> float:
        return _clip(delta, -self.bounds.delta_max, self.bounds.delta_max)

    def _safe(self, c: Command) -> Command:
        """Clip to the bounds; a non-finite value is replaced by a safe one (hold, zero)."""
        b = self.bounds
        hold = self._last.delta if self._last is not None else 0.0
        delta = c.delta if math.isfinite(c.delta) else hold
        rate = c.delta_rate if math.isfinite(c.delta_rate) else 0.0
        torque = c.drive_torque if math.isfinite(c.drive_torque) else 0.0
        return Command(c.stamp, self._clip_delta(delta),
                       _clip(rate, -b.delta_dot_max, b.delta_dot_max),
                       _clip(torque, b.T_R_min, b.T_R_max), c.mode)

    @property
    def consecutive_failures(self) -> int:
        """Cycles since the last accepted solution."""
        return self._failures


class LockstepTrigger:
    """When to solve if states, not a timer, drive the NMPC (the simulator's lock-step mode).

    Once per ``period`` of state time (``PeriodGate``): as soon as the reference computed for
    the state that opens the period is in, or ``reference_wait`` (wall clock) later with the
    latest reference, so a missing reference never stalls the loop; a reference node serving
    other states than ours sets the phase from then on. With
    ``first_reference`` the first solve waits for a reference however long it takes: in sim time
    the reference node may still be discovering us (~2.5 s), and the simulator, which waits for
    the command, bounds that wait itself (its startup timeout) - the run then starts the same way
    every time.
    """

    EPS = 1e-3   # stamp tolerance [s]

    def __init__(self, period: float, reference_wait: float = 0.005,
                 first_reference: bool = False):
        self.period, self.reference_wait = period, reference_wait
        self.first_reference = first_reference
        self.gate = PeriodGate(period)
        self._ref_stamp = -math.inf
        self._pending: tuple[float, float] | None = None   # (state stamp, wall time it came)

    def on_state(self, stamp: float, wall: float, clock: float | None = None) -> bool:
        """A state arrived (``clock``: the node's own time [s]); True: solve now."""
        if self._pending is not None and stamp == self._pending[0]:
            return self._ready()   # the same state offered again: the wait goes on, not anew
        if self.gate.due(stamp, clock):
            self._pending = (stamp, wall)
            if self._ref_stamp > stamp + PeriodGate.FUTURE_MAX:   # references of a dead timeline
                self._ref_stamp = -math.inf
        return self._ready()

    def on_reference(self, stamp: float) -> bool:
        """A reference for the state at ``stamp`` arrived; True: solve now."""
        self._ref_stamp = max(self._ref_stamp, stamp)
        return self._ready()

    def poll(self, wall: float) -> bool:
        """True when a due state has waited ``reference_wait`` for its reference."""
        if self.first_reference and self._ref_stamp == -math.inf:
            return False
        return self._pending is not None and wall - self._pending[1] >= self.reference_wait

    @property
    def pending(self) -> bool:
        """Whether a due state waits for its reference."""
        return self._pending is not None

    def fired(self) -> float:
        """The solve for the pending state is done; returns that state's stamp."""
        stamp, before = self._pending[0], self.gate.last
        self.gate.fired(stamp)
        if not self._ready() and before < self._ref_stamp < stamp - self.EPS:
            # the reference node serves the states in between (it started on another one, or
            # lost one): take its phase, at the cost of one short period
            self.gate.fired(self._ref_stamp)
        self._pending = None
        return stamp

    def _ready(self) -> bool:
        return self._pending is not None and self._ref_stamp >= self._pending[0] - self.EPS


def _clip(value: float, low: float, high: float) -> float:
    """``float(np.clip(value, low, high))`` for one number, without numpy's call overhead."""
    return float(low if value < low else high if value > high else value)


def _shift_rows(rows: np.ndarray, shift: float, hold: bool = False) -> np.ndarray:
    """``rows`` (one per stage) ``shift`` stages later, the last repeated; in between linear,
    or with ``hold`` the row of the stage that time falls in (a piecewise-constant input)."""
    low, high, keep, frac = _shift_weights(len(rows) - 1, float(shift))
    if hold:
        return rows[low]
    return keep * rows[low] + frac * rows[high]


@functools.lru_cache(maxsize=64)
def _shift_weights(n: int, shift: float):
    """Rows before and after each shifted stage and their weights (the same few shifts
    every cycle: worked out once)."""
    at = np.minimum(np.arange(n + 1) + shift, n)
    low = np.floor(at + 1e-9).astype(int)
    high = np.minimum(low + 1, n)
    frac = (at - low)[:, None]
    for a in (low, high, frac):
        a.flags.writeable = False   # shared between calls
    keep = 1.0 - frac
    keep.flags.writeable = False
    return low, high, keep, frac


def path_curvature(ref: Reference, N: int) -> np.ndarray:
    """(N+1,) the path's curvature at each stage: ``ref.horizon_curvature`` (padded with its
    last), else ``ref.curvature`` throughout [1/m]."""
    K = ref.horizon_curvature or (ref.curvature,)
    return np.asarray(K, dtype=float)[np.minimum(np.arange(N + 1), len(K) - 1)]


def reference_rows(ref: Reference, N: int) -> np.ndarray:
    """(N+1, 7) reference rows: ``ref.horizon`` per stage (padded with its last), else target."""
    stages = ref.horizon or (ref.target,)
    rows = np.array([[e.V, e.beta, e.r, e.omega_F, e.omega_R, e.delta, e.T_R] for e in stages])
    out = rows[np.minimum(np.arange(N + 1), len(stages) - 1)]
    assert out.shape == (N + 1, NREF)
    return out


__all__ = ['INPUT_NAMES', 'STATE_NAMES', 'LockstepTrigger', 'Nmpc', 'NmpcResult', 'NmpcStatus',
           'path_curvature', 'reference_rows']

"""Steady-state drift equilibria of the single-track model (paper section III, Eq. 3).

For a sideslip ``beta`` and a path radius ``R`` the equilibrium ``x_eq = [V, beta, r, omega_F,
omega_R, delta, T_R]`` makes the first five state derivatives of ``VehicleModel.f`` zero
(``delta_dot = 0`` by construction) with ``r = V / R``. The square system is solved by bounded
nonlinear least squares (scipy ``least_squares``, trust-region reflective, exact CasADi Jacobian)
and polished by Newton steps. The rear wheel enters through its longitudinal slip ``kappa_R``, so
the slip is box-bounded like the speed, the steering angle and the torque (paper: "constraints on
desired velocities, wheel speeds, and wheel slip").

Sign convention: ``radius > 0`` and ``r > 0`` is a LEFT drift with ``beta < 0``; right-hand
equilibria are the mirror images (``Equilibrium.mirrored()``), never a second solve.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from drift_control.params import VehicleParams
from drift_control.signals import Equilibrium
from drift_control.tyre import lateral_peak_slip, longitudinal_peak_slip
from drift_control.vehicle import NX, U, X, VehicleModel, smooth_max

Kind = Literal['grip', 'slight_drift', 'drift']

# Decision vector of the solver: z = [V, omega_F, kappa_R, delta, T_R]; r = V / R and
# omega_R follows from kappa_R (the slip is what we want to bound, not the wheel speed).
Z_V, Z_OMEGA_F, Z_KAPPA_R, Z_DELTA, Z_T_R = range(5)
N_Z = 5
N_RES = 5   # V, beta, r, omega_F, omega_R derivatives

DEFAULT_TOL = 1e-8   # max |x_dot| (scaled, see ``derivative_scale``) of a converged point


@dataclass(frozen=True)
class SolverSettings:
    """Bounds and tolerances of the equilibrium solve (``config/maps.yaml`` ``solver``)."""

    V_min: float = 1.0          # speed bounds [m/s]
    V_max: float = 40.0
    kappa_R_min: float = -0.05  # rear longitudinal slip bounds [-]
    kappa_R_max: float = 3.0
    tol: float = DEFAULT_TOL    # converged when max |scaled x_dot| <= tol [-]
    max_nfev: int = 200         # least-squares function evaluations per point
    newton_steps: int = 6       # polishing Newton steps after least squares


@dataclass(frozen=True)
class EquilibriumSolution:
    """One solved equilibrium with the tyre quantities that classify it.

    Attributes
    ----------
    eq : Equilibrium
        The equilibrium state and inputs (LEFT for ``radius > 0``).
    residual : numpy.ndarray
        Scaled derivatives ``x_dot[:5] / derivative_scale(p)`` at ``eq`` [-].
    converged : bool
        ``max |residual| <= tol`` and the point lies inside the bounds.
    kind : {'grip', 'slight_drift', 'drift'}
        'drift': rear longitudinal slip past its peak; 'slight_drift': rear slip angle past its
        lateral peak, longitudinal slip not; 'grip' otherwise.
    F_xR, F_yF, F_yR : float
        Rear longitudinal, front and rear lateral tyre forces [N].
    kappa_R : float
        Rear longitudinal slip [-].
    alpha_R : float
        Rear slip angle [rad].
    """

    eq: Equilibrium
    residual: np.ndarray
    converged: bool
    kind: Kind
    F_xR: float
    F_yF: float
    F_yR: float
    kappa_R: float
    alpha_R: float


def derivative_scale(p: VehicleParams) -> np.ndarray:
    """Scale of the first five state derivatives, so 1 means "one vehicle weight" of imbalance.

    ``V_dot / g``; ``beta_dot`` in rad/s and ``r_dot`` in rad/s^2 as they are; wheel accelerations
    relative to a longitudinal force of ``m g`` on the wheel (``m g R / I_w``).
    """
    return np.array([p.g, 1.0, 1.0, p.m * p.g * p.R_F / p.I_wF, p.m * p.g * p.R_R / p.I_wR])


class _Problem:
    """CasADi residual and Jacobian of the equilibrium conditions, built once per model."""

    def __init__(self, model: VehicleModel):
        p = model.p
        z = ca.SX.sym('z', N_Z)
        beta, radius, mu = ca.SX.sym('beta'), ca.SX.sym('radius'), ca.SX.sym('mu')
        x = self._state(z, beta, radius, p)
        u = ca.vertcat(0.0, z[Z_T_R])
        theta = ca.vertcat(0.0, mu)
        x_dot = model.f(x, u, theta)[:N_RES] / derivative_scale(p)
        args = [z, beta, radius, mu]
        self.res = ca.Function('eq_res', args, [x_dot])
        self.jac = ca.Function('eq_jac', args, [ca.jacobian(x_dot, z)])
        self.state = ca.Function('eq_state', args, [x])

    @staticmethod
    def _state(z, beta, radius, p: VehicleParams):
        """Full state from the decision vector; omega_R inverts the slip of ``vehicle.slips``."""
        V = z[Z_V]
        v_x = V * ca.cos(beta)
        den_R = smooth_max(v_x, p.v_eps)
        omega_R = (v_x + z[Z_KAPPA_R] * den_R) / p.R_R
        x = [V, beta, V / radius, z[Z_OMEGA_F], omega_R, z[Z_DELTA]] + [0.0] * (NX - 6)
        return ca.vertcat(*x)


_PROBLEMS: 'weakref.WeakKeyDictionary[VehicleModel, _Problem]' = weakref.WeakKeyDictionary()
_DEFAULT_MODELS: dict = {}


def _problem(model: VehicleModel) -> _Problem:
    if model not in _PROBLEMS:
        _PROBLEMS[model] = _Problem(model)
    return _PROBLEMS[model]


def default_model(p: VehicleParams) -> VehicleModel:
    """The (cached) ``VehicleModel(p)`` used when no model is passed."""
    key = id(p)
    entry = _DEFAULT_MODELS.get(key)
    if entry is None or entry[0] is not p:
        entry = (p, VehicleModel(p))
        _DEFAULT_MODELS[key] = entry
    return entry[1]


def initial_guess(beta: float, radius: float, p: VehicleParams, mu: float = 1.0,
                  speed_factor: float = 0.8, kappa_R: float | None = None,
                  delta: float | None = None) -> np.ndarray:
    """A drift-branch starting point: saturated, spinning rear and counter-steer.

    The speed follows from the lateral balance with the rear saturated,
    ``V^2 / R ~ speed_factor mu g``; the rear slip is set past the longitudinal peak and the front
    steers against the turn (``delta`` of the opposite sign to ``r``) once ``|beta|`` is large.
    Returns the solver vector ``[V, omega_F, kappa_R, delta, T_R]``.
    """
    beta_abs = abs(beta)
    V = float(np.sqrt(speed_factor * mu * p.g * radius))
    if kappa_R is None:
        kappa_R = 0.1 + 1.2 * beta_abs      # deeper drifts spin the rear wheels faster
    if delta is None:
        delta = 0.1 - 0.9 * beta_abs
    delta = float(np.clip(delta, -p.limits.delta_max, p.limits.delta_max))
    T_R = 0.5 * mu * p.m * p.g * p.a / p.L * p.R_R
    return np.array([V, V / p.R_F, kappa_R, delta, T_R])


def drift_guesses(beta: float, radius: float, p: VehicleParams, mu: float = 1.0):
    """Starting points tried in turn when no guess is given, the drift branch first."""
    yield initial_guess(beta, radius, p, mu)
    beta_abs = abs(beta)
    for speed_factor in (0.6, 0.8, 1.0, 0.4):
        for kappa_R in (0.3, 0.6, 0.15, 1.0):
            for delta in (-0.5 * beta_abs, 0.1 - 0.9 * beta_abs, 0.1):
                yield initial_guess(beta, radius, p, mu, speed_factor, kappa_R, delta)


def bounds(p: VehicleParams, settings: SolverSettings) -> tuple[np.ndarray, np.ndarray]:
    """Box bounds of the solver vector ``[V, omega_F, kappa_R, delta, T_R]``."""
    lim = p.limits
    omega_F_max = 1.5 * settings.V_max / p.R_F
    lo = np.array([settings.V_min, 0.0, settings.kappa_R_min, -lim.delta_max, lim.T_R_min])
    hi = np.array([settings.V_max, omega_F_max, settings.kappa_R_max, lim.delta_max, lim.T_R_max])
    return lo, hi


def solve_equilibrium(beta: float, radius: float, p: VehicleParams, mu: float = 1.0,
                      guess: Equilibrium | np.ndarray | None = None,
                      model: VehicleModel | None = None,
                      settings: SolverSettings = SolverSettings()) -> EquilibriumSolution:
    """Steady-state circular equilibrium of the single-track model.

    Parameters
    ----------
    beta : float
        Sideslip angle [rad]; negative for a left drift.
    radius : float
        Path radius [m], positive (left-hand circle, ``r > 0``).
    p : VehicleParams
        Vehicle parameters.
    mu : float
        Surface friction scale [-].
    guess : Equilibrium or array, optional
        Starting point: a neighbouring equilibrium (continuation) or a solver vector
        ``[V, omega_F, kappa_R, delta, T_R]``. Default: the ``drift_guesses`` in turn until one
        converges to a counter-steering drift (a few ms when the first works; up to ~1 s to
        give up where no equilibrium exists within the bounds).
    model : VehicleModel, optional
        The model whose ``f`` is solved; default ``VehicleModel(p)``.
    settings : SolverSettings
        Bounds and tolerances.

    Returns
    -------
    EquilibriumSolution
        Always returned; ``converged`` says whether it is an equilibrium.
    """
    if not radius > 0.0:
        raise ValueError(f'radius must be positive (left-hand circle), got {radius}')
    model = model if model is not None else default_model(p)
    prob = _problem(model)
    if guess is None:
        guesses = drift_guesses(beta, radius, p, mu)
    elif isinstance(guess, Equilibrium):
        guesses = [_z_from_eq(guess, p)]
    else:
        guesses = [np.asarray(guess, dtype=float)]
    best = None
    for z0 in guesses:
        sol = _solve_from(z0, beta, radius, mu, prob, model, settings)
        if sol.converged and (beta == 0.0 or np.sign(sol.eq.delta) == np.sign(beta)
                              or sol.kind != 'drift'):
            return sol     # a drift counter-steers: delta has the sign of beta
        if best is None or _worse(best, sol):
            best = sol
    return best


def solve_row(betas, radius: float, p: VehicleParams, mu: float = 1.0, seed_beta: float = -0.5236,
              model: VehicleModel | None = None,
              settings: SolverSettings = SolverSettings()) -> list[EquilibriumSolution]:
    """Equilibria along a row of sideslips at one radius, by continuation from a drift seed.

    The point nearest ``seed_beta`` [rad] is solved from the drift guesses (so the row starts on
    the drift branch); the row is then walked outwards in both directions, each point starting
    from its converged neighbour. A point that fails is retried once from ``initial_guess``;
    continuation goes on from the last converged point.

    Parameters
    ----------
    betas : sequence of float
        Sideslip angles [rad], sorted, all of one sign (negative: left drift).
    radius : float
        Path radius [m].

    Returns
    -------
    list of EquilibriumSolution
        One per entry of ``betas``, in order.
    """
    betas = np.asarray(betas, dtype=float)
    model = model if model is not None else default_model(p)
    order = np.argsort(np.abs(betas - seed_beta))
    seeds = order[:6]   # a seed that is no equilibrium (e.g. steering-limited): the next one
    out: list[EquilibriumSolution | None] = [None] * len(betas)
    i0 = int(seeds[0])
    for i in seeds:
        sol = solve_equilibrium(betas[i], radius, p, mu, model=model, settings=settings)
        out[i] = sol
        if sol.converged:
            i0 = int(i)
            break
    for step in (1, -1):
        last = out[i0]
        for i in range(i0 + step, len(betas) if step > 0 else -1, step):
            if out[i] is not None and out[i].converged:
                last = out[i]
                continue
            guess = last.eq if last.converged else None
            sol = (solve_equilibrium(betas[i], radius, p, mu, guess=guess, model=model,
                                     settings=settings) if guess is not None else None)
            if sol is None or not sol.converged:
                retry = solve_equilibrium(betas[i], radius, p, mu,
                                          guess=initial_guess(betas[i], radius, p, mu),
                                          model=model, settings=settings)
                sol = retry if (sol is None or retry.converged) else sol
            out[i] = sol
            if sol.converged:
                last = sol
    return out


def _worse(a: EquilibriumSolution, b: EquilibriumSolution) -> bool:
    """True when ``b`` is the better of two candidate solutions."""
    if a.converged != b.converged:
        return b.converged
    return np.max(np.abs(b.residual)) < np.max(np.abs(a.residual))


def _solve_from(z0, beta, radius, mu, prob: _Problem, model: VehicleModel,
                settings: SolverSettings) -> EquilibriumSolution:
    """Bounded least squares from one starting point, then Newton polishing."""
    lo, hi = bounds(model.p, settings)
    z0 = np.clip(z0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    args = (beta, radius, mu)
    fun = lambda z: np.asarray(prob.res(z, *args)).ravel()    # noqa: E731
    jac = lambda z: np.asarray(prob.jac(z, *args))              # noqa: E731
    sol = least_squares(fun, z0, jac=jac, bounds=(lo, hi), method='trf', x_scale='jac',
                        xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=settings.max_nfev)
    z = _polish(sol.x, fun, jac, lo, hi, settings)
    return _solution(z, fun(z), beta, radius, mu, prob, model, settings, lo, hi)


def _polish(z, fun, jac, lo, hi, settings: SolverSettings) -> np.ndarray:
    """Newton steps on the square system; kept only while they reduce the residual in bounds."""
    best, best_norm = z, np.max(np.abs(fun(z)))
    for _ in range(settings.newton_steps):
        if best_norm < 1e-14:
            break
        try:
            step = np.linalg.solve(jac(best), -fun(best))
        except np.linalg.LinAlgError:
            break
        cand = best + step
        if np.any(cand < lo) or np.any(cand > hi):
            break
        norm = np.max(np.abs(fun(cand)))
        if not norm < best_norm:
            break
        best, best_norm = cand, norm
    return best


def _solution(z, res, beta, radius, mu, prob: _Problem, model: VehicleModel,
              settings: SolverSettings, lo, hi) -> EquilibriumSolution:
    p = model.p
    x = np.asarray(prob.state(z, beta, radius, mu)).ravel()
    eq = Equilibrium(V=float(x[X.V]), beta=float(beta), r=float(x[X.R]),
                     omega_F=float(x[X.OMEGA_F]), omega_R=float(x[X.OMEGA_R]),
                     delta=float(x[X.DELTA]), T_R=float(z[Z_T_R]))
    f = model.forces(x, mu)
    inside = bool(np.all(z >= lo) and np.all(z <= hi))
    converged = bool(np.all(np.isfinite(res)) and np.max(np.abs(res)) <= settings.tol and inside)
    return EquilibriumSolution(eq=eq, residual=res, converged=converged,
                               kind=classify(f.kappa_R, f.alpha_R, f.F_zR, p, mu),
                               F_xR=float(f.F_xR), F_yF=float(f.F_yF), F_yR=float(f.F_yR),
                               kappa_R=float(f.kappa_R), alpha_R=float(f.alpha_R))


def classify(kappa_R: float, alpha_R: float, F_zR: float, p: VehicleParams,
             mu: float = 1.0) -> Kind:
    """Grip, slight drift or drift from the rear slips at rear load ``F_zR`` [N] (section III)."""
    if kappa_R > longitudinal_peak_slip(F_zR, p.rear_tyre, mu):
        return 'drift'
    if abs(alpha_R) > lateral_peak_slip(F_zR, p.rear_tyre, mu):
        return 'slight_drift'
    return 'grip'


def _z_from_eq(eq: Equilibrium, p: VehicleParams) -> np.ndarray:
    """Solver vector of a (neighbouring) equilibrium, used as a starting point."""
    v_x = eq.V * np.cos(eq.beta)
    den_R = float(smooth_max(v_x, p.v_eps))
    kappa_R = (eq.omega_R * p.R_R - v_x) / den_R
    return np.array([eq.V, eq.omega_F, kappa_R, eq.delta, eq.T_R])


def state_vector(eq: Equilibrium) -> np.ndarray:
    """The model state (length NX, path states zero) of an equilibrium."""
    x = np.zeros(NX)
    x[[X.V, X.BETA, X.R, X.OMEGA_F, X.OMEGA_R, X.DELTA]] = [eq.V, eq.beta, eq.r, eq.omega_F,
                                                            eq.omega_R, eq.delta]
    return x


def input_vector(eq: Equilibrium) -> np.ndarray:
    """The model input (steering rate zero, drive torque) holding an equilibrium."""
    u = np.zeros(len(U))
    u[U.T_R] = eq.T_R
    return u


def scaled_derivative(eq: Equilibrium, model: VehicleModel, mu: float = 1.0) -> np.ndarray:
    """``x_dot[:5] / derivative_scale`` of the model at an equilibrium (zero when it is one)."""
    x_dot = model.rhs(state_vector(eq), input_vector(eq), 0.0, mu)
    return x_dot[:N_RES] / derivative_scale(model.p)


__all__ = ['EquilibriumSolution', 'SolverSettings', 'classify', 'derivative_scale',
           'drift_guesses', 'initial_guess', 'input_vector', 'scaled_derivative',
           'solve_equilibrium', 'solve_row',
           'state_vector']

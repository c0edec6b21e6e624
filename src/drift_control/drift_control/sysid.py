"""System identification: fit the controller's single-track model to recorded driving.

Equation error on the state derivatives: the measured signals are smoothed and differentiated
with a Savitzky-Golay filter (a local cubic over ``window_s``: noise handled before the
derivative), and the tyre coefficients (and, if asked, the yaw inertia) are the nonlinear least
squares fit of the model's ``rhs`` (``drift_control.vehicle``, the NMPC's own body, evaluated
with the fitted coefficients as casadi symbols) to the derivatives of speed, sideslip, yaw rate
and rear wheel speed. Why derivatives and not multi-step predictions: a drift is an unstable
equilibrium, so an open-loop prediction over seconds diverges and its error surface is rough;
the one-step equation error is smooth, fast (one mapped casadi call per iteration) and uses
every sample. Multi-step predictions judge the result on held-out blocks of the log.

The powertrain (request -> applied drive torque) is fitted separately
(``drift_control.powertrain_fit``), and the result is judged by multi-step predictions on held-out
data (``drift_control.prediction``). Confidence intervals come from the Jacobian at the optimum, with the
covariance inflated by the residuals' correlation time (smoothed, serially correlated residuals
hold fewer independent samples than the log has rows). A parameter the log cannot identify is
refused with ``IdentificationError`` naming it and why.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import casadi as ca
import numpy as np
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from drift_control.params import VehicleParams
from drift_control.tyre import lateral_peak_slip, longitudinal_peak_slip
from drift_control.vehicle import NTHETA, NU, NX, THETA, U, X, rhs, slips

# what the fit may change, with the bounds it keeps to (physical ranges of each coefficient)
FITTABLE = {
    'front_tyre.lateral.B': (2.0, 40.0),
    'front_tyre.lateral.C': (0.8, 2.4),
    'front_tyre.lateral.D': (0.2, 2.0),
    'rear_tyre.pKy1': (2.0, 80.0),
    'rear_tyre.pCy1': (0.8, 2.4),
    'rear_tyre.pDy1': (0.2, 2.0),
    'rear_tyre.pKx1': (2.0, 80.0),
    'rear_tyre.pDx1': (0.2, 2.0),
    'rear_tyre.rBx1': (2.0, 40.0),
    'I_z': (100.0, 20000.0),
}
# The rear wheel spins past its longitudinal peak only in the drift, at rear slip angles of
# 15-35 deg, where the force is the combined-slip weight G_xa times the pure-slip force: the log
# identifies their product. The default fits the weight (rBx1) and keeps the pure peak (pDx1)
# from the data sheet; pDx1 is fitted only from wheelspin at small slip angles (``min_spin_s``).
DEFAULT_FIT = ('front_tyre.lateral.B', 'front_tyre.lateral.C', 'front_tyre.lateral.D',
               'rear_tyre.pKy1', 'rear_tyre.pCy1', 'rear_tyre.pDy1',
               'rear_tyre.pKx1', 'rear_tyre.rBx1')
CHANNELS = ('V_dot', 'beta_dot', 'r_dot', 'omega_R_dot')
_ROWS = (X.V, X.BETA, X.R, X.OMEGA_R)


class IdentificationError(ValueError):
    """The data cannot identify what was asked; the message names the parameter and why."""


@dataclass(frozen=True)
class SysIdSettings:
    """How the log is cut, smoothed and judged."""

    window_s: float = 0.21        # Savitzky-Golay window [s] (cubic)
    v_min: float = 5.0            # samples slower than this are left out [m/s]
    block_s: float = 10.0         # the held-out split works in blocks of this length [s]
    holdout_every: int = 4        # every n-th block is held out [-]
    min_beyond_s: float = 1.0     # rear slip well past its peak needed to fit the rear [s]
    beyond_factor: float = 1.5    # 'well past': this times the peak slip angle [-] (a car at
                                  # its grip limit only touches the peak; a drift is 2-4 times)
    front_near_peak: float = 0.7  # the front's slip must reach this share of its peak slip [-]
    min_spin_s: float = 1.0       # rear wheelspin past the longitudinal peak at small slip
    spin_alpha_deg: float = 3.0   # angles (below this) needed to fit the pure peak pDx1 [s, deg]
    max_rel_ci: float = 0.5       # a parameter whose 95 % CI half-width exceeds this share of
                                  # its value is refused as not identified [-]
    horizon_s: float = 0.5        # multi-step prediction horizon (the NMPC's 25 x 20 ms) [s]
    stride_s: float = 0.25        # start of a prediction every this [s]


@dataclass(frozen=True)
class Log:
    """A recorded run as uniform time series (the model's states and inputs), SI units.

    ``T`` is the drive torque at the wheels as applied (measured), ``T_cmd`` the request
    (NaN where the bag has none).
    """

    t: np.ndarray
    V: np.ndarray
    beta: np.ndarray
    r: np.ndarray
    omega_F: np.ndarray
    omega_R: np.ndarray
    delta: np.ndarray
    T: np.ndarray
    T_cmd: np.ndarray

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t)))

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])


def uniform_log(state: dict, command: dict | None = None, dt: float = 0.01) -> Log:
    """A ``Log`` on a uniform grid from ``drift_tools.timeseries`` groups (``t`` + columns)."""
    t0, t1 = float(state['t'][0]), float(state['t'][-1])
    t = t0 + dt * np.arange(int(math.floor((t1 - t0) / dt)) + 1)
    cols = {k: np.interp(t, state['t'], state[k]) for k in
            ('V', 'beta', 'r', 'omega_F', 'omega_R', 'delta')}
    cols['T'] = np.interp(t, state['t'], state['drive_torque'])
    if command is not None and len(command.get('t', ())) > 1:
        idx = np.searchsorted(command['t'], t, side='right') - 1   # a request holds until the next
        T_cmd = command['drive_torque'][np.clip(idx, 0, None)].astype(float)
        T_cmd[idx < 0] = np.nan
    else:
        T_cmd = np.full(len(t), np.nan)
    return Log(t, T_cmd=T_cmd, **cols)


@dataclass(frozen=True)
class Smoothed:
    """Smoothed states (n, NX), inputs (n, NU), derivatives of ``CHANNELS`` (n, 4)."""

    x: np.ndarray
    u: np.ndarray
    xdot: np.ndarray


def smooth(log: Log, window_s: float) -> Smoothed:
    """Savitzky-Golay smoothing and derivative of every signal the model needs."""
    dt = log.dt
    n = max(5, int(round(window_s / dt)) | 1)
    sg = lambda y, d=0: savgol_filter(y, n, 3, deriv=d, delta=dt)   # noqa: E731
    x = np.zeros((len(log.t), NX))
    for i, y in ((X.V, log.V), (X.BETA, log.beta), (X.R, log.r), (X.OMEGA_F, log.omega_F),
                 (X.OMEGA_R, log.omega_R), (X.DELTA, log.delta)):
        x[:, i] = sg(y)
    u = np.zeros((len(log.t), NU))
    u[:, U.DELTA_DOT] = sg(log.delta, 1)
    u[:, U.T_R] = sg(log.T)
    xdot = np.column_stack([sg(y, 1) for y in (log.V, log.beta, log.r, log.omega_R)])
    return Smoothed(x, u, xdot)


def split(log: Log, s: SysIdSettings) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (train, held out): blocks of ``block_s``, every ``holdout_every``-th held
    out, so every kind of driving in the manoeuvre lands on both sides; slow samples and the
    filter's edge samples are in neither."""
    block = ((log.t - log.t[0]) // s.block_s).astype(int)
    held = block % s.holdout_every == s.holdout_every - 1
    usable = log.V > s.v_min
    edge = int(round(s.window_s / log.dt))
    usable[:edge] = usable[-edge:] = False
    return usable & ~held, usable & held


# --- the model with symbolic coefficients -----------------------------------------------------

def _namespace(obj, fitted: dict, prefix: str = ''):
    """A copy of a params dataclass tree as namespaces, with the ``fitted`` names replaced."""
    out = {}
    for f in dataclasses.fields(obj):
        name = prefix + f.name
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = _namespace(value, fitted, name + '.')
        else:
            out[f.name] = fitted.get(name, value)
    ns = SimpleNamespace(**out)
    if isinstance(obj, VehicleParams):
        ns.b = ns.L - ns.a
    return ns


def with_values(vehicle: VehicleParams, values: dict) -> VehicleParams:
    """``vehicle`` with the dotted names of ``values`` replaced (validated like a YAML)."""
    def apply(obj, prefix):
        changes = {}
        for f in dataclasses.fields(obj):
            name = prefix + f.name
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                changes[f.name] = apply(value, name + '.')
            elif name in values:
                changes[f.name] = float(values[name])
        return dataclasses.replace(obj, **changes)
    return apply(vehicle, '')


def value_of(vehicle: VehicleParams, name: str) -> float:
    """The value of a dotted parameter name (``rear_tyre.pKy1``)."""
    obj = vehicle
    for part in name.split('.'):
        obj = getattr(obj, part)
    return float(obj)


class EquationError:
    """Residuals of the model's derivatives against the measured ones, and their Jacobian.

    The model is ``drift_control.vehicle.rhs`` with the NMPC's front-wheel treatment
    (free rolling: the manoeuvre never brakes, so the front longitudinal force is not excited).
    """

    def __init__(self, vehicle: VehicleParams, names, mu: float, data: Smoothed,
                 mask: np.ndarray):
        self.names = tuple(names)
        q = ca.SX.sym('q', len(self.names))
        p = _namespace(vehicle, {n: q[i] for i, n in enumerate(self.names)})
        x, u = ca.SX.sym('x', NX), ca.SX.sym('u', NU)
        theta = ca.DM.zeros(NTHETA)
        theta[THETA.MU] = mu
        f = rhs(x, u, theta, p, load_passes=1, front_wheel='free_rolling')
        g = ca.vertcat(*[f[i] for i in _ROWS])
        n = int(mask.sum())
        self._f = ca.Function('g', [x, u, q], [g]).map(n, 'serial')
        self._J = ca.Function('J', [x, u, q], [ca.jacobian(g, q)]).map(n, 'serial')
        self.x, self.u = data.x[mask].T, data.u[mask].T
        self.xdot = data.xdot[mask]
        self.n = n
        self.weights = np.ones(len(CHANNELS))

    def predicted(self, q) -> np.ndarray:
        """Model derivatives (n, 4)."""
        return np.asarray(self._f(self.x, self.u, q)).T

    def residuals(self, q) -> np.ndarray:
        """Weighted residuals, channel-major (4 n,)."""
        return ((self.predicted(q) - self.xdot) / self.weights).T.ravel()

    def jacobian(self, q) -> np.ndarray:
        """d residuals / d q (4 n, nq)."""
        J = np.asarray(self._J(self.x, self.u, q))          # (4, n * nq)
        J = J.reshape(len(CHANNELS), self.n, len(self.names))
        return (J / self.weights[:, None, None]).reshape(-1, len(self.names))


# --- results ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ParamFit:
    """One fitted parameter: value, 95 % confidence half-width, the prior it started from."""

    name: str
    value: float
    ci95: float
    prior: float


@dataclass(frozen=True)
class Fit:
    """What ``identify`` found."""

    vehicle: VehicleParams             # the prior with the fitted values in
    params: tuple[ParamFit, ...]
    rms_train: dict                    # per channel, unweighted
    rms_held: dict
    n_train: int
    n_held: int
    correlation_samples: float         # residual correlation time, in samples
    seconds: float                     # wall time of the fit [s]
    evidence: dict = field(default_factory=dict)   # what the log shows of the grip limits


def _rms(e) -> dict:
    return {c: float(np.sqrt(np.mean(e[:, i] ** 2))) for i, c in enumerate(CHANNELS)}


def correlation_time(res: np.ndarray, max_lag: int = 300) -> float:
    """Integrated autocorrelation time of residual series (n, k), in samples, >= 1."""
    taus = []
    for col in res.T:
        c = col - col.mean()
        spec = np.fft.rfft(c, 2 * len(c))
        acf = np.fft.irfft(spec * np.conj(spec))[:max_lag]
        acf = acf / acf[0]
        below = np.nonzero(acf < 0.05)[0]
        stop = int(below[0]) if len(below) else max_lag
        taus.append(1.0 + 2.0 * float(acf[1:stop].sum()))
    return max(1.0, float(np.mean(taus)))


def grip_evidence(vehicle: VehicleParams, data: Smoothed, mask: np.ndarray, mu: float,
                  dt: float, beyond_factor: float = SysIdSettings.beyond_factor,
                  spin_alpha_deg: float = SysIdSettings.spin_alpha_deg) -> dict:
    """How far the log goes past each axle's grip limit, by the model's slips and ``vehicle``'s
    peak slips: the rear's time beyond ``beyond_factor`` x its peak slip angle [s], its time
    spinning past the longitudinal peak at slip angles below ``spin_alpha_deg`` [s], the
    front's largest slip (99.5th percentile) and its peak."""
    a_F, _, a_R, k_R = slips(data.x[mask].T, vehicle)
    a_F, a_R = np.abs(np.asarray(a_F).ravel()), np.abs(np.asarray(a_R).ravel())
    k_R = np.asarray(k_R).ravel()
    F_zR = vehicle.m * vehicle.g * vehicle.a / vehicle.L
    rear_peak = lateral_peak_slip(F_zR, vehicle.rear_tyre, mu)
    spin_peak = longitudinal_peak_slip(F_zR, vehicle.rear_tyre, mu)
    spinning = k_R > spin_peak
    lat = vehicle.front_tyre.lateral
    front_peak = math.tan(math.pi / (2.0 * lat.C)) / lat.B if lat.C > 1.0 else math.inf
    return {'rear_peak_deg': math.degrees(rear_peak),
            'rear_beyond_s': float((a_R > beyond_factor * rear_peak).sum() * dt),
            'rear_max_deg': math.degrees(float(a_R.max())),
            'spin_peak': spin_peak,
            'spin_straight_s': float((spinning & (a_R < math.radians(spin_alpha_deg))).sum()
                                     * dt),
            'spin_s': float(spinning.sum() * dt),
            'front_peak_deg': math.degrees(front_peak),
            'front_max_deg': math.degrees(float(np.percentile(a_F, 99.5)))}


def _check_evidence(ev: dict, names, s: SysIdSettings) -> None:
    rear = [n for n in names if n in ('rear_tyre.pDy1', 'rear_tyre.pCy1')]
    if rear and ev['rear_beyond_s'] < s.min_beyond_s:
        raise IdentificationError(
            f'{", ".join(rear)}: no sideslip beyond the grip limit in the log: the rear slip '
            f"angle is past {s.beyond_factor:g} x its peak ({ev['rear_peak_deg']:.1f} deg) for "
            f"{ev['rear_beyond_s']:.2f} s, {s.min_beyond_s:.1f} s needed (largest "
            f"{ev['rear_max_deg']:.1f} deg); drive the power-on bursts of the manoeuvre")
    if 'rear_tyre.pDx1' in names and ev['spin_straight_s'] < s.min_spin_s:
        raise IdentificationError(
            'rear_tyre.pDx1: no wheelspin at small slip angles in the log '
            f"({ev['spin_straight_s']:.2f} s past the longitudinal peak slip "
            f"{ev['spin_peak']:.2f} below {s.spin_alpha_deg:g} "
            f"deg of rear slip angle, {s.min_spin_s:.1f} s needed; {ev['spin_s']:.1f} s in all, "
            'in the drift): the drift identifies the combined-slip weight rear_tyre.rBx1, not '
            'the peak; keep the data sheet\'s or drive straight-line wheelspin')
    front = [n for n in names if n in ('front_tyre.lateral.D', 'front_tyre.lateral.C')]
    if front and ev['front_max_deg'] < s.front_near_peak * ev['front_peak_deg']:
        raise IdentificationError(
            f"{', '.join(front)}: the front tyres never near their grip limit in the log (slip "
            f"angle {ev['front_max_deg']:.1f} deg, peak {ev['front_peak_deg']:.1f} deg); drive the "
            'constant-steer circles up to the limit')


def identify(log: Log, prior: VehicleParams, mu: float, names=DEFAULT_FIT,
             settings: SysIdSettings = SysIdSettings()) -> Fit:
    """Fit ``names`` of ``prior`` to the log by nonlinear least squares on state derivatives.

    Parameters
    ----------
    log : Log
        The recorded run (uniform time grid).
    prior : VehicleParams
        The data-sheet vehicle: its mass, geometry and inertias are taken as known, its tyre
        coefficients are the starting point.
    mu : float
        The surface's friction the log was driven on (the fitted peaks are per mu = 1) [-].
    names : sequence of str
        Dotted parameter names, from ``FITTABLE``.

    Raises
    ------
    IdentificationError
        Too little driving, no data beyond a grip limit a fitted peak needs, or a parameter
        whose confidence interval is too wide to call it identified.
    """
    wall0 = time.perf_counter()
    s = settings
    unknown = [n for n in names if n not in FITTABLE]
    if unknown:
        raise IdentificationError(f'{unknown[0]}: not a fittable parameter; fittable: '
                                  f'{", ".join(FITTABLE)}')
    if len(log.t) < 10 or log.duration < 5.0 * s.block_s / s.holdout_every:
        raise IdentificationError(f'log: {log.duration:.1f} s is too short to identify anything')
    data = smooth(log, s.window_s)
    train, held = split(log, s)
    if train.sum() * log.dt < 20.0:
        raise IdentificationError(f'log: only {train.sum() * log.dt:.1f} s above '
                                  f'{s.v_min:.0f} m/s for the fit (20 s needed)')
    if held.sum() == 0:
        raise IdentificationError(f'log: nothing held out to judge the fit on (every '
                                  f'{s.holdout_every}th block of {s.block_s:g} s above '
                                  f'{s.v_min:.0f} m/s); a longer log is needed')
    evidence = grip_evidence(prior, data, train | held, mu, log.dt, s.beyond_factor,
                             s.spin_alpha_deg)
    _check_evidence(evidence, names, s)

    problem = EquationError(prior, names, mu, data, train)
    q0 = np.array([value_of(prior, n) for n in names])
    lo = np.array([FITTABLE[n][0] for n in names])
    hi = np.array([FITTABLE[n][1] for n in names])
    q0 = np.clip(q0, lo * 1.001, hi * 0.999)
    # pass 1 weights the channels by their spread, pass 2 by the residuals of pass 1:
    # each channel then counts by its own noise (iteratively reweighted least squares)
    problem.weights = np.std(problem.xdot, axis=0) + 1e-9
    q = q0
    for _ in range(2):
        sol = least_squares(problem.residuals, q, jac=problem.jacobian, bounds=(lo, hi),
                            x_scale='jac', method='trf', max_nfev=200)
        q = sol.x
        problem.weights = np.sqrt(np.mean((problem.predicted(q) - problem.xdot) ** 2, axis=0))
    res = problem.residuals(q)
    J = problem.jacobian(q)
    tau_corr = correlation_time(res.reshape(len(CHANNELS), -1).T)
    dof = max(len(res) - len(q), 1)
    sigma2 = float(res @ res) / dof * tau_corr
    JTJ = J.T @ J
    try:
        cov = np.linalg.inv(JTJ) * sigma2
        ci = 1.96 * np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        ci = np.full(len(q), np.inf)
    fitted = with_values(prior, dict(zip(names, q)))
    evidence_fit = grip_evidence(fitted, data, train | held, mu, log.dt, s.beyond_factor,
                                  s.spin_alpha_deg)
    _check_evidence(evidence_fit, names, s)
    for n, v, c, lo_i, hi_i in zip(names, q, ci, lo, hi):
        if not np.isfinite(c) or c > s.max_rel_ci * abs(v):
            raise IdentificationError(
                f'{n}: not identified by this log (fit {v:.4g}, 95 % CI +-{c:.3g}, over '
                f'{100 * s.max_rel_ci:.0f} % of the value); fix it from the data sheet or drive '
                'more of the manoeuvre')
        if min(v - lo_i, hi_i - v) < 1e-3 * (hi_i - lo_i):
            raise IdentificationError(f'{n}: the fit ran into its bound ({v:.4g}, allowed '
                                      f'{lo_i:g}..{hi_i:g}): the model cannot explain the log')
    held_problem = EquationError(prior, names, mu, data, held)
    e_held = held_problem.predicted(q) - held_problem.xdot
    e_train = problem.predicted(q) - problem.xdot
    params = tuple(ParamFit(n, float(v), float(c), float(p0))
                   for n, v, c, p0 in zip(names, q, ci, [value_of(prior, n) for n in names]))
    return Fit(fitted, params, _rms(e_train), _rms(e_held),
               int(train.sum()), int(held.sum()), tau_corr, time.perf_counter() - wall0,
               {'prior': evidence, 'fitted': evidence_fit})

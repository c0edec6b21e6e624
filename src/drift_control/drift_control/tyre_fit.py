"""Least-squares fit of the controller's tyre forms (``tyre.py``) to a Magic Formula ``.tir`` tyre.

The reference is the full MF of ``tir.mf_forces`` on an axle of two tyres: a left tyre as in the
file and a right tyre mirrored (MF ``TYRESIDE``), each at half the axle load. For a tyre without
offsets that is exactly twice the force of one tyre; with offsets (``PVY1``, ``PEY3``...) the
lateral offsets of the two cancel, as on a real axle, instead of making left and right drifts
differ by several per cent. Slip angles are in the controller's sign (a positive slip angle gives a
positive lateral force, ``vehicle.slips``), which is the MF's ``-alpha``.

The forms are evaluated through the very functions of ``tyre.py`` (CasADi, with the coefficients
as symbols), so the fit sees the formula the controller runs, with an exact Jacobian. Residuals
are force errors per unit load ``(F_fit - F_MF) / (mu F_z)``, so every load counts alike; the
reported errors are in newtons and relative to the MF's peak.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from types import SimpleNamespace

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from drift_control.params import CombinedTyreParams, FrontTyreParams, SimpleMF, VehicleParams
from drift_control.tir import MfForces, TirTyre, mf_forces
from drift_control.tyre import combined_forces, simple_force

# --- the operating region of a drift ----------------------------------------------------------
# Rear: at a steady drift the rear slip angle is exactly atan(tan|beta| + b / (R cos beta)) (the
# rear axle's lateral speed is V sin(beta) - b r with r = V / R): 34.8 deg for 30 deg on
# R = 15 m with b = 1.51 m, 38.5 deg on R = 8 m. 0..40 deg covers sideslips up to 30 deg on any
# radius of the maps and up to 35 deg on R >= 15 m. The spinning rear wheel runs at slip 0.5..0.6
# in the 30 deg drift (dry and wet); 0.8 leaves room for deeper drifts, -0.05 covers engine
# braking. Load 0.5..1.5 of static: longitudinal load transfer at full drive and braking, plus
# margin.
REAR_ALPHA_DEG = (0.0, 40.0)
REAR_KAPPA = (-0.05, 0.8)
REAR_LOAD = (0.5, 1.5)
# Front: it stays below its lateral peak in a drift (2.5..3.5 deg at 30 deg / 15 m); 0..12 deg
# includes the peak so the saturation is fitted too. The front wheel rolls freely: |kappa| <= 0.02
# for the lateral force; the longitudinal curve is fitted on |kappa| <= 0.15 at zero slip angle, to
# its peak (the form has no combined slip). Load 0.6..1.4 of static.
FRONT_ALPHA_DEG = (0.0, 12.0)
FRONT_KAPPA = (-0.02, 0.02)
FRONT_LONG_KAPPA = (-0.15, 0.15)
FRONT_LOAD = (0.6, 1.4)
# The drift point: the paper's 30 deg drift on R = 15 m. Rear slip angle from the geometry above,
# rear slip 0.5 (the controller's equilibrium has 0.49 dry, 0.52 wet), static axle loads; front
# slip angle 3.5 deg (3.4 dry, 2.5 wet at that equilibrium), free-rolling front wheel.
DRIFT_BETA_DEG = 30.0
DRIFT_RADIUS = 15.0
DRIFT_KAPPA_R = 0.5
DRIFT_ALPHA_F_DEG = 3.5
WET_MU = 0.7   # default wet surface of the report (a YAML's wet surface overrides it)

REAR_NAMES = tuple(f.name for f in fields(CombinedTyreParams) if f.name != 'Fz0')
_REAR_BOUNDS = {   # validators of params.py, and sign-free terms (cos(atan(x)) is even) kept >= 0
    'pCx1': (0.1, 3.0), 'pDx1': (0.05, 3.0), 'pDx2': (-1.0, 1.0), 'pEx1': (-20.0, 1.0),
    'pKx1': (0.1, 200.0), 'pKx2': (-100.0, 100.0), 'pKx3': (-5.0, 5.0),
    'pCy1': (0.1, 3.0), 'pDy1': (0.05, 3.0), 'pDy2': (-1.0, 1.0), 'pEy1': (-20.0, 1.0),
    'pKy1': (0.1, 200.0), 'pKy2': (0.1, 20.0),
    'rBx1': (0.0, 200.0), 'rBx2': (0.0, 200.0), 'rCx1': (0.05, 3.0),
    'rBy1': (0.0, 200.0), 'rBy2': (0.0, 200.0), 'rBy3': (-1.0, 1.0), 'rCy1': (0.05, 3.0)}
_SIMPLE_BOUNDS = (np.array([0.01, 0.1, 0.05, -20.0]), np.array([200.0, 3.0, 3.0, 1.0]))


@dataclass(frozen=True)
class Region:
    """A box of slip angle, slip and load factor: where a form is fitted and judged.

    ``f_z_static`` is the static axle load [N]; ``load`` are factors of it.
    """

    alpha_deg: tuple[float, float]
    kappa: tuple[float, float]
    load: tuple[float, float]
    f_z_static: float

    def grid(self, alpha_step_deg: float = 2.5, kappa_step: float = 0.05, n_load: int = 5):
        """Flat arrays ``(alpha [rad], kappa, f_z [N])`` of a regular grid over the box."""
        alpha = np.radians(_steps(*self.alpha_deg, alpha_step_deg))
        kappa = _steps(*self.kappa, kappa_step)
        f_z = self.f_z_static * np.linspace(*self.load, n_load)
        A, K, F = np.meshgrid(alpha, kappa, f_z, indexing='ij')
        return A.ravel(), K.ravel(), F.ravel()

    def describe(self) -> str:
        """One line: the box in degrees, slip and load."""
        def span(lo, hi):
            return f'{lo:g}' if lo == hi else f'{lo:g}..{hi:g}'
        return (f'alpha {span(*self.alpha_deg)} deg, kappa {span(*self.kappa)}, load '
                f'{span(*self.load)} x {self.f_z_static:.0f} N')


@dataclass(frozen=True)
class ForceError:
    """Error of one force component over a region [N], and the MF peak it is relative to [N]."""

    rms: float
    max: float
    peak: float

    @property
    def rms_rel(self) -> float:
        """RMS error relative to the peak [-]."""
        return self.rms / self.peak

    @property
    def max_rel(self) -> float:
        """Largest error relative to the peak [-]."""
        return self.max / self.peak


@dataclass(frozen=True)
class PointCheck:
    """MF and fitted forces at one operating point [rad, -, N]."""

    alpha: float
    kappa: float
    f_z: float
    mu: float
    Fx_mf: float
    Fx_fit: float
    Fy_mf: float
    Fy_fit: float

    @property
    def Fx_rel(self) -> float:
        """``(Fx_fit - Fx_MF) / |Fx_MF|`` [-]; nan where ``|Fx_MF| < 0.1 f_z`` (no force)."""
        return _rel(self.Fx_fit, self.Fx_mf, self.f_z)

    @property
    def Fy_rel(self) -> float:
        """``(Fy_fit - Fy_MF) / |Fy_MF|`` [-]."""
        return _rel(self.Fy_fit, self.Fy_mf, self.f_z)


@dataclass(frozen=True)
class SurfaceFit:
    """How well the fitted form matches the MF on one surface ``mu``."""

    mu: float
    Fx: ForceError
    Fy: ForceError
    drift: PointCheck


@dataclass(frozen=True)
class AxleFit:
    """The fitted form of one axle and its errors.

    Attributes
    ----------
    axle : {'front', 'rear'}
    params : FrontTyreParams or CombinedTyreParams
        The fitted coefficients, valid for ``params.py``.
    regions : tuple of (str, Region)
        Where it was fitted (and the errors taken), named by the force they are for.
    surfaces : tuple of SurfaceFit
        Errors at ``mu = 1`` (fitted there) and at the wet ``mu`` (not fitted).
    copied : tuple of PointCheck
        Rear only: the drift point with MF's combined-slip coefficients copied, not fitted.
    notes : tuple of str
        What the form cannot represent, with numbers.
    """

    axle: str
    params: object
    regions: tuple
    surfaces: tuple
    copied: tuple
    notes: tuple


@dataclass(frozen=True)
class TyreFit:
    """Both axles fitted to one ``.tir`` for one vehicle (either may be None)."""

    tyre: TirTyre
    front: AxleFit | None
    rear: AxleFit | None


# --- the reference: two MF tyres on an axle ---------------------------------------------------

def axle_mf(tyre: TirTyre, alpha, kappa, f_z, mu=1.0) -> MfForces:
    """MF forces of an axle [N]: left tyre as in the file + mirrored right tyre, ``f_z / 2`` each.

    Parameters
    ----------
    alpha : array_like
        Slip angle [rad], controller sign (positive gives a positive lateral force).
    kappa : array_like
        Longitudinal slip [-].
    f_z : array_like
        Axle load [N].
    mu : array_like
        Road friction scale [-].
    """
    alpha = np.asarray(alpha, dtype=float)
    half = 0.5 * np.asarray(f_z, dtype=float)
    left = mf_forces(tyre, kappa, -alpha, half, mu)     # ISO alpha = -controller alpha
    right = mf_forces(tyre, kappa, alpha, half, mu)     # mirrored: F_y(a) -> -F_y(-a)
    return MfForces(left.Fx + right.Fx, left.Fy - right.Fy)


def static_loads(p: VehicleParams) -> tuple[float, float]:
    """Static axle loads ``(F_zF, F_zR) = m g (b, a) / L`` [N]."""
    return p.m * p.g * p.b / p.L, p.m * p.g * p.a / p.L


def drift_alpha_R(p: VehicleParams, beta_deg: float = DRIFT_BETA_DEG,
                  radius: float = DRIFT_RADIUS) -> float:
    """Rear slip angle of a steady drift, ``atan(tan|beta| + b / (R cos beta))`` [rad]."""
    beta = math.radians(beta_deg)
    return math.atan(math.tan(beta) + p.b / (radius * math.cos(beta)))


def mf_peak(tyre: TirTyre, component: str, f_z: float, mu: float) -> float:
    """Pure-slip peak of the axle's MF ``Fx`` (over kappa) or ``Fy`` (over alpha) [N]."""
    if component == 'Fx':
        return float(np.max(np.abs(axle_mf(tyre, 0.0, np.linspace(0.0, 1.0, 2001), f_z, mu).Fx)))
    alpha = np.radians(np.linspace(0.0, 60.0, 2401))
    return float(np.max(np.abs(axle_mf(tyre, alpha, 0.0, f_z, mu).Fy)))


# --- the controller's forms with symbolic coefficients ----------------------------------------

class _Form:
    """A ``tyre.py`` force function as a CasADi function of (coefficients, alpha, kappa, f_z, mu).

    ``evaluate`` maps it over points and returns the forces and their Jacobian in the
    coefficients (exact, for ``least_squares``).
    """

    def __init__(self, body, names, fixed=None):
        theta = ca.SX.sym('theta', len(names))
        a, k, f_z, mu = (ca.SX.sym(s) for s in ('alpha', 'kappa', 'f_z', 'mu'))
        # duck-typed coefficients: the same body the controller runs, with symbols in it
        p = SimpleNamespace(**(fixed or {}), **{n: theta[i] for i, n in enumerate(names)})
        out = ca.vertcat(*body(a, k, f_z, p, mu))
        self.n_out, self.n_theta = out.shape[0], len(names)
        self._fun = ca.Function('form', [theta, a, k, f_z, mu], [out, ca.jacobian(out, theta)])
        self._maps = {}

    def evaluate(self, theta, alpha, kappa, f_z, mu):
        n = len(alpha)
        if n not in self._maps:
            self._maps[n] = self._fun.map(n)

        def row(v):
            return np.broadcast_to(np.asarray(v, dtype=float), (n,))[None, :]

        out, jac = self._maps[n](np.tile(np.asarray(theta, float)[:, None], (1, n)),
                                 row(alpha), row(kappa), row(f_z), row(mu))
        jac = np.asarray(jac).reshape(self.n_out, n, self.n_theta)
        return np.asarray(out), jac


def _rear_body(a, k, f_z, p, mu):
    return combined_forces(a, k, f_z, p, mu)


def _simple_body(a, k, f_z, p, mu):
    return (simple_force(a, f_z, p, mu),)   # slip passed as alpha (or kappa, see _fit_simple)


# --- fitting ----------------------------------------------------------------------------------

def fit_tir(tyre: TirTyre, vehicle: VehicleParams, axles=('front', 'rear'),
            wet_mu: float = WET_MU) -> TyreFit:
    """Fit the controller's front and/or rear tyre forms to ``tyre`` on ``vehicle``'s axles.

    Parameters
    ----------
    tyre : TirTyre
        The Magic Formula reference (one tyre; two per axle).
    vehicle : VehicleParams
        Gives the static axle loads and the rear drift-point geometry (``a``, ``b``).
    axles : sequence of {'front', 'rear'}
    wet_mu : float
        Friction scale of the wet surface the errors are also reported at [-] (fit at 1).
    """
    f_zF, f_zR = static_loads(vehicle)
    front = fit_front(tyre, f_zF, wet_mu) if 'front' in axles else None
    rear = fit_rear(tyre, f_zR, drift_alpha_R(vehicle), wet_mu) if 'rear' in axles else None
    return TyreFit(tyre, front, rear)


def fit_front(tyre: TirTyre, f_z_static: float, wet_mu: float = WET_MU) -> AxleFit:
    """Front axle: ``SimpleMF`` lateral and longitudinal, each fitted at ``mu = 1``."""
    lat_region = Region(FRONT_ALPHA_DEG, FRONT_KAPPA, FRONT_LOAD, f_z_static)
    lon_region = Region((0.0, 0.0), FRONT_LONG_KAPPA, FRONT_LOAD, f_z_static)
    lat_pts = lat_region.grid(alpha_step_deg=1.0, kappa_step=0.02)
    lon_pts = lon_region.grid(kappa_step=0.01)
    form = _Form(_simple_body, ('B', 'C', 'D', 'E'))
    lateral = _fit_simple(form, tyre, lat_pts, 'Fy', f_z_static)
    longitudinal = _fit_simple(form, tyre, lon_pts, 'Fx', f_z_static)
    params = FrontTyreParams(lateral=lateral, longitudinal=longitudinal)

    theta_x = np.array([getattr(longitudinal, n) for n in 'BCDE'])
    theta_y = np.array([getattr(lateral, n) for n in 'BCDE'])

    def forces(alpha, kappa, f_z, mu):
        alpha, kappa, f_z = np.broadcast_arrays(*map(np.atleast_1d, (alpha, kappa, f_z)))
        return (form.evaluate(theta_x, kappa, 0.0, f_z, mu)[0][0],
                form.evaluate(theta_y, alpha, 0.0, f_z, mu)[0][0])

    alpha_d = math.radians(DRIFT_ALPHA_F_DEG)
    surfaces = tuple(_surface(tyre, forces, mu, lon_pts, lat_pts, f_z_static,
                              (alpha_d, 0.0, f_z_static)) for mu in (1.0, wet_mu))
    fit = AxleFit('front', params, (('Fy', lat_region), ('Fx', lon_region)), surfaces, (), ())
    return _replace_notes(fit, _front_notes(tyre, fit, forces, f_z_static))


def fit_rear(tyre: TirTyre, f_z_static: float, alpha_drift: float,
             wet_mu: float = WET_MU) -> AxleFit:
    """Rear axle: ``CombinedTyreParams`` fitted jointly on Fx and Fy at ``mu = 1``.

    Two stages: the pure-slip coefficients on the pure-slip edges of the region (combined-slip
    weights copied from the MF), then every coefficient on the whole combined-slip region.
    ``Fz0`` is the axle's nominal load, twice the tyre's ``LFZO * FNOMIN``, so the load terms
    keep their MF meaning.
    """
    region = Region(REAR_ALPHA_DEG, REAR_KAPPA, REAR_LOAD, f_z_static)
    Fz0 = 2.0 * tyre.Fz0
    form = _Form(_rear_body, REAR_NAMES, {'Fz0': Fz0})
    pts = region.grid()
    copy = _rear_copy(tyre)
    lo = np.array([_REAR_BOUNDS[n][0] for n in REAR_NAMES])
    hi = np.array([_REAR_BOUNDS[n][1] for n in REAR_NAMES])
    x0 = np.clip([copy[n] for n in REAR_NAMES], lo + 1e-9, hi - 1e-9)

    alpha, kappa, f_z = pts
    pure = (alpha == 0.0) | (kappa == 0.0)
    free = np.array([n.startswith('p') for n in REAR_NAMES])
    target = axle_mf(tyre, alpha, kappa, f_z, 1.0)
    x_pure = _least_squares(form, (alpha[pure], kappa[pure], f_z[pure]),
                            (target.Fx[pure], target.Fy[pure]), x0, lo, hi, free)
    x = _least_squares(form, pts, (target.Fx, target.Fy), x_pure, lo, hi,
                       np.ones(len(REAR_NAMES), bool))
    params = CombinedTyreParams(Fz0=Fz0, **dict(zip(REAR_NAMES, map(float, x))))

    def forces_of(theta):
        return lambda a, k, f, mu: form.evaluate(theta, np.atleast_1d(a), np.atleast_1d(k),
                                                 np.atleast_1d(f), mu)[0]

    drift = (alpha_drift, DRIFT_KAPPA_R, f_z_static)
    surfaces = tuple(_surface(tyre, forces_of(x), mu, pts, pts, f_z_static, drift)
                     for mu in (1.0, wet_mu))
    copied = tuple(_check(tyre, forces_of(x_pure), mu, *drift) for mu in (1.0, wet_mu))
    fit = AxleFit('rear', params, (('Fx, Fy', region),), surfaces, copied, ())
    return _replace_notes(fit, _rear_notes(tyre, fit, f_z_static))


def _least_squares(form: _Form, pts, targets, x0, lo, hi, free):
    """Fit the ``free`` coefficients so the form's outputs match ``targets`` per unit load."""
    alpha, kappa, f_z = pts
    scale = 1.0 / f_z

    def residual(z):
        x = x0.copy()
        x[free] = z
        out, _ = form.evaluate(x, alpha, kappa, f_z, 1.0)
        return np.concatenate([(out[i] - t) * scale for i, t in enumerate(targets)])

    def jacobian(z):
        x = x0.copy()
        x[free] = z
        _, jac = form.evaluate(x, alpha, kappa, f_z, 1.0)
        return np.concatenate([jac[i][:, free] * scale[:, None] for i in range(len(targets))])

    sol = least_squares(residual, x0[free], jac=jacobian, bounds=(lo[free], hi[free]),
                        method='trf', x_scale='jac', max_nfev=400)
    x = x0.copy()
    x[free] = sol.x
    return x


def _fit_simple(form: _Form, tyre: TirTyre, pts, component: str, f_z_static: float) -> SimpleMF:
    """One ``SimpleMF`` (lateral: slip = alpha, longitudinal: slip = kappa) at ``mu = 1``."""
    alpha, kappa, f_z = pts
    target = getattr(axle_mf(tyre, alpha, kappa, f_z, 1.0), component)
    slip = alpha if component == 'Fy' else kappa
    x0 = np.clip(_simple_guess(tyre, component, f_z_static), *_SIMPLE_BOUNDS)
    x = _least_squares(form, (slip, np.zeros_like(slip), f_z), (target,), x0,
                       *_SIMPLE_BOUNDS, np.ones(4, bool))
    return SimpleMF(*map(float, x))


def _simple_guess(tyre: TirTyre, component: str, f_z_axle: float) -> np.ndarray:
    """B, C, D, E of the MF itself at the static load (per unit axle load)."""
    s, f_z = tyre.scaling, 0.5 * f_z_axle
    dfz = (f_z - tyre.Fz0) / tyre.Fz0
    if component == 'Fx':
        c = tyre.longitudinal
        C, D = c.PCX1 * s.LCX, (c.PDX1 + c.PDX2 * dfz) * s.LMUX
        K = (c.PKX1 + c.PKX2 * dfz) * math.exp(c.PKX3 * dfz) * s.LKX
        E = (c.PEX1 + c.PEX2 * dfz + c.PEX3 * dfz ** 2) * s.LEX
    else:
        c = tyre.lateral
        C, D = c.PCY1 * s.LCY, (c.PDY1 + c.PDY2 * dfz) * s.LMUY
        K = c.PKY1 * tyre.Fz0 * math.sin(c.PKY4 * math.atan(f_z / (c.PKY2 * tyre.Fz0))) / f_z
        E = (c.PEY1 + c.PEY2 * dfz) * s.LEY
    return np.array([abs(K / (C * D)), C, abs(D), min(E, 1.0)])


def _rear_copy(tyre: TirTyre) -> dict:
    """The MF coefficients copied into the controller's rear form (signs made positive)."""
    s, x, y = tyre.scaling, tyre.longitudinal, tyre.lateral
    sign_y = math.copysign(1.0, y.PDY1)   # ISO files may carry mu_y < 0 (then K_y < 0 as well)
    return {'pCx1': x.PCX1 * s.LCX, 'pDx1': x.PDX1 * s.LMUX, 'pDx2': x.PDX2 * s.LMUX,
            'pEx1': min(x.PEX1 * s.LEX, 1.0), 'pKx1': x.PKX1 * s.LKX, 'pKx2': x.PKX2 * s.LKX,
            'pKx3': x.PKX3, 'pCy1': y.PCY1 * s.LCY, 'pDy1': abs(y.PDY1) * s.LMUY,
            'pDy2': sign_y * y.PDY2 * s.LMUY, 'pEy1': min(y.PEY1 * s.LEY, 1.0),
            'pKy1': abs(y.PKY1) * s.LKY, 'pKy2': y.PKY2,
            'rBx1': x.RBX1 * s.LXAL, 'rBx2': abs(x.RBX2), 'rCx1': x.RCX1,
            'rBy1': y.RBY1 * s.LYKA, 'rBy2': abs(y.RBY2), 'rCy1': y.RCY1,
            'rBy3': 0.0}   # the left tyre sees -RBY3, the mirrored right one +RBY3


# --- errors and notes -------------------------------------------------------------------------

def _surface(tyre, forces, mu, lon_pts, lat_pts, f_z_static, drift) -> SurfaceFit:
    """Errors of ``forces(alpha, kappa, f_z, mu) -> (Fx, Fy)`` against the MF on one surface."""
    errors = {}
    for component, pts in (('Fx', lon_pts), ('Fy', lat_pts)):
        i = 0 if component == 'Fx' else 1
        fit = np.asarray(forces(*pts, mu)[i]).ravel()
        err = fit - getattr(axle_mf(tyre, *pts, mu), component)
        errors[component] = ForceError(float(np.sqrt(np.mean(err ** 2))),
                                       float(np.max(np.abs(err))),
                                       mf_peak(tyre, component, f_z_static, mu))
    return SurfaceFit(mu, errors['Fx'], errors['Fy'], _check(tyre, forces, mu, *drift))


def _check(tyre, forces, mu, alpha, kappa, f_z) -> PointCheck:
    ref = axle_mf(tyre, alpha, kappa, f_z, mu)
    Fx, Fy = (float(np.asarray(v).ravel()[0]) for v in forces(alpha, kappa, f_z, mu))
    return PointCheck(alpha, kappa, f_z, mu, float(ref.Fx), Fx, float(ref.Fy), Fy)


def _front_notes(tyre: TirTyre, fit: AxleFit, forces, f_z: float) -> tuple[str, ...]:
    dry, wet = fit.surfaces
    offset = float(axle_mf(tyre, 0.0, 0.0, f_z).Fx)
    da = 1e-4
    K_mf = float(axle_mf(tyre, da, 0.0, f_z).Fy) / da
    K_fit = float(forces(da, 0.0, f_z, 1.0)[1][0]) / da
    a = math.radians(DRIFT_ALPHA_F_DEG)
    G = float(axle_mf(tyre, a, 0.05, f_z).Fx / axle_mf(tyre, 0.0, 0.05, f_z).Fx)
    alpha = np.radians(np.linspace(0.0, 60.0, 601))
    load_err = []
    for factor in FRONT_LOAD:
        peak_fit = float(np.max(forces(alpha, 0.0, factor * f_z, 1.0)[1]))
        load_err.append(peak_fit / mf_peak(tyre, 'Fy', factor * f_z, 1.0) - 1.0)
    return (
        f'wet (mu {wet.mu:g}, not fitted): the form scales the whole curve with mu, so its '
        f'cornering stiffness falls to {wet.mu:g} x; the MF keeps K_y and only lowers the peak '
        f'(B_y = K_y / (C_y D_y) grows). Fy at the drift point is {100 * wet.drift.Fy_rel:+.1f} % '
        f'off on the wet (dry {100 * dry.drift.Fy_rel:+.1f} %): the form cannot represent this.',
        f'cornering stiffness at the static load: fitted {K_fit / 1e3:.0f} kN/rad, MF '
        f'{K_mf / 1e3:.0f} kN/rad per axle ({100 * (K_fit / K_mf - 1):+.1f} %).',
        f'load sensitivity: the form is linear in F_z (no PDY2, PKY2); its peak lateral force is '
        f'{100 * load_err[0]:+.1f} % off the MF at {FRONT_LOAD[0]:g} x static load, '
        f'{100 * load_err[1]:+.1f} % at {FRONT_LOAD[1]:g} x.',
        f'no combined slip: at {DRIFT_ALPHA_F_DEG:g} deg slip angle the MF cuts Fx at kappa 0.05 '
        f'to {G:.2f} x its pure value, the form keeps all of it (irrelevant while the front '
        'rolls freely).',
        f'offset: the MF axle gives Fx = {offset:+.0f} N at zero slip (PHX1, PHX2); the form '
        'gives 0.')


def _rear_notes(tyre: TirTyre, fit: AxleFit, f_z: float) -> tuple[str, ...]:
    dry, wet = fit.surfaces
    copy_dry = fit.copied[0]
    alpha = dry.drift.alpha
    tan_excess = math.tan(alpha) / alpha - 1.0
    offset = float(axle_mf(tyre, 0.0, 0.0, f_z).Fx)
    return (
        f'combined slip: with the MF weights RBX/RBY copied (pure slip fitted) the drift point '
        f'is off by Fx {100 * copy_dry.Fx_rel:+.1f} %, Fy {100 * copy_dry.Fy_rel:+.1f} %; '
        f'fitted: Fx {100 * dry.drift.Fx_rel:+.1f} %, Fy {100 * dry.drift.Fy_rel:+.1f} %. The '
        f'form weights with alpha where the MF uses tan(alpha) ({100 * tan_excess:.0f} % more at '
        f'{math.degrees(alpha):.1f} deg) and has no REX, REY, RHX1, RHY or kappa-induced side '
        'force (RVY).',
        f'wet (mu {wet.mu:g}, not fitted): the form divides B by mu as the MF does (K does not '
        f'scale with mu), so it carries over: drift point Fx {100 * wet.drift.Fx_rel:+.1f} %, Fy '
        f'{100 * wet.drift.Fy_rel:+.1f} %; region RMS Fx {100 * wet.Fx.rms_rel:.1f} %, Fy '
        f'{100 * wet.Fy.rms_rel:.1f} % of the wet peak.',
        'curvature: one E per direction, no load dependence (PEX2, PEX3, PEY2) and no '
        f'asymmetry (PEX4, PEY3). Offsets: the MF axle gives Fx = {offset:+.0f} N at zero slip '
        '(PHX1, PHX2), the form 0; the lateral offsets (PHY, PVY) cancel between the left and '
        'the mirrored right tyre.')


def _replace_notes(fit: AxleFit, notes) -> AxleFit:
    return AxleFit(fit.axle, fit.params, fit.regions, fit.surfaces, fit.copied, tuple(notes))


def _steps(lo: float, hi: float, step: float) -> np.ndarray:
    if hi <= lo:
        return np.array([lo])
    n = max(int(round((hi - lo) / step)), 1) + 1
    return np.linspace(lo, hi, n)


def _rel(fit: float, ref: float, f_z: float) -> float:
    return (fit - ref) / abs(ref) if abs(ref) >= 0.1 * f_z else float('nan')

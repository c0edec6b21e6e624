"""Tyre forces: simplified Magic Formula (front) and MF 5.2-style combined slip (rear).

Each formula is written once with ``casadi`` operations, which return a float for floats and an
expression for symbols, so the NMPC, the equilibrium solver, the simulator and the plots evaluate
the very same body. Sign convention: a positive slip angle gives a positive lateral force, a
positive longitudinal slip (wheel faster than the ground) a positive (driving) force.
"""
from __future__ import annotations

from typing import NamedTuple

import casadi as ca

from drift_control.params import CombinedTyreParams, FrontTyreParams, SimpleMF


class TyreForces(NamedTuple):
    """Forces in the wheel frame [N]: ``Fx`` along the wheel, ``Fy`` across it."""

    Fx: object
    Fy: object


def magic_formula(x, B, C, E):
    """The Magic Formula shape ``sin(C atan(Bx - E (Bx - atan(Bx))))``, peak 1 [-]."""
    Bx = B * x
    return ca.sin(C * ca.atan(Bx - E * (Bx - ca.atan(Bx))))


def simple_force(slip, f_z, p: SimpleMF, mu):
    """Pure-slip force of the simplified Magic Formula [N].

    Parameters
    ----------
    slip : float or casadi.SX
        Slip angle [rad] or longitudinal slip [-].
    f_z : float or casadi.SX
        Vertical load [N].
    p : SimpleMF
        Coefficients; the peak is ``mu * D * f_z``.
    mu : float or casadi.SX
        Surface friction scale [-].
    """
    return mu * p.D * f_z * magic_formula(slip, p.B, p.C, p.E)


def front_forces(alpha, kappa, f_z, p: FrontTyreParams, mu) -> TyreForces:
    """Front axle forces: simplified Magic Formula in each direction, no combined-slip coupling.

    The paper keeps the front simple because the front tyres stay within their friction limit
    during a drift; the front wheel is nearly free rolling, so ``kappa`` stays small.
    """
    return TyreForces(simple_force(kappa, f_z, p.longitudinal, mu),
                      simple_force(alpha, f_z, p.lateral, mu))


def combined_forces(alpha, kappa, f_z, p: CombinedTyreParams, mu) -> TyreForces:
    """Combined-slip forces after Magic Formula 5.2 (shifts and camber terms left out) [N].

    Pure-slip forces with a load-dependent peak (``pDx2``, ``pDy2``) and stiffness, then the
    cosine weighting functions ``G_xa`` and ``G_yk``: lateral force falls as the longitudinal slip
    grows (a spinning rear wheel loses grip sideways) and vice versa.

    Parameters
    ----------
    alpha : float or casadi.SX
        Slip angle [rad].
    kappa : float or casadi.SX
        Longitudinal slip [-].
    f_z : float or casadi.SX
        Vertical load [N]; must be positive (callers regularise it, see ``vehicle.py``).
    p : CombinedTyreParams
        MF 5.2 coefficients.
    mu : float or casadi.SX
        Surface friction scale (MF ``lambda_mu``) [-].
    """
    dfz = (f_z - p.Fz0) / p.Fz0

    mu_x = mu * (p.pDx1 + p.pDx2 * dfz)
    # B = K / (C D): written per unit load so that f_z -> 0 divides by nothing
    B_x = (p.pKx1 + p.pKx2 * dfz) * ca.exp(p.pKx3 * dfz) / (p.pCx1 * mu_x)
    F_x0 = mu_x * f_z * magic_formula(kappa, B_x, p.pCx1, p.pEx1)

    mu_y = mu * (p.pDy1 + p.pDy2 * dfz)
    # MF 5.2 K_y = pKy1 Fz0 sin(2 atan(Fz / (pKy2 Fz0))), using sin(2 atan q) = 2 q / (1 + q^2)
    q = f_z / (p.pKy2 * p.Fz0)
    B_y = 2.0 * p.pKy1 / (p.pKy2 * (1.0 + q * q)) / (p.pCy1 * mu_y)
    F_y0 = mu_y * f_z * magic_formula(alpha, B_y, p.pCy1, p.pEy1)

    B_xa = p.rBx1 * ca.cos(ca.atan(p.rBx2 * kappa))
    G_xa = ca.cos(p.rCx1 * ca.atan(B_xa * alpha))
    B_yk = p.rBy1 * ca.cos(ca.atan(p.rBy2 * (alpha - p.rBy3)))
    G_yk = ca.cos(p.rCy1 * ca.atan(B_yk * kappa))
    return TyreForces(G_xa * F_x0, G_yk * F_y0)


def longitudinal_peak_slip(f_z: float, p: CombinedTyreParams, mu: float = 1.0) -> float:
    """Longitudinal slip at which the pure driving force peaks, at load ``f_z`` [-].

    Used to classify equilibria: a rear wheel past this slip is a full drift (paper section III).
    """
    return _argmax(lambda k: float(combined_forces(0.0, k, f_z, p, mu).Fx), 0.0, 1.0)


def simple_peak_slip(p: SimpleMF) -> float:
    """Slip at which a simplified Magic Formula force peaks [rad or -] (the same at any load
    and friction: they scale the force, not its shape)."""
    return _argmax(lambda x: float(magic_formula(x, p.B, p.C, p.E)), 0.0, 1.2)


def lateral_peak_slip(f_z: float, p: CombinedTyreParams, mu: float = 1.0) -> float:
    """Slip angle at which the pure lateral force peaks, at load ``f_z`` [rad]."""
    return _argmax(lambda a: float(combined_forces(a, 0.0, f_z, p, mu).Fy), 0.0, 1.2)


def _argmax(fun, lo: float, hi: float, iterations: int = 80) -> float:
    """Golden-section search for the maximum of a unimodal function on [lo, hi]."""
    ratio = (5 ** 0.5 - 1) / 2
    for _ in range(iterations):
        m1, m2 = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        if fun(m1) < fun(m2):
            lo = m1
        else:
            hi = m2
    return 0.5 * (lo + hi)

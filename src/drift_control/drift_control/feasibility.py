"""Before the car moves: where a path's sideslip profile asks for a drift the car cannot hold.

The reference selector looks up the equilibrium map at the requested sideslip and the path's
radius; beyond the map's sideslip grid it clamps (the car would drift at less than asked), and the
NMPC refuses an equilibrium that needs the steering past its lock, torque past the car's limits or
no forward speed (``equilibrium_problem``, the one rule for both): a run asking for one of those
stops pressing on in its fallback. ``reference_problems`` walks the path once, as the selector
will, and names each stretch where that would happen, with the reason. (Grid points the map's
solver found no equilibrium for are filled from their neighbours: the entry ramp crosses such a
gap between the grip and drift branches on every path, and is driven through.)
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from drift_control.signals import Direction

STEP = 0.5          # path sampling of the check [m]


@dataclass(frozen=True)
class Problem:
    """A stretch of path whose requested drift is not an equilibrium the car can hold."""

    start: float        # arc length [m] (unwrapped: the entry lap counts)
    end: float          # [m]
    beta_deg: float     # largest requested |beta| in the stretch [deg]
    radius: float       # smallest path radius in it [m]
    why: str

    def __str__(self) -> str:
        return (f's = {self.start:.1f}-{self.end:.1f} m ({self.beta_deg:.1f} deg at '
                f'R = {self.radius:.1f} m): {self.why}')


def equilibrium_problem(eq, bounds, tol: float = 1e-6) -> str | None:
    """Why the car cannot hold equilibrium ``eq`` within ``bounds`` (``ocp.Bounds``), or None."""
    if abs(eq.delta) > bounds.delta_max + tol:
        return f'steering {eq.delta:.3f} rad beyond the {bounds.delta_max:.3f} rad lock'
    if not bounds.T_R_min - tol <= eq.T_R <= bounds.T_R_max + tol:
        return (f'torque {eq.T_R:.0f} Nm outside [{bounds.T_R_min:.0f}, '
                f'{bounds.T_R_max:.0f}] Nm')
    if not eq.V > 0.0:
        return f'speed {eq.V:.2f} m/s'
    return None


def reference_problems(path, eqmap, bounds, radius_min: float, radius_max: float,
                       step: float = STEP) -> list[Problem]:
    """The stretches of ``path`` (its first lap with the entry, or all of an open path) whose
    requested sideslip has no holdable equilibrium on ``eqmap``.

    Parameters
    ----------
    path : drift_control.path.Path
    eqmap : drift_control.eqmap.EquilibriumMap
    bounds : drift_control.ocp.Bounds
        The NMPC's actuator bounds.
    radius_min, radius_max : float
        The selector's radius range [m] (``ReferenceParams``, narrowed to the map): a straighter
        path is driven on the ``radius_max`` equilibrium, blended between the sides.
    """
    entry = path.sideslip.grip_until + path.sideslip.ramp_length
    span = path.length + (entry if path.closed else 0.0)
    s = np.arange(0.0, span + 1e-9, step)
    K = np.asarray(path.curvature_at(s))
    beta = np.asarray(path.beta_at(s))
    b_max = float(eqmap.beta_abs[-1])
    top = _highest_equilibria(eqmap)
    slack = 0.5 * float(np.diff(eqmap.beta_abs).max())
    why = []
    for k, b in zip(K, beta):
        if abs(k) < 1.0 / radius_max or b <= 0.0:    # straight, or grip driving: not a drift
            why.append(None)
            continue
        R = min(max(1.0 / abs(k), radius_min), radius_max)
        b_top = top[int(np.abs(eqmap.radius - R).argmin())]
        if b > b_max + 1e-9:
            why.append(f'sideslip beyond the map\'s {np.degrees(b_max):.0f} deg '
                       f'(config/maps.yaml grid.beta_deg): clamped')
        elif b > b_top + slack:
            why.append(f'no equilibrium above {np.degrees(b_top):.1f} deg at this radius within '
                       f'the steering lock and torque limits (the map\'s edge)')
        else:
            eq, _ = eqmap.lookup(float(b), R, Direction.LEFT)
            why.append(equilibrium_problem(eq, bounds))
    return _stretches(s, K, beta, why, step)


def sideslip_limit(eqmap, bounds):
    """``limit(radius [m]) -> |beta| [rad]``: the largest sideslip the car can hold at a radius.

    Per map radius, the largest grid sideslip with a converged equilibrium within ``bounds``
    (``equilibrium_problem``); between two map radii the smaller of theirs (conservative), 0
    where only grip driving is left. The selector keeps its sideslip reference below this, so
    a lateral correction towards a tighter radius asks for less sideslip instead of steering
    past the lock (the NMPC refuses that reference and falls back). ``limit.floor`` is its
    smallest value.
    """
    delta, T_R, V = (eqmap.filled(name) for name in ('delta', 'T_R', 'V'))
    tol = 1e-6
    holdable = (eqmap.converged & (np.abs(delta) <= bounds.delta_max - tol)
                & (T_R >= bounds.T_R_min + tol) & (T_R <= bounds.T_R_max - tol) & (V > 0.0))
    beta = np.where(holdable, eqmap.beta_abs[:, None], 0.0).max(axis=0).tolist()   # per radius
    radius = np.asarray(eqmap.radius, dtype=float).tolist()

    def limit(R: float) -> float:   # asked per horizon stage: plain floats, no numpy call
        j = bisect.bisect_left(radius, R)
        if j <= 0:
            return beta[0]
        if j >= len(radius):
            return beta[-1]
        return beta[j] if radius[j] == R else min(beta[j - 1], beta[j])
    limit.floor = min(beta)   # no radius limits a sideslip at or below this
    return limit


def _highest_equilibria(eqmap) -> np.ndarray:
    """Per map radius: the largest sideslip with an equilibrium [rad] (-inf where none).
    Above it the map holds its neighbours' values, not equilibria."""
    b = np.where(eqmap.converged, eqmap.beta_abs[:, None], -np.inf)
    return b.max(axis=0)


def _stretches(s, K, beta, why, step) -> list[Problem]:
    """Consecutive samples failing for the same cause (the reason's first word), one Problem
    each, named by the first sample's reason."""
    out, start = [], None
    for k in range(len(s) + 1):
        reason = why[k] if k < len(s) else None
        if start is not None and (reason is None or reason.split()[0] != why[start].split()[0]):
            sel = slice(start, k)
            radii = 1.0 / np.maximum(np.abs(K[sel]), 1e-12)
            out.append(Problem(float(s[start]), float(s[k - 1] + step),
                               float(np.degrees(beta[sel].max())), float(radii.min()),
                               why[start]))
            start = None
        if start is None and reason is not None:
            start = k
    return out


def describe(problems: list[Problem], vehicle: str, surface: str) -> str:
    """One line per stretch, for the user before the run."""
    n = len(problems)
    head = (f'reference infeasible: the path asks {vehicle} on {surface} for a drift it cannot '
            f'hold in {n} stretch{"es" if n != 1 else ""}:')
    return '\n'.join([head] + [f'  {p}' for p in problems])


__all__ = ['Problem', 'describe', 'equilibrium_problem', 'reference_problems',
           'sideslip_limit']

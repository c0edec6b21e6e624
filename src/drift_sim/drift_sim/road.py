"""The road: a friction coefficient that varies smoothly in space, deterministic from a seed.

``mu(x, y) = mu_surface + variation * g(x, y)`` with ``g`` a normalised sum of plane waves,
``g = sum_k w_k sin(kx_k x + ky_k y + phi_k) / sum_k w_k``, so ``|g| <= 1`` holds exactly and the
field stays within ``+- variation`` (the paper's ~0.05 measured on the Aschheim proving ground).
The same body evaluates on floats, numpy arrays and casadi symbols.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from drift_sim.params import RoadParams

N_FIELD = 4   # numbers per plane wave: kx [rad/m], ky [rad/m], phase [rad], weight [-]


def friction_modes(p: RoadParams, seed: int) -> np.ndarray:
    """The field's plane waves drawn from ``seed``: array (modes, 4) of kx, ky, phase, weight.

    Wavelengths are log-uniform in ``[wavelength_min, wavelength_max]``, directions and phases
    uniform, weights uniform in [0.5, 1]; the weights are normalised to sum to one.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED]))
    lam = np.exp(rng.uniform(np.log(p.wavelength_min), np.log(p.wavelength_max), p.modes))
    heading = rng.uniform(0.0, 2.0 * np.pi, p.modes)
    k = 2.0 * np.pi / lam
    phase = rng.uniform(0.0, 2.0 * np.pi, p.modes)
    w = rng.uniform(0.5, 1.0, p.modes)
    return np.column_stack([k * np.cos(heading), k * np.sin(heading), phase, w / w.sum()])


def friction(x, y, mu_surface, variation, modes):
    """Friction coefficient at map position ``(x, y)`` [m] [-].

    Parameters
    ----------
    x, y : float, numpy.ndarray or casadi.SX
        Position in the map frame [m].
    mu_surface : float or casadi.SX
        Mean friction of the surface [-].
    variation : float or casadi.SX
        Amplitude of the variation [-].
    modes : array (n, 4) or casadi.SX of length 4 n
        Plane waves from ``friction_modes`` (weights summing to one), flattened row by row when
        symbolic.
    """
    n = modes.shape[0] if isinstance(modes, np.ndarray) and modes.ndim == 2 else modes.numel() // 4
    sin = np.sin if isinstance(x, (float, int, np.ndarray)) and isinstance(modes, np.ndarray) \
        else ca.sin
    flat = modes.reshape(-1) if isinstance(modes, np.ndarray) else modes
    g = 0.0
    for i in range(n):
        kx, ky, phase, w = (flat[N_FIELD * i + j] for j in range(N_FIELD))
        g = g + w * sin(kx * x + ky * y + phase)
    return mu_surface + variation * g

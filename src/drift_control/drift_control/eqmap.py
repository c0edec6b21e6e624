"""The equilibrium map: its file format (``maps/<surface>.npz`` + ``.json``), building and lookup.

The map holds LEFT-drift equilibria (``beta <= 0``, ``r > 0``) on a regular grid of sideslip
magnitude ``beta_abs`` [rad] and path radius ``R`` [m]; right-hand ones are their mirror images.
Arrays are stored with ``np.savez`` (no pickles) and shaped ``(n_beta, n_radius)``; the JSON file
beside it says which parameters, grid and solver settings produced it.
"""
from __future__ import annotations

import json
import logging
import math
import multiprocessing
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.interpolate import RectBivariateSpline

from drift_control.equilibrium import (SolverSettings, default_model, derivative_scale,
                                       solve_row)
from drift_control.params import (ParamError, Surface, VehicleParams, config_dir, from_dict,
                                  load_surface, load_vehicle, load_yaml, params_hash, require)
from drift_control.signals import Direction, Equilibrium

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
KINDS = ('grip', 'slight_drift', 'drift')   # stored as int8 codes 0, 1, 2
# Interpolated fields; beta comes from the query and r = V / R, so R = V / r holds exactly.
LOOKUP_FIELDS = ('V', 'omega_F', 'omega_R', 'delta', 'T_R')
STATE_FIELDS = ('V', 'beta', 'r', 'omega_F', 'omega_R', 'delta', 'T_R')
FORCE_FIELDS = ('F_xR', 'F_yF', 'F_yR', 'kappa_R', 'alpha_R')
UNITS = {'beta_abs': 'rad', 'radius': 'm', 'V': 'm/s', 'beta': 'rad', 'r': 'rad/s',
         'omega_F': 'rad/s', 'omega_R': 'rad/s', 'delta': 'rad', 'T_R': 'N m', 'F_xR': 'N',
         'F_yF': 'N', 'F_yR': 'N', 'kappa_R': '-', 'alpha_R': 'rad', 'residual': '-',
         'converged': 'bool', 'kind': f'int8 index into {list(KINDS)}'}
WARN_PERIOD_S = 5.0   # clamping warnings at most this often


class MapError(ValueError):
    """A map file is missing, unreadable or inconsistent; the message names the file."""


@dataclass(frozen=True)
class GridParams:
    """Map grid: ``[start, stop, step]``, stop included; degrees and metres at this edge only."""

    beta_deg: tuple[float, ...] = (0.0, 45.0, 1.0)
    radius_m: tuple[float, ...] = (8.0, 40.0, 1.0)

    def __post_init__(self):
        for name in ('beta_deg', 'radius_m'):
            v = getattr(self, name)
            require(len(v) == 3 and v[2] > 0 and v[1] > v[0], f'maps.grid.{name}',
                    f'expected [start, stop, step] with stop > start and step > 0, got {v}')
        require(self.beta_deg[0] >= 0.0, 'maps.grid.beta_deg', 'sideslip magnitudes are >= 0')
        require(self.radius_m[0] > 0.0, 'maps.grid.radius_m', 'radii must be positive')

    def beta_abs(self) -> np.ndarray:
        """Sideslip magnitudes [rad]."""
        return np.radians(_arange(*self.beta_deg))

    def radius(self) -> np.ndarray:
        """Path radii [m]."""
        return _arange(*self.radius_m)


@dataclass(frozen=True)
class MapParams:
    """``config/maps.yaml``: grid, continuation seed and solver settings."""

    grid: GridParams = field(default_factory=GridParams)
    seed_beta_deg: float = 30.0        # each radius row starts on the drift branch here [deg]
    solver: SolverSettings = field(default_factory=SolverSettings)


def load_map_params(path=None) -> MapParams:
    """Load ``config/maps.yaml`` (or ``path``) into MapParams."""
    path = Path(path) if path else config_dir() / 'maps.yaml'
    return from_dict(MapParams, load_yaml(path), path.name)


def _arange(start: float, stop: float, step: float) -> np.ndarray:
    n = int(math.floor((stop - start) / step + 1e-9)) + 1
    return start + step * np.arange(n)


class EquilibriumMap:
    """LEFT-drift equilibria on a (beta_abs, radius) grid with a smooth, clamped lookup.

    Parameters
    ----------
    beta_abs : numpy.ndarray
        Sideslip magnitudes [rad], increasing, shape (nb,).
    radius : numpy.ndarray
        Path radii [m], increasing, shape (nr,).
    data : dict of numpy.ndarray
        Fields of ``STATE_FIELDS + FORCE_FIELDS`` and ``converged``, ``kind``, ``residual``,
        each of shape (nb, nr); non-converged entries may hold anything.
    meta : dict
        Metadata (the JSON file's content).
    """

    def __init__(self, beta_abs, radius, data: dict, meta: dict):
        self.beta_abs = np.asarray(beta_abs, dtype=float)
        self.radius = np.asarray(radius, dtype=float)
        self.data = {k: np.asarray(v) for k, v in data.items()}
        self.meta = dict(meta)
        self.converged = self.data['converged'].astype(bool)
        self._filled = {k: fill_holes(self.data[k], self.converged, self.beta_abs, self.radius)
                        for k in LOOKUP_FIELDS}
        k = min(3, len(self.beta_abs) - 1), min(3, len(self.radius) - 1)
        self._splines = [RectBivariateSpline(self.beta_abs, self.radius, self._filled[f],
                                             kx=k[0], ky=k[1]) for f in LOOKUP_FIELDS]
        self._last_warning = -math.inf

    @property
    def converged_fraction(self) -> float:
        """Share of grid points that are equilibria [-]."""
        return float(np.mean(self.converged))

    def filled(self, name: str) -> np.ndarray:
        """A lookup field with its holes filled, shape (nb, nr)."""
        return self._filled[name]

    def lookup(self, beta_abs: float, radius: float,
               direction: Direction) -> tuple[Equilibrium, bool]:
        """The interpolated equilibrium at a sideslip magnitude and radius.

        Parameters
        ----------
        beta_abs : float
            Sideslip magnitude [rad].
        radius : float
            Path radius [m], positive.
        direction : Direction
            LEFT (``r > 0``, ``beta < 0``) or RIGHT (mirrored).

        Returns
        -------
        (Equilibrium, bool)
            The equilibrium, and True when the query was clamped to the grid or fell on a grid
            cell without a converged equilibrium (a hole, filled from its neighbours).
        """
        return self.lookup_many([(beta_abs, radius, direction)])[0]

    def lookup_many(self, queries) -> list[tuple[Equilibrium, bool]]:
        """``[lookup(beta_abs, radius, direction) for ... in queries]``, the splines evaluated
        once for all queries (point by point as one lookup would: the same values)."""
        for _, _, direction in queries:
            if direction not in (Direction.LEFT, Direction.RIGHT):
                raise ValueError(f'lookup needs Direction.LEFT or RIGHT, got {direction!r}')
        asked_b = np.array([q[0] for q in queries], dtype=float)
        asked_R = np.array([q[1] for q in queries], dtype=float)
        b, clamped_b = _clamp_many(asked_b, self.beta_abs[0], self.beta_abs[-1])
        R, clamped_r = _clamp_many(asked_R, self.radius[0], self.radius[-1])
        clamped = clamped_b | clamped_r
        if clamped.any():   # throttled: the first one of a batch says it
            k = int(np.argmax(clamped))
            self._warn_clamped(asked_b[k], asked_R[k], b[k], R[k])
        i = np.abs(self.beta_abs[None, :] - b[:, None]).argmin(axis=1)
        j = np.abs(self.radius[None, :] - R[:, None]).argmin(axis=1)
        flagged = (clamped | ~self.converged[i, j]).tolist()
        values = zip(*(s.ev(b, R).tolist() for s in self._splines))   # per query: V .. T_R
        out = []
        for bn, Rn, (_, _, direction), flag, (V, omega_F, omega_R, delta, T_R) in zip(
                b.tolist(), R.tolist(), queries, flagged, values):
            eq = Equilibrium(V, -bn, V / Rn, omega_F, omega_R, delta, T_R)
            out.append((eq if direction == Direction.LEFT else eq.mirrored(), flag))
        return out

    def _warn_clamped(self, beta_abs, radius, b, R) -> None:
        now = time.monotonic()
        if now - self._last_warning >= WARN_PERIOD_S:
            self._last_warning = now
            log.warning('equilibrium map %s: query beta_abs=%.3f rad, R=%.1f m outside the grid, '
                        'clamped to %.3f rad, %.1f m', self.meta.get('surface', '?'),
                        beta_abs, radius, b, R)

    def casadi_interpolant(self):
        """``casadi.Function`` (beta_abs [rad], R [m]) -> [V, omega_F, omega_R, delta, T_R] (LEFT).

        Cubic B-spline through the hole-filled grid, for use inside an OCP; no clamping.
        """
        import casadi as ca
        values = np.stack([self._filled[f] for f in LOOKUP_FIELDS], axis=-1)   # (nb, nr, 5)
        # casadi wants the first grid dimension fastest: Fortran order over (beta, radius)
        flat = values.transpose(1, 0, 2).reshape(-1, len(LOOKUP_FIELDS)).T.ravel(order='F')
        # a cubic B-spline needs four points per axis; a smaller grid gets a linear interpolant
        method = 'bspline' if min(len(self.beta_abs), len(self.radius)) >= 4 else 'linear'
        return ca.interpolant('equilibrium_map', method,
                              [self.beta_abs.tolist(), self.radius.tolist()], flat.tolist())


def _clamp_many(values: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """The values limited to [lo, hi], a non-finite one to ``lo`` (never hand a NaN on), and
    which of them moved (flagged)."""
    finite = np.isfinite(values)
    out = np.where(finite, np.minimum(np.maximum(values, lo), hi), lo)
    return out, ~finite | (out != values)


def fill_holes(values: np.ndarray, valid: np.ndarray, beta_abs: np.ndarray,
               radius: np.ndarray) -> np.ndarray:
    """Fill non-converged entries: linear in beta inside a row, held at the row's ends.

    Rows without a converged point are then filled the same way along the radius. The result
    is finite wherever at least one point of the map converged.
    """
    out = np.array(values, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    row_ok = valid.any(axis=0)
    for j in np.flatnonzero(row_ok):
        ok = valid[:, j]
        out[:, j] = np.interp(beta_abs, beta_abs[ok], out[ok, j])
    if row_ok.any() and not row_ok.all():
        for i in range(len(beta_abs)):
            out[i, :] = np.interp(radius, radius[row_ok], out[i, row_ok])
    return out


# --- building --------------------------------------------------------------------------------

_WORKER: dict = {}


def _init_worker(vehicle: VehicleParams) -> None:
    _WORKER['vehicle'] = vehicle
    _WORKER['model'] = default_model(vehicle)


def _solve_radius(task):
    j, radius, betas, mu, seed_beta, settings = task
    p = _WORKER['vehicle']
    return j, solve_row(betas, radius, p, mu, seed_beta, model=_WORKER['model'],
                        settings=settings)


def build_map(vehicle: VehicleParams, surface: Surface, params: MapParams = MapParams(),
              jobs: int = 1, on_row: Callable[[int], None] | None = None) -> EquilibriumMap:
    """Solve the whole grid, one radius row per task, rows in parallel on ``jobs`` processes.

    ``on_row(j)`` is called as each row finishes (a progress bar hook).
    """
    t0 = time.perf_counter()
    betas, radii = params.grid.beta_abs(), params.grid.radius()
    seed = -math.radians(params.seed_beta_deg)
    tasks = [(j, float(R), -betas, surface.mu, seed, params.solver) for j, R in enumerate(radii)]
    rows = {}
    if jobs <= 1:
        _init_worker(vehicle)
        for task in tasks:
            j, sols = _solve_radius(task)
            rows[j] = sols
            if on_row:
                on_row(j)
    else:
        # spawn, not fork: a forked worker inherits the parent's threads and signal handlers
        # (rclpy's SIGTERM handler after an in-process node), and Pool.terminate() then hangs
        with multiprocessing.get_context('spawn').Pool(jobs, _init_worker, (vehicle,)) as pool:
            for j, sols in pool.imap_unordered(_solve_radius, tasks):
                rows[j] = sols
                if on_row:
                    on_row(j)
    build_time = time.perf_counter() - t0

    model = default_model(vehicle)   # the model each worker solved (same parameters)
    shape = (len(betas), len(radii))
    data = {k: np.zeros(shape) for k in STATE_FIELDS + FORCE_FIELDS + ('residual',)}
    data['converged'] = np.zeros(shape, dtype=bool)
    data['kind'] = np.zeros(shape, dtype=np.int8)
    for j, sols in rows.items():
        for i, s in enumerate(sols):
            for k in STATE_FIELDS:
                data[k][i, j] = getattr(s.eq, k)
            for k in FORCE_FIELDS:
                data[k][i, j] = getattr(s, k)
            data['residual'][i, j] = float(np.max(np.abs(s.residual)))
            data['converged'][i, j] = s.converged
            data['kind'][i, j] = KINDS.index(s.kind)
    meta = {
        'version': FORMAT_VERSION,
        'surface': surface.name,
        'mu': surface.mu,
        'params_hash': map_hash(vehicle, surface),
        'grid': {'beta_deg': list(params.grid.beta_deg), 'radius_m': list(params.grid.radius_m),
                 'n_beta': len(betas), 'n_radius': len(radii),
                 'layout': 'arrays shaped (n_beta, n_radius); LEFT drift: beta = -beta_abs'},
        'units': UNITS,
        'kinds': list(KINDS),
        'seed_beta_deg': params.seed_beta_deg,
        'solver': {'method': 'scipy.optimize.least_squares trf + exact CasADi Jacobian, '
                             'Newton polish; continuation along beta per radius',
                   'residual_scale': derivative_scale(vehicle).tolist(),
                   'residual': 'max |x_dot[V, beta, r, omega_F, omega_R] / residual_scale|',
                   **asdict(params.solver)},
        'model': {'class': 'drift_control.vehicle.VehicleModel', 'load_passes': model.load_passes,
                  'front_wheel': model.front_wheel},
        'converged_fraction': float(np.mean(data['converged'])),
        'build_time_s': round(build_time, 3),
        'jobs': jobs,
        'built_utc': datetime.now(timezone.utc).isoformat(timespec='seconds'),
    }
    return EquilibriumMap(betas, radii, data, meta)


# --- files -----------------------------------------------------------------------------------

def map_paths(path) -> tuple[Path, Path]:
    """``(<stem>.npz, <stem>.json)`` for a map path given with either suffix or none."""
    path = Path(path)
    if path.suffix in ('.npz', '.json'):
        path = path.with_suffix('')
    return path.with_name(path.name + '.npz'), path.with_name(path.name + '.json')


def save_map(eqmap: EquilibriumMap, path) -> tuple[Path, Path]:
    """Write ``<path>.npz`` (arrays) and ``<path>.json`` (metadata); returns both paths."""
    npz, meta = map_paths(path)
    npz.parent.mkdir(parents=True, exist_ok=True)
    arrays = {'beta_abs': eqmap.beta_abs, 'radius': eqmap.radius, **eqmap.data}
    with open(npz, 'wb') as fh:
        np.savez(fh, **arrays)
    meta.write_text(json.dumps(eqmap.meta, indent=2, sort_keys=True) + '\n', encoding='utf-8')
    return npz, meta


def load_map(path, vehicle: VehicleParams | None = None,
             surface: Surface | None = None, strict: bool = False) -> EquilibriumMap:
    """Read a map and check it against the current parameters.

    Parameters
    ----------
    path : str or Path
        ``maps/<surface>`` with or without ``.npz`` / ``.json``.
    vehicle, surface : optional
        The parameters the map must match; default the project's YAML (``load_vehicle()`` and
        the surface named in the metadata).
    strict : bool
        A map built for other parameters is a MapError (else a warning, for analysis tools).

    Raises
    ------
    MapError
        A file is missing, unreadable, or its content is inconsistent.
    """
    npz, meta_path = map_paths(path)
    for f in (npz, meta_path):
        if not f.is_file():
            raise MapError(f'{f}: equilibrium map file not found (build it with '
                           f'scripts/build_maps.py)')
    try:
        meta = json.loads(meta_path.read_text(encoding='utf-8'))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MapError(f'{meta_path}: not valid JSON metadata: {err}') from None
    if not isinstance(meta, dict):
        raise MapError(f'{meta_path}: metadata must be a JSON object')
    missing = [k for k in ('version', 'surface', 'params_hash', 'grid') if k not in meta]
    if missing:
        raise MapError(f'{meta_path}: metadata lacks {missing}')
    if meta['version'] != FORMAT_VERSION:
        raise MapError(f'{meta_path}: format version {meta["version"]}, this code reads '
                       f'{FORMAT_VERSION}')
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as err:   # zipfile, pickle refusal, truncated data: all one answer
        raise MapError(f'{npz}: not a readable map archive: {type(err).__name__}: {err}') from None
    _check_arrays(npz, arrays, meta)

    _check_hash(meta, meta_path, vehicle, surface, strict)
    beta_abs, radius = arrays.pop('beta_abs'), arrays.pop('radius')
    return EquilibriumMap(beta_abs, radius, arrays, meta)


def _check_arrays(npz: Path, arrays: dict, meta: dict) -> None:
    need = ('beta_abs', 'radius', 'converged', 'kind', 'residual') + STATE_FIELDS + FORCE_FIELDS
    missing = [k for k in need if k not in arrays]
    if missing:
        raise MapError(f'{npz}: missing array(s) {missing}')
    b, r = arrays['beta_abs'], arrays['radius']
    if b.ndim != 1 or r.ndim != 1 or len(b) < 2 or len(r) < 2:
        raise MapError(f'{npz}: beta_abs and radius must be 1-D grids of >= 2 points')
    if not (np.all(np.diff(b) > 0) and np.all(np.diff(r) > 0)):
        raise MapError(f'{npz}: grid axes must be strictly increasing')
    shape = (len(b), len(r))
    grid = meta.get('grid', {})
    if (grid.get('n_beta'), grid.get('n_radius')) != shape:
        raise MapError(f'{npz}: grid {shape} does not match the metadata '
                       f'({grid.get("n_beta")}, {grid.get("n_radius")})')
    for k in need[2:]:
        if arrays[k].shape != shape:
            raise MapError(f'{npz}: array {k!r} has shape {arrays[k].shape}, expected {shape}')
    ok = arrays['converged'].astype(bool)
    if not ok.any():
        raise MapError(f'{npz}: no converged equilibrium in the map')
    for k in LOOKUP_FIELDS:
        if not np.all(np.isfinite(arrays[k][ok])):
            raise MapError(f'{npz}: non-finite {k!r} at converged points')


def map_hash(vehicle, surface) -> str:
    """The hash a map is tied to: the vehicle and surface, less what no equilibrium depends on
    (the powertrain's lag: a steady torque has reached the wheel)."""
    return params_hash(replace(vehicle, torque_lag=None), surface)


def _check_hash(meta: dict, meta_path: Path, vehicle, surface, strict: bool) -> None:
    try:
        vehicle = vehicle if vehicle is not None else load_vehicle(meta.get('vehicle'))
        surface = surface if surface is not None else load_surface(meta['surface'])
    except ParamError as err:
        raise MapError(f'{meta_path}: cannot load the parameters to check it: {err}') from None
    current = map_hash(vehicle, surface)
    # a map built while the lag was still hashed is as good if the lag is the one it had
    if meta['params_hash'] not in (current, params_hash(vehicle, surface)):
        msg = (f'{meta_path}: equilibrium map built for parameter hash {meta["params_hash"]}, '
               f'current parameters hash to {current} (surface {surface.name}, mu {surface.mu}); '
               f'the map is stale -- rebuild with scripts/build_maps.py')
        if strict:
            raise MapError(msg)
        log.warning(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


__all__ = ['EquilibriumMap', 'GridParams', 'MapError', 'MapParams', 'build_map', 'fill_holes',
           'load_map', 'load_map_params', 'map_hash', 'map_paths', 'save_map']

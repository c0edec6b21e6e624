"""Reference paths: a dense, arc-length sampled curve with curvature and a desired sideslip profile.

A path is built from YAML (``load_path``): a circle, the paper's alternating manoeuvre (a left
drift circle, a transition, a right drift circle), a figure-8, a list of curvature segments or a
polyline with smoothed curvature. Internally every path is the same thing: samples ``x, y, psi, K``
at ``s_i = i * ds`` (uniform, so ``s -> index`` is O(1)), a closed/open flag and a
``SideslipProfile``. Curvature is positive turning left; ``psi`` is the unwrapped tangent angle.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace

import numpy as np

from drift_control.params import ParamError, load_yaml, merge
from drift_control.signals import Direction

_SEGMENT_CLOSURE_TOL = 1e-3   # [m] a closed path built from segments must end where it started


def _smoothstep(u):
    """C1 ramp 0 -> 1 on u in [0, 1], clipped outside."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


@dataclass(frozen=True)
class SideslipProfile:
    """Desired sideslip magnitude along the path, with an entry phase from grip driving.

    ``beta_abs(s) = entry_beta + (beta(s) - entry_beta) * ramp(s)``, where ``ramp`` is 0 until
    ``grip_until``, rises smoothly to 1 over ``ramp_length``, and ``beta(s)`` is ``beta`` or, if
    ``knots`` are given, the piecewise-linear profile through them (periodic on a closed path).
    The entry phase is measured on the unwrapped arc length, so it happens once, on the first lap.

    Attributes
    ----------
    beta : float
        Drift sideslip magnitude [rad].
    entry_beta : float
        Sideslip magnitude while grip driving before the entry ramp [rad].
    grip_until : float
        Arc length at which the entry ramp starts [m].
    ramp_length : float
        Length of the grip-to-drift ramp [m].
    knots : tuple of (s [m], beta [rad])
        Optional profile along one lap; overrides ``beta``.
    """

    beta: float
    entry_beta: float = 0.0
    grip_until: float = 0.0
    ramp_length: float = 0.0
    knots: tuple[tuple[float, float], ...] = ()

    @property
    def entry_end(self) -> float:
        """Unwrapped arc length where the entry ramp reaches the drift sideslip [m]."""
        return self.grip_until + self.ramp_length

    def beta_abs(self, s, s_lap, length: float, closed: bool):
        """Desired |beta| [rad] at unwrapped arc length ``s`` and lap position ``s_lap`` [m]."""
        if self.knots:
            ks = np.array([k[0] for k in self.knots])
            kb = np.array([k[1] for k in self.knots])
            base = np.interp(s_lap, ks, kb, period=length if closed else None)
        else:
            base = self.beta
        if self.ramp_length > 0.0:
            w = _smoothstep((np.asarray(s) - self.grip_until) / self.ramp_length)
        else:
            w = (np.asarray(s) >= self.grip_until).astype(float)
        return self.entry_beta + (base - self.entry_beta) * w


@dataclass(frozen=True, eq=False)
class Path:
    """A reference path sampled at uniform arc length.

    Attributes
    ----------
    x, y : numpy.ndarray
        Sample positions in the map frame [m]; sample ``i`` is at ``s = i * ds``.
    psi : numpy.ndarray
        Unwrapped tangent angle [rad].
    K : numpy.ndarray
        Curvature [1/m], positive turning left (counter-clockwise).
    ds : float
        Sample spacing [m].
    closed : bool
        A closed path repeats; its last sample is ``ds`` before the first (no duplicate).
    sideslip : SideslipProfile
        Desired sideslip magnitude along ``s``.
    name : str
        For logs and plots.
    side : numpy.ndarray, optional
        Planned drift side per sample, the left weight (1 left, 0 right, in between a flip:
        ``plan_sides``); None: the side follows the curvature (the selector's ``side_band``).
    """

    x: np.ndarray
    y: np.ndarray
    psi: np.ndarray
    K: np.ndarray
    ds: float
    closed: bool
    sideslip: SideslipProfile = field(default_factory=lambda: SideslipProfile(0.0))
    name: str = ''
    side: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.x)
        if n < 3 or not (len(self.y) == len(self.psi) == len(self.K) == n):
            raise ParamError(f'path {self.name}: need >= 3 samples of equal length')
        if not (self.ds > 0.0 and all(np.all(np.isfinite(a)) for a in (self.x, self.y, self.psi,
                                                                          self.K))):
            raise ParamError(f'path {self.name}: samples must be finite and ds positive')

    @property
    def n(self) -> int:
        """Number of samples."""
        return len(self.x)

    @property
    def length(self) -> float:
        """Length of one lap (closed) or of the whole path (open) [m]."""
        return self.n * self.ds if self.closed else (self.n - 1) * self.ds

    def lap_position(self, s):
        """Arc length within the lap [m]: ``s mod length`` when closed, clipped when open."""
        if self.closed:
            return np.mod(s, self.length)
        return np.clip(s, 0.0, self.length)

    def index_at(self, s):
        """Index of the sample at or before arc length ``s`` [m]."""
        return self._segment(s)[0]

    def _segment(self, s):
        """Sample index before ``s``, the one after it, and the fraction between them."""
        u = np.asarray(self.lap_position(s)) / self.ds
        if self.closed:
            i0 = np.floor(u).astype(int)
            return np.mod(i0, self.n), np.mod(i0 + 1, self.n), u - i0
        i0 = np.clip(np.floor(u).astype(int), 0, self.n - 2)
        return i0, i0 + 1, u - i0

    def curvature_at(self, s):
        """Curvature K(s) [1/m], linear between samples."""
        i0, i1, w = self._segment(s)
        return (1.0 - w) * self.K[i0] + w * self.K[i1]

    def heading_at(self, s):
        """Tangent angle [rad], wrapped to (-pi, pi]; exact on arcs and straights."""
        i0, i1, w = self._segment(s)
        # from the sample before, not between unwrapped samples: psi jumps at a closed seam
        return wrap_angle(self.psi[i0] + w * self.ds * 0.5 * (self.K[i0] + self.K[i1]))

    def side_at(self, s):
        """Planned left weight of the drift side at ``s`` [-], linear between samples."""
        i0, i1, w = self._segment(s)
        return (1.0 - w) * self.side[i0] + w * self.side[i1]

    def beta_at(self, s):
        """Desired sideslip magnitude [rad] at unwrapped arc length ``s`` [m]."""
        return self.sideslip.beta_abs(s, self.lap_position(s), self.length, self.closed)

    def drift_beta_at(self, s):
        """The drift sideslip magnitude the entry ramps to at ``s`` [rad] (no entry ramp)."""
        return self.sideslip.beta_abs(np.maximum(s, self.sideslip.entry_end), self.lap_position(s),
                                      self.length, self.closed)

    def direction_at(self, s) -> Direction:
        """Drift direction at ``s``: the sign of the curvature."""
        return Direction(int(np.sign(self.curvature_at(s))))

    def mirrored(self) -> 'Path':
        """The path reflected about the map x axis: left turns become right turns."""
        return replace(self, y=-self.y, psi=-self.psi, K=-self.K,
                       side=None if self.side is None else 1.0 - self.side,
                       name=f'{self.name} (mirrored)')

    def with_planned_sides(self, flip_length: float, K_straight: float) -> 'Path':
        """The path with its drift sides planned (``plan_sides``)."""
        return replace(self, side=plan_sides(self.K, self.ds, self.closed, flip_length,
                                             K_straight, self.name))


def plan_sides(K, ds: float, closed: bool, flip_length: float, K_straight: float,
               name: str = '') -> np.ndarray:
    """The drift side along a path: the left weight per sample [-].

    A curve (``|K| >= K_straight``) is drifted on its own side; a straighter stretch keeps the
    side of the curves around it, or, between curves of opposite sides, flips at its middle (a
    clothoid from one side to the other: where the curvature crosses zero). Each flip is a
    smoothstep over ``flip_length`` [m] centred there: the sides are planned along the path, so
    a drift on a wide curve (small ``|K|``) is a drift on its side, not a blend of both.
    """
    K = np.asarray(K, dtype=float)
    n = len(K)
    d = np.where(K >= K_straight, 1, np.where(K <= -K_straight, -1, 0))
    if not d.any():
        return np.full(n, 0.5)   # no curve: no side (left and right blended, as without a plan)
    if closed:   # start the lap on a curve: a straight across the seam is then one stretch
        shift = int(np.flatnonzero(d)[0])
        return np.roll(_sides(np.roll(d, -shift), ds, flip_length, name, True), shift)
    return _sides(d, ds, flip_length, name, False)


def _sides(d, ds: float, flip_length: float, name: str, wrap: bool) -> np.ndarray:
    """``plan_sides`` on directions ``d`` (+1, -1, 0 straight) that start on a curve when
    ``wrap`` (a closed lap: the last stretch continues into the first sample)."""
    n = len(d)
    curved = np.flatnonzero(d)
    filled = d.copy()
    runs = np.split(np.arange(n), np.flatnonzero(np.diff((d == 0).astype(int))) + 1)
    for run in runs:
        if d[run[0]] != 0:
            continue
        before = curved[curved < run[0]]
        after = curved[curved > run[-1]]
        if wrap and not after.size:   # the lap's last stretch: the next curve is the first
            after = curved[:1]
        prev = d[before[-1]] if before.size else d[after[0]]
        nxt = d[after[0]] if after.size else prev
        mid = (run[0] + run[-1] + 1) // 2
        filled[run] = np.where(run < mid, prev, nxt) if prev != nxt else prev
    change = [c for c in np.flatnonzero(np.diff(filled)) + 1]
    if wrap and filled[-1] != filled[0]:
        change.append(n)   # a flip at the seam
    s = np.arange(n) * ds
    length = n * ds
    w = (filled + 1) / 2.0
    out = w.copy()
    for i, c in enumerate(change):
        for other in change[i + 1:]:
            gap = (other - c) * ds
            if wrap:
                gap = min(gap, length - gap)
            if gap < flip_length:
                raise ParamError(f'path {name}: flips at s = {c * ds:.1f} and {other * ds:.1f} m '
                                 f'are closer than flip_length {flip_length} m')
        a, b = w[c - 1], w[c % n]
        off = s - (c - 0.5) * ds   # the flip's centre: between samples c - 1 and c
        if wrap:
            off = (off + 0.5 * length) % length - 0.5 * length
        inside = np.abs(off) < 0.5 * flip_length
        out[inside] = a + (b - a) * _smoothstep(off[inside] / flip_length + 0.5)
    return out


def wrap_angle(a):
    """Wrap an angle to (-pi, pi] [rad]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2.0 * np.pi)


# --- builders -----------------------------------------------------------------------------------

def from_segments(segments, start=(0.0, 0.0, 0.0), ds: float = 0.1, closed: bool = False,
                  sideslip: SideslipProfile | None = None, name: str = '') -> Path:
    """Integrate a sequence of curvature segments into a path.

    Parameters
    ----------
    segments : sequence of (length, K_start, K_end)
        Segment length [m] and curvature at its start and end [1/m]; curvature is linear in
        ``s`` (an arc when equal, a clothoid when not, a straight when both are 0).
    start : (x [m], y [m], yaw [rad])
        Start pose.
    ds : float
        Target sample spacing [m]; adjusted so that it divides the total length.
    closed : bool
        The segments close on themselves; checked to ``1 mm``.
    """
    seg = np.array(segments, dtype=float).reshape(-1, 3)
    if np.any(seg[:, 0] <= 0.0):
        raise ParamError(f'path {name}: every segment needs a positive length')
    total = float(seg[:, 0].sum())
    n_int = max(int(round(total / ds)), 3)
    ds = total / n_int
    s = np.arange(n_int + 1) * ds
    edges = np.concatenate(([0.0], np.cumsum(seg[:, 0])))
    idx = np.clip(np.searchsorted(edges, s, side='right') - 1, 0, len(seg) - 1)
    u = s - edges[idx]
    length, k0, k1 = seg[idx, 0], seg[idx, 1], seg[idx, 2]
    K = k0 + (k1 - k0) * u / length
    # heading: exact integral of the piecewise-linear curvature
    turn = seg[:, 0] * 0.5 * (seg[:, 1] + seg[:, 2])
    psi_edges = start[2] + np.concatenate(([0.0], np.cumsum(turn)))
    psi = psi_edges[idx] + k0 * u + 0.5 * (k1 - k0) * u * u / length
    # positions: chords of the arc between samples (exact on arcs and straights)
    dpsi = np.diff(psi)
    chord = ds * np.sinc(dpsi / (2.0 * np.pi))       # np.sinc(x) = sin(pi x) / (pi x)
    mid = psi[:-1] + 0.5 * dpsi
    x = start[0] + np.concatenate(([0.0], np.cumsum(chord * np.cos(mid))))
    y = start[1] + np.concatenate(([0.0], np.cumsum(chord * np.sin(mid))))
    if closed:
        gap = math.hypot(x[-1] - x[0], y[-1] - y[0])
        turned = abs(math.remainder(psi[-1] - psi[0], 2.0 * math.pi))
        if gap > _SEGMENT_CLOSURE_TOL or turned > 1e-6:
            raise ParamError(f'path {name}: closed path does not close (gap {gap:.3g} m, '
                             f'heading {turned:.3g} rad)')
        x, y, psi, K = x[:-1], y[:-1], psi[:-1], K[:-1]
    return Path(x, y, psi, K, ds, closed, sideslip or SideslipProfile(0.0), name)


def circle(radius: float, direction: Direction = Direction.LEFT, start=(0.0, 0.0, 0.0),
           ds: float = 0.1, **kw) -> Path:
    """A closed circle of ``radius`` [m] starting at ``start`` tangent to its yaw."""
    if radius <= 0.0:
        raise ParamError('path.radius: must be positive')
    k = int(direction) / radius
    return from_segments([(2.0 * math.pi * radius, k, k)], start, ds, closed=True, **kw)


def alternating(radius: float, transition: float = 10.0, laps_first: float = 1.0,
                laps_second: float = 1.0, first: Direction = Direction.LEFT, entry: float = 0.0,
                start=(0.0, 0.0, 0.0), ds: float = 0.1, **kw) -> Path:
    """The paper's alternating manoeuvre: a drift circle, a transition, the opposite circle.

    Optionally a straight ``entry`` [m] with a half transition onto the first circle. The
    transition [m] is a clothoid from ``+1/R`` to ``-1/R``; 0 gives two tangent circles (an S).
    """
    k = int(first) / radius
    segs = []
    if entry > 0.0:
        segs.append((entry, 0.0, 0.0))
        if transition > 0.0:
            segs.append((0.5 * transition, 0.0, k))
    segs.append((2.0 * math.pi * radius * laps_first, k, k))
    if transition > 0.0:
        segs.append((transition, k, -k))
    segs.append((2.0 * math.pi * radius * laps_second, -k, -k))
    return from_segments(segs, start, ds, closed=False, **kw)


def _figure8_arc(radius: float, transition: float) -> float:
    """Arc angle [rad] of each lobe so that a lobe (half clothoid, arc, half clothoid) closes."""
    k, half = 1.0 / radius, 0.5 * transition

    def chord(theta):   # chord of the lobe projected on its mid-direction (zero = closed)
        segs = [(half, 0.0, k)] if half > 0 else []
        segs += [(theta * radius, k, k)] + ([(half, k, 0.0)] if half > 0 else [])
        p = from_segments(segs, ds=min(0.02, radius / 100))
        mid = 0.5 * (p.psi[-1] - p.psi[0])
        return (p.x[-1] * math.cos(mid) + p.y[-1] * math.sin(mid))

    if transition <= 0.0:
        return 2.0 * math.pi
    from scipy.optimize import brentq
    return brentq(chord, math.pi, 2.0 * math.pi, xtol=1e-12)


def figure8(radius: float, transition: float = 10.0, first: Direction = Direction.LEFT,
            start=(0.0, 0.0, 0.0), ds: float = 0.1, **kw) -> Path:
    """A closed figure-8 of two drift circles joined at the crossing by clothoid transitions.

    Starts at the crossing point (curvature 0) heading ``start`` yaw, turns ``first`` way.
    """
    k = int(first) / radius
    theta = _figure8_arc(radius, transition)
    half = 0.5 * transition
    arc = theta * radius
    if half > 0.0:
        segs = [(half, 0.0, k), (arc, k, k), (transition, k, -k), (arc, -k, -k), (half, -k, 0.0)]
    else:
        segs = [(arc, k, k), (arc, -k, -k)]
    return from_segments(segs, start, ds, closed=True, **kw)


def polyline(points, closed: bool = False, smoothing: float = 0.0, ds: float = 0.1, **kw) -> Path:
    """A path through ``points`` [m] via a smoothing spline, resampled at arc length ``ds``.

    ``smoothing`` is the spline's residual budget per point [m^2] (0 interpolates exactly).
    """
    from scipy.interpolate import splev, splprep
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 4:
        raise ParamError('path.points: need at least 4 [x, y] pairs')
    if closed and np.allclose(pts[0], pts[-1]):
        pts = pts[:-1]
    if closed:
        pts = np.vstack([pts, pts[:1]])
    tck, _ = splprep([pts[:, 0], pts[:, 1]], s=smoothing * len(pts), per=int(closed), k=3)
    u = np.linspace(0.0, 1.0, 50 * len(pts) + 1)
    dx, dy = splev(u, tck, der=1)
    seg = np.hypot(dx, dy)
    arc = np.concatenate(([0.0], np.cumsum(0.5 * (seg[1:] + seg[:-1]) * np.diff(u))))
    total = arc[-1]
    n_int = max(int(round(total / ds)), 3)
    ds = total / n_int
    s = np.arange(n_int if closed else n_int + 1) * ds
    uu = np.interp(s, arc, u)
    x, y = splev(uu, tck)
    dx, dy = splev(uu, tck, der=1)
    ddx, ddy = splev(uu, tck, der=2)
    K = (dx * ddy - dy * ddx) / np.hypot(dx, dy) ** 3
    psi = np.unwrap(np.arctan2(dy, dx))
    return Path(np.asarray(x), np.asarray(y), psi, K, ds, closed, **kw)


# --- YAML ---------------------------------------------------------------------------------------

_COMMON = {'type', 'ds', 'start', 'sideslip', 'name', 'flip_length'}
STRAIGHT_RADIUS = 100.0   # planned sides: a stretch straighter than this takes its neighbours' [m]
_TYPES = {
    'circle': {'radius', 'direction'},
    'alternating': {'radius', 'transition', 'laps_first', 'laps_second', 'first', 'entry'},
    'figure8': {'radius', 'transition', 'first'},
    'segments': {'segments', 'closed'},
    'polyline': {'points', 'closed', 'smoothing'},
}
_SIDESLIP_KEYS = {'beta_deg', 'entry_beta_deg', 'grip_until', 'ramp_length', 'knots_deg'}


def _check_keys(raw, allowed, where):
    if not isinstance(raw, dict):
        raise ParamError(f'{where}: expected a mapping, got {type(raw).__name__}')
    unknown = sorted(str(k) for k in raw if k not in allowed and not str(k).startswith('_'))
    if unknown:
        raise ParamError(f'{where}: unknown key(s) {unknown}')


def _number(raw, key, where, default=None, positive=False, nonnegative=False):
    value = raw.get(key, default)
    if value is None:
        raise ParamError(f'{where}.{key}: missing')
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ParamError(f'{where}.{key}: expected a finite number, got {value!r}')
    if positive and value <= 0:
        raise ParamError(f'{where}.{key}: must be positive, got {value!r}')
    if nonnegative and value < 0:
        raise ParamError(f'{where}.{key}: must not be negative, got {value!r}')
    return float(value)


def _direction(raw, key, where, default='left') -> Direction:
    value = raw.get(key, default)
    if value not in ('left', 'right'):
        raise ParamError(f"{where}.{key}: must be 'left' or 'right', got {value!r}")
    return Direction.LEFT if value == 'left' else Direction.RIGHT


def _sideslip(raw, where) -> SideslipProfile:
    _check_keys(raw, _SIDESLIP_KEYS, where)
    knots = tuple((float(s), math.radians(float(b))) for s, b in raw.get('knots_deg', ()))
    if 'beta_deg' not in raw and not knots:
        raise ParamError(f'{where}: needs beta_deg or knots_deg')
    return SideslipProfile(
        beta=math.radians(_number(raw, 'beta_deg', where, 0.0)),
        entry_beta=math.radians(_number(raw, 'entry_beta_deg', where, 0.0)),
        grip_until=_number(raw, 'grip_until', where, 0.0, nonnegative=True),
        ramp_length=_number(raw, 'ramp_length', where, 0.0, nonnegative=True),
        knots=knots)


def _segment(raw, where, k_prev):
    """``{length, curvature}``, ``{length, curvature_end}`` (ramp) or ``{radius, angle_deg,
    direction}``; returns (length, K_start, K_end)."""
    _check_keys(raw, {'length', 'curvature', 'curvature_end', 'radius', 'angle_deg', 'direction'},
                where)
    if 'radius' in raw:
        k = int(_direction(raw, 'direction', where)) / _number(raw, 'radius', where, positive=True)
        return (math.radians(_number(raw, 'angle_deg', where, positive=True)) / abs(k), k, k)
    length = _number(raw, 'length', where, positive=True)
    if 'curvature_end' in raw:
        return (length, k_prev, _number(raw, 'curvature_end', where))
    k = _number(raw, 'curvature', where, 0.0)
    return (length, k, k)


def load_path(raw: dict, where: str = 'path') -> Path:
    """Build a path from its YAML mapping; every error is a ParamError naming the key.

    Example::

        type: alternating          # circle | alternating | figure8 | segments | polyline
        radius: 15.0               # [m]
        transition: 10.0           # [m] clothoid between the circles
        start: [0.0, 0.0, 0.0]     # x [m], y [m], yaw [deg]
        ds: 0.1                    # sample spacing [m]
        sideslip: {beta_deg: 30.0, entry_beta_deg: 2.0, grip_until: 20.0, ramp_length: 15.0}
        flip_length: 20.0          # optional [m]: plan the drift sides along the path, each
                                   # flip over this length (``plan_sides``)
    """
    path = _build_path(raw, where)
    if 'flip_length' in raw:
        path = path.with_planned_sides(_number(raw, 'flip_length', where, positive=True),
                                       1.0 / STRAIGHT_RADIUS)
    return path


def _build_path(raw: dict, where: str) -> Path:
    _check_keys(raw, _COMMON | set().union(*_TYPES.values()), where)
    kind = raw.get('type')
    if kind not in _TYPES:
        raise ParamError(f'{where}.type: must be one of {sorted(_TYPES)}, got {kind!r}')
    _check_keys(raw, _COMMON | _TYPES[kind], where)
    start = raw.get('start', [0.0, 0.0, 0.0])
    if not (isinstance(start, (list, tuple)) and len(start) == 3):
        raise ParamError(f'{where}.start: expected [x, y, yaw_deg], got {start!r}')
    start = (float(start[0]), float(start[1]), math.radians(float(start[2])))
    kw = dict(ds=_number(raw, 'ds', where, 0.1, positive=True),
              sideslip=_sideslip(raw.get('sideslip', {'beta_deg': 0.0}), f'{where}.sideslip'),
              name=str(raw.get('name', kind)))
    if kind == 'circle':
        return circle(_number(raw, 'radius', where, positive=True),
                      _direction(raw, 'direction', where), start, **kw)
    if kind == 'alternating':
        return alternating(_number(raw, 'radius', where, positive=True),
                           _number(raw, 'transition', where, 10.0),
                           _number(raw, 'laps_first', where, 1.0, positive=True),
                           _number(raw, 'laps_second', where, 1.0, positive=True),
                           _direction(raw, 'first', where), _number(raw, 'entry', where, 0.0),
                           start, **kw)
    if kind == 'figure8':
        return figure8(_number(raw, 'radius', where, positive=True),
                       _number(raw, 'transition', where, 10.0), _direction(raw, 'first', where),
                       start, **kw)
    closed = raw.get('closed', False)
    if not isinstance(closed, bool):
        raise ParamError(f'{where}.closed: expected true/false, got {closed!r}')
    if kind == 'segments':
        segs, k_prev = [], 0.0
        for i, seg in enumerate(raw.get('segments') or []):
            segs.append(_segment(seg, f'{where}.segments[{i}]', k_prev))
            k_prev = segs[-1][2]
        if not segs:
            raise ParamError(f'{where}.segments: needs at least one segment')
        return from_segments(segs, start, closed=closed, **kw)
    if start != (0.0, 0.0, 0.0):
        raise ParamError(f'{where}.start: a polyline starts at its first point')
    return polyline(raw.get('points') or [], closed,
                    _number(raw, 'smoothing', where, 0.0), **kw)


def load_path_file(file: str | os.PathLike, overlay: dict | None = None,
                   where: str | None = None) -> Path:
    """A path file: a ``path:`` mapping (or the mapping itself); named after the file.

    ``overlay``: keys laid over the file's mapping, mappings key by key (``{'sideslip':
    {'ramp_length': 80.0}}`` changes the ramp and keeps the rest of the sideslip profile).
    ``where``: how errors name the mapping (default: the file's name).
    """
    raw = load_yaml(file)
    raw = raw.get('path', raw)
    if not isinstance(raw, dict):
        raise ParamError(f'{file}: path: expected a mapping')
    raw = dict(raw)
    raw.setdefault('name', os.path.splitext(os.path.basename(file))[0])
    return load_path(merge(raw, overlay), where or os.path.basename(file))


__all__ = ['Path', 'SideslipProfile', 'alternating', 'circle', 'figure8', 'from_segments',
           'load_path', 'load_path_file', 'polyline', 'wrap_angle']

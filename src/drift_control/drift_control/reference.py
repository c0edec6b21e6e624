"""ReferenceSelector: dynamic referencing -- the map equilibrium for the corrected path curvature.

Paper Sec. IV: the offline equilibria are selected along the path by arc length ``s_x``; a
path-following controller alters the path curvature in proportion to the lateral error ``e_y``,
and the altered curvature indexes the lookup table. Here::

    K_cmd = K(s) - (k_p e_y + k_d de_y/dt + k_i int e_y dt + b),   de_y/dt = V sin(psi + beta)

with positive gains: a car left of the path (``e_y > 0``) is asked to turn more to the right. On
a left circle the outside is ``e_y < 0``, so an outside car gets a tighter left curvature. ``b``
is the car's curvature beyond the one asked, learnt in steady drifts (``_learn_bias``).
``|K_cmd|`` is limited to the map's curvature range and rate-limited in time. The left and right
equilibria are blended with a weight that is a smoothstep in the path's curvature ``K(s)`` on
``|K| < side_band`` (the side is the path's; the correction only changes the radius) and
rate-limited in time, so a left <-> right transition passes continuously through
(beta, r, delta) = 0 and takes at least ``1 / side_rate_max`` seconds. During a flip the yaw-rate
reference carries ``-d(beta_ref)/dt`` so the course keeps turning with the path (``_course_yaw``).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields, replace
from typing import Callable

import numpy as np

from drift_control.frenet import Frenet
from drift_control.params import from_dict, load_yaml, require
from drift_control.path import Path
from drift_control.signals import Direction, Equilibrium, Reference, Validity, VehicleState

_log = logging.getLogger(__name__)

Lookup = Callable[[float, float, Direction], tuple[Equilibrium, bool]]


@dataclass(frozen=True)
class ReferenceParams:
    """Reference selector parameters (``config/reference.yaml``, section ``reference``)."""

    k_p: float                    # lateral error gain [1/m^2]
    k_d: float                    # lateral error rate gain [s/m^2]
    radius_min: float             # smallest radius of the equilibrium map [m]
    radius_max: float             # largest radius of the map; straighter blends left/right [m]
    k_i: float = 0.0              # lateral error integral gain [1/(m^2 s)]
    integral_limit: float = 1.0   # anti-windup bound on int e_y dt [m s]
    integral_band: float = 1.5    # integrate e_y only while |e_y| is below this [m] ...
    integral_beta_band: float = 0.05   # ... and |beta - beta_ref| below this [rad]
    curvature_bias_time: float = 0.0   # time constant of the learnt curvature bias [s] (0: off)
    curvature_bias_limit: float = 0.0  # bound on |b| [1/m] (0: correction_limit)
    correction_limit: float = 0.05     # bound on |K_cmd - K(s)| [1/m]
    curvature_rate_max: float = 0.5    # bound on |dK_cmd/dt| [1/(m s)]
    beta_rate_max: float = 1.0         # bound on |d beta_ref/dt| [rad/s]
    side_rate_max: float = 1.5    # left<->right blend weight rate [1/s]; a flip takes >= 1/this
    horizon_steps: int = 0        # equilibria along the predicted arc length (0: none)
    horizon_dt: float = 0.02      # time between horizon stages [s]
    side_band: float = 0.0        # |K| below which left/right blend [1/m]; 0: 1/radius_max
    side_from_path: bool = True   # drift side from the path's curvature, not the corrected one
    side_from_path_beta: float = 0.05   # ... on a straight only while the sideslip reference
                                  # is above this [rad]; in grip the corrected curvature's
    course_yaw: bool = True       # yaw-rate reference r_eq - d(beta_ref)/dt (see _course_yaw)
    course_yaw_entry: bool = False  # ... in the entry ramp too, where the NMPC steers
                                  # (``Setup.build_selector``: not in TORQUE_ONLY)
    speed_rise_max: float = 0.0   # leaving a drift (and in grip after the entry) the speed
                                  # reference rises at most this fast, in time and along the
                                  # horizon [m/s^2] (0: off); the YAML's is per unit friction
    drift_speed_rise: float = 0.0  # in a drift after the entry (not in a flip) the speed
                                  # reference rises at most this fast, in time and along the
                                  # horizon [m/s^2] (0: off); the YAML's is per unit friction
    drift_speed_fall: float = 0.0  # ... and falls ahead of a tighter curve at most this fast
                                  # along the path (_plan_speed) [m/s^2] (0: off); per friction
    catch_beta: float = 0.0       # in the entry, a slide to the drift side beyond this [rad] is
                                  # caught: the reference continues from it (0: off)
    entry_lead: float = 0.0       # in the entry the sideslip reference leads the car's sideslip
                                  # to the drift side by at most this [rad] (0: off)
    flip_radius_max: float = 0.0  # left and right blended in a flip (a straighter stretch
                                  # between curves of opposite sides): looked up at most at this
                                  # radius [m] (0: radius_max); a straight after one curve only
                                  # (an exit) is not a flip
    window_back: float = 5.0      # Frenet search window behind the last projection [m]
    window_forward: float = 15.0  # ... and ahead of it [m]
    lost_distance: float = 5.0    # beyond this distance from the path search globally [m]
    warn_interval: float = 2.0    # minimum time between two identical warnings [s]
    period: float = 0.02          # publishing period of the reference node [s]

    def __post_init__(self):
        require(0.0 < self.radius_min < self.radius_max, 'reference.radius_min',
                'need 0 < radius_min < radius_max')
        for f in fields(self):
            value = getattr(self, f.name)
            require(value >= 0.0, f'reference.{f.name}', f'must not be negative, got {value}')
        require(self.flip_radius_max == 0.0
                or self.radius_min <= self.flip_radius_max <= self.radius_max,
                'reference.flip_radius_max', 'need 0 (off) or radius_min <= it <= radius_max, '
                f'got {self.flip_radius_max}')
        require(self.horizon_dt > 0.0, 'reference.horizon_dt', 'must be positive')
        require(self.period > 0.0, 'reference.period', 'must be positive')


def load_reference_params(path) -> ReferenceParams:
    """Read the ``reference`` section of a YAML file (``config/reference.yaml``)."""
    raw = load_yaml(path)
    return from_dict(ReferenceParams, raw.get('reference', raw), 'reference')


def check_horizon_spacing(params: ReferenceParams, stage_dt: float) -> None:
    """The horizon's equilibria must be spaced as the NMPC's stages (``nmpc.stage_dt``), or the
    NMPC tracks the path's curvature and the flip at the wrong times; ParamError otherwise."""
    require(params.horizon_steps == 0
            or math.isclose(params.horizon_dt, stage_dt, rel_tol=1e-6, abs_tol=1e-9),
            'reference.horizon_dt',
            f'{params.horizon_dt} s, must equal the NMPC stage length '
            f'({stage_dt} s, nmpc.stage_dt)')


class _Throttled:
    """Log a warning at most once per ``interval`` seconds per key."""

    def __init__(self, interval: float):
        self._interval, self._last = interval, {}

    def warning(self, key: str, msg: str, *args) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -math.inf) >= self._interval:
            self._last[key] = now
            _log.warning(msg, *args)


def _blend(a: Equilibrium, b: Equilibrium, w: float) -> Equilibrium:
    """``w * a + (1 - w) * b`` field by field."""
    v = 1.0 - w
    return Equilibrium(w * a.V + v * b.V, w * a.beta + v * b.beta, w * a.r + v * b.r,
                       w * a.omega_F + v * b.omega_F, w * a.omega_R + v * b.omega_R,
                       w * a.delta + v * b.delta, w * a.T_R + v * b.T_R)


def _limit(value: float, target: float, step: float) -> float:
    """``target`` moved towards no further than ``step`` from ``value``."""
    return value + max(-step, min(step, target - value))


class ReferenceSelector:
    """Picks the NMPC reference along a path from an equilibrium map.

    Parameters
    ----------
    lookup : callable
        ``lookup(beta_abs [rad], radius [m], direction) -> (Equilibrium, clamped)``, e.g.
        ``EquilibriumMap.lookup``.
    path : Path
        The path to follow, with its desired sideslip profile.
    params : ReferenceParams
        Gains and limits.
    lookup_many : callable, optional
        ``lookup_many([(beta_abs, radius, direction), ...]) -> [(Equilibrium, clamped), ...]``,
        the same lookups in one call (``EquilibriumMap.lookup_many``: the horizon's 25 lookups
        evaluate the map's splines once).
    beta_limit : callable, optional
        ``beta_limit(radius) -> |beta|`` the car can hold there
        (``feasibility.sideslip_limit``): the sideslip reference is kept below it.
    """

    def __init__(self, lookup: Lookup, path: Path, params: ReferenceParams,
                 lookup_many: Callable | None = None,
                 beta_limit: Callable[[float], float] | None = None):
        self._lookup, self.path, self.p = lookup, path, params
        self._lookup_many = lookup_many
        self._beta_limit = beta_limit
        # at or below the limit's smallest value (its ``floor``, if it tells) nothing is limited
        self._beta_free = (getattr(beta_limit, 'floor', -math.inf) if beta_limit is not None
                           else math.inf)
        self.frenet = Frenet(path, params.window_back, params.window_forward, params.lost_distance)
        self._warn = _Throttled(params.warn_interval)
        self._last: Reference | None = None
        self._integral = 0.0
        self._bias = 0.0       # the car's curvature beyond the one asked, left drift [1/m]
        self._steady = False   # the last reference was a steady one-sided drift
        self._beta_ref = self._w = None
        self._caught = 0.0     # sideslip of a slide caught in the entry [rad]
        self.rejected = 0      # states refused as non-finite or without a pose
        self._speed_plan = self._plan_speed() if params.drift_speed_fall > 0.0 else None
        #: per path sample: a flip's stretch, where a blend is looked up at ``flip_radius_max``
        self._flips = (flip_samples(path.K, self._band, path.closed)
                       if params.flip_radius_max > 0.0 else None)

    def reset(self, s_hint: float | None = None) -> None:
        """Forget the previous cycle (new run): zero integrator, no rate limits, and a global
        search for the path position (or a local one around ``s_hint`` [m])."""
        self.frenet.reset(s_hint)
        self._last, self._integral, self._beta_ref, self._w = None, 0.0, None, None
        self._caught, self._bias, self._steady = 0.0, 0.0, False

    def side_weight(self, K: float) -> float:
        """Weight of the left equilibrium [-]: 1 for ``K >= band``, 0 for ``K <= -band``, a
        smoothstep in between (``band = side_band``, or ``1/radius_max``): the sideslip and
        yaw-rate references start and end a flip without a jump in their rates."""
        band = self._band
        u = max(0.0, min(1.0, 0.5 * (1.0 + K / band)))
        return u * u * (3.0 - 2.0 * u)

    def equilibrium(self, beta_abs: float, K_cmd: float, w: float | None = None,
                    flip: bool = True) -> tuple[Equilibrium, Direction, bool]:
        """The map equilibrium for sideslip magnitude [rad] and signed curvature [1/m].

        ``w`` is the weight of the left equilibrium (default ``side_weight(K_cmd)``); both sides
        are looked up at the radius ``1 / |K_cmd|`` limited to the map range, a blend in a
        ``flip`` at most at ``flip_radius_max``. Returns the equilibrium, the direction (NONE
        while blending) and whether the lookup clamped.
        """
        w = self.side_weight(K_cmd) if w is None else w
        radius = self._radius(K_cmd)
        if w in (0.0, 1.0):
            direction = Direction.LEFT if w == 1.0 else Direction.RIGHT
            eq, clamped = self._lookup(beta_abs, radius, direction)
            return eq, direction, clamped
        if flip:
            radius = min(radius, self._flip_radius)
        left, c_l = self._lookup(beta_abs, radius, Direction.LEFT)
        right, c_r = self._lookup(beta_abs, radius, Direction.RIGHT)
        return _blend(left, right, w), Direction.NONE, c_l or c_r

    @property
    def _band(self) -> float:
        """|K| below which left and right are blended [1/m]: ``side_band``, or the curvature
        of ``radius_max``."""
        return self.p.side_band or 1.0 / self.p.radius_max

    @property
    def _flip_radius(self) -> float:
        """The largest radius of a blended lookup [m]: a flip's speed and wheel speeds are those
        of a drift this wide, however far the map reaches for the steady curves."""
        return self.p.flip_radius_max or self.p.radius_max

    def _holdable(self, beta_abs: float, K_cmd: float, s: float) -> float:
        """The path's sideslip, or less where the car cannot hold it at this radius."""
        if self._beta_limit is None:
            return beta_abs
        limit = self._beta_limit(self._radius(K_cmd))
        if beta_abs > limit:
            self._warn.warning('limit', 'reference: sideslip %.1f deg limited to %.1f deg at '
                               's=%.1f m, R=%.1f m: beyond it the car cannot hold the drift '
                               '(steering lock or torque)', math.degrees(beta_abs),
                               math.degrees(limit), s, self._radius(K_cmd))
            return limit
        return beta_abs

    def _path_side(self, beta_abs: float, K_path: float) -> bool:
        """Whether the side comes from the path's curvature: in a drift, so the lateral
        correction cannot flip it back and forth mid-flip, and on a curve. In grip on a
        straighter stretch (``|K| < side_band``) the corrected curvature's: there the left and
        right references cancel and the correction would steer nothing."""
        p = self.p
        return p.side_from_path and (beta_abs > p.side_from_path_beta
                                     or abs(K_path) >= self._band)

    def _catch(self, state: VehicleState, s: float) -> float:
        """The sideslip of a slide the entry catches [rad] (0: none).

        A car with less rear grip than the map's starts to slide before the entry ramp asks for
        it; pulling it back to grip fights the slide (torque bang-bang, then a spin). In the
        entry, a slide to the drift side beyond ``catch_beta`` becomes the reference's floor,
        latched, and at each ``s`` at most the drift sideslip the ramp leads to there (a profile
        that falls within the entry lowers it: a floor above it would end the entry in a step);
        after the entry it lapses.
        """
        if self.p.catch_beta <= 0.0 or s >= self.path.sideslip.entry_end or self._w is None:
            self._caught = 0.0
            return 0.0
        slide = -state.beta if self._w >= 0.5 else state.beta   # a left drift has beta < 0
        drift = float(self.path.drift_beta_at(s))
        if slide > self.p.catch_beta:
            self._caught = max(self._caught, min(slide, drift))
        return min(self._caught, drift)

    def _led(self, beta_abs: float, state: VehicleState, s: float) -> float:
        """The entry's sideslip reference [rad], at most ``entry_lead`` beyond the car's own
        sideslip to the drift side: a car with more rear grip than the map's does not slide as
        the ramp asks, and a reference far ahead of it swings it wide when it does."""
        if self.p.entry_lead <= 0.0 or s >= self.path.sideslip.entry_end or self._w is None:
            return beta_abs
        slide = -state.beta if self._w >= 0.5 else state.beta   # a left drift has beta < 0
        return min(beta_abs, max(slide, 0.0) + self.p.entry_lead)

    def _radius(self, K_cmd: float) -> float:
        """The lookup radius of a curvature, limited to the map range [m]."""
        return 1.0 / max(min(abs(K_cmd), 1.0 / self.p.radius_min), 1.0 / self.p.radius_max)

    def select(self, state: VehicleState) -> Reference | None:
        """The reference for ``state``; the previous one (or None) when the state is unusable."""
        if not state.is_finite() or not state.has(Validity.POSE):
            self.rejected += 1
            self._warn.warning('state', 'reference: non-finite state or no pose, keeping the '
                               'last reference (%d refused)', self.rejected)
            return self._last
        p, last = self.p, self._last
        dt = state.stamp - last.stamp if last is not None else -1.0
        limited = 0.0 <= dt < 1.0    # no rate limit on the first call, after a gap or a reset
        dt = max(dt, 0.0) if limited else 0.0
        fp = self.frenet.project(state.x, state.y, state.yaw, state.beta)
        e_y_rate = state.V * math.sin(fp.heading_error + state.beta)
        k_max = 1.0 / p.radius_min
        # the integral holds the steady curvature offset of a left drift (the car turns less
        # tightly than its equilibrium says); a right drift needs the mirror image, so it is
        # scaled by the side, 2 w - 1, which passes through 0 mid-flip (last cycle's weight)
        side = 1.0 if self._w is None else 2.0 * self._w - 1.0
        integral = side * self._integral
        if limited and self._steady and p.curvature_bias_time > 0.0 and state.V > 1.0:
            self._learn_bias(side * (state.r / state.V - last.curvature_cmd), dt)
        correction = (p.k_p * fp.e_y + p.k_d * e_y_rate + p.k_i * integral
                      + side * self._bias)
        correction = max(-p.correction_limit, min(p.correction_limit, correction))
        K_raw = fp.K - correction
        K_cmd = max(-k_max, min(k_max, K_raw))
        saturated = K_cmd != K_raw or abs(correction) >= p.correction_limit
        # anti-windup: integrate only once the car is settled near the path and on its sideslip
        # reference (the grip phase and the entry are the P and D terms' job: an integral wound
        # up there spins the car at the entry) and only while it does not push into a limit
        settled = (abs(fp.e_y) < p.integral_band and last is not None
                   and abs(abs(state.beta) - abs(last.target.beta)) < p.integral_beta_band
                   and abs(last.target.beta) > p.integral_beta_band)
        if settled and not (saturated and fp.e_y * integral > 0.0):
            self._integral = max(-p.integral_limit,
                                 min(p.integral_limit, self._integral + side * fp.e_y * dt))
        if limited:
            K_cmd = _limit(last.curvature_cmd, K_cmd, p.curvature_rate_max * dt)
        beta_abs = self._holdable(max(float(self.path.beta_at(fp.s)), self._catch(state, fp.s)),
                                  K_cmd, fp.s)
        beta_abs = self._led(beta_abs, state, fp.s)
        if limited and self._beta_ref is not None:
            beta_abs = _limit(self._beta_ref, beta_abs, p.beta_rate_max * dt)
        self._beta_ref = beta_abs
        if not self._path_side(beta_abs, fp.K):
            w = self.side_weight(K_cmd)
        elif self.path.side is not None:   # sides planned along the path
            w = float(self.path.side_at(fp.s))
        else:
            w = self.side_weight(fp.K)
        if limited and self._w is not None:
            w = _limit(self._w, w, p.side_rate_max * dt)
        self._w = w
        horizon, weights, beta_end, K_path, (target, direction, clamped) = self._horizon(
            fp.s, state.V, correction, (K_cmd, beta_abs, w))
        clamped = clamped or abs(K_raw) > k_max
        if clamped:
            self._warn.warning('clamp', 'reference: lookup clamped (off the map grid or in a '
                               'hole) at s=%.1f m (beta %.1f deg, K %.4f 1/m)', fp.s,
                               math.degrees(beta_abs), K_raw)
        after_entry = fp.s >= self.path.sideslip.entry_end
        # leaving a drift: the sideslip falls along the horizon, or grip driving after it
        unwinding = beta_end < beta_abs - 1e-3 or beta_abs < p.side_from_path_beta
        if p.speed_rise_max > 0.0 and after_entry and unwinding:
            cap = last.target.V + p.speed_rise_max * dt if limited else math.inf
            horizon = _speed_rise(horizon, cap, p.speed_rise_max * p.horizon_dt)
            target = horizon[0]
        elif after_entry and state.V > 1.0 and horizon and not any(
                0.0 < wk < 1.0 for wk in weights):
            # the plan scales the map's speeds first: the rise starts from the last target
            if self._speed_plan is not None:
                s_k = fp.s + state.V * p.horizon_dt * np.arange(len(horizon))
                share = np.interp(self.path.lap_position(s_k), *self._speed_plan)
                horizon = tuple(_slower(e, e.V * f) if f < 1.0 else e
                                for e, f in zip(horizon, share))
            if p.drift_speed_rise > 0.0:
                cap = last.target.V + p.drift_speed_rise * dt if limited else math.inf
                horizon = _speed_rise(horizon, cap, p.drift_speed_rise * p.horizon_dt)
            target = horizon[0]
        flipping = any(0.0 < wk < 1.0 for wk in weights)
        in_use = flipping or after_entry or p.course_yaw_entry
        if p.course_yaw and in_use and len(horizon) > 1:   # needs stages
            horizon = _course_yaw(horizon, p.horizon_dt)
            target = horizon[0]
        self._steady = p.curvature_bias_time > 0.0 and self._steady_drift(
            fp, state, beta_abs, beta_end, after_entry and not flipping)
        ref = Reference(stamp=state.stamp, target=target, direction=direction, horizon=horizon,
                        curvature=fp.K, curvature_cmd=K_cmd, s=fp.s, e_y=fp.e_y,
                        heading_error=fp.heading_error, clamped=clamped,
                        horizon_curvature=K_path)
        if not ref.is_finite():   # a lookup returned NaN: never hand that on
            self.rejected += 1
            self._warn.warning('nan', 'reference: lookup gave a non-finite equilibrium at '
                               's=%.1f m, keeping the last reference', fp.s)
            return last
        self._last = ref
        return ref

    def _plan_speed(self, ds: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(s [m], share [-] <= 1) along one lap: the share of the map's drift speed that
        reaches every slower curve ahead at ``drift_speed_fall`` (the NMPC's 0.75 s horizon
        sees it too late). A share, so the lateral correction's radius keeps its own speed."""
        p, path = self.p, self.path
        s = np.arange(0.0, path.length, ds)
        K, beta = path.curvature_at(s), path.drift_beta_at(s)
        sides = path.side_at(s) if path.side is not None else [self.side_weight(k) for k in K]
        # a flip's own speed is not capped (its blended references are not a drift's); the
        # cap passes through it
        V = np.array([self.equilibrium(float(b), float(k), float(w))[0].V
                      if w in (0.0, 1.0) else math.inf for b, k, w in zip(beta, K, sides)])
        laps = 2 if path.closed else 1
        V = np.tile(V, laps)
        cap, fall = V.copy(), 2.0 * p.drift_speed_fall * ds
        for i in range(len(V) - 2, -1, -1):
            cap[i] = min(V[i], math.sqrt(cap[i + 1] ** 2 + fall))
        flip = np.isinf(V)
        return s, np.divide(cap, V, out=np.ones_like(V), where=~flip)[:len(s)]

    def _steady_drift(self, fp, state: VehicleState, beta_abs: float, beta_end: float,
                      one_sided: bool) -> bool:
        """Whether the car drifts steadily: after the entry, one side, on its sideslip
        reference, and the sideslip and the path's curvature the same over the horizon (in a
        clothoid the car's curvature lags the one asked, which is no bias)."""
        p = self.p
        if not (one_sided and beta_abs > p.integral_beta_band
                and abs(beta_end - beta_abs) < 1e-3
                and abs(abs(state.beta) - beta_abs) < p.integral_beta_band):
            return False
        ahead = fp.s + max(state.V, 0.0) * p.horizon_steps * p.horizon_dt
        return abs(float(self.path.curvature_at(ahead)) - fp.K) < 1e-3

    def _learn_bias(self, error: float, dt: float) -> None:
        """Move the curvature bias towards ``error``, the car's curvature ``r / V`` beyond the
        one asked last cycle (a left drift's sign), over ``curvature_bias_time``.

        A car that turns tighter or wider than its equilibrium says holds a steady lateral error
        the P term only shrinks; the integral of ``e_y`` removes it but also learns every
        flip's and entry's transient, and then overshoots through the next drift. The bias is
        measured on the curvature itself, only in a steady drift on its sideslip reference,
        and mirrored for a right drift as the integral is. It is bounded
        (``curvature_bias_limit``): a yaw-rate signal stuck at zero reads as a car that does not
        turn, and would otherwise pull ``b`` to ``-K``.
        """
        p = self.p
        bias = self._bias + min(1.0, dt / p.curvature_bias_time) * (error - self._bias)
        bound = p.curvature_bias_limit or p.correction_limit
        if abs(bias) > bound:   # more than the correction may ask: a yaw rate at odds with the turn
            self._warn.warning('bias', 'reference: the learnt curvature bias %.4f 1/m is at its '
                               'bound (reference.curvature_bias_limit %.4f): does the yaw rate '
                               'match the turn?', bias, bound)
            bias = math.copysign(bound, bias)
        self._bias = bias

    def _horizon(self, s, V, correction, start):
        """Equilibria at ``s + V k dt`` for k = 0..N-1 (stage 0 at ``start``), same limits,
        their left weights, the last stage's sideslip magnitude [rad], the path's own curvature
        at the stages (the NMPC's path states, ``cost.e_y``) and stage 0's ``equilibrium()``:
        (equilibrium, direction, clamped). The map is looked up once."""
        p, h = self.p, self.p.horizon_dt
        (K, beta, w) = start
        if p.horizon_steps == 0:
            return (), (w,), beta, (), self.equilibrium(beta, K, w)
        weights, queries = [w], [(beta, K, w)]
        k_max = 1.0 / p.radius_min
        # the path along the whole horizon in one call each; the limits run stage by stage
        s_all = s + max(V, 0.0) * np.arange(p.horizon_steps) * h
        K_all = self.path.curvature_at(s_all)
        s_k, K_paths = s_all[1:], K_all[1:]
        betas = self.path.beta_at(s_k)
        if self._caught > 0.0:   # a caught slide holds the stages still in the entry
            floor = np.minimum(self._caught, self.path.drift_beta_at(s_k))
            betas = np.where(s_k < self.path.sideslip.entry_end, np.maximum(betas, floor), betas)
        planned = self.path.side_at(s_k).tolist() if self.path.side is not None else None
        # _limit and side_weight written out: 24 stages a cycle, the same operations
        dK, dbeta, dw = p.curvature_rate_max * h, p.beta_rate_max * h, p.side_rate_max * h
        band = self._band
        from_path, path_beta = p.side_from_path, p.side_from_path_beta
        for k, (K_path, beta_path) in enumerate(zip(K_paths.tolist(),
                                                    np.broadcast_to(betas, s_k.shape).tolist())):
            K_k = max(-k_max, min(k_max, K_path - correction))
            K = K + max(-dK, min(dK, K_k - K))
            if beta_path > self._beta_free:
                beta_path = min(beta_path, self._beta_limit(self._radius(K)))
            beta = beta + max(-dbeta, min(dbeta, beta_path - beta))
            on_path = from_path and (beta > path_beta or abs(K_path) >= band)   # _path_side
            if on_path and planned is not None:
                side = planned[k]
            else:
                u = max(0.0, min(1.0, 0.5 * (1.0 + (K_path if on_path else K) / band)))
                side = u * u * (3.0 - 2.0 * u)
            w = w + max(-dw, min(dw, side - w))
            queries.append((beta, K, w))
            weights.append(w)
        flips = (self._flips[self.path.index_at(s_all)].tolist()
                 if self._flips is not None else None)
        stages = self._equilibria(queries, flips)
        return (tuple(eq for eq, _, _ in stages), tuple(weights), beta, tuple(K_all.tolist()),
                stages[0])

    def _equilibria(self, queries, flips=None):
        """``[equilibrium(beta_abs, K_cmd, w, flip) for ... in queries]``, the map looked up
        once (``flips``: per query, a blend in a flip; None: every blend)."""
        if self._lookup_many is None:
            return [self.equilibrium(*q, flip=flips is None or flips[k])
                    for k, q in enumerate(queries)]
        asks, plan = [], []   # map queries, and per stage: (direction, where its lookups are)
        for k, (beta_abs, K_cmd, w) in enumerate(queries):
            radius = self._radius(K_cmd)
            if w in (0.0, 1.0):
                direction = Direction.LEFT if w == 1.0 else Direction.RIGHT
                plan.append((direction, len(asks), None, w))
                asks.append((beta_abs, radius, direction))
            else:
                if flips is None or flips[k]:
                    radius = min(radius, self._flip_radius)
                plan.append((Direction.NONE, len(asks), len(asks) + 1, w))
                asks += [(beta_abs, radius, Direction.LEFT), (beta_abs, radius, Direction.RIGHT)]
        found = self._lookup_many(asks)
        out = []
        for direction, i, j, w in plan:
            if j is None:
                out.append((found[i][0], direction, found[i][1]))
            else:
                (left, c_l), (right, c_r) = found[i], found[j]
                out.append((_blend(left, right, w), direction, c_l or c_r))
        return out


def flip_samples(K, band: float, closed: bool) -> np.ndarray:
    """Per path sample: True on a straighter stretch (``|K| < band``) between curves of opposite
    sides (a flip), False on curves and on straights with a curve of one side only (an exit)."""
    d = np.where(K >= band, 1, np.where(K <= -band, -1, 0))
    reps = 2 if closed else 1   # around the lap: the curve before the seam counts

    def last_side(d):
        dd = np.tile(d, reps)
        last = np.maximum.accumulate(np.where(dd != 0, np.arange(len(dd)), -1))
        return np.where(last >= 0, dd[np.maximum(last, 0)], 0)[-len(d):]
    return (d == 0) & (last_side(d) * last_side(d[::-1])[::-1] < 0)


def _speed_rise(stages: tuple[Equilibrium, ...], cap: float,
                step: float) -> tuple[Equilibrium, ...]:
    """The stages with their speed rising at most ``step`` per stage from at most ``cap`` [m/s].

    Leaving a drift for a straight, the map's equilibria ask for the grip speed of its largest
    radius at once (9 -> 16 m/s in 2 s): the torque that asks for makes the rear slide while it
    regrips and the car runs wide. A capped stage is the same turn driven slower: speed, yaw
    rate and wheel speeds scaled together (radius and sideslip kept).
    """
    out = []
    for e in stages:
        if e.V > cap:
            e = _slower(e, cap)
        out.append(e)
        cap = e.V + step
    return tuple(out)


def _slower(e: Equilibrium, V: float) -> Equilibrium:
    """The same turn driven at ``V``: speed, yaw rate and wheel speeds scaled together,
    radius and sideslip kept."""
    f = V / e.V
    return Equilibrium(V, e.beta, e.r * f, e.omega_F * f, e.omega_R * f, e.delta, e.T_R)


def _course_yaw(stages: tuple[Equilibrium, ...], dt: float) -> tuple[Equilibrium, ...]:
    """The stages with the yaw rate that keeps the velocity direction on the path while the
    sideslip reference changes.

    The velocity direction (course) is ``psi + beta``, so its rate is ``r + d(beta)/dt``. An
    equilibrium has ``d(beta)/dt = 0`` and course rate ``r_eq = V_eq K``; when the reference's
    sideslip moves (the left <-> right flip: 60 deg in about 2 s) the yaw rate must be
    ``r_eq - d(beta_ref)/dt`` for the course to keep turning with the path. Tracking ``r_eq``
    and the moving sideslip together would turn the course by the whole sideslip change (the
    flip's lateral overshoot: 4.4 m without, 0.6 m with; an exit's 30 deg unwinding ran the
    car 3-8 m wide). The rate is a central difference along the stages. Applied while a flip
    is in the horizon and after the entry; in the entry ramp (~0.16 rad/s) only with
    ``course_yaw_entry`` (docs/tuning_log.md).
    """
    beta = [e.beta for e in stages]
    n = len(beta)
    out = []
    for k, e in enumerate(stages):
        lo, hi = max(k - 1, 0), min(k + 1, n - 1)
        beta_rate = (beta[hi] - beta[lo]) / ((hi - lo) * dt)
        out.append(Equilibrium(e.V, e.beta, e.r - beta_rate, e.omega_F, e.omega_R, e.delta,
                               e.T_R))   # not dataclasses.replace: 25 a cycle, 4x as fast
    return tuple(out)


def mirrored_reference(ref: Reference) -> Reference:
    """The reference for the mirror-image situation (left <-> right), for tests and analysis."""
    return replace(ref, target=ref.target.mirrored(), direction=Direction(-int(ref.direction)),
                   horizon=tuple(e.mirrored() for e in ref.horizon), curvature=-ref.curvature,
                   curvature_cmd=-ref.curvature_cmd, e_y=-ref.e_y,
                   heading_error=-ref.heading_error,
                   horizon_curvature=tuple(-K for K in ref.horizon_curvature))


__all__ = ['Lookup', 'ReferenceParams', 'ReferenceSelector', 'check_horizon_spacing',
           'load_reference_params', 'mirrored_reference']

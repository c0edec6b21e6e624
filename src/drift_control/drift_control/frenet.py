"""Frenet projection: a map-frame pose onto a path (arc length, lateral and heading error).

Between two samples the path is taken as the arc that leaves the first sample with the segment's
mean curvature, so the projection is exact on circles and straight lines. The search is local: a
window of fixed length around the previous projection (O(1) per call on any path length), with a
global search on the first call and whenever the car is lost. Arc length is unwrapped on a closed
path (it keeps growing lap after lap; no jump at the seam).
"""
from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np

from drift_control.path import Path

_log = logging.getLogger(__name__)

_HEADING_LENGTH = 2.0   # [m] a course error of 1 rad weighs like 2 m in a global search


_WIDE_FACTOR = 3.0   # beyond this many lost_distances off the path, search it globally


class FrenetPoint(NamedTuple):
    """A pose in path coordinates.

    Attributes
    ----------
    s : float
        Arc length [m], unwrapped (``s // path.length`` is the lap on a closed path).
    e_y : float
        Lateral error [m], positive left of the path.
    heading_error : float
        Vehicle yaw minus path tangent angle, wrapped to (-pi, pi] [rad].
    K : float
        Path curvature at ``s`` [1/m].
    distance : float
        Distance to the nearest path sample [m] (large means lost).
    """

    s: float
    e_y: float
    heading_error: float
    K: float
    distance: float


def project_on_arc(px, py, x0, y0, psi0, k):
    """Project a point on the arc leaving ``(x0, y0)`` with heading ``psi0`` and curvature ``k``.

    Returns ``(ds, e_y)``: arc length from the start point [m] (negative behind it) and signed
    normal distance [m], positive left. Exact for any constant curvature [1/m], including 0.
    """
    c, s = math.cos(psi0), math.sin(psi0)
    dx, dy = px - x0, py - y0
    a = dx * c + dy * s          # along the start tangent
    b = -dx * s + dy * c         # along the start normal (left)
    q = (a * k) ** 2 + (1.0 - b * k) ** 2
    # e_y = (1 - sqrt(q)) / k, written without the cancellation at small k
    e_y = (2.0 * b - (a * a + b * b) * k) / (1.0 + math.sqrt(q))
    if abs(k) < 1e-12:
        return a, e_y
    return math.atan2(a * k, 1.0 - b * k) / k, e_y


class Frenet:
    """Stateful projector onto one path; keep one per vehicle.

    Parameters
    ----------
    path : Path
        The path.
    window_back, window_forward : float
        Search window behind and ahead of the previous projection [m].
    lost_distance : float
        Distance to the path beyond which the local result is distrusted and a global search
        is run [m].
    """

    def __init__(self, path: Path, window_back: float = 5.0, window_forward: float = 15.0,
                 lost_distance: float = 5.0):
        self.path = path
        self._back = max(int(math.ceil(window_back / path.ds)), 1)
        self._fwd = max(int(math.ceil(window_forward / path.ds)), 1)
        if path.closed and self._back + self._fwd >= path.n // 2:
            # a window of half a lap or more would see the car ahead and behind: shrink it
            self._back, self._fwd = max(path.n // 12, 1), max(path.n // 4, 1)
        self._lost = lost_distance
        self._j: int | None = None      # unwrapped index of the previous nearest sample
        self.points_examined = 0        # samples looked at by the last call (for tests, logs)
        self.global_searches = 0
        self.lost = False               # the last call was further than lost_distance

    def reset(self, s_hint: float | None = None) -> None:
        """Forget the previous projection.

        The next call searches the whole path, or, given ``s_hint`` [m], the window around it
        (where an open path overlaps itself, e.g. at the start of the alternating manoeuvre).
        """
        self._j = None if s_hint is None else int(round(s_hint / self.path.ds))
        self.lost = False

    def _nearest(self, px, py, j_lo, j_hi, course=None):
        p = self.path
        j = np.arange(j_lo, j_hi + 1)
        i = np.mod(j, p.n) if p.closed else j
        d2 = (p.x[i] - px) ** 2 + (p.y[i] - py) ** 2
        cost = d2
        if course is not None:   # global search: where branches cross, prefer the one driven
            cost = d2 + _HEADING_LENGTH ** 2 * 2.0 * (1.0 - np.cos(course - p.psi[i]))
        self.points_examined += len(j)
        k = int(np.argmin(cost))
        return int(j[k]), math.sqrt(float(d2[k])), k in (0, len(j) - 1)

    def _global(self, px, py, course):
        p = self.path
        self.global_searches += 1
        # an open path is driven forward: a car lost after some progress is not handed back to
        # a stretch it has passed (a drift circle before the exit straight it left)
        lo = 0 if p.closed or self._j is None else min(max(self._j - self._back, 0), p.n - 1)
        j, dist, _ = self._nearest(px, py, lo, p.n - 1, course)
        if p.closed and self._j is not None:   # keep the lap nearest to the previous one
            j += p.n * round((self._j - j) / p.n)
        return j, dist

    def _local(self, px, py):
        p = self.path
        j = self._j
        for _ in range(4):   # re-centre a few times if the car left the window along the path
            lo, hi = j - self._back, j + self._fwd
            if not p.closed:
                lo, hi = max(lo, 0), min(hi, p.n - 1)
            j_new, dist, at_edge = self._nearest(px, py, lo, hi)
            at_end = not p.closed and j_new in (0, p.n - 1)
            if not at_edge or at_end:
                return j_new, dist
            j = j_new
        return None, math.inf

    def project(self, px: float, py: float, yaw: float, beta: float = 0.0) -> FrenetPoint:
        """Project the pose ``(px [m], py [m], yaw [rad])`` onto the path.

        ``beta`` [rad], the sideslip, only helps a global search tell crossing branches apart by
        the course angle ``yaw + beta``.
        """
        p = self.path
        self.points_examined = 0
        j, dist = (None, math.inf) if self._j is None else self._local(px, py)
        # A car some metres off (a drift entry cuts inside the circle) keeps its continuous
        # local projection: a global search would hand it to the other lap or branch of a path
        # that passes itself (the alternating manoeuvre, a figure-8). Only far off search anew.
        if j is None or dist > _WIDE_FACTOR * self._lost:
            if self._j is not None and not self.lost:
                _log.warning('frenet: lost the path (%.1f m off), searching globally', dist)
            j, dist = self._global(px, py, yaw + beta)
        self.lost = dist > self._lost
        self._j = j
        # the projection lies on the segment after or before the nearest sample
        j0 = j if (p.closed or j < p.n - 1) else j - 1
        ds, e_y = self._on_segment(px, py, j0)
        if ds < 0.0 and (p.closed or j0 > 0):
            ds_prev, e_prev = self._on_segment(px, py, j0 - 1)
            if ds_prev <= p.ds:
                j0, ds, e_y = j0 - 1, ds_prev, e_prev
        s = j0 * p.ds + ds
        i0 = j0 % p.n if p.closed else j0
        psi = p.psi[i0] + ds * self._seg_curvature(i0)
        heading_error = math.remainder(yaw - psi, 2.0 * math.pi)
        return FrenetPoint(s, e_y, heading_error, float(p.curvature_at(s)), dist)

    def _seg_curvature(self, i0):
        p = self.path
        i1 = (i0 + 1) % p.n if p.closed else min(i0 + 1, p.n - 1)
        return 0.5 * (p.K[i0] + p.K[i1])

    def _on_segment(self, px, py, j0):
        p = self.path
        i0 = j0 % p.n if p.closed else j0
        return project_on_arc(px, py, p.x[i0], p.y[i0], p.psi[i0], self._seg_curvature(i0))


__all__ = ['Frenet', 'FrenetPoint', 'project_on_arc']

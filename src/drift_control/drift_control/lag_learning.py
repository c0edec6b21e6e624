"""The powertrain's lag learnt while driving: the NMPC's one first-order lag, fitted online.

The NMPC models request -> wheel torque as one first-order lag (``nmpc.torque_lag``). A car's
lag and delay differ from the data sheet's (boost build-up, the ECU's task cycle, a gateway), and
a flip's torque burst that arrives late is what spins it (docs/tuning_log.md, the oracle screen).
The NMPC hands over each request it sends and the measured drive torque, each with its instant:
over a sliding window the transport delay and first-order lag whose response to the requests
best matches the measurements (least squares on a grid, the response simulated from the window's
first measurement) are this car's, and the NMPC plans with their sum, as ``scripts/identify.py``
writes it offline (``Ocp``: the lag is a runtime parameter).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from drift_control.params import require


@dataclass(frozen=True)
class LagLearningParams:
    """``torque_lag_learning:`` of ``config/nmpc.yaml``."""

    enabled: bool = False
    window: float = 2.0            # the fit's window [s]
    every: float = 0.2             # a fit this often [s]
    lag_min: float = 0.05          # the learnt lag's range (delay plus lag) [s]
    lag_max: float = 0.25
    delay_max: float = 0.1         # the fit's delays: 0 .. this [s]
    lag_step: float = 0.005        # the fit's grid, delays and lags [s]
    excitation: float = 400.0      # fit only when the requests span this much [Nm]
    signal_delay: float = 0.02     # the state's drive torque trails its stamp by this [s]
    speed_min: float = 5.0         # requests count only at this speed and above [m/s]
    gain: float = 0.5              # share of a fit's lag taken into the estimate [-]

    def __post_init__(self):
        require(self.window > 0 and self.every > 0, 'nmpc.torque_lag_learning.window/every',
                'must be positive')
        require(0 < self.lag_min < self.lag_max, 'nmpc.torque_lag_learning.lag_min/lag_max',
                'must be 0 < lag_min < lag_max')
        require(0 <= self.delay_max < self.lag_max, 'nmpc.torque_lag_learning.delay_max',
                'must be in [0, lag_max)')
        require(0 < self.lag_step <= self.lag_max - self.lag_min,
                'nmpc.torque_lag_learning.lag_step', 'must be in (0, lag_max - lag_min]')
        require(self.excitation > 0, 'nmpc.torque_lag_learning.excitation', 'must be positive')
        require(self.signal_delay >= 0, 'nmpc.torque_lag_learning.signal_delay', 'must be >= 0')
        require(self.speed_min >= 0, 'nmpc.torque_lag_learning.speed_min', 'must be >= 0')
        require(0 < self.gain <= 1, 'nmpc.torque_lag_learning.gain', 'must be in (0, 1]')


class LagLearner:
    """The powertrain lag [s] learnt from the requests sent (``request``, one a control period
    ``Ts``) and the drive torque measured (``measure``), each at its own instant; ``lag``
    starts at ``initial`` (the configured or identified one).

    A request due for a fit (every ``every`` seconds of a full window) takes the window as it
    stands; ``update`` fits it, so the data a fit sees does not depend on when it runs.
    """

    def __init__(self, params: LagLearningParams, Ts: float, initial: float):
        self.params, self.Ts = params, float(Ts)
        self.initial = min(max(float(initial), params.lag_min), params.lag_max)
        step = params.lag_step
        self._delays = np.arange(0.0, params.delay_max + 1e-9, step)
        self._taus = np.arange(step, params.lag_max + 1e-9, step)
        self.reset()

    def reset(self) -> None:
        """Back to the initial lag, nothing seen."""
        self.lag = self.initial
        self.fits = 0               # fits taken into ``lag``
        self._fitted_at = -math.inf
        self.interrupt()

    def interrupt(self) -> None:
        """The requests stop being the learnt ones (a fallback, a slow car, a gap): the window
        starts again with the next request."""
        self._requests: deque[tuple[float, float]] = deque()
        self._measured: deque[tuple[float, float]] = deque()
        self._due: tuple | None = None

    @property
    def window(self) -> tuple[int, int]:
        """Requests and measurements in the window now."""
        return len(self._requests), len(self._measured)

    def measure(self, t: float, torque: float) -> None:
        """The drive torque at the wheels at instant ``t`` [s] (older than the newest one
        measured: ignored; not finite: the window starts again)."""
        if not (math.isfinite(t) and math.isfinite(torque)):
            self.interrupt()
        elif not self._measured or t > self._measured[-1][0]:
            self._measured.append((float(t), float(torque)))

    def request(self, t: float, torque: float) -> None:
        """The request sent at ``t`` [s], held until the next; a period missed or a request not
        finite starts the window again."""
        if not (math.isfinite(t) and math.isfinite(torque)):
            self.interrupt()
            return
        if self._requests and not 0.0 < t - self._requests[-1][0] < 2.5 * self.Ts:
            self.interrupt()
        self._requests.append((float(t), float(torque)))
        while self._measured and self._measured[-1][0] > t:   # stamped in the future: never
            self._measured.pop()                                # let one block the newer ones
        start = t - self.params.window
        while len(self._requests) > 1 and self._requests[1][0] <= start - self.params.delay_max:
            self._requests.popleft()
        while self._measured and self._measured[0][0] < start:
            self._measured.popleft()
        if self._requests[0][0] <= start - self.params.delay_max \
                and t - self._fitted_at >= self.params.every - 1e-9:
            self._fitted_at = t
            self._due = (t, list(self._requests), list(self._measured))

    def update(self) -> float:
        """Fit the window taken by the last due request, if not yet fitted, and move the lag
        into the fit's interval; nothing otherwise, so calling it again is free. Returns the
        lag."""
        if self._due is not None:
            fitted = self.fit(*self._due)
            self._due = None
            if fitted is not None:
                lo, hi = fitted
                self.lag += self.params.gain * (min(max(self.lag, lo), hi) - self.lag)
                self.fits += 1
        return self.lag

    def fit(self, end: float, requests, measured) -> tuple[float, float] | None:
        """The interval of delay plus lag the window supports: ``measured`` ((t, torque)
        pairs) as the response to ``requests`` ((t, torque), each held until the next) up to
        ``end``, seen with an unknown initial torque and gain (a torque model's scale error);
        the sums whose best pair's squared error is within the 95 % bound of the best one's,
        within the range. None without enough excitation or measurements, or with the best
        pair at the grid's top edge (the car's is not within it)."""
        t_req, u = np.asarray(requests).T
        start = end - self.params.window
        if len(measured) < 8 or np.ptp(u[t_req >= start - self.params.delay_max]) \
                < self.params.excitation:
            return None
        t, m = np.asarray(measured).T
        keep = (t >= start) & (t <= end)
        t, m = t[keep], m[keep]
        if len(t) < 8:
            return None
        # the requests' integral at the instants each delay brings them to the wheel
        U = np.concatenate([[0.0], np.cumsum(u[:-1] * np.diff(t_req))])
        q = t[None, :] - self._delays[:, None]
        k = np.clip(np.searchsorted(t_req, q, side='right') - 1, 0, len(u) - 1)
        at = U[k] + u[k] * (q - t_req[k])
        h = np.diff(t)
        mean_u = np.diff(at, axis=1) / h                 # the delayed request, step by step
        decay = np.exp(-h[:, None] / self._taus[None, :])
        rise = 1.0 - decay
        shape = (len(self._delays), len(self._taus))
        # m ~ c0 x + c1 f: x the initial torque's decay, f the response from zero
        f, F = np.zeros(shape), np.empty((len(h),) + shape)
        for j in range(len(h)):   # the exact ZOH step of T' = (u - T) / tau, every pair at once
            f *= decay[j]
            f += rise[j] * mean_u[:, j, None]
            F[j] = f
        x = np.exp(-(t[1:, None] - t[0]) / self._taus[None, :])
        m = m[1:]
        ff, fx, fm = (np.einsum('jdt,jdt->dt', F, F), np.einsum('jdt,jt->dt', F, x),
                      np.einsum('jdt,j->dt', F, m))
        xx, xm = (x * x).sum(axis=0), x.T @ m
        det = ff * xx - fx * fx
        with np.errstate(divide='ignore', invalid='ignore'):
            c1 = (xx * fm - fx * xm) / det
            c0 = (ff * xm - fx * fm) / det
        sse = np.where(det > 0, float(m @ m) - c0 * xm - c1 * fm, np.inf)
        i, j = np.unravel_index(int(np.argmin(sse)), shape)
        if i == shape[0] - 1 or j == shape[1] - 1:
            return None
        # the profile over delay plus lag, and the sums within the bound (chi-square, 1 dof)
        sums = np.add.outer(np.arange(shape[0]), np.arange(1, shape[1] + 1))
        profile = np.full(sums.max() + 1, np.inf)
        np.minimum.at(profile, sums.ravel(), sse.ravel())
        bound = sse[i, j] * (1.0 + _CHI2_1_95 / (len(m) - 4))
        inside = np.flatnonzero(profile <= bound) * self.params.lag_step
        lo, hi = (min(max(v, self.params.lag_min), self.params.lag_max)
                  for v in (inside[0], inside[-1]))
        return lo, hi


_CHI2_1_95 = 3.841   # the chi-square distribution's 95 % quantile, one degree of freedom


__all__ = ['LagLearner', 'LagLearningParams']

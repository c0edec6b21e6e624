"""The powertrain's lag learnt while driving: the NMPC's one first-order lag, fitted online.

The NMPC models request -> wheel torque as one first-order lag (``nmpc.torque_lag``). A car's
lag and delay differ from the data sheet's (boost build-up, the ECU's task cycle, a gateway), and
a flip's torque burst that arrives late is what spins it (docs/tuning_log.md, the oracle screen).
Every control period brings the request sent and the measured drive torque: over a sliding
window the transport delay and first-order lag whose response to the requests best matches the
measurement (least squares on a grid, the response simulated from the window's first
measurement) are this car's, and the NMPC plans with their sum, as ``scripts/identify.py``
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
    signal_delay: float = 0.02     # the measured torque's own delay (its signal chain) [s]
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
        require(0 < self.gain <= 1, 'nmpc.torque_lag_learning.gain', 'must be in (0, 1]')


class LagLearner:
    """The powertrain lag [s] learnt from the requests and the measured torque, one sample a
    control period ``Ts`` (``add``), fitted when ``update`` finds a fit due; ``lag`` starts at
    ``initial`` (the configured or identified one)."""

    def __init__(self, params: LagLearningParams, Ts: float, initial: float):
        self.params, self.Ts = params, float(Ts)
        self.initial = min(max(float(initial), params.lag_min), params.lag_max)
        n = max(4, round(params.window / Ts))
        self._requests: deque[float] = deque(maxlen=n)
        self._measured: deque[float] = deque(maxlen=n)
        self._shift = round(params.signal_delay / Ts)   # samples the measurement trails by
        self._every = max(1, round(params.every / Ts))
        step = params.lag_step
        self._delays = np.arange(0.0, params.delay_max + 1e-9, step)
        self._taus = np.arange(step, params.lag_max + 1e-9, step)
        self._decay = np.exp(-Ts / self._taus)
        self.reset()

    def reset(self) -> None:
        """Back to the initial lag, nothing seen."""
        self.lag = self.initial
        self.fits = 0               # fits taken into ``lag``
        self._requests.clear()
        self._measured.clear()
        self._since = 0

    def add(self, request: float, measured: float | None) -> None:
        """One period: the ``request`` sent for it and the torque measured at its end (None or
        non-finite: not measured, the window starts again)."""
        if measured is None or not (math.isfinite(measured) and math.isfinite(request)):
            self._requests.clear()
            self._measured.clear()
            return
        self._requests.append(float(request))
        self._measured.append(float(measured))
        self._since += 1

    def update(self) -> float:
        """Fit the window if a fit is due (every ``every`` seconds of a full window) and take
        it into the lag; nothing otherwise, so calling it again is free. Returns the lag."""
        if self._since >= self._every and len(self._measured) == self._measured.maxlen:
            self._since = 0
            fitted = self.fit()
            if fitted is not None:
                self.lag += self.params.gain * (fitted - self.lag)
                self.fits += 1
        return self.lag

    def fit(self) -> float | None:
        """Delay plus lag of the grid's pair that best explains the window, within the range;
        None without enough excitation or with the best at the grid's top edge (the car's is
        not within it)."""
        u, m = np.asarray(self._requests), np.asarray(self._measured)
        s = self._shift
        # the measurement trails the wheel torque by s samples: T[j] is measured as m[j + s]
        u, m = u[:len(u) - s], m[s:]
        if len(m) < 4 or np.ptp(u) < self.params.excitation:
            return None
        # the requests each delay brings to the wheel, period j (held requests, delayed by a
        # fraction of a period: a blend of two)
        k, frac = np.divmod(self._delays / self.Ts, 1.0)
        k = k.astype(int)
        n = len(m)
        idx = np.arange(n)[None, :] - k[:, None]
        held = u[np.clip(idx, 0, n - 1)]
        before = u[np.clip(idx - 1, 0, n - 1)]
        delayed = (1.0 - frac[:, None]) * held + frac[:, None] * before
        a = self._decay[None, :]
        T = np.full((len(self._delays), len(self._taus)), m[0])
        sse = np.zeros_like(T)
        for j in range(1, n):   # the exact ZOH step of T' = (u - T) / tau, every pair at once:
            # u[j] was requested for the period that ends where m[j] is measured
            T = a * T + (1.0 - a) * delayed[:, j, None]
            sse += (T - m[j]) ** 2
        i, j = np.unravel_index(int(np.argmin(sse)), sse.shape)
        if i == len(self._delays) - 1 or j == len(self._taus) - 1:
            return None
        lag = float(self._delays[i] + self._taus[j])
        return min(max(lag, self.params.lag_min), self.params.lag_max)


__all__ = ['LagLearner', 'LagLearningParams']

"""Powertrain identification: the applied drive torque behind the request, delay plus lag.

The NMPC models request -> wheel torque as one first-order lag (``nmpc.torque_lag``); a log with
the requests (``/drift/command``) and the measured torque gives its delay and lag.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from drift_control.sysid import Log, correlation_time


@dataclass(frozen=True)
class LagFit:
    """Powertrain: request -> applied torque as a transport delay and a first-order lag."""

    delay: float          # [s]
    tau: float            # [s]
    tau_ci95: float       # [s]
    rms: float            # [Nm]

    @property
    def torque_lag(self) -> float:
        """The one first-order lag the NMPC models (``nmpc.torque_lag``): lag plus delay [s]."""
        return self.delay + self.tau


def fit_powertrain(log: Log, delays=np.arange(0.0, 0.205, 0.01)) -> LagFit | None:
    """Delay and lag of the applied torque behind the request; None without requests.

    For each delay on the grid the lag is a least-squares fit of the exact discrete first-order
    response to the recorded (held) requests; the delay with the least residual wins.
    """
    ok = np.isfinite(log.T_cmd)
    if ok.sum() < 100 or np.ptp(log.T_cmd[ok]) < 100.0:
        return None
    start = int(np.argmax(ok))
    u, y, dt = log.T_cmd[start:], log.T[start:], log.dt

    def response(tau, d):
        k = int(round(d / dt))
        shifted = np.concatenate([np.full(k, u[0]), u[:len(u) - k]])
        a = math.exp(-dt / tau)
        out = np.empty(len(u))
        state = y[0]
        for i, v in enumerate(shifted):      # the exact ZOH step of T' = (u - T) / tau
            out[i] = state
            state = a * state + (1.0 - a) * v
        return out

    best = None
    for d in delays:
        sol = least_squares(lambda z: response(z[0], d) - y, [0.08], bounds=([0.005], [1.0]),
                            diff_step=1e-3)
        if best is None or sol.cost < best[1].cost:
            best = (d, sol)
    d, sol = best
    res = sol.fun
    J = sol.jac
    tau_corr = correlation_time(res[:, None])
    var = float(res @ res) / max(len(res) - 2, 1) * tau_corr
    ci = 1.96 * math.sqrt(var / max(float(J[:, 0] @ J[:, 0]), 1e-30))
    return LagFit(float(d), float(sol.x[0]), ci, float(np.sqrt(np.mean(res ** 2))))

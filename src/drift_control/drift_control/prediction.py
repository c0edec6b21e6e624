"""Multi-step predictions of the single-track model from recorded states: how identification is
judged on held-out data (``drift_control.sysid``)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drift_control.params import VehicleParams
from drift_control.sysid import IdentificationError, Log, SysIdSettings, smooth
from drift_control.vehicle import X, VehicleModel


@dataclass(frozen=True)
class Prediction:
    """Open-loop predictions from measured states under measured inputs."""

    t0: np.ndarray            # start times [s]
    r: np.ndarray             # predicted yaw rate (windows, steps) [rad/s]
    beta: np.ndarray          # predicted sideslip [rad]
    r_meas: np.ndarray
    beta_meas: np.ndarray

    @property
    def rms_r(self) -> float:
        return float(np.sqrt(np.mean((self.r - self.r_meas) ** 2)))

    @property
    def rms_beta(self) -> float:
        return float(np.sqrt(np.mean((self.beta - self.beta_meas) ** 2)))


def predict(vehicle: VehicleParams, log: Log, mask: np.ndarray, mu: float,
            settings: SysIdSettings = SysIdSettings()) -> Prediction:
    """Multi-step predictions of ``horizon_s`` from every ``stride_s`` inside ``mask``.

    Each starts at the smoothed measured state and runs the model (RK4, the NMPC's front-wheel
    treatment) under the measured steering rate and applied torque; a window counts only when
    all of it lies inside ``mask``.
    """
    s = settings
    data = smooth(log, s.window_s)
    dt = log.dt
    H = int(round(s.horizon_s / dt))
    stride = max(1, int(round(s.stride_s / dt)))
    inside = np.convolve(mask.astype(int), np.ones(H + 1, int), 'valid') == H + 1
    starts = [k for k in range(0, len(inside), stride) if inside[k]]
    if not starts:
        raise IdentificationError('held-out data: no stretch of '
                                  f'{s.horizon_s:.2f} s to predict over')
    model = VehicleModel(vehicle, 1, 'free_rolling')
    sim = model.discrete(dt, 2).mapaccum(H)
    theta = np.tile([[0.0], [mu]], (1, H))
    r, beta = [], []
    for k in starts:
        traj = np.asarray(sim(data.x[k], data.u[k:k + H].T, theta))
        r.append(traj[X.R])
        beta.append(traj[X.BETA])
    idx = np.array(starts)[:, None] + np.arange(1, H + 1)[None, :]
    return Prediction(log.t[starts], np.array(r), np.array(beta), data.x[idx, X.R],
                      data.x[idx, X.BETA])

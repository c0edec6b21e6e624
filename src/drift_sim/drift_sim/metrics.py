"""Run metrics on time series (pure numpy): tracking, path error, spin, time in drift, timing.

Used by ``scripts/simulate.py`` on the simulator's ground truth and by the run-report tool on
recorded bags; every function takes arrays sampled at the same times ``t`` [s].
"""
from __future__ import annotations

import math

import numpy as np

SPIN_BETA = math.radians(75.0)   # |beta| beyond this the car has spun [rad] ...
SPIN_MIN_SPEED = 1.0             # ... at this speed or more [m/s]: a stopped car's sideslip is
                                 # the direction of its last creep, not a spin


def in_windows(t, windows) -> np.ndarray:
    """Boolean mask of the samples of ``t`` inside any ``[t0, t1)`` window."""
    t = np.asarray(t, dtype=float)
    mask = np.zeros(t.shape, dtype=bool)
    for t0, t1 in windows:
        mask |= (t >= t0) & (t < t1)
    return mask


def settled_windows(t, beta_ref, settle: float, drift_beta: float,
                    band: float = math.radians(1.0)) -> list[list[float]]:
    """Steady-drift windows found from the reference: where the sideslip reference has stayed
    within ``band`` [rad] of one drift value (``|beta_ref| > drift_beta``, one side) for at
    least ``settle`` seconds. Judges a course with many flips (a figure-8) on the parts
    between them, wherever a plant's speed puts the flips in time."""
    t, beta_ref = np.asarray(t, dtype=float), np.asarray(beta_ref, dtype=float)
    windows, start, open_at = [], None, None
    for i in range(len(t) + 1):
        b = beta_ref[i] if i < len(t) else math.nan
        drifting = abs(b) > drift_beta     # False for NaN (no reference yet, or the end)
        if start is None or not drifting or abs(b - beta_ref[start]) > band:
            if open_at is not None:
                windows.append([float(t[open_at]), float(t[i - 1])])
            start, open_at = (i if drifting else None), None
        elif open_at is None and t[i] - t[start] >= settle:
            open_at = i
    return windows


def rms(values) -> float:
    """Root mean square; NaN for no samples."""
    values = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(values ** 2))) if values.size else math.nan


def beta_rms_error(t, beta, beta_ref, windows) -> float:
    """RMS sideslip tracking error inside the steady-drift windows [rad]."""
    mask = in_windows(t, windows)
    return rms((np.asarray(beta) - np.asarray(beta_ref))[mask])


def max_abs_after(t, values, t_from: float) -> float:
    """Largest ``|value|`` at ``t >= t_from`` (e.g. the lateral error after the transient)."""
    t, values = np.asarray(t), np.asarray(values)
    sel = np.abs(values[t >= t_from])
    return float(sel.max()) if sel.size else math.nan


def max_abs_in_windows(t, values, windows) -> float:
    """Largest ``|value|`` inside the windows (e.g. the lateral error in the steady parts)."""
    sel = np.abs(np.asarray(values, dtype=float)[in_windows(t, windows)])
    return float(sel.max()) if sel.size else math.nan


def exit_time(t, beta, beta_ref, grip_beta: float = math.radians(3.0)) -> float:
    """Time to leave the drift for grip driving [s]: from the sideslip reference's last moment
    on its drift value (within 1 deg of its largest magnitude) to the first sample from which
    ``|beta|`` stays below ``grip_beta`` to the end. NaN when the run does not end in grip
    (reference or car)."""
    t, beta = np.asarray(t, dtype=float), np.abs(np.asarray(beta, dtype=float))
    ref = np.abs(np.asarray(beta_ref, dtype=float))
    finite = np.isfinite(ref)
    if not finite.any() or not ref[finite][-1] < grip_beta:
        return math.nan
    on_drift = np.flatnonzero(finite & (ref >= np.nanmax(ref) - math.radians(1.0)))
    above = np.flatnonzero(~(beta < grip_beta))
    if not on_drift.size or (above.size and above[-1] == len(t) - 1):
        return math.nan
    start = on_drift[-1]
    end = max(above[-1] + 1, start) if above.size else start
    return float(t[end] - t[start])


def transition_time(t, beta, threshold: float) -> float:
    """Time to flip the drift: from the last ``|beta| > threshold`` on one side to the first on
    the other side [s]; NaN when the run has no such flip."""
    t, beta = np.asarray(t, dtype=float), np.asarray(beta, dtype=float)
    side = np.where(beta > threshold, 1, np.where(beta < -threshold, -1, 0))
    idx = np.flatnonzero(side)
    for a, b in zip(idx, idx[1:]):
        if side[a] != side[b]:
            return float(t[b] - t[a])
    return math.nan


def spin_time(t, beta, threshold: float = SPIN_BETA, V=None) -> float:
    """First time |beta| exceeds ``threshold`` [s], at ``SPIN_MIN_SPEED`` or more when the
    speed ``V`` is given; NaN when the car never spun."""
    spun = np.abs(np.asarray(beta)) > threshold
    if V is not None:
        spun &= np.asarray(V) >= SPIN_MIN_SPEED
    idx = np.flatnonzero(spun)
    return float(np.asarray(t)[idx[0]]) if idx.size else math.nan


def time_in_drift(t, beta, threshold: float) -> float:
    """Total time with ``threshold < |beta| <= SPIN_BETA`` [s] (sample-and-hold)."""
    t, beta = np.asarray(t, dtype=float), np.abs(np.asarray(beta, dtype=float))
    if t.size < 2:
        return 0.0
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2]))
    return float(np.sum(dt[(beta > threshold) & (beta <= SPIN_BETA)]))


def laps(t, s, windows, lap_length: float) -> float:
    """Laps of the path driven inside the windows: arc length travelled / lap length [-]."""
    t, s = np.asarray(t, dtype=float), np.asarray(s, dtype=float)
    travelled = 0.0
    for t0, t1 in windows:
        sel = s[(t >= t0) & (t < t1)]
        if sel.size > 1:
            travelled += float(sel[-1] - sel[0])
    return travelled / lap_length if lap_length > 0 else math.nan


def steer_proposal_diff(t, delta_proposed, delta_applied, windows,
                        name: str = 'steer_proposal') -> dict:
    """The NMPC's steering proposal against the applied (driver's) steering in the windows.

    The paper's semi-automated comparison (Sec. VI-B): in TORQUE_ONLY mode ``command.delta`` is
    what the NMPC would steer, the driver's angle is what the car got. The NMPC plans from the
    measured angle and holds it ``torque_only_hold_stages``, so ``command.delta`` is at most
    one control period of steering rate away from it (``delta_dot_max Ts``, 1.15 deg); the
    steering it plans at the end of its horizon shows how far it would take the wheel.

    Parameters
    ----------
    t : array
        Sample times [s].
    delta_proposed, delta_applied : array
        Proposed and applied road-wheel angles [rad]; NaN samples (no command yet) are skipped.
    windows : sequence of (t0, t1)
        Steady-drift windows [s].
    name : str
        Key prefix: ``'steer_proposal'`` for ``command.delta``, ``'steer_plan'`` for the steering
        the NMPC plans at the end of its horizon.

    Returns
    -------
    dict
        ``<name>_diff_max_deg`` and ``<name>_diff_rms_deg`` [deg]; NaN without samples.
    """
    diff = np.asarray(delta_proposed, dtype=float) - np.asarray(delta_applied, dtype=float)
    sel = diff[in_windows(t, windows) & np.isfinite(diff)]
    return {
        f'{name}_diff_max_deg': math.degrees(float(np.abs(sel).max())) if sel.size else math.nan,
        f'{name}_diff_rms_deg': math.degrees(rms(sel)),
    }


def steady_windows(spec_metrics, t, beta_ref) -> list:
    """A scenario's steady windows (``metrics:`` of its spec): its fixed ones, or with
    ``settle`` the settled parts of the reference (``settled_windows``), as the closed loop
    judges them."""
    if spec_metrics.settle > 0.0:
        return settled_windows(t, beta_ref, spec_metrics.settle,
                               math.radians(spec_metrics.drift_beta_deg))
    return [list(w) for w in spec_metrics.steady]


def torque_smoothness(t, T_cmd, windows, period: float = 0.02) -> tuple[float, float]:
    """Std and mean |change| per control ``period`` [s] of the torque request in the windows
    [Nm]; NaN without a window. ``T_cmd``: the request held at each sample of ``t``."""
    t, T_cmd = np.asarray(t, dtype=float), np.asarray(T_cmd, dtype=float)
    if len(t) < 2:
        return math.nan, math.nan
    step = max(1, int(round(period / (t[1] - t[0]))))
    values, changes = [], []
    for start, end in windows:
        T = T_cmd[(t >= start) & (t < end)][::step]
        T = T[np.isfinite(T)]
        values.append(T)
        changes.append(np.abs(np.diff(T)))
    values, changes = np.concatenate(values or [[]]), np.concatenate(changes or [[]])
    if not changes.size:
        return math.nan, math.nan
    return float(np.std(values)), float(np.mean(changes))


def percentiles(values, qs=(50, 99)) -> dict:
    """``{'p50': ..., 'p99': ...}`` of ``values``; NaN for no samples."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return {f'p{q}': float(np.percentile(values, q)) if values.size else math.nan for q in qs}


def summary(t, beta, beta_ref, e_y, windows, transient_end: float, drift_beta: float,
            solve_times=(), wall_time: float = math.nan, V=None) -> dict:
    """The standard metrics of one run, as a JSON-ready dict (angles in degrees, suffixed);
    with the speed ``V`` a spin counts only while the car moves."""
    t = np.asarray(t, dtype=float)
    spun_at = spin_time(t, beta, V=V)
    duration = float(t[-1] - t[0]) if t.size > 1 else 0.0
    solve = percentiles(np.asarray(solve_times, dtype=float) * 1e3)
    return {
        'beta_rms_error_deg': math.degrees(beta_rms_error(t, beta, beta_ref, windows)),
        'max_abs_e_y_m': max_abs_after(t, e_y, transient_end),
        'spun': bool(math.isfinite(spun_at)),
        'spin_time_s': None if math.isnan(spun_at) else spun_at,
        'time_in_drift_s': time_in_drift(t, beta, drift_beta),
        'solve_time_ms_p50': solve['p50'],
        'solve_time_ms_p99': solve['p99'],
        'sim_duration_s': duration,
        'real_time_factor': duration / wall_time if wall_time and wall_time > 0 else math.nan,
    }

"""Run reports: metrics, a Markdown summary and paper-style figures from any recorded run.

Works on a bag from the simulator or from a car: states, references, commands and NMPC status are
read by topic (``drift_tools.timeseries``); the metric definitions are the simulator's
(``drift_sim.metrics``), so a bag and an in-process run are judged alike.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from drift_sim import metrics
from drift_tools.timeseries import RunSeries, resample

BUDGET_S = 0.020             # one NMPC cycle [s]
DRIFT_BETA = math.radians(10.0)   # |beta| above this counts as drifting [rad]
SETTLE_S = 3.0               # after the reference reaches its plateau, judge from here on [s]


def steady_windows(run: RunSeries, settle: float = SETTLE_S) -> tuple[list, float]:
    """Steady-drift windows derived from the reference, and the end of the entry transient.

    A window is a stretch where the reference sideslip stays within 1 deg of its largest value
    and the drift direction does not change; it starts ``settle`` seconds into that stretch.
    """
    ref = run.reference
    if not len(ref.get('t', ())):
        return [], 0.0
    t, beta = ref['t'], np.abs(ref['beta'])
    plateau = (beta >= beta.max() - math.radians(1.0)) & (beta > DRIFT_BETA)
    direction = ref['direction']
    windows, start = [], None
    for i in range(len(t) + 1):
        inside = i < len(t) and plateau[i] and (start is None or direction[i] == direction[start])
        if inside and start is None:
            start = i
        elif not inside and start is not None:
            if t[i - 1] - t[start] > settle:
                windows.append([float(t[start] + settle), float(t[i - 1])])
            start = i if i < len(t) and plateau[i] else None
    transient_end = windows[0][0] if windows else float(t[-1])
    return windows, transient_end


def run_metrics(run: RunSeries, windows=None, transient_end=None, wall_time=math.nan) -> dict:
    """The standard metrics of a run (``drift_sim.metrics.summary``) plus command statistics."""
    if windows is None or transient_end is None:
        auto_w, auto_end = steady_windows(run)
        windows = auto_w if windows is None else windows
        transient_end = auto_end if transient_end is None else transient_end
    src = run.truth if len(run.truth.get('t', ())) else run.state
    if not len(src.get('t', ())):
        raise ValueError('the run has no vehicle state: nothing to judge')
    t = src['t']
    beta_ref = resample(run.reference, t, 'beta')
    e_y = resample(run.reference, t, 'e_y')
    solve = run.status.get('solve_time', np.zeros(0))
    out = metrics.summary(t, src['beta'], np.nan_to_num(beta_ref), np.nan_to_num(e_y), windows,
                          transient_end, DRIFT_BETA, solve_times=solve, wall_time=wall_time,
                          V=src.get('V'))
    out.update({
        'steady_windows_s': windows,
        'transient_end_s': transient_end,
        'state_source': 'ground truth (/sim/state)' if src is run.truth else '/vehicle/state',
        'mean_abs_beta_steady_deg': _mean_abs_deg(t, src['beta'], windows),
        'solve_time_ms_max': float(np.max(solve) * 1e3) if len(solve) else math.nan,
        'solve_p99_over_budget': float(np.percentile(solve, 99) / BUDGET_S) if len(solve) else math.nan,
        'nmpc_cycles': int(len(solve)),
        'nmpc_not_ok': int(np.sum(run.status.get('status', np.zeros(0)) != 0)),
        'commands': int(len(run.command.get('t', ()))),
    })
    return out


def _mean_abs_deg(t, beta, windows) -> float:
    mask = metrics.in_windows(t, windows)
    return float(np.degrees(np.mean(np.abs(beta[mask])))) if mask.any() else math.nan


def markdown(name: str, m: dict, figures: list[str]) -> str:
    """A short Markdown report of the metrics with the figures linked."""
    rows = [
        ('sideslip RMS error in steady drift', f"{m['beta_rms_error_deg']:.2f} deg"),
        ('mean abs. sideslip in steady drift', f"{m['mean_abs_beta_steady_deg']:.1f} deg"),
        ('max abs. e_y after the entry transient', f"{m['max_abs_e_y_m']:.2f} m"),
        ('spun', 'yes, at %.1f s' % m['spin_time_s'] if m['spun'] else 'no'),
        ('time in drift (abs. beta > 10 deg)', f"{m['time_in_drift_s']:.1f} s"),
        ('NMPC solve time p50 / p99 / max',
         f"{m['solve_time_ms_p50']:.2f} / {m['solve_time_ms_p99']:.2f} / "
         f"{m['solve_time_ms_max']:.2f} ms"),
        ('p99 / 20 ms budget', f"{m['solve_p99_over_budget']:.2f}"),
        ('NMPC cycles not OK', f"{m['nmpc_not_ok']} of {m['nmpc_cycles']}"),
        ('steady windows', ', '.join(f'{a:.1f}-{b:.1f} s' for a, b in m['steady_windows_s'])
         or 'none'),
        ('judged on', m['state_source']),
    ]
    lines = [f'# Run report: {name}', '', '| metric | value |', '|---|---|']
    lines += [f'| {k} | {v} |' for k, v in rows]
    lines += [''] + [f'![{Path(f).stem}]({Path(f).name})' for f in figures]
    return '\n'.join(lines) + '\n'


def figures(run: RunSeries, out_dir: Path, m: dict) -> list[str]:
    """Figures in the style of the paper's Figs. 4-8; returns the written PNG paths."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    s, ref, cmd, st = run.state, run.reference, run.command, run.status

    def shade(ax):
        for a, b in m['steady_windows_s']:
            ax.axvspan(a, b, color='0.9', zorder=0)

    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    pairs = [('beta', 'sideslip [deg]', np.degrees), ('r', 'yaw rate [rad/s]', None),
             ('V', 'speed [m/s]', None)]
    for ax, (key, label, conv) in zip(axes, pairs):
        conv = conv or (lambda v: v)
        ax.plot(s['t'], conv(s[key]), label='measured')
        if len(ref.get('t', ())):
            ax.plot(ref['t'], conv(ref[key]), '--', label='reference')
        ax.set_ylabel(label)
        shade(ax)
    axes[3].plot(s['t'], s['omega_F'], label='omega_F')
    axes[3].plot(s['t'], s['omega_R'], label='omega_R')
    if len(ref.get('t', ())):
        axes[3].plot(ref['t'], ref['omega_F'], '--', label='omega_F ref')
        axes[3].plot(ref['t'], ref['omega_R'], '--', label='omega_R ref')
    axes[3].set_ylabel('wheel speed [rad/s]')
    shade(axes[3])
    axes[-1].set_xlabel('time [s]')
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc='upper right')
    fig.suptitle('States and references (cf. paper Figs. 4, 7)')
    written.append(_save(fig, out_dir / 'states.png'))

    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    axes[0].plot(s['t'], np.degrees(s['delta']), label='applied (measured)')
    axes[1].plot(s['t'], s['drive_torque'], label='applied (measured)')
    if len(cmd.get('t', ())):
        axes[0].plot(cmd['t'], np.degrees(cmd['delta']), '--', label='NMPC optimised')
        axes[1].plot(cmd['t'], cmd['drive_torque'], '--', label='NMPC optimised')
    if len(ref.get('t', ())):
        axes[0].plot(ref['t'], np.degrees(ref['delta']), ':', label='equilibrium')
        axes[1].plot(ref['t'], ref['drive_torque'], ':', label='equilibrium')
    axes[0].set_ylabel('road-wheel angle [deg]')
    axes[1].set_ylabel('rear drive torque [Nm]')
    axes[1].set_xlabel('time [s]')
    for ax in axes:
        shade(ax)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc='upper right')
    fig.suptitle('Inputs: optimised vs applied (cf. paper Figs. 5, 6, 8)')
    written.append(_save(fig, out_dir / 'inputs.png'))

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), gridspec_kw={'width_ratios': [1, 1.4]})
    if len(run.path_xy):
        axes[0].plot(run.path_xy[:, 0], run.path_xy[:, 1], color='0.75', lw=4, label='path')
    axes[0].plot(s['x'], s['y'], label='car')
    axes[0].set_aspect('equal')
    axes[0].set(xlabel='x [m]', ylabel='y [m]', title='Path')
    axes[0].legend(fontsize=7)
    if len(ref.get('t', ())):
        axes[1].plot(ref['t'], ref['e_y'], label='e_y')
    axes[1].axhline(1.0, color='r', lw=0.8, ls=':')
    axes[1].axhline(-1.0, color='r', lw=0.8, ls=':', label='paper: 1 m')
    axes[1].axvline(m['transient_end_s'], color='0.5', lw=0.8, ls='--', label='transient end')
    axes[1].set(xlabel='time [s]', ylabel='lateral error [m]', title='Lateral path error')
    axes[1].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    written.append(_save(fig, out_dir / 'path.png'))

    fig, ax = plt.subplots(figsize=(9, 3.2))
    if len(st.get('t', ())):
        ax.plot(st['t'], st['solve_time'] * 1e3, lw=0.8, label='solve time')
    ax.axhline(BUDGET_S * 1e3, color='r', ls=':', label='20 ms budget')
    ax.set(xlabel='time [s]', ylabel='[ms]', title='NMPC solve time')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    written.append(_save(fig, out_dir / 'solve_time.png'))
    return written


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    import matplotlib.pyplot as plt
    plt.close(fig)
    return str(path)


def write_report(run: RunSeries, out_dir, name: str, windows=None, transient_end=None,
                 with_figures: bool = True) -> dict:
    """Metrics JSON, Markdown summary and figures into ``out_dir``; returns the metrics."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    m = run_metrics(run, windows, transient_end)
    figs = figures(run, out_dir, m) if with_figures else []
    (out_dir / 'metrics.json').write_text(json.dumps(_jsonable(m), indent=2))
    (out_dir / 'report.md').write_text(markdown(name, m, figs))
    return m


def _jsonable(m: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in m.items()}

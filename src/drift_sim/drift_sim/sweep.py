"""Seed sweeps and campaigns: how often a scenario holds its drift, not just whether seed 0 does.

The seed draws the friction field, the measurement noise and the driver's noise; a campaign also
draws the plant (``drift_sim.population``). The grip-to-drift entry is sensitive to them (a car
that drops to walking pace in the entry spins), so one run says little about a controller
change: ``scripts/seed_sweep.py``, ``scripts/results_table.py`` and ``scripts/campaign.py`` run
many, and this module classifies and summarises the runs. Pure Python on the metric dicts of
``drift_sim.closed_loop.run_closed_loop``.
"""
from __future__ import annotations

import logging
import math
import statistics
import time

import numpy as np

HELD, LOST, SPUN, TRIPPED, ERROR = 'held', 'lost', 'spun', 'tripped', 'error'
# a run that neither spun nor tripped but is this far off its sideslip reference (RMS in the
# steady windows) or its path did not hold the drift either
LOST_BETA_RMS_DEG = 2.0
LOST_E_Y_M = 5.0

# Robustness (issue: mass +10 %, 20 ms more actuator delay, on top of the +-0.05 friction field
# every scenario has): mass 1830 -> 2013 kg, the torque's transport delay 30 -> 50 ms. Then the
# same with the friction 5 % below and above the map's, a surface the controller is not told of.
ROBUST = ('plant.body.m=2013.0', 'plant.powertrain.delay=0.05')
ROBUST_LOW_MU = ('surface.mu=0.95',) + ROBUST
ROBUST_HIGH_MU = ('surface.mu=1.05',) + ROBUST


def parse_seeds(text: str, what: str = 'seeds') -> list[int]:
    """``'0-4,7,9'`` -> ``[0, 1, 2, 3, 4, 7, 9]`` (sorted, without repeats); ``what`` names the
    option in errors."""
    seeds = set()
    for part in text.split(','):
        part = part.strip()
        if not part:
            continue
        lo, sep, hi = part.partition('-')
        try:
            first, last = int(lo), int(hi) if sep else int(lo)
        except ValueError:
            raise ValueError(f'{what}: {part!r} is not N or N-M') from None
        if first < 0 or last < first:
            raise ValueError(f'{what}: {part!r} is not a range of {what} >= 0')
        seeds.update(range(first, last + 1))
    if not seeds:
        raise ValueError(f'{what}: none given')
    return sorted(seeds)


def parse_plants(text: str) -> list[int]:
    """Plant draws: ``'100'`` -> draws 0 .. 99 (``'0'``: none, the nominal plant); a list of
    draws as for seeds, ``'25-49'`` or ``'3,7'``, to extend a campaign or split it."""
    text = text.strip()
    if text.isdigit():
        return list(range(int(text)))
    return parse_seeds(text, 'plants')


def run_seed(scenario: str, overrides=(), seed: int | None = None,
             config: str | None = None, vehicle: str | None = None, sensors: str = '',
             estimator: str = '', sensor_set=()) -> tuple[dict, float]:
    """One ``run_closed_loop`` for a sweep: (metrics, wall seconds).

    An exception becomes ``{'error': ...}`` (one broken run must not lose the others) and NaN
    becomes None (JSON has none). The metrics gain ``event_t_s`` and ``event_s_m``: when and
    where on the path the car spun, the supervisor tripped, or else the lateral error after
    the entry was largest; and ``torque_std_Nm``, ``torque_change_Nm``: the torque request's
    std and mean change per control period in the steady windows. The supervisor's trip
    messages are silenced: the outcome says them. ``sensors``, ``estimator``, ``sensor_set``:
    as ``run_closed_loop``'s ('': the plant's measurement model). Meant for worker processes; it
    imports the closed loop on first use.
    """
    from drift_sim.closed_loop import run_closed_loop
    logging.disable(logging.ERROR)
    t0 = time.perf_counter()
    try:
        extra = {'sensors': sensors, 'estimator': estimator or 'none',
                 'sensor_set': tuple(sensor_set)} if sensors else {}
        metrics, log = run_closed_loop(scenario, overrides, seed=seed, config=config,
                                       vehicle=vehicle, **extra)
        metrics.update(_event(metrics, log))
        metrics.update(_torque(scenario, overrides, config, vehicle, log))
    except Exception as err:   # noqa: BLE001
        metrics = {'error': f'{type(err).__name__}: {err}'}
    metrics = {k: None if isinstance(v, float) and not math.isfinite(v) else v
               for k, v in metrics.items()}
    return metrics, time.perf_counter() - t0


def _torque(scenario, overrides, config, vehicle, log) -> dict:
    """The torque request's smoothness in the scenario's steady windows [Nm]."""
    from drift_control.scenario import load_scenario_spec
    from drift_sim.metrics import steady_windows, torque_smoothness
    spec = load_scenario_spec(scenario, overrides, config, vehicle=vehicle)
    windows = steady_windows(spec.metrics, log['t'], log['beta_ref'])
    std, change = torque_smoothness(log['t'], log['T_cmd'], windows)
    return {'torque_std_Nm': std, 'torque_change_Nm': change}


def _event(metrics: dict, log: dict) -> dict:
    """When [s] and where (arc length [m]) the run failed, or was furthest off its path."""
    t, s, e_y = log['t'], log['s'], log['e_y']
    at = metrics.get('spin_time_s')
    if at is None:
        at = metrics.get('supervisor_trip_s')
    if at is not None and len(t):
        i = min(int(np.searchsorted(t, at)), len(t) - 1)
    else:
        # the sample whose |e_y| is the largest after the entry (max_abs_e_y_m is that value)
        at_max = np.flatnonzero(np.abs(e_y) == metrics.get('max_abs_e_y_m'))
        if not at_max.size:
            return {'event_t_s': None, 'event_s_m': None}
        i = int(at_max[-1])
    return {'event_t_s': float(t[i]), 'event_s_m': float(s[i])}


def outcome(metrics: dict) -> str:
    """How one run ended: an error, a spin, a supervisor trip (the stack stopped pressing on),
    lost (no spin, but the sideslip RMS error or the lateral error beyond ``LOST_*``) or the
    drift held to the end."""
    if 'error' in metrics:
        return ERROR
    if metrics.get('spun'):
        return SPUN
    if metrics.get('supervisor_trip_s') is not None:
        return TRIPPED
    beta, e_y = metrics.get('beta_rms_error_deg'), metrics.get('max_abs_e_y_m')
    if not (beta is None or beta <= LOST_BETA_RMS_DEG) or not (e_y is None or e_y <= LOST_E_Y_M):
        return LOST
    return HELD


def _spread(values) -> dict | None:
    values = [v for v in values if v is not None and math.isfinite(v)]
    if not values:
        return None
    return {'min': min(values), 'median': statistics.median(values), 'max': max(values)}


def summarise(runs: list[tuple[int, dict]]) -> dict:
    """Summary of ``(seed, metrics)`` runs of one scenario and variant.

    ``held`` counts runs that held the drift to the end; ``as_expected`` counts runs that ended
    as the scenario says the paper's did (a held drift, or for ``expect_spin`` scenarios a spin,
    a supervisor trip or a lost drift). The spreads are over the held runs only: the lateral error of a car
    that spun says nothing about tracking.
    """
    held = [(seed, m) for seed, m in runs if outcome(m) == HELD]
    expected = sum(as_expected(m) for _, m in runs)
    failures = [{'seed': seed, 'outcome': outcome(m),
                 'time_s': m.get('spin_time_s') if outcome(m) == SPUN
                 else m.get('supervisor_trip_s'), 'error': m.get('error')}
                for seed, m in runs if outcome(m) != HELD]
    return {
        'runs': len(runs),
        'held': len(held),
        'as_expected': expected,
        'max_abs_e_y_m': _spread(m.get('max_abs_e_y_m') for _, m in held),
        'beta_rms_error_deg': _spread(m.get('beta_rms_error_deg') for _, m in held),
        'transition_time_s': _spread(m.get('transition_time_s') for _, m in held),
        'not_held': failures,
    }


def format_summary(name: str, summary: dict) -> str:
    """One line per scenario: held count and the spreads ``min / median / max``."""
    def spread(key, unit):
        s = summary[key]
        if s is None:
            return f'{key} -'
        return f"{key} {s['min']:.2f} / {s['median']:.2f} / {s['max']:.2f} {unit}"
    not_held = ', '.join(
        f"seed {f['seed']} {f['outcome']}" + (f" at {f['time_s']:.1f} s" if f['time_s'] else '')
        for f in summary['not_held'])
    return (f"{name}: held {summary['held']}/{summary['runs']}, as expected "
            f"{summary['as_expected']}/{summary['runs']}; {spread('max_abs_e_y_m', 'm')}; "
            f"{spread('beta_rms_error_deg', 'deg')}" + (f'; not held: {not_held}' if not_held
                                                        else ''))


def format_run(name: str, seed: int, metrics: dict, secs: float | None = None,
               width: int = 18) -> str:
    """One line for one run: its outcome, sideslip RMS error, max |e_y| and flip time."""
    def fmt(value):
        return '-' if value is None else f'{value:.2f}'
    took = f'  ({secs:.0f} s)' if secs is not None else ''
    if 'error' in metrics:
        return f'{name:{width}s} seed {seed:3d}  error: {metrics["error"]}{took}'
    return (f"{name:{width}s} seed {seed:3d}  {outcome(metrics):7s} "
            f"beta RMS {fmt(metrics.get('beta_rms_error_deg'))} deg  "
            f"max |e_y| {fmt(metrics.get('max_abs_e_y_m'))} m  "
            f"flip {fmt(metrics.get('transition_time_s'))} s{took}")


# --- campaigns: rows of drift_sim.campaign grouped by scenario and vehicle --------------------

# worst first: an error says least about the controller but most that something is broken
SEVERITY = (ERROR, SPUN, TRIPPED, LOST, HELD)


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a pass rate ``k / n`` (95 % for ``z = 1.96``); (0, 1) for n = 0.

    Unlike ``p +- z sqrt(p (1 - p) / n)`` it stays inside [0, 1] and is not zero-wide at 0/n
    or n/n, which small campaigns hit often.
    """
    if n == 0:
        return 0.0, 1.0
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4 * n * n)) / denom
    # in exact arithmetic the interval holds p (its bound is p at 0/n and n/n); rounding can
    # leave it a hair outside, which plots as a negative error bar
    return max(0.0, min(p, centre - half)), min(1.0, max(p, centre + half))


def as_expected(metrics: dict) -> bool:
    """The run ended as the scenario says the paper's did (held; or left the drift)."""
    end = outcome(metrics)
    return end != ERROR and (end != HELD) == bool(metrics.get('expect_spin'))


def _quantiles(values) -> dict | None:
    values = sorted(v for v in values if v is not None and math.isfinite(v))
    if not values:
        return None
    q = statistics.quantiles(values, n=10, method='inclusive') if len(values) > 1 else values * 9
    return {'min': values[0], 'p50': statistics.median(values), 'p90': q[8], 'max': values[-1]}


def campaign_summary(rows: list[dict], worst: int = 10) -> dict:
    """Pass rates, error spreads and failure modes per scenario and vehicle, and the worst runs.

    ``rows``: campaign rows (``drift_sim.campaign.run_job``), each with ``scenario``,
    ``vehicle``, ``metrics``, ``outcome`` and ``replay``. The pass rate counts held runs with
    a Wilson 95 % interval; error spreads are over the held runs; a failure mode lists when
    (``event_t_s``) and where on the path (``event_s_m``) its runs failed. The worst runs are
    those not ending as expected first, by severity, then by their largest lateral error.
    """
    groups: dict[tuple, list] = {}
    for row in rows:
        groups.setdefault((row['scenario'], row['vehicle']), []).append(row)
    out = []
    for (scenario, vehicle), mine in sorted(groups.items()):
        ends = [outcome(r['metrics']) for r in mine]
        held = [r['metrics'] for r, end in zip(mine, ends) if end == HELD]
        modes = {}
        for mode in SEVERITY[:-1]:
            failed = [r['metrics'] for r, end in zip(mine, ends) if end == mode]
            if failed:
                modes[mode] = {'runs': len(failed),
                               'when_s': _quantiles(m.get('event_t_s') for m in failed),
                               'where_s_m': _quantiles(m.get('event_s_m') for m in failed),
                               'errors': sorted({m['error'] for m in failed if 'error' in m})}
        lo, hi = wilson_interval(len(held), len(mine))
        out.append({'scenario': scenario, 'vehicle': vehicle, 'runs': len(mine),
                    'held': len(held), 'pass_rate': len(held) / len(mine), 'ci95': [lo, hi],
                    'as_expected': sum(as_expected(r['metrics']) for r in mine),
                    'expect_spin': any(r['metrics'].get('expect_spin') for r in mine),
                    'beta_rms_error_deg': _quantiles(m.get('beta_rms_error_deg') for m in held),
                    'max_abs_e_y_m': _quantiles(m.get('max_abs_e_y_m') for m in held),
                    'failure_modes': modes})

    def badness(row):
        m = row['metrics']
        return (as_expected(m), SEVERITY.index(outcome(m)), -(m.get('max_abs_e_y_m') or 0.0))

    worst_rows = sorted(rows, key=badness)[:worst]
    return {'runs': len(rows), 'held': sum(g['held'] for g in out), 'groups': out,
            'worst': [{k: r.get(k) for k in ('scenario', 'vehicle', 'seed', 'draw', 'replay')}
                      | {'outcome': outcome(r['metrics'])}
                      | {k: r['metrics'].get(k) for k in ('event_t_s', 'event_s_m',
                                                          'max_abs_e_y_m', 'beta_rms_error_deg',
                                                          'error')}
                      for r in worst_rows]}


def format_campaign(summary: dict) -> str:
    """The campaign summary as Markdown: pass rates, failure modes, worst runs."""
    def q(spread, spec='.2f'):
        if spread is None:
            return '-'
        return ' / '.join(format(spread[k], spec) for k in ('p50', 'p90', 'max'))

    lines = ['| scenario | vehicle | runs | held | pass rate (95 % CI) | as expected | '
             'beta RMS error p50 / p90 / max [deg] | max abs e_y p50 / p90 / max [m] |',
             '|---|---|---|---|---|---|---|---|']
    for g in summary['groups']:
        lo, hi = g['ci95']
        lines.append(f"| {g['scenario']}{' (paper: spun)' if g['expect_spin'] else ''} | "
                     f"{g['vehicle']} | {g['runs']} | {g['held']} | {100 * g['pass_rate']:.0f} % "
                     f"({100 * lo:.0f}-{100 * hi:.0f} %) | {g['as_expected']} | "
                     f"{q(g['beta_rms_error_deg'])} | {q(g['max_abs_e_y_m'])} |")
    modes = [(g, mode, m) for g in summary['groups'] for mode, m in g['failure_modes'].items()]
    if modes:
        lines += ['', '| scenario | vehicle | failure | runs | when [s] p50 / p90 / max | '
                  'where, arc length [m] p50 / p90 / max |', '|---|---|---|---|---|---|']
        for g, mode, m in modes:
            what = f"{mode} ({'; '.join(m['errors'])})" if m['errors'] else mode
            lines.append(f"| {g['scenario']} | {g['vehicle']} | {what} | {m['runs']} | "
                         f"{q(m['when_s'], '.1f')} | {q(m['where_s_m'], '.0f')} |")
    if summary['worst']:
        lines += ['', 'Worst runs (not as expected first), each with the command that replays it:',
                  '']
        for i, w in enumerate(summary['worst'], 1):
            where = (f" at {w['event_t_s']:.1f} s, s = {w['event_s_m']:.0f} m"
                     if w['event_t_s'] is not None else '')
            e_y = (f", max abs e_y {w['max_abs_e_y_m']:.2f} m"
                   if w['max_abs_e_y_m'] is not None else '')
            plant = 'nominal plant' if w['draw'] is None else f"plant {w['draw']}"
            lines.append(f"{i}. {w['scenario']}, {w['vehicle']}, {plant}, seed {w['seed']}: "
                         f"{w['outcome']}{where}{e_y}" + (f" ({w['error']})" if w['error'] else '')
                         + f"\n   `{w['replay']}`")
    return '\n'.join(lines) + '\n'


__all__ = ['ERROR', 'HELD', 'LOST', 'SEVERITY', 'SPUN', 'TRIPPED', 'as_expected',
           'campaign_summary', 'format_campaign', 'format_run', 'format_summary', 'outcome',
           'parse_seeds', 'run_seed', 'summarise', 'wilson_interval']

#!/usr/bin/env python3
"""Run every scenario (and the robustness variants) and write the README's results table.

    .venv/bin/python scripts/results_table.py [--jobs 2] [--seeds 0-9] [--only steady_dry,...]
        [--no-readme] [--store runs/results_table.jsonl]

Each row is ``drift_sim.closed_loop.run_closed_loop`` (the same loop as scripts/simulate.py) on
every seed of ``--seeds``, measured in this run: the columns are the first seed's run, then how
many seeds held the drift and the spread of their lateral error (``drift_sim.sweep``); the
paper's figure for the same claim stands beside it. The runs are a campaign of the nominal
plant (``drift_sim.campaign``: Ray with ``--jobs`` processes, ``--jobs 1`` in this process),
printed as they finish; ``--store`` keeps them so that an interrupted table resumes. Writes
docs/results.md and replaces the block between the results markers in README.md, only once
every row has run.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

from drift_control.cli_args import output_problem, write_text
from drift_control.params import ParamError, default_vehicle
from drift_sim.campaign import campaign_jobs, run_jobs, scenario_vehicle
from drift_sim.executor import ClusterError, make_executor
from drift_sim.store import RunStore
from drift_sim.sweep import (LOST_BETA_RMS_DEG, LOST_E_Y_M, ROBUST, ROBUST_HIGH_MU,
                             ROBUST_LOW_MU, format_run, parse_seeds, summarise)

ROOT = Path(__file__).resolve().parents[1]
START, END = '<!-- results:start -->', '<!-- results:end -->'

# the first seed of every row once more through the car's sensors and the state estimator
ESTIMATED = {'sensors': 'realistic', 'estimator': 'ekf'}

# (row label, scenario, overrides, the paper's figure for the same claim); the robustness
# perturbations are drift_sim.sweep's
RUNS = [
    ('alternating_dry', 'alternating_dry', (), 'max lateral deviation 1 m (simulation, Sec. V-B)'),
    ('steady_dry', 'steady_dry', (), '30 deg held for several laps (Sec. VI)'),
    ('steady_wet', 'steady_wet', (), '30 deg held on the watered skid pad (Sec. VI)'),
    ('semi_auto_dry', 'semi_auto_dry', (), 'NMPC steering within ~5 deg of the driver'),
    ('semi_auto_wet', 'semi_auto_wet', (), 'NMPC steering within ~5 deg of the driver'),
    ('eps_limited_dry', 'eps_limited_dry', (), '30 Nm EPS: car spun (Sec. VI-A)'),
    ('drift_hold_dry', 'drift_hold_dry', (), '-'),
    ('steady_dry, robustness', 'steady_dry', ROBUST, '-'),
    ('alternating_dry, robustness', 'alternating_dry', ROBUST, '-'),
    ('steady_dry, robustness mu -5 %', 'steady_dry', ROBUST_LOW_MU, '-'),
    ('alternating_dry, robustness mu -5 %', 'alternating_dry', ROBUST_LOW_MU, '-'),
    ('steady_dry, robustness mu +5 %', 'steady_dry', ROBUST_HIGH_MU, '-'),
    ('alternating_dry, robustness mu +5 %', 'alternating_dry', ROBUST_HIGH_MU, '-'),
    ('gr86: steady_dry', 'steady_dry', ('vehicle=gr86',), '-'),
    ('gr86: alternating_dry', 'alternating_dry', ('vehicle=gr86',), '-'),
    ('gr86: steady_wet', 'steady_wet', ('vehicle=gr86',), '-'),
]


def _vehicle(run) -> str:
    """The vehicle a row runs: its ``vehicle=`` override, else the scenario's."""
    return next((o.split('=', 1)[1] for o in run[2] if o.startswith('vehicle=')), '')


def _fmt(value, spec):
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '-'
    return format(value, spec)


def _held(summary) -> str:
    """``held/runs``, the spread of max |e_y| over the held runs, and for a scenario whose
    paper outcome is a spin how many runs left the drift as the paper's did."""
    e_y, n = summary['max_abs_e_y_m'], summary['runs']
    spread = (f" ({e_y['min']:.2f} / {e_y['median']:.2f} / {e_y['max']:.2f})"
              if e_y is not None and n > 1 else '')
    paper = (f"; left the drift as in the paper {summary['as_expected']}/{n}"
             if summary['as_expected'] != summary['held'] else '')
    return f"{summary['held']}/{n}{spread}{paper}"


def _torque(m) -> str:
    """``std / mean change`` of the torque request [Nm], '-' without a steady window."""
    if m.get('torque_std_Nm') is None:
        return '-'
    return f"{m['torque_std_Nm']:.0f} / {m['torque_change_Nm']:.0f}"


def _estimated(m) -> str:
    """The estimated run's torque columns and sideslip error, or its failure."""
    if m is None or 'error' in m:
        return f"error: {m['error']}" if m else '-'
    spun = '; spun' if m.get('spun') else ''
    return f"{_torque(m)}; {_fmt(m.get('beta_rms_error_deg'), '.2f')}{spun}"


def table(rows, seeds) -> str:
    """``rows``: (run, first seed's metrics, sweep summary, the estimated run's metrics)."""
    seed_text = f'{seeds[0]}-{seeds[-1]}' if len(seeds) > 1 else str(seeds[0])
    lines = [f'| scenario | spun | beta RMS err [deg] | max abs e_y after entry / in steady parts [m] | '
             f'laps held | left-right flip [s] | NMPC vs driver steer max [deg] | safe stop | '
             f'solve p50 / p99 [ms] | RTF | torque std / change [Nm] | sensors + EKF: torque std '
             f'/ change [Nm]; beta RMS err [deg] | held, seeds {seed_text} (max abs e_y min / '
             f'median / max [m]) | paper |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for (label, _, _, paper), m, summary, est in rows:
        if 'error' in m:
            lines.append(f'| {label} | error: {m["error"]} | | | | | | | | | | | | {paper} |')
            continue
        spun = 'yes (%.1f s)' % m['spin_time_s'] if m.get('spun') else 'no'
        safe = m.get('supervisor_trip_s')
        lines.append(
            f"| {label} | {spun} | {_fmt(m.get('beta_rms_error_deg'), '.2f')} | "
            f"{_fmt(m.get('max_abs_e_y_m'), '.2f')} / {_fmt(m.get('max_abs_e_y_steady_m'), '.2f')} | "
            f"{_fmt(m.get('laps_in_steady_drift'), '.1f')} | "
            f"{_fmt(None if m.get('spun') else m.get('transition_time_s'), '.1f')} | "
            f"{_fmt(m.get('steer_proposal_diff_max_deg'), '.1f')} | "
            f"{'at %.1f s' % safe if safe is not None else '-'} | "
            f"{_fmt(m.get('solve_time_ms_p50'), '.2f')} / {_fmt(m.get('solve_time_ms_p99'), '.2f')} | "
            f"{_fmt(m.get('real_time_factor'), '.1f')} | {_torque(m)} | {_estimated(est)} | "
            f"{_held(summary)} | {paper} |")
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--jobs', type=int, default=2,
                        help='processes (default 2, on Ray; 1: in this process)')
    parser.add_argument('--store', help='keep finished runs in this JSON lines file: the same '
                        'command resumes an interrupted table')
    parser.add_argument('--seeds', default='0-9',
                        help='seeds of every row, e.g. 0-9 (default) or 0; the first one fills '
                        'the metric columns')
    parser.add_argument('--only', action='append',
                        help='row labels or scenario names, comma-separated or repeated (a '
                        'label with a comma, e.g. "steady_dry, robustness", is taken whole)')
    parser.add_argument('--vehicle', help='only the rows of this vehicle (rows without a '
                        'vehicle= override run the scenario\'s)')
    parser.add_argument('--no-readme', action='store_true', help='only docs/results.md')
    parser.add_argument('--json', help='also write all metrics here')
    args = parser.parse_args(argv)
    runs = RUNS
    if args.only:
        known = {r[0] for r in RUNS} | {r[1] for r in RUNS}
        wanted = set()
        for value in args.only:
            wanted.update({value} if value in known else
                          {name.strip() for name in value.split(',') if name.strip()})
        unknown = wanted - {r[0] for r in RUNS} - {r[1] for r in RUNS}
        if unknown:
            parser.error(f'--only: no row or scenario {sorted(unknown)}')
        runs = [r for r in runs if r[0] in wanted or r[1] in wanted]
    if args.vehicle:
        runs = [r for r in runs if (_vehicle(r) or default_vehicle()) == args.vehicle]
        if not runs:
            parser.error(f'--vehicle {args.vehicle}: no rows; rows name '
                         f'{sorted({_vehicle(r) or default_vehicle() for r in RUNS})}')
    partial = len(runs) != len(RUNS)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as err:
        parser.error(str(err))
    if args.jobs < 1:
        parser.error(f'--jobs: expected >= 1, got {args.jobs}')
    problem = ((output_problem(args.store) if args.store else None)
               or (output_problem(args.json, [args.store]) if args.json else None))
    if problem is not None:
        print(f'results_table: {problem}', file=sys.stderr)
        return 2
    try:
        jobs = {run[0]: campaign_jobs([run[1]], [scenario_vehicle(run[1], run[2])], seeds,
                                      overrides=run[2]) for run in runs}
        store = RunStore(args.store)
    except ParamError as err:
        print(f'results_table: {err}', file=sys.stderr)
        return 2
    estimated = {label: dataclasses.replace(mine[0], **ESTIMATED) for label, mine in jobs.items()}
    labels = {job.key: label for label, mine in jobs.items() for job in mine}
    labels.update({job.key: f'{label} +EKF' for label, job in estimated.items()})
    width = max(len(label) for label in labels.values())

    def show(row):
        from tqdm import tqdm   # above the progress bar
        tqdm.write(format_run(labels[row['key']], row['seed'], row['metrics'], row['wall_s'],
                              width))

    everything = [job for mine in jobs.values() for job in mine] + list(estimated.values())
    fresh = sum(1 for job in everything if job.key not in store)
    t0 = time.perf_counter()
    try:
        with make_executor(args.jobs) as pool:
            run_jobs(everything, pool, store, on_row=show)
    except ClusterError as err:
        print(f'results_table: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:   # a partial table must not replace the whole one
        print('\nresults_table: interrupted; docs/results.md and README.md left as they are'
              + (f'; finished runs are in {args.store}' if args.store else ''), file=sys.stderr)
        return 130
    wall = time.perf_counter() - t0
    results = [(label, job.seed, store.get(job.key)['metrics'])
               for label, mine in jobs.items() for job in mine]
    rows, all_metrics = [], {}
    for run in runs:
        mine = [(seed, m) for label, seed, m in results if label == run[0]]
        rows.append((run, mine[0][1], summarise(mine),
                     (store.get(estimated[run[0]].key) or {}).get('metrics')))
        all_metrics[run[0]] = {str(seed): m for seed, m in mine}
    measured = f'{len(results)} runs in {wall:.0f} s wall on {args.jobs} process(es)'
    if fresh < len(results):
        measured = (f'{len(results)} runs, {fresh} of them in {wall:.0f} s wall on '
                    f'{args.jobs} process(es), the rest from its store')
    text = (f'{table(rows, seeds)}\n\n'
            f'Measured by `scripts/results_table.py` ({measured}); '
            f'plant = `drift_sim` double-track model, '
            f'controller = single-track NMPC (model mismatch by design). The metric columns are '
            f'seed {seeds[0]}; "held" counts the seeds that neither spun, tripped the supervisor '
            f'nor lost the drift (sideslip RMS error > {LOST_BETA_RMS_DEG:g} deg or lateral '
            f'error > {LOST_E_Y_M:g} m). Robustness rows: {", ".join(ROBUST)} (mass +10 %, torque '
            f'delay +20 ms) with the friction field of every row, then also surface.mu=0.95 / '
            f'1.05 (mu -5 % / +5 %). Torque: the NMPC\'s torque request, its std and mean '
            f'change per 20 ms cycle in the steady parts (issue 22), seed {seeds[0]}; "sensors + '
            f'EKF": seed {seeds[0]} once more through the realistic sensors and the state '
            f'estimator (docs/estimator.md).\n')
    problem = write_text(args.json, json.dumps(all_metrics, indent=2, default=str)) \
        if args.json else None
    if problem is not None:
        print(f'results_table: {problem}', file=sys.stderr)
        return 2
    if partial:   # a subset must not replace the whole table
        print(text)
        print('a subset of the rows: docs/results.md and README.md left as they are')
        return 0 if all('error' not in m for _, _, m in results) else 1
    (ROOT / 'docs').mkdir(exist_ok=True)
    (ROOT / 'docs' / 'results.md').write_text('# Closed-loop results\n\n' + text)
    if not args.no_readme:
        readme = (ROOT / 'README.md').read_text()
        if START in readme and END in readme:
            head, rest = readme.split(START, 1)
            _, tail = rest.split(END, 1)
            (ROOT / 'README.md').write_text(f'{head}{START}\n{text}{END}{tail}')
        else:
            print('README.md has no results markers; wrote docs/results.md only', file=sys.stderr)
    print(f'wrote docs/results.md ({wall:.0f} s)')
    return 0 if all('error' not in m for _, _, m in results) else 1


if __name__ == '__main__':
    sys.exit(main())

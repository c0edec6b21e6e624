#!/usr/bin/env python3
"""Run scenarios over many seeds and print how often each holds its drift.

    .venv/bin/python scripts/seed_sweep.py --scenario steady_wet --seeds 0-9
    .venv/bin/python scripts/seed_sweep.py --scenario alternating_dry --scenario steady_dry \\
        --seeds 0-4 --set surface.mu=0.95 --config-dir /tmp/variant/config --json sweep.json

One seed is one friction field, one noise draw and one driver: a controller change judged on
seed 0 alone is judged on luck (the grip-to-drift entry is chaotic). A sweep is a campaign of
the nominal plant (``drift_sim.campaign``; ``scripts/campaign.py`` also draws plants): each
run is ``drift_sim.closed_loop.run_closed_loop`` (the loop of ``scripts/simulate.py``), on Ray
with ``--jobs`` processes or, with ``--jobs 1``, in this process. ``--store`` keeps finished
runs so that the same command resumes. Prints a line per run, then per scenario the held count
and the spread (min / median / max) of the lateral error and sideslip error over the held runs.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from drift_control.cli_args import output_problem, write_text
from drift_control.params import ParamError, config_dir, vehicle_file
from drift_sim.campaign import campaign_jobs, default_config, run_jobs, scenario_vehicle
from drift_sim.executor import ClusterError, make_executor
from drift_sim.store import RunStore
from drift_sim.sweep import format_run, format_summary, parse_seeds, summarise


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', action='append', required=True,
                        help='name under config/scenarios (repeat for several)')
    parser.add_argument('--seeds', default='0-4', help='e.g. 0-9 or 0,3,7 (default 0-4)')
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        help='override a scenario key in every run (surface.mu=0.95)')
    parser.add_argument('--vehicle', help='config/vehicle/<name>.yaml for every run (default: '
                        'the scenario\'s)')
    parser.add_argument('--config-dir', default=str(config_dir()),
                        help='a config directory (a variant of config/ to compare)')
    parser.add_argument('--jobs', type=int, default=2,
                        help='processes (default 2, on Ray; 1: in this process)')
    parser.add_argument('--store', help='keep finished runs in this JSON lines file (resumes)')
    parser.add_argument('--json', help='write every run and the summaries here')
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as err:
        parser.error(str(err))
    if args.jobs < 1:
        parser.error(f'--jobs: expected >= 1, got {args.jobs}')
    if args.vehicle:
        try:
            vehicle_file(args.vehicle, args.config_dir)
        except ParamError as err:
            parser.error(str(err))
    problem = ((output_problem(args.store) if args.store else None)
               or (output_problem(args.json, [args.store]) if args.json else None))
    if problem is not None:
        print(f'seed_sweep: {problem}', file=sys.stderr)
        return 2
    config = default_config(args.config_dir)
    try:
        jobs = [job for sc in args.scenario for job in campaign_jobs(
            [sc], [args.vehicle or scenario_vehicle(sc, args.set, args.config_dir)], seeds,
            overrides=args.set, config=config)]
        store = RunStore(args.store)
    except ParamError as err:
        print(f'seed_sweep: {err}', file=sys.stderr)
        return 1
    t0 = time.perf_counter()
    try:
        with make_executor(args.jobs) as pool:
            rows = run_jobs(jobs, pool, store, progress=args.jobs > 1, on_row=_print_row)
    except ClusterError as err:
        print(f'seed_sweep: {err}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print('\nseed_sweep: interrupted' + (f'; finished runs are in {args.store}'
                                             if args.store else ''), file=sys.stderr)
        return 130
    summaries = {}
    for sc in args.scenario:
        summaries[sc] = summarise([(r['seed'], r['metrics']) for r in rows
                                   if r['scenario'] == sc])
        print(format_summary(sc, summaries[sc]))
    print(f'{len(rows)} runs in {time.perf_counter() - t0:.0f} s on {args.jobs} process(es)'
          + (f"; overrides: {', '.join(args.set)}" if args.set else ''))
    if args.json:
        problem = write_text(args.json, json.dumps(
            {'seeds': seeds, 'overrides': args.set, 'config_dir': args.config_dir,
             'vehicle': args.vehicle, 'summaries': summaries,
             'runs': [{'scenario': r['scenario'], 'vehicle': r['vehicle'], 'seed': r['seed'],
                       'metrics': r['metrics']} for r in rows]}, indent=2, default=str))
        if problem is not None:
            print(f'seed_sweep: {problem}', file=sys.stderr)
            return 2
    return 1 if any('error' in r['metrics'] for r in rows) else 0


def _print_row(row):
    from tqdm import tqdm   # above the progress bar, if there is one
    tqdm.write(format_run(row['scenario'], row['seed'], row['metrics'], row['wall_s']))


if __name__ == '__main__':
    sys.exit(main())

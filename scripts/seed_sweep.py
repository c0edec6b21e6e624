#!/usr/bin/env python3
"""Run scenarios over many seeds and print how often each holds its drift.

    .venv/bin/python scripts/seed_sweep.py --scenario steady_wet --seeds 0-9
    .venv/bin/python scripts/seed_sweep.py --scenario alternating_dry --scenario steady_dry \\
        --seeds 0-4 --set surface.mu=0.95 --config-dir /tmp/variant/config --json sweep.json

One seed is one friction field, one noise draw and one driver: a controller change judged on
seed 0 alone is judged on luck (the grip-to-drift entry is chaotic). Each run is
``drift_sim.closed_loop.run_closed_loop`` (the loop of ``scripts/simulate.py``); ``--jobs``
processes run them side by side. Prints a line per run, then per scenario the held count and
the spread (min / median / max) of the lateral error and sideslip error over the held runs.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time

from drift_control.params import ParamError, config_dir, vehicle_file
from drift_sim.sweep import format_summary, outcome, parse_seeds, run_seed, summarise


def _run(job):
    scenario, overrides, seed, config = job
    metrics, secs = run_seed(scenario, overrides, seed, config)
    return scenario, seed, metrics, secs


def _fmt(value, spec='.2f'):
    return '-' if value is None else format(value, spec)


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
    parser.add_argument('--jobs', type=int, default=2, help='processes (default 2)')
    parser.add_argument('--json', help='write every run and the summaries here')
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as err:
        parser.error(str(err))
    if args.vehicle:
        try:
            vehicle_file(args.vehicle, args.config_dir)
        except ParamError as err:
            parser.error(str(err))
        args.set.append(f'vehicle={args.vehicle}')
    jobs = [(sc, tuple(args.set), seed, args.config_dir) for sc in args.scenario for seed in seeds]
    t0 = time.perf_counter()
    results = []
    if args.jobs > 1:
        with multiprocessing.get_context('spawn').Pool(args.jobs) as pool:
            for res in pool.imap(_run, jobs):
                results.append(res)
                _print_run(*res)
    else:
        for job in jobs:
            results.append(_run(job))
            _print_run(*results[-1])
    summaries = {}
    for sc in args.scenario:
        summaries[sc] = summarise([(seed, m) for name, seed, m, _ in results if name == sc])
        print(format_summary(sc, summaries[sc]))
    print(f'{len(results)} runs in {time.perf_counter() - t0:.0f} s on {args.jobs} process(es)'
          + (f"; overrides: {', '.join(args.set)}" if args.set else ''))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump({'seeds': seeds, 'overrides': args.set, 'config_dir': args.config_dir,
                       'summaries': summaries,
                       'runs': [{'scenario': sc, 'seed': seed, 'metrics': m}
                                for sc, seed, m, _ in results]}, f, indent=2, default=str)
    return 1 if any('error' in m for _, _, m, _ in results) else 0


def _print_run(scenario, seed, m, secs):
    if 'error' in m:
        print(f'{scenario:18s} seed {seed:3d}  error: {m["error"]}', flush=True)
        return
    print(f"{scenario:18s} seed {seed:3d}  {outcome(m):7s} "
          f"beta RMS {_fmt(m.get('beta_rms_error_deg'))} deg  "
          f"max |e_y| {_fmt(m.get('max_abs_e_y_m'))} m  "
          f"flip {_fmt(m.get('transition_time_s'))} s  ({secs:.0f} s)", flush=True)


if __name__ == '__main__':
    sys.exit(main())

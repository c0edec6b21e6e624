#!/usr/bin/env python3
"""Run a campaign of closed loops on Ray: scenario x vehicle x plant draw x seed, resumable.

    .venv/bin/python scripts/campaign.py --plants 100 --store runs/campaign.jsonl \\
        --summary runs/campaign.md
    .venv/bin/python scripts/campaign.py --scenario steady_dry --vehicle gr86 --plants 10 \\
        --seeds 0-2 --set duration=20 --store runs/gr86.jsonl --jobs 2
    .venv/bin/python scripts/campaign.py --address 192.0.2.10:6379 --plants 100 --store ...

Each run is one Ray task (``drift_sim.campaign.run_job``: the loop of scripts/simulate.py);
``--jobs 1`` without ``--address`` runs them in this process instead. Plants are draws of
``config/sim/populations/<vehicle>.yaml`` (``--plants 0``: the nominal plant). Every finished
run is appended to ``--store`` at once; the same command again skips what is there, so an
interrupted campaign resumes where it stopped. The summary (pass rate with a 95 % interval per
scenario and vehicle, error spreads, failure modes, the worst runs with their replay commands)
is printed and written to ``--summary`` once every run has finished. Figures:
``scripts/plot_campaign.py``. Exit status: 0 done, 1 done with failed runs (errors), 2 bad
input, 130 interrupted. docs/campaigns.md has the cluster commands.
"""
from __future__ import annotations

import argparse
import json
import shlex
import signal
import sys
import time
from pathlib import Path

from drift_control.cli_args import output_problem, write_text
from drift_control.params import ParamError, config_dir, vehicle_names
from drift_control.scenario import control_scenario_names
from drift_sim.campaign import campaign_jobs, default_config, run_jobs
from drift_sim.executor import ClusterError, check_address, interrupt, make_executor
from drift_sim.store import RunStore
from drift_sim.sweep import ERROR, campaign_summary, format_campaign, parse_plants, parse_seeds


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--scenario', action='append',
                   help='name under config/scenarios (repeat; default: every scenario the '
                   'controller drives, not the identification manoeuvres)')
    p.add_argument('--vehicle', action='append',
                   help='config/vehicle/<name>.yaml (repeat; default: every vehicle)')
    p.add_argument('--seeds', default='0', help='run seeds, e.g. 0-9 or 0,3 (default 0)')
    p.add_argument('--plants', default='0',
                   help='plant draws per vehicle from config/sim/populations/: N for draws '
                   '0..N-1, or a list of draws, e.g. 25-49 (default 0: the nominal plant)')
    p.add_argument('--plant-seed', type=int, default=0,
                   help='seed of the plant draws (default 0)')
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='override a scenario key in every run (duration=5, surface.mu=0.95)')
    p.add_argument('--sensors', default='', metavar='NAME',
                   help='the controller sees the car through config/sim/sensors/NAME.yaml '
                   '(e.g. realistic) instead of the plant\'s own noise model')
    p.add_argument('--estimator', default='',
                   help='with --sensors: fuse them (ekf) or pass the newest samples (none; '
                   'the default with --sensors)')
    p.add_argument('--identify', action='store_true',
                   help='drive each plant through the identification manoeuvre first and run '
                   'the controller on the model identified from its log (docs/sysid.md), as a '
                   'team does with its car, instead of the data sheet')
    p.add_argument('--config-dir', default=str(config_dir()))
    p.add_argument('--store', required=True,
                   help='JSON lines file of finished runs; read first, appended to')
    p.add_argument('--summary', help='write the summary (Markdown) here when every run is done')
    p.add_argument('--summary-json', help='the same summary as JSON')
    p.add_argument('--worst', type=int, default=10, help='worst runs listed (default 10)')
    p.add_argument('--jobs', type=int, default=2,
                   help='local worker processes (default 2; 1: in this process, no Ray)')
    p.add_argument('--address', help='a Ray cluster: host:port of its head, ray://host:port '
                   'or auto')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    for name, least in (('plant_seed', 0), ('worst', 0), ('jobs', 1)):
        if getattr(args, name) < least:
            return _fail(f"--{name.replace('_', '-')}: expected an integer >= {least}, "
                         f'got {getattr(args, name)}')
    problem = _output_problem(args)
    if problem is not None:
        return _fail(problem)
    config = default_config(args.config_dir)
    try:
        seeds = parse_seeds(args.seeds)
        plants = parse_plants(args.plants)
        scenarios = args.scenario or control_scenario_names(args.config_dir)
        vehicles = args.vehicle or vehicle_names(args.config_dir)
        jobs = campaign_jobs(scenarios, vehicles, seeds, plants, args.set,
                             args.plant_seed, config, args.sensors,
                             args.estimator or ('none' if args.sensors else ''), args.identify)
        store = RunStore(args.store)
        if args.address:
            check_address(args.address)
    except (ParamError, ValueError, ClusterError) as err:
        return _fail(err)
    if not jobs:
        return _fail(f'no runs: no scenario under {args.config_dir}/scenarios')
    todo = sum(1 for job in jobs if job.key not in store)
    header = (f'campaign: {len(jobs)} runs ({len(scenarios)} scenario(s) x {len(vehicles)} '
              f'vehicle(s) x {max(len(plants), 1)} plant(s) x {len(seeds)} seed(s)); '
              f'{len(jobs) - todo} already in {args.store}')
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    t0 = time.perf_counter()
    try:
        rows = _run(jobs, todo, store, args, header)
    except ClusterError as err:
        return _fail(err)
    except KeyboardInterrupt:
        done = sum(1 for job in jobs if job.key in store)
        print(f'\ncampaign: interrupted; {done} of {len(jobs)} runs are in {args.store} '
              '(the same command resumes)', file=sys.stderr)
        return 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    wall = time.perf_counter() - t0
    summary = campaign_summary(rows, args.worst)
    text = format_campaign(summary)
    print(text)
    if todo:
        print(f'campaign: {todo} run(s) in {wall:.0f} s ({wall / todo:.1f} s a run)',
              file=sys.stderr)
    for path, content in ((args.summary, f'# Campaign: {len(jobs)} runs\n\n`{_command(argv)}`'
                                         f'\n\n{text}'),
                          (args.summary_json, json.dumps(summary, indent=2) + '\n')):
        problem = write_text(path, content) if path else None
        if problem is not None:   # the runs are in the store: the same command writes it
            return _fail(problem)
    return 1 if any(row['outcome'] == ERROR for row in rows) else 0


def _output_problem(args) -> str | None:
    """Why the store or a summary path cannot be written (before any run), or None."""
    if args.summary and args.summary_json and Path(args.summary) == Path(args.summary_json):
        return '--summary and --summary-json name the same file'
    return (output_problem(args.store)
            or (output_problem(args.summary, [args.store]) if args.summary else None)
            or (output_problem(args.summary_json, [args.store]) if args.summary_json else None))


def _run(jobs, todo, store, args, header: str) -> list[dict]:
    if not todo:   # everything finished already: no workers to start
        print(header, file=sys.stderr)
        return [store.get(job.key) for job in jobs]
    with make_executor(args.jobs, args.address) as pool:
        print(header, file=sys.stderr)   # after the workers: a refused cluster is one line
        # `kill` stops like Ctrl-C: the finished runs stay, the workers are released (set
        # after Ray's start, whose own SIGTERM handler would end the process at once)
        signal.signal(signal.SIGTERM, interrupt)
        signal.signal(signal.SIGINT, interrupt)   # also where a shell passed it on ignored
        return run_jobs(jobs, pool, store, progress=not args.quiet)


def _fail(err) -> int:
    print(f'campaign: {err}', file=sys.stderr)
    return 2


def _command(argv) -> str:
    return shlex.join(['scripts/campaign.py', *(sys.argv[1:] if argv is None else argv)])


if __name__ == '__main__':
    sys.exit(main())

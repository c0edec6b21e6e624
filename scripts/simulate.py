#!/usr/bin/env python3
"""Closed loop in one process, no DDS: plant + reference selector + NMPC on a scenario.

    .venv/bin/python scripts/simulate.py --scenario steady_dry --json out.json
    .venv/bin/python scripts/simulate.py --scenario steady_wet --set surface.mu=0.55 --seed 3
    .venv/bin/python scripts/simulate.py --scenario steady_dry --vehicle gr86
    .venv/bin/python scripts/simulate.py --scenario alternating_dry --plan-at 25.9 --plan-at 26.3

The loop itself is ``drift_sim.closed_loop.run_closed_loop``; this prints its metrics as JSON.
``--controller feedforward`` applies the selected equilibrium's (delta, T_R) open loop: a
baseline to judge the NMPC against, not a substitute. ``--plan-at`` prints what the NMPC planned
at those times (its predicted states and inputs next to the reference, every other stage) and
adds the plans to the JSON, SI units.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

import numpy as np

from drift_control import cli_args
from drift_control.params import ParamError, config_dir
from drift_sim.closed_loop import run_closed_loop



def format_plan(plan: dict, every: int = 2) -> str:
    """One ``plans`` record as a table: each stage's predicted value (reference in brackets),
    angles in degrees."""
    m = plan['measured']
    lines = [f"NMPC plan at t = {plan['t']:.2f} s (status: {plan['message']})"]
    if m is not None:
        lines.append(f"  measured: V {m['V']:.2f} m/s, beta {math.degrees(m['beta']):.1f} deg, "
                     f"r {m['r']:.2f} rad/s, omega_R {m['omega_R']:.1f} rad/s, delta "
                     f"{math.degrees(m['delta']):.1f} deg, torque {m['drive_torque']:.0f} Nm")
    x, u, ref = plan['states'], plan['inputs'], plan['reference']
    if not x:
        return '\n'.join(lines + ['  no plan (fallback)'])
    lines.append('  predicted (reference) per stage; angles in deg; torque: the request')
    deg = {'beta', 'delta'}
    lines.append('  stage  ' + '  '.join(f'{k:>15s}' for k in
                                         ('V', 'beta', 'r', 'omega_R', 'delta', 'T_R')))
    for k in range(0, len(x['V']), every):
        cells = []
        for name in ('V', 'beta', 'r', 'omega_R', 'delta'):
            f = math.degrees if name in deg else float
            cells.append(f'{f(x[name][k]):6.2f} ({f(ref[name][k]):6.2f})')
        T = u['T_R'][min(k, len(u['T_R']) - 1)]   # N inputs for N + 1 states
        cells.append(f'{T:6.0f} ({ref["T_R"][k]:6.0f})')
        lines.append(f'  {k:5d}  ' + '  '.join(cells))
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', required=True, help='name under config/scenarios or file')
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        help='override a scenario key (surface.mu=0.55, plant.lsd.locking=1)')
    parser.add_argument('--vehicle', help='config/vehicle/<name>.yaml (default: the scenario\'s, '
                        'else config/defaults.yaml\'s)')
    parser.add_argument('--seed', type=cli_args.seed, default=None, help='a seed >= 0')
    parser.add_argument('--controller', choices=('nmpc', 'feedforward'), default='nmpc')
    parser.add_argument('--plant', choices=('double_track', 'single_track'),
                        default='double_track', help='single_track: the controller model itself '
                        '(diagnosis: no mismatch, no actuators, no noise)')
    parser.add_argument('--config-dir', default=str(config_dir()))
    parser.add_argument('--json', help='write the metrics here')
    parser.add_argument('--trace', help='write the time series here (.npz)')
    parser.add_argument('--stop-on-spin', action='store_true')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    parser.add_argument('--sensors', metavar='NAME', help='see the car through '
                        'config/sim/sensors/NAME.yaml (e.g. realistic) instead of the plant\'s '
                        'noise and delay model')
    parser.add_argument('--estimator', choices=('none', 'ekf'), default='none',
                        help='with --sensors: fuse them (ekf) or pass the newest samples (none)')
    parser.add_argument('--sensor-set', action='append', default=[], metavar='KEY=VALUE',
                        help='override a sensor key (ins.channels.beta.std=0.003)')
    parser.add_argument('--sensor-fault', action='append', default=[], metavar='FAULT',
                        help='unit[.channel]:kind:start:end[:value], e.g. ins:dropout:30:31')
    parser.add_argument('--plan-at', action='append', default=[], type=cli_args.seconds,
                        metavar='SECONDS', help='print the NMPC\'s plan at this time (repeat)')
    parser.add_argument('--allow-infeasible', action='store_true',
                        help='run a path that asks for a drift the car cannot hold')
    args = parser.parse_args(argv)
    if (args.estimator != 'none' or args.sensor_set or args.sensor_fault) and not args.sensors:
        parser.error('--estimator, --sensor-set and --sensor-fault need --sensors')
    trace_file = None if not args.trace else (
        args.trace if args.trace.endswith('.npz') else args.trace + '.npz')   # numpy's naming
    problem = ((cli_args.output_problem(args.json) if args.json else None)
               or (cli_args.output_problem(trace_file) if trace_file else None))
    if problem is not None:
        print(f'simulate: {problem}', file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.WARNING)
    try:
        out, trace = run_closed_loop(args.scenario, args.set, args.seed, args.controller,
                                     args.plant, args.config_dir, progress=not args.quiet,
                                     stop_on_spin=args.stop_on_spin, vehicle=args.vehicle,
                                     refuse_infeasible=not args.allow_infeasible,
                                     sensors=args.sensors, estimator=args.estimator,
                                     sensor_set=args.sensor_set,
                                     sensor_faults=args.sensor_fault,
                                     plans_at=args.plan_at)
    except ParamError as err:
        print(f'simulate: {err}', file=sys.stderr)
        return 2
    if trace_file:
        try:
            np.savez_compressed(trace_file, **trace)
        except OSError as err:
            print(f'simulate: {trace_file}: cannot be written ({err.strerror or err})',
                  file=sys.stderr)
            return 2
    for plan in out.get('plans', ()):
        print(format_plan(plan), file=sys.stderr)
    for t in sorted(args.plan_at)[len(out.get('plans', ())):]:
        print(f'simulate: no NMPC solve at {t:g} s (the run ended at '
              f"{out['sim_duration_s']:.2f} s)", file=sys.stderr)
    out = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
           for k, v in out.items()}
    text = json.dumps(out, indent=2, sort_keys=True)
    print(text)
    problem = cli_args.write_text(args.json, text + '\n') if args.json else None
    if problem is not None:
        print(f'simulate: {problem}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())

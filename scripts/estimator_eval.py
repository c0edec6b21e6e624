#!/usr/bin/env python3
"""Measures what the sensors and the state estimator do to the closed loop (issue 22).

    .venv/bin/python scripts/estimator_eval.py --seeds 0 1 2 --out runs/estimator_eval.json
    .venv/bin/python scripts/estimator_eval.py --seeds 0 --fault ins:dropout:30:31
    .venv/bin/python scripts/estimator_eval.py --synthetic 55 --seeds $(seq 0 59)

Per seed, one run each of (a) the plant's own measurement model (the default), (b) the realistic
sensors handed to the NMPC as their newest samples, (c) the realistic sensors through the EKF;
prints the NMPC torque request's std and mean |change| per 20 ms cycle in the steady window, the
sideslip RMS error against the reference, the error of the sideslip the controller saw, the
largest sideslip error in a fault window, and the estimator's NIS, events and cost per step.
Runs one simulation at a time.

``--synthetic SECONDS``: no closed loop; a steady drift the EKF's model describes exactly
(``drift_sim.synthetic``) through the realistic sensors, one run per seed, and over the seeds
each channel's mean NIS, its spread from run to run against the spread the runs' intervals
imply, and how many runs' means fall within their interval (a consistency check of the filter
and of its intervals).
"""
from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from drift_control import cli_args
from drift_control.params import ParamError
from drift_sim.closed_loop import run_closed_loop
from drift_sim.sensors import parse_fault

CONFIGS = {'a': {}, 'b': {'sensors': 'realistic', 'estimator': 'none'},
           'c': {'sensors': 'realistic', 'estimator': 'ekf'}}


def torque_smoothness(t, T_cmd, window, period=0.02):
    """Std and mean |change| per control period of the torque request in ``window`` [Nm]."""
    start, end = window
    keep = (t >= start) & (t < end)
    T = T_cmd[keep]
    step = max(1, int(round(period / (t[1] - t[0]))))
    T = T[::step]
    return float(np.std(T)), float(np.mean(np.abs(np.diff(T))))


def evaluate(scenario, seed, config, window, faults=(), estimator_set=(), sensor_set=(),
             vehicle=None):
    kwargs = dict(CONFIGS[config], vehicle=vehicle)
    if faults and 'sensors' in kwargs:
        kwargs['sensor_faults'] = list(faults)
    if config == 'c':
        kwargs['estimator_set'] = list(estimator_set)
    if 'sensors' in kwargs:
        kwargs['sensor_set'] = list(sensor_set)
    out, data = run_closed_loop(scenario, seed=seed, **kwargs)
    t = data['t']
    std, change = torque_smoothness(t, data['T_cmd'], window)
    row = {'scenario': scenario, 'vehicle': vehicle, 'seed': seed, 'config': config,
           'faults': list(faults),
           'spun': out['spun'], 'beta_rms_error_deg': out['beta_rms_error_deg'],
           'torque_std_Nm': std, 'torque_change_Nm': change,
           'max_abs_e_y_steady_m': out['max_abs_e_y_steady_m']}
    keep = (t >= window[0]) & (t < window[1])
    beta_ref = data['beta_ref']
    for fault in faults:
        parsed = parse_fault(fault)
        start, end = parsed.start, parsed.end
        inside = (t >= start) & (t < end + 0.5)
        row[f'max_beta_error_deg {fault}'] = float(np.degrees(
            np.nanmax(np.abs(data['beta'][inside] - beta_ref[inside]))))
    if 'beta_seen' in data:
        err = data['beta_seen'][keep] - data['beta'][keep]
        row['beta_seen_rms_error_deg'] = float(np.degrees(np.sqrt(np.mean(err ** 2))))
        row['r_seen_rms_error'] = float(np.sqrt(np.mean(
            (data['r_seen'][keep] - data['r'][keep]) ** 2)))
    summary = out.get('estimator_summary') or {}
    if summary:
        row['nis'] = summary['nis']
        row['events'] = summary['events']
        row.update({k: summary[k] for k in ('step_ms_mean', 'step_ms_p50', 'step_ms_p99')})
    return row


def synthetic_consistency(seconds, seeds, vehicle, estimator_set=(), sensor_set=()):
    """The NIS summaries of the synthetic drift, one per seed."""
    from drift_control.estimator import Estimator, load_estimator_params
    from drift_control.params import config_dir, load_vehicle
    from drift_sim import synthetic
    from drift_sim.sensors import Sensors, load_sensor_params
    car = load_vehicle(vehicle or 'm3_competition')
    params = load_estimator_params(config_dir() / 'estimator.yaml', estimator_set)
    sensor_params = load_sensor_params('realistic', overrides=sensor_set)
    out = []
    for seed in seeds:
        est = Estimator(car, params)
        synthetic.drive(Sensors(sensor_params, 0.01, seed), est, seconds,
                        lambda t: synthetic.circle(t, car))
        out.append({'seed': seed, 'nis': est.nis_summary()})
    return out


def print_consistency(rows) -> None:
    print(f'{"channel":22s} {"mean NIS":>9s} {"(s.e.)":>7s} {"spread":>7s} {"implied":>8s}  within')
    for name in rows[0]['nis']:
        means = np.array([r['nis'][name]['mean'] for r in rows])
        implied = np.mean([math.sqrt(2.0 / r['nis'][name]['n_eff']) for r in rows])
        within = sum(lo <= r['nis'][name]['mean'] <= hi
                     for r in rows for lo, hi in [r['nis'][name]['interval_95']])
        spread = means.std(ddof=1) if len(means) > 1 else float('nan')
        print(f'{name:22s} {means.mean():9.3f} {spread / math.sqrt(len(means)):7.3f} '
              f'{spread:7.3f} {implied:8.3f}  {within}/{len(rows)} '
              f'({rows[0]["nis"][name]["interval_from"]})')


def write_rows(path, rows) -> int:
    """The rows as JSON to ``path`` (none: nothing); an unwritable path is one line, exit 2."""
    if not path:
        return 0
    try:
        with open(path, 'w') as fh:
            json.dump(rows, fh, indent=1, default=lambda v: None if not math.isfinite(v) else v)
    except OSError as err:
        print(f'estimator_eval: --out {path}: {err.strerror}', file=sys.stderr)
        return 2
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', default='steady_dry')
    parser.add_argument('--vehicle', help="config/vehicle/<name>.yaml (default: the scenario's)")
    parser.add_argument('--seeds', type=cli_args.seed, nargs='+', default=[0])
    parser.add_argument('--configs', nargs='+', default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument('--window', type=cli_args.seconds, nargs=2, default=(20.0, 55.0),
                        metavar=('START', 'END'), help='the steady part [s] (default 20 55)')
    parser.add_argument('--fault', action='append', default=[],
                        help='a sensor fault for (b) and (c), e.g. ins:dropout:30:31')
    parser.add_argument('--estimator-set', action='append', default=[], metavar='KEY=VALUE',
                        help='override a key of config/estimator.yaml for (c)')
    parser.add_argument('--sensor-set', action='append', default=[], metavar='KEY=VALUE',
                        help='override a key of the sensor set for (b) and (c)')
    parser.add_argument('--synthetic', type=cli_args.positive, metavar='SECONDS',
                        help='the synthetic drift instead of the closed loop, this long')
    parser.add_argument('--out', help='write the rows here (JSON)')
    args = parser.parse_args(argv)
    if not args.window[0] < args.window[1]:
        parser.error(f'--window: START must be before END, got {args.window[0]:g} '
                     f'{args.window[1]:g}')
    try:
        for fault in args.fault:
            parse_fault(fault)
    except ParamError as err:
        parser.error(str(err))
    problem = cli_args.output_problem(args.out) if args.out else None
    if problem is not None:
        print(f'estimator_eval: {problem}', file=sys.stderr)
        return 2
    if args.synthetic is not None:
        try:
            rows = synthetic_consistency(args.synthetic, args.seeds, args.vehicle,
                                         args.estimator_set, args.sensor_set)
        except ParamError as err:
            print(f'estimator_eval: {err}', file=sys.stderr)
            return 2
        print_consistency(rows)
        return write_rows(args.out, rows)
    rows = []
    for seed in args.seeds:
        for config in args.configs:
            try:
                row = evaluate(args.scenario, seed, config, args.window, args.fault,
                               args.estimator_set, args.sensor_set, args.vehicle)
            except ParamError as err:
                print(f'estimator_eval: {err}', file=sys.stderr)
                return 2
            rows.append(row)
            brief = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()
                     if k not in ('nis', 'events')}
            print(json.dumps(brief), flush=True)
            if 'nis' in row:
                print('  NIS mean [its 95 % interval] / share within 95 %:')
                for name, v in row['nis'].items():
                    lo, hi = v['interval_95']
                    side = 'low' if v['mean'] < lo else 'high' if v['mean'] > hi else 'within'
                    print(f'    {name:22s} {v["mean"]:6.2f} [{lo:.2f}, {hi:.2f}] {side:6s} '
                          f'{v["within_95"]:.3f}')
                print('  events:', row['events'][:12], f'({len(row["events"])} in all)')
    return write_rows(args.out, rows)


if __name__ == '__main__':
    sys.exit(main())

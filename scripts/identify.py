#!/usr/bin/env python3
"""Identify the controller's single-track model from a recorded run (issue 23).

    identify.py BAG --vehicle NAME [--out FILE] [--report DIR] [--surface dry|wet]
    identify.py runs/sysid_dry_0 --vehicle m3_competition --out /tmp/cfg/vehicle/m3_id.yaml

Reads the measured vehicle state (``/vehicle/state``) and, for the powertrain, the drive torque
requests (``/drift/command``) of a bag (``scripts/sysid_drive.py``, a ``run_stack`` run, a car
through the bridge), fits what a data sheet does not give (``drift_control.sysid``: front and
rear tyre coefficients by default, ``--fit`` names others, ``--fit-inertia`` adds I_z) to
``--vehicle``'s YAML, and writes

- the vehicle YAML with the fitted values (``--out``; default
  ``BAG_sysid/<vehicle>_identified.yaml``) and an ``_identified`` record: the bag, the fit statistics, each value's prior and 95 % CI;
- a fit report in ``--report`` (default ``BAG_sysid/``): ``report.md``, ``fit.json``,
  ``predictions.png`` (yaw rate and sideslip predicted over 0.5 s from measured states on
  held-out data, identified and data-sheet model) and ``tyres.png``.

The surface is the bag's scenario's (its run record), else ``--surface`` (default dry). Exit 2
with one line on bad input (no bag, missing topics, unknown vehicle or parameter), 1 when the log
cannot identify a parameter (the line names it and why), 0 otherwise.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import sys
from pathlib import Path


def _fail(message: str, code: int = 2) -> int:
    print(f'identify: {message}', file=sys.stderr)
    return code


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bag', help='rosbag2 directory (metadata.yaml + .mcap)')
    parser.add_argument('--vehicle', required=True,
                        help='config/vehicle/<name>.yaml: the data sheet (mass, geometry) and '
                        'the starting point of the fitted values')
    parser.add_argument('--out', help='vehicle YAML to write (default: BAG_sysid/'
                        '<vehicle>_identified.yaml)')
    parser.add_argument('--report', help='report directory (default: BAG_sysid)')
    parser.add_argument('--surface', help="surface the log was driven on (default: the bag's "
                        "scenario's, else dry)")
    parser.add_argument('--fit', help='comma-separated parameters to fit (default: the tyres)')
    parser.add_argument('--fit-inertia', action='store_true', help='also fit the yaw inertia')
    parser.add_argument('--truth', action='store_true',
                        help='fit to /sim/state (ground truth; a diagnosis aid)')
    parser.add_argument('--config-dir', type=Path, default=None)
    parser.add_argument('--no-figures', action='store_true')
    args = parser.parse_args(argv)

    from drift_control import sysid
    from drift_control.cli_args import output_problem
    from drift_control.powertrain_fit import fit_powertrain
    from drift_control.prediction import predict
    from drift_control.params import (ParamError, config_dir, load_surface, load_vehicle,
                                      load_yaml, vehicle_file)
    from drift_tools.bag import read_bag
    from drift_tools.bag_salvage import BagDamagedError
    from drift_tools.run_info import read_run_info, run_scenario
    from drift_tools.timeseries import COMMAND, STATE, TRUTH, series_from_bag

    cfg = args.config_dir or config_dir()
    bag = Path(args.bag)
    if not (bag / 'metadata.yaml').is_file():
        return _fail(f'{bag}: not a bag directory (no metadata.yaml)')
    names = list(sysid.DEFAULT_FIT)
    if args.fit is not None:
        names = [n.strip() for n in args.fit.split(',') if n.strip()]
        if not names:
            return _fail(f'--fit: no parameter named in {args.fit!r}; fittable: '
                         f'{", ".join(sysid.FITTABLE)}')
    if args.fit_inertia and 'I_z' not in names:
        names.append('I_z')
    unknown = [n for n in names if n not in sysid.FITTABLE]
    if unknown:
        return _fail(f'--fit: {unknown[0]!r} is not fittable; fittable: '
                     f'{", ".join(sysid.FITTABLE)}')
    try:
        vfile = vehicle_file(args.vehicle, cfg)
        prior = load_vehicle(vfile)
        info = read_run_info(bag)
        scenario = run_scenario(info, cfg) if info and not args.surface else None
        surface = args.surface or (scenario.surface.name if scenario else 'dry')
        mu = load_surface(surface, Path(cfg) / 'vehicle' / 'surfaces.yaml').mu
        if scenario is not None and scenario.surface.mu > 0:
            mu = scenario.surface.mu
        topic = TRUTH if args.truth else STATE
        messages = read_bag(bag, topics=[topic, COMMAND])
    except (ParamError, BagDamagedError, ValueError, OSError) as err:
        return _fail(str(err))
    stem = f'{args.vehicle}_identified'
    report = Path(args.report) if args.report else bag.with_name(bag.name + '_sysid')
    out = Path(args.out) if args.out else report / f'{stem}.yaml'
    problem = (output_problem(report, [bag, vfile], directory=True)
               or output_problem(out, [bag, vfile]))
    if problem is not None:   # before the fit: the vehicle file read and the bag stay as they are
        return _fail(problem)
    run = series_from_bag(messages)
    state = run.truth if args.truth else run.state
    if len(state.get('t', ())) < 100:
        return _fail(f'{bag}: no {topic} in the bag (or under 1 s of it): the fit needs the '
                     'vehicle state')
    log = sysid.uniform_log(state, run.command)
    try:
        fit = sysid.identify(log, prior, mu, names)
        train, held = sysid.split(log, sysid.SysIdSettings())
        pred_fit = predict(fit.vehicle, log, held, mu)
        pred_prior = predict(prior, log, held, mu)
    except sysid.IdentificationError as err:
        return _fail(str(err), 1)

    report.mkdir(parents=True, exist_ok=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    summary = _summary(bag, info, args, surface, mu, log, fit, fit_powertrain(log), pred_fit,
                       pred_prior, sysid.SysIdSettings().horizon_s)
    raw = load_yaml(vfile)
    for p in fit.params:
        _set(raw, p.name, float(f'{p.value:.4g}'))
    for block in ('front_tyre', 'rear_tyre'):     # each block says which of its values are fitted
        fitted = [p.name.split('.', 1)[1] for p in fit.params if p.name.startswith(block + '.')]
        if fitted and isinstance(raw.get(block), dict):
            raw[block]['_source'] = (f"[identified] {', '.join(fitted)} fitted to {bag.name} "
                                     '(scripts/identify.py); the rest as the data sheet: '
                                     + str(raw[block].get('_source', '')).strip())
    if summary['powertrain'] is not None:   # the car's own lag, for the NMPC (VehicleParams)
        raw['torque_lag'] = summary['powertrain']['nmpc_torque_lag_s']
    raw['_identified'] = {k: summary[k] for k in ('bag', 'scenario', 'seed', 'surface',
                                                   'date', 'log_s', 'parameters', 'held_out',
                                                   'powertrain')}
    import yaml
    header = (f'# {args.vehicle} with its tyre coefficients identified from {bag.name} by '
              'scripts/identify.py (issue 23).\n# Identified values carry their 95 % CI and '
              'prior in _identified.parameters; the rest is the data sheet of '
              f'{vfile.name}.\n')
    out.write_text(header + yaml.safe_dump(raw, sort_keys=False, width=100))
    try:
        load_vehicle(out)          # what was written loads like any vehicle
    except ParamError as err:
        return _fail(f'{out}: the identified vehicle does not validate: {err}', 1)
    (report / 'fit.json').write_text(json.dumps(summary, indent=2) + '\n')
    (report / 'report.md').write_text(_markdown(summary, out))
    if not args.no_figures:
        _figures(report, log, held, fit, prior, pred_fit, pred_prior, mu)
    print((report / 'report.md').read_text())
    return 0


def _set(raw: dict, dotted: str, value: float) -> None:
    node = raw
    *path, last = dotted.split('.')
    for part in path:
        node = node[part]
    node[last] = value


def _summary(bag, info, args, surface, mu, log, fit, lag, pred_fit, pred_prior,
             horizon_s: float) -> dict:
    deg = math.degrees
    return {
        'bag': str(bag.resolve()),
        'scenario': (info or {}).get('scenario', ''),
        'seed': (info or {}).get('seed', ''),
        'source': '/sim/state' if args.truth else '/vehicle/state',
        'surface': f'{surface} (mu {mu:g})',
        'date': datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ'),
        'log_s': round(log.duration, 2),
        'fit_s': round(fit.seconds, 2),
        'samples': {'train': fit.n_train, 'held_out': fit.n_held,
                    'residual_correlation_samples': round(fit.correlation_samples, 1)},
        'parameters': {p.name: {'value': float(f'{p.value:.5g}'), 'ci95': float(f'{p.ci95:.3g}'),
                                'prior': p.prior} for p in fit.params},
        'rms_derivative_error': {'train': {k: float(f'{v:.4g}') for k, v in fit.rms_train.items()},
                                 'held_out': {k: float(f'{v:.4g}')
                                              for k, v in fit.rms_held.items()}},
        'held_out': {
            'horizon_s': horizon_s,
            'windows': int(len(pred_fit.t0)),
            'identified': {'rms_r': round(pred_fit.rms_r, 5),
                           'rms_beta_deg': round(deg(pred_fit.rms_beta), 4)},
            'data_sheet': {'rms_r': round(pred_prior.rms_r, 5),
                           'rms_beta_deg': round(deg(pred_prior.rms_beta), 4)}},
        'grip_evidence': {k: {kk: round(vv, 3) for kk, vv in v.items()}
                          for k, v in fit.evidence.items()},
        'powertrain': None if lag is None else {
            'delay_s': round(lag.delay, 3), 'tau_s': round(lag.tau, 4),
            'tau_ci95_s': float(f'{lag.tau_ci95:.2g}'), 'rms_Nm': round(lag.rms, 1),
            'nmpc_torque_lag_s': round(lag.torque_lag, 3),
            'note': 'request to measured torque (includes the signal delay): delay + tau, '
                    'written as the vehicle\'s torque_lag (the NMPC\'s lag for this car)'},
    }


def _markdown(s: dict, out: Path) -> str:
    lines = [f"# Identification of {Path(s['bag']).name}", '',
             f"{s['log_s']:.0f} s of {s['source']} on {s['surface']}, fitted in {s['fit_s']:.1f} s "
             f"({s['samples']['train']} samples fitted, {s['samples']['held_out']} held out; "
             f"residual correlation {s['samples']['residual_correlation_samples']} samples). "
             f'Vehicle YAML: `{out}`.', '',
             '| parameter | identified | 95 % CI | prior (data sheet) |', '|---|---|---|---|']
    for name, p in s['parameters'].items():
        lines.append(f"| {name} | {p['value']:.4g} | +-{p['ci95']:.2g} | {p['prior']:.4g} |")
    h = s['held_out']
    lines += ['', f"Held out: {h['windows']} predictions of {h['horizon_s']} s from measured "
              'states under the measured inputs.', '',
              '| model | yaw rate RMS [rad/s] | sideslip RMS [deg] |', '|---|---|---|',
              f"| identified | {h['identified']['rms_r']:.4f} | "
              f"{h['identified']['rms_beta_deg']:.3f} |",
              f"| data sheet | {h['data_sheet']['rms_r']:.4f} | "
              f"{h['data_sheet']['rms_beta_deg']:.3f} |", '',
              '| derivative RMS error | ' + ' | '.join(s['rms_derivative_error']['train']) + ' |',
              '|---|' + '---|' * len(s['rms_derivative_error']['train'])]
    for part in ('train', 'held_out'):
        lines.append(f'| {part} | ' + ' | '.join(
            f'{v:.4g}' for v in s['rms_derivative_error'][part].values()) + ' |')
    ev = s['grip_evidence']['fitted']
    lines += ['', f"Grip limits in the log (fitted model): rear slip angle past 1.5 x its peak "
              f"({ev['rear_peak_deg']:.1f} deg) for {ev['rear_beyond_s']:.1f} s, up to "
              f"{ev['rear_max_deg']:.0f} deg; front slip angle up to {ev['front_max_deg']:.1f} "
              f"deg (peak {ev['front_peak_deg']:.1f} deg); rear wheelspin past the driving "
              f"peak for {ev['spin_s']:.1f} s, {ev['spin_straight_s']:.2f} s of it at small slip "
              'angles (what the pure peak `pDx1` needs).']
    pt = s['powertrain']
    lines += ['', 'Powertrain: no drive torque requests in the bag, not identified.' if pt is None
              else f"Powertrain: delay {pt['delay_s'] * 1000:.0f} ms + lag "
              f"{pt['tau_s'] * 1000:.0f} ms (+-{pt['tau_ci95_s'] * 1000:.1f}), RMS {pt['rms_Nm']:.0f} Nm: torque_lag "
              f"{pt['nmpc_torque_lag_s']:.3f} s ({pt['note']}).", '']
    return '\n'.join(lines)


def _figures(report, log, held, fit, prior, pred_fit, pred_prior, mu) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import numpy as np

    from drift_control.sysid import smooth
    from drift_control.tyre import combined_forces, simple_force
    from drift_control.vehicle import X

    data = smooth(log, 0.21)
    t = log.t - log.t[0]
    # the held-out block with the most sideslip: where a drift is predicted
    block = ((log.t - log.t[0]) // 10.0).astype(int)
    blocks = sorted(set(block[held]))
    best = max(blocks, key=lambda b: np.abs(log.beta[(block == b) & held]).max())
    sel = (block == best) & held
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    for ax, key, scale, label in ((axes[0], 'r', 1.0, 'yaw rate [rad/s]'),
                                  (axes[1], 'beta', 180 / math.pi, 'sideslip [deg]')):
        row = X.R if key == 'r' else X.BETA
        ax.plot(t[sel], data.x[sel, row] * scale, 'k', lw=1.5, label='measured (smoothed)')
        H = getattr(pred_fit, key).shape[1]
        for pred, color, name in ((pred_fit, 'tab:blue', 'identified'),
                                  (pred_prior, 'tab:red', 'data sheet')):
            first = True
            for t0, y in zip(pred.t0 - log.t[0], getattr(pred, key)):
                if (block[int(round(t0 / log.dt))] == best):
                    ax.plot(t0 + log.dt * np.arange(1, H + 1), y * scale, color=color, lw=1,
                            label=f'{name}, 0.5 s predictions' if first else None)
                    first = False
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[1].set_xlabel('time [s]')
    fig.suptitle('held-out data: open-loop predictions from measured states')
    fig.tight_layout()
    fig.savefig(report / 'predictions.png', dpi=110)
    plt.close(fig)

    alpha = np.radians(np.linspace(0, 40, 200))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for p, style, name in ((prior, '--', 'data sheet'), (fit.vehicle, '-', 'identified')):
        F_zR = p.m * p.g * p.a / p.L
        axes[0].plot(np.degrees(alpha), [float(simple_force(a, 1.0, p.front_tyre.lateral, mu))
                                         for a in alpha], style, label=name)
        axes[1].plot(np.degrees(alpha), [float(combined_forces(a, 0.0, F_zR, p.rear_tyre, mu).Fy)
                                         / F_zR for a in alpha], style, label=name)
    ev = fit.evidence['fitted']
    axes[0].axvline(ev['front_max_deg'], color='gray', lw=0.8, label='largest slip in the log')
    axes[1].axvline(min(ev['rear_max_deg'], 40), color='gray', lw=0.8)
    for ax, title in zip(axes, ('front axle, lateral', 'rear axle, lateral (kappa = 0)')):
        ax.set_title(title)
        ax.set_xlabel('slip angle [deg]')
        ax.set_ylabel('F_y / F_z [-]')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(report / 'tyres.png', dpi=110)
    plt.close(fig)


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""Build a vehicle's equilibrium maps <maps>/<vehicle>/<surface>.npz + .json (paper section III).

    python scripts/build_maps.py --vehicle gr86 --surface all [--jobs N]
    python scripts/build_maps.py --config-dir ~/mycar/config --vehicle mycar

Maps go where ``maps:`` of the config dir's ``defaults.yaml`` says (the checkout's ``maps/`` for
its own ``config/``), each with the hash of the vehicle and surface it was built for.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

from tqdm import tqdm

from drift_control.assembly import map_file
from drift_control.cli_args import count, output_problem
from drift_control.eqmap import GridParams, build_map, load_map_params, map_paths, save_map
from drift_control.params import ParamError, config_dir, load_surface, load_vehicle, vehicle_file


def _range(text: str) -> tuple[float, float, float]:
    try:
        start, stop, step = (float(v) for v in text.split(':'))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected start:stop:step, got {text!r}') from None
    return start, stop, step


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vehicle', help='config/vehicle/<name>.yaml (default: defaults.yaml\'s)')
    ap.add_argument('--surface', choices=('dry', 'wet', 'all'), default='all')
    ap.add_argument('--beta-deg', type=_range, help='sideslip grid start:stop:step [deg]')
    ap.add_argument('--radius', type=_range, help='radius grid start:stop:step [m]')
    ap.add_argument('--jobs', type=count, default=os.cpu_count() or 1, help='worker processes')
    ap.add_argument('--config-dir', type=Path, default=None,
                    help='config directory (default: the checkout\'s config/)')
    ap.add_argument('--out', type=Path, help='output directory (default: <maps>/<vehicle>/)')
    args = ap.parse_args(argv)
    cfg = args.config_dir or config_dir()
    try:
        vfile = vehicle_file(args.vehicle, cfg)
        vehicle = load_vehicle(vfile)
        params = load_map_params(cfg / 'maps.yaml')
        grid = params.grid
        if args.beta_deg:
            grid = dataclasses.replace(grid, beta_deg=args.beta_deg)
        if args.radius:
            grid = dataclasses.replace(grid, radius_m=args.radius)
        params = dataclasses.replace(params, grid=grid)
        GridParams(*dataclasses.astuple(grid))   # validate the overrides
        surfaces = [load_surface(name, cfg / 'vehicle' / 'surfaces.yaml') for name in
                    (('dry', 'wet') if args.surface == 'all' else (args.surface,))]
    except ParamError as err:
        print(f'build_maps: {err}', file=sys.stderr)
        return 2
    name = vfile.stem
    targets = [args.out / s.name if args.out else map_file(name, s.name, cfg) for s in surfaces]
    for target in targets:   # before minutes of solving
        problem = output_problem(map_paths(target)[0])
        if problem is not None:
            print(f'build_maps: {problem}', file=sys.stderr)
            return 2
    for surface in surfaces:
        n_rows = len(grid.radius())
        with tqdm(total=n_rows, desc=f'{name} {surface.name} (mu {surface.mu})',
                  unit='row') as bar:
            eqmap = build_map(vehicle, surface, params, jobs=args.jobs,
                              on_row=lambda _j: bar.update())
        eqmap.meta['vehicle'] = name
        out = args.out / surface.name if args.out else map_file(name, surface.name, cfg)
        npz, meta = save_map(eqmap, out)
        n = eqmap.converged.size
        t = eqmap.meta['build_time_s']
        print(f'{name} {surface.name}: {eqmap.converged_fraction:.1%} of {n} points converged, '
              f'{t:.1f} s on {args.jobs} process(es) ({1e3 * t * args.jobs / n:.1f} ms per '
              f'point and process) -> {npz}, {meta.name}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

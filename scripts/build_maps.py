#!/usr/bin/env python3
"""Build the equilibrium maps maps/<surface>.npz + .json from the YAML parameters (section III).

    python scripts/build_maps.py --surface all [--beta-deg 0:45:1] [--radius 8:40:1] [--jobs N]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

from tqdm import tqdm

from drift_control.eqmap import GridParams, build_map, load_map_params, save_map
from drift_control.params import load_surface, load_vehicle

MAPS_DIR = Path(__file__).resolve().parents[1] / 'maps'


def _range(text: str) -> tuple[float, float, float]:
    try:
        start, stop, step = (float(v) for v in text.split(':'))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected start:stop:step, got {text!r}') from None
    return start, stop, step


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--surface', choices=('dry', 'wet', 'all'), default='all')
    ap.add_argument('--beta-deg', type=_range, help='sideslip grid start:stop:step [deg]')
    ap.add_argument('--radius', type=_range, help='radius grid start:stop:step [m]')
    ap.add_argument('--jobs', type=int, default=os.cpu_count() or 1, help='worker processes')
    ap.add_argument('--config', help='maps YAML (default config/maps.yaml)')
    ap.add_argument('--out', type=Path, default=MAPS_DIR, help='output directory')
    args = ap.parse_args(argv)

    params = load_map_params(args.config)
    grid = params.grid
    if args.beta_deg:
        grid = dataclasses.replace(grid, beta_deg=args.beta_deg)
    if args.radius:
        grid = dataclasses.replace(grid, radius_m=args.radius)
    params = dataclasses.replace(params, grid=grid)
    GridParams(*dataclasses.astuple(grid))   # validate the overrides

    vehicle = load_vehicle()
    surfaces = ('dry', 'wet') if args.surface == 'all' else (args.surface,)
    for name in surfaces:
        surface = load_surface(name)
        n_rows = len(grid.radius())
        with tqdm(total=n_rows, desc=f'{name} (mu {surface.mu})', unit='row') as bar:
            eqmap = build_map(vehicle, surface, params, jobs=args.jobs,
                              on_row=lambda _j: bar.update())
        npz, meta = save_map(eqmap, args.out / name)
        n = eqmap.converged.size
        t = eqmap.meta['build_time_s']
        print(f'{name}: {eqmap.converged_fraction:.1%} of {n} points converged, '
              f'{t:.1f} s on {args.jobs} process(es) ({1e3 * t * args.jobs / n:.1f} ms per '
              f'point and process) -> {npz}, {meta.name}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""Plot the equilibrium maps like the paper's Fig. 2: docs/maps_<surface>.png.

    python scripts/plot_maps.py [--surface dry|wet|all] [--radii 8,12,16,20,25,30,40]

Each panel shows one quantity against the sideslip for several radii (converged points only);
markers: peak drive torque (blue), peak rear lateral force (cyan), peak front lateral force
(teal), onset of the full drift, i.e. rear longitudinal slip past its peak (black x).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from drift_control.assembly import load_checked_map  # noqa: E402
from drift_control.cli_args import positive  # noqa: E402
from drift_control.eqmap import KINDS  # noqa: E402
from drift_control.params import (ParamError, default_vehicle, load_surface,  # noqa: E402
                                  load_vehicle, vehicle_file)

ROOT = Path(__file__).resolve().parents[1]
# (field, colour, marker size, label); the rear marker is drawn larger so a coinciding front
# peak does not hide it
PEAKS = (('F_yR', 'cyan', 10, 'peak rear lateral force'), ('F_yF', 'teal', 6,
         'peak front lateral force'), ('T_R', 'blue', 6, 'peak drive torque'))


def plot(vehicle: str, surface: str, radii: list[float], out: Path) -> None:
    m = load_checked_map(vehicle, load_vehicle(vehicle), load_surface(surface))
    beta_deg = np.degrees(m.beta_abs)
    d = m.data
    panels = [('(a) $F_{yF}^{eq}$ [kN]', lambda j: d['F_yF'][:, j] / 1e3),
              ('(b) $F_{yR}^{eq}$ [kN]', lambda j: d['F_yR'][:, j] / 1e3),
              ('(c) $\\omega_F^{eq}$ (--), $\\omega_R^{eq}$ (-) [rad/s]', None),
              ('(d) $T_R^{eq}$ [kNm]', lambda j: d['T_R'][:, j] / 1e3),
              ('(e) $\\delta^{eq}$ [deg]', lambda j: np.degrees(d['delta'][:, j])),
              ('(f) $V^{eq}$ [m/s]', lambda j: d['V'][:, j])]
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5), sharex=True)
    colours = plt.cm.viridis(np.linspace(0, 0.9, len(radii)))
    drift = KINDS.index('drift')
    for R, c in zip(radii, colours):
        j = int(np.abs(m.radius - R).argmin())
        ok = m.converged[:, j]
        if not ok.any():
            continue
        first_drift = np.flatnonzero(ok & (d['kind'][:, j] == drift))
        for ax, (title, value) in zip(axes.flat, panels):
            if value is None:   # wheel speeds: both in one panel
                ax.plot(beta_deg, np.where(ok, d['omega_R'][:, j], np.nan), '-', color=c,
                        label=f'R = {m.radius[j]:.0f} m')
                ax.plot(beta_deg, np.where(ok, d['omega_F'][:, j], np.nan), '--', color=c)
                ys = d['omega_R'][:, j]
            else:
                ys = value(j)
                ax.plot(beta_deg, np.where(ok, ys, np.nan), '-', color=c)
            for name, colour, size, _ in PEAKS:
                i = np.flatnonzero(ok)[np.argmax(np.abs(d[name][ok, j]))]
                ax.plot(beta_deg[i], ys[i], 'o', color=colour, ms=size, mec='k', mew=0.5)
            if first_drift.size:
                i = first_drift[0]
                ax.plot(beta_deg[i], ys[i], 'x', color='k', ms=7, mew=1.5)
            ax.set_title(title)
    for ax in axes[1]:
        ax.set_xlabel('sideslip $|\\beta^{eq}|$ [deg]')
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    axes[1, 1].axhline(0.0, color='k', lw=0.8)
    handles, _ = axes[0, 2].get_legend_handles_labels()
    handles += [plt.Line2D([], [], ls='', marker='o', color=col, mec='k', label=lab)
                for _, col, _, lab in PEAKS]
    handles.append(plt.Line2D([], [], ls='', marker='x', color='k',
                              label='rear slip past its longitudinal peak (drift onset)'))
    fig.legend(handles=handles, loc='lower center', ncol=6, fontsize=9)
    fig.suptitle(f'{vehicle}: steady-state drift equilibria, {surface} (mu {m.meta["mu"]}), '
                 f'left drift; '
                 f'{m.converged_fraction:.0%} of the grid converged, gaps = no equilibrium '
                 f'within the bounds')
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f'wrote {out}')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vehicle', help='config/vehicle/<name>.yaml (default: defaults.yaml\'s)')
    ap.add_argument('--surface', choices=('dry', 'wet', 'all'), default='all')
    ap.add_argument('--radii', default='8,12,16,20,25,30,40', help='radii to draw [m]')
    args = ap.parse_args(argv)
    try:
        radii = [positive(r) for r in args.radii.split(',')]
    except argparse.ArgumentTypeError as err:
        ap.error(f'--radii: {err}')
    try:
        vehicle = vehicle_file(args.vehicle).stem
    except ParamError as err:
        print(f'plot_maps: {err}', file=sys.stderr)
        return 2
    suffix = '' if vehicle == default_vehicle() else f'_{vehicle}'
    try:
        for surface in (('dry', 'wet') if args.surface == 'all' else (args.surface,)):
            plot(vehicle, surface, radii, ROOT / 'docs' / f'maps_{surface}{suffix}.png')
    except ParamError as err:
        print(f'plot_maps: {err}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())

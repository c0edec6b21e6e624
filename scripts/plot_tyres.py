#!/usr/bin/env python3
"""Plot the controller's tyre curves (pure and combined slip, dry and wet) to a PNG.

    .venv/bin/python scripts/plot_tyres.py [--out docs/tyre_curves.png]
"""
import argparse
import sys
from pathlib import Path

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from drift_control.cli_args import output_problem  # noqa: E402
from drift_control.params import ParamError, load_surface, load_vehicle, vehicle_file  # noqa: E402
from drift_control.tyre import (combined_forces, front_forces, lateral_peak_slip,  # noqa: E402
                                longitudinal_peak_slip)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--vehicle', help='config/vehicle/<name>.yaml (default: defaults.yaml\'s)')
    parser.add_argument('--out', default='docs/tyre_curves.png')
    args = parser.parse_args(argv)
    out = Path(args.out)
    if not out.suffix:   # matplotlib would add its default format's
        out = out.with_suffix('.png')
    problem = output_problem(out)
    if problem is not None:
        print(f'plot_tyres: {problem}', file=sys.stderr)
        return 2
    try:
        vfile = vehicle_file(args.vehicle)
        vp = load_vehicle(vfile)
    except ParamError as err:
        print(f'plot_tyres: {err}', file=sys.stderr)
        return 2
    f_zF = vp.m * vp.g * vp.b / vp.L
    f_zR = vp.m * vp.g * vp.a / vp.L
    alpha = np.radians(np.linspace(-60, 60, 601))
    kappa = np.linspace(-1.0, 1.0, 601)
    fig, ax = plt.subplots(2, 2, figsize=(11, 8))
    for name, style in (('dry', '-'), ('wet', '--')):
        mu = load_surface(name).mu
        ax[0, 0].plot(np.degrees(alpha), [front_forces(a, 0.0, f_zF, vp.front_tyre, mu).Fy / 1e3
                                          for a in alpha], style, label=f'front F_yF, {name}')
        ax[0, 0].plot(np.degrees(alpha), [combined_forces(a, 0.0, f_zR, vp.rear_tyre, mu).Fy / 1e3
                                          for a in alpha], style, label=f'rear F_yR, {name}')
        ax[0, 1].plot(kappa, [combined_forces(0.0, k, f_zR, vp.rear_tyre, mu).Fx / 1e3
                              for k in kappa], style, label=f'rear F_xR, {name}')
    for a_deg in (0, 5, 10, 20, 35):
        a = np.radians(a_deg)
        forces = [combined_forces(a, k, f_zR, vp.rear_tyre, 1.0) for k in kappa]
        ax[1, 0].plot(kappa, [f.Fy / 1e3 for f in forces], label=f'alpha {a_deg} deg')
        ax[1, 1].plot([f.Fx / 1e3 for f in forces], [f.Fy / 1e3 for f in forces],
                      label=f'alpha {a_deg} deg')
    kp = longitudinal_peak_slip(f_zR, vp.rear_tyre)
    ap = np.degrees(lateral_peak_slip(f_zR, vp.rear_tyre))
    ax[0, 0].set(title=f'Pure lateral (static axle loads; rear peak at {ap:.1f} deg)',
                 xlabel='slip angle alpha [deg]', ylabel='force [kN]')
    ax[0, 1].set(title=f'Pure longitudinal, rear (peak at kappa {kp:.3f})',
                 xlabel='longitudinal slip kappa [-]', ylabel='force [kN]')
    ax[1, 0].set(title='Combined slip, rear: F_yR falls as the wheel spins (dry)',
                 xlabel='longitudinal slip kappa [-]', ylabel='F_yR [kN]')
    ax[1, 1].set(title='Combined slip, rear: force envelope (dry)', xlabel='F_xR [kN]',
                 ylabel='F_yR [kN]')
    ax[1, 1].set_aspect('equal')
    for a in ax.flat:
        a.grid(True, alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle(f'Controller tyre model (config/vehicle/{vfile.name})')
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

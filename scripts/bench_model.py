#!/usr/bin/env python3
"""Evaluation cost of the single-track model f(x, u, theta) and its Jacobians.

Prints microseconds per call for the casadi Function called from Python (one point), the same
mapped over 1000 points (the per-point cost without Python overhead), and the Jacobian.

    .venv/bin/python scripts/bench_model.py [--repeat 2000]
"""
import argparse
import sys
import time

import casadi as ca
import numpy as np

from drift_control.cli_args import count
from drift_control.params import ParamError, load_vehicle
from drift_control.vehicle import NTHETA, NU, NX, X, VehicleModel


def per_call_us(fun, args, repeat: int) -> float:
    fun(*args)
    best = float('inf')
    for _ in range(5):   # best of 5 batches: the least disturbed by other processes
        t0 = time.perf_counter()
        for _ in range(repeat):
            fun(*args)
        best = min(best, (time.perf_counter() - t0) / repeat)
    return best * 1e6


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=count, default=2000, help='calls per batch')
    parser.add_argument('--vehicle', help='config/vehicle/<name>.yaml (default: defaults.yaml\'s)')
    args = parser.parse_args(argv)
    try:
        vp = load_vehicle(args.vehicle)
    except ParamError as err:
        print(f'bench_model: {err}', file=sys.stderr)
        return 2
    model = VehicleModel(vp)
    x = np.zeros(NX)
    x[[X.V, X.BETA, X.R, X.OMEGA_F, X.OMEGA_R, X.DELTA]] = 10.7, -0.52, 0.71, 31.2, 41.8, -0.38
    u, theta = np.array([0.0, 1434.0]), np.array([1 / 15, 1.0])
    xs, us, ts = ca.SX.sym('x', NX), ca.SX.sym('u', NU), ca.SX.sym('t', NTHETA)
    out = model.f(xs, us, ts)
    jac = ca.Function('jac_f', [xs, us, ts], [ca.jacobian(out, ca.vertcat(xs, us))])
    n = 1000
    batch = (np.tile(x[:, None], n), np.tile(u[:, None], n), np.tile(theta[:, None], n))
    rows = [
        ('f, one call from Python', per_call_us(model.f, (x, u, theta), args.repeat)),
        ('f, per point in a map of 1000', per_call_us(model.f.map(n), batch, 20) / n),
        ('df/d(x,u), one call from Python', per_call_us(jac, (x, u, theta), args.repeat)),
        ('df/d(x,u), per point in a map of 1000', per_call_us(jac.map(n), batch, 20) / n),
    ]
    print(f'model: {model.f.n_instructions()} SX instructions in f, '
          f'{jac.n_instructions()} in the Jacobian (load_passes={model.load_passes})')
    for name, us_ in rows:
        print(f'  {name:42s} {us_:8.2f} us')
    return 0


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""Benchmark the NMPC in closed loop at a 30 deg drift, against do-mpc on the same problem.

Plant: the full single-track model (dynamic front wheel, 1 ms RK4) with the friction 5 % below
the controller's and noisy measurements. Prints percentiles of the step (state in -> command out,
the Python wrapper included) and of the solve inside it, the ratio p99 / 20 ms budget,
failures, tracking error, and the same loop with do-mpc (same model via ``vehicle.rhs``,
same RK4 stage, horizon, cost, bounds and scaling; do-mpc's defaults otherwise: IPOPT, MUMPS),
giving the speed-up measured in this run. ``--compare`` runs every solver option as well.

    .venv/bin/python scripts/bench_nmpc.py [--seconds 10] [--json out.json] [--compare]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from drift_control.equilibrium import solve_equilibrium
from drift_control.nmpc import Nmpc, reference_rows
from drift_control.ocp import NXO, NmpcParams, Ocp, load_nmpc_params
from drift_control.assembly import load_checked_map, map_file
from drift_control.params import ParamError, load_surface, load_vehicle, vehicle_file
from drift_control.signals import Command, Direction, Mode, Reference, VehicleState
from drift_control.vehicle import VehicleModel

BUDGET = 0.02   # control period [s]


def reference_equilibrium(name: str, vehicle, surface: str, beta_deg: float, radius: float):
    """The vehicle's map equilibrium when its map exists, else solved directly."""
    npz = map_file(name, surface).with_suffix('.npz')
    if npz.exists():   # stale: a ParamError naming the rebuild command
        eqmap = load_checked_map(name, vehicle, load_surface(surface))
        eq, _ = eqmap.lookup(math.radians(beta_deg), radius, Direction.LEFT)
        return eq, f'map {npz}'
    mu = load_surface(surface).mu
    return solve_equilibrium(math.radians(-beta_deg), radius, vehicle, mu=mu).eq, 'solved'


class DoMpcController:
    """do-mpc on the same OCP: discrete model with the NMPC's RK4 stage (vehicle states and the
    powertrain lag state), same cost and bounds; without our offset-free model-error estimate."""

    def __init__(self, vehicle, params: NmpcParams, mu: float):
        import casadi as ca
        try:   # do-mpc mixes numpy and casadi; keep casadi's legacy behaviour, without the notice
            ca.GlobalOptions.setNumpyMode(-1)
        except AttributeError:
            pass
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            import do_mpc
        ocp = Ocp(vehicle, params)
        c, b = params.cost, ocp.bounds
        model = do_mpc.model.Model('discrete', 'SX')
        names = ('V', 'beta', 'r', 'omega_F', 'omega_R', 'delta', 'T_act')
        x = ca.vertcat(*[model.set_variable('_x', n) for n in names])
        u = ca.vertcat(model.set_variable('_u', 'delta_dot'), model.set_variable('_u', 'T_R'))
        ref = model.set_variable('_tvp', 'ref', shape=(7, 1))
        mu_p = model.set_variable('_p', 'mu')
        x_next = ocp.F(ca.vertcat(x, 0.0), u, mu_p, params.torque_lag)[:NXO + 1]   # T_last: r-term
        for i, n in enumerate(names):
            model.set_rhs(n, x_next[i])
        model.setup()
        # after setup the objective must use the model's own structured symbols
        x = ca.vertcat(*[model.x[n] for n in names[:NXO]])
        u = ca.vertcat(model.u['delta_dot'], model.u['T_R'])
        ref = model.tvp['ref']
        scale = np.array([c.V, c.beta, c.r, c.omega_F, c.omega_R, c.delta])
        err = ca.sumsqr((x - ref[:NXO]) / scale)
        T_R_scale, T_R_rate_scale = c.torque(b)
        lterm = err + (u[0] / c.delta_dot) ** 2 + ((u[1] - ref[6]) / T_R_scale) ** 2
        mpc = do_mpc.controller.MPC(model)
        mpc.settings.n_horizon = params.N
        mpc.settings.t_step = params.dt
        mpc.settings.store_full_solution = False
        mpc.settings.nlpsol_opts = {'ipopt.print_level': 0, 'ipopt.sb': 'yes', 'print_time': 0}
        mpc.set_objective(lterm=lterm, mterm=c.terminal_factor * err)
        mpc.set_rterm(T_R=1.0 / (T_R_rate_scale * params.dt) ** 2)
        mpc.bounds['lower', '_x', 'delta'] = -b.delta_max
        mpc.bounds['upper', '_x', 'delta'] = b.delta_max
        mpc.bounds['lower', '_u', 'delta_dot'] = -b.delta_dot_max
        mpc.bounds['upper', '_u', 'delta_dot'] = b.delta_dot_max
        mpc.bounds['lower', '_u', 'T_R'] = b.T_R_min
        mpc.bounds['upper', '_u', 'T_R'] = b.T_R_max
        for n, s in zip(names, ocp.state_scale()):
            mpc.scaling['_x', n] = s
        # no input scaling: do-mpc's default r-term penalises the *scaled* input change
        mpc.set_uncertainty_values(mu=np.array([mu]))
        self._tvp = mpc.get_tvp_template()
        self._ref = np.zeros(7)

        def tvp_fun(t_now):
            for k in range(params.N + 1):
                self._tvp['_tvp', k, 'ref'] = self._ref
            return self._tvp
        mpc.set_tvp_fun(tvp_fun)
        mpc.setup()
        self.mpc, self.params, self._started = mpc, params, False
        self._T_act = 0.0

    def step(self, state: VehicleState, ref: Reference, now: float):
        if not self._started:
            self._T_act = ref.target.T_R
        x0 = np.array([[state.V], [state.beta], [state.r], [state.omega_F], [state.omega_R],
                       [state.delta], [self._T_act]])
        self._ref = reference_rows(ref, self.params.N)[0]
        if not self._started:
            self.mpc.x0 = x0
            self.mpc.u0 = np.array([[0.0], [ref.target.T_R]])
            self.mpc.set_initial_guess()
            self._started = True
        t0 = time.perf_counter()
        u = np.asarray(self.mpc.make_step(x0)).ravel()
        dt = time.perf_counter() - t0
        ok = bool(self.mpc.solver_stats['success'])
        lag = self.params.torque_lag   # the same torque model as the NMPC's
        self._T_act = u[1] if lag <= 0 else self._T_act + (
            1.0 - math.exp(-self.params.Ts / lag)) * (u[1] - self._T_act)
        return Command(now, state.delta + u[0] * self.params.Ts, u[0], u[1], Mode.FULL), ok, dt


def closed_loop(step, vehicle, eq, seconds: float, mu: float, seed: int = 0,
                actuator: bool = False, prepare=None) -> dict:
    """Run ``step(state, ref, now) -> (command, solved, solve_time)`` against the plant, and
    ``prepare()`` after each step (the work ahead of the next state: timed apart).

    ``actuator``: the drive torque reaches the wheels through a powertrain of the car class
    (request delay 30 ms, then a first-order lag of 80 ms), stepped at 10 ms.
    """
    plant = VehicleModel(vehicle).discrete(BUDGET / 2, 10)
    rng = np.random.default_rng(seed)
    x = np.zeros(9)
    x[:6] = [0.95 * eq.V, eq.beta + 0.1, 0.8 * eq.r, eq.omega_F, 0.95 * eq.omega_R,
             eq.delta + 0.05]
    pipe, torque = [eq.T_R] * (3 if actuator else 0), eq.T_R
    times, steps, preps, failures, beta = [], [], [], 0, []
    for k in range(int(round(seconds / BUDGET))):
        now = k * BUDGET
        n = rng.normal(0.0, 1.0, 5)
        state = VehicleState(stamp=now, V=x[0] + 0.05 * n[0], beta=x[1] + 0.005 * n[1],
                             r=x[2] + 0.005 * n[2],
                             wheel_speeds=(x[3] + 0.1 * n[3], x[3], x[4] + 0.1 * n[4], x[4]),
                             delta=x[5])
        ref = Reference(now, eq, Direction.LEFT)
        t0 = time.perf_counter()
        command, solved, solve_time = step(state, ref, now)
        steps.append(time.perf_counter() - t0)
        if prepare is not None:
            t0 = time.perf_counter()
            prepare()
            preps.append(time.perf_counter() - t0)
        times.append(solve_time)
        failures += not solved
        for _ in range(2):
            pipe.append(command.drive_torque)
            request = pipe.pop(0)
            torque = torque + (1.0 - math.exp(-0.01 / 0.08)) * (request - torque) if actuator \
                else request
            x = np.asarray(plant(x, [command.delta_rate, torque], [0.0, 0.95 * mu])).ravel()
        beta.append(x[1])
    t = np.array(times[1:]) * 1e3   # the first (cold) solve is reported apart
    w = np.array(steps[1:]) * 1e3
    prep = np.array(preps[1:] if preps else np.zeros(len(w))) * 1e3
    settle = min(3.0, seconds / 2)   # tracking error counted after this [s]
    err = np.degrees(np.array(beta) - eq.beta)[int(settle / BUDGET):]
    return {'steps': len(times), 'cold_ms': times[0] * 1e3,
            'step_p50_ms': float(np.percentile(w, 50)), 'step_p99_ms': float(np.percentile(w, 99)),
            'step_max_ms': float(w.max()),
            'prepare_p50_ms': float(np.percentile(prep, 50)),
            'prepare_p99_ms': float(np.percentile(prep, 99)),
            'cycle_p50_ms': float(np.percentile(w + prep, 50)),
            'cycle_p99_ms': float(np.percentile(w + prep, 99)),
            'p50_ms': float(np.percentile(t, 50)), 'p95_ms': float(np.percentile(t, 95)),
            'p99_ms': float(np.percentile(t, 99)), 'max_ms': float(t.max()),
            'p99_over_budget': float(np.percentile(w + prep, 99) / (BUDGET * 1e3)),
            'failures': int(failures), 'beta_err_rms_deg': float(np.sqrt(np.mean(err ** 2))),
            'beta_err_max_deg': float(np.max(np.abs(err)))}


def nmpc_step(ctrl: Nmpc):
    def step(state, ref, now):
        res = ctrl.step(state, ref, now)
        return res.command, res.solved, res.solve_time_s
    return step


COMPARE = [   # (label, solver overrides, model overrides)
    ('rti hpipm gcc (default)', {}, {}),
    ('rti hpipm speed gcc', {'hpipm_mode': 'speed'}, {}),
    ('rti hpipm speed_abs gcc', {'hpipm_mode': 'speed_abs'}, {}),
    ('rti hpipm interpreted', {'codegen': False}, {}),
    ('rti qrqp gcc', {'qp_solver': 'qrqp'}, {}),
    ('rti osqp gcc', {'qp_solver': 'osqp'}, {}),
    ('rti qpoases gcc', {'qp_solver': 'qpoases'}, {}),
    ('gn-sqp hpipm 3 it gcc', {'max_iter': 3}, {}),
    ('rti hpipm gcc, dynamic front wheel, 6 substeps', {}, {'front_wheel': 'dynamic',
                                                            'substeps': 6}),
    ('rti hpipm gcc, dynamic front wheel, 2 substeps', {}, {'front_wheel': 'dynamic',
                                                            'substeps': 2}),
    ('sqpmethod qrqp max_iter=1 gcc', {'method': 'sqp', 'qp_solver': 'qrqp'}, {}),
    ('sqpmethod hpipm max_iter=1 gcc', {'method': 'sqp', 'qp_solver': 'hpipm'}, {}),
    ('sqpmethod osqp max_iter=1 gcc', {'method': 'sqp', 'qp_solver': 'osqp'}, {}),
    ('sqpmethod qpoases max_iter=1 gcc', {'method': 'sqp', 'qp_solver': 'qpoases'}, {}),
    ('sqpmethod qrqp converged gcc', {'method': 'sqp', 'qp_solver': 'qrqp', 'max_iter': 30}, {}),
    ('ipopt converged gcc', {'method': 'ipopt', 'max_iter': 100}, {}),
    ('fatrop converged gcc', {'method': 'fatrop', 'max_iter': 100}, {}),
    ('fatrop converged interpreted', {'method': 'fatrop', 'max_iter': 100, 'codegen': False}, {}),
]


def compare(vehicle, base: NmpcParams, eq, seconds: float, mu: float,
            actuator: bool = False) -> list[dict]:
    rows = []
    for label, solver_kw, model_kw in COMPARE:
        params = dataclasses.replace(base, solver=dataclasses.replace(base.solver, **solver_kw),
                                     **model_kw)
        t0 = time.perf_counter()
        try:
            ctrl = Nmpc(vehicle, params, mu=mu)
        except Exception as err:   # report, keep measuring the others
            rows.append({'solver': label, 'error': f'{type(err).__name__}: {err}'[:200]})
            print(f'{label:50s} build failed: {rows[-1]["error"]}', flush=True)
            continue
        build = time.perf_counter() - t0
        row = {'solver': label, 'build_s': build,
               **closed_loop(nmpc_step(ctrl), vehicle, eq, seconds, mu, actuator=actuator,
                             prepare=ctrl.prepare)}
        rows.append(row)
        print(f'{label:50s} step p50 {row["step_p50_ms"]:6.2f} p99 {row["step_p99_ms"]:6.2f}  '
              f'cycle p50 {row["cycle_p50_ms"]:6.2f} p99 {row["cycle_p99_ms"]:6.2f}  '
              f'solve p50 {row["p50_ms"]:6.2f} p99 {row["p99_ms"]:6.2f} ms  '
              f'fail {row["failures"]:3d}  beta rms '
              f'{row["beta_err_rms_deg"]:.2f} deg  (build {build:.1f} s)', flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=10.0, help='closed-loop length [s]')
    ap.add_argument('--vehicle', help='config/vehicle/<name>.yaml (default: defaults.yaml\'s)')
    ap.add_argument('--surface', default='dry')
    ap.add_argument('--beta-deg', type=float, default=30.0)
    ap.add_argument('--radius', type=float, default=15.0)
    ap.add_argument('--no-dompc', action='store_true', help='skip the do-mpc baseline')
    ap.add_argument('--compare', action='store_true', help='also measure every solver option')
    ap.add_argument('--compare-seconds', type=float, default=4.0)
    ap.add_argument('--actuator', action='store_true',
                    help='plant with a powertrain: 30 ms request delay, 80 ms torque lag')
    ap.add_argument('--json', help='write the figures to this file')
    args = ap.parse_args(argv)

    try:
        name = vehicle_file(args.vehicle).stem
        vehicle, params = load_vehicle(name), load_nmpc_params()
        mu = load_surface(args.surface).mu
        eq, source = reference_equilibrium(name, vehicle, args.surface, args.beta_deg, args.radius)
    except ParamError as err:
        print(f'bench_nmpc: {err}', file=sys.stderr)
        return 2
    load = os.getloadavg()
    print(f'{name}: {args.beta_deg:g} deg drift on R {args.radius:g} m, {args.surface} '
          f'(mu {mu:g}, plant '
          f'{0.95 * mu:.3f}), reference {source}; {os.cpu_count()} cores, load '
          f'{load[0]:.2f} {load[1]:.2f}', flush=True)
    out = {'scenario': {'beta_deg': args.beta_deg, 'radius': args.radius, 'surface': args.surface,
                        'seconds': args.seconds, 'actuator': args.actuator, 'loadavg': load,
                        'cores': os.cpu_count()},
           'config': dataclasses.asdict(params)}
    t0 = time.perf_counter()
    ctrl = Nmpc(vehicle, params, mu=mu)
    print(f'NMPC {params.solver.method}/{params.solver.qp_solver} codegen '
          f'{params.solver.codegen}: build {time.perf_counter() - t0:.1f} s', flush=True)
    out['nmpc'] = ours = closed_loop(nmpc_step(ctrl), vehicle, eq, args.seconds, mu,
                                     actuator=args.actuator, prepare=ctrl.prepare)
    report('NMPC', ours)
    if not args.no_dompc:
        t0 = time.perf_counter()
        base = DoMpcController(vehicle, params, mu)
        print(f'do-mpc build {time.perf_counter() - t0:.1f} s', flush=True)
        out['do_mpc'] = theirs = closed_loop(base.step, vehicle, eq, args.seconds, mu,
                                             actuator=args.actuator)
        report('do-mpc', theirs)
        out['speedup_p50'] = theirs['p50_ms'] / ours['p50_ms']
        out['speedup_p99'] = theirs['p99_ms'] / ours['p99_ms']
        print(f'speed-up over do-mpc: p50 {out["speedup_p50"]:.1f}x, p99 '
              f'{out["speedup_p99"]:.1f}x')
    goals = {'step p50 <= 0.5 ms': ours['step_p50_ms'] <= 0.5,
             'step p99 <= 1 ms': ours['step_p99_ms'] <= 1.0}
    if 'speedup_p50' in out:
        goals['>= 5x do-mpc'] = out['speedup_p50'] >= 5.0
    out['goals'] = goals
    print('goals: ' + ', '.join(f'{k}: {"met" if v else "MISSED"}' for k, v in goals.items()))
    if args.compare:
        out['compare'] = compare(vehicle, params, eq, args.compare_seconds, mu, args.actuator)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2, default=str))
    return 0


def report(name: str, r: dict) -> None:
    print(f'{name}: {r["steps"]} steps; step (state in -> command out, wrapper included) p50 '
          f'{r["step_p50_ms"]:.2f} p99 {r["step_p99_ms"]:.2f} max {r["step_max_ms"]:.2f} ms; '
          f'preparation (after the command) p50 {r["prepare_p50_ms"]:.2f} p99 '
          f'{r["prepare_p99_ms"]:.2f} ms; whole cycle p50 {r["cycle_p50_ms"]:.2f} p99 '
          f'{r["cycle_p99_ms"]:.2f} ms; '
          f'solve time p50 {r["p50_ms"]:.2f} p95 {r["p95_ms"]:.2f} '
          f'p99 {r["p99_ms"]:.2f} max {r["max_ms"]:.2f} ms (cold {r["cold_ms"]:.1f} ms); '
          f'cycle p99 / 20 ms budget = {r["p99_over_budget"]:.3f}; failures {r["failures"]}; beta error '
          f'after settling rms {r["beta_err_rms_deg"]:.2f} max {r["beta_err_max_deg"]:.2f} deg',
          flush=True)


if __name__ == '__main__':
    sys.exit(main())

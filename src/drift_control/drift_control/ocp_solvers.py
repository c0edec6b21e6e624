"""Solver backends of the NMPC's OCP: Gauss-Newton RTI on a casadi QP solver, or a casadi nlpsol.

Both share one call, ``solve(w0, p, lbw, ubw, iterations) -> SolveOutput``. With ``codegen`` the
problem's functions are written as C by casadi, compiled with gcc into a shared object cached
under ``.codegen/<hash of the C source>.so`` (so a changed problem is never served stale code),
and loaded back; without gcc the interpreted functions are used.
"""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import casadi as ca
import numpy as np

from drift_control.ocp import NS, Ocp, SolverParams
from drift_control.params import config_dir
from drift_control.vehicle import NU

log = logging.getLogger(__name__)


class SolveOutput(NamedTuple):
    """What one solve returns."""

    w: np.ndarray        # decision vector after the solve
    success: bool
    status: str          # solver return status
    iterations: int
    cost: float


def compile_cached(fn_or_solver, name: str, sp: SolverParams, dependencies: bool = False):
    """Generate C for a casadi Function (or an nlpsol's dependencies), compile, return the .so path.

    Returns None when gcc is missing or the compilation fails (the caller stays interpreted).
    """
    if shutil.which('gcc') is None:
        log.warning('gcc not found: %s runs interpreted', name)
        return None
    try:
        return _compile_cached(fn_or_solver, name, sp, dependencies)
    except OSError as err:   # e.g. a read-only install: slower, not broken
        log.warning('cannot compile %s (%s): running interpreted', name, err)
        return None


def _compile_cached(fn_or_solver, name: str, sp: SolverParams, dependencies: bool):
    cache = Path(sp.codegen_dir)
    if not cache.is_absolute():
        cache = config_dir().parent / cache
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache) as tmp:
        c_file = f'{name}.c'
        cwd = os.getcwd()
        try:   # casadi writes into the working directory
            os.chdir(tmp)
            if dependencies:
                fn_or_solver.generate_dependencies(c_file)
            else:
                fn_or_solver.generate(c_file)
        finally:
            os.chdir(cwd)
        source = (Path(tmp) / c_file).read_bytes()
        key = hashlib.sha256(source + ' '.join(sp.gcc_flags).encode()
                             + ca.__version__.encode()).hexdigest()[:16]
        so = cache / f'{name}_{key}.so'
        if so.exists():
            return so
        t0 = time.perf_counter()
        tmp_so = Path(tmp) / so.name
        cmd = ['gcc', '-shared', '-fPIC', *sp.gcc_flags, '-o', str(tmp_so), str(Path(tmp) / c_file),
               '-lm']
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            log.warning('gcc failed for %s, running interpreted: %s', name, done.stderr[-500:])
            return None
        os.replace(tmp_so, so)   # atomic: a concurrent process sees all or nothing
        log.info('compiled %s in %.1f s -> %s', name, time.perf_counter() - t0, so)
        return so


class RtiSolver:
    """Gauss-Newton SQP on the least-squares cost; ``iterations = 1`` is a real-time iteration.

    Each iteration linearises the shooting gaps and the cost residuals at ``w`` and solves
    ``min 0.5 dw' H dw + g' dw  s.t.  A dw = -gap,  lbw - w <= dw <= ubw - w`` with
    ``H = 2 Jr' Jr`` (Gauss-Newton: positive semi-definite, no second derivatives of the model).
    """

    def __init__(self, ocp: Ocp, sp: SolverParams):
        self.ocp, self.sp = ocp, sp
        # the QP runs in scaled variables w = D ws (torques in kNm next to angles in rad):
        # interior-point and ADMM QP solvers need the similar magnitudes
        self.D = ocp.variable_scale()
        # cost residuals are linear in w: constant Hessian, gradient from a small SX function
        ws_sx = ca.SX.sym('ws', ocp.nw)
        r = ca.substitute(ocp.residual, ocp.w, self.D * ws_sx)
        Jr = ca.jacobian(r, ws_sx)
        self.H = ca.DM(ca.Function('H', [ws_sx, ocp.p], [2 * ca.mtimes(Jr.T, Jr)])(0, 0))
        grad_fn = ca.Function('grad', [ws_sx, ocp.p], [2 * ca.mtimes(Jr.T, r), ca.sumsqr(r)])
        # shooting gaps (scaled like the states) and their Jacobian: one mapped stage function
        ws, p = ca.MX.sym('ws', ocp.nw), ca.MX.sym('p', ocp.np)
        g = ocp.gaps(self.D * ws, p) / np.tile(ocp.state_scale(), ocp.N)
        A = ca.jacobian(g, ws)
        grad, J = grad_fn(ws, p)
        qp_data = ca.Function('nmpc_qp_data', [ws, p], [grad, A, g, J],
                              ['ws', 'p'], ['grad', 'A', 'gap', 'J'])
        self.qp_data = qp_data
        if sp.codegen:
            so = compile_cached(qp_data, 'nmpc_qp_data', sp)
            if so is not None:
                self.qp_data = ca.external('nmpc_qp_data', str(so))
        opts = dict(_QP_OPTIONS.get(sp.qp_solver, {}))
        if sp.qp_solver == 'hpipm':
            N = ocp.N
            opts.update({'N': N, 'nx': [NS] * (N + 1), 'nu': [NU] * N + [0], 'ng': [0] * (N + 1)})
        opts['error_on_fail'] = False
        self.qp = ca.conic('nmpc_qp', sp.qp_solver, {'h': self.H.sparsity(), 'a': A.sparsity()},
                           opts)

    def solve(self, w0, p, lbw, ubw, iterations: int) -> SolveOutput:
        ws = np.asarray(w0, dtype=float) / self.D
        lbs, ubs = lbw / self.D, ubw / self.D
        status, ok, it, cost = 'not run', False, 0, float('nan')
        for it in range(1, iterations + 1):
            grad, A, gap, J = self.qp_data(ws, p)
            gap = np.asarray(gap).ravel()
            sol = self.qp(h=self.H, g=grad, a=A, lba=-gap, uba=-gap, lbx=lbs - ws, ubx=ubs - ws)
            stats = self.qp.stats()
            ok = bool(stats.get('success', False))
            status = str(stats.get('return_status', ''))
            dws = np.asarray(sol['x']).ravel()
            if not ok or not np.all(np.isfinite(dws)):
                return SolveOutput(ws * self.D, False, status or 'qp failed', it, float('nan'))
            ws = ws + dws
            # the cost is quadratic in w, so the QP's model cost is the exact new cost
            cost = float(J) + float(sol['cost'])
            if np.max(np.abs(dws)) < self.sp.tol:
                break
        return SolveOutput(ws * self.D, ok, status or 'ok', it, cost)


# Options measured to be reliable on this problem (see scripts/bench_nmpc.py --compare).
_QP_OPTIONS = {
    'qrqp': {'print_iter': False, 'print_header': False, 'max_iter': 200},
    'osqp': {'osqp': {'verbose': False, 'eps_abs': 1e-6, 'eps_rel': 1e-6, 'max_iter': 4000,
                      'polish': True}, 'warm_start_primal': True},
    # HPIPM's default tolerances (1e-8) are not reached with x_0 fixed by equal bounds (it then
    # stops at iter_max with the right solution); 1e-6 in scaled variables takes ~9 iterations
    'hpipm': {'hpipm': {'mode': 'balance', 'iter_max': 50, 'res_g_max': 1e-6, 'res_b_max': 1e-6,
                        'res_d_max': 1e-6, 'res_m_max': 1e-6}},
    'qpoases': {'printLevel': 'none', 'sparse': True},
}


class NlpSolver:
    """A casadi nlpsol (sqpmethod with a QP solver, ipopt or fatrop) on the same, scaled NLP.

    The NLP is MX with one mapped stage function, so generated code stays small. ``max_iter``
    applies to warm-started steps, ``cold_start_iter`` to the first one (two solver instances on
    the same compiled functions).
    """

    def __init__(self, ocp: Ocp, sp: SolverParams):
        self.ocp, self.sp = ocp, sp
        self.D = ocp.variable_scale()
        ws_sx = ca.SX.sym('ws', ocp.nw)
        J_fn = ca.Function('J', [ws_sx, ocp.p],
                           [ca.sumsqr(ca.substitute(ocp.residual, ocp.w, self.D * ws_sx))])
        ws, p = ca.MX.sym('ws', ocp.nw), ca.MX.sym('p', ocp.np)
        g = ocp.gaps(self.D * ws, p) / np.tile(ocp.state_scale(), ocp.N)
        plugin = self._plugin(sp)
        if plugin == 'fatrop':   # fatrop's gap form is x_{k+1} - F(x_k, u_k), HPIPM's the negative
            g = -g
        nlp = {'x': ws, 'p': p, 'f': J_fn(ws, p), 'g': g}
        self.ng = g.shape[0]
        source = nlp
        if sp.codegen:
            so = compile_cached(ca.nlpsol('nmpc_nlp', plugin, nlp, self._options(sp, 5)),
                                f'nmpc_nlp_{plugin}', sp, dependencies=True)
            source = str(so) if so is not None else nlp
        self.warm = ca.nlpsol('nmpc_nlp', plugin, source, self._options(sp, sp.max_iter))
        self.cold = (self.warm if sp.cold_start_iter == sp.max_iter else
                     ca.nlpsol('nmpc_nlp', plugin, source, self._options(sp, sp.cold_start_iter)))

    @staticmethod
    def _plugin(sp: SolverParams) -> str:
        return {'sqp': 'sqpmethod', 'ipopt': 'ipopt', 'fatrop': 'fatrop'}[sp.method]

    def _options(self, sp: SolverParams, max_iter: int) -> dict:
        common = {'print_time': False, 'error_on_fail': False}
        N = self.ocp.N
        structure = {'N': N, 'nx': [NS] * (N + 1), 'nu': [NU] * N + [0], 'ng': [0] * (N + 1)}
        if sp.method == 'sqp':
            qp_opts = dict(_QP_OPTIONS.get(sp.qp_solver, {}))
            if sp.qp_solver == 'hpipm':
                qp_opts.update(structure)
            qp_opts['error_on_fail'] = False
            return {**common, 'qpsol': sp.qp_solver, 'qpsol_options': qp_opts,
                    'max_iter': max_iter, 'tol_pr': sp.tol, 'tol_du': sp.tol,
                    'print_header': False, 'print_iteration': False, 'print_status': False}
            # no convexification: 'regularize' stalls (50 iterations, 2 % above the optimum),
            # the exact Hessian converges in ~6 iterations from a cold start
        if sp.method == 'ipopt':
            return {**common, 'ipopt': {'print_level': 0, 'tol': sp.tol, 'max_iter': max_iter,
                                        'sb': 'yes', 'warm_start_init_point': 'yes'}}
        if sp.method == 'fatrop':
            return {**common, 'structure_detection': 'manual', **structure,
                    'fatrop': {'print_level': 0, 'max_iter': max_iter, 'tol': sp.tol}}
        raise ValueError(f'unknown NLP method {sp.method!r}')

    def solve(self, w0, p, lbw, ubw, iterations: int) -> SolveOutput:
        solver = self.cold if iterations > self.sp.max_iter else self.warm
        zeros = np.zeros(self.ng)
        sol = solver(x0=np.asarray(w0) / self.D, p=p, lbx=lbw / self.D, ubx=ubw / self.D,
                     lbg=zeros, ubg=zeros)
        stats = solver.stats()
        status = str(stats.get('return_status', ''))
        it = int(stats.get('iter_count', 0))
        ok = bool(stats.get('success', False))
        if status.lower() == 'maximum_iterations_exceeded' and iterations <= 2:
            ok = True   # real-time use of sqpmethod: the iteration budget is the design
        w = np.asarray(sol['x']).ravel() * self.D
        return SolveOutput(w, ok and bool(np.all(np.isfinite(w))), status, it, float(sol['f']))


def make_solver(ocp: Ocp, sp: SolverParams):
    """The backend named by ``sp.method``."""
    if sp.method == 'rti':
        return RtiSolver(ocp, sp)
    return NlpSolver(ocp, sp)

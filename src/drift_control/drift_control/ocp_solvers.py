"""Solver backends of the NMPC's OCP: Gauss-Newton RTI on a casadi QP solver, or a casadi nlpsol.

Both share one call, ``solve(w0, p, lbw, ubw, iterations) -> SolveOutput``. With ``codegen`` the
problem's functions are written as C by casadi, compiled with gcc into a shared object cached
under ``.codegen/<hash of the C source>.so`` (so a changed problem is never served stale code),
and loaded back; without gcc the interpreted functions are used.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import NamedTuple

import casadi as ca
import numpy as np

from drift_control.compiled import HPIPM_FLAGS, CompiledFunction, build_cached
from drift_control.ocp import NREF, Ocp, SolverParams
from drift_control.params import cache_dir
from drift_control.vehicle import NU

log = logging.getLogger(__name__)


class SolveOutput(NamedTuple):
    """What one solve returns."""

    w: np.ndarray        # decision vector after the solve
    success: bool
    status: str          # solver return status
    iterations: int
    cost: float


def compile_cached(fn_or_solver, name: str, sp: SolverParams, dependencies: bool = False,
                   link=()):
    """Generate C for a casadi Function (or an nlpsol's dependencies), compile, return the .so path.

    Cached under ``sp.codegen_dir`` (relative to ``cache_dir()``); None when gcc is missing or the
    compilation fails (the caller stays interpreted).
    """
    cache = Path(sp.codegen_dir)
    if not cache.is_absolute():
        cache = cache_dir() / cache   # the checkout, else a user cache: never the install space
    return build_cached(fn_or_solver, name, cache, sp.gcc_flags, link, dependencies)


class RtiSolver:
    """Gauss-Newton SQP on the least-squares cost; ``iterations = 1`` is a real-time iteration.

    Each iteration linearises the shooting gaps and the cost residuals at ``w`` and solves
    ``min 0.5 dw' H dw + g' dw  s.t.  A dw = -gap,  lbw - w <= dw <= ubw - w`` with
    ``H = 2 Jr' Jr`` (Gauss-Newton: positive semi-definite, no second derivatives of the model).

    With ``codegen`` and a QP solver casadi generates C for (HPIPM, qrqp), one iteration
    (linearisation, QP, step) is two compiled calls (``iteration``): the part that needs no
    measurement can run ahead (``prepare``, the real-time iteration's preparation phase), so a
    state waits only for the feedback part. A failed QP is solved again by the interpreted QP
    solver on the same data, which reports its status.
    """

    def __init__(self, ocp: Ocp, sp: SolverParams):
        self.ocp, self.sp = ocp, sp
        # the QP runs in scaled variables w = D ws (torques in kNm next to angles in rad):
        # interior-point and ADMM QP solvers need the similar magnitudes
        self.D = ocp.variable_scale()
        # cost residuals are linear in w: the Hessian depends on p at most (a flip's weight,
        # ``cost.omega_R_flip``, a slowing drift's ``cost.V_slow``), else it is a constant;
        # gradient from a small SX function
        ws_sx = ca.SX.sym('ws', ocp.nw)
        r = ca.substitute(ocp.residual, ocp.w, self.D * ws_sx)
        Jr = ca.jacobian(r, ws_sx)
        self.H_fn = ca.Function('H', [ocp.p], [2 * ca.mtimes(Jr.T, Jr)])
        self.H = None if ca.depends_on(Jr, ocp.p) else ca.DM(self.H_fn(0))
        grad_fn = ca.Function('grad', [ws_sx, ocp.p], [2 * ca.mtimes(Jr.T, r), ca.sumsqr(r)])
        # shooting gaps (scaled like the states) and their Jacobian: one mapped stage function
        ws, p = ca.MX.sym('ws', ocp.nw), ca.MX.sym('p', ocp.np)
        g = ocp.gaps(self.D * ws, p) / np.tile(ocp.state_scale(), ocp.N)
        A = ca.jacobian(g, ws)
        grad, J = grad_fn(ws, p)
        qp_data = ca.Function('nmpc_qp_data', [ws, p], [grad, A, g, J],
                              ['ws', 'p'], ['grad', 'A', 'gap', 'J'])
        self.qp_data = qp_data
        self.qp = self._conic(A.sparsity())
        self.iteration = None
        # what ``prepare`` linearised: the guess's stages 1 .. N-1, mu and the powertrain lag
        self._linearised = slice(ocp.ns + NU, ocp.N * (ocp.ns + NU))
        self._mu_index, self._lag_index = (ocp.N + 1) * NREF, ocp.np - 1
        self._prepared: tuple[np.ndarray, float, float] | None = None
        if sp.codegen and sp.qp_solver in _CODEGEN_QP:
            self.iteration = self._compiled_iteration(grad_fn)
        if sp.codegen and self.iteration is None:
            so = compile_cached(qp_data, 'nmpc_qp_data', sp)
            if so is not None:
                self.qp_data = ca.external('nmpc_qp_data', str(so))

    def _conic(self, a_sparsity: ca.Sparsity) -> ca.Function:
        sp, N = self.sp, self.ocp.N
        opts = qp_options(sp)
        if sp.qp_solver == 'hpipm':
            opts.update({'N': N, 'nx': [self.ocp.ns] * (N + 1), 'nu': [NU] * N + [0],
                         'ng': [0] * (N + 1)})
        opts['error_on_fail'] = False
        return ca.conic('nmpc_qp', sp.qp_solver, {'h': self.H_fn.sparsity_out(0), 'a': a_sparsity},
                        opts)

    def _hessian(self, p):
        """The QP's Hessian for the parameters ``p`` (numeric or MX)."""
        return self.H if self.H is not None else self.H_fn(p)

    def _compiled_iteration(self, grad_fn) -> tuple[CompiledFunction, CompiledFunction] | None:
        """One iteration as two compiled calls in scaled variables: ``prepare``, the model's
        stages 1 .. N-1 linearised at ``(ws, mu)`` (no measurement needed), then ``feedback``,
        ``(ws, p, lbs, ubs, prepared) -> (QP data, J, dws, qp_cost, ...)``: stage 0 at the
        measured state, the gaps with the model error, the cost gradient, the QP and its step.

        The gap Jacobian comes from one SX function per stage (value and forward derivatives
        share their subexpressions: ~40 % less work than differentiating the mapped MX gaps,
        equal to rounding), mapped over the stages.
        """
        ocp, N, ns = self.ocp, self.ocp.N, self.ocp.ns
        nz = ns + NU
        S = ocp.state_scale()
        x, u, mu, lag = ca.SX.sym('x', ns), ca.SX.sym('u', NU), ca.SX.sym('mu'), ca.SX.sym('lag')
        xu = ca.vertcat(x, u)
        x_next = ocp.F(x, u, mu, lag)
        # seeds D e_j as the chain rule through w = D ws gives them; rows scaled like the gaps
        jac = ca.jtimes(x_next, xu, ca.DM(np.diag(self.D[:nz]))) / S
        jac = ca.project(jac, ca.jacobian(x_next, xu).sparsity())
        stage = ca.Function('nmpc_stage', [x, u, mu, lag], [x_next, jac])

        ws, p = ca.MX.sym('ws', ocp.nw), ca.MX.sym('p', ocp.np)
        lbs, ubs = ca.MX.sym('lbs', ocp.nw), ca.MX.sym('ubs', ocp.nw)
        mu_s, lag_s = ca.MX.sym('mu'), ca.MX.sym('lag')
        w = self.D * ws
        body = ca.reshape(w[:N * nz], nz, N)
        rest = stage.map(N - 1)(body[:ns, 1:], body[ns:, 1:], mu_s, lag_s)
        prepare = ca.Function('nmpc_rti_prepare', [ws, mu_s, lag_s], list(rest))
        X_rest = ca.MX.sym('X_rest', rest[0].sparsity())
        jac_rest = ca.MX.sym('jac_rest', rest[1].sparsity())

        par = ocp.unpack_params(p)
        X_0, jac_0 = stage(body[:ns, 0], body[ns:, 0], par.mu, par.lag)
        X_next, jacs = ca.horzcat(X_0, X_rest), ca.horzcat(jac_0, jac_rest)
        # the gaps exactly as Ocp.gaps computes them
        X_next = X_next + ocp.offsets(p)
        X_after = ca.horzcat(body[:ns, 1:], w[N * nz:])
        gap = ca.vec(X_next - X_after) / np.tile(S, N)
        minus_eye = -ca.DM.eye(ns)   # d gap_k / d x_{k+1}: -D/S = -1 (D is S for states)
        A = ca.vertcat(*[ca.horzcat(ca.MX(ns, k * nz), jacs[:, k * nz:(k + 1) * nz], minus_eye,
                                    ca.MX(ns, ocp.nw - (k + 1) * nz - ns)) for k in range(N)])
        grad, J = grad_fn(ws, p)
        self._qp_same = self._conic(A.sparsity())   # the QP as compiled, for a failure's status
        # the generated HPIPM reads its initial guesses: zeros, as the interpreted call passes
        zeros = ca.DM.zeros(ocp.nw), ca.DM.zeros(A.shape[0])
        sol = self._qp_same(h=self._hessian(p), g=grad, a=A, lba=-gap, uba=-gap, lbx=lbs - ws,
                            ubx=ubs - ws, x0=zeros[0], lam_x0=zeros[0], lam_a0=zeros[1])
        # outputs in the order the generated code writes them: the QP data (computed before
        # the QP) stay readable when the QP fails; every multiplier is written, so requested
        feedback = ca.Function('nmpc_rti_feedback', [ws, p, lbs, ubs, X_rest, jac_rest],
                               [ca.densify(grad), A.nz[:], gap, J, sol['x'], sol['cost'],
                                sol['lam_x'], sol['lam_a']])
        so_prepare = compile_cached(prepare, 'nmpc_rti_prepare', self.sp)
        so_feedback = compile_cached(feedback, 'nmpc_rti_feedback', self.sp,
                                     link=HPIPM_FLAGS if self.sp.qp_solver == 'hpipm' else ())
        if so_prepare is None or so_feedback is None:
            return None
        return CompiledFunction(so_prepare, prepare), CompiledFunction(so_feedback, feedback)

    def prepare(self, w, mu: float, lag: float) -> None:
        """Linearise the model's stages 1 .. N-1 at the guess ``w`` now, before the state
        arrives: a ``solve`` from the same guess (whatever its stage 0), ``mu`` and powertrain
        ``lag`` then only does the feedback part. The result is the same bit for bit; without
        codegen this does nothing."""
        if self.iteration is None:
            return
        prep = self.iteration[0]
        self._prepared = None   # until this preparation is complete
        prep.inputs[0][:] = np.asarray(w, dtype=float) / self.D
        prep.inputs[1][0], prep.inputs[2][0] = mu, lag
        prep()
        self._prepared = prep.inputs[0][self._linearised].copy(), float(mu), float(lag)

    def _iterate(self, ws, p, lbs, ubs):
        """One iteration: (dws, J, QP cost, QP status); dws is None when the QP failed."""
        qp = self.qp
        if self.iteration is None:
            grad, A, gap, J = self.qp_data(ws, p)
            gap = np.asarray(gap).ravel()
        else:
            prep, fb = self.iteration
            mu, lag = float(p[self._mu_index]), float(p[self._lag_index])
            done = self._prepared
            if done is None or done[1:] != (mu, lag) \
                    or not np.array_equal(done[0], ws[self._linearised]):
                prep.inputs[0][:], prep.inputs[1][0], prep.inputs[2][0] = ws, mu, lag
                prep()
            self._prepared = None   # the step moves ws: an iteration after this one prepares anew
            fb.inputs[0][:], fb.inputs[1][:], fb.inputs[2][:], fb.inputs[3][:] = ws, p, lbs, ubs
            fb.inputs[4][:], fb.inputs[5][:] = prep.outputs
            if fb():
                dws, cost = fb.outputs[4:6]
                return dws.copy(), fb.outputs[3][0], cost[0], _CODEGEN_QP[self.sp.qp_solver]
            # a failed QP: solved again interpreted on the same data, which names the status
            grad, a_nz, gap, J = (out.copy() for out in fb.outputs[:4])
            qp = self._qp_same
            A = ca.DM(qp.sparsity_in('a'), a_nz)
            J = J[0]
        sol = qp(h=self._hessian(p), g=grad, a=A, lba=-gap, uba=-gap, lbx=lbs - ws, ubx=ubs - ws)
        stats = qp.stats()
        status = str(stats.get('return_status', ''))
        if not stats.get('success', False):
            return None, None, None, status
        return np.asarray(sol['x']).ravel(), float(J), float(sol['cost']), status

    def solve(self, w0, p, lbw, ubw, iterations: int) -> SolveOutput:
        ws = np.asarray(w0, dtype=float) / self.D
        lbs, ubs = lbw / self.D, ubw / self.D
        status, it, cost = 'not run', 0, float('nan')
        for it in range(1, iterations + 1):
            dws, J, qp_cost, status = self._iterate(ws, p, lbs, ubs)
            if dws is None or not np.all(np.isfinite(dws)):
                return SolveOutput(ws * self.D, False, status or 'qp failed', it, float('nan'))
            ws = ws + dws
            # the cost is quadratic in w, so the QP's model cost is the exact new cost
            cost = float(J) + float(qp_cost)
            if np.max(np.abs(dws)) < self.sp.tol:
                break
        return SolveOutput(ws * self.D, True, status or 'ok', it, cost)


# QP solvers casadi generates C for, with the status their interpreted form reports on success
_CODEGEN_QP = {'hpipm': '0', 'qrqp': 'success'}


# Options measured to be reliable on this problem (see scripts/bench_nmpc.py --compare).
_QP_OPTIONS = {
    'qrqp': {'print_iter': False, 'print_header': False, 'max_iter': 200},
    'osqp': {'osqp': {'verbose': False, 'eps_abs': 1e-6, 'eps_rel': 1e-6, 'max_iter': 4000,
                      'polish': True}, 'warm_start_primal': True},
    # HPIPM's default tolerances (1e-8) are not reached with x_0 fixed by equal bounds (it then
    # stops at iter_max with the right solution); 1e-6 in scaled variables takes ~3-4 iterations
    'hpipm': {'hpipm': {'iter_max': 50, 'res_g_max': 1e-6, 'res_b_max': 1e-6,
                        'res_d_max': 1e-6, 'res_m_max': 1e-6}},
    'qpoases': {'printLevel': 'none', 'sparse': True},
}


def qp_options(sp: SolverParams) -> dict:
    """The casadi conic options of ``sp.qp_solver`` (HPIPM in ``sp.hpipm_mode``)."""
    opts = dict(_QP_OPTIONS.get(sp.qp_solver, {}))
    if sp.qp_solver == 'hpipm':
        opts['hpipm'] = dict(opts['hpipm'], mode=sp.hpipm_mode)
    return opts


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
        structure = {'N': N, 'nx': [self.ocp.ns] * (N + 1), 'nu': [NU] * N + [0],
                     'ng': [0] * (N + 1)}
        if sp.method == 'sqp':
            qp_opts = qp_options(sp)
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

    def prepare(self, w, mu: float, lag: float) -> None:
        """Nothing to do ahead of the measurement: an NLP solve starts from its guess."""

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


def period_function(ocp: Ocp, sp: SolverParams):
    """``ocp.F_period`` as ``(x, u, mu, lag) -> numpy array``, compiled with ``sp.codegen``.

    The one-period prediction the model-error estimate compares the next state against.
    """
    so = compile_cached(ocp.F_period, 'nmpc_period', sp) if sp.codegen else None
    if so is None:
        return lambda x, u, mu, lag: np.asarray(ocp.F_period(x, u, mu, lag)).ravel()
    f = CompiledFunction(so, ocp.F_period)

    def period(x, u, mu, lag):
        f.inputs[0][:], f.inputs[1][:], f.inputs[2][0], f.inputs[3][0] = x, u, mu, lag
        f()
        return f.outputs[0].copy()
    return period


def make_solver(ocp: Ocp, sp: SolverParams):
    """The backend named by ``sp.method``."""
    if sp.method == 'rti':
        return RtiSolver(ocp, sp)
    return NlpSolver(ocp, sp)

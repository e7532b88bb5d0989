"""The IPOPT driver: one NLP per problem structure, built once from the numpy assembly
(:mod:`castimate.solver.assembly`) and solved for any data or fixed values."""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import platform
import sys
import time
import weakref

import casadi as ca
import numpy as np
import scipy.sparse as sp
from ..problem.graph import LeastSquaresProblem, Solution, SolverOptions, solver_threads
from . import uncertainty
from .assembly import Assembly, Block, Callback, EvaluationError, Stages
from .elimination import Projection



class Solver:
    """IPOPT on a :class:`LeastSquaresProblem`, built once and solved for any data or fixed values.

    Public methods take and return x in the layout's order; inside the NLP the variables may be
    ordered by stage (:class:`Stages`)."""

    def __init__(self, problem: LeastSquaresProblem, options: SolverOptions = SolverOptions()):
        t0 = time.perf_counter()
        self.problem, self.options = problem, options
        self.marginal_memo = None  # (point, S, G) of the last marginal information (uncertainty.py)
        lay = problem.layout
        self.n_x = n = lay.n_x
        self.blocks = [Block(b, lay) for b in problem.blocks if b.n]
        if options.elimination not in ("motion", "none"):
            raise ValueError(f"unknown elimination {options.elimination!r}")
        threads = solver_threads(options.threads)
        # the nuisance rows eliminated by variable projection (compiles the blocks), or None
        self.projection, self.elimination_note = Projection.build(self.blocks, lay, options.hessian, options.jit) \
            if options.elimination == "motion" else (None, "full NLP (elimination: none)")
        P = self.projection
        if P is not None:
            P.threads = threads
        self.stages, self.staged = st, staged = Stages.find(lay, self.blocks) if P is None else (None, {})
        cache: dict = {}
        off = 0
        for i, b in enumerate(self.blocks):
            if P is None:
                b.compile(cache, staged[i].n_cal if i in staged else b.w_idx.shape[1], options.hessian, options.jit)
            b.data_offset = off  # into the data vector
            b.data = np.ascontiguousarray(b.block.data, float)  # the default data, not copied
            off += b.block.n * b.f.nd
        self.perm = st.perm if st else np.arange(n)  # NLP order -> layout index
        keep = [np.ones(b.block.n * b.f.m, bool) if b.block.valid is None else
                np.broadcast_to(np.asarray(b.block.valid, bool).reshape(b.block.n, -1), (b.block.n, b.f.m)).ravel()
                for b in self.blocks]
        self.prior = pi, _, _ = lay.priors()
        # residuals of instances that are not valid (masked data) are exactly zero and not reported
        self.keep = np.concatenate(keep + [np.ones(len(pi), bool)])
        self.n_data_residuals = int(self.keep.sum()) - len(pi)
        self.n_residuals = int(self.keep.sum())
        self._jacobian_plan = None  # :meth:`jacobians`' CSR structure, made at its first call

        # constraints |row|^2 = 1, rows grouped by width for vectorisation; with the projection
        # only the rows on calibration variables (the families' own are kept inside it)
        self.unit_rows = U = lay.unit_norm_rows()
        self.n_constraints = U.shape[0]
        p = ca.MX.sym("p", lay.n_p)  # the fixed values; the data stay in numpy (Assembly.data)
        if P is None:
            x = ca.MX.sym("x", n)  # in NLP order
            w = ca.vertcat((x[np.argsort(self.perm).tolist()] if st else x) * lay.x_scale, p)
            w_pos, rows = np.arange(n + lay.n_p), np.arange(len(U))
        else:
            x = ca.MX.sym("theta", P.c)
            w = ca.vertcat(x * lay.x_scale[P.cal], p)
            w_pos = np.concatenate([P.tpos, P.c + np.arange(lay.n_p)])  # w index -> position in this w
            rows = np.array([j for j, r in enumerate(U) if (P.tpos[r[(r >= 0) & (r < n)]] >= 0).all()], int)
        c_parts, self.unit_order = [], []
        for width in sorted({int((U[j] >= 0).sum()) for j in rows}):
            sel = rows[(U[rows] >= 0).sum(axis=1) == width]
            idx = w_pos[U[sel][:, :width]]
            c_parts.append(ca.sum1(ca.reshape(w[idx.ravel().tolist()], width, len(sel)) ** 2).T - 1)
            self.unit_order.append(sel)
        c = ca.vertcat(*c_parts) if c_parts else ca.MX(0, 1)
        self.constraint_order = np.concatenate(self.unit_order) if self.unit_order else np.zeros(0, int)
        if P is not None:
            self.assembly = P  # residuals and local functions, in layout order
            self.nlp = self._projected_nlp(x, p, c)
            self.theta = self._reported()
            self.build_s = time.perf_counter() - t0
            return

        # objective, gradient and Hessian of the Lagrangian: numpy assembly of the local functions
        A = self.assembly = Assembly(self.blocks, lay, st, staged, self.perm, U[self.constraint_order], self.n_constraints)

        def objective(a, o):
            o[0][0] = A.objective(a[0], a[1], A.data)

        def gradient(a, o):
            f, g, _ = A.derivatives(a[0], a[1], A.data)
            o[0][0], o[1][:] = f, g

        def hessian(a, o):
            _, _, H = A.derivatives(a[0], a[1], A.data)
            A.hessian_values(H, a[2][0], out=o[0])
            o[0][: A.n_cal_nz] += A.C_h @ a[3]

        self.nlp = self._nlpsol(x, p, c, objective, gradient, hessian, A.sparsity)
        self.theta = self._reported()
        self.build_s = time.perf_counter() - t0

    def _reported(self) -> np.ndarray:
        """The reported parameters (layout x indices): their covariance is computed."""
        lay = self.problem.layout
        nuisance = np.zeros(self.n_x, bool)
        for g in lay.groups:
            if g.nuisance:
                nuisance[lay.x_indices(g.name)] = True
        return np.flatnonzero(~nuisance)

    def _projected_nlp(self, x, p, c):
        """IPOPT over the calibration variables θ: the reduced objective, its gradient and the
        dense upper triangle of its exact Hessian plus the constraints' curvature
        (:class:`castimate.solver.elimination.Projection`)."""
        P, lay = self.projection, self.problem.layout
        H_sp = ca.Sparsity.upper(P.c)
        hr, hc = (np.asarray(v, int) for v in H_sp.get_triplet())
        diag_nz = np.full(P.c, -1)
        diag_nz[hr[hr == hc]] = np.flatnonzero(hr == hc)
        # d^2/dθ^2 of |θ s|^2 - 1 = 2 s^2 on the diagonal, per constraint (in CasADi's order)
        rows, cols, vals = [], [], []
        for j, row in enumerate(self.unit_rows[self.constraint_order]):
            f = P.tpos[row[(row >= 0) & (row < self.n_x)]]
            rows.append(diag_nz[f]), cols.append(np.full(len(f), j)), vals.append(2 * lay.x_scale[P.cal][f] ** 2)
        cat = lambda a, t: np.concatenate(a).astype(t) if a else np.zeros(0, t)  # noqa: E731
        C_h = sp.csr_matrix((cat(vals, float), (cat(rows, int), cat(cols, int))), shape=(len(hr), c.numel()))

        def objective(a, o):
            o[0][0] = P.reduced(a[0], a[1], P.data, hessian=False)[0]

        def gradient(a, o):
            f, g, _ = P.reduced(a[0], a[1], P.data, hessian=False)
            o[0][0], o[1][:] = f, g

        def hessian(a, o):
            S = P.hessian(a[0], a[1], P.data)
            o[0][:] = S[hr, hc] * a[2][0] + C_h @ a[3]

        return self._nlpsol(x, p, c, objective, gradient, hessian, H_sp)

    def _nlpsol(self, x, p, c, objective, gradient, hessian, H_sp):
        """nlpsol with the numpy callbacks for the objective, its gradient and the Hessian of the
        Lagrangian (sparsity H_sp); CasADi never differentiates the objective itself."""
        dense = ca.Sparsity.dense
        n, n_c = x.numel(), c.numel()
        io = [dense(n), dense(p.numel())]
        grad_cb = Callback("gradient", io, [dense(1), dense(n)], gradient)
        self.callbacks = cbs = [Callback("objective", io, [dense(1)], objective, grad_cb), grad_cb,
                                Callback("hessian", io + [dense(1), dense(n_c)], [H_sp], hessian)]
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_c)
        grad_f = ca.Function("nlp_grad_f", [x, p], cbs[1](x, p), ["x", "p"], ["f", "grad"])
        hess_lag = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [cbs[2](x, p, lam_f, lam_g)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        jac_g = ca.Function("nlp_jac_g", [x, p], [c, ca.jacobian(c, x)], ["x", "p"], ["g", "jac_g_x"])
        nlp = {"x": x, "p": p, "f": cbs[0](x, p), "g": c}
        # the solver held weakly: a bound method would close a cycle (solver -> stall -> solver) that
        # only the cyclic garbage collector frees, which runs seldom among CasADi's many long-lived
        # objects: every solver built and dropped kept its compiled maps and elimination state until
        # then (diagnose of MIMU4444 exp_1: its score tests' and cross-validation folds' solvers, 3.4 GB
        # freed by one pass)
        solver = weakref.ref(self)
        self.stall = Stall(n, n_c, p.numel(), lambda x, lam_g: solver()._idle_decrement(x, lam_g))
        return ca.nlpsol("castimate", "ipopt", nlp, {**self.options.ipopt(), "hess_lag": hess_lag,
                                                     "grad_f": grad_f, "jac_g": jac_g,
                                                     "iteration_callback": self.stall})

    # -- numeric ---------------------------------------------------------------------------------
    def fixed_and_data(self, p_fixed, data) -> tuple[np.ndarray, np.ndarray | None]:
        """The fixed values and the data vector (defaults: the layout's values and, as None, the
        factor blocks' own data)."""
        p_fixed = self.problem.layout.p0() if p_fixed is None else p_fixed
        return np.asarray(p_fixed, float), None if data is None else np.asarray(data, float).ravel()

    def nlp_order(self, x) -> np.ndarray:
        """Layout order -> NLP order."""
        return np.asarray(x, float)[self.perm]

    def residuals(self, x, p_fixed=None, data=None) -> np.ndarray:
        """All whitened residuals (data of the valid instances, then priors) at scaled x."""
        r = self.assembly.residuals(self.nlp_order(x), *self.fixed_and_data(p_fixed, data))
        return r if self.n_residuals == len(self.keep) else r[self.keep]  # no copy when every residual counts

    def jacobians(self, x, p_fixed=None, data=None) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Sparse Jacobians w.r.t. scaled x of the whitened residuals (data, then priors) and of the
        constraints (in the order of ``Layout.unit_norm_rows``)."""
        pf, data = self.fixed_and_data(p_fixed, data)
        local = self.assembly.local(self.nlp_order(x), pf, data, "jac")
        if self._jacobian_plan is None:
            self._jacobian_plan = self._plan_jacobian([J.size for J in local])
        take, factor, indices, indptr, dest = self._jacobian_plan
        vals = np.concatenate([J.ravel() for J in local] + [np.ones(1)])[take] * factor
        if dest is not None:
            vals = np.bincount(dest, weights=vals, minlength=indices.size)
        J = sp.csr_matrix((vals, indices, indptr), shape=(self.n_residuals, self.n_x))
        J.has_sorted_indices = J.has_canonical_format = True
        return J, self.constraint_jacobian(x, pf)

    def _plan_jacobian(self, sizes: list[int]):
        """Where the entries of :meth:`jacobians`' CSR come from, the same at every point: the
        positions in the blocks' local Jacobians (raveled, concatenated, then a 1 for the priors'
        constant entries), the factors (x_scale, 1/σ of a prior), the CSR's indices and indptr, in
        canonical order, and None, or where a block reads one x twice, the CSR position each entry is
        summed onto (:meth:`_plan_jacobian_summed`).

        Without repeated reads the canonical order comes block by block: an instance's rows share
        its columns, so sorting each instance's columns once orders all its rows (a sort of A
        columns per instance instead of a COO -> CSR pass over every entry; 0.4 -> 0.1 s CPU on
        the exp_1 joint problem's 9 million entries)."""
        n, scale = self.n_x, self.problem.layout.x_scale
        takes, indices, counts = [], [], []
        row0 = off = 0
        for b, size in zip(self.blocks, sizes):
            N, f = b.block.n, b.f
            A, m = len(f.act), f.m
            W = b.w_idx[:, f.act]
            order = np.argsort(np.where(W < n, W, n), axis=1, kind="stable")  # free columns ascending, fixed last
            cols = np.take_along_axis(W, order, axis=1)
            free = cols < n
            if (free[:, 1:] & (cols[:, 1:] == cols[:, :-1])).any():  # a block reads one x twice
                return self._plan_jacobian_summed(sizes)
            keep = self.keep[row0: row0 + N * m].reshape(N, m)
            on = free[:, None, :] & keep[:, :, None]  # (instance, row, sorted column)
            local = off + (np.arange(N)[:, None] * A + order) * m  # (N, A): entry of row i is local + i
            takes.append((local[:, None, :] + np.arange(m)[None, :, None])[on])
            indices.append(np.broadcast_to(cols[:, None, :], on.shape)[on])
            counts.append((free.sum(axis=1)[:, None] * keep)[keep])
            row0 += N * m
            off += size
        pi, _, ps = self.prior
        take = np.concatenate(takes + [np.full(len(pi), off)])
        index = np.concatenate(indices + [pi])
        dtype = np.int32 if max(take.size, n) < 2**31 else np.int64  # scipy's choice for the CSR
        indptr = np.zeros(self.n_residuals + 1, dtype)
        np.cumsum(np.concatenate(counts + [np.ones(len(pi), int)]), out=indptr[1:])
        factor = scale[index]
        factor[take.size - len(pi):] /= ps
        return take, factor, index.astype(dtype), indptr, None

    def _plan_jacobian_summed(self, sizes: list[int]):
        """:meth:`_plan_jacobian` through a COO -> CSR pass over every entry, summing repeated reads."""
        n, scale = self.n_x, self.problem.layout.x_scale
        rows, cols, take, factor = [], [], [], []
        row0 = off = 0
        for b, size in zip(self.blocks, sizes):
            N, f = b.block.n, b.f
            t, a = np.nonzero(b.w_idx[:, f.act] < n)  # a indexes the active components
            gi = b.w_idx[t, f.act[a]]
            for i in range(f.m):
                rows.append(row0 + t * f.m + i)
                cols.append(gi)
                take.append(off + (t * len(f.act) + a) * f.m + i)
                factor.append(scale[gi])
            row0 += N * f.m
            off += size
        pi, _, ps = self.prior
        rows.append(row0 + np.arange(len(pi))), cols.append(pi)
        take.append(np.full(len(pi), off)), factor.append(scale[pi] / ps)
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        new_row = np.cumsum(self.keep) - 1  # the reported rows (valid instances, priors)
        on = np.flatnonzero(self.keep[rows])
        # scipy's COO -> CSR (linear time) on the entries' numbers gives the canonical order
        take, factor = np.concatenate(take)[on], np.concatenate(factor)[on]
        rows, cols = new_row[rows[on]], cols[on]
        P = sp.csr_matrix((np.arange(1.0, on.size + 1), (rows, cols)), shape=(self.n_residuals, n))
        P.sum_duplicates()
        if P.nnz == on.size:  # each entry its own: gathered in CSR order
            order = P.data.astype(np.int64) - 1
            return take[order], factor[order], P.indices, P.indptr, None
        # a block reads one variable twice (e.g. a sample and its neighbour are the same variable):
        # the entries are summed onto their CSR position
        key = rows.astype(np.int64) * n + cols
        order = np.argsort(key, kind="stable")
        first = np.r_[True, key[order][1:] != key[order][:-1]]
        dest = np.empty(on.size, np.int64)
        dest[order] = np.cumsum(first) - 1
        return take, factor, P.indices, P.indptr, dest

    def constraint_jacobian(self, x, pf) -> sp.csr_matrix:
        lay, n = self.problem.layout, self.n_x
        scale = lay.x_scale
        w = np.concatenate([np.asarray(x, float) * scale, pf])
        gr, gc, gv = [], [], []
        for j, row in enumerate(self.unit_rows):
            f = row[(row >= 0) & (row < n)]
            gr.append(np.full(len(f), j)), gc.append(f), gv.append(2 * w[f] * scale[f])
        return sp.csr_matrix((np.concatenate(gv), (np.concatenate(gr), np.concatenate(gc))),
                             shape=(self.n_constraints, n)) if gr else sp.csr_matrix((0, n))

    def symbolic_nlp(self) -> dict:
        """The same NLP as one CasADi expression graph, in the layout's order: {"x", "p", "f", "g"}
        with g in the order of ``Layout.unit_norm_rows``. A reference for tests and for CasADi's own
        solvers; unlike the solve path, it grows with the data. p = [fixed values; data]."""
        lay = self.problem.layout
        x, p = ca.MX.sym("x", self.n_x), ca.MX.sym("p", lay.n_p + self.problem.data.size)
        w = ca.vertcat(x * lay.x_scale, p[: lay.n_p])
        rs = []
        for b in self.blocks:
            N, fn = b.block.n, b.block.residual
            W = np.empty_like(b.w_idx)
            W[:, b.order] = b.w_idx  # the factor function's own input order
            Z = ca.reshape(w[W.ravel().tolist()], W.shape[1], N)
            d0 = lay.n_p + b.data_offset
            rs.append(ca.vec(fn.map(N)(Z, ca.reshape(p[d0: d0 + b.f.nd * N], b.f.nd, N))))
        pi, pm, ps = self.prior
        r = ca.vertcat(*rs, (w[pi.tolist()] - pm) / ps)
        g = [ca.sumsqr(w[row[row >= 0].tolist()]) - 1 for row in self.unit_rows]
        return {"x": x, "p": p, "f": 0.5 * ca.sumsqr(r), "g": ca.vertcat(*g) if g else ca.MX(0, 1)}

    def information(self, x, p_fixed=None, data=None) -> sp.csc_matrix:
        """The Fisher information J^T J at scaled x (:func:`castimate.solver.uncertainty.information`)."""
        return uncertainty.information(self, x, p_fixed, data)

    def marginal_information(self, x, p_fixed=None, data=None) -> tuple[np.ndarray, np.ndarray]:
        """Fisher information of the reported parameters with the nuisance variables marginalised."""
        return uncertainty.marginal_information(self, x, p_fixed, data)

    def undetermined(self, x, p_fixed=None, data=None, top: int = 4) -> list[str]:
        """Directions of the reported parameters the data cannot determine at x, named."""
        return uncertainty.undetermined(self, x, p_fixed, data, top)

    def covariance(self, x, p_fixed=None, data=None) -> np.ndarray:
        """Covariance of the reported parameters ``theta`` (physical units), nuisance marginalised."""
        return uncertainty.covariance(self, x, p_fixed, data)

    def solve(self, x0=None, p_fixed=None, data=None, lam_g0=None, covariance: bool | None = None,
              settle: float | None = None, warm: bool = False) -> Solution:
        """Solve from x0 (default: the groups' initial values); ``lam_g0`` warm-starts the constraint
        multipliers, e.g. from a Gauss-Newton solution polished with the exact Hessian.
        ``covariance``: compute the Fisher covariance (default: ``options.covariance``); False for a
        fit that an outer iteration refits anyway (the noise model's).

        For an outer iteration's refits (:class:`Stall`): ``settle`` (χ² units) stops the solve after
        the first iteration that changed χ² by at most ``settle``, unconverged (``Solution.settled``;
        an intermediate fit whose residuals only feed the next round); ``warm`` tests the Newton
        decrement at the first iteration that leaves χ² unchanged to round-off rather than after
        :attr:`Stall.EARLY` idle ones (a warm start near the optimum)."""
        cov = self.options.covariance if covariance is None else covariance
        if self.projection is not None:  # no MUMPS factor storage to keep: glibc's defaults fragment less
            return self._solve(x0, p_fixed, data, lam_g0, cov, settle, warm)
        with solve_settings():
            return self._solve(x0, p_fixed, data, lam_g0, cov, settle, warm)

    def _solve(self, x0, p_fixed, data, lam_g0, with_covariance: bool, settle=None, warm=False) -> Solution:
        lay, P = self.problem.layout, self.projection
        x0 = lay.x0() if x0 is None else np.asarray(x0, float)
        lbx, ubx = lay.bounds()
        pf, data = self.fixed_and_data(p_fixed, data)
        t0 = time.perf_counter()
        if P is None:
            sel = self.perm
            self.assembly.data, self.assembly._cache = data, None
            start = x0[sel]
        else:  # IPOPT over the calibration variables
            sel = P.cal
            start = P.reset(x0, data)
        self.stall.reset(settle, warm)
        self._pf = pf
        sol = self.nlp(x0=start, p=pf, lbx=lbx[sel], ubx=ubx[sel], lbg=0, ubg=0,
                       lam_g0=0 if lam_g0 is None else lam_g0)
        wall = time.perf_counter() - t0
        st = self.nlp.stats()
        unsolved = ""
        if P is None:
            x = np.empty(self.n_x)
            x[sel] = np.asarray(sol["x"]).ravel()
        else:
            try:
                x = P.solution(np.asarray(sol["x"]).ravel(), pf)
            except EvaluationError:  # a failed solve's last iterate has no motion: report the failure at the start
                if st["success"]:
                    raise
                x, unsolved = x0.copy(), "; the eliminated nuisance variables did not converge at its last iterate"
        values = lay.unpack(x, pf)
        cov = self.covariance(x, pf, data) if with_covariance and not unsolved else None
        std = uncertainty.std_by_group(self, cov) if cov is not None else {}
        residual = self.residuals(x, pf, data)
        cost = 0.5 * float(residual @ residual)
        lam = np.asarray(sol["lam_g"]).ravel()
        success, message = bool(st["success"]), str(st["return_status"]) + unsolved
        settled = message == "User_Requested_Stop" and self.stall.settled is not None
        if settled:
            message = (f"Settled, not converged (an iteration changed χ² by {self.stall.settled:.2g}, "
                       f"at most {settle:.2g})")
        if message == "User_Requested_Stop" and self.stall.stalled:
            message = f"Stalled ({self.stall.idle} iterations that moved x by less than {Stall.RELATIVE:.0e})"
        violation = float(np.abs(np.asarray(sol["g"])).max(initial=0.0))
        if not success and (message == "Search_Direction_Becomes_Too_Small" or self.stall.stalled) \
                and violation < 1e-9:
            # IPOPT stops here when round-off in stiff residuals (e.g. the process model's tiny σ_int)
            # keeps the gradient above its tolerance: the full NLP at estimated process-noise levels
            # sits at the optimum (steps of 1e-13) with its dual infeasibility at a floor of 1e-6,
            # and went on to max_iter (6 s) before Stall stopped it. Converged if the constraints hold
            # and a further Newton step could not change χ² by more than 1e-6 (Newton decrement with
            # the Gauss-Newton Hessian).
            # the stall test's, if it stopped the solve at this iterate on the decrement
            decrement = self.stall.early if self.stall.early is not None else self.newton_decrement(x, lam, pf, data)
            if decrement < 1e-6:
                success, message = True, f"Converged to machine precision (Newton decrement {decrement:.1e})"
        return Solution(
            success=success,
            message=message,
            iterations=int(st["iter_count"]),
            wall_s=wall,
            x=x,
            values=values,
            std=std,
            cost=cost,
            chi2=2.0 * cost,
            dof=int(self.n_residuals - (x.size - self.n_constraints)),
            residual=residual[: self.n_data_residuals],
            covariance=cov,
            lam_g=lam,
            evaluated=not unsolved,
            settled=settled,
        )

    def newton_decrement(self, x, lam_g, p_fixed=None, data=None) -> float:
        """Twice the χ² decrease a full Gauss-Newton step would still achieve at x."""
        return uncertainty.newton_decrement(self, x, lam_g, p_fixed, data)

    def _idle_decrement(self, x_nlp, lam_g) -> float:
        """The Newton decrement at IPOPT's iterate x_nlp (its variables, in NLP order), with the fixed
        values and data of the solve under way (:class:`Stall`)."""
        P, pf = self.projection, self._pf
        if P is not None:  # the decrement's elimination must not disturb the solve's
            with P.kept():
                return self.newton_decrement(P.solution(x_nlp, pf), lam_g, pf, P.data)
        x = np.empty(self.n_x)
        x[self.perm] = x_nlp
        return self.newton_decrement(x, lam_g, pf, self.assembly.data)


class Stall(ca.Callback):
    """IPOPT's iteration callback: stops the solve (User_Requested_Stop) once ITERATIONS
    consecutive iterations moved no variable by more than RELATIVE (relative to max(1, |x|)), or
    after EARLY such iterations if the Newton decrement there (``decrement(x, lam_g)``) is below
    DECREMENT: a warm-started refit that starts near its optimum can sit there with IPOPT's scaled
    gradient at its round-off floor above ``tol`` (the exp_1 joint problem's last noise-model
    refit: 9 of 12 iterations idle, decrement 1e-22), while a problem that is still converging
    slowly (a static case sits still for 7 iterations at a decrement far above it, then moves by
    3e-9) goes on. The caller then decides convergence by the Newton decrement
    (:meth:`Solver.solve`).

    For an outer iteration's refits (``reset(settle, warm)``): with ``settle`` (χ² units) it stops
    after the first iteration that changed χ² = 2f by at most ``settle`` (``settled``: that
    change); with ``warm`` the decrement is tested at the first iteration that changed χ² by at
    most FLAT relative (round-off), not after EARLY idle ones: the exp_1 joint problem's last
    noise-model refit moved by 1e-7 in its second iteration and then sat idle for three more
    (1.5 s), at a decrement of 1e-22."""

    ITERATIONS = 10
    RELATIVE = 1e-12
    EARLY = 3
    DECREMENT = 1e-15  # χ² units: test_elimination's bar for a converged solve
    FLAT = 1e-12

    def __init__(self, n: int, n_c: int, n_p: int, decrement=None):
        ca.Callback.__init__(self)
        self.decrement = decrement
        self._sp = [ca.Sparsity.dense(n), ca.Sparsity.dense(1), ca.Sparsity.dense(n_c), ca.Sparsity.dense(n),
                    ca.Sparsity.dense(n_c), ca.Sparsity.dense(n_p)]
        self.reset()
        self.construct("stall", {})

    def reset(self, settle: float | None = None, warm: bool = False):
        self._last, self.idle, self.stalled = None, 0, False
        self.early = None  # the Newton decrement that stopped the solve after EARLY idle iterations
        self._f, self.settle, self.warm = None, settle, warm
        self.settled = None  # the χ² change of the iteration that stopped the solve by ``settle``

    def get_n_in(self):
        return len(self._sp)

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        return self._sp[i]

    def eval(self, arg):
        x = np.asarray(arg[0]).ravel()
        if self._last is not None and np.abs(x - self._last).max(initial=0.0) <= \
                self.RELATIVE * max(1.0, np.abs(x).max(initial=0.0)):
            self.idle += 1
        else:
            self.idle = 0
        self._last = x.copy()
        f, change = float(np.asarray(arg[1]).ravel()[0]), None
        if self._f is not None:
            change = 2.0 * abs(self._f - f)
        self._f = f
        if self.settle is not None and change is not None and change <= self.settle:
            self.settled = change
            return [1]
        self.stalled = self.idle >= self.ITERATIONS
        flat = self.warm and change is not None and change <= self.FLAT * 2.0 * abs(f)
        if flat:
            self.warm = False  # tested once; then the idle iterations' test as usual
        if (self.idle == self.EARLY or flat) and self.decrement is not None:
            d = self.decrement(x, np.asarray(arg[4]).ravel())
            if d < self.DECREMENT:
                self.stalled, self.early = True, d
        return [1 if self.stalled else 0]


@contextlib.contextmanager
def solve_settings():
    """The process's settings for the duration of a solve, each restored afterwards; nested blocks
    (``castimate solve`` and :func:`castimate.solve` hold one around the whole calibration) leave
    them to the outermost. The same settings serve the calibration from Python as from the CLI.

    - Large allocations served from the heap, freed memory kept (where glibc is the C library).
      MUMPS allocates and frees its factor storage at every factorisation; by glibc's default every
      block above 32 MB is a fresh mmap whose pages the kernel zeroes on first touch. On the joint
      MIMU4444 problem that was 10 s of system time in 24 s of IPOPT search directions (31 s -> 19 s
      per solve), and 32 x 20 000 went from 16.9 s to 14.3 s with the same peak memory. Afterwards
      the heap is trimmed.
    - No advice of transparent huge pages for NumPy's large arrays (``madvise(MADV_HUGEPAGE)``, on by
      default on Linux), unless the user chose (``NUMPY_MADVISE_HUGEPAGE`` set, as the CLI does for
      its whole process). On a virtual machine that returns freed memory to its host (the 2-core VM
      of the benchmarks: a balloon's free-page reporting) a huge page's first touch is the host's
      too: there 1 GiB of np.ones took 3.8-4.1 s with the advice and 0.74-0.76 s without, and
      MIMU4444 exp_1 joint through the CLI 12.5-13.4 s (3.4-3.9 s system time) with
      NUMPY_MADVISE_HUGEPAGE=1 against 11.0-11.5 s (1.3-1.6 s) with 0, the same user time.
    - One thread in each OpenBLAS library loaded (CasADi's, NumPy's and SciPy's bundle their own),
      unless the user chose (``OPENBLAS_NUM_THREADS``, ``GOTO_NUM_THREADS`` or ``OMP_NUM_THREADS``
      set, as the CLI does): castimate's threads are its own (``solver.threads``), and its dense
      kernels are small (the CLI's reasons, at the top of :mod:`castimate.cli`)."""
    if _DEPTH[0]:
        _DEPTH[0] += 1
        try:
            yield
        finally:
            _DEPTH[0] -= 1
        return
    restore = [_heap(), _numpy_hugepage_off(), _one_blas_thread()]
    _DEPTH[0] = 1
    try:
        yield
    finally:
        _DEPTH[0] = 0
        for undo in restore:
            undo()


_DEPTH = [0]  # open solve_settings blocks (one thread of control sets the process's options)


def _heap():
    """glibc: large blocks from the heap, freed memory kept; returns what restores the defaults."""
    libc = _glibc()
    if libc is None:
        return lambda: None
    libc.mallopt(_M_MMAP_MAX, 0)
    libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)

    def undo():
        libc.mallopt(_M_MMAP_MAX, 65536)
        libc.mallopt(_M_TRIM_THRESHOLD, 128 * 1024)
        libc.malloc_trim(0)
    return undo


try:  # NumPy's switch of its huge-page advice (returns the previous setting); NumPy < 2: numpy.core
    from numpy._core.multiarray import _set_madvise_hugepage as _numpy_hugepage
except ImportError:  # pragma: no cover - depends on the NumPy version
    try:
        from numpy.core.multiarray import _set_madvise_hugepage as _numpy_hugepage
    except ImportError:
        _numpy_hugepage = None


def _numpy_hugepage_off():
    """NumPy's huge-page advice off unless the user chose; returns what restores it."""
    if _numpy_hugepage is None or os.environ.get("NUMPY_MADVISE_HUGEPAGE") is not None:
        return lambda: None
    before = _numpy_hugepage(False)
    return lambda: _numpy_hugepage(before)


def _one_blas_thread():
    """One thread in every OpenBLAS library loaded, unless the user chose; returns what restores
    their counts."""
    if any(os.environ.get(v) is not None for v in ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")):
        return lambda: None
    controls = _openblas_controls()
    before = [get() for get, _ in controls]
    for _, put in controls:
        put(1)
    return lambda: [put(n) for (_, put), n in zip(controls, before)]


def _openblas_controls() -> list:
    """(get, set) of the thread count of every OpenBLAS library this process has loaded, found by
    file name in /proc/self/maps and by the names they export (``openblas_set_num_threads``,
    SciPy's ``scipy_openblas_...``, NumPy's 64-bit ``..._num_threads64_``); none elsewhere."""
    try:
        with open("/proc/self/maps") as f:
            paths = sorted({ln.split()[-1] for ln in f if "openblas" in ln.rsplit("/", 1)[-1].lower() and "/" in ln})
    except OSError:
        return []
    out = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in (("openblas", ""), ("scipy_openblas", ""), ("scipy_openblas", "64_"), ("openblas", "64_")):
            get = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
            put = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
            if get is not None and put is not None:
                get.restype, put.argtypes = ctypes.c_int, [ctypes.c_int]
                out.append((get, put))
                break
    return out


_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # glibc's mallopt parameters


@functools.lru_cache(maxsize=1)
def _glibc():
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None

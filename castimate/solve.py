"""The one solve path shared by every kind.

A problem is a weighted nonlinear least-squares problem with equality constraints::

    minimise   1/2 |r(x, p)|^2      r: whitened residuals (factor blocks and priors)
    subject to c(x, p) = 0          unit-norm constraints of quaternions and unit vectors
               lbx <= x <= ubx

The residual is a factor graph: each :class:`FactorBlock` is one small CasADi function of a few
parameter groups and a few data, mapped over its instances (``Function.map``). IPOPT gets the exact
sparse Hessian of the Lagrangian, assembled from the blocks' local Hessians through a sparsity
pattern computed once in numpy. Build time and memory therefore grow linearly with the number of
instances; differentiating one monolithic expression graph (CasADi's default) colours a Hessian
with a dense border and grows about quadratically.

Uncertainty comes from the Fisher information J^T J at the solution, restricted to the tangent
space of the constraints; its inverse's blocks for the calibration parameters are the marginals
with the nuisance variables integrated out.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from .jit import compile_functions
from .problem.parameters import Layout


@dataclass(frozen=True)
class SolverOptions:
    """IPOPT settings with documented defaults.

    Attributes
    ----------
    max_iter
        Iteration limit; hitting it is a failure to converge.
    tol
        IPOPT's overall tolerance (on the scaled KKT error).
    linear_solver
        ``mumps`` (default, fastest in the wheel) or ``spral``.
    print_level
        IPOPT verbosity, 0-12.
    hessian
        ``exact`` (default): the exact Hessian of the Lagrangian. ``gauss_newton``: J^T J plus the
        constraint curvature, more robust far from the solution.
    identifiability_tol
        Relative eigenvalue of the Fisher information below which a direction counts as not
        determined by the data.
    method
        ``ipopt`` (default) or ``bcd``: Carlsson 2017's block coordinate descent (Algorithm 1), a
        baseline for dynamic problems with gyroscopes where only positions are free.
    jit
        Compile the factors' local functions to C (:mod:`castimate.jit`, cached on disk); the
        results are the same as on CasADi's virtual machine, about ten times faster.
    """

    method: str = "ipopt"
    max_iter: int = 200
    tol: float = 1e-8
    linear_solver: str = "mumps"
    print_level: int = 0
    hessian: str = "exact"
    identifiability_tol: float = 1e-10
    jit: bool = True

    def ipopt(self) -> dict:
        return {
            "ipopt.max_iter": self.max_iter,
            "ipopt.tol": self.tol,
            "ipopt.linear_solver": self.linear_solver,
            "ipopt.print_level": self.print_level,
            "ipopt.sb": "yes",
            "ipopt.mumps_pivot_order": 5,  # METIS ordering
            "print_time": False,
            "record_time": True,
        }


@dataclass
class FactorBlock:
    """One kind of residual term repeated over instances: a factor of the factor graph.

    Attributes
    ----------
    name
        For messages.
    residual
        ``(z, d) -> r``: whitened residual of one instance. ``z`` stacks the values of the
        instance's inputs (physical units), ``d`` its data.
    inputs
        ``(group, rows)`` in the order they stack into ``z``. ``group`` is a group name or a tuple
        of names whose rows are stacked (one plain group per triad, say); ``rows`` (N,) picks a row
        per instance, ``None`` feeds the single row to every instance. One block per kind of factor
        keeps CasADi's graph small: one ``map`` node instead of one per triad.
    data
        (N, nd) data of the instances; they enter the NLP as parameters, so one build serves any
        number of data sets.
    """

    name: str
    residual: ca.Function
    inputs: list[tuple[str | tuple[str, ...], np.ndarray | None]]
    data: np.ndarray

    @property
    def n(self) -> int:
        return self.data.shape[0]

    @property
    def n_residuals(self) -> int:
        return self.n * self.residual.size1_out(0)


@dataclass
class LeastSquaresProblem:
    """A whitened least-squares problem: parameter groups plus factor blocks."""

    layout: Layout
    blocks: list[FactorBlock]

    @property
    def data(self) -> np.ndarray:
        return np.concatenate([b.data.ravel() for b in self.blocks])

    def pack(self, block_data: list[np.ndarray]) -> np.ndarray:
        """Data vector from per-block (N, nd) arrays."""
        return np.concatenate([np.asarray(d, float).ravel() for d in block_data])


@dataclass
class Solution:
    """The outcome of one solve, in physical units."""

    success: bool
    message: str
    iterations: int
    wall_s: float
    x: np.ndarray
    values: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    cost: float
    chi2: float
    dof: int
    residual: np.ndarray
    covariance: np.ndarray = field(repr=False)  # of the free calibration components (Solver.theta), physical units
    lam_g: np.ndarray = field(default=None, repr=False)  # constraint multipliers, to warm-start another solve  # of the free calibration components (Solver.theta), physical units

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")


class _Compiled:
    """Local functions of one factor: residual, Jacobian and the Hessian entries worth assembling.

    Derivatives are taken only with respect to the components that are free in some instance
    (``active``): fixed intrinsics feed the residual but are never differentiated, which cut the
    exact local Hessian of a Schopp accelerometer factor from about 6500 to about 2400 instructions.
    """

    def __init__(self, fn: ca.Function, active: np.ndarray, hessian: str, jit: bool):
        nz, nd = fn.size1_in(0), fn.size1_in(1)
        z, d = ca.SX.sym("z", nz), ca.SX.sym("d", nd)
        r = fn(z, d)
        self.act = act = np.flatnonzero(active)
        za = ca.vertcat(*[z[int(i)] for i in act]) if len(act) else ca.SX(0, 1)
        J = ca.jacobian(r, za)
        # exact: the Hessian of 1/2 |r|^2 = J^T J + sum_i r_i Hess(r_i); Gauss-Newton leaves out the sum
        H = ca.hessian(0.5 * ca.sumsqr(r), za)[0] if hessian == "exact" else ca.mtimes(J.T, J)
        sp_H = H.sparsity()
        # entries (a <= b), as indices into z, that are structurally nonzero
        self.pairs = [(int(act[a]), int(act[b])) for b in range(len(act)) for a in range(b + 1) if sp_H.has_nz(a, b)]
        loc = {int(i): k for k, i in enumerate(act)}
        self.hess = ca.Function(f"{fn.name()}_hess", [z, d], [ca.vertcat(*[H[loc[a], loc[b]] for a, b in self.pairs])
                                                               if self.pairs else ca.SX(0, 1)])
        self.jac = ca.Function(f"{fn.name()}_jac", [z, d], [ca.densify(J)])
        self.res = ca.Function(f"{fn.name()}_res", [z, d], [r])
        if jit:
            self.res, self.jac, self.hess = compile_functions([self.jac, self.hess], [self.res]) or \
                (self.res, self.jac, self.hess)
        self.nz, self.nd, self.m = nz, nd, fn.size1_out(0)


class _Block:
    """A factor block bound to the layout: its index matrix into w and its compiled functions."""

    def __init__(self, block: FactorBlock, layout: Layout, cache: dict, hessian: str, jit: bool):
        self.block = block
        cols = []
        for g, rows in block.inputs:
            W = layout.w_index(g) if isinstance(g, str) else np.vstack([layout.w_index(n) for n in g])
            cols.append(np.broadcast_to(W[0], (block.n, W.shape[1])) if rows is None else W[np.asarray(rows)])
        self.w_idx = np.hstack(cols).astype(int)
        nz = block.residual.size1_in(0)
        if self.w_idx.shape[1] != nz:
            raise ValueError(f"factor block {block.name}: inputs give {self.w_idx.shape[1]} values, "
                             f"the function takes {nz}")
        active = (self.w_idx < layout.n_x).any(axis=0)
        key = (id(block.residual), active.tobytes())
        if key not in cache:
            cache[key] = _Compiled(block.residual, active, hessian, jit)
        self.f = cache[key]


class Solver:
    """IPOPT on a :class:`LeastSquaresProblem`, built once and solved for any data or fixed values."""

    def __init__(self, problem: LeastSquaresProblem, options: SolverOptions = SolverOptions()):
        t0 = time.perf_counter()
        self.problem, self.options = problem, options
        lay = problem.layout
        self.n_x = n = lay.n_x
        cache: dict = {}
        self.blocks = [_Block(b, lay, cache, options.hessian, options.jit) for b in problem.blocks if b.n]
        x = ca.MX.sym("x", n)
        p = self._p_sym = ca.MX.sym("p", lay.n_p + problem.data.size)
        scale = lay.x_scale
        w = ca.vertcat(x * scale, p[: lay.n_p])

        # residuals: each block's function mapped over its instances
        residuals, hess_parts, off = [], [], lay.n_p
        for b in self.blocks:
            N, f = b.block.n, b.f
            Z = ca.reshape(w[b.w_idx.ravel().tolist()], f.nz, N)
            D = ca.reshape(p[off: off + f.nd * N], f.nd, N)
            b.data_offset = off
            off += f.nd * N
            residuals.append(ca.vec(f.res.map(N)(Z, D)))
            if f.pairs:
                hess_parts.append(ca.vec(f.hess.map(N)(Z, D)))
        self.n_data_residuals = sum(b.block.n_residuals for b in self.blocks)
        pi, pm, ps = lay.priors()
        self._prior = (pi, pm, ps)
        prior_r = (w[pi.tolist()] - pm) / ps if len(pi) else ca.MX(0, 1)
        r_data = ca.vertcat(*residuals) if residuals else ca.MX(0, 1)
        r_all = ca.vertcat(r_data, prior_r)
        self.n_residuals = r_all.shape[0]

        # constraints |row|^2 = 1, rows grouped by width for vectorisation
        self._unit = U = lay.unit_norm_rows()
        self.n_constraints = U.shape[0]
        c_parts = []
        self._unit_order = []
        for width in sorted({int((row >= 0).sum()) for row in U}):
            sel = np.flatnonzero((U >= 0).sum(axis=1) == width)
            idx = U[sel][:, :width]
            c_parts.append(ca.sum1(ca.reshape(w[idx.ravel().tolist()], width, len(sel)) ** 2).T - 1)
            self._unit_order.append(sel)
        c = ca.vertcat(*c_parts) if c_parts else ca.MX(0, 1)
        self._c_perm = np.concatenate(self._unit_order) if self._unit_order else np.zeros(0, int)
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", self.n_constraints)

        # exact Hessian of the Lagrangian, upper triangle, assembled from the local Hessians
        A, B, sparsity = self._hessian_pattern(lay, scale, pi, ps)
        H_nz = lam_f * ca.mtimes(_dm(A), ca.vertcat(*hess_parts, ca.DM.ones(len(pi))))
        if self.n_constraints:
            H_nz += ca.mtimes(_dm(B), lam_g)
        hess_lag = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [ca.MX(sparsity, H_nz)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        nlp = {"x": x, "p": p, "f": 0.5 * ca.sumsqr(r_all), "g": c}
        self.nlp = ca.nlpsol("castimate", "ipopt", nlp, {**options.ipopt(), "hess_lag": hess_lag})
        self._res = ca.Function("data_residual", [x, p], [r_data])
        self._res_all = ca.Function("residual", [x, p], [r_all])
        nuisance = np.zeros(n, bool)
        for g in lay.groups:
            if g.nuisance:
                nuisance[lay.x_indices(g.name)] = True
        self.theta = np.flatnonzero(~nuisance)  # reported parameters: their covariance is computed
        self.build_s = time.perf_counter() - t0

    def _hessian_pattern(self, lay: Layout, scale, pi, ps):
        """Constant maps from local Hessian entries (and prior and constraint curvature) to the
        nonzeros of the global upper-triangular Hessian, with the chain rule of the x scaling."""
        n = self.n_x
        rows, cols, src, val = [], [], [], []
        col0 = 0
        for b in self.blocks:
            pairs = b.f.pairs
            if not pairs:
                continue
            a_idx = np.array([a for a, _ in pairs])
            b_idx = np.array([bb for _, bb in pairs])
            gi, gj = b.w_idx[:, a_idx], b.w_idx[:, b_idx]  # (N, n_pairs) positions in w
            k = np.nonzero((gi < n) & (gj < n))
            i, j = gi[k], gj[k]
            rows.append(np.minimum(i, j))
            cols.append(np.maximum(i, j))
            # entry (a, b) of instance t sits at column-major position t * n_pairs + pair index
            src.append(col0 + k[0] * len(pairs) + k[1])
            v = scale[i] * scale[j]
            v[(i == j) & (a_idx[k[1]] != b_idx[k[1]])] *= 2  # both (a,b) and (b,a) land on the diagonal
            val.append(v)
            col0 += b.block.n * len(pairs)
        # priors: d^2/dx^2 of 1/2 ((x s - m) / std)^2 = (s / std)^2
        rows.append(pi), cols.append(pi), src.append(col0 + np.arange(len(pi))), val.append((scale[pi] / ps) ** 2)
        n_src = col0 + len(pi)
        # unit-norm constraints: d^2/dx^2 of |x s|^2 - 1 = 2 s^2 on the free components
        crow, ccol, cval = [], [], []
        for j, row in enumerate(self._unit[self._c_perm]):
            f = row[(row >= 0) & (row < n)]
            crow.append(f), ccol.append(np.full(len(f), j)), cval.append(2 * scale[f] ** 2)
        R, C = np.concatenate(rows + crow), np.concatenate(cols + crow)
        pattern = sp.coo_matrix((np.ones(len(R)), (R, C)), shape=(n, n)).tocsc()
        pattern.sum_duplicates()
        pattern.sort_indices()
        sparsity = ca.Sparsity(n, n, pattern.indptr.tolist(), pattern.indices.tolist())
        pos = sp.csc_matrix((np.arange(pattern.nnz) + 1.0, pattern.indices, pattern.indptr), shape=(n, n))

        def nz_of(r, c):
            return np.asarray(pos[r, c]).ravel().astype(int) - 1

        r_all, c_all = np.concatenate(rows), np.concatenate(cols)
        A = sp.csc_matrix((np.concatenate(val), (nz_of(r_all, c_all), np.concatenate(src))), shape=(pattern.nnz, n_src))
        if crow:
            cr = np.concatenate(crow)
            B = sp.csc_matrix((np.concatenate(cval), (nz_of(cr, cr), np.concatenate(ccol))),
                              shape=(pattern.nnz, self.n_constraints))
        else:
            B = sp.csc_matrix((pattern.nnz, 0))
        return A, B, sparsity

    # -- numeric ---------------------------------------------------------------------------------
    def _p(self, p_fixed, data):
        lay = self.problem.layout
        p_fixed = lay.p0() if p_fixed is None else p_fixed
        data = self.problem.data if data is None else data
        return np.concatenate([np.asarray(p_fixed, float), np.asarray(data, float).ravel()])

    def residuals(self, x, p_fixed=None, data=None) -> np.ndarray:
        """All whitened residuals (data, then priors) at scaled x."""
        return np.asarray(self._res_all(x, self._p(p_fixed, data))).ravel()

    def jacobians(self, x, p_fixed=None, data=None) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Sparse Jacobians w.r.t. scaled x of the whitened residuals (data, then priors) and of the
        constraints (in the order of ``Layout.unit_norm_rows``)."""
        lay = self.problem.layout
        p = self._p(p_fixed, data)
        n = self.n_x
        scale = lay.x_scale
        w = np.concatenate([np.asarray(x, float) * scale, p[: lay.n_p]])
        rows, cols, vals = [], [], []
        row0 = 0
        for b in self.blocks:
            N, f = b.block.n, b.f
            Z = w[b.w_idx].T
            D = p[b.data_offset: b.data_offset + f.nd * N].reshape(N, f.nd).T
            na = len(f.act)
            Jl = np.asarray(f.jac.map(N)(Z, D)).reshape(f.m, na, N, order="F")  # instances side by side
            t, a = np.nonzero(b.w_idx[:, f.act] < n)  # a indexes the active components
            gi = b.w_idx[t, f.act[a]]
            for i in range(f.m):
                rows.append(row0 + t * f.m + i)
                cols.append(gi)
                vals.append(Jl[i, a, t] * scale[gi])
            row0 += N * f.m
        pi, _, ps = self._prior
        rows.append(row0 + np.arange(len(pi))), cols.append(pi), vals.append(scale[pi] / ps)
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(self.n_residuals, n))
        gr, gc, gv = [], [], []
        for j, row in enumerate(self._unit):
            f = row[(row >= 0) & (row < n)]
            gr.append(np.full(len(f), j)), gc.append(f), gv.append(2 * w[f] * scale[f])
        G = sp.csr_matrix((np.concatenate(gv), (np.concatenate(gr), np.concatenate(gc))), shape=(self.n_constraints, n)) \
            if gr else sp.csr_matrix((0, n))
        return J, G

    def _eliminate(self, x, p_fixed=None, data=None, g: np.ndarray | None = None):
        """Eliminate the nuisance block from the Gauss-Newton KKT system at x.

        With F = J^T J split into reported parameters t and nuisance n, and N = [[F_nn, G_n^T],
        [G_n, 0]] the sparse KKT matrix of the nuisance block with its own constraints, returns
        S = F_tt - B N^-1 B^T, the constraints G_t on t, and, for a gradient g, the reduced
        gradient g_t - B N^-1 g_n and g_n^T N^-1 g_n. Unit-norm constraints act on either block,
        never both.
        """
        J, G = self.jacobians(x, p_fixed, data)
        F = (J.T @ J).tocsc()
        t = self.theta
        nu = np.setdiff1d(np.arange(self.n_x), t)
        G = G.tocsc()
        on_theta = np.asarray(abs(G[:, t]).sum(axis=1)).ravel() > 0
        G_t, G_n = G[on_theta][:, t], G[~on_theta][:, nu]
        S = F[t][:, t].toarray()
        g_t, g_nn = (None, 0.0) if g is None else (g[t].copy(), 0.0)
        if len(nu):
            K = sp.bmat([[F[nu][:, nu], G_n.T], [G_n, None]], format="csc")
            # C order: SuperLU's solve is orders of magnitude slower on a Fortran-ordered right-hand side
            Bt = np.ascontiguousarray(sp.vstack([F[nu][:, t], sp.csc_matrix((G_n.shape[0], len(t)))]).toarray())
            try:
                lu = _factor(K)
            except RuntimeError:  # exactly singular: some nuisance direction is undetermined
                raise np.linalg.LinAlgError("the nuisance variables are not determined by the data") from None
            S = S - Bt.T @ lu.solve(Bt)
            if g is not None:
                y = lu.solve(np.concatenate([g[nu], np.zeros(G_n.shape[0])]))
                g_t -= Bt.T @ y
                g_nn = float(g[nu] @ y[: len(nu)])
        return S, G_t.toarray(), g_t, g_nn

    def marginal_information(self, x, p_fixed=None, data=None) -> tuple[np.ndarray, np.ndarray]:
        """Fisher information of the reported parameters with the nuisance variables marginalised:
        (S, G_theta), see :meth:`_eliminate`."""
        S, G_t, _, _ = self._eliminate(x, p_fixed, data)
        return S, G_t

    def undetermined(self, x, p_fixed=None, data=None, top: int = 4) -> list[str]:
        """Directions of the reported parameters the data cannot determine at x, each named by its
        largest components."""
        try:
            S, G = self.marginal_information(x, p_fixed, data)
        except np.linalg.LinAlgError as e:
            return [str(e)]
        U = np.linalg.qr(G.T, mode="complete")[0][:, G.shape[0]:] if G.shape[0] else np.eye(len(self.theta))
        w, V = np.linalg.eigh(U.T @ S @ U)
        tol = self.options.identifiability_tol * max(w.max(), 1e-300)
        labels = self.problem.layout.x_labels
        out = []
        for k in np.flatnonzero(w <= tol):
            d = U @ V[:, k]
            idx = np.argsort(-np.abs(d))[:top]
            idx = [i for i in idx if abs(d[i]) > 0.2 * abs(d[idx[0]])]
            out.append(" + ".join(f"{d[i]:+.2f}*{labels[self.theta[i]]}" for i in idx))
        return out

    def covariance(self, x, p_fixed=None, data=None) -> np.ndarray:
        """Covariance of the reported parameters ``theta`` (physical units), nuisance marginalised.

        The top-left block of the inverse of [[S, G^T], [G, 0]] with S the marginal information:
        U (U^T S U)^-1 U^T for a basis U of the constraints' tangent space.
        """
        S, G = self.marginal_information(x, p_fixed, data)
        nt, c = S.shape[0], G.shape[0]
        K = np.zeros((nt + c, nt + c))
        K[:nt, :nt], K[nt:, :nt], K[:nt, nt:] = S, G, G.T
        rhs = np.zeros((nt + c, nt))
        rhs[:nt] = np.eye(nt)
        try:
            C = np.linalg.solve(K, rhs)[:nt]
        except np.linalg.LinAlgError:
            U = np.linalg.qr(G.T, mode="complete")[0][:, c:] if c else np.eye(nt)
            C = U @ np.linalg.pinv(U.T @ S @ U, hermitian=True) @ U.T
        s = self.problem.layout.x_scale[self.theta]
        return C * np.outer(s, s)

    def solve(self, x0=None, p_fixed=None, data=None, lam_g0=None) -> Solution:
        """Solve from x0 (default: the groups' initial values); ``lam_g0`` warm-starts the constraint
        multipliers, e.g. from a Gauss-Newton solution polished with the exact Hessian."""
        lay = self.problem.layout
        x0 = lay.x0() if x0 is None else np.asarray(x0, float)
        lbx, ubx = lay.bounds()
        p = self._p(p_fixed, data)
        t0 = time.perf_counter()
        sol = self.nlp(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=0, ubg=0, lam_g0=0 if lam_g0 is None else lam_g0)
        wall = time.perf_counter() - t0
        st = self.nlp.stats()
        x = np.asarray(sol["x"]).ravel()
        pf, data = p[: lay.n_p], p[lay.n_p:]
        values = lay.unpack(x, pf)
        cov = self.covariance(x, pf, data)
        sd = np.full(self.n_x, np.nan)
        sd[self.theta] = np.sqrt(np.clip(np.diag(cov), 0, None))
        std = {}
        for g in lay.groups:
            s = np.zeros(g.free.shape)
            s[g.free] = sd[lay.x_indices(g.name)]
            std[g.name] = g.shaped(s)
        cost = float(sol["f"])
        lam = np.asarray(sol["lam_g"]).ravel()
        success, message = bool(st["success"]), str(st["return_status"])
        if not success and message == "Search_Direction_Becomes_Too_Small":
            # IPOPT stops here when round-off in stiff residuals (e.g. the process model's tiny σ_int)
            # keeps the gradient above its tolerance. Converged if a further Newton step could not
            # change χ² by more than 1e-6 (Newton decrement with the Gauss-Newton Hessian).
            decrement = self.newton_decrement(x, lam, pf, data)
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
            residual=np.asarray(self._res(x, p)).ravel(),
            covariance=cov,
            lam_g=lam,
        )

    def newton_decrement(self, x, lam_g, p_fixed=None, data=None) -> float:
        """g^T H^-1 g of the Lagrangian gradient with the Gauss-Newton Hessian on the constraints'
        tangent space: twice the χ² decrease a full Newton step would still achieve. The nuisance
        block is eliminated first (:meth:`_eliminate`), so this costs what the covariance costs."""
        J, G = self.jacobians(x, p_fixed, data)
        r = self.residuals(x, p_fixed, data)
        lam = np.zeros(self.n_constraints)
        lam[self._c_perm] = lam_g  # CasADi's multipliers follow its constraint order (grouped by width)
        g = J.T @ r + G.T @ lam
        try:
            S, G_t, g_t, g_nn = self._eliminate(x, p_fixed, data, g)
        except np.linalg.LinAlgError:
            return float("inf")
        nt, c = S.shape[0], G_t.shape[0]
        K = np.zeros((nt + c, nt + c))
        K[:nt, :nt], K[nt:, :nt], K[:nt, nt:] = S, G_t, G_t.T
        try:
            step = np.linalg.solve(K, np.concatenate([g_t, np.zeros(c)]))[:nt]
        except np.linalg.LinAlgError:
            return float("inf")
        return g_nn + float(g_t @ step)


def _factor(K: sp.spmatrix):
    """Sparse LU of a symmetric (KKT) matrix. The minimum-degree ordering on K + K^T keeps the
    triangular solves fast: with SuperLU's default COLAMD, solving for 100 right-hand sides on a
    block-diagonal motion block of 18 000 rows took 31 s instead of 0.17 s."""
    return splu(sp.csc_matrix(K), permc_spec="MMD_AT_PLUS_A")


def _dm(M: sp.spmatrix) -> ca.DM:
    """A scipy sparse matrix as a CasADi DM with the same sparsity."""
    M = sp.csc_matrix(M)
    M.sort_indices()
    return ca.DM(ca.Sparsity(M.shape[0], M.shape[1], M.indptr.tolist(), M.indices.tolist()), M.data.tolist())

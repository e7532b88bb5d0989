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
    """

    max_iter: int = 200
    tol: float = 1e-10
    linear_solver: str = "mumps"
    print_level: int = 0
    hessian: str = "exact"
    identifiability_tol: float = 1e-10

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
        instance's parameter groups (physical units), ``d`` its data.
    groups
        For each instance, the names of the groups forming ``z``, in order.
    data
        (N, nd) data of the instances; they enter the NLP as parameters, so one build serves any
        number of data sets.
    """

    name: str
    residual: ca.Function
    groups: list[tuple[str, ...]]
    data: np.ndarray

    @property
    def n(self) -> int:
        return len(self.groups)

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
    covariance_x: np.ndarray = field(repr=False)

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")


class _Block:
    """A factor block compiled for the solver: mapped functions and its index arrays."""

    def __init__(self, block: FactorBlock, layout: Layout, hessian: str):
        fn = block.residual
        nz, nd = fn.size1_in(0), fn.size1_in(1)
        self.block, self.nz, self.nd, self.m = block, nz, nd, fn.size1_out(0)
        self.w_idx = np.array([np.concatenate([layout.w_index(g) for g in gs]) for gs in block.groups], dtype=int)
        if self.w_idx.shape != (block.n, nz):
            raise ValueError(f"factor block {block.name}: groups give {self.w_idx.shape[1]} values, the function takes {nz}")
        z, d = ca.SX.sym("z", nz), ca.SX.sym("d", nd)
        r = fn(z, d)
        J = ca.jacobian(r, z)
        H = ca.mtimes(J.T, J)
        if hessian == "exact":
            for i in range(self.m):  # + sum_i r_i Hess(r_i): the curvature Gauss-Newton leaves out
                H += r[i] * ca.hessian(r[i], z)[0]
        self.pairs = [(a, b) for b in range(nz) for a in range(b + 1)]
        H = ca.densify(H)
        self.hess = ca.Function(f"{block.name}_hess", [z, d], [ca.vertcat(*[H[a, b] for a, b in self.pairs])])
        self.jac = ca.Function(f"{block.name}_jac", [z, d], [ca.densify(J)])
        self.res = fn


class Solver:
    """IPOPT on a :class:`LeastSquaresProblem`, built once and solved for any data or fixed values."""

    def __init__(self, problem: LeastSquaresProblem, options: SolverOptions = SolverOptions()):
        t0 = time.perf_counter()
        self.problem, self.options = problem, options
        lay = problem.layout
        self.n_x = n = lay.n_x
        self.blocks = [_Block(b, lay, options.hessian) for b in problem.blocks]
        n_data = sum(b.block.data.size for b in self.blocks)
        x = ca.MX.sym("x", n)
        p = self._p_sym = ca.MX.sym("p", lay.n_p + n_data)
        scale = lay.x_scale
        w = ca.vertcat(x * scale, p[: lay.n_p])

        # residuals: each block's function mapped over its instances
        residuals, hess_parts, off = [], [], lay.n_p
        lam_f = ca.MX.sym("lam_f")
        for b in self.blocks:
            Z = ca.reshape(w[b.w_idx.ravel().tolist()], b.nz, b.block.n)
            D = ca.reshape(p[off: off + b.nd * b.block.n], b.nd, b.block.n)
            off += b.nd * b.block.n
            residuals.append(ca.vec(b.res.map(b.block.n)(Z, D)))
            hess_parts.append(ca.vec(b.hess.map(b.block.n)(Z, D)))
        self.n_data_residuals = sum(b.block.n_residuals for b in self.blocks)
        pi, pm, ps = lay.priors()
        self._prior = (pi, pm, ps)
        prior_r = (w[pi.tolist()] - pm) / ps if len(pi) else ca.MX(0, 1)
        r_data = ca.vertcat(*residuals) if residuals else ca.MX(0, 1)
        r_all = ca.vertcat(r_data, prior_r)
        self.n_residuals = r_all.shape[0]

        # constraints |v|^2 = 1
        self._unit = [lay.w_index(g.name) for g in lay.unit_norm_groups()]
        c = ca.vertcat(*[ca.sumsqr(w[i.tolist()]) - 1 for i in self._unit]) if self._unit else ca.MX(0, 1)
        self.n_constraints = c.shape[0]
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
        self.build_s = time.perf_counter() - t0

    def _hessian_pattern(self, lay: Layout, scale, pi, ps):
        """Constant maps from local Hessian entries (and prior and constraint curvature) to the
        nonzeros of the global upper-triangular Hessian, with the chain rule of the x scaling."""
        n = self.n_x
        rows, cols, src, val = [], [], [], []
        col0 = 0
        for b in self.blocks:
            a_idx = np.array([a for a, _ in b.pairs])
            b_idx = np.array([bb for _, bb in b.pairs])
            gi, gj = b.w_idx[:, a_idx], b.w_idx[:, b_idx]  # (N, n_pairs) positions in w
            free = (gi < n) & (gj < n)
            k = np.nonzero(free)
            i, j = gi[k], gj[k]
            rows.append(np.minimum(i, j))
            cols.append(np.maximum(i, j))
            # entry (a, b) of instance t sits at column-major position t * n_pairs + pair index
            src.append(col0 + k[0] * len(b.pairs) + k[1])
            v = scale[i] * scale[j]
            v[(i == j) & (a_idx[k[1]] != b_idx[k[1]])] *= 2  # both (a,b) and (b,a) land on the diagonal
            val.append(v)
            col0 += b.block.n * len(b.pairs)
        # priors: d^2/dx^2 of 1/2 ((x s - m) / std)^2 = (s / std)^2
        rows.append(pi), cols.append(pi), src.append(col0 + np.arange(len(pi))), val.append((scale[pi] / ps) ** 2)
        n_src = col0 + len(pi)
        # unit-norm constraints: d^2/dx^2 of |x s|^2 - 1 = 2 s^2 on the free components
        crow, ccol, cval = [], [], []
        for j, idx in enumerate(self._unit):
            f = idx[idx < n]
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

    def jacobians(self, x, p_fixed=None, data=None) -> tuple[sp.csr_matrix, np.ndarray]:
        """Jacobians w.r.t. scaled x of the whitened residuals (data, then priors) and of the constraints."""
        lay = self.problem.layout
        p = self._p(p_fixed, data)
        n = self.n_x
        w = np.concatenate([np.asarray(x, float) * lay.x_scale, p[: lay.n_p]])
        scale = lay.x_scale
        rows, cols, vals = [], [], []
        row0, off = 0, lay.n_p
        for b in self.blocks:
            N = b.block.n
            Z = w[b.w_idx].T
            D = p[off: off + b.nd * N].reshape(N, b.nd).T
            off += b.nd * N
            Jl = np.asarray(b.jac.map(N)(Z, D)).reshape(b.m, b.nz, N, order="F")  # instances side by side
            t, a = np.nonzero(b.w_idx < n)
            gi = b.w_idx[t, a]
            for i in range(b.m):
                rows.append(row0 + t * b.m + i)
                cols.append(gi)
                vals.append(Jl[i, a, t] * scale[gi])
            row0 += N * b.m
        pi, _, ps = self._prior
        rows.append(row0 + np.arange(len(pi))), cols.append(pi), vals.append(scale[pi] / ps)
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(self.n_residuals, n))
        G = np.zeros((self.n_constraints, n))
        for j, idx in enumerate(self._unit):
            f = idx[idx < n]
            G[j, f] = 2 * w[f] * scale[f]
        return J, G

    def _tangent_fisher(self, x, p_fixed, data) -> tuple[np.ndarray, np.ndarray]:
        """Fisher information J^T J restricted to the constraint tangent space, and its basis U."""
        J, G = self.jacobians(x, p_fixed, data)
        F = (J.T @ J).toarray()
        if G.shape[0]:
            U = np.linalg.qr(G.T, mode="complete")[0][:, G.shape[0]:]
            return U.T @ F @ U, U
        return F, np.eye(F.shape[0])

    def undetermined(self, x, p_fixed=None, data=None, top: int = 4) -> list[str]:
        """Directions the data cannot determine at x, each named by its largest components."""
        Fu, U = self._tangent_fisher(x, p_fixed, data)
        w, V = np.linalg.eigh(Fu)
        tol = self.options.identifiability_tol * max(w.max(), 1e-300)
        out = []
        labels = self.problem.layout.x_labels
        for k in np.flatnonzero(w <= tol):
            d = U @ V[:, k]
            idx = np.argsort(-np.abs(d))[:top]
            idx = [i for i in idx if abs(d[i]) > 0.2 * abs(d[idx[0]])]
            out.append(" + ".join(f"{d[i]:+.2f}*{labels[i]}" for i in idx))
        return out

    def covariance(self, x, p_fixed=None, data=None) -> np.ndarray:
        """Covariance of all free components (physical units): the constrained inverse Fisher information.

        Computed as the top-left block of the inverse of the KKT matrix [[J^T J, G^T], [G, 0]],
        which equals U (U^T J^T J U)^-1 U^T for a basis U of the constraints' tangent space.
        """
        J, G = self.jacobians(x, p_fixed, data)
        n, c = J.shape[1], G.shape[0]
        K = np.zeros((n + c, n + c))
        K[:n, :n] = (J.T @ J).toarray()
        K[n:, :n], K[:n, n:] = G, G.T
        rhs = np.zeros((n + c, n))
        rhs[:n] = np.eye(n)
        try:
            C = np.linalg.solve(K, rhs)[:n]
        except np.linalg.LinAlgError:
            Fu, U = self._tangent_fisher(x, p_fixed, data)  # rank deficient: pseudo-inverse
            C = U @ np.linalg.pinv(Fu, hermitian=True) @ U.T
        s = self.problem.layout.x_scale
        return C * np.outer(s, s)

    def solve(self, x0=None, p_fixed=None, data=None) -> Solution:
        lay = self.problem.layout
        x0 = lay.x0() if x0 is None else np.asarray(x0, float)
        lbx, ubx = lay.bounds()
        p = self._p(p_fixed, data)
        t0 = time.perf_counter()
        sol = self.nlp(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=0, ubg=0)
        wall = time.perf_counter() - t0
        st = self.nlp.stats()
        x = np.asarray(sol["x"]).ravel()
        pf, data = p[: lay.n_p], p[lay.n_p:]
        values = lay.unpack(x, pf)
        cov = self.covariance(x, pf, data)
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        std = {}
        for g in lay.groups:
            s = np.zeros(g.size)
            s[g.free] = sd[lay.x_indices(g.name)]
            std[g.name] = s
        cost = float(sol["f"])
        return Solution(
            success=bool(st["success"]),
            message=str(st["return_status"]),
            iterations=int(st["iter_count"]),
            wall_s=wall,
            x=x,
            values=values,
            std=std,
            cost=cost,
            chi2=2.0 * cost,
            dof=int(self.n_residuals - (x.size - self.n_constraints)),
            residual=np.asarray(self._res(x, p)).ravel(),
            covariance_x=cov,
        )


def _dm(M: sp.spmatrix) -> ca.DM:
    """A scipy sparse matrix as a CasADi DM with the same sparsity."""
    M = sp.csc_matrix(M)
    M.sort_indices()
    return ca.DM(ca.Sparsity(M.shape[0], M.shape[1], M.indptr.tolist(), M.indices.tolist()), M.data.tolist())

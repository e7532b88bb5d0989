"""The one solve path shared by every kind.

A problem is a weighted nonlinear least-squares problem with equality constraints::

    minimise   1/2 |r(x, p)|^2      r: whitened residuals (factor blocks and priors)
    subject to c(x, p) = 0          unit-norm constraints of quaternions and unit vectors
               lbx <= x <= ubx

The residual is a factor graph: each :class:`FactorBlock` is one small CasADi function of a few
parameter groups and a few data, mapped over its instances (``Function.map``), its local
residual, Jacobian, gradient and Hessian compiled to C (:mod:`castimate.jit`). IPOPT gets the
gradient and the exact sparse Hessian of the Lagrangian assembled from the local ones: for blocks
of calibration parameters through a constant sparse matrix computed in numpy; for blocks that
touch per-sample motion states stage by stage (:class:`_Stages`), so that nothing the size of the
Hessian is passed from Python to CasADi. Build time and memory therefore grow linearly with the
number of instances; differentiating one monolithic expression graph (CasADi's default) colours a
Hessian with a dense border and grows about quadratically.

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
            "calc_lam_p": False,  # the multipliers of the data are never used; their AD graph is large
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
    valid
        (N,) instances whose residuals count (default all). The data of the others must make
        their residuals exactly zero (a masked sample with σ = inf): they keep a block's
        instances on a regular grid, which the solver exploits, and are left out of the reported
        residuals and degrees of freedom.
    """

    name: str
    residual: ca.Function
    inputs: list[tuple[str | tuple[str, ...], np.ndarray | None]]
    data: np.ndarray
    valid: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.data.shape[0]


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

    Each takes (z_cal, z_stage, d): the factor's inputs split into the components that are not
    stage variables and those that are (:class:`_Stages`; none for an unstaged block), and its data.
    Derivatives are taken only with respect to the components that are free in some instance
    (``active``): fixed intrinsics feed the residual but are never differentiated, which cut the
    exact local Hessian of a Schopp accelerometer factor from about 6500 to about 2400 instructions.
    """

    def __init__(self, fn: ca.Function, order: np.ndarray, n_cal: int, active: np.ndarray, hessian: str, jit: bool):
        nz, nd = fn.size1_in(0), fn.size1_in(1)
        zc, zs, d = ca.SX.sym("zc", n_cal), ca.SX.sym("zs", nz - n_cal), ca.SX.sym("d", nd)
        z = ca.vertcat(zc, zs)  # the block's inputs in its (reordered) w_idx order
        r = fn(z[np.argsort(order).tolist()], d)
        self.act = act = np.flatnonzero(active)
        za = ca.vertcat(*[z[int(i)] for i in act]) if len(act) else ca.SX(0, 1)
        J = ca.jacobian(r, za)
        # exact: the Hessian of 1/2 |r|^2 = J^T J + sum_i r_i Hess(r_i); Gauss-Newton leaves out the sum
        H = ca.hessian(0.5 * ca.sumsqr(r), za)[0] if hessian == "exact" else ca.mtimes(J.T, J)
        sp_H = H.sparsity()
        # entries (a <= b), as indices into z, that are structurally nonzero
        self.pairs = [(int(act[a]), int(act[b])) for b in range(len(act)) for a in range(b + 1) if sp_H.has_nz(a, b)]
        loc = {int(i): k for k, i in enumerate(act)}
        args = [zc, zs, d]
        self.hess = ca.Function(f"{fn.name()}_hess", args, [ca.vertcat(*[H[loc[a], loc[b]] for a, b in self.pairs])
                                                            if self.pairs else ca.SX(0, 1)])
        self.jac = ca.Function(f"{fn.name()}_jac", args, [ca.densify(J)])
        self.grad = ca.Function(f"{fn.name()}_grad", args, [ca.densify(ca.mtimes(J.T, r))])
        self.res = ca.Function(f"{fn.name()}_res", args, [r])
        if jit:
            local = (self.res, self.jac, self.grad, self.hess)
            self.res, self.jac, self.grad, self.hess = compile_functions(list(local[1:]), [self.res]) or local
        self.nz, self.nd, self.m, self.n_cal = nz, nd, fn.size1_out(0), n_cal


class _Block:
    """A factor block bound to the layout: its index matrix into w and its compiled functions.

    ``w_idx`` (N, nz) gives each instance's inputs as positions in w; a staged block's columns
    are reordered (``order``), calibration components first."""

    def __init__(self, block: FactorBlock, layout: Layout):
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
        self.order = np.arange(nz)
        self.n_x = layout.n_x

    def reorder(self, order: np.ndarray):
        self.w_idx, self.order = self.w_idx[:, order], self.order[order]

    def compile(self, cache: dict, n_cal: int, hessian: str, jit: bool):
        active = (self.w_idx < self.n_x).any(axis=0)
        key = (id(self.block.residual), self.order.tobytes(), n_cal, active.tobytes())
        if key not in cache:
            cache[key] = _Compiled(self.block.residual, self.order, n_cal, active, hessian, jit)
        self.f = cache[key]


class _NotStaged(Exception):
    """A block touches stage variables without the stage structure."""


class _StagedBlock:
    """How the instances of one block map to stages: instance t = j K + k belongs to stage
    ``base + j`` (plus the offset ``rel`` of each input component, 0 or 1) and sees the same
    variables of it for every k; which calibration variables it sees depends on k only.
    Raises LookupError for a block without stage variables, _NotStaged for one that has them
    without this structure."""

    def __init__(self, b: _Block, st: "_Stages"):
        n = len(st.stage_of)
        W = b.w_idx
        free = W < n
        stg = np.where(free, st.stage_of[np.where(free, W, 0)], -1)
        is_st = (stg >= 0).any(axis=0)
        if not is_st.any():
            raise LookupError
        if not (stg[:, is_st] >= 0).all():
            raise _NotStaged
        N = W.shape[0]
        base = stg[:, is_st].min(axis=1)
        K = int(np.count_nonzero(base == base[0]))
        if N % K or not np.array_equal(base, base[0] + np.arange(N) // K):
            raise _NotStaged
        rel = np.where(is_st, stg - base[:, None], -1)
        q = np.where(is_st, st.within[np.where(free, W, 0)], W)  # stage position, or w index
        J = N // K
        if not ((rel.reshape(J, K, -1) == rel[:K]).all() and (q.reshape(J, K, -1) == q[:K]).all()) \
                or rel.max() > 1 or not np.where(is_st, q[:K] == q[0], True).all():
            raise _NotStaged
        self.K, self.J, self.base = K, J, int(base[0])
        self.rel, self.q, self.is_st = rel[:K], q[:K], is_st
        self.n_cal = int((~is_st).sum())
        # calibration components first, then the stage components by offset and position
        self.order = np.lexsort((q[0], rel[0], is_st))

    def zs(self, Xp: ca.MX, offset: int, R: int) -> ca.MX:
        """The stage components (n_s, R) of the instance groups j = s - offset ... for s = 0..R-1,
        from the stage values padded by one column on either side."""
        a, out, nz = self.n_cal, [], len(self.is_st)
        while a < nz:
            e = a + 1
            while e < nz and self.rel[0, e] == self.rel[0, a]:
                e += 1
            s0 = 1 + self.base + int(self.rel[0, a]) - offset
            out.append(Xp[self.q[0, a:e].tolist(), s0: s0 + R])
            a = e
        return ca.vertcat(*out)


class _Stages:
    """The stage structure that makes assembly linear in the number of samples.

    Stages are the rows of the nuisance matrix groups with the most free variables (the motion
    states of each sample). Inside the NLP the decision vector is ordered [calibration variables
    (everything else) | stage 0 | stage 1 | ...], each stage holding its row of every stage group.
    A block is *staged* when its instances come in runs of K per stage (t = j K + k: sample j,
    triad k) and each touches its stage and possibly the next (:class:`_StagedBlock`). Its local
    functions are mapped over the instances, the K calibration inputs tiled over the stages and
    each stage's variables spread over its K instances, each by one sparse product (CasADi's
    ``repmat`` and ``reduce_in`` make one node per copy, which grew superlinearly).

    The upper-triangular Hessian's columns of stage s then have the same pattern for every s: rows
    of calibration variables, of stage s-1 and of stage s (the first stage lacks s-1). One function
    per stage computes their nonzeros from the local Hessians of every instance that touches them,
    through a small constant sparse matrix per block and offset (sums over the instances that share
    an entry, such as a sample's motion block seen by every triad, included); mapped over the
    stages, its output matrix *is* the stage columns' nonzero vector, and their sparsity is built
    from Kronecker products. Nothing of the size of the Hessian crosses from Python to CasADi. The
    calibration x calibration entries are a second output of the same map, summed over the stages
    by a product with ones, and assembled with the priors and constraints like any other block's.
    The gradient is assembled the same way from the local gradients (:meth:`Solver._gradient`).
    """

    def __init__(self, lay: Layout, groups):
        n = lay.n_x
        self.R = groups[0].rows
        self.X = np.hstack([lay.w_index(g.name)[:, g.free[0]] for g in groups])  # (R, m) x indices of each stage
        self.m = self.X.shape[1]
        in_stage = np.zeros(n, bool)
        in_stage[self.X.ravel()] = True
        glob = np.flatnonzero(~in_stage)
        self.c = len(glob)
        self.perm = np.concatenate([glob, self.X.ravel()])  # NLP order -> layout index
        self.stage_of = np.full(n, -1)
        self.stage_of[self.X] = np.arange(self.R)[:, None]
        self.within = np.full(n, -1)
        self.within[self.X] = np.arange(self.m)[None, :]
        self.scale = lay.x_scale[self.X[0]]

    @staticmethod
    def find(lay: Layout, blocks: list[_Block]) -> tuple["_Stages | None", dict]:
        """The stage structure and the staged blocks {block index: _StagedBlock} (reordering
        their inputs), or (None, {}) if the problem has none or a block touches stage variables
        otherwise."""
        by_rows: dict = {}
        for g in lay.groups:
            if g.matrix and g.nuisance and g.free.any():
                by_rows.setdefault(g.rows, []).append(g)
        if not by_rows:
            return None, {}
        groups = max(by_rows.values(), key=lambda gs: sum(int(g.free.sum()) for g in gs))
        for g in groups:  # uniform rows, no priors or constraints on them
            f = g.free[0]
            if g.rows < 2 or not (g.free == f).all() or g.unit_norm or np.isfinite(g.prior_std[g.free]).any() \
                    or not (g.scale[:, f] == g.scale[0, f]).all():
                return None, {}
        st = _Stages(lay, groups)
        staged = {}
        for i, b in enumerate(blocks):
            try:
                sb = _StagedBlock(b, st)
            except LookupError:
                continue
            except _NotStaged:
                for b2 in blocks:
                    b2.reorder(np.argsort(b2.order))
                return None, {}
            b.reorder(sb.order)
            staged[i] = _StagedBlock(b, st)
        return st, staged

    def values(self, x: ca.MX) -> ca.MX:
        """The stage variables in physical units (m, R), padded by a copy of the first and last
        stage on either side (instances beyond the ends are evaluated there and weighted zero)."""
        Xs = ca.mtimes(ca.diag(ca.DM(self.scale)), ca.reshape(x[self.c:], self.m, self.R))
        return ca.horzcat(Xs[:, 0], Xs, Xs[:, self.R - 1])


class Solver:
    """IPOPT on a :class:`LeastSquaresProblem`, built once and solved for any data or fixed values.

    Public methods take and return x in the layout's order; inside the NLP the variables may be
    ordered by stage (:class:`_Stages`)."""

    def __init__(self, problem: LeastSquaresProblem, options: SolverOptions = SolverOptions()):
        t0 = time.perf_counter()
        self.problem, self.options = problem, options
        lay = problem.layout
        self.n_x = n = lay.n_x
        self.blocks = [_Block(b, lay) for b in problem.blocks if b.n]
        self._stages, self._staged = st, staged = _Stages.find(lay, self.blocks)
        cache: dict = {}
        for i, b in enumerate(self.blocks):
            b.compile(cache, staged[i].n_cal if i in staged else b.w_idx.shape[1], options.hessian, options.jit)
        self._perm = st.perm if st else np.arange(n)  # NLP order -> layout index
        x = ca.MX.sym("x", n)  # in NLP order
        p = self._p_sym = ca.MX.sym("p", lay.n_p + problem.data.size)
        scale = lay.x_scale
        w = ca.vertcat((x[np.argsort(self._perm).tolist()] if st else x) * scale, p[: lay.n_p])
        Xp = st.values(x) if st else None

        # residuals and local Jacobians: each block's functions mapped over its instances
        residuals, jacobians, gradients, keep, off = [], [], [], [], lay.n_p
        for i, b in enumerate(self.blocks):
            N, f = b.block.n, b.f
            b.data_offset = off
            b.D = ca.reshape(p[off: off + f.nd * N], f.nd, N)
            off += f.nd * N
            if i in staged:
                sb = staged[i]
                b.Zc = ca.reshape(w[sb.q[:, : f.n_cal].ravel().tolist()], f.n_cal, sb.K)
                args = (_tile(b.Zc, sb.J), _spread(sb.zs(Xp, 0, sb.J), sb.K), b.D)
            else:
                args = (ca.reshape(w[b.w_idx.ravel().tolist()], f.nz, N), ca.MX(0, N), b.D)
            mapped = [g.map(N) for g in (f.res, f.jac, f.grad)]
            residuals.append(mapped[0](*args))
            jacobians.append(mapped[1](*args))
            gradients.append(mapped[2](*args))
            keep.append(np.repeat(np.ones(N, bool) if b.block.valid is None else b.block.valid, f.m))
            b.args = args
        pi, pm, ps = lay.priors()
        self._prior = (pi, pm, ps)
        # residuals of instances that are not valid (masked data) are exactly zero and not reported
        self._keep = np.concatenate(keep + [np.ones(len(pi), bool)])
        self.n_data_residuals = int(self._keep.sum()) - len(pi)
        self.n_residuals = int(self._keep.sum())
        prior_r = (w[pi.tolist()] - pm) / ps if len(pi) else ca.MX(0, 1)
        r_data = ca.vertcat(*[ca.vec(r) for r in residuals]) if residuals else ca.MX(0, 1)
        r_all = ca.vertcat(r_data, prior_r)
        f_obj = 0.5 * ca.sumsqr(r_all)
        grad_f = ca.Function("nlp_grad_f", [x, p], [f_obj, self._gradient(scale, prior_r, gradients)],
                             ["x", "p"], ["f", "grad"])

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
        sparsity, H_nz = self._hessian(scale, pi, ps, Xp, lam_f, lam_g)
        hess_lag = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [ca.MX(sparsity, H_nz)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        # the derivative functions are given, so that CasADi never differentiates (or propagates
        # sparsity through) the whole residual graph, which grows quadratically with its size
        jac_g = ca.Function("nlp_jac_g", [x, p], [c, ca.jacobian(c, x)], ["x", "p"], ["g", "jac_g_x"])
        # (the objective as an opaque call: nlpsol's analysis of an inlined f took 5 s at 5000 x 32)
        f_call = ca.Function("objective", [x, p], [f_obj], {"never_inline": True})(x, p)
        nlp = {"x": x, "p": p, "f": f_call, "g": c}
        self.nlp = ca.nlpsol("castimate", "ipopt", nlp, {**options.ipopt(), "hess_lag": hess_lag, "grad_f": grad_f,
                                                         "jac_g": jac_g})
        self._res = ca.Function("data_residual", [x, p], [r_data])
        self._res_all = ca.Function("residual", [x, p], [r_all])
        self._jac = ca.Function("local_jacobians", [x, p], jacobians)
        nuisance = np.zeros(n, bool)
        for g in lay.groups:
            if g.nuisance:
                nuisance[lay.x_indices(g.name)] = True
        self.theta = np.flatnonzero(~nuisance)  # reported parameters: their covariance is computed
        self.build_s = time.perf_counter() - t0

    def _gradient(self, scale, prior_r, gradients) -> ca.MX:
        """Gradient of 1/2 |r|^2 in NLP order, J^T r assembled like the Hessian from the local
        gradients (na, N) (local Jacobian times residual of each instance): a sparse matrix maps those of
        unstaged blocks, staged blocks' calibration entries summed over stages and the priors'
        to the calibration variables; staged blocks' stage entries are summed over the K
        instances of a stage by one small product per stage offset."""
        n, st = self.n_x, self._stages
        ipos = np.empty(n, int)
        ipos[self._perm] = np.arange(n)
        c = st.c if st else n
        rows, src, val, sources, stage = [], [], [], [], 0
        col0 = 0
        for i, (b, g) in enumerate(zip(self.blocks, gradients)):
            na = len(b.f.act)
            if not na:
                continue
            g = ca.vec(g)  # local gradient of instance t at t na + a
            sb = self._staged.get(i)
            W = b.w_idx[:, b.f.act] if sb is None else b.w_idx[: sb.K, b.f.act]
            glob = W < n if sb is None else (W < n) & ~sb.is_st[b.f.act][None, :]
            t, a = np.nonzero(glob)
            rows.append(ipos[W[t, a]]), val.append(scale[W[t, a]])
            if sb is None:
                sources.append(g)
                src.append(col0 + t * na + a)
                col0 += W.shape[0] * na
                continue
            G = ca.reshape(g, na * sb.K, sb.J)
            sources.append(ca.mtimes(G[(t * na + a).tolist(), :], ca.DM.ones(sb.J)))
            src.append(col0 + np.arange(len(t)))
            col0 += len(t)
            act_st = np.flatnonzero(sb.is_st[b.f.act])
            for rel in np.unique(sb.rel[0, b.f.act[act_st]]):
                sel = act_st[sb.rel[0, b.f.act[act_st]] == rel]
                k, a = np.repeat(np.arange(sb.K), len(sel)), np.tile(sel, sb.K)
                q = sb.q[0, b.f.act[a]]
                S = sp.csc_matrix((st.scale[q], (q, k * na + a)), shape=(st.m, na * sb.K))
                s0 = sb.base + int(rel)
                stage = stage + ca.horzcat(ca.MX(st.m, s0), ca.mtimes(_dm(S), G), ca.MX(st.m, st.R - s0 - sb.J))
        pi, _, ps = self._prior
        rows.append(ipos[pi]), val.append(scale[pi] / ps), src.append(col0 + np.arange(len(pi)))
        sources.append(prior_r)
        A = sp.csc_matrix((np.concatenate(val), (np.concatenate(rows), np.concatenate(src))), shape=(c, col0 + len(pi)))
        grad = ca.mtimes(_dm(A), ca.vertcat(*sources))
        return ca.vertcat(grad, ca.vec(ca.densify(stage))) if st else grad

    def _hessian(self, scale, pi, ps, Xp, lam_f, lam_g) -> tuple[ca.Sparsity, ca.MX]:
        """Sparsity and nonzeros of the upper-triangular Hessian of the Lagrangian (NLP order).

        Calibration columns: a constant sparse matrix A maps local Hessian entries (every instance
        of an unstaged block; for a staged block, its entries summed over stages) and the priors'
        curvature to the nonzeros, with the chain rule of the x scaling; B adds the unit-norm
        constraints' curvature times their multipliers. Stage columns: see :class:`_Stages`.
        """
        n, st = self.n_x, self._stages
        ipos = np.empty(n, int)
        ipos[self._perm] = np.arange(n)  # layout index -> NLP index
        sx = scale[self._perm]  # scale in NLP order
        c = st.c if st else n
        rows, cols, src, val, sources, stage = [], [], [], [], [], []
        col0 = 0
        for i, b in enumerate(self.blocks):
            if not b.f.pairs:
                continue
            P = len(b.f.pairs)
            a_idx = np.array([a for a, _ in b.f.pairs])
            b_idx = np.array([bb for _, bb in b.f.pairs])
            sb = self._staged.get(i)
            W = b.w_idx if sb is None else b.w_idx[: sb.K]
            gi, gj = W[:, a_idx], W[:, b_idx]  # (instances, pairs) positions in w
            both = (gi < n) & (gj < n)
            if sb is None:
                sources.append(ca.vec(b.f.hess.map(b.block.n)(*b.args)))  # entry p of instance t at t * P + p
            else:
                sources.append(i)  # placeholder: the staged block's entries summed over stages, k * P + p
                stage.append(self._stage_entries(i, sb, a_idx, b_idx, ipos, sx))
                both &= ~sb.is_st[a_idx][None, :] & ~sb.is_st[b_idx][None, :]
            k = np.nonzero(both)
            ii, jj = ipos[gi[k]], ipos[gj[k]]
            rows.append(np.minimum(ii, jj))
            cols.append(np.maximum(ii, jj))
            v = sx[ii] * sx[jj]
            v[(ii == jj) & (a_idx[k[1]] != b_idx[k[1]])] *= 2  # both (a,b) and (b,a) land on the diagonal
            val.append(v)
            if sb is None:
                src.append(col0 + k[0] * P + k[1])
                col0 += W.shape[0] * P
            else:  # the staged block's sums over stages are of these entries only
                stage[-1]["global"] = k[0] * P + k[1]
                src.append(col0 + np.arange(len(k[0])))
                col0 += len(k[0])
        if st:
            stage_sp, V, sums = self._stage_columns(stage, Xp)
            sources = [sums[s] if isinstance(s, int) else s for s in sources]
        # priors: d^2/dx^2 of 1/2 ((x s - m) / std)^2 = (s / std)^2
        pin = ipos[pi]
        rows.append(pin), cols.append(pin), src.append(col0 + np.arange(len(pi))), val.append((sx[pin] / ps) ** 2)
        sources.append(ca.DM.ones(len(pi)))
        # unit-norm constraints: d^2/dx^2 of |x s|^2 - 1 = 2 s^2 on the free components
        crow, ccol, cval = [], [], []
        for j, row in enumerate(self._unit[self._c_perm]):
            f = ipos[row[(row >= 0) & (row < n)]]
            crow.append(f), ccol.append(np.full(len(f), j)), cval.append(2 * sx[f] ** 2)
        R, C = np.concatenate(rows + crow), np.concatenate(cols + crow)
        pattern = sp.coo_matrix((np.ones(len(R)), (R, C)), shape=(c, c)).tocsc()
        pattern.sum_duplicates()
        pattern.sort_indices()
        pos = sp.csc_matrix((np.arange(pattern.nnz) + 1.0, pattern.indices, pattern.indptr), shape=(c, c))

        def nz_of(r, cc):
            if not len(r):  # scipy returns a sparse matrix, not an array, for empty fancy indices
                return np.zeros(0, int)
            return np.asarray(pos[r, cc]).ravel().astype(int) - 1

        r_all, c_all = np.concatenate(rows), np.concatenate(cols)
        A = sp.csc_matrix((np.concatenate(val), (nz_of(r_all, c_all), np.concatenate(src))),
                          shape=(pattern.nnz, col0 + len(pi)))
        H_nz = lam_f * ca.mtimes(_dm(A), ca.vertcat(*sources))
        if crow:
            cr = np.concatenate(crow)
            H_nz += ca.mtimes(_dm(sp.csc_matrix((np.concatenate(cval), (nz_of(cr, cr), np.concatenate(ccol))),
                                                shape=(pattern.nnz, self.n_constraints))), lam_g)
        sparsity = ca.Sparsity(c, c, pattern.indptr.tolist(), pattern.indices.tolist())
        if st is None:
            return sparsity, H_nz
        sparsity = ca.vertcat(ca.horzcat(sparsity, stage_sp[0]), ca.horzcat(ca.Sparsity(st.R * st.m, c), stage_sp[1]))
        return sparsity, ca.vertcat(H_nz, lam_f * V)

    def _stage_entries(self, i, sb: _StagedBlock, a_idx, b_idx, ipos, sx) -> dict:
        """The stage-column entries of one staged block's local Hessian pairs, for one stage:
        kind (0: calibration row, 1: previous stage's row, 2: own stage's row), row (NLP index or
        stage position), column (stage position), shift (the stage of instance group j is
        j + shift), source k P + p and value factor (chain rule of the scaling)."""
        st, n = self._stages, self.n_x
        K, P = sb.K, len(a_idx)
        kk = np.repeat(np.arange(K), P)
        a, b = np.tile(a_idx, K), np.tile(b_idx, K)
        sa, sbb = sb.is_st[a], sb.is_st[b]
        keep = (sa | sbb) & np.where(sa, True, sb.q[kk, a] < n) & np.where(sbb, True, sb.q[kk, b] < n)
        kk, a, b, sa, sbb = kk[keep], a[keep], b[keep], sa[keep], sbb[keep]
        src = kk * P + np.tile(np.arange(P), K)[keep]

        def virtual(comp, s):  # position in NLP order relative to stage j (stage comps after all others)
            return np.where(s, st.c + sb.rel[kk, comp] * st.m + sb.q[kk, comp], ipos[np.where(s, 0, sb.q[kk, comp])])

        va, vb = virtual(a, sa), virtual(b, sbb)
        swap = va > vb
        col, row = np.where(swap, a, b), np.where(swap, b, a)
        s_row = np.where(swap, sbb, sa)
        rel_c, q_c = sb.rel[kk, col], sb.q[kk, col]
        d = np.where(s_row, sb.rel[kk, row] - rel_c, 0)
        kind = np.where(s_row, np.where(d < 0, 1, 2), 0)
        r = np.where(s_row, sb.q[kk, row], ipos[np.where(s_row, 0, sb.q[kk, row])])
        v = np.where(s_row, st.scale[np.where(s_row, r, 0)], sx[np.where(s_row, 0, r)]) * st.scale[q_c]
        v[s_row & (va == vb) & (a != b)] *= 2
        return {"block": i, "sb": sb, "P": P, "kind": kind, "row": r, "col": q_c, "shift": sb.base + rel_c,
                "src": src, "val": v}

    def _stage_columns(self, entries: list[dict], Xp):
        """Sparsity of the stage columns ((calibration rows, stage rows)), their nonzeros stage
        after stage, and every staged block's calibration x calibration entries summed over the
        stages ({block index: (K P,) vector})."""
        st = self._stages
        c, m, R = st.c, st.m, st.R
        vrow = np.concatenate([np.where(e["kind"] == 0, e["row"], c + (e["kind"] - 1) * m + e["row"]) for e in entries])
        vcol = np.concatenate([e["col"] for e in entries])
        B = sp.coo_matrix((np.ones(len(vrow)), (vrow, vcol)), shape=(c + 2 * m, m)).tocsc()
        B.sum_duplicates()
        B.sort_indices()
        pos = sp.csc_matrix((np.arange(B.nnz) + 1.0, B.indices, B.indptr), shape=B.shape)

        # one stage: v = sum over staged blocks b and shifts d of S_bd vec(local Hessians of
        # instance group s - d), weighted zero where that group does not exist
        sym_in, call_in, v, sums, off = [], [], 0, {}, 0
        for e in entries:
            i, sb, P = e["block"], e["sb"], e["P"]
            b = self.blocks[i]
            n_e = len(e["kind"])
            nz = np.asarray(pos[vrow[off: off + n_e], vcol[off: off + n_e]]).ravel().astype(int) - 1
            off += n_e
            zc = ca.MX.sym("zc", b.f.n_cal, sb.K)
            sym_in.append(zc), call_in.append(_tile(b.Zc, R))
            Dm = ca.reshape(b.D, b.f.nd * sb.K, sb.J)
            shifts = np.unique(e["shift"]) if len(e["shift"]) else np.array([sb.base])
            for d in shifts:
                d = int(d)
                zs, D, wgt = ca.MX.sym("zs", b.f.nz - b.f.n_cal), ca.MX.sym("d", b.f.nd, sb.K), ca.MX.sym("w")
                sym_in += [zs, D, wgt]
                lo, hi = d, R - d - sb.J  # instance groups missing at either end, padded by the end ones
                Dp = ca.horzcat(*([ca.repmat(Dm[:, 0], 1, lo)] if lo else []), Dm,
                                *([ca.repmat(Dm[:, sb.J - 1], 1, hi)] if hi else []))
                call_in += [sb.zs(Xp, d, R), ca.reshape(Dp, b.f.nd, sb.K * R),
                            ca.DM(((np.arange(R) >= d) & (np.arange(R) < d + sb.J)).astype(float)).T]
                h = ca.vec(b.f.hess.map(sb.K)(zc, ca.repmat(zs, 1, sb.K), D))
                sel = e["shift"] == d
                S = sp.csc_matrix((e["val"][sel], (nz[sel], e["src"][sel])), shape=(B.nnz, sb.K * P))
                v = v + wgt * ca.mtimes(_dm(S), h)
                if d == shifts[0]:
                    sums[i] = wgt * h[e["global"].tolist()]
        order = list(sums)
        out = ca.Function("stage_hessian", sym_in, [ca.densify(v), *[sums[i] for i in order]]).map(R).call(call_in)
        V = out[0]
        sums = {i: ca.mtimes(out[1 + k], ca.DM.ones(R)) for k, i in enumerate(order)}
        first = np.flatnonzero((B.indices < c) | (B.indices >= c + m))  # the first stage has no previous one

        def part(lo, hi):
            M = B[lo:hi].tocsc()
            M.sort_indices()
            return ca.Sparsity(hi - lo, m, M.indptr.tolist(), M.indices.tolist())

        cal = ca.kron(ca.Sparsity.dense(1, R), part(0, c))
        own = ca.kron(ca.Sparsity.diag(R), part(c + m, c + 2 * m)) \
            .unite(ca.kron(ca.Sparsity.band(R, -1), part(c, c + m)))  # own stage; previous stage
        return (cal, own), ca.vertcat(V[first.tolist(), 0], ca.vec(V[:, 1:])), sums


    # -- numeric ---------------------------------------------------------------------------------
    def _p(self, p_fixed, data):
        lay = self.problem.layout
        p_fixed = lay.p0() if p_fixed is None else p_fixed
        data = self.problem.data if data is None else data
        return np.concatenate([np.asarray(p_fixed, float), np.asarray(data, float).ravel()])

    def residuals(self, x, p_fixed=None, data=None) -> np.ndarray:
        """All whitened residuals (data of the valid instances, then priors) at scaled x."""
        return np.asarray(self._res_all(np.asarray(x, float)[self._perm], self._p(p_fixed, data))).ravel()[self._keep]

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
        local = self._jac.call([np.asarray(x, float)[self._perm], p])
        for b, Jb in zip(self.blocks, local):
            N, f = b.block.n, b.f
            na = len(f.act)
            Jl = np.asarray(Jb).reshape(f.m, na, N, order="F")  # instances side by side
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
                          shape=(len(self._keep), n))[np.flatnonzero(self._keep)]
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
        perm = self._perm
        t0 = time.perf_counter()
        sol = self.nlp(x0=x0[perm], p=p, lbx=lbx[perm], ubx=ubx[perm], lbg=0, ubg=0,
                       lam_g0=0 if lam_g0 is None else lam_g0)
        wall = time.perf_counter() - t0
        st = self.nlp.stats()
        x = np.empty(self.n_x)
        x[perm] = np.asarray(sol["x"]).ravel()
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
            residual=np.asarray(self._res(x[perm], p)).ravel()[self._keep[: len(self._keep) - len(self._prior[0])]],
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


def _tile(M: ca.MX, n: int) -> ca.MX:
    """[M M ... M] (n copies) as one sparse product: no node per copy (CasADi's repmat makes one)."""
    return ca.mtimes(M, ca.DM(ca.repmat(ca.Sparsity.diag(M.shape[1]), 1, n), 1.0))


def _spread(M: ca.MX, n: int) -> ca.MX:
    """Every column of M repeated n times in place, as one sparse product."""
    return ca.mtimes(M, ca.DM(ca.kron(ca.Sparsity.diag(M.shape[1]), ca.Sparsity.dense(1, n)), 1.0))


def _dm(M: sp.spmatrix) -> ca.DM:
    """A scipy sparse matrix as a CasADi DM with the same sparsity."""
    M = sp.csc_matrix(M)
    M.sort_indices()
    return ca.DM(ca.Sparsity(M.shape[0], M.shape[1], M.indptr.tolist(), M.indices.tolist()), M.data.tolist())

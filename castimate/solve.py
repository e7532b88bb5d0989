"""The one solve path shared by every kind.

A problem is a weighted nonlinear least-squares problem with equality constraints::

    minimise   1/2 |r(x, p)|^2      r: whitened residuals (factor blocks and priors)
    subject to c(x, p) = 0          unit-norm constraints of quaternions and unit vectors
               lbx <= x <= ubx

The residual is a factor graph: each :class:`FactorBlock` is one small CasADi function of a few
parameter groups and a few data, repeated over its instances. Its local residual, Jacobian,
gradient and Hessian are CasADi functions compiled to C (:mod:`castimate.jit`) and evaluated over
chunks of instances in place on numpy arrays (``Function.map`` through a ``FunctionBuffer``).
IPOPT's objective, gradient and exact sparse Hessian of the Lagrangian are assembled from them in
numpy (:class:`_Assembly`) and handed to ``nlpsol`` as CasADi callbacks that write into CasADi's
own buffers: for blocks of calibration parameters through a constant sparse matrix; for blocks
that touch per-sample motion states stage by stage (:class:`_Stages`). No expression graph grows
with the data, and the data themselves stay in numpy: build time, time per iteration and memory
grow linearly with the number of instances. (Differentiating one monolithic expression graph,
CasADi's default, colours a Hessian with a dense border and grows about quadratically; mapping the
local functions inside one MX graph grew CasADi's work arrays past 6 GB at 32 IMUs x 20 000
samples.) ``Solver.symbolic_nlp`` gives the same problem as one graph, as a reference.

Uncertainty comes from the Fisher information J^T J at the solution, assembled the same way from
the local Jacobians and restricted to the tangent space of the constraints; its inverse's blocks
for the calibration parameters are the marginals with the nuisance variables (the motion)
eliminated stage-blocked.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import platform
import sys
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
            # no MUMPS scaling: x is scaled already, and on a 32 x 20 000 problem computing the
            # scalings took a quarter of the factorisation time
            "ipopt.mumps_scaling": 0,
            "ipopt.mumps_permuting_scaling": 0,
            "print_time": False,
            "record_time": True,
            "calc_lam_p": False,
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


CHUNK = 4096  # instances per call of a local function: bounds the work arrays, not the results


class _Compiled:
    """Local functions of one factor, each evaluated over many instances at once.

    Each takes (z_cal, z_stage, d): the factor's inputs split into the components that are not
    stage variables and those that are (:class:`_Stages`; none for an unstaged block), and its data.
    ``res`` gives the residual, ``jac`` its Jacobian, ``rgh`` the residual, the local gradient J^T r
    and the local Hessian entries ``pairs`` (exact, or J^T J for Gauss-Newton), ``gn`` the entries
    of J^T J (the information). Derivatives are
    taken only with respect to the components that are free in some instance (``active``): fixed
    intrinsics feed the residual but are never differentiated, which cut the exact local Hessian of
    a Schopp accelerometer factor from about 6500 to about 2400 instructions.
    """

    def __init__(self, fn: ca.Function, order: np.ndarray, n_cal: int, active: np.ndarray, hessian: str, jit: bool):
        nz, nd = fn.size1_in(0), fn.size1_in(1)
        zc, zs, d = ca.SX.sym("zc", n_cal), ca.SX.sym("zs", nz - n_cal), ca.SX.sym("d", nd)
        z = ca.vertcat(zc, zs)  # the block's inputs in its (reordered) w_idx order
        r = fn(z[np.argsort(order).tolist()], d)
        self.act = act = np.flatnonzero(active)
        za = ca.vertcat(*[z[int(i)] for i in act]) if len(act) else ca.SX(0, 1)
        J = ca.jacobian(r, za)
        JtJ = ca.mtimes(J.T, J)
        # exact: the Hessian of 1/2 |r|^2 = J^T J + sum_i r_i Hess(r_i); Gauss-Newton leaves out the sum
        H = ca.hessian(0.5 * ca.sumsqr(r), za)[0] if hessian == "exact" else JtJ
        sp_H = H.sparsity().unite(JtJ.sparsity())  # the information J^T J is assembled on the same pattern
        # entries (a <= b), as indices into z, that are structurally nonzero
        self.pairs = np.array([(int(act[a]), int(act[b])) for b in range(len(act)) for a in range(b + 1)
                               if sp_H.has_nz(a, b)], int).reshape(-1, 2)
        loc = np.full(nz, -1)
        loc[act] = np.arange(len(act))

        def entries(M):  # M's values at the pairs
            return ca.densify(ca.vertcat(*[M[int(a), int(b)] for a, b in loc[self.pairs]]) if len(self.pairs)
                              else ca.SX(0, 1))

        args = [zc, zs, d]
        name = fn.name()
        local = [ca.Function(f"{name}_res", args, [r]),
                 ca.Function(f"{name}_jac", args, [ca.densify(J)]),
                 ca.Function(f"{name}_rgh", args, [r, ca.densify(ca.mtimes(J.T, r)), entries(H)]),
                 ca.Function(f"{name}_gn", args, [entries(JtJ)])]
        self.res, self.jac, self.rgh, self.gn = (compile_functions(local) if jit else None) or local
        self.nz, self.nd, self.m, self.n_cal = nz, nd, fn.size1_out(0), n_cal
        self._buffers: dict = {}

    def __call__(self, fn: ca.Function, args: list[np.ndarray], outs: list[np.ndarray]):
        """Evaluate ``fn`` on n instances in place: ``args`` and ``outs`` are C-contiguous (n, size)
        arrays, one row per instance (CasADi's buffers point into them; nothing is copied)."""
        key = (fn.name(), args[0].shape[0])
        if key not in self._buffers:
            self._buffers[key] = fn.map(key[1]).buffer()
        buf, run = self._buffers[key]
        for i, a in enumerate(args):
            buf.set_arg(i, memoryview(a))
        for i, o in enumerate(outs):
            buf.set_res(i, memoryview(o))
        run()


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
        # C order: gathers by rows stay C order; 32 bits: half the memory of the largest index array
        self.w_idx = np.ascontiguousarray(np.hstack(cols), dtype=np.int32 if layout.n_x + layout.n_p < 2**31 else int)
        nz = block.residual.size1_in(0)
        if self.w_idx.shape[1] != nz:
            raise ValueError(f"factor block {block.name}: inputs give {self.w_idx.shape[1]} values, "
                             f"the function takes {nz}")
        self.order = np.arange(nz)
        self.n_x = layout.n_x

    def reorder(self, order: np.ndarray):
        self.w_idx, self.order = np.ascontiguousarray(self.w_idx[:, order]), self.order[order]

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
        stage_of = np.append(st.stage_of, -1)  # w indices of fixed values map to -1
        stg = stage_of[np.where(free, W, n)]
        is_st = (stg >= 0).any(axis=0)
        if not is_st.any():
            raise LookupError
        S = stg[:, is_st]
        if not (S >= 0).all():
            raise _NotStaged
        N = W.shape[0]
        base = S.min(axis=1)
        K = int(np.count_nonzero(base == base[0]))
        J = N // K
        if N % K or not np.array_equal(base, base[0] + np.arange(N) // K):
            raise _NotStaged
        rel = np.where(is_st, stg[:K] - base[:K, None], -1)
        q = np.where(is_st, st.within[np.where(free[:K], W[:K], 0)], W[:K])  # stage position, or w index
        # every stage group sees the same stage positions and offsets and the same calibration inputs
        Wc = W[:, ~is_st].reshape(J, K, -1)
        if not ((S - base[:, None]).reshape(J, K, -1) == rel[:, is_st]).all() or not (Wc == Wc[0]).all() \
                or not (st.within[W[:, is_st]].reshape(J, K, -1) == q[:, is_st]).all() \
                or rel.max() > 1 or not np.where(is_st, q == q[0], True).all():
            raise _NotStaged
        self.K, self.J, self.base = K, J, int(base[0])
        self.rel, self.q, self.is_st = rel, q, is_st
        self.n_cal = int((~is_st).sum())
        # calibration components first, then the stage components by offset and position
        self.order = np.lexsort((q[0], rel[0], is_st))

    def stage_inputs(self, Xs: np.ndarray, j0: int, j1: int) -> np.ndarray:
        """The stage components (j1 - j0, n_s) of instance groups j0 ... j1 - 1, from the stage
        values Xs (R, m) in physical units (inputs after the calibration ones, as ordered)."""
        rel, q = self.rel[0, self.n_cal:], self.q[0, self.n_cal:]
        return Xs[(self.base + j0 + rel)[None, :] + np.arange(j1 - j0)[:, None], q[None, :]]


class _Stages:
    """The stage structure that makes assembly linear in the number of samples.

    Stages are the rows of the nuisance matrix groups with the most free variables (the motion
    states of each sample). Inside the NLP the decision vector is ordered [calibration variables
    (everything else) | stage 0 | stage 1 | ...], each stage holding its row of every stage group.
    A block is *staged* when its instances come in runs of K per stage (t = j K + k: sample j,
    triad k) and each touches its stage and possibly the next (:class:`_StagedBlock`).

    The upper-triangular Hessian's columns of stage s then have the same pattern for every s: rows
    of calibration variables, of stage s-1 and of stage s (the first stage lacks s-1), and the
    local entries of instance group j land on them through one small constant matrix per block
    and stage offset (:class:`_Assembly`).
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
            sb.rel, sb.q = (np.ascontiguousarray(M[:, sb.order]) for M in (sb.rel, sb.q))
            sb.is_st = sb.is_st[sb.order]
            staged[i] = sb
        return st, staged


class _Assembly:
    """Objective, gradient and Hessian of 1/2 |r|^2 (NLP order, scaled x) from the local functions
    of every instance, evaluated in numpy a chunk at a time.

    Calibration entries: a constant sparse matrix maps the local entries that land on calibration
    variables (every instance of an unstaged block; a staged block's, summed over its stage groups)
    and the priors' to their place, with the chain rule of the x scaling. Stage entries: the
    columns of every stage have the same pattern (:class:`_Stages`), so the local entries of one
    stage group land on them through one small constant matrix per block and stage offset, applied
    to the whole chunk at once. Memory is the result plus one chunk of local values, and time is
    linear in the number of instances; no expression graph grows with the data.
    """

    def __init__(self, blocks: list[_Block], layout: Layout, stages: _Stages | None, staged: dict,
                 perm: np.ndarray, unit_rows: np.ndarray, n_constraints: int):
        self.blocks, self.layout, self.st, self.staged = blocks, layout, stages, staged
        self.n = n = layout.n_x
        self.ipos = np.empty(n, int)
        self.ipos[perm] = np.arange(n)  # layout index -> NLP index
        self.scale = layout.x_scale
        self.c = stages.c if stages else n
        self.prior = layout.priors()
        self._gradient_plan()
        self._hessian_plan(unit_rows, n_constraints)
        self._cache, self._stage_buffer = None, None
        self.data = None  # the data vector the NLP's functions see (None: the blocks' own)

    # -- plans -----------------------------------------------------------------------------------
    def _gradient_plan(self):
        n, st, ipos, scale = self.n, self.st, self.ipos, self.scale
        rows, src, val, ncol = [], [], [], 0
        self.g_plan = []
        for i, b in enumerate(self.blocks):
            f, sb = b.f, self.staged.get(i)
            na = len(f.act)
            W = (b.w_idx if sb is None else b.w_idx[: sb.K])[:, f.act]
            glob = W < n if sb is None else (W < n) & ~sb.is_st[f.act][None, :]
            t, a = np.nonzero(glob)
            rows.append(ipos[W[t, a]]), val.append(scale[W[t, a]])
            plan = {"col": ncol, "stage": []}
            if sb is None:
                src.append(ncol + t * na + a)
                ncol += W.shape[0] * na
            else:  # calibration entries summed over stage groups; stage entries by offset
                plan["sel"] = t * na + a
                src.append(ncol + np.arange(len(t)))
                ncol += len(t)
                act_st = np.flatnonzero(sb.is_st[f.act])
                for rel in np.unique(sb.rel[0, f.act[act_st]]):
                    sel = act_st[sb.rel[0, f.act[act_st]] == rel]
                    k, a2 = np.repeat(np.arange(sb.K), len(sel)), np.tile(sel, sb.K)
                    q = sb.q[0, f.act[a2]]
                    S = sp.csr_matrix((st.scale[q], (q, k * na + a2)), shape=(st.m, na * sb.K))
                    plan["stage"].append((sb.base + int(rel), S))
            self.g_plan.append(plan)
        pi, _, ps = self.prior
        rows.append(ipos[pi]), val.append(scale[pi] / ps), src.append(ncol + np.arange(len(pi)))
        self.g_prior_col = ncol
        ncol += len(pi)
        self.A_g = sp.csr_matrix((np.concatenate(val), (np.concatenate(rows), np.concatenate(src))),
                                 shape=(self.c, ncol))

    def _hessian_plan(self, unit_rows, n_constraints):
        n, st, ipos = self.n, self.st, self.ipos
        sx = self.scale[np.argsort(ipos)]  # scale in NLP order
        c = self.c
        rows, cols, src, val, entries, ncol = [], [], [], [], [], 0
        self.h_plan = []
        for i, b in enumerate(self.blocks):
            f, sb = b.f, self.staged.get(i)
            P = len(f.pairs)
            plan = {"col": ncol}
            self.h_plan.append(plan)
            if not P:
                continue
            a_idx, b_idx = f.pairs[:, 0], f.pairs[:, 1]
            W = b.w_idx if sb is None else b.w_idx[: sb.K]
            gi, gj = W[:, a_idx], W[:, b_idx]  # (instances, pairs) positions in w
            both = (gi < n) & (gj < n)
            if sb is not None:
                entries.append(self._stage_entries(i, sb, a_idx, b_idx, sx))
                both &= ~sb.is_st[a_idx][None, :] & ~sb.is_st[b_idx][None, :]
            k = np.nonzero(both)
            ii, jj = ipos[gi[k]], ipos[gj[k]]
            rows.append(np.minimum(ii, jj))
            cols.append(np.maximum(ii, jj))
            v = sx[ii] * sx[jj]
            v[(ii == jj) & (a_idx[k[1]] != b_idx[k[1]])] *= 2  # both (a,b) and (b,a) land on the diagonal
            val.append(v)
            if sb is None:
                src.append(ncol + k[0] * P + k[1])
                ncol += W.shape[0] * P
            else:  # summed over stage groups: the entries of one stage group, k P + p
                plan["sel"] = k[0] * P + k[1]
                src.append(ncol + np.arange(len(k[0])))
                ncol += len(k[0])
        # priors: d^2/dx^2 of 1/2 ((x s - m) / std)^2 = (s / std)^2
        pi, _, ps = self.prior
        pin = ipos[pi]
        rows.append(pin), cols.append(pin), src.append(ncol + np.arange(len(pi))), val.append((sx[pin] / ps) ** 2)
        self.h_prior_col = ncol
        ncol += len(pi)
        # unit-norm constraints (in CasADi's order): d^2/dx^2 of |x s|^2 - 1 = 2 s^2 on the free components
        crow, ccol, cval = [], [], []
        for j, row in enumerate(unit_rows):
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

        self.A_h = sp.csr_matrix((np.concatenate(val), (nz_of(np.concatenate(rows), np.concatenate(cols)),
                                                        np.concatenate(src))), shape=(pattern.nnz, ncol))
        cr = np.concatenate(crow) if crow else np.zeros(0, int)
        self.C_h = sp.csr_matrix((np.concatenate(cval) if cval else np.zeros(0), (nz_of(cr, cr),
                                  np.concatenate(ccol) if ccol else np.zeros(0, int))),
                                 shape=(pattern.nnz, n_constraints))
        self.n_cal_nz = pattern.nnz
        self._cal_pattern = pattern
        if st:
            self._stage_columns(entries)
        indices, indptr = self.pattern()
        self.sparsity = ca.Sparsity(n, n, indptr.tolist(), indices.tolist())
        self.nnz = len(indices)

    def _stage_entries(self, i, sb: _StagedBlock, a_idx, b_idx, sx) -> dict:
        """The stage-column entries of one staged block's local Hessian pairs, for one stage group:
        kind (0: calibration row, 1: previous stage's row, 2: own stage's row), row (NLP index or
        stage position), column (stage position), shift (the stage of instance group j is
        j + shift), source k P + p and value factor (chain rule of the scaling)."""
        st, n, ipos = self.st, self.n, self.ipos
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

    def _stage_columns(self, entries: list[dict]):
        """The pattern B of one stage's columns (rows: calibration, previous stage, own stage) and
        the matrices from local entries to its nonzeros."""
        st = self.st
        c, m = st.c, st.m
        vrow = np.concatenate([np.where(e["kind"] == 0, e["row"], c + (e["kind"] - 1) * m + e["row"]) for e in entries])
        vcol = np.concatenate([e["col"] for e in entries])
        B = sp.coo_matrix((np.ones(len(vrow)), (vrow, vcol)), shape=(c + 2 * m, m)).tocsc()
        B.sum_duplicates()
        B.sort_indices()
        pos = sp.csc_matrix((np.arange(B.nnz) + 1.0, B.indices, B.indptr), shape=B.shape)
        off = 0
        for e in entries:
            n_e = len(e["kind"])
            nz = np.asarray(pos[vrow[off: off + n_e], vcol[off: off + n_e]]).ravel().astype(int) - 1
            off += n_e
            plan, K = self.h_plan[e["block"]], e["sb"].K
            plan["stage"] = [(int(d), sp.csr_matrix((e["val"][sel], (nz[sel], e["src"][sel])), shape=(B.nnz, K * e["P"])))
                             for d in np.unique(e["shift"]) for sel in [e["shift"] == d]]
        self.n_stage_nz = B.nnz
        self.first = np.flatnonzero((B.indices < c) | (B.indices >= c + m))  # the first stage has no previous one
        self._B = B

    def pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """The upper-triangular Hessian's pattern in NLP order as CSC (indices, indptr): the
        calibration columns, then stage s's columns with B's rows, shifted by (s - 1) m where
        they are stage rows (stage 0 without the previous stage's)."""
        P = self._cal_pattern
        indices, indptr = [P.indices], [P.indptr]
        if self.st:
            B, c, m, R = self._B, self.st.c, self.st.m, self.st.R
            Bi, counts = B.indices.astype(np.int32), np.diff(B.indptr)
            shift = np.where(Bi >= c, m, 0).astype(np.int32)
            counts0 = np.bincount(np.repeat(np.arange(m), counts)[self.first], minlength=m)
            rest = np.multiply(np.arange(R - 1, dtype=np.int32)[:, None], shift[None, :])  # 32 bits: half the traffic
            rest += Bi[None, :]
            indices += [(Bi - shift)[self.first], rest.ravel()]
            indptr.append(P.nnz + np.cumsum(np.concatenate([counts0, np.tile(counts, R - 1)])))
        return np.concatenate(indices), np.concatenate(indptr)

    def csc(self, values: np.ndarray) -> sp.csc_matrix:
        """The upper-triangular Hessian nonzeros ``values`` as a scipy matrix (NLP order)."""
        return sp.csc_matrix((values, *self.pattern()), shape=(self.n, self.n))

    def information_blocks(self, parts) -> tuple[sp.csc_matrix, np.ndarray | None, sp.csc_matrix | None]:
        """The symmetric matrix of assembled Hessian parts in three blocks (NLP order):
        calibration x calibration (sparse), calibration x stages (dense, (c, R m); the motion of
        every sample couples to every position) and stages x stages (sparse, block tridiagonal)."""
        H_cal, VT = parts
        c = self.c
        P = self._cal_pattern
        U = sp.csc_matrix((H_cal, P.indices, P.indptr), shape=(c, c))
        F_cc = (U + U.T - sp.diags(U.diagonal())).tocsc()
        if VT is None:
            return F_cc, None, None
        m, R, B = self.st.m, self.st.R, self._B
        Bi, col = B.indices, np.repeat(np.arange(m), np.diff(B.indptr))
        stages = np.arange(R)[:, None]
        cal = Bi < c
        F_cs = np.zeros((c, R * m))
        F3 = F_cs.reshape(c, R, m)
        for e in np.flatnonzero(cal):  # one strided copy per entry of the pattern: no (R, entries) index arrays
            F3[Bi[e], :, col[e]] = VT[:, e]
        own, prev = Bi >= c + m, (Bi >= c) & (Bi < c + m)
        rows = [(stages * m + (Bi[own] - c - m)).ravel(), (stages[1:] - 1) * m + (Bi[prev] - c)]
        cols = [(stages * m + col[own]).ravel(), stages[1:] * m + col[prev]]
        U = sp.coo_matrix((np.concatenate([VT[:, own].ravel(), VT[1:, prev].ravel()]),
                           (np.concatenate([rows[0], rows[1].ravel()]), np.concatenate([cols[0], cols[1].ravel()]))),
                          shape=(R * m, R * m)).tocsc()
        return F_cc, F_cs, (U + U.T - sp.diags(U.diagonal())).tocsc()

    # -- evaluation ------------------------------------------------------------------------------
    def _chunks(self, i: int, w: np.ndarray, Xs, D: np.ndarray):
        """(t0, t1, j0, j1, [z_cal, z_stage, d]) for the instances t0 ... t1 - 1 of block i, CHUNK
        at a time (whole stage groups j0 ... j1 - 1 for a staged block)."""
        b, sb = self.blocks[i], self.staged.get(i)
        N = b.block.n
        if sb is None:
            for t0 in range(0, N, CHUNK):
                t1 = min(N, t0 + CHUNK)
                yield t0, t1, None, None, [w[b.w_idx[t0:t1]], np.empty((t1 - t0, 0)), D[t0:t1]]
            return
        K = sb.K
        Zc = w[sb.q[:, : sb.n_cal]]
        step = max(1, CHUNK // K)
        for j0 in range(0, sb.J, step):
            j1 = min(sb.J, j0 + step)
            yield j0 * K, j1 * K, j0, j1, [np.tile(Zc, (j1 - j0, 1)), np.repeat(sb.stage_inputs(Xs, j0, j1), K, axis=0),
                                           D[j0 * K: j1 * K]]

    def _inputs(self, x: np.ndarray, pf: np.ndarray):
        """w (layout order, physical units, then the fixed values) and the stage values (R, m)."""
        w = np.concatenate([x[self.ipos] * self.scale, pf])
        Xs = (x[self.c:].reshape(self.st.R, self.st.m) * self.st.scale) if self.st else None
        return w, Xs

    def _data(self, i: int, data: np.ndarray | None) -> np.ndarray:
        """Block i's (N, nd) data: from the data vector, or (None) the block's own array."""
        b = self.blocks[i]
        if data is None:
            return b.data
        return data[b.data_offset: b.data_offset + b.block.n * b.f.nd].reshape(b.block.n, b.f.nd)

    def local(self, x, pf, data, which: str) -> list[np.ndarray]:
        """One local function (``res`` or ``jac``) of every block over all instances: (N, size)."""
        w, Xs = self._inputs(x, pf)
        out = []
        for i, b in enumerate(self.blocks):
            fn = getattr(b.f, which)
            R = np.empty((b.block.n, fn.size1_out(0) * fn.size2_out(0)))
            for t0, t1, _, _, args in self._chunks(i, w, Xs, self._data(i, data)):
                b.f(fn, args, [R[t0:t1]])
            out.append(R)
        return out

    def prior_residual(self, w):
        pi, pm, ps = self.prior
        return (w[pi] - pm) / ps

    def residuals(self, x, pf, data) -> np.ndarray:
        """Every whitened residual at x: each block's, instance by instance, then the priors'."""
        r = self.local(x, pf, data, "res")
        return np.concatenate([a.ravel() for a in r] + [self.prior_residual(self._inputs(x, pf)[0])])

    def assemble(self, x, pf, data, information: bool = False):
        """(f, gradient, Hessian) of 1/2 |r|^2 at x; with ``information`` only the Hessian, of
        J^T J (the Fisher information), from the local Jacobians. The Hessian comes in parts
        (calibration nonzeros, stage columns (R, n_stage_nz)) for :meth:`hessian_values`; the
        stage columns are one buffer that the next call overwrites (reusing it saves touching
        fresh pages, a sixth of the time at 32 x 20 000, and its size in memory)."""
        st = self.st
        w, Xs = self._inputs(x, pf)
        s_g, s_h = np.zeros(self.A_g.shape[1]), np.zeros(self.A_h.shape[1])
        GS = np.zeros((st.R, st.m)) if st else None
        VT = None
        if st:
            if self._stage_buffer is None:
                self._stage_buffer = np.empty((st.R, self.n_stage_nz))
            VT = self._stage_buffer
            VT.fill(0.0)
            self._cache = None  # its Hessian is in this buffer
        f_val = 0.0
        for i, b in enumerate(self.blocks):
            f, gp, hp = b.f, self.g_plan[i], self.h_plan[i]
            na, P, m = len(f.act), len(f.pairs), f.m
            sb = self.staged.get(i)
            for t0, t1, j0, j1, args in self._chunks(i, w, Xs, self._data(i, data)):
                nI = t1 - t0
                h = np.empty((nI, P))
                if information:
                    f(f.gn, args, [h])
                else:
                    r, g = np.empty((nI, m)), np.empty((nI, na))
                    f(f.rgh, args, [r, g, h])
                    f_val += 0.5 * float(np.einsum("ij,ij->", r, r))
                    _scatter(gp, sb, g, t0, t1, j0, j1, s_g, GS)
                _scatter(hp, sb, h, t0, t1, j0, j1, s_h, VT)
        pr = self.prior_residual(w)
        f_val += 0.5 * float(pr @ pr)
        s_g[self.g_prior_col:] = pr
        s_h[self.h_prior_col:] = 1.0
        H = (self.A_h @ s_h, VT)
        if information:
            return H
        grad = self.A_g @ s_g
        return f_val, (np.concatenate([grad, GS.ravel()]) if st else grad), H

    def hessian_values(self, parts, factor: float = 1.0, out: np.ndarray | None = None) -> np.ndarray:
        """The Hessian nonzeros in the sparsity's order, times ``factor``, from assembled parts."""
        H_cal, VT = parts
        out = np.empty(self.nnz) if out is None else out
        np.multiply(H_cal, factor, out=out[: self.n_cal_nz])
        if VT is not None:
            n0 = self.n_cal_nz + len(self.first)
            np.multiply(VT[0, self.first], factor, out=out[self.n_cal_nz: n0])
            np.multiply(VT[1:].reshape(-1), factor, out=out[n0:])
        return out

    def objective(self, x, pf, data) -> float:
        c = self._cache
        if c is not None and c["key"] == (x.tobytes(), pf.tobytes(), id(data)):
            return c["f"]
        r = self.residuals(x, pf, data)
        return 0.5 * float(r @ r)

    def derivatives(self, x, pf, data):
        """(f, gradient, Hessian nonzeros of the objective) at x, cached for the Hessian call
        that follows the gradient's at the same point (data are compared by identity: the
        solver never changes an array it was given)."""
        key = (x.tobytes(), pf.tobytes(), id(data))
        c = self._cache
        if c is None or c["key"] != key:
            self._cache = None
            f, g, H = self.assemble(x, pf, data)
            self._cache = c = {"key": key, "data": data, "f": f, "g": g, "H": H}  # data kept: ids stay unique
        return c["f"], c["g"], c["H"]


def _scatter(plan: dict, sb, v: np.ndarray, t0, t1, j0, j1, sources: np.ndarray, stage: np.ndarray | None):
    """Add the local values v (instances t0 ... t1 - 1, entries) of one block to the source vector
    of the calibration entries and to the stage entries (stage s in row s)."""
    width = v.shape[1]
    if not width:
        return
    col = plan["col"]
    if sb is None:
        sources[col + t0 * width: col + t1 * width] = v.ravel()
        return
    V = v.reshape(j1 - j0, sb.K * width)  # one row per stage group
    sel = plan["sel"]
    sources[col: col + len(sel)] += V[:, sel].sum(axis=0)
    for d, S in plan["stage"]:
        stage[d + j0: d + j1] += (S @ V.T).T


class _Callback(ca.Callback):
    """A numpy function as a CasADi function, computed in place on CasADi's own buffers."""

    def __init__(self, name: str, sp_in: list[ca.Sparsity], sp_out: list[ca.Sparsity], fn, gradient=None):
        ca.Callback.__init__(self)
        self._in, self._out, self._fn, self._gradient = sp_in, sp_out, fn, gradient
        self.construct(name, {})

    def get_n_in(self):
        return len(self._in)

    def get_n_out(self):
        return len(self._out)

    def get_sparsity_in(self, i):
        return self._in[i]

    def get_sparsity_out(self, i):
        return self._out[i]

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        self._fn([np.frombuffer(a, float) for a in arg], [np.frombuffer(r, float) for r in res])
        return 0

    # reverse mode of a scalar function of (x, p) from its gradient in x: IPOPT's interface builds
    # the Lagrangian's gradient with it (for the bound multipliers). The derivative in p, the data,
    # is never evaluated (calc_lam_p is off) and is returned as structural zeros.
    def has_reverse(self, nadj):
        return self._gradient is not None

    def get_reverse(self, nadj, name, inames, onames, opts):
        x, p = ca.MX.sym("x", self._in[0]), ca.MX.sym("p", self._in[1])
        out, adj = ca.MX.sym("out", 1), ca.MX.sym("adj", 1, nadj)
        g = self._gradient(x, p)[1]
        return ca.Function(name, [x, p, out, adj], [ca.mtimes(g, adj), ca.MX(self._in[1].size1(), nadj)],
                           inames, onames, opts)


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
        off = 0
        for i, b in enumerate(self.blocks):
            b.compile(cache, staged[i].n_cal if i in staged else b.w_idx.shape[1], options.hessian, options.jit)
            b.data_offset = off  # into the data vector
            b.data = np.ascontiguousarray(b.block.data, float)  # the default data, not copied
            off += b.block.n * b.f.nd
        self._perm = st.perm if st else np.arange(n)  # NLP order -> layout index
        keep = [np.repeat(np.ones(b.block.n, bool) if b.block.valid is None else b.block.valid, b.f.m)
                for b in self.blocks]
        self._prior = pi, _, _ = lay.priors()
        # residuals of instances that are not valid (masked data) are exactly zero and not reported
        self._keep = np.concatenate(keep + [np.ones(len(pi), bool)])
        self.n_data_residuals = int(self._keep.sum()) - len(pi)
        self.n_residuals = int(self._keep.sum())

        # constraints |row|^2 = 1, rows grouped by width for vectorisation
        self._unit = U = lay.unit_norm_rows()
        self.n_constraints = U.shape[0]
        x = ca.MX.sym("x", n)  # in NLP order
        p = ca.MX.sym("p", lay.n_p)  # the fixed values; the data stay in numpy (_Assembly.data)
        w = ca.vertcat((x[np.argsort(self._perm).tolist()] if st else x) * lay.x_scale, p)
        c_parts, self._unit_order = [], []
        for width in sorted({int((row >= 0).sum()) for row in U}):
            sel = np.flatnonzero((U >= 0).sum(axis=1) == width)
            idx = U[sel][:, :width]
            c_parts.append(ca.sum1(ca.reshape(w[idx.ravel().tolist()], width, len(sel)) ** 2).T - 1)
            self._unit_order.append(sel)
        c = ca.vertcat(*c_parts) if c_parts else ca.MX(0, 1)
        self._c_perm = np.concatenate(self._unit_order) if self._unit_order else np.zeros(0, int)

        # objective, gradient and Hessian of the Lagrangian: numpy assembly of the local functions
        A = self._assembly = _Assembly(self.blocks, lay, st, staged, self._perm, U[self._c_perm], self.n_constraints)
        dense = ca.Sparsity.dense
        io = [dense(n), dense(lay.n_p)]

        def objective(a, o):
            o[0][0] = A.objective(a[0], a[1], A.data)

        def gradient(a, o):
            f, g, _ = A.derivatives(a[0], a[1], A.data)
            o[0][0], o[1][:] = f, g

        def hessian(a, o):
            _, _, H = A.derivatives(a[0], a[1], A.data)
            A.hessian_values(H, a[2][0], out=o[0])
            o[0][: A.n_cal_nz] += A.C_h @ a[3]

        grad_cb = _Callback("gradient", io, [dense(1), dense(n)], gradient)
        self._callbacks = cbs = [_Callback("objective", io, [dense(1)], objective, grad_cb), grad_cb,
                                 _Callback("hessian", io + [dense(1), dense(self.n_constraints)], [A.sparsity], hessian)]
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self.n_constraints)
        # the derivative functions are given, so that CasADi never differentiates the objective
        grad_f = ca.Function("nlp_grad_f", [x, p], cbs[1](x, p), ["x", "p"], ["f", "grad"])
        hess_lag = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [cbs[2](x, p, lam_f, lam_g)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        jac_g = ca.Function("nlp_jac_g", [x, p], [c, ca.jacobian(c, x)], ["x", "p"], ["g", "jac_g_x"])
        nlp = {"x": x, "p": p, "f": cbs[0](x, p), "g": c}
        self.nlp = ca.nlpsol("castimate", "ipopt", nlp, {**options.ipopt(), "hess_lag": hess_lag, "grad_f": grad_f,
                                                         "jac_g": jac_g})
        nuisance = np.zeros(n, bool)
        for g in lay.groups:
            if g.nuisance:
                nuisance[lay.x_indices(g.name)] = True
        self.theta = np.flatnonzero(~nuisance)  # reported parameters: their covariance is computed
        self.build_s = time.perf_counter() - t0

    # -- numeric ---------------------------------------------------------------------------------
    def _p(self, p_fixed, data) -> tuple[np.ndarray, np.ndarray | None]:
        """The fixed values and the data vector (defaults: the layout's values and, as None, the
        factor blocks' own data)."""
        p_fixed = self.problem.layout.p0() if p_fixed is None else p_fixed
        return np.asarray(p_fixed, float), None if data is None else np.asarray(data, float).ravel()

    def _x(self, x) -> np.ndarray:
        """Layout order -> NLP order."""
        return np.asarray(x, float)[self._perm]

    def residuals(self, x, p_fixed=None, data=None) -> np.ndarray:
        """All whitened residuals (data of the valid instances, then priors) at scaled x."""
        return self._assembly.residuals(self._x(x), *self._p(p_fixed, data))[self._keep]

    def jacobians(self, x, p_fixed=None, data=None) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Sparse Jacobians w.r.t. scaled x of the whitened residuals (data, then priors) and of the
        constraints (in the order of ``Layout.unit_norm_rows``)."""
        pf, data = self._p(p_fixed, data)
        n, scale = self.n_x, self.problem.layout.x_scale
        rows, cols, vals = [], [], []
        row0 = 0
        for b, Jb in zip(self.blocks, self._assembly.local(self._x(x), pf, data, "jac")):
            N, f = b.block.n, b.f
            Jl = Jb.reshape(N, len(f.act), f.m)
            t, a = np.nonzero(b.w_idx[:, f.act] < n)  # a indexes the active components
            gi = b.w_idx[t, f.act[a]]
            for i in range(f.m):
                rows.append(row0 + t * f.m + i)
                cols.append(gi)
                vals.append(Jl[t, a, i] * scale[gi])
            row0 += N * f.m
        pi, _, ps = self._prior
        rows.append(row0 + np.arange(len(pi))), cols.append(pi), vals.append(scale[pi] / ps)
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(len(self._keep), n))[np.flatnonzero(self._keep)]
        return J, self._constraint_jacobian(x, pf)

    def _constraint_jacobian(self, x, pf) -> sp.csr_matrix:
        lay, n = self.problem.layout, self.n_x
        scale = lay.x_scale
        w = np.concatenate([np.asarray(x, float) * scale, pf])
        gr, gc, gv = [], [], []
        for j, row in enumerate(self._unit):
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
        pi, pm, ps = self._prior
        r = ca.vertcat(*rs, (w[pi.tolist()] - pm) / ps)
        g = [ca.sumsqr(w[row[row >= 0].tolist()]) - 1 for row in self._unit]
        return {"x": x, "p": p, "f": 0.5 * ca.sumsqr(r), "g": ca.vertcat(*g) if g else ca.MX(0, 1)}

    def information(self, x, p_fixed=None, data=None) -> sp.csc_matrix:
        """The Fisher information J^T J of the whitened residuals (priors included) at scaled x, in
        the layout's order and scaled units, assembled like the Hessian from the local Jacobians."""
        A = self._assembly
        U = A.csc(A.hessian_values(A.assemble(self._x(x), *self._p(p_fixed, data), information=True)))
        F = (U + U.T - sp.diags(U.diagonal())).tocsr()
        return F[A.ipos][:, A.ipos].tocsc()

    def _eliminate(self, x, p_fixed=None, data=None, g: np.ndarray | None = None):
        """Eliminate the nuisance block from the Gauss-Newton KKT system at x.

        With F = J^T J split into reported parameters t and nuisance n, and N = [[F_nn, G_n^T],
        [G_n, 0]] the sparse KKT matrix of the nuisance block with its own constraints, returns
        S = F_tt - B N^-1 B^T, the constraints G_t on t, and, for a gradient g, the reduced
        gradient g_t - B N^-1 g_n and g_n^T N^-1 g_n. Unit-norm constraints act on either block,
        never both.
        """
        # in NLP order: the reported parameters are calibration variables, never stage variables
        A = self._assembly
        pf, d = self._p(p_fixed, data)
        F_cc, F_cs, F_ss = A.information_blocks(A.assemble(self._x(x), pf, d, information=True))
        G = self._constraint_jacobian(x, pf)[:, self._perm].tocsc()
        g = None if g is None else np.asarray(g, float)[self._perm]
        t = A.ipos[self.theta]
        nc = np.setdiff1d(np.arange(A.c), t)
        nu = np.concatenate([nc, np.arange(A.c, self.n_x)])
        on_theta = np.asarray(abs(G[:, t]).sum(axis=1)).ravel() > 0
        G_t, G_n = G[on_theta][:, t], G[~on_theta][:, nu]
        S = F_cc[t][:, t].toarray()
        g_t, g_nn = (None, 0.0) if g is None else (g[t].copy(), 0.0)
        if len(nu):
            F_nn = F_cc[nc][:, nc]
            if F_ss is not None:
                coupling = sp.csc_matrix(F_cs[nc])
                F_nn = sp.bmat([[F_nn, coupling], [coupling.T, F_ss]], format="csc")
            K = sp.bmat([[F_nn, G_n.T], [G_n, None]], format="csc") if G_n.shape[0] else F_nn.tocsc()
            F_ct = F_cc[nc][:, t].toarray()
            F_st = F_cs[t].T if F_ss is not None else np.zeros((0, len(t)))  # a view: (R m, n_t)

            def B_T(Y):  # B^T Y with B = [F_nc,t; F_s,t; 0] (nuisance rows, constraint rows)
                return F_ct.T @ Y[: len(nc)] + F_st.T @ Y[len(nc): len(nu)]

            try:
                lu = _factor(K)
            except RuntimeError:  # exactly singular: some nuisance direction is undetermined
                raise np.linalg.LinAlgError("the nuisance variables are not determined by the data") from None
            # a few columns of B at a time: B itself is as large as the coupling F_cs
            for k0 in range(0, len(t), 16):
                k = slice(k0, min(len(t), k0 + 16))
                # C order: SuperLU's solve is orders of magnitude slower on a Fortran-ordered right-hand side
                rhs = np.zeros((K.shape[0], k.stop - k.start))
                rhs[: len(nc)], rhs[len(nc): len(nu)] = F_ct[:, k], F_st[:, k]
                S[:, k] -= B_T(lu.solve(rhs))
            if g is not None:
                y = lu.solve(np.concatenate([g[nu], np.zeros(G_n.shape[0])]))
                g_t -= B_T(y)
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
        with _heap_allocation():
            return self._solve(x0, p_fixed, data, lam_g0)

    def _solve(self, x0, p_fixed, data, lam_g0) -> Solution:
        lay = self.problem.layout
        x0 = lay.x0() if x0 is None else np.asarray(x0, float)
        lbx, ubx = lay.bounds()
        pf, data = self._p(p_fixed, data)
        perm = self._perm
        t0 = time.perf_counter()
        self._assembly.data, self._assembly._cache = data, None
        sol = self.nlp(x0=x0[perm], p=pf, lbx=lbx[perm], ubx=ubx[perm], lbg=0, ubg=0,
                       lam_g0=0 if lam_g0 is None else lam_g0)
        wall = time.perf_counter() - t0
        st = self.nlp.stats()
        x = np.empty(self.n_x)
        x[perm] = np.asarray(sol["x"]).ravel()
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
            residual=self.residuals(x, pf, data)[: self.n_data_residuals],
            covariance=cov,
            lam_g=lam,
        )

    def newton_decrement(self, x, lam_g, p_fixed=None, data=None) -> float:
        """g^T H^-1 g of the Lagrangian gradient with the Gauss-Newton Hessian on the constraints'
        tangent space: twice the χ² decrease a full Newton step would still achieve. The nuisance
        block is eliminated first (:meth:`_eliminate`), so this costs what the covariance costs."""
        pf, d = self._p(p_fixed, data)
        G = self._constraint_jacobian(x, pf)
        lam = np.zeros(self.n_constraints)
        lam[self._c_perm] = lam_g  # CasADi's multipliers follow its constraint order (grouped by width)
        g = self._assembly.derivatives(self._x(x), pf, d)[1][self._assembly.ipos] + G.T @ lam
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


@contextlib.contextmanager
def _heap_allocation():
    """Serve large allocations from the heap and keep freed memory, for the duration of a solve
    (glibc only; elsewhere nothing changes). MUMPS allocates and frees its factor storage at every
    factorisation; by glibc's default every block above 32 MB is a fresh mmap whose pages the
    kernel zeroes on first touch. On the joint MIMU4444 problem that was 10 s of system time in 24 s
    of IPOPT search directions (31 s -> 19 s per solve), and 32 x 20 000 went from 16.9 s to 14.3 s
    with the same peak memory. Afterwards glibc's defaults are restored and the heap is trimmed."""
    libc = _glibc()
    if libc is None:
        yield
        return
    libc.mallopt(_M_MMAP_MAX, 0)
    libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
    try:
        yield
    finally:
        libc.mallopt(_M_MMAP_MAX, 65536)
        libc.mallopt(_M_TRIM_THRESHOLD, 128 * 1024)
        libc.malloc_trim(0)


_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # glibc's mallopt parameters


@functools.lru_cache(maxsize=1)
def _glibc():
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def _factor(K: sp.spmatrix):
    """Sparse LU of a symmetric (KKT) matrix. The minimum-degree ordering on K + K^T keeps the
    triangular solves fast: with SuperLU's default COLAMD, solving for 100 right-hand sides on a
    block-diagonal motion block of 18 000 rows took 31 s instead of 0.17 s."""
    return splu(sp.csc_matrix(K), permc_spec="MMD_AT_PLUS_A")

"""Numpy assembly of the objective, gradient and exact Hessian of the Lagrangian from compiled local
functions (see castimate.solver for the overview).
"""

from __future__ import annotations

import copy

import casadi as ca
import numpy as np
import scipy.sparse as sp

from ..jit import compiled, evaluation_work, worth_compiling
from ..problem.parameters import Layout
from ..problem.graph import FactorBlock


LOCAL = ("res", "jac", "rgh", "gn")  # the local functions of a factor (:class:`_Compiled`)
CHUNK = 4096  # instances per call of a local function: bounds the work arrays, not the results


def exact_hessian(r: ca.SX, z: ca.SX, JtJ: ca.SX) -> ca.SX:
    """The exact Hessian of 1/2 |r|^2 in z, J^T J + sum_i r_i Hess(r_i), given J^T J: the second-order
    sum as the Hessian of λ^T r with λ a symbol, then λ = r. Gauss-Newton leaves out the sum.

    The same matrix as CasADi's ``hessian(sumsqr(r) / 2, z)`` (to round-off), in fewer
    instructions: the sum is sparse (a rigid-body accelerometer's specific force is bilinear in
    the motion and the position) and J^T J is formed from the Jacobian once. At 32 IMUs x 20 000
    samples, a Carlsson accelerometer factor's local function (residual, gradient, Hessian) went
    from 1534 to 1024 instructions and from 0.23 to 0.15 s CPU per 640 000 instances."""
    lam = ca.SX.sym("lam", r.numel())
    second = ca.hessian(ca.dot(lam, r), z)[0]
    return JtJ + ca.substitute(second, lam, r)


def entries_at(M: ca.SX, pairs: np.ndarray) -> ca.SX:
    """M's entries at the (row, column) ``pairs``, as a dense column (a structural zero as 0): the
    same expressions as ``densify(vertcat(M[a, b], ...))``, in one selection from the dense M
    instead of one element access per pair (in the chip-age diagnose of tests/test_diagnose_warm.py,
    3.9 s of 38 s one by one, 0.3 s so; load 4-5)."""
    if not len(pairs):
        return ca.SX(0, 1)
    return ca.densify(M).nz[(pairs[:, 0] + pairs[:, 1] * M.size1()).tolist()]


class _Compiled:
    """Local functions of one factor, each evaluated over many instances at once.

    Each takes (z_cal, z_stage, d): the factor's inputs split into the components that are not
    stage variables and those that are (:class:`Stages`; none for an unstaged block), and its data.
    ``res`` gives the residual, ``jac`` its Jacobian, ``rgh`` the residual, the local gradient J^T r
    and the local Hessian entries ``pairs`` (exact, or J^T J for Gauss-Newton), ``gn`` the entries
    of J^T J (the information). Derivatives are
    taken only with respect to the components that are free in some instance (``active``): fixed
    intrinsics feed the residual but are never differentiated, which cut the exact local Hessian of
    a Schopp accelerometer factor from about 6500 to about 2400 instructions. Those in ``which`` are
    compiled to C with ``jit`` when ``instances`` of them at a time are worth it (``compiled``;
    :func:`castimate.jit.worth_compiling`).
    """

    def __init__(self, fn: ca.Function, order: np.ndarray, n_cal: int, active: np.ndarray, hessian: str, jit: bool,
                 which: tuple[str, ...], instances: int):
        nz, nd = fn.size1_in(0), fn.size1_in(1)
        zc, zs, d = ca.SX.sym("zc", n_cal), ca.SX.sym("zs", nz - n_cal), ca.SX.sym("d", nd)
        z = ca.vertcat(zc, zs)  # the block's inputs in its (reordered) w_idx order
        r = fn(z[np.argsort(order).tolist()], d)
        self.act = act = np.flatnonzero(active)
        za = ca.vertcat(*[z[int(i)] for i in act]) if len(act) else ca.SX(0, 1)
        J = ca.jacobian(r, za)
        JtJ = ca.mtimes(J.T, J)
        H = exact_hessian(r, za, JtJ) if hessian == "exact" else JtJ
        sp_H = H.sparsity().unite(JtJ.sparsity())  # the information J^T J is assembled on the same pattern
        # entries (a <= b), as indices into z, that are structurally nonzero
        self.pairs = np.array([(int(act[a]), int(act[b])) for b in range(len(act)) for a in range(b + 1)
                               if sp_H.has_nz(a, b)], int).reshape(-1, 2)
        loc = np.full(nz, -1)
        loc[act] = np.arange(len(act))

        def entries(M):  # M's values at the pairs
            return entries_at(M, loc[self.pairs])

        args = [zc, zs, d]
        name = fn.name()
        local = [ca.Function(f"{name}_res", args, [r]),
                 ca.Function(f"{name}_jac", args, [ca.densify(J)]),
                 ca.Function(f"{name}_rgh", args, [r, ca.densify(ca.mtimes(J.T, r)), entries(H)]),
                 ca.Function(f"{name}_gn", args, [entries(JtJ)])]
        self.symbolic = dict(zip(LOCAL, local))  # for functions built on them
        # compiled to C when they run over enough instances (``jit``), else on CasADi's virtual machine
        self.compiled = jit and worth_compiling(instances, self.symbolic["rgh"])
        self.work = evaluation_work(instances, self.symbolic["rgh"])  # gcc's optimisation level (castimate.jit)
        # gcc on a worker thread while the Solver's other blocks are built (the first use waits)
        self._library = compiled({name: self.symbolic[name] for name in LOCAL if name in which}, self.work,
                                 self.compiled)
        self.nz, self.nd, self.m, self.n_cal = nz, nd, fn.size1_out(0), n_cal
        self._buffers: dict = {}

    def _get(self, name: str) -> ca.Function:
        return self._library.result().get(name, self.symbolic[name])

    # the local functions, compiled where chosen (``which``)
    res = property(lambda self: self._get("res"))
    jac = property(lambda self: self._get("jac"))
    rgh = property(lambda self: self._get("rgh"))
    gn = property(lambda self: self._get("gn"))

    def __call__(self, fn: ca.Function, args: list[np.ndarray], outs: list[np.ndarray]):
        """Evaluate ``fn`` on n instances in place: ``args`` and ``outs`` are C-contiguous (n, size)
        arrays, one row per instance (CasADi's buffers point into them; nothing is copied)."""
        key = (fn.name(), args[0].shape[0])
        if key not in self._buffers:
            self._buffers[key] = fn.map(key[1]).buffer()
        buf, run = self._buffers[key]
        args = [np.ascontiguousarray(a) for a in args]  # no copy for C-order inputs
        for i, a in enumerate(args):
            buf.set_arg(i, memoryview(a))
        for i, o in enumerate(outs):
            if not o.flags.c_contiguous:
                raise ValueError(f"{fn.name()}: output {i} is not a C-contiguous array")
            buf.set_res(i, memoryview(o))
        run()


class Block:
    """A factor block bound to the layout: its index matrix into w and its compiled functions.

    ``w_idx`` (N, nz) gives each instance's inputs as positions in w; a staged block's columns
    are reordered (``order``), calibration components first."""

    def __init__(self, block: FactorBlock, layout: Layout):
        self.block = block
        # C order: gathers by rows stay C order; 32 bits: half the memory of the largest index array
        dtype = np.int32 if layout.n_x + layout.n_p < 2**31 else int
        cols = []
        for g, rows in block.inputs:
            W = (layout.w_index(g) if isinstance(g, str) else np.vstack([layout.w_index(n) for n in g])).astype(dtype)
            cols.append((W, rows))
        nz = block.residual.size1_in(0)
        width = sum(W.shape[1] for W, _ in cols)
        if width != nz:
            raise ValueError(f"factor block {block.name}: inputs give {width} values, the function takes {nz}")
        # written into one C-order array (CasADi's buffers read C order): no temporaries of its size
        # (np.hstack, then a C-order copy, was 0.05 s at 640 000 instances). Consecutive inputs
        # indexed by the same rows (a sensor factor's intrinsics, all by triad) are gathered
        # together: the copy into the array's columns, which strides over it, costs more than the
        # gather and is then made once per run (0.16 -> 0.06 s at 32 x 20 000)
        self.w_idx = np.empty((block.n, nz), dtype)
        runs: list = []
        for W, rows in cols:
            if runs and rows is not None and runs[-1][1] is rows and runs[-1][0][0].shape[0] == W.shape[0]:
                runs[-1][0].append(W)
            else:
                runs.append(([W], rows))
        c0 = 0
        for Ws, rows in runs:
            W = Ws[0] if len(Ws) == 1 else np.hstack(Ws)
            c1 = c0 + W.shape[1]
            if rows is None:
                self.w_idx[:, c0:c1] = W[0]
            else:
                self.w_idx[:, c0:c1] = np.take(W, rows, axis=0)
            c0 = c1
        self.order = np.arange(nz)
        self.n_x = layout.n_x

    def segment(self, t0: int, t1: int) -> "Block":
        """Instances t0 ... t1 - 1 as a block of their own (the same factor; its own column order
        and compiled functions)."""
        seg = copy.copy(self)
        seg.w_idx, seg.order = self.w_idx[t0:t1].copy(), self.order.copy()
        return seg

    def reorder(self, order: np.ndarray):
        """Permute the columns, in place a slab of instances at a time (no second index matrix:
        at 32 x 20 000 it is 61 MB of fresh pages). np.take: several times faster than fancy
        column indexing on a large C-order matrix."""
        W = self.w_idx
        for t0 in range(0, len(W), StagedBlock.SLAB):
            W[t0: t0 + StagedBlock.SLAB] = np.take(W[t0: t0 + StagedBlock.SLAB], order, axis=1)
        self.order = self.order[order]

    def compile(self, cache: dict, n_cal: int, hessian: str, jit: bool, which: tuple[str, ...] = LOCAL,
                instances: int | None = None):
        """The local functions (:class:`_Compiled`); with ``jit`` only those in ``which`` compiled to
        C (gcc's time on a new structure), and only when they run over enough ``instances`` (default
        the block's; :func:`castimate.jit.worth_compiling`), the others left on CasADi's virtual machine."""
        active = (self.w_idx < self.n_x).any(axis=0)
        instances = self.block.n if instances is None else instances
        key = (id(self.block.residual), self.order.tobytes(), n_cal, active.tobytes(), (which, instances) if jit else ())
        if key not in cache:
            cache[key] = _Compiled(self.block.residual, self.order, n_cal, active, hessian, jit, which, instances)
        self.f = cache[key]


class NotStaged(Exception):
    """A block touches stage variables without the stage structure."""


class StagedBlock:
    """How the instances of one block map to stages: instance t = j K + k belongs to stage
    ``base + j`` (plus the offset ``rel`` of each input component, at most ``max_offset``; None:
    any) and sees the same variables of it for every k; which calibration variables it sees
    depends on k only. ``st`` gives every x index's stage and position within it (``stage_of``,
    ``within``, -1 for other variables). Raises LookupError for a block without stage variables,
    NotStaged for one that has them without this structure."""

    SLAB = 65536  # instances per slab of the checks: their temporaries stay small

    def __init__(self, b: Block, st, max_offset: int | None = 1):
        W = b.w_idx
        N, nz = W.shape
        n = len(st.stage_of)
        size = max(int(W.max()) + 1, n)
        stage_of, within = np.full(size, -1, np.int32), np.full(size, -1, np.int32)
        stage_of[:n], within[:n] = st.stage_of, st.within
        # the stage components are those of the first instance: the other components must repeat
        # every K instances and read no stage variable in the first K (checked below), so only the
        # stage columns are gathered (at 32 x 20 000, 9 of the accelerometers' 24); if the first
        # instance has none, every column is looked at
        is_st = np.take(stage_of, W[0]) >= 0
        if not is_st.any():
            is_st = (np.take(stage_of, W) >= 0).any(axis=0)
            if not is_st.any():
                raise LookupError
        # the first stage group: the instances up to the first whose first stage differs from the
        # first instance's (a prefix, in windows that double); the others are checked against it
        # below, so the stage of every instance is never gathered on its own
        cols, K, t0, t1 = np.flatnonzero(is_st), N, 0, min(N, 64)
        base = int(np.take(stage_of, W[0, cols]).min())
        while t0 < N:
            S = np.take(stage_of, W[t0:t1, cols])
            if not (S >= 0).all():
                raise NotStaged
            other = np.flatnonzero(S.min(axis=1) != base)
            if len(other):
                K = t0 + int(other[0])
                break
            t0, t1 = t1, min(N, t1 + min(t1, self.SLAB))
        J = N // K
        if N % K:
            raise NotStaged
        rel = np.full((K, nz), -1)
        rel[:, is_st] = np.take(stage_of, W[:K, is_st]) - base
        q = np.where(is_st, within[W[:K]], W[:K])  # stage position, or w index
        if (max_offset is not None and rel.max() > max_offset) or not (np.take(stage_of, W[:K, ~is_st]) < 0).all() \
                or not np.where(is_st, q == q[0], True).all() or base + J - 1 + rel.max() > stage_of.max():
            raise NotStaged
        # every stage group sees the same stage positions and offsets and the same calibration
        # inputs (which then are no stage variables in any instance, as in the first K); checked a
        # slab of stage groups at a time, each stage input against the w index of its (stage,
        # position): one gather instead of its stage's and its position's (with the prefix above,
        # 0.21-0.24 -> 0.09 s for the two sensor blocks at 32 x 20 000)
        mw = int(within.max()) + 1
        var = np.full((int(stage_of.max()) + 1) * mw, -1, W.dtype)  # stage * mw + position -> w index
        on = np.flatnonzero(stage_of >= 0)
        var[stage_of[on] * mw + within[on]] = on
        at = rel[:, is_st] * mw + q[:, is_st]  # of stage group 0, relative to its stage
        step = max(1, self.SLAB // K)
        for j0 in range(0, J, step):
            j1 = min(J, j0 + step)
            Ws = W[j0 * K: j1 * K].reshape(j1 - j0, K, nz)
            # the calibration columns compared on the whole width (no copy of them: 4 x faster)
            if not (Ws == W[:K]).all(axis=0)[:, ~is_st].all() \
                    or not (Ws[:, :, is_st] == np.take(var, at + ((base + np.arange(j0, j1)) * mw)[:, None, None])).all():
                raise NotStaged
        self.K, self.J, self.base = K, J, base
        self.rel, self.q, self.is_st = rel, q, is_st
        self.n_cal = int((~is_st).sum())
        # calibration components first, then the stage components by offset and position
        self.order = np.lexsort((q[0], rel[0], is_st))

    def reordered(self):
        """Adopt the block's reordering by ``order`` (after Block.reorder)."""
        self.rel, self.q = (np.ascontiguousarray(M[:, self.order]) for M in (self.rel, self.q))
        self.is_st = self.is_st[self.order]

    def stage_inputs(self, Xs: np.ndarray, j0: int, j1: int) -> np.ndarray:
        """The stage components (j1 - j0, n_s) of instance groups j0 ... j1 - 1, from the stage
        values Xs (R, m) in physical units (inputs after the calibration ones, as ordered)."""
        rel, q = self.rel[0, self.n_cal:], self.q[0, self.n_cal:]
        return Xs[(self.base + j0 + rel)[None, :] + np.arange(j1 - j0)[:, None], q[None, :]]


class Stages:
    """The stage structure that makes assembly linear in the number of samples.

    Stages are the rows of the nuisance matrix groups with the most free variables (the motion
    states of each sample). Inside the NLP the decision vector is ordered [calibration variables
    (everything else) | stage 0 | stage 1 | ...], each stage holding its row of every stage group.
    A block is *staged* when its instances come in runs of K per stage (t = j K + k: sample j,
    triad k) and each touches its stage and possibly the next (:class:`StagedBlock`).

    The upper-triangular Hessian's columns of stage s then have the same pattern for every s: rows
    of calibration variables, of stage s-1 and of stage s (the first stage lacks s-1), and the
    local entries of instance group j land on them through one small constant matrix per block
    and stage offset (:class:`Assembly`).
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
    def find(lay: Layout, blocks: list[Block]) -> tuple["Stages | None", dict]:
        """The stage structure and the staged blocks {block index: StagedBlock} (reordering
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
        st = Stages(lay, groups)
        staged = {}
        for i, b in enumerate(blocks):
            try:
                sb = StagedBlock(b, st)
            except LookupError:
                continue
            except NotStaged:
                for b2 in blocks:
                    b2.reorder(np.argsort(b2.order))
                return None, {}
            b.reorder(sb.order)
            sb.reordered()
            staged[i] = sb
        return st, staged


class Assembly:
    """Objective, gradient and Hessian of 1/2 |r|^2 (NLP order, scaled x) from the local functions
    of every instance, evaluated in numpy a chunk at a time.

    Calibration entries: a constant sparse matrix maps the local entries that land on calibration
    variables (every instance of an unstaged block; a staged block's, summed over its stage groups)
    and the priors' to their place, with the chain rule of the x scaling. Stage entries: the
    columns of every stage have the same pattern (:class:`Stages`), so the local entries of one
    stage group land on them through one small constant matrix per block and stage offset, applied
    to the whole chunk at once. Memory is the result plus one chunk of local values, and time is
    linear in the number of instances; no expression graph grows with the data.
    """

    def __init__(self, blocks: list[Block], layout: Layout, stages: Stages | None, staged: dict,
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

    def _stage_entries(self, i, sb: StagedBlock, a_idx, b_idx, sx) -> dict:
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


class EvaluationError(RuntimeError):
    """A function evaluated in a :class:`Callback` has no value at this point (e.g. the eliminated
    nuisance variables did not converge): IPOPT takes it as an evaluation error and cuts its step back."""


class Callback(ca.Callback):
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
        try:
            self._fn([np.frombuffer(a, float) for a in arg], [np.frombuffer(r, float) for r in res])
        except EvaluationError:
            return 1  # IPOPT's evaluation error, as raising would be, without CasADi printing a traceback
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

"""Variable projection: the per-sample motion and the per-pose directions eliminated exactly.

Every problem is arrow-shaped: thousands of small nuisance blocks (the motion states ω, ω̇, s of
each sample; the specific-force direction of each static pose) couple to each other only through a
banded process model, and to a few hundred calibration parameters θ, a dense border. IPOPT solves
the *reduced* problem over θ alone::

    φ(θ) = min_m f(θ, m)    (m: the nuisance rows, subject to their own unit-norm constraints)

At each θ the nuisance m*(θ) is found by Newton steps on m alone, warm-started from the first-order
prediction of the implicit function theorem, dm/dθ = -H_mm^-1 H_mθ. The reduced gradient is
∇φ = g_θ - H_θm H_mm^-1 g_m (exact at m*; the correction makes it exact to second order in the
inner residual), and the exact reduced Hessian is the Schur complement of the full Hessian of the
Lagrangian, second-order terms included::

    ∇²φ = H_θθ - H_θm H_mm^-1 H_mθ

H_mm is block diagonal (independent samples or poses) or block banded (a process model coupling
consecutive samples: a Kalman/RTS-like sweep, here LAPACK's band Cholesky), so every evaluation costs
time and memory linear in the number of samples; the only dense matrix is the (θ, θ) one. Unit-norm
rows of a nuisance family (pose directions) are handled in their tangent space (basis Z, multiplier
curvature added). The covariance uses the same elimination with the Fisher information J^T J.

A *family* is a set of nuisance matrix groups with the same rows (:class:`Family`); the factor
blocks that touch it must come in runs of instances per row (:class:`assembly.StagedBlock`, the
instances sorted by row if needed), or be cut into a few runs that are each staged (a factor that
reads the neighbouring samples, clamped at the ends of the record: first sample, interior, last
sample); groups with priors or bounds on their rows, or read by a block without that structure,
stay calibration variables, and the reason is reported (``Solver.elimination_note``). A staged
block is evaluated a stage group at a time by compiled functions that also sum its instances'
entries onto the stage's arrays (:class:`_StageFunctions`); otherwise local derivatives from the
same local functions as the reference assembly (:mod:`castimate.solver.assembly`), plus one of the
nuisance components alone for the inner steps, land on the eliminated system's arrays through
small constant maps in numpy (:class:`_Plan`).

Measured against the reference path (the full NLP, KKT factorised by MUMPS), same start, same
optimum to 1e-13 relative, in ``benchmarks/dynamic_scaling.py``: at 32 IMUs x 20 000 samples 5.1 s
CPU and 714 MB against 13.6 s and 2.7 GB (load 4.5).
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import functools
import threading
import weakref

import casadi as ca
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.linalg import blas, lapack

from ..jit import compiled
from ..problem.parameters import Layout
from .assembly import CHUNK, LOCAL, Block, EvaluationError, NotStaged, StagedBlock, entries_at, exact_hessian
from .threads import map_threads, pool


STAGE_CHUNK = 4096  # instances per call of a stage function (whole stage groups)
CHECK_STAGES = 256  # stage groups per slab when checking that the shared data columns are shared (_StageFunctions.shared_values)


class Family:
    """Rows of nuisance matrix groups eliminated together: the motion states of every sample, or
    the direction of every static pose. Stage r holds row r of every group of the family."""

    def __init__(self, lay: Layout, groups):
        self.groups = groups
        self.R = groups[0].rows
        self.X = np.hstack([lay.w_index(g.name)[:, g.free[0]] for g in groups])  # (R, m) layout x indices
        self.m = self.X.shape[1]
        # stage and position of every w index: the variables at 0 ... m - 1, the groups' fixed
        # components (a tilt quaternion's zero) after them, so that a factor reads them per stage
        fixed = np.hstack([lay.w_index(g.name)[:, ~g.free[0]] for g in groups])
        self.stage_of = np.full(lay.n_x + lay.n_p, -1)
        self.within = np.full(lay.n_x + lay.n_p, -1)
        for cols, offset in ((self.X, 0), (fixed, self.m)):
            self.stage_of[cols] = np.arange(self.R)[:, None]
            self.within[cols] = offset + np.arange(cols.shape[1])[None, :]
        self.scale = lay.x_scale[self.X[0]]
        self.unit = []  # unit-norm groups: (stage positions (k,), w indices of fixed components (R, nf))
        col = 0
        for g in groups:
            f = g.free[0]
            k = int(f.sum())
            if g.unit_norm:
                self.unit.append((col + np.arange(k), lay.w_index(g.name)[:, ~f]))
            col += k
        self.width = 1  # stages coupled by one factor instance (1: independent stages)

    @staticmethod
    def candidate(g) -> bool:
        """A nuisance matrix group with free rows: what the projection would eliminate."""
        return bool(g.matrix and g.nuisance and g.free.any() and g.rows >= 2)

    @staticmethod
    def refusal(g) -> str | None:
        """Why a candidate group cannot be eliminated (None: it can)."""
        f = g.free[0]
        if not (g.free == f).all() or not (g.scale[:, f] == g.scale[0, f]).all():
            return f"{g.name}: rows with different free components or scales"
        if np.isfinite(g.prior_std[g.free]).any():
            return f"{g.name}: a prior on its rows"
        if np.isfinite(g.lower[g.free]).any() or np.isfinite(g.upper[g.free]).any():
            # the nuisance optimum m*(θ) would not be differentiable where a bound becomes active: the
            # reduced problem would have no exact Hessian there (its Schur complement jumps with the
            # active set), so bounded rows stay IPOPT's variables, whose bounds it handles exactly
            return f"{g.name}: bounds on its rows (the reduced problem has no exact Hessian where a bound becomes active)"
        return None


class _View:
    """A block's instances in another order (sorted by stage) for the stage analysis."""

    def __init__(self, w_idx):
        self.w_idx = w_idx


def find_families(lay: Layout, blocks: list[Block]):
    """Families, per block touching one (family index, segments, instance order or None), and
    the reasons why other nuisance groups are not eliminated.
    A segment is (instance slice or None for the whole block, StagedBlock, the Block evaluated);
    a whole block is reordered in place (calibration inputs first), a part of one is a copy
    (:meth:`Block.segment`). Families that some block touches without the stage structure are
    dropped (their variables stay calibration variables)."""
    by_rows: dict = {}
    refused = []  # why candidate groups stay calibration variables
    for g in lay.groups:
        if Family.candidate(g):
            why = Family.refusal(g)
            if why is None:
                by_rows.setdefault(g.rows, []).append(g)
            else:
                refused.append(why)
    cands = list(by_rows.values())
    while True:
        fams = [Family(lay, gs) for gs in cands]
        staged, bad = {}, None
        for i, b in enumerate(blocks):
            for fi, fam in enumerate(fams):
                try:
                    segs, order = _stage(b, fam)
                except LookupError:
                    continue
                except NotStaged:
                    bad, why = fi, f"factor block {b.block.name} reads them without the stage structure"
                    break
                if i in staged:  # touches two families
                    bad, why = fi, f"factor block {b.block.name} also reads another family"
                    break
                staged[i] = (fi, segs, order)
            if bad is not None:
                break
        if bad is None:
            break
        refused.append(f"{', '.join(g.name for g in cands[bad])}: {why}")
        cands.pop(bad)
    out = {}
    for i, (fi, segs, order) in staged.items():
        b, parts = blocks[i], []
        for t0, t1, sb in segs:
            whole = len(segs) == 1
            blk = b if whole else b.segment(t0, t1)
            blk.reorder(sb.order)
            sb.reordered()
            fams[fi].width = max(fams[fi].width, int(sb.rel.max()) + 1)
            parts.append((None if whole else slice(t0, t1), sb, blk))
        out[i] = (fi, parts, order)
    return fams, out, refused


GRAM_ROWS = 512  # rows of L^-1 H_mθ per rank-k update of the Schur complement (:meth:`_Factor.lower_gram`)
MAX_SEGMENTS = 8  # runs of differently staged instances a block may be cut into


def _stage(b, fam):
    """[(t0, t1, StagedBlock)] of b for a family and the instance order (or None): the whole
    block, on the instances sorted by their first stage if needed; else (unsorted) the runs of
    instances whose stage inputs have the same offsets from their first stage, each staged on
    its own: a factor that reads its neighbours' motion, clamped at the ends of the record
    (a rate by central differences), has one run for the first sample, one for the interior and
    one for the last."""
    W = b.w_idx
    n = len(fam.stage_of)
    none = np.iinfo(np.int32).max
    stage_of = np.full(max(int(W.max()) + 1, n), none, np.int32)
    stage_of[:n][fam.stage_of >= 0] = fam.stage_of[fam.stage_of >= 0]
    tried = (np.take(stage_of, W[0]) != none).any()
    if tried:
        # staged as given (instances in stage order): StagedBlock finds out from the first
        # instance's stage columns alone; else the general analysis below
        try:
            return [(0, len(W), StagedBlock(b, fam, max_offset=None))], None
        except NotStaged:
            pass
    base = np.take(stage_of, W).min(axis=1)
    if (base == none).all():
        raise LookupError
    order = None
    if (np.diff(base) < 0).any():
        order = np.argsort(base, kind="stable")
        return [(0, len(W), StagedBlock(_View(W[order]), fam, max_offset=None))], order
    try:
        if tried:
            raise NotStaged
        return [(0, len(W), StagedBlock(b, fam, max_offset=None))], None
    except NotStaged:
        S = np.take(stage_of, W)
        S = np.compress((S != none).any(axis=0), S, axis=1)
        S -= base[:, None]
        cut = np.flatnonzero((S[1:] != S[:-1]).any(axis=1)) + 1
        if len(cut) >= MAX_SEGMENTS:
            raise
        bounds = [0, *cut.tolist(), len(W)]
        return [(t0, t1, StagedBlock(_View(W[t0:t1]), fam, max_offset=None)) for t0, t1 in zip(bounds, bounds[1:])], None


# ------------------------------------------------------------------------------------------------
# Local functions of the stage components only (the inner problem)
# ------------------------------------------------------------------------------------------------

def inner_function(fn: ca.Function, order: np.ndarray, n_cal: int, hessian: str, jit: bool):
    """The local function of the nuisance components alone, for the inner Newton steps:
    (z_cal, z_stage, d) -> (r, J_s^T r, H_ss and J_s^T J_s at the pairs), with the pairs and the
    active components as indices into z. H_ss is the exact Hessian of 1/2 |r|^2 (J_s^T J_s for
    ``gauss_newton``); J_s^T J_s serves the Levenberg-Marquardt steps far from the optimum."""
    nz, nd = fn.size1_in(0), fn.size1_in(1)
    zc, zs, d = ca.SX.sym("zc", n_cal), ca.SX.sym("zs", nz - n_cal), ca.SX.sym("d", nd)
    z = ca.vertcat(zc, zs)
    r = fn(z[np.argsort(order).tolist()], d)
    J = ca.jacobian(r, zs)
    JtJ = ca.mtimes(J.T, J)
    H = exact_hessian(r, zs, JtJ) if hessian == "exact" else JtJ
    sp_H = H.sparsity().unite(JtJ.sparsity())
    ns = nz - n_cal
    pairs = np.array([(a, b) for b in range(ns) for a in range(b + 1) if sp_H.has_nz(a, b)], int).reshape(-1, 2)

    f = ca.Function(f"{fn.name()}_rghs", [zc, zs, d],
                    [r, ca.densify(ca.mtimes(J.T, r)), entries_at(H, pairs), entries_at(JtJ, pairs)])
    return f, n_cal + pairs, n_cal + np.arange(ns)


class _Map:
    """Local entries -> targets: ``out[:, dest] += (V[:, src] * val)`` summed over equal targets."""

    def __init__(self, src, dest, val):
        o = np.argsort(dest, kind="stable")
        self.src, dest, self.val = src[o], dest[o], val[o]
        self.dest, starts = np.unique(dest, return_index=True)
        self.starts = None if len(starts) == len(dest) else starts

    def __call__(self, V):
        X = np.take(V, self.src, axis=1)
        X *= self.val
        return X if self.starts is None else np.add.reduceat(X, self.starts, axis=1)


class _Plan:
    """Where the local gradient and Hessian entries of one stage group of a block land.

    Sources: stage group j's entries k * width + e (instance k of the group, entry e). Targets:
    ``gc`` (c,) and ``hcc`` (c * c,) summed over the groups; per stage offset d, ``gs[d]`` (m,),
    ``hsc[d]`` (m * c,) of stage base + j + d; per (d, o), ``hss[(d, o)]`` (m * m,) of the block
    coupling stage base + j + d to stage base + j + d + o (o = 0: the diagonal block)."""

    def __init__(self, K, is_st, rel, q, act, pairs, fam_scale, m, tpos, xscale, n, c):
        na, P = len(act), len(pairs)
        self.na, self.P, self.K = na, P, K
        # gradient
        k = np.repeat(np.arange(K), na)
        a = np.tile(act, K)
        src = k * na + np.tile(np.arange(na), K)
        st, r, qq = is_st[a], rel[k, a], q[k, a]
        st &= qq < m  # stage variables (not a row's fixed components)
        cal = ~is_st[a] & (qq < n)
        self.gc = _Map(src[cal], tpos[qq[cal]], xscale[qq[cal]]) if cal.any() else None
        # stage targets are the same for every instance of a stage group (StagedBlock): their
        # entries are summed over the group first, and the maps read instance 0's sources
        st &= k == 0
        self.gs = {int(d): _Map(src[s], qq[s], fam_scale[qq[s]]) for d in np.unique(r[st]) for s in [st & (r == d)]}
        # Hessian
        k = np.repeat(np.arange(K), P)
        pa, pb = np.tile(pairs[:, 0], K), np.tile(pairs[:, 1], K)
        src = k * P + np.tile(np.arange(P), K)
        sa, sb = is_st[pa], is_st[pb]
        qa, qb, ra, rb = q[k, pa], q[k, pb], rel[k, pa], rel[k, pb]
        keep = np.where(sa, qa < m, qa < n) & np.where(sb, qb < m, qb < n)  # variables only
        s = keep & ~sa & ~sb
        i, j, v, mirror = tpos[qa[s]], tpos[qb[s]], xscale[qa[s]] * xscale[qb[s]], pa[s] != pb[s]
        self.hcc = _Map(np.concatenate([src[s], src[s][mirror]]), np.concatenate([i * c + j, (j * c + i)[mirror]]),
                        np.concatenate([v, v[mirror]])) if s.any() else None
        s = keep & (sa ^ sb)
        sq, sr, cq = np.where(sa, qa, qb)[s], np.where(sa, ra, rb)[s], np.where(sa, qb, qa)[s]
        v, dest, ss = fam_scale[sq] * xscale[cq], sq * c + tpos[cq], src[s]
        self.hsc = {int(d): _Map(ss[sel], dest[sel], v[sel]) for d in np.unique(sr) for sel in [sr == d]}
        s = keep & sa & sb & (k == 0)
        swap = ra[s] > rb[s]
        r1, r2 = np.where(swap, rb[s], ra[s]), np.where(swap, ra[s], rb[s])
        q1, q2 = np.where(swap, qb[s], qa[s]), np.where(swap, qa[s], qb[s])
        v, ss, o = fam_scale[q1] * fam_scale[q2], src[s], r2 - r1
        mirror = (o == 0) & (pa[s] != pb[s])
        self.hss = {}
        for key in sorted({(int(x), int(y)) for x, y in zip(r1, o)}):
            sel = (r1 == key[0]) & (o == key[1])
            ms = sel & mirror
            self.hss[key] = _Map(np.concatenate([ss[sel], ss[ms]]),
                                 np.concatenate([q1[sel] * m + q2[sel], q2[ms] * m + q1[ms]]),
                                 np.concatenate([v[sel], v[ms]]))


def _groups(M: _Map) -> np.ndarray:
    """The target (index into M.dest) of each of M's sources."""
    if M.starts is None:
        return np.arange(len(M.src))
    t = np.zeros(len(M.src), int)
    t[M.starts[1:]] = 1
    return np.cumsum(t)


def _reduce(M: _Map, values: np.ndarray) -> np.ndarray:
    """M applied to values already gathered at its sources (in M.src's order)."""
    X = values * M.val
    return X if M.starts is None else np.add.reduceat(X, M.starts)


def _shared_split(fn: ca.Function, shared: tuple[int, ...]):
    """fn (z_cal, z_stage, d) of one instance split into (pre, post): pre (z_cal, d) -> p, the
    subexpressions that depend on the calibration inputs and the data columns ``shared`` alone
    (CasADi's extract_parametric; e.g. a triad's T = K L M R̄), and post (p, z_cal, z_stage, d) ->
    fn's outputs from them. None if there is nothing to split off."""
    zc, zs, d = (ca.SX.sym(n, fn.sparsity_in(i)) for i, n in enumerate(("zc", "zs", "d")))
    outs = fn(zc, zs, d)
    outs = list(outs) if isinstance(outs, (list, tuple)) else [outs]
    ret, syms, par = ca.extract_parametric(outs, ca.vertcat(zc, *[d[i] for i in shared]))
    if not syms:
        return None
    pre = ca.Function(f"{fn.name()}_shared", [zc, d], [ca.veccat(*par)])
    return pre, ca.Function(f"{fn.name()}_per_instance", [ca.veccat(*syms), zc, zs, d], ret)


def _outputs(fn: ca.Function, k: int) -> ca.Function:
    """fn's first k outputs alone (an SX function keeps only the operations they need)."""
    ins = [ca.SX.sym(f"i{i}", fn.sparsity_in(i)) for i in range(fn.n_in())]
    return ca.Function(f"{fn.name()}{k}", ins, fn(*ins)[:k])


class _StageFunctions:
    """One compiled function per evaluation mode of a staged block that does a stage group's
    whole share at once: the local function of its K instances (``map``), and the sums of their
    entries onto the stage targets (the maps of :class:`_Plan` as constant sparse matrices).

    (z_cal of the K instances, the stage inputs, the K instances' data) -> (the entries that land
    on calibration targets, summed over the stage groups of a call (``reduce_out``), with
    1/2 |r|^2 first; per stage group the stage gradient G, the stage Hessian blocks B and the
    coupling Hsc entries, each at the targets of one map). Mapped over a chunk of stage groups,
    the calibration inputs shared (``reduce_in``). Numpy then only adds contiguous slabs: the
    K-fold sums and the gathers of the local entries (two thirds of an assembly at 32 × 20 000)
    run in the compiled code. A target that gets every entry of its slab (dense) is an output of
    its own, which the call writes straight into the assembled array where the block is the
    first to write that array, and all of it (:meth:`Projection.assemble`; ``direct``): the
    coupling Hsc, the largest array, is then neither zeroed nor added."""

    # scattered targets added by flat indices into their slab (False: numpy's (rows, columns) fancy
    # indexing, as a reference; one addition per entry either way, so the same bits)
    flat_add = True
    # dense targets written in place by the call where they may be (False: every target added onto
    # the zeroed arrays, as a reference; 0 + v = v, so the same bits)
    direct = True

    @staticmethod
    def applies(sb) -> bool:
        """Every instance of a stage group sees the same stage inputs."""
        return bool((sb.rel[:, sb.is_st] == sb.rel[0, sb.is_st]).all())

    def __init__(self, f, inner_fn, plan: _Plan, inner_plan: _Plan, sb, m: int, c: int, jit: bool,
                 shared: tuple[int, ...] = ()):
        K, nc, nd = sb.K, f.n_cal, f.nd
        self.K, self.nc, self.shared = K, nc, tuple(shared)
        self._checked = None  # the last data array found to have its shared columns shared
        widths = {"G": m, "B": m * m, "Bgn": m * m, "Hsc": m * c}
        na, P = len(f.act), len(f.pairs)
        ns_act, P_in = inner_plan.na, inner_plan.P
        gs = [("g", M, True, ("G", d)) for d, M in plan.gs.items()]
        hss = [("h", M, True, ("B", k)) for k, M in plan.hss.items()]
        hsc = [("h", M, False, ("Hsc", d)) for d, M in plan.hsc.items()]
        red_full = [("g", "gc", plan.gc)] * (plan.gc is not None) + [("h", "hcc", plan.hcc)] * (plan.hcc is not None)
        specs = {
            "full": (f.symbolic["rgh"], ("r", "g", "h"), {"r": 1, "g": na, "h": P}, red_full, gs + hss + hsc),
            "info": (f.symbolic["gn"], ("h",), {"h": P}, [x for x in red_full if x[1] == "hcc"], hss + hsc),
            "grad": (_outputs(f.symbolic["rgh"], 2), ("r", "g"), {"r": 1, "g": na}, [x for x in red_full if x[1] == "gc"],
                     gs),
            "inner": (inner_fn, ("r", "g", "h", "hgn"), {"r": 1, "g": ns_act, "h": P_in, "hgn": P_in}, [],
                      [("g", M, True, ("G", d)) for d, M in inner_plan.gs.items()]
                      + [("h", M, True, ("B", k)) for k, M in inner_plan.hss.items()]
                      + [("hgn", M, True, ("Bgn", k)) for k, M in inner_plan.hss.items()]),
        }
        functions, self.layout = self._functions(specs, f, inner_fn, K, nc, nd, widths, self.shared)
        # compiled while the Solver's other blocks are built (gcc on worker threads: :attr:`fns` waits)
        self._library = compiled(functions, f.work, jit)
        # without the shared part, for data whose declared-shared columns are not (built when needed)
        self._plain_args, self._plain_fns, self._jit, self._work = (specs, f, inner_fn, K, nc, nd, widths, ()), None, jit, f.work
        self._maps: dict = {}  # (mode, stage groups, inputs) -> the map, built once for every thread
        self._buffers: dict = {}  # the same and the thread -> a buffer of the map (arguments and work: one per thread)
        self._lock = threading.Lock()  # the workers' first calls build the maps one after the other
        self._flat: dict = {}  # (mode, segment, stage groups) -> flat indices of a scattered target in its slab

    @property
    def fns(self) -> dict[str, ca.Function]:
        """The stage functions of every mode (and their shared parts) by name, compiled to C where
        the block runs over enough instances: the first access waits for gcc."""
        return self._library.result()

    def _plain(self) -> dict[str, ca.Function]:
        """:attr:`fns` without the shared part (built the first time they are needed)."""
        if self._plain_fns is None:
            self._plain_fns = compiled(self._functions(*self._plain_args)[0], self._work, self._jit).result()
        return self._plain_fns

    @classmethod
    def _functions(cls, specs, f, inner_fn, K, nc, nd, widths, shared):
        """The stage functions of every mode (and their shared parts) by name, and their layouts."""
        layouts, functions = {}, {}
        for mode, (fn, names, width, red, tgt) in specs.items():
            split = _shared_split(fn, shared) if shared else None
            F, pre, layout = cls._build(f"{fn.name()}_{mode}_stages", fn, names, width, red, tgt, K, nc, nd, widths,
                                        split)
            functions[mode] = F
            if pre is not None:
                functions[f"{mode}_shared"] = pre
            layouts[mode] = layout
        # the residuals themselves, instance by instance (K m per stage group, the block's order)
        zc, zs, d = ca.MX.sym("zc", K * nc), ca.MX.sym("zs", inner_fn.size1_in(1)), ca.MX.sym("d", K * nd)
        split = _shared_split(f.symbolic["res"], shared) if shared else None
        args = [ca.reshape(zc, nc, K), ca.repmat(zs, 1, K), ca.reshape(d, nd, K)]
        ins, pre = [zc, zs, d], None
        if split is None:
            r = f.symbolic["res"].map(K, "serial")(*args)
        else:
            npar = split[0].size1_out(0)
            pk = ca.MX.sym("pk", K * npar)
            r = split[1].map(K, "serial")(ca.reshape(pk, npar, K), *args)
            ins.append(pk)
            pre = cls._pre(f"{f.symbolic['res'].name()}_vec_stages", split[0], K, nc, nd)
        r = ca.vec(r)
        functions["vec"] = ca.Function(f"{f.symbolic['res'].name()}_vec_stages", ins, [0.5 * ca.sumsqr(r), r])
        if pre is not None:
            functions["vec_shared"] = pre
        layouts["vec"] = (True, [], [], 1, [K * f.m])
        return functions, layouts

    @staticmethod
    def _pre(name, pre, K, nc, nd):
        """The shared part (:func:`_shared_split`) of K instances: (z_cal (K nc), d (K nd)) -> p (K np)."""
        zc, d = ca.MX.sym("zc", K * nc), ca.MX.sym("d", K * nd)
        return ca.Function(f"{name}_shared", [zc, d], [ca.vec(pre.map(K, "serial")(ca.reshape(zc, nc, K),
                                                                                  ca.reshape(d, nd, K)))])

    def shared_values(self, mode, zc, D, J):
        """p of the shared part of ``mode``'s functions for the K instances of a stage group, from
        their calibration inputs zc and the data D (J K, nd) of all stage groups; None if the mode
        has none, or if the declared-shared columns (FactorBlock.shared_data) differ between stage
        groups in these data (the calls then use the functions without a shared part)."""
        pre = self.fns.get(f"{mode}_shared")
        if pre is None:
            return None
        K = self.K
        # checked once per data array (a view of the same memory counts as the same: the data
        # vector's block is a new view at every assembly; inputs are never modified in place). The
        # array owning the memory is held weakly: once it is gone, its address means nothing
        owner = D
        while isinstance(owner.base, np.ndarray):
            owner = owner.base
        key = (D.__array_interface__["data"][0], D.shape, D.strides)
        if self._checked is None or self._checked[0] != key or self._checked[1]() is not owner:
            # a slab of stages at a time: the shared columns of all stage groups at once are a
            # strided copy as large as the data: 0.18 s per check at 32 triads x 20 000 samples, 0.02 s by slabs
            S, cols = D.reshape(J, K, -1), list(self.shared)
            first = S[0][:, cols]
            same = all((S[j: j + CHECK_STAGES][:, :, cols] == first).all() for j in range(0, J, CHECK_STAGES))
            self._checked = (key, weakref.ref(owner), bool(same))
        if not self._checked[2]:  # not shared in these data: the functions without the shared part
            self._plain()
            return None
        return np.asarray(pre(np.ascontiguousarray(zc).ravel(), np.ascontiguousarray(D[:K]).ravel())).ravel()

    @classmethod
    def _build(cls, name, fn, names, width, red, tgt, K, nc, nd, widths, split=None):
        zc, zs, d = ca.MX.sym("zc", K * nc), ca.MX.sym("zs", fn.size1_in(1)), ca.MX.sym("d", K * nd)
        args, ins, pre = [ca.reshape(zc, nc, K), ca.repmat(zs, 1, K), ca.reshape(d, nd, K)], [zc, zs, d], None
        if split is None:
            outs = fn.map(K, "serial")(*args)
        else:  # the shared part computed once per call (input 4, the same for every stage group)
            npar = split[0].size1_out(0)
            pk = ca.MX.sym("pk", K * npar)
            outs = split[1].map(K, "serial")(ca.reshape(pk, npar, K), *args)
            ins.append(pk)
            pre = cls._pre(name, split[0], K, nc, nd)
        loc = {nm: ca.vec(o) for nm, o in zip(names, outs if isinstance(outs, (list, tuple)) else [outs])}
        red_x = [0.5 * ca.sumsqr(loc["r"])] if "r" in loc else []
        red_layout = []
        for src_name, kind, M in red:
            red_x.append(loc[src_name][M.src.tolist()])
            red_layout.append((kind, M))
        # per stage group outputs: each dense target one of its own, the scattered ones together in
        # one; per output {source name: (rows, columns, values)} and its width
        outs: list = []
        scattered = None
        segs = []
        for src_name, M, per_k, (label, key) in tgt:
            t, dest = _groups(M), M.dest
            if 4 * len(dest) >= widths[label]:  # dense output: numpy adds a contiguous slab, no scatter
                t, dest = dest[t], np.arange(widths[label])
            dense = len(dest) == widths[label]
            if dense or scattered is None:
                outs.append([{}, 0])
            o = len(outs) - 1 if dense or scattered is None else scattered
            if not dense:
                scattered = o
            rows, L = outs[o]
            cols = M.src if not per_k else (np.arange(K)[:, None] * width[src_name] + M.src[None, :]).ravel()
            r_, c_, v_ = rows.setdefault(src_name, ([], [], []))
            r_.append(L + (np.tile(t, K) if per_k else t)), c_.append(cols)
            v_.append(np.tile(M.val, K) if per_k else M.val)
            segs.append((label, key, o, L, L + len(dest), None if dense else dest))
            outs[o][1] = L + len(dest)
        res = []
        for rows, L in outs:
            T = ca.MX(L, 1)
            for nm, y in loc.items():
                if nm not in rows:
                    continue
                r_, c_, v_ = rows[nm]
                A = sp.coo_matrix((np.concatenate(v_), (np.concatenate(r_), np.concatenate(c_))),
                                  shape=(L, K * width[nm])).tocsc()
                A.sum_duplicates()
                A = ca.DM(ca.Sparsity(L, K * width[nm], A.indptr.tolist(), A.indices.tolist()), A.data)
                T += ca.mtimes(A, y)
            res.append(ca.densify(T))  # dense: the buffers hold every entry
        red_v = ca.densify(ca.vertcat(*red_x)) if red_x else ca.MX(0, 1)
        F = ca.Function(name, ins, [red_v, *res])
        return F, pre, ("r" in loc, red_layout, segs, red_v.size1(), [L for _, L in outs])

    def __call__(self, mode, zc, zs, D, into: dict | None = None, shared: np.ndarray | None = None):
        """(reduced (Lr,), [per stage group (nJ, L) of each output]) of stage groups with stage inputs
        zs (nJ, ns); ``into``: {output: the (nJ, L) C-contiguous array to write it into} (the others
        are new arrays); ``shared``: the shared values of :meth:`shared_values` (None: the
        functions without a shared part)."""
        nJ = zs.shape[0]
        plain = shared is None and self.fns[mode].n_in() == 4  # data without the shared columns shared
        key = (mode, nJ, not plain, threading.get_ident())
        if key not in self._buffers:
            with self._lock:
                fn = (self._plain() if plain else self.fns)[mode]  # (shared_values)
                mapped = self._maps.get(key[:3])
                if mapped is None:
                    # CasADi's MapSum: zc and the shared data are one column for all stage groups, and
                    # the first output is summed in place (the named map's repmat/repsum would build and
                    # fill nJ copies of both)
                    mapped = self._maps[key[:3]] = fn.map(nJ, [i in (0, 3) for i in range(fn.n_in())],
                                                          [o == 0 for o in range(fn.n_out())])
                self._buffers[key] = mapped, mapped.buffer()
        fn, (buf, run) = self._buffers[key]
        _, _, _, Lr, widths = self.layout[mode]
        red = np.empty(Lr)
        outs = []
        for o, L in enumerate(widths):
            T = (into or {}).get(o)
            if T is None:
                T = np.empty((nJ, L))
            elif T.shape != (nJ, L) or T.dtype != np.float64 or not T.flags.c_contiguous:
                raise ValueError(f"{mode}: output {o} must be a C-contiguous {nJ} x {L} array of doubles")
            outs.append(T)
        args = [np.ascontiguousarray(a, float) for a in (zc, zs, D)]
        if fn.n_in() == 4:
            args.append(np.ascontiguousarray(shared, float))
        for i, a in enumerate(args):
            buf.set_arg(i, memoryview(a))
        buf.set_res(0, memoryview(red))
        for o, T in enumerate(outs):
            buf.set_res(o + 1, memoryview(T))
        run()
        return red, outs

    @staticmethod
    def target(parts, label, key, fi, j0, j1, base):
        """The slab (j1 - j0, width) of the assembled array that segment (label, key) of stage groups
        j0 ... j1 lands on (None: the parts have no such array)."""
        if label == "G":
            return parts.G[fi][base + key + j0: base + key + j1]
        if label == "Hsc":
            return None if parts.Hsc is None else parts.Hsc[fi][base + key + j0: base + key + j1].reshape(j1 - j0, -1)
        d, o = key
        return (parts.B if label == "B" else parts.Bgn)[fi][o][base + d + j0: base + d + j1].reshape(j1 - j0, -1)

    def slabs(self, parts, mode, direct, fi, base):
        """(j0, j1) -> {output: its slab of the assembled array} for the segments ``direct``, which
        the calls write in place (``into`` of :meth:`__call__`); None if there are none."""
        if not direct:
            return None
        segs = [self.layout[mode][2][si] for si in sorted(direct)]
        return lambda j0, j1: {o: self.target(parts, label, key, fi, j0, j1, base) for label, key, o, *_ in segs}

    def add(self, parts, mode, red, outs, j0, j1, base, fi, direct=frozenset()):
        """Add one call's results to the assembled parts, but for the segments ``direct``, which
        the call wrote in place."""
        has_r, red_layout, segs, _, _ = self.layout[mode]
        pos = 0
        if has_r:
            parts.f += float(red[0])
            pos = 1
        for kind, M in red_layout:
            n = len(M.src)
            target = parts.gc if kind == "gc" else parts.hcc
            if target is not None:
                target[M.dest] += _reduce(M, red[pos: pos + n])
            pos += n
        nJ = j1 - j0
        for si, (label, key, o, a, b, dest) in enumerate(segs):
            tgt = None if si in direct else self.target(parts, label, key, fi, j0, j1, base)
            if tgt is None:
                continue
            T = outs[o]
            if dest is None:  # every target entry, in order
                tgt += T[:, a:b]
            elif self.flat_add and tgt.flags.c_contiguous:
                # by flat indices into the slab: one addition per entry as below, in a third of the
                # time of numpy's (rows, columns) fancy indexing (the gyroscopes' 198 of 1620 H_mθ
                # entries per sample on MIMU4444 exp_1)
                flat = self._flat.get((mode, si, nJ))
                if flat is None:
                    flat = self._flat[mode, si, nJ] = (np.arange(nJ)[:, None] * tgt.shape[1] + dest).ravel()
                np.add.at(tgt.reshape(-1), flat, T[:, a:b].ravel())
            else:
                tgt[:, dest] += T[:, a:b]


class _Unit:
    """What :meth:`Projection.assemble` evaluates: block ``parent`` (index into the blocks) or its
    instances ``rows`` (a slice; None: all), as Block ``b``, staged ``st`` = (family index,
    StagedBlock) or not (None), with instance ``order`` (None: as given), the local entries'
    ``plan``, and either its stage functions or (fn, plan) for the inner steps."""

    def __init__(self, b, parent, rows, order, st, plan):
        self.b, self.parent, self.rows, self.order, self.st, self.plan = b, parent, rows, order, st, plan
        self.stage_fns, self.inner = None, None
        self.direct: dict = {}  # mode -> the stage functions' segments written in place (Projection._direct)


class _Parts:
    """The assembled pieces at one point: objective, calibration gradient and Hessian, and per
    family the stage gradient G (R, m), the stage Hessian blocks B[o] (R - o, m, m) and the
    coupling Hsc (R, m, c)."""

    def __init__(self, c, fams, cal: bool, gn: bool = False, grad: bool = False):
        self.f = 0.0
        self.gc = np.zeros(c) if cal or grad else None
        self.hcc = np.zeros(c * c) if cal else None
        self.G = [np.zeros((f.R, f.m)) for f in fams]
        self.B = [[np.zeros((f.R - o, f.m, f.m)) for o in range(f.width)] for f in fams]
        self.Hsc = [np.zeros((f.R, f.m, c)) for f in fams] if cal else None
        self.Bgn = [[np.zeros((f.R - o, f.m, f.m)) for o in range(f.width)] for f in fams] if gn else None

    def arrays(self) -> dict:
        """{(label, family, offset): array} of the stage arrays (offset: of a Hessian block B[o], else None)."""
        out = {}
        for fi in range(len(self.G)):
            out["G", fi, None] = self.G[fi]
            if self.Hsc is not None:
                out["Hsc", fi, None] = self.Hsc[fi]
            for label, blocks in (("B", self.B), ("Bgn", self.Bgn)):
                for o, a in enumerate(blocks[fi] if blocks is not None else []):
                    out[label, fi, o] = a
        return out

    def zero(self, skip=frozenset()) -> "_Parts":
        """Reset to zero in place, but for the arrays ``skip`` ((label, family, offset) of
        :meth:`arrays`) that the next assembly writes whole: reusing the arrays saves the page
        faults of fresh ones (at 32 x 20 000 the coupling alone is 134 MB, a quarter of an assembly
        when touched fresh)."""
        self.f = 0.0
        for a in [self.gc, self.hcc, *(a for k, a in self.arrays().items() if k not in skip)]:
            if a is not None:
                a.fill(0.0)
        return self


class _Factor:
    """Cholesky factor L of a family's stage Hessian (block diagonal: per stage; block banded:
    LAPACK band storage). ``lower(v)`` = L^-1 v, ``upper(v)`` = L^-T v for v (R, m, k).

    A block-diagonal stage whose Hessian is singular to rounding (a direction no reading
    determines, e.g. the specific force along an axis that every accelerometer has masked at
    that sample; with no process model nothing else ties it) is inverted on its range only:
    Linv = W^-1/2 V^T over the eigenvalues above NULL_TOL times the largest, zero rows for the
    others, so Linv^T Linv is the pseudo-inverse. Those directions then take no step and add
    nothing to the reduced problem, as they add nothing to the objective. An eigenvalue below
    -NULL_TOL times the largest is an indefinite stage: LinAlgError, as from the Cholesky."""

    NULL_TOL = 1e-12

    def __init__(self, B):
        self.R, self.m = B[0].shape[0], B[0].shape[1]
        if len(B) == 1:
            B0 = B[0]
            try:
                L = _cholesky(B0)  # entry-major (m, m, R)
                piv = np.einsum("iir->ir", L) ** 2
                null = (piv <= self.NULL_TOL * np.einsum("rii->ri", B0).max(axis=1)[None, :]).any(axis=0)
            except np.linalg.LinAlgError:
                L, null = None, np.ones(self.R, bool)
            if L is None:  # some stage is not positive definite: singular ones are kept, indefinite ones not
                L = np.zeros_like(B0)
                ok = np.zeros(self.R, bool)
                for s0 in range(0, self.R, 1024):
                    w = np.linalg.eigvalsh(B0[s0: s0 + 1024])
                    if (w[:, 0] < -self.NULL_TOL * np.abs(w[:, -1])).any():
                        raise np.linalg.LinAlgError("a stage Hessian is not positive semidefinite")
                    ok[s0: s0 + 1024] = w[:, 0] > self.NULL_TOL * w[:, -1]
                L[ok] = np.linalg.cholesky(B0[ok])
                null = ~ok
                L = np.ascontiguousarray(L.transpose(1, 2, 0))
            if null.any():  # their inverse is replaced below
                L[:, :, null] = np.eye(self.m)[:, :, None]
            self.Linv = _lower_inverse(L)
            if null.any():
                w, V = np.linalg.eigh(B0[null])
                keep = w > self.NULL_TOL * np.abs(w[:, -1:])
                self.Linv[null] = np.swapaxes(V * np.where(keep, 1.0 / np.sqrt(np.where(keep, w, 1.0)), 0.0)[:, None, :],
                                              1, 2)
            self.L = None
        else:
            self.L = sla.cholesky_banded(_banded(B, self.m), lower=True, check_finite=False)

    def lower(self, v):
        if self.L is None:
            return np.matmul(self.Linv, v)
        k = v.shape[2]
        return _tbtrs(self.L, np.asfortranarray(v.reshape(-1, k))).reshape(self.R, self.m, k)

    def lower_gram(self, v, threads: int = 1):
        """(Y, the upper triangle of YᵀY (k, k)) for Y = L^-1 v (R m, k) of v (R, m, k), C-contiguous:
        block diagonal, in v's storage. The Gram matrix of the stages' two halves, each on a worker
        thread with ``threads`` > 1 (numpy's matmul and BLAS run without the GIL), summed; within a
        half, slab after slab of GRAM_ROWS rows, each L^-1 v of the slab followed by BLAS's rank-k
        update with it while it is in cache (block banded: after the band solve of the whole). The
        same operations in the same order on any number of threads, so the same result."""
        k = v.shape[2]
        Y = v if self.L is None else self.lower(v)
        step = max(1, GRAM_ROWS // self.m)

        def half(s0, s1):
            acc = np.zeros((k, k), order="F")
            for a in range(s0, s1, step):
                b = min(s1, a + step)
                if self.L is None:
                    Y[a:b] = np.matmul(self.Linv[a:b], Y[a:b])
                _syrk_update(acc, Y[a:b].reshape(-1, k))
            return acc

        h = self.R // 2
        a, b = map_threads(lambda s: half(*s), ((0, h), (h, self.R)), threads if h else 1)
        return Y.reshape(-1, k), a + b

    def upper(self, v):
        if self.L is None:
            return np.matmul(self.Linv.transpose(0, 2, 1), v)
        k = v.shape[2]
        return _tbtrs(self.L, np.asfortranarray(v.reshape(-1, k)), "T").reshape(self.R, self.m, k)


def _syrk_update(acc: np.ndarray, A: np.ndarray):
    """acc += AᵀA on the upper triangle of acc (k, k), Fortran order, for A (n, k) C-contiguous:
    BLAS's dsyrk (upper, no transpose, on Aᵀ as the Fortran-order (k, n) it is), the routine and
    arguments of ``scipy.linalg.blas.dsyrk(1.0, A.T, beta=1.0, c=acc, trans=0, overwrite_c=1)``,
    so the same bits. Called through scipy's Cython BLAS pointer (:func:`_dsyrk`) by ctypes, which
    releases the GIL for the call: scipy's f2py wrapper holds it, so the two halves of
    :meth:`_Factor.lower_gram` ran one after the other on two threads (0.11 s of rank-k updates per
    Schur complement at 32 x 20 000, on one core whatever the thread count)."""
    f = _dsyrk() if acc.flags.f_contiguous and A.flags.c_contiguous and acc.dtype == A.dtype == np.float64 else None
    if f is None:  # scipy's wrapper, holding the GIL (and copying where the layouts differ)
        out = blas.dsyrk(1.0, A.T, beta=1.0, c=acc, trans=0, overwrite_c=1)
        if out is not acc:
            acc[...] = out
        return
    n, k = A.shape
    if not n or not k:  # nothing to add (and BLAS would refuse a leading dimension of 0)
        return
    i = ctypes.c_int
    f(b"U", b"N", ctypes.byref(i(k)), ctypes.byref(i(n)), ctypes.byref(ctypes.c_double(1.0)), A.ctypes.data,
      ctypes.byref(i(k)), ctypes.byref(ctypes.c_double(1.0)), acc.ctypes.data, ctypes.byref(i(k)))


@functools.lru_cache(maxsize=1)
def _dsyrk():
    """BLAS's dsyrk as scipy links it (``scipy.linalg.cython_blas``), as a ctypes function, or None
    where the pointer cannot be had."""
    try:
        from scipy.linalg import cython_blas

        capsule = cython_blas.__pyx_capi__["dsyrk"]
        # prototypes of their own: ctypes.pythonapi's shared attributes keep their argtypes
        name = ctypes.PYFUNCTYPE(ctypes.c_char_p, ctypes.py_object)(("PyCapsule_GetName", ctypes.pythonapi))
        get = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(("PyCapsule_GetPointer", ctypes.pythonapi))
        pointer = get(capsule, name(capsule))
    except (ImportError, AttributeError, KeyError, ValueError):
        return None
    c_int, c_double = ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_double)
    return ctypes.CFUNCTYPE(None, ctypes.c_char_p, ctypes.c_char_p, c_int, c_int, c_double, ctypes.c_void_p, c_int,
                            c_double, ctypes.c_void_p, c_int)(pointer)


def _cholesky(B: np.ndarray) -> np.ndarray:
    """Cholesky factors of a stack of small SPD matrices B (R, m, m), all R at a time, entry-major:
    L (m, m, R) with L[:, :, r] L[:, :, r]^T = B[r], computed column by column on the entries (each a
    contiguous vector over the stack). np.linalg.cholesky and np.linalg.inv make a LAPACK call per
    matrix: with :func:`_lower_inverse`, 20 000 x 9 x 9 in 15 ms against 39 ms. Raises LinAlgError
    where a pivot is <= 0 or NaN, as LAPACK's potrf does."""
    R, m, _ = B.shape
    A = np.ascontiguousarray(B.transpose(1, 2, 0))  # (m, m, R)
    L = np.zeros((m, m, R))
    for j in range(m):
        d = A[j, j] - np.einsum("kr,kr->r", L[j, :j], L[j, :j])
        if not (d > 0).all():
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        L[j, j] = np.sqrt(d)
        L[j + 1:, j] = (A[j + 1:, j] - np.einsum("ikr,kr->ir", L[j + 1:, :j], L[j, :j])) / L[j, j]
    return L


def _lower_inverse(L: np.ndarray) -> np.ndarray:
    """L^-1 (R, m, m) of lower-triangular matrices with nonzero diagonals given entry-major,
    L (m, m, R) (:func:`_cholesky`), row by row on the entries."""
    m, _, R = L.shape
    X = np.zeros((m, m, R))
    for i in range(m):
        X[i, i] = 1.0 / L[i, i]
        for c in range(i):
            X[i, c] = -np.einsum("kr,kr->r", L[i, c:i], X[c:i, c]) * X[i, i]
    return np.ascontiguousarray(X.transpose(2, 0, 1))


def _inputs(w, W, nc) -> list[np.ndarray]:
    """The local functions' (z_cal, z_stage) of instances W (rows of a block's index matrix)."""
    return [np.take(w, W[:, :nc]), np.take(w, W[:, nc:])]


def _banded(B, m):
    """LAPACK lower band storage ab[i - j, j] = H[i, j] of the block-banded symmetric matrix with
    blocks B[o][s] = H[stage s, stage s + o]."""
    R = B[0].shape[0]
    ab = np.zeros((len(B) * m, R * m))
    a, b = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    for o, Bo in enumerate(B):
        diff = o * m + a - b
        ok = diff >= 0
        ab[diff[ok][None, :], np.arange(R - o)[:, None] * m + b[ok][None, :]] = Bo[:, b[ok], a[ok]]
    return ab


def _tbtrs(L, rhs, trans="N"):
    x, info = lapack.dtbtrs(L, rhs, uplo="L", trans=trans, overwrite_b=1)
    if info:
        raise np.linalg.LinAlgError("singular band factor")
    return x


class Projection:
    """The reduced objective φ(θ) of the calibration variables θ (every free variable outside the
    nuisance families, in layout order), its gradient and exact Hessian, and the elimination of
    the families at any point. Built by :meth:`build`, which compiles the blocks' local functions.

    Scaled variables throughout (x = value / scale); stage values Xs: one (R, m) array per family.
    """

    threads = 1  # worker threads of the stage functions (:meth:`stage_calls`; SolverOptions.threads)
    shortcut = True  # accept the gradient at the Newton point (False: a full evaluation there, as a reference)
    # the largest Newton decrement (relative to 1 + f) from which the Hessian is accepted one step
    # early: any (a failed attempt costs one gradient evaluation, a quarter of a full one; the
    # optimum depends on the gradient only). At 32 x 20 000 from the nominal geometry (decrements
    # 0.06 and 0.1 of f at the first two iterates): 5 full evaluations instead of 7 (1e-3), the
    # same 4 IPOPT iterations and optimum
    shortcut_dec = np.inf
    shortcuts = 0  # reduced() evaluations accepted after one full evaluation and an objective check
    # the largest Newton decrement (relative to 1 + f) of the previous point's prediction from which
    # the next point is tried on the gradient alone first (:meth:`_grad_first`); near the optimum the
    # prediction's decrement falls quadratically (at 32 x 20 000: 0.06, 0.1, 6e-5, 2e-13, 1e-24)
    grad_first_dec = 1e-9
    grad_firsts = 0  # reduced() evaluations accepted on the gradient alone
    _last_dec = np.inf
    max_inner = 60  # Newton steps on the nuisance at one θ
    inner_tol = 1e-12  # Newton decrement (χ²/2 units) at which the nuisance counts as converged, relative to 1 + f

    @classmethod
    def build(cls, blocks: list[Block], layout: Layout, hessian: str, jit: bool) -> tuple["Projection | None", str]:
        """The projection of a problem, or None if it has no nuisance family to eliminate or nothing
        else to estimate (the motion alone, for a known geometry: the full NLP is that problem), and
        what was eliminated or why not (``Solver.elimination_note``, the results' status)."""
        fams, staged, refused = find_families(layout, blocks)
        kept = f"; not eliminated: {'; '.join(refused)}" if refused else ""
        if not fams or sum(f.X.size for f in fams) == layout.n_x:
            for i in staged:  # undo the reordering
                blocks[i].reorder(np.argsort(blocks[i].order))
            why = "nothing else to estimate" if fams else "no nuisance rows to eliminate"
            return None, f"full NLP ({why}){kept}"
        done = ", ".join(f"{f.R} x {f.m} ({', '.join(g.name for g in f.groups)})" for f in fams)
        return cls(blocks, layout, fams, staged, hessian, jit), f"eliminated: {done}{kept}"

    def __init__(self, blocks, layout, fams, staged, hessian: str, jit: bool):
        self.layout, self.blocks = layout, blocks
        # the Newton point's gradient is accepted with the exact Hessian only: Gauss-Newton steps
        # on the nuisance converge linearly, and the tests' agreement with the full NLP suffers
        self.shortcut = self.shortcut and hessian == "exact"
        n = self.n = layout.n_x
        self.fams = fams
        in_fam = np.zeros(n, bool)
        for f in fams:
            in_fam[f.X.ravel()] = True
        self.cal = np.flatnonzero(~in_fam)
        c = self.c = len(self.cal)
        self.tpos = np.full(n, -1)
        self.tpos[self.cal] = np.arange(c)
        self.xscale = xs = layout.x_scale
        cache, inner_cache = {}, {}
        self.units: list[_Unit] = []  # what assemble() evaluates: blocks and parts of blocks
        for i, b in enumerate(blocks):
            st = staged.get(i)
            whole = st is not None and st[1][0][0] is None
            # a block cut into segments keeps its own compiled functions (unstaged) for local();
            # stage functions do the assembly (compiled to C only what runs over many instances)
            sf = whole and _StageFunctions.applies(st[1][0][1])
            b.compile(cache, st[1][0][1].n_cal if whole else b.w_idx.shape[1], hessian, jit,
                      ("res", "jac") if st is not None and (sf or not whole) else LOCAL)
            if st is None:
                N, nz = b.w_idx.shape
                self.units.append(_Unit(b, i, None, None, None, _Plan(
                    N, np.zeros(nz, bool), np.zeros((N, nz), int), b.w_idx, b.f.act, b.f.pairs, np.ones(1), 1,
                    self.tpos, xs, n, c)))
                continue
            fi, segs, order = st
            fam = fams[fi]
            for rows, sb, blk in segs:
                applies = _StageFunctions.applies(sb)
                if blk is not b:
                    blk.compile(cache, sb.n_cal, hessian, jit, () if applies else LOCAL, sb.J * sb.K)
                f = blk.f
                many = f.compiled  # where they run over enough instances, else CasADi's virtual machine
                u = _Unit(blk, i, rows, order, (fi, sb),
                          _Plan(sb.K, sb.is_st, sb.rel, sb.q, f.act, f.pairs, fam.scale, fam.m, self.tpos, xs, n, c))
                key = (id(blk.block.residual), blk.order.tobytes(), sb.n_cal)
                if key not in inner_cache:
                    inner_cache[key] = inner_function(blk.block.residual, blk.order, sb.n_cal, hessian, jit)
                fn, pairs_s, act_s = inner_cache[key]
                inner_plan = _Plan(sb.K, sb.is_st, sb.rel, sb.q, act_s, pairs_s, fam.scale, fam.m, self.tpos, xs, n, c)
                if applies:
                    u.stage_fns = _StageFunctions(f, fn, u.plan, inner_plan, sb, fam.m, c, many,
                                                  blk.block.shared_data)
                else:
                    u.inner = (compiled({"inner": fn}, f.work, many).result()["inner"], inner_plan)
                self.units.append(u)
        self.stage_fns = [u.stage_fns for u in self.units if u.stage_fns is not None]
        for sf in self.stage_fns:  # built once every library is: gcc compiled them side by side
            sf.fns  # noqa: B018
        self._written = {mode: self._direct(mode) for mode in ("grad", "full", "info", "inner")}
        self.prior = layout.priors()
        self.data = None
        self._cache, self._anchor, self._factors, self._pending, self._lazy = None, None, None, None, None
        self._reused: dict = {}  # _Parts reused by reduced() and marginal()

    def _direct(self, mode: str) -> frozenset:
        """Set each staged unit's ``direct[mode]``: its dense segments that the stage functions
        write in place (:attr:`_StageFunctions.direct`), those whose array (label, family, offset) no
        earlier unit and no other segment of the unit writes and whose stage groups cover all its
        rows; returns those arrays (:meth:`_Parts.zero` leaves them)."""
        written, whole = set(), set()
        for u in self.units:
            if u.st is None:  # the calibration entries alone
                continue
            fi, sb = u.st
            fam = self.fams[fi]
            if u.stage_fns is None:  # numpy's additions (_scatter): any array of the family
                written |= {(label, fi, o) for label in ("G", "Hsc", "B", "Bgn")
                            for o in ([None] if label in ("G", "Hsc") else range(fam.width))}
                continue
            segs = u.stage_fns.layout[mode][2]
            arrays = [(label, fi, key[1] if label in ("B", "Bgn") else None) for label, key, *_ in segs]
            u.direct[mode] = frozenset(
                si for si, (label, key, _, _, _, dest) in enumerate(segs)
                if dest is None and arrays[si] not in written
                and arrays.count(arrays[si]) == 1
                and sb.base + (key[0] if label in ("B", "Bgn") else key) == 0
                and sb.J == fam.R - (arrays[si][2] or 0))
            whole |= {arrays[si] for si in u.direct[mode]}
            written |= set(arrays)
        return frozenset(whole)

    # -- evaluation --------------------------------------------------------------------------------
    def x_full(self, theta, Xs) -> np.ndarray:
        x = np.empty(self.n)
        x[self.cal] = theta
        for f, X in zip(self.fams, Xs):
            x[f.X] = X
        return x

    def split(self, x):
        return x[self.cal], [x[f.X] for f in self.fams]

    def _data(self, i, data):
        b = self.blocks[i]
        if data is None:
            return b.data
        return data[b.data_offset: b.data_offset + b.block.n * b.f.nd].reshape(b.block.n, b.f.nd)

    def local(self, x, pf, data, which: str, into: np.ndarray | None = None) -> list[np.ndarray]:
        """One local function (res or jac) of every block over all instances, original order;
        ``into``: the blocks' results one after the other in this array (no copies of them)."""
        w = np.concatenate([x * self.xscale, pf])
        out, off = [], 0
        whole = {u.parent: u for u in self.units if u.stage_fns is not None and u.rows is None and u.order is None}
        for i, b in enumerate(self.blocks):
            fn = getattr(b.f, which)
            D = self._data(i, data)
            nc = b.f.n_cal
            size = fn.size1_out(0) * fn.size2_out(0)
            R = np.empty((b.block.n, size)) if into is None else into[off: off + b.block.n * size].reshape(b.block.n, size)
            off += b.block.n * size
            if which == "res" and i in whole:  # a stage group at a time: the calibration inputs gathered once
                sb = whole[i].st[1]
                def rows(j0, j1, R=R, K=sb.K):
                    return {0: R[j0 * K: j1 * K].reshape(j1 - j0, -1)}

                for _ in self.stage_calls(whole[i].stage_fns, "vec", w, b.w_idx, D, sb.K, sb.J, nc, rows):
                    pass  # written in place
                out.append(R)
                continue
            for t0 in range(0, b.block.n, CHUNK):
                t1 = min(b.block.n, t0 + CHUNK)
                b.f(fn, _inputs(w, b.w_idx[t0:t1], nc) + [D[t0:t1]], [R[t0:t1]])
            out.append(R)
        return out

    def stage_calls(self, sf, mode, w, W, D, K, J, nc, into=None):
        """The stage functions ``sf`` of a staged block over its J stage groups (K instances each;
        index matrix W, data D, w the layout's values), a chunk of STAGE_CHUNK instances per call:
        yields (j0, j1, (reduced, per stage group)) in chunk order. ``into``: (j0, j1) -> the
        arrays that outputs are written into (:meth:`_StageFunctions.__call__`), e.g. the
        per-instance residuals of mode "vec".

        With ``threads`` > 1 the calls run on that many worker threads (the compiled code runs
        without the GIL), at most two chunks per thread ahead of the consumer; every chunk is the
        same call with the same inputs and the consumer adds them up in the same order, so the
        results are identical to one thread's."""
        Zc = np.take(w, W[:K, :nc])
        pk = sf.shared_values(mode, Zc, D, J)  # once per call (a triad's T, say), not per sample
        step = max(1, STAGE_CHUNK // K)
        spans = [(j0, min(J, j0 + step)) for j0 in range(0, J, step)]

        def call(j0, j1):
            return sf(mode, Zc, np.take(w, W[j0 * K: j1 * K: K, nc:]), D[j0 * K: j1 * K].reshape(j1 - j0, -1),
                      into=None if into is None else into(j0, j1), shared=pk)

        if self.threads <= 1 or len(spans) < 2:
            for j0, j1 in spans:
                yield j0, j1, call(j0, j1)
            return
        workers, pending = pool(self.threads), collections.deque()
        try:
            for j0, j1 in spans:
                pending.append((j0, j1, workers.submit(call, j0, j1)))
                if len(pending) > 2 * self.threads:
                    a, b, fut = pending.popleft()
                    yield a, b, fut.result()
            while pending:
                a, b, fut = pending.popleft()
                yield a, b, fut.result()
        finally:  # an error in one chunk: the others finish before their inputs go away
            for *_, fut in pending:
                fut.cancel() or fut.exception()

    def residuals(self, x, pf, data):
        """Every whitened residual (the blocks', instance by instance, then the priors'), written
        into one array (at 32 x 20 000 it is 31 MB: no per-block arrays and no concatenation)."""
        pi, pm, ps = self.prior
        n = sum(b.block.n * b.f.res.size1_out(0) * b.f.res.size2_out(0) for b in self.blocks)
        r = np.empty(n + len(pi))
        self.local(x, pf, data, "res", into=r[:n])
        r[n:] = (x[pi] * self.xscale[pi] - pm) / ps
        return r

    def assemble(self, theta, Xs, pf, data, mode: str, reuse: bool = False) -> _Parts:
        """mode: "grad" (objective and gradient), "inner" (stage derivatives), "full" (all
        derivatives), "info" (J^T J).
        ``reuse``: into the arrays of the previous reusing call (which must no longer be needed)."""
        c = self.c
        slot = "coupled" if mode in ("full", "info") else mode  # the same arrays
        if reuse and self._reused.get(slot) is not None:
            parts = self._reused[slot].zero(self._written[mode] if _StageFunctions.direct else ())
        else:
            parts = _Parts(c, self.fams, mode in ("full", "info"), mode == "inner", mode == "grad")
            if reuse:
                self._reused[slot] = parts
        w = np.concatenate([self.x_full(theta, Xs) * self.xscale, pf])
        for u in self.units:
            b, st = u.b, u.st
            f = b.f
            D = self._data(u.parent, data)
            if u.rows is not None:
                D = D[u.rows]
            W = b.w_idx
            if st is None:
                K, J, base, fi, plan = len(W), 1, 0, None, u.plan
                fn = {"full": f.rgh, "grad": f.rgh, "info": f.gn}.get(mode, f.res)
                step = 1
            else:
                fi, sb = st
                if u.order is not None:
                    W, D = W[u.order], D[u.order]
                K, J, base = sb.K, sb.J, sb.base
                if u.stage_fns is not None:  # a stage group at a time, summed in compiled code
                    sf = u.stage_fns
                    direct = u.direct[mode] if sf.direct else frozenset()
                    into = sf.slabs(parts, mode, direct, fi, base)
                    for j0, j1, (red, outs) in self.stage_calls(sf, mode, w, W, D, K, J, f.n_cal, into):
                        sf.add(parts, mode, red, outs, j0, j1, base, fi, direct)
                    continue
                if mode == "inner":
                    fn, plan = u.inner
                else:
                    fn, plan = {"full": f.rgh, "grad": f.rgh, "info": f.gn}[mode], u.plan
                step = max(1, CHUNK // K)
            nc = f.n_cal
            if st is None:  # the whole block at once: its entries go through one map
                outs = [np.empty((len(W), fn.size1_out(k))) for k in range(fn.n_out())]
                for t0 in range(0, len(W), CHUNK):
                    t1 = min(len(W), t0 + CHUNK)
                    b.f(fn, _inputs(w, W[t0:t1], nc) + [D[t0:t1]], [o[t0:t1] for o in outs])
                self._scatter(parts, fn, outs, plan, mode, 0, 1, 0, None)
                continue
            for j0 in range(0, J, step):
                j1 = min(J, j0 + step)
                t0, t1 = j0 * K, j1 * K
                outs = [np.empty((t1 - t0, fn.size1_out(k))) for k in range(fn.n_out())]
                b.f(fn, _inputs(w, W[t0:t1], nc) + [D[t0:t1]], outs)
                self._scatter(parts, fn, outs, plan, mode, j0, j1, base, fi)
        pi, pm, ps = self.prior
        pr = (w[pi] - pm) / ps
        parts.f += 0.5 * float(pr @ pr)
        if parts.gc is not None and len(pi):
            t = self.tpos[pi]
            s = self.xscale[pi] / ps
            np.add.at(parts.gc, t, pr * s if mode != "info" else 0.0)
            if parts.hcc is not None:
                np.add.at(parts.hcc, t * c + t, s * s)
        return parts

    def _scatter(self, parts, fn, outs, plan, mode, j0, j1, base, fi):
        nJ = j1 - j0
        if mode == "info":
            g, h = None, outs[0]
        else:
            r, g, h = outs[:3] if len(outs) >= 3 else (outs[0], None, None)
            parts.f += 0.5 * float(np.einsum("ij,ij->", r, r))
            if h is None:
                return
        K = 1 if fi is None else plan.K
        if g is not None and g.shape[1]:
            V = g.reshape(nJ, -1)
            if plan.gc is not None and parts.gc is not None:
                parts.gc[plan.gc.dest] += plan.gc(V.sum(axis=0, keepdims=True))[0]
            if plan.gs:
                Vk = V.reshape(nJ, K, -1).sum(axis=1)
                for d, M in plan.gs.items():
                    parts.G[fi][base + d + j0: base + d + j1][:, M.dest] += M(Vk)
        if not h.shape[1] or mode == "grad":
            return
        V = h.reshape(nJ, -1)
        if plan.hcc is not None and parts.hcc is not None:
            parts.hcc[plan.hcc.dest] += plan.hcc(V.sum(axis=0, keepdims=True))[0]
        if fi is None:
            return
        Vk = V.reshape(nJ, K, -1).sum(axis=1)
        if parts.Hsc is not None:
            for d, M in plan.hsc.items():
                parts.Hsc[fi][base + d + j0: base + d + j1].reshape(nJ, -1)[:, M.dest] += M(V)
        for (d, o), M in plan.hss.items():
            parts.B[fi][o][base + d + j0: base + d + j1].reshape(nJ, -1)[:, M.dest] += M(Vk)
        if mode == "inner" and len(outs) == 4:  # the Gauss-Newton Hessian too
            Vk = outs[3].reshape(nJ, K, -1).sum(axis=1)
            for (d, o), M in plan.hss.items():
                parts.Bgn[fi][o][base + d + j0: base + d + j1].reshape(nJ, -1)[:, M.dest] += M(Vk)

    # -- elimination -------------------------------------------------------------------------------
    def _tangent(self, fi, X, pf):
        """Basis Z (R, m, m') of the tangent space of the family's unit-norm rows at X (scaled), and
        the constraint gradients [(positions, a (R, k))]; (None, []) without unit-norm rows."""
        fam = self.fams[fi]
        if not fam.unit:
            return None, []
        N = np.zeros((fam.R, fam.m, len(fam.unit)))
        grads = self._constraint_gradients(fi, X)
        for u, (pos, a) in enumerate(grads):
            N[:, pos, u] = a
        U = np.linalg.svd(N, full_matrices=True)[0]
        return U[:, :, len(fam.unit):], grads

    def _constraint_gradients(self, fi, X):
        """[(positions, a (R, k))]: the gradient 2 x scale² of each unit-norm row group of family fi
        at X (scaled)."""
        fam = self.fams[fi]
        return [(pos, 2 * X[:, pos] * fam.scale[pos] ** 2) for pos, _ in fam.unit]

    def eliminate(self, parts, Xs, pf, coupling: bool, curvature: bool, damping: float = 0.0,
                  limit: float = np.inf, gauss_newton: bool = False):
        """Eliminate every family: returns (dec, steps, S, g) with dec = sum G^T H^-1 G (tangent),
        steps the Newton steps of the stage variables (scaled), and with ``coupling`` the Schur
        complement S = Hcc - Hcs H^-1 Hsc and the reduced gradient g = gc - Hcs H^-1 G; the
        factors are kept for the predictor (self._factors). With ``coupling`` and a decrement
        above ``limit``, S and g are None and :meth:`couple` or :meth:`reduced_gradient` finish
        the elimination from the factors kept in ``self._pending``."""
        c = self.c
        S = parts.hcc.reshape(c, c).copy() if coupling else None
        g = parts.gc.copy() if coupling else None
        dec, steps = 0.0, []
        prepared = []
        self._pending = None
        for fi, fam in enumerate(self.fams):
            B = (parts.Bgn if gauss_newton else parts.B)[fi]
            G, B = parts.G[fi], [b.copy() for b in B] if (damping or fam.unit) else B
            Z, grads = self._tangent(fi, Xs[fi], pf)
            if Z is not None:
                if curvature:
                    for pos, a in grads:
                        lam = -np.einsum("rk,rk->r", a, G[:, pos]) / np.einsum("rk,rk->r", a, a)
                        B[0][:, pos, pos] += lam[:, None] * 2 * fam.scale[pos] ** 2
                G = np.einsum("rmk,rm->rk", Z, G)
                B = [np.einsum("rma,rmn,rnb->rab", Z[: fam.R - o], Bo, Z[o:]) for o, Bo in enumerate(B)]
            if damping:  # Levenberg-Marquardt, relative to the mean diagonal
                B[0] += damping * float(np.einsum("rii->", B[0])) / B[0].shape[0] / B[0].shape[1] * np.eye(B[0].shape[1])
            F = _Factor(B)
            y = F.lower(G[:, :, None])
            dec += float(np.einsum("ijk,ijk->", y, y))
            step = -F.upper(y.copy())[:, :, 0]  # the band solve overwrites its right-hand side; y serves the coupling
            if Z is not None:
                step = np.einsum("rmk,rk->rm", Z, step)
            steps.append(step)
            prepared.append((F, y, Z))
        if coupling and dec > limit:
            self._pending = (parts, prepared)  # :meth:`couple` finishes this elimination
            return dec, steps, None, None
        S, g = self._couple(parts, prepared, S, g, coupling)
        return dec, steps, S, g

    def recheck(self, grad: _Parts, Xs):
        """At the Newton point Xs of the elimination that :meth:`eliminate` left at its limit, with
        the gradient ``grad`` assembled there: (decrement, Newton steps) by the factors of that
        elimination (its Hessian, one step earlier: the error is of the order of the step times
        this gradient, which is at the tolerance). Unit-norm rows take the gradient in their
        tangent space at Xs, the factors' basis carried there (:meth:`_carried`)."""
        _, prepared = self._pending
        dec, steps, ys, Zs = 0.0, [], [], []
        for fi, ((F, _, Z), G) in enumerate(zip(prepared, grad.G)):
            y, step, Z = self._earlier_factors_step(fi, F, Z, G, Xs[fi])
            dec += float(np.einsum("ijk,ijk->", y, y))
            steps.append(step), ys.append(y), Zs.append(Z)
        self._recheck = ys, Zs
        return dec, steps

    def _earlier_factors_step(self, fi, F, Z, G, X):
        """(y = L⁻¹ G, the Newton step −H⁻¹ G, the tangent basis used) of family fi's gradient G at
        X by the factors F of an earlier point (tangent basis Z there): unit-norm rows take G in Z
        carried to X (:meth:`_carried`), and the step comes back to the stage variables."""
        if Z is not None:
            Z = self._carried(fi, Z, X)
            G = np.einsum("rmk,rm->rk", Z, G)
        y = F.lower(G[:, :, None].copy())
        step = -F.upper(y.copy())[:, :, 0]
        return y, step if Z is None else np.einsum("rmk,rk->rm", Z, step), Z

    def _carried(self, fi, Z, X):
        """The tangent basis Z (R, m, m') of family fi's unit-norm rows carried to X (scaled): its
        projection onto the tangent space there, which moves with X as continuously as X (a basis
        of its own, :meth:`_tangent`'s, may turn within the tangent space); within the order of the
        step of Z. The rows' groups share no positions: projected one at a time."""
        Z = Z.copy()
        for pos, n in self._constraint_gradients(fi, X):
            Zp = Z[:, pos, :]
            Z[:, pos, :] = Zp - n[:, :, None] * (np.einsum("rk,rka->ra", n, Zp) / np.einsum("rk,rk->r", n, n)[:, None])[:, None, :]
        return Z

    def couple(self) -> np.ndarray:
        """The Schur complement S of the elimination that :meth:`eliminate` left at its limit (its
        factors kept); its reduced gradient is :meth:`reduced_gradient`'s."""
        parts, prepared = self._pending
        self._pending = None
        c = self.c
        return self._couple(parts, prepared, parts.hcc.reshape(c, c).copy(), None, True)[0]

    def _lazy_hessian(self) -> np.ndarray:
        """The Schur complement of the evaluation that :meth:`reduced` left pending (its factors
        and coupling still in place); the predictor's anchor then keeps L^-1 Hsc."""
        S = self.couple()
        self._lazy = None
        if self._anchor is not None:
            self._anchor = (*self._anchor[:2], self._factors, True)
        return S

    def reduced_gradient(self, gc=None):
        """The reduced gradient g = gc - Hcs H^-1 G of the elimination that :meth:`eliminate` left
        at its limit, without the Schur complement: H^-1 G by the factors' band solves and one
        product with the coupling (a fiftieth of the Schur complement's work at 32 x 20 000).
        With ``gc``, from the stage gradients of :meth:`recheck` (in its tangent bases). The
        factors stay pending for :meth:`couple` (the Hessian, when IPOPT asks for it), with their
        own tangent bases: the Schur complement of the factors' point."""
        parts, prepared = self._pending
        if gc is not None:
            ys, Zs = self._recheck
            self._pending = (parts, [(F, y, Z) for (F, _, Z), y in zip(prepared, ys)])
            prepared = [(F, y, Z) for (F, _, _), y, Z in zip(prepared, ys, Zs)]
        g = (parts.gc if gc is None else gc).copy()
        for fi, (F, y, Z) in enumerate(prepared):
            v = F.upper(y.copy())[:, :, 0]  # H^-1 G (tangent coordinates)
            if Z is not None:
                v = np.einsum("rmk,rk->rm", Z, v)
            g -= v.reshape(-1) @ parts.Hsc[fi].reshape(-1, self.c)
        return g

    def _couple(self, parts, prepared, S, g, coupling):
        """(S - Hcs H^-1 Hsc, g - Hcs H^-1 G) from the factors ``prepared`` (without ``coupling``: (S, g)
        as given; g None: no reduced gradient); keeps the factors for the predictor."""
        factors = []
        for fi, (F, y, Z) in enumerate(prepared):
            Y = None
            if coupling:
                Hsc = parts.Hsc[fi]
                if Z is not None:
                    Hsc = np.einsum("rmk,rmc->rkc", Z, Hsc)
                Y, gram = F.lower_gram(Hsc, self.threads)  # (R m', c), in Hsc's storage where block diagonal
                S -= gram
                if g is not None:
                    g -= Y.T @ y.reshape(-1)
            factors.append((F, Y, Z))
        if coupling:
            S = np.triu(S) + np.triu(S, 1).T  # dsyrk fills the upper triangle
        self._factors = factors
        return S, g

    def _move(self, Xs, steps, alpha, pf):
        out = []
        for fi, (X, s) in enumerate(zip(Xs, steps)):
            Xn = X + alpha * s
            fam = self.fams[fi]
            for pos, fixed in fam.unit:  # back onto the unit sphere
                v = Xn[:, pos] * fam.scale[pos]
                rest = 1.0 - (pf[fixed - self.n] ** 2).sum(axis=1) if fixed.shape[1] else 1.0
                Xn[:, pos] *= np.sqrt(rest / (v * v).sum(axis=1))[:, None]
            out.append(Xn)
        return out

    def inner_solve(self, theta, Xs, pf, data):
        """The stage variables minimising the objective at theta, from Xs: Levenberg-Marquardt
        steps on the Gauss-Newton Hessian while the exact Hessian is not positive definite or the
        decrement is large (near zero motion the exact Hessian is indefinite and Gauss-Newton
        singular), then Newton steps."""
        parts = self.assemble(theta, Xs, pf, data, "inner")
        f, mu = parts.f, 0.0
        for it in range(self.max_inner):
            exact = mu == 0.0
            try:
                dec, steps, _, _ = self.eliminate(parts, Xs, pf, coupling=False, curvature=True, damping=mu,
                                                  gauss_newton=not exact)
            except np.linalg.LinAlgError:
                mu = 1e-6 if exact else mu * 10
                if mu > 1e6:
                    raise np.linalg.LinAlgError("the nuisance variables are not determined by the data") from None
                continue
            if exact and dec <= self.inner_tol * (1.0 + abs(f)):
                return Xs, f - 0.5 * dec, it
            Xn = self._move(Xs, steps, 1.0, pf)
            pn = self.assemble(theta, Xn, pf, data, "inner")
            if pn.f <= f:
                Xs, parts = Xn, pn
                # Newton once the step barely changes the objective
                mu = 0.0 if exact or f - pn.f < 1e-3 * (1.0 + abs(pn.f)) else mu / 10
                f = pn.f
            else:
                mu = 1e-6 if exact else mu * 10
        return Xs, f, self.max_inner

    def predict(self, theta, pf):
        """Stage variables at theta to first order from the last full evaluation: the implicit
        function theorem, dm = -H_mm^-1 H_mθ dθ = -L^-T (Y dθ) with Y = L^-1 H_mθ kept."""
        th, Xs, factors, coupled = self._anchor
        if factors is None:  # given up for their memory (marginal): the last solution as it is
            return Xs
        d = theta - th
        out = []
        for fi, (X, (F, Y, Z)) in enumerate(zip(Xs, factors)):
            if coupled:  # Y = L^-1 H_mθ
                v = (Y @ d).reshape(F.R, F.m, 1)
            else:  # Y = H_mθ (the Schur complement was not needed)
                v = Y.reshape(-1, self.c) @ d
                v = (v.reshape(F.R, -1) if Z is None else np.einsum("rmk,rm->rk", Z, v.reshape(F.R, -1)))
                v = F.lower(v[:, :, None])
            dx = -F.upper(v)[:, :, 0]
            if Z is not None:
                dx = np.einsum("rmk,rk->rm", Z, dx)
            out.append(dx)
        return self._move(Xs, out, 1.0, pf)

    def reduced(self, theta, pf, data, hessian: bool = True):
        """(phi, gradient, Hessian S) of the reduced objective at theta. One full evaluation at the
        predicted stage variables when they are close enough (Newton decrement below inner_tol);
        else Newton iterations on the stage variables alone first. Without ``hessian``, S is None
        and the Schur complement is left pending: a later call at the same theta with ``hessian``
        finishes it from the kept factors (IPOPT asks for it after the objective and gradient of
        an accepted iterate, and never at the last one, whose Schur complement cost a third of a
        full evaluation at 32 x 20 000)."""
        key = (theta.tobytes(), pf.tobytes(), id(data))
        c = self._cache
        if c is not None and c["key"] == key:
            if c["S"] is None and hessian:
                if self._lazy is not c:  # its factors are gone (or never computed): evaluate again
                    self._cache = None
                    return self._evaluate(theta, pf, data, hessian, key, grad_first=False)
                c["S"] = self._lazy_hessian()
            return c["phi"], c["g"], c["S"]
        return self._evaluate(theta, pf, data, hessian, key, grad_first=True)

    def _grad_first(self, theta, Xs, pf, data, factors, key):
        """Accept the predicted stage variables Xs on the gradient alone, with the factors and the
        coupling of the previous point (as the Newton-point shortcut does): when the prediction is
        converged there, φ and ∇φ need no Hessian, and the full evaluation is left to a request for
        the Hessian (IPOPT makes none at its last iterate). None if the decrement is above inner_tol.
        Unit-norm rows take the gradient in the factors' tangent basis carried to Xs."""
        pg = self.assemble(theta, Xs, pf, data, "grad")
        dec, steps, g = 0.0, [], pg.gc.copy()
        for fi, ((F, Y, Z, coupled), G) in enumerate(zip(factors, pg.G)):
            y, step, _ = self._earlier_factors_step(fi, F, Z, G, Xs[fi])
            dec += float(np.einsum("ijk,ijk->", y, y))
            if coupled:  # Y = L^-1 H_mθ: g - Y^T L^-1 G
                g -= Y.T @ y.reshape(-1)
            else:  # Y = H_mθ: g - H_θm H^-1 G
                g += step.reshape(-1) @ Y.reshape(-1, self.c)
            steps.append(step)
        if dec > self.inner_tol * (1.0 + abs(pg.f)):
            return None
        Xs = self._move(Xs, steps, 1.0, pf)
        self.grad_firsts += 1
        self._last_dec = dec / (1.0 + abs(pg.f))
        self._cache = {"key": key, "X": Xs, "phi": pg.f - 0.5 * dec, "g": g, "S": None, "data": data}
        return self._cache["phi"], g, None

    def _evaluate(self, theta, pf, data, hessian, key, grad_first: bool):
        Xs = self.predict(theta, pf) if self._anchor is not None else self._X0
        anchor = self._anchor
        self._anchor = self._factors = self._lazy = None  # as large as the coupling: freed before the next ones
        # the gradient alone with an earlier point's factors (:meth:`_grad_first`)
        if grad_first and not hessian and self.shortcut and self._last_dec <= self.grad_first_dec \
                and anchor is not None and anchor[2] is not None:
            out = self._grad_first(theta, Xs, pf, data, [(*f, anchor[3]) for f in anchor[2]], key)
            if out is not None:
                self._anchor = (theta.copy(), self._cache["X"], anchor[2], anchor[3])
                return out
        prev = None
        first = True
        for it in range(self.max_inner):
            parts = self.assemble(theta, Xs, pf, data, "full", reuse=True)
            limit = self.inner_tol * (1.0 + abs(parts.f))
            if prev is not None and parts.f > prev[1]:  # the full step failed: damped Newton on the stage variables
                Xs, _, _ = self.inner_solve(theta, prev[0], pf, data)
                prev = None
                continue
            try:
                dec, steps, _, _ = self.eliminate(parts, Xs, pf, coupling=True, curvature=True, limit=-np.inf)
            except np.linalg.LinAlgError:
                Xs, _, _ = self.inner_solve(theta, Xs, pf, data)
                continue
            if first:  # how close the prediction was
                self._last_dec, first = dec / (1.0 + abs(parts.f)), False
            if dec <= limit:
                g, f = self.reduced_gradient(), parts.f
                Xs = self._move(Xs, steps, 1.0, pf)  # the last Newton step (its decrement is below inner_tol)
                break
            prev = (Xs, parts.f)
            Xs = self._move(Xs, steps, 1.0, pf)
            # At the Newton point, the gradient alone (a quarter of a full evaluation): if its
            # decrement is below the tolerance, the reduced objective and gradient come from it
            # (with the factors of the step), and the Hessian from the previous point (the
            # Schur complement one Newton step of the nuisance earlier: IPOPT's model, not its
            # stopping test, sees the difference)
            near = self.shortcut and dec <= self.shortcut_dec * (1.0 + abs(parts.f))
            pg = self.assemble(theta, Xs, pf, data, "grad") if near else None
            chk = self.recheck(pg, Xs) if near else None
            if chk is not None and pg.f <= prev[1] and chk[0] <= self.inner_tol * (1.0 + abs(pg.f)):
                dec, steps = chk
                g, f = self.reduced_gradient(pg.gc), pg.f
                Xs = self._move(Xs, steps, 1.0, pf)
                self.shortcuts += 1
                break
        else:
            raise EvaluationError("the nuisance variables did not converge")
        pending = self._pending
        self._anchor = (theta.copy(), Xs, [(F, pending[0].Hsc[fi], Z) for fi, (F, _, Z) in enumerate(pending[1])], False)
        self._cache = self._lazy = {"key": key, "X": Xs, "phi": f - 0.5 * dec, "g": g, "S": None, "data": data}
        if hessian:
            self._cache["S"] = self._lazy_hessian()
        return self._cache["phi"], g, self._cache["S"]

    def hessian(self, theta, pf, data) -> np.ndarray:
        """The reduced Hessian S at theta (:meth:`reduced`)."""
        return self.reduced(theta, pf, data)[2]

    @contextlib.contextmanager
    def kept(self):
        """The state of the solve under way (the evaluation cache, the predictor's anchor, the
        factors pending for the Schur complement) restored on exit: for a side computation at an
        iterate, e.g. the stall test's Newton decrement (:class:`castimate.solver.ipopt.Stall`)."""
        state = {k: getattr(self, k) for k in ("_cache", "_anchor", "_factors", "_pending", "_lazy", "_last_dec")}
        try:
            yield
        finally:
            self.__dict__.update(state)

    def reset(self, x0: np.ndarray, data) -> np.ndarray:
        """Start a solve at layout-order x0 with the data vector (None: the blocks' own); returns
        θ0. The nuisance starts at x0's rows."""
        th0, self._X0 = self.split(x0)
        self.data, self._cache, self._anchor, self._factors, self._lazy = data, None, None, None, None
        self._last_dec = np.inf
        return th0

    def solution(self, theta, pf) -> np.ndarray:
        """Layout-order x at θ with the nuisance at its optimum."""
        self.reduced(theta, pf, self.data, hessian=False)
        return self.x_full(theta, self._cache["X"])

    def gradient(self, x, pf, data) -> np.ndarray:
        """Gradient of the objective w.r.t. every variable (layout order, scaled) at x: the "grad"
        assembly, without the Hessian entries a "full" one would form and drop."""
        th, Xs = self.split(x)
        parts = self.assemble(th, Xs, pf, data, "grad")
        g = np.empty(self.n)
        g[self.cal] = parts.gc
        for f, G in zip(self.fams, parts.G):
            g[f.X] = G
        return g

    def marginal(self, x, pf, data, g: np.ndarray | None = None):
        """Fisher information of the calibration variables with the families eliminated at x:
        (S (c, c), and for a layout-order gradient g the reduced gradient and g_m^T F_mm^-1 g_m)."""
        th, Xs = self.split(x)
        self._lazy = None  # a pending Schur complement's arrays are reused here
        if self._anchor is not None:  # its factors live in the arrays reused here
            self._anchor = (*self._anchor[:2], None, False)
        parts = self.assemble(th, Xs, pf, data, "info", reuse=True)
        if g is not None:
            parts.gc = np.asarray(g, float)[self.cal].copy()
            for G, f in zip(parts.G, self.fams):  # into the reused arrays, which assemblies may write in place
                G[...] = np.asarray(g, float)[f.X]
        else:
            parts.gc = np.zeros(self.c)
        try:
            dec, _, S, gr = self.eliminate(parts, Xs, pf, coupling=True, curvature=False)
        except np.linalg.LinAlgError:
            raise np.linalg.LinAlgError("the nuisance variables are not determined by the data") from None
        self._factors = None
        return S, (gr if g is not None else None), dec

    def nuisance_map(self, x, pf, data):
        """The marginal Fisher information S (c, c) of :meth:`marginal` and, per family,
        D (R, m, c) = H_mm⁻¹ H_mc of the Fisher information (to first order dm = -D dθ; on the
        tangent space of unit-norm rows), for the eliminated Jacobian J_c - J_m D of the HAC
        covariance (:mod:`castimate.solver.serial`). D is as large as the coupling H_mc."""
        th, Xs = self.split(x)
        self._lazy = None  # a pending Schur complement's arrays are reused here
        if self._anchor is not None:  # its factors live in the arrays reused here
            self._anchor = (*self._anchor[:2], None, False)
        parts = self.assemble(th, Xs, pf, data, "info", reuse=True)
        parts.gc = np.zeros(self.c)
        try:
            _, _, S, _ = self.eliminate(parts, Xs, pf, coupling=True, curvature=False)
        except np.linalg.LinAlgError:
            raise np.linalg.LinAlgError("the nuisance variables are not determined by the data") from None
        D = []
        for F, Y, Z in self._factors:
            Dk = F.upper(np.ascontiguousarray(Y.reshape(F.R, F.m, -1)))  # L^-T L^-1 H_mc
            D.append(Dk if Z is None else np.einsum("rmk,rkc->rmc", Z, Dk))
        self._factors = None
        return S, D

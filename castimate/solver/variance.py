"""Variance components: noise levels of residuals estimated from the fit itself.

The one machinery behind both of the package's noise estimators: the process-noise levels of the
motion model (:func:`estimate_levels`, ``motion.process_noise: auto``) and the motion-dependent
measurement noise (:mod:`castimate.solver.motion_noise`, ``noise.motion_dependent``). Each models
the variance of residual j as v_j = Σ_m G_jm θ_m and needs two things from a solution:

1. the redundancy r_j = 1 − h_j of each residual, h_j the diagonal of the hat matrix J P Jᵀ with P
   the Gauss-Newton covariance of all variables (unit-norm constraints respected): the share of its
   own degree of freedom the fit leaves it (:func:`hat_diagonal`; Σ_j h_j = variables − constraints);
2. θ from the residuals and their redundancies (:func:`variance_components`): REML's score
   equations with the hat diagonal (Förstner 1979), Σ_j G_jm (e_j² − r_j v_j) / v_j² = 0. With one
   component per group of rows (the process levels) that is Helmert's estimator as Förstner iterates
   it, σ_k² ← σ_k² · r_kᵀ r_k / ρ_k with ρ_k = Σ_{j∈k} r_j, in closed form.

Iterated with re-solves (the caller's outer iteration), the fixed point is the REML estimate.

The hat diagonal uses the arrow structure of the dynamic problems: the motion states are stages
coupled to their neighbours only (a block-tridiagonal H_mm, as eliminated in
:mod:`castimate.solver.elimination`) and to a dense border θ. With B = H_mm⁻¹ H_mθ and P_θ the
constrained inverse of the Schur complement S = H_θθ − H_θm B,

    j P jᵀ = j_m Σ j_mᵀ + (j_m B − j_θ) P_θ (j_m B − j_θ)ᵀ,

where only the block-tridiagonal part Σ of H_mm⁻¹ is needed (a backward sweep like an RTS
smoother's covariance), so the leverages of all rows cost time linear in the number of samples.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.special import chdtrc  # chi2.sf without scipy.stats's import (1 s of the CLI's start)

from ..errors import NotConvergedError
from ..problem.graph import solver_threads
from .threads import map_threads


def block_rows(solver, name: str) -> np.ndarray:
    """(instances, rows) indices of a factor block's whitened residuals in ``Solver.residuals``
    (and in the rows of ``Solver.jacobians``); -1 where a row is not valid (left out there)."""
    off = 0
    for b in solver.blocks:
        n, m = b.block.n, b.f.m
        keep = np.ones((n, m), bool) if b.block.valid is None else \
            np.broadcast_to(np.asarray(b.block.valid, bool).reshape(n, -1), (n, m))
        if b.block.name == name:
            idx = np.full((n, m), -1)
            idx[keep] = off + np.arange(int(keep.sum()))
            return idx
        off += int(keep.sum())
    raise KeyError(f"no factor block {name!r}")


def selected_inverse(A: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The block-tridiagonal part of the inverse of a symmetric positive-definite block-tridiagonal
    matrix (diagonal blocks A (N, m, m), upper blocks C (N-1, m, m)): (Σ_nn (N, m, m), Σ_n,n+1
    (N-1, m, m)). Forward: D_n = A_n − C_n-1ᵀ D_n-1⁻¹ C_n-1; backward: Σ_n = D_n⁻¹ + F_n Σ_n+1 F_nᵀ,
    Σ_n,n+1 = −F_n Σ_n+1 with F_n = D_n⁻¹ C_n."""
    N = len(A)
    if not C.any():  # independent stages (no process model): the blocks' inverses, in one batched call
        return np.linalg.inv(A), np.zeros_like(C)
    Dinv = np.empty_like(A)
    D = A[0]
    for n in range(N):
        if n:
            D = A[n] - C[n - 1].T @ Dinv[n - 1] @ C[n - 1]
        Dinv[n] = np.linalg.inv(D)
    S, So = np.empty_like(A), np.empty_like(C)
    S[-1] = Dinv[-1]
    for n in range(N - 2, -1, -1):
        F = Dinv[n] @ C[n]
        So[n] = -F @ S[n + 1]
        S[n] = Dinv[n] - So[n] @ F.T
    return 0.5 * (S + S.transpose(0, 2, 1)), So


def _band_cholesky(A: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Band Cholesky factor of the block-tridiagonal matrix of diagonal blocks A (N, m, m) and upper
    blocks C (N-1, m, m), with a ridge of 1e-12 × its largest diagonal where it is singular (a
    direction of one sample that no row reads: its leverage is then 0, not undefined). Returns the
    (possibly regularised) diagonal blocks and the factor (``scipy.linalg.cholesky_banded``'s upper form)."""
    N, m = A.shape[:2]
    u = 2 * m - 1
    ab = np.zeros((u + 1, N * m))
    for a in range(m):
        for b in range(m):
            if b >= a:  # diagonal blocks: row n·m + a, column n·m + b
                ab[u + a - b, b::m] = A[:, a, b]
            ab[u - (m + b - a), m + b::m] = C[:, a, b]  # upper blocks: row n·m + a, column (n+1)·m + b
    try:
        return A, sla.cholesky_banded(ab)
    except np.linalg.LinAlgError:
        ridge = 1e-12 * max(float(ab[u].max(initial=0.0)), 1e-300)
        ab[u] += ridge
        return A + ridge * np.eye(m), sla.cholesky_banded(ab)


#: First stages per chunk of :func:`hat_diagonal`, at most: per chunk and worker thread it holds two
#: arrays of its slots × rows per slot × coupled θ floats (T and V X), 18 MB on MIMU4444 exp_1 joint.
CHUNK = 256
#: Floats of each of those arrays at most (32 MB): a board with more rows per stage and more coupled θ
#: takes fewer stages per chunk (32 triads with gyroscopes, 192 rows a stage, and 640 θ: 34 stages, not 256
#: in 250 MB).
CHUNK_FLOATS = 1 << 22


def _stage_inverse(A: np.ndarray) -> np.ndarray:
    """Inverses of independent stage blocks A (N, m, m), with :func:`_band_cholesky`'s ridge where one is singular."""
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        ridge = 1e-12 * max(float(np.diagonal(A, axis1=1, axis2=2).max(initial=0.0)), 1e-300)
        A = A + ridge * np.eye(A.shape[1])
    return np.linalg.inv(A)


def _hash_multipliers(k: int) -> np.ndarray:
    """Odd random 64-bit multipliers of a row's column indices, position by position (fixed seed)."""
    return np.random.default_rng(0).integers(1, 2**62, size=k, dtype=np.uint64) | np.uint64(1)


def _row_patterns(Jt: sp.csr_matrix) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The rows of a canonical CSR grouped by their column pattern: per pattern (the rows in order,
    its columns, the positions of the rows' entries in ``Jt.data`` (rows, k)); rows without entries left out. A dynamic problem's
    border has a few hundred patterns (one per sensor axis and kind of reading), each read a few
    times per sample at most. Patterns are hashed, and the hash is checked for exactness."""
    n = Jt.shape[0]
    nnz = np.diff(Jt.indptr)
    if not Jt.nnz:
        return []
    # each entry's position in its row (in the index arrays' integer type: no (nnz,) int64 arrays)
    start = Jt.indptr[:-1]
    pos = np.arange(Jt.nnz, dtype=Jt.indptr.dtype)
    pos -= np.repeat(start, nnz)
    mult = _hash_multipliers(int(nnz.max()))
    with np.errstate(over="ignore"):
        terms = Jt.indices.astype(np.uint64)
        terms += np.uint64(1)
        terms *= mult[pos]
        key = np.zeros(n, np.uint64)
        has = nnz > 0
        key[has] = np.add.reduceat(terms, start[has], dtype=np.uint64)
    del terms
    key = np.where(has, key ^ (nnz.astype(np.uint64) << np.uint64(56)), key)
    _, rep, group = np.unique(key, return_index=True, return_inverse=True)
    group = group.ravel()
    r = rep[group]  # each row's representative
    ok = np.array_equal(nnz, nnz[r])
    if ok:  # each entry against its representative's at the same position
        pos += np.repeat(Jt.indptr[r], nnz)
        ok = np.array_equal(Jt.indices, Jt.indices[pos])
    if not ok:  # a collision: one group per distinct pattern, exactly
        keys = {}
        group = np.array([keys.setdefault(tuple(Jt.indices[Jt.indptr[i]:Jt.indptr[i + 1]]), len(keys))
                          for i in range(n)], int)
    order = np.argsort(group, kind="stable")
    ends = np.flatnonzero(np.diff(np.r_[-1, group[order], -2]))
    out = []
    for a, b in zip(ends[:-1], ends[1:]):
        idx = order[a:b]
        k = int(nnz[idx[0]])
        if k:
            at = Jt.indptr[idx][:, None] + np.arange(k)
            out.append((idx, Jt.indices[at[0]].astype(np.int64), at))
    return out


def _segment_reduce(ufunc, values: np.ndarray, indptr: np.ndarray, has: np.ndarray) -> np.ndarray:
    """``ufunc`` over the segments values[indptr[i]:indptr[i+1]] of the rows with ``has`` (non-empty)."""
    return ufunc.reduceat(values, indptr[:-1][has]) if has.any() else np.zeros(0, values.dtype)


def _structure(J: sp.csr_matrix, stages: np.ndarray, cache: dict | None) -> dict:
    """What :func:`hat_diagonal` needs of the sparsity of a canonical J (not of its values), kept in
    ``cache`` while J's structure and the stages stay the same (the noise model's rounds):

    - the (super-)stages: N stages of m variables (super-stages of w samples where a row reads
      samples w apart, padded with decoupled unit variables to a whole number), whether rows read two
      neighbouring ones (``span`` 2) or one, each row's first stage;
    - the slots: the rows that read a stage, by their first stage, R to a slot (a stage with more
      rows takes several, one with fewer leaves some empty), each row's place in them; the stage
      entries' places in V (slots, R, span·m) and the coupled θ entries' in T (slots, R, c), those
      sorted, with c the θ columns that rows reading a stage also read;
    - the θ part as a canonical CSR (J's θ entries keep their order: the θ numbering follows J's
      columns) and its rows grouped by pattern (:func:`_row_patterns`)."""
    def same(a, b):
        return a is b or (a.shape == b.shape and np.array_equal(a, b))

    key = (J.shape, J.indptr, J.indices, stages)
    if cache is not None and "plan" in cache:
        old = cache["key"]
        if old[0] == key[0] and all(same(a, b) for a, b in zip(old[1:], key[1:])):
            return cache["plan"]
    n_all, n_x = J.shape
    N0, m0 = stages.shape
    place = np.full(n_x, -1)  # each stage variable's place n·m0 + i in the stage order
    place[stages.ravel()] = np.arange(stages.size)
    theta = np.flatnonzero(place < 0)
    tmap = np.full(n_x, -1)
    tmap[theta] = np.arange(theta.size)
    at_stage = place[J.indices]
    ev, et = np.flatnonzero(at_stage >= 0), np.flatnonzero(at_stage < 0)
    pv = at_stage[ev]
    # each row's segments of ev and et, its smallest and largest stage place
    ptr, tptr = np.searchsorted(ev, J.indptr), np.searchsorted(et, J.indptr)
    reads = np.diff(ptr) > 0
    lo, hi = np.zeros(n_all, int), np.zeros(n_all, int)
    lo[reads], hi[reads] = _segment_reduce(np.minimum, pv, ptr, reads), _segment_reduce(np.maximum, pv, ptr, reads)
    w = max(int(np.max(hi[reads] // m0 - lo[reads] // m0, initial=0)), 1)  # the farthest samples a row reads apart
    m = w * m0
    N = -(-N0 * m0 // m)
    span = 2 if N > 1 and np.any(hi[reads] // m != lo[reads] // m) else 1
    first = np.minimum(lo // m, N - span)  # a row reads its first stage and the next at most
    rt, tt = np.repeat(np.arange(n_all), np.diff(tptr)), tmap[J.indices[et]]
    coupled = np.zeros(theta.size, bool)
    coupled[tt[reads[rt]]] = True  # the θ columns of the rows that read a stage
    coupled = np.flatnonzero(coupled)
    c = coupled.size
    cmap = np.full(theta.size, -1)
    cmap[coupled] = np.arange(c)
    # the slots: rows reading a stage ordered by their first stage, R per slot
    sr = np.flatnonzero(reads)
    sr = sr[np.argsort(first[sr], kind="stable")]
    per_stage = np.bincount(first[sr], minlength=N)
    R = max(1, int(np.ceil(np.quantile(per_stage[per_stage > 0], 0.9)))) if sr.size else 1
    slots = -(-per_stage // R)
    slot_ptr = np.r_[0, np.cumsum(slots)]  # each stage's first slot
    within = np.arange(sr.size) - np.r_[0, np.cumsum(per_stage)][first[sr]]
    rowpos = np.full(n_all, -1)
    rowpos[sr] = (slot_ptr[first[sr]] + within // R) * R + within % R
    slot_rows = np.full(slot_ptr[-1] * R, -1)
    slot_rows[rowpos[sr]] = sr
    rv = np.repeat(np.arange(n_all), np.diff(ptr))
    # the coupled θ entries in the order of their place in T: the rows in slot order, each its
    # entries in J's order (increasing column)
    q = slot_rows[slot_rows >= 0]
    lens = tptr[q + 1] - tptr[q]
    e = np.repeat(tptr[q] - np.r_[0, np.cumsum(lens)[:-1]], lens) + np.arange(int(lens.sum()))
    tdest = rowpos[rt[e]] * c + cmap[tt[e]]
    e = et[e]
    groups = _row_patterns(sp.csr_matrix((np.arange(et.size), tt, tptr), shape=(n_all, theta.size)))
    plan = {"N": N, "m": m, "pad": N * m - N0 * m0, "span": span, "R": R, "theta": theta, "coupled": coupled,
            "ev": ev, "V": rowpos[rv] * (span * m) + pv - first[rv] * m, "et": et, "T": (e, tdest),
            "slot_ptr": slot_ptr, "slot_stage": np.repeat(np.arange(N), slots), "slot_rows": slot_rows,
            "groups": groups}
    if cache is not None:
        cache["key"], cache["plan"] = key, plan
    return plan


def _buffer(plan: dict, name: str, shape: tuple) -> np.ndarray:
    """A zeroed array of ``shape`` kept in ``plan`` for the next call: the large arrays of
    :func:`hat_diagonal` (tens of MB on MIMU4444 exp_1) written into the same pages each round
    instead of fresh ones, which the kernel zeroes on first touch (the heap is trimmed between
    rounds)."""
    buffers = plan.setdefault("buffers", {})
    if name not in buffers or buffers[name].shape != shape:
        buffers[name] = np.zeros(shape)
    else:
        buffers[name].fill(0.0)
    return buffers[name]


def _by_stage(x: np.ndarray, slots: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Per stage the sum of its slots' ``x`` (slots in stage order; ``slots`` per stage, ``starts``
    each stage's first slot, from the chunk's first); as is when every stage has one slot."""
    if np.all(slots == 1):
        return x
    out = np.zeros((slots.size,) + x.shape[1:])
    has = slots > 0
    if has.any():
        out[has] = np.add.reduceat(x, starts[has], axis=0)
    return out


def hat_diagonal(J: sp.spmatrix, G: sp.spmatrix, stages: np.ndarray, rows=None, cache: dict | None = None,
                 threads: int = 1) -> np.ndarray:
    """Leverages h_j = (J P Jᵀ)_jj of residual rows at one Jacobian (the module docstring's sweep).

    J (rows, n_x) and G (constraints, n_x) are the Jacobians of the whitened residuals and of the
    constraints (``Solver.jacobians``), ``stages`` (N, m) the x indices of the banded nuisance
    variables, stage by stage (no constraint may act on them); every other variable is θ. Every row
    reads at most two neighbouring (super-)stages; ``rows`` (default: all) the rows wanted. Time and
    memory are linear in the number of rows and samples. The redundancy of a row is 1 − h_j; Σ h_j
    over all rows is the number of variables less the constraints.

    With the covariance written out, a row j = (v on its stage(s) s, t on θ) has
    j P jᵀ = v Q_s vᵀ − 2 v X_s tᵀ + t P_θ tᵀ, Q_s = Σ_s + B_s P_θ B_sᵀ the stages' covariance and
    X = B P_θ (−X their covariance with θ). B, X and H_mθ only have the c columns of the θ's that rows
    reading a stage also read (not a joint problem's static pose directions). The rows that read a
    stage sit in slots of R rows (:func:`_structure`), stage by stage: their stage values V
    (slots, R, span·m) and, a chunk of stages at a time (:data:`CHUNK`, :data:`CHUNK_FLOATS`), their θ values T (slots, R, c)
    are dense, so that H_mm's blocks (VᵀV), H_mθ (VᵀT), v Q_s vᵀ and v X_s (V X) are batched
    matrix products; v X_s tᵀ takes V X at the row's θ entries. H_θθ and t P_θ tᵀ are summed per pattern
    of θ columns (one per sensor axis and reading kind), on the entries a row has. The chunks run
    on ``threads`` worker threads when > 1 (``solver.threads``), as do the two halves of H_θm B and
    the patterns: the same operations on the same numbers for any number of threads, so the same
    bits. What depends on J's sparsity only is kept in ``cache`` (a dict the caller keeps) for the
    next call with the same structure and stages: the noise model's rounds.

    Large freed blocks are kept on the heap meanwhile (:func:`castimate.solver.ipopt.solve_settings`):
    its arrays of a few 10 MB would otherwise come as fresh pages from the kernel, zeroed on first
    touch.
    """
    from .ipopt import solve_settings
    with solve_settings():
        h = _hat_diagonal(J, G, stages, cache, threads)
    return h if rows is None else h[np.asarray(rows, int).ravel()]


def _hat_diagonal(J: sp.spmatrix, G: sp.spmatrix, stages: np.ndarray, cache: dict | None, threads: int
                  ) -> np.ndarray:
    """:func:`hat_diagonal` of every row."""
    J, G = sp.csr_matrix(J), sp.csr_matrix(G)
    if not J.has_canonical_format:
        J = J.copy()
        J.sum_duplicates()
    plan = _structure(J, stages, cache)
    N, m, span, R, theta, coupled = (plan[k] for k in ("N", "m", "span", "R", "theta", "coupled"))
    if np.any(np.isin(G.indices[G.data != 0], stages.ravel())):
        raise ValueError("constraints on the stage variables")
    c, sm, slot_ptr, slot_stage = coupled.size, span * m, plan["slot_ptr"], plan["slot_stage"]
    V = _buffer(plan, "V", (slot_ptr[-1], R, sm))
    V.ravel()[plan["V"]] = J.data[plan["ev"]]
    t_entries, t_dest = plan["T"]
    t_data = J.data[t_entries]
    Jt_data = J.data[plan["et"]]
    step = max(1, min(CHUNK, CHUNK_FLOATS // max(1, (slot_ptr[-1] * R * c) // max(N, 1))))  # slots per stage ~ 1
    chunks = range(0, N - span + 1, step)

    def chunk_rows(n0):
        """The chunk of first stages n0 ... n1 − 1: (n1, its slots s0, s1, its θ entries' T places from
        its first (its slots' rows × c + column) and values)."""
        n1 = min(n0 + step, N - span + 1)
        s0, s1 = slot_ptr[n0], slot_ptr[n1]
        a, b = np.searchsorted(t_dest, (s0 * R * c, s1 * R * c))
        return n1, s0, s1, t_dest[a:b] - s0 * R * c, t_data[a:b]

    # H_mm (diagonal blocks A, upper blocks C) and H_mθ (N, m, c) from the slots, chunk by chunk; with
    # coupled stages a chunk's last first stage adds to the next chunk's first: added after
    A, C = np.zeros((N, m, m)), np.zeros((max(N - 1, 0), m, m))
    Hmt = _buffer(plan, "Hmt", (N, m, c))

    def assemble(n0):
        n1, s0, s1, dest, vals = chunk_rows(n0)
        T = np.zeros((s1 - s0) * R * c)
        T[dest] = vals
        Vt = V[s0:s1].transpose(0, 2, 1)
        slots, starts = np.diff(slot_ptr[n0:n1 + 1]), slot_ptr[n0:n1] - s0
        Gm = _by_stage(np.matmul(Vt, V[s0:s1]), slots, starts)
        Hm = _by_stage(np.matmul(Vt, T.reshape(s1 - s0, R, c)), slots, starts)
        if span == 1:
            A[n0:n1], Hmt[n0:n1] = Gm, Hm
            return None
        A[n0:n1] += Gm[:, :m, :m]
        A[n0 + 1:n1] += Gm[:-1, m:, m:]
        C[n0:n1] = Gm[:, :m, m:]
        Hmt[n0:n1] += Hm[:, :m]
        Hmt[n0 + 1:n1] += Hm[:-1, m:]
        return n1, Gm[-1, m:, m:], Hm[-1, m:]

    for spill in map_threads(assemble, chunks, threads):
        if spill is not None:
            A[spill[0]] += spill[1]
            Hmt[spill[0]] += spill[2]
    if plan["pad"]:  # the padding of the last super-stage: decoupled unit variables that no row reads
        A[-1, m - plan["pad"]:, m - plan["pad"]:] += np.eye(plan["pad"])
    groups = [(idx, cols, Jt_data[at]) for idx, cols, at in plan["groups"]]
    # H_θθ summed pattern by pattern
    S = np.zeros((len(theta), len(theta)))
    for idx, cols, t in groups:
        S[np.ix_(cols, cols)] += t.T @ t
    Hmt = Hmt.reshape(N * m, c)
    if span == 1:
        Sd = _stage_inverse(A)
        B = np.matmul(Sd, Hmt.reshape(N, m, c), out=_buffer(plan, "B", (N, m, c))).reshape(N * m, c)
    else:
        A, chol = _band_cholesky(A, C)
        # factor, then solve: LAPACK's one-call pbsv is orders of magnitude slower for many right-hand sides
        B = sla.cho_solve_banded((chol, False), Hmt) if c else np.zeros((N * m, 0))
        Sd, So = selected_inverse(A, C)
    if c:  # H_θm B by halves of its rows (the same products either way), on worker threads with threads > 1
        half = (c + 1) // 2
        S[np.ix_(coupled, coupled)] -= np.vstack(map_threads(lambda k: Hmt[:, k:k + half].T @ B, range(0, c, half), threads))
    Gt = G[:, theta].toarray()
    U = np.linalg.qr(Gt.T, mode="complete")[0][:, Gt.shape[0]:] if Gt.shape[0] else np.eye(len(theta))
    # P_θ = K Kᵀ, the constrained inverse of the Schur complement
    ev, vec = np.linalg.eigh(U.T @ S @ U)
    pos = ev > ev.max(initial=0.0) * len(ev) * np.finfo(float).eps
    K = U @ (vec[:, pos] / np.sqrt(ev[pos]))
    P = K @ K.T
    Pc = P[np.ix_(coupled, coupled)]
    h = np.zeros(J.shape[0])
    slot_rows = plan["slot_rows"]

    def leverages(n0):
        """v Q_s vᵀ − 2 v X_s tᵀ of the rows of the chunk's slots (X = B P_θ and Q of its stages and the
        next, formed here: rows of other chunks do not read them)."""
        n1, s0, s1, dest, vals = chunk_rows(n0)
        n = n1 + span - 1 - n0  # the stages the chunk's rows read
        B2 = B[n0 * m:(n0 + n) * m]
        B3, X3 = B2.reshape(n, m, c), np.matmul(B2, Pc).reshape(n, m, c)
        Bt = B3.transpose(0, 2, 1)
        if span == 1:
            Q = Sd[n0:n1] + np.matmul(X3, Bt)
        else:
            Q = np.empty((n1 - n0, sm, sm))
            Q[:, :m, :m] = Sd[n0:n1] + np.matmul(X3[:-1], Bt[:-1])
            Q[:, m:, m:] = Sd[n0 + 1:n1 + 1] + np.matmul(X3[1:], Bt[1:])
            Q[:, :m, m:] = So[n0:n1] + np.matmul(X3[:-1], Bt[1:])
            Q[:, m:, :m] = Q[:, :m, m:].transpose(0, 2, 1)
            X3 = np.concatenate([X3[:-1], X3[1:]], axis=1)  # per first stage, its stage's and the next's
        if np.any(np.diff(slot_ptr[n0:n1 + 1]) != 1):  # not one slot per stage
            k = slot_stage[s0:s1] - n0
            Q, X3 = Q[k], X3[k]
        Vs = V[s0:s1]
        hv = np.einsum("srj,srj->sr", np.matmul(Vs, Q), Vs).ravel()
        Y = np.matmul(Vs, X3).ravel()
        hv -= 2.0 * np.bincount(dest // c, Y[dest] * vals, minlength=hv.size)
        r = slot_rows[s0 * R:s1 * R]
        h[r[r >= 0]] = hv[r >= 0]

    map_threads(leverages, chunks, threads)  # each chunk writes the leverages of its own rows
    # t P_θ tᵀ pattern by pattern (each pattern its own rows)
    for (idx, _, _), ht in zip(groups, map_threads(
            lambda g: np.einsum("ri,ri->r", g[2] @ P[np.ix_(g[1], g[1])], g[2]), groups, threads), strict=True):
        h[idx] += ht
    return h



def redundancies(J: sp.spmatrix, G: sp.spmatrix, stages: np.ndarray, components: dict[str, np.ndarray]
                 ) -> dict[str, float]:
    """ρ_k = n_k − tr(J_k P J_kᵀ) of each component (rows of J) at one Jacobian (:func:`hat_diagonal`)."""
    names = list(components)
    idx = [np.asarray(components[k]).ravel() for k in names]
    h = hat_diagonal(J, G, stages, np.concatenate(idx) if idx else np.zeros(0, int))
    ends = np.cumsum([0] + [len(i) for i in idx])
    return {k: float(len(i) - h[a:b].sum()) for k, i, a, b in zip(names, idx, ends[:-1], ends[1:])}


# --- the components' update -------------------------------------------------------------------
#
# Both estimators of the package are variance components v_j = Σ_m G_jm θ_m of residuals e_j whose
# redundancy is r_j = 1 − h_j: the process-noise levels (one component per group of process rows,
# G one-hot, v the level squared) and the motion-dependent measurement noise (θ = (1, σ_d², τ², κ²),
# G = (σ₀², 1, u̇², |ω|²) per reading; castimate.solver.motion_noise). With the hat diagonal, REML's
# score equations (Förstner 1979; Koch 1999, "Parameter Estimation and Hypothesis Testing in Linear
# Models", sec. 3.6) are those of the objective
#
#     ℓ(θ) = ½ Σ_j (e_j² / v_j + r_j log v_j),     s_m = −∂ℓ/∂θ_m = ½ Σ_j G_jm (e_j² − r_j v_j) / v_j²,
#
# (E[e_j²] = r_j v_j) with the expected information I_mk = ½ Σ_j r_j G_jm G_jk / v_j². For a single
# component over a group (G = 1) its root is Helmert's θ = Σ e² / Σ r = σ² r'r/ρ in closed form.


@dataclass(frozen=True)
class Components:
    """Variance components θ of v = G θ (:func:`variance_components`).

    ``theta`` the estimates (≥ 0), ``std`` their Fisher σ (0 where fixed or at the bound θ = 0),
    ``nll`` the objective ℓ at ``theta``, ``iterations``."""

    theta: np.ndarray
    std: np.ndarray
    nll: float
    iterations: int


def negative_log_likelihood(theta, G: np.ndarray, e2: np.ndarray, r: np.ndarray) -> float:
    """ℓ(θ) = ½ Σ_j (e_j²/v_j + r_j log v_j), v = G θ (REML with the hat diagonal; constants left out)."""
    return _nll(np.asarray(theta, float) @ np.ascontiguousarray(np.asarray(G, float).T), e2, r)


def score_information(theta, G: np.ndarray, e2: np.ndarray, r: np.ndarray, observed: bool = False
                      ) -> tuple[np.ndarray, np.ndarray]:
    """−∂ℓ/∂θ, s_m = ½ Σ G_jm (e_j² − r_j v_j)/v_j², and the expected information I_mk = ½ Σ r_j G_jm G_jk / v_j²
    (``observed``: ∂²ℓ/∂θ_m∂θ_k = ½ Σ G_jm G_jk (2 e_j²/v_j − r_j)/v_j² instead)."""
    return _score_information(np.asarray(theta, float), np.ascontiguousarray(np.asarray(G, float).T), e2, r, observed)


# The iteration works on Gᵀ (components × rows, contiguous): its products with the rows' weights are
# BLAS calls over long contiguous rows (a 153 000 × 4 G took 10-15 ms per score, Gᵀ 4 ms, and 2 ms
# with the information's products taken row by row).
def _nll(v: np.ndarray, e2: np.ndarray, r: np.ndarray) -> float:
    return 0.5 * float(np.sum(e2 / v + r * np.log(v)))


def _score_information(theta, Gt, e2, r, observed, v=None):
    """(score, information) at θ; ``v`` = θ Gᵀ if already at hand (the line search's last trial)."""
    q = 1.0 / (theta @ Gt if v is None else v)
    a = e2 * q  # e²/v
    u = a - r
    u *= q  # (e² − r v)/v²
    if observed:
        w = np.subtract(2.0 * a, r, out=a)  # (2e²/v − r), over v² below
        w *= q
    else:
        w = r * q
    w *= q
    # row by row: a matrix-vector product each (Gᵀ w Gᵀᵀ as one product took 2 ms for 4 × 153 000, these 0.7)
    info = np.array([Gt @ (g * w) for g in Gt]).reshape(len(Gt), len(Gt))
    return 0.5 * (Gt @ u), 0.5 * info


def variance_components(e: np.ndarray, r: np.ndarray, G: np.ndarray, theta0, free, max_iter: int = 100,
                        tol: float = 1e-10) -> Components:
    """REML estimate of θ ≥ 0 in v_j = G_j θ from residuals e_j of redundancy r_j ∈ (0, 1].

    Newton's method on ℓ (above) with the observed information where it is positive definite on the
    components that move, Fisher scoring (the expected information) elsewhere: Fisher scoring alone
    converges only linearly where the model misfits (E[e²] ≠ r v), hundreds of iterations on real
    sessions. The step is halved until ℓ does not increase, and a component that would turn negative
    stays at 0 (active set). Components with ``free`` False keep their ``theta0``. The rows with r ≤ 0
    or non-finite e or G carry no information. Raises :class:`~castimate.errors.NotConvergedError` when
    the iteration does not converge in ``max_iter`` steps.
    """
    e, r, G = np.asarray(e, float).ravel(), np.asarray(r, float).ravel(), np.asarray(G, float)
    ok = np.isfinite(e) & (r > 0) & np.all(np.isfinite(G), axis=1)
    return solve_components(e[ok] ** 2, r[ok], np.ascontiguousarray(G[ok].T), theta0, free, max_iter, tol)


def solve_components(e2: np.ndarray, r: np.ndarray, Gt: np.ndarray, theta0, free, max_iter: int = 100,
                     tol: float = 1e-10) -> Components:
    """:func:`variance_components` of rows already selected (finite, r > 0) and laid out for the
    iteration: squared residuals e², redundancies r and Gᵀ (components × rows, C-contiguous), for
    several fits of the same rows (the noise model's likelihood-ratio tests)."""
    theta = np.array(theta0, float)
    free = np.asarray(free, bool)
    v = theta @ Gt
    if np.any(v <= 0):
        raise ValueError("the starting components give a non-positive variance")
    nll = _nll(v, e2, r)
    for it in range(1, max_iter + 1):
        s, hess = _score_information(theta, Gt, e2, r, True, v)
        act = free & ~((theta <= 0) & (s < 0))  # at the bound and pushed outwards: stays there
        if not act.any():
            break
        step = np.zeros_like(theta)
        A = np.ix_(act, act)
        try:
            step[act] = sla.cho_solve(sla.cho_factor(hess[A]), s[act])
        except np.linalg.LinAlgError:
            step[act] = np.linalg.solve(_score_information(theta, Gt, e2, r, False, v)[1][A], s[act])
        t = 1.0
        while True:
            trial = np.maximum(theta + t * step, 0.0)
            vt = trial @ Gt
            if np.all(vt > 0):
                new = _nll(vt, e2, r)
                if new <= nll + 1e-12 * abs(nll):
                    break
            t *= 0.5
            if t < 1e-12:
                trial, new, vt = theta, nll, v
                break
        change = np.max(np.abs(trial - theta) / np.maximum(np.abs(trial), 1e-300))
        theta, nll, v = trial, new, vt
        if change < tol:
            break
    else:
        raise NotConvergedError(f"the variance components did not converge in {max_iter} iterations "
                                f"(last relative change {change:.2g})")
    info = _score_information(theta, Gt, e2, r, False, v)[1]
    std = np.zeros_like(theta)
    act = free & (theta > 0)
    if act.any():
        std[act] = np.sqrt(np.diag(np.linalg.inv(info[np.ix_(act, act)])))
    return Components(theta, std, nll, it)


def likelihood_ratio(nll_restricted: float, nll_full: float) -> tuple[float, float]:
    """(Λ, p) for one component tested at its bound 0: Λ = 2 (ℓ₀ − ℓ₁) is then distributed as
    ½ χ²₀ + ½ χ²₁ (Self & Liang 1987), so p = ½ P(χ²₁ > Λ)."""
    lam = max(0.0, 2.0 * (nll_restricted - nll_full))
    return lam, 0.5 * float(chdtrc(1, lam))


#: Largest factor by which one iteration changes a level.
MAX_STEP = 10.0


def _next_level(level: float, e: np.ndarray, r: np.ndarray) -> float:
    """The level σ of one component from its rows' whitened residuals e (at ``level``) and their
    redundancies r: √θ of :func:`variance_components` with G = 1 (Helmert's σ·sqrt(r'r/ρ)), at most
    ×/÷ ``MAX_STEP`` from ``level``."""
    theta = variance_components(e * level, r, np.ones((e.size, 1)), [level ** 2], [True]).theta[0]
    return float(np.clip(np.sqrt(theta), level / MAX_STEP, level * MAX_STEP))


#: A component whose rows hold less than this share of their own degrees of freedom (ρ_k < share·n_k)
#: is not estimable from the data (e.g. the integration rows of Euler's step without gyroscopes, which
#: the motion fits exactly): its level is kept as given.
MIN_REDUNDANCY_SHARE = 0.01


@dataclass
class VarianceComponents:
    """Levels estimated by :func:`estimate_levels`: per component its level, rows, redundancy
    and r_kᵀ r_k / ρ_k of the last solve (1 at the fixed point), the components kept at their
    given level (not estimable), with the iterations' history."""

    levels: dict[str, float]
    rows: dict[str, int]
    redundancy: dict[str, float]
    ratio: dict[str, float]
    iterations: int
    converged: bool
    kept: tuple[str, ...] = ()
    history: list[dict] = field(default_factory=list)


def estimate_levels(solve: Callable[[dict[str, float], object], tuple[object, object, np.ndarray]],
                    rows: Callable[[object], dict[str, np.ndarray]], stages: np.ndarray,
                    levels: dict[str, float], first=None, tol: float = 1e-2, max_iter: int = 30,
                    log: Callable[[str], None] = lambda m: None):
    """Helmert/Förstner iteration of the levels of residual components.

    ``solve(levels, previous solution)`` -> (solver, solution, data vector) solves the problem with
    the levels; ``rows(solver)`` gives each component's residual indices; ``first`` is an
    already available (solver, solution, data) at ``levels``. Stops when every estimable level
    changes by less than ``tol`` (relative). Returns (VarianceComponents, the last (solver,
    solution, data)).
    """
    levels = dict(levels)
    cur = first or solve(levels, None)
    history: list[dict] = []
    kept: set[str] = set()
    structure: dict = {}  # the hat diagonal's, kept while the Jacobian's sparsity stays the same
    for it in range(1, max_iter + 1):
        solver, sol, data = cur
        idx = rows(solver)
        J, G = solver.jacobians(sol.x, data=data)
        h = hat_diagonal(J, G, stages, np.concatenate([i.ravel() for i in idx.values()]), structure,
                         solver_threads(solver.options.threads))
        ends = np.cumsum([0] + [i.size for i in idx.values()])
        redund = {k: 1.0 - h[a:b] for k, a, b in zip(idx, ends[:-1], ends[1:])}
        red = {k: float(v.sum()) for k, v in redund.items()}
        r = solver.residuals(sol.x, data=data)
        ratio = {k: float(np.sum(r[i] ** 2)) / max(red[k], 1e-12) for k, i in idx.items()}
        kept |= {k for k in levels if red[k] < MIN_REDUNDANCY_SHARE * idx[k].size}
        new = {k: levels[k] if k in kept else _next_level(levels[k], r[idx[k].ravel()], redund[k]) for k in levels}
        history.append({"levels": dict(levels), "redundancy": red, "ratio": ratio, "cost": sol.cost})
        log(f"  variance components, iteration {it}: " + ", ".join(
            f"{k} {levels[k]:.4g} (r'r/redundancy {ratio[k]:.4g}, redundancy {red[k]:.1f} of {idx[k].size}"
            + (", not estimable: kept" if k in kept else "") + ")" for k in levels))
        done = max(abs(new[k] / levels[k] - 1) for k in levels) < tol
        if done or it == max_iter:
            comp = VarianceComponents(levels, {k: int(i.size) for k, i in idx.items()}, red, ratio, it, done,
                                      tuple(sorted(kept)), history)
            return comp, cur
        levels = new
        cur = solve(levels, sol)
    raise ValueError("max_iter must be at least 1")

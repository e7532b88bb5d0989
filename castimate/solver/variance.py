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


def _tridiagonal_blocks(H: sp.spmatrix, N: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal (N, m, m) and upper off-diagonal (N-1, m, m) blocks of a block-tridiagonal matrix."""
    H = sp.coo_matrix(H)
    bi, bj = H.row // m, H.col // m
    if np.any(np.abs(bi - bj) > 1):
        raise ValueError("the stage Hessian couples more than neighbouring stages")
    A, C = np.zeros((N, m, m)), np.zeros((max(N - 1, 0), m, m))
    d, u = bi == bj, bj == bi + 1
    np.add.at(A, (bi[d], H.row[d] % m, H.col[d] % m), H.data[d])
    np.add.at(C, (bi[u], H.row[u] % m, H.col[u] % m), H.data[u])
    return A, C


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


def _factor(Hmm: sp.spmatrix, u: int):
    """Band Cholesky of the stage Hessian, with a ridge of 1e-12 × its largest diagonal where it is
    singular (a direction of one sample that no row reads: its leverage is then 0, not undefined).
    Returns the (possibly regularised) matrix and the factor."""
    H = sp.coo_matrix(Hmm)
    up = H.row <= H.col
    if np.any(H.col[up] - H.row[up] > u):
        raise ValueError("the stage Hessian is wider than its band")
    ab = np.zeros((u + 1, H.shape[0]))
    np.add.at(ab, (u + H.row[up] - H.col[up], H.col[up]), H.data[up])
    try:
        return Hmm, sla.cholesky_banded(ab)
    except np.linalg.LinAlgError:
        ridge = 1e-12 * max(float(ab[u].max(initial=0.0)), 1e-300)
        ab[u] += ridge
        return (Hmm + ridge * sp.eye(Hmm.shape[0])).tocsc(), sla.cholesky_banded(ab)


#: Stages per chunk of :func:`hat_diagonal` (bounds its memory: chunk × m × n_θ floats of X and the
#: rows that read these stages; a chunk of X stays in the processor's cache while its rows use it).
CHUNK = 512


def _stage_inverse(A: np.ndarray) -> np.ndarray:
    """Inverses of independent stage blocks A (N, m, m), with :func:`_factor`'s ridge where one is singular."""
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


def _halves(used: np.ndarray, m: int, span: int):
    """The stage variables ``used`` (0 ... span·m − 1, from a row's first stage) split by stage:
    (offset of the stage from the first, the positions in ``used``, the variables within the stage)."""
    for k in range(span):
        sel = np.flatnonzero(used // m == k)
        if sel.size:
            yield k, sel, used[sel] % m


def _split_columns(A: sp.csr_matrix, k: int, left: np.ndarray | None = None) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """A canonical CSR's columns < k and ≥ k (shifted by k), both canonical: a row's first entries are
    its columns < k (the same as ``A[:, :k], A[:, k:]``, without scipy's general column slicing).
    ``left``: ``A.indices < k`` if the caller has it."""
    if left is None:
        left = A.indices < k
    at, rest = np.flatnonzero(left), np.flatnonzero(~left)
    ptr = np.searchsorted(at, A.indptr).astype(A.indptr.dtype)  # the entries < k up to each row
    right = A.indices[rest]
    right -= k
    return (sp.csr_matrix((A.data[at], A.indices[at], ptr), shape=(A.shape[0], k)),
            sp.csr_matrix((A.data[rest], right, A.indptr - ptr), shape=(A.shape[0], A.shape[1] - k)))


def _structure(J: sp.csr_matrix, stages: np.ndarray, rows, cache: dict | None, span: int | None = None) -> dict:
    """What :func:`hat_diagonal` needs of the sparsity of a canonical J (not of its values): the
    permutation of its entries into the stage columns then the θ columns, the stage part's CSR
    structure, the super-stages, each row's first stage and the positions of its stage entries in
    V, the coupled θ columns, the rows grouped by θ pattern (rows, columns, positions of their
    entries), H_mθ's right factor and the rows wanted. Kept in ``cache`` while J's structure, the
    stages and the rows stay the same (the noise model's rounds); ``span`` forces the stages to be
    treated as coupled (2) or not (1), else it comes from J's structure."""
    def same(a, b):
        return a is b or (a is not None and b is not None and a.shape == b.shape and np.array_equal(a, b))

    key = (J.shape, J.indptr, J.indices, stages, None if rows is None else np.asarray(rows, int).ravel())
    if cache is not None and "plan" in cache and (span is None or cache["plan"]["span"] == span):
        old = cache["key"]
        if old[0] == key[0] and all(same(a, b) for a, b in zip(old[1:], key[1:])):
            return cache["plan"]
    N, m = stages.shape
    mx = stages.ravel()
    on_stage = np.zeros(J.shape[1], bool)
    on_stage[mx] = True
    theta = np.flatnonzero(~on_stage)
    # the permutation of J's entries: J's entry numbers as the data of J with its columns permuted, sorted
    # row by row (in J's index type: scipy keeps it, no copies)
    perm = np.empty(J.shape[1], J.indices.dtype)
    perm[mx], perm[theta] = np.arange(mx.size), mx.size + np.arange(theta.size)
    Jp = sp.csr_matrix((np.arange(J.nnz), perm[J.indices], J.indptr.copy()), shape=J.shape)
    Jp.sort_indices()
    order = Jp.data
    left = Jp.indices < mx.size
    Jm, Jt = _split_columns(Jp, mx.size, left)
    # each row's smallest and largest stage column (canonical: its first and last entry), if it reads one
    reads = np.diff(Jm.indptr) > 0
    lo, hi = Jm.indices[Jm.indptr[:-1][reads]], Jm.indices[Jm.indptr[1:][reads] - 1]
    w = max(int(np.max(hi // m - lo // m, initial=0)), 1)  # the farthest stages a row reads apart
    pad = None
    if w > 1:
        pad = (-N) % w * m
        Jm = sp.csr_matrix((Jm.data, Jm.indices, Jm.indptr), shape=(Jm.shape[0], Jm.shape[1] + pad))
        N, m = (N * m + pad) // (w * m), w * m
    if span is None:  # stages coupled when a row reads two of them
        span = 2 if N > 1 and np.any(hi // m != lo // m) else 1
    n_all = Jm.shape[0]
    first = np.zeros(n_all, int)
    first[reads] = lo // m
    first = np.minimum(first, N - span)
    # each stage entry's position in its row of V: its column less its row's first stage's first column
    counts = np.diff(Jm.indptr)
    vpos = Jm.indices - np.repeat(first * m, counts)
    if np.any((vpos < 0) | (vpos >= span * m)):
        raise ValueError("a residual row spans more than two neighbouring stages")
    vpos += np.repeat(np.arange(n_all) * (span * m), counts)  # unique (canonical CSR)
    on_v = np.zeros(n_all * span * m, bool)
    on_v[vpos] = True
    on_v = on_v.reshape(n_all, span * m)
    # the θ columns that rows reading a stage also read: the border's coupled part
    coupled = np.zeros(Jt.shape[1], bool)
    coupled[Jt.indices[np.repeat(reads, np.diff(Jt.indptr))]] = True
    coupled = np.flatnonzero(coupled)
    c = coupled.size
    cmap = np.full(Jt.shape[1], -1)
    cmap[coupled] = np.arange(c)
    want = np.arange(n_all) if rows is None else np.asarray(rows, int).ravel()
    if want.size > 1 and not np.all(want[1:] > want[:-1]):  # unordered or repeated rows
        want = np.unique(want)
    wanted = np.zeros(n_all, bool)
    wanted[want] = True
    # per pattern also its wanted rows (positions in the pattern's rows) in the order of their first
    # stage and those stages: the chunks of stages of hat_diagonal take runs of them
    groups = []
    for idx, cols, at in _row_patterns(Jt):
        sel = np.flatnonzero(wanted[idx])
        sel = sel[np.argsort(first[idx[sel]], kind="stable")]
        groups.append((idx, cols, at, cmap[cols], np.flatnonzero(np.any(on_v[idx], axis=0)), sel, first[idx[sel]]))
    want = want[np.argsort(first[want], kind="stable")]
    on = np.flatnonzero((cmap >= 0)[Jt.indices])  # the entries on coupled columns
    plan = {"order": order, "left": left, "Jm": (Jm.indices, Jm.indptr, Jm.shape), "N": N, "m": m, "pad": pad,
            "span": span, "first": first, "V": vpos, "c": c, "coupled": coupled, "groups": groups,
            "Jc": (on, cmap[Jt.indices[on]], np.searchsorted(on, Jt.indptr)),
            "want": want, "want_first": first[want]}
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


def hat_diagonal(J: sp.spmatrix, G: sp.spmatrix, stages: np.ndarray, rows=None, cache: dict | None = None,
                 threads: int = 1) -> np.ndarray:
    """Leverages h_j = (J P Jᵀ)_jj of residual rows at one Jacobian (the module docstring's sweep).

    J (rows, n_x) and G (constraints, n_x) are the Jacobians of the whitened residuals and of the
    constraints (``Solver.jacobians``), ``stages`` (N, m) the x indices of the banded nuisance
    variables, stage by stage (no constraint may act on them); every other variable is θ. ``rows``
    (default: all) the rows wanted, each reading at most two neighbouring (super-)stages. Time and
    memory are linear in the number of rows and samples. The redundancy of a row is 1 − h_j; Σ h_j
    over all rows is the number of variables less the constraints.

    With the covariance written out, a row j = (v on its stage(s) s, t on θ) has
    j P jᵀ = v Q_s vᵀ − 2 v X_s tᵀ + t P_θ tᵀ, Q_s = Σ_s + B_s P_θ B_sᵀ the stages' covariance and
    X = B P_θ (−X their covariance with θ). B, X and H_mθ only have the columns of the θ's that rows
    reading a stage also read (not a joint problem's static pose directions); H_mθ is one sparse
    product, H_θθ and the θ terms are summed per pattern of θ columns (one per sensor axis and
    reading kind), on the entries a row has: no (rows × n_θ) array is formed. X, Q and the rows'
    leverages are formed chunk by chunk of :data:`CHUNK` stages (a row's in the chunk of its first
    stage), on ``threads`` worker threads when > 1 (``solver.threads``), as are the two halves of
    H_θm B: the same operations on the same numbers for any number of threads, so the same bits.
    What depends on J's sparsity only (:func:`_structure`: the permutation and split of its columns,
    the patterns, the rows by stage) is kept in ``cache`` (a dict the caller keeps) for the next call
    with the same structure, stages and rows: the noise model's rounds.

    Large freed blocks are kept on the heap meanwhile (:func:`castimate.solver.ipopt.solve_settings`):
    its arrays of a few 10 MB would otherwise come as fresh pages from the kernel, zeroed on first
    touch (on MIMU4444 exp_1 joint up to as much system time as user time, about 1 s a call).
    """
    from .ipopt import solve_settings
    with solve_settings():
        return _hat_diagonal(J, G, stages, rows, cache, threads)


def _hat_diagonal(J: sp.spmatrix, G: sp.spmatrix, stages: np.ndarray, rows=None, cache: dict | None = None,
                  threads: int = 1) -> np.ndarray:
    """:func:`hat_diagonal` itself."""
    J, G = sp.csr_matrix(J), sp.csr_matrix(G)
    if not J.has_canonical_format:
        J = J.copy()
        J.sum_duplicates()
    on_stage = np.zeros(J.shape[1], bool)
    on_stage[stages.ravel()] = True
    theta = np.flatnonzero(~on_stage)
    if np.any(on_stage[G.indices] & (G.data != 0)):
        raise ValueError("constraints on the stage variables")
    plan = _structure(J, stages, rows, cache)
    # the columns permuted (stages first, then θ), canonical (sorted column indices per row, used
    # below) and split into the stage and the θ columns: each row's stage entries come first
    data = J.data[plan["order"]]
    Jm = sp.csr_matrix((data[plan["left"]], plan["Jm"][0], plan["Jm"][1]), shape=plan["Jm"][2])
    Jm.has_canonical_format = True  # its index arrays are the plan's: never sorted in place
    Jt_data = data[~plan["left"]]
    N, m, pad, c = plan["N"], plan["m"], plan["pad"], plan["c"]
    # H_mm and H_mθ (coupled columns, flat (N·m, c)): two sparse products, side by side on worker
    # threads with threads > 1 (scipy's release Python's lock)
    Jc = sp.csr_matrix((Jt_data[plan["Jc"][0]], plan["Jc"][1], plan["Jc"][2]), shape=(Jm.shape[0], c))
    Hmm, Hmt = map_threads(lambda k: (Jm.T @ Jm).tocsc() if k == 0 else
                           (Jm.T.tocsr() @ Jc).toarray(out=_buffer(plan, "Hmt", (N * m, c))), range(2), threads)
    if pad is not None:
        # rows that read samples n-1..n+1 (sample-age effects' central differences) couple stages w
        # apart: super-stages of w samples are block-tridiagonal again, padded with decoupled unit
        # stages (no rows read them) to a whole number of super-stages (plan["N"], plan["m"])
        Hmm = (Hmm + sp.diags(np.r_[np.zeros(Hmm.shape[0] - pad), np.ones(pad)])).tocsc()
    A, C = _tridiagonal_blocks(Hmm, N, m)
    span = 2 if C.any() and N > 1 else 1  # independent stages (no row reads two): span 1
    if span != plan["span"]:  # stages coupled by exactly cancelling values only: the plan made for this span
        plan = _structure(J, stages, rows, cache, span)
    first, n_all, coupled = plan["first"], Jm.shape[0], plan["coupled"]
    # each row's values v on its first stage (its smallest column; any for a row that reads none) and the next
    V = _buffer(plan, "V", (n_all, span * m))
    V.ravel()[plan["V"]] = Jm.data
    groups = [(idx, cols, Jt_data[at], ci, used, sel, fs) for idx, cols, at, ci, used, sel, fs in plan["groups"]]
    # H_θθ summed pattern by pattern
    S = np.zeros((len(theta), len(theta)))
    for idx, cols, t, *_ in groups:
        S[np.ix_(cols, cols)] += t.T @ t
    if span == 1:
        Sd = _stage_inverse(A)
        B = np.matmul(Sd, Hmt.reshape(N, m, c), out=_buffer(plan, "B", (N, m, c))).reshape(N * m, c)
    else:
        Hmm, chol = _factor(Hmm, 2 * m - 1)
        # factor, then solve: LAPACK's one-call pbsv is orders of magnitude slower for many right-hand sides
        B = sla.cho_solve_banded((chol, False), Hmt) if c else np.zeros((N * m, 0))
        Sd, So = selected_inverse(*_tridiagonal_blocks(Hmm, N, m))
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
    Pc, want, want_first = P[np.ix_(coupled, coupled)], plan["want"], plan["want_first"]
    h = np.zeros(n_all)

    def theta_terms(idx, cols, t, ci, used, X3, n0):
        """t P_θ tᵀ − 2 v X_s tᵀ of a pattern's rows (their stages' X from X3, which starts at stage n0)."""
        ht = np.einsum("ri,ri->r", t @ P[np.ix_(cols, cols)], t)
        if used.size:  # −2 v X_s tᵀ, X_s the rows' stages' X on their θ columns
            s = first[idx] - n0
            Xs = np.concatenate([X3[:, u[:, None], ci[None, :]][s + k] for k, _, u in _halves(used, m, span)], axis=1)
            ht -= 2.0 * np.einsum("rk,rk->r", np.matmul(V[idx][:, None, used], Xs)[:, 0], t)
        h[idx] += ht

    def chunk(n0):
        """The leverages of the wanted rows whose first stage is n0 ... n0 + CHUNK − 1 (X = B P_θ and Q of
        these stages and the next, formed here: rows of other chunks do not read them)."""
        n1 = min(n0 + CHUNK, N - span + 1)
        n = n1 + span - 1 - n0  # the stages the chunk's rows read
        B2 = B[n0 * m:(n0 + n) * m]
        B3, X3 = B2.reshape(n, m, c), np.matmul(B2, Pc).reshape(n, m, c)
        Bt = B3.transpose(0, 2, 1)
        if span == 1:
            Q = Sd[n0:n1] + np.matmul(X3, Bt)
        else:
            Q = np.empty((n1 - n0, 2 * m, 2 * m))
            Q[:, :m, :m] = Sd[n0:n1] + np.matmul(X3[:-1], Bt[:-1])
            Q[:, m:, m:] = Sd[n0 + 1:n1 + 1] + np.matmul(X3[1:], Bt[1:])
            Q[:, :m, m:] = So[n0:n1] + np.matmul(X3[:-1], Bt[1:])
            Q[:, m:, :m] = Q[:, :m, m:].transpose(0, 2, 1)
        r = want[np.searchsorted(want_first, n0):np.searchsorted(want_first, n1)]
        h[r] = np.einsum("ri,ri->r", V[r], np.matmul(Q[first[r] - n0], V[r][:, :, None])[:, :, 0])
        for idx, cols, t, ci, used, sel, fs in groups:
            if used.size:
                part = sel[np.searchsorted(fs, n0):np.searchsorted(fs, n1)]
                if part.size:
                    theta_terms(idx[part], cols, t[part], ci, used, X3, n0)

    map_threads(chunk, range(0, N - span + 1, CHUNK), threads)  # each chunk writes the leverages of its own rows
    for idx, cols, t, ci, used, sel, fs in groups:  # the rows that read no stage (a joint problem's static rows)
        if not used.size and sel.size:
            theta_terms(idx[sel], cols, t[sel], ci, used, None, 0)
    return h if rows is None else h[np.asarray(rows, int).ravel()]


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

"""Variance components: noise levels of groups of residuals estimated from the fit itself.

Helmert's estimator as Förstner (1979) iterates it: with the residuals r whitened by the current
levels σ_k, component k (a set of residual rows) gets

    σ_k² ← σ_k² · r_kᵀ r_k / ρ_k,        ρ_k = n_k − tr(J_k P J_kᵀ)

where ρ_k is the component's redundancy (its rows' share of the degrees of freedom, from the
diagonal of the hat matrix J P Jᵀ) and P the Gauss-Newton covariance of all variables at the
solution (unit-norm constraints respected). Iterated with re-solves, the fixed point is the REML
estimate of the levels; Σ_k ρ_k + (the other rows' redundancy) = rows − (variables − constraints).

The hat-matrix trace uses the arrow structure of the dynamic problems: the motion states are
stages coupled to their neighbours only (a block-tridiagonal H_mm, as eliminated in
:mod:`castimate.solver.elimination`) and to a dense border θ. With B = H_mm⁻¹ H_mθ and P_θ the
constrained inverse of the Schur complement S = H_θθ − H_θm B,

    j P jᵀ = j_m Σ j_mᵀ + (j_m B − j_θ) P_θ (j_m B − j_θ)ᵀ,

where only the block-tridiagonal part Σ of H_mm⁻¹ is needed (a backward sweep like an RTS
smoother's covariance), so a component costs time linear in the number of samples.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp


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


def _banded_solve(H: sp.spmatrix, rhs: np.ndarray, u: int) -> np.ndarray:
    """H⁻¹ rhs for a symmetric positive-definite H with u superdiagonals (LAPACK's band Cholesky)."""
    H = sp.coo_matrix(H)
    up = H.row <= H.col
    if np.any(H.col[up] - H.row[up] > u):
        raise ValueError("the stage Hessian is wider than its band")
    ab = np.zeros((u + 1, H.shape[0]))
    np.add.at(ab, (u + H.row[up] - H.col[up], H.col[up]), H.data[up])
    # factor, then solve: LAPACK's one-call pbsv is orders of magnitude slower for many right-hand sides
    return sla.cho_solve_banded((sla.cholesky_banded(ab), False), rhs)


def selected_inverse(A: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The block-tridiagonal part of the inverse of a symmetric positive-definite block-tridiagonal
    matrix (diagonal blocks A (N, m, m), upper blocks C (N-1, m, m)): (Σ_nn (N, m, m), Σ_n,n+1
    (N-1, m, m)). Forward: D_n = A_n − C_n-1ᵀ D_n-1⁻¹ C_n-1; backward: Σ_n = D_n⁻¹ + F_n Σ_n+1 F_nᵀ,
    Σ_n,n+1 = −F_n Σ_n+1 with F_n = D_n⁻¹ C_n."""
    N = len(A)
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


def redundancies(J: sp.spmatrix, G: sp.spmatrix, stages: np.ndarray, components: dict[str, np.ndarray]
                 ) -> dict[str, float]:
    """ρ_k = n_k − tr(J_k P J_kᵀ) of each component (rows of J) at one Jacobian.

    J (rows, n_x) and G (constraints, n_x) are the Jacobians of the whitened residuals and of the
    constraints (``Solver.jacobians``), ``stages`` (N, m) the x indices of the banded nuisance
    variables, stage by stage (no constraint may act on them); every other variable is θ.
    """
    J, G = sp.csr_matrix(J), sp.csr_matrix(G)
    N, m = stages.shape
    mx = stages.ravel()
    theta = np.setdiff1d(np.arange(J.shape[1]), mx)
    if G.shape[0] and abs(G[:, mx]).sum() > 0:
        raise ValueError("constraints on the stage variables")
    Jm, Jt = J[:, mx].tocsc(), J[:, theta].tocsc()
    Hmm = (Jm.T @ Jm).tocsc()
    H = Hmm.tocoo()
    w = int(np.abs(H.row // m - H.col // m).max(initial=1))
    if w > 1:
        # rows that read samples n-1..n+1 (sample-age effects' central differences) couple stages w
        # apart: super-stages of w samples are block-tridiagonal again. Padded with decoupled unit
        # stages (no rows read them) to a whole number of super-stages.
        pad = (-N) % w * m
        Jm = sp.hstack([Jm, sp.csc_matrix((Jm.shape[0], pad))]).tocsc()
        Hmm = (Jm.T @ Jm + sp.diags(np.r_[np.zeros(N * m), np.ones(pad)])).tocsc()
        N, m = (N * m + pad) // (w * m), w * m
    Hmt = (Jm.T @ Jt).toarray()
    B = _banded_solve(Hmm, Hmt, 2 * m - 1) if len(theta) else np.zeros((Jm.shape[1], 0))
    S = (Jt.T @ Jt).toarray() - Hmt.T @ B
    Gt = G[:, theta].toarray()
    U = np.linalg.qr(Gt.T, mode="complete")[0][:, Gt.shape[0]:] if Gt.shape[0] else np.eye(len(theta))
    P = U @ np.linalg.pinv(U.T @ S @ U, hermitian=True) @ U.T
    Sd, So = selected_inverse(*_tridiagonal_blocks(Hmm, N, m))
    out = {}
    for name, rows in components.items():
        rows = np.asarray(rows).ravel()
        Jk = sp.coo_matrix(Jm[rows])
        stage = Jk.col // m
        first = np.full(len(rows), N)
        np.minimum.at(first, Jk.row, stage)
        first = np.minimum(first, max(N - 2, 0))
        V = np.zeros((len(rows), 2 * m))
        rel = stage - first[Jk.row]
        if np.any((rel < 0) | (rel > 1)):
            raise ValueError(f"rows of component {name!r} span more than two neighbouring stages")
        np.add.at(V, (Jk.row, rel * m + Jk.col % m), Jk.data)
        if N > 1:
            Q = np.empty((N - 1, 2 * m, 2 * m))
            Q[:, :m, :m], Q[:, m:, m:], Q[:, :m, m:] = Sd[:-1], Sd[1:], So
            Q[:, m:, :m] = So.transpose(0, 2, 1)
        else:
            Q = Sd[:, :m, :m]
            V = V[:, :m]
        tr = float(np.einsum("ri,rij,rj->", V, Q[first], V))
        W = Jm[rows] @ B - Jt[rows].toarray()
        tr += float(np.sum((W @ P) * W))
        out[name] = len(rows) - tr
    return out


#: Largest factor by which one iteration changes a level.
MAX_STEP = 10.0


def _next_level(level: float, ratio: float) -> float:
    """Helmert's update σ ← σ·sqrt(r'r/ρ) (Newton's step on log(r'r/ρ) = 0 when the ratio falls
    like σ⁻², a well-determined component), at most ×/÷ ``MAX_STEP``."""
    return level * float(np.clip(np.sqrt(max(ratio, 0.0)), 1 / MAX_STEP, MAX_STEP))


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
    for it in range(1, max_iter + 1):
        solver, sol, data = cur
        idx = rows(solver)
        J, G = solver.jacobians(sol.x, data=data)
        red = redundancies(J, G, stages, idx)
        r = solver.residuals(sol.x, data=data)
        ratio = {k: float(np.sum(r[i] ** 2)) / max(red[k], 1e-12) for k, i in idx.items()}
        kept |= {k for k in levels if red[k] < MIN_REDUNDANCY_SHARE * idx[k].size}
        new = {k: levels[k] if k in kept else _next_level(levels[k], ratio[k]) for k in levels}
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

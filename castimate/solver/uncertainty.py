"""Uncertainty: Fisher information J^T J at the solution, elimination of the nuisance variables
(pose directions, motion) by a sparse Schur complement, marginal covariance and undetermined
directions.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def factor(K: sp.spmatrix):
    """Sparse LU of a symmetric (KKT) matrix. The minimum-degree ordering on K + K^T keeps the
    triangular solves fast: with SuperLU's default COLAMD, solving for 100 right-hand sides on a
    block-diagonal motion block of 18 000 rows took 31 s instead of 0.17 s. (scipy.sparse.linalg
    is imported here: a dynamic solve with the motion eliminated never needs it.)"""
    from scipy.sparse.linalg import splu

    return splu(sp.csc_matrix(K), permc_spec="MMD_AT_PLUS_A")


def information(solver, x, p_fixed=None, data=None) -> sp.csc_matrix:
    """The Fisher information J^T J of the whitened residuals (priors included) at scaled x, in
    the layout's order and scaled units, assembled like the Hessian from the local Jacobians."""
    if solver.projection is not None:  # small problems (tests): from the Jacobian
        J = solver.jacobians(x, p_fixed, data)[0]
        return (J.T @ J).tocsc()
    A = solver.assembly
    U = A.csc(A.hessian_values(A.assemble(solver.nlp_order(x), *solver.fixed_and_data(p_fixed, data), information=True)))
    F = (U + U.T - sp.diags(U.diagonal())).tocsr()
    return F[A.ipos][:, A.ipos].tocsc()

def eliminate(solver, x, p_fixed=None, data=None, g: np.ndarray | None = None):
    """Eliminate the nuisance block from the Gauss-Newton KKT system at x.

    With F = J^T J split into reported parameters t and nuisance n, and N = [[F_nn, G_n^T],
    [G_n, 0]] the sparse KKT matrix of the nuisance block with its own constraints, returns
    S = F_tt - B N^-1 B^T, the constraints G_t on t, and, for a gradient g, the reduced
    gradient g_t - B N^-1 g_n and g_n^T N^-1 g_n. Unit-norm constraints act on either block,
    never both.
    """
    if solver.projection is not None:
        return _eliminate_projected(solver, x, p_fixed, data, g)
    # in NLP order: the reported parameters are calibration variables, never stage variables
    A = solver.assembly
    pf, d = solver.fixed_and_data(p_fixed, data)
    F_cc, F_cs, F_ss = A.information_blocks(A.assemble(solver.nlp_order(x), pf, d, information=True))
    G = solver.constraint_jacobian(x, pf)[:, solver.perm].tocsc()
    g = None if g is None else np.asarray(g, float)[solver.perm]
    t = A.ipos[solver.theta]
    nc = np.setdiff1d(np.arange(A.c), t)
    nu = np.concatenate([nc, np.arange(A.c, solver.n_x)])
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
            lu = factor(K)
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


def _eliminate_projected(solver, x, p_fixed, data, g):
    """:func:`eliminate` with the nuisance families eliminated by the projection
    (:meth:`castimate.solver.elimination.Projection.marginal`), then the remaining nuisance
    calibration variables (if any) by :func:`eliminate_rest`."""
    pf, d = solver.fixed_and_data(p_fixed, data)
    x = np.asarray(x, float)
    S, gr, g_nn = solver.projection.marginal(x, pf, d, g)
    S_tt, G_t, g_t, rest_nn, _ = eliminate_rest(solver, x, pf, S, gr)
    return S_tt, G_t, g_t, g_nn + rest_nn


def eliminate_rest(solver, x, pf, S, gr=None):
    """The nuisance calibration variables outside the projection's families (e.g. a joint problem's
    pose directions) eliminated from the families' marginal information S (c, c) by a dense Schur
    complement with their constraints: (S_tt, G_t, for a gradient ``gr`` (c,) the reduced gradient
    and g_n^T K^-1 g_n, and D = K^-1 B, their change per unit change of the reported parameters to
    first order, or None where there are none)."""
    P = solver.projection
    G = solver.constraint_jacobian(x, pf)[:, P.cal]
    t = P.tpos[solver.theta]
    nc = np.setdiff1d(np.arange(P.c), t)
    on_t = np.asarray(abs(G[:, t]).sum(axis=1)).ravel() > 0
    on_n = np.asarray(abs(G[:, nc]).sum(axis=1)).ravel() > 0
    G_t, G_n = G[on_t][:, t].toarray(), G[on_n & ~on_t][:, nc].toarray()
    S_tt, g_t, g_nn, D = S[np.ix_(t, t)], None if gr is None else gr[t], 0.0, None
    if len(nc):
        k = G_n.shape[0]
        K = np.zeros((len(nc) + k, len(nc) + k))
        K[: len(nc), : len(nc)], K[len(nc):, : len(nc)], K[: len(nc), len(nc):] = S[np.ix_(nc, nc)], G_n, G_n.T
        B = np.zeros((len(nc) + k, len(t)))
        B[: len(nc)] = S[np.ix_(nc, t)]
        rhs = B if gr is None else np.column_stack([B, np.concatenate([gr[nc], np.zeros(k)])])
        try:
            Y = np.linalg.solve(K, rhs)
        except np.linalg.LinAlgError:
            raise np.linalg.LinAlgError("the nuisance variables are not determined by the data") from None
        S_tt, D = S_tt - B.T @ Y[:, : len(t)], Y[: len(nc), : len(t)]
        if gr is not None:
            g_t = g_t - B.T @ Y[:, -1]
            g_nn = float(gr[nc] @ Y[: len(nc), -1])
    return S_tt, G_t, g_t, g_nn, D


def memo_key(x, pf, d) -> tuple:
    """The point of a marginal information in ``Solver.marginal_memo``: (x, fixed values, data)."""
    return np.asarray(x, float).tobytes(), pf.tobytes(), None if d is None else hash(d.tobytes())


def marginal_information(solver, x, p_fixed=None, data=None) -> tuple[np.ndarray, np.ndarray]:
    """Fisher information of the reported parameters with the nuisance variables marginalised:
    (S, G_theta), see :func:`eliminate`. The last point's is kept (``solver.marginal_memo``): the
    covariance and the identifiability check of a solution ask for the same one, and the HAC
    covariance's elimination (:mod:`castimate.solver.serial`) leaves its own there."""
    pf, d = solver.fixed_and_data(p_fixed, data)
    x = np.asarray(x, float)
    key = memo_key(x, pf, d)
    memo = solver.marginal_memo
    if memo is None or memo[0] != key:
        S, G_t, _, _ = eliminate(solver, x, pf, d)
        solver.marginal_memo = memo = (key, S, G_t)
    return memo[1].copy(), memo[2].copy()

def undetermined(solver, x, p_fixed=None, data=None, top: int = 4) -> list[str]:
    """Directions of the reported parameters the data cannot determine at x, each named by its
    largest components."""
    try:
        S, G = marginal_information(solver, x, p_fixed, data)
    except np.linalg.LinAlgError as e:
        return [str(e)]
    U = np.linalg.qr(G.T, mode="complete")[0][:, G.shape[0]:] if G.shape[0] else np.eye(len(solver.theta))
    w, V = np.linalg.eigh(U.T @ S @ U)
    if not w.size:  # nothing reported is free (e.g. only the motion of a dynamic problem)
        return []
    tol = solver.options.identifiability_tol * max(w.max(), 1e-300)
    out, labels = [], None
    for k in np.flatnonzero(w <= tol):
        labels = solver.problem.layout.x_labels if labels is None else labels  # only to name one (every x's: 0.1 s)
        d = U @ V[:, k]
        idx = np.argsort(-np.abs(d))[:top]
        idx = [i for i in idx if abs(d[i]) > 0.2 * abs(d[idx[0]])]
        out.append(" + ".join(f"{d[i]:+.2f}*{labels[solver.theta[i]]}" for i in idx))
    return out

def covariance(solver, x, p_fixed=None, data=None) -> np.ndarray:
    """Covariance of the reported parameters ``theta`` (physical units), nuisance marginalised.

    The top-left block of the inverse of [[S, G^T], [G, 0]] with S the marginal information:
    U (U^T S U)^-1 U^T for a basis U of the constraints' tangent space.
    """
    S, G = marginal_information(solver, x, p_fixed, data)
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
    s = solver.problem.layout.x_scale[solver.theta]
    return C * np.outer(s, s)

def partial_bound(solver, x, p_fixed=None, data=None, share: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """The Cramér-Rao bound of the reported parameters when some directions are undetermined: σ's
    (physical units) of the inverse of the marginal information on the determined subspace (the
    tangent space of the constraints less the undetermined directions of :func:`undetermined`, same
    tolerance), i.e. the bound with those directions held fixed (as a prior would), and a mask of
    the parameters that carry an undetermined direction: a component above ``share`` of that
    direction's largest (their bound is infinite; the σ given for them is not a bound)."""
    S, G = marginal_information(solver, x, p_fixed, data)
    c = G.shape[0]
    U = np.linalg.qr(G.T, mode="complete")[0][:, c:] if c else np.eye(len(solver.theta))
    w, V = np.linalg.eigh(U.T @ S @ U)
    null = w <= solver.options.identifiability_tol * max(w.max(), 1e-300)
    D = U @ V[:, ~null]
    C = (D / w[~null]) @ D.T
    N = np.abs(U @ V[:, null])
    undetermined_mask = (N > share * N.max(axis=0, initial=0.0)).any(axis=1)
    return np.sqrt(np.clip(np.diag(C), 0, None)) * solver.problem.layout.x_scale[solver.theta], undetermined_mask


def newton_decrement(solver, x, lam_g, p_fixed=None, data=None) -> float:
    """g^T H^-1 g of the Lagrangian gradient with the Gauss-Newton Hessian on the constraints'
    tangent space: twice the χ² decrease a full Newton step would still achieve. The nuisance
    block is eliminated first (:func:`eliminate`), so this costs what the covariance costs."""
    pf, d = solver.fixed_and_data(p_fixed, data)
    G = solver.constraint_jacobian(x, pf)
    lam, lam_g = np.zeros(solver.n_constraints), np.asarray(lam_g, float).ravel()
    if lam_g.size == solver.constraint_order.size:  # a solve's multipliers (Solution.lam_g)
        lam[solver.constraint_order] = lam_g  # CasADi's multipliers follow its constraint order (grouped by width)
    elif lam_g.any():  # else only zeros, of any length: no multipliers
        raise ValueError(f"expected {solver.constraint_order.size} constraint multipliers, found {lam_g.size}")
    if solver.projection is not None:
        g = solver.projection.gradient(np.asarray(x, float), pf, d)
    else:
        g = solver.assembly.derivatives(solver.nlp_order(x), pf, d)[1][solver.assembly.ipos]
    g = g + G.T @ lam
    try:
        S, G_t, g_t, g_nn = eliminate(solver, x, p_fixed, data, g)
    except np.linalg.LinAlgError:
        return float("inf")
    # the same marginal information as marginal_information's at x: kept for the identifiability
    # check or covariance that follows (the score test asks for both at one point)
    x = np.asarray(x, float)
    solver.marginal_memo = (memo_key(x, pf, d), S.copy(), G_t.copy())
    nt, c = S.shape[0], G_t.shape[0]
    K = np.zeros((nt + c, nt + c))
    K[:nt, :nt], K[nt:, :nt], K[:nt, nt:] = S, G_t, G_t.T
    try:
        step = np.linalg.solve(K, np.concatenate([g_t, np.zeros(c)]))[:nt]
    except np.linalg.LinAlgError:
        return float("inf")
    return g_nn + float(g_t @ step)


def std_by_group(solver, cov: np.ndarray) -> dict[str, np.ndarray]:
    """σ per parameter group (zero where not free) from a covariance of ``solver.theta``, as in
    a :class:`castimate.problem.graph.Solution`'s ``std``."""
    lay = solver.problem.layout
    sd = np.full(solver.n_x, np.nan)
    sd[solver.theta] = np.sqrt(np.clip(np.diag(cov), 0, None))
    out = {}
    for g in lay.groups:
        v = np.zeros(g.free.shape)
        v[g.free] = sd[lay.x_indices(g.name)]
        out[g.name] = g.shaped(v)
    return out

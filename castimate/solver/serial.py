"""Honest σ's under serially correlated residuals: a HAC (heteroskedasticity and autocorrelation
consistent) sandwich covariance of the reported parameters, the estimates unchanged.

The Fisher covariance C = (Ĵᵀ Ĵ)⁻¹ (:func:`castimate.solver.uncertainty.covariance`) assumes white
whitened residuals. When they are correlated in time (on the MIMU4444 sessions the lag-1
autocorrelation is about 0.5 after every model), the least-squares estimate stays consistent but
its covariance is the sandwich (Newey & West 1987; Andrews 1991, eq. 2.3)::

    Cov_θ = C S̃ C,    S̃ = Σ_|l|<L (1 - |l|/L) Σ_t ĝ_t ĝ_{t+l}ᵀ   (Bartlett weights)

with ĝ_t = Σ_{rows n of sample t} Ĵ_nᵀ e_n the score of sample t: e_n the whitened residual and
Ĵ = J_θ - J_m D the Jacobian with the nuisance variables m (the motion, then any other nuisance
calibration variable) eliminated, D = H_mm⁻¹ H_mθ, which the Schur complement onto θ already
computes (:meth:`castimate.solver.elimination.Projection.nuisance_map`; linear in the samples).
The constraints act through C, the covariance on their tangent space.

The scores are summed over the channels of a sample before the lags are taken. Each sample's
motion is fitted to that sample's rows, so Ĵ_tᵀ J_m,t = 0 sample by sample (independent samples)
and the sum ĝ_t is unbiased, while per-channel score products miss the motion's leverage
(-P_nm e_n e_m, up to 60 % of a row's variance gyro-free). The sum also keeps the correlation
between channels at the same sample (vibration seen by every triad).

Rows of instances that are not in a time series (priors, averaged static poses) are independent:
they contribute their Fisher information Ĵ_nᵀ Ĵ_n.

The bandwidth is Andrews' AR(1) plug-in (Andrews 1991, eqs. 6.2 and 6.4), from the lag-1
autocorrelation ρ_a and innovation variance σ_a² of each channel's whitened residuals::

    α(1) = Σ_a 4 ρ_a² σ_a⁴ / ((1 - ρ_a)⁶ (1 + ρ_a)²) / Σ_a σ_a⁴ / (1 - ρ_a)⁴,   S_T = 1.1447 (α(1) T)^(1/3)

and L = round(S_T) (at least 1: white residuals give the Fisher information's empirical form).

Every reported σ is at least its Fisher σ (:func:`at_least`; the correlations stay the
sandwich's). The sandwich is estimated from residuals, which
the fit has shrunk (by its leverage, and across samples by the process model's smoothing, which
makes neighbouring residuals anticorrelated); with white noise its scatter around the Fisher
covariance is then biased low (std(error/σ) 1.14-1.24 in simulation against 1.01-1.10 with the
Fisher σ's). Sensor noise is not anticorrelated in time, so a σ below the Fisher σ is that bias,
not information.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .uncertainty import covariance, eliminate_rest, factor, information, memo_key

ANDREWS_BARTLETT = 1.1447  # Andrews 1991, eq. 6.2: S_T = 1.1447 (α(1) T)^(1/3) for the Bartlett kernel
RHO_LIMIT = 0.97  # |ρ| at which the AR(1) plug-in is clipped (its α diverges as ρ -> 1)
ROW_CHUNK = 20000  # residual rows eliminated at a time (dense (rows, nθ) arrays)


def bartlett(G: np.ndarray, L: int) -> np.ndarray:
    """Σ_|l|<L (1 - |l|/L) Σ_t g_t g_{t+l}ᵀ of the rows g_t of G (T, k), in O(T k²).

    Bartlett's triangle is a box convolved with itself: with the moving sums b_j = Σ_{t=j-L+1}^{j} g_t
    (zeros outside the record), Σ_j b_j b_jᵀ = Σ_{t,s} (L - |t - s|)₊ g_t g_sᵀ."""
    G = np.asarray(G, float)
    L = max(1, int(L))
    if L == 1:
        return G.T @ G
    c = np.vstack([np.zeros((1, G.shape[1])), np.cumsum(np.vstack([G, np.zeros((L - 1, G.shape[1]))]), axis=0)])
    B = c[1:] - np.vstack([np.zeros((L, G.shape[1])), c[1:-L]])
    return (B.T @ B) / L


def lag1(E: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of E (T, channels), NaN where a channel has no reading: the lag-1 products
    Σ e_t e_{t+1} and squares Σ e_t² over the pairs of consecutive readings, and the variance
    (mean square). ρ = products / squares."""
    E = np.asarray(E, float)
    both = np.isfinite(E[1:]) & np.isfinite(E[:-1])
    a, b = np.where(both, E[:-1], 0.0), np.where(both, E[1:], 0.0)
    num = (a * b).sum(axis=0)
    den = 0.5 * ((a * a).sum(axis=0) + (b * b).sum(axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.nanmean(np.where(np.isfinite(E), E * E, np.nan), axis=0) if E.size else np.zeros(E.shape[1])
    return num, den, var


def andrews_bandwidth(rho: np.ndarray, var: np.ndarray, T: int) -> float:
    """Andrews' (1991, eqs. 6.2, 6.4) AR(1) plug-in bandwidth S_T of the Bartlett kernel from the
    channels' lag-1 autocorrelations ρ and variances (equal weights); innovation variance σ² = var (1 - ρ²)."""
    rho = np.clip(np.asarray(rho, float), -RHO_LIMIT, RHO_LIMIT)
    s4 = (np.asarray(var, float) * (1 - rho ** 2)) ** 2
    ok = np.isfinite(rho) & np.isfinite(s4) & (s4 > 0)
    if not ok.any() or T < 2:
        return 1.0
    rho, s4 = rho[ok], s4[ok]
    alpha = float((4 * rho ** 2 * s4 / ((1 - rho) ** 6 * (1 + rho) ** 2)).sum() / (s4 / (1 - rho) ** 4).sum())
    return ANDREWS_BARTLETT * (alpha * T) ** (1 / 3)


@dataclass
class SerialCovariance:
    """The HAC covariance of the reported parameters and what it rests on."""

    covariance: np.ndarray  # (nθ, nθ) physical units, Solver.theta order
    fisher: np.ndarray  # the Fisher covariance (white residuals), same layout
    bandwidth: float  # Andrews' S_T (samples)
    lags: int  # L: Bartlett weights 1 - |l|/L for |l| < L
    samples: int  # T, the length of the time series
    channels: list = field(default_factory=list)  # (block name, rank within a sample, component) per channel
    rho: np.ndarray = None  # lag-1 autocorrelation of each channel's whitened residuals
    products: np.ndarray = None  # Σ e_t e_{t+1} per channel (to pool channels: ρ = Σ products / Σ squares)
    squares: np.ndarray = None

    @property
    def inflation(self) -> np.ndarray:
        """σ_HAC / σ_Fisher per reported parameter."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(np.diag(self.covariance) / np.diag(self.fisher))


def at_least(cov: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """``cov`` with every parameter's variance raised to at least ``floor``'s, its correlations kept:
    D cov D with D = diag(max(1, √(floor_ii / cov_ii))). A parameter whose variance in ``cov`` is
    zero takes ``floor``'s row and column. (Clipping the generalised eigenvalues of the pair at 1
    instead raises the σ's above both wherever the sandwich scatters above the Fisher covariance in
    some directions and below it in others: 24 % above both on a simulated 8-IMU board.)"""
    dc, df = np.diag(cov), np.diag(floor)
    zero = ~(dc > 0)
    s = np.where(zero, 1.0, np.sqrt(np.maximum(1.0, np.divide(df, dc, out=np.ones_like(dc), where=~zero))))
    out = cov * np.outer(s, s)
    out[zero, :], out[:, zero] = floor[zero, :], floor[:, zero]
    return out


def _elimination(solver, x, pf, d):
    """A function mapping sparse Jacobian rows (layout order, scaled x) to the eliminated rows Ĵ
    (rows, nθ): the nuisance variables (every variable outside ``solver.theta``) eliminated with the
    Fisher information, their constraints included."""
    theta, n = solver.theta, solver.n_x
    P = solver.projection
    if P is None:
        G = solver.constraint_jacobian(x, pf).tocsc()
        nu = np.setdiff1d(np.arange(n), theta)
        F = information(solver, x, pf, d).tocsc()
        on_t = np.asarray(abs(G[:, theta]).sum(axis=1)).ravel() > 0
        G_n = G[~on_t][:, nu]
        if not len(nu):
            return lambda J: J[:, theta].toarray()
        K = sp.bmat([[F[nu][:, nu], G_n.T], [G_n, None]], format="csc") if G_n.shape[0] else F[nu][:, nu]
        rhs = np.zeros((K.shape[0], len(theta)))
        rhs[: len(nu)] = F[nu][:, theta].toarray()
        D = factor(K).solve(rhs)[: len(nu)]
        return lambda J: J[:, theta].toarray() - J[:, nu] @ D
    # the families by the projection's own elimination, then the other nuisance calibration variables;
    # the marginal information on the way is the Fisher covariance's: kept for it (Solver.marginal_memo)
    S, Ds = P.nuisance_map(x, pf, d)
    fam_cols = [f.X.ravel() for f in P.fams]
    Dm = [Dk.reshape(-1, P.c) for Dk in Ds]
    t = P.tpos[theta]
    nc = np.setdiff1d(np.arange(P.c), t)
    S_tt, G_t, _, _, D2 = eliminate_rest(solver, x, pf, S)
    solver.marginal_memo = (memo_key(x, pf, d), S_tt, G_t)

    def eliminate(J):
        J1 = J[:, P.cal].toarray()
        for cols, D in zip(fam_cols, Dm):
            Jm = J[:, cols]
            if Jm.nnz:
                J1 -= Jm @ D
        return J1[:, t] if D2 is None else J1[:, t] - J1[:, nc] @ D2

    return eliminate


def _rows(solver, x, pf, d):
    """Per factor block (then the priors): (name, sparse whitened Jacobian rows (layout order, scaled x),
    whitened residuals, the block's FactorBlock.series or None, rows per instance, valid rows). The
    rows are the solver's own Jacobian (:meth:`Solver.jacobians`, its CSR planned once), a block's
    masked rows empty."""
    n, scale = solver.n_x, solver.problem.layout.x_scale
    res = solver.assembly.local(solver.nlp_order(x), pf, d, "res")
    J_all = solver.jacobians(x, pf, d)[0]  # the valid rows, then the priors
    row0 = k0 = 0
    for b, Rb in zip(solver.blocks, res):
        N, f = b.block.n, b.f
        valid = solver.keep[row0: row0 + N * f.m]
        k1 = k0 + int(valid.sum())
        counts = np.zeros(N * f.m, np.int64)
        counts[valid] = np.diff(J_all.indptr[k0: k1 + 1])
        lo, hi = J_all.indptr[k0], J_all.indptr[k1]
        J = sp.csr_matrix((J_all.data[lo:hi], J_all.indices[lo:hi], np.concatenate([[0], np.cumsum(counts)])),
                          shape=(N * f.m, n))
        yield b.block.name, J, Rb.reshape(-1), getattr(b.block, "series", None), f.m, valid
        row0, k0 = row0 + N * f.m, k1
    pi, pm, ps = solver.prior
    if len(pi):
        w = np.asarray(x, float)[pi] * scale[pi]
        yield "prior", J_all[k0:], (w - pm) / ps, None, 1, np.ones(len(pi), bool)


def serial_covariance(solver, x, p_fixed=None, data=None, lags: int | None = None,
                      pooling: str = "sample", floor: bool = True, fisher=None) -> SerialCovariance | None:
    """The HAC covariance of ``solver.theta`` at scaled layout-order x (module docstring), or None
    when no factor block is a time series (``FactorBlock.series``). ``lags``: a fixed L instead of
    Andrews' plug-in (tests). ``pooling="channel"`` (with ``lags``; for comparison only): the
    Bartlett sum of each channel's own scores, no correlation between channels. ``floor``: the
    σ's are at least the Fisher ones (:func:`at_least`; module docstring). ``fisher``: the Fisher
    covariance at x (physical units, ``Solution.covariance``) where already computed."""
    if pooling not in ("sample", "channel") or (pooling == "channel" and lags is None):
        raise ValueError(f"pooling {pooling!r}: expected 'sample', or 'channel' with lags")
    if not any(getattr(b.block, "series", None) is not None for b in solver.blocks):
        return None
    pf, d = solver.fixed_and_data(p_fixed, data)
    x = np.asarray(x, float)
    reduce = _elimination(solver, x, pf, d)  # first: the Fisher covariance takes its marginal information
    C_phys = covariance(solver, x, pf, d) if fisher is None else np.asarray(fisher, float)
    s = solver.problem.layout.x_scale[solver.theta]
    C = C_phys / np.outer(s, s)
    nt = len(solver.theta)
    T = 1 + max(int(np.max(b.block.series)) for b in solver.blocks
                if getattr(b.block, "series", None) is not None and len(b.block.series))
    Gt = np.zeros((T, nt))  # per-sample scores
    F_ind = np.zeros((nt, nt))  # Fisher information of the independent rows
    S_channels = np.zeros((nt, nt))  # pooling="channel": the channels' own Bartlett sums
    channels, num, den, var = [], [], [], []
    scores = sp.csr_matrix((T, solver.n_x))  # Σ_rows of sample t e_n J_n, before the elimination
    for name, J, e, series, m, valid in _rows(solver, x, pf, d):
        e = np.where(valid, e, 0.0)
        if series is not None:
            series = np.asarray(series, int)
            if pooling == "sample":
                scores = scores + sp.csr_matrix((e, (np.repeat(series, m), np.arange(J.shape[0]))),
                                                shape=(T, J.shape[0])) @ J
            # channels: the k-th instance of a sample and its residual component
            order = np.argsort(series, kind="stable")
            first = np.searchsorted(series[order], series[order])
            rank = np.empty(len(series), int)
            rank[order] = np.arange(len(series)) - first
            E = np.full((T, rank.max() + 1, m), np.nan)
            ok = valid.reshape(-1, m)
            E[series[:, None], rank[:, None], np.arange(m)[None, :]] = np.where(ok, e.reshape(-1, m), np.nan)
            if pooling == "channel":
                for k in range(E.shape[1]):
                    for i in range(m):
                        rows = np.flatnonzero(rank == k) * m + i
                        Jh = reduce(J[rows]) * e[rows, None]
                        Gc = np.zeros((T, nt))
                        np.add.at(Gc, series[rows // m], Jh)
                        S_channels += bartlett(Gc, lags)
            a, b_, v = lag1(E.reshape(T, -1))
            channels += [(name, k, i) for k in range(E.shape[1]) for i in range(m)]
            num.append(a), den.append(b_), var.append(v)
        else:
            for r0 in range(0, J.shape[0], ROW_CHUNK):
                r = slice(r0, min(J.shape[0], r0 + ROW_CHUNK))
                Jh = reduce(J[r])[valid[r]]
                F_ind += Jh.T @ Jh
    # the elimination is linear: ĝ_t = reduce(Σ_n e_n J_n), one row per sample instead of per residual
    for r0 in range(0, T if pooling == "sample" else 0, ROW_CHUNK):
        Gt[r0: r0 + ROW_CHUNK] = reduce(scores[r0: r0 + ROW_CHUNK])
    num, den, var = np.concatenate(num), np.concatenate(den), np.concatenate(var)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = num / den
    S_T = andrews_bandwidth(rho, var, T)
    L = max(1, round(S_T)) if lags is None else int(lags)
    S = (bartlett(Gt, L) if pooling == "sample" else S_channels) + F_ind
    cov = C @ S @ C
    cov = 0.5 * (cov + cov.T) * np.outer(s, s)
    return SerialCovariance(at_least(cov, C_phys) if floor else cov, C_phys, S_T, L, T, channels, rho, num, den)

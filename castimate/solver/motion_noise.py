"""Motion-dependent measurement noise: variance components estimated from the residuals.

A reading taken at a slightly wrong instant (a chip's sampling jitter) is off by −δ u̇, δ the
random age of the sample and u̇ the time derivative of the noise-free reading. With white δ of RMS
τ, the reading's noise variance per axis i is

    σ_i² = σ₀_i² + (τ u̇_i)²                                                             (1)

σ₀ the white noise of the sensor at rest (from the static segments), u̇ = T ḟ for an accelerometer
(ṡ and the rotational terms' derivative at the triad) and T_g ω̇ for a gyroscope: the
``reading_rates`` of the dynamic problem. On the real MIMU4444 sessions the residual variance of the
white-noise fit does grow with |u̇|, but it also has a floor far above σ₀ at low rates and a part
growing with |ω| (gain and coupling errors; ``reports`` and README, "Honest noise"), so the model is

    σ_i² = σ₀_i² + σ_d² + (τ u̇_i)² + (κ |ω|)²                                            (2)

with one σ_d, τ, κ per sensor type (:data:`COMPONENTS`): ``noise.motion_dependent`` in a problem file.

**Estimation.** (2) is linear in its components θ = (1, σ_d², τ², κ²): v_j = Σ_m G_jm θ_m with known,
non-negative regressors G_j = (σ₀_j², 1, u̇_j², |ω|²). The σ's depend on the motion states, so the
exact likelihood of the states has a log-det term ½ Σ log v_j(x) that a least-squares solver does not
carry. castimate instead alternates (Carroll & Ruppert 1988, "Transformation and Weighting in
Regression", ch. 2: generalised least squares with an estimated variance function):

1. the weighted least-squares fit with the σ's of the current θ held fixed (the calibration and
   the motion);
2. θ by maximum likelihood from the residuals e_j with the regressors held fixed, accounting for
   the redundancy r_j = 1 − h_jj of each residual (the motion of a sample absorbs part of its
   readings' noise, E[e_j²] = r_j v_j; Förstner 1979's variance-component estimation):
   e_j² / r_j ~ v_j χ²₁, maximised by Fisher scoring (:func:`variance_components`);

until θ no longer changes. The fixed point is the pseudo-likelihood estimate of Carroll & Ruppert;
their theory shows it is as efficient for the mean parameters (here the calibration) as weighted
least squares with the true σ's, and, unlike the joint maximum likelihood with the log-det term,
it does not let the motion states bend towards a smaller |u̇| or |ω| to shrink their own σ's. The
Fisher σ's of the calibration are then those of the weighted problem at the fixed point (the σ's as
known): the information between θ and the calibration is zero when the variance does not depend on
the calibration, and small here, where it depends on it only through u̇ and ω.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc  # chi2.sf without scipy.stats's import (1 s of the CLI's start)


@dataclass(frozen=True)
class Components:
    """Variance components θ of v = G θ (:func:`variance_components`).

    ``theta`` the estimates (≥ 0), ``std`` their Fisher σ (0 where fixed or at the bound θ = 0),
    ``nll`` the negative log-likelihood ½ Σ (e²/(r v) + log v) at ``theta``, ``iterations``."""

    theta: np.ndarray
    std: np.ndarray
    nll: float
    iterations: int


def negative_log_likelihood(theta, G: np.ndarray, e2r: np.ndarray) -> float:
    """½ Σ_j (e_j²/r_j / v_j + log v_j), v = G θ (the constant ½ log 2π per residual left out)."""
    v = G @ np.asarray(theta, float)
    return 0.5 * float(np.sum(e2r / v + np.log(v)))


def score_information(theta, G: np.ndarray, e2r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient of −:func:`negative_log_likelihood` in θ, s_m = ½ Σ G_jm (e_j²/r_j − v_j)/v_j², and the
    expected information I_mk = ½ Σ G_jm G_jk / v_j²."""
    v = G @ np.asarray(theta, float)
    return 0.5 * G.T @ ((e2r - v) / v ** 2), 0.5 * (G / v[:, None] ** 2).T @ G


def variance_components(e: np.ndarray, r: np.ndarray, G: np.ndarray, theta0, free, max_iter: int = 200,
                        tol: float = 1e-10) -> Components:
    """Maximum likelihood of θ ≥ 0 in v_j = G_j θ from residuals e_j of redundancy r_j ∈ (0, 1].

    Fisher scoring on ½ Σ (e²/(r v) + log v): score s_m = ½ Σ G_jm (e_j²/r_j − v_j)/v_j², information
    I_mk = ½ Σ G_jm G_jk / v_j²; the step is halved until the likelihood does not decrease, and a
    component that would turn negative stays at 0 (active set). Components with ``free`` False keep
    their ``theta0``. The rows of G, e and r with r ≤ 0 or non-finite e carry no information.
    """
    e, r, G = np.asarray(e, float).ravel(), np.asarray(r, float).ravel(), np.asarray(G, float)
    ok = np.isfinite(e) & (r > 0) & np.all(np.isfinite(G), axis=1)
    e2r, G = e[ok] ** 2 / r[ok], G[ok]
    theta = np.array(theta0, float)
    free = np.asarray(free, bool)
    if np.any(G @ theta <= 0):
        raise ValueError("the starting components give a non-positive variance")
    nll = negative_log_likelihood(theta, G, e2r)
    it = 0
    for it in range(1, max_iter + 1):
        s, info = score_information(theta, G, e2r)
        act = free & ~((theta <= 0) & (s < 0))  # at the bound and pushed outwards: stays there
        if not act.any():
            break
        step = np.zeros_like(theta)
        step[act] = np.linalg.solve(info[np.ix_(act, act)], s[act])
        t = 1.0
        while True:
            trial = np.maximum(theta + t * step, 0.0)
            vt = G @ trial
            if np.all(vt > 0):
                new = negative_log_likelihood(trial, G, e2r)
                if new <= nll + 1e-12 * abs(nll):
                    break
            t *= 0.5
            if t < 1e-12:
                trial, new = theta, nll
                break
        change = np.max(np.abs(trial - theta) / np.maximum(np.abs(trial), 1e-300))
        theta, nll = trial, new
        if change < tol:
            break
    info = score_information(theta, G, e2r)[1]
    std = np.zeros_like(theta)
    act = free & (theta > 0)
    if act.any():
        std[act] = np.sqrt(np.diag(np.linalg.inv(info[np.ix_(act, act)])))
    return Components(theta, std, nll, it)


def likelihood_ratio(nll_restricted: float, nll_full: float) -> tuple[float, float]:
    """(Λ, p) for one component tested at its bound 0: Λ = 2 (nll₀ − nll₁) is then distributed as
    ½ χ²₀ + ½ χ²₁ (Self & Liang 1987), so p = ½ P(χ²₁ > Λ)."""
    lam = max(0.0, 2.0 * (nll_restricted - nll_full))
    return lam, 0.5 * float(chdtrc(1, lam))


def block_leverages(rows: np.ndarray, sample: np.ndarray, A: np.ndarray, n_samples: int) -> np.ndarray:
    """Leverage h_jj of every residual row on the nuisance states of its own sample: with A_n the
    whitened Jacobian of sample n's rows with respect to that sample's states,
    h = diag(A_n (A_nᵀ A_n)⁺ A_nᵀ). ``rows`` (R,) row indices into the result, ``sample`` (R,)
    their sample, ``A`` (R, q) their Jacobian rows on the sample's q states. Returns (max(rows)+1,)."""
    order = np.lexsort((rows, sample))
    rows, sample, A = rows[order], sample[order], A[order]
    first = np.searchsorted(sample, np.arange(n_samples))
    pos = np.arange(len(rows)) - first[sample]
    width = int(pos.max()) + 1 if len(pos) else 0
    q = A.shape[1]
    D = np.zeros((n_samples, width, q))
    D[sample, pos] = A
    F = np.einsum("nrq,nrp->nqp", D, D)
    Fi = np.linalg.pinv(F, hermitian=True)
    h = np.einsum("nrq,nqp,nrp->nr", D, Fi, D)
    out = np.zeros(int(rows.max()) + 1 if len(rows) else 0)
    out[rows] = h[sample, pos]
    return out


def stage_leverages(solver, x, groups: tuple[str, ...], data=None) -> np.ndarray:
    """Leverage h_jj (``solver.n_data_residuals``,) of every data residual on the per-sample states
    ``groups`` (matrix groups with one row per sample, e.g. the motion ω, ω̇, s) of its own sample:
    the sample whose row of ``groups[0]`` it depends on. A residual that touches none has h = 0.
    The calibration parameters (a few against thousands of samples) and couplings between samples
    (neighbouring samples' motion in a rate term, a process model) are left out; the redundancy of
    the residual is r = 1 − h (:func:`block_leverages`)."""
    lay = solver.problem.layout
    J = solver.jacobians(x, data=data)[0].tocsr()[: solver.n_data_residuals]
    col_sample = np.full(J.shape[1], -1)
    col_state = np.full(J.shape[1], -1)
    q = 0
    for g in groups:
        w = lay.w_index(g)
        free = w < lay.n_x
        col_sample[w[free]] = np.nonzero(free)[0]
        col_state[w[free]] = q + np.nonzero(free)[1]
        q += w.shape[1]
    coo = J.tocoo()
    anchor = col_state[coo.col] >= 0
    anchor &= col_state[coo.col] < lay.w_index(groups[0]).shape[1]
    row_sample = np.full(J.shape[0], -1)
    row_sample[coo.row[anchor]] = col_sample[coo.col[anchor]]
    keep = (col_state[coo.col] >= 0) & (row_sample[coo.row] >= 0) & (col_sample[coo.col] == row_sample[coo.row])
    rows = np.flatnonzero(row_sample >= 0)
    A = np.zeros((J.shape[0], q))
    A[coo.row[keep], col_state[coo.col[keep]]] = coo.data[keep]
    h = np.zeros(J.shape[0])
    if len(rows):
        lev = block_leverages(rows, row_sample[rows], A[rows], int(row_sample.max()) + 1)
        h[: len(lev)] = lev
    return h


#: The components of the motion-dependent noise model beyond σ₀² (module docstring, eq. 2): name ->
#: (what its regressor g is, the unit of its parameter per sensor). The parameter is √θ.
COMPONENTS = {
    "floor": ("1: a model error of the dynamic phase independent of the motion",
              {"accelerometer": "m/s^2", "gyroscope": "rad/s"}),
    "jitter": ("u̇_i²: a random sample age of RMS τ (sampling jitter)", {"accelerometer": "s", "gyroscope": "s"}),
    "rate": ("|ω|²: an error growing with the angular rate (gain, coupling, lever-arm errors)",
             {"accelerometer": "m/s^2 per rad/s", "gyroscope": "rad/s per rad/s"}),
}


@dataclass(frozen=True)
class ComponentFit:
    """One component of the noise model for one sensor type: its parameter √θ (σ_d, τ or κ) and Fisher
    σ, whether it is kept, and the likelihood-ratio statistic Λ and p-value of dropping it (NaN where
    it was not tested: fixed or free)."""

    value: float
    std: float
    kept: bool
    statistic: float = float("nan")
    p_value: float = float("nan")


def noise_sigma(sigma0, values: dict[str, float], regressors: dict[str, np.ndarray]) -> np.ndarray:
    """Per-sample σ (N, 3) of eq. (2): σ₀ (3,) or (N, 3), parameters √θ by component name, regressors
    g (N, 3) by component name."""
    v = np.asarray(sigma0, float) ** 2
    for k, x in values.items():
        if x:
            v = v + x ** 2 * regressors[k]
    return np.sqrt(v)


def fit_noise(residual, leverage, sigma0, regressors: dict[str, list], settings: dict[str, str | float],
              start: dict[str, float] | None = None, alpha: float = 0.01) -> dict[str, ComponentFit]:
    """Maximum likelihood of the components of σ² = σ₀² + Σ θ_m g_m for the triads of one sensor type:
    lists of (N, 3) residuals e (NaN where masked), leverages h (r = 1 − h) and σ₀ (3,) per triad;
    ``regressors`` component -> list of (N, 3) g per triad; ``settings`` component -> ``free``
    (estimated), ``auto`` (estimated, dropped unless the likelihood-ratio test of θ = 0 rejects at
    ``alpha``, least significant first), ``none`` or a fixed parameter √θ. σ₀ is held (it comes from
    the static segments)."""
    flat = lambda xs: np.concatenate([np.ravel(x) for x in xs])  # noqa: E731
    e, r = flat(residual), 1.0 - flat(leverage)
    names = list(settings)
    G = np.column_stack([flat([np.broadcast_to(np.asarray(s, float) ** 2, np.shape(x)) for s, x in zip(sigma0, residual)])]
                        + [flat(regressors[k]) for k in names])
    ok = np.isfinite(e) & (r > 0) & np.all(np.isfinite(G), axis=1)
    e, r, G = e[ok], r[ok], G[ok]
    e2r = e ** 2 / r
    fixed = {k: float(v) for k, v in settings.items() if not isinstance(v, str)}
    active = [k for k, v in settings.items() if v in ("auto", "free")]
    start = start or {}

    def fit(keep):
        theta0 = np.array([1.0] + [fixed.get(k, start.get(k, 0.0) if k in keep else 0.0) ** 2 for k in names])
        free = [False] + [k in keep for k in names]
        return variance_components(e, r, G, theta0, free)

    keep = list(active)
    full = fit(keep)
    tests = {}
    while True:
        cand = {}
        for k in [k for k in keep if settings[k] == "auto"]:
            lam, p = likelihood_ratio(fit([x for x in keep if x != k]).nll, full.nll)
            cand[k] = (lam, p)
        tests.update(cand)
        drop = [k for k, (_, p) in cand.items() if p >= alpha]
        if not drop:
            break
        keep.remove(max(drop, key=lambda k: cand[k][1]))
        full = fit(keep)
    out = {}
    for i, k in enumerate(names, start=1):
        theta, sd = full.theta[i], full.std[i]
        value = float(np.sqrt(theta))
        lam, p = tests.get(k, (float("nan"), float("nan")))
        out[k] = ComponentFit(value, float(sd / (2 * value)) if value > 0 and k in keep else 0.0,
                              value > 0, lam, p)
    return out

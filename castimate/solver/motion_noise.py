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
2. θ from the residuals e_j with the regressors held fixed, accounting for the redundancy
   r_j = 1 − h_jj of each residual (the fit absorbs part of its noise, E[e_j²] = r_j v_j; h the
   diagonal of the hat matrix): the variance components of :mod:`castimate.solver.variance`, the
   machinery the process-noise levels use too (REML's score equations with the hat diagonal,
   Förstner 1979);

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

from .variance import likelihood_ratio, variance_components


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
    """REML estimate (:func:`castimate.solver.variance.variance_components`) of the components of σ² = σ₀² + Σ θ_m g_m for the triads of one sensor type:
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


#: The bounds of :func:`relaxation`'s factor: at most a tenth of the step is taken (a map whose
#: log-slope is near −9, far beyond the 2-cycles seen), and never more than the step: each estimate
#: comes from a refit that ends at the solver's tolerance, so a secant through two of them is noisy,
#: and extrapolating it (a slow monotone approach, slope in (0, 1)) overshot on real exp_1 and exp_2
#: (9 and 6 refits instead of 5 and 3 with factors up to 2).
RELAXATION_BOUNDS = (0.1, 1.0)


def relaxation(previous: tuple[float, float] | None, x: float, dx: float) -> float:
    """The factor ω of the step x ← x + ω dx of a fixed-point iteration x = F(x), dx = F(x) − x,
    from the previous round's (x, dx): the secant of dx(x), s = (dx − dx₋₁)/(x − x₋₁), gives
    Newton's step for dx(x) = 0, ω = −1/s (Aitken's Δ² per component; Burden & Faires, sec. 2.5).
    A 2-cycle (F' = −1, s = −2) is halved onto its fixed point; an alternation that converges
    slowly (F' ∈ (−1, 0)) is damped onto it too. ω = 1 without a usable previous round (none, no
    movement, or a secant s ≥ 0 along which F does not contract), and within
    :data:`RELAXATION_BOUNDS` (a monotone approach, F' ∈ (0, 1), is not extrapolated).

    >>> relaxation((0.0, 1.0), 1.0, -1.0)  # x₋₁ = 0 → 1 → back to 0: a 2-cycle
    0.5
    """
    if previous is None or abs(x - previous[0]) < 1e-12:
        return 1.0
    s = (dx - previous[1]) / (x - previous[0])
    if s >= 0:
        return 1.0
    return float(np.clip(-1.0 / s, *RELAXATION_BOUNDS))


@dataclass(frozen=True)
class OuterIteration:
    """How :func:`relaxed_fixed_point` ended: the parameters of the last weighted fit, the number of
    weighted refits, whether the estimate from the last fit changed no σ by more than the
    tolerance, that last change, and a status line."""

    params: dict[str, dict[str, float]]
    rounds: int
    converged: bool
    change: float
    status: str


def relaxed_fixed_point(propose, refit, params: dict[str, dict[str, float]], relaxed, tol: float, max_rounds: int,
                        log=lambda m: None) -> OuterIteration:
    """The outer iteration of the noise model: θ = F(θ), F the components estimated from the weighted
    fit with θ's σ's.

    ``propose(params)`` -> (the estimate F from the current fit, the largest relative change of a σ
    from ``params`` to it); ``refit(params)`` fits with the σ's of ``params``. Converged when the change
    is at most ``tol`` (after at least one refit, or at once when the white noise needs nothing
    added); unconverged after ``max_rounds`` refits. Each round moves every estimated (``relaxed(s,
    k)``) positive parameter in log-space by the secant factor of :func:`relaxation`; one switched on or
    off (0 ↔ > 0) takes the estimate as it is.
    """
    steps: dict = {}
    rounds = 0
    while True:
        proposal, change = propose(params)
        if rounds == 0 and not any(v for c in proposal.values() for v in c.values()):
            converged = True
            break
        if rounds > 0 and change <= tol:
            converged = True
            break
        if rounds == max_rounds:
            converged = False
            break
        new = {s: dict(c) for s, c in proposal.items()}
        for s, c in proposal.items():
            for k, v in c.items():
                old = params[s][k]
                if relaxed(s, k) and old > 0 and v > 0:
                    x, dx = float(np.log(old)), float(np.log(v / old))
                    w = relaxation(steps.get((s, k)), x, dx)
                    steps[s, k] = (x, dx)
                    new[s][k] = float(np.exp(x + w * dx))
                else:
                    steps.pop((s, k), None)
        params, rounds = new, rounds + 1
        log(f"motion-dependent noise, round {rounds}: " + "; ".join(
            f"{s}: " + ", ".join(f"{k} {v:.3g}" for k, v in c.items() if v) for s, c in params.items()
            if any(c.values())) + f" (the estimate changed a σ by up to {change:.1%})")
        refit(params)
    status = (f"converged after {rounds} weighted refit(s): the components estimated from the last fit change no σ "
              f"by more than {change:.2%} (tolerance {tol:.0%})" if converged else
              f"not converged: stopped at the limit of {max_rounds} weighted refits with the components estimated "
              f"from the last fit still changing a σ by {change:.2%} (tolerance {tol:.0%})")
    return OuterIteration(params, rounds, converged, change, status)

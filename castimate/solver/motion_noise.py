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

import functools
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from .variance import likelihood_ratio, solve_components


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
              start: dict[str, float] | None = None, alpha: float = 0.01, warm: dict | None = None
              ) -> dict[str, ComponentFit]:
    """REML estimate (:func:`castimate.solver.variance.variance_components`) of the components of σ² = σ₀² + Σ θ_m g_m for the triads of one sensor type:
    lists of (N, 3) residuals e (NaN where masked), leverages h (r = 1 − h) and σ₀ (3,) per triad;
    ``regressors`` component -> list of (N, 3) g per triad; ``settings`` component -> ``free``
    (estimated), ``auto`` (estimated, dropped unless the likelihood-ratio test of θ = 0 rejects at
    ``alpha``, least significant first), ``none`` or a fixed parameter √θ. σ₀ is held (it comes from
    the static segments). ``warm`` (filled here): the components of every fit made (the full model
    and those without one component each, for the tests), where the next call starts the same fit,
    e.g. the outer iteration's next round (from the previous parameters Newton's method took up to
    23 iterations on real exp_1 for a fit without a component, from its last optimum 3-5)."""
    warm = {} if warm is None else warm
    flat = lambda xs: np.concatenate([np.ravel(x) for x in xs])  # noqa: E731
    e, r = flat(residual), 1.0 - flat(leverage)
    names = list(settings)
    G = np.column_stack([flat([np.broadcast_to(np.asarray(s, float) ** 2, np.shape(x)) for s, x in zip(sigma0, residual)])]
                        + [flat(regressors[k]) for k in names])
    ok = np.isfinite(e) & (r > 0) & np.all(np.isfinite(G), axis=1)
    e, r, G = e[ok], r[ok], G[ok]
    e2, Gt = e ** 2, np.ascontiguousarray(G.T)  # the rows as every fit below takes them
    fixed = {k: float(v) for k, v in settings.items() if not isinstance(v, str)}
    active = [k for k, v in settings.items() if v in ("auto", "free")]
    start = start or {}
    # where to start: the previous round's parameters (the outer iteration's), or, for components
    # without one, the moment estimate (from the white fit Newton's method took ~30 iterations)
    guess = functools.cache(lambda: moment_estimate(e, r, G))  # only for a fit without a warm start

    def fit(keep, theta=None):
        key = frozenset(keep)
        if key in warm:  # the same fit in the outer iteration's previous round
            theta = warm[key]
        elif theta is None:
            theta = [fixed.get(k, (start.get(k) or np.sqrt(guess()[i])) if k in keep else 0.0) ** 2
                     for i, k in enumerate(names, start=1)]
        theta0 = np.array([1.0] + [t if k in keep or k in fixed else 0.0 for k, t in zip(names, theta)])
        free = [False] + [k in keep for k in names]
        out = solve_components(e2, r, Gt, theta0, free)
        warm[key] = out.theta[1:]
        return out

    keep = list(active)
    full = fit(keep)
    tests = {}
    while True:
        cand = {}
        for k in [k for k in keep if settings[k] == "auto"]:
            # the fit without k starts from the fit with it (the other components move little)
            lam, p = likelihood_ratio(fit([x for x in keep if x != k], full.theta[1:]).nll, full.nll)
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


def moment_estimate(e: np.ndarray, r: np.ndarray, G: np.ndarray) -> np.ndarray:
    """A starting point for the REML iteration of θ (v = G θ, θ₀ = 1 held): the least-squares fit of
    E[e²] = r G θ (moments), each row weighted by 1/(r v)² at the white v = G₀ (the σ₀² column),
    clipped at 0. Returns θ (θ₀ = 1)."""
    v0 = r * G[:, 0]
    A, b = (r[:, None] * G[:, 1:]) / v0[:, None], (e ** 2 - v0) / v0
    theta = np.linalg.lstsq(A, b, rcond=None)[0] if A.shape[1] else np.zeros(0)
    return np.r_[1.0, np.maximum(theta, 0.0)]


#: Anderson acceleration of :func:`accelerated_fixed_point`: the number of previous rounds whose
#: steps enter the multi-secant model, and the damping of a step taken without one (after a restart).
ANDERSON_MEMORY, DAMPING = 3, 0.5
#: The refit after a round whose step (the RMS change of the log σ's) is within TIGHT × the tolerance
#: converges fully; those after larger steps may stop early (:func:`accelerated_fixed_point`). The
#: steps on MIMU4444 exp_1 fall by a factor 20-50 per round (4.1, 0.08, 0.001 bundled; 4.1, 0.13,
#: 0.004, 0.0003 joint), so the next estimate is checkable after a step of 10 %.
TIGHT = 10.0
#: A converged refit whose σ's are within the tolerance (RMS) of those of the fit whose leverages the
#: last estimate took is tested with those leverages, against REUSED × the tolerance: on exp_1 an 8 %
#: step changed the estimate's σ's by 0.03 % RMS (0.25 % at most) through the leverages.
REUSED = 0.5
#: Largest Σ|γ| of an accelerated step (the secant model's weights): beyond it the previous steps are
#: nearly collinear (each refit ends at the solver's tolerance, so their differences are noisy) and
#: the step is damped instead.
MAX_WEIGHTS = 10.0


def anderson_step(z: np.ndarray, f: np.ndarray, history: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """The next iterate of x = F(x) by Anderson acceleration (type II; Walker & Ni 2011, "Anderson
    acceleration for fixed-point iterations", SIAM J. Numer. Anal. 49, eq. 2.1 with β = 1):
    z the current iterate, f = F(z) − z its step, ``history`` the previous rounds' (z, f), oldest
    first. With ΔZ, ΔF the differences of consecutive iterates and steps, γ minimises
    |f − ΔF γ|₂ and the next iterate is z + f − (ΔZ + ΔF) γ: a multi-secant (quasi-Newton) step
    for f(z) = 0 over all coordinates jointly, which settles a 2-cycle of F (any coupling of the
    coordinates) and extrapolates a slow approach. None without history or when γ is not usable
    (Σ|γ| above :data:`MAX_WEIGHTS`). Coordinates non-finite in any round are left out of the fit
    and keep F. All coordinates enter the fit with equal weight: leaving out the 1 % whose steps
    were largest (the readings at poorly determined samples) made them cycle, 10 refits instead of
    6 on real exp_2.

    >>> float(anderson_step(np.array([1.0]), np.array([-1.0]), [(np.array([0.0]), np.array([1.0]))])[0])
    0.5
    """
    if not history:
        return None
    zs = [h[0] for h in history] + [z]
    fs = [h[1] for h in history] + [f]
    ok = np.logical_and.reduce([np.isfinite(v) for v in zs + fs])
    dZ = np.column_stack([(b - a)[ok] for a, b in pairwise(zs)])
    dF = np.column_stack([(b - a)[ok] for a, b in pairwise(fs)])
    gamma = np.linalg.lstsq(dF, f[ok], rcond=1e-8)[0]
    if not np.all(np.isfinite(gamma)) or np.abs(gamma).sum() > MAX_WEIGHTS:
        return None
    out = z + f
    out[ok] -= (dZ + dF) @ gamma
    return out


@dataclass(frozen=True)
class OuterIteration:
    """How :func:`accelerated_fixed_point` ended: the components estimated from the last weighted
    fit, the number of weighted refits, whether it converged, the largest relative change of a
    reading's σ by the last estimate (from the previous one), the RMS relative difference between
    the σ's of the last estimate and those the last fit used, and a status line."""

    params: dict[str, dict[str, float]]
    rounds: int
    converged: bool
    change: float
    rms: float
    status: str


def _rms(x: np.ndarray) -> float:
    ok = np.isfinite(x)
    return float(np.sqrt(np.mean(x[ok] ** 2))) if ok.any() else 0.0


def accelerated_fixed_point(propose, refit, z: np.ndarray, tol: float, max_rounds: int, log=lambda m: None,
                            memory: int = ANDERSON_MEMORY) -> OuterIteration:
    """The outer iteration of the noise model as a fixed point of the readings' log σ's: z = Φ(z),
    Φ(z) the log σ's that the components estimated from the weighted fit with the σ's exp(z) give at
    that fit's motion (its regressors u̇, |ω|).

    ``propose(reused)`` -> (the components estimated from the current fit, sensor -> component -> √θ;
    the log σ's they give at the current fit, the layout of ``z``; the log σ's the previous round's
    estimate gives there, None in the first round), with ``reused`` the leverages (the residuals'
    redundancies) of the fit the last estimate was made at instead of the current fit's own, and then
    without taking it as the round's estimate (the next call is the same round's); ``refit(z, tight)`` fits with the σ's exp(z) and
    returns whether that fit converged: with ``tight`` False it may stop early, once the fit no longer
    moves the residuals by much (an intermediate fit, far from the fixed point); ``z`` the log σ's of
    the current (converged) fit. Converged when the estimate from the last fit changes no reading's σ
    by more than ``tol`` (relative, from the previous estimate) and the σ's it gives are within
    ``tol`` of those the fit used in RMS over the readings (after at least one refit, or at once when
    the white noise needs nothing added), that fit converged; unconverged after ``max_rounds`` refits.
    A refit converges fully when the step that chose its σ's was within :data:`TIGHT` × ``tol`` RMS
    (the next estimate may then pass the test); if the test passes at a fit that stopped early, that
    fit is continued to convergence at the same σ's and the test repeated there. A converged fit whose
    σ's are within ``tol`` RMS of those of the fit the last estimate was made at is first tested with
    that fit's leverages, against :data:`REUSED` × ``tol`` (the leverages change little with the σ's;
    the estimates, made at this fit, are the same whichever leverages certify it); failing that, with
    its own. The RMS, not every
    reading: the few readings at saturated or fast samples, where the motion and so u̇ and |ω| are
    poorly determined, move their σ by up to 140 % from one refit to the next on real exp_2 while
    the RMS is 0.3 % and the components are constant to 0.2 % (their largest change is in the status).

    Iterating on the σ's rather than on the components, the motion's part of the map is accelerated
    too: the applied σ's of a plain alternation come from the regressors of the previous fit, and
    on the real MIMU4444 exp_2 and exp_3 (delay variant) the estimate alternated by 1.5–4 % at
    components constant to three digits, which no relaxation of the components settles. Each round
    takes the Anderson step (:func:`anderson_step`) over the last ``memory`` rounds. Safeguards: the
    history restarts when the set of non-zero components changes (a component switched on or off is
    no smooth step) and when a round's step grew in RMS over the previous one (the accelerated step
    did not help), which step is then damped by :data:`DAMPING`; without a usable history otherwise
    the plain step Φ(z) is taken.
    """
    history: list[tuple[np.ndarray, np.ndarray]] = []
    rounds, last_norm, last_support, tight = 0, None, None, True
    at = None  # the log σ's of the fit whose leverages the last estimate took

    def measure(estimate):
        params, g, previous = estimate
        f = g - z
        ok = np.isfinite(f)
        worst = float(np.max(np.abs(np.expm1(f[ok])), initial=0.0))
        norm = _rms(f)
        moved = np.abs(np.expm1(g - previous)) if previous is not None else None
        change = float(np.max(moved[np.isfinite(moved)], initial=0.0)) if moved is not None else float("inf")
        return params, g, previous, f, worst, norm, change

    while True:
        shift = _rms(z - at) if at is not None and tight else float("inf")
        reused = shift <= tol  # the σ's hardly moved since the last leverages: they may serve the test
        params, g, previous, f, worst, norm, change = measure(propose(reused))
        if reused and not (change <= REUSED * tol and norm <= REUSED * tol):
            reused = False  # not converged with margin: the estimate with this fit's own leverages
            params, g, previous, f, worst, norm, change = measure(propose(False))
        if not reused:
            at = z
        support = frozenset((s, k) for s, c in params.items() for k, v in c.items() if v)
        if rounds == 0 and not support:
            converged = True
            break
        if rounds > 0 and change <= tol and norm <= tol:
            if tight:
                converged = True
                break
            log(f"motion-dependent noise, round {rounds}: the estimate is within the tolerance of a fit that "
                f"stopped early; that fit continued to convergence")
            tight = refit(z, True)
            continue
        if rounds == max_rounds:
            converged = False
            break
        grew = last_norm is not None and norm > last_norm
        if support != last_support or grew:
            history = []
        step, how = anderson_step(z, f, history[-memory:]), "Anderson"
        if step is None:
            beta = DAMPING if grew or history else 1.0
            step, how = z + beta * f, "plain" if beta == 1 else f"damped ×{beta:g} (" + (
                "the step grew: restarted)" if grew else "the secant model's weights too large)")
        if rounds:  # the white fit's step (components switched on) starts no secant
            history = (history + [(z, f)])[-memory:]
        last_norm, last_support = norm, support
        z, rounds = np.where(np.isfinite(step), step, g), rounds + 1
        log(f"motion-dependent noise, round {rounds}: " + "; ".join(
            f"{s}: " + ", ".join(f"{k} {v:.3g}" for k, v in c.items() if v) for s, c in params.items()
            if any(c.values())) + (f" (the estimate changed a σ by up to {change:.1%}; " if previous is not None
                                   else " (the first estimate; ") + f"its σ's differ from the fit's by {norm:.2%} "
            f"RMS, {worst:.1%} at most; step: {how})")
        tight = refit(z, norm <= TIGHT * tol)
    what = (f"the estimate from the last fit changed no reading's σ by more than {change:.2%} and its σ's differ "
            f"from that fit's by {norm:.2%} RMS ({worst:.1%} at most; tolerance {tol:.0%})") + (
        f" with the leverages of the previous fit, whose σ's were {shift:.2%} RMS away (tolerance halved)"
        if converged and reused else "")
    status = (f"converged after {rounds} weighted refit(s): {what}" if converged and rounds else
              "converged: the white noise needs no component" if converged else
              f"not converged: stopped at the limit of {max_rounds} weighted refits: {what}")
    return OuterIteration(params, rounds, converged, change, norm, status)

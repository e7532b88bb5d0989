"""Close the loop on measured data: find residual structure, test the effects the model lacks, add
what the data demand, and measure the error before and after (``castimate diagnose``).

The procedure, for a problem with its declared model H0:

1. **Fit H0** and analyse its residual per triad, axis and pose (static) or sample (dynamic): χ²
   against its expected value,
   whiteness over time (lag-1 correlation in time order) and correlation across triads (common
   mode), see :func:`analyse_residuals`.
2. **Score test** every effect of the library (:mod:`castimate.problem.effects`) that the model
   does not include and the data can inform, at the H0 solution and without refitting. With the
   effect's k parameters appended at their neutral value, the Lagrange-multiplier statistic is
   LM = gᵀ I⁻¹ g, g the gradient of ½|r|² and I = JᵀJ the Fisher information (nuisance variables
   eliminated, unit-norm constraints projected out): :meth:`Solver.newton_decrement` at that
   point. The noise σ's are themselves estimates, so LM is put on the residual's own scale,
   F = LM / (k s²) with s² = χ²/dof of H0, and compared with F(k, dof).
3. **Confirm** the significant candidates, most significant first (Wilson–Hilferty z of the
   score statistic), by refitting: the F form of the likelihood-ratio test,
   F = ((χ²₀ − χ²₁)/k) / (χ²₁/dof₁) against F(k, dof₁), and the cross-validated prediction error on
   held-out poses (static) or blocks of samples (dynamic) must not grow. Both tests use α/m, Bonferroni over the m candidates of the round,
   so the family-wise false-alarm rate of a round is at most α.
4. **Add** the first confirmed effect and repeat from 2 until no candidate is significant.

Every kind is handled by one :class:`Session` through the kind's pipeline
(:class:`castimate.kinds.Kind`): read once, fitted with any set of effects. Only the math and
orchestration live here; :mod:`castimate.report.diagnose` writes the report.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from . import CrossValidation, Log, Residuals, kind_of, quiet
from .dynamic import CLOCK_BEAT, estimate_clocks, implied_ages
from ..problem.clocks import Beat, estimate_beats, periodogram
from ..errors import CastimateError, InputError
from ..problem.effects import BY_KEY, EFFECTS, TEMPERATURE, Effect, group_names
from ..spec import ProblemSpec, motion_noise_setting
from ..problem.triads import GroupSetting
from ..solver.ipopt import Solver


#: Family-wise false-alarm level of one round of score tests (Bonferroni over the candidates).
ALPHA = 0.01
#: Cross-validation folds over the poses (interleaved in time, so each fold spans the session).
FOLDS = 5
#: Candidates confirmed by a refit per round, most significant first.
CONFIRM = 2



# ---------------------------------------------------------------------------------------------
# Model variants of one session
# ---------------------------------------------------------------------------------------------

def with_effects(spec: ProblemSpec, keys) -> ProblemSpec:
    """The problem with the effects ``keys`` included, free on every triad that does not set them."""
    settings = dict(spec.model.settings)
    for key in keys:
        e = BY_KEY[key]
        for name in spec.array.names:
            settings.setdefault((name, e.sensor, e.name), GroupSetting(free=(True,) * len(e.group.components)))
    effects = tuple(e.key for e in EFFECTS if e.key in set(spec.model.effects) | set(keys))
    return replace(spec, model=replace(spec.model, settings=settings, effects=effects))


@dataclass
class Model:
    """One fitted model variant of a session."""

    effects: tuple[str, ...]
    outcome: object  # the kind's outcome
    cv: CrossValidation | None = None

    @property
    def chi2(self) -> float:
        return self.outcome.solution.chi2

    @property
    def dof(self) -> int:
        return self.outcome.solution.dof

    @property
    def s2(self) -> float:
        """χ²/dof: the residual's variance relative to the declared σ's."""
        return self.chi2 / self.dof

    def retire(self) -> None:
        """Let go of the outcome's solver once no fit, test or σ starts from this model (a refit
        rejected, or a model another refit replaced): its compiled stage functions and elimination
        state (MIMU4444 exp_1: the declared model's 0.13 GB; the 8 models that the rounds replaced or
        rejected held 2.5 GB). The estimates, residuals and problem stay; ``outcome.solver`` is then
        None."""
        if getattr(self.outcome, "solver", None) is not None:
            self.outcome = replace(self.outcome, solver=None)


class Session:
    """A session read once through its kind's pipeline (:class:`castimate.kinds.Kind`), fitted
    with any set of effects.

    ``warm`` (kinds with ``warm_start``: dynamic sessions): every refit starts from the fit it
    extends (its parameters and motion; the new effect's parameters at their neutral value), and
    every cross-validation fold's fit and prediction from the whole session's fit of the same
    model. The optima are the same as from the nominal start (the reference path, ``warm=False``),
    found without the search from zero motion that a real session's refits kept needing."""

    def __init__(self, spec: ProblemSpec, log: Log = quiet, warm: bool = True):
        if spec.data.static_range is not None:
            raise InputError(spec.path, "data.static", "diagnose runs on a static or a dynamic problem, not a joint one")
        # The search compares models by their χ² and held-out error under the same σ's: the effects are
        # searched with the white noise of the static segments, and the motion-dependent noise model
        # the problem declares is fitted once, to the refined model (Diagnosis.final).
        self.declared, self.kind = spec, kind_of(spec)
        self.spec = replace(spec, noise=replace(spec.noise, motion_dependent=motion_noise_setting("none")))
        self.data = self.kind.load(spec, log)
        self.clocks: dict[str, Beat] = {}  # the chip clocks found by find_clocks (dynamic sessions)
        self.warm = warm and getattr(self.kind, "warm_start", False)
        self.log = log
        self.clock = Stopwatch()  # fits, cross-validation, score tests

    def fit(self, effects=(), start: Model | None = None, spec: ProblemSpec | None = None,
            stage: str = "fits", sigmas: bool = True) -> Model:
        """The model with ``effects`` added to the declared ones (of ``spec``, default: the
        declared problem under white noise), started from ``start``'s fit when warm; its time is
        counted under ``stage``. ``sigmas=False`` (kinds with ``estimate`` and ``with_sigmas``:
        dynamic sessions): the estimates alone, e.g. a candidate's refit, whose σ's are reported
        only if it ends the search (:meth:`with_sigmas`)."""
        s = with_effects(spec or self.spec, effects)
        kw = {"start": start.outcome} if self.warm and start is not None else {}
        with self.clock(stage):
            if not sigmas and hasattr(self.kind, "estimate"):
                return Model(s.model.effects, self.kind.estimate(s, self.data, _indent(self.log), **kw))
            return Model(s.model.effects, self.kind.calibrate(s, self.data, _indent(self.log), quick=True, **kw))

    def with_sigmas(self, model: Model) -> Model:
        """``model`` with its σ's, if it was fitted without them (:meth:`fit`)."""
        if not hasattr(self.kind, "with_sigmas"):
            return model
        with self.clock("fits"):
            outcome = self.kind.with_sigmas(model.outcome)
        return model if outcome is model.outcome else Model(model.effects, outcome, model.cv)

    def augmented(self, model: Model, effects) -> Solver:
        """The Gauss-Newton solver of the model with ``effects`` added (same session regressors),
        on CasADi's virtual machine: a score test evaluates it twice (the gradient, then the
        information for the Newton decrement and the identifiability check), which does not repay
        gcc. The same numbers bit for bit as compiled (:mod:`castimate.jit`). On MIMU4444 exp_1
        dynamic the first round's 10 score tests took 12.8 s so, 11.2 s compiled from the cache and
        29.9 s compiling their libraries."""
        if CLOCK_BEAT in effects:
            self.find_clocks(model)
        s = with_effects(self.spec, effects)
        problem = self.kind.build(self.kind.settled(self.kind.configure(s, self.data), model.outcome), self.data)
        return Solver(problem.lsq, replace(s.solver, hessian="gauss_newton", jit=False))

    def has_temperature(self) -> bool:
        return self.kind.has_temperature(self.data)

    def find_clocks(self, model: Model) -> None:
        """The chip clocks' beats (ν, φ) from ``model``'s implied sample ages, once per session: the
        sawtooth age's regressor for the score test and every later fit (dynamic sessions)."""
        if not self.data.regressors.beats:
            self.clocks = estimate_clocks(model.outcome)
            self.data = replace(self.data, regressors=self.data.regressors.with_beats(
                {n: (b.nu, b.phi) for n, b in self.clocks.items()}))

    def cross_validate(self, effects, folds: int = FOLDS, start: Model | None = None) -> CrossValidation:
        """K-fold prediction error of the model with ``effects``; ``start``: its fit to the whole
        session (warm sessions start every fold there)."""
        spec = with_effects(self.spec, effects)
        with self.clock("cross-validation"):
            return self.kind.cross_validate(spec, self.data, folds, start=start.outcome if self.warm and start
                                            else None, log=_indent(self.log))

    def residuals(self, outcome) -> tuple[np.ndarray, Residuals]:
        return self.kind.residuals(outcome)


def open_session(spec: ProblemSpec, log: Log = quiet, warm: bool = True) -> Session:
    """Read a problem's data once, for fitting any of its model variants."""
    return Session(spec, log, warm)


def _indent(log: Log) -> Log:
    return lambda m: log("    " + m)


# ---------------------------------------------------------------------------------------------
# Residual analysis
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ResidualRow:
    """Residual statistics of one triad axis."""

    triad: str
    sensor: str
    axis: str
    rms: float  # physical units
    chi2: float
    expected: float  # its share of the degrees of freedom
    lag1: float  # correlation of consecutive poses or samples in time order
    lag1_z: float  # lag1 * sqrt(n): about N(0, 1) for white residuals


@dataclass(frozen=True)
class ResidualAnalysis:
    rows: list[ResidualRow]
    common_mode: dict[str, float]  # sensor -> mean correlation between triads' residuals

    def worst(self, n: int = 3) -> list[ResidualRow]:
        return sorted(self.rows, key=lambda r: -r.chi2 / max(r.expected, 1e-12))[:n]


def analyse_residuals(t: np.ndarray, residuals: Residuals, dof: int) -> ResidualAnalysis:
    """Per triad and axis: χ² against its expected share of ``dof``, whiteness over time (lag-1
    correlation in time order), and the correlation of the residuals across triads (a common-mode
    error points at an effect shared by the array, or at the pose or motion model)."""
    order = np.argsort(t, kind="stable")
    n_total = sum(int(np.isfinite(r).sum()) for per in residuals.values() for r, _ in per.values())
    share = dof / max(n_total, 1)
    rows, common = [], {}
    for sensor, per in residuals.items():
        W = []
        for n, (e, sig) in per.items():
            w = e / sig
            W.append(w)
            for a, axis in enumerate("xyz"):
                x = w[order, a]
                x = x[np.isfinite(x)] - np.nanmean(x)
                lag = float(x[1:] @ x[:-1] / (x @ x)) if len(x) > 1 and x @ x > 0 else 0.0
                rows.append(ResidualRow(n, sensor, axis, float(np.sqrt(np.nanmean(e[:, a] ** 2))),
                                        float(np.nansum(w[:, a] ** 2)), share * len(x), lag, lag * np.sqrt(len(x))))
        if len(W) > 1:
            ok = np.all([np.isfinite(w).all(axis=1) for w in W], axis=0)
            C = [np.corrcoef(np.stack([w[ok, a] for w in W]))[np.triu_indices(len(W), 1)].mean() for a in range(3)]
            common[sensor] = float(np.mean(C))
    return ResidualAnalysis(rows, common)


@dataclass(frozen=True)
class TimingTrace:
    """The sample age one triad's residuals imply over time (dynamic sessions, issue 11): the
    residual along the reading's rate, relative to the array's mean age; its periodogram and the
    chip-clock sawtooth that fits it best. A beat shows as a peak (with harmonics), a drift as a
    trend, a delay as a non-zero mean."""

    triad: str
    t: np.ndarray
    age: np.ndarray  # s
    weight: np.ndarray  # 1/s^2: 1/variance of each sample's age
    freqs: np.ndarray  # Hz
    power: np.ndarray  # fraction of the weighted variance a sinusoid explains
    beat: Beat

    @property
    def mean(self) -> float:
        return float(np.sum(self.weight * self.age) / np.sum(self.weight))


def timing_traces(outcome) -> list[TimingTrace]:
    """Per triad: the implied sample age over time, its periodogram and its best sawtooth."""
    t, ages = outcome.data.t, implied_ages(outcome)
    beats = estimate_beats(t, ages)
    return [TimingTrace(n, t, age, w, *periodogram(t, age, w)[:2], beats[n]) for n, (age, w) in ages.items()]


# ---------------------------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------------------------

def _z(F: float, k: int) -> float:
    """Wilson–Hilferty normal deviate of k F ~ χ²(k): ranks statistics whose p-values underflow."""
    a = 2.0 / (9 * k)
    return float(((max(F, 0.0)) ** (1 / 3) - (1 - a)) / np.sqrt(a))


@dataclass(frozen=True)
class ScoreTest:
    """Lagrange-multiplier test of one candidate effect at the current solution."""

    effect: str
    k: int  # parameters the effect adds
    lm: float  # gᵀ I⁻¹ g
    F: float  # lm / (k s²)
    p: float  # against F(k, dof)
    z: float  # Wilson–Hilferty deviate, for ranking
    note: str = ""  # why it was not tested, if it was not


@dataclass(frozen=True)
class Refit:
    """Confirmation of a candidate by refitting."""

    effect: str
    k: int
    chi2_before: float
    chi2_after: float
    F: float
    p: float
    cv_before: CrossValidation | None  # None: not needed (the likelihood-ratio test rejected first)
    cv_after: CrossValidation | None
    delta_bic: float  # on the refit's residual scale; negative favours the effect
    accepted: bool
    reason: str
    model: Model = field(repr=False, default=None)


@dataclass
class Round:
    tests: list[ScoreTest]
    refits: list[Refit]
    level: float  # per-test significance level α/m
    times: dict = field(default_factory=dict)  # stage -> (wall s, CPU s): score tests, refits, cross-validation


class Stopwatch:
    """Wall and CPU time (this process) per stage, summed over its uses."""

    def __init__(self):
        self.times: dict[str, tuple[float, float]] = {}

    @contextlib.contextmanager
    def __call__(self, stage: str):
        w, c = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            w0, c0 = self.times.get(stage, (0.0, 0.0))
            self.times[stage] = (w0 + time.perf_counter() - w, c0 + time.process_time() - c)


def candidates(session: Session, model: Model, tried=()) -> list[Effect]:
    """Library effects the model lacks and the session can inform. An effect that another
    re-parameterises (``Effect.instead_of``: per-triad sensing-element offsets, which the chip model's
    shared ones replace) waits until that one was ``tried`` (passed over in an earlier round: not
    significant, or refitted and rejected); neither is a candidate once the other is in the model."""
    out = []
    replacing = {e.instead_of: e.key for e in EFFECTS if e.instead_of}
    for e in EFFECTS:
        if session.spec.kind not in e.kinds or e.key in model.effects:
            continue
        if e.instead_of in model.effects or replacing.get(e.key) in model.effects:
            continue
        if e.key in replacing and session.spec.kind in BY_KEY[replacing[e.key]].kinds \
                and replacing[e.key] not in tried:
            continue
        if e.sensor == "gyroscope" and not model.outcome.problem.gyro_triads:
            continue
        if TEMPERATURE in e.needs and not session.has_temperature():
            continue
        out.append(e)
    return out


def score_test(session: Session, model: Model, effect: Effect) -> ScoreTest:
    """The score test of ``effect`` at ``model``'s solution (module docstring, step 2)."""
    solver = session.augmented(model, model.effects + (effect.key,))
    lay = solver.problem.layout
    x = lay.x0(model.outcome.solution.values)
    k = sum(len(lay.x_indices(g)) for g in group_names(effect, session.spec.array.names) if g in lay)
    if k == 0:
        return ScoreTest(effect.key, 0, np.nan, np.nan, np.nan, -np.inf,
                         "not determined by these data: the triads' mountings leave every parameter a gauge")
    if effect.key == CLOCK_BEAT:
        # ν and φ were searched over a grid: test only if some chip's periodogram peak stands out
        # of the noise at all the frequencies searched (Bonferroni over the chips at ALPHA)
        p_min = min(b.p for b in session.clocks.values()) * len(session.clocks)
        if p_min >= ALPHA:
            return ScoreTest(effect.key, k, np.nan, np.nan, np.nan, -np.inf,
                             f"no chip's implied-age periodogram has a significant peak (p = {min(p_min, 1):.2g})")
    # the decrement first: its elimination leaves the marginal information that the identifiability
    # check then reads (Solver.marginal_memo), so the nuisance block is eliminated once per candidate
    lm = solver.newton_decrement(x, np.zeros(solver.n_constraints))
    bad = solver.undetermined(x)
    if bad:
        return ScoreTest(effect.key, k, np.nan, np.nan, np.nan, -np.inf, f"not determined by these data: {bad[0]}")
    F = lm / (k * model.s2)
    return ScoreTest(effect.key, k, lm, F, float(stats.f.sf(F, k, model.dof)), _z(F, k))


def confirm(session: Session, model: Model, test: ScoreTest, level: float) -> Refit:
    """Refit with the candidate and apply the likelihood-ratio F test and cross-validation.

    The held-out errors are compared on the folds both models predicted: a fold whose fit or
    prediction did not converge is left out of both, and the reason says which (no fold in common:
    the candidate is not confirmed)."""
    try:
        new = session.fit(model.effects + (test.effect,), start=model, sigmas=False)  # σ's: if it ends the search
    except CastimateError as e:  # not identifiable after all, or no convergence: the candidate is not confirmed
        nan = CrossValidation(0, np.nan, np.nan, np.nan)
        return Refit(test.effect, test.k, model.chi2, np.nan, np.nan, np.nan, model.cv or nan, nan, np.nan, False,
                     f"the refit failed: {e}")
    k = new.outcome.problem.lsq.layout.n_x - model.outcome.problem.lsq.layout.n_x
    F = (model.chi2 - new.chi2) / k / new.s2
    p = float(stats.f.sf(F, k, new.dof))
    n = len(new.outcome.solution.residual)
    dbic = (new.chi2 - model.chi2) / new.s2 + k * np.log(n)
    if p >= level:  # the held-out error is not needed to reject
        return Refit(test.effect, k, model.chi2, new.chi2, F, p, model.cv, None, float(dbic), False,
                     f"likelihood-ratio p = {p:.2g} ≥ {level:.2g}", new)
    model.cv = model.cv or session.cross_validate(model.effects, start=model)
    try:
        new.cv = session.cross_validate(new.effects, start=new)
    except CastimateError as e:  # a fold cannot determine it: not confirmed
        nan = CrossValidation(0, np.nan, np.nan, np.nan)
        return Refit(test.effect, k, model.chi2, new.chi2, F, p, model.cv, nan, float(dbic), False,
                     f"the cross-validation failed: {e}", new)
    both = model.cv.predicted & new.cv.predicted
    cv0, cv1 = model.cv.rms_over(both), new.cv.rms_over(both)
    failed = "; ".join([f"without {test.effect}, {f}" for f in model.cv.failed]
                       + [f"with {test.effect}, {f}" for f in new.cv.failed])
    compared = f" (on the {int(both.sum())} of {len(both)} folds both models predicted; {failed})" if failed else ""
    if not both.any():
        accepted, reason = False, f"no cross-validation fold was predicted by both models: {failed}"
    elif cv1 > cv0:
        accepted, reason = False, f"held-out error grew ({cv0:.4g} → {cv1:.4g}){compared}"
    else:
        accepted, reason = True, f"likelihood-ratio p = {p:.2g} < {level:.2g}; held-out error " \
                                 f"{cv0:.4g} → {cv1:.4g}{compared}"
    return Refit(test.effect, k, model.chi2, new.chi2, F, p, model.cv, new.cv, float(dbic), accepted, reason, new)


# ---------------------------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------------------------

@dataclass
class Diagnosis:
    session: Session
    before: Model
    after: Model
    rounds: list[Round]
    residuals_before: ResidualAnalysis
    residuals_after: ResidualAnalysis
    timing_before: list[TimingTrace] = field(default_factory=list)  # dynamic sessions
    timing_after: list[TimingTrace] = field(default_factory=list)
    final: Model | None = None  # ``after`` refitted with the declared motion-dependent noise model, if any
    times: dict = field(default_factory=dict)  # stage -> (wall s, CPU s), and "total"

    @property
    def spec(self) -> ProblemSpec:
        return self.session.spec

    @property
    def added(self) -> list[str]:
        """The effects added, in the order they were added."""
        return [f.effect for r in self.rounds for f in r.refits if f.accepted]


def _since(clock: Stopwatch, mark: dict) -> dict:
    return {k: (w - mark.get(k, (0.0, 0.0))[0], c - mark.get(k, (0.0, 0.0))[1]) for k, (w, c) in clock.times.items()
            if (w, c) != mark.get(k)}


def diagnose(spec: ProblemSpec, log: Log = quiet, alpha: float = ALPHA, session: Session | None = None,
             max_rounds: int = len(EFFECTS), warm: bool = True, held_out: bool = True) -> Diagnosis:
    """Fit, test, confirm and add effects until nothing significant is left (module docstring).
    ``warm``: refits and cross-validation folds start from the fit they extend (:class:`Session`);
    ``warm=False`` is the reference path, every fit from the nominal start. ``held_out=False``: when
    nothing was added, the declared model's held-out error (reported beside the refined model's; no
    decision reads it) is not computed, and ``before.cv`` stays None (decision-only callers:
    :func:`castimate.simulate.diagnose_trials.diagnose_trials`)."""
    w0, c0 = time.perf_counter(), time.process_time()
    session = session or open_session(spec, log, warm)
    clock = session.clock
    log("fitting the declared model")
    model = before = session.fit()
    log(f"  χ²/dof = {model.s2:.3g} ({model.dof} dof)")
    rounds, tried, waited = [], set(), None
    for _ in range(max_rounds):
        cands = [e for e in candidates(session, model, tried) if waited is None or e.key in waited]
        # a round of effects that waited (below) counts the round before's candidates in its Bonferroni level
        m = len(cands) + (len(rounds[-1].tests) if waited is not None else 0)
        waited = None
        if not cands:
            break
        mark = dict(clock.times)
        level = alpha / m
        with clock("score tests"):
            tests = sorted((score_test(session, model, e) for e in cands), key=lambda t: -t.z)
        for t in tests:
            log(f"  score test {t.effect}: F = {t.F:.3g} (k = {t.k}), p = {t.p:.2g}" + (f" [{t.note}]" if t.note else ""))
        refits = []
        for t in [t for t in tests if t.p < level][:CONFIRM]:
            log(f"  refitting with {t.effect}")
            r = confirm(session, model, t, level)
            log(f"    {'added' if r.accepted else 'rejected'}: {r.reason}"
                + (f" (χ²/dof {model.s2:.4g} → {r.model.s2:.4g})" if r.model is not None else ""))
            refits.append(r)
            if r.accepted:
                break
            if r.model is not None:
                r.model.retire()  # only its χ² is read from here on
        rounds.append(Round(tests, refits, level, _since(clock, mark)))
        log("  round " + f"{len(rounds)}: " + ", ".join(f"{k} {w:.0f} s ({c:.0f} s CPU)" for k, (w, c) in rounds[-1].times.items()))
        accepted = [r for r in refits if r.accepted]
        # passed over: not significant (or not testable), or refitted and rejected
        tried |= {t.effect for t in tests if not t.p < level} | {r.effect for r in refits if not r.accepted}
        if not accepted:
            # an effect that waited for the one replacing it (candidates) is tested in one more round, alone
            waited = {e.key for e in candidates(session, model, tried)} - {e.key for e in cands}
            if waited:
                continue
            break
        if model is not before:
            model.retire()  # replaced: every later fit starts from the new one
        model = accepted[0].model
    if model is before and held_out:
        before.cv = before.cv or session.cross_validate(before.effects, start=before)
    model = session.with_sigmas(model)  # the refits were fitted for their estimates alone
    analyse = lambda m: analyse_residuals(*session.residuals(m.outcome), m.dof)  # noqa: E731
    timing = (lambda m: timing_traces(m.outcome)) if session.kind.sampled else (lambda m: [])  # noqa: E731
    final = model
    if session.declared.noise.motion_noise:
        log("fitting the refined model with the declared motion-dependent noise model")
        final = session.fit(model.effects, start=model, spec=session.declared, stage="noise model")
        log(f"  χ²/dof = {final.s2:.3g}")
    times = dict(clock.times)
    times["total"] = (time.perf_counter() - w0, time.process_time() - c0)
    return Diagnosis(session, before, model, rounds, analyse(before), analyse(model), timing(before), timing(model),
                     final, times)

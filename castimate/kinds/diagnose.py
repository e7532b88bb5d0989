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

Static and dynamic problems are handled by a session each (:class:`StaticSession`,
:class:`DynamicSession`): read once, fitted with any set of effects. Only the math and
orchestration live here; :mod:`castimate.report.diagnose` writes the report.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from . import Log, quiet
from .static import StaticOutcome, calibrate_static, load_static, static_config
from .dynamic import DynamicOutcome, calibrate_dynamic, dynamic_config, load_dynamic, measurement_residuals
from ..errors import CastimateError, InputError, NotConvergedError
from ..problem.dynamic import build_dynamic
from ..problem.effects import BY_KEY, EFFECTS, TEMPERATURE, Effect
from ..spec import ProblemSpec
from ..problem.triads import GroupSetting, Regressors, fixed_config, group_name
from ..problem.static import build_static
from ..solve.ipopt import Solver


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


@dataclass(frozen=True)
class CrossValidation:
    """Prediction error on held-out data: fit on the other folds, fix the calibration (and
    geometry), estimate only the held-out nuisance variables (pose directions or motion), and take
    the residual."""

    folds: int
    rms: float  # whitened residual RMS, all sensors (1 for a perfect model and honest σ)
    rms_acc: float  # m/s^2
    rms_gyro: float  # rad/s, nan without gyroscopes


@dataclass
class Model:
    """One fitted model variant of a session."""

    effects: tuple[str, ...]
    outcome: StaticOutcome | DynamicOutcome
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


Residuals = dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]  # sensor -> triad -> (residual (n, 3), σ (n, 3))


def _cv(white: list, acc: list, gyro: list, folds: int) -> CrossValidation:
    def rms(parts):
        x = np.concatenate([np.ravel(p) for p in parts]) if parts else np.array([])
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")

    return CrossValidation(folds, rms(white), rms(acc), rms(gyro))


class StaticSession:
    """A static session read once, fitted with any set of effects (Nilsson 2014 model)."""

    def __init__(self, spec: ProblemSpec, log: Log = quiet):
        self.spec, self.data = spec, load_static(spec, log)

    def fit(self, effects=()) -> Model:
        s = with_effects(self.spec, effects)
        return Model(s.model.effects, calibrate_static(s, data=self.data, consistency=False))

    def augmented(self, model: Model, effects) -> Solver:
        """The Gauss-Newton solver of the model with ``effects`` added, regressors as in ``model``."""
        s = with_effects(self.spec, effects)
        config, _ = static_config(s, self.data.averages)
        config = replace(config, regressors=model.outcome.problem.config.regressors)
        return Solver(build_static(config, self.data.averages).lsq, replace(s.solver, hessian="gauss_newton"))

    def has_temperature(self) -> bool:
        return bool(self.data.averages.temp_mean)

    def cross_validate(self, effects, folds: int = FOLDS) -> CrossValidation:
        """K-fold over the poses, interleaved in time so that each fold spans the session."""
        s = with_effects(self.spec, effects)
        avg = self.data.averages
        config, _ = static_config(s, avg)
        config = replace(config, regressors=Regressors.from_poses(avg))
        fold = np.empty(avg.n_poses, int)
        fold[np.argsort(avg.t_start, kind="stable")] = np.arange(avg.n_poses) % folds
        white, acc, gyro = [], [], []
        for k in range(folds):
            train, test = np.flatnonzero(fold != k), np.flatnonzero(fold == k)
            prob = build_static(config, avg.take(train))
            sol = Solver(prob.lsq, s.solver).solve()
            if not sol.success:
                raise NotConvergedError(f"cross-validation fold {k + 1} of {folds} did not converge: {sol.message}")
            held = build_static(fixed_config(prob.config, sol.values), avg.take(test))
            hs = Solver(held.lsq, s.solver).solve()
            if not hs.success:
                raise NotConvergedError(f"prediction of fold {k + 1} of {folds} did not converge: {hs.message}")
            bd = held.block_data(avg.take(test))
            r = hs.residual.reshape(-1, 3)
            white.append(r)
            n_acc = len(bd[0])
            acc.append(r[:n_acc] * bd[0][:, 3:6])
            if len(bd) > 1:
                gyro.append(r[n_acc:] * bd[1][:, 3:6])
        return _cv(white, acc, gyro, folds)

    def residuals(self, outcome: StaticOutcome) -> tuple[np.ndarray, Residuals]:
        """Pose mid-times and the residuals with their σ per sensor and triad."""
        avg = outcome.averages
        return (avg.t_start + avg.t_end) / 2, {
            "accelerometer": {n: (r, avg.acc_sigma[n]) for n, r in outcome.residual_acc.items()},
            "gyroscope": {n: (r, avg.gyro_sigma[n]) for n, r in outcome.residual_gyro.items()}}


class DynamicSession:
    """A dynamic session read once, fitted with any set of effects (Carlsson 2017, Schopp 2016)."""

    def __init__(self, spec: ProblemSpec, log: Log = quiet):
        if spec.data.static_range is not None:
            raise InputError(spec.path, "data.static", "diagnose runs on a static or a dynamic problem, not a joint one")
        self.spec, self.loaded = spec, load_dynamic(spec, log)

    def fit(self, effects=()) -> Model:
        s = with_effects(self.spec, effects)
        return Model(s.model.effects, calibrate_dynamic(s, loaded=self.loaded))

    def augmented(self, model: Model, effects) -> Solver:
        s = with_effects(self.spec, effects)
        config = replace(dynamic_config(s, self.loaded.full, quiet), regressors=self.loaded.regressors)
        return Solver(build_dynamic(config, self.loaded.data).lsq, replace(s.solver, hessian="gauss_newton"))

    def has_temperature(self) -> bool:
        return bool(self.loaded.data.temp)

    def cross_validate(self, effects, folds: int = FOLDS) -> CrossValidation:
        """K-fold over contiguous blocks of samples."""
        s = with_effects(self.spec, effects)
        data = self.loaded.data
        fold = np.arange(data.n) * folds // data.n
        white, acc, gyro = [], [], []
        for k in range(folds):
            train, test = np.flatnonzero(fold != k), np.flatnonzero(fold == k)
            fitted = calibrate_dynamic(s, loaded=replace(self.loaded, data=data.take(train)))
            part = data.take(test)
            held = build_dynamic(fixed_config(fitted.problem.config, fitted.solution.values), part)
            hs = Solver(held.lsq, replace(s.solver, hessian="gauss_newton")).solve()
            if not hs.success:
                raise NotConvergedError(f"prediction of fold {k + 1} of {folds} did not converge: {hs.message}")
            ra, rg = measurement_residuals(held, part, hs)
            for r, sig, out in ((ra, part.acc_sigma, acc), (rg, part.gyro_sigma, gyro)):
                for n, e in r.items():
                    out.append(e)
                    white.append(e / sig[n])
        return _cv(white, acc, gyro, folds)

    def residuals(self, outcome: DynamicOutcome) -> tuple[np.ndarray, Residuals]:
        """Sample times and the residuals (NaN where masked) with their σ per sensor and triad."""
        d = outcome.data
        return d.t, {
            "accelerometer": {n: (r, np.broadcast_to(d.acc_sigma[n], r.shape)) for n, r in outcome.residual_acc.items()},
            "gyroscope": {n: (r, np.broadcast_to(d.gyro_sigma[n], r.shape)) for n, r in outcome.residual_gyro.items()}}


Session = StaticSession | DynamicSession


def open_session(spec: ProblemSpec, log: Log = quiet) -> Session:
    """Read a problem's data once, for fitting any of its model variants."""
    return DynamicSession(spec, log) if spec.kind == "dynamic_array" else StaticSession(spec, log)


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
    cv_before: CrossValidation
    cv_after: CrossValidation
    delta_bic: float  # on the refit's residual scale; negative favours the effect
    accepted: bool
    reason: str
    model: Model = field(repr=False, default=None)


@dataclass
class Round:
    tests: list[ScoreTest]
    refits: list[Refit]
    level: float  # per-test significance level α/m


def candidates(session: Session, model: Model) -> list[Effect]:
    """Library effects the model lacks and the session can inform."""
    out = []
    for e in EFFECTS:
        if session.spec.kind not in e.kinds or e.key in model.effects:
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
    k = sum(len(lay.x_indices(group_name(n, effect.sensor, effect.name)))
            for n in session.spec.array.names if group_name(n, effect.sensor, effect.name) in lay)
    bad = solver.undetermined(x)
    if bad:
        return ScoreTest(effect.key, k, np.nan, np.nan, np.nan, -np.inf, f"not determined by these data: {bad[0]}")
    lm = solver.newton_decrement(x, np.zeros(solver.n_constraints))
    F = lm / (k * model.s2)
    return ScoreTest(effect.key, k, lm, F, float(stats.f.sf(F, k, model.dof)), _z(F, k))


def confirm(session: Session, model: Model, test: ScoreTest, level: float) -> Refit:
    """Refit with the candidate and apply the likelihood-ratio F test and cross-validation."""
    try:
        new = session.fit(model.effects + (test.effect,))
    except CastimateError as e:  # not identifiable after all, or no convergence: the candidate is not confirmed
        nan = CrossValidation(0, np.nan, np.nan, np.nan)
        return Refit(test.effect, test.k, model.chi2, np.nan, np.nan, np.nan, model.cv or nan, nan, np.nan, False,
                     f"the refit failed: {e}")
    k = new.outcome.problem.lsq.layout.n_x - model.outcome.problem.lsq.layout.n_x
    F = (model.chi2 - new.chi2) / k / new.s2
    p = float(stats.f.sf(F, k, new.dof))
    model.cv = model.cv or session.cross_validate(model.effects)
    new.cv = session.cross_validate(new.effects)
    n = len(new.outcome.solution.residual)
    dbic = (new.chi2 - model.chi2) / new.s2 + k * np.log(n)
    if p >= level:
        accepted, reason = False, f"likelihood-ratio p = {p:.2g} ≥ {level:.2g}"
    elif new.cv.rms > model.cv.rms:
        accepted, reason = False, f"held-out error grew ({model.cv.rms:.4g} → {new.cv.rms:.4g})"
    else:
        accepted, reason = True, f"likelihood-ratio p = {p:.2g} < {level:.2g}; held-out error " \
                                 f"{model.cv.rms:.4g} → {new.cv.rms:.4g}"
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

    @property
    def spec(self) -> ProblemSpec:
        return self.session.spec

    @property
    def added(self) -> list[str]:
        """The effects added, in the order they were added."""
        return [f.effect for r in self.rounds for f in r.refits if f.accepted]


def diagnose(spec: ProblemSpec, log: Log = quiet, alpha: float = ALPHA, session: Session | None = None,
             max_rounds: int = len(EFFECTS)) -> Diagnosis:
    """Fit, test, confirm and add effects until nothing significant is left (module docstring)."""
    session = session or open_session(spec, log)
    log("fitting the declared model")
    model = before = session.fit()
    log(f"  χ²/dof = {model.s2:.3g} ({model.dof} dof)")
    rounds = []
    for _ in range(max_rounds):
        cands = candidates(session, model)
        if not cands:
            break
        level = alpha / len(cands)
        tests = sorted((score_test(session, model, e) for e in cands), key=lambda t: -t.z)
        for t in tests:
            log(f"  score test {t.effect}: F = {t.F:.3g} (k = {t.k}), p = {t.p:.2g}" + (f" [{t.note}]" if t.note else ""))
        refits = []
        for t in [t for t in tests if t.p < level][:CONFIRM]:
            log(f"  refitting with {t.effect}")
            r = confirm(session, model, t, level)
            log(f"    {'added' if r.accepted else 'rejected'}: {r.reason}")
            refits.append(r)
            if r.accepted:
                break
        rounds.append(Round(tests, refits, level))
        accepted = [r for r in refits if r.accepted]
        if not accepted:
            break
        model = accepted[0].model
    if model is before:
        before.cv = before.cv or session.cross_validate(before.effects)
    analyse = lambda m: analyse_residuals(*session.residuals(m.outcome), m.dof)  # noqa: E731
    return Diagnosis(session, before, model, rounds, analyse(before), analyse(model))

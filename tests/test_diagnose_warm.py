"""Diagnose's warm path on a dynamic session (every refit and cross-validation fold started from the
fit it extends) against the reference path (every fit from the nominal start): the same decisions,
and statistics that agree to a small fraction of their own sampling spread. A cross-validation fold
that does not converge is reported and left out of both models' held-out errors."""

import numpy as np
import pytest

from castimate.errors import NotConvergedError
from castimate.kinds import dynamic
from castimate.kinds.diagnose import Session, confirm, diagnose, score_test
from castimate.output.diagnosis import diagnosis_document
from castimate.problem.effects import BY_KEY

EFFECT = "accelerometer.age"
#: Agreement asked of the two paths, as a fraction of each statistic's own sampling standard deviation.
SHARE = 1e-3


@pytest.fixture(scope="module")
def spec(age_session):
    """A small Carlsson-board session (4 IMUs x 300 samples) with sub-millisecond chip sample ages
    (conftest's, shared with test_diagnose)."""
    return age_session[0]


def _chi2_tol(dof: int) -> float:
    return SHARE * np.sqrt(2.0 * dof)  # χ²'s sampling σ


def _lm_tol(lm: float, k: int) -> float:
    return SHARE * np.sqrt(2.0 * (k + 2.0 * max(lm, 0.0)))  # σ of a noncentral χ²(k, λ ≈ LM)


def _cv_tol(cv) -> float:
    return SHARE * cv.rms / np.sqrt(2.0 * sum(cv.fold_n))  # σ of an RMS of n standard residuals


def test_warm_path_gives_the_reference_decisions_and_statistics(spec, age_diagnosis):
    """Every round of the default run (conftest's, which test_diagnose reads too) against the reference."""
    fast = age_diagnosis
    ref = diagnose(spec, warm=False)
    assert fast.added == ref.added and EFFECT in fast.added, (fast.added, ref.added)
    assert len(fast.rounds) == len(ref.rounds)
    for rf, rr in zip(fast.rounds, ref.rounds):
        assert [t.effect for t in rf.tests] == [t.effect for t in rr.tests]
        for a, b in zip(rf.tests, rr.tests):
            assert (np.isnan(a.lm) and np.isnan(b.lm)) or abs(a.lm - b.lm) <= _lm_tol(b.lm, b.k), (a, b)
        assert [(f.effect, f.accepted) for f in rf.refits] == [(f.effect, f.accepted) for f in rr.refits]
        for a, b in zip(rf.refits, rr.refits):
            assert abs(a.chi2_after - b.chi2_after) <= _chi2_tol(b.model.dof), (a.chi2_after, b.chi2_after)
            for ca, cb in ((a.cv_before, b.cv_before), (a.cv_after, b.cv_after)):
                if cb is None or not np.isfinite(cb.rms):  # not needed, or a fold could not determine it
                    assert (ca is None) == (cb is None) and (ca is None or not np.isfinite(ca.rms)), (ca, cb)
                else:
                    assert not ca.failed and not cb.failed
                    assert abs(ca.rms - cb.rms) <= _cv_tol(cb), (ca.rms, cb.rms)
    assert abs(fast.after.chi2 - ref.after.chi2) <= _chi2_tol(ref.after.dof)
    # the warm refits start at the fit they extend: no attempt from the nominal poses
    last = [f for r in fast.rounds for f in r.refits if f.accepted][-1]
    for r in fast.rounds:
        for f in r.refits:
            assert [a["start"] for a in f.model.outcome.attempts] == ["previous fit"]
            # a refit rejected or replaced let go of its solver (Model.retire: its memory), the last added kept it
            assert (f.model.outcome.solver is None) == (f is not last), (f.effect, f.accepted)
    assert fast.before.outcome.solver is not None and fast.after.outcome.solver is last.model.outcome.solver
    doc = diagnosis_document(fast)
    assert doc["times"]["total"]["wall_s"] > 0 and "cross-validation" in doc["rounds"][0]["times"]


def test_an_unconverged_cross_validation_fold_is_reported(spec, monkeypatch):
    session = Session(spec)
    model = session.fit()
    test = score_test(session, model, BY_KEY[EFFECT])
    n = session.data.data.n
    held = session.data.data.t[np.arange(n) * 5 // n == 2]  # the third block of samples
    calibrate = dynamic.calibrate_dynamic

    def failing(spec_, *args, loaded=None, **kw):
        if loaded is not None and loaded.data.n < n and EFFECT in spec_.model.effects \
                and not np.isin(held, loaded.data.t).any():
            raise NotConvergedError("simulated: IPOPT stopped at the iteration limit")
        return calibrate(spec_, *args, loaded=loaded, **kw)

    monkeypatch.setattr(dynamic, "calibrate_dynamic", failing)
    r = confirm(session, model, test, level=0.01)
    assert not model.cv.failed
    assert len(r.cv_after.failed) == 1 and r.cv_after.failed[0].startswith("fold 3 of 5: the fit did not converge")
    assert "iteration limit" in r.cv_after.failed[0]
    assert list(r.cv_after.predicted) == [True, True, False, True, True]
    both = r.cv_after.predicted
    # the held-out errors are compared on the four folds both models predicted, and the reason says so
    assert "on the 4 of 5 folds both models predicted" in r.reason and "fold 3 of 5" in r.reason
    assert r.cv_after.rms == pytest.approx(r.cv_after.rms_over(both))
    assert model.cv.rms_over(both) != pytest.approx(model.cv.rms)
    assert r.accepted == (r.p < 0.01 and r.cv_after.rms_over(both) <= model.cv.rms_over(both))

    # no fold predicted by the candidate: not confirmed, whatever the likelihood ratio says
    monkeypatch.setattr(dynamic, "calibrate_dynamic", lambda spec_, *a, loaded=None, **kw:
                        (_ for _ in ()).throw(NotConvergedError("simulated"))
                        if loaded is not None and loaded.data.n < n else calibrate(spec_, *a, loaded=loaded, **kw))
    r = confirm(session, model, test, level=0.01)
    assert not r.accepted and r.reason.startswith("no cross-validation fold was predicted by both models")
    assert len(r.cv_after.failed) == 5


def test_a_score_test_compiles_nothing_and_gives_the_compiled_statistic(spec, tmp_path, monkeypatch):
    """A score test's solver runs on CasADi's virtual machine (it is evaluated a few times, which
    would not repay gcc): no library is compiled for it, and its statistic is the one of the same
    solver compiled, bit for bit."""
    from dataclasses import replace

    from castimate import jit
    from castimate.solver.ipopt import Solver

    if jit.compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("CASTIMATE_CACHE_DIR", str(tmp_path))
    session = Session(spec)
    model = session.fit()
    calls, run = [], jit.subprocess.run
    monkeypatch.setattr(jit.subprocess, "run", lambda *a, **k: calls.append(a) or run(*a, **k))
    test = score_test(session, model, BY_KEY[EFFECT])
    assert not calls and test.k > 0 and test.lm > 0
    vm = session.augmented(model, model.effects + (EFFECT,))
    compiled = Solver(vm.problem, replace(vm.options, jit=True))
    assert calls  # the augmented model's libraries were new to the cache: compiled now
    x = vm.problem.layout.x0(model.outcome.solution.values)
    assert compiled.newton_decrement(x, np.zeros(compiled.n_constraints)) == test.lm


def test_cross_validation_folds_compute_no_uncertainty(spec, monkeypatch):
    """The folds use their fits' estimates only: no Fisher or HAC σ's are computed for them, and the
    estimates are those of the solve with σ's (the same iterations; only what follows them is skipped)."""
    from dataclasses import replace

    from castimate.solver import ipopt, uncertainty
    from castimate.solver.ipopt import Solver

    session = Session(spec)
    model = session.fit()
    out = model.outcome
    # the same solve with and without the σ's: identical estimates, none of the σ's
    x0 = out.problem.lsq.layout.x0(out.solution.values)
    with_std = Solver(out.problem.lsq, spec.solver).solve(x0)
    without = Solver(out.problem.lsq, replace(spec.solver, covariance=False)).solve(x0)
    assert with_std.success and without.success
    np.testing.assert_array_equal(without.x, with_std.x)
    assert without.cost == with_std.cost and without.covariance is None and without.std == {}
    assert with_std.covariance is not None and with_std.std

    def forbidden(*a, **k):
        raise AssertionError("a cross-validation fold computed σ's")

    monkeypatch.setattr(uncertainty, "covariance", forbidden)
    monkeypatch.setattr(dynamic, "serial_covariance", forbidden)
    monkeypatch.setattr(ipopt.uncertainty, "covariance", forbidden)
    cv = session.cross_validate(model.effects, start=model)
    assert not cv.failed and np.isfinite(cv.rms) and len(cv.fold_n) == 5



def test_a_refit_without_sigmas_gets_the_same_sigmas_later(spec):
    """Diagnose fits a candidate for its estimates alone and adds the σ's (Fisher, then HAC) only to
    the model that ends the search: the same σ's and serial-correlation record as a fit that
    computed them, and the same estimates."""
    session = Session(spec)
    model = session.fit()
    full = session.fit((EFFECT,), start=model)
    bare = session.fit((EFFECT,), start=model, sigmas=False)
    assert bare.outcome.solution.covariance is None and bare.outcome.solution.std == {}
    assert bare.outcome.spec == full.outcome.spec  # the problem as declared, not the σ-less variant
    np.testing.assert_array_equal(bare.outcome.solution.x, full.outcome.solution.x)
    done = session.with_sigmas(bare)
    assert session.with_sigmas(done) is done and session.with_sigmas(full) is full
    a, b = done.outcome.solution, full.outcome.solution
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9, atol=0)
    assert a.std.keys() == b.std.keys()
    for k in b.std:
        np.testing.assert_allclose(a.std[k], b.std[k], rtol=1e-9, atol=0)
    assert done.outcome.serial["reported"] == full.outcome.serial["reported"] == "hac"
    assert done.outcome.serial["bandwidth_samples"] == full.outcome.serial["bandwidth_samples"]

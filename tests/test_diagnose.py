"""castimate diagnose: it finds each undeclared effect in simulated data and names it first, adds
nothing to data without one, agrees with a refit, and runs on the real MIMU4444 data and the CLI."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from castimate.cli import main
from castimate.kinds.diagnose import Session, candidates, score_test
from castimate.simulate.diagnose_trials import diagnose_trials
from castimate.problem.effects import BY_KEY
from castimate.spec import load_problem
from castimate.simulate.scenarios import simulate_scenario
from castimate.simulate.effects import REALISTIC_EFFECTS

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "problems" / "sim_effects_8x24.yaml"


@pytest.mark.parametrize("effect", list(REALISTIC_EFFECTS))
def test_finds_each_undeclared_effect_first(effect, tmp_path):
    (trial,) = diagnose_trials(SCENARIO, effect, [1], tmp_path)
    assert trial.added == (effect,), trial
    assert trial.first == effect


def test_adds_nothing_without_an_undeclared_effect(tmp_path):
    """Ten null sessions: at family-wise α = 1 % per round, two or more false alarms in ten has
    probability below 0.5 %."""
    trials = diagnose_trials(SCENARIO, None, range(100, 110), tmp_path)
    assert sum(t.false_alarm for t in trials) <= 1, [t.added for t in trials]


def _session(tmp_path, effect, scale, seed=5):
    raw = yaml.safe_load(SCENARIO.read_text())
    raw.update(seed=seed, effects={effect: REALISTIC_EFFECTS[effect] * scale})
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    return Session(load_problem(simulate_scenario(tmp_path / "s.yaml", tmp_path)["problem"]))



@pytest.mark.parametrize("effect", ["accelerometer.bias_drift", "gyroscope.g_sensitivity"])
def test_score_statistic_agrees_with_the_refit(effect, tmp_path):
    """For a small effect the Lagrange-multiplier statistic and the likelihood-ratio statistic
    χ²₀ − χ²₁ are asymptotically equal; at a weak effect they agree to a few percent."""
    session = _session(tmp_path, effect, scale=0.3)
    null = session.fit()
    test = score_test(session, null, BY_KEY[effect])
    alt = session.fit((effect,))
    lr = null.chi2 - alt.chi2
    assert test.lm > 3 * test.k  # the effect is visible, else the comparison says little
    assert abs(test.lm - lr) < 0.05 * lr, (test.lm, lr)


def test_candidates_follow_the_data(tmp_path):
    """Temperature effects only with a logged temperature, gyroscope effects only with gyroscopes."""
    session = _session(tmp_path, "accelerometer.bias_drift", 1.0)
    keys = {e.key for e in candidates(session, session.fit())}
    assert keys == set(REALISTIC_EFFECTS)
    sim = ROOT / "problems" / "sim_nilsson_14x20.yaml"
    files = simulate_scenario(sim, tmp_path / "nilsson")
    s2 = Session(load_problem(files["problem"]))
    keys2 = {e.key for e in candidates(s2, s2.fit())}
    assert keys2 == {"accelerometer.bias_drift", "accelerometer.scale_nonlinearity"}


def test_cli_on_real_mimu4444_session(shared_data, tmp_path):
    """The bundled real problem exp_2: the refined model predicts held-out poses better, the refined
    problem file solves, and the input file is untouched."""
    problem = ROOT / "problems" / "mimu4444_exp2_static.yaml"
    before = problem.read_bytes()
    out = tmp_path / "diag"
    assert main(["diagnose", str(problem), "-o", str(out), "-q"]) == 0
    assert problem.read_bytes() == before
    import json
    doc = json.loads((out / "diagnose.json").read_text())
    assert doc["added"], "the real session has drifting biases"
    assert doc["after"]["cross_validation"]["rms_whitened"] < doc["before"]["cross_validation"]["rms_whitened"]
    assert doc["after"]["chi2_per_dof"] < doc["before"]["chi2_per_dof"]
    for r in doc["rounds"]:
        for f in r["refits"]:
            if f["accepted"]:
                assert f["p"] < r["level"]
    refined = out / "mimu4444_exp2_static_refined.yaml"
    spec = load_problem(refined)
    assert set(spec.model.effects) == set(doc["added"])
    assert main(["solve", str(refined), "-o", str(tmp_path / "solved"), "-q"]) == 0
    results = json.loads((tmp_path / "solved" / "results.json").read_text())
    assert np.isclose(results["residuals"]["chi2"], doc["after"]["chi2"], rtol=1e-6)
    html = (out / "report.html").read_text()
    assert "Before and after" in html and "data:image/png;base64" in html


def test_dynamic_session_finds_a_chip_sample_age(age_session, age_diagnosis):
    """A small Carlsson-board session (4 IMUs × 300 samples) with sub-millisecond sample ages between
    the chips: diagnose adds the age, and the held-out error drops. The age's gyroscope part alone is
    a gyroscope delay (its accelerometer part tells them apart): the delay may be added first, then
    found zero within its σ. The session and its diagnosis are conftest's, shared with
    test_diagnose_warm."""
    spec, directory = age_session
    d = age_diagnosis
    assert "accelerometer.age" in d.added[:2] and set(d.added[:2]) <= {"accelerometer.age", "gyroscope.delay"}, d.added
    assert d.after.cv.rms < d.before.cv.rms
    truth = json.loads((directory / "truth.json").read_text())["effects"]
    sol = d.after.outcome.solution
    if "gyroscope.delay" in d.added:
        truth.update({f"{n}.gyroscope.delay": [0.0] for n in spec.array.names})
    for key, value in truth.items():
        assert abs(sol.values[key][0] - value[0]) < 4.5 * sol.std[key][0], key

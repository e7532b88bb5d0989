"""Reuse and refresh of an earlier calibration (model.intrinsics) in the static kind."""

import numpy as np
import pytest
import yaml

import castimate
from castimate.errors import InputError
from castimate.simulate.scenarios import simulate_scenario

SCENARIO = """
seed: 11
kind: static_array
triads: 3
poses: 14
gyroscope: true
"""


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("refresh")
    (d / "s.yaml").write_text(SCENARIO)
    problem = simulate_scenario(d / "s.yaml", d / "sim")["problem"]
    first = castimate.solve(problem)
    castimate.write(first, d / "first")
    return d, yaml.safe_load(open(problem)), first


def refreshed(session, bias_shift=0.0, **model):
    d, doc, first = session
    doc = {**doc, "model": {**doc.get("model", {}), "intrinsics": str(d / "first" / "results.json"), **model}}
    return castimate.load(doc, base_dir=d / "sim")


def test_refresh_fixes_the_intrinsics_and_estimates_the_biases(session):
    _, _, first = session
    spec = refreshed(session)
    out = castimate.solve(spec)
    lay = out.problem.lsq.layout
    free = {g.name.split(".", 1)[1] for g in lay.groups if g.free.any() and not g.nuisance}
    assert free == {"accelerometer.bias", "gyroscope.bias"}
    for name in out.config.names:
        for g in ("gain", "nonorthogonality"):
            key = f"{name}.accelerometer.{g}"
            np.testing.assert_allclose(out.solution.values[key], first.solution.values[key], rtol=0, atol=1e-12)
            assert np.all(out.solution.std[key] == 0)
        # same data: the refreshed biases are the full calibration's, within a fraction of their σ
        key = f"{name}.accelerometer.bias"
        assert np.all(np.abs(out.solution.values[key] - first.solution.values[key]) < 0.2 * first.solution.std[key])
        np.testing.assert_allclose(out.config.triads[out.config.names.index(name)].R_nominal,
                                   first.config.triads[first.config.names.index(name)].R_nominal)


def test_reuse_prior_frees_the_intrinsics_under_priors_from_their_sigmas(session):
    _, _, first = session
    spec = refreshed(session, reuse="prior")
    out = castimate.solve(spec)
    t = out.config.triads[1]
    gain = t.accelerometer["gain"]
    assert all(gain.free)
    np.testing.assert_allclose(gain.prior_mean, first.solution.values[f"{t.name}.accelerometer.gain"])
    np.testing.assert_allclose(gain.prior_std, first.solution.std[f"{t.name}.accelerometer.gain"])
    # prior from the same data: the estimate stays within its σ of the first one
    d = out.solution.values[f"{t.name}.accelerometer.gain"] - first.solution.values[f"{t.name}.accelerometer.gain"]
    assert np.all(np.abs(d) < first.solution.std[f"{t.name}.accelerometer.gain"])


def test_reuse_without_intrinsics_is_refused(session):
    d, doc, _ = session
    with pytest.raises(InputError, match=r"model\.reuse: applies to the intrinsics of model\.intrinsics, which is not given"):
        castimate.load({**doc, "model": {"reuse": "prior"}}, base_dir=d / "sim")
    with pytest.raises(InputError, match=r"model\.reuse: expected one of fixed, prior, found 'free'"):
        castimate.load({**doc, "model": {"intrinsics": str(d / "first" / "results.json"), "reuse": "free"}},
                       base_dir=d / "sim")

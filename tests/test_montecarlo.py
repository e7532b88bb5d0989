"""Honest σ's and efficiency on a simulated 14-triad, 20-pose array (issue acceptance, CI-sized),
through ``castimate montecarlo``'s engine in this process (client None): every run simulated, read,
built and solved by the static kind's pipeline (``problems/montecarlo_nilsson_14x20.yaml``, the
scenario of ``benchmarks/monte_carlo_static.py``, whose 1000 runs on a 2-worker cluster are quoted).

With R runs, the sample std of a standard normal has a standard error of about 1/sqrt(2(R-1)); the
bands below are derived from it, not guessed.
"""

from pathlib import Path

import numpy as np
import pytest

from castimate.scale.montecarlo import run_montecarlo
from castimate.scale.stats import pooled_score

RUNS = 60
SE = 1 / np.sqrt(2 * (RUNS - 1))  # 0.092
SCENARIO = Path(__file__).resolve().parents[1] / "problems" / "montecarlo_nilsson_14x20.yaml"


@pytest.fixture(scope="module")
def study():
    return run_montecarlo(None, SCENARIO, RUNS, lambda m: None)


def test_every_run_converges(study):
    mc = study.score
    assert study.failures() == {} and mc.z.shape == (RUNS, 14 * 12 - 3)
    assert study.bound_document()["name"] == "problem"


def test_reported_sigma_is_honest(study):
    mc = study.score
    # per parameter within 4.5 standard errors (165 parameters)
    assert np.all(np.abs(mc.z_std - 1) < 4.5 * SE), (mc.z_std.min(), mc.z_std.max())
    # and unbiased: |mean z| below 4.5 standard errors of a mean
    assert np.abs(mc.z.mean(axis=0)).max() < 4.5 / np.sqrt(RUNS)
    # pooled over the parameters, with the standard error from the bound's correlation
    p = pooled_score(mc, correlation=study.bound.correlation)
    assert abs(p["z_reported_std"] - 1) < 4 * p["z_std_se"], p
    assert p["z_std_se"] < 0.02


def test_rmse_reaches_the_cramer_rao_bound(study):
    mc = study.score
    ratio = mc.rmse_over_crb
    assert np.all(np.abs(ratio - 1) < 4.5 * SE), (ratio.min(), ratio.max())
    p = pooled_score(mc, correlation=study.bound.correlation)
    assert abs(p["rmse_over_crb"] - 1) < 4 * p["rmse_over_crb_se"], p

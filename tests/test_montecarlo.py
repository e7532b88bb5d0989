"""Honest σ's and efficiency on a simulated 14-triad, 20-pose array (issue acceptance, CI-sized).

With R runs, the sample std of a standard normal has a standard error of about 1/sqrt(2(R-1));
the bands below are derived from it (about 4 standard errors), not guessed.
"""

import numpy as np
import pytest

from castimate.simulate.montecarlo import monte_carlo_static

RUNS = 400
SE = 1 / np.sqrt(2 * (RUNS - 1))  # 0.035


@pytest.fixture(scope="module")
def mc():
    return monte_carlo_static(RUNS, n_triads=14, n_poses=20, seed=11)


def test_every_run_converges(mc):
    assert mc.failures == 0 and mc.z.shape == (RUNS, 14 * 12 - 3)


def test_reported_sigma_is_honest_per_parameter(mc):
    # issue acceptance: std(error / σ) in [0.85, 1.15] for every parameter (0.15 = 4.2 SE)
    assert mc.z_std.min() > 0.85 and mc.z_std.max() < 1.15, (mc.z_std.min(), mc.z_std.max())
    # and unbiased: |mean z| below 4 standard errors of a mean
    assert np.abs(mc.z.mean(axis=0)).max() < 4.5 / np.sqrt(RUNS)


def test_rmse_reaches_the_cramer_rao_bound(mc):
    ratio = mc.rmse_over_crb
    # pooled over 165 parameters the ratio is resolved to ~0.3 %: within 10 % of the CRB
    assert 0.9 < np.sqrt(np.mean(ratio ** 2)) < 1.1
    # per parameter within 4 standard errors of the RMSE estimate
    assert np.all(np.abs(ratio - 1) < 4 * SE), (ratio.min(), ratio.max())

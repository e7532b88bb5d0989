"""The dynamic blocks' data rows (DynamicProblem.block_data), instance by instance.

block_data fills its result a slab of samples at a time (castimate.problem.dynamic.SLAB); here every
row is checked against the documented layout d = [y, σ, vec(Rbar), τ, τ², ΔT, ΔT², beat,
1/(t_n+1 - t_n-1), 4/(t_n+1 - t_n-1)² (0 at the ends)], with masked axes (y = 0, σ = MASKED_SIGMA),
masked samples (y = 0, σ = inf), a per-sample σ, a temperature, a chip clock and a record length
that leaves a partial last slab.
"""

from dataclasses import replace

import numpy as np
import pytest

from castimate.problem import dynamic
from castimate.problem.dynamic import MASKED_SIGMA, DynamicConfig, DynamicData, build_dynamic
from castimate.problem.triads import GroupSetting, N_SAMPLE_REGRESSORS, Regressors, TriadConfig
from castimate.simulate.dynamic import rotation_vector_to_matrix

FIXED3 = GroupSetting(free=(False,) * 3)


def case(n: int):
    rng = np.random.default_rng(11)
    names = ["a", "b", "c"]
    R = {nm: rotation_vector_to_matrix(rng.standard_normal(3)) for nm in names}
    t = np.cumsum(rng.uniform(0.009, 0.011, n))  # a non-uniform grid: inv_span differs per sample
    acc = {nm: rng.standard_normal((n, 3)) for nm in names}
    gyro = {nm: rng.standard_normal((n, 3)) for nm in names[:2]}
    axes_b = rng.uniform(size=(n, 3)) > 0.2  # per axis, some samples with no axis at all
    axes_b[:5] = False
    acc_valid = {"b": axes_b, "c": np.arange(n) % 9 != 4}  # per axis; per sample
    gyro_valid = {"a": rng.uniform(size=(n, 3)) > 0.1}
    sig_c = rng.uniform(0.01, 0.05, (n, 3))
    data = DynamicData(t, acc, {nm: np.full(3, 0.02 + 0.01 * i) for i, nm in enumerate(names)}, gyro,
                       {nm: np.full(3, 1e-3) for nm in names[:2]}, acc_valid, gyro_valid,
                       temp={"a": 300 + rng.standard_normal(n)}, sigma_sample={"acc": {"c": sig_c}})
    triads = tuple(TriadConfig(nm, R[nm], {"gain": FIXED3, "bias": FIXED3, "nonorthogonality": FIXED3,
                                          "misalignment": FIXED3},
                               {"gain": FIXED3, "bias": FIXED3, "misalignment": FIXED3} if nm in gyro else None,
                               rng.standard_normal(3) * 0.01) for nm in names)
    reg = Regressors.from_times(t, data.temp).with_beats({"b": (0.37, 0.1)})
    config = DynamicConfig(triads, "a", "small_angle", regressors=reg)
    return config, data, R, reg


def expected_rows(kind, names, data, R, reg):
    """Row (n, k) of a sensor block, instance by instance from the documented layout."""
    N = data.n
    rows = np.zeros((N, len(names), 17 + N_SAMPLE_REGRESSORS))
    y = data.acc if kind == "acc" else data.gyro
    for k, nm in enumerate(names):
        axes = data.axis_valid(kind, nm)
        sigma = data.sigma(kind, nm)
        moments = reg.sample_moments(data.t, data.temp.get(nm), nm)
        for n in range(N):
            prev, nxt = max(n - 1, 0), min(n + 1, N - 1)
            span = data.t[nxt] - data.t[prev]
            row = rows[n, k]
            ok = axes[n].any()
            row[0:3] = np.where(axes[n], y[nm][n], 0.0)
            row[3:6] = np.where(axes[n], sigma[n], MASKED_SIGMA if ok else np.inf)
            row[6:15] = R[nm].ravel(order="F")
            row[15: 15 + N_SAMPLE_REGRESSORS] = moments[n]
            row[15 + N_SAMPLE_REGRESSORS] = 1.0 / span
            row[16 + N_SAMPLE_REGRESSORS] = 4.0 * ((1.0 / span) * (1.0 / span)) if nxt - prev == 2 else 0.0
    return rows.reshape(-1, rows.shape[2])


@pytest.mark.parametrize("slab", [None, 7])
def test_sensor_block_rows_follow_the_documented_layout(monkeypatch, slab):
    if slab is not None:  # many slabs, the last one partial
        monkeypatch.setattr(dynamic, "SLAB", slab)
    config, data, R, reg = case(2 * dynamic.SLAB + 37)
    problem = build_dynamic(config, data)
    acc, gyro = problem.block_data(data)[:2]
    np.testing.assert_array_equal(acc, expected_rows("acc", config.names, data, R, reg))
    np.testing.assert_array_equal(gyro, expected_rows("gyro", ["a", "b"], data, R, reg))
    # the blocks of the built problem hold the same rows
    np.testing.assert_array_equal(problem.lsq.blocks[0].data, acc)


def test_block_data_of_a_shorter_record():
    """A record shorter than one slab (a cross-validation fold, a window)."""
    config, data, R, reg = case(40)
    config = replace(config, regressors=reg)
    problem = build_dynamic(config, data)
    np.testing.assert_array_equal(problem.block_data(data)[0], expected_rows("acc", config.names, data, R, reg))

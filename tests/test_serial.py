"""Honest σ's under serially correlated residuals (castimate.solver.serial, issue 11 item 5): the
Bartlett sum, Andrews' bandwidth and the lag-1 autocorrelation by hand; the HAC variance of a line
fit with an eliminated intercept in closed form; the eliminated computation against the dense
full-space sandwich H⁻¹ S H⁻¹ on small dynamic problems (both elimination paths, constraints, a
prior, masked samples, banded motion); Monte Carlo truth with AR(1) residuals (HAC σ's honest, Fisher
σ's not) and white ones (no inflation); the problem file's key and results.json."""

import json

import casadi as ca
import numpy as np
import pytest
import yaml

from castimate.problem.dynamic import DynamicConfig, DynamicData, MotionSigmas, build_dynamic
from castimate.problem.graph import FactorBlock, LeastSquaresProblem
from castimate.problem.parameters import Group, Layout
from castimate.solver import Solver, SolverOptions
from castimate.solver.serial import andrews_bandwidth, bartlett, lag1, serial_covariance
from castimate.problem.triads import GroupSetting, TriadConfig
from castimate.simulate.dynamic import dynamic_measurements, smooth_random_motion
from castimate.spec import load_problem

from test_assembly import FIXED3, dynamic_case
from test_elimination import dynamic_sample_ages
from test_validation import expect_error


def test_bartlett_by_hand():
    # g = 1, 2, 3 and L = 2: lag 0 gives 1 + 4 + 9 = 14, lag ±1 (weight 1/2) gives 2 · ½ · (1·2 + 2·3) = 8
    assert bartlett(np.array([[1.0], [2.0], [3.0]]), 2)[0, 0] == pytest.approx(22.0)
    assert bartlett(np.array([[1.0], [2.0], [3.0]]), 1)[0, 0] == pytest.approx(14.0)
    # L = 3: + 2 · ⅓ · (1·3) = 2 more and lag 1 at weight ⅔: 14 + 2·⅔·8 + 2
    assert bartlett(np.array([[1.0], [2.0], [3.0]]), 3)[0, 0] == pytest.approx(14 + 4 / 3 * 8 + 2)
    # vectors: the double sum over sample pairs, weights (1 - |t - s|/L)₊
    G = np.random.default_rng(0).standard_normal((30, 4))
    L = 5
    ref = sum(max(0.0, 1 - abs(t - s) / L) * np.outer(G[t], G[s]) for t in range(30) for s in range(30))
    assert np.allclose(bartlett(G, L), ref, rtol=1e-12, atol=1e-12)


def test_andrews_bandwidth_by_hand():
    # one channel, ρ = 0.5: α(1) = 4·0.25 / (0.5² · 1.5²) = 16/9; S_T = 1.1447 (16/9 · 1000)^(1/3)
    assert andrews_bandwidth([0.5], [2.0], 1000) == pytest.approx(1.1447 * (16 / 9 * 1000) ** (1 / 3))
    # white residuals: the lag-0 term alone
    assert andrews_bandwidth([0.0, 0.0], [1.0, 1.0], 1000) == 0.0
    # two equal channels give the one channel's bandwidth
    assert andrews_bandwidth([0.3, 0.3], [1.0, 1.0], 500) == pytest.approx(andrews_bandwidth([0.3], [1.0], 500))


def test_lag1_by_hand():
    # e = 1, 2, NaN, 3, 1: the one pair (1, 2) and the pair (3, 1) -> products 2 + 3, squares ½(1 + 9 + 4 + 1)
    num, den, var = lag1(np.array([[1.0], [2.0], [np.nan], [3.0], [1.0]]))
    assert num[0] == pytest.approx(5.0) and den[0] == pytest.approx(7.5) and var[0] == pytest.approx(15 / 4)


def line_problem(x, y, sigma=1.0):
    """y = α + β x + e with whitened residuals (y - α - β x)/σ, α a nuisance variable, one
    instance per sample of a time series."""
    z, d = ca.SX.sym("z", 2), ca.SX.sym("d", 2)
    f = ca.Function("line", [z, d], [(d[1] - z[0] - z[1] * d[0]) / sigma])
    groups = [Group.make("alpha", ("a",), [0.0], nuisance=True), Group.make("beta", ("b",), [0.0])]
    N = len(x)
    block = FactorBlock("line", f, [("alpha", None), ("beta", None)], np.column_stack([x, y]), series=np.arange(N))
    return LeastSquaresProblem(Layout(groups), [block])


def ar1(rng, n, rho, size=()):
    e = rng.standard_normal((n, *size))
    for t in range(1, n):
        e[t] = rho * e[t - 1] + np.sqrt(1 - rho ** 2) * e[t]
    return e


def test_line_fit_hac_variance_in_closed_form():
    """Frisch–Waugh: with the intercept eliminated, x̃ = x - mean(x), β̂'s HAC variance is
    Σ_{t,s} (1 - |t - s|/L)₊ x̃_t e_t x̃_s e_s / (Σ x̃²)² and its Fisher variance 1/Σ x̃²."""
    rng = np.random.default_rng(2)
    N, sigma = 200, 0.5
    x = np.cumsum(rng.standard_normal(N)) * 0.1
    y = 1.0 + 2.0 * x + sigma * ar1(rng, N, 0.6)
    solver = Solver(line_problem(x, y, sigma))
    sol = solver.solve()
    assert sol.success
    xt = x - x.mean()
    beta = xt @ (y - y.mean()) / (xt @ xt)
    assert sol.values["beta"][0] == pytest.approx(beta, rel=1e-8)
    e = (y - y.mean() - beta * xt) / sigma
    L = 6
    w = np.maximum(0.0, 1 - np.abs(np.subtract.outer(np.arange(N), np.arange(N))) / L)
    s = xt * e / sigma
    hac = s @ w @ s / (xt @ xt / sigma ** 2) ** 2
    hc = serial_covariance(solver, sol.x, lags=L, floor=False)
    assert hc.fisher[0, 0] == pytest.approx(sigma ** 2 / (xt @ xt), rel=1e-8)
    assert hc.covariance[0, 0] == pytest.approx(hac, rel=1e-8)
    assert hc.lags == L and hc.samples == N
    assert hc.rho[0] == pytest.approx((e[1:] @ e[:-1]) / (0.5 * (e[1:] @ e[1:] + e[:-1] @ e[:-1])), rel=1e-9)


def test_line_fit_monte_carlo_hac_honest_fisher_not():
    """AR(1) errors (ρ 0.6) on an AR(1) regressor (0.8): β̂'s Fisher σ is too small by about
    √((1 + 0.48)/(1 - 0.48)) = 1.69; the HAC σ with Andrews' bandwidth is honest. 150 draws:
    std(error/σ) has a sampling σ of 1/√300 = 0.06; band ±0.2 (the Bartlett estimate's own
    downward bias at N = 400 is a few %)."""
    rng = np.random.default_rng(7)
    N, R = 400, 150
    x = ar1(rng, N, 0.8)
    solver = Solver(line_problem(x, np.zeros(N)))
    prob = solver.problem
    z_hac, z_fisher = [], []
    for _ in range(R):
        y = 1.0 + 2.0 * x + ar1(rng, N, 0.6)
        d = prob.pack([np.column_stack([x, y])])
        sol = solver.solve(data=d)
        hc = serial_covariance(solver, sol.x, data=d)
        err = sol.values["beta"][0] - 2.0
        z_hac.append(err / np.sqrt(hc.covariance[0, 0]))
        z_fisher.append(err / np.sqrt(hc.fisher[0, 0]))
    assert abs(np.std(z_hac) - 1) < 0.2
    assert np.std(z_fisher) > 1.4


def brute_force(solver, x, L):
    """θ block of the full-space sandwich K⁻¹ S K⁻¹ (K the KKT matrix of J^T J and the constraints),
    S the Bartlett sum of the per-sample full-space scores Σ J_nᵀ e_n plus the Fisher information
    of the rows outside any series, dense; physical units."""
    J, G = (m.toarray() for m in solver.jacobians(x))
    e = solver.residuals(x)
    sample = np.concatenate([np.repeat(b.block.series, b.f.m) if b.block.series is not None
                             else np.full(b.block.n * b.f.m, -1) for b in solver.blocks]
                            + [np.full(len(solver.prior[0]), -1)])[solver.keep]
    n, c = J.shape[1], G.shape[0]
    K = np.block([[J.T @ J, G.T], [G, np.zeros((c, c))]])
    P = np.linalg.inv(K)[:n, :n]
    T = sample.max() + 1
    scores = np.zeros((T, n))
    np.add.at(scores, sample[sample >= 0], J[sample >= 0] * e[sample >= 0, None])
    Ji = J[sample < 0]
    S = bartlett(scores, L) + Ji.T @ Ji
    th = solver.theta
    s = solver.problem.layout.x_scale[th]
    return (P @ S @ P)[np.ix_(th, th)] * np.outer(s, s), P[np.ix_(th, th)] * np.outer(s, s)


CASES = {"process_model": lambda: dynamic_case(40, True), "no_process_model": lambda: dynamic_case(40, False),
         "banded_sample_ages": dynamic_sample_ages}


@pytest.mark.parametrize("case", list(CASES))
def test_eliminated_hac_equals_the_dense_full_space_sandwich(case):
    """The motion (and every other nuisance variable) eliminated sample by sample gives exactly
    the θ block of the full-space sandwich: at the optimum and at a point off it (an identity,
    not a property of the optimum), by both elimination paths."""
    prob = CASES[case]()
    ref = Solver(prob.lsq, SolverOptions(elimination="none"))
    new = Solver(prob.lsq)
    assert ref.projection is None and new.projection is not None
    sol = new.solve()
    assert sol.success
    off = sol.x + 1e-3 * np.random.default_rng(1).standard_normal(sol.x.size) * (np.abs(sol.x) + 1e-3)
    for x in (sol.x, off):
        for L in (1, 4):
            full, fisher = brute_force(ref, x, L)
            for solver in (ref, new):
                hc = serial_covariance(solver, x, lags=L, floor=False)
                scale = np.sqrt(np.outer(np.diag(full), np.diag(full)))
                assert np.abs(hc.covariance - full).max() / scale.max() < 1e-7
                assert np.abs(np.sqrt(np.diag(hc.covariance) / np.diag(full)) - 1).max() < 1e-6
                assert np.abs(np.sqrt(np.diag(hc.fisher) / np.diag(fisher)) - 1).max() < 1e-6


def test_channel_pooling_is_each_channels_own_sandwich():
    """pooling="channel" (the comparison of benchmarks/serial_correlation.py): the sum over channels
    (a triad's sensor axis) of each channel's own Bartlett sum, dense, with the motion eliminated."""
    prob = dynamic_case(40, False)
    solver = Solver(prob.lsq)
    x = solver.solve().x
    ref = Solver(prob.lsq, SolverOptions(elimination="none"))
    J, G = (m.toarray() for m in ref.jacobians(x))
    e = ref.residuals(x)
    n, c = J.shape[1], G.shape[0]
    P = np.linalg.inv(np.block([[J.T @ J, G.T], [G, np.zeros((c, c))]]))[:n, :n]
    sample, channel = [], []
    for k, b in enumerate(ref.blocks):
        per = b.block.n // 40  # instances per sample, sample-major
        inst = np.arange(b.block.n)
        sample.append(np.repeat(b.block.series, b.f.m))
        channel.append(1000 * k + np.repeat(inst % per, b.f.m) * b.f.m + np.tile(np.arange(b.f.m), b.block.n))
    sample, channel = np.concatenate(sample), np.concatenate(channel)
    valid = ref.keep[: len(sample)]
    sample, channel = sample[valid], channel[valid]
    Jd, ed = J[: len(sample)], e[: len(sample)]
    S = sum(bartlett(_scores(Jd, ed, sample, channel == ch, n), 3) for ch in np.unique(channel))
    Jp = J[len(sample):]
    S = S + Jp.T @ Jp
    th = solver.theta
    sc = prob.lsq.layout.x_scale[th]
    full = (P @ S @ P)[np.ix_(th, th)] * np.outer(sc, sc)
    hc = serial_covariance(solver, x, lags=3, pooling="channel", floor=False)
    assert np.abs(np.sqrt(np.diag(hc.covariance) / np.diag(full)) - 1).max() < 1e-6
    with pytest.raises(ValueError, match="pooling 'channel': expected 'sample', or 'channel' with lags"):
        serial_covariance(solver, x, pooling="channel")


def _scores(J, e, sample, rows, n):
    G = np.zeros((sample.max() + 1, n))
    np.add.at(G, sample[rows], J[rows] * e[rows, None])
    return G


def ar1_board(n=150):
    """4 triads (3 free positions, gyroscopes on all, everything else fixed), no process model, one
    smooth motion: the problem with noise-free readings, and a function giving the data vector of
    the readings plus noise drawn by ``noise(rng)`` (n, 3) per triad and sensor."""
    names = ["a", "b", "c", "d"]
    pos = np.array([[0, 0, 0], [0.03, 0, 0], [0, 0.04, 0.01], [0.02, -0.03, 0]], float)
    motion = smooth_random_motion(n, 100.0, 8.0, 40.0, np.random.default_rng(3))
    Rs = np.stack([np.eye(3)] * 4)
    gyro = {"T_g": Rs, "b_g": np.zeros((4, 3)), "sigma": 0.0, "saturation": None}
    acc, gy, _ = dynamic_measurements(motion, pos, Rs, np.zeros((4, 3)), np.random.default_rng(0), 0.0, gyro=gyro,
                                      names=names)
    fixed = {"gain": FIXED3, "bias": FIXED3, "nonorthogonality": FIXED3,
             "misalignment": GroupSetting(free=(False,) * 4, initial=(1.0, 0.0, 0.0, 0.0))}
    triads = tuple(TriadConfig(nm, np.eye(3), fixed, {"gain": FIXED3, "bias": FIXED3, "misalignment": FIXED3},
                               pos[i] + 1e-3 * (i > 0)) for i, nm in enumerate(names))
    sa, sg = 0.02, 1e-3
    cfg = DynamicConfig(triads, "a", "rotation", MotionSigmas(), process_model=False)

    def data(rng, noise):
        return DynamicData(motion.t, {k: v + sa * noise(rng) for k, v in acc.items()}, {k: np.full(3, sa) for k in names},
                           {k: v + sg * noise(rng) for k, v in gy.items()}, {k: np.full(3, sg) for k in names}, {}, {})

    prob = build_dynamic(cfg, data(np.random.default_rng(1), lambda rng: rng.standard_normal((n, 3))))
    return prob, pos, data


def board_monte_carlo(noise, runs, seed, n=150):
    """error/σ of the free positions with the HAC and with the Fisher σ's, and their ratio, over runs."""
    prob, truth, data = ar1_board(n)
    solver = Solver(prob.lsq)
    lay = prob.lsq.layout
    x0 = solver.solve().x
    idx = np.concatenate([lay.x_indices(f"{n}.position") for n in "bcd"])
    sel = np.searchsorted(solver.theta, idx)
    assert (solver.theta[sel] == idx).all()
    rng = np.random.default_rng(seed)
    zh, zf, ratio = [], [], []
    for _ in range(runs):
        dv = prob.data_vector(data(rng, noise))
        sol = solver.solve(x0, data=dv)
        assert sol.success
        hc = serial_covariance(solver, sol.x, data=dv)
        err = sol.x[idx] * lay.x_scale[idx] - truth[1:].ravel()
        zh.append(err / np.sqrt(np.diag(hc.covariance)[sel]))
        zf.append(err / np.sqrt(np.diag(hc.fisher)[sel]))
        ratio.append(hc.inflation[sel])
    return np.array(zh), np.array(zf), np.array(ratio)


def test_monte_carlo_ar1_residuals_hac_honest_fisher_not():
    """AR(1) noise of lag-1 correlation 0.5 (as on the MIMU4444 sessions) on every reading, 300
    samples: the Fisher σ's of the positions are too small (about √(1.5/0.5) = 1.73 for a slowly
    varying regressor); std(error/σ) with the HAC σ's is within 1 ± 3/√(2 · runs) (each run's 9
    components are correlated: the band counts runs only) and the Fisher σ's fall outside it.
    Measured: 1.15-1.18 (HAC; the Bartlett estimate's bias at 300 samples) and 1.67-1.68 (Fisher)."""
    runs = 40
    zh, zf, _ = board_monte_carlo(lambda rng: ar1(rng, 300, 0.5, (3,)), runs, 11, n=300)
    band = 3 / np.sqrt(2 * runs)
    assert abs(np.std(zh) - 1) < band
    assert np.std(zf) > 1 + band


def test_monte_carlo_white_residuals_no_inflation():
    """White noise: the HAC σ's stay the Fisher ones (RMS ratio within 10 %) and both are honest."""
    runs = 20
    zh, zf, ratio = board_monte_carlo(lambda rng: rng.standard_normal((150, 3)), runs, 12)
    assert abs(np.sqrt(np.mean(ratio ** 2)) - 1) < 0.1
    band = 3 / np.sqrt(2 * runs)
    assert abs(np.std(zh) - 1) < band + 0.1 and abs(np.std(zf) - 1) < band


def small_session(tmp_path, extra=None):
    scenario = {"kind": "dynamic_array", "seed": 3, "geometry": "carlsson", "imus": 4, "samples": 300, "rate": 62.5,
                "max_omega": 1000, "max_omega_dot": 20000, "euler_consistent": False,
                "motion": {"process_model": False}, "noise": {"pink": {"accelerometer": 0.04, "gyroscope": 0.06}}}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(scenario))
    from castimate.simulate.scenarios import simulate_scenario
    simulate_scenario(tmp_path / "s.yaml", tmp_path)
    doc = yaml.safe_load((tmp_path / "problem.yaml").read_text())
    doc.update(extra or {})
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(doc))
    return tmp_path / "p.yaml"


@pytest.mark.parametrize("value, found", [("sometimes", "expected one of auto, none, found 'sometimes'"),
                                          (True, "expected one of auto, none, found True")])
def test_residual_correlation_key_errors(tmp_path, value, found):
    p = small_session(tmp_path, {"uncertainty": {"residual_correlation": value}})
    expect_error(lambda: load_problem(p), p, "uncertainty.residual_correlation", found)


def test_uncertainty_unknown_key(tmp_path):
    p = small_session(tmp_path, {"uncertainty": {"hac": "auto"}})
    expect_error(lambda: load_problem(p), p, "uncertainty.hac", "unknown key")


def test_results_record_the_reported_sigmas(tmp_path):
    """Pink noise as large as the white: the default reports the HAC σ's (larger than the Fisher
    ones, which results.json keeps), the lag-1 autocorrelation per triad and sensor is positive,
    and the report page says which σ's it shows; ``none`` reports the Fisher σ's."""
    from castimate.api import load, solve
    from castimate.output.results import dynamic_results
    from castimate.report.dynamic import sigma_source

    p = small_session(tmp_path)
    assert load_problem(p).uncertainty.residual_correlation == "auto"
    out = solve(load(p))
    doc = json.loads(json.dumps(dynamic_results(out), default=lambda o: np.asarray(o).tolist()))
    u = doc["uncertainty"]
    assert u["reported"] == "hac" and u["lags"] >= 2 and u["bandwidth_samples"] > 1
    assert set(u["lag1_autocorrelation"]) == {"accelerometer", "gyroscope"}
    assert all(0.1 < r < 0.9 for c in u["lag1_autocorrelation"].values() for r in c.values())
    t = doc["triads"]["imu32"]
    assert np.all(np.asarray(t["position_std"]) > np.asarray(t["position_std_fisher"]))
    assert u["inflation"]["position_rms"] > 1.2
    assert "HAC" in sigma_source(doc) and "Fisher" in sigma_source({"uncertainty": {"reported": "fisher"}})
    (tmp_path / "none").mkdir()
    q = small_session(tmp_path / "none", {"uncertainty": {"residual_correlation": "none"}})
    plain = solve(load(q))
    doc2 = json.loads(json.dumps(dynamic_results(plain), default=lambda o: np.asarray(o).tolist()))
    assert doc2["uncertainty"] == {"reported": "fisher", "residual_correlation": "none"}
    assert "position_std_fisher" not in doc2["triads"]["imu32"]
    assert np.allclose(doc2["triads"]["imu32"]["position_std"], t["position_std_fisher"], rtol=1e-6)


def test_at_least_raises_each_variance_to_the_floor_keeping_correlations():
    """Hand-computed: against the floor F = diag(4, 1), a covariance 2F stays, F/2 becomes F, and
    diag(8, 0.5) becomes diag(8, 1); a correlated case keeps its correlation coefficient, and a
    parameter with zero variance takes the floor's row and column."""
    from castimate.solver.serial import at_least

    F = np.diag([4.0, 1.0])
    assert np.allclose(at_least(2 * F, F), 2 * F)
    assert np.allclose(at_least(F / 2, F), F)
    assert np.allclose(at_least(np.diag([8.0, 0.5]), F), np.diag([8.0, 1.0]))
    cov = np.array([[9.0, 0.6], [0.6, 0.25]])  # σ 3 and 0.5, correlation 0.4
    assert np.allclose(at_least(cov, F), [[9.0, 1.2], [1.2, 1.0]])  # σ 3 and 1, correlation 0.4
    assert np.allclose(at_least(np.diag([5.0, 0.0]), F), np.diag([5.0, 1.0]))

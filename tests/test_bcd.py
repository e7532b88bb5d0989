"""Carlsson, Skog, Jaldén 2017, Algorithm 1 (castimate.bcd): motion ML, eq. 9, and the full BCD.

The simulation is built here with numpy alone: K = 8 accelerometer triads within ±1 cm (reference at
the origin), one gyroscope triad, N = 400 samples of a smooth 3-D rotation (ω a sum of random
sinusoids per axis, |ω| up to ~30 rad/s, ω̇ its analytic derivative) and an arbitrary smooth
specific force s (a free per-sample unknown of the estimator, so it need not be integrable).
"""

from __future__ import annotations

import numpy as np
import pytest

from castimate.solver import bcd

SIGMA_A = 0.04  # m/s²
SIGMA_G = 0.001  # rad/s
K, N, DT = 8, 400, 0.005
NSIG = 4.5


def _cross_mat(v):
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def _model(positions, s, omega, omega_dot):
    """y_k = s + ω×(ω×r_k) + ω̇×r_k, written with np.cross (independent of the module)."""
    r = positions[:, None, :]
    return s[None] + np.cross(omega[None], np.cross(omega[None], r)) + np.cross(omega_dot[None], r)


def _simulate(seed=0):
    rng = np.random.default_rng(seed)
    r = rng.uniform(-0.01, 0.01, (K, 3))
    r[0] = 0.0
    t = np.arange(N) * DT
    amp = rng.uniform(0.5, 1.0, (3, 3))
    amp *= 55.0 / (np.sqrt(3) * amp.sum(axis=1, keepdims=True))
    freq = rng.uniform(0.3, 2.0, (3, 3))
    phase = rng.uniform(0, 2 * np.pi, (3, 3))
    arg = 2 * np.pi * freq[:, :, None] * t + phase[:, :, None]
    omega = (amp[:, :, None] * np.sin(arg)).sum(axis=1).T
    omega_dot = (amp[:, :, None] * 2 * np.pi * freq[:, :, None] * np.cos(arg)).sum(axis=1).T
    s = 9.81 * np.stack([np.sin(0.7 * t), np.cos(0.5 * t), np.sin(0.3 * t + 1)], 1) + 3 * np.sin(5 * t)[:, None]
    acc0 = _model(r, s, omega, omega_dot)
    gyro0 = omega[None].copy()
    acc = acc0 + SIGMA_A * rng.normal(size=acc0.shape)
    gyro = gyro0 + SIGMA_G * rng.normal(size=gyro0.shape)
    r0 = r + rng.normal(scale=1e-3, size=r.shape)  # 1 mm initial errors
    r0[0] = r[0]
    return dict(r=r, s=s, omega=omega, omega_dot=omega_dot, acc0=acc0, gyro0=gyro0, acc=acc, gyro=gyro, r0=r0)


@pytest.fixture(scope="module")
def sim():
    return _simulate()


def _gram(omega, omega_dot):
    a = _cross_mat(omega) @ _cross_mat(omega) + _cross_mat(omega_dot)
    return np.einsum("nji,njk->ik", a, a)


def _jacobians(r, omega, omega_dot, reference=0, mask=None):
    """Per sample, the whitened Jacobians of (accelerometers, gyroscope) w.r.t. x_n = (s, ω, ω̇)
    and w.r.t. the non-reference positions θ: (N, 3K+3, 9), (N, 3K+3, 3(K−1)), and θ's triads."""
    free = [k for k in range(K) if k != reference]
    n = omega.shape[0]
    rows, p = 3 * K + 3, 3 * len(free)
    a = _cross_mat(omega) @ _cross_mat(omega) + _cross_mat(omega_dot)
    jx = np.zeros((n, rows, 9))
    jt = np.zeros((n, rows, p))
    eye = np.eye(3)
    for k in range(K):
        rk = r[k]
        # ∂(ω×(ω×r))/∂ω = (ω·r) I + ω rᵀ − 2 r ωᵀ
        d = (omega @ rk)[:, None, None] * eye + omega[:, :, None] * rk[None, None, :] - 2 * rk[None, :, None] * omega[:, None, :]
        jx[:, 3 * k : 3 * k + 3, 0:3] = eye / SIGMA_A
        jx[:, 3 * k : 3 * k + 3, 3:6] = d / SIGMA_A
        jx[:, 3 * k : 3 * k + 3, 6:9] = -_cross_mat(rk) / SIGMA_A
        if k != reference:
            j = free.index(k)
            jt[:, 3 * k : 3 * k + 3, 3 * j : 3 * j + 3] = a / SIGMA_A
    valid = np.ones(n, bool) if mask is None else mask[0]
    jx[valid, 3 * K :, 3:6] = eye / SIGMA_G
    return jx, jt, free


def _marginal_crb(r, omega, omega_dot, reference=0, mask=None):
    """Cramér–Rao bound (standard deviations, (K−1, 3)) of the non-reference positions with the
    per-sample motion marginalised.

    The Fisher information of θ is Σ_n (J_θᵀJ_θ − J_θᵀJ_x (J_xᵀJ_x)⁻¹ J_xᵀJ_θ). Without the
    marginalisation (the motion taken as known) it is Σ_n A_nᵀA_n / σ_a² per triad (eq. 9's
    covariance), which underestimates the error of the joint estimate by a factor of about 1.5 here.
    """
    jx, jt, free = _jacobians(r, omega, omega_dot, reference, mask)
    fxx = np.einsum("nri,nrj->nij", jx, jx)
    fxt = np.einsum("nri,nrj->nij", jx, jt)
    ftt = np.einsum("nri,nrj->ij", jt, jt)
    info = ftt - np.einsum("nji,njk->ik", fxt, np.linalg.solve(fxx, fxt))
    cov = np.linalg.inv(info)
    return np.sqrt(np.diag(cov)).reshape(len(free), 3), free


def _omega_sd(r, omega, omega_dot, mask=None):
    """Per-sample Cramér–Rao standard deviation of ω given the positions, (N, 3)."""
    jx, _, _ = _jacobians(r, omega, omega_dot, 0, mask)
    cov = np.linalg.inv(np.einsum("nri,nrj->nij", jx, jx))
    return np.sqrt(np.diagonal(cov, axis1=1, axis2=2)[:, 3:6])


# --------------------------------------------------------------------------------------------
# step (a)


def test_motion_ml_hand_computed_sample():
    """One sample worked by hand: r = 0, a·e_x, a·e_y, a·e_z with a = 1 cm, ω = (0,0,3), ω̇ = (0,0,4).

    ω×(ω×r) = (ω·r)ω − |ω|² r and ω̇×r give
      r1 = 0        : y = s
      r2 = a e_x    : −9a e_x + 4a e_y          -> s + (−0.09, 0.04, 0)
      r3 = a e_y    : −9a e_y − 4a e_x          -> s + (−0.04, −0.09, 0)
      r4 = a e_z    : 9a e_z − 9a e_z + 0 = 0   -> s
    with s = (0, 0, 9.81), and the gyroscope reads (0, 0, 3).
    """
    a = 0.01
    positions = np.array([[0, 0, 0], [a, 0, 0], [0, a, 0], [0, 0, a]], float)
    acc = np.array(
        [[[0, 0, 9.81]], [[-0.09, 0.04, 9.81]], [[-0.04, -0.09, 9.81]], [[0, 0, 9.81]]], float
    )  # (K=4, N=1, 3)
    gyro = np.array([[[0.0, 0.0, 3.0]]])
    for omega0 in (None, np.array([[0.5, -0.3, 2.0]])):
        est = bcd.motion_ml(acc, gyro, positions, SIGMA_A, SIGMA_G, omega0=omega0)
        np.testing.assert_allclose(est.omega, [[0, 0, 3]], rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.omega_dot, [[0, 0, 4]], rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.s, [[0, 0, 9.81]], rtol=0, atol=1e-9)
        assert est.cost[0] < 1e-12 and est.converged.all()


def test_motion_ml_noise_free_equals_truth(sim):
    # start far from the truth (0.3 rad/s off, and from zero): the ML motion is the truth
    for omega0 in (sim["omega"] + 0.3, np.zeros_like(sim["omega"]), None):
        est = bcd.motion_ml(sim["acc0"], sim["gyro0"], sim["r"], SIGMA_A, SIGMA_G, omega0=omega0)
        np.testing.assert_allclose(est.omega, sim["omega"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.omega_dot, sim["omega_dot"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.s, sim["s"], rtol=0, atol=1e-9)
        assert est.converged.all() and est.cost.max() < 1e-12


def test_motion_ml_minimises_the_full_cost(sim):
    """With noise, no perturbation of any of the 9 unknowns of a sample lowers its whitened cost."""
    est = bcd.motion_ml(sim["acc"], sim["gyro"], sim["r"], SIGMA_A, SIGMA_G)

    def cost(s, om, omd, n):
        e = sim["acc"][:, n] - _model(sim["r"], s[None], om[None], omd[None])[:, 0]
        eg = sim["gyro"][0, n] - om
        return (e**2).sum() / SIGMA_A**2 + (eg**2).sum() / SIGMA_G**2

    rng = np.random.default_rng(5)
    for n in (0, 123, 399):
        x = (est.s[n], est.omega[n], est.omega_dot[n])
        c0 = cost(*x, n)
        assert c0 == pytest.approx(est.cost[n], rel=1e-9)
        for _ in range(20):
            dx = [v + rng.normal(scale=h, size=3) for v, h in zip(x, (1e-3, 1e-5, 1e-2))]
            assert cost(*dx, n) >= c0 - 1e-9
    # the whitened cost per sample is χ² with 3K + 3 − 9 = 18 degrees of freedom
    assert est.cost.mean() == pytest.approx(18, abs=5 * np.sqrt(2 * 18 / N))


# --------------------------------------------------------------------------------------------
# step (b), eq. 9


def test_eq9_noise_free_exact(sim):
    r = bcd.positions_given_motion(sim["acc0"], sim["s"], sim["omega"], sim["omega_dot"], reference=0)
    np.testing.assert_allclose(r, sim["r"], rtol=0, atol=1e-13)
    np.testing.assert_allclose(bcd.motion_gram(sim["omega"], sim["omega_dot"]), _gram(sim["omega"], sim["omega_dot"]), rtol=1e-12)


def test_eq9_noisy_within_its_covariance(sim):
    r = bcd.positions_given_motion(sim["acc"], sim["s"], sim["omega"], sim["omega_dot"], reference=0)
    cov = SIGMA_A**2 * np.linalg.inv(_gram(sim["omega"], sim["omega_dot"]))
    err = (r - sim["r"])[1:]
    assert np.all(np.abs(err) <= NSIG * np.sqrt(np.diag(cov)))
    assert np.all(r[0] == 0.0)


# --------------------------------------------------------------------------------------------
# Algorithm 1


@pytest.mark.parametrize("reference", [0, 3])
def test_bcd_recovers_positions(sim, reference):
    r0 = sim["r0"].copy()
    r0[reference] = sim["r"][reference]
    calls = []
    res = bcd.bcd_positions(
        sim["acc"], sim["gyro"], SIGMA_A, SIGMA_G, r0, reference=reference, max_iter=400,
        progress=lambda it, c, dr: calls.append((it, c, dr)),
    )
    assert res.converged and res.iterations < 400
    assert res.step_history[-1] < 1e-9
    np.testing.assert_array_equal(res.positions[reference], r0[reference])
    # relative positions are what is identifiable; compare them to the marginal CRB
    sd, free = _marginal_crb(sim["r"] - sim["r"][reference], sim["omega"], sim["omega_dot"], reference)
    err = (res.positions - sim["r"])[free]
    assert np.all(np.abs(err) <= NSIG * sd), np.abs(err / sd).max()
    assert np.abs(sim["r0"] - sim["r"])[free].max() > 20 * sd.max()  # it really moved
    # the cost never increases, and at the optimum it is χ² with `dof` degrees of freedom
    ch = res.cost_history
    assert np.all(np.diff(ch) <= 1e-9 * ch[0])
    assert res.cost <= ch[-1] * (1 + 1e-12)
    assert res.dof == 3 * K * N + 3 * N - 9 * N - 3 * (K - 1)
    assert res.cost / res.dof == pytest.approx(1.0, abs=5 * np.sqrt(2 / res.dof))
    # progress was called once per iteration with the recorded numbers
    assert [c[0] for c in calls] == list(range(1, res.iterations + 1))
    np.testing.assert_array_equal([c[1] for c in calls], ch)
    np.testing.assert_array_equal([c[2] for c in calls], res.step_history)
    # the returned motion is the motion ML at the returned positions
    est = bcd.motion_ml(sim["acc"], sim["gyro"], res.positions, SIGMA_A, SIGMA_G)
    np.testing.assert_allclose(est.omega, res.omega, atol=1e-9)
    assert est.cost.sum() == pytest.approx(res.cost, rel=1e-9)
    assert res.wall_s > 0
    with pytest.raises(ValueError):
        res.positions[0, 0] = 1.0  # results are read-only


def test_bcd_noise_free_is_exact(sim):
    res = bcd.bcd_positions(sim["acc0"], sim["gyro0"], SIGMA_A, SIGMA_G, sim["r0"], max_iter=1000, tol=1e-12)
    assert res.converged
    np.testing.assert_allclose(res.positions, sim["r"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.omega_dot, sim["omega_dot"], rtol=0, atol=1e-5)


def test_bcd_max_iter_reports_not_converged(sim):
    res = bcd.bcd_positions(sim["acc"], sim["gyro"], SIGMA_A, SIGMA_G, sim["r0"], max_iter=3)
    assert not res.converged and res.iterations == 3 and len(res.cost_history) == 3


# --------------------------------------------------------------------------------------------
# gyroscope mask


def test_masked_gyro_samples_are_ignored(sim):
    sat = np.quantile(np.abs(sim["gyro"]).max(axis=2), 0.8)  # rad/s per axis: a saturating gyroscope
    mask = np.all(np.abs(sim["gyro"]) < sat, axis=2)
    assert (~mask).sum() == pytest.approx(0.2 * N, abs=2)
    clipped = np.clip(sim["gyro"], -sat, sat)  # what a saturated gyroscope really reads
    nan = np.where(mask[:, :, None], sim["gyro"], np.nan)
    huge = np.where(mask[:, :, None], sim["gyro"], 1e6)
    results = [
        bcd.bcd_positions(sim["acc"], g, SIGMA_A, SIGMA_G, sim["r0"], gyro_mask=mask, max_iter=400)
        for g in (clipped, nan, huge)
    ]
    for res in results[1:]:
        np.testing.assert_allclose(res.positions, results[0].positions, rtol=0, atol=1e-12)
        np.testing.assert_allclose(res.omega, results[0].omega, rtol=0, atol=1e-9)
    res = results[0]
    assert res.converged
    sd, free = _marginal_crb(sim["r"], sim["omega"], sim["omega_dot"], 0, mask)
    assert np.all(np.abs((res.positions - sim["r"])[free]) <= NSIG * sd)
    assert res.dof == 3 * K * N + 3 * int(mask.sum()) - 9 * N - 3 * (K - 1)
    # in the saturated runs ω comes from the accelerometers alone, with the right sign
    bad = ~mask[0]
    err = np.abs(res.omega[bad] - sim["omega"][bad])
    sd = _omega_sd(sim["r"], sim["omega"], sim["omega_dot"], mask)[bad]
    assert np.all(err <= 5 * sd), (err / sd).max()
    assert 0.02 < sd.max() < 1.0  # ~1 % of |ω|: the accelerometers alone do determine it
    # the clipped values would have been wrong by several rad/s
    assert np.linalg.norm(clipped[0, bad] - sim["omega"][bad], axis=1).max() > 1.0


def test_sample_without_gyro_and_zero_start_stays_finite(sim):
    mask = np.ones((1, N), bool)
    mask[0, 100:110] = False
    omega0 = sim["omega"].copy()
    omega0[100:110] = 0.0  # ω = 0 is a stationary point of a sample without gyroscope
    est = bcd.motion_ml(sim["acc0"], sim["gyro0"], sim["r"], SIGMA_A, SIGMA_G, gyro_mask=mask, omega0=omega0)
    assert np.all(np.isfinite(est.s)) and np.all(np.isfinite(est.omega)) and np.all(np.isfinite(est.omega_dot))
    keep = np.ones(N, bool)
    keep[100:110] = False
    np.testing.assert_allclose(est.omega[keep], sim["omega"][keep], atol=1e-9)
    # the default start interpolates the gyroscope over the gap and finds the truth there too
    est = bcd.motion_ml(sim["acc0"], sim["gyro0"], sim["r"], SIGMA_A, SIGMA_G, gyro_mask=mask)
    np.testing.assert_allclose(est.omega, sim["omega"], atol=1e-9)
    # no gyroscope at all, ω0 = 0: still finite (ω stays at the stationary point)
    est = bcd.motion_ml(sim["acc0"], None, sim["r"], SIGMA_A, SIGMA_G)
    assert np.all(np.isfinite(est.omega_dot)) and np.all(est.omega == 0.0)


# --------------------------------------------------------------------------------------------
# input validation


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(acc=np.zeros((K, N))), r"acc must have shape \(K, N, 3\)"),
        (dict(acc=np.zeros((2, N, 3))), r"at least 3 accelerometer triads"),
        (dict(gyro=np.zeros((1, N - 1, 3))), r"gyro has 399 samples but acc has 400"),
        (dict(gyro=np.zeros((1, N, 2))), r"gyro must have shape \(G, N, 3\)"),
        (dict(r0=np.zeros((K - 1, 3))), r"r0 must have shape \(K, 3\) = \(8, 3\)"),
        (dict(acc_sigma=np.ones(K - 1)), r"acc_sigma must be a scalar or have shape \(8,\)"),
        (dict(acc_sigma=-1.0), r"acc_sigma must be finite and positive"),
        (dict(gyro_sigma=np.ones(2)), r"gyro_sigma must be a scalar or have shape \(1,\)"),
        (dict(gyro_mask=np.ones((1, N - 1), bool)), r"gyro_mask must have shape \(G, N\) = \(1, 400\)"),
        (dict(gyro_mask=np.ones((1, N), int)), r"gyro_mask must be a boolean array"),
        (dict(gyro=None, gyro_mask=np.ones((1, N), bool)), r"gyro_mask was given but gyro is None"),
        (dict(reference=K), r"reference must be a triad index in \[0, 7\]"),
        (dict(reference=1.5), r"reference must be an integer"),
        (dict(max_iter=0), r"max_iter must be a positive integer"),
        (dict(tol=-1.0), r"tol must be finite and >= 0"),
        (dict(omega0=np.zeros((N, 2))), r"omega0 must have shape \(N, 3\)"),
        (dict(r0=np.outer(np.arange(K), [1e-3, 0, 0])), r"do not span a plane"),
    ],
)
def test_bcd_validation(sim, change, match):
    args = dict(acc=sim["acc"], gyro=sim["gyro"], acc_sigma=SIGMA_A, gyro_sigma=SIGMA_G, r0=sim["r0"])
    args.update(change)
    with pytest.raises(ValueError, match=match):
        bcd.bcd_positions(**args)


def test_validation_of_values_and_other_entry_points(sim):
    acc = sim["acc"].copy()
    acc[2, 5, 1] = np.nan
    with pytest.raises(ValueError, match="acc contains non-finite values"):
        bcd.bcd_positions(acc, sim["gyro"], SIGMA_A, SIGMA_G, sim["r0"])
    gyro = sim["gyro"].copy()
    gyro[0, 7] = np.nan
    with pytest.raises(ValueError, match="non-finite values at samples that gyro_mask marks valid"):
        bcd.bcd_positions(sim["acc"], gyro, SIGMA_A, SIGMA_G, sim["r0"])
    with pytest.raises(ValueError, match=r"positions must have shape \(K, 3\)"):
        bcd.motion_ml(sim["acc"], sim["gyro"], sim["r"][:5], SIGMA_A, SIGMA_G)
    with pytest.raises(ValueError, match=r"omega must have shape \(N, 3\) = \(400, 3\)"):
        bcd.positions_given_motion(sim["acc"], sim["s"], sim["omega"][:10], sim["omega_dot"])
    # a motion about one fixed axis (ω ∥ ω̇ always) does not excite all position axes (Lemma 1)
    axis = np.array([0.0, 0.0, 1.0])
    om = np.outer(np.sin(np.arange(N) * 0.05), axis)
    with pytest.raises(ValueError, match="does not excite all three position axes"):
        bcd.positions_given_motion(sim["acc"], sim["s"], om, 2 * om)

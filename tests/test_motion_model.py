"""The motion's process models and their noise levels estimated from the data.

Hand-computed residuals of every integration, the Wiener models' whitening against their
covariance written out, derivatives against finite differences, the variance components'
redundancies against the dense hat matrix, recovery of known process-noise levels from a motion
that is a sample of the model, and the problem file's motion keys.
"""

import casadi as ca
import numpy as np
import scipy.sparse as sp
import pytest

from castimate.errors import InputError
from castimate.kinds.dynamic import solve_dynamic
from castimate.models import motion as mot
from castimate.problem.dynamic import OMEGA_DDOT, DynamicConfig, DynamicData, MotionSigmas
from castimate.problem.graph import SolverOptions
from castimate.problem.triads import GroupSetting, TriadConfig
from castimate.simulate.dynamic import Motion, dynamic_measurements, sinusoid_motion
from castimate.solver.ipopt import Solver
from castimate.solver.variance import block_rows, hat_diagonal, redundancies, selected_inverse

from test_assembly import dynamic_case

W, WD, S = ca.DM([1, 0, 0]), ca.DM([10, 0, 0]), ca.DM([0, 0, 9])
W1, WD1, S1 = ca.DM([1.2, 0, 0]), ca.DM([10, 1, 0]), ca.DM([0, 0, 9.5])


def residual(integration, dt=0.01, ss=2.0, si=0.5, sw=4.0):
    return np.asarray(ca.evalf(mot.process_residual(W, WD, S, W1, WD1, S1, dt, ss, si, sw, integration))).ravel()


def test_euler_and_trapezoid_by_hand():
    # Euler (Schopp eq. 7): s (9.5 - 9)/(2·0.01); ω (1.2 - 1 - 10·0.01)/(0.5·0.01); ω̇ (1 - 0)/(4·0.01)
    assert np.allclose(residual("euler"), [0, 0, 25, 20, 0, 0, 0, 25, 0])
    # trapezoid: ω_x (1.2 - 1 - ½(10 + 10)·0.01)/0.005 = 20, ω_y (0 - ½(0 + 1)·0.01)/0.005 = -1
    assert np.allclose(residual("trapezoid"), [0, 0, 25, 20, -1, 0, 0, 25, 0])


def test_wiener2_by_hand():
    # √q_s = 2, √q_ω = 4, Δt = 0.01: s 0.5/(2·0.1); ω̇_y 1/(4·0.1); ω the trapezoid misfit over
    # 4·sqrt(Δt³/12) = 1.1547e-3: x 0.1/1.1547e-3, y -0.005/1.1547e-3
    r = residual("wiener2", si=4.0)
    d = 4 * np.sqrt(1e-6 / 12)
    assert np.allclose(r, [0, 0, 2.5, 0.1 / d, -0.005 / d, 0, 0, 2.5, 0])


def test_wiener_whitening_against_the_covariance():
    """|r|² of the exact steps equals eᵀ Q⁻¹ e with Q written out: wiener2 q[[Δt³/3, Δt²/2], [Δt²/2, Δt]]
    and wiener3 q[[Δt⁵/20, Δt⁴/8, Δt³/6], [Δt⁴/8, Δt³/3, Δt²/2], [Δt³/6, Δt²/2, Δt]]."""
    dt, q = 0.008, 7.0 ** 2
    Q2 = q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
    Q3 = q * np.array([[dt ** 5 / 20, dt ** 4 / 8, dt ** 3 / 6], [dt ** 4 / 8, dt ** 3 / 3, dt ** 2 / 2],
                       [dt ** 3 / 6, dt ** 2 / 2, dt]])
    rng = np.random.default_rng(0)
    x0, x1 = rng.standard_normal((2, 3, 3))  # (ω, ω̇, ω̈) rows, xyz columns
    s0 = s1 = np.zeros(3)
    r2 = np.asarray(ca.evalf(mot.process_residual(*x0[:2], s0, *x1[:2], s1, dt, 1.0, 7.0, 7.0, "wiener2"))).ravel()
    e2 = np.stack([x1[0] - x0[0] - x0[1] * dt, x1[1] - x0[1]])  # (2, 3)
    assert np.isclose(r2 @ r2, np.einsum("ia,ij,ja->", e2, np.linalg.inv(Q2), e2), rtol=1e-9)
    r3 = np.asarray(ca.evalf(mot.process_residual_snap(x0[0], x0[1], x0[2], s0, x1[0], x1[1], x1[2], s1, dt, 1.0,
                                                       7.0))).ravel()
    e3 = np.stack([x1[0] - x0[0] - x0[1] * dt - x0[2] * dt ** 2 / 2, x1[1] - x0[1] - x0[2] * dt, x1[2] - x0[2]])
    assert np.isclose(r3 @ r3, np.einsum("ia,ij,ja->", e3, np.linalg.inv(Q3), e3), rtol=1e-8)


@pytest.mark.parametrize("integration", mot.INTEGRATIONS)
def test_process_factor_derivatives_match_finite_differences(integration):
    from castimate.problem.dynamic import process_factor

    f = process_factor(integration)
    z, d = ca.SX.sym("z", f.size1_in(0)), ca.SX.sym("d", 4)
    J = ca.Function("J", [z, d], [ca.jacobian(f(z, d), z)])
    rng = np.random.default_rng(1)
    z0, d0 = rng.standard_normal(f.size1_in(0)), np.array([0.01, 2.0, 0.5, 3.0])
    if integration.startswith("wiener"):
        d0[2] = d0[3]
    h = 1e-6
    fd = np.column_stack([(np.asarray(f(z0 + h * e, d0)) - np.asarray(f(z0 - h * e, d0))).ravel() / (2 * h)
                          for e in np.eye(len(z0))])
    assert np.allclose(np.asarray(J(z0, d0)), fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


@pytest.mark.parametrize("coupled", [True, False])
def test_selected_inverse_matches_the_dense_inverse(coupled):
    """With neighbours coupled (the forward/backward sweep) and without (independent stages: the
    blocks' own inverses)."""
    rng = np.random.default_rng(2)
    N, m = 6, 3
    G = rng.standard_normal((3 * N * m, N * m)) * (np.abs(np.subtract.outer(np.arange(3 * N * m) // (3 * m),
                                                                             np.arange(N * m) // m)) <= 0)
    H = G.T @ G + np.diag(np.ones(N * m))
    for n in range(N - 1):  # couple neighbours
        c = 0.3 * rng.standard_normal((m, m)) * coupled
        H[n * m:(n + 1) * m, (n + 1) * m:(n + 2) * m] += c
        H[(n + 1) * m:(n + 2) * m, n * m:(n + 1) * m] += c.T
    H += 3 * np.eye(N * m)
    A = np.stack([H[n * m:(n + 1) * m, n * m:(n + 1) * m] for n in range(N)])
    C = np.stack([H[n * m:(n + 1) * m, (n + 1) * m:(n + 2) * m] for n in range(N - 1)])
    Sd, So = selected_inverse(A, C)
    Hi = np.linalg.inv(H)
    assert np.allclose(Sd, np.stack([Hi[n * m:(n + 1) * m, n * m:(n + 1) * m] for n in range(N)]), atol=1e-12)
    assert np.allclose(So, np.stack([Hi[n * m:(n + 1) * m, (n + 1) * m:(n + 2) * m] for n in range(N - 1)]),
                       atol=1e-12)


@pytest.mark.parametrize("integration", ["wiener3", "euler"])
def test_redundancies_match_the_dense_hat_matrix(integration):
    """ρ_k = n_k − Σ diag(J P Jᵀ) over the component's rows, P the constrained Gauss-Newton
    covariance of every variable (quaternion misalignments, a prior, masked samples)."""
    prob = dynamic_case(30, model=MotionSigmas(integration))
    solver = Solver(prob.lsq, SolverOptions(elimination="none"))
    sol = solver.solve()
    J, G = solver.jacobians(sol.x)
    J, G = J.toarray(), G.toarray()
    n, c = J.shape[1], G.shape[0]
    K = np.block([[J.T @ J, G.T], [G, np.zeros((c, c))]])
    P = np.linalg.inv(K)[:n, :n]
    h = np.einsum("ri,ij,rj->r", J, P, J)
    assert np.isclose(h.sum(), n - c, rtol=1e-8)
    lay = prob.lsq.layout
    stages = np.hstack([lay.w_index(g.name)[:, g.free[0]] for g in lay.groups if g.name.startswith("motion.")])
    idx = block_rows(solver, "process_model")
    comps = {k: idx[:, list(r)] for k, r in prob.config.motion.components.items()}
    red = redundancies(J, G, stages, comps)
    for k, rows in comps.items():
        assert red[k] == pytest.approx(rows.size - h[rows.ravel()].sum(), rel=1e-8, abs=1e-8)
    # the merged machinery's leverages row by row (measurement and process rows; the noise model's
    # redundancies 1 − h), in chunks smaller than the problem
    import castimate.solver.variance as var
    chunk, var.CHUNK = var.CHUNK, 37
    try:
        assert np.allclose(hat_diagonal(J, G, stages), h, rtol=1e-6, atol=1e-7)
        some = np.array([5, 0, len(h) - 1, 17])
        assert np.allclose(hat_diagonal(J, G, stages, some), h[some], rtol=1e-6, atol=1e-7)
    finally:
        var.CHUNK = chunk


def test_redundancies_with_rows_reading_both_neighbours():
    """Rows that read the stages n-1, n and n+1 (a sample age's central differences) couple stages
    two apart: the redundancies still equal the dense hat matrix's (super-stages of two samples,
    an odd number of stages so that one is padded)."""
    rng = np.random.default_rng(7)
    N, m, c = 11, 2, 3
    stages = np.arange(N * m).reshape(N, m)
    comps: dict[str, list[int]] = {"reading": [], "process": [], "rate": []}
    rows = []

    def row(name, reads):
        r = np.zeros(N * m + c)
        for n in reads:
            r[stages[n]] = rng.normal(size=m)
        r[N * m:] = rng.normal(size=c)
        comps[name].append(len(rows))
        rows.append(r)

    for n in range(N):
        for _ in range(3):
            row("reading", [n])
    for n in range(N - 1):
        for _ in range(m):
            row("process", [n, n + 1])
    for n in range(1, N - 1):
        row("rate", [n - 1, n, n + 1])
    J = np.array(rows)
    h = np.einsum("ri,ij,rj->r", J, np.linalg.inv(J.T @ J), J)
    red = redundancies(sp.csr_matrix(J), sp.csr_matrix((0, J.shape[1])), stages,
                       {k: np.array(v) for k, v in comps.items()})
    for k, r in comps.items():
        assert red[k] == pytest.approx(len(r) - h[r].sum(), rel=1e-9, abs=1e-9)
    assert np.allclose(hat_diagonal(sp.csr_matrix(J), sp.csr_matrix((0, J.shape[1])), stages), h, atol=1e-10)
    # rows that read no stage (a joint problem's static rows), alone in a chunk of their own
    Jt = np.vstack([J, np.hstack([np.zeros((4, N * m)), rng.normal(size=(4, c))])])
    ht = np.einsum("ri,ij,rj->r", Jt, np.linalg.inv(Jt.T @ Jt), Jt)
    import castimate.solver.variance as var
    chunk, var.CHUNK = var.CHUNK, 4
    try:
        got = hat_diagonal(sp.csr_matrix(Jt), sp.csr_matrix((0, J.shape[1])), stages, np.arange(len(J), len(Jt)))
    finally:
        var.CHUNK = chunk
    assert np.allclose(got, ht[len(J):], atol=1e-10)


def test_hat_diagonal_with_a_stage_no_row_reads():
    """A stage variable no row reads (a sample whose every reading is masked) is undetermined: the
    Hessian is singular there, the ridge keeps the sweep defined and the other rows' leverages equal
    the hat matrix of the determined part."""
    rng = np.random.default_rng(8)
    N, m, c = 6, 2, 2
    stages = np.arange(N * m).reshape(N, m)
    J = np.zeros((4 * N, N * m + c))
    for n in range(N):
        J[4 * n:4 * n + 4, stages[n]] = rng.normal(size=(4, m))
        J[4 * n:4 * n + 4, N * m:] = rng.normal(size=(4, c))
    J[4 * 3:4 * 3 + 4, stages[3, 1]] = 0.0  # the second state of stage 3 unread
    keep = np.ones(J.shape[1], bool)
    keep[stages[3, 1]] = False
    Jd = J[:, keep]
    h = np.einsum("ri,ij,rj->r", Jd, np.linalg.inv(Jd.T @ Jd), Jd)
    assert np.allclose(hat_diagonal(sp.csr_matrix(J), sp.csr_matrix((0, J.shape[1])), stages), h, atol=1e-8)


def joint_jacobian(coupled_stages: bool, seed: int = 11):
    """A Jacobian shaped like a joint static-plus-dynamic problem's: stages of m = 3 motion states,
    each read by two 'accelerometer' rows per axis pattern (a triad's θ columns, repeated within
    the stage) and a 'gyroscope' row reading one state; static rows that read the unit pose
    directions (|d|² = 1 constraints) and some of the calibration θ but no stage; with
    ``coupled_stages`` also process rows reading stages n and n+1. Returns (J, G, stages)."""
    rng = np.random.default_rng(seed)
    N, m, n_cal, n_pose = 23, 3, 7, 4
    stages = np.arange(N * m).reshape(N, m)
    cal = N * m + np.arange(n_cal)
    pose = N * m + n_cal + np.arange(3 * n_pose).reshape(n_pose, 3)
    n = N * m + n_cal + pose.size
    rows = []

    def row(cols, stage_cols=()):
        r = np.zeros(n)
        r[list(stage_cols)] = rng.normal(size=len(stage_cols))
        r[list(cols)] = rng.normal(size=len(cols))
        rows.append(r)

    for k in range(N):
        for _ in range(2):
            row(cal[[0, 1, 2]], stages[k])          # triad 1: the same θ pattern twice per stage
            row(cal[[3, 4, 5, 6]], stages[k])       # triad 2
        row(cal[[6]], stages[k, [1]])               # a gyroscope axis: one state
        if coupled_stages and k + 1 < N:
            row((), np.r_[stages[k], stages[k + 1]])
    d = rng.normal(size=(n_pose, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for p in range(n_pose):
        for _ in range(3):
            row(np.r_[pose[p], cal[[0, 3]]])
    G = np.zeros((n_pose, n))
    for p in range(n_pose):
        G[p, pose[p]] = 2 * d[p]
    return np.array(rows), G, stages


@pytest.mark.parametrize("coupled_stages", [False, True])
def test_hat_diagonal_of_a_joint_problem_matches_the_dense_hat_matrix(coupled_stages):
    """Leverages of every row, and of a subset (unordered, repeated), equal diag(J P Jᵀ) with P the
    constrained inverse written out densely, to 1e-10: stages alone (block-diagonal) or coupled,
    static rows that read no stage, θ patterns repeated within a stage, a row reading part of a stage."""
    J, G, stages = joint_jacobian(coupled_stages)
    n, c = J.shape[1], G.shape[0]
    P = np.linalg.inv(np.block([[J.T @ J, G.T], [G, np.zeros((c, c))]]))[:n, :n]
    h = np.einsum("ri,ij,rj->r", J, P, J)
    assert h.sum() == pytest.approx(n - c, rel=1e-10)
    got = hat_diagonal(sp.csr_matrix(J), sp.csr_matrix(G), stages)
    assert np.abs(got - h).max() < 1e-10
    some = np.array([len(h) - 1, 3, 0, 3, 57])
    assert np.abs(hat_diagonal(sp.csr_matrix(J), sp.csr_matrix(G), stages, some) - h[some]).max() < 1e-10


def _dense_hat(J, G):
    n, c = J.shape[1], G.shape[0]
    P = np.linalg.inv(np.block([[J.T @ J, G.T], [G, np.zeros((c, c))]]))[:n, :n]
    return np.einsum("ri,ij,rj->r", J, P, J)


@pytest.mark.parametrize("coupled_stages", [False, True])
def test_hat_diagonal_structure_kept_across_calls(coupled_stages):
    """With a ``cache``, the second call at other values of the same sparsity reuses the first
    call's structure and still equals the dense hat matrix's diagonal; a Jacobian of another
    sparsity (one more static row) replaces it, other rows wanted keep it (they only select)."""
    J, G, stages = joint_jacobian(coupled_stages)
    J2, G2, _ = joint_jacobian(coupled_stages, seed=12)  # same pattern, other values
    assert np.array_equal(J != 0, J2 != 0)
    cache = {}
    assert np.abs(hat_diagonal(sp.csr_matrix(J), sp.csr_matrix(G), stages, None, cache) - _dense_hat(J, G)).max() < 1e-10
    plan = cache["plan"]
    got = hat_diagonal(sp.csr_matrix(J2), sp.csr_matrix(G2), stages, None, cache)
    assert cache["plan"] is plan
    assert np.abs(got - _dense_hat(J2, G2)).max() < 1e-10
    J3 = np.vstack([J2, J2[-1:]])  # a repeated static row: another structure
    got = hat_diagonal(sp.csr_matrix(J3), sp.csr_matrix(G2), stages, None, cache)
    assert cache["plan"] is not plan and np.abs(got - _dense_hat(J3, G2)).max() < 1e-10
    some = np.array([len(J3) - 1, 4, 0])
    plan = cache["plan"]
    got = hat_diagonal(sp.csr_matrix(J3), sp.csr_matrix(G2), stages, some, cache)
    assert cache["plan"] is plan and np.abs(got - _dense_hat(J3, G2)[some]).max() < 1e-10


def _three_stage_rows(c: int = 3, seed: int = 13):
    """J of rows reading stages n-1, n and n+1 (a sample age's central differences: super-stages of
    two samples, one padded) beside rows reading one stage, all with the c θ columns; no constraints."""
    rng = np.random.default_rng(seed)
    N, m = 13, 2
    stages = np.arange(N * m).reshape(N, m)
    rows = []
    for n in range(N):
        reads = [n] if n in (0, N - 1) else [n - 1, n, n + 1]
        for _ in range(4):
            r = np.zeros(N * m + c)
            r[stages[reads].ravel()] = rng.normal(size=m * len(reads))
            r[N * m:] = rng.normal(size=c)
            rows.append(r)
    return np.array(rows), np.zeros((0, N * m + c)), stages


@pytest.mark.parametrize("case", ["independent", "coupled", "three_stages", "no_border"])
def test_hat_diagonal_in_chunks_on_threads_is_identical(monkeypatch, case):
    """The leverages computed chunk of stages by chunk (CHUNK stages each, or fewer by CHUNK_FLOATS: 2
    and 3 do not divide the 23 stages, a coupled row's second stage and a pattern's rows fall in the
    next chunk, the static rows in none) on worker threads equal those of the same chunks in the calling thread bit for bit,
    with the structure kept across calls and for a subset of rows (unordered, repeated); and the
    dense hat matrix's diagonal in any chunking; also without a border (no θ: only the motion estimated)."""
    import threading

    import castimate.solver.variance as var
    J, G, stages = (_three_stage_rows() if case == "three_stages" else _three_stage_rows(c=0) if case == "no_border"
                    else joint_jacobian(case == "coupled"))
    J2 = J * (1 + 0.1 * np.random.default_rng(3).standard_normal(J.shape))  # same sparsity, other values
    dense = [_dense_hat(J, G), _dense_hat(J2, G)]
    some = np.array([len(J) - 1, 7, 0, 7, len(J) // 2])
    seen = set()
    by_stage = var._by_stage

    def spy(*a):
        seen.add(threading.current_thread().name)
        return by_stage(*a)

    monkeypatch.setattr(var, "_by_stage", spy)
    for chunk, floats in ((2, 1 << 22), (3, 1 << 22), (1000, 1 << 22), (1000, 1)):  # the last: one stage a chunk
        monkeypatch.setattr(var, "CHUNK", chunk)
        monkeypatch.setattr(var, "CHUNK_FLOATS", floats)
        got = {}
        for threads in (1, 3):
            cache = {}
            got[threads] = [hat_diagonal(sp.csr_matrix(Ji), sp.csr_matrix(G), stages, rows, cache, threads)
                            for Ji, rows in ((J, None), (J2, None), (J2, some))]
        for a, b in zip(got[1], got[3], strict=True):
            np.testing.assert_array_equal(a, b)
        for a, h in zip(got[3], dense + [dense[1][some]], strict=True):
            assert np.abs(a - h).max() < 1e-10
    # the chunks did run on the worker threads
    assert any(n.startswith("castimate-threads") for n in seen)


def test_known_process_noise_recovered():
    """A motion that is a sample of the wiener3 model (ω̈ a Wiener process of density q_ω, s a
    random walk of density q_s), read by four triads with gyroscopes: the estimated levels
    (started 10x off) within 4 standard errors, SE(√q̂)/√q ≈ 1/sqrt(2ρ) for the redundancy ρ."""
    rng = np.random.default_rng(5)
    N, dt, sq_w, sq_s = 300, 0.01, 10.0, 3.0  # |ω| up to ~30 rad/s
    t = np.arange(N) * dt
    p = np.arange(3)[::-1]
    M = 1.0 / ((p[:, None] + p[None, :] + 1) * np.array([2, 1, 1.0])[:, None] * np.array([2, 1, 1.0])[None, :])
    D = np.diag(dt ** (p + 0.5))
    L = sq_w * np.linalg.cholesky(D @ M @ D)
    F = np.array([[1, dt, dt ** 2 / 2], [0, 1, dt], [0, 0, 1]])
    x = np.zeros((N, 3, 3))  # (sample, (ω, ω̇, ω̈), axis)
    x[0] = np.array([[5.0, -3.0, 2.0], [0, 0, 0], [0, 0, 0]])
    for n in range(N - 1):
        x[n + 1] = F @ x[n] + L @ rng.standard_normal((3, 3))
    s = np.array([0, 0, 9.81]) + np.cumsum(sq_s * np.sqrt(dt) * rng.standard_normal((N, 3)), axis=0)
    motion = Motion(t, x[:, 0], x[:, 1], s, np.tile([1.0, 0, 0, 0], (N, 1)))
    names = ["a", "b", "c", "d"]
    pos = np.array([[0, 0, 0], [0.03, 0, 0], [0, 0.04, 0.01], [0.02, -0.03, 0]])
    Rs = np.stack([np.eye(3)] * 4)
    gyro = {"T_g": Rs, "b_g": np.zeros((4, 3)), "sigma": 2e-3, "saturation": None}
    acc, gy, _ = dynamic_measurements(motion, pos, Rs, np.zeros((4, 3)), rng, 0.02, gyro=gyro, names=names)
    fixed = GroupSetting(free=(False,) * 3)
    triads = tuple(TriadConfig(nm, np.eye(3), {g: fixed for g in ("gain", "bias", "nonorthogonality", "misalignment")},
                               {g: fixed for g in ("gain", "bias", "misalignment")}, pos[i]) for i, nm in enumerate(names))
    cfg = DynamicConfig(triads, "a", motion=MotionSigmas("wiener3", s=0.1 * sq_s, omega_dot=10 * sq_w))
    data = DynamicData(t, acc, {nm: np.full(3, 0.02) for nm in names}, gy, {nm: np.full(3, 2e-3) for nm in names})
    problem, _, sol, _, var = solve_dynamic(cfg, data, {nm: pos[i] for i, nm in enumerate(names)})
    assert sol.success and var.converged
    assert OMEGA_DDOT in sol.values
    for k, truth in (("s", sq_s), ("omega_dot", sq_w)):
        se = 1 / np.sqrt(2 * var.redundancy[k])
        assert abs(var.levels[k] / truth - 1) < 4 * se, (k, var.levels[k], truth, se)
    assert problem.config.motion.levels() == pytest.approx(var.levels)


def test_integration_level_without_gyroscopes_is_kept():
    """Without gyroscopes the trapezoid's integration rows are fitted exactly by the motion (no
    redundancy): that level is kept as given, the other two are estimated."""
    from castimate.simulate.dynamic import schopp_geometry

    rng = np.random.default_rng(4)
    names, nominal, true, R, _ = schopp_geometry(rng, 1e-3, reference="acc1")
    motion = sinusoid_motion(250, 125.0, 10.0, 150.0, rng)
    Rs = np.stack([R[n] for n in names])
    acc, _, _ = dynamic_measurements(motion, true - true[0], Rs, np.zeros((5, 3)), rng, 0.02, names=names)
    fixed = GroupSetting(free=(False,) * 3)
    triads = tuple(TriadConfig(n, R[n], {g: fixed for g in ("gain", "bias", "nonorthogonality", "misalignment")}, None,
                               nominal[i] - nominal[0]) for i, n in enumerate(names))
    cfg = DynamicConfig(triads, "acc1", motion=MotionSigmas("trapezoid"))
    data = DynamicData(motion.t, acc, {n: np.full(3, 0.02) for n in names})
    problem, _, sol, _, var = solve_dynamic(cfg, data, {n: nominal[i] - nominal[0] for i, n in enumerate(names)})
    assert var.kept == ("omega",) and var.converged
    assert var.levels["omega"] == MotionSigmas("trapezoid").omega
    assert var.redundancy["omega"] < 0.01 * var.rows["omega"] < var.redundancy["s"]


def test_sinusoid_motion_exact_and_not_euler_consistent():
    """ω̇, ω̈ and ṡ are the derivatives of ω, ω̇ and s (central differences at 2 kHz); the motion
    is smooth but violates Euler's step by ½ ω̈ Δt² at 100 Hz; both bounds are respected."""
    rate = 2000.0
    m = sinusoid_motion(4000, rate, 20.0, 300.0, np.random.default_rng(3))
    for v, dv in ((m.omega, m.omega_dot), (m.omega_dot, m.omega_ddot), (m.s, m.s_dot)):
        fd = (v[2:] - v[:-2]) * rate / 2
        assert np.abs(fd - dv[1:-1]).max() < 1e-3 * np.abs(dv).max()
    assert np.linalg.norm(m.omega, axis=1).max() <= 20.0 + 1e-9
    assert np.linalg.norm(m.omega_dot, axis=1).max() <= 300.0 + 1e-9
    c = sinusoid_motion(500, 100.0, 20.0, 300.0, np.random.default_rng(3))
    euler = c.omega[1:] - c.omega[:-1] - c.omega_dot[:-1] * 0.01
    assert np.abs(euler).max() > 0.2 * 0.5 * np.abs(c.omega_ddot).max() * 0.01 ** 2


# -- problem file keys -------------------------------------------------------------------------------

def _spec(tmp_path, motion):
    import yaml
    from castimate.spec import load_problem

    (tmp_path / "d.csv").write_text("t,imu1.ax,imu1.ay,imu1.az\n0,0,0,9.8\n")
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"kind": "dynamic_array", "data": {"path": "d.csv", "format": "csv"},
                                 "array": {"reference": "imu1", "triads": [{"name": "imu1"}]}, "motion": motion}))
    return lambda: load_problem(p)


@pytest.mark.parametrize("motion, where, found", [
    ({"integration": "rk4"}, "motion.integration", "expected one of wiener3, wiener2, trapezoid, euler, found 'rk4'"),
    ({"process_noise": "tuned"}, "motion.process_noise", "expected one of auto, fixed, found 'tuned'"),
    ({"sigma_s": 1.0}, "motion.sigma_s", "is a level of integration trapezoid or euler; with integration: wiener3 "
                                          "give density_s, density_omega"),
    ({"integration": "euler", "density_omega": 3.0}, "motion.density_omega",
     "is a level of integration wiener3 or wiener2; with integration: euler give sigma_s"),
    ({"density_s": -1.0}, "motion.density_s", "expected a positive finite number, found -1.0"),
], ids=["integration", "process_noise", "sigma_with_wiener", "density_with_euler", "negative_level"])
def test_motion_key_errors(tmp_path, motion, where, found):
    with pytest.raises(InputError, match=f"{where}: {found}".replace("(", r"\(").replace(")", r"\)")) as e:
        _spec(tmp_path, motion)()
    assert "\n" not in str(e.value) and e.value.where == where


def test_motion_keys_reach_the_config(tmp_path):
    from castimate.kinds.dynamic import motion_sigmas

    m = motion_sigmas(_spec(tmp_path, {"integration": "euler", "process_noise": "fixed", "sigma_s": 7.0})())
    assert (m.integration, m.estimate, m.s, m.omega_dot) == ("euler", False, 7.0, 1e3 ** 0.5)
    m = motion_sigmas(_spec(tmp_path, {})())
    assert (m.integration, m.estimate) == ("wiener3", True)


@pytest.mark.parametrize("collide", [False, True])
def test_row_patterns_group_rows_by_their_columns(monkeypatch, collide):
    """The hat diagonal's grouping of rows by θ pattern: every row of a group has the group's
    columns and its own values; rows without entries are left out. With a hash that collides
    (all multipliers 1: columns {0, 3} and {1, 2} sum alike) the exact grouping takes over."""
    import castimate.solver.variance as var
    if collide:
        monkeypatch.setattr(var, "_hash_multipliers", lambda k: np.ones(k, np.uint64))
    dense = np.array([[1.0, 0, 0, 2], [0, 3, 4, 0], [5, 0, 0, 6], [0, 0, 0, 0], [0, 7, 8, 0], [9, 0, 0, 0]])
    groups = var._row_patterns(sp.csr_matrix(dense))
    seen = []
    data = sp.csr_matrix(dense).data
    for idx, cols, at in groups:
        assert np.array_equal(dense[idx][:, cols], data[at])
        mask = np.zeros(dense.shape[1], bool)
        mask[cols] = True
        assert np.all(dense[idx][:, ~mask] == 0) and np.all(dense[idx][:, mask] != 0)
        seen += list(idx)
    assert sorted(seen) == [0, 1, 2, 4, 5] and len(groups) == 3


def test_hat_diagonal_plan_by_hand():
    """The slots of the hat diagonal's plan, hand-computed: rows reading one stage each (span 1, one
    row per slot), then a row reading the stages 1 and 2 (span 2: stages coupled) beside them, whose
    first stage is 1; the last stage's row then counts from stage 2 (N − span), R = 2 rows per slot."""
    from castimate.solver.variance import _structure

    N, m = 4, 2
    stages = np.arange(N * m).reshape(N, m)
    J = np.zeros((N + 1, N * m + 1))
    for n in range(N):
        J[n, stages[n]] = 1.0
    J[:, -1] = 1.0
    plan = _structure(sp.csr_matrix(J[:N]), stages, None)
    assert (plan["span"], plan["R"], plan["N"], plan["m"]) == (1, 1, N, m)
    assert np.array_equal(plan["V"], np.arange(N * m)) and np.array_equal(plan["slot_rows"], np.arange(N))
    J[N, stages[1, 1]] = J[N, stages[2, 0]] = 1.0  # reads the stages 1 and 2
    plan = _structure(sp.csr_matrix(J), stages, None)
    # first stages 0, 1, 2, 2 (the last row: N - span), 1: two rows at most per stage; slots of
    # stages 0, 1, 2 hold rows (0, -), (1, 4), (2, 3), none for stage 3
    assert (plan["span"], plan["R"]) == (2, 2)
    assert np.array_equal(plan["slot_rows"], [0, -1, 1, 4, 2, 3]) and np.array_equal(plan["slot_ptr"], [0, 1, 2, 3, 3])
    # each row's stage entries at their place in its row of V (4 wide: its first stage, the next)
    # (row 3 reads stage 3 as its first stage's next: places 2, 3)
    assert np.array_equal(plan["V"], [0, 1, 2 * 4 + 0, 2 * 4 + 1, 4 * 4 + 0, 4 * 4 + 1, 5 * 4 + 2, 5 * 4 + 3,
                                      3 * 4 + 1, 3 * 4 + 2])
    # the θ column: one value per row (J's entries 2, 5, 8, 11, 14), at the row's place in the slots (c = 1)
    assert np.array_equal(plan["T"][1], [0, 2, 3, 4, 5]) and np.array_equal(plan["T"][0], [2, 5, 14, 8, 11])
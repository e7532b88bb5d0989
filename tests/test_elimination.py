"""Variable projection (``SolverOptions(elimination="motion")``, the default) against the full NLP
(``elimination="none"``, the reference path): the same optimum and the same σ's on static and
dynamic problems, with and without the process model, with quaternion-constrained misalignments,
a prior, a free gain and masked samples (``test_assembly``'s cases); the reduced gradient and the
exact reduced Hessian against finite differences of the reduced objective.
"""

import functools

import numpy as np
import pytest

from castimate.problem.dynamic import MotionSigmas
from castimate.problem.static import build_static
from castimate.solver import Solver, SolverOptions

from test_assembly import dynamic_case, static_case
from test_static import make_case


def static_directions(direction: str):
    """Static poses as tilt quaternions (a fixed component in the unit-norm row) or pitch/roll
    angles (no constraint)."""
    cfg, poses, _, _ = make_case(M=4, P=20, gyro=True, direction=direction)
    return build_static(cfg, poses)


def dynamic_sample_ages():
    """8 IMUs with chip sample ages and gyroscope delays: the accelerometer's rate reads the
    neighbouring samples' motion (central differences, one-sided at the ends), so its block is
    staged in three runs (first sample, interior, last sample) and the motion block banded."""
    from castimate.problem.dynamic import build_dynamic
    from test_effects import dynamic_effect_case
    names = [f"imu{i}" for i in (1, 4, 6, 11, 13, 17, 23, 32)]
    effects = {**{f"{nm}.accelerometer.age": np.array([1e-3 * (-1) ** i]) for i, nm in enumerate(names[1:])},
               **{f"{nm}.gyroscope.delay": np.array([-5e-4 * (-1) ** i]) for i, nm in enumerate(names)}}
    cfg, data, _ = dynamic_effect_case(n=40, effects=effects)
    return build_dynamic(cfg, data)


CASES = {"dynamic": lambda: dynamic_case(40, True), "dynamic_no_process_model": lambda: dynamic_case(40, False),
         "dynamic_sample_ages": dynamic_sample_ages,
         "dynamic_wiener2": lambda: dynamic_case(40, True, MotionSigmas("wiener2")),
         "dynamic_euler": lambda: dynamic_case(40, True, MotionSigmas("euler")),
         "static": static_case, "static_quaternion": lambda: static_directions("quaternion"),
         "static_pitch_roll": lambda: static_directions("pitch_roll")}


# both paths converged, what is left is floating point amplified by the conditioning: the static
# case's information has a condition number of 1e10, and its two optima differ by 1.6e-9 relative
# (at most 2.2e-7 σ) on one machine's BLAS and by less on another; every other case agrees to 1e-9
STATIC_RELATIVE = 1e-8


def relative(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


@pytest.mark.parametrize("kind", list(CASES))
@pytest.mark.parametrize("hessian", ["exact", "gauss_newton"])
def test_same_optimum_and_sigmas_as_the_full_nlp(kind, hessian):
    prob = CASES[kind]()
    # the optimum does not depend on the Hessian; the reference's Gauss-Newton path needs 72
    # iterations on one case and stops at "acceptable", so the reference is always exact
    ref = Solver(prob.lsq, SolverOptions(tol=1e-12, elimination="none"))
    new = Solver(prob.lsq, SolverOptions(hessian=hessian, tol=1e-12))
    assert ref.projection is None and new.projection is not None
    a, b = ref.solve(), new.solve()
    assert a.success and b.success
    # the reference stops where IPOPT's tolerance allows; from there a Newton step changes x by
    # about its Newton decrement's square root times the σ's: both must be converged much further
    assert ref.newton_decrement(a.x, a.lam_g) < 1e-15 and new.newton_decrement(b.x, b.lam_g) < 1e-15
    assert relative(b.x, a.x) < (STATIC_RELATIVE if kind == "static" else 1e-9)
    assert abs(b.cost - a.cost) < 1e-12 * a.cost
    # σ's: the Fisher information with the nuisance eliminated, at the same point for both
    sa, sb = np.sqrt(np.diag(ref.covariance(b.x))), np.sqrt(np.diag(b.covariance))
    assert np.abs(sb / sa - 1).max() < 1e-6  # the static case's information has a condition number of 1e10
    assert b.dof == a.dof and b.residual.shape == a.residual.shape


def test_families_found():
    """Dynamic: one family of motion states per sample (12 and block tridiagonal with the wiener3
    process model, 9 and block diagonal without); static: the pose directions with their unit-norm constraint."""
    fams = {k: [(f.R, f.m, f.width, len(f.unit)) for f in Solver(mk().lsq).projection.fams] for k, mk in CASES.items()}
    assert fams == {"dynamic": [(40, 12, 2, 0)], "dynamic_wiener2": [(40, 9, 2, 0)], "dynamic_euler": [(40, 9, 2, 0)],
                    "dynamic_no_process_model": [(40, 9, 1, 0)], "dynamic_sample_ages": [(40, 9, 3, 0)],
                    "static": [(8, 3, 1, 1)], "static_quaternion": [(20, 3, 1, 1)], "static_pitch_roll": [(20, 2, 1, 0)]}


@pytest.mark.parametrize("kind", list(CASES))
def test_reduced_derivatives_match_finite_differences(kind):
    """∇φ and ∇²φ (the Schur complement with second-order terms) of φ(θ) = min_m f(θ, m), off the
    optimum, against central differences of φ and ∇φ."""
    prob = CASES[kind]()
    solver = Solver(prob.lsq)
    P = solver.projection
    sol = solver.solve()
    pf = prob.lsq.layout.p0()
    theta = P.reset(sol.x, None) + 1e-3 * np.random.default_rng(0).standard_normal(P.c)
    P.shortcut = False  # the exact Schur complement at every point (the default may take it one Newton step early)

    def reduced(t):
        P._cache = None  # noqa: SLF001 - re-evaluate: a cached θ would not see the step
        return P.reduced(t, pf, None)

    f0, g0, S0 = reduced(theta)
    h = 1e-6
    steps = [(reduced(theta + h * e), reduced(theta - h * e)) for e in np.eye(P.c)]
    g_fd = np.array([(a[0] - b[0]) / (2 * h) for a, b in steps])
    S_fd = np.array([(a[1] - b[1]) / (2 * h) for a, b in steps])
    assert relative(g_fd, g0) < 1e-7
    assert relative(S_fd, S0) < 1e-5
    assert relative(S0, S0.T) < 1e-12


def test_rate_factors_are_staged_in_runs():
    """The accelerometer block with time offsets is cut into its first sample, the interior and
    its last sample (K = 8 instances per stage group); the gyroscope block stays whole."""
    P = Solver(dynamic_sample_ages().lsq).projection
    runs = [(u.parent, u.rows, u.st[1].J) for u in P.units]
    assert runs == [(0, slice(0, 8), 1), (0, slice(8, 312), 38), (0, slice(312, 320), 1), (1, None, 40)]


def test_masked_samples_and_outside_nuisance_unchanged():
    """Masked samples stay out of the residuals; the motion of every sample is returned."""
    prob = dynamic_case(40, True)
    sol = Solver(prob.lsq).solve()
    assert sol.values["motion.omega"].shape == (40, 3)
    assert np.isfinite(sol.x).all()
    n_masked = (np.arange(40) % 7 == 3).sum() + (np.arange(40) % 5 == 1).sum()
    assert sol.residual.size == 3 * (4 * 40 + 3 * 40 - n_masked) + 12 * 39  # wiener3: 12 process rows


def test_unknown_elimination_is_refused():
    with pytest.raises(ValueError, match="elimination"):
        Solver(dynamic_case(10).lsq, SolverOptions(elimination="schur"))


@pytest.mark.parametrize("elimination", ["motion", "none"])
def test_single_row_inputs_reach_casadi_in_c_order(elimination):
    """A block whose every input is one row fed to all instances (rows=None, as a turn factor on a
    triad's gyroscope) has an index matrix that np.hstack builds in Fortran order: the local
    functions must still get C-order inputs (CasADi's buffers refused them). Both paths solve it
    with a pull of 3 instances on a free gain, to the same optimum."""
    from castimate.problem.graph import FactorBlock, LeastSquaresProblem
    from castimate.solver.assembly import Block
    import casadi as ca
    prob = static_case()
    z, d = ca.SX.sym("z", 3), ca.SX.sym("d", 3)
    pull = FactorBlock("pull", ca.Function("pull", [z, d], [(z - d) / 0.1]), [("imu2.gyroscope.gain", None)],
                       np.array([[1.01, 0.99, 1.0], [1.0, 1.02, 0.98], [0.99, 1.0, 1.01]]))
    lsq = LeastSquaresProblem(prob.lsq.layout, [*prob.lsq.blocks, pull])
    assert Block(pull, lsq.layout).w_idx.flags.c_contiguous
    sol = Solver(lsq, SolverOptions(tol=1e-12, elimination=elimination)).solve()
    ref = Solver(lsq, SolverOptions(tol=1e-12, elimination="none")).solve()
    assert sol.success and relative(sol.x, ref.x) < STATIC_RELATIVE
    assert np.isfinite(sol.covariance).all()


def test_elimination_note_says_what_was_eliminated_and_why_not():
    """The solver states what it eliminated (results.json's status.elimination); a nuisance group
    with bounds or a prior stays a calibration variable, with the reason."""
    from types import SimpleNamespace
    from castimate.solver.elimination import Family
    assert Solver(dynamic_case(10).lsq).elimination_note == \
        "eliminated: 10 x 12 (motion.omega, motion.omega_dot, motion.s, motion.omega_ddot)"  # wiener3
    assert Solver(dynamic_case(10).lsq, SolverOptions(elimination="none")).elimination_note == \
        "full NLP (elimination: none)"
    free, inf = np.ones((4, 3), bool), np.full((4, 3), np.inf)
    g = SimpleNamespace(name="pose.tilt", matrix=True, nuisance=True, free=free, rows=4, scale=np.ones((4, 3)),
                        prior_std=inf, lower=-inf, upper=inf)
    assert Family.candidate(g) and Family.refusal(g) is None
    assert "bounds" in Family.refusal(SimpleNamespace(**{**vars(g), "lower": np.zeros((4, 3))}))
    assert "prior" in Family.refusal(SimpleNamespace(**{**vars(g), "prior_std": np.ones((4, 3))}))


def _projection_at_optimum(kind):
    """The solved case's projection, its fixed parameters and its reduced variables at the optimum."""
    prob = CASES[kind]()
    solver = Solver(prob.lsq)
    P = solver.projection
    sol = solver.solve()
    return P, prob.lsq.layout.p0(), P.reset(sol.x, None)


@pytest.mark.parametrize("kind", ["static", "static_quaternion"])
def test_tangent_basis_carried_to_a_moved_point(kind):
    """The tangent basis of unit-norm rows carried to a moved point is tangent there (orthogonal to
    the constraint gradient 2 x scale²), unchanged at its own point, and within the order of the
    move of the basis at the start (a fresh basis there may turn within the tangent space)."""
    P, pf, th0 = _projection_at_optimum(kind)
    fi = next(i for i, f in enumerate(P.fams) if f.unit)
    fam, X0 = P.fams[fi], P._X0[fi]  # noqa: SLF001
    Z0, _ = P._tangent(fi, X0, pf)  # noqa: SLF001
    assert np.abs(P._carried(fi, Z0, X0) - Z0).max() < 1e-15  # noqa: SLF001
    rng = np.random.default_rng(3)
    for size in (1e-6, 1e-3):
        X1 = X0 + size * rng.standard_normal(X0.shape) * np.abs(X0).max()
        for pos, _ in fam.unit:  # back onto the unit sphere (unscaled), as the Newton step's move does
            X1[:, pos] /= np.linalg.norm(X1[:, pos] * fam.scale[pos], axis=1)[:, None]
        Z1 = P._carried(fi, Z0, X1)  # noqa: SLF001
        for pos, _ in fam.unit:
            a = X1[:, pos] * fam.scale[pos] ** 2
            cos = np.einsum("rk,rka->ra", a, Z1[:, pos, :]) / np.linalg.norm(a, axis=1)[:, None]
            assert np.abs(cos).max() < 1e-13
        assert 0 < np.abs(Z1 - Z0).max() < 100 * size


@pytest.mark.parametrize("kind", [k for k in CASES if k.startswith("dynamic")] + ["static", "static_quaternion"])
def test_newton_point_shortcut_keeps_the_reduced_objective_and_gradient(kind):
    """Off the optimum, φ and ∇φ accepted from the gradient at the Newton point of the nuisance
    (one full evaluation fewer) equal those of the path that evaluates everything there, to
    round-off; the Hessian is the previous point's, within the Newton step's size. Also with
    unit-norm nuisance rows (the static cases' pose directions), whose tangent basis moves with
    the step."""
    P, pf, th0 = _projection_at_optimum(kind)
    for size in (1e-5, 1e-4, 1e-3, 1e-2):  # a step whose prediction needs one Newton step, not more
        theta = th0 + size * np.random.default_rng(1).standard_normal(P.c)
        P._cache = None  # noqa: SLF001
        P.reduced(th0, pf, None)
        anchor, before = P._anchor, P.shortcuts  # noqa: SLF001
        f1, g1, S1 = P.reduced(theta, pf, None)
        if P.shortcuts == before + 1:
            break
    else:
        pytest.fail("no evaluation took the shortcut")
    P._cache, P._anchor, P.shortcut = None, anchor, False  # noqa: SLF001
    f2, g2, S2 = P.reduced(theta, pf, None)
    assert abs(f1 - f2) < 1e-12 * (1 + abs(f2))
    assert relative(g1, g2) < 1e-9
    assert relative(S1, S2) < 1e-2


def test_stall_stops_after_iterations_that_do_not_move_x():
    """IPOPT's iteration callback: 10 consecutive iterations that move x by at most 1e-12 relative
    stop the solve; a larger move restarts the count (hand-made iterates)."""
    from castimate.solver.ipopt import Stall
    s = Stall(3, 0, 0)
    x = np.array([1.0, -2.0, 3.0])
    rest = [np.zeros(1), np.zeros(0), np.zeros(3), np.zeros(0), np.zeros(0)]
    assert s.eval([x] + rest) == [0]
    for _ in range(9):
        assert s.eval([x + 1e-13] + rest) == [0] and not s.stalled
    assert s.eval([x + 1e-6] + rest) == [0]  # moved: the count starts again
    for _ in range(9):
        assert s.eval([x + 1e-6] + rest) == [0]
    assert s.eval([x + 1e-6 + 2e-12] + rest) == [1] and s.stalled
    s.reset()
    assert not s.stalled and s.eval([x] + rest) == [0]


def test_stall_asks_the_newton_decrement_after_three_idle_iterations():
    """After EARLY = 3 idle iterations the callback asks for the Newton decrement once: below 1e-15
    it stops there, above it the count goes on to 10 (hand-made iterates and decrements)."""
    from castimate.solver.ipopt import Stall
    asked = []
    for dec, stop_at in ((1e-22, 3), (1e-9, 10)):
        s = Stall(3, 0, 0, lambda x, lam, d=dec: asked.append(d) or d)
        x = np.array([1.0, -2.0, 3.0])
        rest = [np.zeros(1), np.zeros(0), np.zeros(3), np.zeros(0), np.zeros(0)]
        assert s.eval([x] + rest) == [0]
        flags = [s.eval([x] + rest)[0] for _ in range(stop_at)]
        assert flags == [0] * (stop_at - 1) + [1] and s.stalled and s.idle == stop_at
        assert s.early == (dec if stop_at == 3 else None)  # the value that stopped it, for Solver.solve
    assert asked == [1e-22, 1e-9]  # once per solve, at the third idle iteration


def _decrement(asked, value, x, lam):
    asked.append(value)
    return value


def test_stall_settles_on_a_small_chi2_change_and_tests_a_flat_warm_start_at_once():
    """An outer iteration's refits (Stall.reset(settle, warm)), hand-made objective values f = χ²/2:
    ``settle`` 1 stops at the first iteration that changed χ² by at most 1 (here 0.4, after 100),
    recording that change; ``warm`` asks for the Newton decrement at the first iteration whose χ²
    change is round-off (2e-13 of 200), not after three idle ones, and only once per solve."""
    from castimate.solver.ipopt import Stall
    def rest(f):
        return [np.array([f]), np.zeros(0), np.zeros(3), np.zeros(0), np.zeros(0)]

    x = np.array([1.0, -2.0, 3.0])
    s = Stall(3, 0, 0)
    s.reset(settle=1.0)
    assert [s.eval([x + k] + rest(f))[0] for k, f in enumerate((100.0, 50.0))] == [0, 0] and s.settled is None
    assert s.eval([x + 2] + rest(49.8)) == [1] and s.settled == pytest.approx(0.4) and not s.stalled
    s.reset()
    assert s.settled is None and s.eval([x] + rest(100.0)) == [0] and s.eval([x + 1] + rest(99.9)) == [0]
    asked = []
    for dec, stop in ((1e-22, 1), (1e-9, 0)):
        s = Stall(3, 0, 0, functools.partial(_decrement, asked, dec))
        s.reset(warm=True)
        assert s.eval([x] + rest(100.0)) == [0] and s.eval([x + 1e-3] + rest(99.0)) == [0]  # moved: not flat
        assert s.eval([x + 2e-3] + rest(99.0 - 1e-13)) == [stop] and s.early == (dec if stop else None)
        if not stop:  # not asked again at the next flat iteration
            assert s.eval([x + 3e-3] + rest(99.0 - 2e-13)) == [0]
    assert asked == [1e-22, 1e-9]


@pytest.mark.parametrize("elimination", ["motion", "none"])
def test_a_solver_dropped_is_freed_at_once(elimination):
    """A solver that has solved is freed when its last reference goes, not at the cyclic garbage
    collector's next full pass (its stall callback holds it weakly): diagnose builds and drops one
    per score test and cross-validation fold, and on MIMU4444 exp_1 the ones waiting for that pass
    held 3.5 GB. The callback still reaches the solver's Newton decrement while it lives."""
    import gc
    import weakref

    solver = Solver(CASES["dynamic_no_process_model"]().lsq, SolverOptions(elimination=elimination))
    a = solver.solve()
    at = a.x[solver.perm] if solver.projection is None else a.x[solver.projection.cal]  # IPOPT's variables
    assert a.success and solver.stall.decrement(at, a.lam_g) == pytest.approx(solver.newton_decrement(a.x, a.lam_g))
    gone = [weakref.ref(solver), weakref.ref(solver.stall), weakref.ref(solver.assembly)]
    enabled = gc.isenabled()
    gc.disable()
    try:
        del solver
        assert [r() is None for r in gone] == [True] * 3
    finally:
        if enabled:
            gc.enable()


def test_settled_refit_continued_reaches_the_same_optimum():
    """A solve stopped by ``settle`` after its first iteration is reported unconverged (success False,
    ``settled``), and continued from there with the usual tolerance it reaches the optimum of a solve
    from the start to 1e-9, as the noise model's outer iteration does with its intermediate fits."""
    prob = CASES["dynamic_no_process_model"]()
    solver = Solver(prob.lsq)
    ref = solver.solve()
    early = solver.solve(settle=np.inf)
    assert early.settled and not early.success and early.iterations == 1 and early.message.startswith("Settled")
    assert relative(early.x, ref.x) > 1e-6  # not yet at the optimum
    polished = solver.solve(early.x, lam_g0=early.lam_g, warm=True)
    assert polished.success and not polished.settled and relative(polished.x, ref.x) < 1e-9


def test_warm_refit_at_its_optimum_stops_after_three_idle_iterations():
    """A solve started at its own optimum (a refit whose weights did not change) stops on the
    Newton decrement after 3 idle iterations, not 10, with the same optimum."""
    prob = CASES["static"]()
    solver = Solver(prob.lsq, SolverOptions(tol=1e-14))
    a = solver.solve()
    b = solver.solve(a.x, lam_g0=a.lam_g)
    assert b.success and b.iterations <= 5, (b.message, b.iterations)
    assert relative(b.x, a.x) < 1e-12


@pytest.mark.parametrize("kind", ["dynamic", "dynamic_no_process_model", "static"])
def test_hessian_left_pending_equals_the_eager_one(kind):
    """Without ``hessian`` the reduced evaluation leaves the Schur complement pending; asked for
    afterwards at the same θ it equals the one computed with the objective and gradient, also
    when the pending factors were given up in between (the covariance reuses their arrays), and
    the objective and gradient do not depend on it. (Without the shortcut: the Hessian at the
    nuisance optimum, not one Newton step before it, whatever the start.)"""
    prob = CASES[kind]()
    P = Solver(prob.lsq).projection
    P.shortcut = False
    pf = prob.lsq.layout.p0()
    theta = P.reset(prob.lsq.layout.x0(), None)
    f1, g1, S1 = P.reduced(theta, pf, None)
    P.reset(prob.lsq.layout.x0(), None)
    f2, g2, S2 = P.reduced(theta, pf, None, hessian=False)
    assert S2 is None and f2 == f1 and relative(g2, g1) < 1e-12
    np.testing.assert_array_equal(P.hessian(theta, pf, None), S1)
    P.reset(prob.lsq.layout.x0(), None)
    P.reduced(theta, pf, None, hessian=False)
    P.marginal(P.x_full(theta, P._cache["X"]), pf, None)  # noqa: SLF001 - reuses the coupling's arrays
    assert relative(P.hessian(theta, pf, None), S1) < 1e-9


@pytest.mark.parametrize("kind", ["dynamic_no_process_model", "static_quaternion"])
def test_gradient_of_every_variable_comes_from_the_gradient_assembly(kind):
    """Projection.gradient (the Newton decrement's, e.g. of a score test) assembles the objective
    and the gradient alone: bit for bit the gradient of a full assembly, which forms the Hessian
    too, and the full NLP's (elimination none) to round-off."""
    prob = CASES[kind]()
    solver, ref = Solver(prob.lsq, SolverOptions()), Solver(prob.lsq, SolverOptions(elimination="none"))
    P = solver.projection
    x = prob.lsq.layout.x0() + 1e-3 * np.random.default_rng(5).standard_normal(solver.n_x)
    pf, _ = solver.fixed_and_data(None, None)
    modes = []
    assemble = P.assemble
    P.assemble = lambda *a, **k: modes.append(a[4]) or assemble(*a, **k)
    g = P.gradient(x, pf, None)
    assert modes == ["grad"]
    th, Xs = P.split(x)
    full = assemble(th, Xs, pf, None, "full")
    np.testing.assert_array_equal(g[P.cal], full.gc)
    for fam, G in zip(P.fams, full.G):
        np.testing.assert_array_equal(g[fam.X], G)
    g_ref = ref.assembly.derivatives(ref.nlp_order(x), pf, None)[1][ref.assembly.ipos]
    assert relative(g, g_ref) < 1e-12


@pytest.mark.parametrize("kind", ["dynamic_no_process_model", "static_quaternion"])
@pytest.mark.parametrize("elimination", ["motion", "none"])
def test_newton_decrement_leaves_the_marginal_information_of_its_point(kind, elimination):
    """The score test asks for the decrement and the identifiability check at one point: the
    decrement's elimination is kept (``Solver.marginal_memo``) and is the marginal information a
    fresh solver computes there; at another point the memo is not used."""
    from castimate.solver import uncertainty
    prob = CASES[kind]()
    opts = SolverOptions(elimination=elimination)
    solver, fresh = Solver(prob.lsq, opts), Solver(prob.lsq, opts)
    x = prob.lsq.layout.x0() + 1e-3 * np.random.default_rng(3).standard_normal(solver.n_x)
    solver.newton_decrement(x, np.zeros(solver.n_constraints))
    assert solver.marginal_memo is not None
    calls = []
    original = uncertainty.eliminate
    uncertainty.eliminate = lambda *a, **k: calls.append(1) or original(*a, **k)
    try:
        S, G = solver.marginal_information(x)
        assert not calls  # from the memo
        S0, G0 = fresh.marginal_information(x)
        assert calls  # computed
        np.testing.assert_allclose(S, S0, rtol=1e-12, atol=1e-12 * np.abs(S0).max())
        np.testing.assert_array_equal(G, G0)
        assert solver.undetermined(x) == fresh.undetermined(x)
        calls.clear()
        solver.marginal_information(x + 1e-6)
        assert calls  # another point: computed again
    finally:
        uncertainty.eliminate = original


@pytest.mark.parametrize("kind", ["dynamic", "dynamic_no_process_model", "dynamic_sample_ages", "static",
                                  "static_quaternion"])
def test_gradient_first_near_the_optimum_keeps_the_reduced_objective_gradient_and_hessian(kind):
    """Once a prediction of the nuisance was converged, the next point is accepted on the gradient
    alone with the previous point's factors (no full evaluation unless the Hessian is asked for):
    φ and ∇φ equal those of the path that evaluates everything, to round-off, and the Hessian
    asked for afterwards is the full evaluation's; also with unit-norm nuisance rows (the static
    cases' pose directions)."""
    P, pf, th0 = _projection_at_optimum(kind)
    theta = th0 + 1e-7 * np.random.default_rng(2).standard_normal(P.c)
    P.reduced(th0, pf, None, hessian=False)
    anchor, last, before = P._anchor, P._last_dec, P.grad_firsts  # noqa: SLF001
    assert last <= P.grad_first_dec
    f1, g1, S1 = P.reduced(theta, pf, None, hessian=False)
    assert P.grad_firsts == before + 1 and S1 is None
    S1 = P.hessian(theta, pf, None)
    P._cache, P._anchor, P.shortcut = None, anchor, False  # noqa: SLF001
    f2, g2, S2 = P.reduced(theta, pf, None)
    assert abs(f1 - f2) < 1e-12 * (1 + abs(f2))
    assert relative(g1, g2) < 1e-9
    assert relative(S1, S2) < 1e-9


def test_motion_that_no_reading_determines_is_left_out_of_the_reduced_problem(monkeypatch):
    """At two samples every accelerometer's x (z) axis is masked and no process model ties the
    samples: the specific force along that axis has no information at all (its stage Hessian is
    singular), as on MIMU4444 exp_4 where all eight accelerometers sit on a 16 g rail. The
    projection inverts those stages on their range only; it converged to the full NLP's optimum
    (Cholesky of the singular stages had put 1e64 into the reduced Hessian: IPOPT stopped with
    Error_In_Step_Computation)."""
    import dataclasses
    import test_assembly
    from castimate.problem.dynamic import build_dynamic

    def masked(cfg, data):
        valid = {nm: np.ones((data.t.size, 3), bool) for nm in data.acc}
        for v in valid.values():
            v[11, 0] = v[23, 2] = False
        return build_dynamic(cfg, dataclasses.replace(data, acc_valid=valid))

    monkeypatch.setattr(test_assembly, "build_dynamic", masked)
    prob = dynamic_case(40, False)
    ref = Solver(prob.lsq, SolverOptions(tol=1e-12, elimination="none"))
    new = Solver(prob.lsq, SolverOptions(tol=1e-12))
    a, b = ref.solve(), new.solve()
    assert a.success and b.success, (a.message, b.message)
    assert relative(b.x, a.x) < 1e-9
    sa, sb = np.sqrt(np.diag(ref.covariance(b.x))), np.sqrt(np.diag(b.covariance))
    assert np.abs(sb / sa - 1).max() < 1e-6


def test_singular_stage_factor_is_the_pseudo_inverse_and_indefinite_stages_are_refused():
    """_Factor on hand-made 3 x 3 stages: positive definite (Cholesky), singular to rounding (the
    pseudo-inverse: Linv^T Linv = B^+), and indefinite (LinAlgError, for the damped inner solve)."""
    from castimate.solver.elimination import _Factor
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    pd = A @ A.T + np.eye(3)
    u = np.array([1.0, 2.0, 2.0]) / 3.0
    sing = 5.0 * np.outer(u, u) + 2.0 * np.outer([0, 1, -1], [0, 1, -1]) / 2
    F = _Factor([np.stack([pd, sing])])
    inv = np.swapaxes(F.Linv, 1, 2) @ F.Linv
    assert np.allclose(inv[0], np.linalg.inv(pd), rtol=1e-12, atol=1e-14)
    assert np.allclose(inv[1], np.linalg.pinv(sing), rtol=1e-12, atol=1e-14)
    v = rng.normal(size=(2, 3, 1))
    assert np.allclose(F.upper(F.lower(v))[1, :, 0], np.linalg.pinv(sing) @ v[1, :, 0])
    with pytest.raises(np.linalg.LinAlgError):
        _Factor([np.stack([pd, np.diag([1.0, 1.0, -1e-3])])])


@pytest.mark.parametrize("kind", ["static", "static_quaternion", "dynamic"])
def test_gradient_alone_at_newton_points_and_with_earlier_factors(kind):
    """The gradient alone is assembled at a Newton point of the nuisance (the shortcut) and with
    the previous point's factors (gradient first) for every kind: also with unit-norm nuisance rows
    (the static cases' pose directions, as tilt quaternions too), which take it in the factors'
    tangent basis carried to the point."""
    prob = CASES[kind]()
    solver = Solver(prob.lsq)
    P = solver.projection
    assert solver.solve().success
    assert any(f.unit for f in P.fams) == (kind != "dynamic")
    assert P.shortcuts > 0 and P.grad_firsts > 0

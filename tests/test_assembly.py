"""The solver's assembled derivatives against CasADi's own automatic differentiation.

``Solver`` assembles IPOPT's objective, gradient and exact Hessian of the Lagrangian in numpy from
compiled local functions (unstaged blocks through a sparse matrix, staged blocks stage by stage, see
``castimate.solver``). Here they must equal ``ca.gradient`` and ``ca.hessian`` of the same problem
written as one symbolic graph (``Solver.symbolic_nlp``), at a random point and for random
multipliers, on small static and dynamic problems with priors, unit-norm constraints, masked
samples, a process model and free intrinsics.
"""

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

from castimate.problem.dynamic import DynamicConfig, DynamicData, MotionSigmas, build_dynamic
from castimate.problem.triads import GroupSetting, TriadConfig
from castimate.problem.static import build_static
from castimate.simulate.dynamic import dynamic_measurements, euler_consistent, smooth_random_motion
from castimate.solver.ipopt import Solver
from castimate.problem.graph import SolverOptions

from test_static import make_case

FREE3, FIXED3 = GroupSetting(free=(True,) * 3), GroupSetting(free=(False,) * 3)


def dynamic_case(n=40, process_model=True, model: MotionSigmas | None = None):
    """4 triads (3 with gyroscopes), quaternion misalignments, a position prior, a free gain,
    masked accelerometer and gyroscope samples."""
    rng = np.random.default_rng(3)
    names = ["a", "b", "c", "d"]
    pos = np.array([[0, 0, 0], [0.03, 0, 0], [0, 0.04, 0.01], [0.02, -0.03, 0]], float)
    motion = euler_consistent(smooth_random_motion(n, 100.0, 8.0, 40.0, rng))
    Rs = np.stack([np.eye(3)] * 4)
    gyro = {"T_g": Rs, "b_g": np.zeros((4, 3)), "sigma": 1e-3, "saturation": None}
    acc, gy, _ = dynamic_measurements(motion, pos, Rs, np.zeros((4, 3)), rng, 0.02, gyro=gyro, names=names)
    quat = GroupSetting(free=(True,) * 4, initial=(1.0, 0.0, 0.0, 0.0))
    triads = []
    for i, nm in enumerate(names):
        a = {"gain": FREE3 if nm == "c" else FIXED3, "bias": FIXED3, "nonorthogonality": FIXED3,
             "misalignment": quat if i else GroupSetting(free=(False,) * 4)}
        g = {"gain": FIXED3, "bias": FREE3 if nm == "b" else FIXED3, "misalignment": FIXED3} if i < 3 else None
        ps = GroupSetting(free=(True,) * 3, prior_mean=tuple(pos[i]), prior_std=(0.01,) * 3) if nm == "d" else None
        triads.append(TriadConfig(nm, np.eye(3), a, g, pos[i] + 1e-3, ps))
    acc_valid = {"b": np.arange(n) % 7 != 3}
    gyro_valid = {"a": np.arange(n) % 5 != 1}
    data = DynamicData(motion.t, acc, {nm: np.full(3, 0.02) for nm in names}, {nm: gy[nm] for nm in names[:3]},
                       {nm: np.full(3, 1e-3) for nm in names[:3]}, acc_valid, gyro_valid)
    cfg = DynamicConfig(tuple(triads), "a", "rotation", model or MotionSigmas(), process_model=process_model)
    return build_dynamic(cfg, data)


def static_case():
    """4 triads with gyroscopes, 8 poses (unit-vector directions), a prior on one triad's gain."""
    cfg, poses, _, _ = make_case(M=4, P=8, gyro=True)
    t = cfg.triads[1]
    prior = GroupSetting(free=(True,) * 3, prior_mean=(1.0,) * 3, prior_std=(0.05,) * 3)
    cfg = replace(cfg, triads=(cfg.triads[0], replace(t, accelerometer={**t.accelerometer, "gain": prior}),
                               *cfg.triads[2:]))
    return build_static(cfg, poses)


def reference_derivatives(solver: Solver):
    """CasADi's gradient and Hessian of the Lagrangian of the solver's symbolic NLP (layout order,
    constraints in the order of ``Layout.unit_norm_rows``), as functions."""
    nlp = solver.symbolic_nlp()
    x, p = nlp["x"], nlp["p"]
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", solver.n_constraints)
    lag = lam_f * nlp["f"] + ca.dot(lam_g, nlp["g"])
    return (ca.Function("reference_objective", [x, p], [nlp["f"]]),
            ca.Function("reference_gradient", [x, p], [ca.gradient(nlp["f"], x)]),
            ca.Function("reference_hessian", [x, p, lam_f, lam_g], [ca.hessian(lag, x)[0]]))


def assembled(solver: Solver, x, p, lam_f, lam_g):
    """The solver's objective, gradient (NLP order) and upper-triangular Hessian of the Lagrangian
    as IPOPT gets them."""
    f_val, grad = solver.nlp.get_function("nlp_grad_f")(x, p)
    H = solver.nlp.get_function("nlp_hess_l")(x, p, lam_f, lam_g)
    return float(f_val), np.asarray(grad).ravel(), H


@pytest.mark.parametrize("kind", ["dynamic", "dynamic_no_process_model", "static"])
@pytest.mark.parametrize("hessian", ["exact", "gauss_newton"])
def test_assembled_derivatives_equal_casadi_ad(kind, hessian):
    prob = static_case() if kind == "static" else dynamic_case(process_model=kind == "dynamic")
    solver = Solver(prob.lsq, SolverOptions(hessian=hessian, jit=False, elimination="none"))
    assert (solver.stages is None) == (kind == "static")  # the dynamic problems are assembled by stage
    rng = np.random.default_rng(0)
    lay = prob.lsq.layout
    x = lay.x0() * (1 + 0.05 * rng.standard_normal(lay.n_x))  # layout order
    xn, perm = x[solver.perm], solver.perm  # NLP order
    pf = solver.fixed_and_data(None, None)[0]
    p = np.concatenate([pf, prob.lsq.data])  # the reference's parameters; the NLP's are the fixed values only
    lam_f, lam_g = 0.7, rng.standard_normal(solver.n_constraints)  # CasADi's constraint order
    lam = np.zeros(solver.n_constraints)
    lam[solver.constraint_order] = lam_g  # the reference's order
    f_ref, grad_ref, hess_ref = reference_derivatives(solver)

    f_val, grad, H = assembled(solver, xn, pf, lam_f, lam_g)
    assert f_val == pytest.approx(float(f_ref(x, p)), rel=1e-12)
    assert float(solver.nlp.get_function("nlp_f")(xn, pf)[0]) == pytest.approx(f_val, rel=1e-12)
    g_ref = np.asarray(grad_ref(x, p)).ravel()[perm]
    np.testing.assert_allclose(grad, g_ref, rtol=1e-10, atol=1e-10 * np.abs(g_ref).max())

    assert H.sparsity().is_triu()
    H = np.asarray(ca.densify(H))
    if hessian == "exact":
        R = np.triu(np.asarray(ca.densify(hess_ref(x, p, lam_f, lam)))[np.ix_(perm, perm)])
        np.testing.assert_allclose(H, R, rtol=1e-9, atol=1e-9 * np.abs(R).max())
    else:  # Gauss-Newton: J^T J (priors included) plus the constraints' curvature
        J, _ = solver.jacobians(x)
        curv = np.zeros(lay.n_x)
        for j, row in enumerate(solver.unit_rows):
            f = row[(row >= 0) & (row < lay.n_x)]
            curv[f] += 2 * lam[j] * lay.x_scale[f] ** 2
        expect = np.triu((lam_f * (J.T @ J).toarray() + np.diag(curv))[np.ix_(perm, perm)])
        np.testing.assert_allclose(H, expect, rtol=1e-9, atol=1e-9 * np.abs(expect).max())


@pytest.mark.parametrize("elimination", ["none", "motion"])
@pytest.mark.parametrize("kind", ["dynamic", "static"])
def test_information_is_jacobian_gram(kind, elimination):
    """The Fisher information assembled from local Jacobians equals J^T J of the full Jacobian."""
    prob = static_case() if kind == "static" else dynamic_case()
    solver = Solver(prob.lsq, SolverOptions(jit=False, elimination=elimination))
    x = prob.lsq.layout.x0() * (1 + 0.05 * np.random.default_rng(1).standard_normal(prob.lsq.layout.n_x))
    J, _ = solver.jacobians(x)
    expect = (J.T @ J).toarray()
    np.testing.assert_allclose(solver.information(x).toarray(), expect, rtol=1e-10, atol=1e-10 * np.abs(expect).max())


@pytest.mark.parametrize("elimination", ["none", "motion"])
@pytest.mark.parametrize("process_model", [True, False])
def test_marginal_information_is_schur_complement(process_model, elimination):
    """The stage-blocked elimination of the motion (sparse LU of the full information, or the
    projection's block-banded Cholesky) equals the dense Schur complement of J^T J."""
    prob = dynamic_case(process_model=process_model)
    solver = Solver(prob.lsq, SolverOptions(jit=False, elimination=elimination))
    x = prob.lsq.layout.x0() * (1 + 0.05 * np.random.default_rng(4).standard_normal(prob.lsq.layout.n_x))
    J, G = solver.jacobians(x)
    F = (J.T @ J).toarray()
    t = solver.theta
    nu = np.setdiff1d(np.arange(x.size), t)
    assert not abs(G[:, nu]).sum()  # the unit-norm rows (quaternions) are reported parameters here
    expect = F[np.ix_(t, t)] - F[np.ix_(t, nu)] @ np.linalg.solve(F[np.ix_(nu, nu)], F[np.ix_(nu, t)])
    S, G_t = solver.marginal_information(x)
    np.testing.assert_allclose(S, expect, rtol=1e-8, atol=1e-8 * np.abs(expect).max())
    np.testing.assert_allclose(G_t, G[:, t].toarray())


@pytest.mark.parametrize("elimination", ["none", "motion"])
def test_jacobian_matches_finite_differences_of_residuals(elimination):
    prob = dynamic_case()
    solver = Solver(prob.lsq, SolverOptions(jit=False, elimination=elimination))
    x = prob.lsq.layout.x0()
    J = solver.jacobians(x)[0].toarray()
    rng = np.random.default_rng(2)
    for j in rng.choice(x.size, 12, replace=False):
        e = np.zeros(x.size)
        e[j] = 1e-6
        fd = (solver.residuals(x + e) - solver.residuals(x - e)) / 2e-6
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(fd).max()))


def test_compiled_and_virtual_machine_assembly_agree(monkeypatch):
    from castimate import jit as jit_module

    monkeypatch.setattr(jit_module, "MIN_WORK", 0)  # this small case compiled all the same
    prob = dynamic_case()
    a, b = (Solver(prob.lsq, SolverOptions(jit=jit, elimination="none")) for jit in (True, False))
    if jit_module.compiler() is not None:
        assert {blk.f.rgh.class_name() for blk in a.blocks} == {"External"}
    assert {blk.f.rgh.class_name() for blk in b.blocks} == {"SXFunction"}
    x = prob.lsq.layout.x0()[a.perm]
    p = a.fixed_and_data(None, None)[0]
    lam_g = np.linspace(-1, 1, a.n_constraints)
    ha, hb = (np.asarray(s.nlp.get_function("nlp_hess_l")(x, p, 1.0, lam_g).nonzeros()) for s in (a, b))
    np.testing.assert_allclose(ha, hb, rtol=1e-13, atol=0)


def test_only_functions_with_enough_work_are_compiled(monkeypatch):
    """With jit a block's local functions are compiled to C when instances × instructions of one
    evaluation reach castimate.jit.MIN_WORK, else they stay on CasADi's virtual machine."""
    import casadi as ca
    from castimate import jit as jit_module

    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [ca.sin(x[0]) * x[1]])
    monkeypatch.setattr(jit_module, "MIN_WORK", 10 * f.n_instructions())
    assert jit_module.worth_compiling(10, f) and not jit_module.worth_compiling(9, f)
    if jit_module.compiler() is None:
        pytest.skip("no C compiler")
    prob = dynamic_case()
    # the case's works: accelerometers 624 000, process model 34 788, gyroscopes 24 840 instructions
    expected = {10**6: set(), 10**5: {"accelerometer_sample"}, 3 * 10**4: {"accelerometer_sample", "process_model"}}
    for threshold, names in expected.items():
        monkeypatch.setattr(jit_module, "MIN_WORK", threshold)
        solver = Solver(prob.lsq, SolverOptions(jit=True, elimination="none"))
        work = {blk.block.residual.name(): blk.block.n * blk.f.symbolic["rgh"].n_instructions() for blk in solver.blocks}
        compiled = {blk.block.residual.name() for blk in solver.blocks if blk.f.rgh.class_name() == "External"}
        assert compiled == {name for name, w in work.items() if w >= threshold}
        assert compiled == names, work


def test_chunked_evaluation_equals_one_chunk(monkeypatch):
    """Splitting the instances into chunks (whole stage groups) changes nothing."""
    from castimate.solver import assembly as solve

    prob = dynamic_case()
    x = prob.lsq.layout.x0()
    one = Solver(prob.lsq, SolverOptions(jit=False, elimination="none"))
    monkeypatch.setattr(solve, "CHUNK", 7)  # several chunks per block, not a multiple of the triads
    many = Solver(prob.lsq, SolverOptions(jit=False, elimination="none"))
    pf, data = one.fixed_and_data(None, None)
    fa, ga, ha = one.assembly.assemble(x[one.perm], pf, data)
    fb, gb, hb = many.assembly.assemble(x[many.perm], pf, data)
    ha, hb = one.assembly.hessian_values(ha), many.assembly.hessian_values(hb)
    assert fa == pytest.approx(fb, rel=1e-13)
    np.testing.assert_allclose(ga, gb, rtol=1e-12, atol=1e-12 * np.abs(ga).max())
    np.testing.assert_allclose(ha, hb, rtol=1e-12, atol=1e-12 * np.abs(ha).max())


@pytest.mark.parametrize("elimination", ["none", "motion"])
def test_masked_samples_are_not_residuals(elimination):
    prob = dynamic_case()
    solver = Solver(prob.lsq, SolverOptions(jit=False, elimination=elimination))
    n = prob.n_samples
    masked = int((np.arange(n) % 7 == 3).sum() + (np.arange(n) % 5 == 1).sum())
    full = 3 * n * 4 + 3 * n * 3 + 12 * (n - 1)  # wiener3: 12 process rows
    assert solver.n_data_residuals == full - 3 * masked
    J, _ = solver.jacobians(prob.lsq.layout.x0())
    assert J.shape[0] == solver.n_residuals == solver.residuals(prob.lsq.layout.x0()).size


def test_projection_compiled_virtual_machine_and_chunks_agree(monkeypatch):
    """The projection's reduced objective, gradient and Hessian: compiled and on CasADi's virtual
    machine, with the instances split into chunks that are not a multiple of the triads, and
    with each instance's entries scattered in numpy instead of a stage group's summed in the
    stage functions; the information too."""
    import castimate.solver.elimination as elimination
    from castimate import jit as jit_module

    monkeypatch.setattr(jit_module, "MIN_WORK", 0)  # this small case compiled all the same
    prob = dynamic_case()
    pf = prob.lsq.layout.p0()
    x0 = prob.lsq.layout.x0()

    def reduced(jit, stage_functions=True):
        P = Solver(prob.lsq, SolverOptions(jit=jit)).projection
        assert bool(P.stage_fns) == stage_functions
        if stage_functions and jit_module.compiler() is not None:
            assert all(f.class_name() == ("External" if jit else "MXFunction")
                       for s in P.stage_fns for f in s.fns.values())
        out = P.reduced(P.reset(x0, None), pf, None)
        return out + P.marginal(x0, pf, None)[:1]

    a, b = reduced(True), reduced(False)
    monkeypatch.setattr(elimination, "CHUNK", 7)
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 7)
    c = reduced(False)
    monkeypatch.setattr(elimination._StageFunctions, "applies", staticmethod(lambda sb: False))  # noqa: SLF001
    d = reduced(True, stage_functions=False)
    for other in (b, c, d):
        assert other[0] == pytest.approx(a[0], rel=1e-13)
        for u, v in zip(a[1:], other[1:]):
            np.testing.assert_allclose(v, u, rtol=1e-11, atol=1e-11 * np.abs(u).max())


@pytest.mark.parametrize("misalignment", ["rotation", "small_angle"])
def test_exact_local_hessian_matches_finite_differences(misalignment):
    """The local exact Hessian built as J^T J plus the second-order sum (``exact_hessian``) of an
    accelerometer factor with every input free, against central differences of its gradient
    J^T r and against CasADi's ``hessian`` of 1/2 |r|^2, at a random point."""
    from castimate.problem.dynamic import accelerometer_sample_factor
    from castimate.solver.assembly import exact_hessian
    from types import SimpleNamespace
    fn = accelerometer_sample_factor(SimpleNamespace(misalignment=misalignment, effects=()))
    z, d = ca.SX.sym("z", fn.size1_in(0)), ca.SX.sym("d", fn.size1_in(1))
    r = fn(z, d)
    J = ca.jacobian(r, z)
    H = exact_hessian(r, z, ca.mtimes(J.T, J))
    f = ca.Function("f", [z, d], [ca.mtimes(J.T, r), H, ca.hessian(0.5 * ca.sumsqr(r), z)[0]])
    rng = np.random.default_rng(5)
    z0, d0 = rng.standard_normal(z.numel()), rng.standard_normal(d.numel())
    d0[3:6] = 0.5 + rng.random(3)  # σ > 0
    _, H0, H_ad = (np.asarray(ca.densify(v)) for v in f(z0, d0))
    h = 1e-6
    fd = np.column_stack([(np.asarray(f(z0 + h * e, d0)[0]) - np.asarray(f(z0 - h * e, d0)[0])).ravel() / (2 * h)
                          for e in np.eye(z.numel())])
    scale = np.abs(H0).max()
    assert np.abs(fd - H0).max() < 1e-6 * scale
    assert np.abs(H_ad - H0).max() < 1e-12 * scale
    assert np.abs(H0 - H0.T).max() == 0.0


@pytest.mark.parametrize("process_model", [True, False])
def test_projection_residuals_by_stage_equal_the_reference(process_model):
    """The projection's residual vector (whole staged blocks a stage group at a time through the
    stage functions, the calibration inputs gathered once) equals the reference path's, instance
    by instance, at a random point, masked samples included, and with other data."""
    prob = dynamic_case(process_model=process_model)
    lay = prob.lsq.layout
    x = lay.x0() * (1 + 0.05 * np.random.default_rng(4).standard_normal(lay.n_x))
    new, ref = Solver(prob.lsq), Solver(prob.lsq, SolverOptions(elimination="none"))
    assert any(u.stage_fns is not None and u.rows is None for u in new.projection.units)
    a, b = new.residuals(x), ref.residuals(x)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    other = prob.lsq.data * 1.01
    a, b = new.residuals(x, data=other), ref.residuals(x, data=other)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())


def _sample_ages_case():
    from test_elimination import dynamic_sample_ages
    return dynamic_sample_ages()


@pytest.mark.parametrize("case", ["dynamic", "sample_ages"])
def test_jacobian_structure_reused_at_another_point_and_data(case):
    """``Solver.jacobians`` plans its CSR at the first call; at a second point with other data the
    reused structure still gives that point's Jacobian (finite differences of the residuals there),
    canonical (sorted, unique column indices per row). With sample ages a block reads the
    neighbouring sample, at the ends the same one twice: those entries are summed."""
    prob = dynamic_case() if case == "dynamic" else _sample_ages_case()
    solver = Solver(prob.lsq, SolverOptions(jit=False))
    lay = prob.lsq.layout
    rng = np.random.default_rng(7)
    solver.jacobians(lay.x0())
    x = lay.x0() * (1 + 0.05 * rng.standard_normal(lay.n_x))
    data = prob.lsq.data * (1 + 0.01 * rng.standard_normal(prob.lsq.data.size))
    Jc = solver.jacobians(x, data=data)[0]
    J = Jc.toarray()
    ref = Jc.copy()
    ref.has_canonical_format = False
    ref.sum_duplicates()
    assert np.array_equal(ref.indices, Jc.indices) and np.array_equal(ref.indptr, Jc.indptr)
    expect = (Jc.T @ Jc).toarray()  # the Fisher information the assembly sums from the local Jacobians
    np.testing.assert_allclose(solver.information(x, data=data).toarray(), expect, rtol=1e-10,
                               atol=1e-10 * np.abs(expect).max())
    for j in rng.choice(x.size, 12, replace=False):
        e = np.zeros(x.size)
        e[j] = 1e-6
        fd = (solver.residuals(x + e, data=data) - solver.residuals(x - e, data=data)) / 2e-6
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(fd).max()))


@pytest.mark.parametrize("case", ["dynamic", "dynamic_no_process_model", "static", "sample_ages"])
def test_jacobian_plan_by_instance_equals_the_coo_pass(case, monkeypatch):
    """``Solver._plan_jacobian`` orders each instance's columns once; its plan must be the reference
    COO -> CSR pass's (``_plan_jacobian_summed``) entry for entry: the same local positions, factors,
    indices and indptr (masked samples, priors, fixed inputs). A block that reads one variable twice
    (sample ages, at the ends) takes the reference pass, which sums those entries."""
    prob = {"dynamic": dynamic_case, "dynamic_no_process_model": lambda: dynamic_case(process_model=False),
            "static": static_case, "sample_ages": _sample_ages_case}[case]()
    solver = Solver(prob.lsq, SolverOptions(jit=False))
    local = solver.assembly.local(solver.nlp_order(prob.lsq.layout.x0()), *solver.fixed_and_data(None, None), "jac")
    sizes = [J.size for J in local]
    ref = solver._plan_jacobian_summed(sizes)
    summed = []
    monkeypatch.setattr(Solver, "_plan_jacobian_summed", lambda self, s: summed.append(s) or ref)
    plan = solver._plan_jacobian(sizes)
    assert bool(summed) == (case == "sample_ages") and (ref[4] is not None) == (case == "sample_ages")
    for got, want in zip(plan[:4], ref[:4]):
        assert got.dtype == want.dtype and np.array_equal(got, want)
    assert ref[0].size > 100 and (len(solver.prior[0]) > 0 or case == "sample_ages")  # priors: their own rows
    if case.startswith("dynamic"):
        assert not solver.keep.all()  # masked samples' rows are left out


def test_entries_at_are_the_element_by_element_entries():
    """assembly.entries_at (one selection from the dense matrix) gives the same expressions as the
    entries read one by one, structural zeros included: the functions serialize identically."""
    from castimate.solver.assembly import entries_at

    x = ca.SX.sym("x", 3)
    M = ca.SX(3, 3)
    M[0, 0], M[0, 2], M[1, 1], M[2, 0], M[2, 2] = ca.sin(x[0]), x[0] * x[2], 2.5, x[2] ** 2, x[1]  # (0, 1) zero
    pairs = np.array([(0, 0), (0, 1), (1, 1), (0, 2), (2, 2), (2, 0)])
    one_by_one = ca.densify(ca.vertcat(*[M[int(a), int(b)] for a, b in pairs]))
    at = entries_at(M, pairs)
    assert at.sparsity() == ca.Sparsity.dense(len(pairs), 1)
    assert ca.Function("e", [x], [at]).serialize() == ca.Function("e", [x], [one_by_one]).serialize()
    np.testing.assert_array_equal(np.array(ca.Function("e", [x], [at])([0.3, -1.0, 2.0])).ravel(),
                                  [np.sin(0.3), 0.0, 2.5, 0.6, -1.0, 4.0])
    assert entries_at(M, np.zeros((0, 2), int)).shape == (0, 1)

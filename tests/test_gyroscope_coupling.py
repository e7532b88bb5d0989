"""The gyroscope cross-axis coupling (issue 11, item 2), added as one registry entry: its term by
hand, its derivatives, recovery of a simulated truth, the identifiability check, and (through the
generic undoing) apply and the C: tests/test_compensation.py runs every sample-wise registry entry,
this one included."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from castimate.models import effects as fx
from castimate.problem.dynamic import build_dynamic
from castimate.problem.effects import BY_KEY, DYNAMIC, NEWTON
from castimate.solver import Solver

from test_effects import assert_dynamic_jacobian_matches_finite_differences, dynamic_effect_case

KEY = "gyroscope.coupling"


def test_coupling_by_hand():
    u = ca.DM([2.0, -3.0, 5.0])
    got = np.asarray(ca.evalf(fx.coupling(ca.DM([0.01, -0.02, 0.03]), u))).ravel()
    np.testing.assert_allclose(got, [0.0, 0.01 * 2, -0.02 * 2 + 0.03 * -3], rtol=1e-15)


def test_gain_coupling_rotation_is_a_general_matrix():
    """Any 3x3 matrix with a positive determinant is C K M: its LQ decomposition (C unit lower-
    triangular, K the positive diagonal, M a rotation), which gain and rotation alone (K M) are not."""
    A = np.array([[1.01, 0.015, -0.004], [0.012, 0.98, 0.007], [-0.02, 0.003, 1.02]])  # not antisymmetric
    Q, R = np.linalg.qr(A.T)
    S = np.diag(np.sign(np.diag(R)))
    L, M = (R.T @ S), (S @ Q.T)
    K = np.diag(np.diag(L))
    C = L @ np.linalg.inv(K)
    assert np.allclose(np.triu(C, 1), 0) and np.allclose(np.diag(C), 1)
    assert np.allclose(M @ M.T, np.eye(3)) and np.linalg.det(M) > 0
    c = np.array([C[1, 0], C[2, 0], C[2, 1]])
    # the registry's term reproduces the reading C K M ω for every ω
    w = np.array([0.3, -1.2, 2.0])
    u = K @ M @ w
    got = u + np.asarray(ca.evalf(fx.coupling(ca.DM(c), ca.DM(u)))).ravel()
    np.testing.assert_allclose(got, A @ w, rtol=1e-13)
    assert np.abs(c).max() > 1e-3


def test_registry_entry():
    e = BY_KEY[KEY]
    assert e.kinds == (DYNAMIC,) and e.undoing == NEWTON and e.group.components == ("yx", "zx", "zy")


def coupling_case(n=400, seed=6, **kw):
    rng = np.random.default_rng(seed)
    names = ["imu1", "imu4", "imu6", "imu11", "imu13", "imu17", "imu23", "imu32"]  # dynamic_effect_case's
    truth = {f"{nm}.{KEY}": 0.01 * rng.standard_normal(3) for nm in names}
    return dynamic_effect_case(seed=seed, n=n, effects=truth, **kw)


def test_coupling_jacobian_matches_finite_differences():
    assert_dynamic_jacobian_matches_finite_differences(*coupling_case(n=30)[:2], ".gyroscope.coupling", 10)


def test_coupling_recovered_within_sigma():
    """Coupling of 1 % (the MIMU4444's size) on every gyroscope, the reference's included, simulated by
    the simulator's own term (simulate/effects.py), is recovered within the reported σ's, with the
    positions free and the reference gyroscope's gain fixed (the rate scale gauge)."""
    cfg, data, truth = coupling_case()
    sol = Solver(build_dynamic(cfg, data).lsq).solve()
    assert sol.success, sol.message
    z = np.concatenate([(sol.values[k] - v) / sol.std[k] for k, v in truth.items()])
    assert len(z) == 24 and np.abs(z).max() < 4.5, z
    assert abs(sol.chi2 - sol.dof) < 5 * np.sqrt(2 * sol.dof)
    assert max(sol.std[k].max() for k in truth) < 2e-3  # determined well below the effect's size


def test_coupling_undetermined_by_rotation_about_one_axis_is_named():
    """Rotation about the body z axis only: every gyroscope's x and y readings vanish (the triads map
    body z to their ±z), so nothing determines the coupling; the identifiability check that the
    dynamic kind runs before solving (Solver.undetermined) names the coupling groups."""
    from dataclasses import replace

    def about_z(m):
        keep = np.array([0.0, 0.0, 1.0])
        return replace(m, omega=m.omega * keep, omega_dot=m.omega_dot * keep)

    cfg, data, _ = coupling_case(n=60, reshape_motion=about_z, position_free=False)
    assert all(np.allclose(np.abs(t.R_nominal[:, 2]), [0, 0, 1]) for t in cfg.triads)
    from castimate.problem.dynamic import OMEGA, OMEGA_DOT, initial_motion

    start = initial_motion(cfg, data, cfg.names)  # gyro-aided, as the kind starts; without the noise's x, y
    start = {k: start[k] * [0.0, 0.0, 1.0] for k in (OMEGA, OMEGA_DOT)}
    solver = Solver(build_dynamic(cfg, data, start).lsq)
    bad = solver.undetermined(solver.problem.layout.x0())
    assert bad and all(".gyroscope.coupling[" in b for b in bad), bad


def test_problem_files_include_it_and_the_rate_scale_gauge_is_named(tmp_path):
    """``gyroscope: {coupling: free}`` in a dynamic problem file; with every gyroscope gain free too
    (the reference's included) the rate scale is a gauge (ω -> aω, r -> r/a²), and the kind refuses
    the problem naming the undetermined directions. The static kind has no such effect."""
    from castimate.errors import InputError
    from castimate.kinds.dynamic import calibrate_dynamic
    from castimate.spec import load_problem
    from test_dynamic import dynamic_problem

    for d in ("a", "b"):
        (tmp_path / d).mkdir()
    spec = load_problem(dynamic_problem(tmp_path / "a", model__gyroscope={"coupling": "free", "bias": "fixed"}))
    assert KEY in spec.model.effects
    path = dynamic_problem(tmp_path / "b", model__gyroscope={"gain": "free", "coupling": "free", "bias": "fixed"})
    with pytest.raises(InputError, match="the data cannot determine") as e:
        calibrate_dynamic(load_problem(path))
    assert e.value.where == "model"
    static = tmp_path / "s.yaml"
    static.write_text("kind: static_array\nseed: 1\ntriads: 3\nposes: 12\ngyroscope: true\n")
    from castimate.cli import main
    assert main(["simulate", str(static), "-o", str(tmp_path / "sim")]) == 0
    import yaml
    prob = yaml.safe_load((tmp_path / "sim" / "problem.yaml").read_text())
    prob.setdefault("model", {})["gyroscope"] = {"coupling": "free"}
    (tmp_path / "sim" / "problem.yaml").write_text(yaml.safe_dump(prob))
    with pytest.raises(InputError, match="coupling"):
        load_problem(tmp_path / "sim" / "problem.yaml")

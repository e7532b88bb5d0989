"""The static array problem on simulated data: recovery of known truth, parameterisations,
a cross-check of two solvers, and re-solving with other fixed values without a rebuild."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.optimize

from castimate.problem.triads import ACCELEROMETER_GROUPS, GYROSCOPE_GROUPS, GroupSetting, TriadConfig
from castimate.problem.static import StaticConfig, build_static
from castimate.prepare.poses import pose_averages_from_means
from castimate.simulate.static import pose_directions, random_static_truth, static_pose_means
from castimate.solver.ipopt import Solver

FREE, FIXED = GroupSetting(free=(True,) * 3), GroupSetting(free=(False,) * 3)
SIGMA, N_SAMPLES = 0.01, 1000


def make_case(M=6, P=20, seed=0, gyro=False, direction="unit_vector", misalignment="small_angle"):
    rng = np.random.default_rng(seed)
    names = [f"imu{i + 1}" for i in range(M)]
    truth = random_static_truth(names, "imu1", rng, gyroscope=gyro)
    U = pose_directions(P, rng)
    mis = FREE if misalignment == "small_angle" else GroupSetting(free=(True,) * 4)
    acc = {"gain": FREE, "bias": FREE, "nonorthogonality": FREE, "misalignment": mis}
    gy = {"gain": FIXED, "bias": FREE, "misalignment": FIXED} if gyro else None
    cfg = StaticConfig(tuple(TriadConfig(n, np.eye(3), acc, gy) for n in names), "imu1", truth.gravity,
                       direction, misalignment)
    a, g = static_pose_means(truth, U, SIGMA, N_SAMPLES, rng, SIGMA / 5 if gyro else None)
    poses = pose_averages_from_means(a, N_SAMPLES, SIGMA, g or None, SIGMA / 5 if gyro else None)
    return cfg, poses, truth, U


def solve(cfg, poses):
    prob = build_static(cfg, poses)
    solver = Solver(prob.lsq)
    return prob, solver, solver.solve()


def test_recovers_truth_within_reported_sigma():
    cfg, poses, truth, _ = make_case(gyro=True)
    prob, solver, sol = solve(cfg, poses)
    assert sol.success and sol.iterations < 20
    z = np.concatenate([(sol.values[k] - v) / sol.std[k] for k, v in truth.values.items()])
    # 6 triads x 15 parameters: all within 4.5 sigma (false alarm probability < 1e-3)
    assert np.abs(z).max() < 4.5, z
    assert 0.5 < np.std(z) < 1.5
    # chi2 of the whitened residual follows chi2(dof): within 5 standard deviations
    assert abs(sol.chi2 - sol.dof) < 5 * np.sqrt(2 * sol.dof)


@pytest.mark.parametrize("direction", ["quaternion", "pitch_roll"])
def test_direction_parameterisations_reach_the_same_optimum(direction):
    cfg, poses, _, _ = make_case(seed=2)
    _, _, ref = solve(cfg, poses)
    _, _, sol = solve(replace(cfg, gravity_direction=direction), poses)
    assert sol.success
    assert np.isclose(sol.cost, ref.cost, rtol=1e-9)
    for k, v in ref.values.items():
        if not k.startswith("pose"):
            assert np.allclose(sol.values[k], v, atol=1e-7), k
            assert np.allclose(sol.std[k], ref.std[k], rtol=1e-4), k


def test_full_rotation_misalignment_matches_small_angle_truth():
    cfg, poses, truth, _ = make_case(seed=3, misalignment="rotation")
    prob, solver, sol = solve(cfg, poses)
    assert sol.success
    cal = prob.calibration(sol.values)
    for n in cfg.names:
        assert np.isclose(np.linalg.norm(sol.values[f"{n}.accelerometer.misalignment"]), 1)
        # T differs from truth by O(xi^2) ~ 1e-4 (second-order term the small-angle truth lacks)
        assert np.abs(cal[n][0] - truth.T(n)).max() < 3e-4
        assert np.abs(cal[n][1] - truth.b(n)).max() < 5 * SIGMA / np.sqrt(N_SAMPLES) * 10


def test_ipopt_and_scipy_least_squares_agree():
    """Two solvers on one problem: IPOPT (exact Hessian) and scipy's trust-region least squares,
    both on the CasADi residual with pitch/roll directions (no constraints)."""
    cfg, poses, _, _ = make_case(M=4, seed=4, direction="pitch_roll")
    prob, solver, sol = solve(replace(cfg, gravity_direction="pitch_roll"), poses)
    lay = prob.lsq.layout
    ls = scipy.optimize.least_squares(lambda x: solver.residuals(x), lay.x0(),
                                      jac=lambda x: solver.jacobians(x)[0].toarray(), method="trf", xtol=1e-15,
                                      ftol=1e-15, gtol=1e-12)
    assert ls.success
    assert np.isclose(ls.cost, sol.cost, rtol=1e-10)
    assert np.allclose(ls.x, sol.x, atol=1e-7)


def test_residual_jacobian_matches_finite_differences():
    cfg, poses, _, _ = make_case(M=3, seed=5, gyro=True)
    prob = build_static(cfg, poses)
    solver = Solver(prob.lsq)
    x0 = prob.lsq.layout.x0()
    J = solver.jacobians(x0)[0].toarray()
    h = 1e-6
    rng = np.random.default_rng(0)
    for i in rng.choice(len(x0), 15, replace=False):
        e = np.zeros_like(x0)
        e[i] = h
        fd = (solver.residuals(x0 + e) - solver.residuals(x0 - e)) / (2 * h)
        assert np.allclose(J[:, i], fd, rtol=1e-6, atol=1e-5 * max(1, np.abs(fd).max())), prob.lsq.layout.x_labels[i]


def test_fixed_values_are_parameters_not_rebuilt():
    """A fixed group lives in p: re-solving with another fixed value needs no rebuild and moves the fit."""
    cfg, poses, truth, _ = make_case(M=3, seed=6)
    fixed_gain = GroupSetting(free=(False,) * 3)
    t2 = replace(cfg.triads[1], accelerometer={**cfg.triads[1].accelerometer, "gain": fixed_gain})
    cfg = replace(cfg, triads=(cfg.triads[0], t2, cfg.triads[2]))
    prob = build_static(cfg, poses)
    solver = Solver(prob.lsq)
    lay = prob.lsq.layout
    at_one = solver.solve()
    at_truth = solver.solve(p_fixed=lay.p0({"imu2.accelerometer.gain": truth.values["imu2.accelerometer.gain"]}))
    assert np.allclose(at_truth.values["imu2.accelerometer.gain"], truth.values["imu2.accelerometer.gain"])
    assert at_truth.std["imu2.accelerometer.gain"].max() == 0
    # the true gain explains the data; a unit gain leaves a large chi2
    assert at_truth.chi2 < 2 * at_truth.dof < at_one.chi2


def test_gyroscope_bias_is_the_weighted_mean():
    cfg, poses, truth, _ = make_case(M=2, seed=7, gyro=True)
    _, _, sol = solve(cfg, poses)
    for n in cfg.names:
        assert np.allclose(sol.values[f"{n}.gyroscope.bias"], poses.gyro_mean[n].mean(axis=0), atol=1e-10)
        assert np.allclose(sol.std[f"{n}.gyroscope.bias"], SIGMA / 5 / np.sqrt(N_SAMPLES * 20), rtol=1e-6)


def test_static_groups_tables_are_consistent():
    assert set(ACCELEROMETER_GROUPS) == {"gain", "bias", "nonorthogonality", "misalignment"}
    assert set(GYROSCOPE_GROUPS) == {"gain", "bias", "misalignment"}

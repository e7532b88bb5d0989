"""Gyroscope calibration from the rotations between static poses (Tedaldi 2014): the per-sample
exponential, the factor's derivatives, the simulator's exact rotations, recovery of the truth and
the refusals."""

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import expm

from castimate.errors import InputError
from castimate.io.readers import write_npz
from castimate.models.rotation import rotate_back
from castimate.problem.static import StaticConfig
from castimate.problem.transitions import normal_bases, transition_factor
from castimate.simulate.static import StaticTruthScale, pose_directions, random_static_truth, static_time_series


def _skew(a):
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def test_rotate_back_is_the_exponential():
    w, u = ca.SX.sym("w", 3), ca.SX.sym("u", 3)
    f = ca.Function("f", [w, u], [rotate_back(w, u)])
    rng = np.random.default_rng(0)
    for theta in (0.0, 1e-6, 0.05, 0.3, 0.5):
        a = rng.standard_normal(3)
        a *= theta / np.linalg.norm(a)
        x = rng.standard_normal(3)
        np.testing.assert_allclose(np.array(f(a, x)).ravel(), expm(_skew(a)).T @ x, atol=3e-11)


def test_transition_factor_derivatives_match_finite_differences():
    fn = transition_factor(StaticConfig((), "imu"))
    rng = np.random.default_rng(1)
    u0 = np.array([0.3, -0.2, 0.93])
    u0 /= np.linalg.norm(u0)
    z = np.concatenate([1 + 0.01 * rng.standard_normal(3), 0.01 * rng.standard_normal(3),
                        0.02 * rng.standard_normal(3), u0, u0 + 0.01])
    d = np.concatenate([[0.5, -1.0, 2.0], [0.01], np.eye(3).ravel(), [1e-4], normal_bases(u0[None])[0]])
    zs = ca.SX.sym("z", len(z))
    J = np.array(ca.Function("J", [zs], [ca.jacobian(fn(zs, d), zs)])(z))
    r = lambda z: np.array(fn(z, d)).ravel()  # noqa: E731
    h = 1e-6
    Jfd = np.column_stack([(r(z + h * e) - r(z - h * e)) / (2 * h) for e in np.eye(len(z))])
    np.testing.assert_allclose(J, Jfd, rtol=1e-6, atol=1e-6 * np.abs(J).max())


def _session(tmp_path, seed=7, poses=10, heading_swing=0.8, extra_model=""):
    rng = np.random.default_rng(seed)
    truth = random_static_truth(["imu"], "imu", rng, gyroscope=True,
                                scale=StaticTruthScale(gyro_gain=0.01, gyro_misalignment=0.01))
    rec, iv = static_time_series(truth, pose_directions(poses, rng), 0.02, rng, rate=100, pose_duration=3.0,
                                 transition=1.5, gyro_sigma=0.003, heading_swing=heading_swing)
    write_npz(tmp_path / "data.npz", rec)
    segs = ", ".join(f"[{a + 0.3:.2f}, {b - 0.3:.2f}]" for a, b in iv)
    p = tmp_path / "problem.yaml"
    p.write_text(f"kind: static_array\ndata: {{path: data.npz, format: npz, segments: [{segs}]}}\n"
                 "array: {reference: imu, triads: [{name: imu}]}\n"
                 f"model: {{gyroscope: {{gain: free, misalignment: free{extra_model}}}}}\n")
    return p, truth, rec, iv


def test_simulated_rotations_are_exact_for_the_integration(tmp_path):
    """Noise-free rates of the simulator (closed-form, sampled mid-interval, with a heading swing that
    makes the body axis wander) integrated sample by sample carry each pose's direction to the next
    to 1e-4 rad (the O(Δt²) error of a mid-interval sample; the gyroscope noise of a transition
    here is about 4e-4 rad), where one exponential of the summed rates is off by far more."""
    rng = np.random.default_rng(2)
    truth = random_static_truth(["imu"], "imu", rng, gyroscope=True,
                                scale=StaticTruthScale(gyro_gain=0.01, gyro_misalignment=0.01))
    U = pose_directions(5, rng)
    rec, iv = static_time_series(truth, U, 0.0, rng, rate=100, pose_duration=2.0, transition=1.5,
                                 gyro_sigma=0.0, heading_swing=1.0)
    w = (rec.gyro["imu"] - truth.values["imu.gyroscope.bias"]) @ np.linalg.inv(truth.Tg("imu")).T
    for n in range(4):
        k0, k1 = int(round(iv[n][1] * 100)), int(round(iv[n + 1][0] * 100))
        u = U[n]
        for k in range(k0 - 1, k1):
            u = expm(_skew(w[k] * 0.01)).T @ u
        assert np.linalg.norm(np.cross(u, U[n + 1])) < 1e-4
        summed = expm(_skew(w[k0 - 1:k1].sum(axis=0) * 0.01)).T @ U[n]
        assert np.linalg.norm(np.cross(summed, U[n + 1])) > 1e-2


def test_recovers_simulated_gyroscope_truth(tmp_path):
    from castimate.kinds.static import calibrate_static
    from castimate.spec import load_problem

    p, truth, _, _ = _session(tmp_path)
    out = calibrate_static(load_problem(p))
    sol = out.solution
    assert sol.success
    for g in ("gain", "misalignment", "bias"):
        k = f"imu.gyroscope.{g}"
        z = (sol.values[k] - truth.values[k]) / sol.std[k]
        assert np.abs(z).max() < 4, (g, z)
    assert sol.std["imu.gyroscope.gain"].max() < 2e-3  # the transitions determine the gain well


def test_static_poses_alone_leave_the_gain_undetermined(tmp_path):
    from castimate.kinds.static import check_identifiable, pose_averages, static_config, load_recording
    from castimate.problem.static import build_static
    from castimate.solver import Solver
    from castimate.spec import load_problem

    p, *_ = _session(tmp_path, poses=6)
    spec = load_problem(p)
    avg, _ = pose_averages(spec, load_recording(spec))
    problem = build_static(static_config(spec, avg)[0], avg)
    with pytest.raises(InputError, match="cannot determine.*gyroscope"):
        check_identifiable(spec.path, problem, Solver(problem.lsq), avg)


def test_refuses_gyroscope_effects_with_transitions(tmp_path):
    from castimate.kinds.static import calibrate_static
    from castimate.spec import load_problem

    p, *_ = _session(tmp_path, poses=6, extra_model=", bias_drift: free")
    with pytest.raises(InputError, match="model.gyroscope.bias_drift: is not modelled during the rotations"):
        calibrate_static(load_problem(p))


def test_refuses_a_turn_too_fast_for_the_sample_rate(tmp_path):
    from castimate.kinds.static import calibrate_static
    from castimate.spec import load_problem

    p, truth, rec, iv = _session(tmp_path, poses=6)
    k = int(round(iv[0][1] * 100)) + 20
    rec.gyro["imu"][k] = [60.0, 0, 0]  # 0.6 rad in one 10 ms sample
    write_npz(tmp_path / "data.npz", rec)
    with pytest.raises(InputError, match="gyroscope of imu: turns 0.60 rad in one sample"):
        calibrate_static(load_problem(p))

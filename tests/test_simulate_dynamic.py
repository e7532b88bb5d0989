"""The dynamic-array simulator: rigid-body kinematics, motion consistency, geometries, saturation."""

import numpy as np
import pytest

from castimate.simulate.dynamic import CARLSSON_BOTTOM_ROTATION, carlsson_geometry, dynamic_measurements, integrate_attitude, quaternion_multiply, quaternion_to_matrix, rigid_body_motion, schopp_geometry, smooth_random_motion, specific_force_at

DEG = np.pi / 180
W_MAX, WDOT_MAX = 2000 * DEG, 2000 * DEG  # Carlsson 2017, Fig. 4


@pytest.fixture(scope="module")
def carlsson_motion():
    return smooth_random_motion(1000, 100.0, W_MAX, WDOT_MAX, np.random.default_rng(1))


def test_specific_force_hand_computed():
    w, a, d = 3.0, 5.0, 0.2
    s = np.array([[0.1, -0.2, 9.81]])
    r = np.array([d, 0.0, 0.0])
    f = specific_force_at(s, [[0, 0, w]], [[0, 0, 0]], r)
    np.testing.assert_allclose(f, s + [-w * w * d, 0, 0])  # centripetal: −w² d x̂
    f = specific_force_at(s, [[0, 0, 0]], [[0, 0, a]], r)
    np.testing.assert_allclose(f, s + [0, a * d, 0])  # Euler: a d ŷ
    # a rate along r has no centripetal effect; vectorised over samples and positions
    f = specific_force_at(np.zeros((4, 3)), np.tile([w, 0, 0], (4, 1)), np.zeros((4, 3)), r)
    np.testing.assert_allclose(f, 0, atol=1e-15)
    F = specific_force_at(s, [[0, 0, w]], [[0, 0, a]], np.array([[[d, 0, 0]], [[0, d, 0]]]))
    assert F.shape == (2, 1, 3)
    np.testing.assert_allclose(F[1, 0], s[0] + [-a * d, -w * w * d, 0])


def test_omega_dot_is_derivative_of_omega(carlsson_motion):
    m = carlsson_motion
    h = m.t[1] - m.t[0]
    central = (m.omega[2:] - m.omega[:-2]) / (2 * h)
    # central-difference error ≤ h²/6 max|ω'''|; ω''' estimated from second differences of ω̇
    third = np.abs(m.omega_dot[2:] - 2 * m.omega_dot[1:-1] + m.omega_dot[:-2]).max() / h ** 2
    tol = h ** 2 / 6 * third * 1.5 + 1e-9
    assert np.abs(central - m.omega_dot[1:-1]).max() <= tol
    assert tol < 1e-3 * WDOT_MAX  # the check is not vacuous


def test_bounds_and_directions(carlsson_motion):
    m = carlsson_motion
    wn = np.linalg.norm(m.omega, axis=1)
    wdn = np.linalg.norm(m.omega_dot, axis=1)
    assert abs(wn.max() / W_MAX - 1) < 0.05
    assert wdn.max() <= WDOT_MAX * (1 + 1e-9)
    assert m.binding == "omega_dot" and wdn.max() > 0.99 * WDOT_MAX
    for v in (m.omega, m.omega_dot):
        u = v / np.linalg.norm(v, axis=1, keepdims=True)
        assert np.linalg.eigvalsh(u.T @ u / len(u))[0] > 0.05
    # a gentle bound on ω̇ is not binding: ω is, and ω̇ stays below
    m2 = smooth_random_motion(300, 100.0, 2.0, 500.0, np.random.default_rng(2))
    assert m2.binding == "omega"
    assert np.isclose(np.linalg.norm(m2.omega, axis=1).max(), 2.0)
    assert np.linalg.norm(m2.omega_dot, axis=1).max() <= 500.0


def test_attitude_and_specific_force_consistent(carlsson_motion):
    m = carlsson_motion
    R = quaternion_to_matrix(m.attitude)
    np.testing.assert_allclose(np.linalg.norm(m.attitude, axis=1), 1, atol=1e-12)
    # s = Rᵀ(a + g ẑ); the linear acceleration is ~ linear_accel
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, m.s) - m.accel_world, np.tile([0, 0, 9.81], (len(m), 1)),
                               atol=1e-12)
    assert np.isclose(np.linalg.norm(m.accel_world, axis=1).max(), 2.0)
    # the rotation between consecutive samples, q_n⁻¹ ⊗ q_n+1, is the integral of ω (trapezoid rule,
    # whose error ~ h³(|ω̈| + |ω×ω̇|)/12 is below 1e-3 of the increment ‖ω‖h)
    h = m.t[1] - m.t[0]
    conj = m.attitude[:-1] * [1, -1, -1, -1]
    dq = quaternion_multiply(conj, m.attitude[1:])
    dq *= np.sign(dq[:, :1])
    vn = np.linalg.norm(dq[:, 1:], axis=1, keepdims=True)
    rotvec = 2 * np.arctan2(vn, dq[:, :1]) * dq[:, 1:] / vn
    trapezoid = h * (m.omega[:-1] + m.omega[1:]) / 2
    assert np.abs(rotvec - trapezoid).max() < 1e-3 * W_MAX * h


def test_static_body_reads_gravity():
    m = smooth_random_motion(50, 100.0, 0.0, 0.0, np.random.default_rng(3), linear_accel=0.0)
    assert np.all(m.omega == 0) and np.all(m.omega_dot == 0)
    R = quaternion_to_matrix(m.attitude)
    np.testing.assert_allclose(m.s, R.transpose(0, 2, 1) @ np.array([0, 0, 9.81]), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(m.s, axis=1), 9.81)
    np.testing.assert_allclose(m.s, np.tile(m.s[0], (50, 1)), atol=1e-12)  # it does not move
    # every triad of a static array reads gravity whatever its position
    np.testing.assert_allclose(m.specific_force_at([0.1, -0.2, 0.3]), m.s)


def test_constant_rate_attitude_closed_form():
    w, u = 30.0, np.array([1.0, 2.0, -2.0]) / 3
    q0 = np.array([np.cos(0.3), np.sin(0.3), 0, 0])
    t = np.arange(200) / 100.0
    q = integrate_attitude(lambda tt: np.tile(w * u, (len(tt), 1)), t, q0)
    exact = quaternion_multiply(q0, np.column_stack([np.cos(w * t / 2), np.sin(w * t / 2)[:, None] * u]))
    assert np.abs(np.abs(np.sum(q * exact, axis=1)) - 1).max() < 1e-12  # same rotation, up to sign
    np.testing.assert_allclose(quaternion_to_matrix(q), quaternion_to_matrix(exact), atol=1e-8)
    # the same through rigid_body_motion: a body spinning about the vertical keeps s = g ẑ
    m = rigid_body_motion(t, lambda tt: np.tile([0, 0, w], (len(tt), 1)), lambda tt: np.zeros((len(tt), 3)))
    np.testing.assert_allclose(m.s, np.tile([0, 0, 9.81], (len(t), 1)), atol=1e-9)


def test_carlsson_geometry():
    names, nominal, true, rot = carlsson_geometry(np.random.default_rng(4))
    assert len(names) == 32 and nominal.shape == true.shape == (32, 3) and set(rot) == set(names)
    for side, z in ((slice(0, 16), 1e-3), (slice(16, 32), -1e-3)):
        P = nominal[side]
        np.testing.assert_allclose(P[:, 2], z)
        np.testing.assert_allclose(P[:, :2].mean(axis=0), 0, atol=1e-15)
        for k in range(2):
            np.testing.assert_allclose(np.diff(np.unique(np.round(P[:, k], 9))), 6.3e-3)
    for n, R in rot.items():
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
        assert np.isclose(np.linalg.det(R), 1)
    np.testing.assert_array_equal(rot["imu17"], CARLSSON_BOTTOM_ROTATION)
    err = true - nominal
    assert 0.5e-3 < err.std() < 1.5e-3
    _, _, true0, _ = carlsson_geometry(np.random.default_rng(4), position_error=0.0)
    np.testing.assert_array_equal(true0, nominal)


def test_schopp_geometry():
    names, nominal, true, rot, true_rot = schopp_geometry(np.random.default_rng(5), position_error=1e-3,
                                                          orientation_error_deg=1.0, reference="acc1")
    assert names == ["acc1", "acc2", "acc3", "acc4", "acc5"]
    np.testing.assert_allclose(nominal[0], [0.0007, -0.0024, 0.0387])
    np.testing.assert_allclose(nominal[4], [-0.1194, 0.0029, 0.0251])
    np.testing.assert_allclose(nominal[:, 2], [0.0387, 0.0247, 0.0250, 0.0251, 0.0251])
    np.testing.assert_array_equal(true[0], nominal[0])
    assert np.all(np.abs(true[1:] - nominal[1:]) < 6e-3)
    for n in names:
        np.testing.assert_array_equal(rot[n], np.eye(3))
        R = true_rot[n]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
        assert angle < 6 and (angle > 0) == (n != "acc1")


def test_measurements_and_saturation():
    rng = np.random.default_rng(6)
    m = smooth_random_motion(200, 100.0, 2200 * DEG, 4000 * DEG, rng)
    P = np.array([[0.01, 0, 0], [0, -0.02, 0.003]])
    T = np.stack([np.eye(3), np.diag([1.01, 0.99, 1.0]) @ CARLSSON_BOTTOM_ROTATION])
    b = np.array([[0.1, 0, -0.1], [0, 0.2, 0]])
    sat = 2000 * DEG
    gyro = {"T_g": np.stack([np.eye(3)] * 2), "b_g": np.zeros((2, 3)), "sigma": 0.0, "saturation": sat}
    acc, gy, mask = dynamic_measurements(m, P, T, b, rng, 0.0, gyro=gyro, names=["a", "b"])
    assert set(acc) == set(gy) == set(mask) == {"a", "b"}
    np.testing.assert_allclose(acc["b"], specific_force_at(m.s, m.omega, m.omega_dot, P[1]) @ T[1].T + b[1])
    over = np.abs(m.omega) >= sat
    assert over.any() and not over.all()  # some axis exceeds 2000 °/s
    np.testing.assert_array_equal(mask["a"], over)
    np.testing.assert_allclose(gy["a"][over], np.sign(m.omega[over]) * sat)
    np.testing.assert_allclose(gy["a"][~over], m.omega[~over])
    # noise has the requested σ
    acc_n, gy_n, _ = dynamic_measurements(m, P, T, b, rng, 0.04, gyro={**gyro, "saturation": None, "sigma": 0.001})
    assert 0.03 < np.std(acc_n["imu1"] - acc["a"]) < 0.05
    assert 0.0008 < np.std(gy_n["imu1"] - m.omega) < 0.0012
    with pytest.raises(ValueError):
        dynamic_measurements(m, P, T, b, rng, 0.0, gyro={"T": np.eye(3), "b_g": 0, "sigma": 0})

"""Hand-computed cases for each symbolic model function, and derivatives against finite differences."""

import casadi as ca
import numpy as np
import pytest

from castimate.models import rotation as rot
from castimate.models import triad as tri
from castimate.problem.static import recover_nominal_rotation, tilt_quaternion


def ev(expr):
    return np.asarray(ca.DM(ca.evalf(expr)) if isinstance(expr, (ca.SX, ca.MX)) else ca.DM(expr))


def test_skew_is_cross_product():
    a, b = np.array([1.0, -2.0, 3.0]), np.array([0.5, 4.0, -1.0])
    assert np.allclose(ev(rot.skew(ca.DM(a))) @ b, np.cross(a, b))


def test_small_angle_rotation_by_hand():
    # I + [xi]x for xi = (0.01, 0.02, 0.03): off-diagonals are +-xi_k
    M = ev(rot.small_angle_rotation(ca.DM([0.01, 0.02, 0.03])))
    assert np.allclose(M, [[1, -0.03, 0.02], [0.03, 1, -0.01], [-0.02, 0.01, 1]])


def test_quaternion_rotation_by_hand():
    # 90 deg about z: q = (cos 45, 0, 0, sin 45) maps x to y
    c = np.sqrt(0.5)
    R = ev(rot.quaternion_to_rotation(ca.DM([c, 0, 0, c])))
    assert np.allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    q = np.array([0.3, -0.5, 0.7, 0.2])
    q /= np.linalg.norm(q)
    R = ev(rot.quaternion_to_rotation(ca.DM(q)))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
    assert np.allclose(rot.rotation_to_quaternion(R), q if q[0] > 0 else -q)


def test_nonorthogonality_and_gain_by_hand():
    L = ev(tri.nonorthogonality_matrix(ca.DM([0.1, 0.2, 0.3])))
    assert np.allclose(L, [[1, 0, 0], [0.1, 1, 0], [0.2, 0.3, 1]])
    K = ev(tri.gain_matrix(ca.DM([1.1, 0.9, 1.0])))
    assert np.allclose(K, np.diag([1.1, 0.9, 1.0]))
    # y = T f + b: T = K L, f = g e_x -> column 0 of K L times g, plus b
    y = ev(tri.triad_output(ca.DM(K @ L), ca.DM([0.1, 0.2, 0.3]), tri.static_specific_force(9.81, ca.DM([1, 0, 0]))))
    assert np.allclose(y.ravel(), [1.1 * 9.81 + 0.1, 0.9 * 0.1 * 9.81 + 0.2, 0.2 * 9.81 + 0.3])


def test_pitch_roll_direction_by_hand():
    # Nilsson 2014: s(phi, psi) = [-sin phi, cos phi sin psi, cos phi cos psi]
    s = ev(rot.pitch_roll_direction(np.pi / 6, np.pi / 4)).ravel()
    assert np.allclose(s, [-0.5, np.cos(np.pi / 6) * np.sqrt(0.5), np.cos(np.pi / 6) * np.sqrt(0.5)])


@pytest.mark.parametrize("u", [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, -0.4, 0.866], [-0.6, 0.0, -0.8]])
def test_tilt_quaternion_reproduces_direction(u):
    u = np.asarray(u, float) / np.linalg.norm(u)
    q = tilt_quaternion(u)
    assert q[3] == 0 and np.isclose(np.linalg.norm(q), 1)
    assert np.allclose(ev(rot.tilt_quaternion_direction(ca.DM(q))).ravel(), u)


def test_axis_rotations_and_recovery():
    assert len(rot.axis_rotations()) == 24
    rng = np.random.default_rng(0)
    body = rng.standard_normal((20, 3)) * 9.81
    A = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1]], float)  # MIMU4444 bottom-side mounting
    small = np.eye(3) + np.array([[0, -0.01, 0.005], [0.01, 0, -0.02], [-0.005, 0.02, 0]])
    R_found, resid = recover_nominal_rotation(body, body @ (small @ A).T + 0.01 * rng.standard_normal((20, 3)))
    assert np.array_equal(R_found, A) and resid < 2.0


def test_triad_jacobian_matches_finite_differences():
    """The exact derivatives CasADi gives IPOPT agree with central differences."""
    k, l, xi, b, u = (ca.SX.sym(n, 3) for n in "klxbu")
    T = ca.mtimes([tri.gain_matrix(k), tri.nonorthogonality_matrix(l), rot.small_angle_rotation(xi)])
    z = ca.vertcat(k, l, xi, b, u)
    y = tri.triad_output(T, b, tri.static_specific_force(9.81, u))
    f = ca.Function("f", [z], [y])
    J = ca.Function("J", [z], [ca.jacobian(y, z)])
    rng = np.random.default_rng(1)
    z0 = np.concatenate([1 + 0.01 * rng.standard_normal(3), 0.01 * rng.standard_normal(9), rng.standard_normal(3)])
    h = 1e-6
    fd = np.column_stack([(np.asarray(f(z0 + h * e)) - np.asarray(f(z0 - h * e))).ravel() / (2 * h)
                          for e in np.eye(len(z0))])
    assert np.allclose(np.asarray(J(z0)), fd, rtol=1e-7, atol=1e-7)

"""Rotations: skew matrices, small angles, unit quaternions, directions.

Conventions (DESIGN.md): Hamilton quaternions, scalar first, unit norm. ``R`` maps a vector from
the body frame to the triad frame.
"""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np


def skew(a):
    """Skew-symmetric matrix [a]x with [a]x b = a x b (Nilsson 2014, footnote 1)."""
    return ca.vertcat(
        ca.horzcat(0, -a[2], a[1]),
        ca.horzcat(a[2], 0, -a[0]),
        ca.horzcat(-a[1], a[0], 0),
    )


def small_angle_rotation(xi):
    """First-order rotation I + [xi]x for small misalignment angles xi [rad] (Nilsson 2014, sec. II)."""
    return ca.DM.eye(3) + skew(xi)


def quaternion_to_rotation(q):
    """Rotation matrix of the unit quaternion q = (w, x, y, z), Hamilton convention.

    Uses the homogeneous form, which stays a rotation for |q| = 1 and is quadratic in q so that
    the exact Hessian is cheap.
    """
    w, x, y, z = q[0], q[1], q[2], q[3]
    return ca.vertcat(
        ca.horzcat(w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)),
        ca.horzcat(2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)),
        ca.horzcat(2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z),
    )


def pitch_roll_direction(phi, psi):
    """Unit direction s(phi, psi) = [-sin phi, cos phi sin psi, cos phi cos psi] (Nilsson 2014, sec. II).

    phi is the pitch and psi the roll [rad] of the specific force direction in the body frame.
    """
    return ca.vertcat(-ca.sin(phi), ca.cos(phi) * ca.sin(psi), ca.cos(phi) * ca.cos(psi))


def tilt_quaternion_direction(q):
    """Direction of the specific force for a body tilted by the unit quaternion q.

    ``R(q)^T e_z``: the up direction of the world seen in the body frame. Heading about the vertical
    is unobservable from gravity, so callers fix q_z = 0 to remove that gauge.
    """
    return ca.mtimes(quaternion_to_rotation(q).T, ca.DM([0, 0, 1]))


def rotate_back(w, u):
    """exp([w]x)^T u: a vector fixed in the world seen from the body after it turned by the rotation
    vector w (body frame) [rad].

    Closed form (Rodrigues): exp([w]x) = I + a [w]x + c [w]x^2 with a = sin θ / θ and
    c = (1 - cos θ) / θ^2, θ = |w|, so exp([w]x)^T u = u - a (w x u) + c (w x (w x u)). a and c are
    evaluated by their Taylor series in θ^2 up to θ^8 (smooth at θ = 0, no square root), whose
    truncation error is below 3e-11 for θ < 0.5 rad: exact in double precision for any per-sample
    turn a gyroscope can measure at a usual rate.
    """
    t2 = ca.dot(w, w)
    a = 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42 * (1 - t2 / 72)))
    c = 0.5 * (1 - t2 / 12 * (1 - t2 / 30 * (1 - t2 / 56 * (1 - t2 / 90))))
    wu = ca.cross(w, u)
    return u - a * wu + c * ca.cross(w, wu)


#: Largest per-sample rotation [rad] for which :func:`rotate_back`'s series is exact to 3e-11.
ROTATE_BACK_MAX_ANGLE = 0.5


# ---------------------------------------------------------------------------------------------
# Numeric helpers (numpy): initialisation and the recovery of nominal mounting rotations.
# ---------------------------------------------------------------------------------------------

def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix, w >= 0."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.empty(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q, dtype=float)
    return q if q[0] >= 0 else -q


def axis_rotations() -> list[np.ndarray]:
    """The 24 proper rotations that map coordinate axes onto coordinate axes."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def wahba_rotation(body: np.ndarray, triad: np.ndarray) -> np.ndarray:
    """The rotation R minimising sum |triad_n - R body_n|^2 (Kabsch / Wahba), vectors as rows."""
    U, _, Vt = np.linalg.svd(np.asarray(triad).T @ np.asarray(body))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def nearest_axis_rotation(R: np.ndarray) -> np.ndarray:
    """The axis-aligned rotation closest to R (circuit boards mount sensors at multiples of 90 deg)."""
    return max(axis_rotations(), key=lambda A: float(np.trace(A.T @ R)))


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))

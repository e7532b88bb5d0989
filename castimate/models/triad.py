"""Sensor triad models (Nilsson 2014, eqs. 1-3; DESIGN.md conventions).

Accelerometer triad:  y = K L M Rbar f + b + v
Gyroscope triad:      y = K_g M_g Rbar_g w + b_g + v

K = diag(k) is the gain, L the unit lower-triangular non-orthogonality, M the misalignment
rotation (I + [xi]x to first order, or R(q)), Rbar the nominal mounting rotation (body -> triad).
The first three rows of L put the x sensitivity axis along x and the y axis in the x-y plane,
which is what defines the body frame on the reference triad.
"""

from __future__ import annotations

import casadi as ca

#: Names of the non-orthogonality components: L[1,0], L[2,0], L[2,1]. Component "yx" is the
#: sensitivity of the y axis to force along x. (Nilsson's l = [l_yz, l_zy, l_zx] in this order.)
NONORTHOGONALITY_COMPONENTS = ("yx", "zx", "zy")


def gain_matrix(k):
    """K = diag(k) (Nilsson 2014, eq. 1); k is dimensionless."""
    return ca.diag(k)


def nonorthogonality_matrix(l):
    """L = unitri(l): unit lower-triangular, l = (L10, L20, L21) in rad (Nilsson 2014, eq. 1)."""
    return ca.vertcat(
        ca.horzcat(1, 0, 0),
        ca.horzcat(l[0], 1, 0),
        ca.horzcat(l[1], l[2], 1),
    )


def triad_output(T, b, f):
    """Noise-free triad reading y = T f + b: T (3x3) maps the body-frame input f to the triad, b the bias."""
    return ca.mtimes(T, f) + b


def static_specific_force(g, u):
    """Specific force of a static body: magnitude g [m/s^2] along the unit up-direction u (body frame)."""
    return g * u

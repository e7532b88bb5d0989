"""Additional sensor effects: one pure symbolic function each.

Each function returns the term an effect adds to a triad's noise-free reading (sensor frame, the
triad's own units), so a measurement model is ``y = T f + b + Σ effect terms``. The effects are
the usual suspects of MEMS inertial sensors beyond the Nilsson 2014 model (gain, bias,
non-orthogonality, misalignment):

- a bias that drifts with time or with temperature (polynomial, :func:`polynomial`);
- a gain that varies with temperature (:func:`relative_gain_change`);
- a quadratic scale nonlinearity per axis (:func:`scale_nonlinearity`);
- per-axis sensing-element offsets inside an accelerometer triad, the "size effect"
  (:func:`axis_offsets`);
- the age of a triad's sample: a chip's constant age, drifting or a sawtooth at the beat between the
  chip's clock and the board's read-out, and a gyroscope's delay behind its accelerometer
  (:func:`sample_age`);
- the g-sensitivity of a gyroscope (:func:`g_sensitivity`);
- the cross-axis coupling of a gyroscope (:func:`coupling`).

Arguments are CasADi symbols or numbers; nothing here knows about problems or data.
"""

from __future__ import annotations

import casadi as ca
import numpy as np


def polynomial(c, m1, m2):
    """c1 m1 + c2 m2 per axis, c = [c1 (3), c2 (3)]: a bias polynomial in a regressor x, with the
    regressor's first and second moments m1 = mean(x), m2 = mean(x²) over the averaging interval.

    With x the normalised time τ ∈ [-1, 1] this is the bias drift; with x the temperature minus
    its session mean it is the temperature dependence of the bias. Using the interval moments makes
    the term exact for pose averages (for a single sample, m2 = m1²).
    """
    return c[0:3] * m1 + c[3:6] * m2


def relative_gain_change(c, m1, m2, u):
    """(c1 x + c2 x²) ⊙ u: a gain that changes with a regressor x (temperature), acting on the
    noise-free sensor-frame reading u = T f. Same moment convention as :func:`polynomial`."""
    return polynomial(c, m1, m2) * u


def scale_nonlinearity(k2, u):
    """k2 ⊙ u²: quadratic scale nonlinearity of each axis [1/(m/s²)], u = T f the linear reading."""
    return k2 * u ** 2


def axis_offsets(T, delta, omega, omega_dot):
    """Size effect: the y and z sensing elements of an accelerometer triad sit at δ_y, δ_z (body
    frame, m) from the x element, which is at the triad's position r.

    Axis i then senses the specific force at r + δ_i, which adds e_iᵀ T (ω×(ω×δ_i) + ω̇×δ_i) to
    its reading (Carlsson 2017 eq. 1 applied per axis); delta = [δ_y (3), δ_z (3)].
    """
    def extra(d):
        return ca.mtimes(T, ca.cross(omega, ca.cross(omega, d)) + ca.cross(omega_dot, d))

    return ca.vertcat(0, extra(delta[0:3])[1], extra(delta[3:6])[2])


def sensing_elements(r, delta):
    """Positions (3×3, rows: the x, y, z sensing elements; body frame, m) of an accelerometer triad at
    r with the sensing-element offsets delta = [δ_y (3), δ_z (3)] of :func:`axis_offsets` (numbers)."""
    r, delta = np.asarray(r, float), np.asarray(delta, float)
    return np.stack([r, r + delta[0:3], r + delta[3:6]])


def along_sensing_axes(r, delta, R):
    """The triad's position taken coordinate by coordinate from the sensing element that measures it:
    body coordinate c from the element whose sensing axis (row of the nominal rotation R, the reading
    being T R f) is closest to body axis c. That element's readings carry −|ω⊥|² p_c, the centripetal
    term along its own axis; its coordinates across that axis rest on the tangential and cross terms
    (ω̇×p, ω_c ω_c' p_c') alone. With :func:`axis_offsets` free, r is the x element's position, so
    the coordinates of r across the x element's axis are of the second kind (issue 11, exp_1's
    in-plane ratio)."""
    P = sensing_elements(r, delta)
    element = np.argmax(np.abs(np.asarray(R, float)), axis=0)  # per body axis c, the element sensing along it
    return P[element, np.arange(3)]


def sample_age(age, h_dot, h_ddot=None):
    """−a ḣ + ½ a² ḧ: a triad whose sample is a [s] old when the board reads it returns
    h(t − a) ≈ h(t) − a ḣ(t) + ½ a² ḧ(t) (Taylor to second order; first order where ḧ is None), ḣ and ḧ
    the time derivatives of its noise-free reading. ``age`` is the triad's whole age: the second-order
    term of a sum of ages is not the sum of theirs. The age of a chip sampling on its own clock is a
    sawtooth a(t) = A (frac(ν t + φ) − ½) at the beat ν between the chip's clock and the board's
    read-out (issue 11); a clock-rate drift makes it linear in time; a constant age and a gyroscope's
    filter delay behind its accelerometer are constants. At 1.5 ms and 2·10⁴ rad/s³ (fast hand
    twisting) the second-order term is 0.02 rad/s, several gyroscope σ's."""
    first = -age * h_dot
    return first if h_ddot is None else first + 0.5 * age ** 2 * h_ddot


def g_sensitivity(G, f):
    """G f: the linear-acceleration sensitivity of a gyroscope [rad/s per m/s²], G (9,) row-major
    3×3, f the specific force in the gyroscope's frame."""
    return ca.mtimes(ca.reshape(G, 3, 3).T, f)


def coupling(c, u):
    """(C - I) u: cross-axis coupling of a gyroscope triad, C = unitri(c) unit lower-triangular like
    the accelerometer's non-orthogonality L (Nilsson 2014, eq. 1), c = (C10, C20, C21) = (yx, zx, zy):
    the y axis reads c_yx times the x axis's reading, the z axis c_zx and c_zy times x's and y's.

    The reading is then C K_g M_g R̄ ω: gain times coupling (a lower-triangular matrix) times a
    rotation is a general 3×3 matrix (its LQ decomposition), which gain and rotation alone cannot
    express (issue 11: on MIMU4444 exp_1 a full matrix lowers χ²/dof by about a third).
    """
    return ca.vertcat(0, c[0] * u[0], c[1] * u[0] + c[2] * u[1])

"""Additional sensor effects: one pure symbolic function each.

Each function returns the term an effect adds to a triad's noise-free reading (sensor frame, the
triad's own units), so a measurement model is ``y = T f + b + Σ effect terms``. The effects are
the usual suspects of MEMS inertial sensors beyond the Nilsson 2014 model (gain, bias,
non-orthogonality, misalignment):

- a bias that drifts with time or with temperature (polynomial, :func:`polynomial`);
- a gain that varies with temperature (:func:`relative_gain_change`);
- a quadratic scale nonlinearity per axis (:func:`scale_nonlinearity`);
- per-axis sensing-element offsets inside an accelerometer triad, the "size effect"
  (:func:`axis_offsets`), per triad in the body frame or shared by every chip of one model in the
  chip's own frame (:func:`chip_axis_offsets`);
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


def chip_to_body(Rbar, d):
    """[R̄ᵀ d_y, R̄ᵀ d_z]: sensing-element offsets d = [d_y (3), d_z (3)] given in a chip's own frame
    (m), as the body-frame offsets δ of :func:`axis_offsets` of a triad mounted with the nominal
    rotation R̄ (body -> triad). CasADi symbols or numbers (then a numpy array)."""
    if isinstance(Rbar, (ca.SX, ca.MX, ca.DM)) or isinstance(d, (ca.SX, ca.MX, ca.DM)):
        return ca.vertcat(ca.mtimes(Rbar.T, d[0:3]), ca.mtimes(Rbar.T, d[3:6]))
    R, d = np.asarray(Rbar, float), np.asarray(d, float).ravel()
    return np.concatenate([R.T @ d[0:3], R.T @ d[3:6]])


def chip_axis_offsets(T, Rbar, d, omega, omega_dot):
    """Size effect of a chip model: its y and z sensing elements sit at d_y, d_z (the chip's own frame,
    m) from its x element, the same in every chip of that model. A triad mounted with the nominal
    rotation R̄ (body -> triad) then has the body-frame offsets R̄ᵀ d (:func:`chip_to_body`), and the
    physics is that of :func:`axis_offsets`.

    Shared by every triad of a board, d cannot absorb a per-triad scale difference as per-triad
    offsets can (issue 11: on MIMU4444 the per-triad offsets grow with the distance from the
    reference triad). With free positions the data leave some directions of d undetermined
    (:func:`chip_offsets_gauge`): on a board with chips on both sides, d_z."""
    return axis_offsets(T, chip_to_body(Rbar, d), omega, omega_dot)


def chip_offsets_gauge(rotations, free_positions=None, tol: float = 1e-9) -> np.ndarray:
    """(m, 6) orthonormal rows: the directions of the chip-frame offsets d of :func:`chip_axis_offsets`
    that a board of triads with the nominal rotations ``rotations`` (body -> triad) cannot determine,
    with the specific force s free per sample and the positions ``free_positions`` ((K, 3) bool; default
    all but the first triad's) free.

    Each element senses along its axis a = R̄ᵀ e_j at p = r + δ_j: a (ω, ω̇)-dependent reading
    aᵀ (s + L p), L = [ω]×² + [ω̇]× (which spans every 3×3 matrix over a motion). The undetermined changes
    are the (d, Δr_k, V) with aᵀ L (Δr_k + Δδ_j) = aᵀ V vec(L) for every element and L, s changed by
    V vec(L): for instance all z-sensing elements moved together, which moves d_z and, through the
    bottom-side chips' x and y elements, d_y and their positions. Triads of one mounting leave all of d
    to s; the MIMU4444's two sides leave the 3 directions Δd_z arbitrary with Δd_y = (I − R̄_bottom) Δd_z,
    so only d_y − (I − R̄_bottom) d_z is determined."""
    Rs = [np.asarray(R, float) for R in rotations]
    K = len(Rs)
    free = np.ones((K, 3), bool) if free_positions is None else np.asarray(free_positions, bool)
    if free_positions is None:
        free[0] = False
    pos = [(k, c) for k in range(K) for c in range(3) if free[k, c]]
    n = 6 + len(pos) + 27  # d, the free position components, V (3 x 9)
    rows = []
    for k, R in enumerate(Rs):
        for j in range(3):
            a = R[j]  # the element's sensing axis in the body frame
            for i in range(9):
                L = np.eye(9)[i].reshape(3, 3)
                row = np.zeros(n)
                aL = a @ L
                if j > 0:
                    row[3 * (j - 1):3 * j] = aL @ R.T  # aᵀ L R̄ᵀ Δd_j
                for m, (kk, c) in enumerate(pos):
                    if kk == k:
                        row[6 + m] = aL[c]
                row[6 + len(pos) + np.arange(3) * 9 + i] = -a  # -aᵀ V e_i
                rows.append(row)
    _, sv, Vt = np.linalg.svd(np.array(rows))
    sv = np.concatenate([sv, np.zeros(n - len(sv))])
    null = Vt[sv <= tol * max(sv.max(), 1.0)][:, :6]
    if not len(null):
        return np.zeros((0, 6))
    U, w, _ = np.linalg.svd(null.T, full_matrices=False)
    return U[:, w > tol].T


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

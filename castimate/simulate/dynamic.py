"""Ground-truth sessions for the dynamic array models (Carlsson 2017, Schopp 2016), in numpy.

A smooth random rigid-body motion is built in closed form, so that ω̇ is the exact derivative of ω
at every sample, and the attitude is integrated from ω with RK4 on a fine sub-grid. Accelerometer
triads read the specific force at their own position,

    f = s + ω×(ω×r) + ω̇×r,        y = T f + b + v,

and gyroscope triads read y_g = T_g ω + b_g + v, clipped at the saturation level like an ADC. The
measurements can be made messy as real ones are: each sensor reading the motion at its own delayed
instant (evaluated exactly from the closed-form motion), pink (1/f) noise on top of the white, and an
ADC of a given resolution whose rails are asymmetric (int16: −32768 … +32767 counts).

Conventions (DESIGN.md): SI units; ω, ω̇ and s in the body frame; Hamilton quaternions, scalar
first, for the body→world rotation; s is the specific force at the body origin including gravity,
s = Rᵀ(a − g_world) with g_world = (0, 0, −g), so a body at rest reads +g along the world's up axis.

This module is an independent numpy implementation (no CasADi), meant as the reference that the
symbolic models are checked against.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ..models.rotation import rotation_to_quaternion
from . import effects as fx
from .effects import sensed_specific_force, shifted
from .static import random_rotation

GRAVITY = 9.81

# Carlsson 2017, sec. IV / MIMU4444 board: 4x4 grid on each side of the PCB.
CARLSSON_PITCH = 6.3e-3  # m, spacing in x and y
CARLSSON_HALF_THICKNESS = 1.0e-3  # m, top side at +1 mm, bottom side at -1 mm (2 mm apart)
CARLSSON_BOTTOM_ROTATION = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

# Schopp 2016, Table I: reference positions of the five triads [cm].
SCHOPP_POSITIONS_CM = np.array([[0.07, -0.24, 3.87],
                                [0.28, 11.89, 2.47],
                                [11.93, -0.28, 2.50],
                                [-0.27, -11.94, 2.51],
                                [-11.94, 0.29, 2.51]])


# ---------------------------------------------------------------------------------------------
# Rigid-body kinematics and quaternions (numpy)
# ---------------------------------------------------------------------------------------------

def specific_force_at(s, omega, omega_dot, r) -> np.ndarray:
    """Specific force at position r of a rigid body: f = s + ω×(ω×r) + ω̇×r.

    All arguments are arrays with a last axis of 3 that broadcast against each other, e.g.
    s, omega, omega_dot (N, 3) and r (3,) -> (N, 3), or r (K, 1, 3) -> (K, N, 3).
    """
    s, omega, omega_dot, r = (np.asarray(x, dtype=float) for x in (s, omega, omega_dot, r))
    return s + np.cross(omega, np.cross(omega, r)) + np.cross(omega_dot, r)


def quaternion_multiply(p, q) -> np.ndarray:
    """Hamilton product p ⊗ q of (..., 4) arrays, scalar first."""
    p, q = np.asarray(p, dtype=float), np.asarray(q, dtype=float)
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    v = pw * qv + qw * pv + np.cross(pv, qv)
    return np.concatenate([w, v], axis=-1)


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) (Hamilton, scalar first)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def rotation_vector_to_matrix(phi) -> np.ndarray:
    """Rotation matrix exp([φ]×) of a rotation vector φ (3,) [rad] (Rodrigues)."""
    phi = np.asarray(phi, dtype=float)
    angle = np.linalg.norm(phi)
    if angle < 1e-12:
        return np.eye(3)
    k = phi / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _omega_matrix(omega: np.ndarray) -> np.ndarray:
    """(M, 4, 4) matrices A with ½ q ⊗ (0, ω) = A q (right multiplication by a pure quaternion)."""
    x, y, z = omega[:, 0], omega[:, 1], omega[:, 2]
    o = np.zeros_like(x)
    A = np.stack([o, -x, -y, -z,
                  x, o, z, -y,
                  y, -z, o, x,
                  z, y, -x, o], axis=-1).reshape(-1, 4, 4)
    return 0.5 * A


def integrate_attitude(omega_fn: Callable[[np.ndarray], np.ndarray], t: np.ndarray, q0=None,
                       max_angle_step: float = 0.02) -> np.ndarray:
    """Body→world attitude at the times t, integrated from the body rate ω(t) with classical RK4.

    q̇ = ½ q ⊗ (0, ω). ``omega_fn`` is a vectorised callable (M,) -> (M, 3), evaluated on a fine
    sub-grid: each sample interval is split so that ‖ω‖ h ≤ ``max_angle_step`` rad, which puts the
    RK4 error of a constant rate far below 1e-9 rad per second. The quaternion is renormalised after
    every step. Returns (N, 4) unit quaternions (scalar first), attitude[0] = q0 (identity if None).
    """
    t = np.asarray(t, dtype=float)
    q = np.array([1.0, 0, 0, 0]) if q0 is None else np.asarray(q0, dtype=float) / np.linalg.norm(q0)
    out = np.empty((len(t), 4))
    out[0] = q
    if len(t) < 2:
        return out
    dt = np.diff(t)
    w_max = np.max(np.linalg.norm(omega_fn(t), axis=1))
    n_sub = max(2, int(np.ceil(w_max * 1.2 * np.max(dt) / max_angle_step)))
    # Fine grid with half steps: nodes 0, h/2, h, ... per interval (RK4 needs ω at t, t+h/2, t+h).
    frac = np.arange(2 * n_sub) / (2 * n_sub)
    tf = np.concatenate([(t[:-1, None] + dt[:, None] * frac[None]).ravel(), t[-1:]])
    A = _omega_matrix(np.asarray(omega_fn(tf), dtype=float))
    h = np.repeat(dt / n_sub, n_sub)[:, None, None]  # one per sub-step
    A1, A2, A3 = A[0:-1:2], A[1::2], A[2::2]
    eye = np.eye(4)
    B1 = eye + 0.5 * h * A1
    B2 = eye + 0.5 * h * A2 @ B1
    B3 = eye + h * A2 @ B2
    M = eye + h / 6 * (A1 + 2 * A2 @ B1 + 2 * A2 @ B2 + A3 @ B3)  # one RK4 step of the linear ODE
    M = M.reshape(len(dt), n_sub, 4, 4)
    for i in range(len(dt)):
        for j in range(n_sub):
            q = M[i, j] @ q
        q = q / np.linalg.norm(q)
        out[i + 1] = q
    return out


# ---------------------------------------------------------------------------------------------
# Motion
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Motion:
    """A sampled rigid-body motion. Body frame unless stated; SI units.

    t (N,) [s]; omega (N, 3) [rad/s]; omega_dot (N, 3) [rad/s²], the exact derivative of omega;
    s (N, 3) [m/s²], specific force at the body origin including gravity; attitude (N, 4), unit
    quaternions of the body→world rotation (Hamilton, scalar first); accel_world (N, 3) [m/s²],
    the acceleration of the origin in the world frame; binding says which bound set the scale of
    a random motion ("omega" or "omega_dot"); ``at`` (optional) evaluates the motion exactly at any
    times, (M,) -> (ω, ω̇, s) (M, 3) each, where it is known in closed form (else None: only the samples);
    omega_ddot (N, 3) [rad/s³] and s_dot (N, 3) [m/s³], the exact derivatives, where the motion gives
    them in closed form (else None).
    """

    t: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    s: np.ndarray
    attitude: np.ndarray
    accel_world: np.ndarray | None = None
    gravity: float = GRAVITY
    binding: str = ""
    at: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
    omega_ddot: np.ndarray | None = None  # (N, 3) rad/s³, where known in closed form
    s_dot: np.ndarray | None = None  # (N, 3) m/s³, where known in closed form

    def __len__(self) -> int:
        return len(self.t)

    def rotation_matrices(self) -> np.ndarray:
        """Body→world rotation matrices (N, 3, 3)."""
        return quaternion_to_matrix(self.attitude)

    def specific_force_at(self, r) -> np.ndarray:
        """Specific force (N, 3) at a body position r (3,)."""
        return specific_force_at(self.s, self.omega, self.omega_dot, r)

    def shifted_state(self, dt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ω, ω̇, s) at the times t + dt (dt a number or (N,)): exact where the motion is in closed form
        (:attr:`at`), else by cubic-spline interpolation of the samples."""
        if not np.any(dt):
            return self.omega, self.omega_dot, self.s
        if self.at is not None:
            return self.at(self.t + dt)
        return tuple(shifted(self.t, x, dt) for x in (self.omega, self.omega_dot, self.s))


def rigid_body_motion(t, omega_fn, omega_dot_fn, accel_fn=None, q0=None, gravity: float = GRAVITY,
                      binding: str = "") -> Motion:
    """A Motion from closed-form ω(t), ω̇(t) (body frame) and a(t) (world frame, None for zero).

    The attitude is integrated from ``omega_fn`` (see integrate_attitude) and
    s = Rᵀ (a − g_world), g_world = (0, 0, −gravity). ``Motion.at`` evaluates the same motion at any
    times (:func:`exact_state`).
    """
    t = np.asarray(t, dtype=float)
    attitude = integrate_attitude(omega_fn, t, q0)
    a = np.zeros((len(t), 3)) if accel_fn is None else np.asarray(accel_fn(t), dtype=float)
    R = quaternion_to_matrix(attitude)
    s = np.einsum("nji,nj->ni", R, a + np.array([0.0, 0.0, gravity]))

    def at(tq):
        return exact_state(tq, t, attitude, omega_fn, omega_dot_fn, accel_fn, gravity)

    return Motion(t=t, omega=np.asarray(omega_fn(t), dtype=float), omega_dot=np.asarray(omega_dot_fn(t), dtype=float),
                  s=s, attitude=attitude, accel_world=a, gravity=gravity, binding=binding, at=at)


def exact_state(tq, t, attitude, omega_fn, omega_dot_fn, accel_fn=None, gravity: float = GRAVITY
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ω, ω̇, s) (M, 3) of a closed-form motion at any times tq (M,): ω and ω̇ from their formulas, s =
    Rᵀ (a + (0, 0, g)) with the attitude carried from the nearest sample of ``t``/``attitude`` to tq by
    RK4 sub-steps on ω(t) (each turning at most 0.005 rad: error far below 1e-9 rad)."""
    tq = np.asarray(tq, dtype=float)
    i = np.clip(np.searchsorted(t, tq), 1, len(t) - 1) if len(t) > 1 else np.zeros(len(tq), int)
    if len(t) > 1:
        i = np.where(np.abs(tq - t[i - 1]) <= np.abs(tq - t[i]), i - 1, i)
    span = tq - t[i]
    w_max = np.max(np.linalg.norm(omega_fn(np.concatenate([t, tq])), axis=1)) if len(tq) else 0.0
    steps = max(1, int(np.ceil(w_max * np.max(np.abs(span), initial=0.0) / 0.005)))
    h, q, tk = span / steps, attitude[i].copy(), t[i].copy()

    def qdot(q, tt):
        w = np.asarray(omega_fn(tt), dtype=float)
        return 0.5 * quaternion_multiply(q, np.concatenate([np.zeros((len(tt), 1)), w], axis=1))

    for _ in range(steps):
        k1 = qdot(q, tk)
        k2 = qdot(q + 0.5 * h[:, None] * k1, tk + 0.5 * h)
        k3 = qdot(q + 0.5 * h[:, None] * k2, tk + 0.5 * h)
        k4 = qdot(q + h[:, None] * k3, tk + h)
        q = q + h[:, None] / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        tk = tk + h
    a = np.zeros((len(tq), 3)) if accel_fn is None else np.asarray(accel_fn(tq), dtype=float)
    s = np.einsum("nji,nj->ni", quaternion_to_matrix(q), a + np.array([0.0, 0.0, gravity]))
    return np.asarray(omega_fn(tq), dtype=float), np.asarray(omega_dot_fn(tq), dtype=float), s


def _wandering_axis(rng: np.random.Generator, bandwidth: float):
    """Unit-peak rate w(τ) = Ω(τ) u(τ) and its derivative w'(τ), in closed form.

    The axis u(τ) = Q Rz(ατ + φ1) Rx(βτ + φ2) e_z sweeps a great circle that itself turns about a
    second axis, so over a few turns it covers the whole sphere (Q uniformly random). The magnitude
    Ω(τ) = (1 + μ sin(2π f τ + φ)) / (1 + μ) never vanishes, like a hand twisting back and forth
    at speed; ‖u'‖ ≤ sqrt(α² + β²).
    """
    Q = random_rotation(rng)
    rho = 2 * np.pi * bandwidth * rng.uniform(0.3, 1.0)
    gamma = rng.uniform(np.deg2rad(25), np.deg2rad(65))
    alpha, beta = rho * np.sin(gamma) * rng.choice([-1, 1]), rho * np.cos(gamma) * rng.choice([-1, 1])
    phi1, phi2, phi_m = rng.uniform(0, 2 * np.pi, 3)
    mu = rng.uniform(0.1, 0.4)
    f_m = bandwidth * rng.uniform(0.2, 1.0)

    def parts(tau):
        tau = np.asarray(tau, dtype=float)
        psi, th = alpha * tau + phi1, beta * tau + phi2
        sp, cp, st, ct = np.sin(psi), np.cos(psi), np.sin(th), np.cos(th)
        u = np.stack([st * sp, -st * cp, ct], axis=-1) @ Q.T
        du = (alpha * np.stack([st * cp, st * sp, 0 * st], axis=-1)
              + beta * np.stack([ct * sp, -ct * cp, -st], axis=-1)) @ Q.T
        arg = 2 * np.pi * f_m * tau + phi_m
        mag = (1 + mu * np.sin(arg)) / (1 + mu)
        dmag = mu * 2 * np.pi * f_m * np.cos(arg) / (1 + mu)
        return u, du, mag, dmag

    def w(tau):
        u, _, mag, _ = parts(tau)
        return mag[:, None] * u

    def dw(tau):
        u, du, mag, dmag = parts(tau)
        return dmag[:, None] * u + mag[:, None] * du

    return w, dw


def smooth_random_motion(n_samples: int, rate: float, max_omega: float, max_omega_dot: float,
                         rng: np.random.Generator, linear_accel: float = 2.0, *, bandwidth: float = 2.0,
                         q0=None, gravity: float = GRAVITY) -> Motion:
    """A smooth random rigid-body motion sampled at ``rate`` Hz (body-frame ω, ω̇, s).

    ω(t) = c·w(λt) with w(τ) = Ω(τ)·u(τ): a magnitude that never vanishes (Ω ∈ [(1−μ)/(1+μ), 1],
    μ ~ U(0.1, 0.4)) times an axis u that sweeps a great circle which itself turns about a second,
    random axis, at rates ~ 2π·[0.3, 1]·bandwidth rad/s for λ = 1. So the directions of ω and ω̇
    cover the sphere (positions observable) once the record lasts a few radians of axis travel.
    ω̇ = c·λ·w'(λt) is the analytic derivative, exact at every sample.

    Scaling: c makes max‖ω‖ over the samples equal to ``max_omega`` exactly. If then
    max‖ω̇‖ ≤ ``max_omega_dot``, λ = 1 and ω is the binding bound (``Motion.binding == "omega"``).
    Otherwise the time axis is slowed down (λ < 1, found by bisection on the sampled
    max‖ω̇‖ / max‖ω‖, c re-fitted) until max‖ω̇‖ ≤ ``max_omega_dot``, met to about 0.1 %
    (``binding == "omega_dot"``). That is the case for the paper's 2000 °/s with 2000 °/s²: the
    axis then travels about max_omega_dot / max_omega = 1 rad/s, so use ≳ 10 s for full coverage.

    The origin's world-frame acceleration is a random three-axis sum of sinusoids (frequencies in
    [0.1, 1]·bandwidth Hz) with max‖a‖ = ``linear_accel``; s = Rᵀ(a + (0, 0, g)). The initial
    attitude is uniformly random unless q0 is given. max_omega = 0 with linear_accel = 0 gives a
    body at rest.
    """
    t = np.arange(n_samples) / rate
    w, dw = _wandering_axis(rng, bandwidth)

    def ratio(lam):  # max‖ω̇‖ / max‖ω‖ for the time scale λ
        return lam * np.max(np.linalg.norm(dw(lam * t), axis=1)) / np.max(np.linalg.norm(w(lam * t), axis=1))

    if max_omega <= 0:
        lam, c, binding = 1.0, 0.0, "omega"
    else:
        target = max_omega_dot / max_omega
        if ratio(1.0) <= target:
            lam, binding = 1.0, "omega"
        elif target <= 0:
            lam, binding = 0.0, "omega_dot"
        else:
            lo, hi = 0.0, 1.0
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if ratio(mid) <= target else (lo, mid)
                if hi - lo < 1e-4 * hi:
                    break
            lam, binding = lo, "omega_dot"
        c = max_omega / np.max(np.linalg.norm(w(lam * t), axis=1))

    def omega_fn(tt):
        return c * w(lam * np.asarray(tt, dtype=float))

    def omega_dot_fn(tt):
        return c * lam * dw(lam * np.asarray(tt, dtype=float))

    # Linear acceleration of the origin, world frame: three-axis sum of sinusoids.
    n_a = 4
    a_amp = rng.standard_normal((n_a, 3))
    a_freq = rng.uniform(0.1 * bandwidth, bandwidth, n_a)
    a_phase = rng.uniform(0, 2 * np.pi, n_a)

    def accel_raw(tt):
        return np.sin(2 * np.pi * np.outer(tt, a_freq) + a_phase) @ a_amp

    peak = np.max(np.linalg.norm(accel_raw(t), axis=1)) if n_samples else 0.0
    a_scale = linear_accel / peak if peak > 0 else 0.0

    def accel_fn(tt):
        return a_scale * accel_raw(np.asarray(tt, dtype=float))

    if q0 is None:
        q0 = rotation_to_quaternion(random_rotation(rng))
    return rigid_body_motion(t, omega_fn, omega_dot_fn, accel_fn, q0, gravity, binding)


class _Sinusoids:
    """x(t) = Σ_j a_j sin(2π f_j t + φ_j) per axis, (n, 3) amplitudes, with its derivatives in closed form."""

    def __init__(self, rng: np.random.Generator, n_terms: int, f_lo: float, f_hi: float):
        self.a = rng.standard_normal((n_terms, 3))
        self.w = 2 * np.pi * rng.uniform(f_lo, f_hi, (n_terms, 3))
        self.phi = rng.uniform(0, 2 * np.pi, (n_terms, 3))

    def __call__(self, t, order: int = 0) -> np.ndarray:
        """The ``order``-th derivative at the times t (M,) -> (M, 3): d^k sin(x)/dx^k = sin(x + kπ/2)."""
        arg = np.asarray(t, dtype=float)[:, None, None] * self.w + self.phi + order * np.pi / 2
        return np.sum(self.a * self.w ** order * np.sin(arg), axis=1)


def sinusoid_motion(n_samples: int, rate: float, max_omega: float, max_omega_dot: float, rng: np.random.Generator,
                    linear_accel: float = 2.0, *, f_lo: float = 0.3, f_hi: float = 3.0, n_terms: int = 3,
                    q0=None, gravity: float = GRAVITY) -> Motion:
    """Smooth motion that no process model was made to agree with: every axis of ω (body frame) and
    of the origin's acceleration a (world frame) is a sum of ``n_terms`` sinusoids with random
    amplitudes, phases and frequencies in [f_lo, f_hi] Hz (a hand twisting and shaking an array).

    ω, ω̇ and ω̈ are exact at every sample; the attitude is integrated from ω(t) on a fine sub-grid
    (``integrate_attitude``, not with any estimator's step); s = Rᵀ (a + (0, 0, g)) and its exact
    derivative ṡ = −ω×s + Rᵀ ȧ. One factor c scales ω so that max‖ω‖ ≤ ``max_omega`` and
    max‖ω̇‖ ≤ ``max_omega_dot`` over the samples, one of them with equality (``Motion.binding``).
    The initial attitude is uniformly random unless q0 is given.
    """
    t = np.arange(n_samples) / rate
    w, acc = _Sinusoids(rng, n_terms, f_lo, f_hi), _Sinusoids(rng, n_terms, f_lo, f_hi)
    peak_w, peak_wd = (np.max(np.linalg.norm(w(t, k), axis=1)) if n_samples else 0.0 for k in (0, 1))
    by_w = max_omega / peak_w if peak_w > 0 else 0.0
    by_wd = max_omega_dot / peak_wd if peak_wd > 0 else 0.0
    c, binding = (by_w, "omega") if by_w <= by_wd else (by_wd, "omega_dot")
    peak_a = np.max(np.linalg.norm(acc(t), axis=1)) if n_samples else 0.0
    ca_ = linear_accel / peak_a if peak_a > 0 else 0.0
    if q0 is None:
        q0 = rotation_to_quaternion(random_rotation(rng))
    m = rigid_body_motion(t, lambda tt: c * w(tt), lambda tt: c * w(tt, 1), lambda tt: ca_ * acc(tt), q0, gravity,
                          binding)
    R = m.rotation_matrices()
    s_dot = -np.cross(m.omega, m.s) + np.einsum("nji,nj->ni", R, ca_ * acc(t, 1))
    return replace(m, omega_ddot=c * w(t, 2), s_dot=s_dot)


#: Trajectories of the simulator (scenario key ``trajectory``).
TRAJECTORIES = ("sinusoids", "wandering", "euler_consistent")


# ---------------------------------------------------------------------------------------------
# Geometries
# ---------------------------------------------------------------------------------------------

def carlsson_geometry(rng: np.random.Generator, position_error: float = 1e-3, reference: str | None = None
                      ) -> tuple[list[str], np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The 32-IMU array of Carlsson 2017 (sec. IV, Fig. 2; the MIMU4444 board).

    imu1..imu16: a 4x4 grid at 6.3 mm pitch centred at the origin on the top side, z = +1 mm,
    nominal rotation I (row-major in x, then y); imu17..imu32: the same grid on the bottom side,
    z = −1 mm, mounted rotated by [[0,-1,0],[-1,0,0],[0,0,-1]] (body→triad). True positions are
    nominal + N(0, position_error²) per component, except for ``reference`` (if given), whose
    true position is its nominal one.

    Note: the origin is the board centre, not a triad; shift all positions by a triad's position
    to use it as the body origin (s changes accordingly, the relative geometry does not).
    Returns (names, nominal_positions (32, 3), true_positions (32, 3), nominal_rotations).
    """
    g = (np.arange(4) - 1.5) * CARLSSON_PITCH
    X, Y = np.meshgrid(g, g, indexing="xy")
    xy = np.column_stack([X.ravel(), Y.ravel()])
    top = np.column_stack([xy, np.full(16, CARLSSON_HALF_THICKNESS)])
    bottom = np.column_stack([xy, np.full(16, -CARLSSON_HALF_THICKNESS)])
    nominal = np.vstack([top, bottom])
    names = [f"imu{i + 1}" for i in range(32)]
    rotations = {n: (np.eye(3) if i < 16 else CARLSSON_BOTTOM_ROTATION.copy()) for i, n in enumerate(names)}
    true = nominal + position_error * rng.standard_normal(nominal.shape)
    if reference is not None:
        k = names.index(reference)
        true[k] = nominal[k]
    return names, nominal, true, rotations


def schopp_geometry(rng: np.random.Generator, position_error: float = 1e-3, orientation_error_deg: float = 0.0,
                    reference: str | None = None
                    ) -> tuple[list[str], np.ndarray, np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The five accelerometer triads of Schopp 2016 (Table I), acc1..acc5, in metres.

    Nominal rotations are the identity. True positions are nominal + N(0, position_error²) per
    component; true rotations are exp([ξ]×)·R_nominal with ξ ~ N(0, orientation_error_deg²) per
    component (in degrees, converted to rad). ``reference`` (e.g. "acc1", the triad the paper
    fixes) keeps its nominal pose.
    Returns (names, nominal_positions (5, 3), true_positions (5, 3), nominal_rotations,
    true_rotations).
    """
    names = [f"acc{i + 1}" for i in range(5)]
    nominal = SCHOPP_POSITIONS_CM * 1e-2
    true = nominal + position_error * rng.standard_normal(nominal.shape)
    nominal_rot = {n: np.eye(3) for n in names}
    true_rot = {n: rotation_vector_to_matrix(np.deg2rad(orientation_error_deg) * rng.standard_normal(3))
                @ nominal_rot[n] for n in names}
    if reference is not None:
        k = names.index(reference)
        true[k] = nominal[k]
        true_rot[reference] = nominal_rot[reference].copy()
    return names, nominal, true, nominal_rot, true_rot


# ---------------------------------------------------------------------------------------------
# Measurements
# ---------------------------------------------------------------------------------------------

_GYRO_KEYS = {"T_g", "b_g", "sigma", "saturation"}
SENSORS = ("accelerometer", "gyroscope")


def dynamic_measurements(motion: Motion, positions, T, b, rng: np.random.Generator, acc_sigma, gyro=None,
                         names: list[str] | None = None, effects: dict | None = None, *, delay: dict | None = None,
                         pink: dict | None = None, adc: dict | None = None, jitter: float = 0.0,
                         mounting: dict | None = None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Raw readings of K triads rigidly attached to the moving body.

    Accelerometers: y = T_k (s + ω×(ω×r_k) + ω̇×r_k) + b_k + v, v ~ N(0, acc_sigma²) (a scalar, or an
    array broadcastable to (K, 3)). Gyroscopes, if ``gyro`` is given as a dict with keys T_g (K, 3, 3),
    any matrices, b_g (K, 3), sigma and saturation [rad/s] (None for no limit): y_g = T_g ω + b_g + v,
    then clipped to ±saturation per axis.

    Messy measurements, per sensor (``accelerometer``, ``gyroscope``):

    - ``delay`` [s]: the sensor's group delay, the same on every chip; every triad's sensor reads the
      motion at t − delay, evaluated exactly where the motion is in closed form (``Motion.at``). In
      the estimator's parameters it is ``gyroscope.delay`` = delay.gyroscope − delay.accelerometer on
      every IMU (added to the per-chip truth of ``effects``); the common part is the motion's time (a gauge);
    - ``pink`` [m/s², rad/s]: σ of pink (1/f) noise added to the white (:func:`effects.pink_noise`);
    - ``adc``: (lsb [SI per count], bits): the reading quantised to counts and clipped at the
      converter's asymmetric rails (:func:`effects.adc_counts`), returned as counts × lsb.

    Returns (acc, gyro_readings, saturated): dicts name -> (N, 3); ``saturated`` is a boolean (N, 3)
    per gyroscope, True where the axis was clipped or sits on a rail (empty dicts without gyroscopes).
    Names default to imu1..imuK.

    ``effects`` (optional) maps "<triad>.<sensor>.<effect>" to coefficients of the effects
    (:mod:`castimate.simulate.effects`, the truth terms shared with the static simulator): the
    geometric ones simulated exactly rather than as the model's first-order terms
    (``accelerometer.axis_offsets``: axis i senses the specific force at r + δ_i;
    the chip's sample age ``accelerometer.age``, ``accelerometer.clock_beat``,
    ``accelerometer.clock_drift``: both sensors of the triad read the true signal at t − a(t), the
    gyroscope at t − a(t) − d with ``gyroscope.delay`` d, :func:`effects.sample_shift`), and the sample-wise ones
    that need no temperature or specific force at the gyroscope (drifts over the record, scale terms).

    ``mounting`` (name -> body -> chip rotation): where the chip model's sensing-element offsets
    ``array.accelerometer.chip_axis_offsets`` (chip frame, in ``effects``) sit in the body frame.

    ``jitter`` [s] (RMS): every chip's sampling instant jitters at random from sample to sample
    (:func:`castimate.simulate.effects.jitter_ages`, independent per chip, shared by its
    accelerometer and gyroscope); both read the true signal at their sample's own instant. The error
    this makes grows with the signal's rate: the truth of ``noise.motion_dependent``.
    """
    effects, delay, pink, adc = dict(effects or {}), delay or {}, pink or {}, adc or {}
    for what, d in (("delay", delay), ("pink", pink), ("adc", adc)):
        if set(d) - set(SENSORS):
            raise ValueError(f"{what}: unknown sensors {sorted(set(d) - set(SENSORS))}; expected {SENSORS}")
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    K, N = len(positions), len(motion.t)
    t0, t1 = motion.t[0], motion.t[-1]
    tau, zero = (motion.t - (t0 + t1) / 2) / max((t1 - t0) / 2, 1e-9), np.zeros(N)  # normalised time; no temperature
    T = np.broadcast_to(np.asarray(T, dtype=float), (K, 3, 3))
    b = np.broadcast_to(np.asarray(b, dtype=float), (K, 3))
    sig = np.broadcast_to(np.asarray(acc_sigma, dtype=float), (K, 3))
    names = list(names) if names is not None else [f"imu{k + 1}" for k in range(K)]
    if len(names) != K:
        raise ValueError(f"{len(names)} names for {K} positions")

    def force_at(r, dt):  # the true specific force at body position r at the times t + dt
        omega, omega_dot, s = motion.shifted_state(dt)
        return specific_force_at(s, omega, omega_dot, r)

    def convert(sensor, y):  # (reading, on a rail) through the sensor's ADC, if any
        if sensor not in adc:
            return y, np.zeros(y.shape, bool)
        lsb, bits = adc[sensor]
        counts, rail = fx.adc_counts(y, lsb, bits)
        return counts * lsb, rail

    if jitter > 0:
        effects.update({f"{n}.accelerometer.jitter": fx.jitter_ages(jitter, N, rng) for n in names})
    acc: dict[str, np.ndarray] = {}
    for k, n in enumerate(names):
        u = sensed_specific_force(effects, n, motion.t, force_at, positions[k], T[k], delay.get("accelerometer", 0.0),
                                  (mounting or {}).get(n))
        acc[n] = convert("accelerometer", u + b[k] + fx.sample_terms(effects, n, "accelerometer", u, None, tau, zero)
                         + sig[k] * rng.standard_normal((N, 3))
                         + fx.pink_noise(rng, N, pink.get("accelerometer", 0.0)))[0]
    gyro_out: dict[str, np.ndarray] = {}
    saturated: dict[str, np.ndarray] = {}
    if gyro is not None:
        unknown = set(gyro) - _GYRO_KEYS
        missing = {"T_g", "b_g", "sigma"} - set(gyro)
        if unknown or missing:
            raise ValueError(f"gyro: unknown keys {sorted(unknown)}, missing keys {sorted(missing)}; "
                             f"expected {sorted(_GYRO_KEYS)}")
        Tg = np.broadcast_to(np.asarray(gyro["T_g"], dtype=float), (K, 3, 3))
        bg = np.broadcast_to(np.asarray(gyro["b_g"], dtype=float), (K, 3))
        sg = np.broadcast_to(np.asarray(gyro["sigma"], dtype=float), (K, 3))
        sat = gyro.get("saturation")
        if sat is not None and "gyroscope" in adc:
            raise ValueError("gyro saturation and a gyroscope adc both clip; give one")
        for k, n in enumerate(names):
            dt = fx.sample_shift(effects, n, "gyroscope", motion.t) - delay.get("gyroscope", 0.0)
            u = motion.shifted_state(dt)[0] @ Tg[k].T
            y = u + bg[k] + fx.sample_terms(effects, n, "gyroscope", u, None, tau, zero) \
                + sg[k] * rng.standard_normal((N, 3)) + fx.pink_noise(rng, N, pink.get("gyroscope", 0.0))
            y, saturated[n] = convert("gyroscope", y)
            if sat is not None:
                saturated[n] = np.abs(y) >= sat
                y = np.clip(y, -sat, sat)
            gyro_out[n] = y
    return acc, gyro_out, saturated


def euler_consistent(motion: Motion) -> Motion:
    """The same motion with ω re-integrated from ω̇ by the process model's Euler step,
    ω_{n+1} = ω_n + ω̇_n Δt (Schopp 2016, eq. 7), so that simulation and model agree exactly and
    Monte Carlo errors can be compared with the Cramér-Rao bound. s is kept (it is free per sample)."""
    dt = np.diff(motion.t)[:, None]
    omega = np.vstack([motion.omega[:1], motion.omega[:1] + np.cumsum(motion.omega_dot[:-1] * dt, axis=0)])
    return replace(motion, omega=omega, at=None)  # known at its samples only

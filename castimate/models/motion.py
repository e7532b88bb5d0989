"""Rigid-body motion: the specific force at a point and the motion process model.

Motion states per sample (body frame): angular rate ω [rad/s], angular acceleration ω̇ [rad/s²] and
the specific force s [m/s²] at the body origin (gravity included).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np


def specific_force_at(s, omega, omega_dot, r):
    """f = s + ω×(ω×r) + ω̇×r: specific force at position r [m] of a rigid body
    (Carlsson 2017, eq. 1: centrifugal and Euler terms)."""
    return s + ca.cross(omega, ca.cross(omega, r)) + ca.cross(omega_dot, r)


def specific_force_rate(s_dot, omega, omega_dot, omega_ddot, r):
    """ḟ = ṡ + ω̈×r + ω̇×(ω×r) + ω×(ω̇×r): the time derivative of :func:`specific_force_at`
    (what a triad's sample age acts on, see ``models.effects.sample_age``)."""
    return s_dot + ca.cross(omega_ddot, r) + ca.cross(omega_dot, ca.cross(omega, r)) + ca.cross(omega, ca.cross(omega_dot, r))


def specific_force_acceleration(s_ddot, omega, omega_dot, omega_ddot, omega_dddot, r):
    """f̈ = s̈ + ω⃛×r + ω̈×(ω×r) + 2 ω̇×(ω̇×r) + ω×(ω̈×r): the second time derivative of
    :func:`specific_force_at` (the second-order term of a sample age, ``models.effects.sample_age``)."""
    return (s_ddot + ca.cross(omega_dddot, r) + ca.cross(omega_ddot, ca.cross(omega, r))
            + 2 * ca.cross(omega_dot, ca.cross(omega_dot, r)) + ca.cross(omega, ca.cross(omega_ddot, r)))


#: The process models' integration rules (``motion.integration`` of a problem file).
INTEGRATIONS = ("wiener3", "wiener2", "trapezoid", "euler")


def wiener_whitening(order: int) -> np.ndarray:
    """W with W Wᵀ = M⁻¹ for the covariance q D M D of the exact step of an integrated Wiener
    process of ``order`` states (x, x', ..., x^(order-1), the last one a Wiener process driven by
    white noise of density q): M_ij = 1 / ((p_i + p_j + 1) i'! j'!) with p_i = order - 1 - i, and
    D = diag(Δt^(p_i + 1/2)). The whitened residual of e = x_n+1 − exp(A Δt) x_n is
    Wᵀ D⁻¹ e / √q (Wᵀ = L⁻¹ for the Cholesky factor L of M)."""
    p = np.arange(order)[::-1]
    fact = np.array([math.factorial(k) for k in p], float)
    M = 1.0 / ((p[:, None] + p[None, :] + 1) * fact[:, None] * fact[None, :])
    return np.linalg.inv(np.linalg.cholesky(M)).T


def process_residual(omega, omega_dot, s, omega_next, omega_dot_next, s_next, dt, sigma_s, sigma_int, sigma_omega_dot,
                     integration: str = "wiener2"):
    """Whitened process-model residual between samples n and n+1: rows s (3), ω (3), ω̇ (3).

    ``euler`` (Schopp 2016, eqs. 7, 8, 14): ω_{n+1} = ω_n + ω̇_n Δt, with ω̇ and s random walks. The
    covariance is Δt² diag(σ_s², σ_int², σ_ω̇²), so each residual is divided by its σ times Δt
    (σ_s [m/s²], σ_int [rad/s], σ_ω̇ [rad/s²]). Its local error ½ ω̈ Δt² biases smooth motion.

    ``trapezoid``: ω_{n+1} = ω_n + ½ (ω̇_n + ω̇_{n+1}) Δt (local error ω⃛ Δt³ / 12), with Euler's
    σ's and whitening.

    ``wiener2``: the exact discretisation of a continuous-time model, ω̇ a Wiener process (white
    angular jerk of density q_ω) and ω its integral; s a random walk of density q_s. The (ω, ω̇)
    step has covariance q_ω [[Δt³/3, Δt²/2], [Δt²/2, Δt]]; whitened by its Cholesky factor (ω̇
    first) it splits into the ω̇ increment over sqrt(q_ω Δt) and the trapezoid rule over
    sqrt(q_ω Δt³ / 12), the conditional σ of ω_{n+1} given both ω̇'s. Here ``sigma_s`` = √q_s
    [m/s^2.5] and ``sigma_int`` = ``sigma_omega_dot`` = √q_ω [rad/s^2.5].
    """
    if integration not in INTEGRATIONS[1:]:
        raise ValueError(f"unknown integration {integration!r}; expected one of {INTEGRATIONS[1:]} "
                         "(wiener3: process_residual_snap)")
    step = omega_dot * dt if integration == "euler" else 0.5 * (omega_dot + omega_dot_next) * dt
    if integration == "wiener2":
        return ca.vertcat((s_next - s) / (sigma_s * ca.sqrt(dt)),
                          (omega_next - omega - step) / (sigma_int * ca.sqrt(dt ** 3 / 12)),
                          (omega_dot_next - omega_dot) / (sigma_omega_dot * ca.sqrt(dt)))
    return ca.vertcat(
        (s_next - s) / (sigma_s * dt),
        (omega_next - omega - step) / (sigma_int * dt),
        (omega_dot_next - omega_dot) / (sigma_omega_dot * dt),
    )


def process_residual_snap(omega, omega_dot, omega_ddot, s, omega_next, omega_dot_next, omega_ddot_next, s_next, dt,
                          sigma_s, sigma_snap):
    """Whitened process residual of ``wiener3``: ω̈ a Wiener process (white angular snap of density
    q_ω = ``sigma_snap``² [rad²/s⁷]), ω̇ and ω its integrals, s a random walk (√q_s = ``sigma_s``
    [m/s^2.5]). Exact discretisation: e = (ω, ω̇, ω̈)_n+1 − F (ω, ω̇, ω̈)_n with F the Taylor step
    to second order, covariance q_ω D M D (``wiener_whitening``), per axis. Rows: s (3), then
    the three whitened rows of each axis' chain (9)."""
    W = wiener_whitening(3)
    e = [omega_next - omega - omega_dot * dt - omega_ddot * dt ** 2 / 2,
         omega_dot_next - omega_dot - omega_ddot * dt,
         omega_ddot_next - omega_ddot]
    scaled = [e[i] / dt ** (2.5 - i) for i in range(3)]  # D⁻¹ e
    rows = [sum(float(W[i, j]) * scaled[i] for i in range(3)) / sigma_snap for j in range(3)]  # Wᵀ D⁻¹ e / √q
    return ca.vertcat((s_next - s) / (sigma_s * ca.sqrt(dt)), *rows)


def angular_motion_from_specific_forces(t: np.ndarray, f: np.ndarray, r: np.ndarray,
                                        valid: np.ndarray | None = None
                                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Angular rate and acceleration from an accelerometer array without gyroscopes, sample by sample.

    Per sample, ``f_k = s + W r_k`` (:func:`specific_force_at`, Carlsson 2017 eq. 1, with
    ``W = [ω]×² + [ω̇]×``) is linear in (s, W): a least-squares fit over the triads gives W, whose
    antisymmetric part is [ω̇]× and whose symmetric part is S = ωωᵀ − |ω|² I, so |ω|² = −tr(S)/2,
    S + |ω|² I = ωωᵀ and ω lies along its top eigenvector with magnitude sqrt(top eigenvalue).
    The sign of each ω (the centripetal terms are even in ω) is chained from sample to sample by
    continuity with the trapezoid integral of ω̇, ω_n ≈ ω_{n−1} + (ω̇_{n−1} + ω̇_n) Δt/2; the sign
    of the first sample is the one whose chain agrees best with that integral overall.

    A coplanar array (a board: positions in one plane) gives only W's two in-plane columns; ω and ω̇
    then follow from :func:`_planar_candidates` up to the sign of ω and the sign of its normal
    component, both chained by the same continuity.

    t: (N,) times [s]; f: (N, K, 3) specific forces in the body frame [m/s²]; r: (K, 3) positions
    [m]; valid: (N, K, 3) which readings count (default all). Returns (ω, ω̇, s, determined): (N, 3)
    each and (N,) whether the sample's valid readings determine ω (the positions of the triads
    reading an axis must span 3-D, affinely, or the array's plane). Undetermined samples take ω, ω̇
    interpolated from the determined ones (zero where none is: collinear positions, for example),
    and are left to the process model (Schopp 2016, sec. VI-B: ω = 0 then, without a sign
    predetermined).
    """
    t, f, r = np.asarray(t, float), np.asarray(f, float), np.asarray(r, float)
    N, K = f.shape[:2]
    ok = np.ones((N, K, 3), bool) if valid is None else np.broadcast_to(np.asarray(valid, bool), (N, K, 3))
    A = np.column_stack([np.ones(K), r])  # (K, 4): row k of f_k = [s | W] [1; r_k]
    planar = affine_dimension(r) == 2
    if planar:  # in-plane coordinates (a, b) of the positions: f_k = (s + W c) + a_k W q1 + b_k W q2
        c = r.mean(axis=0)
        Q = np.linalg.svd(r - c)[2].T  # columns q1, q2 in the plane, q3 its normal
        Q[:, 2] *= np.sign(np.linalg.det(Q))  # right-handed: the cross products keep their form
        A = np.column_stack([np.ones(K), (r - c) @ Q[:, :2]])
    X = np.full((N, 3, A.shape[1]), np.nan)
    for j in range(3):  # the rows of [s | W] are separate problems, one per body axis
        pattern = ok[:, :, j]
        keys, inverse = np.unique(pattern, axis=0, return_inverse=True)
        for p, key in enumerate(keys):
            rows = np.flatnonzero(inverse.ravel() == p)
            Ak = A[key]
            if np.linalg.matrix_rank(Ak) < A.shape[1]:
                continue
            X[rows, j] = f[rows][:, key, j] @ np.linalg.pinv(Ak).T
    determined = np.isfinite(X).all(axis=(1, 2))
    omega, omega_dot = np.zeros((N, 3)), np.zeros((N, 3))
    d = np.flatnonzero(determined)
    if planar and d.size:
        Wp = np.einsum("ji,njk->nik", Q, X[d, :, 1:])  # Qᵀ W [q1 q2]: W's in-plane columns, plane coordinates
        w, wd = _planar_candidates(Wp)
        w, wd = w @ Q.T, wd @ Q.T  # to the body frame, (M, 4, 3)
        pick = _chain_candidates(t[d], w, wd)
        omega[d], omega_dot[d] = w[np.arange(d.size), pick], wd[np.arange(d.size), pick]
        W = _rate_matrix(omega[d], omega_dot[d])
        s = np.full((N, 3), np.nan)
        s[d] = X[d, :, 0] - W @ c  # the fit's offset is the specific force at the centroid c
    else:
        s, W = X[:, :, 0], X[:, :, 1:]
        omega_dot = 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], axis=1)
        if d.size:
            Sym = 0.5 * (W[d] + W[d].transpose(0, 2, 1))
            norm2 = -0.5 * np.trace(Sym, axis1=1, axis2=2)
            lam, vec = np.linalg.eigh(Sym + norm2[:, None, None] * np.eye(3))
            u = vec[:, :, -1] * np.sqrt(np.maximum(lam[:, -1], 0.0))[:, None]  # ± ω
            wd = np.repeat(omega_dot[d, None], 2, axis=1)
            pick = _chain_candidates(t[d], np.stack([u, -u], axis=1), wd)
            omega[d] = np.where(pick[:, None] == 0, u, -u)
    if d.size:
        for i in range(3):
            omega[:, i] = np.interp(t, t[d], omega[d, i])
            omega_dot[:, i] = np.interp(t, t[d], omega_dot[d, i])
        s = np.where(determined[:, None], s, np.nan)
    else:
        omega_dot[:] = 0.0
        s = np.full((N, 3), np.nan)
    return omega, omega_dot, s, determined


def affine_dimension(r: np.ndarray) -> int:
    """The dimension of the affine span of positions r (K, 3): 3 for an array in space, 2 for a
    coplanar one (a board), 1 for a line, 0 for one point (what a gyro-free start can use, see
    :func:`angular_motion_from_specific_forces`)."""
    r = np.atleast_2d(np.asarray(r, float))
    return int(np.linalg.matrix_rank(np.column_stack([np.ones(len(r)), r]))) - 1


def line_spread(r: np.ndarray) -> tuple[float, np.ndarray]:
    """How far positions r (K, 3) lie off their best-fit line: the root-sum-square of the triads'
    distances from the least-squares line (through their centroid, along their principal direction
    u), that is sqrt(s₂² + s₃²) of the centred positions' singular values s₁ ≥ s₂ ≥ s₃ [m]; and u
    (3,). On the line, 0; for two triads, 0 (two points make a line)."""
    r = np.atleast_2d(np.asarray(r, float))
    if len(r) < 2:
        return 0.0, np.array([1.0, 0.0, 0.0])
    _, s, vt = np.linalg.svd(r - r.mean(axis=0), full_matrices=False)
    return float(np.sqrt(np.sum(s[1:] ** 2))), vt[0]


def _rate_matrix(omega: np.ndarray, omega_dot: np.ndarray) -> np.ndarray:
    """W = [ω]×² + [ω̇]× = ωωᵀ − |ω|² I + [ω̇]× per row, (M, 3, 3) (Carlsson 2017, eq. 1)."""
    x, y, z = omega_dot.T
    o = np.zeros_like(x)
    skew = np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], axis=1)
    return (np.einsum("ni,nj->nij", omega, omega) - np.einsum("ni,ni->n", omega, omega)[:, None, None] * np.eye(3)
            + skew)


def _planar_candidates(Wp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ω and ω̇ (plane coordinates, normal = axis 3) from W's two in-plane columns Wp (M, 3, 2) of
    W = ωωᵀ − |ω|² I + [ω̇]× (:func:`specific_force_at`): W₁₁ = −(ω₂² + ω₃²), W₂₂ = −(ω₁² + ω₃²),
    W₂₁ + W₁₂ = 2 ω₁ω₂ and W₂₁ − W₁₂ = 2 ω̇₃, so (ω₁ + iω₂)² = W₁₁ − W₂₂ + i (W₂₁ + W₁₂) and
    ω₃² = −(W₁₁ + W₂₂ + |ω₁ + iω₂|²)/2; then W₃₁ = ω₃ω₁ − ω̇₂ and W₃₂ = ω₃ω₂ + ω̇₁ give ω̇₁, ω̇₂.
    The column along the normal is not measured, so ω is known up to its sign and that of ω₃:
    returns the four candidates (M, 4, 3) each of ω and ω̇, ordered (+, +), (+, −), (−, +), (−, −)
    (sign of the in-plane part, of ω₃)."""
    W11, W21, W31 = Wp[:, 0, 0], Wp[:, 1, 0], Wp[:, 2, 0]
    W12, W22, W32 = Wp[:, 0, 1], Wp[:, 1, 1], Wp[:, 2, 1]
    p = np.sqrt((W11 - W22) + 1j * (W21 + W12))  # ω₁ + iω₂, up to its sign
    h = np.sqrt(np.maximum(-(W11 + W22 + np.abs(p) ** 2) / 2, 0.0))  # |ω₃|
    w, wd = np.empty((len(Wp), 4, 3)), np.empty((len(Wp), 4, 3))
    for k, (a, b) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        w1, w2, w3 = a * p.real, a * p.imag, b * h
        w[:, k] = np.column_stack([w1, w2, w3])
        wd[:, k] = np.column_stack([W32 - w3 * w2, w3 * w1 - W31, 0.5 * (W21 - W12)])
    return w, wd


def _chain_candidates(t: np.ndarray, w: np.ndarray, wd: np.ndarray) -> np.ndarray:
    """The candidate (M,) of every sample, out of w, wd (M, C, 3) (ω and ω̇ per candidate), chained by
    continuity with the trapezoid integral of ω̇ (see :func:`angular_motion_from_specific_forces`):
    each sample takes the candidate nearest to ω_{n−1} + (ω̇_{n−1} + ω̇_n) Δt/2; every first
    candidate is tried and the chain with the smallest sum of squared misfits wins.

    The misfit of every candidate after every candidate of the previous sample is one array
    (M − 1, C, C); the chains then only follow its row minima, all first candidates at once."""
    M, C = w.shape[:2]
    dt = np.diff(t)[:, None, None, None]
    # miss[n − 1, prev, cand]: sample n's candidate cand after sample n − 1's candidate prev
    miss = np.sum((w[1:, None] - w[:-1, :, None] - 0.5 * (wd[:-1, :, None] + wd[1:, None]) * dt) ** 2, axis=3)
    nxt = np.argmin(miss, axis=2)  # (M − 1, C): the nearest candidate after each previous one
    step = np.take_along_axis(miss, nxt[:, :, None], axis=2)[:, :, 0]
    picks = np.empty((M, C), int)
    picks[0] = np.arange(C)  # one chain per first candidate
    cost = np.zeros(C)
    for n in range(1, M):
        cost += step[n - 1, picks[n - 1]]
        picks[n] = nxt[n - 1, picks[n - 1]]
    return picks[:, int(np.argmin(cost))]

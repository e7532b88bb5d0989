"""Accelerometer positions by block coordinate descent (Carlsson, Skog, Jaldén 2017, Algorithm 1).

A numpy/scipy baseline for the ``dynamic_array`` kind with gyroscopes. The inputs are *calibrated*
measurements in the body frame (gains, biases and rotations already compensated by the caller):

- accelerometer triad k at position r_k (eq. 1)::

      y_a,n^k = s_n + ω_n×(ω_n×r_k) + ω̇_n×r_k + ε,     ε ~ N(0, σ_a,k² I)

- gyroscope triad g (eq. 2)::

      y_g,n^g = ω_n + ε,                               ε ~ N(0, σ_g,g² I)

The negative log-likelihood (up to constants and a factor ½) is the whitened sum of squares ::

      cost = Σ_n [ Σ_k |y_a,n^k − s_n − A_n r_k|²/σ_a,k² + Σ_g valid |y_g,n^g − ω_n|²/σ_g,g² ]

with A_n = [ω_n]×² + [ω̇_n]×. At the optimum it is about the number of residuals minus the number of
free parameters (``BCDResult.dof``). Algorithm 1 alternates two exact minimisations of it:

(a) **Motion given positions** (:func:`motion_ml`, eq. 5). Per sample, the cost is linear in
    (s_n, ω̇_n) given ω_n, so these are eliminated in closed form (variable projection) and a
    Levenberg–Marquardt iteration runs on ω_n alone, vectorised over all samples.

    With positions centred on their weighted centroid r̄ (d_k = r_k − r̄, weights w_k = σ_a,k⁻²,
    so Σ w_k d_k = 0) the projection decouples completely: the specific force at r̄ is the
    weighted mean ȳ_n of the accelerometers, and ω̇_n = J⁻¹ g_n(ω_n), where ::

        S = Σ_k w_k d_k d_kᵀ,  J = tr(S) I − S,  Q_n = Σ_k w_k d_k y_a,n^kᵀ,
        m_n = Σ_k w_k d_k × y_a,n^k,  g_n(ω) = m_n + ω × (S ω).

    With B(ω) = [ω]×² = ωωᵀ − |ω|² I, the accelerometer part of the concentrated cost is the
    quartic ::

        f_n(ω) = c_n − 2 tr(B Q_n) + tr(B² S) − g_nᵀ J⁻¹ g_n,     c_n = Σ_k w_k |y_a,n^k − ȳ_n|²,

    which depends on the data only through (c_n, Q_n), i.e. the cost of one Gauss–Newton step is
    independent of the number of triads K. Its Gauss–Newton matrix (that of the projected
    residual) is, again in closed form, ::

        Σ_k w_k D_kᵀD_k − G_ωᵀ J⁻¹ G_ω + w_G I,      D_k = ∂(B d_k)/∂ω,  G_ω = ∂g/∂ω = [ω]× S − [Sω]×,
        Σ_k w_k D_kᵀD_k = |ω|² S + (ωᵀSω) I + 4 tr(S) ωωᵀ − 3 (Sωωᵀ + ωωᵀS),

    with w_G the summed weight of the valid gyroscope samples. The specific force at the body
    origin is then s_n = ȳ_n − B(ω_n) r̄ − ω̇_n × r̄.

    The motion is observable iff J is regular, i.e. the accelerometers span at least a plane, and
    ω_n is then determined (up to the sign, which the gyroscopes fix) where the gyroscopes are valid
    or |ω_n| is large. A sample with no valid gyroscope starts from ``omega0``, else from the
    gyroscope rate interpolated in time over its masked run (a saturated run is bracketed by large
    valid rates, so the start has the right sign), else from zero; ω = 0 is a stationary point of
    f_n, so a sample without gyroscope information that starts exactly there stays there.

(b) **Positions given motion** (:func:`positions_given_motion`, eq. 9)::

        r_k = (Σ_n A_nᵀA_n)⁻¹ Σ_n A_nᵀ (y_a,n^k − s_n)

    for every triad but the reference, whose position is fixed. The 3×3 inverse is shared by all
    triads. Given the motion, the covariance of r_k is σ_a,k² (Σ_n A_nᵀA_n)⁻¹ (:func:`motion_gram`).

Both steps never increase the cost (step (a) starts from the previous iteration's ω and only
accepts decreasing steps), so the recorded cost is non-increasing.
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = [
    "BCDResult",
    "MotionEstimate",
    "bcd_positions",
    "motion_gram",
    "motion_ml",
    "positions_given_motion",
    "skew",
]

_I3 = np.eye(3)


# ---------------------------------------------------------------------------------------------
# results


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class MotionEstimate:
    """Per-sample maximum-likelihood motion given the accelerometer positions (step (a)).

    Attributes
    ----------
    s, omega, omega_dot
        (N, 3) specific force at the body origin [m/s²], angular rate [rad/s] and angular
        acceleration [rad/s²], body frame.
    cost
        (N,) whitened sum of squared residuals of each sample at the estimate.
    iterations
        Levenberg–Marquardt iterations (the largest over the samples).
    converged
        (N,) whether each sample's iteration met the step tolerance.
    """

    s: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    cost: np.ndarray
    iterations: int
    converged: np.ndarray


@dataclass(frozen=True, eq=False)
class BCDResult:
    """Outcome of :func:`bcd_positions`.

    Attributes
    ----------
    positions
        (K, 3) accelerometer positions [m], body frame; the reference row equals ``r0[reference]``.
    s, omega, omega_dot
        (N, 3) motion re-estimated at the returned positions.
    iterations
        Number of block coordinate descent iterations (each one step (a) and one step (b)).
    cost_history
        (iterations,) whitened cost after step (a) of each iteration, i.e. at that iteration's
        motion and the positions it started from. Non-increasing.
    step_history
        (iterations,) largest position change [m] made by step (b) of each iteration.
    cost
        Whitened cost at the returned positions and motion (≤ the last entry of cost_history).
    dof
        Number of residuals minus number of free parameters; ``cost / dof`` ≈ 1 for a correct
        noise model.
    converged
        True iff the largest position change fell below ``tol`` within ``max_iter`` iterations.
    reference
        Index of the reference triad.
    wall_s
        Wall time [s].
    """

    positions: np.ndarray
    s: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    iterations: int
    cost_history: np.ndarray
    step_history: np.ndarray
    cost: float
    dof: int
    converged: bool
    reference: int
    wall_s: float


# ---------------------------------------------------------------------------------------------
# small vectorised helpers


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]× for v of shape (..., 3); ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def _a_matrices(omega: np.ndarray, omega_dot: np.ndarray) -> np.ndarray:
    """A_n = [ω_n]×² + [ω̇_n]× for all samples, (N, 3, 3)."""
    q = np.einsum("ni,ni->n", omega, omega)
    a = omega[:, :, None] * omega[:, None, :] - q[:, None, None] * _I3 + skew(omega_dot)
    return a


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _matvec(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", m, v)


# ---------------------------------------------------------------------------------------------
# validation (library level: plain ValueError with a clear message)


def _as_sigma(value, count: int, name: str, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(count, float(arr))
    if arr.shape != (count,):
        raise ValueError(f"{name} must be a scalar or have shape ({count},) (one per {what}); got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"{name} must be finite and positive; got {arr.tolist()}")
    return arr


def _validate(acc, gyro, acc_sigma, gyro_sigma, positions, gyro_mask, omega0, pos_name: str):
    acc = np.asarray(acc, dtype=float)
    if acc.ndim != 3 or acc.shape[2] != 3:
        raise ValueError(f"acc must have shape (K, N, 3) (triads, samples, axes); got shape {acc.shape}")
    k, n, _ = acc.shape
    if k < 3:
        raise ValueError(f"acc must hold at least 3 accelerometer triads (K >= 3 spanning a plane); got K = {k}")
    if n < 1:
        raise ValueError("acc holds no samples (N = 0)")
    if not np.all(np.isfinite(acc)):
        raise ValueError("acc contains non-finite values (NaN or inf)")
    w_a = 1.0 / _as_sigma(acc_sigma, k, "acc_sigma", "accelerometer triad") ** 2

    if gyro is None:
        if gyro_mask is not None:
            raise ValueError("gyro_mask was given but gyro is None")
        gyro = np.zeros((0, n, 3))
        mask = np.zeros((0, n), dtype=bool)
        w_g = np.zeros(0)
    else:
        gyro = np.asarray(gyro, dtype=float)
        if gyro.ndim != 3 or gyro.shape[2] != 3:
            raise ValueError(f"gyro must have shape (G, N, 3) (triads, samples, axes) or be None; got shape {gyro.shape}")
        if gyro.shape[1] != n:
            raise ValueError(
                f"gyro has {gyro.shape[1]} samples but acc has {n}: shapes (G, N, 3) = {gyro.shape} "
                f"and (K, N, 3) = {acc.shape} must share N"
            )
        g = gyro.shape[0]
        w_g = 1.0 / _as_sigma(gyro_sigma, g, "gyro_sigma", "gyroscope triad") ** 2
        if gyro_mask is None:
            mask = np.ones((g, n), dtype=bool)
        else:
            mask = np.asarray(gyro_mask)
            if mask.dtype != bool:
                raise ValueError(f"gyro_mask must be a boolean array (True = valid sample); got dtype {mask.dtype}")
            if mask.shape != (g, n):
                raise ValueError(f"gyro_mask must have shape (G, N) = ({g}, {n}); got shape {mask.shape}")
        finite = np.all(np.isfinite(gyro), axis=2)
        if np.any(mask & ~finite):
            raise ValueError("gyro contains non-finite values at samples that gyro_mask marks valid")
        # masked samples are never read: zero them so that garbage (NaN, clipped) cannot propagate
        gyro = np.where(mask[:, :, None], gyro, 0.0)

    positions = np.asarray(positions, dtype=float)
    if positions.shape != (k, 3):
        raise ValueError(f"{pos_name} must have shape (K, 3) = ({k}, 3), one row per accelerometer triad; got shape {positions.shape}")
    if not np.all(np.isfinite(positions)):
        raise ValueError(f"{pos_name} contains non-finite values")

    if omega0 is not None:
        omega0 = np.asarray(omega0, dtype=float)
        if omega0.shape != (n, 3):
            raise ValueError(f"omega0 must have shape (N, 3) = ({n}, 3); got shape {omega0.shape}")
        if not np.all(np.isfinite(omega0)):
            raise ValueError("omega0 contains non-finite values")
    return acc, gyro, mask, w_a, w_g, positions, omega0


# ---------------------------------------------------------------------------------------------
# step (a): per-sample ML motion, variable projection on ω


class _Gyro:
    """Per-sample gyroscope sufficient statistics: w_G |ω|² − 2 ω·b_G + c_G."""

    def __init__(self, gyro: np.ndarray, mask: np.ndarray, w_g: np.ndarray):
        wm = mask * w_g[:, None]  # (G, N)
        self.w = wm.sum(axis=0)  # (N,)
        self.b = np.einsum("gn,gni->ni", wm, gyro)  # (N, 3)
        self.c = np.einsum("gn,gni,gni->n", wm, gyro, gyro)  # (N,)

    def mean(self) -> np.ndarray:
        """Weighted mean gyroscope rate, interpolated in time over samples without a valid one."""
        n = self.w.shape[0]
        valid = self.w > 0
        out = np.zeros((n, 3))
        if not np.any(valid):
            return out
        out[valid] = self.b[valid] / self.w[valid, None]
        if not np.all(valid):
            idx = np.arange(n)
            for i in range(3):
                out[~valid, i] = np.interp(idx[~valid], idx[valid], out[valid, i])
        return out


class _Accel:
    """Accelerometer statistics that the concentrated cost needs, for fixed positions."""

    def __init__(self, acc: np.ndarray, w_a: np.ndarray, positions: np.ndarray, sum_wyy: np.ndarray | None = None):
        wsum = w_a.sum()
        self.rbar = w_a @ positions / wsum
        d = positions - self.rbar
        wd = w_a[:, None] * d
        self.S = d.T @ wd
        self.trS = float(np.trace(self.S))
        jmat = self.trS * _I3 - self.S
        ev = np.linalg.eigvalsh(jmat)
        if ev[0] <= 1e-10 * max(ev[-1], np.finfo(float).tiny):
            raise ValueError(
                "the accelerometer positions do not span a plane (at least 3 non-collinear triads are "
                "needed): the angular acceleration is not observable"
            )
        self.Jinv = np.linalg.inv(jmat)
        self.ybar = np.einsum("k,kni->ni", w_a, acc) / wsum  # (N, 3)
        if sum_wyy is None:
            sum_wyy = np.einsum("k,kni,kni->n", w_a, acc, acc)
        self.c = sum_wyy - wsum * _dot(self.ybar, self.ybar)  # (N,)
        # Q_n = Σ_k w_k d_k y_kᵀ (Σ_k w_k d_k = 0, so centring y is not needed)
        self.Q = np.tensordot(acc, wd, axes=([0], [0])).transpose(0, 2, 1)  # (N, 3, 3): [n, i(d), j(y)]
        self.trQ = np.trace(self.Q, axis1=1, axis2=2)
        q = self.Q
        self.m = np.stack([q[:, 1, 2] - q[:, 2, 1], q[:, 2, 0] - q[:, 0, 2], q[:, 0, 1] - q[:, 1, 0]], axis=1)
        self.Qs = q + q.transpose(0, 2, 1)

    def g(self, omega: np.ndarray, idx) -> np.ndarray:
        return self.m[idx] + np.cross(omega, omega @ self.S.T)

    def cost(self, omega: np.ndarray, idx, gy: _Gyro) -> np.ndarray:
        """Concentrated cost f_n(ω) (accelerometers with s, ω̇ eliminated, plus gyroscopes)."""
        q = _dot(omega, omega)
        s_om = omega @ self.S.T
        w_s_w = _dot(omega, s_om)
        wqw = _dot(omega, _matvec(self.Q[idx], omega))
        g = self.m[idx] + np.cross(omega, s_om)
        f = (
            self.c[idx]
            - 2.0 * (wqw - q * self.trQ[idx])
            + q * q * self.trS
            - q * w_s_w
            - _dot(g, g @ self.Jinv.T)
        )
        f += gy.w[idx] * q - 2.0 * _dot(omega, gy.b[idx]) + gy.c[idx]
        return f

    def grad_gn(self, omega: np.ndarray, idx, gy: _Gyro) -> tuple[np.ndarray, np.ndarray]:
        """Half the gradient of f_n and its Gauss–Newton matrix, (M, 3) and (M, 3, 3)."""
        S, trS = self.S, self.trS
        q = _dot(omega, omega)
        s_om = omega @ S.T
        w_s_w = _dot(omega, s_om)
        g = self.m[idx] + np.cross(omega, s_om)
        jg = g @ self.Jinv.T
        gw = skew(omega) @ S - skew(s_om)  # ∂g/∂ω, (M, 3, 3)
        gwt = gw.transpose(0, 2, 1)
        half_grad = (
            -_matvec(self.Qs[idx], omega)
            + 2.0 * self.trQ[idx, None] * omega
            + 2.0 * trS * q[:, None] * omega
            - w_s_w[:, None] * omega
            - q[:, None] * s_om
            - _matvec(gwt, jg)
            + gy.w[idx, None] * omega
            - gy.b[idx]
        )
        oo = omega[:, :, None] * omega[:, None, :]
        so_o = s_om[:, :, None] * omega[:, None, :]
        gn = (
            q[:, None, None] * S
            + (w_s_w + gy.w[idx])[:, None, None] * _I3
            + 4.0 * trS * oo
            - 3.0 * (so_o + so_o.transpose(0, 2, 1))
            - gwt @ self.Jinv @ gw
        )
        return half_grad, gn

    def motion(self, omega: np.ndarray, positions_ref: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(s, ω̇) eliminated in closed form for the given ω (all samples)."""
        g = self.m + np.cross(omega, omega @ self.S.T)
        omega_dot = g @ self.Jinv.T
        rb = self.rbar
        q = _dot(omega, omega)
        b_rbar = omega * _dot(omega, rb[None, :])[:, None] - q[:, None] * rb
        s = self.ybar - b_rbar - np.cross(omega_dot, rb)
        return s, omega_dot


def _lm_omega(acc_stats: _Accel, gy: _Gyro, omega: np.ndarray, max_iter: int, xtol: float):
    """Vectorised Levenberg–Marquardt on ω_n for all samples; returns (ω, iterations, converged)."""
    omega = np.array(omega, dtype=float, copy=True)
    n = omega.shape[0]
    all_idx = np.arange(n)
    f = acc_stats.cost(omega, all_idx, gy)
    lam = np.full(n, 1e-4)
    active = np.ones(n, dtype=bool)
    converged = np.zeros(n, dtype=bool)
    it = 0
    tiny = np.finfo(float).tiny
    while it < max_iter:
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        it += 1
        w = omega[idx]
        half_grad, gn = acc_stats.grad_gn(w, idx, gy)
        scale = np.maximum(np.trace(gn, axis1=1, axis2=2) / 3.0, tiny)
        damped = gn + (lam[idx] * scale)[:, None, None] * _I3
        delta = -np.linalg.solve(damped, half_grad[:, :, None])[:, :, 0]
        w_new = w + delta
        f_new = acc_stats.cost(w_new, idx, gy)
        ok = f_new <= f[idx]
        small = np.sqrt(_dot(delta, delta)) <= xtol * (1.0 + np.sqrt(_dot(w, w)))
        acc_idx = idx[ok]
        omega[acc_idx] = w_new[ok]
        f[acc_idx] = f_new[ok]
        lam[idx] = np.where(ok, np.maximum(lam[idx] * 0.1, 1e-12), lam[idx] * 10.0)
        done = small | (lam[idx] > 1e10)
        converged[idx[small]] = True
        active[idx[done]] = False
    return omega, it, converged


def _sample_costs(acc, gyro, mask, w_a, w_g, positions, s, omega, omega_dot) -> np.ndarray:
    """Per-sample whitened cost, evaluated directly from the residuals (N,)."""
    a = _a_matrices(omega, omega_dot)
    pred = s[None, :, :] + np.einsum("nij,kj->kni", a, positions)
    e = acc - pred
    cost = np.einsum("k,kni,kni->n", w_a, e, e)
    if gyro.shape[0]:
        eg = gyro - omega[None, :, :]
        cost += np.einsum("g,gn,gni,gni->n", w_g, mask, eg, eg)
    return cost


def _motion_step(acc, gy, w_a, positions, omega_start, max_iter, xtol, sum_wyy=None):
    stats = _Accel(acc, w_a, positions, sum_wyy)
    omega, it, conv = _lm_omega(stats, gy, omega_start, max_iter, xtol)
    s, omega_dot = stats.motion(omega)
    return s, omega, omega_dot, it, conv


def motion_ml(
    acc: np.ndarray,
    gyro: np.ndarray | None,
    positions: np.ndarray,
    acc_sigma,
    gyro_sigma,
    gyro_mask: np.ndarray | None = None,
    omega0: np.ndarray | None = None,
    max_iter: int = 100,
    xtol: float = 1e-13,
) -> MotionEstimate:
    """Per-sample maximum-likelihood motion (s, ω, ω̇) given the accelerometer positions (step (a)).

    Parameters
    ----------
    acc
        (K, N, 3) specific force per accelerometer triad [m/s²], body frame, calibrated.
    gyro
        (G, N, 3) angular rate per gyroscope triad [rad/s], body frame, calibrated; or None.
    positions
        (K, 3) accelerometer positions [m], body frame.
    acc_sigma, gyro_sigma
        Noise standard deviations, scalar or one per triad ((K,) and (G,)).
    gyro_mask
        (G, N) bool, True where a gyroscope sample is valid (e.g. not saturated); masked samples are
        never read. None: all valid.
    omega0
        (N, 3) starting angular rates. None: the weighted mean of the valid gyroscopes, interpolated
        in time over samples without one (zero if there is no valid gyroscope sample at all).
    max_iter, xtol
        Levenberg–Marquardt limits: a sample stops when its step is below ``xtol·(1 + |ω|)``.
    """
    acc, gyro, mask, w_a, w_g, positions, omega0 = _validate(
        acc, gyro, acc_sigma, gyro_sigma, positions, gyro_mask, omega0, "positions"
    )
    gy = _Gyro(gyro, mask, w_g)
    start = gy.mean() if omega0 is None else omega0
    s, omega, omega_dot, it, conv = _motion_step(acc, gy, w_a, positions, start, max_iter, xtol)
    cost = _sample_costs(acc, gyro, mask, w_a, w_g, positions, s, omega, omega_dot)
    return MotionEstimate(_frozen(s), _frozen(omega), _frozen(omega_dot), _frozen(cost), int(it), _frozen_bool(conv))


def _frozen_bool(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=bool, copy=True)
    a.setflags(write=False)
    return a


# ---------------------------------------------------------------------------------------------
# step (b): positions given the motion, eq. 9


def motion_gram(omega: np.ndarray, omega_dot: np.ndarray) -> np.ndarray:
    """Σ_n A_nᵀA_n (3×3), A_n = [ω_n]×² + [ω̇_n]×.

    Given the motion, the covariance of each estimated position r_k is σ_a,k² times its inverse.
    """
    omega = np.asarray(omega, dtype=float)
    omega_dot = np.asarray(omega_dot, dtype=float)
    if omega.ndim != 2 or omega.shape[1] != 3 or omega_dot.shape != omega.shape:
        raise ValueError(f"omega and omega_dot must both have shape (N, 3); got {omega.shape} and {omega_dot.shape}")
    a = _a_matrices(omega, omega_dot)
    return np.einsum("nji,njk->ik", a, a)


def _positions_step(acc, s, a, reference, r_ref, sum_a=None):
    gram = np.einsum("nji,njk->ik", a, a)
    ev = np.linalg.eigvalsh(gram)
    if not np.all(np.isfinite(ev)) or ev[0] <= 1e-12 * max(ev[-1], np.finfo(float).tiny):
        raise ValueError(
            "the motion does not excite all three position axes: Σ A_nᵀA_n is singular "
            "(ω_n and ω̇_n must not be parallel for all samples; eq. 9)"
        )
    c = np.linalg.inv(gram)  # shared by all triads (Algorithm 1, line 10)
    rhs = np.einsum("nji,knj->ki", a, acc) - np.einsum("nji,nj->i", a, s)[None, :]
    r = rhs @ c.T
    r[reference] = r_ref
    return r


def positions_given_motion(
    acc: np.ndarray,
    s: np.ndarray,
    omega: np.ndarray,
    omega_dot: np.ndarray,
    reference: int = 0,
    reference_position=(0.0, 0.0, 0.0),
) -> np.ndarray:
    """Least-squares accelerometer positions given the motion (eq. 9); step (b) of Algorithm 1.

    ``r_k = (Σ_n A_nᵀA_n)⁻¹ Σ_n A_nᵀ (y_a,n^k − s_n)`` for every triad but ``reference``, whose row is
    ``reference_position``. Returns (K, 3) [m].
    """
    acc = np.asarray(acc, dtype=float)
    if acc.ndim != 3 or acc.shape[2] != 3:
        raise ValueError(f"acc must have shape (K, N, 3); got shape {acc.shape}")
    k, n, _ = acc.shape
    arrs = {}
    for name, v in (("s", s), ("omega", omega), ("omega_dot", omega_dot)):
        v = np.asarray(v, dtype=float)
        if v.shape != (n, 3):
            raise ValueError(f"{name} must have shape (N, 3) = ({n}, 3) to match acc {acc.shape}; got shape {v.shape}")
        arrs[name] = v
    reference = _check_reference(reference, k)
    r_ref = np.asarray(reference_position, dtype=float)
    if r_ref.shape != (3,):
        raise ValueError(f"reference_position must have shape (3,); got shape {r_ref.shape}")
    a = _a_matrices(arrs["omega"], arrs["omega_dot"])
    return _positions_step(acc, arrs["s"], a, reference, r_ref)


def _check_reference(reference, k: int) -> int:
    if isinstance(reference, (bool, np.bool_)) or not isinstance(reference, numbers.Integral):
        raise ValueError(f"reference must be an integer triad index; got {reference!r}")
    reference = int(reference)
    if not 0 <= reference < k:
        raise ValueError(f"reference must be a triad index in [0, {k - 1}]; got {reference}")
    return reference


# ---------------------------------------------------------------------------------------------
# Algorithm 1


def bcd_positions(
    acc: np.ndarray,
    gyro: np.ndarray | None,
    acc_sigma,
    gyro_sigma,
    r0: np.ndarray,
    reference: int = 0,
    gyro_mask: np.ndarray | None = None,
    max_iter: int = 50,
    tol: float = 1e-9,
    progress: Callable[[int, float, float], object] | None = None,
    omega0: np.ndarray | None = None,
) -> BCDResult:
    """Accelerometer positions and per-sample motion by block coordinate descent (Algorithm 1).

    Parameters
    ----------
    acc
        (K, N, 3) specific force per accelerometer triad [m/s²], body frame, calibrated.
    gyro
        (G, N, 3) angular rate per gyroscope triad [rad/s], body frame, calibrated; or None (then
        give ``omega0``: without gyroscopes ω has a sign ambiguity and ω = 0 is stationary).
    acc_sigma, gyro_sigma
        Noise standard deviations [m/s²], [rad/s]; scalar or one per triad ((K,), (G,)).
    r0
        (K, 3) initial positions [m]; row ``reference`` is kept fixed.
    reference
        Index of the reference triad.
    gyro_mask
        (G, N) bool, True where a gyroscope sample is valid (unsaturated). None: all valid.
    max_iter, tol
        Stop when the largest position change of an iteration is below ``tol`` [m], or after
        ``max_iter`` iterations (then ``converged`` is False).
    progress
        Called as ``progress(iteration, cost, max_position_change)`` after every iteration.
    omega0
        (N, 3) starting angular rates for the first step (a); default from the gyroscopes.

    Returns
    -------
    BCDResult
        The motion in it is re-estimated at the returned positions.
    """
    t0 = time.perf_counter()
    acc, gyro, mask, w_a, w_g, r0, omega0 = _validate(acc, gyro, acc_sigma, gyro_sigma, r0, gyro_mask, omega0, "r0")
    reference = _check_reference(reference, acc.shape[0])
    if isinstance(max_iter, (bool, np.bool_)) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer; got {max_iter!r}")
    tol = float(tol)
    if not (math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be finite and >= 0 [m]; got {tol!r}")
    if progress is not None and not callable(progress):
        raise ValueError("progress must be callable as progress(iteration, cost, max_position_change)")

    k, n, _ = acc.shape
    gy = _Gyro(gyro, mask, w_g)
    sum_wyy = np.einsum("k,kni,kni->n", w_a, acc, acc)
    omega = gy.mean() if omega0 is None else omega0.copy()
    positions = r0.copy()
    r_ref = r0[reference].copy()
    not_ref = np.arange(k) != reference
    lm_iter, lm_tol = 100, 1e-13

    costs: list[float] = []
    steps: list[float] = []
    converged = False
    it = 0
    while it < max_iter:
        it += 1
        s, omega, omega_dot, _, _ = _motion_step(acc, gy, w_a, positions, omega, lm_iter, lm_tol, sum_wyy)  # (a)
        cost = float(_sample_costs(acc, gyro, mask, w_a, w_g, positions, s, omega, omega_dot).sum())
        a = _a_matrices(omega, omega_dot)
        new = _positions_step(acc, s, a, reference, r_ref)  # (b)
        dr = float(np.max(np.linalg.norm(new[not_ref] - positions[not_ref], axis=1), initial=0.0))
        positions = new
        costs.append(cost)
        steps.append(dr)
        if progress is not None:
            progress(it, cost, dr)
        if dr < tol:
            converged = True
            break

    s, omega, omega_dot, _, _ = _motion_step(acc, gy, w_a, positions, omega, lm_iter, lm_tol, sum_wyy)
    final = float(_sample_costs(acc, gyro, mask, w_a, w_g, positions, s, omega, omega_dot).sum())
    n_res = 3 * k * n + 3 * int(mask.sum())
    dof = n_res - 9 * n - 3 * (k - 1)
    return BCDResult(
        positions=_frozen(positions),
        s=_frozen(s),
        omega=_frozen(omega),
        omega_dot=_frozen(omega_dot),
        iterations=it,
        cost_history=_frozen(costs),
        step_history=_frozen(steps),
        cost=final,
        dof=int(dof),
        converged=converged,
        reference=reference,
        wall_s=time.perf_counter() - t0,
    )

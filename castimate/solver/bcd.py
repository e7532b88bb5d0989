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

Neither step increases the cost (step (a) starts from the previous iteration's ω and accepts only
steps that do not increase it beyond its rounding error), so the recorded cost is non-increasing.
Convergence is linear and can be slow: for the simulated arrays in ``tests/test_bcd.py`` about
100 iterations take 1 mm initial errors to a 1 nm step, and a 32-triad planar array needs several
hundred; ``converged`` says whether ``tol`` was reached.
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
_EPS = np.finfo(float).eps


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
    """Per-sample gyroscope sufficient statistics: w_G |ω|² − 2 ω·b_G + c_G (component-major)."""

    def __init__(self, gyro: np.ndarray, mask: np.ndarray, w_g: np.ndarray):
        wm = mask * w_g[:, None]  # (G, N)
        self.w = wm.sum(axis=0)  # (N,)
        self.b = np.einsum("gn,gni->in", wm, gyro)  # (3, N)
        self.c = np.einsum("gn,gni,gni->n", wm, gyro, gyro)  # (N,)

    def mean(self) -> np.ndarray:
        """Weighted mean gyroscope rate (N, 3), interpolated in time over samples without a valid one."""
        n = self.w.shape[0]
        valid = self.w > 0
        out = np.zeros((n, 3))
        if not np.any(valid):
            return out
        out[valid] = (self.b[:, valid] / self.w[valid]).T
        if not np.all(valid):
            idx = np.arange(n)
            for i in range(3):
                out[~valid, i] = np.interp(idx[~valid], idx[valid], out[valid, i])
        return out


def _cross_e(a: int, v: np.ndarray) -> np.ndarray:
    """e_a × v for v of shape (3, M)."""
    out = np.zeros_like(v)
    b, c = (a + 1) % 3, (a + 2) % 3
    out[b] = -v[c]
    out[c] = v[b]
    return out


class _Accel:
    """Accelerometer statistics that the concentrated cost needs, for fixed positions.

    Per-sample quantities are stored component-major ((3, N), (3, 3, N)) so that the
    Levenberg–Marquardt algebra runs on contiguous length-N vectors.
    """

    def __init__(self, y: np.ndarray, w_a: np.ndarray, positions: np.ndarray, sum_wyy: np.ndarray | None = None):
        n, _, k = y.shape  # accelerometers in (N, 3, K) layout
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
        flat = y.reshape(n * 3, k)
        self.ybar = (flat @ w_a).reshape(n, 3) / wsum  # (N, 3)
        if sum_wyy is None:
            sum_wyy = _sum_wyy(y, w_a)
        self.c = sum_wyy - wsum * np.einsum("ni,ni->n", self.ybar, self.ybar)  # (N,)
        # Q_n = Σ_k w_k d_k y_kᵀ (Σ_k w_k d_k = 0, so centring y is not needed); Q[i, j, n]
        self.Q = np.ascontiguousarray((flat @ wd).reshape(n, 3, 3).transpose(2, 1, 0))
        q = self.Q
        self.trQ = q[0, 0] + q[1, 1] + q[2, 2]
        self.m = np.stack([q[1, 2] - q[2, 1], q[2, 0] - q[0, 2], q[0, 1] - q[1, 0]])  # Σ w d × y, (3, N)
        self.Qs = q + q.transpose(1, 0, 2)

    @staticmethod
    def _take(a: np.ndarray, idx):
        return a if idx is None else a[..., idx]

    def cost(self, om: np.ndarray, idx, gy: _Gyro) -> tuple[np.ndarray, np.ndarray]:
        """Concentrated cost f_n(ω) (s, ω̇ eliminated; plus gyroscopes) and its rounding scale.

        ``om`` is (3, M); ``idx`` selects the M samples (None: all).
        """
        take = self._take
        q = np.einsum("im,im->m", om, om)
        s_om = self.S @ om
        w_s_w = np.einsum("im,im->m", om, s_om)
        wqw = np.einsum("im,ijm,jm->m", om, take(self.Q, idx), om)
        g = take(self.m, idx) + np.cross(om, s_om, axis=0)
        terms = (
            take(self.c, idx),
            -2.0 * wqw,
            2.0 * q * take(self.trQ, idx),
            q * q * self.trS,
            -q * w_s_w,
            -np.einsum("im,im->m", g, self.Jinv @ g),
            take(gy.w, idx) * q,
            -2.0 * np.einsum("im,im->m", om, take(gy.b, idx)),
            take(gy.c, idx),
        )
        f = sum(terms)
        # the terms cancel down to the (small) residual cost: its rounding error is about eps·Σ|terms|
        scale = sum(np.abs(x) for x in terms)
        return f, scale

    def grad_gn(self, om: np.ndarray, idx, gy: _Gyro) -> tuple[np.ndarray, np.ndarray]:
        """Half the gradient of f_n, (3, M), and its Gauss–Newton matrix, (M, 3, 3)."""
        take = self._take
        S, trS, Jinv = self.S, self.trS, self.Jinv
        q = np.einsum("im,im->m", om, om)
        s_om = S @ om
        w_s_w = np.einsum("im,im->m", om, s_om)
        g = take(self.m, idx) + np.cross(om, s_om, axis=0)
        jg = Jinv @ g
        wg = take(gy.w, idx)
        # (∂g/∂ω)ᵀ v = −S (ω × v) + (Sω) × v
        gwt_jg = -S @ np.cross(om, jg, axis=0) + np.cross(s_om, jg, axis=0)
        half_grad = (
            -np.einsum("ijm,jm->im", take(self.Qs, idx), om)
            + (2.0 * take(self.trQ, idx) + 2.0 * trS * q - w_s_w + wg) * om
            - q * s_om
            - gwt_jg
            - take(gy.b, idx)
        )
        # columns of ∂g/∂ω: ω × S e_a + e_a × Sω
        cols = [np.cross(om, np.broadcast_to(S[:, a : a + 1], om.shape), axis=0) + _cross_e(a, s_om) for a in range(3)]
        jcols = [Jinv @ c for c in cols]
        mdim = om.shape[1]
        gn = np.empty((mdim, 3, 3))
        diag = w_s_w + wg
        for a in range(3):
            for b in range(a, 3):
                v = (
                    q * S[a, b]
                    + 4.0 * trS * om[a] * om[b]
                    - 3.0 * (s_om[a] * om[b] + om[a] * s_om[b])
                    - np.einsum("im,im->m", cols[a], jcols[b])
                )
                if a == b:
                    v = v + diag
                gn[:, a, b] = v
                gn[:, b, a] = v
        return half_grad, gn

    def motion(self, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(s, ω̇), (N, 3) each, eliminated in closed form for the given ω (N, 3)."""
        om = omega.T
        g = self.m + np.cross(om, self.S @ om, axis=0)
        omega_dot = (self.Jinv @ g).T
        rb = self.rbar
        q = np.einsum("ni,ni->n", omega, omega)
        b_rbar = omega * (omega @ rb)[:, None] - q[:, None] * rb
        s = self.ybar - b_rbar - np.cross(omega_dot, rb)
        return s, omega_dot


def _lm_omega(acc_stats: _Accel, gy: _Gyro, omega: np.ndarray, max_iter: int, xtol: float):
    """Vectorised Levenberg–Marquardt on ω_n for all samples; returns (ω (N, 3), iterations, converged)."""
    om_all = np.array(omega, dtype=float).T.copy()  # (3, N)
    n = om_all.shape[1]
    f, _ = acc_stats.cost(om_all, None, gy)
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
        sel = None if idx.size == n else idx
        w = om_all if sel is None else om_all[:, idx]
        half_grad, gn = acc_stats.grad_gn(w, sel, gy)
        scale = np.maximum((gn[:, 0, 0] + gn[:, 1, 1] + gn[:, 2, 2]) / 3.0, tiny)
        lam_i = lam[idx]
        for a in range(3):
            gn[:, a, a] += lam_i * scale
        delta = -np.linalg.solve(gn, half_grad.T[:, :, None])[:, :, 0].T
        w_new = w + delta
        f_new, f_scale = acc_stats.cost(w_new, sel, gy)
        # accept a decrease, or a change within the rounding error of the cost: there the
        # (accurate) Gauss-Newton step is the better judge, and it only shrinks from then on
        ok = f_new <= f[idx] + 64.0 * _EPS * f_scale
        small = np.sqrt(np.einsum("im,im->m", delta, delta)) <= xtol * (1.0 + np.sqrt(np.einsum("im,im->m", w, w)))
        acc_idx = idx[ok]
        om_all[:, acc_idx] = w_new[:, ok]
        f[acc_idx] = f_new[ok]
        lam[idx] = np.where(ok, np.maximum(lam_i * 0.1, 1e-12), lam_i * 10.0)
        done = small | (lam[idx] > 1e10)
        converged[idx[small]] = True
        active[idx[done]] = False
    return om_all.T.copy(), it, converged


def _sum_wyy(y: np.ndarray, w_a: np.ndarray) -> np.ndarray:
    return np.einsum("nik,nik->nk", y, y) @ w_a


def _sample_costs(y, gyro, mask, w_a, w_g, positions, s, omega, omega_dot) -> np.ndarray:
    """Per-sample whitened cost, evaluated directly from the residuals (N,); y is (N, 3, K)."""
    n, _, k = y.shape
    a = _a_matrices(omega, omega_dot)
    e = y - s[:, :, None] - (a.reshape(n * 3, 3) @ positions.T).reshape(n, 3, k)
    cost = np.einsum("nik,nik->nk", e, e) @ w_a
    if gyro.shape[0]:
        eg = gyro - omega[None, :, :]
        cost += (w_g[:, None] * mask * np.einsum("gni,gni->gn", eg, eg)).sum(axis=0)
    return cost


def _motion_step(y, gy, w_a, positions, omega_start, max_iter, xtol, sum_wyy=None):
    stats = _Accel(y, w_a, positions, sum_wyy)
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
        (G, N, 3) angular rate per gyroscope triad [rad/s], body frame, calibrated; or None
        (then ``gyro_sigma`` is ignored, and ``omega0`` should be given).
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
    if isinstance(max_iter, (bool, np.bool_)) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer; got {max_iter!r}")
    if not (math.isfinite(float(xtol)) and xtol >= 0):
        raise ValueError(f"xtol must be finite and >= 0; got {xtol!r}")
    gy = _Gyro(gyro, mask, w_g)
    start = gy.mean() if omega0 is None else omega0
    y = _layout(acc)
    s, omega, omega_dot, it, conv = _motion_step(y, gy, w_a, positions, start, max_iter, xtol)
    cost = _sample_costs(y, gyro, mask, w_a, w_g, positions, s, omega, omega_dot)
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
    return np.tensordot(a, a, axes=([0, 1], [0, 1]))


def _layout(acc: np.ndarray) -> np.ndarray:
    """(K, N, 3) -> contiguous (N, 3, K), the layout in which every sum over triads is one GEMM."""
    return np.ascontiguousarray(acc.transpose(1, 2, 0))


def _positions_step(y, s, a, reference, r_ref):
    gram = np.tensordot(a, a, axes=([0, 1], [0, 1]))
    ev = np.linalg.eigvalsh(gram)
    if not np.all(np.isfinite(ev)) or ev[0] <= 1e-12 * max(ev[-1], np.finfo(float).tiny):
        raise ValueError(
            "the motion does not excite all three position axes: Σ A_nᵀA_n is singular "
            "(ω_n and ω̇_n must not be parallel for all samples; eq. 9)"
        )
    c = np.linalg.inv(gram)  # shared by all triads (Algorithm 1, line 10)
    n, _, k = y.shape
    a_flat = a.reshape(n * 3, 3)
    rhs = y.reshape(n * 3, k).T @ a_flat - (s.reshape(n * 3) @ a_flat)[None, :]  # Σ_n A_nᵀ(y_n^k − s_n)
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
    return _positions_step(_layout(acc), arrs["s"], a, reference, r_ref)


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
    max_iter: int = 1000,
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
    y = _layout(acc)
    sum_wyy = _sum_wyy(y, w_a)
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
        s, omega, omega_dot, _, _ = _motion_step(y, gy, w_a, positions, omega, lm_iter, lm_tol, sum_wyy)  # (a)
        cost = float(_sample_costs(y, gyro, mask, w_a, w_g, positions, s, omega, omega_dot).sum())
        a = _a_matrices(omega, omega_dot)
        new = _positions_step(y, s, a, reference, r_ref)  # (b)
        dr = float(np.max(np.linalg.norm(new[not_ref] - positions[not_ref], axis=1), initial=0.0))
        positions = new
        costs.append(cost)
        steps.append(dr)
        if progress is not None:
            progress(it, cost, dr)
        if dr < tol:
            converged = True
            break

    s, omega, omega_dot, _, _ = _motion_step(y, gy, w_a, positions, omega, lm_iter, lm_tol, sum_wyy)
    final = float(_sample_costs(y, gyro, mask, w_a, w_g, positions, s, omega, omega_dot).sum())
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

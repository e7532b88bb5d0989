"""Chip clocks: the sawtooth sample age of a chip that samples on its own clock, and how its beat
frequency ν and phase φ are found before the smooth fit (issue 11, item 4).

An array board reads all its chips at the same instant, but each chip samples on its own internal
clock (f_c, about 1 kHz on an MPU9150). At the board's read-out times t_k = k / f_r the returned
sample is a(t) = frac((t − t_0) f_c) / f_c old: a sawtooth of amplitude A = 1 / f_c at the aliased
beat ν = f_c − round(f_c / f_r) f_r, folded into (−f_r/2, f_r/2]. In the model it is

    a(t) = A (frac(ν t + φ) − ½),      A ≥ 0, ν signed (a falling sawtooth has ν < 0).

ν and φ enter non-smoothly (the wrap of frac), so they are estimated from the per-sample implied age
(the part of a triad's residual along the time derivative of its reading): a periodogram gives |ν|,
a grid over the sign, ν and φ then fits A by weighted least squares. A is afterwards a smooth
parameter of the fit (effect ``accelerometer.clock_beat``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def sawtooth(t, nu: float, phi: float) -> np.ndarray:
    """frac(ν t + φ) − ½ ∈ [−½, ½) at times t [s] (ν in Hz, φ in cycles)."""
    x = nu * np.asarray(t, float) + phi
    return x - np.floor(x) - 0.5


def implied_age(residual: list[np.ndarray], rate: list[np.ndarray], sigma: list[np.ndarray]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: the age a that best explains the residuals r = y − model ≈ −a u̇ of a chip's
    triads (accelerometer and gyroscope: lists of (N, 3) residuals, reading rates u̇ and σ's), and its
    weight Σ |u̇/σ|² (1/variance of a). NaN residuals (masked samples) carry no weight."""
    num, den = 0.0, 0.0
    for r, u, s in zip(residual, rate, sigma):
        ok = np.isfinite(r)
        w = np.where(ok, u / np.broadcast_to(s, u.shape) ** 2, 0.0)
        num = num - np.sum(w * np.where(ok, r, 0.0), axis=1)
        den = den + np.sum(w * u, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        age = np.where(den > 0, num / den, 0.0)
    return age, np.asarray(den, float)


def periodogram(t, age, weight, oversample: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares periodogram of ``age`` (a constant and a sinusoid fitted at every
    frequency), for samples on a uniform grid of step Δt = median(diff(t)) (gaps allowed).

    Returns the frequencies [Hz] from 1/(oversample · duration) to 1/(2 Δt), the fraction of the
    weighted variance the sinusoid explains, and its amplitude [s]. The weighted sums of cos, sin
    and their products are zero-padded FFTs of the weights and of the weighted age."""
    t, age, w = (np.asarray(x, float) for x in (t, age, weight))
    dt = float(np.median(np.diff(t)))
    idx = np.round((t - t[0]) / dt).astype(int)
    M = int(2 ** np.ceil(np.log2(oversample * (idx[-1] + 1))))
    W, A = np.zeros(M), np.zeros(M)
    np.add.at(W, idx, w / w.sum())
    a = age - (w / w.sum()) @ age
    np.add.at(A, idx, w / w.sum() * a)
    FW, FA = np.fft.fft(W), np.fft.fft(A)  # Σ w e^{-iθ}, θ = 2π f t (the double angle at index 2k mod M)
    k = np.arange(1, M // 2)
    C1, S1, C2, S2 = FW[k].real, -FW[k].imag, FW[2 * k % M].real, -FW[2 * k % M].imag
    G = np.empty((len(k), 3, 3))
    G[:, 0] = np.stack([np.ones(len(k)), C1, S1], axis=1)
    G[:, 1] = np.stack([C1, (1 + C2) / 2, S2 / 2], axis=1)
    G[:, 2] = np.stack([S1, S2 / 2, (1 - C2) / 2], axis=1)
    rhs = np.stack([np.zeros(len(k)), FA[k].real, -FA[k].imag], axis=1)
    beta = np.linalg.solve(G, rhs[..., None])[..., 0]
    freqs = k / (M * dt)
    keep = freqs <= 0.5 / dt
    frac = np.einsum("fi,fi->f", beta, rhs) / ((w / w.sum()) @ (a * a))
    return freqs[keep], frac[keep], np.hypot(beta[:, 1], beta[:, 2])[keep]


@dataclass(frozen=True)
class Beat:
    """A chip's sawtooth age found from its implied age: ν [Hz], φ [cycles], A [s], the fraction of
    the implied age's weighted variance it explains, and the false-alarm probability of its
    periodogram peak among all frequencies searched (:func:`peak_p_value`)."""

    nu: float
    phi: float
    amplitude: float
    explained: float
    p: float = 1.0

    def to_dict(self) -> dict:
        return {"frequency_Hz": self.nu, "phase_cycles": self.phi, "amplitude_s": self.amplitude,
                "explained": self.explained, "peak_p_value": self.p}


def peak_p_value(fraction: float, n: int, bandwidth: float) -> float:
    """Probability that white noise of n samples puts a periodogram peak as high as ``fraction``
    anywhere in the searched band: with z = (n − 1) · fraction / 2 (half the sinusoid's Δχ², χ²(2)/2
    at one frequency), Baluev's (2008) bound for a continuous search, P ≈ e^−z (1 + W √z), W the
    band width times the duration (``bandwidth``: about n/2 for a uniform series)."""
    z = (n - 1) * fraction / 2
    return float(min(1.0, np.exp(-z) * (1 + bandwidth * np.sqrt(z))))


def _grid(t, a, W, nus, phis):
    """Best (ν, φ, A, explained weighted variance) of the sawtooth on a grid; A and a constant by
    weighted least squares."""
    best = (0.0, 0.0, 0.0, -np.inf)
    for nu in nus:
        p = sawtooth(t[None, :], nu, phis[:, None])
        p = p - (p @ W)[:, None]
        num, den = p @ (W * a), (p * p) @ W
        gain = num * num / np.maximum(den, 1e-12)
        j = int(np.argmax(gain))
        if gain[j] > best[3]:
            best = (float(nu), float(phis[j]), float(num[j] / den[j]), float(gain[j]))
    return best


def estimate_beat(t, age, weight) -> Beat:
    """ν, φ and A of the sawtooth in an implied-age series (module docstring): the periodogram's
    peak, then a grid over the sign and ±2 periodogram steps of ν and over φ, refined tenfold. Only
    beats that wrap at least once over the series are searched (|ν| ≥ 1/duration); an age that
    changes more slowly is a clock drift."""
    t = np.asarray(t, float)
    freqs, frac, _ = periodogram(t, age, weight)
    df = freqs[1] - freqs[0]
    frac = np.where(freqs >= 1 / (t[-1] - t[0]), frac, 0.0)  # a slower beat never wraps: a drift, not a sawtooth
    nu0 = freqs[int(np.argmax(frac))]
    p = peak_p_value(float(np.max(frac)), int(np.count_nonzero(np.asarray(weight) > 0)), freqs[-1] * (t[-1] - t[0]))
    W = np.asarray(weight, float) / np.sum(weight)
    a = np.asarray(age, float) - W @ age
    steps = np.arange(-2, 2.001, 0.2) * df
    nu, phi, A, _ = _grid(t, a, W, np.concatenate([-nu0 + steps, nu0 + steps]), np.arange(0, 1, 0.02))
    nu, phi, A, gain = _grid(t, a, W, nu + steps / 10, phi + np.arange(-0.02, 0.0201, 0.002))
    if A < 0:  # the same sawtooth: A (frac(x) − ½) = −A (frac(−x) − ½)
        nu, phi, A = -nu, -phi, -A
    return Beat(nu, phi % 1.0, A, gain / (W @ (a * a)), p)


def estimate_beats(t, ages: dict[str, tuple[np.ndarray, np.ndarray]], rounds: int = 2) -> dict[str, Beat]:
    """Every chip's sawtooth from its implied age relative to the array's mean (name -> (age,
    weight)). The mean carries 1/K of every other chip's sawtooth into each chip's series (K chips);
    after a first :func:`estimate_beat` per chip, that share of the others' fitted sawtooths is added
    back and the beats estimated again, ``rounds`` times."""
    beats = {n: estimate_beat(t, a, w) for n, (a, w) in ages.items()}
    K = len(ages)
    if K < 2:
        return beats
    for _ in range(rounds):
        full = {n: b.amplitude / (1 - 1 / K) * sawtooth(t, b.nu, b.phi) for n, b in beats.items()}
        total = sum(full.values())
        beats = {n: estimate_beat(t, a + (total - full[n]) / K, w) for n, (a, w) in ages.items()}
    return beats

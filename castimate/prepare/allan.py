"""Noise characterisation of static data: the Allan deviation and its three noise terms.

For a rate signal x sampled every τ0 and a cluster time τ = m τ0, the overlapping Allan variance
(IEEE Std 952-1997, annex C, eq. C.2) is

    AVAR(τ) = 1 / (2 τ² (n - 2m)) Σ_k (θ_{k+2m} - 2 θ_{k+m} + θ_k)²,   θ_k = τ0 Σ_{i<k} x_i.

Each static segment contributes its own sums (the orientation differs between poses, so a segment's
constant offset must not enter); the pooled AVAR at τ is the sum over the segments that are longer
than 2τ divided by their number of terms.

The three terms of the IEEE 952 model, AVAR(τ) = N²/τ + (2 ln 2/π) B² + K² τ/3, are read off it
(:func:`fit_noise_terms`):

- N, the white-noise density (angle/velocity random walk), in unit/√Hz: σ(1 s) for pure white noise;
  a white sequence of per-sample σ_d at rate f has N = σ_d / √f. Kalibr's ``*_noise_density``.
- B, the bias instability (flicker floor), reported from the minimum of σ(τ) as σ_min / 0.664.
- K, the rate random walk, in unit·√Hz/s: Kalibr's ``*_random_walk``. When the data are too short
  for the +1/2 slope to show, the bound K ≤ σ(τ_max) √(3 / τ_max) is then
  reported instead (``random_walk_resolved`` false).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

#: σ_min / B for a flicker floor: sqrt(2 ln 2 / π) (IEEE 952, table C.2).
FLICKER_FACTOR = float(np.sqrt(2 * np.log(2) / np.pi))


def cluster_sizes(n: int, per_decade: int = 10) -> np.ndarray:
    """Cluster sizes m, logarithmically spaced from 1 up to n // 10 (beyond it an AVAR rests on
    fewer than about five independent differences)."""
    top = max(n // 10, 1)
    m = np.unique(np.round(np.logspace(0, np.log10(top), max(int(per_decade * np.log10(top)) + 1, 1))).astype(int))
    return m[m >= 1]


def allan_variance(segments: Sequence[np.ndarray], dt: float, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pooled overlapping Allan variance (IEEE 952, eq. C.2) of rate segments, each (n_s, C).

    Returns AVAR (len(m), C) and the number of terms (len(m),) behind each value (0: no segment
    has 2 m samples; AVAR is NaN there).
    """
    C = np.asarray(segments[0]).reshape(len(segments[0]), -1).shape[1]
    num, cnt = np.zeros((len(m), C)), np.zeros(len(m))
    for x in segments:
        x = np.asarray(x, float).reshape(len(x), -1)
        theta = np.vstack([np.zeros((1, C)), np.cumsum(x, axis=0) * dt])
        n = len(x)
        for i, mi in enumerate(m):
            if 2 * mi > n:
                continue
            d = theta[2 * mi:] - 2 * theta[mi:n + 1 - mi] + theta[:n + 1 - 2 * mi]
            num[i] += (d ** 2).sum(axis=0) / (2 * (mi * dt) ** 2)
            cnt[i] += len(d)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / cnt[:, None], cnt


@dataclass(frozen=True)
class NoiseTerms:
    """The IEEE 952 noise terms of one channel (units of the rate: m/s² or rad/s)."""

    noise_density: float  # N, unit/√Hz
    bias_instability: float  # B, unit
    random_walk: float  # K, unit·√Hz/s (or its bound, see random_walk_resolved)
    random_walk_resolved: bool
    tau_min_deviation: float  # τ [s] at the minimum of σ(τ)


def fit_noise_terms(tau: np.ndarray, adev: np.ndarray) -> NoiseTerms:
    """N, B, K of one channel from its Allan deviation at cluster times tau (IEEE 952, annex C).

    N is read off the -1/2 slope: the median of σ(τ)√τ over the points before the minimum whose
    local log-log slope is within ±1/4 of -1/2 (the point with the slope nearest -1/2 if none).
    K is read off the +1/2 slope after the minimum: the median of σ(τ)√(3/τ) over the points with
    slope within ±1/4 of +1/2; if there are none the data are too short to see it and the bound
    σ(τ_max)√(3/τ_max) is reported (``random_walk_resolved`` false). B is σ_min / 0.664.
    """
    ok = np.isfinite(adev) & (adev > 0)
    tau, s = tau[ok], adev[ok]
    slope = np.gradient(np.log(s), np.log(tau)) if len(s) > 1 else np.array([-0.5])
    i = int(np.argmin(s))
    white = np.flatnonzero((np.arange(len(s)) <= i) & (np.abs(slope + 0.5) <= 0.25))
    if not len(white):
        white = [int(np.argmin(np.abs(slope[:i + 1] + 0.5)))]
    walk = np.flatnonzero((np.arange(len(s)) > i) & (np.abs(slope - 0.5) <= 0.25))
    N = float(np.median(s[white] * np.sqrt(tau[white])))
    K = float(np.median(s[walk] * np.sqrt(3 / tau[walk]))) if len(walk) else float(s[-1] * np.sqrt(3 / tau[-1]))
    return NoiseTerms(N, float(s[i] / FLICKER_FACTOR), K, bool(len(walk)), float(tau[i]))


@dataclass(frozen=True)
class AllanResult:
    """Allan deviation of one sensor (3 axes) over pooled static segments."""

    tau: np.ndarray  # (K,) s
    adev: np.ndarray  # (K, 3)
    terms: tuple[NoiseTerms, NoiseTerms, NoiseTerms]  # per axis
    rate: float  # Hz
    duration: float  # s, total data used
    longest: float  # s, the longest segment

    def axis_max(self, field: str) -> float:
        """The largest of the three axes' values of a term (what a single-number yaml wants)."""
        return max(getattr(t, field) for t in self.terms)


def allan_deviation(segments: Sequence[np.ndarray], dt: float, per_decade: int = 10) -> AllanResult:
    """Allan deviation and noise terms of rate data (segments (n_s, 3) sampled every dt s)."""
    n = max(len(s) for s in segments)
    m = cluster_sizes(n, per_decade)
    avar, cnt = allan_variance(segments, dt, m)
    keep = cnt > 0
    tau, avar = m[keep] * dt, avar[keep]
    T = sum(len(s) for s in segments) * dt
    adev = np.sqrt(avar)
    terms = tuple(fit_noise_terms(tau, adev[:, c]) for c in range(adev.shape[1]))
    return AllanResult(tau, adev, terms, 1 / dt, T, n * dt)

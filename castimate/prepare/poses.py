"""Pose averages: per-triad means of each static segment with the σ of the mean.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from castimate.errors import InputError
from castimate.io.recording import Recording
from .detect import Detection, resolve_triads, sample_period


# --------------------------------------------------------------------------------------------
# Pose averages
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PoseAverages:
    """Per-pose means of a static session and their noise.

    P poses. All dicts map triad name -> array.

    Attributes
    ----------
    triads
        Triad names, in order.
    acc_mean
        (P, 3) mean specific force per pose, m/s² (uncalibrated readings).
    acc_sigma
        (P, 3) standard deviation of each mean, m/s² (= ``acc_sigma_sample / sqrt(n)``).
    acc_sigma_sample
        (3,) white-noise-equivalent per-sample σ per axis, m/s².
    gyro_mean, gyro_sigma, gyro_sigma_sample
        Same for the angular rate, rad/s; only triads with gyroscopes.
    n
        (P,) samples per pose.
    t_start, t_end
        (P,) pose start and end times, s.
    segments
        The sample index ranges averaged (empty if built from given means).
    sigma_dof
        Degrees of freedom of the σ estimates (0 when σ was given, not estimated).
    temp_mean
        (P,) mean temperature per pose, K; only triads with a logged temperature.
    """

    triads: tuple[str, ...]
    acc_mean: dict[str, np.ndarray]
    acc_sigma: dict[str, np.ndarray]
    acc_sigma_sample: dict[str, np.ndarray]
    n: np.ndarray
    t_start: np.ndarray
    t_end: np.ndarray
    gyro_mean: dict[str, np.ndarray] = field(default_factory=dict)
    gyro_sigma: dict[str, np.ndarray] = field(default_factory=dict)
    gyro_sigma_sample: dict[str, np.ndarray] = field(default_factory=dict)
    segments: list[tuple[int, int]] = field(default_factory=list)
    sigma_dof: int = 0
    temp_mean: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_poses(self) -> int:
        return len(self.n)

    def take(self, idx) -> "PoseAverages":
        """The poses ``idx`` only (e.g. a cross-validation fold)."""
        idx = np.asarray(idx)
        pick = lambda d: {k: v[idx] for k, v in d.items()}  # noqa: E731
        return replace(self, acc_mean=pick(self.acc_mean), acc_sigma=pick(self.acc_sigma),
                       gyro_mean=pick(self.gyro_mean), gyro_sigma=pick(self.gyro_sigma), n=self.n[idx],
                       t_start=self.t_start[idx], t_end=self.t_end[idx],
                       segments=[self.segments[i] for i in idx] if self.segments else [],
                       temp_mean=pick(self.temp_mean))


def _batch_means_variance(x: np.ndarray, segments: Sequence[tuple[int, int]],
                          n_blocks: int) -> tuple[np.ndarray, int]:
    """Pooled white-noise-equivalent per-sample variance of each column of ``x`` by batch means.

    Each segment is cut into ``n_blocks`` blocks of length L (the remainder at the end dropped);
    ``L * var(block means)`` estimates σ² with ``n_blocks - 1`` degrees of freedom. The estimates
    are pooled weighted by their degrees of freedom, after discarding, per column, segments whose
    estimate exceeds the 99.9 % chi-square quantile relative to the median-based estimate (gross
    outliers, e.g. a tap on the table). Returns (variance per column, total degrees of freedom).
    """
    from scipy.special import chdtri  # the χ² quantiles as chi2.ppf computes them, without scipy.stats's 1 s import

    ests, dofs = [], []
    for a, b in segments:
        n = b - a
        B = min(n_blocks, n)
        if B < 2:
            continue
        L = n // B
        blocks = np.asarray(x[a:a + B * L], dtype=float).reshape(B, L, -1).mean(axis=1)
        ests.append(blocks.var(axis=0, ddof=1) * L)
        dofs.append(B - 1)
    ncol = x.shape[1]
    if not ests:
        return np.full(ncol, np.nan), 0
    E = np.array(ests)                     # (S, C)
    D = np.array(dofs, dtype=float)        # (S,)
    out = np.empty(ncol)
    total_dof = int(D.sum())
    for c in range(ncol):
        e = E[:, c]
        ok = np.isfinite(e)
        if len(e) >= 3:
            # median of s²·χ²_k/k is σ²·median(χ²_k)/k; undo that bias to get a robust reference
            ref = np.median(e[ok] / (chdtri(D[ok], 0.5) / D[ok])) if ok.any() else np.nan
            ok &= e <= ref * chdtri(D, 0.001) / D
        out[c] = np.sum(D[ok] * e[ok]) / np.sum(D[ok]) if ok.any() else np.nan
        total_dof = min(total_dof, int(D[ok].sum()))
    return out, total_dof


def average_poses(rec: Recording, detection: Detection, triads: Sequence[str] | None = None,
                  n_blocks: int = 8) -> PoseAverages:
    """Average each segment of ``detection`` per triad and estimate the noise from the data.

    Parameters
    ----------
    rec
        The recording the detection was made on.
    detection
        From :func:`detect_static` or :func:`explicit_segments`.
    triads
        Triads to average; default all accelerometer triads.
    n_blocks
        Blocks per segment for the batch-means noise estimate (default 8).
    """
    names = resolve_triads(rec, triads)
    if n_blocks < 2:
        raise ValueError("n_blocks must be at least 2")
    segs = [(int(a), int(b)) for a, b in detection.segments]
    N = len(rec.t)
    for a, b in segs:
        if not 0 <= a < b <= N:
            raise InputError(rec.source, "segments", f"segment ({a}, {b}) is outside the recording "
                                                     f"of {N} samples")
    t = np.asarray(rec.t, dtype=float)
    dt = sample_period(t)
    n = np.array([b - a for a, b in segs], dtype=int)

    def do(src: dict[str, np.ndarray]):
        mean, sig, sig_s = {}, {}, {}
        dof = 0
        for k in names:
            if k not in src:
                continue
            x = np.asarray(src[k], dtype=float)
            mean[k] = (np.array([np.mean(x[a:b], axis=0) for a, b in segs]) if segs
                       else np.zeros((0, 3)))
            var, dof = _batch_means_variance(x, segs, n_blocks)
            sig_s[k] = np.sqrt(var)
            sig[k] = sig_s[k][None, :] / np.sqrt(n)[:, None]
        return mean, sig, sig_s, dof

    am, asg, ass, dof = do(rec.acc)
    gm, gsg, gss, _ = do(rec.gyro)
    return PoseAverages(
        triads=tuple(names),
        acc_mean=am, acc_sigma=asg, acc_sigma_sample=ass,
        gyro_mean=gm, gyro_sigma=gsg, gyro_sigma_sample=gss,
        n=n,
        t_start=np.array([t[a] for a, _ in segs], dtype=float),
        t_end=np.array([t[b - 1] + dt for _, b in segs], dtype=float),
        segments=segs,
        sigma_dof=dof,
        temp_mean={k: np.array([np.mean(v[a:b]) for a, b in segs]) for k, v in rec.temp.items() if k in names},
    )


def pose_averages_from_means(acc_mean: Mapping[str, Any], n: Any, acc_sigma_sample: Any,
                             gyro_mean: Mapping[str, Any] | None = None,
                             gyro_sigma_sample: Any = None, *,
                             t_start: Any = None, t_end: Any = None, temp_mean: Mapping[str, Any] | None = None,
                             source: object = "", where: str = "") -> PoseAverages:
    """Build :class:`PoseAverages` from data that is already averaged per pose.

    Parameters
    ----------
    acc_mean
        Triad name -> (P, 3) mean specific force, m/s².
    n
        Samples per pose: an integer (same for all) or (P,).
    acc_sigma_sample
        Per-sample σ, m/s²: a number, a (3,) array, or a dict triad name -> number or (3,).
    gyro_mean, gyro_sigma_sample
        The same for the angular rate (rad/s), optional; only for the triads with gyroscopes.
    t_start, t_end
        (P,) pose times, s; default NaN.
    temp_mean
        Triad name -> (P,) mean temperature per pose, K, where logged.
    source, where
        For error messages.

    Raises
    ------
    InputError
        On a shape mismatch, a non-positive n or σ, or a σ for an unknown triad.
    """
    def loc(*parts: str) -> str:
        return ".".join(p for p in (where, *parts) if p)

    if not isinstance(acc_mean, Mapping) or not acc_mean:
        raise InputError(source, loc("acc_mean"), "expected a mapping triad -> (P, 3) means")
    names = list(acc_mean)

    def means(d: Mapping[str, Any], key: str) -> tuple[dict[str, np.ndarray], int]:
        out, P = {}, None
        for k, v in d.items():
            a = np.asarray(v, dtype=float)
            if a.ndim == 1 and a.shape == (3,):
                a = a[None, :]
            if a.ndim != 2 or a.shape[1] != 3:
                raise InputError(source, loc(key, k), f"expected shape (P, 3), found {a.shape}")
            if not np.all(np.isfinite(a)):
                raise InputError(source, loc(key, k), "expected finite values")
            if P is not None and a.shape[0] != P:
                raise InputError(source, loc(key, k), f"expected {P} poses like the other triads, "
                                                      f"found {a.shape[0]}")
            P = a.shape[0]
            out[k] = a
        return out, P

    am, P = means(acc_mean, "acc_mean")
    gm: dict[str, np.ndarray] = {}
    if gyro_mean:
        gm, Pg = means(gyro_mean, "gyro_mean")
        if Pg != P:
            raise InputError(source, loc("gyro_mean"), f"expected {P} poses like acc_mean, found {Pg}")
        for k in gm:
            if k not in am:
                raise InputError(source, loc("gyro_mean", k), "triad has no acc_mean")

    nn = np.asarray(n)
    if nn.ndim == 0:
        nn = np.full(P, nn)
    if nn.shape != (P,):
        raise InputError(source, loc("n"), f"expected a number or shape ({P},), found {nn.shape}")
    if not np.all(np.isfinite(nn.astype(float))) or np.any(nn <= 0):
        raise InputError(source, loc("n"), "expected positive sample counts")
    nf = nn.astype(float)

    def sigmas(s: Any, triads: list[str], key: str) -> dict[str, np.ndarray]:
        if isinstance(s, Mapping):
            for k in s:
                if k not in triads:
                    raise InputError(source, loc(key, str(k)), f"unknown triad; expected one of {', '.join(triads)}")
            missing = [k for k in triads if k not in s]
            if missing:
                raise InputError(source, loc(key), f"missing σ for triad(s) {', '.join(missing)}")
            items = {k: s[k] for k in triads}
        else:
            items = {k: s for k in triads}
        out = {}
        for k, v in items.items():
            a = np.asarray(v, dtype=float)
            if a.ndim == 0:
                a = np.full(3, float(a))
            if a.shape != (3,):
                raise InputError(source, loc(key, k), f"expected a number or shape (3,), found {a.shape}")
            if not np.all(np.isfinite(a)) or np.any(a <= 0):
                raise InputError(source, loc(key, k), f"expected positive σ, found {a.tolist()}")
            out[k] = a
        return out

    if acc_sigma_sample is None:
        raise InputError(source, loc("acc_sigma_sample"), "expected the per-sample σ")
    ass = sigmas(acc_sigma_sample, names, "acc_sigma_sample")
    gss = {}
    if gm:
        if gyro_sigma_sample is None:
            raise InputError(source, loc("gyro_sigma_sample"), "expected the per-sample σ of the gyroscopes")
        gss = sigmas(gyro_sigma_sample, list(gm), "gyro_sigma_sample")

    def times(x: Any, key: str) -> np.ndarray:
        if x is None:
            return np.full(P, np.nan)
        a = np.asarray(x, dtype=float)
        if a.shape != (P,):
            raise InputError(source, loc(key), f"expected shape ({P},), found {a.shape}")
        return a

    return PoseAverages(
        triads=tuple(names),
        acc_mean=am,
        acc_sigma={k: ass[k][None, :] / np.sqrt(nf)[:, None] for k in names},
        acc_sigma_sample=ass,
        gyro_mean=gm,
        gyro_sigma={k: gss[k][None, :] / np.sqrt(nf)[:, None] for k in gm},
        gyro_sigma_sample=gss,
        n=nn.astype(int),
        t_start=times(t_start, "t_start"),
        t_end=times(t_end, "t_end"),
        segments=[],
        sigma_dof=0,
        temp_mean={k: times(v, f"temp_mean.{k}") for k, v in (temp_mean or {}).items()},
    )

"""Static-pose detection and pose averaging.

The static multi-position calibration (Nilsson, Skog, Händel 2014; Tedaldi, Pretto, Menegatti
2014) needs the recording cut into *static poses*: intervals in which the array rests in one
orientation. This module finds them and averages each one.

Detection (:func:`detect_static`)
---------------------------------
The array is rigid, so every triad rests and moves at the same time. One statistic is built from
all triads jointly:

1. For every channel (triad x axis) the standard deviation over a sliding window of
   ``window`` seconds.
2. Each channel is divided by its own *noise floor*, a low quantile (``floor_quantile``) of its
   windowed standard deviation over the whole recording. A channel whose noise is twice as large
   thus weighs the same as the others.
3. The normalised channels are combined by their root mean square and scaled back to physical
   units by the RMS noise floor, giving one statistic in m/s² (and one in rad/s for the
   gyroscopes, when present).
4. The threshold is *adaptive*: ``threshold_factor`` times a low quantile of that statistic, i.e. a
   multiple of the noise floor estimated from the data itself, so sensors whose noise differs by
   10x need no tuning. A threshold given by the user overrides it.

A window is *quiet* when both statistics are below their thresholds; every sample inside a quiet
window is a static candidate (the union of quiet windows, so the candidates reach the real edges of
the rest). Candidates are the maximal runs of such samples. A quiet window may still hide the
slow start of a motion, so each candidate's edges are then moved inward by a mean-shift
change-point test (:func:`_refine_edges`, over at least 2 x ``REFINE_SPAN`` at each edge, repeated on
what it leaves until the edges stop moving), which is far more sensitive than the standard deviation. Each candidate is then accepted or rejected with a
reason, in this order:

- *merged*: a candidate that follows the previous one after a gap of at most ``merge_gap`` seconds
  and whose mean specific-force direction differs from it by less than ``min_separation_deg`` is
  the same pose (interrupted, e.g. by a tap on the table); the two are merged into one segment
  spanning the gap, and the later candidate is listed in ``rejected`` with the reason
  ``"merged with previous (...)"``;
- *too short*: the candidate lasts less than ``min_duration`` seconds;
- ``trim`` seconds are cut off each end (*too short* as well if fewer than 2 samples remain);
- *drifting*: the mean specific force of the second half differs from that of the first half
  by more than ``max_drift`` m/s² and by more than ``drift_sigmas`` times its noise (median over
  triads of the norm of the change; its noise from the median triad's floor);

Without tuning (the defaults) the window, the minimum hold and the trim follow the data: a window
of 0.5 s, at least 10 samples, and longer for noisy data, long enough that a slow 5°/s turn raises
the windowed standard deviation (g ω w / √12 for a ramp) by the threshold's margin over the noise
floor; a minimum hold of two windows; a trim of 1/8 of each candidate up to 0.5 s. Holds from about 1 s (imu_tk's 100 samples at 100 Hz) to minutes are
accepted, and the edge refinement and the drift test keep slow motion out of them.
- *rotating* (only with ``max_gyro``): the mean angular rate, after removing each triad's median
  over all candidates (its bias), exceeds ``max_gyro`` rad/s.

An accepted segment whose direction is within ``min_separation_deg`` of an earlier accepted one,
but which was not merged (the gap is long), is kept and noted as a *repeated orientation*.

Averaging (:func:`average_poses`)
---------------------------------
Per triad and segment the mean specific force (and angular rate). The noise of each mean is
estimated from the data by *batch means*: each segment is cut into ``n_blocks`` blocks of length
L; ``L * var(block means)`` estimates the white-noise-equivalent per-sample variance, including
slowly correlated noise. These estimates are pooled over the segments (weighted by their
degrees of freedom, after discarding segments that are gross outliers), giving per triad and
axis a per-sample σ; the σ of a segment mean is σ/sqrt(n).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from castimate.errors import InputError
from castimate.io.recording import Recording
from castimate.validation import Check
from .options import (AUTO_MIN_WINDOWS, AUTO_SLOW_TURN, AUTO_TRIM_FRACTION, AUTO_TRIM_MAX, AUTO_WINDOW,
                      AUTO_WINDOW_MAX, AUTO_WINDOW_SAMPLES, DetectionOptions)

__all__ = [
    "DetectionOptions",
    "Detection",
    "detect_static",
    "explicit_segments",
]

#: Fewest samples an explicitly given segment may hold.
MIN_EXPLICIT_SAMPLES = 10


# --------------------------------------------------------------------------------------------
# Detection result
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Detection:
    """Static segments of a recording and how they were found.

    Attributes
    ----------
    segments
        Accepted segments as sample index ranges ``(start, stop)``, stop exclusive, after trimming,
        in time order. One segment = one pose.
    rejected
        Candidates not accepted as poses, ``(start, stop, reason)``: their sample ranges before
        trimming, in time order. A reason starting with ``"merged"`` means the samples became part
        of the previous segment (which then spans the gap between them).
    window, min_duration
        The window of the motion statistic and the shortest accepted hold, s, as used (given or
        automatic; None for explicit segments).
    threshold
        Threshold of the specific-force statistic, m/s² (None for explicit segments).
    gyro_threshold
        Threshold of the angular-rate statistic, rad/s (None if the gyroscopes were not used).
    threshold_method
        How the thresholds were chosen (``"adaptive: ..."``, ``"given"``, ``"explicit ..."``).
    noise_floor, gyro_noise_floor
        The noise floors estimated from the data (m/s², rad/s), where computed.
    notes
        Remarks on accepted segments, ``(segment index, text)``, e.g. repeated orientations.
    segment_times, rejected_times
        ``(t_start, t_end)`` in seconds of each entry of ``segments`` / ``rejected``.
    t_range
        First and last sample time of the recording, s.
    source
        The recording's source, for messages.
    statistic, gyro_statistic
        The combined windowed statistic per sample (m/s², rad/s), for plots; None if not computed.
    """

    segments: list[tuple[int, int]]
    rejected: list[tuple[int, int, str]] = field(default_factory=list)
    window: float | None = None
    min_duration: float | None = None
    threshold: float | None = None
    gyro_threshold: float | None = None
    threshold_method: str = ""
    noise_floor: float | None = None
    gyro_noise_floor: float | None = None
    notes: list[tuple[int, str]] = field(default_factory=list)
    segment_times: list[tuple[float, float]] = field(default_factory=list)
    rejected_times: list[tuple[float, float]] = field(default_factory=list)
    t_range: tuple[float, float] = (0.0, 0.0)
    source: str = ""
    statistic: np.ndarray | None = field(default=None, repr=False, compare=False)
    gyro_statistic: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def n_poses(self) -> int:
        return len(self.segments)

    def summary(self) -> str:
        """A multi-line, human-readable account: thresholds, then every candidate in time order."""
        lines = []
        src = f" in {self.source}" if self.source else ""
        lines.append(f"Static-segment detection{src} ({self.t_range[0]:.2f} s to {self.t_range[1]:.2f} s)")
        if self.threshold is not None:
            lines.append(f"  threshold: {self.threshold:.4g} m/s² (specific force)"
                         + (f", {self.gyro_threshold:.4g} rad/s (angular rate)"
                            if self.gyro_threshold is not None else ""))
        if self.threshold_method:
            lines.append(f"  chosen by: {self.threshold_method}")
        lines.append(f"  {len(self.segments)} poses accepted, {len(self.rejected)} candidates not accepted")
        notes: dict[int, list[str]] = {}
        for i, text in self.notes:
            notes.setdefault(i, []).append(text)
        entries = []
        for i, ((a, b), (t0, t1)) in enumerate(zip(self.segments, self.segment_times)):
            text = f"pose {i + 1:3d}: {t0:9.2f} s to {t1:9.2f} s ({t1 - t0:6.2f} s, {b - a} samples)"
            if i in notes:
                text += "; " + "; ".join(notes[i])
            entries.append((t0, "  " + text))
        for (a, b, reason), (t0, t1) in zip(self.rejected, self.rejected_times):
            entries.append((t0, f"  {'-' if reason.startswith('merged') else 'x'}"
                                f"         {t0:9.2f} s to {t1:9.2f} s: {reason}"))
        entries.sort(key=lambda e: e[0])
        lines.extend(e[1] for e in entries)
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()


# --------------------------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------------------------

def resolve_triads(rec: Recording, triads: Sequence[str] | None, where: str = "triads") -> list[str]:
    if triads is None:
        names = list(rec.acc)
    else:
        if isinstance(triads, str):
            triads = [triads]
        names = list(triads)
        for name in names:
            if name not in rec.acc:
                raise InputError(rec.source, where,
                                 f"triad {name!r} is not in the recording; it has {', '.join(rec.acc) or 'none'}")
    if not names:
        raise InputError(rec.source, where, "no accelerometer triads to use")
    return names


def sample_period(t: np.ndarray) -> float:
    if len(t) < 2:
        return 1.0
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 1.0


def _windowed_std(x: np.ndarray, w: int) -> np.ndarray:
    """Standard deviation of each column over windows ``[k, k+w)``, k = 0..N-w; shape (N-w+1, C).

    Windows containing a non-finite sample get +inf (never quiet).
    """
    x = np.asarray(x, dtype=float)
    bad = ~np.isfinite(x)
    flagged = bad.any()  # else the columns' medians at once and no count of bad samples
    med = np.array([np.median(col[np.isfinite(col)]) if np.isfinite(col).any() else 0.0
                    for col in x.T]) if flagged else np.median(x, axis=0)
    xc = x - med
    if flagged:
        xc[bad] = 0.0
    c1, c2 = np.zeros((2, len(x) + 1, x.shape[1]))
    np.cumsum(xc, axis=0, out=c1[1:])
    np.cumsum(np.square(xc, out=xc), axis=0, out=c2[1:])
    s1 = c1[w:] - c1[:-w]
    var = (c2[w:] - c2[:-w] - s1 * s1 / w) / (w - 1)
    std = np.sqrt(np.maximum(var, 0.0, out=var), out=var)
    if flagged:
        cb = np.concatenate([np.zeros((1, x.shape[1]), int), np.cumsum(bad, axis=0)])
        std[(cb[w:] - cb[:-w]) > 0] = np.inf
    return std


def _channel_floors(std: np.ndarray, q: float) -> np.ndarray:
    """The noise floor of each channel: quantile q of its finite windowed standard deviations."""
    floors = np.zeros(std.shape[1])
    for c in range(std.shape[1]):
        col = std[:, c]
        col = col[np.isfinite(col)]
        floors[c] = np.quantile(col, q) if len(col) else 0.0
    return floors


def _combine(std: np.ndarray, q: float) -> tuple[np.ndarray, float]:
    """Normalise each channel by its noise floor, combine by RMS, rescale to physical units.

    Returns the combined statistic per window and the RMS of the channel floors.
    """
    floors = _channel_floors(std, q)
    ok = floors > 0
    if not ok.any():
        # constant channels (e.g. quantised noise below one count): use raw RMS
        return np.sqrt(np.mean(std ** 2, axis=1)), 0.0
    scale = float(np.sqrt(np.mean(floors[ok] ** 2)))
    ratio = std[:, ok] / floors[ok]
    return scale * np.sqrt(np.mean(ratio ** 2, axis=1)), scale


def _direction_angle_deg(m1: np.ndarray, m2: np.ndarray) -> float:
    """Median over triads of the angle between two mean specific-force vectors (the rows of m1 and
    m2, one per triad), degrees."""
    na, nb = np.linalg.norm(m1, axis=1), np.linalg.norm(m2, axis=1)
    ok = (na > 0) & (nb > 0) & np.isfinite(na) & np.isfinite(nb)
    if not ok.any():
        return float("nan")
    c = np.clip(np.einsum("ij,ij->i", m1[ok], m2[ok]) / (na[ok] * nb[ok]), -1.0, 1.0)
    return float(np.median(np.degrees(np.arccos(c))))


#: The edges of a candidate are refined over at least 2 x this span, s, whatever the window: a short
#: window is blind to a slow motion (a ramp's standard deviation grows with the window), the mean-shift
#: test of the refinement is not.
REFINE_SPAN = 1.0
#: Refinements of a candidate's edges, each on what the previous one left, until they stop moving.
REFINE_PASSES = 4

#: Per-sample excess (in units of the mean normalised squared deviation) that an edge sample
#: must show, on average, to be cut off a candidate by :func:`_refine_edges`.
_EDGE_PENALTY = 0.5


def _refine_edges(x: np.ndarray, a0: int, b0: int, w: int) -> tuple[int, int]:
    """Move the edges of candidate ``[a0, b0)`` inward to where the motion really stops/starts.

    The windowed statistic is blind to a motion that starts slowly and is hidden in a window
    that is otherwise at rest, so a candidate can reach a little into the neighbouring motion.
    Near each edge (the outer ``m = min(2w, n/3)`` samples) every sample is compared with the
    mean and standard deviation of the adjacent stretch of rest, ``z_i = mean_c((x_ic - μ_c)/s_c)²
    - 1``, i.e. a mean-shift test that sees a departure from rest long before the standard
    deviation does. The edge is moved to the maximiser of the cumulative sum of
    ``z_i - penalty`` counted from the edge (a one-sided change-point estimate); at rest that sum
    only decreases, so the edge stays put.
    """
    n = b0 - a0
    m = min(2 * w, n // 3)
    if m < 2:
        return a0, b0
    r = min(2 * w, n - 2 * m)

    def excess(seg: np.ndarray, ref: np.ndarray) -> np.ndarray:
        mu = np.nanmean(ref, axis=0)
        sd = np.nanstd(ref, axis=0, ddof=1)
        ok = np.isfinite(sd) & (sd > 0)
        if not ok.any():
            return np.full(len(seg), -1.0)
        z = np.mean(((seg[:, ok] - mu[ok]) / sd[ok]) ** 2, axis=1) - 1.0 - _EDGE_PENALTY
        return np.where(np.isfinite(z), z, 10.0)

    # end edge: S[j] = sum of z over [b0 - m + j, b0)
    z = excess(x[b0 - m:b0], x[b0 - m - r:b0 - m])
    S = np.cumsum(z[::-1])[::-1]
    j = int(np.argmax(S))
    b = b0 - m + j if S[j] > 0 else b0
    # start edge: S[j] = sum of z over [a0, a0 + j + 1)
    z = excess(x[a0:a0 + m], x[a0 + m:a0 + m + r])
    S = np.cumsum(z)
    j = int(np.argmax(S))
    a = a0 + j + 1 if S[j] > 0 else a0
    return a, max(b, a)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist()))


def detect_static(rec: Recording, options: DetectionOptions = DetectionOptions(),
                  triads: Sequence[str] | None = None) -> Detection:
    """Find the static poses of a recording.

    Parameters
    ----------
    rec
        The recording (all selected triads are used jointly: the array is rigid).
    options
        Detection settings; see :class:`DetectionOptions`.
    triads
        Names of the triads to use; default all accelerometer triads. The gyroscopes of those
        triads are used when present (and ``options.use_gyro``).

    Returns
    -------
    Detection
        Accepted segments (trimmed, index ranges), rejected candidates with reasons, and the
        thresholds with how they were chosen. ``print(det.summary())`` explains the result.
    """
    names = resolve_triads(rec, triads)
    t = np.asarray(rec.t, dtype=float)
    N = len(t)
    dt = sample_period(t)
    t_range = (float(t[0]), float(t[-1])) if N else (0.0, 0.0)
    acc = np.concatenate([np.asarray(rec.acc[k], dtype=float) for k in names], axis=1)
    gyro_names = [k for k in names if k in rec.gyro] if options.use_gyro else []
    q = options.floor_quantile

    def window_samples(window: float) -> int:
        w = max(3, int(round(window / dt)))
        if N < w + 1:
            raise InputError(rec.source, "t", f"{N} samples are too few for a {window:g} s window "
                                              f"({w} samples); expected a longer recording")
        return w

    method, automatic = [], []
    if options.window is not None:
        w = window_samples(options.window)
        a_std = _windowed_std(acc, w)
        a_stat, a_scale = _combine(a_std, q)
    else:
        w = window_samples(max(AUTO_WINDOW, AUTO_WINDOW_SAMPLES * dt))
        a_std = _windowed_std(acc, w)
        a_stat, a_scale = _combine(a_std, q)
        # long enough for a slow turn to raise the windowed std (g ω w / √12 for a ramp) above the
        # threshold's margin over the noise floor
        slow = math.sqrt(12) * (options.threshold_factor - 1) * a_scale / (9.81 * math.radians(AUTO_SLOW_TURN))
        slow = min(slow, AUTO_WINDOW_MAX, N * dt / 4)  # a floor raised by motion everywhere must not run away
        if slow > w * dt:
            w = window_samples(slow)
            a_std = _windowed_std(acc, w)
            a_stat, a_scale = _combine(a_std, q)
        automatic.append(f"window: automatic, {w * dt:.3g} s ({w} samples; at least {AUTO_WINDOW:g} s, "
                      f"{AUTO_WINDOW_SAMPLES} samples, and up to {AUTO_WINDOW_MAX:g} s long enough for a "
                      f"{AUTO_SLOW_TURN:g}°/s turn to rise "
                      f"{options.threshold_factor - 1:g} x the noise floor {a_scale:.3g} m/s² above it)")
    # the per-sample noise of the drift test's statistic (a median over triads): the median triad's floor
    sigma_triad = float(np.median([np.sqrt(np.mean(np.square(_channel_floors(a_std[:, 3 * k:3 * k + 3], q))))
                                   for k in range(len(names))]))
    finite = np.isfinite(a_stat)
    a_floor = float(np.quantile(a_stat[finite], q)) if finite.any() else float("nan")
    if options.threshold is not None:
        a_thr = float(options.threshold)
        method.append(f"specific force: given ({a_thr:.4g} m/s²)")
    else:
        a_thr = options.threshold_factor * a_floor
        method.append(f"specific force: adaptive, {options.threshold_factor:g} x noise floor "
                      f"{a_floor:.4g} m/s² (quantile {q:g} of the {w * dt:.3g} s windowed std, "
                      f"RMS over {acc.shape[1]} channels normalised by their own floors)")
    quiet = a_stat < a_thr

    g_stat = g_floor = g_thr = None
    if gyro_names:
        gyro = np.concatenate([np.asarray(rec.gyro[k], dtype=float) for k in gyro_names], axis=1)
        g_std = _windowed_std(gyro, w)
        g_stat, _ = _combine(g_std, q)
        gf = np.isfinite(g_stat)
        g_floor = float(np.quantile(g_stat[gf], q)) if gf.any() else float("nan")
        if options.gyro_threshold is not None:
            g_thr = float(options.gyro_threshold)
            method.append(f"angular rate: given ({g_thr:.4g} rad/s)")
        else:
            g_thr = options.threshold_factor * g_floor
            method.append(f"angular rate: adaptive, {options.threshold_factor:g} x noise floor "
                          f"{g_floor:.4g} rad/s")
        quiet &= g_stat < g_thr

    min_duration, trim = options.min_duration, options.trim
    if min_duration is None:  # seen at rest by more than one window: a pause at the turn of a motion is not
        min_duration = AUTO_MIN_WINDOWS * w * dt
        automatic.append(f"minimum hold: automatic, {AUTO_MIN_WINDOWS} windows = {min_duration:.3g} s")
    if trim is None:
        automatic.append(f"trim: automatic, {AUTO_TRIM_FRACTION:g} of each candidate, at most {AUTO_TRIM_MAX:g} s")
    method += automatic

    # Every sample inside a quiet window is static: dilate the quiet windows [k, k+w).
    nwin = len(quiet)
    cq = np.concatenate([[0], np.cumsum(quiet)])
    i = np.arange(N)
    lo = np.clip(i - w + 1, 0, nwin)
    hi = np.clip(i + 1, 0, nwin)
    static = (cq[hi] - cq[lo]) > 0

    def per_sample(stat):
        out = np.full(N, np.nan)
        if stat is not None:
            out[w // 2: w // 2 + len(stat)] = stat
        return out

    candidates = _runs(static)

    def tt(a: int, b: int) -> tuple[float, float]:
        return float(t[a]), float(t[b - 1]) + dt

    def means(a: int, b: int) -> np.ndarray:  # (triads, 3): the mean specific force of each triad
        return np.nanmean(acc[a:b], axis=0).reshape(len(names), 3)

    channels = acc if not gyro_names else np.concatenate([acc, gyro], axis=1)

    rejected: list[tuple[int, int, str]] = []

    # 1. merge consecutive candidates of the same orientation separated by a short gap
    groups: list[list[int]] = []   # [start, stop] (untrimmed)
    last_dir = None
    for a, b in candidates:
        d = means(a, b)
        if groups:
            ga, gb = groups[-1]
            gap = float(t[a] - t[gb - 1]) - dt
            ang = _direction_angle_deg(last_dir, d)
            if gap <= options.merge_gap + 1e-9 and ang < options.min_separation_deg:
                groups[-1][1] = b
                rejected.append((a, b, f"merged with previous (same orientation, {ang:.2f}° apart, "
                                       f"gap {max(gap, 0.0):.2f} s)"))
                last_dir = means(ga, b)
                continue
        groups.append([a, b])
        last_dir = d

    # 2. trim, duration, drift
    kept: list[tuple[int, int, int, int]] = []   # trimmed a, b, untrimmed (refined) a, b
    for a0, b0 in groups:
        ra, rb = a0, b0
        for _ in range(REFINE_PASSES):  # again on what is left: its middle, the reference, is then cleaner
            na, nb = _refine_edges(channels, ra, rb, max(w, int(round(REFINE_SPAN / dt))))
            if (na, nb) == (ra, rb):
                break
            ra, rb = na, nb
        dur = (rb - ra) * dt
        cut = trim if trim is not None else min(AUTO_TRIM_MAX, AUTO_TRIM_FRACTION * dur)
        ntrim = int(round(cut / dt))
        a, b = ra + ntrim, rb - ntrim
        if dur < min_duration - 1e-9:
            rejected.append((ra, rb, f"too short ({dur:.2g} s < {min_duration:.3g} s)"))
            continue
        if b - a < 2:
            rejected.append((ra, rb, f"too short after trimming {cut:.3g} s off each end "
                                     f"({max(b - a, 0)} samples left of {rb - ra})"))
            continue
        if options.max_drift is not None:
            h = (a + b) // 2
            change = float(np.median(np.linalg.norm(means(h, b) - means(a, h), axis=1)))
            n1, n2 = h - a, b - h
            sigma_change = sigma_triad * math.sqrt(1.0 / n1 + 1.0 / n2) * math.sqrt(3.0)
            limit = max(options.max_drift, options.drift_sigmas * sigma_change)
            if change > limit:
                rejected.append((ra, rb, f"drifting (mean changes by {change:.3g} m/s² between "
                                         f"halves > {limit:.3g} m/s²)"))
                continue
        kept.append((a, b, ra, rb))

    # 3. rotation (optional): mean angular rate after removing the bias
    if options.max_gyro is not None and gyro_names and kept:
        gm = {k: np.array([np.nanmean(rec.gyro[k][a:b], axis=0) for a, b, _, _ in kept])
              for k in gyro_names}
        bias = {k: np.median(v, axis=0) for k, v in gm.items()}
        keep2 = []
        for j, item in enumerate(kept):
            rate = float(np.median([np.linalg.norm(gm[k][j] - bias[k]) for k in gyro_names]))
            if rate > options.max_gyro:
                rejected.append((item[2], item[3], f"rotating (mean angular rate {rate:.3g} rad/s "
                                                   f"after bias removal > {options.max_gyro:g} rad/s)"))
            else:
                keep2.append(item)
        kept = keep2

    # 4. notes: repeated orientations
    segments = [(a, b) for a, b, _, _ in kept]
    notes: list[tuple[int, str]] = []
    dirs = [means(a, b) for a, b in segments]
    for j in range(len(segments)):
        best = None
        for i2 in range(j):
            ang = _direction_angle_deg(dirs[i2], dirs[j])
            if ang < options.min_separation_deg and (best is None or ang < best[1]):
                best = (i2, ang)
        if best is not None:
            notes.append((j, f"repeated orientation (same as pose {best[0] + 1}, {best[1]:.2f}° apart)"))
    for j, (a, b, a0, b0) in enumerate(kept):
        merged = [r for r in rejected if r[2].startswith("merged") and a0 <= r[0] < b0]
        if merged:
            notes.append((j, f"merged from {len(merged) + 1} candidates"))

    rejected.sort(key=lambda r: r[0])
    return Detection(
        segments=segments,
        rejected=rejected,
        window=w * dt,
        min_duration=min_duration,
        threshold=a_thr,
        gyro_threshold=g_thr,
        threshold_method="; ".join(method),
        noise_floor=a_floor,
        gyro_noise_floor=g_floor,
        notes=sorted(notes),
        segment_times=[tt(a, b) for a, b in segments],
        rejected_times=[tt(a, b) for a, b, _ in rejected],
        t_range=t_range,
        source=rec.source,
        statistic=per_sample(a_stat),
        gyro_statistic=per_sample(g_stat) if g_stat is not None else None,
    )


def explicit_segments(rec: Recording, segments_s: Any, source: object = "",
                      where: str = "data.segments") -> Detection:
    """Segments given in seconds, ``[[t0, t1], ...]``, as a :class:`Detection`.

    A segment holds the samples with ``t0 <= t <= t1``. The segments keep the given order.

    Raises
    ------
    InputError
        Naming ``where[i]``: not a pair of numbers, ``t0 >= t1``, outside the recording, fewer than
        :data:`MIN_EXPLICIT_SAMPLES` samples, or overlapping an earlier segment.
    """
    t = np.asarray(rec.t, dtype=float)
    src = source or rec.source
    if isinstance(segments_s, (str, bytes)) or not isinstance(segments_s, (Sequence, np.ndarray)):
        raise InputError(src, where, f"expected a list of [t0, t1] pairs in seconds, found {segments_s!r}")
    if len(segments_s) == 0:
        raise InputError(src, where, "expected at least one [t0, t1] segment, found an empty list")
    if len(t) == 0:
        raise InputError(src, where, "the recording has no samples")
    dt = sample_period(t)
    tol = 0.5 * dt
    ranges: list[tuple[int, int]] = []
    for i, seg in enumerate(segments_s):
        w = f"{where}[{i}]"
        if isinstance(seg, (str, bytes)) or not isinstance(seg, (Sequence, np.ndarray)) or len(seg) != 2:
            raise InputError(src, w, f"expected a pair [t0, t1] in seconds, found {seg!r}")
        t0, t1 = Check(src).number(seg[0], f"{w}[0]"), Check(src).number(seg[1], f"{w}[1]")
        if not t0 < t1:
            raise InputError(src, w, f"expected t0 < t1, found [{t0:g}, {t1:g}]")
        if t0 < t[0] - tol or t1 > t[-1] + tol:
            raise InputError(src, w, f"[{t0:g}, {t1:g}] s is outside the recording "
                                     f"({t[0]:g} s to {t[-1]:g} s)")
        a = int(np.searchsorted(t, t0, side="left"))
        b = int(np.searchsorted(t, t1, side="right"))
        if b - a < MIN_EXPLICIT_SAMPLES:
            raise InputError(src, w, f"[{t0:g}, {t1:g}] s holds {b - a} samples; expected at least "
                                     f"{MIN_EXPLICIT_SAMPLES}")
        for j, (a2, b2) in enumerate(ranges):
            if a < b2 and a2 < b:
                raise InputError(src, w, f"[{t0:g}, {t1:g}] s overlaps {where}[{j}] "
                                         f"([{segments_s[j][0]:g}, {segments_s[j][1]:g}] s)")
        ranges.append((a, b))
    return Detection(
        segments=ranges,
        rejected=[],
        threshold=None,
        gyro_threshold=None,
        threshold_method=f"explicit segments ({where})",
        segment_times=[(float(t[a]), float(t[b - 1]) + dt) for a, b in ranges],
        t_range=(float(t[0]), float(t[-1])),
        source=str(src),
    )

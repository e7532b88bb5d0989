"""One time base for every reader: sample times from a sampling rate, with gaps reported.

A sensor samples on its own clock, so sample k is taken at t_k = a + T n_k, with n_k an integer
sample number and T the sampling period. The stamps in a log are often not those times: rounded to a
coarse resolution (10 ms in many logs, so that at 200 Hz half of them repeat), jittered by the host
that stamped them on arrival, or interrupted by lost samples. :func:`regular_times` recovers n_k
and T from the stamps (or takes T from a declared rate, and n_k from a packet counter or a
sample-number column) and returns the times on that grid, with a note of what it did:

1. **Period.** Declared (``data.rate``); with a counter, the median step per counted sample; else
   first the median of the L-sample differences / L (L = :data:`LAG`: rounding errors shrink as
   1/L, a minority of windows holding a gap does not move the median), then the pooled
   least-squares slope of stamp vs row within the gap-free runs (step 2), which no gap biases.
2. **Sample numbers.** A *break candidate* is a step that differs from T by more than T/2 plus
   the stamps' own spread (the 95th percentile of |step - T|: for 10 ms rounding at 200 Hz every
   step is 0 or 10 ms, 5 ms from T). At each candidate the level of ``stamp - T row`` (median over
   up to :data:`LEVEL_WINDOW` rows of the adjacent runs) jumps by m T: m >= 1 is a gap of m
   missing samples, m = 0 an outlying stamp (jitter), m <= -1 time running backwards, refused.
   A gap shorter than the stamps' uncertainty cannot be told from rounding and is not seen.
3. **Grid.** t = a + T n, with a the median of ``stamp - T n`` over the first rows. Stamps that
   are strictly increasing and within :data:`KEEP_FRACTION` of a period of the grid everywhere
   are kept as they are (a well-behaved log is not touched). So are strictly increasing stamps
   further off whose successive steps do not anticorrelate (:data:`JITTER_CORRELATION`): that is a
   clock whose period wanders, not stamp errors. Otherwise every time is the grid's.

Time running backwards is never read as a wrap: it is refused with the row, unless a counter says
the samples are contiguous (then the stamps are wrong, and are repaired with a note).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from castimate.errors import InputError

#: Rows in the lag of the first period estimate.
LAG = 100
#: Rows on each side of a break over which the stamp level is taken.
LEVEL_WINDOW = 50
#: Fewer rows cannot show a rate: the stamps must then be strictly increasing as given.
MIN_SAMPLES = 8
#: Strictly increasing stamps within this fraction of a period of the grid are kept unchanged.
KEEP_FRACTION = 0.1
#: Lag-1 correlation of the step deviations below which strictly increasing stamps off the grid are
#: taken as stamp errors (jitter, rounding) and repaired; white jitter gives -1/2, a wandering clock 0.
JITTER_CORRELATION = -0.25
#: A declared rate and the stamps' own must agree to this fraction.
RATE_AGREEMENT = 0.01
#: Rows over which the grid's offset a is taken (median).
ANCHOR_ROWS = 1000
#: Gaps listed one by one in the note (the rest are counted).
GAPS_LISTED = 3


@dataclass(frozen=True)
class Gap:
    """Samples missing before ``row`` (0-based), against the sampling rate."""

    row: int
    t: float  # time of the last sample before the gap, s
    missing: int

    def duration(self, period: float) -> float:
        return self.missing * period


@dataclass(frozen=True)
class TimeBase:
    """Sample times of a recording and how they were obtained.

    Attributes
    ----------
    t
        Sample times, s, strictly increasing: the stamps as given, or the grid a + T n.
    rate
        Sampling rate 1/T, Hz.
    rate_from
        ``"declared"``, ``"sample numbers"`` or ``"stamps"``.
    repaired
        True when the times are the grid's, not the stamps.
    repeated, backwards
        Steps of zero and negative steps in the stamps (all absorbed by the repair).
    max_correction
        Largest |grid - stamp|, s.
    gaps
        Missing samples, in time order.
    notes
        One-line remarks for ``Recording.notes``.
    """

    t: np.ndarray
    rate: float
    rate_from: str
    repaired: bool = False
    repeated: int = 0
    backwards: int = 0
    max_correction: float = 0.0
    gaps: tuple[Gap, ...] = ()
    notes: tuple[str, ...] = ()

    @property
    def period(self) -> float:
        return 1.0 / self.rate

    @property
    def missing(self) -> int:
        return sum(g.missing for g in self.gaps)

    @property
    def alerts(self) -> tuple[str, ...]:
        """The notes a user must see: the stamps were repaired, or samples are missing."""
        return self.notes if self.repaired or self.gaps else ()

    def as_dict(self) -> dict:
        """For results.json: the rate and where it came from, the repair, every gap."""
        return {"rate_hz": self.rate, "rate_from": self.rate_from, "repaired": self.repaired,
                "repeated_stamps": self.repeated, "backward_stamps": self.backwards,
                "max_correction_s": self.max_correction, "missing_samples": self.missing,
                "gaps": [{"row": g.row, "t_before_s": g.t, "missing": g.missing,
                          "duration_s": g.duration(self.period)} for g in self.gaps]}


def _first_bad_step(t: np.ndarray) -> int | None:
    bad = np.flatnonzero(~(np.diff(t) > 0))
    return int(bad[0]) + 1 if bad.size else None


def _runs(n_rows: int, breaks: np.ndarray) -> list[tuple[int, int]]:
    """Row ranges [start, stop) between break steps (step k joins rows k and k+1)."""
    edges = np.concatenate(([0], breaks + 1, [n_rows]))
    return [(int(a), int(b)) for a, b in pairwise(edges)]


def _pooled_slope(t: np.ndarray, runs: list[tuple[int, int]]) -> float | None:
    """Least-squares slope of stamp vs row, every run with its own offset (gaps do not bias it)."""
    sxy = sxx = 0.0
    for a, b in runs:
        if b - a < 2:
            continue
        k = np.arange(b - a, dtype=float)
        k -= k.mean()
        sxy += float(k @ (t[a:b] - t[a:b].mean()))
        sxx += float(k @ k)
    return sxy / sxx if sxx > 0 else None


def _period_from_lags(t: np.ndarray) -> float:
    lag = min(len(t) - 1, LAG)
    return float(np.median((t[lag:] - t[:-lag]) / lag))


def _sample_numbers(t: np.ndarray, period: float, declared: bool, source: str, column: str,
                    row_label: Callable[[int], str]) -> tuple[np.ndarray, float]:
    """Integer sample numbers n (n_0 = 0) of stamps without a counter, and the period (step 1-2)."""
    N = len(t)
    dev = np.diff(t) - period
    spread = float(np.quantile(np.abs(dev), 0.95))
    breaks = np.flatnonzero(np.abs(dev) > 0.5 * period + spread)
    runs = _runs(N, breaks)
    if not declared:
        period = _pooled_slope(t, runs) or period
    level = t - period * np.arange(N)
    missing = np.zeros(N, dtype=np.int64)
    for r, k in enumerate(breaks):
        (a0, _), (_, b1) = runs[r], runs[r + 1]
        before = np.median(level[max(a0, k + 1 - LEVEL_WINDOW):k + 1])
        after = np.median(level[k + 1:min(b1, k + 1 + LEVEL_WINDOW)])
        m = int(np.round((after - before) / period))
        if m < 0 and t[k + 1] == t[k]:  # "runs backwards by 0.02 s (1.2 after 1.2)" said it before
            raise InputError(source, column, f"time repeats {float(t[k])!r} (on {row_label(k)} and {row_label(k + 1)}) "
                                             f"and the stamps after it fall {-(after - before):.6g} s behind those "
                                             f"before ({1 / period:.6g} Hz): a duplicated row? expected increasing time")
        if m < 0:
            raise InputError(source, column, f"time runs backwards by {-(after - before):.6g} s at {row_label(k + 1)} "
                                             f"({float(t[k + 1])!r} after {float(t[k])!r} on {row_label(k)}; "
                                             f"{1 / period:.6g} Hz): expected increasing time; split the recording there")
        missing[k + 1] = m
    return np.arange(N) + np.cumsum(missing), period


def regular_times(stamps: np.ndarray, source: object, column: str, row_label: Callable[[int], str], *,
                  rate: float | None = None, index: np.ndarray | None = None,
                  index_name: str = "sample numbers") -> TimeBase:
    """The sample times of a recording from its stamps (see the module docstring).

    Parameters
    ----------
    stamps
        Time stamps of the rows, s, finite.
    source, column, row_label
        For messages: the file, the time column, and ``row_label(i)`` naming row i (``"line 12"``).
    rate
        Declared sampling rate, Hz, or None to estimate it from the stamps (or the counter).
    index
        Sample numbers of the rows (a packet counter, unwrapped), or None to infer them.
    index_name
        What ``index`` is, for the notes.

    Raises
    ------
    InputError
        Naming the file and column: stamps all equal, time running backwards beyond the stamps'
        uncertainty (the row named), too few rows to repair non-increasing stamps, sample numbers not
        strictly increasing, or a declared rate the stamps contradict.
    """
    t = np.asarray(stamps, dtype=float)
    N = len(t)
    src = str(source)
    declared = rate is not None
    if N < 2:
        return TimeBase(t=t.copy(), rate=float(rate) if declared else 1.0, rate_from="declared" if declared else "none")
    d = np.diff(t)
    if index is not None:
        n = np.asarray(index, dtype=np.int64) - int(index[0])
        dn = np.diff(n)
        bad = np.flatnonzero(dn <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise InputError(src, column, f"expected strictly increasing {index_name}, found {int(index[i])} at "
                                          f"{row_label(i)} after {int(index[i - 1])} at {row_label(i - 1)}")
        period = 1.0 / rate if declared else float(np.median(d / dn))
        rate_from = "declared" if declared else f"the stamps and the {index_name}"
    elif N < MIN_SAMPLES:
        i = _first_bad_step(t)
        if i is not None:
            raise InputError(src, column, f"expected strictly increasing time, found {float(t[i])!r} at {row_label(i)} "
                                          f"after {float(t[i - 1])!r} at {row_label(i - 1)} (with {N} rows, too few "
                                          f"to repair the stamps from a rate)")
        return TimeBase(t=t.copy(), rate=float(rate) if declared else 1.0 / float(np.median(d)),
                        rate_from="declared" if declared else "the stamps")
    else:
        period = 1.0 / rate if declared else _period_from_lags(t)
        if not period > 0:
            period = 0.0  # refused below
        else:
            n, period = _sample_numbers(t, period, declared, src, column, row_label)
            if not declared:  # all rows in one least-squares fit, now that the gaps are known
                period = float(np.polyfit(n, t, 1)[0])
        rate_from = "declared" if declared else "the stamps"
    if not period > 0:
        raise InputError(src, column, f"expected increasing time, found stamps that do not advance "
                                      f"({float(t[0])!r} to {float(t[-1])!r} over {N} rows)")
    if declared:
        # the stamps' own period, with the gaps found above taken out
        own = float(np.median(d / np.diff(n))) if index is not None else float(np.polyfit(n, t, 1)[0])
        if not abs(own / period - 1) <= RATE_AGREEMENT:
            raise InputError(src, column, f"the stamps advance at {1 / own:.6g} Hz; the declared rate (data.rate) is "
                                          f"{1 / period:.6g} Hz: expected them to agree within {RATE_AGREEMENT:.0%}")
    K = min(N, ANCHOR_ROWS)
    a = float(np.median(t[:K] - period * n[:K]))
    grid = a + period * n
    corr = np.abs(grid - t)
    max_corr = float(corr.max())
    repeated, backwards = int(np.count_nonzero(d == 0)), int(np.count_nonzero(d < 0))
    # Errors of the stamps about the grid make successive steps anticorrelated (white jitter: -1/2,
    # rounding: down to -1); a clock whose own period wanders does not. Without a counter, strictly
    # increasing stamps are replaced only when their deviations show that pattern.
    dev = d - period * np.diff(n)
    rho = float(dev[:-1] @ dev[1:] / (dev @ dev)) if N > 2 and dev @ dev > 0 else 0.0
    off_grid = max_corr > KEEP_FRACTION * period
    repaired = repeated + backwards > 0 or (off_grid and (index is not None or rho < JITTER_CORRELATION))
    jumps = np.flatnonzero(np.diff(n) > 1)
    gaps = tuple(Gap(row=int(k) + 1, t=float((grid if repaired else t)[k]), missing=int(n[k + 1] - n[k] - 1))
                 for k in jumps)
    hz = f"{1 / period:.6g} Hz ({'declared' if declared else 'estimated from ' + rate_from})"
    notes = []
    if repaired:
        what = [f"{repeated} repeated", f"{backwards} running backwards"]
        if index is not None:  # against a counter, a step off by half a period is a clock fault
            off = np.abs(d - period * np.diff(n)) > 0.5 * period * np.diff(n)
            what.append(f"{int(off.sum())} disagreeing with the {index_name} by more than half a period")
        notes.append(f"{column}: timestamps repaired: {N} samples put on a uniform grid at {hz}; the stamps had "
                     f"{', '.join(what)}; largest correction {1e3 * max_corr:.4g} ms")
    elif off_grid:
        notes.append(f"{column}: {N} samples at {hz}; timestamps up to {1e3 * max_corr:.3g} ms off a uniform grid, "
                     f"kept: successive steps do not anticorrelate (lag-1 correlation {rho:+.2f}, stamp errors "
                     f"give below {JITTER_CORRELATION:+.2f}), so the clock itself varies")
    else:
        notes.append(f"{column}: {N} samples at {hz}; timestamps within {1e3 * max_corr:.3g} ms of a uniform grid, kept")
    if gaps:
        longest = max(gaps, key=lambda g: g.missing)
        listed = "; ".join(f"{g.missing} after {row_label(g.row - 1)} (t = {g.t:.6g} s)" for g in gaps[:GAPS_LISTED])
        more = f"; and {len(gaps) - GAPS_LISTED} more" if len(gaps) > GAPS_LISTED else ""
        notes.append(f"{column}: {len(gaps)} gap(s) against {1 / period:.6g} Hz, {sum(g.missing for g in gaps)} samples "
                     f"missing; longest {longest.duration(period):.6g} s ({longest.missing} samples) after "
                     f"{row_label(longest.row - 1)}; missing samples: {listed}{more}")
    return TimeBase(t=grid if repaired else t.copy(), rate=1.0 / period, rate_from="declared" if declared else rate_from,
                    repaired=repaired, repeated=repeated, backwards=backwards, max_correction=max_corr, gaps=gaps,
                    notes=tuple(notes))


__all__ = ["Gap", "TimeBase", "regular_times"]
